"""The paper's simulations (Section 6) as data: each :class:`Case` with the paper's reported E, and the settings
the reproduction evaluates them with (reference grids, closed-loop runs)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from ..systems import get_system

__all__ = [
    "Case",
    "CASES",
    "INF",
    "THIRD_ORDER_PAPER",
    "REFERENCE_POINTS",
    "CLOSED_LOOP",
    "CLOSED_LOOP_SYSTEM",
    "cases",
]

INF = math.inf


@dataclass(frozen=True)
class Case:
    """One simulation: a chain (first horizon, extended to ``to`` in ``step`` s) or the steady-state PINN.

    ``paper`` maps a horizon (``inf`` for the steady-state PINN) to the paper's reported E.
    """

    name: str
    system: str
    params: dict = field(default_factory=dict)
    kind: str = "chain"
    first: float = 1.0
    to: float | None = None
    step: float | None = None
    paper: dict = field(default_factory=dict)

    def build_system(self):
        return get_system(self.system, **self.params)

    @property
    def horizons(self) -> list[float]:
        if self.kind == "steady":
            return [INF]
        if self.to is None:
            return [self.first]
        n = int(round((self.to - self.first) / self.step))
        return [round(self.first + k * self.step, 9) for k in range(n + 1)]


THIRD_ORDER_PAPER = {0.01: 0.0008, 0.1: 0.1152, 1.0: 0.0430, 10.0: 0.0031, 100.0: 0.0027}

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
    # Table 2 is T = 0.5; the large-R cases are extended to test the paper's explanation of the R trend.
    Case(
        f"third_order_R{R:g}",
        "third_order",
        params={"R": R},
        first=0.5,
        to=1.5 if R >= 1 else None,
        step=0.5 if R >= 1 else None,
        paper={0.5: E},
    )
    for R, E in THIRD_ORDER_PAPER.items()
]

# Reference grid resolution (points per axis) for V* and for the finite-horizon V_T, by state dimension.
REFERENCE_POINTS = {"full": {2: (41, 21), 3: (5, 5)}, "quick": {2: (5, 5), 3: (3, 3)}}
CLOSED_LOOP = {"full": {"t_final": 20.0, "dt": 0.01}, "quick": {"t_final": 10.0, "dt": 0.05}}
# The third-order system has a slow mode (time constant ~ 20 s with little control authority): longer runs.
CLOSED_LOOP_SYSTEM = {"third_order": {"t_final": 80.0, "dt": 0.05}}


def cases(quick: bool = False, only: list[str] | None = None) -> list[Case]:
    selected = [c for c in CASES if only is None or c.name in only]
    if only is not None and len(selected) != len(set(only)):
        unknown = sorted(set(only) - {c.name for c in CASES})
        raise KeyError(f"unknown case(s) {unknown}; known: {[c.name for c in CASES]}")
    if not quick:
        return selected
    # --quick: the same cases with short chains, for CI.
    return [
        Case(c.name, c.system, c.params, c.kind, c.first, None if c.to is None else c.first + c.step, c.step, c.paper)
        for c in selected
    ]
