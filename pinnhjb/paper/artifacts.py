"""Where the reproduction's artifacts live, and the loaders the chapters call: stored solutions per case and
seed, the reference grids, the results table, and the benchmarks' stored runs that chapters 8 to 10 read."""

from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import torch

from ..config import TrainConfig
from ..storage import load
from .cases import CASES, INF, Case
from .evaluation import reference_grid_residual

__all__ = [
    "DEFAULT_OUT",
    "artifacts_dir",
    "checkpoint_path",
    "reference_path",
    "load_case",
    "stored_seeds",
    "stage_metric",
    "reference_residual",
    "load_reference",
    "load_results",
    "results_dir",
    "benchmark_run",
    "benchmark_runs",
    "dimension_rows",
    "dimension_states",
    "benchmark_reference",
    "benchmark_reference_path",
]

#: The artifacts folder, relative to the working directory.
DEFAULT_OUT = Path("artifacts")


def _case(case: str | Case) -> Case:
    """A case by name (a :class:`Case` is returned as it is); a KeyError names an unknown one and the known ones."""
    if isinstance(case, Case):
        return case
    for c in CASES:
        if c.name == case:
            return c
    raise KeyError(f"unknown case {case!r}; known: {[c.name for c in CASES]}")


def checkpoint_path(out: Path, case: str, seed: int) -> Path:
    """Where a case's checkpoint for one seed lives: ``<out>/checkpoints/<case>/seed<seed>.pt``."""
    return Path(out) / "checkpoints" / case / f"seed{seed}.pt"


def _system_key(case: Case) -> str:
    return case.system + "".join(f"_{k}{v:g}" if isinstance(v, float) else f"_{k}{v}" for k, v in case.params.items())


def reference_path(out: Path, case: Case, horizon: float) -> Path:
    """Where a case's reference grid for one horizon (``inf``: V*) lives, under ``<out>/reference/``."""
    tag = "inf" if horizon == INF else f"T{horizon:g}"
    return Path(out) / "reference" / f"{_system_key(case)}_{tag}.npz"


def artifacts_dir() -> Path:
    """Where the committed artifacts are.

    ``$PINNHJB_ARTIFACTS``, else the nearest ``artifacts/`` folder with checkpoints in the working directory or
    above it (notebooks run from ``notebooks/``).
    """
    env = os.environ.get("PINNHJB_ARTIFACTS")
    if env:
        return Path(env)
    for base in [Path.cwd(), *Path.cwd().parents]:
        if (base / DEFAULT_OUT / "checkpoints").is_dir():
            return base / DEFAULT_OUT
    return DEFAULT_OUT


_RETRAINED: set = set()


def load_case(case: str, seed: int = 0, out: Path | None = None, device=None, retrain: bool = False):
    """The stored solution of a case, as the notebooks load it.

    * ``case``: a case's name (:data:`~pinnhjb.paper.cases.CASES`); an unknown one is a KeyError.
    * ``seed``: the seed.
    * ``out``: the artifacts folder; None: :func:`artifacts_dir`.
    * ``device``: where the networks go; None: CUDA when present.
    * ``retrain``: a notebook's ``RETRAIN`` switch; first train this case and seed again with the default
      recipe, in place (checkpoint and results table, as ``reproduce --cases``), once per process.
    """
    if case not in {c.name for c in CASES}:
        raise KeyError(f"unknown case {case!r}; known: {[c.name for c in CASES]}")
    out = Path(out or artifacts_dir())
    if retrain and (case, seed, out) not in _RETRAINED:
        from . import reproduce  # the pipeline imports this module

        reproduce.run(out=out, seeds=seed + 1, only=[case], first_seed=seed)
        _RETRAINED.add((case, seed, out))
    return load(checkpoint_path(out, case, seed), device=device)


def stored_seeds(case: str, out: Path | None = None) -> list[int]:
    """The seeds with a stored checkpoint for ``case`` (a name) under ``out`` (None: :func:`artifacts_dir`)."""
    folder = Path(out or artifacts_dir()) / "checkpoints" / case
    return sorted(int(p.stem[4:]) for p in folder.glob("seed*.pt"))


