"""The 6-D rigid body from the residual alone (issue #18, item 2): true errors against a Pontryagin reference.

:func:`pinnhjb.systems.rigid_body` is the satellite attitude problem of Nakamura-Zimmerer, Gong & Kang (SIAM J.
Sci. Comput. 2021), n = 6, m = 3. No V* is known in closed form, so the reference is
:func:`pinnhjb.reference.reference_points`: one Pontryagin BVP per state at ``--reference-points`` seeded uniform
states of Omega, stored under ``artifacts/reference/`` (made once, then loaded), each checked by re-integrating
its open-loop control (``replay_value`` = ``value``).

* **Infinite horizon (our setting).** The default recipe with ``flat_origin`` (grad V(0, t) = 0 in the ansatz, so
  that the policy is 0 at the origin; ``--no-flat-origin``: without) and ``--loop-share`` of its training states
  along closed loops from Omega (``TrainConfig.loop_share``; 0: all uniform in the training box), widened to
  ``--width``, solves on [0, step] and extends one stage at a time until E / E(V = 0) <= ``--ratio``,
  T = ``--max-horizon`` or ``--max-time`` seconds of training; after each stage: max abs(V - V_ref) / max V_ref
  and the mean relative error of grad V on the reference points. Then the closed loop of the learned policy from
  the first ``--closed-loop`` reference states: the cost to t = inf (J to ``t_final`` plus the LQR tail,
  :func:`pinnhjb.metrics.infinite_horizon_cost`) against V_ref, and whether each run settles (norm of
  x(t_final) < 1e-3). Where the largest value errors accrue: the residual along the closed loops from the
  ``--budget-states`` reference states with the largest errors
  (:meth:`~pinnhjb.solution.FiniteHorizonSolution.residual_along_loop`), the share of its integral accrued
  outside the training box (``--train-scale`` sets that box: Omega enlarged by this factor, one or six numbers).
* **Carried on.** ``--resume DIR`` extends the chain of a stored run (``DIR`` its ``--out``; the chain from its
  ``--artifacts`` or ``--resume-chain``) to ``--max-horizon`` with the same settings (checked before any work),
  but for the start of the stages trained here (``--cold-start``, ``--best-start``) and their LM iterations
  (``--lm-steps``); stage k trains with seed + k as in one uninterrupted run, and the page reports the stored and
  new stages and their wall time as one chain.
* **The mean of chains.** ``--mean RUN RUN ...`` trains nothing: it checks the mean V = (1/K) sum_k V_k
  (:class:`pinnhjb.AveragedSolution`) of the chains of K stored runs of one recipe from different seeds (each
  chain from its run's ``--artifacts``, or ``--mean-chains``) as a run's last stage is checked, and writes it as a
  run whose wall time is the members' training time, summed.
* **Finite horizon (their setting).** T = 20 with terminal cost ``abs(v)^2/2 + abs(w)^2/2``, reached by extension in
  stages of ``--finite-step``; V_20(., 0) against its own reference.

    .venv/bin/python benchmarks/rigid_body.py
    .venv/bin/python benchmarks/rigid_body.py --width 24 --max-horizon 8 --skip-finite --out /tmp/rb
    .venv/bin/python benchmarks/rigid_body.py --mean /tmp/rb /tmp/rb-seed1 --out /tmp/rb-mean

Writes ``rigid_body.md`` and ``rigid_body.json`` (config, seed, versions, wall times) to ``benchmarks/results/``
and the trained chains to ``artifacts/checkpoints/rigid_body_inf/`` and ``rigid_body_T20/`` (``--save``), which
chapter 8 loads.
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings
from pathlib import Path

import numpy as np
from _common import (  # benchmarks/_common.py, a sibling
    TERMINALS,
    add_lm_arguments,
    add_mean_argument,
    add_start_arguments,
    first_terminal_cost,
    lm_rule,
    lm_settings,
    loop_budget,
    machine,
    one_recipe,
    other_attempt,
    parse,
    stored_members,
    warm_start_of,
)

import pinnhjb as ph
from pinnhjb.paper import benchmark_reference_path
from pinnhjb.reference import ReferenceGrid, reference_points
from pinnhjb.storage import provenance

ARTIFACTS = Path(__file__).resolve().parent.parent / "artifacts"
FINITE_T = 20.0
TERMINAL = 0.5 * np.eye(6)  # their terminal cost abs(v)^2/2 + abs(w)^2/2 as x'Px
FLAT = ", grad V(0, t) = 0 built into the ansatz (flat_origin)"
COLD = ", each stage from fresh weights (no warm start)"
BEST = ", each stage trained from the stage before's weights and from fresh ones, the lower E kept (warm_start='best')"
FEATURES = ", each stage from the stage before's weights with the last layer zero (warm_start='features')"
POOL = ph.TrainConfig().pool_size  # the recipe's training states per stage


def reference(system, horizon: float, points: int, seed: int, progress: bool, artifacts: Path) -> ReferenceGrid:
    """The stored reference at ``points`` seeded states (infinite horizon, or T = 20 with their terminal cost);
    computed and saved when missing."""
    path = benchmark_reference_path("rigid_body", horizon, points, artifacts)
    if path.exists():
        ref = ReferenceGrid.load(path)
        if ref.info.get("seed") == seed:
            return ref
    print(f"reference {path.name}: {points} BVPs", flush=True)
    kw = {"t_inf": 20.0} if math.isinf(horizon) else {"horizon": horizon, "terminal_cost": TERMINAL}
    ref = reference_points(system, points, seed=seed, tol=1e-8, progress=progress, **kw)
    ref.save(path)
    return ref


def errors(sol, ref: ReferenceGrid) -> dict:
    """max abs(V - V_ref) / max V_ref and the mean relative error of grad V at the converged reference points."""
    ok = ref.converged
    x, g_ref = ref.points[ok], ref.gradient[ok]
    g = sol.gradient(x)
    rel_g = np.linalg.norm(g - g_ref, axis=1) / np.maximum(np.linalg.norm(g_ref, axis=1), 1e-12)
    return {
        "value_rel_error": float(ref.value_error(sol).max()),
        "grad_mean_rel_error": float(np.mean(rel_g)),
    }


def chain(
    system, config, seed, step, terminal, until, ref, args, every=True, resume=None
) -> tuple[object, list[dict], float]:
    """Solve on [0, step] and extend until ``until(sol, wall)`` holds; a row after every stage, with the errors
    against ``ref`` after every stage (``every``) or after the last only. ``resume``: ``(sol, rows)`` of a stored
    run, extended from its last stage (stage k trains with seed + k, as in one uninterrupted run), its wall time
    carried on."""

    def evaluate(sol):  # with the best start, each attempt's errors too (the one not kept is in Stage.rejected)
        return {**sol.evaluate(config.eval_points_per_dim), **errors(sol, ref)}

    solver = ph.FiniteHorizonSolver(
        system,
        config,
        seed=seed,
        device=args.device,
        progress=not args.no_progress,
        evaluate=evaluate if config.warm_start == "best" else None,
    )
    rows, wall = ([], 0.0) if resume is None else (list(resume[1]), resume[1][-1]["wall_s"])
    with warnings.catch_warnings():  # a late stage can be no better than its terminal cost: that is convergence
        warnings.simplefilter("ignore", RuntimeWarning)
        start = time.perf_counter()
        sol = (
            solver.solve(step, terminal_cost=terminal)
            if resume is None
            else solver.extend(resume[0], to=resume[0].horizon + step)
        )
        while True:
            wall += time.perf_counter() - start
            done = until(sol, wall)
            row = {"T": sol.horizon, "E_ratio": sol.metrics["E"] / sol.metrics["E_zero"], "wall_s": wall}
            history = sol.stages[-1].history  # the stage's LM iterations and why it stopped
            row.update(iterations=history.step[-1] if history.step else 0, stop_reason=history.stop_reason)
            row.update(errors(sol, ref) if every or done else {"value_rel_error": None, "grad_mean_rel_error": None})
            other = other_attempt(sol.stages[-1], ("value_rel_error", "grad_mean_rel_error"))
            if other is not None:  # the best start: which attempt was kept, and the other's E and errors
                row.update(started_warm=sol.stages[-1].started_warm, other=other)
            rows.append(row)
            print(f"  {row}", flush=True)
            if done:
                return sol, rows, wall
            start = time.perf_counter()
            sol = solver.extend(sol, to=sol.horizon + step)


def closed_loop(system, sol, ref: ReferenceGrid, count: int, t_final: float, dt: float) -> dict:
    """The learned policy from the first ``count`` converged reference states: cost to t = inf against V_ref."""
    idx = np.flatnonzero(ref.converged)[:count]
    run = ph.metrics.closed_loop(system, sol.policy, ref.points[idx], t_final=t_final, dt=dt)
    cost, tail = ph.metrics.infinite_horizon_cost(system, run)
    ratio = cost / ref.value[idx]
    return {
        "states": int(idx.size),
        "settled": int(run.stabilized.sum()),
        "cost_ratio_max": float(np.max(ratio)),
        "cost_ratio_mean": float(np.mean(ratio)),
        "tail_share_max": float(np.max(tail / cost)),
        "t_final": t_final,
        "dt": dt,
    }


def budget(sol, ref: ReferenceGrid, count: int, t_final: float = 10.0) -> dict:
    """:func:`_common.loop_budget` over the converged reference states: the residual along the closed loops from
    the ``count`` of them with the largest value errors, and how much of it accrued outside the training box."""
    return loop_budget(sol, ref.points[ref.converged], ref.value[ref.converged], count, t_final)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--width", type=int, default=None, help="the hidden width (default: the recipe's rule, 40 at n = 6)")
    p.add_argument("--points", type=int, default=None, help="LM points per iteration (default: the rule's)")
    p.add_argument("--points-coarse", type=int, default=None, help="LM points at the coarse level (with --points)")
    add_lm_arguments(p, coarse=False)
    p.add_argument("--step", type=float, default=4.0, help="the stage length")
    p.add_argument("--ratio", type=float, default=1e-6, help="stop at E / E(V = 0) <= this")
    p.add_argument("--max-horizon", type=float, default=16.0)
    p.add_argument("--max-time", type=float, default=1800.0, help="stop extending after this many seconds")
    p.add_argument(
        "--terminal",
        choices=tuple(TERMINALS),
        default="lqr",
        help="the first stage's terminal cost: x'Px, the linearisation's LQR value (default), or 0 (the paper's)",
    )
    p.add_argument("--ablation", action="store_true", help="also 3 x 24 chains to T = 8 from both terminal costs")
    p.add_argument(
        "--flat-origin",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="build grad V(0, t) = 0 into the ansatz too (default; without it the learned loops rest off the origin)",
    )
    p.add_argument(
        "--loop-share",
        type=float,
        default=0.3,
        help="share of the training states along the linearisation's LQR loops from Omega (TrainConfig.loop_share)",
    )
    p.add_argument("--loop-time", type=float, default=1.5, help="seconds of loop they are drawn from (loop_time)")
    p.add_argument(
        "--loop-policy",
        choices=ph.config.LOOP_POLICIES,
        default="lqr",
        help="whose loops: the linearisation's LQR policy, or each stage's terminal cost's (loop_policy)",
    )
    p.add_argument(
        "--train-scale",
        type=lambda a: [float(b) for b in a.split(",")],
        default=None,
        help="the training box: Omega enlarged by this factor, one number or six comma-separated (default 1.1)",
    )
    p.add_argument(
        "--pool-size",
        type=int,
        default=None,
        help="training states per stage, each drawn at fresh times (TrainConfig.pool_size; default: the recipe's)",
    )
    p.add_argument("--budget-states", type=int, default=20, help="states of the largest errors for the loop budget")
    p.add_argument("--reference-points", type=int, default=1000)
    p.add_argument("--closed-loop", type=int, default=100, help="initial states of the closed-loop check")
    p.add_argument("--t-final", type=float, default=40.0)
    p.add_argument("--dt", type=float, default=0.01)
    p.add_argument("--finite-step", type=float, default=4.0, help="stage length towards T = 20 (their setting)")
    p.add_argument("--skip-finite", action="store_true")
    add_start_arguments(p, note="; with --resume, the stages trained here")
    p.add_argument("--save", action="store_true", help="store the chains under ARTIFACTS/checkpoints/")
    p.add_argument("--artifacts", type=Path, default=ARTIFACTS, help="where references and checkpoints live")
    p.add_argument("--note", default="", help="a sentence on the conditions of the run, printed under the header")
    p.add_argument(
        "--resume",
        type=Path,
        default=None,
        help="a stored run's --out folder whose chain (its --artifacts, or --resume-chain) this run extends to "
        "--max-horizon, with the same settings; the stages and wall time of both are reported as one chain",
    )
    p.add_argument("--resume-chain", type=Path, default=None, help="the chain --resume extends (default: the run's)")
    add_mean_argument(
        p,
        "train nothing: check the mean (ph.AveragedSolution) of the chains of two or more stored runs (their "
        "--out folders) of one recipe from different seeds as a run is checked; its wall time is theirs, summed",
    )
    p.add_argument(
        "--mean-chains",
        type=Path,
        nargs="+",
        default=None,
        metavar="CHAIN",
        help="the chains --mean averages, one per run, in order (default: each run's, under its --artifacts)",
    )
    args = parse(p, argv, device=True)
    if args.mean is not None:
        return mean_main(p, args)
    if args.mean_chains is not None:
        p.error("--mean-chains goes with --mean")
    warm_start = warm_start_of(p, args)
    if args.budget_states < 1:
        p.error(f"--budget-states must be >= 1; got {args.budget_states}")
    try:
        system = ph.systems.rigid_body(args.train_scale)
    except ValueError as exc:
        p.error(str(exc))
    config = ph.TrainConfig.preset("default", dimension=system.n)
    try:  # every setting checked before the work starts
        if args.width is not None:
            config = config.replace(width=args.width)
        if args.flat_origin:
            config = config.replace(flat_origin=True)
        config = config.replace(warm_start=warm_start)
        config = config.replace(loop_share=args.loop_share, loop_time=args.loop_time, loop_policy=args.loop_policy)
        if args.pool_size is not None:
            config = config.replace(pool_size=args.pool_size)
        if args.points is not None:
            coarse = args.points_coarse or config.phase("lm").points_coarse
            config = config.with_phase("lm", points=args.points, points_coarse=coarse if coarse < args.points else None)
        config = config.with_phase("lm", **lm_settings(args))
    except ValueError as exc:
        p.error(str(exc))
    args.width, args.points = config.width, config.phase("lm").points
    resume = _resumed(p, args, system, config) if args.resume is not None else None
    progress = not args.no_progress  # the arguments are checked: the work starts here
    ref_inf = reference(system, math.inf, args.reference_points, 0, progress, args.artifacts)
    terminal = first_terminal_cost(system, args.terminal)

    def until(sol, wall):
        return (
            sol.metrics["E"] <= args.ratio * sol.metrics["E_zero"]
            or sol.horizon >= args.max_horizon - 1e-9
            or wall >= args.max_time
        )

    print(f"rigid body, infinite horizon: width {args.width}, stages of {args.step:g} s", flush=True)
    sol, rows, wall = chain(system, config, args.seed, args.step, terminal, until, ref_inf, args, resume=resume)
    checked = sol.to("cpu")  # the checks run step by step on a small batch: a GPU only waits there
    loop = closed_loop(system, checked, ref_inf, args.closed_loop, args.t_final, args.dt)
    print(f"  closed loop: {loop}", flush=True)
    loops = budget(checked, ref_inf, args.budget_states)
    print(f"  residual along the loops of the largest errors: {loops}", flush=True)
    result = {"infinite": {"stages": rows, "wall_s": wall, "closed_loop": loop, "budget": loops}}
    if args.ablation:  # what the terminal cost and the width do, on the small network
        small = ph.TrainConfig.preset("default")
        result["ablation"] = {}
        for name in ("zero", "lqr"):
            phi = first_terminal_cost(system, name)
            print(f"ablation: 3 x {small.width}, terminal cost {name}", flush=True)
            _, rows_a, wall_a = chain(
                system, small, args.seed, 2.0, phi, lambda s, w: s.horizon >= 8 - 1e-9, ref_inf, args
            )
            result["ablation"][name] = {"width": small.width, "stages": rows_a, "wall_s": wall_a}
    if args.save:
        ph.save(sol, args.artifacts / "checkpoints" / "rigid_body_inf" / f"seed{args.seed}.pt")
    if not args.skip_finite:
        ref_T = reference(system, FINITE_T, args.reference_points, 0, progress, args.artifacts)
        print(f"rigid body, T = {FINITE_T:g} (their setting), stages of {args.finite_step:g} s", flush=True)
        sol_T, rows_T, wall_T = chain(
            system,
            config,
            args.seed,
            args.finite_step,
            TERMINAL,
            lambda s, w: s.horizon >= FINITE_T - 1e-9,
            ref_T,
            args,
            every=False,
        )
        result["finite"] = {"stages": rows_T, "wall_s": wall_T}
        if args.save:
            ph.save(sol_T, args.artifacts / "checkpoints" / "rigid_body_T20" / f"seed{args.seed}.pt")
    meta = {
        **provenance(),
        "seed": args.seed,
        "threads": args.threads,
        "machine": machine(args.device),
        "args": {k: _plain(v) for k, v in vars(args).items()},
        "config": config.to_dict(),
        "weights": sum(q.numel() for q in sol.stages[0].model.parameters()),
        "reference": {
            "points": int(ref_inf.converged.sum()),
            "wall_s": ref_inf.wall_time,
            "replay_max_rel": ref_inf.replay_error,
        },
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "rigid_body.json").write_text(json.dumps({"meta": meta, **result}))
    (args.out / "rigid_body.md").write_text(table(meta, result, args))
    print(table(meta, result, args))
    return 0


def _plain(value):
    """An argument as JSON stores it: paths, and lists of them (``--mean``), as text."""
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return str(value) if isinstance(value, Path) else value


SAME = ("seed", "step", "terminal", "train_scale", "flat_origin", "device", "threads")  # a resumed run keeps these
MEAN_SAME = ("step", "terminal", "train_scale", "flat_origin", "device")  # the members of a mean share these
# what a mean takes beside --mean: the checks' settings and where things are (none of the training's)
MEAN_OPTIONS = {"mean", "mean_chains", "reference_points", "closed_loop", "t_final", "dt", "budget_states"}
MEAN_OPTIONS |= {"artifacts", "note", "threads", "out", "no_progress"}


def _members(p, args) -> tuple[object, list[dict], list[object]]:
    """The stored runs ``--mean`` names, checked before any work: one recipe (the same training config and
    settings but the seed), different seeds, each chain loaded and ending where its run did, all at one T."""
    runs = stored_members(p, args, MEAN_OPTIONS, "rigid_body.json", lambda run: "members" in run["infinite"])
    if args.mean_chains is not None and len(args.mean_chains) != len(args.mean):
        p.error(f"--mean-chains: one chain per run of --mean ({len(args.mean)}); got {len(args.mean_chains)}")
    one_recipe(p, args.mean, runs, lambda run: {k: run["meta"]["args"].get(k) for k in MEAN_SAME})
    first, seeds = runs[0]["meta"], [run["meta"]["seed"] for run in runs]
    system = ph.systems.rigid_body(first["args"]["train_scale"])
    chains = []
    for i, (folder, run) in enumerate(zip(args.mean, runs)):
        default = Path(run["meta"]["args"]["artifacts"]) / "checkpoints" / "rigid_body_inf" / f"seed{seeds[i]}.pt"
        path = args.mean_chains[i] if args.mean_chains is not None else default
        try:  # on the CPU, where the checks run (step by step on a small batch: a GPU only waits there)
            sol = ph.load(path, system=system, device="cpu")
        except (OSError, ValueError) as exc:
            p.error(f"--mean: cannot load the chain {path} (--mean-chains names the chains): {exc}")
        end = run["infinite"]["stages"][-1]["T"]
        if abs(sol.horizon - end) > 1e-9 or abs(sol.horizon - runs[0]["infinite"]["stages"][-1]["T"]) > 1e-9:
            p.error(
                f"--mean: the chain {path} ends at T = {sol.horizon:g}, its run {folder} at T = {end:g}; "
                f"every chain must end where its run did, all at one T"
            )
        chains.append(sol)
    return system, runs, chains


def mean_main(p, args) -> int:
    """``--mean``: the mean of stored chains, checked as :func:`main` checks a run's last stage (errors, E, closed
    loop, loop budget); written as a run whose one row is the mean's and whose wall time is the members' sum."""
    system, runs, chains = _members(p, args)
    progress = not args.no_progress  # the arguments are checked: the work starts here
    ref = reference(system, math.inf, args.reference_points, 0, progress, args.artifacts)
    recipe = ph.TrainConfig.from_dict(runs[0]["meta"]["config"])
    mean = ph.AveragedSolution(chains)
    start = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ev = mean.evaluate(recipe.eval_points_per_dim)
    wall = sum(run["infinite"]["wall_s"] for run in runs)
    row = {"T": chains[0].horizon, "E_ratio": ev["E"] / ev["E_zero"], "wall_s": wall, "iterations": None}
    row.update(stop_reason=f"mean of {len(chains)}", **errors(mean, ref))
    print(f"  {row}", flush=True)
    loop = closed_loop(system, mean, ref, args.closed_loop, args.t_final, args.dt)
    print(f"  closed loop: {loop}", flush=True)
    loops = budget(mean, ref, args.budget_states)
    members = [
        {
            "run": str(folder),
            "seed": run["meta"]["seed"],
            "machine": run["meta"]["machine"],
            "wall_s": run["infinite"]["wall_s"],
            **{k: run["infinite"]["stages"][-1][k] for k in ("T", "E_ratio", "value_rel_error", "grad_mean_rel_error")},
        }
        for folder, run in zip(args.mean, runs)
    ]
    result = {"infinite": {"stages": [row], "wall_s": wall, "closed_loop": loop, "budget": loops, "members": members}}
    args.device = runs[0]["meta"]["args"]["device"]  # where the members trained (the checks ran on the CPU)
    meta = {
        **provenance(),
        "seed": [m["seed"] for m in members],
        "threads": args.threads,
        "machine": machine("cpu"),
        "args": {k: _plain(v) for k, v in vars(args).items()},
        "config": runs[0]["meta"]["config"],
        "weights": sum(run["meta"]["weights"] for run in runs),
        "reference": {"points": int(ref.converged.sum()), "wall_s": ref.wall_time, "replay_max_rel": ref.replay_error},
        "check_wall_s": time.perf_counter() - start,
    }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "rigid_body.json").write_text(json.dumps({"meta": meta, **result}))
    (args.out / "rigid_body.md").write_text(mean_table(meta, result))
    print(mean_table(meta, result))
    return 0


def _resumed(p, args, system, config) -> tuple[object, list[dict]]:
    """The stored run ``--resume`` names, checked before any work: its chain and its infinite-horizon rows."""
    stored = args.resume / "rigid_body.json"
    if not stored.exists():
        p.error(f"--resume: no stored run at {stored}")
    run = json.loads(stored.read_text())
    if "members" in run["infinite"]:
        p.error(f"--resume: {args.resume} is a mean of chains (--mean), not one chain to carry on")
    if not args.skip_finite or args.ablation:
        p.error("--resume extends the infinite-horizon chain only: pass --skip-finite, not --ablation")
    old, new = run["meta"]["args"], vars(args)
    differ = [k for k in SAME if old.get(k) != new[k]]
    stored_config = ph.TrainConfig.from_dict(run["meta"]["config"])
    # the stored stages' LM iterations and adaptive share, for the page
    args.resumed_lm_steps, args.resumed_adaptive = stored_config.phase("lm").steps, stored_config.phase("lm").adaptive
    # all but the start, the LM iterations and the adaptive share: a chain may go on from fresh weights, with longer
    # stages, or with points chosen by their residual
    new = config.phase("lm")
    stored_config = stored_config.replace(warm_start=config.warm_start).with_phase(
        "lm", steps=new.steps, adaptive=new.adaptive, candidates=new.candidates
    )
    if stored_config != config:
        differ.append("the training config (width, points, stall rule, loops, pool size, ...)")
    if differ:
        p.error(f"--resume: this run's settings differ from the stored run's: {', '.join(differ)}")
    path = args.resume_chain or Path(old["artifacts"]) / "checkpoints" / "rigid_body_inf" / f"seed{args.seed}.pt"
    try:
        sol = ph.load(path, system=system)
    except (OSError, ValueError) as exc:
        p.error(f"--resume: cannot load the chain {path}: {exc}")
    rows = run["infinite"]["stages"]
    if abs(sol.horizon - rows[-1]["T"]) > 1e-9 or sol.horizon >= args.max_horizon - 1e-9:
        p.error(
            f"--resume: the chain ends at T = {sol.horizon:g}, the stored run at T = {rows[-1]['T']:g}; "
            f"--max-horizon ({args.max_horizon:g}) must be beyond both"
        )
    return sol, rows


def _resumed_note(args, config: dict) -> str:
    """The header's clause on ``--resume``: the stored run carried on, with its stages' LM iterations where the
    stages trained here (the stored ``config``'s) have others."""
    if getattr(args, "resume", None) is None:
        return ""
    lm = next(p for p in config["phases"] if p["name"] == "lm")
    steps, share = lm["steps"], lm.get("adaptive", 0.0)
    old = getattr(args, "resumed_lm_steps", steps)
    its = f"; its stages trained {old} LM iterations each, those here {steps}" if old != steps else ""
    old_share = getattr(args, "resumed_adaptive", share)
    if old_share != share:

        def chose(a: float) -> str:
            if not a:
                return "drew each iteration's points as usual"
            return f"chose {a:.0%} of each iteration's points where the residual is largest"

        its += f"; its stages {chose(old_share)}, those here {chose(share)}"
    return f", the stored run `{args.resume}` carried on (its stages, chain and wall time continued here{its})"


def _loops(config: dict) -> str:
    share = config.get("loop_share", 0.0)
    if not share:
        return ""
    whose = {
        "lqr": "the linearisation's LQR loops",
        "terminal": "the loops of each stage's terminal cost's policy (the previous stage's value)",
    }[config.get("loop_policy", "lqr")]
    seconds = config.get("loop_time", 1.5)
    return f", {share:.0%} of the training states along {seconds:g} s of {whose} from Omega (loop_share)"


def _pool(config: dict) -> str:
    """The training states per stage, named when not the recipe's (runs made before the option have the default)."""
    size = config.get("pool_size", POOL)
    return "" if size == POOL else f", {size} training states per stage (pool_size; the recipe's {POOL})"


def _scale(scale) -> str:
    if scale is None:
        return "1.1x"
    if len(set(scale)) == 1:
        return f"{scale[0]:g}x"
    return "(" + ", ".join(f"{a:g}" for a in scale) + ")x per coordinate"


def _budget_lines(b: dict | None) -> list[str]:
    """Where the largest value errors accrue, as a sentence (none for runs made before it was measured)."""
    if not b:
        return []
    share = np.asarray(b["share_outside"]) + 0.0  # no "-0%"
    return [
        f"Residual along the closed loops from the {b['states']} reference states with the largest value errors "
        f"(to t = {b['t_final']:g}; their errors {min(np.abs(b['value_error'])):.1e} to "
        f"{max(np.abs(b['value_error'])):.1e} of max V_ref): {b['leave_box']} of the loops leave the training box; "
        f"the share of the integrated residual accrued outside it is {np.median(share):.0%} (median) and "
        f"{share[:3].min():.0%} to {share[:3].max():.0%} for the three largest errors.",
        "",
    ]


def _time_goal(wall: float, device: str) -> str:
    """The issue's time goal for the device the run trained on, as a row of the goals table."""
    what, limit = ("under 3 minutes on one GPU", 180) if device == "cuda" else ("under 30 minutes on 2 CPU cores", 1800)
    return f"| {what} | {wall:.0f} s | {'yes' if wall <= limit else 'no'} |"


def _loop_line(loop: dict, whose: str) -> str:
    """The closed-loop check of ``whose`` policy (``closed_loop``'s dict) as a sentence of the page."""
    return (
        f"Closed loop of {whose} policy from {loop['states']} reference states (RK4, dt {loop['dt']:g}, to "
        f"t = {loop['t_final']:g}, then the LQR tail): {loop['settled']} of {loop['states']} settle (norm of "
        f"x(t_final) < 1e-3); cost / V_ref: mean {loop['cost_ratio_mean']:.4f}, max {loop['cost_ratio_max']:.4f}."
    )


def _goal_lines(last: dict, loop: dict, wall: float, device: str) -> list[str]:
    """The issue's goals for the rigid body, met or missed by a run's last row and closed loop, as a table."""
    return [
        "| goal (issue #18) | measured | met |",
        "|---|---|---|",
        f"| max abs(V - V_ref) / max V_ref <= 1e-3 | {last['value_rel_error']:.1e} | "
        f"{'yes' if last['value_rel_error'] <= 1e-3 else 'no'} |",
        f"| mean rel. error of grad V <= 1e-2 | {last['grad_mean_rel_error']:.1e} | "
        f"{'yes' if last['grad_mean_rel_error'] <= 1e-2 else 'no'} |",
        f"| all {loop['states']} closed loops settle | {loop['settled']} | "
        f"{'yes' if loop['settled'] == loop['states'] else 'no'} |",
        f"| closed-loop cost within 0.1% of V_ref | max {loop['cost_ratio_max']:.4f} | "
        f"{'yes' if loop['cost_ratio_max'] <= 1.001 else 'no'} |",
        _time_goal(wall, device),
    ]


def mean_table(meta: dict, result: dict) -> str:
    """The page of a ``--mean`` run: its members, the mean's errors and closed loop, and the goals."""
    inf = result["infinite"]
    row, loop, members = inf["stages"][-1], inf["closed_loop"], inf["members"]
    lines = [
        "# The 6-D rigid body: the mean of chains (generated by `benchmarks/rigid_body.py --mean`; do not edit)",
        "",
        f"The mean V = (1/K) sum_k V_k (`ph.AveragedSolution`) of the K = {len(members)} chains below, one recipe "
        f"from seeds {', '.join(str(m['seed']) for m in members)}, each trained by its own stored run (its page "
        f"gives the recipe); nothing is trained here. Its wall time is the members' training time, summed (each on "
        f"its own machine). Checked on {meta['machine']} in {meta['check_wall_s']:.0f} s; torch {meta['torch']}; "
        f"created {meta['created']}. Reference: {meta['reference']['points']} converged Pontryagin BVPs at seeded "
        "uniform states of Omega.",
        *([meta["args"]["note"]] if meta["args"].get("note") else []),
        "",
        "| chain | seed | machine | T | E / E(V = 0) | max abs(V - V_ref) / max V_ref | mean rel. error of grad V "
        "| wall s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for m in members:
        lines.append(
            f"| `{m['run']}` | {m['seed']} | {m['machine']} | {m['T']:g} | {m['E_ratio']:.1e} | "
            f"{m['value_rel_error']:.2e} | {m['grad_mean_rel_error']:.1e} | {m['wall_s']:.0f} |"
        )
    lines += [
        f"| the mean | | | {row['T']:g} | {row['E_ratio']:.1e} | {row['value_rel_error']:.2e} | "
        f"{row['grad_mean_rel_error']:.1e} | {row['wall_s']:.0f} (sum) |",
        "",
        _loop_line(loop, "the mean's"),
        "",
        *_budget_lines(inf.get("budget")),
        *_goal_lines(row, loop, inf["wall_s"], meta["args"]["device"]),
    ]
    return "\n".join(lines) + "\n"


def _start(args) -> str:
    """How the stages trained here started, for the page's header."""
    start = BEST if args.best_start else COLD if args.cold_start else FEATURES if args.features_start else ""
    return f"{start} from here on" if start and args.resume else start


def _kept(row: dict) -> str:
    """The best start's choice for one stage: the start kept, and the E ratio and value error of the other."""
    if "started_warm" not in row:
        return ""
    other = row["other"]
    kept = "warm" if row["started_warm"] else "fresh"
    return f"{kept} ({other['E_ratio']:.1e}, {other['value_rel_error']:.1e})"


def table(meta: dict, result: dict, args) -> str:
    """The results as a markdown page: the stages, the closed loop, and the issue's goals met or missed."""
    inf, loop = result["infinite"], result["infinite"]["closed_loop"]
    last = inf["stages"][-1]
    lines = [
        "# The 6-D rigid body from the residual alone (generated by `benchmarks/rigid_body.py`; do not edit)",
        "",
        f"Default recipe with a 3 x {args.width} network ({meta['weights']} weights), {args.points} LM points per "
        f"iteration{lm_rule(meta['config'])}{FLAT if args.flat_origin else ''}"
        f"{_start(args)}{_loops(meta['config'])}"
        f"{_pool(meta['config'])}{_resumed_note(args, meta['config'])}, "
        f"stages of {args.step:g} s from the terminal cost {TERMINALS[args.terminal]}, trained on Omega enlarged "
        f"{_scale(args.train_scale)}, seed {args.seed}, {args.threads} thread(s), {meta['machine']}; "
        f"torch {meta['torch']}; created {meta['created']}. Reference: "
        f"{meta['reference']['points']} converged Pontryagin BVPs at seeded uniform states of Omega "
        f"({meta['reference']['wall_s']:.0f} s to compute; their open-loop controls re-integrated give the same "
        f"cost to {meta['reference']['replay_max_rel']:.0e}).",
        *([args.note] if args.note else []),
        "",
        "## Infinite horizon",
        "",
        "| T | E / E(V = 0) | max abs(V - V_ref) / max V_ref | mean rel. error of grad V | wall s (cumulative) | "
        "LM iterations (stop) | start kept (the other's E ratio, value error) |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in inf["stages"]:
        lines.append(
            f"| {r['T']:g} | {r['E_ratio']:.1e} | {r['value_rel_error']:.1e} | {r['grad_mean_rel_error']:.1e} | "
            f"{r['wall_s']:.0f} | {r['iterations']} ({r['stop_reason']}) | {_kept(r)} |"
        )
    lines += [
        "",
        _loop_line(loop, "the last stage's"),
        "",
        *_budget_lines(inf.get("budget")),
        *_goal_lines(last, loop, inf["wall_s"], args.device),
    ]
    if "ablation" in result:
        lines += [
            "",
            "## What the terminal cost does (3 x 24 network, stages of 2 s)",
            "",
            "| first terminal cost | T | E / E(V = 0) | max abs(V - V_ref) / max V_ref | mean rel. error of grad V |",
            "|---|---|---|---|---|",
        ]
        for name, abl in result["ablation"].items():
            for r in abl["stages"]:
                lines.append(
                    f"| {TERMINALS[name]} | {r['T']:g} | {r['E_ratio']:.1e} | {r['value_rel_error']:.1e} | "
                    f"{r['grad_mean_rel_error']:.1e} |"
                )
    if "finite" in result:
        lines += [
            "",
            f"## Finite horizon T = {FINITE_T:g} (their setting: terminal cost abs(v)^2/2 + abs(w)^2/2)",
            "",
            "| T | E / E(V = 0) | max abs(V_T - V_T,ref) / max V_T,ref at t = 0 | mean rel. error of grad V_T | "
            "wall s (cumulative) |",
            "|---|---|---|---|---|",
        ]
        for r in result["finite"]["stages"]:
            errs = [f"{r[k]:.1e}" if r[k] is not None else "-" for k in ("value_rel_error", "grad_mean_rel_error")]
            lines.append(f"| {r['T']:g} | {r['E_ratio']:.1e} | {errs[0]} | {errs[1]} | {r['wall_s']:.0f} |")
        lines += [
            "",
            f"Only the chain at T = {FINITE_T:g} is their problem, so only it is compared with the reference.",
        ]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())
