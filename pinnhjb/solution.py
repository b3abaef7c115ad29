"""What a solver returns: the value, its policy, its metrics and its provenance.

A :class:`FiniteHorizonSolution` is a chain of :class:`Stage` objects. Stage 1 solves the finite-horizon HJB
:eq:`eq-hjbt` on [0, T_1] with terminal cost phi; stage k solves the extension HJB :eq:`eq-hjbinc` on
[0, T_k - T_{k-1}] with terminal cost V_{T_{k-1}}(., 0) (Theorem 2), so ``value(x, t)`` of the chain is
V_{T_K}(x, t) for any t in [0, T_K]. A :class:`SteadyStateSolution` is the direct steady-state PINN (the
paper's T = infinity). An :class:`AveragedSolution` is the mean of solutions trained independently (other seeds).

Results are frozen dataclasses; their metrics are computed once, by the solver or read from a checkpoint. A
changed result is a new one, made with ``dataclasses.replace``.
"""

from __future__ import annotations

import math
import tempfile
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from . import metrics as _metrics
from .pinn import CallableTerminalCost, FiniteHorizonValue, SteadyStateValue, gradient
from .residuals import SteadyStateHJB
from .training import TrainHistory, resolve_device

if TYPE_CHECKING:
    from .config import TrainConfig
    from .systems import ControlAffineSystem

Tensor = torch.Tensor

__all__ = ["Stage", "FiniteHorizonSolution", "SteadyStateSolution", "AveragedSolution"]


