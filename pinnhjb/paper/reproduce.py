"""Reproduce every simulation of the paper (Section 6) and measure what it could not: true errors against an
independent reference, closed-loop cost of the learned policies, spread over seeds.

``python -m pinnhjb reproduce [--quick] [--seeds N] [--out artifacts]`` trains every case of
:data:`pinnhjb.paper.cases.CASES`, saves the checkpoints and the reference grids the notebooks load, and writes
the results tables (:mod:`pinnhjb.paper.tables`) with the paper's number beside ours. Reference grids do not
depend on the seed and are reused when present.
"""

from __future__ import annotations

import time
from pathlib import Path

from ..config import TrainConfig
from ..solver import FiniteHorizonSolver, SteadyStateSolver
from ..storage import provenance, save
from .artifacts import DEFAULT_OUT, checkpoint_path, reference_path
from .cases import CLOSED_LOOP, CLOSED_LOOP_SYSTEM, INF, REFERENCE_POINTS, Case, cases
from .evaluation import closed_loop_setup, converged, stage_row, stage_rows
from .tables import aggregate, merge_records, reference_wall_time, write_tables

__all__ = ["run"]


def _reference(case: Case, system, horizon: float, points: int, out: Path, progress: bool):
    from ..reference import ReferenceGrid, reference_grid

    path = reference_path(out, case, horizon)
    if path.exists():
        ref = ReferenceGrid.load(path)
        if ref.points.shape[0] == points**system.n:
            return ref
    print(f"   reference {path.name}: {points}^{system.n} points", flush=True)
    ref = reference_grid(system, points_per_dim=points, horizon=horizon, progress=progress)
    ref.save(path)
    return ref


def _train(case: Case, system, config: TrainConfig, seed: int, progress: bool, on_stage, evaluate):
    """The trained solution, and its rows when the case was evaluated stage by stage (``until``), else None."""
    if case.kind == "steady":
        return SteadyStateSolver(system, config=config, seed=seed, progress=progress).solve(), None
    solver = FiniteHorizonSolver(system, config=config, seed=seed, progress=progress)
    sol = solver.solve(case.first)
    on_stage(sol)
    if case.to is None:
        return sol, None
    if not case.until:
        return solver.extend(sol, to=case.to, step=case.step, callback=on_stage), None
    rows = [evaluate(sol)]
    while not converged(rows[-1]) and sol.horizon < case.to - 1e-9:
        sol = solver.extend(sol, to=min(sol.horizon + case.step, case.to))
        on_stage(sol)
        rows.append(evaluate(sol))
    return sol, rows


def run(
    out: Path = DEFAULT_OUT,
    seeds: int = 3,
    quick: bool = False,
    only: list[str] | None = None,
    progress: bool = True,
    first_seed: int = 0,
) -> dict:
    """Train and evaluate every case; write checkpoints, reference grids and the results tables.

    * ``out``: the artifacts folder.
    * ``seeds``: run the seeds ``first_seed .. seeds - 1``.
    * ``quick``: short chains and coarse references, for CI.
    * ``only``: case names; None: all.
    * ``progress``: show progress bars.
    * ``first_seed``: the first seed to run.

    Returns the records, the summary and the metadata; rows of seeds and cases not run are kept.
    """
    if (
        isinstance(seeds, bool)
        or not isinstance(seeds, int)
        or isinstance(first_seed, bool)
        or not isinstance(first_seed, int)
        or not 0 <= first_seed < seeds
    ):
        raise ValueError(
            f"reproduce needs integer seeds with 0 <= first_seed < seeds (at least one seed to "
            f"train); got first_seed={first_seed!r}, seeds={seeds!r}"
        )
    out = Path(out)
    mode = "quick" if quick else "full"
    start = time.perf_counter()
    records = []
    for case in cases(quick, only):
        system = case.build_system()
        config = TrainConfig.preset("quick" if quick else "default")
        v_pts, t_pts = REFERENCE_POINTS[mode][system.n]
        refs = {}
        if system.value_star is None:
            refs[INF] = _reference(case, system, INF, v_pts, out, progress)
        else:  # validates the reference method where V* is known (reported in the table's header)
            _reference(case, system, INF, t_pts, out, progress)
        if case.kind == "chain":
            for h in case.horizons:
                if h <= case.reference_to:
                    refs[h] = _reference(case, system, h, t_pts, out, progress)
        loop = closed_loop_setup(case, system, refs, mode)
        for seed in range(first_seed, seeds):
            print(f"== {case.name} (seed {seed})", flush=True)
            path = checkpoint_path(out, case.name, seed)
            t0 = time.perf_counter()
            sol, rows = _train(
                case,
                system,
                config,
                seed,
                progress,
                on_stage=lambda s, p=path, name=case.name: save(s, p, seed=s.stages[0].seed, case=name),
                evaluate=lambda view, refs=refs, loop=loop: stage_row(system, view, refs, loop),
            )
            wall = time.perf_counter() - t0
            rows = rows or stage_rows(case, system, sol, refs, loop)
            save(sol, path, seed=seed, case=case.name, evaluation={"rows": rows})
            for row in rows:
                print(
                    f"   T={row['T']:g}: E={row['E']:.3e}"
                    + (f" max|V-V*|={row['value_max_error']:.2e}" if "value_max_error" in row else ""),
                    flush=True,
                )
            records.append(
                {
                    "case": case.name,
                    "system": case.system,
                    "params": case.params,
                    "seed": seed,
                    "wall_time": wall,
                    "train_time": sol.wall_time,
                    "rows": rows,
                    "paper": {str(k): v for k, v in case.paper.items()},
                }
            )
    records = merge_records(out, records)
    summary = aggregate(records)
    meta = provenance(
        mode=mode,
        seeds=seeds,
        config=TrainConfig.preset("quick" if quick else "default").to_dict(),
        closed_loop={"default": CLOSED_LOOP[mode], **({} if quick else CLOSED_LOOP_SYSTEM)},
        reference_points=REFERENCE_POINTS[mode],
        wall_time=time.perf_counter() - start,
        cases_wall_time=float(sum(r["wall_time"] for r in records)),
        reference_wall_time=reference_wall_time(out),
    )
    write_tables(out, records, summary, meta)
    return {"records": records, "summary": summary, "meta": meta}
