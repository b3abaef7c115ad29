"""Every stored benchmark run on one page: ``benchmarks/results/index.md``.

One section per benchmark script, one table row per stored run (the main run, then every run under
``results/repeats/``, ``results/cuda_nd/`` and the other folders of ``results/``), with the numbers the run itself
wrote: when and where it ran, and its headline results; below each table, the command that made each run. Nothing
on the page is typed: it is all read from the runs' JSON files, so ``tests/test_benchmarks.py`` can check that the
committed page is this script's output. Takes a second, trains nothing::

    .venv/bin/python benchmarks/index.py            # rewrite results/index.md
    .venv/bin/python benchmarks/index.py --check    # exit 1 if results/index.md is not up to date
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
from pathlib import Path

from pinnhjb.paper import benchmark_runs, dimension_goals

RESULTS = Path(__file__).resolve().parent / "results"

#: The benchmarks in the order the page lists them.
BENCHMARKS = (
    "dimension",
    "rigid_body",
    "speed",
    "accuracy",
    "parametric",
    "parametric_extended",
    "third_order_horizon",
    "step_cost",
    "lm_step",
    "polish",
)

#: Flags left out of the commands shown: where the output went and the free-text note.
_DROP = {"--out", "--note", "--artifacts"}
_DROP_BARE = {"--no-progress"}


def _num(v, spec: str = ".2e") -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "-"
    return format(v, spec)


def _date(meta: dict) -> str:
    return str(meta.get("created", "-"))[:10]


def where(meta: dict) -> str:
    """Where a run trained, from its ``meta``: the machine and the threads."""
    where = meta.get("machine") or "not recorded"
    threads = meta.get("threads")
    return where if threads is None else f"{where}; {threads} thread(s)"


def command(meta: dict) -> str:
    """A run's command as stored in its ``meta`` (its words joined by single spaces, so an empty argument is two
    spaces), without where its output went and its free-text note; an empty argument shows as ``""``."""
    words = meta.get("command", "").split(" ") if meta.get("command") else []
    kept, i = [], 0
    while i < len(words):
        word = words[i]
        if word in _DROP_BARE:
            i += 1
        elif word == "--note":
            i += 1
            while i < len(words) and not words[i].startswith("--"):
                i += 1
        elif word in _DROP:
            i += 2
        else:
            kept.append('""' if word == "" else shlex.quote(word))
            i += 1
    return " ".join(kept) if kept else "not recorded"


def _commands(runs: dict[str, dict]) -> list[str]:
    lines = ["", "The command of each run (without `--out`, `--note`, `--artifacts` and `--no-progress`):", ""]
    lines += [f"- `{run}`: `{command(record['meta'])}`" for run, record in runs.items()]
    return lines


def _dimension(runs: dict[str, dict]) -> list[str]:
    lines = [
        "| run | created | machine | system | recipe | n | weights | T | E / E(V = 0) | value error | "
        "grad error | wall s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for run, record in runs.items():
        meta = record["meta"]
        for row in record["rows"]:
            lines.append(
                f"| `{run}` | {_date(meta)} | {where(meta)} | {row['system']} | {row.get('recipe', 'default')} "
                f"| {row['n']} | {row.get('weights', '-')} | {_num(row.get('T'), 'g')} | {_num(row.get('E_ratio'))} "
                f"| {_num(row.get('value_rel_error'))} | {_num(row.get('grad_mean_rel_error'))} "
                f"| {_num(row.get('wall_s'), '.0f')} |"
            )
    return lines


def _rigid_body(runs: dict[str, dict]) -> list[str]:
    lines = [
        "| run | created | machine | problem | weights | T | E / E(V = 0) | value error | grad error | "
        "loops settled | worst cost / V_ref | wall s |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for run, record in runs.items():
        meta = record["meta"]
        for problem in ("infinite", "finite"):
            part = record.get(problem)
            if not part or not part.get("stages"):
                continue
            last = part["stages"][-1]
            loops = part.get("closed_loop") or {}
            settled = f"{loops['settled']} of {loops['states']}" if "settled" in loops else "-"
            lines.append(
                f"| `{run}` | {_date(meta)} | {where(meta)} | {problem} | {meta.get('weights', '-')} "
                f"| {_num(last.get('T'), 'g')} | {_num(last.get('E_ratio'))} | {_num(last.get('value_rel_error'))} "
                f"| {_num(last.get('grad_mean_rel_error'))} | {settled} | {_num(loops.get('cost_ratio_max'), '.5f')} "
                f"| {_num(part.get('wall_s'), '.0f')} |"
            )
    return lines


def _other(name: str, runs: dict[str, dict]) -> list[str]:
    lines = ["| run | created | machine | results page |", "|---|---|---|---|"]
    for run, record in runs.items():
        page = f"{name}.md" if run == "main run" else f"{run}/{name}.md"
        lines.append(f"| `{run}` | {_date(record['meta'])} | {where(record['meta'])} | [{page}]({page}) |")
    return lines


def _artifacts(results: Path) -> Path:
    """The artifacts folder whose :func:`pinnhjb.paper.results_dir` is ``results``, for the package's readers."""
    return results.parent.parent / "artifacts"


