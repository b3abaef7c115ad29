"""Training one stage: the finite-horizon PINN of Algorithm 1 and the direct steady-state baseline.

The loss is the paper's eq. (MSE): MSE_e (flow residual F_e) + MSE_b (terminal residual F_b) + MSE_in
(origin residual F_in); under the ansatz of :class:`~pinnhjb.pinn.FiniteHorizonValue` the last two are zero
by construction and only MSE_e is minimised: by Adam and L-BFGS, or (our default) by Levenberg-Marquardt on the
per-point residuals (:mod:`pinnhjb.gauss_newton`). f, g, Q and the terminal cost phi (with its gradient) are
evaluated once per stage on a pool of states and then indexed, so a frozen chain of previous stages
costs nothing per step.
"""
from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import torch
from torch import nn
from torch.func import functional_call, grad
from tqdm.auto import tqdm

from .config import TrainConfig
from .gauss_newton import DivergenceError, FlatParameters, levenberg_marquardt
from .jacobian import residual_jacobian
from .pinn import FiniteHorizonValue, SteadyStateValue, ValueTerminalCost, gradient

Tensor = torch.Tensor

__all__ = ["TrainHistory", "train_finite_horizon", "train_steady_state", "resolve_device", "DTYPES"]

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def resolve_device(device=None) -> torch.device:
    """``None``/"auto" picks CUDA when present, else CPU; anything else is passed to torch.device."""
    if device is None or device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device={device!r} requested but CUDA is not available on this machine")
    return dev


@dataclass
class TrainHistory:
    """Loss and wall time along training; ``stop_reason`` says why training stopped (Adam's reason, or the
    Levenberg-Marquardt phase's when there was no Adam or it ran out of time)."""

    step: list = field(default_factory=list)
    loss: list = field(default_factory=list)
    wall: list = field(default_factory=list)
    phase: list = field(default_factory=list)
    stop_reason: str = ""
    wall_time: float = 0.0
    final_loss: float = float("nan")

    def record(self, step: int, loss: float, wall: float, phase: str):
        self.step.append(int(step))
        self.loss.append(float(loss))
        self.wall.append(float(wall))
        self.phase.append(phase)

    def to_dict(self) -> dict:
        return {"step": list(self.step), "loss": list(self.loss), "wall": list(self.wall), "phase": list(self.phase),
                "stop_reason": self.stop_reason, "wall_time": self.wall_time, "final_loss": self.final_loss}

    @classmethod
    def from_dict(cls, d: dict) -> "TrainHistory":
        return cls(**d)


# ---------------------------------------------------------------------- cached data

def _check_finite(values: Tensor, x: Tensor, what: str, hint: str):
    """Before training: a ValueError naming ``what`` and a state where ``values`` (one row per state) is not finite."""
    bad = ~torch.isfinite(values.reshape(values.shape[0], -1)).all(-1)
    if torch.any(bad):
        raise ValueError(f"{what} is NaN or infinite at {int(bad.sum())} of {x.shape[0]} training states, e.g. "
                         f"x = {x[bad][0].detach().cpu().tolist()}; {hint}")


