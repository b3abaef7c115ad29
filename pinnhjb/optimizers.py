"""The optimisers of a training recipe: each phase is an object, and a recipe is a tuple of phases run in turn.

A phase (:class:`Adam`, :class:`LBFGS`, :class:`LevenbergMarquardt`) holds its settings and runs itself on an
:class:`Objective`, the loss of one stage built by :mod:`pinnhjb.training`. A new optimiser is one class with a
``name`` and a ``run`` method, registered with :func:`register`; ``TrainConfig.phases`` takes it
like the built-in ones, and checkpoints store it by its name.
"""

from __future__ import annotations

import math
import time
import warnings
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, fields
from typing import Any, ClassVar

import torch
from tqdm.auto import tqdm

from .checks import integer, raise_invalid, real
from .gauss_newton import DivergenceError, FlatParameters, levenberg_marquardt

__all__ = [
    "Phase",
    "Adam",
    "LBFGS",
    "LevenbergMarquardt",
    "Objective",
    "Tracker",
    "PhaseOutcome",
    "PHASES",
    "register",
    "get_phase",
    "phase_from_dict",
]

PHASES: dict[str, type[Phase]] = {}
"""Every registered phase class by its ``name``."""


def register(cls: type[Phase]) -> type[Phase]:
    """Register a phase class under its ``name`` (a class decorator), so configs and checkpoints can name it.

    * ``cls``: a subclass of :class:`Phase` with a class attribute ``name``.
    """
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name or not issubclass(cls, Phase):
        raise TypeError(f"{cls!r}: a phase is a subclass of Phase with a class attribute name (a non-empty string)")
    if name in PHASES and PHASES[name] is not cls:
        raise ValueError(f"a phase named {name!r} is already registered ({PHASES[name].__qualname__})")
    PHASES[name] = cls
    return cls


def get_phase(name: str) -> type[Phase]:
    """The phase class registered under ``name``.

    * ``name``: a registered name, e.g. ``"adam"``, ``"lbfgs"``, ``"lm"``.
    """
    if name not in PHASES:
        raise KeyError(f"unknown optimiser phase {name!r}; registered: {sorted(PHASES)}")
    return PHASES[name]


def phase_from_dict(d: dict) -> Phase:
    """The phase stored as ``d`` by :meth:`Phase.to_dict` (its ``name`` and its fields).

    * ``d``: the stored dict.
    """
    d = dict(d)
    cls = get_phase(d.pop("name", None))
    known = {f.name for f in fields(cls)}
    unknown = set(d) - known
    if unknown:
        raise ValueError(f"unknown {cls.__name__} field(s) {sorted(unknown)}; its fields: {sorted(known)}")
    return cls(**d)


@dataclass(frozen=True)
class Objective:
    """What a phase minimises: one stage's loss and its samplers, built by :mod:`pinnhjb.training`.

    * ``params``: the network's parameters, optimised in place.
    * ``loss``: a batch -> the scalar training loss :eq:`eq-mse` (MSE_e alone under the ansatz).
    * ``sample``: a number of points -> a batch of fresh collocation points.
    * ``epochs``: () -> the mini-batches of one epoch over the fixed data set (``sampling="fixed"``), else None.
    * ``sampling``: ``"resample"`` or ``"fixed"``, from the config.
    * ``batch_size``: flow points per first-order step, from the config.
    * ``flat``: the network's weights as one vector (for second-order phases).
    * ``residual``: the PDE form (:class:`pinnhjb.residuals.Residual`): per-point residual and Jacobian.
    * ``point_sample``: a number of points -> the residual's per-point arguments on fresh points.
    * ``desc``: the stage's label, for the progress bar and errors.
    """

    params: list
    loss: Callable[[Any], torch.Tensor]
    sample: Callable[[int], Any]
    epochs: Callable[[], Iterable] | None
    sampling: str
    batch_size: int
    flat: FlatParameters
    residual: Any
    point_sample: Callable[[int], tuple]
    desc: str


