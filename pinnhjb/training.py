"""Training one stage: the finite-horizon PINN of Algorithm 1 and the direct steady-state baseline.

The loss is the paper's :eq:`eq-mse`: MSE_e (flow residual F_e, :eq:`eq-fe`) + MSE_b (terminal residual F_b,
:eq:`eq-fb`) + MSE_in (origin residual F_in, :eq:`eq-fin`). Under the ansatz of
:class:`~pinnhjb.pinn.FiniteHorizonValue` the last two are zero by construction and only MSE_e is minimised.

This module builds a stage's loss and samplers (an :class:`~pinnhjb.optimizers.Objective`) and runs the config's
optimiser phases on it (:mod:`pinnhjb.optimizers`); the residuals and their Jacobians are the objects of
:mod:`pinnhjb.residuals`. f, g, Q and the terminal cost phi (with its gradient) are evaluated once per stage on a
pool of states and then indexed, so a frozen chain of previous stages costs nothing per step. The pool is uniform
in the training box, or partly along closed loops from Omega (``TrainConfig.loop_share``, :func:`loop_states`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

from . import lq
from .config import TrainConfig
from .gauss_newton import FlatParameters
from .metrics import closed_loop, policy_of
from .optimizers import Objective, Tracker
from .pinn import FiniteHorizonValue, SteadyStateValue, ValueTerminalCost, ZeroTerminalCost, gradient
from .residuals import Residual, get_residual

Tensor = torch.Tensor

__all__ = [
    "TrainHistory",
    "StatePool",
    "run_phases",
    "shared_times",
    "loop_states",
    "train_finite_horizon",
    "train_steady_state",
    "resolve_device",
    "DTYPES",
]

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def resolve_device(device=None) -> torch.device:
    """``None``/"auto" picks CUDA when present, else CPU; anything else is passed to torch.device (a device torch
    does not know: ValueError; "cuda" on a machine without CUDA: RuntimeError)."""
    if device is None or device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        expected = "None, 'auto', 'cpu', 'cuda' or 'cuda:K' (a torch device)"
        raise ValueError(f"device must be {expected}; got {device!r}") from exc
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError(f"device={device!r} requested but CUDA is not available on this machine")
    return dev


@dataclass(frozen=True)
class TrainHistory:
    """The training log of one stage, built once when training ends.

    * ``step``: the optimiser step of each logged point (every ``config.log_every`` steps, the first, the last).
    * ``loss``: the training loss at those steps.
    * ``wall``: the seconds since the stage's training started, at those steps.
    * ``phase``: the phase of each logged point: ``"adam"``, ``"lbfgs"``, ``"lm"``, and ``"final"`` for the last.
    * ``stop_reason``: why training stopped (Adam's reason, or the Levenberg-Marquardt phase's when there was no
      Adam or it ran out of time).
    * ``wall_time``: the stage's training time in seconds (evaluation not included).
    * ``final_loss``: the loss at the end of training.

    The history holds its own copies of the four lists.
    """

    step: list = field(default_factory=list)
    loss: list = field(default_factory=list)
    wall: list = field(default_factory=list)
    phase: list = field(default_factory=list)
    stop_reason: str = ""
    wall_time: float = 0.0
    final_loss: float = float("nan")

    def __post_init__(self):
        for name in ("step", "loss", "wall", "phase"):
            object.__setattr__(self, name, list(getattr(self, name)))

    def to_dict(self) -> dict:
        """The history as plain data (checkpoints store it)."""
        return {
            "step": list(self.step),
            "loss": list(self.loss),
            "wall": list(self.wall),
            "phase": list(self.phase),
            "stop_reason": self.stop_reason,
            "wall_time": self.wall_time,
            "final_loss": self.final_loss,
        }

    @classmethod
    def from_dict(cls, d: dict) -> TrainHistory:
        """The history stored as ``d`` by :meth:`to_dict`."""
        return cls(**d)


# ---------------------------------------------------------------------- cached data


def _check_finite(values: Tensor, x: Tensor, what: str, hint: str):
    """Before training: a ValueError naming ``what`` and a state where ``values`` (one row per state) is not finite."""
    bad = ~torch.isfinite(values.reshape(values.shape[0], -1)).all(-1)
    if torch.any(bad):
        raise ValueError(
            f"{what} is NaN or infinite at {int(bad.sum())} of {x.shape[0]} training states, e.g. "
            f"x = {x[bad][0].detach().cpu().tolist()}; {hint}"
        )


class StatePool:
    """States with cached f(x), g(x), Q(x), phi(x), grad phi(x); indexed to form batches.

    * ``system``: the control-affine system.
    * ``x``: the states (N, n).
    * ``terminal``: the terminal cost phi to cache, or None.
    * ``need_phi_grad``: also cache grad phi (the ansatz's residual needs it).
    * ``chunk``: states per autograd pass through phi.
    """

    def __init__(self, system, x: Tensor, terminal=None, need_phi_grad: bool = False, chunk: int = 8192):
        self.x = x
        with torch.no_grad():
            self.fx = system.f(x)
            self.gx = system.g(x)
            self.qx = system.Q(x)
        for key, out in (("f", self.fx), ("g", self.gx), ("Q", self.qx)):
            _check_finite(
                out,
                x,
                f"system '{system.name}': {key}(x)",
                f"f, g, Q must be finite on the whole training box {system.train_domain.tolist()}",
            )
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
        """The cached data of the states at ``idx``: x, f(x), g(x), Q(x) and, when cached, phi and its gradient."""
        out = {"x": self.x[idx], "fx": self.fx[idx], "gx": self.gx[idx], "qx": self.qx[idx]}
        if self.phi is not None:
            out["phi"] = self.phi[idx]
        if self.dphi is not None:
            out["dphi"] = self.dphi[idx]
        return out


# ---------------------------------------------------------------------- the optimisation loop


def run_phases(objective: Objective, config: TrainConfig, progress: bool) -> TrainHistory:
    """Run ``config.phases`` in turn on ``objective``; the stage's training log.

    * ``objective``: the stage's loss and samplers.
    * ``config``: the recipe (its phases, ``max_time``, ``log_every``).
    * ``progress``: show a progress bar.

    The first phase always starts; a later one not yet started when ``max_time`` has passed is skipped. The
    history's stop reason is the last reason a phase gave (L-BFGS, which runs its fixed count, gives none).
    """
    tracker = Tracker(sum(p.steps for p in config.phases), objective.desc, progress, config.log_every, config.max_time)
    loss, reason = float("nan"), ""
    try:
        for i, phase in enumerate(config.phases):
            if i > 0 and tracker.out_of_time():
                reason = "max_time"
                break
            outcome = phase.run(objective, tracker)
            loss, reason = outcome.loss, outcome.stop_reason or reason
    finally:
        tracker.bar.close()
    wall_time = tracker.elapsed()
    tracker.record(tracker.done, loss, "final", wall=wall_time)
    return TrainHistory(tracker.step, tracker.loss, tracker.wall, tracker.phase, reason, wall_time, loss)


def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(int(seed))


def _randint(gen, high: int, size: int, device) -> Tensor:
    return torch.randint(high, (size,), generator=gen).to(device)


def _uniform(gen, size: int, scale: float, dtype, device) -> Tensor:
    return (scale * torch.rand(size, generator=gen, dtype=torch.float64)).to(dtype=dtype, device=device)


def loop_states(
    system, count: int, generator, duration: float, dt: float = 0.01, dtype=torch.float64, device=None, policy=None
):
    """States along closed loops from Omega: ``count`` uniform states of Omega, each flown for ``duration``
    seconds under ``policy`` (RK4, :func:`pinnhjb.metrics.closed_loop`) and taken at a uniform time of its own
    loop. A loop that blew up gives a uniform state of the training box instead.

    * ``system``: the control-affine system; without ``policy`` its linearisation must be stabilisable
      (:func:`pinnhjb.lq.care`).
    * ``count``: how many states.
    * ``generator``: the CPU torch generator that draws the starts and the times.
    * ``duration``: the seconds of each loop.
    * ``dt``: the RK4 step.
    * ``dtype``, ``device``: of the result.
    * ``policy``: a batched callable x (N, n) -> u (N, m) on float64 CPU states, such as
      :func:`pinnhjb.metrics.policy_of` a learned value; None: the LQR policy of the system's linearisation.

    Returns (count, n).
    """
    if policy is None:
        gain = torch.as_tensor(lq.lqr_gain(system.linearize().B, system.R, system.lqr_value()))

        def policy(x):
            return -x @ gain.T

    starts = system.sample(count, generator, dtype=torch.float64, box=system.domain)
    run = closed_loop(system, policy, starts, t_final=duration, dt=dt)
    when = torch.randint(run.x.shape[0], (count,), generator=generator)
    states = torch.as_tensor(run.x[when.numpy(), range(count)])
    bad = ~torch.isfinite(states).all(dim=-1)
    if bad.any():
        states[bad] = system.sample(int(bad.sum()), generator, dtype=torch.float64)
    return states.to(dtype=dtype, device=device)


def shared_times(gen, size: int, points_per_time: int, T: float, dtype, device) -> tuple[Tensor, tuple]:
    """Collocation times in [0, T], each of ceil(size / points_per_time) fresh times shared by that many points.

    * ``gen``: the CPU random generator.
    * ``size``: the number of points.
    * ``points_per_time``: points per fresh time, in turn.
    * ``T``: the horizon.
    * ``dtype``, ``device``: of the result.

    Returns ``(t, (times, index))`` with ``t = times[index]``.
    """
    k = -(-size // points_per_time)
    times = _uniform(gen, k, T, dtype, device)
    index = torch.arange(size, device=device) % k
    return times[index], (times, index)


def _objective(model, loss, sample, epochs, residual: Residual, point_sample, config: TrainConfig, desc: str):
    """The :class:`~pinnhjb.optimizers.Objective` of ``model``'s network: its weights, loss and samplers."""
    params = list(model.net.parameters())
    return Objective(
        params,
        loss,
        sample,
        epochs,
        config.sampling,
        config.batch_size,
        FlatParameters(model.net),
        residual,
        point_sample,
        desc,
    )


def _residual(system, model, residual, default: str) -> Residual:
    """The residual object of form ``residual`` (a name, a class or None for ``default``) on ``model``."""
    form = get_residual(default if residual is None else residual)
    if form.ansatz is not None and form.ansatz != model.ansatz:
        raise ValueError(
            f"the residual form {form.name!r} trains a model with ansatz={form.ansatz}; this model has "
            f"ansatz={model.ansatz}"
        )
    return form(system, model)


def _loop_policy(system, config: TrainConfig, terminal, dtype, device):
    """The policy whose loops ``config.loop_share`` follows (``config.loop_policy``), called on float64 CPU
    states; None: the linearisation's LQR policy (also for a terminal cost 0, whose policy is u = 0).

    * ``terminal``: the stage's terminal cost, evaluated in ``dtype`` on ``device`` (the stage's network's)."""
    if config.loop_policy == "lqr" or terminal is None or isinstance(terminal, ZeroTerminalCost):
        return None
    mu = policy_of(system, terminal)
    return lambda x: mu(x.to(dtype=dtype, device=device)).to(dtype=torch.float64, device="cpu")


def train_finite_horizon(
    system,
    model: FiniteHorizonValue,
    config: TrainConfig,
    seed: int = 0,
    progress: bool = True,
    desc: str = "stage",
    residual: str | type[Residual] | None = None,
) -> TrainHistory:
    """Train ``model`` in place on the finite-horizon HJB :eq:`eq-hjbt` over Omega x [0, model.horizon] (Algorithm 1).

    * ``system``: the control-affine system.
    * ``model``: the stage's value network, trained in place.
    * ``config``: the training recipe.
    * ``seed``: seeds the collocation points.
    * ``progress``: show a progress bar.
    * ``desc``: the stage's label (progress bar, errors).
    * ``residual``: the PDE form (:mod:`pinnhjb.residuals`), a registered name or class; None: ``"hjbt"`` under
      the ansatz, ``"hjbt_soft"`` without.
    """
    res = _residual(system, model, residual, "hjbt" if model.ansatz else "hjbt_soft")
    p = next(model.parameters())
    dtype, device = p.dtype, p.device
    gen = _generator(seed)
    T = model.horizon
    terminal = model.terminal_cost
    n_pool = config.pool_size if config.sampling == "resample" else config.n_flow
    states = system.sample(n_pool, gen, dtype=dtype, device=device)
    if config.loop_share > 0:
        k = int(round(config.loop_share * n_pool))
        policy = _loop_policy(system, config, terminal, dtype, device)
        states[:k] = loop_states(system, k, gen, config.loop_time, dtype=dtype, device=device, policy=policy)
    pool = StatePool(system, states, terminal, need_phi_grad=model.ansatz)
    bnd = None
    if not model.ansatz:
        n_b = config.n_boundary if config.sampling == "fixed" else config.pool_size
        bnd = StatePool(system, system.sample(n_b, gen, dtype=dtype, device=device), terminal)

    def batch_loss(batch):
        return res.loss(*batch)

    def sample(size):
        flow = pool.take(_randint(gen, len(pool), size, device))
        if model.ansatz and config.points_per_time is not None and config.points_per_time > 1:
            t, shared = shared_times(gen, size, config.points_per_time, T, dtype, device)
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
            idx = perm[b * config.batch_size : (b + 1) * config.batch_size]
            if model.ansatz:
                yield pool.take(idx), t_flow[idx], None, None
            else:
                ib = perm_b[b::n_batches]
                io = perm_o[b::n_batches]
                yield pool.take(idx), t_flow[idx], bnd.take(ib), t_origin[io]

    def lm_sample(size):
        flow = pool.take(_randint(gen, len(pool), size, device))
        t = _uniform(gen, size, T, dtype, device)
        return res.point_arguments(flow, t)

    return run_phases(_objective(model, batch_loss, sample, epochs, res, lm_sample, config, desc), config, progress)


def train_steady_state(
    system,
    model: SteadyStateValue,
    config: TrainConfig,
    seed: int = 0,
    progress: bool = True,
    desc: str = "steady state",
    residual: str | type[Residual] | None = None,
) -> TrainHistory:
    """Train ``model`` in place on the steady-state HJB :eq:`eq-hjb` directly (the paper's T = infinity baseline).

    * ``system``: the control-affine system.
    * ``model``: the value network V(x), trained in place.
    * ``config``: the training recipe.
    * ``seed``: seeds the collocation points.
    * ``progress``: show a progress bar.
    * ``desc``: the label (progress bar, errors).
    * ``residual``: the PDE form (:mod:`pinnhjb.residuals`), a registered name or class; None: ``"hjb"``.
    """
    res = _residual(system, model, residual, "hjb")
    p = next(model.parameters())
    dtype, device = p.dtype, p.device
    gen = _generator(seed)
    n_pool = config.pool_size if config.sampling == "resample" else config.n_flow
    pool = StatePool(system, system.sample(n_pool, gen, dtype=dtype, device=device))

    def sample(size):
        return pool.take(_randint(gen, len(pool), size, device))

    def epochs():
        perm = torch.randperm(len(pool), generator=gen).to(device)
        for b in range(max(1, len(pool) // config.batch_size)):
            yield pool.take(perm[b * config.batch_size : (b + 1) * config.batch_size])

    def lm_sample(size):
        return res.point_arguments(sample(size), None)

    return run_phases(_objective(model, res.loss, sample, epochs, res, lm_sample, config, desc), config, progress)
