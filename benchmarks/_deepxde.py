"""DeepXDE on the finite-horizon HJB, as the benchmarks build it: the pieces ``speed.py`` (the quartic system) and
``dimension.py`` (n = 6) share.

DeepXDE is installed only in the benchmarks' own environment (``benchmarks/.venv``, see
``requirements-deepxde.txt``); :func:`import_deepxde` says why not when it is missing. Everything here is DeepXDE's
API with pinnhjb's Hamiltonian: the network sees (x, s) in reversed time s = T - t, the terminal and origin
conditions are soft (``PointSetBC``), and a chain warm-starts each stage from the last and takes the last stage's
prediction at its s = length as the next terminal cost.
"""

from __future__ import annotations

import os

import numpy as np
import torch


def import_deepxde():
    """(deepxde, None) with the PyTorch backend, or (None, why not): not installed, or another backend."""
    os.environ.setdefault("DDE_BACKEND", "pytorch")
    try:
        import deepxde as dde  # optional: installed only in benchmarks/.venv
    except ImportError as exc:
        print(f"DeepXDE is not importable ({exc}); its methods are marked 'not installed'", flush=True)
        return None, "not installed"
    if dde.backend.backend_name != "pytorch":
        print(f"DeepXDE uses backend {dde.backend.backend_name!r}, not pytorch; set DDE_BACKEND=pytorch", flush=True)
        return None, f"unavailable (DeepXDE backend {dde.backend.backend_name}, not pytorch)"
    return dde, None


def network(dde, system, length: float, width: int, depth: int, activation: str):
    """width x depth tanh FNN on (x, s) with the same input scaling as pinnhjb's network: x from the training box
    and s from [0, length] to [-1, 1], via DeepXDE's ``apply_feature_transform``."""
    net = dde.nn.FNN([system.n + 1] + [width] * depth + [1], activation, "Glorot normal")
    box = torch.as_tensor(system.train_domain, dtype=torch.float32)
    center = torch.cat([(box[:, 0] + box[:, 1]) / 2, torch.tensor([length / 2])])
    half = torch.cat([(box[:, 1] - box[:, 0]) / 2, torch.tensor([length / 2])])
    net.apply_feature_transform(lambda z: (z - center.to(z)) / half.to(z))
    return net


def value_fn(net, s_end: float):
    """V(x, t=0) = net(x, s=s_end) in reversed time, float64 in and out (the net is float32, on its device)."""
    p = next(net.parameters())

    def fn(x):
        xd = x.to(p.device, p.dtype)
        z = torch.cat([xd, torch.full((x.shape[0], 1), s_end, dtype=p.dtype, device=p.device)], dim=1)
        return net(z).squeeze(-1).to(x.device, x.dtype)

    return fn


def pde(dde, system):
    """The finite-horizon HJB in reversed time s = T - t: dV/ds = min_u H(x, grad_x V) (pinnhjb's Hamiltonian)."""

    def residual(z, y):
        dy = dde.grad.jacobian(y, z, i=0)  # (N, n + 1): grad_x V, dV/ds
        return dy[:, -1:] - system.hamiltonian_min(z[:, :-1], dy[:, :-1]).unsqueeze(-1)

    return residual


def geometry(dde, system, length: float):
    """The training box (a hypercube in any n) times [0, length]."""
    lo, hi = system.train_domain[:, 0].tolist(), system.train_domain[:, 1].tolist()
    return dde.geometry.GeometryXTime(dde.geometry.Hypercube(lo, hi), dde.geometry.TimeDomain(0.0, length))


