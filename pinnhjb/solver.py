"""Solvers configured once: Algorithm 1, the horizon extension of Theorem 2, and the steady-state baseline.

>>> import pinnhjb as ph
>>> solver = ph.FiniteHorizonSolver(ph.systems.pendulum(), config="default", seed=0)
>>> sol = solver.solve(horizon=1.0)  # Algorithm 1: V_1 on Omega x [0, 1]
>>> sol = solver.extend(sol, to=4.0, step=1.0)  # Theorem 2: three more stages
>>> sol = solver.solve_until(tol=1e-4, step=1.0)  # until E <= tol (Section 5.1)

Arguments are checked before any training starts (an error names the argument, the value and what is
expected). Nothing trained is lost: when a later stage fails (e.g. :class:`~pinnhjb.gauss_newton.DivergenceError`),
the exception carries the stages completed before it as ``exc.partial_solution`` (say so in its notes), and
``callback`` has already seen each of them. A stage whose E is no better than that of V = 0 warns.

Each result's metrics are computed once, when the solver builds it, by ``FiniteHorizonSolver.evaluate``: by
default E and the errors against V* on ``config.eval_points_per_dim`` points per axis
(:meth:`~pinnhjb.solution.FiniteHorizonSolution.evaluate`); the ``evaluate=`` argument replaces that with any
function of the result (e.g. a benchmark's own timed measure on its own points, or ``lambda sol: {}`` to skip it).
"""

from __future__ import annotations

import math
import numbers
import os
import sys
import warnings
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import torch

from .config import PAPER_SETTINGS, TrainConfig
from .pinn import (
    CallableTerminalCost,
    FiniteHorizonValue,
    QuadraticTerminalCost,
    SteadyStateValue,
    ValueTerminalCost,
    ZeroTerminalCost,
)
from .solution import FiniteHorizonSolution, Stage, SteadyStateSolution
from .training import DTYPES, resolve_device, train_finite_horizon, train_steady_state

__all__ = ["FiniteHorizonSolver", "SteadyStateSolver", "make_terminal_cost", "retry_base", "MAX_STAGES_PER_CALL"]

MAX_STAGES_PER_CALL = 10000  # one extend() call; solve_until extends one stage at a time, so its chain is unbounded


def retry_base(losses, against: str = "previous") -> float:
    """The final training loss the next stage's is compared with (``TrainConfig.retry_against``), given the final
    losses of a chain's stages so far, in order: the last one (``"previous"``) or the lowest finite one
    (``"best"``; the last if none is finite). A stage is tried again when its loss exceeds ``retry_factor`` times it.

    * ``losses``: the stages' final training losses (at least one).
    * ``against``: ``"previous"`` or ``"best"``.
    """
    losses = [float(v) for v in losses]
    if not losses:
        raise ValueError("retry_base needs the final loss of at least one stage")
    if against == "previous":
        return losses[-1]
    if against != "best":
        raise ValueError(f"against must be 'previous' or 'best'; got {against!r}")
    return min((v for v in losses if math.isfinite(v)), default=losses[-1])


def _number(value, name: str, *, positive: bool = True, allow_inf: bool = False, expected: str = "") -> float:
    """A real number (Python, numpy or a one-element tensor) as a float, or an error naming ``name``."""
    if (
        isinstance(value, torch.Tensor)
        and value.numel() == 1
        and not value.dtype.is_complex
        and value.dtype != torch.bool
    ):
        value = value.item()
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(
            f"{name} must be {expected or 'a positive finite number'}; got {value!r} of type "
            f"{type(value).__name__} (not a number)"
        )
    value = float(value)
    if math.isnan(value) or (math.isinf(value) and not allow_inf) or (positive and not value > 0):
        expected = expected or ("a positive number (inf allowed)" if allow_inf else "a positive finite number")
        raise ValueError(f"{name} must be {expected}; got {value!r}")
    return value


def _seed(seed) -> int:
    if isinstance(seed, torch.Tensor) and seed.numel() == 1 and not seed.is_floating_point():
        seed = seed.item()
    if isinstance(seed, bool) or not isinstance(seed, numbers.Integral) or not 0 <= int(seed) < 2**63 - 2**20:
        raise ValueError(f"seed must be an integer in [0, 2**63 - 2**20) (stage k uses seed + k); got {seed!r}")
    return int(seed)


