"""Reproduce every simulation of the paper (Section 6) and measure what it could not: true errors against an
independent reference, closed-loop cost of the learned policies, spread over seeds.

``python -m pinnhjb reproduce [--quick] [--seeds N] [--out artifacts]`` trains every :data:`CASES` entry,
saves the checkpoints and the reference grids the notebooks load, and writes a results table (markdown, CSV
and JSON) with the paper's number beside ours. Reference grids (per-point Pontryagin solutions,
:mod:`pinnhjb.reference`) do not depend on the seed and are reused when already present.
"""
from __future__ import annotations

import csv
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from .config import TrainConfig
from .solver import FiniteHorizonSolver, SteadyStateSolver
from .storage import load, provenance, save
from .paper.cases import CASES, CLOSED_LOOP, CLOSED_LOOP_SYSTEM, INF, REFERENCE_POINTS, Case, cases

__all__ = ["Case", "CASES", "cases", "run", "checkpoint_path", "reference_path", "load_case", "load_reference",
           "load_results", "rewrite_tables", "stored_seeds", "stage_metric", "reference_residual", "artifacts_dir",
           "DEFAULT_OUT"]

DEFAULT_OUT = Path("artifacts")


def checkpoint_path(out: Path, case: str, seed: int) -> Path:
    return Path(out) / "checkpoints" / case / f"seed{seed}.pt"


def _system_key(case: Case) -> str:
    return case.system + "".join(f"_{k}{v:g}" if isinstance(v, float) else f"_{k}{v}" for k, v in case.params.items())


def reference_path(out: Path, case: Case, horizon: float) -> Path:
    tag = "inf" if horizon == INF else f"T{horizon:g}"
    return Path(out) / "reference" / f"{_system_key(case)}_{tag}.npz"


def artifacts_dir() -> Path:
    """Where the committed artifacts are: ``$PINNHJB_ARTIFACTS``, else the nearest ``artifacts/`` folder
    with checkpoints in the working directory or above it (notebooks run from ``notebooks/``)."""
    env = os.environ.get("PINNHJB_ARTIFACTS")
    if env:
        return Path(env)
    for base in [Path.cwd(), *Path.cwd().parents]:
        if (base / DEFAULT_OUT / "checkpoints").is_dir():
            return base / DEFAULT_OUT
    return DEFAULT_OUT


_RETRAINED: set = set()


def load_case(case: str, seed: int = 0, out: Path | None = None, device=None, retrain: bool = False):
    """The stored solution of a case (as the notebooks load it).

    ``retrain=True`` (a notebook's ``RETRAIN`` switch) first trains this case and seed again with the
    default recipe, in place (checkpoint and results table, as ``reproduce --cases``), once per process.
    """
    if case not in {c.name for c in CASES}:
        raise KeyError(f"unknown case {case!r}; known: {[c.name for c in CASES]}")
    out = Path(out or artifacts_dir())
    if retrain and (case, seed, out) not in _RETRAINED:
        run(out=out, seeds=seed + 1, only=[case], first_seed=seed)
        _RETRAINED.add((case, seed, out))
    return load(checkpoint_path(out, case, seed), device=device)


def stored_seeds(case: str, out: Path | None = None) -> list[int]:
    """The seeds with a stored checkpoint for ``case``."""
    folder = Path(out or artifacts_dir()) / "checkpoints" / case
    return sorted(int(p.stem[4:]) for p in folder.glob("seed*.pt"))


def stage_metric(case: str, key: str, out: Path | None = None) -> dict[float, list[float]]:
    """Metric ``key`` of every stored seed of a chain case, per horizon: ``{T: [value per seed]}``."""
    spec = next(c for c in CASES if c.name == case)
    values: dict[float, list[float]] = {T: [] for T in spec.horizons}
    for seed in stored_seeds(case, out):
        for T, row in zip(spec.horizons, load_case(case, seed, out).summary()):
            values[T].append(row[key])
    return values


def reference_residual(case: str | Case, horizon: float, out: Path | None = None) -> float:
    """E of the stored exact (reference) V_T(., 0): the part of a PINN's E that is due to the horizon alone."""
    case = case if isinstance(case, Case) else next(c for c in CASES if c.name == case)
    return _reference_residual(case.build_system(), load_reference(case, horizon, out))


def load_reference(case: str | Case, horizon: float = INF, out: Path | None = None):
    from .reference import ReferenceGrid

    case = case if isinstance(case, Case) else next(c for c in CASES if c.name == case)
    return ReferenceGrid.load(reference_path(out or artifacts_dir(), case, horizon))