def stage_metric(case: str, key: str, out: Path | None = None) -> dict[float, list[float]]:
    """A metric of every stored seed of a chain case, per horizon it reached: ``{T: [value per seed]}``.

    * ``case``: the case's name; an unknown one is a KeyError.
    * ``key``: a metric of :meth:`~pinnhjb.solution.FiniteHorizonSolution.summary`, e.g. ``"E"``.
    * ``out``: the artifacts folder; None: :func:`artifacts_dir`.
    """
    _case(case)
    values: dict[float, list[float]] = {}
    for seed in stored_seeds(case, out):
        for row in load_case(case, seed, out).summary():
            values.setdefault(round(row["horizon"], 9), []).append(row[key])
    return dict(sorted(values.items()))


def reference_residual(case: str | Case, horizon: float, out: Path | None = None) -> float:
    """E of the stored exact (reference) V_T(., 0): the part of a PINN's E that is due to the horizon alone.

    * ``case``: a :class:`~pinnhjb.paper.cases.Case` or its name; an unknown name is a KeyError.
    * ``horizon``: T.
    * ``out``: the artifacts folder; None: :func:`artifacts_dir`.
    """
    case = _case(case)
    return reference_grid_residual(case.build_system(), load_reference(case, horizon, out))


def load_reference(case: str | Case, horizon: float = INF, out: Path | None = None):
    """A case's stored :class:`~pinnhjb.reference.ReferenceGrid`.

    * ``case``: a :class:`~pinnhjb.paper.cases.Case` or its name; an unknown name is a KeyError.
    * ``horizon``: T, or ``inf`` for V*.
    * ``out``: the artifacts folder; None: :func:`artifacts_dir`.
    """
    from ..reference import ReferenceGrid

    case = _case(case)
    return ReferenceGrid.load(reference_path(out or artifacts_dir(), case, horizon))


def load_results(out: Path | None = None) -> dict:
    """The results written by :func:`pinnhjb.paper.reproduce.run`: ``summary`` rows, ``records`` per seed, ``meta``.

    * ``out``: the artifacts folder; None: :func:`artifacts_dir`.
    """
    return json.loads((Path(out or artifacts_dir()) / "results" / "reproduce.json").read_text())


def results_dir(out: Path | None = None) -> Path:
    """Where the benchmarks write their results: ``benchmarks/results/`` beside the artifacts folder.

    * ``out``: the artifacts folder; None: :func:`artifacts_dir`.
    """
    return Path(out or artifacts_dir()).parent / "benchmarks" / "results"


def benchmark_run(
    run: str | None = None, name: str = "rigid_body", folder: str = "repeats", out: Path | None = None
) -> dict:
    """A benchmark's stored run, as its script wrote it (``meta`` and its results).

    * ``run``: the run's folder under ``folder`` (its ``--out``); None: the benchmark's main run,
      ``benchmarks/results/<name>.json``.
    * ``name``: the benchmark: ``"rigid_body"``, ``"dimension"``, ...
    * ``folder``: where ``run`` lies under :func:`results_dir`: ``"repeats"``, or ``"cuda_nd"`` for the runs of
      ``benchmarks/cuda.sh``.
    * ``out``: the artifacts folder; None: :func:`artifacts_dir`.

    A run that is not stored is a FileNotFoundError naming the file looked for.
    """
    base = results_dir(out)
    path = base / f"{name}.json" if run is None else base / folder / run / f"{name}.json"
    if not path.is_file():
        raise FileNotFoundError(f"no stored benchmark run at {path}")
    return json.loads(path.read_text())


def dimension_chain(run: str, system: str, n: int, folder: str = "repeats", out: Path | None = None):
    """The chain a stored ``benchmarks/dimension.py`` run saved (``--save``) for one (system, n), loaded.

    * ``run``: the run's folder under ``folder`` (its ``--out``).
    * ``system``: the family, ``"lq_ladder"`` or ``"converse"``.
    * ``n``: the state dimension.
    * ``folder``, ``out``: as in :func:`benchmark_run`.

    The file is ``OUT/chains/<system>-n<n>-default.pt``, the default recipe's (``dimension.py``'s ``chain_name``).
    """
    return load(results_dir(out) / folder / run / "chains" / f"{system}-n{n}-default.pt")


def run_config(run: dict, *leave_out: str) -> dict:
    """A stored benchmark run's training config (``meta["config"]``, a :class:`~pinnhjb.TrainConfig` as a dict)
    without the settings in ``leave_out``: two runs that differ in those settings alone have equal
    ``run_config(a, *keys) == run_config(b, *keys)``.

    * ``run``: the run, as :func:`benchmark_run` reads it.
    * ``leave_out``: ``TrainConfig`` field names to drop, e.g. ``"warm_start"``; a run stored before a field
      existed lacks it, and is compared without it. A name that is not a field (a misspelling, or a setting
      kept outside the config such as the seed) is a KeyError: it would leave the comparison unchanged.
    """
    fields = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = [key for key in leave_out if key not in fields]
    if unknown:
        raise KeyError(f"{unknown} not TrainConfig field(s); a run's config holds only those: {sorted(fields)}")
    return {key: value for key, value in run["meta"]["config"].items() if key not in leave_out}