def _user_level() -> int:
    """The ``stacklevel`` that makes a warning, given in the calling function, name the first line outside
    pinnhjb (the user's call, however deep in the package the warning is raised)."""
    frame, level, here = sys._getframe(1), 1, os.path.dirname(__file__)
    while frame is not None and frame.f_code.co_filename.startswith(here):
        frame, level = frame.f_back, level + 1
    return level


def _keep(exc: BaseException, solution) -> None:
    """Attach the stages trained before ``exc`` to it (``exc.partial_solution``), once, with a note."""
    if solution is None or getattr(exc, "partial_solution", None) is not None:
        return
    try:
        exc.partial_solution = solution
        exc.add_note(
            f"the {len(solution.stages)} stage(s) trained before this error (up to T={solution.horizon:g}) "
            f"are in this exception's .partial_solution (save them with pinnhjb.save)"
        )
    except (AttributeError, TypeError):  # an exception type that takes no attributes
        pass


def make_terminal_cost(terminal_cost, n: int | None = None) -> torch.nn.Module:
    """The terminal cost phi as a module.

    * ``terminal_cost``: None (zero), an (n, n) matrix P (phi = x'Px), a torch callable, or a terminal-cost module.
    * ``n``: the state dimension, to check P's shape.
    """
    if terminal_cost is None:
        return ZeroTerminalCost()
    if isinstance(terminal_cost, torch.nn.Module):
        return terminal_cost
    if isinstance(terminal_cost, (np.ndarray, list, tuple)) or (
        isinstance(terminal_cost, torch.Tensor) and terminal_cost.ndim == 2
    ):
        try:
            P = np.asarray(
                terminal_cost.cpu() if isinstance(terminal_cost, torch.Tensor) else terminal_cost, dtype=float
            )
        except (TypeError, ValueError) as exc:
            raise ValueError(
                f"terminal_cost as a matrix P (phi = x'Px) must hold numbers; got {terminal_cost!r}"
            ) from exc
        if n is not None and P.shape != (n, n):
            raise ValueError(f"terminal_cost as a matrix P (phi = x'Px) must be ({n}, {n}); got shape {P.shape}")
        if not np.all(np.isfinite(P)):
            raise ValueError("terminal_cost matrix P contains NaN or infinite entries")
        return QuadraticTerminalCost(P)
    if callable(terminal_cost):
        return CallableTerminalCost(terminal_cost)
    raise TypeError(f"terminal_cost must be None, a matrix, a callable or a module; got {type(terminal_cost).__name__}")


def _config(config, system) -> TrainConfig:
    if isinstance(config, TrainConfig):
        return config
    if isinstance(config, str):
        key = system.builder or system.name
        if config == "paper" and key not in PAPER_SETTINGS:
            raise ValueError(
                f"config='paper' is the paper's Section 6 recipe, whose network, learning rate and "
                f"threshold are set per example ({sorted(PAPER_SETTINGS)}); system '{system.name}' is "
                f"not one of them: use config='default' (ours), or borrow an example's settings with "
                f"config=TrainConfig.preset('paper', system='pendulum')"
            )
        return TrainConfig.preset(config, system=key, dimension=system.n)
    if isinstance(config, dict):
        return TrainConfig(**config)
    raise TypeError(f"config must be a TrainConfig, a preset name or a dict; got {type(config).__name__}")


