"""Reproduce every simulation of the paper (Section 6) and measure what it could not: true errors against an
independent reference, closed-loop cost of the learned policies, spread over seeds.

``python -m pinnhjb reproduce [--quick] [--seeds N] [--out artifacts]`` trains every case of
:data:`pinnhjb.paper.cases.CASES`, saves the checkpoints and the reference grids the notebooks load, and writes
the results tables (:mod:`pinnhjb.paper.tables`) with the paper's number beside ours. Reference grids do not
depend on the seed and are reused when present.

``--workers N`` (local processes) or ``--scheduler tcp://HOST:PORT`` (a Dask cluster) trains the (case, seed)
runs side by side through :func:`pinnhjb.executor.map_runs`; a chain's stages stay in order within their run.
The reference grids are computed first, here, one at a time.
"""

from __future__ import annotations

import time
from pathlib import Path

from ..config import TrainConfig
from ..executor import check, executor, map_runs
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


def _run_one(task: dict) -> dict:
    """Train one case for one seed, save its checkpoint after every stage and with its evaluation; its record.

    * ``task``: ``case``, ``seed``, ``config``, ``refs`` (horizon -> reference grid), ``loop``
      (:func:`~pinnhjb.paper.evaluation.closed_loop_setup`), ``path`` (the checkpoint), ``progress``, and
      ``system``: the case's system, or None to build it here (a worker: a system does not pickle).
    """
    case, seed, path, refs, loop = task["case"], task["seed"], task["path"], task["refs"], task["loop"]
    system = task["system"] if task["system"] is not None else case.build_system()
    print(f"== {case.name} (seed {seed})", flush=True)
    t0 = time.perf_counter()
    sol, rows = _train(
        case,
        system,
        task["config"],
        seed,
        task["progress"],
        on_stage=lambda s: save(s, path, seed=s.stages[0].seed, case=case.name),
        evaluate=lambda view: stage_row(system, view, refs, loop),
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
    return {
        "case": case.name,
        "system": case.system,
        "params": case.params,
        "seed": seed,
        "wall_time": wall,
        "train_time": sol.wall_time,
        "rows": rows,
        "paper": {str(k): v for k, v in case.paper.items()},
    }


def run(
    out: Path = DEFAULT_OUT,
    seeds: int = 3,
    quick: bool = False,
    only: list[str] | None = None,
    progress: bool = True,
    first_seed: int = 0,
    workers: int | None = None,
    scheduler: str | None = None,
    threads: int | None = None,
) -> dict:
    """Train and evaluate every case; write checkpoints, reference grids and the results tables.

    * ``out``: the artifacts folder.
    * ``seeds``: run the seeds ``first_seed .. seeds - 1``.
    * ``quick``: short chains and coarse references, for CI.
    * ``only``: case names; None: all.
    * ``progress``: show progress bars (with workers: one bar of finished runs instead of the training bars).
    * ``first_seed``: the first seed to run.
    * ``workers``: train the (case, seed) runs in this many local processes; None or 1: one after the other, here.
    * ``scheduler``: a Dask scheduler's address, ``tcp://HOST:PORT``: train the runs on its cluster, whose workers
      must see ``out`` at the same path (they write the checkpoints); not together with ``workers``.
    * ``threads``: torch threads per run; None: 1 per worker, this process's own count serially.

    The reference grids are computed first, in this process. A run trains the same weights bit for bit in a
    worker as serially *at the same thread count*: compare ``workers=N`` with a serial run given ``threads=1``.
    A failing run stops the sweep (:func:`pinnhjb.executor.map_runs`: its error names the case and seed); the
    checkpoints of runs that finished are saved, the tables are not written.

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
    parallel = check(workers, scheduler, threads) != "serial"
    out = Path(out)
    mode = "quick" if quick else "full"
    start = time.perf_counter()
    selected = cases(quick, only)
    records, pending = [], []
    with executor(workers, scheduler, threads) as pool:
        for case in selected:
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
                task = dict(case=case, seed=seed, config=config, refs=refs, loop=loop)
                if parallel:  # the worker builds the system; an absolute path, whatever its working directory
                    path = checkpoint_path(out.absolute(), case.name, seed)
                    pending.append(dict(task, system=None, path=path, progress=False))
                else:
                    path = checkpoint_path(out, case.name, seed)
                    records.append(_run_one(dict(task, system=system, path=path, progress=progress)))
        if parallel:
            records = map_runs(
                _run_one,
                pending,
                pool=pool,
                progress=progress,
                desc="reproduce runs",
                label=lambda t: f"case {t['case'].name}, seed {t['seed']}",
            )
    records = merge_records(out, records)
    summary = aggregate(records)
    runs = {"workers": workers, "scheduler": scheduler is not None, "threads": threads or 1} if parallel else {}
    meta = provenance(
        mode=mode,
        seeds=seeds,
        config=TrainConfig.preset("quick" if quick else "default").to_dict(),
        closed_loop={"default": CLOSED_LOOP[mode], **({} if quick else CLOSED_LOOP_SYSTEM)},
        reference_points=REFERENCE_POINTS[mode],
        wall_time=time.perf_counter() - start,
        cases_wall_time=float(sum(r["wall_time"] for r in records)),
        reference_wall_time=reference_wall_time(out),
        **({"runs": runs} if runs else {}),
    )
    write_tables(out, records, summary, meta)
    return {"records": records, "summary": summary, "meta": meta}