def load_results(out: Path | None = None) -> dict:
    """The results table written by :func:`run` (``summary`` rows, ``records`` per seed, ``meta``)."""
    return json.loads((Path(out or artifacts_dir()) / "results" / "reproduce.json").read_text())


# ---------------------------------------------------------------------- references

def _reference(case: Case, system, horizon: float, points: int, out: Path, progress: bool):
    from .reference import ReferenceGrid, reference_grid

    path = reference_path(out, case, horizon)
    if path.exists():
        ref = ReferenceGrid.load(path)
        if ref.points.shape[0] == points ** system.n:
            return ref
    print(f"   reference {path.name}: {points}^{system.n} points", flush=True)
    ref = reference_grid(system, points_per_dim=points, horizon=horizon, progress=progress)
    ref.save(path)
    return ref


def _reference_residual(system, ref) -> float:
    """E of the reference V_T(., 0) on its own grid: mean E_e^2 from its gradient (V(0) = 0 exactly)."""
    x = torch.as_tensor(ref.points, dtype=torch.float64)
    g = torch.as_tensor(ref.gradient, dtype=torch.float64)
    ok = torch.as_tensor(ref.converged)
    e = system.hamiltonian_min(x, g)[ok]
    return float((e**2).mean())


def _true_errors(system, solution, ref) -> dict:
    ok = np.asarray(ref.converged)
    x = ref.points[ok]
    dv = solution.value(x) - ref.value[ok]
    du = solution.policy(x) - ref.policy[ok]
    return {"value_max_error": float(np.abs(dv).max()), "value_rmse": float(np.sqrt(np.mean(dv**2))),
            "policy_max_error": float(np.abs(du).max()), "policy_rmse": float(np.sqrt(np.mean(du**2)))}


def _closed_loop_metrics(system, solution, x0: np.ndarray, v_star: np.ndarray, settings: dict) -> dict:
    run = solution.closed_loop(x0, **settings)
    keep = (v_star > 1e-6) & run.stabilized  # a truncated cost of a run that did not settle says nothing
    ratio = run.cost[keep] / v_star[keep]
    finite = np.isfinite(ratio)
    return {"fraction_stabilized": run.fraction_stabilized,
            "suboptimality_mean": float(np.mean(ratio[finite])) if finite.any() else float("nan"),
            "suboptimality_max": float(np.max(ratio[finite])) if finite.any() else float("nan")}