class _Solver:
    def __init__(
        self,
        system,
        config="default",
        seed: int = 0,
        device=None,
        progress: bool = True,
        evaluate: Callable[..., dict] | None = None,
    ):
        from .systems import ControlAffineSystem

        if not isinstance(system, ControlAffineSystem):
            raise TypeError(f"system must be a ControlAffineSystem (see pinnhjb.systems); got {type(system).__name__}")
        if evaluate is not None and not callable(evaluate):
            raise TypeError(
                f"evaluate must be a callable (a solution -> a dict of metrics) or None; got {type(evaluate).__name__}"
            )
        self.system = system
        self.config = _config(config, system)
        self.seed = _seed(seed)
        self.device = resolve_device(device)
        self.progress = bool(progress)
        self.evaluator = evaluate

    @property
    def dtype(self) -> torch.dtype:
        """The networks' dtype, from ``config.dtype``."""
        return DTYPES[self.config.dtype]

    def evaluate(self, solution) -> dict:
        """The metrics this solver gives a result it builds (for a chain: its last stage's), computed once.

        * ``solution``: the trained result, before its metrics are attached.

        Returns the ``evaluate`` hook's dict when the solver was given one, else ``solution.evaluate`` on
        ``config.eval_points_per_dim`` points per axis (E, E_zero and, when the system knows V*, the errors).
        """
        if self.evaluator is not None:
            metrics = self.evaluator(solution)
            if not isinstance(metrics, dict):
                raise TypeError(f"the evaluate hook must return a dict of metrics; got {type(metrics).__name__}")
            return metrics
        return solution.evaluate(self.config.eval_points_per_dim)

    def _check_against_zero(self, metrics: dict, what: str):
        """Warn when a trained stage is no better than V = 0 (E at least E of V = 0 on the same points)."""
        E, E_zero = metrics.get("E"), metrics.get("E_zero")
        if E is not None and E_zero is not None and not E < E_zero:
            warnings.warn(
                f"{what}: E = {E:.3e} is no better than E of V = 0 ({E_zero:.3e}): the network learned "
                f"nothing useful (saturated? check the scale of Q and R, the horizon, or the optimiser phases' "
                f"lr or damping)",
                RuntimeWarning,
                stacklevel=_user_level(),
            )


