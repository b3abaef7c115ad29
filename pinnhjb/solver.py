"""Solvers configured once: Algorithm 1, the horizon extension of Theorem 2, and the steady-state baseline.

>>> import pinnhjb as ph
>>> solver = ph.FiniteHorizonSolver(ph.systems.pendulum(), config="default", seed=0)
>>> sol = solver.solve(horizon=1.0)                    # Algorithm 1: V_1 on Omega x [0, 1]
>>> sol = solver.extend(sol, to=4.0, step=1.0)          # Theorem 2: three more stages, each on [0, 1]
>>> sol = solver.solve_until(tol=1e-4, step=1.0)        # extend until E <= tol (Section 5.1)
"""
from __future__ import annotations

import math
import warnings
from typing import Callable

import numpy as np
import torch

from .config import TrainConfig
from .pinn import (CallableTerminalCost, FiniteHorizonValue, QuadraticTerminalCost, SteadyStateValue,
                   ValueTerminalCost, ZeroTerminalCost)
from .solution import FiniteHorizonSolution, Stage, SteadyStateSolution
from .training import DTYPES, resolve_device, train_finite_horizon, train_steady_state

__all__ = ["FiniteHorizonSolver", "SteadyStateSolver", "make_terminal_cost"]


def make_terminal_cost(terminal_cost) -> torch.nn.Module:
    """phi from ``None`` (zero), a (n, n) matrix P (x'Px), a torch callable, or a terminal-cost module."""
    if terminal_cost is None:
        return ZeroTerminalCost()
    if isinstance(terminal_cost, torch.nn.Module):
        return terminal_cost
    if isinstance(terminal_cost, (np.ndarray, list, tuple)) or (isinstance(terminal_cost, torch.Tensor)
                                                                and terminal_cost.ndim == 2):
        return QuadraticTerminalCost(np.asarray(terminal_cost, dtype=float))
    if callable(terminal_cost):
        return CallableTerminalCost(terminal_cost)
    raise TypeError(f"terminal_cost must be None, a matrix, a callable or a module; got {type(terminal_cost).__name__}")


def _config(config, system) -> TrainConfig:
    if isinstance(config, TrainConfig):
        return config
    if isinstance(config, str):
        return TrainConfig.preset(config, system=system.builder or system.name)
    if isinstance(config, dict):
        return TrainConfig(**config)
    raise TypeError(f"config must be a TrainConfig, a preset name or a dict; got {type(config).__name__}")


class _Solver:
    def __init__(self, system, config="default", seed: int = 0, device=None, progress: bool = True):
        self.system = system
        self.config = _config(config, system)
        self.seed = int(seed)
        self.device = resolve_device(device)
        self.progress = progress

    @property
    def dtype(self) -> torch.dtype:
        return DTYPES[self.config.dtype]

    def _metrics(self, solution) -> dict:
        return solution.evaluate(self.config.eval_points_per_dim)


