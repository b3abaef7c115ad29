"""Error and cost against the state dimension n, from the residual alone (issue #18, items 3 and 4, in part).

Systems with an exact V* (:mod:`pinnhjb.systems`): the LQ ladder ``lq_ladder(k)`` (n = 2k, V* by CARE) and the
nonlinear ``converse(n)`` (V* in closed form). For each, the default recipe solves on [0, step] and extends one
stage at a time (``solve_until``) until E / E(V = 0) <= ``--ratio`` or ``--max-horizon``; then the true errors of
the value are measured on ``--points`` seeded uniform states of Omega:

* max abs(V - V*) / max V* and the mean relative error of grad V;
* the training wall time, and a least-squares exponent of wall time against n (log-log) per family.

    .venv/bin/python benchmarks/dimension.py                       # n = 2, 4, 8 (ladder and converse)
    .venv/bin/python benchmarks/dimension.py --ladder 2,4 --converse 4 --out /tmp/dim

Writes ``dimension.md`` and ``dimension.json`` (config, seed, versions, wall times) to ``benchmarks/results/``.
"""

from __future__ import annotations

import argparse
import json
import time
import warnings

import numpy as np
import torch
from _common import parse  # benchmarks/_common.py: the scripts run as benchmarks/<name>.py

import pinnhjb as ph
from pinnhjb.storage import provenance


def true_errors(system, sol, points: int, seed: int) -> dict:
    """max abs(V - V*) / max V* and the mean relative error of grad V over seeded uniform states of Omega."""
    gen = torch.Generator().manual_seed(seed)
    box = torch.as_tensor(system.domain, dtype=torch.float64)
    x = box[:, 0] + (box[:, 1] - box[:, 0]) * torch.rand(points, system.n, generator=gen, dtype=torch.float64)
    v_star = system.value_star(x)
    xg = x.clone().requires_grad_(True)
    (g_star,) = torch.autograd.grad(system.value_star(xg).sum(), xg)
    v = torch.as_tensor(sol.value(x.numpy()))
    g = torch.as_tensor(sol.gradient(x.numpy()))
    rel_g = (g - g_star).norm(dim=-1) / g_star.norm(dim=-1).clamp_min(1e-12)
    return {
        "value_rel_error": float((v - v_star).abs().max() / v_star.abs().max()),
        "grad_mean_rel_error": float(rel_g.mean()),
    }


def run(system, args, step: float) -> dict:
    solver = ph.FiniteHorizonSolver(system, "default", seed=args.seed, device="cpu", progress=not args.no_progress)
    start = time.perf_counter()
    with warnings.catch_warnings():  # a late stage can be no better than its terminal cost: that is convergence
        warnings.simplefilter("ignore", RuntimeWarning)
        sol = solver.solve(step)
        zero = sol.metrics["E_zero"]
        while sol.metrics["E"] > args.ratio * zero and sol.horizon < args.max_horizon - 1e-9:
            sol = solver.extend(sol, to=sol.horizon + step)
    wall = time.perf_counter() - start
    row = {
        "system": system.name,
        "n": system.n,
        "m": system.m,
        "weights": sum(p.numel() for p in sol.stages[0].model.parameters()),  # the first has no terminal network
        "T": sol.horizon,
        "step": step,
        "stages": len(sol.stages),
        "E_ratio": sol.metrics["E"] / zero,
        "wall_s": wall,
        **true_errors(system, sol, args.points, args.seed),
    }
    print(
        f"{system.name} n={system.n}: T={row['T']:g} E/E0={row['E_ratio']:.1e} "
        f"V err={row['value_rel_error']:.1e} grad err={row['grad_mean_rel_error']:.1e} {row['wall_s']:.0f} s",
        flush=True,
    )
    return row


def exponent(rows: list[dict]) -> float | None:
    """The slope of log(wall time) against log(n) by least squares; None below two points."""
    if len(rows) < 2:
        return None
    return float(np.polyfit(np.log([r["n"] for r in rows]), np.log([r["wall_s"] for r in rows]), 1)[0])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--ladder", default="2,4,8", help="state dimensions n of the LQ ladder (even)")
    p.add_argument("--converse", default="2,4,8", help="state dimensions n of the converse system (even)")
    p.add_argument("--step", type=float, default=2.0, help="the stage length (the ladder)")
    p.add_argument("--converse-step", type=float, default=0.5, help="the stage length of the converse system")
    p.add_argument("--ratio", type=float, default=1e-6, help="stop at E / E(V = 0) <= this")
    p.add_argument("--max-horizon", type=float, default=8.0)
    p.add_argument("--points", type=int, default=4096, help="uniform states of Omega for the true errors")
    args = parse(p, argv)
    sizes = {
        "lq_ladder": [int(n) for n in args.ladder.split(",") if n],
        "converse": [int(n) for n in args.converse.split(",") if n],
    }
    if any(n % 2 for ns in sizes.values() for n in ns):
        p.error("every n must be even (the ladder has n = 2k; the converse system m = n/2 inputs)")
    rows = [run(ph.systems.lq_ladder(n // 2), args, args.step) for n in sizes["lq_ladder"]]
    rows += [run(ph.systems.converse(n), args, args.converse_step) for n in sizes["converse"]]
    meta = {
        **provenance(),
        "seed": args.seed,
        "threads": args.threads,
        "step": args.step,
        "converse_step": args.converse_step,
        "ratio": args.ratio,
        "max_horizon": args.max_horizon,
        "points": args.points,
        "config": ph.TrainConfig.preset("default").to_dict(),
    }
    fits = {name: exponent([r for r in rows if r["system"] == name]) for name in sizes}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "dimension.json").write_text(json.dumps({"meta": meta, "rows": rows, "exponents": fits}))
    lines = [
        "# Error and cost against the dimension (generated by `benchmarks/dimension.py`; do not edit)",
        "",
        f"The default recipe (one network per system), stages of {args.step:g} s (the converse system "
        f"{args.converse_step:g} s: its open loop is fast and unstable) until E / E(V = 0) <= "
        f"{args.ratio:g} or T = {args.max_horizon:g}, seed {args.seed}, {args.threads} thread(s), CPU; torch "
        f"{meta['torch']}; created {meta['created']}. Errors against the exact V* on {args.points} seeded uniform "
        "states of Omega.",
        "",
        "| system | n | m | weights | step | T | E / E(V = 0) | max abs(V - V*) / max V* | mean rel. error of grad V | "
        "wall s (training and measuring E) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['system']} | {r['n']} | {r['m']} | {r['weights']} | {r['step']:g} | {r['T']:g} | "
            f"{r['E_ratio']:.1e} | {r['value_rel_error']:.1e} | {r['grad_mean_rel_error']:.1e} | {r['wall_s']:.0f} |"
        )
    lines.append("")
    for name, slope in fits.items():
        if slope is not None:
            lines.append(f"Wall time against n, {name}: exponent {slope:.2f} (least squares on log-log).")
    (args.out / "dimension.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