class Tracker:
    """The training log, progress bar and clock of one stage, shared by its phases.

    * ``total``: the steps of all phases (the progress bar's length).
    * ``desc``: the stage's label.
    * ``progress``: show a progress bar.
    * ``log_every``: log the loss every this many iterations of a phase (and its first).
    * ``max_time``: the stage's wall-time cap in seconds, or None.
    """

    def __init__(self, total: int, desc: str, progress: bool, log_every: int, max_time: float | None):
        self.start = time.perf_counter()
        self.done = 0  # iterations of the finished phases
        self.log_every = log_every
        self.max_time = max_time
        self.step: list[int] = []
        self.loss: list[float] = []
        self.wall: list[float] = []
        self.phase: list[str] = []
        self.bar = tqdm(total=total, desc=desc, disable=not progress, leave=False, dynamic_ncols=True)

    def elapsed(self) -> float:
        """Seconds since the stage's training started."""
        return time.perf_counter() - self.start

    def time_left(self) -> float | None:
        """Seconds left under ``max_time``, or None without a cap."""
        return None if self.max_time is None else self.max_time - self.elapsed()

    def out_of_time(self) -> bool:
        """Whether the stage has run past ``max_time``."""
        return self.max_time is not None and self.elapsed() > self.max_time

    def record(self, step: int, loss: float, phase: str, wall: float | None = None) -> None:
        """Append one point to the log.

        * ``step``: the iteration, counted over all phases.
        * ``loss``: the loss there.
        * ``phase``: the phase's name.
        * ``wall``: the seconds since the start (None: now).
        """
        self.step.append(int(step))
        self.loss.append(float(loss))
        self.wall.append(float(self.elapsed() if wall is None else wall))
        self.phase.append(phase)

    def advance(self, k: int, loss: float, phase: str, log_first: bool = True) -> None:
        """One iteration of a phase done: log it when due, move the progress bar.

        * ``k``: the iteration within the phase, from 1.
        * ``loss``: its loss.
        * ``phase``: the phase's name.
        * ``log_first``: log iteration 1 too.
        """
        if k % self.log_every == 0 or (log_first and k == 1):
            self.record(self.done + k, loss, phase)
        self.bar.set_postfix(loss=f"{loss:.3e}", refresh=False)  # shown at tqdm's own refresh rate
        self.bar.update(1)


@dataclass(frozen=True)
class PhaseOutcome:
    """What a phase reports when it ends.

    * ``loss``: the training loss at its end.
    * ``iterations``: the iterations it ran.
    * ``stop_reason``: why it stopped, or None for a phase that runs its fixed count (the previous reason stands).
    """

    loss: float
    iterations: int
    stop_reason: str | None


class Phase:
    """One optimiser run for a number of steps: the base class of the phases of a recipe.

    A subclass is a frozen dataclass with a class attribute ``name``, a field ``steps`` (at most this many
    iterations) and a method ``run(objective, tracker) -> PhaseOutcome``; it advances ``tracker`` once per
    iteration, adds its iterations to ``tracker.done`` and raises :class:`~pinnhjb.gauss_newton.DivergenceError`
    on a non-finite loss. ``needs_ansatz`` marks a phase that minimises the flow residual alone.
    """

    name: ClassVar[str] = ""
    needs_ansatz: ClassVar[bool] = False
    added_later: ClassVar[tuple[str, ...]] = ()  # fields stored only when not at their default (:meth:`to_dict`)
    steps: int

    def run(self, objective: Objective, tracker: Tracker) -> PhaseOutcome:
        """Optimise ``objective.params`` in place; what the phase reports.

        * ``objective``: the stage's loss and samplers.
        * ``tracker``: the stage's log, progress bar and clock.
        """
        raise NotImplementedError

    def to_dict(self) -> dict:
        """The phase as a dict: its ``name`` and its fields (:func:`phase_from_dict` inverts it). A field added
        after checkpoints were first stored (the class's ``added_later``) is written only when it differs from its
        default, so a phase stored before it reads back exactly as it was written."""
        skip = {f.name for f in fields(self) if f.name in self.added_later and getattr(self, f.name) == f.default}
        return {"name": self.name, **{k: v for k, v in asdict(self).items() if k not in skip}}

    def replace(self, **changes) -> Phase:
        """A copy with ``changes`` applied (and checked)."""
        known = {f.name for f in fields(self)}
        unknown = set(changes) - known
        if unknown:
            raise ValueError(f"unknown {type(self).__name__} field(s) {sorted(unknown)}; its fields: {sorted(known)}")
        return type(self)(**{**asdict(self), **changes})