class FiniteHorizonSolver(_Solver):
    """Finite-horizon PINN (Algorithm 1) with horizon extension (Theorem 2).

    Parameters: a :class:`~pinnhjb.systems.ControlAffineSystem`; ``config`` a :class:`TrainConfig` or a
    preset name (``"default"``, ``"paper"``, ``"quick"``); ``seed`` for initialisation and sampling
    (stage k uses seed + k); ``device`` (None = CUDA when present, else CPU); ``progress`` bars.
    """

    def _train_stage(self, length: float, start: float, terminal, init: FiniteHorizonValue | None,
                     index: int) -> Stage:
        cfg = self.config
        seed = self.seed + index
        torch.manual_seed(seed)
        model = FiniteHorizonValue(self.system.n, length, self.system.train_domain, terminal, width=cfg.width,
                                   depth=cfg.depth, activation=cfg.activation, ansatz=cfg.ansatz)
        model = model.to(device=self.device, dtype=self.dtype)
        if init is not None and cfg.warm_start:
            model.net.load_state_dict(init.net.state_dict())
        desc = f"{self.system.name} T={start:g}->{start + length:g}"
        history = train_finite_horizon(self.system, model, cfg, seed=seed, progress=self.progress, desc=desc)
        for p in model.parameters():
            p.requires_grad_(False)
        return Stage(model=model.eval(), start=start, history=history, seed=seed)

    def _finish(self, stages, terminal_spec, interrupted=False) -> FiniteHorizonSolution:
        sol = FiniteHorizonSolution(self.system, self.config, stages, terminal_spec, interrupted=interrupted)
        if not stages[-1].metrics:
            stages[-1].metrics = self._metrics(sol)
        return sol

    def solve(self, horizon: float, terminal_cost=None) -> FiniteHorizonSolution:
        """Algorithm 1: train v_T on Omega x [0, horizon] with terminal cost phi (default 0)."""
        if not (isinstance(horizon, (int, float)) and math.isfinite(horizon) and horizon > 0):
            raise ValueError(f"horizon must be a positive finite number; got {horizon!r}")
        phi = make_terminal_cost(terminal_cost)
        stage = self._train_stage(float(horizon), 0.0, phi.to(self.device, self.dtype), None, 0)
        return self._finish([stage], phi.spec())

    def extend(self, solution: FiniteHorizonSolution, to: float, step: float | None = None,
               callback: Callable[[FiniteHorizonSolution], None] | None = None) -> FiniteHorizonSolution:
        """Theorem 2: extend ``solution`` from T to ``to`` in increments of ``step`` (default: one increment).

        Each new stage trains V' only on [0, step] with terminal cost V_T(., 0) (the previous stage's
        frozen network), warm-started from its weights when ``config.warm_start``. ``callback`` is called
        with the chain after every stage (e.g. to save a checkpoint). On KeyboardInterrupt the stages done
        so far are returned with ``interrupted=True``.
        """
        if not isinstance(solution, FiniteHorizonSolution):
            raise TypeError(f"extend needs a FiniteHorizonSolution; got {type(solution).__name__}")
        if solution.system is not self.system and solution.system.spec() != self.system.spec():
            raise ValueError(f"solution was trained on system {solution.system.spec()}, this solver has "
                             f"{self.system.spec()}")
        T = solution.horizon
        if not to > T:
            raise ValueError(f"extension target {to} must exceed the current horizon {T}")
        step = (to - T) if step is None else float(step)
        if not step > 0:
            raise ValueError(f"step must be positive; got {step}")
        ends = list(np.arange(T + step, to, step)) + [to]
        ends = [e for e in ends if e > T + 1e-9]
        if len(ends) > 1 and ends[-1] - ends[-2] < 1e-9:
            ends.pop(-2)
        stages = list(solution.stages)
        current = solution
        try:
            for end in ends:
                prev = stages[-1]
                terminal = ValueTerminalCost(prev.model)  # frozen after training; shared, not copied
                stage = self._train_stage(float(end - prev.end), prev.end, terminal, prev.model, len(stages))
                stages.append(stage)
                current = self._finish(stages, solution.terminal_spec)
                if callback is not None:
                    callback(current)
        except KeyboardInterrupt:
            warnings.warn(f"interrupted: returning the {len(stages)} completed stage(s) up to T={stages[-1].end:g}")
            if len(stages) > len(current.stages):
                stages = stages[:len(current.stages)]
            return FiniteHorizonSolution(self.system, self.config, stages, solution.terminal_spec, interrupted=True)
        return current

    def solve_until(self, tol: float, step: float, first_horizon: float | None = None, max_horizon: float = 20.0,
                    terminal_cost=None, callback=None) -> FiniteHorizonSolution:
        """Solve at ``first_horizon`` (default ``step``), then extend by ``step`` until E <= ``tol`` or
        ``max_horizon`` is reached (the horizon check of Section 5.1). The per-stage report is
        ``solution.summary()``; ``solution.converged`` says whether E met ``tol``."""
        if not tol > 0:
            raise ValueError(f"tol must be positive; got {tol}")
        sol = self.solve(first_horizon or step, terminal_cost)
        if callback is not None:
            callback(sol)
        while sol.metrics["E"] > tol and sol.horizon + 1e-9 < max_horizon and not sol.interrupted:
            sol = self.extend(sol, to=min(sol.horizon + step, max_horizon), callback=callback)
        sol.converged = sol.metrics["E"] <= tol
        return sol


class SteadyStateSolver(_Solver):
    """The direct steady-state PINN on eq. (4) with V(0) = 0 (the paper's T = infinity baseline), trained
    with the same network, data and optimiser budget as one finite-horizon stage."""

    def solve(self) -> SteadyStateSolution:
        cfg = self.config
        torch.manual_seed(self.seed)
        model = SteadyStateValue(self.system.n, self.system.train_domain, width=cfg.width, depth=cfg.depth,
                                 activation=cfg.activation, ansatz=cfg.ansatz).to(self.device, self.dtype)
        history = train_steady_state(self.system, model, cfg, seed=self.seed, progress=self.progress,
                                     desc=f"{self.system.name} steady state")
        for p in model.parameters():
            p.requires_grad_(False)
        sol = SteadyStateSolution(self.system, cfg, model.eval(), history, self.seed)
        sol.metrics = self._metrics(sol)
        return sol
