"""What the benchmark scripts share: the command-line arguments every one of them takes."""

from __future__ import annotations

import argparse
import json
import os
import platform
from pathlib import Path

import numpy as np
import torch

import pinnhjb as ph
from pinnhjb.executor import check
from pinnhjb.optimizers import LevenbergMarquardt

RESULTS = Path(__file__).resolve().parent / "results"
TERMINALS = {"zero": "0 (the paper's)", "lqr": "x'Px (the linearisation's LQR value)"}  # a chain's first terminal cost


def first_terminal_cost(system, name: str) -> np.ndarray | None:
    """The first stage's terminal cost named ``name`` (a key of :data:`TERMINALS`), as ``solve`` takes it: None for
    the paper's 0, the linearisation's LQR matrix P (``system.lqr_value()``, phi = x'Px) for ``"lqr"``."""
    if name not in TERMINALS:
        raise ValueError(f"unknown terminal cost {name!r}; choose from {', '.join(TERMINALS)}")
    return system.lqr_value() if name == "lqr" else None


def parse(parser: argparse.ArgumentParser, argv=None, device: bool = False) -> argparse.Namespace:
    """Add ``--seed``, ``--threads``, ``--out``, ``--no-progress``, ``--workers`` and ``--scheduler`` to ``parser``,
    parse ``argv``, check where the runs go and set torch's thread count.

    A script hands ``workers=args.workers, scheduler=args.scheduler, threads=args.threads`` to
    :func:`pinnhjb.executor.map_runs`; a wrong ``--workers`` or ``--scheduler`` is a usage error before any run.

    * ``parser``: the script's parser, with its own arguments.
    * ``argv``: the arguments; None: the command line.
    * ``device``: also ``--device`` (cpu or cuda: where the networks train); cuda where torch sees no GPU is a
      usage error before any run.
    """
    if device:
        parser.add_argument(
            "--device",
            choices=("cpu", "cuda"),
            default="cpu",
            help="where the networks train (default cpu; cuda: the first GPU, still float64)",
        )
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
    if getattr(args, "device", "cpu") == "cuda" and not torch.cuda.is_available():
        parser.error("--device cuda: CUDA is not available on this machine")
    torch.set_num_threads(args.threads)
    return args


def machine(device: str) -> str:
    """The machine a run trained on, for a results page: the GPU's name and CUDA version with the host, or the
    host's processor, its cores and "CPU"."""
    host = f"{_cpu()}, {os.cpu_count()} cores, {platform.machine()}"
    if device == "cuda":
        return f"{torch.cuda.get_device_name()} (CUDA {torch.version.cuda}), host {host}"
    return f"{host}, CPU"


def _cpu() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def add_lm_arguments(parser: argparse.ArgumentParser, coarse: bool = True) -> None:
    """Add ``--lm-steps``, ``--min-progress``, ``--lm-coarse``, ``--stall-windows`` and ``--adaptive``: the
    Levenberg-Marquardt phase's stopping rule, levels and adaptive share
    (:class:`pinnhjb.optimizers.LevenbergMarquardt`, whose defaults they take), read back by :func:`lm_settings`.

    * ``parser``: the script's parser.
    * ``coarse``: also ``--lm-coarse`` (a script with its own ``--points-coarse`` passes False).
    """
    recipe = LevenbergMarquardt()
    parser.add_argument(
        "--lm-steps", type=int, default=None, help=f"LM iterations per stage at most (default {recipe.steps})"
    )
    parser.add_argument(
        "--min-progress",
        type=lambda a: None if a.lower() == "none" else float(a),
        default=recipe.min_progress,
        help="LM stall rule: a stage stops once its loss fell by less than this factor over --stall-windows windows "
        f"of 10 iterations; none: run --lm-steps (default {recipe.min_progress:g})",
    )
    if coarse:
        parser.add_argument(
            "--lm-coarse",
            type=lambda a: None if a.lower() == "none" else int(a),
            default=False,
            help="LM points per iteration until the loss first stalls (points_coarse); none: the last level's points "
            "throughout (default: the recipe's)",
        )
    parser.add_argument(
        "--stall-windows",
        type=int,
        default=recipe.stall_windows,
        help=f"the windows of the stall rule (default {recipe.stall_windows})",
    )
    parser.add_argument(
        "--adaptive",
        type=float,
        default=recipe.adaptive,
        help="the share of each LM iteration's points chosen where the residual is largest, from "
        f"{recipe.candidates} times as many fresh points (default {recipe.adaptive:g}: all drawn as usual)",
    )


