"""What the benchmark scripts share: the command-line arguments every one of them takes."""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

from pinnhjb.executor import check

RESULTS = Path(__file__).resolve().parent / "results"


def parse(parser: argparse.ArgumentParser, argv=None) -> argparse.Namespace:
    """Add ``--seed``, ``--threads``, ``--out``, ``--no-progress``, ``--workers`` and ``--scheduler`` to ``parser``,
    parse ``argv``, check where the runs go and set torch's thread count.

    A script hands ``workers=args.workers, scheduler=args.scheduler, threads=args.threads`` to
    :func:`pinnhjb.executor.map_runs`; a wrong ``--workers`` or ``--scheduler`` is a usage error before any run.

    * ``parser``: the script's parser, with its own arguments.
    * ``argv``: the arguments; None: the command line.
    """
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2, help="torch threads (per run, with --workers/--scheduler)")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--no-progress", action="store_true")
    parser.add_argument("--workers", type=int, default=None, metavar="N", help="independent runs in N local processes")
    parser.add_argument(
        "--scheduler", default=None, metavar="tcp://HOST:PORT", help="independent runs on a Dask cluster"
    )
    args = parser.parse_args(argv)
    try:
        check(args.workers, args.scheduler, args.threads)
    except (ImportError, TypeError, ValueError) as exc:
        parser.error(str(exc))
    torch.set_num_threads(args.threads)
    return args