class FiniteHorizonSolver(_Solver):
    """Finite-horizon PINN (Algorithm 1) with horizon extension (Theorem 2).

    * ``system``: the :class:`~pinnhjb.systems.ControlAffineSystem` to solve.
    * ``config``: a :class:`~pinnhjb.config.TrainConfig`, a preset name (``"default"``, ``"paper"``, ``"quick"``,
      ...) or a dict.
    * ``seed``: for initialisation and sampling (stage k uses seed + k).
    * ``device``: None for CUDA when present, else CPU.
    * ``progress``: show progress bars.
    * ``evaluate``: the metrics of each new stage, a callable (the chain ending with it) -> dict; None for
      E and the errors on ``config.eval_points_per_dim`` points per axis (see ``evaluate``).
    """

    def _train_stage(
        self,
        length: float,
        start: float,
        terminal,
        init: FiniteHorizonValue | None,
        index: int,
        base_loss=None,
        warm: bool = True,
    ) -> Stage:
        """Train stage ``index`` on [0, ``length``]; with ``config.retries``, try again with new seeds (see
        :class:`~pinnhjb.config.TrainConfig`) and keep the attempt with the lowest final loss.

        * ``init``: the previous stage's network (None for the first stage).
        * ``base_loss``: the final training loss a rise is measured from, as ``config.retry_against`` names
          (:meth:`_base_loss`; None for the first stage).
        * ``warm``: start from ``init``'s weights (``"features"``: with the last layer zero); else from fresh ones.
        """
        cfg = self.config
        attempts: list[Stage] = []
        for attempt in range(1 + cfg.retries):
            if attempts:
                best = min(a.history.final_loss for a in attempts)
                if base_loss is not None and math.isfinite(best) and best <= cfg.retry_factor * base_loss:
                    break  # an extension stage that did not fail
            seed = self.seed + index + 1000 * attempt
            torch.manual_seed(seed)
            model = FiniteHorizonValue(
                self.system.n,
                length,
                self.system.train_domain,
                terminal,
                width=cfg.width,
                depth=cfg.depth,
                activation=cfg.activation,
                ansatz=cfg.ansatz,
                flat_origin=cfg.flat_origin,
            )
            model = model.to(device=self.device, dtype=self.dtype)
            if init is not None and warm:
                model.net.load_state_dict(init.net.state_dict())
                if warm == "features":  # the stage starts at its terminal cost, on the stage before's features
                    model.net.zero_output_()
            desc = f"{self.system.name} T={start:g}->{start + length:g}"
            desc += f", attempt {attempt + 1}" if attempt else ""
            desc += ", fresh" if init is not None and not warm and cfg.warm_start == "best" else ""
            history = train_finite_horizon(self.system, model, cfg, seed=seed, progress=self.progress, desc=desc)
            for p in model.parameters():
                p.requires_grad_(False)
            attempts.append(Stage(model=model.eval(), start=start, history=history, seed=seed))
        losses = [a.history.final_loss for a in attempts]
        kept = min(range(len(attempts)), key=lambda i: (not math.isfinite(losses[i]), losses[i]))
        rejected = [
            {
                "seed": a.seed,
                "final_loss": a.history.final_loss,
                "wall_time": a.history.wall_time,
                "stop_reason": a.history.stop_reason,
            }
            for i, a in enumerate(attempts)
            if i != kept
        ]
        return replace(attempts[kept], rejected=rejected)

    def _check_stage(self, stage: Stage, number: int):
        """Warn when chain stage ``number`` (from 1) is no better than V = 0."""
        self._check_against_zero(stage.metrics, f"stage {number} ({self.system.name} T={stage.start:g}->{stage.end:g})")

    def _evaluated(
        self, done: list[Stage], stage: Stage, terminal_spec: dict, check: bool = True
    ) -> FiniteHorizonSolution:
        """The chain ``done`` + ``stage``, where ``stage`` (just trained) gets its metrics from :meth:`evaluate`;
        ``check``: warn when it is no better than V = 0."""
        trained = FiniteHorizonSolution(self.system, self.config, [*done, stage], terminal_spec)
        try:
            metrics = self.evaluate(trained)
        except Exception as exc:
            _keep(exc, trained)  # the stage trained: keep it even if its evaluation fails
            raise
        sol = FiniteHorizonSolution(self.system, self.config, [*done, replace(stage, metrics=metrics)], terminal_spec)
        if check:
            self._check_stage(sol.stages[-1], len(sol.stages))
        return sol

    def _base_loss(self, chain: FiniteHorizonSolution) -> float:
        """The final training loss the next stage's is compared with: :func:`retry_base` of the chain's."""
        return retry_base([s.history.final_loss for s in chain.stages], self.config.retry_against)

    def _extended(self, chain: FiniteHorizonSolution, end: float, terminal_spec: dict) -> FiniteHorizonSolution:
        """``chain`` with one more stage, trained on [0, ``end`` - T] with terminal cost V_T(., 0) and evaluated.

        With ``config.warm_start="best"`` the stage is trained twice on the same points, from the previous stage's
        weights and from fresh ones, and the attempt with the lower E is kept (the other is listed in
        ``Stage.rejected`` with its ``warm_start`` and ``metrics``).
        """
        prev = chain.stages[-1]
        terminal = ValueTerminalCost(prev.model)  # frozen after training; shared, not copied
        mode = self.config.warm_start
        tried = []
        for warm in (True, False) if mode == "best" else (mode,):
            try:
                stage = self._train_stage(
                    float(end - prev.end),
                    prev.end,
                    terminal,
                    prev.model,
                    len(chain.stages),
                    base_loss=self._base_loss(chain),
                    warm=warm,
                )
                tried.append((warm, self._evaluated(chain.stages, stage, terminal_spec, check=mode != "best")))
            except (Exception, KeyboardInterrupt) as exc:  # the second attempt failed: keep the first, trained
                if tried:
                    _keep(exc, tried[0][1])
                raise
        if len(tried) == 1:
            return tried[0][1]
        E = [t.metrics.get("E") for _, t in tried]
        if any(not isinstance(e, numbers.Real) for e in E):
            exc = ValueError(
                "warm_start='best' keeps the attempt with the lower E, but the evaluate hook returned no number "
                f"'E' (got {E[0]!r} and {E[1]!r}): return E from the hook, or use warm_start=True or False"
            )
            _keep(exc, tried[0][1])
            raise exc
        kept = 1 if math.isnan(E[0]) or E[1] < E[0] else 0
        (warm, loser), winner = tried[1 - kept], tried[kept][1]
        lost = loser.stages[-1]
        entry = {
            "seed": lost.seed,
            "final_loss": lost.history.final_loss,
            "wall_time": lost.history.wall_time,
            "stop_reason": lost.history.stop_reason,
            "warm_start": warm,
            "metrics": dict(lost.metrics),
        }
        stage = replace(winner.stages[-1], rejected=(*winner.stages[-1].rejected, entry))
        self._check_stage(stage, len(chain.stages) + 1)  # the attempt kept
        return FiniteHorizonSolution(self.system, self.config, [*chain.stages, stage], terminal_spec)

    def solve(self, horizon: float, terminal_cost=None) -> FiniteHorizonSolution:
        """Algorithm 1: train v_T on Omega x [0, horizon] :eq:`eq-hjbt`; a chain of one stage.

        * ``horizon``: T.
        * ``terminal_cost``: phi; None (zero), an (n, n) matrix P (x'Px), a torch callable or a terminal-cost module.
        """
        horizon = _number(horizon, "horizon")
        phi = make_terminal_cost(terminal_cost, self.system.n)
        stage = self._train_stage(horizon, 0.0, phi.to(self.device, self.dtype), None, 0)
        return self._evaluated([], stage, phi.spec())

    def extend(
        self,
        solution: FiniteHorizonSolution,
        to: float,
        step: float | None = None,
        callback: Callable[[FiniteHorizonSolution], None] | None = None,
    ) -> FiniteHorizonSolution:
        """Theorem 2: extend ``solution`` from its horizon T to ``to`` :eq:`eq-hjbinc`; the longer chain.

        * ``solution``: the chain to extend (not changed).
        * ``to``: the new horizon, above T.
        * ``step``: the length of each new stage; None: one stage of length ``to`` - T.
        * ``callback``: called with the chain after every stage (e.g. to save a checkpoint).

        Each new stage trains V' only on [0, step] with terminal cost V_T(., 0), the previous stage's frozen
        network, warm-started from its weights when ``config.warm_start`` (with ``"best"``: trained both ways, the
        lower E kept). On KeyboardInterrupt the stages done so far are returned with ``interrupted=True``.
        """
        if not isinstance(solution, FiniteHorizonSolution):
            raise TypeError(f"extend needs a FiniteHorizonSolution; got {type(solution).__name__}")
        if solution.system is not self.system and solution.system.spec() != self.system.spec():
            raise ValueError(
                f"solution was trained on system {solution.system.spec()}, this solver has {self.system.spec()}"
            )
        T = solution.horizon
        to = _number(
            to, "to (the extension target)", expected=f"a finite number that must exceed the current horizon T={T:g}"
        )
        if not to > T:
            raise ValueError(f"extension target to={to:g} must exceed the current horizon T={T:g}")
        step = (to - T) if step is None else _number(step, "step")
        count = math.ceil((to - T) / step - 1e-9)
        if count > MAX_STAGES_PER_CALL:
            raise ValueError(
                f"step={step:g} from T={T:g} to {to:g} would train {count} stages, more than "
                f"MAX_STAGES_PER_CALL={MAX_STAGES_PER_CALL}; choose a larger step"
            )
        if solution.device != self.device or solution.dtype != self.dtype:
            for s in solution.stages:  # every stage of the chain, each its own module
                s.model.to(self.device, self.dtype)
        ends = list(np.arange(T + step, to, step)) + [to]
        ends = [e for e in ends if e > T + 1e-9]
        if len(ends) > 1 and ends[-1] - ends[-2] < 1e-9:
            ends.pop(-2)
        current = solution
        try:
            for end in ends:
                current = self._extended(current, end, solution.terminal_spec)
                if callback is not None:
                    callback(current)
        except KeyboardInterrupt as exc:
            # the stages trained and evaluated before the interrupt (with the best start, a first attempt too)
            stages = (getattr(exc, "partial_solution", None) or current).stages
            warnings.warn(
                f"interrupted: returning the {len(stages)} completed stage(s) up to T={stages[-1].end:g}", stacklevel=2
            )
            return FiniteHorizonSolution(self.system, self.config, stages, solution.terminal_spec, interrupted=True)
        except Exception as exc:
            _keep(exc, current if len(current.stages) > len(solution.stages) else None)
            raise
        return current

    def solve_until(
        self,
        tol: float,
        step: float,
        first_horizon: float | None = None,
        max_horizon: float = 20.0,
        terminal_cost=None,
        callback=None,
    ) -> FiniteHorizonSolution:
        """Solve, then extend one stage at a time until the horizon check E :eq:`eq-e` is at most ``tol``.

        * ``tol``: the target for E.
        * ``step``: the length of each stage.
        * ``first_horizon``: the first stage's horizon; None: ``step``.
        * ``max_horizon``: stop here even when E > ``tol`` (a warning says so); ``inf`` extends until E <= ``tol``.
        * ``terminal_cost``: phi of the first stage, as in :meth:`solve`.
        * ``callback``: called with the chain after every stage.

        The per-stage report is ``solution.summary()``; ``solution.converged`` says whether E met ``tol``.

        Choosing ``tol``: E :eq:`eq-e` is the mean square of the steady-state HJB residual over a grid on
        Omega (``config.eval_points_per_dim`` points per axis; a seeded Monte Carlo sample in high dimension,
        see :mod:`pinnhjb.metrics`), in the units of Q squared. Judge it against ``E_zero`` (E of V = 0 on the same
        points, in every row of ``summary()``): a ``tol`` of 1e-4 to 1e-6 times ``E_zero`` asks for a residual
        of about 1% to 0.1% of Q's.
        """
        tol = _number(tol, "tol")
        step = _number(step, "step")
        first = step if first_horizon is None else _number(first_horizon, "first_horizon")
        max_horizon = _number(max_horizon, "max_horizon", allow_inf=True)
        if first > max_horizon + 1e-9:
            raise ValueError(
                f"the first horizon ({'step' if first_horizon is None else 'first_horizon'}={first:g}) "
                f"exceeds max_horizon={max_horizon:g}; choose max_horizon >= {first:g}"
            )
        if callback is not None and not callable(callback):
            raise TypeError(f"callback must be callable or None; got {type(callback).__name__}")
        sol = self.solve(first, terminal_cost)
        if callback is not None:
            callback(sol)
        while sol.metrics["E"] > tol and sol.horizon + 1e-9 < max_horizon and not sol.interrupted:
            try:
                sol = self.extend(sol, to=min(sol.horizon + step, max_horizon), callback=callback)
            except Exception as exc:
                _keep(exc, sol)
                raise
        sol = replace(sol, tol=tol)
        if not sol.converged and not sol.interrupted:
            warnings.warn(
                f"solve_until stopped at max_horizon={max_horizon:g} without meeting tol={tol:g}: "
                f"E = {sol.metrics['E']:.3e} at T={sol.horizon:g} (converged=False); raise max_horizon, "
                f"or check tol against E_zero = {sol.metrics.get('E_zero', float('nan')):.3e}",
                RuntimeWarning,
                stacklevel=2,
            )
        return sol


class SteadyStateSolver(_Solver):
    """The direct steady-state PINN on the steady-state HJB :eq:`eq-hjb` with V(0) = 0 (the paper's T = infinity
    baseline), trained with the same network, data and optimiser budget as one finite-horizon stage.

    Arguments as for :class:`FiniteHorizonSolver` (``evaluate`` computes the solution's metrics).
    """

    def solve(self) -> SteadyStateSolution:
        """Train V(x) on the steady-state HJB residual with V(0) = 0; the result with its metrics."""
        cfg = self.config
        torch.manual_seed(self.seed)
        model = SteadyStateValue(
            self.system.n,
            self.system.train_domain,
            width=cfg.width,
            depth=cfg.depth,
            activation=cfg.activation,
            ansatz=cfg.ansatz,
        ).to(self.device, self.dtype)
        history = train_steady_state(
            self.system, model, cfg, seed=self.seed, progress=self.progress, desc=f"{self.system.name} steady state"
        )
        for p in model.parameters():
            p.requires_grad_(False)
        trained = SteadyStateSolution(self.system, cfg, model.eval(), history, self.seed)
        sol = replace(trained, metrics=self.evaluate(trained))
        self._check_against_zero(sol.metrics, f"{self.system.name} steady state")
        return sol
