"""What the benchmark scripts share: the command-line arguments every one of them takes."""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

RESULTS = Path(__file__).resolve().parent / "results"


def parse(parser: argparse.ArgumentParser, argv=None) -> argparse.Namespace:
    """Add ``--seed``, ``--threads``, ``--out`` and ``--no-progress`` to ``parser``, parse ``argv`` and set torch's
    thread count.

    * ``parser``: the script's parser, with its own arguments.
    * ``argv``: the arguments; None: the command line.
    """
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--no-progress", action="store_true")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    return args
