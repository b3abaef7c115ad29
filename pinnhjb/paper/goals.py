"""Issue #18's goals against the stored benchmark runs: for each goal, the main run's number, the closest
stored run's (any run of ``benchmarks/rigid_body.py`` or ``benchmarks/dimension.py`` under
``benchmarks/results/``) and whether that one meets it. Chapter 8's goals table and ``benchmarks/index.py`` both
read :func:`dimension_goals`, so the two cannot disagree.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass
from pathlib import Path

from .artifacts import benchmark_run, benchmark_runs, dimension_rows, results_dir

__all__ = ["Goal", "dimension_goals", "GOAL_VALUE", "GOAL_GRAD", "GOAL_LADDER", "GOAL_CONVERSE"]

#: The rigid body's value goal on ``max |V - V_ref| / max V_ref``.
GOAL_VALUE = 1e-3
#: The rigid body's gradient goal: the mean relative error of grad V.
GOAL_GRAD = 1e-2
#: The LQ ladder's value goal at every n.
GOAL_LADDER = 1e-4
#: The converse system's value goal at n = 12.
GOAL_CONVERSE = 1e-3
#: The time goals, in seconds of training: on 2 CPU cores, and on one GPU.
CPU_SECONDS, GPU_SECONDS = 1800.0, 180.0
#: The closed-loop goal: every loop's cost within this factor of V_ref.
COST_RATIO = 1.001


@dataclass(frozen=True)
class Goal:
    """One goal of issue #18 and where the stored runs stand.

    * ``key``: a short name in words: ``"value error"`` (the rigid body's), ``"ladder n = 6"``, ...; unique.
    * ``text``: the goal as the page states it (Markdown with ``$...$`` math).
    * ``main``: the main run's number (None: the main run has none; ``"settled"`` goals: the count).
    * ``closest``: the closest stored run's number (None where only the main run is measured).
    * ``run``: where ``closest`` comes from: ``"main run"`` or ``"<folder>/<run>"`` under ``benchmarks/results/``.
    * ``met``: whether the closest number meets the goal (and ``largest``, where there is one).
    * ``unit``: how the numbers print: ``"error"`` (``.2e``), ``"seconds"``, ``"count"`` or ``"ratio"``.
    * ``note``: what else a reader needs beside the number (e.g. the value error of the fastest GPU run).
    * ``bound``: the number the goal asks the closest run to stay at or below (an error, a time in seconds); None
      for the goals that are not such a bound (the loops that settle, the closed-loop cost).
    * ``largest``: for the ladder and the converse system, the closest over the stored chains of the largest error
      found on Omega beyond the sampled states, with its 2^n vertices and after an ascent
      (``benchmarks/largest_error.py``, :func:`pinnhjb.metrics.largest_value_error`); None where no chain was
      measured so.
    * ``largest_run``: where ``largest`` comes from.
    """

    key: str
    text: str
    main: float | None
    closest: float | None
    run: str
    met: bool
    unit: str = "error"
    note: str = ""
    bound: float | None = None
    largest: float | None = None
    largest_run: str = ""

    @property
    def missed_by(self) -> float | None:
        """By how much a missed goal is missed: the closest stored number over ``bound`` (``main`` where only the
        main run is measured; ``largest`` where there is one, the stricter number), above 1; None for a goal met or
        without a ``bound``."""
        x = self.main if self.closest is None else self.closest if self.largest is None else self.largest
        if self.met or self.bound is None or x is None:
            return None
        return x / self.bound

    @property
    def system(self) -> str:
        """The system the goal is for, as ``text`` opens: ``"rigid body"``, ``"LQ ladder"``, ``"converse system"``."""
        return re.split("[,:]", self.text, maxsplit=1)[0]

    @property
    def aim(self) -> str:
        """``text`` after the system's name: ``"value error $\\leq10^{-3}$"``, ``"$n=6$: value error ..."``."""
        return self.text[len(self.system) :].lstrip(",: ")

    @property
    def verdict(self) -> str:
        """Whether the goal is met, as chapter 8's table and ``benchmarks/results/index.md`` print it: ``"yes"``,
        or ``"no"`` with by how much where the goal is a bound (``"no, 1.9 x"``, ``"no, 140 x"``)."""
        if self.met:
            return "yes"
        by = self.missed_by
        return "no" if by is None else f"no, {by:.0f} x" if by >= 100 else f"no, {by:.2g} x"

    def show(self, which: str = "closest", note: bool = True) -> str:
        """``main`` or ``closest`` as a page prints it ("–" where there is none), ``closest`` with the ``note``
        in brackets unless ``note=False``."""
        from ..report import num

        x = getattr(self, which)
        if x is None:
            return "–"
        text = {
            "error": lambda: num(x, ".2e"),
            "seconds": lambda: f"{x:.0f} s",
            "count": lambda: f"{x:.0f}",
            "ratio": lambda: f"{x:.4f}",
        }[self.unit]()
        return f"{text} ({self.note})" if note and self.note and which == "closest" else text


def largest_errors(out: Path | None = None) -> dict[tuple[str, int], tuple[float, str]]:
    """The lowest largest error on Omega (``benchmarks/largest_error.py``'s ``ascended``) of the stored chains of
    each (system, n), with its run: ``{("lq_ladder", 6): (1.5e-4, "repeats/...")}``; empty where the script's
    ``largest_error.json`` is not stored.

    * ``out``: the artifacts folder; None: :func:`~pinnhjb.paper.artifacts.artifacts_dir`.
    """
    path = results_dir(out) / "largest_error.json"
    if not path.is_file():
        return {}
    best: dict[tuple[str, int], tuple[float, str]] = {}
    for r in json.loads(path.read_text())["rows"]:
        key = (r["system"], r["n"])
        best[key] = min(best.get(key, (float("inf"), "")), (r["ascended"], r["run"]))
    return best


def _end(run: dict) -> dict:
    return run["infinite"]["stages"][-1]


def _mean_note(part: dict) -> str:
    """For a mean of chains (``--mean``: of ``benchmarks/rigid_body.py``, ``part`` a run's ``"infinite"``; of
    ``benchmarks/dimension.py``, a row): how many, and their training time summed; "" for one chain."""
    members = part.get("members")
    if not members:
        return ""
    return f"the mean of {len(members)} chains, {part['wall_s']:.0f} s of training summed"


def dimension_goals(out: Path | None = None) -> list[Goal]:
    """Every goal of issue #18, in the issue's order: the rigid body's six (value, gradient, loops settled,
    closed-loop cost, time on 2 CPU cores, time on one GPU) and its value goal within the CPU time goal, then the
    LQ ladder's value goal at each n any stored run measured, then the converse system's at n = 12.

    * ``out``: the artifacts folder; None: :func:`~pinnhjb.paper.artifacts.artifacts_dir` (the runs lie beside it, under
      ``benchmarks/results/``).

    The closest stored run is the one with the lowest number over every stored run of that benchmark (for the
    ladder and the converse system, over each run's last measured row of that system and n, default recipe); for
    the rigid body a mean of chains (``benchmarks/rigid_body.py --mean``) counts as a run, whose ``note`` says so
    and whose time is its members' summed.
    The loops, cost and CPU-time goals are the main run's alone: closest runs by value trained longer.
    A ladder or converse goal is met only if the lowest largest error on Omega of the chains measured beyond their
    states (``benchmarks/largest_error.py``: with Omega's vertices and after an ascent; ``Goal.largest``) meets it
    too; where it is missed, it is missed by that number.
    """
    rbs = benchmark_runs("rigid_body", out)
    main = rbs["main run"]
    on_gpu = {k: r for k, r in rbs.items() if r["meta"]["args"].get("device") == "cuda"}
    quick = {k: r for k, r in rbs.items() if k not in on_gpu and r["infinite"]["wall_s"] <= CPU_SECONDS}

    def lowest(runs: dict, key: str) -> tuple[str, float]:
        k = min(runs, key=lambda k: _end(runs[k])[key])
        return k, _end(runs[k])[key]

    last, loop, wall = _end(main), main["infinite"]["closed_loop"], main["infinite"]["wall_s"]
    k_v, v = lowest(rbs, "value_rel_error")
    k_g, g = lowest(rbs, "grad_mean_rel_error")
    k_q, q = lowest(quick, "value_rel_error") if quick else ("none within the time", None)
    goals = [
        Goal(
            "value error",
            r"rigid body: value error $\leq10^{-3}$",
            last["value_rel_error"],
            v,
            k_v,
            v <= GOAL_VALUE,
            note=_mean_note(rbs[k_v]["infinite"]),
            bound=GOAL_VALUE,
        ),
        Goal(
            "gradient error",
            r"rigid body: gradient error $\leq10^{-2}$",
            last["grad_mean_rel_error"],
            g,
            k_g,
            g <= GOAL_GRAD,
            note=_mean_note(rbs[k_g]["infinite"]),
            bound=GOAL_GRAD,
        ),
        Goal(
            "closed loops settle",
            f"rigid body: all {loop['states']} closed loops settle",
            loop["settled"],
            None,
            "main run",
            loop["settled"] == loop["states"],
            unit="count",
        ),
        Goal(
            "closed-loop cost",
            r"rigid body: closed-loop cost within 0.1% of $V^\star$",
            loop["cost_ratio_max"],
            None,
            "main run",
            loop["cost_ratio_max"] <= COST_RATIO,
            unit="ratio",
        ),
        Goal(
            "time on 2 CPU cores",
            "rigid body: training under 30 min on 2 CPU cores",
            wall,
            None,
            "main run",
            wall <= CPU_SECONDS,
            unit="seconds",
            bound=CPU_SECONDS,
        ),
        Goal(
            "value error within 30 min",
            r"rigid body: value error $\leq10^{-3}$ within those 30 min",
            last["value_rel_error"] if "main run" in quick else None,
            q,
            k_q,
            q is not None and q <= GOAL_VALUE,
            note=_mean_note(rbs[k_q]["infinite"]) if k_q in rbs else "",
            bound=GOAL_VALUE,
        ),
    ]
    if on_gpu:
        k_gpu = min(on_gpu, key=lambda k: on_gpu[k]["infinite"]["wall_s"])
        from ..report import num

        goals.append(
            Goal(
                "time on one GPU",
                "rigid body: training under 3 min on one GPU",
                None,
                on_gpu[k_gpu]["infinite"]["wall_s"],
                k_gpu,
                on_gpu[k_gpu]["infinite"]["wall_s"] <= GPU_SECONDS,
                unit="seconds",
                note=f"value error {num(_end(on_gpu[k_gpu])['value_rel_error'], '.2e')}",
                bound=GPU_SECONDS,
            )
        )
    main_rows = dimension_rows(benchmark_run(name="dimension", out=out))
    largest = largest_errors(out)
    rows = [(k, r) for k, run in benchmark_runs("dimension", out).items() for r in dimension_rows(run).values()]

    def best(system: str, n: int) -> tuple[float, str]:
        return min((r["value_rel_error"], k) for k, r in rows if (r["system"], r["n"]) == (system, n))

    def note(run: str, system: str, n: int) -> str:  # a mean of chains (dimension.py --mean) says so
        return _mean_note(next(r for k, r in rows if k == run and (r["system"], r["n"]) == (system, n)))

    for n in sorted({r["n"] for _, r in rows if r["system"] == "lq_ladder"}):
        v, k = best("lq_ladder", n)
        mine = main_rows.get(("lq_ladder", n))
        big, big_run = largest.get(("lq_ladder", n), (None, ""))
        goals.append(
            Goal(
                f"ladder n = {n}",
                rf"LQ ladder, $n={n}$: value error $\leq10^{{-4}}$",
                None if mine is None else mine["value_rel_error"],
                v,
                k,
                v <= GOAL_LADDER and (big is None or big <= GOAL_LADDER),
                note=note(k, "lq_ladder", n),
                bound=GOAL_LADDER,
                largest=big,
                largest_run=big_run,
            )
        )
    if any((r["system"], r["n"]) == ("converse", 12) for _, r in rows):
        v, k = best("converse", 12)
        mine = main_rows.get(("converse", 12))
        big, big_run = largest.get(("converse", 12), (None, ""))
        goals.append(
            Goal(
                "converse n = 12",
                r"converse system, $n=12$: value error $\leq10^{-3}$",
                None if mine is None else mine["value_rel_error"],
                v,
                k,
                v <= GOAL_CONVERSE and (big is None or big <= GOAL_CONVERSE),
                note=note(k, "converse", 12),
                bound=GOAL_CONVERSE,
                largest=big,
                largest_run=big_run,
            )
        )
    return goals