def lm_settings(args) -> dict:
    """The LM phase's fields from :func:`add_lm_arguments`'s arguments (for ``config.with_phase("lm", ...)``)."""
    settings = {"min_progress": args.min_progress, "stall_windows": args.stall_windows}
    if getattr(args, "adaptive", 0.0):
        settings["adaptive"] = args.adaptive
    if getattr(args, "lm_coarse", False) is not False:
        settings["points_coarse"] = args.lm_coarse
    return settings if args.lm_steps is None else {**settings, "steps": args.lm_steps}


def lm_rule(config: dict) -> str:
    """How the stored ``config``'s LM phase stops (and, when set, its share of points chosen by residual), as a
    clause for a results page ("" for the recipe's rule). The points per iteration are not named: the width rule
    sets them per dimension."""
    lm = next(p for p in config["phases"] if p["name"] == "lm")
    parts = []
    if lm.get("adaptive"):
        parts.append(f"{lm['adaptive']:.0%} of each iteration's points chosen where the residual is largest")
    recipe = LevenbergMarquardt()
    if lm.get("min_progress") is None:
        parts.append(f"no stall rule: {lm['steps']} iterations per stage, on the last level's points throughout")
    elif (lm["min_progress"], lm.get("stall_windows"), lm["steps"]) != (
        recipe.min_progress,
        recipe.stall_windows,
        recipe.steps,
    ) or lm.get("points_coarse") is None:
        levels = "" if lm.get("points_coarse") else "the last level's points throughout; "
        parts.append(
            f"{levels}a stage stops once its loss fell by less than {lm['min_progress']:g}x over "
            f"{lm['stall_windows']} windows of 10 iterations, or after {lm['steps']}"
        )
    return f" ({'; '.join(parts)})" if parts else ""


def add_start_arguments(parser: argparse.ArgumentParser, note: str = "") -> None:
    """Add ``--cold-start``, ``--best-start`` and ``--features-start``: how each extension stage starts
    (``TrainConfig.warm_start``), read back by :func:`warm_start_of`.

    * ``parser``: the script's parser.
    * ``note``: a clause added to both helps (for example what the flags mean with ``--resume``).
    """
    parser.add_argument(
        "--cold-start",
        action="store_true",
        help=f"each stage from fresh weights, not the stage before's (TrainConfig.warm_start){note}",
    )
    parser.add_argument(
        "--best-start",
        action="store_true",
        help="each stage trained from the stage before's weights and from fresh ones, the lower E kept "
        f"(TrainConfig.warm_start='best'; twice the training){note}",
    )
    parser.add_argument(
        "--features-start",
        action="store_true",
        help="each stage from the stage before's weights with the last layer zero, so that it starts at its "
        f"terminal cost (TrainConfig.warm_start='features'){note}",
    )


def warm_start_of(parser: argparse.ArgumentParser, args) -> bool | str:
    """``TrainConfig.warm_start`` from :func:`add_start_arguments`'s flags (True when none is given); two given
    are refused through ``parser.error``."""
    given = [flag for flag in ("cold_start", "best_start", "features_start") if getattr(args, flag)]
    if len(given) > 1:
        flags = " and ".join("--" + flag.replace("_", "-") for flag in given)
        parser.error(f"{flags}: choose one")
    return "best" if args.best_start else "features" if args.features_start else not args.cold_start


def add_mean_argument(parser: argparse.ArgumentParser, help: str) -> None:
    """Add ``--mean RUN RUN ...``: the stored runs (their ``--out`` folders) whose chains a mean averages."""
    parser.add_argument("--mean", type=Path, nargs="+", default=None, metavar="RUN", help=help)