def _goals(results: Path) -> list[str]:
    """Issue #18's goals against these runs (:func:`pinnhjb.paper.dimension_goals`), as chapter 8 tabulates them."""
    try:
        goals = dimension_goals(_artifacts(results))
    except (FileNotFoundError, KeyError):  # a results folder without the main runs
        return []
    lines = [
        "",
        "## Issue #18's goals",
        "",
        "The main run's number, and the closest of every stored run (lowest over them; chapter 8's goals table); for",
        "the ladder and the converse system also the lowest largest error on Omega of the stored chains, with its",
        "2^n vertices and after an ascent (`largest_error.md`), which must meet the goal too. A goal missed says by",
        "how much (the closest number over the goal's; the largest on Omega where there is one):",
        "",
        "| goal | main run | closest stored run | met | that run | largest on Omega | that chain |",
        "|---|---|---|---|---|---|---|",
    ]
    lines += [
        f"| {g.text} | {g.show('main')} | {g.show()} | {g.verdict} | `{g.run}` | {g.show('largest')} | "
        + (f"`{g.largest_run}` |" if g.largest_run else "– |")
        for g in goals
    ]
    return lines


def render(results: Path = RESULTS) -> str:
    """The page, from every ``<benchmark>.json`` under ``results`` (see the module docstring)."""
    out = [
        "# Stored benchmark runs (generated by `benchmarks/index.py`; do not edit)",
        "",
        "Every run stored under `benchmarks/results/`, with the numbers it wrote: the last stage's errors for",
        "`dimension.py` (one row per system and n; errors against the exact V*) and `rigid_body.py` (against the",
        "stored BVP reference), the results page for the others. Wall times are each run's own, on the machine",
        "named; compare them only between runs on the same machine. A run resumed from another (`--resume`) counts",
        "the stages it resumed in its wall time, trained where that run was. What the runs show: chapters 8 to 10",
        "of the book and `benchmarks/README.md`.",
    ]
    out += _goals(results)
    for name in BENCHMARKS:
        runs = benchmark_runs(name, _artifacts(results))
        if not runs:
            continue
        out += ["", f"## `{name}.py`" if (results.parent / f"{name}.py").is_file() else f"## `{name}`", ""]
        if name == "dimension":
            out += _dimension(runs)
        elif name == "rigid_body":
            out += _rigid_body(runs)
        else:
            out += _other(name, runs)
        out += _commands(runs)
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--results", type=Path, default=RESULTS, help="the results folder (default: this repo's)")
    parser.add_argument("--check", action="store_true", help="only check that index.md is up to date")
    args = parser.parse_args(argv)
    if not args.results.is_dir():
        parser.error(f"--results: no results folder at {args.results}")
    page, path = render(args.results), args.results / "index.md"
    if args.check:
        if not path.is_file() or path.read_text() != page:
            print(f"{path} is not up to date: run benchmarks/index.py", file=sys.stderr)
            return 1
        return 0
    path.write_text(page)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