@register
@dataclass(frozen=True)
class Adam(Phase):
    """Adam on the training loss, from learning rate ``lr`` with a decay schedule.

    * ``steps``: at most this many steps.
    * ``lr``: the initial learning rate.
    * ``schedule``: ``"cosine"`` (to ``lr * lr_final_ratio`` at the last step), ``"inverse_time"``
      (lr / (1 + lr_decay * k), the paper's) or ``"constant"``.
    * ``lr_final_ratio``: the cosine schedule's final learning rate over ``lr``.
    * ``lr_decay``: the inverse-time schedule's decay.
    * ``stop_loss``: with fixed data (``sampling="fixed"``), stop after an epoch whose every mini-batch loss is below
      it (the paper's rule); None: run ``steps``.

    With ``sampling="resample"`` each step draws ``batch_size`` fresh flow points; with ``"fixed"`` the steps run over
    epochs of mini-batches of the fixed data set.
    """

    name: ClassVar[str] = "adam"
    steps: int = 2500
    lr: float = 2e-3
    schedule: str = "cosine"
    lr_final_ratio: float = 0.01
    lr_decay: float = 0.0
    stop_loss: float | None = None

    def __post_init__(self):
        raise_invalid(
            self,
            {
                "steps": (integer(self.steps, 1), "an integer >= 1"),
                "lr": (real(self.lr, 0, low_open=True), "a finite number > 0"),
                "schedule": (
                    self.schedule in ("cosine", "inverse_time", "constant"),
                    "'cosine', 'inverse_time' or 'constant'",
                ),
                "lr_final_ratio": (real(self.lr_final_ratio, 0, 1), "a number in [0, 1]"),
                "lr_decay": (real(self.lr_decay, 0), "a finite number >= 0"),
                "stop_loss": (real(self.stop_loss, 0, low_open=True, none=True), "a finite number > 0 or None"),
            },
        )

    def lr_factor(self) -> Callable[[int], float]:
        """The schedule: step k -> the learning rate over ``lr``."""
        if self.schedule == "cosine":
            K, r = self.steps, self.lr_final_ratio
            return lambda k: r + (1 - r) * 0.5 * (1 + math.cos(math.pi * min(k, K) / K))
        if self.schedule == "inverse_time":
            return lambda k: 1.0 / (1.0 + self.lr_decay * k)
        return lambda k: 1.0

    def run(self, objective: Objective, tracker: Tracker) -> PhaseOutcome:
        opt = torch.optim.Adam(objective.params, lr=self.lr)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, self.lr_factor())
        k = 0
        last = float("nan")

        def step(batch) -> float:
            nonlocal k, last
            opt.zero_grad(set_to_none=True)
            loss = objective.loss(batch)
            if not torch.isfinite(loss):
                raise DivergenceError(
                    objective.desc,
                    "Adam",
                    k + 1,
                    f"the loss is {loss.item()}",
                    "lower lr, or check the scale of the system (f, g, Q, R) and that f, g, Q are "
                    "finite on the training box",
                )
            loss.backward()
            opt.step()
            sched.step()
            k += 1
            last = loss.item()
            tracker.advance(k, last, self.name)
            return last

        reason = "adam_steps"
        if objective.sampling == "resample":
            while k < self.steps:
                step(objective.sample(objective.batch_size))
                if tracker.out_of_time():
                    reason = "max_time"
                    break
        else:
            done = False
            while not done:
                all_below = True
                for batch in objective.epochs():
                    value = step(batch)
                    all_below &= self.stop_loss is not None and value < self.stop_loss
                    if k >= self.steps:
                        done = True
                        break
                    if tracker.out_of_time():
                        reason, done = "max_time", True
                        break
                else:
                    if all_below:
                        reason, done = "stop_loss", True
        tracker.done += k
        return PhaseOutcome(last, k, reason)


@register
@dataclass(frozen=True)
class LBFGS(Phase):
    """L-BFGS with a strong-Wolfe line search on one fixed set of fresh flow points.

    * ``steps``: the iterations (``max_iter`` of ``torch.optim.LBFGS``).
    * ``points``: the flow points, drawn once.

    A line search that ends on a non-finite loss restores the weights from before the phase and warns.
    """

    name: ClassVar[str] = "lbfgs"
    steps: int = 800
    points: int = 4000

    def __post_init__(self):
        raise_invalid(
            self,
            {
                "steps": (integer(self.steps, 1), "an integer >= 1"),
                "points": (integer(self.points, 1), "an integer >= 1"),
            },
        )

    def run(self, objective: Objective, tracker: Tracker) -> PhaseOutcome:
        params, desc = objective.params, objective.desc
        batch = objective.sample(self.points)
        lbfgs = torch.optim.LBFGS(
            params,
            lr=1.0,
            max_iter=self.steps,
            history_size=50,
            tolerance_grad=1e-12,
            tolerance_change=1e-15,
            line_search_fn="strong_wolfe",
        )
        evals = 0

        def closure():
            nonlocal evals
            lbfgs.zero_grad(set_to_none=True)
            loss = objective.loss(batch)
            if evals == 0 and not torch.isfinite(loss):  # at the starting point: not a line-search overshoot
                raise DivergenceError(desc, "L-BFGS", 1, f"the loss is {loss.item()} at its starting point")
            loss.backward()
            evals += 1
            tracker.advance(evals, loss.item(), self.name, log_first=False)
            return loss

        before = [p.detach().clone() for p in params]
        lbfgs.step(closure)
        final = objective.loss(batch)
        if not torch.isfinite(final):  # a diverged line search must not destroy the previous phase's result
            with torch.no_grad():
                for p, b in zip(params, before):
                    p.copy_(b)
            final = objective.loss(batch)
            if not torch.isfinite(final):
                raise DivergenceError(desc, "L-BFGS", evals, f"the loss is {final.item()}")
            warnings.warn(
                f"stage {desc}: L-BFGS diverged (non-finite loss after {evals} evaluations); kept the "
                f"weights from before L-BFGS (loss {final.item():.3e})",
                RuntimeWarning,
                stacklevel=2,
            )
        tracker.done += evals
        return PhaseOutcome(final.item(), evals, None)