def stored_members(parser: argparse.ArgumentParser, args, options: set, page: str, is_mean) -> list[dict]:
    """The stored runs ``--mean`` names (``args.mean``), read and checked before any work: two or more, no flag of
    the training's given (none outside ``options``), an ``--out`` of their own, each a run's ``page`` (its JSON
    record, e.g. ``"dimension.json"``) and not itself a mean (``is_mean(record)``). Returns their records."""
    if len(args.mean) < 2:
        parser.error(f"--mean needs two or more stored runs; got {len(args.mean)}")
    training = sorted(k for k, v in vars(args).items() if k not in options and v != parser.get_default(k))
    if training:
        flags = ", ".join("--" + k.replace("_", "-") for k in training)
        parser.error(f"--mean trains nothing: {flags} would be ignored; its members' runs set them")
    if args.out.resolve() == RESULTS.resolve():
        parser.error(f"--mean: pass --out (a folder other than {RESULTS}, where the main run's page stays)")
    runs = []
    for folder in args.mean:
        stored = folder / page
        if not stored.is_file():
            parser.error(f"--mean: no stored run at {stored}")
        runs.append(json.loads(stored.read_text()))
        if is_mean(runs[-1]):
            parser.error(f"--mean: {folder} is itself a mean; name its members")
    return runs


def one_recipe(parser: argparse.ArgumentParser, folders: list, runs: list[dict], settings) -> None:
    """Refuse, through ``parser.error``, stored runs that are not one recipe run with different seeds: the same
    ``settings(run)`` (a dict of the script's settings a mean's members share) and the same training config
    (``run["meta"]["config"]``, a :class:`ph.TrainConfig` dict), and no seed twice. Both ``--mean`` scripts."""
    first, recipe = settings(runs[0]), ph.TrainConfig.from_dict(runs[0]["meta"]["config"])
    for folder, run in zip(folders[1:], runs[1:]):
        differ = [k for k, v in settings(run).items() if v != first.get(k)]
        if ph.TrainConfig.from_dict(run["meta"]["config"]) != recipe:
            differ.append("the training config (width, points, stall rule, loops, pool size, ...)")
        if differ:
            parser.error(f"--mean: {folder} differs from {folders[0]} in {', '.join(differ)}; a mean is of one recipe")
    seeds = [run["meta"]["seed"] for run in runs]
    if len(set(seeds)) < len(seeds):
        parser.error(f"--mean: the runs must differ in seed; got seeds {seeds}")


def other_attempt(stage, keys: tuple = ()) -> dict | None:
    """With the best start: the attempt a stage did not keep (``Stage.other_attempt``), as its E / E(V = 0) and
    the metrics named in ``keys``; None when the stage's start was not chosen."""
    other = stage.other_attempt
    if other is None:
        return None
    metrics = other["metrics"]
    return {"E_ratio": metrics["E"] / metrics["E_zero"], **{k: metrics[k] for k in keys}}


def loop_budget(sol, x: np.ndarray, v_ref: np.ndarray, count: int, t_final: float = 10.0) -> dict:
    """Where the largest value errors come from: the residual integrated along the learned closed loops
    (:meth:`~pinnhjb.FiniteHorizonSolution.residual_along_loop`) from the ``count`` states of ``x`` with the
    largest ``abs(V - v_ref)``, how much of it accrued outside the training box, how many of those loops leave the
    box and how far each reaches (:meth:`~pinnhjb.systems.ControlAffineSystem.box_reach`, above 1 outside).

    * ``sol``: the trained chain; ``x``: (N, n) states; ``v_ref``: (N,) their reference (or exact) values.
    * ``count``: how many of the largest errors; ``t_final``: the loops' length.

    Errors and integrals are per max ``v_ref``.
    """
    err = sol.value(x) - v_ref
    worst = np.argsort(np.abs(err))[::-1][:count]
    loops = sol.residual_along_loop(x[worst], t_final=t_final)
    return {
        "states": int(worst.size),
        "t_final": t_final,
        "value_error": (err[worst] / v_ref.max()).tolist(),
        "integral": (loops.integral / v_ref.max()).tolist(),
        "share_outside": (loops.integral_outside / loops.integral).tolist(),
        "leave_box": int(loops.outside.any(axis=0).sum()),
        "reach_max": loops.reach.max(axis=0).tolist(),
    }
