"""The paper's simulations (Section 6) as data: each :class:`Case` with the paper's reported E, and the settings
the reproduction evaluates them with (reference grids, closed-loop runs)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

from ..systems import get_system

__all__ = [
    "Case",
    "CASES",
    "INF",
    "THIRD_ORDER_PAPER",
    "REFERENCE_POINTS",
    "CLOSED_LOOP",
    "CLOSED_LOOP_SYSTEM",
    "CONVERGED",
    "THIRD_ORDER_STEPS",
    "cases",
]

INF = math.inf


@dataclass(frozen=True)
class Case:
    """One simulation: a chain (a first horizon, extended to ``to`` in steps of ``step``) or the steady-state PINN.

    * ``name``: the case's name (checkpoints, tables).
    * ``system``: the registry name of its system (:func:`pinnhjb.systems.get_system`).
    * ``params``: the system's parameters.
    * ``kind``: ``"chain"`` or ``"steady"``.
    * ``first``: the first horizon.
    * ``to``: the horizon the chain is extended to; None: one stage.
    * ``step``: the extension's step.
    * ``paper``: horizon (``inf`` for the steady-state PINN) -> the paper's reported E.
    * ``until``: extend one step at a time only until a stage meets :data:`CONVERGED` (``to`` is then the most it
      may reach); False: always to ``to``.
    * ``reference_to``: the longest horizon whose exact V_T is computed for the table's E(ref V_T) column.
    """

    name: str
    system: str
    params: dict = field(default_factory=dict)
    kind: str = "chain"
    first: float = 1.0
    to: float | None = None
    step: float | None = None
    paper: dict = field(default_factory=dict)
    until: bool = False
    reference_to: float = INF

    def build_system(self):
        """The case's system."""
        return get_system(self.system, **self.params)

    @property
    def horizons(self) -> list[float]:
        """The horizons the case reaches, in order (``[inf]`` for the steady-state PINN); for a case extended
        ``until`` it converges, the horizons it may reach (a trained chain's own are its stages' ends)."""
        if self.kind == "steady":
            return [INF]
        if self.to is None:
            return [self.first]
        n = int(round((self.to - self.first) / self.step))
        return [round(self.first + k * self.step, 9) for k in range(n + 1)]


#: The paper's Table 2: R -> E of the third-order system at T = 0.5.
THIRD_ORDER_PAPER = {0.01: 0.0008, 0.1: 0.1152, 1.0: 0.0430, 10.0: 0.0031, 100.0: 0.0027}

#: The third-order chains' extension step and the longest horizon they may reach, per R: the closed loop slows
#: down as R grows (chapter 6), so steps and horizons grow with it.
THIRD_ORDER_STEPS = {0.01: (1.0, 12.5), 0.1: (2.0, 30.5), 1.0: (2.0, 50.5), 10.0: (4.0, 80.5), 100.0: (4.0, 80.5)}

#: What a converged chain meets: the horizon check over that of V = 0, E / E(V = 0); the value's error against
#: the reference V*, max abs(V - V*_ref) / max abs(V*_ref) on Omega; and the closed-loop cost to t = inf over
#: V*_ref from every initial state of the closed-loop grid (:func:`pinnhjb.paper.evaluation.closed_loop_metrics`).
CONVERGED = {"E_ratio": 1e-3, "value_rel_error": 1e-2, "cost_ratio_max": 1.01}

#: Every case of the reproduction, in the order of the results table.
#:
#: :meta hide-value:
CASES: list[Case] = [
    Case(
        "pendulum_extension",
        "pendulum",
        first=1.0,
        to=4.0,
        step=1.0,
        paper={1.0: 0.0453, 2.0: 0.0041, 3.0: 0.0026, 4.0: 0.0022},
    ),
    Case("pendulum_one_stage", "pendulum", first=4.0),  # T = 4 in one stage: what extension saves
    Case("pendulum_steady", "pendulum", kind="steady", paper={INF: 0.0122}),
    Case("quartic_extension", "quartic", first=0.5, to=4.0, step=0.5, paper={0.5: 0.7705, 4.0: 1.536e-4}),
    Case("quartic_one_stage", "quartic", first=4.0),
    Case("quartic_steady", "quartic", kind="steady"),
] + [
    # Table 2 is T = 0.5; each chain is then extended until it converges, to test the paper's explanation of the
    # R trend (steps from benchmarks/third_order_horizon.py, which found the horizons each R needs)
    Case(
        f"third_order_R{R:g}",
        "third_order",
        params={"R": R},
        first=0.5,
        to=THIRD_ORDER_STEPS[R][1],
        step=THIRD_ORDER_STEPS[R][0],
        paper={0.5: E},
        until=True,
        reference_to=0.5,
    )
    for R, E in THIRD_ORDER_PAPER.items()
]

#: Reference grid resolution (points per axis) for V* and for the finite-horizon V_T, by mode and state dimension.
REFERENCE_POINTS = {"full": {2: (41, 21), 3: (5, 5)}, "quick": {2: (5, 5), 3: (3, 3)}}
#: The closed-loop runs' settings, by mode.
CLOSED_LOOP = {"full": {"t_final": 20.0, "dt": 0.01}, "quick": {"t_final": 10.0, "dt": 0.05}}
#: Longer runs for the third-order system: a slow mode (time constant near 20 s with little control authority).
CLOSED_LOOP_SYSTEM = {"third_order": {"t_final": 80.0, "dt": 0.1}}


def cases(quick: bool = False, only: list[str] | None = None) -> list[Case]:
    """The cases to run.

    * ``quick``: the same cases with short chains (one extension step), for CI.
    * ``only``: case names; None: all. An unknown name is a KeyError that lists the known ones.
    """
    selected = [c for c in CASES if only is None or c.name in only]
    if only is not None and len(selected) != len(set(only)):
        unknown = sorted(set(only) - {c.name for c in CASES})
        raise KeyError(f"unknown case(s) {unknown}; known: {[c.name for c in CASES]}")
    if not quick:
        return selected
    return [c if c.to is None else replace(c, to=c.first + c.step, until=False) for c in selected]