class _ValueSolution:
    """Shared evaluation: V, grad V, mu = -1/2 R^{-1} g' grad V, E and errors, for numpy or torch input."""

    def _model_value(self, x: Tensor, t: float) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    @property
    def dtype(self) -> torch.dtype:
        return next(self._models()[0].parameters()).dtype

    @property
    def device(self) -> torch.device:
        return next(self._models()[0].parameters()).device

    def to(self, device):
        """This solution with its networks on ``device``: itself when they are there already, else a copy made by a
        checkpoint round trip (:func:`~pinnhjb.storage.save`, then :func:`~pinnhjb.storage.load` onto ``device``),
        so its weights, training histories and metrics are the ones a checkpoint stores; ``tol``, ``interrupted``
        and ``provenance`` are carried over, and so is a first terminal cost given as a Python function
        (:class:`~pinnhjb.pinn.CallableTerminalCost`, named or not: the same function, which must accept states
        on ``device``).

        * ``device``: a torch device or its name, ``"cpu"`` or ``"cuda"`` (None: CUDA when present); CUDA asked for
          where there is none raises a RuntimeError before anything is copied.
        """
        from . import storage  # storage builds solutions: imported here, not at the top

        dev, here = resolve_device(device), self.device
        if dev.type == here.type and dev.index in (None, here.index):
            return self
        terminal = getattr(self._models()[0], "terminal_cost", None)
        given = terminal if isinstance(terminal, CallableTerminalCost) else None
        source = self
        if given is not None and given.name is None:  # code is not stored: named for the round trip only
            given = CallableTerminalCost(terminal.fn, name="unnamed callable, moved")
            source = replace(self, terminal_spec=given.spec())
        with tempfile.TemporaryDirectory() as tmp:
            path = storage.save(source, Path(tmp) / "solution.pt")
            moved = storage.load(path, system=self.system, device=dev, terminal_cost=given)
        if source is not self:
            given.name = None  # unnamed again, as it was: the moved solution is no more savable than this one
        kept = {k: getattr(self, k) for k in ("tol", "interrupted", "provenance", "terminal_spec") if hasattr(self, k)}
        return replace(moved, **kept)

    def _models(self):  # pragma: no cover - abstract
        raise NotImplementedError

    def _time(self, t: float, horizon: float | None) -> float:
        """The time at which to evaluate: ``t``, or the time that gives the value of horizon ``horizon``."""
        if horizon is not None:
            raise TypeError(f"{type(self).__name__} has no horizon: evaluate it without horizon=")
        return t

    def value_function(self, t: float = 0.0, horizon: float | None = None):
        """V(., t) as a batched torch callable ``x (N, n) -> (N,)``, differentiable in x (and in the weights): for
        autograd through the learned value, e.g. a residual or a loss of one's own. It moves ``x`` to the networks'
        device and dtype, and its result back.

        * ``t``, ``horizon``: as in :meth:`value`, checked here, before any call.
        """
        return self._value_fn(self._time(t, horizon))

    def _value_fn(self, t: float = 0.0):
        def fn(x: Tensor) -> Tensor:
            return self._model_value(x.to(self.device, self.dtype), t).to(x.device, x.dtype)

        return fn

    def _prepare(self, x):
        is_numpy = not isinstance(x, torch.Tensor)
        xt = torch.as_tensor(np.asarray(x, dtype=float)) if is_numpy else x
        return self.system.check_states(xt), is_numpy

    def value(self, x, t: float = 0.0, horizon: float | None = None):
        """The value V(x, t).

        * ``x``: (N, n) states; numpy in gives numpy out, a tensor gives a (detached) tensor.
        * ``t``: the time, in [0, horizon].
        * ``horizon``: instead of ``t``, a horizon tau in [0, T]: the value V_tau(x, 0) of the problem over
          horizon tau with the same terminal cost, which is V_T(x, T - tau) for a time-invariant system (a
          finite-horizon solution only).

        Returns (N,).
        """
        t = self._time(t, horizon)
        xt, is_numpy = self._prepare(x)
        with torch.no_grad():
            v = self._value_fn(t)(xt)
        return v.numpy() if is_numpy else v

    def gradient(self, x, t: float = 0.0, horizon: float | None = None):
        """The gradient grad_x V(x, t), by autograd; ``x``, ``t`` and ``horizon`` as in :meth:`value`.

        Returns (N, n).
        """
        t = self._time(t, horizon)
        xt, is_numpy = self._prepare(x)
        _, g = gradient(self._value_fn(t), xt)
        return g.numpy() if is_numpy else g

    def policy(self, x, t: float = 0.0, horizon: float | None = None):
        """The policy ``mu(x, t) = -1/2 R^{-1} g(x)' grad_x V(x, t)``: :eq:`eq-muhat`.

        ``x``, ``t`` and ``horizon`` as in :meth:`value`. Returns (N, m).
        """
        t = self._time(t, horizon)
        xt, is_numpy = self._prepare(x)
        _, g = gradient(self._value_fn(t), xt)
        u = self.system.policy_from_gradient(xt, g).detach()
        return u.numpy() if is_numpy else u

    def residual_field(self, x, horizon: float | None = None):
        """The steady-state residual E_e(x; V(., 0)) :eq:`eq-ee` at states ``x`` (N, n).

        * ``horizon``: of V_tau(., 0) instead of V(., 0), as in :meth:`value`.

        Returns (N,).
        """
        xt, is_numpy = self._prepare(x)
        e = SteadyStateHJB(self.system, self._value_fn(self._time(0.0, horizon))).field(xt)
        return e.numpy() if is_numpy else e

    def evaluate(self, points_per_dim: int | None = None, horizon: float | None = None) -> dict:
        """The horizon check E :eq:`eq-e` over Omega, and the errors against V*, mu* when the system knows them.

        * ``points_per_dim``: the grid's points per axis; None: :func:`pinnhjb.metrics.default_points_per_dim`.
        * ``horizon``: of V_tau(., 0) instead of V(., 0), as in :meth:`value`.

        Returns the dict of :func:`pinnhjb.metrics.infinite_horizon_residual`, with those of
        :func:`pinnhjb.metrics.optimality_errors` when V* is known.
        """
        fn = self._value_fn(self._time(0.0, horizon))
        out = _metrics.infinite_horizon_residual(self.system, fn, points_per_dim=points_per_dim)
        if self.system.value_star is not None:
            out.update(_metrics.optimality_errors(self.system, fn, points_per_dim=points_per_dim))
        return out

    def closed_loop(self, x0, t_final: float = 20.0, dt: float = 0.01) -> _metrics.ClosedLoopResult:
        """Simulate the learned policy mu(., 0) by :func:`pinnhjb.metrics.closed_loop`.

        * ``x0``: (N, n) initial states.
        * ``t_final``: the simulated time.
        * ``dt``: the RK4 step.

        Returns a :class:`~pinnhjb.metrics.ClosedLoopResult`.
        """
        return _metrics.closed_loop(
            self.system, _metrics.policy_of(self.system, self._value_fn(0.0)), x0, t_final=t_final, dt=dt
        )

    def residual_along_loop(self, x0, t_final: float = 20.0, dt: float = 0.01) -> _metrics.LoopResidual:
        """E_e :eq:`eq-ee` of V(., 0) along the closed loops of mu(., 0) from ``x0``, by
        :func:`pinnhjb.metrics.residual_along_loop`: its ``gap``, ``J_T + V(x(T)) - V(x0)``, is the residual
        integrated along each loop, and ``integral_outside`` the part accrued outside the training box.

        * ``x0``: (N, n) initial states.
        * ``t_final``, ``dt``: as in :meth:`closed_loop`.

        Returns a :class:`~pinnhjb.metrics.LoopResidual`.
        """
        return _metrics.residual_along_loop(self.system, self._value_fn(0.0), x0, t_final=t_final, dt=dt)


