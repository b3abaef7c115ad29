"""Command line: ``python -m pinnhjb train|evaluate|reproduce``.

    python -m pinnhjb train pendulum --horizon 1 --extend-to 4 --step 1 --seed 0 --out artifacts/pendulum.pt
    python -m pinnhjb train third_order --param R=0.1 --horizon 0.5 --out r01.pt
    python -m pinnhjb train quartic --preset adam_lbfgs --set adam.steps=500 --set lbfgs=off --out q.pt
    python -m pinnhjb evaluate artifacts/pendulum.pt
    python -m pinnhjb reproduce --seeds 3          # every simulation of the paper -> artifacts/
    python -m pinnhjb reproduce --workers 4        # the same, 4 runs at a time (or --scheduler tcp://HOST:8786)

``train`` checks its arguments and that ``--out`` can be written before training, then saves a checkpoint after
every stage (atomic), so an interrupted or failing run keeps its finished stages; a diverged stage is an error
(exit 2), never a saved untrained network.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import math
import os
import sys
import tempfile
from pathlib import Path

from .config import TrainConfig
from .solver import MAX_STAGES_PER_CALL, FiniteHorizonSolver, SteadyStateSolver
from .storage import load, save
from .systems import SYSTEMS, get_system


def _parse_params(items: list[str], option: str = "--param") -> dict:
    params = {}
    for item in items:
        if "=" not in item:
            raise SystemExit(f"{option} expects KEY=VALUE; got {item!r}")
        key, value = item.split("=", 1)
        try:
            params[key] = json.loads(value)
        except json.JSONDecodeError:
            params[key] = value
    return params


def _print_metrics(metrics: dict, stream=None):
    stream = sys.stdout if stream is None else stream
    for key, value in metrics.items():
        print(f"  {key:>18s} = {value:.6g}" if isinstance(value, float) else f"  {key:>18s} = {value}", file=stream)


class UsageError(ValueError):
    """A command-line argument that is wrong or contradicts another (exit status 2)."""


def _check_out(out: str) -> Path:
    """``--out`` must be a file path we can write: not an existing folder, in a folder that exists and is
    writable or can be created. Checked before any training."""
    path = Path(out)
    if path.is_dir():
        raise UsageError(f"--out {out}: is an existing folder; give a checkpoint file path such as {path / 'run.pt'}")
    parent = path.parent
    ancestor = parent
    while not ancestor.exists() and ancestor != ancestor.parent:
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise UsageError(f"--out {out}: cannot create a file there: {ancestor} is not a folder")
    if ancestor == parent:
        try:
            fd, probe = tempfile.mkstemp(prefix=".pinnhjb-write-check.", dir=parent)
            os.close(fd)
            os.unlink(probe)
        except OSError as exc:
            raise UsageError(f"--out {out}: the folder {parent} is not writable ({exc.strerror or exc})") from None
    elif not os.access(ancestor, os.W_OK | os.X_OK):
        raise UsageError(f"--out {out}: cannot create the folder {parent}: {ancestor} is not writable")
    return path


def _system(args):
    params = _parse_params(args.param)
    builder = SYSTEMS[args.system]
    known = [k for k in inspect.signature(builder).parameters]
    for key, value in params.items():
        if key not in known:
            raise UsageError(
                f"--param {key}={value}: system {args.system} has no parameter {key!r} "
                f"(its parameters: {', '.join(known) or 'none'})"
            )
    try:
        return get_system(args.system, **params)
    except (TypeError, ValueError) as exc:
        given = " ".join(f"--param {k}={v}" for k, v in params.items())
        raise UsageError(f"{given}: {exc}") from None


def _config(args, dimension: int | None = None) -> TrainConfig:
    """The preset with every ``--set``: ``FIELD=VALUE`` for a TrainConfig field, ``PHASE.FIELD=VALUE`` for a field
    of the optimiser phase named PHASE (``adam``, ``lbfgs``, ``lm``), ``PHASE=off`` to drop that phase."""
    overrides = _parse_params(args.set, "--set")
    fields = {k: v for k, v in overrides.items() if "." not in k and v != "off"}
    try:
        config = TrainConfig.preset(args.preset, system=args.system, dimension=dimension, **fields)
    except TypeError as exc:  # an unknown field
        raise UsageError(
            f"--set: {exc} (TrainConfig fields: {', '.join(TrainConfig.__dataclass_fields__)}; a phase's field: "
            f"PHASE.FIELD=VALUE, e.g. lm.steps=100)"
        ) from None
    except ValueError as exc:
        raise UsageError(f"--set / --preset: {exc}") from None
    for key, value in overrides.items():
        try:
            if "." in key:
                name, field = key.split(".", 1)
                config = config.with_phase(name, **{field: value})
            elif value == "off":
                config = config.without_phase(key)
        except KeyError as exc:
            raise UsageError(f"--set {key}={value}: {exc.args[0]}") from None
        except ValueError as exc:
            raise UsageError(f"--set {key}={value}: {exc}") from None
    return config


def _check_horizons(args):
    if args.steady_state:
        given = [
            flag
            for flag, value in (("--horizon", args.horizon), ("--extend-to", args.extend_to), ("--step", args.step))
            if value is not None
        ]
        if given:
            raise UsageError(
                f"--steady-state trains the direct steady-state PINN, which has no horizon: drop {', '.join(given)}"
            )
        return
    args.horizon = 1.0 if args.horizon is None else args.horizon
    for flag, value in (("--horizon", args.horizon), ("--extend-to", args.extend_to), ("--step", args.step)):
        if value is not None and not (math.isfinite(value) and value > 0):
            raise UsageError(f"{flag} must be a positive finite number; got {value:g}")
    if args.step is not None and args.extend_to is None:
        raise UsageError(f"--step {args.step:g} is the increment of an extension: give --extend-to as well")
    if args.extend_to is not None:
        if not args.extend_to > args.horizon:
            raise UsageError(f"--extend-to {args.extend_to:g} must exceed --horizon {args.horizon:g}")
        step = args.extend_to - args.horizon if args.step is None else args.step
        if (args.extend_to - args.horizon) / step - 1e-9 > MAX_STAGES_PER_CALL:
            raise UsageError(
                f"--step {step:g} from --horizon {args.horizon:g} to --extend-to {args.extend_to:g} "
                f"would train more than {MAX_STAGES_PER_CALL} stages; choose a larger step"
            )


def _train(args) -> int:
    out = _check_out(args.out)
    _check_horizons(args)
    system = _system(args)
    config = _config(args, system.n)
    kw = dict(config=config, seed=args.seed, device=args.device, progress=not args.no_progress)
    if args.steady_state:
        sol = SteadyStateSolver(system, **kw).solve()
        save(sol, out, seed=args.seed)
        print(f"steady-state PINN for {system.name}: saved {out}")
        _print_metrics(sol.metrics)
        return 0
    saved = []

    def checkpoint(current):
        save(current, out, seed=args.seed)
        saved[:] = [current.horizon]
        print(
            f"T = {current.horizon:g}: E = {current.metrics['E']:.4e}  "
            f"(stage {current.stages[-1].history.wall_time:.1f} s) -> {out}",
            flush=True,
        )

    solver = FiniteHorizonSolver(system, **kw)
    try:
        sol = solver.solve(args.horizon)
    except KeyboardInterrupt:
        print("interrupted during the first stage: nothing to save", file=sys.stderr)
        return 130
    try:
        try:
            checkpoint(sol)
        except KeyboardInterrupt:  # inside the first save: the stage trained, keep it
            sol = dataclasses.replace(sol, interrupted=True)
        if args.extend_to is not None and not sol.interrupted:
            sol = solver.extend(sol, to=args.extend_to, step=args.step, callback=checkpoint)
    except Exception as exc:
        if saved:
            exc.add_note(f"{out} holds the stages up to T = {saved[0]:g}")
        raise
    if sol.interrupted:
        # a Ctrl-C inside a save leaves the file one stage behind: write what was returned, flagged interrupted
        save(sol, out, seed=args.seed)
        print(f"interrupted: {out} holds the stages up to T = {sol.horizon:g}", file=sys.stderr)
        return 130
    _print_metrics(sol.metrics)
    return 0


def _evaluate(args) -> int:
    sol = load(args.checkpoint, device=args.device)
    metrics = sol.evaluate(args.points_per_dim)
    kind = f"T = {sol.horizon:g}" if hasattr(sol, "horizon") else "steady state"
    print(f"{args.checkpoint}: system {sol.system.name}, {kind}")
    _print_metrics(metrics)
    stored = sol.metrics
    if args.json:
        print(json.dumps({"metrics": metrics, "stored": stored}, indent=1))
    return 0


def _reproduce(args) -> int:
    from .executor import check
    from .paper.reproduce import run

    if args.seeds < 1:
        raise UsageError(f"--seeds must be at least 1 (seeds 0 .. N-1 are run); got {args.seeds}")

    if args.tables_only:
        from .paper.tables import rewrite_tables

        rewrite_tables(args.out)
        print(f"tables rewritten: {args.out}/results/reproduce.md")
        return 0
    only = args.cases.split(",") if args.cases else None
    try:
        check(args.workers, args.scheduler, args.threads)
    except ImportError as exc:
        raise UsageError(str(exc)) from None
    except (TypeError, ValueError) as exc:
        raise UsageError(f"--workers / --scheduler / --threads: {exc}") from None
    result = run(
        out=args.out,
        seeds=args.seeds,
        quick=args.quick,
        only=only,
        progress=not args.no_progress,
        workers=args.workers,
        scheduler=args.scheduler,
        threads=args.threads,
    )
    print(f"results: {args.out}/results/reproduce.md ({result['meta']['wall_time']:.0f} s)")
    return 0


def _points_per_dim(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 2; got {text!r}") from None
    if value < 2:
        raise argparse.ArgumentTypeError(f"expected an integer >= 2 (points per axis of the grid); got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``python -m pinnhjb`` (sub-commands train, evaluate, reproduce)."""
    p = argparse.ArgumentParser(prog="python -m pinnhjb", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train", help="train a finite-horizon PINN (optionally extended) or the steady-state PINN")
    t.add_argument("system", choices=sorted(k for k in SYSTEMS if k != "lq"))
    t.add_argument("--horizon", type=float, default=None, help="first horizon T (Algorithm 1; default 1)")
    t.add_argument("--extend-to", type=float, default=None, help="extend the horizon to T' (Theorem 2)")
    t.add_argument("--step", type=float, default=None, help="extension increment (default: one increment)")
    t.add_argument("--steady-state", action="store_true", help="train the direct steady-state PINN instead")
    t.add_argument("--preset", default="default", help="training recipe: default, adam_lbfgs, paper, quick")
    t.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a TrainConfig field (width=32), a field of an optimiser phase (adam.steps=500, "
        "lm.points=2000) or drop a phase (lbfgs=off); repeatable",
    )
    t.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="system parameter, e.g. R=0.1")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--device", default=None, help="cpu, cuda, ... (default: CUDA when present)")
    t.add_argument("--out", required=True, help="checkpoint path (.pt)")
    t.add_argument("--no-progress", action="store_true")
    t.set_defaults(func=_train)
    e = sub.add_parser("evaluate", help="print E and the errors of a checkpoint")
    e.add_argument("checkpoint")
    e.add_argument(
        "--points-per-dim",
        type=_points_per_dim,
        default=None,
        help="grid points per axis of Omega for E (an integer >= 2; default: the book's grid)",
    )
    e.add_argument("--device", default=None)
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=_evaluate)
    r = sub.add_parser("reproduce", help="train and evaluate every simulation of the paper; write artifacts")
    r.add_argument("--quick", action="store_true", help="tiny networks and short chains (a few minutes, for CI)")
    r.add_argument("--seeds", type=int, default=3)
    r.add_argument("--out", default="artifacts", help="folder for checkpoints, reference grids and results")
    r.add_argument("--cases", default=None, help="comma-separated subset of case names")
    r.add_argument("--tables-only", action="store_true", help="rewrite the results tables from stored records")
    r.add_argument(
        "--workers", type=int, default=None, metavar="N", help="train the (case, seed) runs in N local processes"
    )
    r.add_argument(
        "--scheduler",
        default=None,
        metavar="tcp://HOST:PORT",
        help="train the runs on a Dask cluster (`dask scheduler`, then `dask worker tcp://HOST:PORT` on each "
        "machine; every worker must see --out at the same path); not with --workers",
    )
    r.add_argument(
        "--threads",
        type=int,
        default=None,
        metavar="N",
        help="torch threads per run (default: 1 per worker; serially, torch's own). Same seeds give bit-identical "
        "weights serially and in workers at the same thread count",
    )
    r.add_argument("--no-progress", action="store_true")
    r.set_defaults(func=_reproduce)
    return p


def main(argv=None) -> int:
    """Run the command line; the exit status (0 success, 2 an error in the arguments or in training, 130 interrupted).

    * ``argv``: the arguments; None: ``sys.argv[1:]``.
    """
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except (KeyError, ValueError, TypeError, RuntimeError, ArithmeticError, OSError) as exc:
        notes = "".join(f"\n{note}" for note in getattr(exc, "__notes__", []) if "partial_solution" not in note)
        print(f"error: {exc}{notes}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
