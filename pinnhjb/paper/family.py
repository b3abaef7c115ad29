"""The third-order system over the paper's whole range of R as one network (chapter 6).

:func:`family` is :class:`pinnhjb.parametric.WeightFamily` of ``third_order(R=1)`` over R in ``R_RANGE``;
:func:`load` returns its stage on [0, ``HORIZON``] trained by the default recipe, from the stored checkpoint
(``artifacts/parametric/third_order_seed0.pt``), training and storing it first when it is missing or when asked
(``python -m pinnhjb.paper.family``, a few seconds).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from ..config import TrainConfig
from ..parametric import WeightFamily
from ..solution import FiniteHorizonSolution
from ..solver import FiniteHorizonSolver
from ..storage import load as _load
from ..storage import save as _save
from ..systems import third_order
from .artifacts import artifacts_dir

__all__ = ["R_RANGE", "HORIZON", "SEED", "family", "path", "load"]

R_RANGE = (0.01, 100.0)  # the paper's R values of Table 2 span it
HORIZON = 0.5  # the paper's horizon for Table 2
SEED = 0


def family() -> WeightFamily:
    """The third-order systems with weight R in ``R_RANGE`` (R0 = 1) as one system."""
    return WeightFamily(third_order(R=1.0), R_RANGE)


def path(out: Path | None = None) -> Path:
    """The stored checkpoint.

    * ``out``: the artifacts folder; None: :func:`pinnhjb.paper.artifacts.artifacts_dir`.
    """
    return Path(out or artifacts_dir()) / "parametric" / f"third_order_seed{SEED}.pt"


def load(retrain: bool = False, out: Path | None = None, progress: bool = False) -> FiniteHorizonSolution:
    """The family's trained stage on [0, ``HORIZON``] (a solution of ``family().system``).

    * ``retrain``: train and store it even when the checkpoint exists.
    * ``out``: the artifacts folder; None: :func:`pinnhjb.paper.artifacts.artifacts_dir`.
    * ``progress``: show a progress bar when training.
    """
    fam = family()
    p = path(out)
    if p.exists() and not retrain:
        return _load(p, system=fam.system, device="cpu")
    solver = FiniteHorizonSolver(fam.system, TrainConfig.preset("default"), seed=SEED, device="cpu", progress=progress)
    sol = solver.solve(HORIZON)
    p.parent.mkdir(parents=True, exist_ok=True)
    _save(sol, p, seed=SEED)
    return sol


def main(argv=None) -> int:
    """Train and store the family's stage (``python -m pinnhjb.paper.family [--out DIR]``)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--out", type=Path, default=None, help="the artifacts folder (default: artifacts/)")
    args = parser.parse_args(argv)
    sol = load(retrain=True, out=args.out, progress=True)
    print(f"stored {path(args.out)}: E = {sol.metrics['E']:.3e}, {sol.wall_time:.1f} s of training")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
