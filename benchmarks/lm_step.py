"""Cost of one Levenberg-Marquardt step against the number of weights P: the step in weight space (J'J, P x P)
against the step in sample space (JJ', N x N; Woodbury), on the 6-D rigid body (issue #18, item 1).

One step of :func:`pinnhjb.gauss_newton.levenberg_marquardt` is: the structured Jacobian J (N x P) of the flow
residual (:meth:`pinnhjb.residuals.FiniteHorizonHJB.jacobian`), then one damped solve, by Cholesky, in the smaller
of the two spaces::

    weight space:  (J'J + lambda I) delta = -J'r          about N P^2 + P^3 / 3 flops
    sample space:  delta = -J'(JJ' + lambda I)^{-1} r     about N^2 P + N^3 / 3 flops: linear in P

This script times the three parts for 3 x width networks (P from about 1300 to 20000) at fixed N, the solves
interleaved, and fits the exponent of each against P (log-log). The weight-space solve is skipped above
``--max-primal`` weights.

    .venv/bin/python benchmarks/lm_step.py [--points 1500] [--widths 24,40,64,96] [--repeats 3]

A second table times the parts of one step in the rigid body's best setting (``--setting-width`` 48,
``--setting-points`` 6400, ``flat_origin``; more points than weights, so the weight-space solve): the Jacobian by
``vmap(jacrev)`` of the per-point residual against the structured one (with its mixed derivative at the origin),
J'J as one product against :func:`pinnhjb.gauss_newton.gram`'s upper blocks, and one Cholesky factorisation.

Writes ``results/lm_step.md`` and ``results/lm_step.json`` (median ms, config, versions).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np
import torch
from _common import parse  # benchmarks/_common.py: the scripts run as benchmarks/<name>.py
from torch.func import jacrev, vmap

import pinnhjb as ph
from pinnhjb.gauss_newton import FlatParameters, gram
from pinnhjb.pinn import FiniteHorizonValue
from pinnhjb.residuals import FiniteHorizonHJB
from pinnhjb.storage import provenance


def timed(fn, repeats: int) -> tuple[float, object]:
    """Median ms of ``repeats`` calls of ``fn`` and its last result."""
    times, out = [], None
    for _ in range(repeats):
        start = time.perf_counter()
        out = fn()
        times.append(1e3 * (time.perf_counter() - start))
    return statistics.median(times), out


def solve(G: torch.Tensor, rhs: torch.Tensor, lam: float = 1e-3) -> torch.Tensor:
    """The Cholesky solve of (G + lam I) y = rhs, as in the LM step."""
    chol = torch.linalg.cholesky(G + lam * torch.eye(G.shape[0], dtype=G.dtype))
    return torch.cholesky_solve(rhs.unsqueeze(-1), chol).squeeze(-1)


def problem(system, width: int, points: int, seed: int, flat_origin: bool = False):
    """A 3 x width network on the system, its residual form, weights and one batch of ``points`` points."""
    torch.manual_seed(seed)
    model = FiniteHorizonValue(system.n, 2.0, system.train_domain, width=width, depth=3, flat_origin=flat_origin).to(
        torch.float64
    )
    residual = FiniteHorizonHJB(system, model)
    flat = FlatParameters(model.net)
    box = torch.as_tensor(system.train_domain, dtype=torch.float64)
    x = box[:, 0] + (box[:, 1] - box[:, 0]) * torch.rand(points, system.n, dtype=torch.float64)
    t = 2.0 * torch.rand(points, dtype=torch.float64)
    args = (x, t, torch.zeros_like(x), system.f(x), system.g(x), system.Q(x))
    return residual, flat, flat.get(), args


def measure(system, width: int, points: int, repeats: int, max_primal: int, seed: int) -> dict:
    """J, the sample-space solve and (up to ``max_primal`` weights) the weight-space solve for one width."""
    residual, _, theta, args = problem(system, width, points, seed)
    jacobian = residual.jacobian()
    jac_ms, (r, J) = timed(lambda: jacobian(theta, *args), repeats)
    P = theta.numel()
    dual_ms, primal_ms = [], []
    for _ in range(repeats):  # interleaved, so both see the same machine state
        start = time.perf_counter()
        dual = -(J.T @ solve(J @ J.T, r))
        dual_ms.append(1e3 * (time.perf_counter() - start))
        if P <= max_primal:
            start = time.perf_counter()
            primal = -solve(J.T @ J, J.T @ r)
            primal_ms.append(1e3 * (time.perf_counter() - start))
    row = {"width": width, "weights": P, "points": points, "jacobian_ms": jac_ms, "dual_ms": statistics.median(dual_ms)}
    if primal_ms:
        row["primal_ms"] = statistics.median(primal_ms)
        # the same damped step both ways (Woodbury), to rounding
        row["step_agreement"] = float((primal - dual).norm() / dual.norm())
    print(row, flush=True)
    return row


def setting(system, width: int, points: int, repeats: int, seed: int) -> dict:
    """The parts of one weight-space step with ``flat_origin``, each timed both ways (median ms)."""
    residual, flat, theta, args = problem(system, width, points, seed, flat_origin=True)
    point = residual.point_residual(flat)
    dims = (None,) + (0,) * len(args)
    plain_ms, J_plain = timed(lambda: vmap(jacrev(point), in_dims=dims)(theta, *args), repeats)
    jacobian = residual.jacobian()
    structured_ms, (_, J) = timed(lambda: jacobian(theta, *args), repeats)
    product_ms, G_plain = timed(lambda: J.T @ J, repeats)
    blocks_ms, G = timed(lambda: gram(J), repeats)
    chol_ms, _ = timed(lambda: torch.linalg.cholesky(G + 1e-3 * torch.eye(G.shape[0], dtype=G.dtype)), repeats)
    row = {
        "width": width,
        "weights": theta.numel(),
        "points": points,
        "jacobian_jacrev_ms": plain_ms,
        "jacobian_structured_ms": structured_ms,
        "jacobian_difference": float((J - J_plain).abs().max() / J_plain.abs().max()),
        "gram_product_ms": product_ms,
        "gram_blocks_ms": blocks_ms,
        "gram_difference": float((G - G_plain).abs().max() / G_plain.abs().max()),
        "cholesky_ms": chol_ms,
    }
    print(row, flush=True)
    return row


def exponent(rows: list[dict], key: str) -> float | None:
    """The slope of log(time) against log(weights); None below two rows."""
    sel = [r for r in rows if key in r]
    if len(sel) < 2:
        return None
    return float(np.polyfit(np.log([r["weights"] for r in sel]), np.log([r[key] for r in sel]), 1)[0])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--points", type=int, default=1500, help="N, the points of one step")
    p.add_argument("--widths", default="24,40,64,96")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--max-primal", type=int, default=9000, help="skip the weight-space solve above this many weights")
    p.add_argument("--setting-width", type=int, default=48, help="the second table's width")
    p.add_argument("--setting-points", type=int, default=6400, help="the second table's points")
    args = parse(p, argv)
    if min(args.points, args.repeats, args.setting_width, args.setting_points) < 1:
        p.error("--points, --repeats, --setting-width and --setting-points must be positive")
    system = ph.systems.rigid_body()
    rows = [
        measure(system, int(w), args.points, args.repeats, args.max_primal, args.seed)
        for w in args.widths.split(",")
        if w
    ]
    fits = {k: exponent(rows, k) for k in ("jacobian_ms", "dual_ms", "primal_ms")}
    best = setting(system, args.setting_width, args.setting_points, args.repeats, args.seed)
    meta = {**provenance(), "seed": args.seed, "threads": args.threads, "points": args.points, "repeats": args.repeats}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "lm_step.json").write_text(json.dumps({"meta": meta, "rows": rows, "exponents": fits, "setting": best}))
    lines = [
        "# Cost of one Levenberg-Marquardt step against the weights (generated by `benchmarks/lm_step.py`; do not "
        "edit)",
        "",
        f"The 6-D rigid body, 3 x width tanh networks in float64, N = {args.points} points, median of {args.repeats}; "
        f"{args.threads} thread(s), CPU; torch {meta['torch']}; created {meta['created']}.",
        "",
        "| width | weights P | Jacobian ms | sample-space solve ms (N x N) | weight-space solve ms (P x P) | "
        "relative difference of the two steps |",
        "|---|---|---|---|---|---|",
    ]
    for r in rows:
        primal = f"{r['primal_ms']:.0f}" if "primal_ms" in r else "skipped"
        agree = f"{r['step_agreement']:.0e}" if "step_agreement" in r else "-"
        lines.append(
            f"| {r['width']} | {r['weights']} | {r['jacobian_ms']:.0f} | {r['dual_ms']:.0f} | {primal} | {agree} |"
        )
    lines.append("")
    for key, name in (("jacobian_ms", "Jacobian"), ("dual_ms", "sample-space solve"), ("primal_ms", "weight-space")):
        if fits[key] is not None:
            lines.append(f"- {name}: time grows like P^{fits[key]:.2f} (least squares on log-log).")
    b = best
    lines += [
        "",
        f"One weight-space step's parts in the rigid body's best setting: 3 x {b['width']} ({b['weights']} weights), "
        f"N = {b['points']} points, grad V(0, t) = 0 built into the ansatz (flat_origin), median of {args.repeats}.",
        "",
        "| part | one way ms | the other ms | ratio | largest relative difference |",
        "|---|---|---|---|---|",
        f"| Jacobian: vmap(jacrev), structured | {b['jacobian_jacrev_ms']:.0f} | {b['jacobian_structured_ms']:.0f} | "
        f"{b['jacobian_jacrev_ms'] / b['jacobian_structured_ms']:.1f} | {b['jacobian_difference']:.0e} |",
        f"| J'J: one product, upper blocks (`gram`) | {b['gram_product_ms']:.0f} | {b['gram_blocks_ms']:.0f} | "
        f"{b['gram_product_ms'] / b['gram_blocks_ms']:.2f} | {b['gram_difference']:.0e} |",
        f"| Cholesky of J'J + lambda I | {b['cholesky_ms']:.0f} | - | - | - |",
    ]
    (args.out / "lm_step.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
