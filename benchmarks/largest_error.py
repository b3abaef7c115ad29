"""Issue #18's ladder and converse goals ask for max |V - V*| / max V* over Omega. ``dimension.py`` measures it on
4096 seeded uniform states, which in six or more dimensions do not come near Omega's corners, where V* and the
error often peak. This script measures every stored run's saved chain (``dimension.py --save``) and every mean of
stored chains (``dimension.py --mean``) once more by :func:`pinnhjb.metrics.largest_value_error`: over the same
states, over those and Omega's 2^n vertices, and after a bounded ascent of the error from the largest ones. It
trains nothing. It writes ``largest_error.md`` and ``largest_error.json`` (``--out``), which chapter 8's goals
table (:func:`pinnhjb.paper.dimension_goals`) and chapter 9 read.

    .venv/bin/python benchmarks/largest_error.py

A run's number of the first kind must be the one it stored (the same states, the same chain): the script stops
when it is not. A mean's states are all its members' states together, with one max V* over them, where
``dimension.py --mean`` took the worst of its members' states one seed at a time: the two differ a little.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

import pinnhjb as ph
from pinnhjb.metrics import largest_value_error
from pinnhjb.paper import benchmark_runs, dimension_rows, dimension_states
from pinnhjb.storage import load, provenance

RESULTS = Path(__file__).resolve().parent / "results"
ROOT = RESULTS.parents[1]


def chain_path(run_dir: Path, system: str, n: int) -> Path:
    return run_dir / "chains" / f"{system}-n{n}-default.pt"


def cases(results: Path) -> list[dict]:
    """Every (run, system, n) whose chain, or whose members' chains, are stored: what to measure."""
    out = []
    for name, record in benchmark_runs("dimension", ROOT / "artifacts").items():
        if name == "main run":
            continue
        for (system, n), row in dimension_rows(record).items():
            members = row.get("members")
            if members:
                paths = [chain_path(ROOT / m["run"], system, n) for m in members]
                seeds = [m["seed"] for m in members]
            else:
                paths, seeds = [chain_path(results / name, system, n)], [record["meta"]["seed"]]
            if all(p.is_file() for p in paths):
                out.append(
                    dict(
                        run=name,
                        system=system,
                        n=n,
                        stored=row["value_rel_error"],
                        chains=paths,
                        seeds=seeds,
                        points=record["meta"]["points"],
                    )
                )
    return out


def measure(case: dict, starts: int) -> dict:
    chains = [load(p) for p in case["chains"]]
    sol = chains[0] if len(chains) == 1 else ph.AveragedSolution(chains)
    x = torch.cat([dimension_states(sol.system, case["points"], s) for s in case["seeds"]])
    t0 = time.perf_counter()
    found = largest_value_error(sol.system, sol.value_function(), x, starts=starts)
    wall = time.perf_counter() - t0
    if len(chains) == 1 and not np.isclose(found.sampled, case["stored"], rtol=1e-6):
        sys.exit(f"{case['run']}: {found.sampled:.6e} on its own states, where it stored {case['stored']:.6e}")
    return {
        "run": case["run"],
        "system": case["system"],
        "n": case["n"],
        "members": len(chains),
        "stored": case["stored"],
        "sampled": found.sampled,
        "vertices": found.vertices,
        "ascended": found.ascended,
        "at_vertex": found.at_vertex,
        "states": len(x),
        "wall_s": wall,
    }


def page(rows: list[dict], meta: dict) -> str:
    lines = [
        "# The largest value error on Omega, beyond the sampled states",
        "",
        f"`{meta['command']}` ({meta['created']}, {meta['threads']} thread(s)). Each stored chain (or mean of",
        "chains) of `benchmarks/dimension.py`: max abs(V - V*) / max V* on its seeded states (as stored; a mean's over",
        "all its members' states), with Omega's 2^n vertices too, and after a bounded ascent from the largest errors.",
        "",
        "| run | system | n | chains | stored | sampled | with vertices | after ascent | at a vertex | s |",
        "|:--|:--|--:|--:|--:|--:|--:|--:|:-:|--:|",
    ]
    for r in rows:
        v = "–" if r["vertices"] is None else f"{r['vertices']:.2e}"
        lines.append(
            f"| `{r['run']}` | {r['system']} | {r['n']} | {r['members']} | {r['stored']:.2e} | {r['sampled']:.2e} | "
            f"{v} | {r['ascended']:.2e} | {'yes' if r['at_vertex'] else 'no'} | {r['wall_s']:.0f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=RESULTS, help="where to write largest_error.md/.json")
    parser.add_argument("--starts", type=int, default=10, help="ascents from this many states and vertices each")
    parser.add_argument("--threads", type=int, default=1, help="torch threads")
    parser.add_argument("--only", default=None, help="measure only runs whose name contains this")
    args = parser.parse_args(argv)
    if args.starts < 1 or args.threads < 1:
        parser.error("--starts and --threads must be at least 1")
    torch.set_num_threads(args.threads)
    todo = [c for c in cases(RESULTS) if args.only is None or args.only in c["run"]]
    if not todo:
        parser.error("no stored chain to measure")
    rows = [measure(c, args.starts) for c in tqdm(todo, desc="chains", unit="chain")]
    meta = provenance(threads=args.threads, starts=args.starts)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "largest_error.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    (args.out / "largest_error.md").write_text(page(rows, meta))
    print(page(rows, meta))


if __name__ == "__main__":
    main()
