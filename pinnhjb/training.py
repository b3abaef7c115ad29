"""Training one stage: the finite-horizon PINN of Algorithm 1 and the direct steady-state baseline.

The loss is the paper's eq-mse: MSE_e (flow residual F_e, eq-fe) + MSE_b (terminal residual F_b, eq-fb) + MSE_in
(origin residual F_in, eq-fin); under the ansatz of :class:`~pinnhjb.pinn.FiniteHorizonValue` the last two are
zero by construction and only MSE_e is minimised: by Adam and L-BFGS, or (our default) by Levenberg-Marquardt on
the per-point residuals (:mod:`pinnhjb.gauss_newton`). The residuals and their Jacobians are the objects of
:mod:`pinnhjb.residuals`. f, g, Q and the terminal cost phi (with its gradient) are
evaluated once per stage on a pool of states and then indexed, so a frozen chain of previous stages
costs nothing per step.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field

import torch
from tqdm.auto import tqdm

from .config import TrainConfig
from .gauss_newton import DivergenceError, FlatParameters, levenberg_marquardt
from .pinn import FiniteHorizonValue, SteadyStateValue, ValueTerminalCost, gradient
from .residuals import Residual, get_residual

Tensor = torch.Tensor

__all__ = [
    "TrainHistory",
    "StatePool",
    "shared_times",
    "train_finite_horizon",
    "train_steady_state",
    "resolve_device",
    "DTYPES",
]

DTYPES = {"float32": torch.float32, "float64": torch.float64}


def resolve_device(device=None) -> torch.device:
    """``None``/"auto" picks CUDA when present, else CPU; anything else is passed to torch.device."""
    if device is None or device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    dev = torch.device(device)
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
        return cls(**d)


class _Log:
    """The :class:`TrainHistory` of a stage while it trains: points appended, then frozen by :meth:`history`."""

    def __init__(self):
        self.step, self.loss, self.wall, self.phase = [], [], [], []
        self.stop_reason = ""
        self.wall_time = 0.0
        self.final_loss = float("nan")

    def record(self, step: int, loss: float, wall: float, phase: str):
        self.step.append(int(step))
        self.loss.append(float(loss))
        self.wall.append(float(wall))
        self.phase.append(phase)

    def history(self) -> TrainHistory:
        return TrainHistory(
            self.step, self.loss, self.wall, self.phase, self.stop_reason, self.wall_time, self.final_loss
        )


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
        out = {"x": self.x[idx], "fx": self.fx[idx], "gx": self.gx[idx], "qx": self.qx[idx]}
        if self.phi is not None:
            out["phi"] = self.phi[idx]
        if self.dphi is not None:
            out["dphi"] = self.dphi[idx]
        return out


# ---------------------------------------------------------------------- the optimisation loop


def _lr_factor(config: TrainConfig):
    K = max(config.adam_steps, 1)
    if config.schedule == "cosine":
        r = config.lr_final_ratio
        return lambda k: r + (1 - r) * 0.5 * (1 + math.cos(math.pi * min(k, K) / K))
    if config.schedule == "inverse_time":
        return lambda k: 1.0 / (1.0 + config.lr_decay * k)
    return lambda k: 1.0


def _optimize(
    params, batch_loss, sample, epochs, config: TrainConfig, desc: str, progress: bool, lm=None
) -> TrainHistory:
    """Adam (resampled batches, or epochs of fixed mini-batches with the paper's stop rule), then L-BFGS, then
    Levenberg-Marquardt.

    ``sample(size)`` returns a fresh batch; ``epochs()`` yields lists of mini-batches (fixed data);
    ``lm = (flat, residual, lm_sample)`` for the Levenberg-Marquardt phase (see :mod:`.gauss_newton`): the network's
    flat weights, the :class:`~pinnhjb.residuals.Residual` whose per-point form and Jacobian it uses, and a sampler
    of its per-point arguments.
    """
    params = list(params)
    hist = _Log()
    start = time.perf_counter()
    opt = torch.optim.Adam(params, lr=config.lr)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, _lr_factor(config))
    bar = tqdm(
        total=config.adam_steps + config.lbfgs_steps + config.lm_steps,
        desc=desc,
        disable=not progress,
        leave=False,
        dynamic_ncols=True,
    )
    step = 0
    last = float("nan")

    def adam_step(batch) -> float:
        nonlocal step, last
        opt.zero_grad(set_to_none=True)
        loss = batch_loss(batch)
        if not torch.isfinite(loss):
            raise DivergenceError(
                desc,
                "Adam",
                step + 1,
                f"the loss is {loss.item()}",
                "lower lr, or check the scale of the system (f, g, Q, R) and that f, g, Q are "
                "finite on the training box",
            )
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
        lbfgs = torch.optim.LBFGS(
            params,
            lr=1.0,
            max_iter=config.lbfgs_steps,
            history_size=50,
            tolerance_grad=1e-12,
            tolerance_change=1e-15,
            line_search_fn="strong_wolfe",
        )

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
            warnings.warn(
                f"stage {desc}: L-BFGS diverged (non-finite loss after {evals} evaluations); kept the "
                f"weights from before L-BFGS (loss {final.item():.3e})",
                RuntimeWarning,
                stacklevel=2,
            )
        hist.final_loss = final.item()
    else:
        hist.final_loss = last
    iterations = 0
    if config.lm_steps > 0:
        flat, residual, lm_sample = lm
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
            result = levenberg_marquardt(
                flat.get(),
                residual.point_residual(flat),
                lm_sample,
                config.lm_steps,
                points,
                damping=config.lm_damping,
                max_time=left,
                on_step=on_step,
                min_progress=config.lm_min_progress,
                stall_windows=config.lm_stall_windows,
                desc=desc,
                jacobian=residual.jacobian(),
            )
            flat.set(result.theta)
            iterations = result.steps
            hist.final_loss = result.loss
            if config.adam_steps == 0 or result.stop_reason == "max_time":
                hist.stop_reason = result.stop_reason
    hist.wall_time = time.perf_counter() - start
    hist.record(step + evals + iterations, hist.final_loss, hist.wall_time, "final")
    bar.close()
    return hist.history()


def _generator(seed: int) -> torch.Generator:
    return torch.Generator().manual_seed(int(seed))


def _randint(gen, high: int, size: int, device) -> Tensor:
    return torch.randint(high, (size,), generator=gen).to(device)


def _uniform(gen, size: int, scale: float, dtype, device) -> Tensor:
    return (scale * torch.rand(size, generator=gen, dtype=torch.float64)).to(dtype=dtype, device=device)


def shared_times(gen, size: int, points_per_time: int, T: float, dtype, device) -> tuple[Tensor, tuple]:
    """Collocation times in [0, T], each of ceil(size / points_per_time) fresh times shared by that many points.

    * ``gen``: the CPU random generator.
    * ``size``: the number of points.
    * ``points_per_time``: points per fresh time, in turn.
    * ``T``: the horizon.
    * ``dtype``, ``device``: of the result.

    Returns (t, (times, index)) with t = times[index].
    """
    k = -(-size // points_per_time)
    times = _uniform(gen, k, T, dtype, device)
    index = torch.arange(size, device=device) % k
    return times[index], (times, index)


def _residual(system, model, residual, default: str) -> Residual:
    """The residual object of form ``residual`` (a name, a class or None for ``default``) on ``model``."""
    form = get_residual(default if residual is None else residual)
    if form.ansatz is not None and form.ansatz != model.ansatz:
        raise ValueError(
            f"the residual form {form.name!r} trains a model with ansatz={form.ansatz}; this model has "
            f"ansatz={model.ansatz}"
        )
    return form(system, model)


def train_finite_horizon(
    system,
    model: FiniteHorizonValue,
    config: TrainConfig,
    seed: int = 0,
    progress: bool = True,
    desc: str = "stage",
    residual: str | type[Residual] | None = None,
) -> TrainHistory:
    """Train ``model`` in place on the finite-horizon HJB (eq-hjbt) over Omega x [0, model.horizon] (Algorithm 1).

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
    pool = StatePool(
        system, system.sample(n_pool, gen, dtype=dtype, device=device), terminal, need_phi_grad=model.ansatz
    )
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

    lm = None
    if config.lm_steps > 0:

        def lm_sample(size):
            flow = pool.take(_randint(gen, len(pool), size, device))
            t = _uniform(gen, size, T, dtype, device)
            return res.point_arguments(flow, t)

        lm = (FlatParameters(model.net), res, lm_sample)
    params = [q for q in model.net.parameters()]
    return _optimize(params, batch_loss, sample, epochs, config, desc, progress, lm)


def train_steady_state(
    system,
    model: SteadyStateValue,
    config: TrainConfig,
    seed: int = 0,
    progress: bool = True,
    desc: str = "steady state",
    residual: str | type[Residual] | None = None,
) -> TrainHistory:
    """Train ``model`` in place on the steady-state HJB (eq-hjb) directly (the paper's T = infinity baseline).

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

    lm = None
    if config.lm_steps > 0:

        def lm_sample(size):
            return res.point_arguments(sample(size), None)

        lm = (FlatParameters(model.net), res, lm_sample)
    return _optimize(model.net.parameters(), res.loss, sample, epochs, config, desc, progress, lm)