def _closed_loop_states(system, ref_points: np.ndarray, per_dim: int) -> np.ndarray:
    """A coarse sub-grid of the V* reference grid (every k-th point per axis)."""
    full = round(ref_points.shape[0] ** (1 / system.n))
    k = max(1, (full - 1) // (per_dim - 1))
    idx = np.arange(0, full, k)
    mesh = np.stack(np.meshgrid(*[idx] * system.n, indexing="ij"), -1).reshape(-1, system.n)
    flat = np.ravel_multi_index(mesh.T, (full,) * system.n)
    return flat


# ---------------------------------------------------------------------- running

def _train(case: Case, system, config: TrainConfig, seed: int, progress: bool, on_stage):
    if case.kind == "steady":
        return SteadyStateSolver(system, config=config, seed=seed, progress=progress).solve()
    solver = FiniteHorizonSolver(system, config=config, seed=seed, progress=progress)
    sol = solver.solve(case.first)
    on_stage(sol)
    if case.to is not None:
        sol = solver.extend(sol, to=case.to, step=case.step, callback=on_stage)
    return sol


def _stage_rows(case, system, sol, refs, x0_idx, mode: str) -> list[dict]:
    """Metrics per horizon of one trained solution."""
    rows = []
    views = [(INF, sol)] if case.kind == "steady" else [(h, sol.truncated(k + 1)) for k, h in
                                                        enumerate(case.horizons)]
    for horizon, view in views:
        row = {"T": horizon, **{k: v for k, v in view.metrics.items()}}
        if system.value_star is None and refs.get(INF) is not None:
            row.update(_true_errors(system, view, refs[INF]))
        if refs.get(horizon) is not None and horizon != INF:
            row["E_reference_VT"] = _reference_residual(system, refs[horizon])
        rows.append(row)
    # closed loop of the final policy only
    if system.value_star is not None:
        x0 = system.grid(11).numpy()
        v_star = system.value_star(torch.as_tensor(x0)).numpy()
    else:
        ref = refs[INF]
        x0, v_star = ref.points[x0_idx], ref.value[x0_idx]
    settings = CLOSED_LOOP[mode] if mode == "quick" else CLOSED_LOOP_SYSTEM.get(case.system, CLOSED_LOOP[mode])
    rows[-1].update(_closed_loop_metrics(system, sol, x0, v_star, settings))
    return rows


def run(out: Path = DEFAULT_OUT, seeds: int = 3, quick: bool = False, only: list[str] | None = None,
        progress: bool = True, first_seed: int = 0) -> dict:
    """Train and evaluate every case for seeds ``first_seed .. seeds - 1``; write checkpoints, references and
    the results table (rows of seeds and cases not run are kept)."""
    if isinstance(seeds, bool) or not isinstance(seeds, int) or isinstance(first_seed, bool) or \
            not isinstance(first_seed, int) or not 0 <= first_seed < seeds:
        raise ValueError(f"reproduce needs integer seeds with 0 <= first_seed < seeds (at least one seed to "
                         f"train); got first_seed={first_seed!r}, seeds={seeds!r}")
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
                refs[h] = _reference(case, system, h, t_pts, out, progress)
        x0_idx = _closed_loop_states(system, refs[INF].points, 11 if system.n == 2 else 5) if INF in refs else None
        for seed in range(first_seed, seeds):
            print(f"== {case.name} (seed {seed})", flush=True)
            path = checkpoint_path(out, case.name, seed)
            t0 = time.perf_counter()
            sol = _train(case, system, config, seed, progress,
                         on_stage=lambda s, p=path: save(s, p, seed=s.stages[0].seed, case=case.name))
            wall = time.perf_counter() - t0
            rows = _stage_rows(case, system, sol, refs, x0_idx, mode)
            save(sol, path, seed=seed, case=case.name, evaluation={"rows": rows})
            for row in rows:
                print(f"   T={row['T']:g}: E={row['E']:.3e}" + (f" max|V-V*|={row['value_max_error']:.2e}"
                                                                 if "value_max_error" in row else ""), flush=True)
            records.append({"case": case.name, "system": case.system, "params": case.params, "seed": seed,
                            "wall_time": wall, "train_time": sol.wall_time, "rows": rows,
                            "paper": {str(k): v for k, v in case.paper.items()}})
    records = _merge(out, records)
    summary = _aggregate(records)
    meta = provenance(mode=mode, seeds=seeds, config=TrainConfig.preset("quick" if quick else "default").to_dict(),
                      closed_loop={"default": CLOSED_LOOP[mode], **({} if quick else CLOSED_LOOP_SYSTEM)},
                      reference_points=REFERENCE_POINTS[mode],
                      wall_time=time.perf_counter() - start,
                      cases_wall_time=float(sum(r["wall_time"] for r in records)),
                      reference_wall_time=_reference_wall_time(out))
    _write(out, records, summary, meta)
    return {"records": records, "summary": summary, "meta": meta}


def rewrite_tables(out: Path = DEFAULT_OUT) -> dict:
    """Rebuild the markdown/CSV/JSON tables from the stored records (no training): after a change to the
    table layout, or to restate the measured wall times from the records and reference grids."""
    payload = load_results(out)
    records = payload["records"]
    meta = dict(payload["meta"], cases_wall_time=float(sum(r["wall_time"] for r in records)),
                reference_wall_time=_reference_wall_time(out))
    summary = _aggregate(records)
    _write(Path(out), records, summary, meta)
    return {"records": records, "summary": summary, "meta": meta}


def _merge(out: Path, records: list[dict]) -> list[dict]:
    """Keep earlier results of cases and seeds not rerun now (a partial rerun updates its own rows only)."""
    path = Path(out) / "results" / "reproduce.json"
    if not path.exists():
        return records
    done = {(r["case"], r["seed"]) for r in records}
    earlier = [r for r in json.loads(path.read_text()).get("records", []) if (r["case"], r["seed"]) not in done]
    order = {c.name: i for i, c in enumerate(CASES)}
    return sorted(earlier + records, key=lambda r: (order.get(r["case"], len(order)), r["seed"]))


METRICS = ["E", "E_reference_VT", "value_max_error", "value_rmse", "policy_max_error", "policy_rmse",
           "suboptimality_mean", "suboptimality_max", "fraction_stabilized"]


def _aggregate(records: list[dict]) -> list[dict]:
    """Mean, standard deviation, min and max over seeds of every metric, per case and horizon."""
    groups: dict[tuple, list[dict]] = {}
    paper: dict[str, dict] = {}
    for r in records:
        paper[r["case"]] = r["paper"]
        for row in r["rows"]:
            groups.setdefault((r["case"], row["T"]), []).append({**row, "wall_time": r["wall_time"]})
    out = []
    for (case, T), rows in groups.items():
        entry = {"case": case, "T": T, "seeds": len(rows), "paper_E": paper[case].get(str(T))}
        for m in METRICS + ["wall_time"]:
            vals = np.array([row[m] for row in rows if row.get(m) is not None], dtype=float)
            if vals.size:
                entry[m] = {"mean": float(vals.mean()), "std": float(vals.std()), "min": float(vals.min()),
                            "max": float(vals.max())}
        out.append(entry)
    return out


def _reference_validation(out: Path) -> str:
    """The reference method's own error where V* is known: the quartic system's V* reference grid."""
    from .reference import ReferenceGrid

    lines = []
    for case in CASES:
        path = reference_path(out, case, INF)
        system = case.build_system()
        if system.value_star is None or not path.exists() or any(path.name in ln for ln in lines):
            continue
        ref = ReferenceGrid.load(path)
        x = torch.as_tensor(ref.points)
        dv = np.abs(ref.value - system.value_star(x).numpy()).max()
        du = np.abs(ref.policy - system.policy_star(x).numpy()).max()
        lines.append(f"The reference method, checked where V* is known ({path.name}, "
                     f"{ref.points.shape[0]} points): max |V_ref - V*| = {dv:.1e}, max |mu_ref - mu*| = {du:.1e}.")
    return " ".join(lines)


def _reference_wall_time(out: Path) -> float:
    """Seconds spent computing the stored reference grids (each records its own wall time)."""
    from .reference import ReferenceGrid

    return float(sum(ReferenceGrid.load(p).wall_time for p in (Path(out) / "reference").glob("*.npz")))


def _pm(stat: dict | None, spec: str = ".2e") -> str:
    if not stat:
        return "–"
    spread = stat["std"] > 1e-9 * abs(stat["mean"])  # a seed-independent number has no spread
    return f"{stat['mean']:{spec}} ± {stat['std']:{spec}}" if spread else f"{stat['mean']:{spec}}"


def _write(out: Path, records, summary, meta):
    res = out / "results"
    res.mkdir(parents=True, exist_ok=True)
    payload = {"meta": meta, "summary": summary, "records": records}
    (res / "reproduce.json").write_text(json.dumps(payload, indent=1, default=str))
    with open(res / "reproduce.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["case", "T", "seeds", "paper_E"] + [f"{m}_{s}" for m in METRICS for s in ("mean", "std")])
        for e in summary:
            w.writerow([e["case"], e["T"], e["seeds"], e["paper_E"]] +
                       [e.get(m, {}).get(s, "") for m in METRICS for s in ("mean", "std")])
    lines = ["# Reproduction of the paper's simulations (generated by `python -m pinnhjb reproduce`; do not edit)", "",
             f"Mode: {meta['mode']}; seeds per case: see the table; torch {meta['torch']}; written "
             f"{meta['created']}. Measured wall time on this machine: {meta['cases_wall_time']:.0f} s training and "
             f"evaluating all cases and seeds (sum over the runs that produced the rows) + "
             f"{meta['reference_wall_time']:.0f} s computing the reference grids. {_reference_validation(out)}", "",
             "E: eq. (IHJB_res) on the evaluation grid over Omega (mean ± std over seeds). E(ref V_T): the same "
             "residual of the independent reference V_T (the part of E due to the horizon). Errors are against "
             "the known V* (quartic) or the reference V* (pendulum, third-order). Suboptimality: J(mu_hat; x0) / "
             "V*(x0) in closed loop over the initial states it stabilised (|x(t_final)| < 1e-3); stabilised: their "
             "fraction. Paper numbers are the paper's, quoted.", "",
             "| case | T | E (paper) | E (ours) | E (ref V_T) | max abs V err | max abs mu err | J/V* mean | "
             "stabilised | case wall s |", "|---|---|---|---|---|---|---|---|---|---|"]
    for e in summary:
        T = "∞" if e["T"] == INF else f"{e['T']:g}"
        paper = "–" if e["paper_E"] is None else f"{e['paper_E']:.4g}"
        lines.append(f"| {e['case']} | {T} | {paper} | {_pm(e.get('E'))} | {_pm(e.get('E_reference_VT'))} | "
                     f"{_pm(e.get('value_max_error'))} | {_pm(e.get('policy_max_error'))} | "
                     f"{_pm(e.get('suboptimality_mean'), '.4f')} | {_pm(e.get('fraction_stabilized'), '.2f')} | "
                     f"{_pm(e.get('wall_time'), '.0f')} |")
    (res / "reproduce.md").write_text("\n".join(lines) + "\n")