def stage_points(system, cfg, length: float, prev=None, prev_length: float | None = None):
    """The soft conditions' points of one stage (numpy's global generator, seeded by DeepXDE's seed):

    * V(0, s) = 0 on ``cfg.n_origin`` points at uniform s;
    * V(x, s = 0) = phi(x) on ``cfg.n_boundary`` uniform states: phi = 0 (first stage), or the previous stage's
      model ``prev`` predicted at its s = ``prev_length``, i.e. V_prev(x, t = 0) (a chain).

    Returns (origin points, terminal points, terminal values), each (N, n + 1) or (N, 1). (phi = 0 is a point set
    too: DeepXDE's IC resamples a varying number of initial points per step, which its PDEPointResampler rejects
    with "`num_bcs` changed".)"""
    lo, hi = system.train_domain[:, 0], system.train_domain[:, 1]
    s_origin = np.random.uniform(0.0, length, size=(cfg.n_origin, 1))
    origin = np.hstack([np.zeros((cfg.n_origin, system.n)), s_origin])
    xs = np.random.uniform(lo, hi, size=(cfg.n_boundary, system.n))
    terminal = np.hstack([xs, np.zeros((cfg.n_boundary, 1))])
    if prev is None:
        values = np.zeros((cfg.n_boundary, 1))
    else:
        values = prev.predict(np.hstack([xs, np.full((cfg.n_boundary, 1), prev_length)]))
    return origin, terminal, values


def point_bcs(dde, points, nb: int, batched: bool) -> list:
    """The two ``PointSetBC`` of :func:`stage_points`' ``points``: ``nb`` points a step (batched, resampled by
    DeepXDE), or the first ``nb`` of each set, fixed (for L-BFGS)."""
    origin, terminal, values = points
    kw = {"batch_size": nb} if batched else {}
    sl = slice(None) if batched else slice(0, nb)
    return [
        dde.icbc.PointSetBC(origin[sl], np.zeros((len(origin[sl]), 1)), **kw),
        dde.icbc.PointSetBC(terminal[sl], values[sl], **kw),
    ]


def soft_points(cfg, flow_points: int) -> int:
    """The soft conditions' points per set for ``flow_points`` flow points, in pinnhjb's proportion."""
    return max(1, flow_points * cfg.n_boundary // max(cfg.n_flow, 1))


def chain(dde, system, cfg, lengths, seed: int, until=None) -> tuple[object, float, list[dict]]:
    """DeepXDE on an extension chain of stages ``lengths``: each stage Adam (``cfg``'s ``adam`` phase: its steps,
    learning rate and cosine decay; ``cfg.batch_size`` fresh flow points a step) then L-BFGS (its ``lbfgs`` phase:
    steps on fixed points), warm-started from the last stage.

    * ``until(value_fn, T)``: called after each stage with V(., 0) of the chain so far; True stops the chain.

    Returns (the last model, its stage length, one dict per stage: ``T`` and ``adam_steps``/``lbfgs_steps``)."""
    adam, lbfgs = cfg.phase("adam"), cfg.phase("lbfgs")
    residual = pde(dde, system)
    prev, prev_length, T, stages = None, None, 0.0, []
    for k, length in enumerate(lengths):
        dde.config.set_random_seed(seed + k)
        geom = geometry(dde, system, length)
        net = network(dde, system, length, cfg.width, cfg.depth, cfg.activation)
        if prev is not None:
            net.load_state_dict(prev.net.state_dict())  # warm start, as our chains
        points = stage_points(system, cfg, length, prev, prev_length)

        def data(flow: int, batched: bool):  # flow points, and the soft conditions in proportion
            bcs = point_bcs(dde, points, soft_points(cfg, flow), batched)
            return dde.data.TimePDE(geom, residual, bcs, num_domain=flow, num_initial=0, train_distribution="pseudo")

        model = dde.Model(data(cfg.batch_size, batched=True), net)
        model.compile("adam", lr=adam.lr, decay=("cosine", adam.steps, adam.lr * adam.lr_final_ratio), verbose=0)
        resample = dde.callbacks.PDEPointResampler(period=1, pde_points=True, bc_points=True)
        model.train(iterations=adam.steps, display_every=adam.steps, callbacks=[resample], verbose=0)
        dde.optimizers.set_LBFGS_options(maxcor=50, ftol=1e-15, gtol=1e-12, maxiter=lbfgs.steps)
        model = dde.Model(data(lbfgs.points, batched=False), net)
        model.compile("L-BFGS", verbose=0)
        model.train(verbose=0)
        T += length
        stages.append({"T": T, "adam_steps": adam.steps, "lbfgs_steps": lbfgs.steps})
        prev, prev_length = model, length
        if until is not None and until(value_fn(net, length), T):
            break
    return prev, prev_length, stages