def benchmark_runs(name: str = "rigid_body", out: Path | None = None) -> dict[str, dict]:
    """Every stored run of a benchmark, by where it lies: ``"main run"`` where there is one, then ``"<folder>/<run>"``
    for each ``<folder>/<run>/<name>.json`` and ``"<folder>"`` for each ``<folder>/<name>.json`` under
    :func:`results_dir` (``repeats/...``, ``cuda_nd/...``, ``cuda``), in name order.

    * ``name``: the benchmark: ``"rigid_body"``, ``"dimension"``, ...
    * ``out``: the artifacts folder; None: :func:`artifacts_dir`.
    """
    base = results_dir(out)
    runs = {"main run": benchmark_run(name=name, out=out)} if (base / f"{name}.json").is_file() else {}
    where = sorted(path.parent.relative_to(base) for path in base.glob(f"*/**/{name}.json"))
    for folder in where:
        if len(folder.parts) <= 2:  # results/<folder>/<run>/ or results/<folder>/
            runs[folder.as_posix()] = json.loads((base / folder / f"{name}.json").read_text())
    return runs


def dimension_rows(record: dict, recipe: str = "default") -> dict[tuple[str, int], dict]:
    """A ``benchmarks/dimension.py`` run's measured rows of one recipe, by ``(system, n)``: where a run holds
    several rows of the same system and n, the last one; rows without a measured error (a recipe that did not
    run) are left out.

    * ``record``: the run, as :func:`benchmark_run` reads it (``name="dimension"``).
    * ``recipe``: ``"default"``, ``"adam_lbfgs"`` or ``"deepxde"`` (rows stored before recipes were named are
      ``"default"``).
    """
    return {
        (r["system"], r["n"]): r
        for r in record["rows"]
        if r.get("recipe", "default") == recipe and r.get("value_rel_error") is not None
    }


def dimension_states(system, points: int, seed: int) -> torch.Tensor:
    """The states on which ``benchmarks/dimension.py`` measures a run's true errors: ``points`` seeded uniform
    states of Omega, float64 on the CPU (a stored run's ``meta["points"]`` and ``meta["seed"]``).

    * ``system``: the :class:`~pinnhjb.systems.ControlAffineSystem` (its ``domain`` is Omega).
    * ``points``: how many states.
    * ``seed``: the seed of their generator.
    """
    return system.sample(points, torch.Generator().manual_seed(seed), dtype=torch.float64, box=system.domain)


def benchmark_reference_path(system: str, horizon: float, points: int | str, out: Path | None = None) -> Path:
    """Where a benchmark stores its reference grid for ``system``: ``<out>/reference/<system>_<inf|T..>_<points>.npz``.

    * ``system``: the name the benchmark stores it under, e.g. ``"rigid_body"``.
    * ``horizon``: T, or ``inf`` for V*.
    * ``points``: the number of seeded states (``"*"``: the glob pattern for any number).
    * ``out``: the artifacts folder; None: :func:`artifacts_dir`.
    """
    tag = "inf" if horizon == INF else f"T{horizon:g}"
    return Path(out or artifacts_dir()) / "reference" / f"{system}_{tag}_{points}.npz"


def benchmark_reference(system: str, horizon: float = INF, out: Path | None = None):
    """The reference grid a benchmark stored for ``system`` (``<out>/reference/<system>_<inf|T..>_<points>.npz``),
    the one with the most states when there are several.

    * ``system``: the name the benchmark stored it under, e.g. ``"rigid_body"``.
    * ``horizon``: T, or ``inf`` for V*.
    * ``out``: the artifacts folder; None: :func:`artifacts_dir`.

    None stored is a FileNotFoundError naming the pattern looked for.
    """
    from ..reference import ReferenceGrid

    pattern = benchmark_reference_path(system, horizon, "*", out)
    files = list(pattern.parent.glob(pattern.name))
    if not files:
        raise FileNotFoundError(f"no stored reference {pattern}")
    return ReferenceGrid.load(max(files, key=lambda p: int(p.stem.rsplit("_", 1)[1])))
