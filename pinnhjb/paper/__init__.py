"""What belongs to the paper, not to the method; the core modules know nothing of it.

* :mod:`.cases`: the paper's simulations (Section 6) with its reported numbers, and the evaluation settings;
* :mod:`.artifacts`: where the stored checkpoints, reference grids and results live, and the loaders the
  chapters call (re-exported here: ``paper.load_case``, ``paper.stored_seeds``, ...);
* :mod:`.reproduce`: the pipeline behind ``python -m pinnhjb reproduce``; :mod:`.evaluation` measures one
  trained case against its reference, :mod:`.tables` writes the results tables;
* :mod:`.theorem3`: Theorem 3 demonstrated on a trained stage (chapter 5), ``python -m pinnhjb.paper.theorem3``;
* :mod:`.family`: the third-order system over the whole range of R as one network (chapter 6);
* :mod:`.goals`: issue #18's goals against the stored benchmark runs (chapter 8, ``benchmarks/index.py``).
"""

import importlib as _importlib

from .artifacts import (
    artifacts_dir,
    benchmark_reference,
    benchmark_reference_path,
    benchmark_run,
    benchmark_runs,
    checkpoint_path,
    dimension_chain,
    dimension_rows,
    dimension_states,
    load_case,
    load_reference,
    load_results,
    reference_path,
    reference_residual,
    results_dir,
    run_config,
    stage_metric,
    stored_seeds,
)
from .cases import CASES, CLOSED_LOOP_SYSTEM, CONVERGED, INF, Case, cases
from .goals import Goal, dimension_goals

__all__ = [
    "CASES",
    "CLOSED_LOOP_SYSTEM",
    "CONVERGED",
    "INF",
    "Case",
    "cases",
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
    "dimension_chain",
    "benchmark_runs",
    "run_config",
    "dimension_rows",
    "dimension_states",
    "benchmark_reference",
    "benchmark_reference_path",
    "Goal",
    "dimension_goals",
]

# Submodules imported on first use (``paper.reproduce`` after ``from pinnhjb import paper``); theorem3 is not
# imported here so that ``python -m pinnhjb.paper.theorem3`` runs it only once (family likewise).
_LAZY = ("reproduce", "evaluation", "tables", "theorem3", "family")


def __getattr__(name):
    if name in _LAZY:
        return _importlib.import_module(f".{name}", __name__)
    raise AttributeError(f"module 'pinnhjb.paper' has no attribute {name!r}")
