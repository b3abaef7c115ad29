"""Command line: ``python -m pinnhjb train|evaluate|reproduce``.

    python -m pinnhjb train pendulum --horizon 1 --extend-to 4 --step 1 --seed 0 --out artifacts/pendulum.pt
    python -m pinnhjb train third_order --param R=0.1 --horizon 0.5 --out r01.pt
    python -m pinnhjb evaluate artifacts/pendulum.pt
    python -m pinnhjb reproduce --seeds 3          # every simulation of the paper -> artifacts/

``train`` saves a checkpoint after every stage (atomic), so an interrupted run keeps its finished stages.
"""
from __future__ import annotations

import argparse
import json
import sys

from .config import TrainConfig
from .solver import FiniteHorizonSolver, SteadyStateSolver
from .storage import load, save
from .systems import SYSTEMS, get_system


def _parse_params(items: list[str]) -> dict:
    params = {}
    for item in items:
        if "=" not in item:
            raise SystemExit(f"--param expects KEY=VALUE; got {item!r}")
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


def _train(args) -> int:
    system = get_system(args.system, **_parse_params(args.param))
    overrides = _parse_params(args.set)
    config = TrainConfig.preset(args.preset, system=args.system, **overrides)
    kw = dict(config=config, seed=args.seed, device=args.device, progress=not args.no_progress)
    if args.steady_state:
        sol = SteadyStateSolver(system, **kw).solve()
        save(sol, args.out, seed=args.seed)
        print(f"steady-state PINN for {system.name}: saved {args.out}")
        _print_metrics(sol.metrics)
        return 0

    def checkpoint(current):
        save(current, args.out, seed=args.seed)
        print(f"T = {current.horizon:g}: E = {current.metrics['E']:.4e}  "
              f"(stage {current.stages[-1].history.wall_time:.1f} s) -> {args.out}", flush=True)

    solver = FiniteHorizonSolver(system, **kw)
    sol = solver.solve(args.horizon)
    checkpoint(sol)
    if args.extend_to is not None and args.extend_to > sol.horizon:
        sol = solver.extend(sol, to=args.extend_to, step=args.step, callback=checkpoint)
        if sol.interrupted:
            print(f"interrupted: {args.out} holds the stages up to T = {sol.horizon:g}", file=sys.stderr)
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
    from .reproduce import run

    if args.tables_only:
        from .reproduce import rewrite_tables

        rewrite_tables(args.out)
        print(f"tables rewritten: {args.out}/results/reproduce.md")
        return 0
    only = args.cases.split(",") if args.cases else None
    result = run(out=args.out, seeds=args.seeds, quick=args.quick, only=only, progress=not args.no_progress)
    print(f"results: {args.out}/results/reproduce.md ({result['meta']['wall_time']:.0f} s)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m pinnhjb", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    t = sub.add_parser("train", help="train a finite-horizon PINN (optionally extended) or the steady-state PINN")
    t.add_argument("system", choices=sorted(k for k in SYSTEMS if k != "lq"))
    t.add_argument("--horizon", type=float, default=1.0, help="first horizon T (Algorithm 1)")
    t.add_argument("--extend-to", type=float, default=None, help="extend the horizon to T' (Theorem 2)")
    t.add_argument("--step", type=float, default=None, help="extension increment (default: one increment)")
    t.add_argument("--steady-state", action="store_true", help="train the direct steady-state PINN instead")
    t.add_argument("--preset", default="default", help="training recipe: default, adam_lbfgs, paper, quick")
    t.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="override a TrainConfig field")
    t.add_argument("--param", action="append", default=[], metavar="KEY=VALUE", help="system parameter, e.g. R=0.1")
    t.add_argument("--seed", type=int, default=0)
    t.add_argument("--device", default=None, help="cpu, cuda, ... (default: CUDA when present)")
    t.add_argument("--out", required=True, help="checkpoint path (.pt)")
    t.add_argument("--no-progress", action="store_true")
    t.set_defaults(func=_train)
    e = sub.add_parser("evaluate", help="print E and the errors of a checkpoint")
    e.add_argument("checkpoint")
    e.add_argument("--points-per-dim", type=int, default=None)
    e.add_argument("--device", default=None)
    e.add_argument("--json", action="store_true")
    e.set_defaults(func=_evaluate)
    r = sub.add_parser("reproduce", help="train and evaluate every simulation of the paper; write artifacts")
    r.add_argument("--quick", action="store_true", help="tiny networks and short chains (a few minutes, for CI)")
    r.add_argument("--seeds", type=int, default=3)
    r.add_argument("--out", default="artifacts", help="folder for checkpoints, reference grids and results")
    r.add_argument("--cases", default=None, help="comma-separated subset of case names")
    r.add_argument("--tables-only", action="store_true", help="rewrite the results tables from stored records")
    r.add_argument("--no-progress", action="store_true")
    r.set_defaults(func=_reproduce)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (KeyError, ValueError, TypeError, RuntimeError, FileNotFoundError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