@dataclass(frozen=True)
class Stage:
    """One trained horizon of a chain: its network, where it sits in the chain, its training history and metrics.

    * ``model``: the trained network v(x, t) on [0, ``length``], frozen (no gradients), with its terminal cost.
    * ``start``: the horizon covered before this stage (T_{k-1}; 0 for the first).
    * ``history``: the stage's training log (:class:`~pinnhjb.training.TrainHistory`).
    * ``seed``: the seed it was trained with (the solver's seed + k for stage k, counted from 0).
    * ``metrics``: E, E_zero and, when the system knows V*, the errors against V*, mu* of the chain ending with
      this stage (:meth:`FiniteHorizonSolution.evaluate`), computed once when the stage is built; empty when it
      was never evaluated. The stage holds its own copy.
    * ``rejected``: the attempts at this stage that were trained and not kept (``config.retries``), each a dict
      with its ``seed``, ``final_loss``, ``wall_time`` and ``stop_reason`` (with ``config.warm_start="best"`` also
      its ``warm_start`` and ``metrics``); empty when the first attempt was kept.
    """

    model: FiniteHorizonValue
    start: float
    history: TrainHistory
    seed: int
    metrics: dict = field(default_factory=dict)
    rejected: tuple = ()

    def __post_init__(self):
        object.__setattr__(self, "metrics", dict(self.metrics))
        object.__setattr__(self, "rejected", tuple(dict(a) for a in self.rejected))

    @property
    def length(self) -> float:
        """The stage's own horizon, ``model.horizon``."""
        return self.model.horizon

    @property
    def end(self) -> float:
        """``start + length``: the T_k whose V_{T_k}(., 0) the chain ending here gives."""
        return self.start + self.length

    @property
    def started_warm(self) -> bool | None:
        """With ``config.warm_start="best"``: whether the kept attempt started from the previous stage's weights
        (the attempt in ``rejected`` started the other way); None when the start was not chosen."""
        other = self.other_attempt
        return None if other is None else not other["warm_start"]

    @property
    def other_attempt(self) -> dict | None:
        """With ``config.warm_start="best"``: the attempt not kept, the entry of ``rejected`` that started the
        other way (its ``warm_start``, ``metrics``, ...); None when the start was not chosen."""
        others = [a for a in self.rejected if "warm_start" in a]
        return others[-1] if others else None