class _Data:
    """States with cached f(x), g(x), Q(x), phi(x), grad phi(x); indexed to form batches."""

    def __init__(self, system, x: Tensor, terminal=None, need_phi_grad: bool = False, chunk: int = 8192):
        self.x = x
        with torch.no_grad():
            self.fx = system.f(x)
            self.gx = system.g(x)
            self.qx = system.Q(x)
        for key, out in (("f", self.fx), ("g", self.gx), ("Q", self.qx)):
            _check_finite(out, x, f"system '{system.name}': {key}(x)",
                          f"f, g, Q must be finite on the whole training box {system.train_domain.tolist()}")
        self.phi = self.dphi = None
        if isinstance(terminal, ValueTerminalCost):  # a long chain: bound the autograd graph held per chunk
            chunk = max(512, chunk * 16 // max(16, len(terminal.previous.chain())))
        if terminal is not None:
            phis, grads = [], []
            for xc in torch.split(x, chunk):
                if need_phi_grad:
                    v, gphi = gradient(terminal, xc)
                    grads.append(gphi.detach())
                else:
                    with torch.no_grad():
                        v = terminal(xc)
                phis.append(v.detach())
            self.phi = torch.cat(phis)
            self.dphi = torch.cat(grads) if grads else None
            _check_finite(self.phi, x, "the terminal cost phi(x)", "check the terminal cost (or the previous stage)")
            if self.dphi is not None:
                _check_finite(self.dphi, x, "the gradient of the terminal cost phi(x)", "check the terminal cost")

    def __len__(self):
        return self.x.shape[0]

    def take(self, idx: Tensor) -> dict:
        out = {"x": self.x[idx], "fx": self.fx[idx], "gx": self.gx[idx], "qx": self.qx[idx]}
        if self.phi is not None:
            out["phi"] = self.phi[idx]
        if self.dphi is not None:
            out["dphi"] = self.dphi[idx]
        return out


# ---------------------------------------------------------------------- losses

def _finite_horizon_loss(system, model: FiniteHorizonValue, flow: dict, t: Tensor, boundary: dict | None,
                         t_origin: Tensor | None, shared_times: tuple | None = None) -> Tensor:
    """MSE of eq. (MSE) for one batch. ``flow`` holds cached states; phi's gradient is added under the ansatz.

    ``shared_times = (times, index)`` says that ``t = times[index]`` (see ``TrainConfig.points_per_time``).
    """
    x = flow["x"]
    gx, gt = model.correction_derivatives(x, t, *(shared_times or (None, None)))
    if model.ansatz:
        gx = gx + flow["dphi"]
    f_e = gt + system.hamiltonian_min(x, gx, flow["fx"], flow["gx"], flow["qx"])
    loss = (f_e**2).mean()
    if not model.ansatz:
        xb = boundary["x"]
        t_end = torch.full((xb.shape[0],), model.horizon, dtype=xb.dtype, device=xb.device)
        f_b = model.raw(xb, t_end) - boundary["phi"]
        f_in = model.raw(torch.zeros(t_origin.shape[0], xb.shape[1], dtype=xb.dtype, device=xb.device), t_origin)
        loss = loss + (f_b**2).mean() + (f_in**2).mean()
    return loss


def _steady_state_loss(system, model: SteadyStateValue, flow: dict) -> Tensor:
    """MSE of the steady-state HJB (4): mean E_e^2 (+ V(0)^2 when not enforced by the ansatz)."""
    x = flow["x"].detach().requires_grad_(True)
    v = model(x)
    (gx,) = torch.autograd.grad(v.sum(), x, create_graph=True)
    e = system.hamiltonian_min(x, gx, flow["fx"], flow["gx"], flow["qx"])
    loss = (e**2).mean()
    if not model.ansatz:
        loss = loss + model(torch.zeros_like(x[:1])).pow(2).sum()
    return loss


class _Correction(nn.Module):
    """``model.correction`` as a module's forward, so :func:`torch.func.functional_call` can swap its weights."""

    def __init__(self, model: FiniteHorizonValue):
        super().__init__()
        self.model = model

    def forward(self, x: Tensor, t: Tensor) -> Tensor:
        return self.model.correction(x, t)


def _finite_horizon_point_residual(system, model: FiniteHorizonValue, flat: FlatParameters):
    """F_e(x, t) of one point as a function of the flat weights theta (for Levenberg-Marquardt, ansatz only).

    The point's data are (x, t, grad phi(x), f(x), g(x), Q(x)), the cached terminal gradient included, so a
    frozen chain of previous stages is not re-evaluated."""
    wrapper = _Correction(model)

    def correction(theta, x, t):
        return functional_call(wrapper, flat.unflatten(theta, "model.net."), (x.unsqueeze(0), t.reshape(1)))[0]

    def residual(theta, x, t, dphi, fx, gx, qx):
        gxc, gtc = grad(correction, argnums=(1, 2))(theta, x, t)
        return gtc + system.hamiltonian_min(x[None], (gxc + dphi)[None], fx[None], gx[None], qx[None])[0]

    return residual


def _finite_horizon_jacobian(system, model: FiniteHorizonValue):
    """The batched twin of :func:`_finite_horizon_point_residual`: (r, J) over a batch by
    :func:`pinnhjb.jacobian.residual_jacobian`, with N(x, t) and N(0, t) of the ansatz as two rows per point."""
    n, T = system.n, model.horizon

    def jacobian(theta, x, t, dphi, fx, gx, qx):
        N = x.shape[0]
        z = torch.cat([model.net_inputs(x, t), model.net_inputs(torch.zeros_like(x), t)])
        dz = torch.diag(model.input_scale(x)).expand(2 * N, n + 1, n + 1)

        def residual_of(out, dout):
            gxc, gtc = model.ansatz_derivatives(t, out[:N], out[N:], dout[:N, :n], dout[:N, n], dout[N:, n])
            return gtc + system.hamiltonian_min(x, gxc + dphi, fx, gx, qx)

        return residual_jacobian(model.net, theta, z, dz, residual_of, copies=2)

    return jacobian


def _steady_state_jacobian(system, model: SteadyStateValue):
    """The batched twin of :func:`_steady_state_point_residual` (V = N(x) - N(0): grad V = grad N(x))."""

    def jacobian(theta, x, fx, gx, qx):
        dz = torch.diag(model.scale_x_derivative(x)).expand(x.shape[0], system.n, system.n)
        return residual_jacobian(model.net, theta, model.scale_x(x), dz,
                                 lambda out, dout: system.hamiltonian_min(x, dout, fx, gx, qx))

    return jacobian


def _steady_state_point_residual(system, model: SteadyStateValue, flat: FlatParameters):
    """E_e(x) of eq. (flow_res) for one point as a function of the flat weights (ansatz only)."""

    def value(theta, x):
        return functional_call(model, flat.unflatten(theta, "net."), (x.unsqueeze(0),))[0]

    def residual(theta, x, fx, gx, qx):
        gv = grad(value, argnums=1)(theta, x)
        return system.hamiltonian_min(x[None], gv[None], fx[None], gx[None], qx[None])[0]

    return residual


# ---------------------------------------------------------------------- the optimisation loop

def _lr_factor(config: TrainConfig):
    K = max(config.adam_steps, 1)
    if config.schedule == "cosine":
        r = config.lr_final_ratio
        return lambda k: r + (1 - r) * 0.5 * (1 + math.cos(math.pi * min(k, K) / K))
    if config.schedule == "inverse_time":
        return lambda k: 1.0 / (1.0 + config.lr_decay * k)
    return lambda k: 1.0


def _optimize(params, batch_loss, sample, epochs, config: TrainConfig, desc: str, progress: bool,
              lm=None) -> TrainHistory:
    """Adam (resampled batches, or epochs of fixed mini-batches with the paper's stop rule), then L-BFGS, then
    Levenberg-Marquardt.

    ``sample(size)`` returns a fresh batch; ``epochs()`` yields lists of mini-batches (fixed data);
    ``lm = (flat, point_residual, lm_sample, jacobian)`` for the Levenberg-Marquardt phase (see :mod:`.gauss_newton`).
    """
    params = list(params)
    hist = TrainHistory()
    start = time.perf_counter()
    opt = torch.optim.Adam(params, lr=config.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, _lr_factor(config))
    bar = tqdm(total=config.adam_steps + config.lbfgs_steps + config.lm_steps, desc=desc, disable=not progress,
               leave=False, dynamic_ncols=True)
    step = 0
    last = float("nan")

    def adam_step(batch) -> float:
        nonlocal step, last
        opt.zero_grad(set_to_none=True)
        loss = batch_loss(batch)
        if not torch.isfinite(loss):
            raise DivergenceError(desc, "Adam", step + 1, f"the loss is {loss.item()}",
                                  "lower lr, or check the scale of the system (f, g, Q, R) and that f, g, Q are "
                                  "finite on the training box")
        loss.backward()
        opt.step()
        sched.step()
        step += 1
        value = last = loss.item()
        if step % config.log_every == 0 or step == 1:
            hist.record(step, value, time.perf_counter() - start, "adam")
        bar.set_postfix(loss=f"{value:.3e}", refresh=False)  # shown at tqdm's own refresh rate
        bar.update(1)
        return value

    def out_of_time() -> bool:
        return config.max_time is not None and time.perf_counter() - start > config.max_time

    hist.stop_reason = "adam_steps"
    if config.sampling == "resample":
        while step < config.adam_steps:
            adam_step(sample(config.batch_size))
            if out_of_time():
                hist.stop_reason = "max_time"
                break
    else:
        done = False
        while not done:
            all_below = True
            for batch in epochs():
                value = adam_step(batch)
                all_below &= config.stop_loss is not None and value < config.stop_loss
                if step >= config.adam_steps:
                    done = True
                    break
                if out_of_time():
                    hist.stop_reason, done = "max_time", True
                    break
            else:
                if all_below:
                    hist.stop_reason, done = "stop_loss", True
    evals = 0
    if config.lbfgs_steps > 0:
        batch = sample(config.lbfgs_points)
        lbfgs = torch.optim.LBFGS(params, lr=1.0, max_iter=config.lbfgs_steps, history_size=50,
                                  tolerance_grad=1e-12, tolerance_change=1e-15, line_search_fn="strong_wolfe")

        def closure():
            nonlocal evals
            lbfgs.zero_grad(set_to_none=True)
            loss = batch_loss(batch)
            if evals == 0 and not torch.isfinite(loss):  # at the starting point: not a line-search overshoot
                raise DivergenceError(desc, "L-BFGS", 1, f"the loss is {loss.item()} at its starting point")
            loss.backward()
            evals += 1
            if evals % config.log_every == 0:
                hist.record(step + evals, loss.item(), time.perf_counter() - start, "lbfgs")
            bar.set_postfix(loss=f"{loss.item():.3e}", refresh=False)
            bar.update(1)
            return loss

        before = [p.detach().clone() for p in params]
        lbfgs.step(closure)
        final = batch_loss(batch)
        if not torch.isfinite(final):  # a diverged line search must not destroy the Adam result
            with torch.no_grad():
                for p, b in zip(params, before):
                    p.copy_(b)
            final = batch_loss(batch)
            if not torch.isfinite(final):
                raise DivergenceError(desc, "L-BFGS", evals, f"the loss is {final.item()}")
            warnings.warn(f"stage {desc}: L-BFGS diverged (non-finite loss after {evals} evaluations); kept the "
                          f"weights from before L-BFGS (loss {final.item():.3e})", RuntimeWarning, stacklevel=2)
        hist.final_loss = final.item()
    else:
        hist.final_loss = last
    iterations = 0
    if config.lm_steps > 0:
        flat, point_residual, lm_sample, jacobian = lm
        done = step + evals

        def on_step(k, loss, damping):
            if k % config.log_every == 0 or k == 1:
                hist.record(done + k, loss, time.perf_counter() - start, "lm")
            bar.set_postfix(loss=f"{loss:.3e}", refresh=False)
            bar.update(1)

        left = None if config.max_time is None else config.max_time - (time.perf_counter() - start)
        if left is None or left > 0:
            # the coarse level ends on a stall: without the stall rule, lm_points throughout
            coarse = config.lm_points_coarse if config.lm_min_progress is not None else None
            points = (config.lm_points,) if coarse is None else (coarse, config.lm_points)
            result = levenberg_marquardt(flat.get(), point_residual, lm_sample, config.lm_steps, points,
                                         damping=config.lm_damping, max_time=left, on_step=on_step,
                                         min_progress=config.lm_min_progress,
                                         stall_windows=config.lm_stall_windows, desc=desc, jacobian=jacobian)
            flat.set(result.theta)
            iterations = result.steps
            hist.final_loss = result.loss
            if config.adam_steps == 0 or result.stop_reason == "max_time":
                hist.stop_reason = result.stop_reason
    hist.wall_time = time.perf_counter() - start
    hist.record(step + evals + iterations, hist.final_loss, hist.wall_time, "final")
    bar.close()
    return hist


def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(int(seed))


def _randint(gen, high: int, size: int, device) -> Tensor:
    return torch.randint(high, (size,), generator=gen).to(device)


def _uniform(gen, size: int, scale: float, dtype, device) -> Tensor:
    return (scale * torch.rand(size, generator=gen, dtype=torch.float64)).to(dtype=dtype, device=device)


def _shared_times(gen, size: int, points_per_time: int, T: float, dtype, device) -> tuple[Tensor, tuple]:
    """``size`` collocation times in [0, T] drawn as ceil(size / points_per_time) fresh times, each shared by
    ``points_per_time`` points in turn: returns (t, (times, index)) with t = times[index]."""
    k = -(-size // points_per_time)
    times = _uniform(gen, k, T, dtype, device)
    index = torch.arange(size, device=device) % k
    return times[index], (times, index)


def train_finite_horizon(system, model: FiniteHorizonValue, config: TrainConfig, seed: int = 0,
                         progress: bool = True, desc: str = "stage") -> TrainHistory:
    """Train ``model`` in place on the finite-horizon HJB over Omega x [0, model.horizon] (Algorithm 1)."""
    p = next(model.parameters())
    dtype, device = p.dtype, p.device
    gen = _generator(seed)
    T = model.horizon
    terminal = model.terminal_cost
    n_pool = config.pool_size if config.sampling == "resample" else config.n_flow
    pool = _Data(system, system.sample(n_pool, gen, dtype=dtype, device=device), terminal,
                 need_phi_grad=model.ansatz)
    bnd = None
    if not model.ansatz:
        n_b = config.n_boundary if config.sampling == "fixed" else config.pool_size
        bnd = _Data(system, system.sample(n_b, gen, dtype=dtype, device=device), terminal)

    def batch_loss(batch):
        return _finite_horizon_loss(system, model, *batch)

    def sample(size):
        flow = pool.take(_randint(gen, len(pool), size, device))
        if model.ansatz and config.points_per_time is not None and config.points_per_time > 1:
            t, shared = _shared_times(gen, size, config.points_per_time, T, dtype, device)
            return flow, t, None, None, shared
        t = _uniform(gen, size, T, dtype, device)
        if model.ansatz:
            return flow, t, None, None
        nb = max(1, size * config.n_boundary // max(config.n_flow, 1))
        return flow, t, bnd.take(_randint(gen, len(bnd), nb, device)), _uniform(gen, nb, T, dtype, device)

    t_flow = _uniform(gen, len(pool), T, dtype, device)
    t_origin = _uniform(gen, config.n_origin, T, dtype, device)

    def epochs():
        n_batches = max(1, len(pool) // config.batch_size)
        perm = torch.randperm(len(pool), generator=gen).to(device)
        perm_b = torch.randperm(len(bnd), generator=gen).to(device) if bnd is not None else None
        perm_o = torch.randperm(config.n_origin, generator=gen).to(device)
        for b in range(n_batches):
            idx = perm[b * config.batch_size:(b + 1) * config.batch_size]
            if model.ansatz:
                yield pool.take(idx), t_flow[idx], None, None
            else:
                ib = perm_b[b::n_batches]
                io = perm_o[b::n_batches]
                yield pool.take(idx), t_flow[idx], bnd.take(ib), t_origin[io]

    lm = None
    if config.lm_steps > 0:
        def lm_sample(size):
            flow = pool.take(_randint(gen, len(pool), size, device))
            t = _uniform(gen, size, T, dtype, device)
            return flow["x"], t, flow["dphi"], flow["fx"], flow["gx"], flow["qx"]

        flat = FlatParameters(model.net)
        lm = (flat, _finite_horizon_point_residual(system, model, flat), lm_sample,
              _finite_horizon_jacobian(system, model))
    params = [q for q in model.net.parameters()]
    return _optimize(params, batch_loss, sample, epochs, config, desc, progress, lm)


def train_steady_state(system, model: SteadyStateValue, config: TrainConfig, seed: int = 0,
                       progress: bool = True, desc: str = "steady state") -> TrainHistory:
    """Train ``model`` in place on the steady-state HJB (4) directly (the paper's T = infinity baseline)."""
    p = next(model.parameters())
    dtype, device = p.dtype, p.device
    gen = _generator(seed)
    n_pool = config.pool_size if config.sampling == "resample" else config.n_flow
    pool = _Data(system, system.sample(n_pool, gen, dtype=dtype, device=device))

    def sample(size):
        return pool.take(_randint(gen, len(pool), size, device))

    def epochs():
        perm = torch.randperm(len(pool), generator=gen).to(device)
        for b in range(max(1, len(pool) // config.batch_size)):
            yield pool.take(perm[b * config.batch_size:(b + 1) * config.batch_size])

    lm = None
    if config.lm_steps > 0:
        def lm_sample(size):
            flow = sample(size)
            return flow["x"], flow["fx"], flow["gx"], flow["qx"]

        flat = FlatParameters(model.net)
        lm = (flat, _steady_state_point_residual(system, model, flat), lm_sample, _steady_state_jacobian(system, model))
    return _optimize(model.net.parameters(), lambda batch: _steady_state_loss(system, model, batch), sample,
                     epochs, config, desc, progress, lm)