@register
@dataclass(frozen=True)
class LevenbergMarquardt(Phase):
    """Levenberg-Marquardt on the per-point flow residuals, fresh points every iteration (:mod:`pinnhjb.gauss_newton`).

    * ``steps``: at most this many iterations.
    * ``points``: the points per iteration at the last level.
    * ``points_coarse``: the points per iteration until the loss first stalls (fewer than the weights: a cheap step
      that stalls at a noise floor); None: ``points`` throughout.
    * ``damping``: the initial damping lambda.
    * ``min_progress``: the loss has stalled when it fell by less than this factor over the last ``stall_windows``
      windows of 10 iterations; None: never stall, run ``steps`` on ``points`` (``points_coarse`` unused).
    * ``stall_windows``: the windows of the stall rule.
    * ``adaptive``: the share of each iteration's points chosen where the residual is largest, from ``candidates``
      times as many fresh points (:func:`~pinnhjb.gauss_newton.levenberg_marquardt`); 0: all drawn as usual.
    * ``candidates``: the fresh points scored per point chosen, an integer >= 2.

    Needs the ansatz (the flow residual is the whole loss). Its cost per iteration grows with the square of the
    number of weights: keep the network small (about 10^3 weights).
    """

    name: ClassVar[str] = "lm"
    needs_ansatz: ClassVar[bool] = True
    steps: int = 300
    points: int = 1500
    points_coarse: int | None = 700
    damping: float = 1e-3
    min_progress: float | None = 2.0
    stall_windows: int = 2
    adaptive: float = 0.0
    candidates: int = 4
    added_later: ClassVar[tuple[str, ...]] = ("adaptive", "candidates")

    def __post_init__(self):
        raise_invalid(
            self,
            {
                "steps": (integer(self.steps, 1), "an integer >= 1"),
                "points": (integer(self.points, 1), "an integer >= 1"),
                "points_coarse": (integer(self.points_coarse, 1, none=True), "an integer >= 1 or None"),
                "damping": (real(self.damping, 0, low_open=True), "a finite number > 0"),
                "min_progress": (real(self.min_progress, 1, none=True), "a finite number >= 1 or None"),
                "stall_windows": (integer(self.stall_windows, 1), "an integer >= 1"),
                "adaptive": (real(self.adaptive, 0) and self.adaptive < 1, "a number in [0, 1)"),
                "candidates": (integer(self.candidates, 2), "an integer >= 2"),
            },
        )
        if self.points_coarse is not None and self.points_coarse >= self.points:
            raise ValueError(
                f"LevenbergMarquardt: points_coarse={self.points_coarse} must be fewer than points={self.points} "
                "(the coarse level comes first); set points_coarse=None to use points throughout"
            )

    def run(self, objective: Objective, tracker: Tracker) -> PhaseOutcome:
        flat, residual = objective.flat, objective.residual

        def on_step(k, loss, damping):
            tracker.advance(k, loss, self.name)

        # the coarse level ends on a stall: without the stall rule, points throughout
        coarse = self.points_coarse if self.min_progress is not None else None
        result = levenberg_marquardt(
            flat.get(),
            residual.point_residual(flat),
            objective.point_sample,
            self.steps,
            (self.points,) if coarse is None else (coarse, self.points),
            damping=self.damping,
            max_time=tracker.time_left(),
            on_step=on_step,
            min_progress=self.min_progress,
            stall_windows=self.stall_windows,
            desc=objective.desc,
            jacobian=residual.jacobian(),
            adaptive=self.adaptive,
            candidates=self.candidates,
        )
        flat.set(result.theta)
        tracker.done += result.steps
        return PhaseOutcome(result.loss, result.steps, result.stop_reason)