@dataclass(eq=False, frozen=True)
class FiniteHorizonSolution(_ValueSolution):
    """V_T(x, t) and mu_T(x, t) from a chain of stages (Algorithm 1 and Theorem 2).

    * ``system``: the :class:`~pinnhjb.systems.ControlAffineSystem` it solves.
    * ``config``: the :class:`~pinnhjb.config.TrainConfig` its stages were trained with.
    * ``stages``: the chain, stage 1 first (a list of :class:`Stage`, at least one); ``metrics`` are the last's.
    * ``terminal_spec``: the first stage's terminal cost phi as stored in a checkpoint (``{"kind": ...}``).
    * ``interrupted``: whether training stopped early on KeyboardInterrupt (the stages done so far are kept).
    * ``tol``: the E that :meth:`~pinnhjb.solver.FiniteHorizonSolver.solve_until` asked for; None otherwise
      (``solve``, ``extend``, a loaded checkpoint). ``converged`` is derived from it.
    * ``provenance``: the versions and time stamp stored with the checkpoint it was loaded from
      (:func:`pinnhjb.storage.provenance`); None for a solution trained in this session.
    """

    system: ControlAffineSystem
    config: TrainConfig
    stages: list[Stage]
    terminal_spec: dict
    interrupted: bool = False
    tol: float | None = None
    provenance: dict | None = None

    def __post_init__(self):
        if not self.stages:
            raise ValueError("a FiniteHorizonSolution needs at least one stage")
        object.__setattr__(self, "stages", list(self.stages))

    def _models(self):
        return [s.model for s in self.stages]

    def _time(self, t: float, horizon: float | None) -> float:
        if horizon is None:
            return t
        if isinstance(t, (int, float)) and t != 0.0:
            raise ValueError(f"give t or horizon, not both; got t={t}, horizon={horizon}")
        try:
            tau = float(horizon)
        except (TypeError, ValueError):
            raise TypeError(f"horizon must be a number; got {horizon!r}") from None
        if not 0.0 <= tau <= self.horizon + 1e-12:
            raise ValueError(
                f"horizon must lie in [0, {self.horizon:g}] (the chain's horizon T: V_tau(x, 0) = V_T(x, T - tau)); "
                f"got {horizon}"
            )
        return max(self.horizon - tau, 0.0)

    @property
    def converged(self) -> bool | None:
        """Whether E met the tolerance ``tol`` that :meth:`~pinnhjb.solver.FiniteHorizonSolver.solve_until` asked
        for; None when no tolerance was asked for (``solve``, ``extend``, a loaded checkpoint)."""
        return None if self.tol is None else bool(self.metrics.get("E", math.inf) <= self.tol)

    @property
    def horizon(self) -> float:
        """The total horizon T_K reached by the chain."""
        return self.stages[-1].end

    @property
    def horizons(self) -> list[float]:
        """The horizon T_k reached after each stage."""
        return [s.end for s in self.stages]

    @property
    def metrics(self) -> dict:
        """The last stage's metrics."""
        return self.stages[-1].metrics

    @property
    def wall_time(self) -> float:
        """Training seconds, all stages together, their attempts not kept included."""
        return float(sum(s.history.wall_time + sum(a["wall_time"] for a in s.rejected) for s in self.stages))

    def _model_value(self, x: Tensor, t: float) -> Tensor:
        t = float(t)
        if not 0.0 <= t <= self.horizon + 1e-12:
            raise ValueError(f"t must lie in [0, {self.horizon}] for this solution; got {t}")
        # V_{T_K}(x, t) = stage_j(x, t - (T_K - T_j)) for t in [T_K - T_j, T_K - T_{j-1}].
        for stage in reversed(self.stages):
            offset = self.horizon - stage.end
            if t <= offset + stage.length + 1e-12:
                return stage.model(x, max(t - offset, 0.0))
        raise AssertionError("unreachable")

    def truncated(self, k: int) -> FiniteHorizonSolution:
        """The solution after the first ``k`` stages (horizon T_k), sharing the trained networks.

        * ``k``: how many stages, 1 to ``len(stages)``.
        """
        if not 1 <= k <= len(self.stages):
            raise ValueError(f"k must be in 1..{len(self.stages)}; got {k}")
        return FiniteHorizonSolution(self.system, self.config, self.stages[:k], self.terminal_spec)

    def summary(self) -> list[dict]:
        """One row per stage: ``stage``, ``horizon`` reached, ``wall_time``, ``final_loss``, ``stop_reason`` and
        the stage's metrics; ``rejected`` (how many attempts were not kept) in the rows of retried stages, and
        ``started_warm`` in those whose start was chosen (``config.warm_start="best"``).

        After ``solve_until`` a row also holds ``converged``: E <= tol at that stage (False in the last row when
        it stopped at ``max_horizon`` short of ``tol``).
        """
        rows = [
            {
                "stage": i + 1,
                "horizon": s.end,
                "wall_time": s.history.wall_time,
                "final_loss": s.history.final_loss,
                "stop_reason": s.history.stop_reason,
                **s.metrics,
                **({"rejected": len(s.rejected)} if s.rejected else {}),
                **({"started_warm": s.started_warm} if s.started_warm is not None else {}),
            }
            for i, s in enumerate(self.stages)
        ]
        if self.tol is not None:
            for row in rows:
                row["converged"] = bool(row.get("E", math.inf) <= self.tol)
        return rows

    def __repr__(self):
        e = self.metrics.get("E")
        return (
            f"FiniteHorizonSolution(system={self.system.name!r}, horizons={self.horizons}, "
            f"E={e if e is None else f'{e:.3e}'}, wall_time={self.wall_time:.1f}s)"
        )


