"""The reproduction's results tables: per-seed records merged with earlier runs, mean ± std over seeds, written
as markdown, CSV and JSON under ``<out>/results/reproduce.*``."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import torch

from .artifacts import DEFAULT_OUT, load_results, reference_path
from .cases import CASES, CONVERGED, INF

__all__ = ["METRICS", "merge_records", "aggregate", "write_tables", "rewrite_tables", "reference_wall_time"]

#: The metrics the tables aggregate over seeds.
METRICS = [
    "E",
    "E_reference_VT",
    "value_max_error",
    "value_rmse",
    "policy_max_error",
    "policy_rmse",
    "E_ratio",
    "value_rel_error",
    "cost_ratio_mean",
    "cost_ratio_max",
    "cost_within",
    "tail_share_max",
]


def rewrite_tables(out: Path = DEFAULT_OUT) -> dict:
    """Rebuild the tables from the stored records, without training.

    For a change of the tables' layout, or to restate the wall times from the records and reference grids.

    * ``out``: the artifacts folder.
    """
    payload = load_results(out)
    records = payload["records"]
    meta = dict(
        payload["meta"],
        cases_wall_time=float(sum(r["wall_time"] for r in records)),
        reference_wall_time=reference_wall_time(out),
    )
    summary = aggregate(records)
    write_tables(Path(out), records, summary, meta)
    return {"records": records, "summary": summary, "meta": meta}


def merge_records(out: Path, records: list[dict]) -> list[dict]:
    """The new records with the stored ones of cases and seeds not rerun (a partial rerun updates its own rows).

    * ``out``: the artifacts folder.
    * ``records``: the new per-seed records.
    """
    path = Path(out) / "results" / "reproduce.json"
    if not path.exists():
        return records
    done = {(r["case"], r["seed"]) for r in records}
    earlier = [r for r in json.loads(path.read_text()).get("records", []) if (r["case"], r["seed"]) not in done]
    order = {c.name: i for i, c in enumerate(CASES)}
    return sorted(earlier + records, key=lambda r: (order.get(r["case"], len(order)), r["seed"]))


def aggregate(records: list[dict]) -> list[dict]:
    """Mean, standard deviation, min and max over seeds of every metric, per case and horizon, of ``records``."""
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
                with np.errstate(invalid="ignore"):  # a diverged run's infinite cost has no spread
                    std = float(vals.std())
                entry[m] = {
                    "mean": float(vals.mean()),
                    "std": std,
                    "min": float(vals.min()),
                    "max": float(vals.max()),
                }
        out.append(entry)
    return out


def _reference_validation(out: Path) -> str:
    """The reference method's own error where V* is known: the quartic system's V* reference grid."""
    from ..reference import ReferenceGrid

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
        lines.append(
            f"The reference method, checked where V* is known ({path.name}, "
            f"{ref.points.shape[0]} points): max |V_ref - V*| = {dv:.1e}, max |mu_ref - mu*| = {du:.1e}."
        )
    return " ".join(lines)


def reference_wall_time(out: Path) -> float:
    """Seconds spent computing the reference grids stored under ``out`` (each records its own wall time)."""
    from ..reference import ReferenceGrid

    return float(sum(ReferenceGrid.load(p).wall_time for p in (Path(out) / "reference").glob("*.npz")))


def _pm(stat: dict | None, spec: str = ".2e") -> str:
    if not stat:
        return "–"
    spread = stat["std"] > 1e-9 * abs(stat["mean"])  # a seed-independent number has no spread
    return f"{stat['mean']:{spec}} ± {stat['std']:{spec}}" if spread else f"{stat['mean']:{spec}}"


def write_tables(out: Path, records, summary, meta):
    """Write ``<out>/results/reproduce.json``, ``.csv`` and ``.md``.

    * ``out``: the artifacts folder.
    * ``records``: per-seed records.
    * ``summary``: the :func:`aggregate` of them.
    * ``meta``: versions, mode, wall times.
    """
    res = out / "results"
    res.mkdir(parents=True, exist_ok=True)
    payload = {"meta": meta, "summary": summary, "records": records}
    (res / "reproduce.json").write_text(json.dumps(payload, indent=1, default=str))
    with open(res / "reproduce.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["case", "T", "seeds", "paper_E"] + [f"{m}_{s}" for m in METRICS for s in ("mean", "std")])
        for e in summary:
            w.writerow(
                [e["case"], e["T"], e["seeds"], e["paper_E"]]
                + [e.get(m, {}).get(s, "") for m in METRICS for s in ("mean", "std")]
            )
    lines = [
        "# Reproduction of the paper's simulations (generated by `python -m pinnhjb reproduce`; do not edit)",
        "",
        f"Mode: {meta['mode']}; seeds per case: see the table; torch {meta['torch']}; written "
        f"{meta['created']}. Measured wall time on this machine: {meta['cases_wall_time']:.0f} s training and "
        f"evaluating all cases and seeds (sum over the runs that produced the rows) + "
        f"{meta['reference_wall_time']:.0f} s computing the reference grids. {_reference_validation(out)}",
        "",
        "E: the horizon check eq-e on the evaluation grid over Omega (mean ± std over the seeds that reached T). "
        "E(ref V_T): the same residual of the independent reference V_T (the part of E due to the horizon). Errors "
        "are against the known V* (quartic) or the reference V* (pendulum, third-order). J/V*: the learned "
        "policy's closed-loop cost to t = inf (J to t_final plus the linearisation's LQR value at x(t_final)) over "
        "V*, worst initial state of the closed-loop grid; the optimal policy scores 1 from every state. Within "
        f"{CONVERGED['cost_ratio_max'] - 1:.0%}: the fraction of initial states where J/V* <= "
        f"{CONVERGED['cost_ratio_max']:g}. Chains marked 'until' stop at the first T where E / E(V = 0) <= "
        f"{CONVERGED['E_ratio']:g}, max abs(V - V*_ref) <= {CONVERGED['value_rel_error']:.0%} of max V*_ref and "
        f"J/V* <= {CONVERGED['cost_ratio_max']:g} from every state. Paper numbers are the paper's, quoted.",
        "",
        "| case | T | seeds | E (paper) | E (ours) | E (ref V_T) | max abs V err | max abs mu err | J/V* max | "
        f"within {CONVERGED['cost_ratio_max'] - 1:.0%} | case wall s |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    until = {c.name for c in CASES if c.until}
    for e in summary:
        T = "∞" if e["T"] == INF else f"{e['T']:g}"
        paper = "–" if e["paper_E"] is None else f"{e['paper_E']:.4g}"
        name = f"{e['case']} (until)" if e["case"] in until else e["case"]
        lines.append(
            f"| {name} | {T} | {e['seeds']} | {paper} | {_pm(e.get('E'))} | {_pm(e.get('E_reference_VT'))} | "
            f"{_pm(e.get('value_max_error'))} | {_pm(e.get('policy_max_error'))} | "
            f"{_pm(e.get('cost_ratio_max'), '.4f')} | {_pm(e.get('cost_within'), '.2f')} | "
            f"{_pm(e.get('wall_time'), '.0f')} |"
        )
    (res / "reproduce.md").write_text("\n".join(lines) + "\n")