@dataclass(eq=False, frozen=True)
class SteadyStateSolution(_ValueSolution):
    """The direct steady-state PINN V(x) (the paper's T = infinity column of Table 1).

    * ``system``: the :class:`~pinnhjb.systems.ControlAffineSystem` it solves.
    * ``config``: the :class:`~pinnhjb.config.TrainConfig` it was trained with.
    * ``model``: the trained network V(x), frozen (no gradients).
    * ``history``: its training log (:class:`~pinnhjb.training.TrainHistory`).
    * ``seed``: the seed it was trained with.
    * ``metrics``: E, E_zero and, when the system knows V*, the errors against V*, mu* (:meth:`evaluate`),
      computed once when the solution is built; empty when it was never evaluated. The solution holds its own copy.
    * ``provenance``: the versions and time stamp stored with the checkpoint it was loaded from
      (:func:`pinnhjb.storage.provenance`); None for a solution trained in this session.
    """

    system: ControlAffineSystem
    config: TrainConfig
    model: SteadyStateValue
    history: TrainHistory
    seed: int
    metrics: dict = field(default_factory=dict)
    provenance: dict | None = None

    def __post_init__(self):
        object.__setattr__(self, "metrics", dict(self.metrics or {}))

    @property
    def converged(self) -> None:
        """Always None: no tolerance is asked of the steady-state PINN (see :attr:`FiniteHorizonSolution.converged`)."""
        return None

    def _models(self):
        return [self.model]

    @property
    def wall_time(self) -> float:
        """Training seconds."""
        return self.history.wall_time

    def _model_value(self, x: Tensor, t: float) -> Tensor:
        return self.model(x)

    def __repr__(self):
        e = self.metrics.get("E")
        return (
            f"SteadyStateSolution(system={self.system.name!r}, E={e if e is None else f'{e:.3e}'}, "
            f"wall_time={self.wall_time:.1f}s)"
        )


@dataclass(eq=False, frozen=True)
class AveragedSolution(_ValueSolution):
    """The mean of solutions of one system trained independently (other seeds): V = (1/K) sum_k V_k, and so
    grad V and the policy mu = -1/2 R^{-1} g' grad V :eq:`eq-muhat` are the members' means too. Where part of each
    member's error is its own (its points and its first weights) rather than the recipe's, the mean is closer to
    V* than a typical member, if not always than the best; chapter 9 (section 3, the ladder) and chapter 10
    (section 5, the rigid body) measure by how much. Checkpoints store the members, one by one.

    * ``members``: the solutions (at least one; a list or tuple of :class:`FiniteHorizonSolution` or
      :class:`SteadyStateSolution`), all of the same system (its name and n); each is evaluated at the same t,
      so chains give the mean of their V_T(., 0) at t = 0.
    """

    members: tuple

    def __post_init__(self):
        members = tuple(self.members) if isinstance(self.members, (list, tuple)) else None
        if not members:
            raise ValueError(f"an AveragedSolution needs a non-empty list of solutions; got {self.members!r}")
        for m in members:
            if not isinstance(m, (FiniteHorizonSolution, SteadyStateSolution)):
                raise TypeError(f"members must be FiniteHorizonSolution or SteadyStateSolution; got {type(m).__name__}")
        first = members[0].system
        for m in members[1:]:
            if (m.system.name, m.system.n) != (first.name, first.n):
                raise ValueError(
                    f"members must solve one system; got '{first.name}' (n = {first.n}) and "
                    f"'{m.system.name}' (n = {m.system.n})"
                )
        object.__setattr__(self, "members", members)

    @property
    def system(self) -> ControlAffineSystem:
        """The first member's system (all members solve one)."""
        return self.members[0].system

    @property
    def converged(self) -> None:
        """Always None: no tolerance is asked of a mean."""
        return None

    @property
    def metrics(self) -> dict:
        """Empty: a mean is measured by :meth:`evaluate`, not when it is built."""
        return {}

    @property
    def wall_time(self) -> float:
        """The members' training seconds, summed (independent runs may have run at the same time)."""
        return sum(m.wall_time for m in self.members)

    def _models(self):
        return [model for m in self.members for model in m._models()]

    def _model_value(self, x: Tensor, t: float) -> Tensor:
        return sum(m._value_fn(t)(x) for m in self.members) / len(self.members)

    def to(self, device):
        """This mean with every member on ``device`` (:meth:`FiniteHorizonSolution.to`)."""
        moved = tuple(m.to(device) for m in self.members)
        return self if all(a is b for a, b in zip(moved, self.members)) else replace(self, members=moved)

    def __repr__(self):
        return f"AveragedSolution(system={self.system.name!r}, members={len(self.members)})"
