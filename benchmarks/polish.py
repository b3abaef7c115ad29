"""Does a last pass on the steady-state HJB polish a trained chain?

A chain's value V0 = V_T(., 0) misses V* by a correction c = V* - V0. Put V0 + c into the steady-state HJB
:eq:`eq-hjb`: c solves an HJB of its own, min_u H(x, grad V0 + grad c) = 0, which is that of a derived system,
f' = f + g mu0 (the learned closed loop), the same g and R, and the state cost Q' = E_e(x; V0), the learned value's
residual :eq:`eq-ee`. Its cost has either sign and f'(0) = g(0) mu0(0) need not vanish, so it is no control problem
(``_Correction`` skips those checks), but near c = 0 the stabilising solution is the one nearby: a network started
at c = 0 (its last layer zero) and trained on it by the default recipe (``train_steady_state``, Levenberg-Marquardt)
should find it, where V0 is close. This script measures whether it does, and what it gains:

* the LQ ladder at n = 6 (``results/repeats/ladder-n6-best-start-seed1``'s chain): the polish after each of its
  stages, and from V0 = 0 without a chain (the direct steady-state PINN of chapter 1), errors against the exact V*
  on the states of ``dimension.py`` (seed 1, that run's);
* the rigid body: the main chain after each stage and the wider-box chain
  (``results/repeats/rigid-body-no-stall-width-48-box``) after its last, errors against the BVP reference.

    .venv/bin/python benchmarks/polish.py [--threads 2] [--out benchmarks/results/repeats/polish]

Writes ``polish.md`` and ``polish.json`` (rows, config, seed, versions, wall times) to ``--out``. Chapter 9
(section 4) reads them.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch
from _common import machine
from dimension import FunctionValue, true_errors
from index import where
from rigid_body import errors

import pinnhjb as ph
from pinnhjb import paper
from pinnhjb.paper import dimension_states
from pinnhjb.pinn import SteadyStateValue, gradient
from pinnhjb.storage import provenance
from pinnhjb.training import train_steady_state

HERE = Path(__file__).resolve().parent
LADDER = HERE / "results" / "repeats" / "ladder-n6-best-start-seed1"
RIGID = {  # stored rigid-body run -> its chain (seed 0)
    "main": "rigid_body_inf",
    "rigid-body-no-stall-width-48-box": "rigid_body_inf_no_stall_w48_box",
}


class _Correction(ph.ControlAffineSystem):
    """The derived system of the correction: its cost is a residual, of either sign, and f'(0) = g(0) mu0(0)."""

    def _check_functions(self):
        pass


def correction_system(system, v0) -> ph.ControlAffineSystem:
    """f' = f + g mu0, g, Q' = E_e(.; V0), R: the correction c = V* - V0 solves its steady-state HJB."""

    def grad0(x):
        return gradient(v0, x)[1].detach()

    def f(x):
        u0 = system.policy_from_gradient(x, grad0(x))
        return system.f(x) + torch.einsum("nij,nj->ni", system.g(x), u0)

    def q(x):
        return system.hamiltonian_min(x, grad0(x)).detach()

    return _Correction(
        f"{system.name} correction", f, system.g, q, R=system.R, domain=system.domain, train_domain=system.train_domain
    )


def polish(system, v0, config, seed: int):
    """Train the correction network on the derived system of V0 (a batched callable); returns V0 + c (another),
    the wall time and the training history."""
    torch.manual_seed(seed)  # the first weights; the training points come from their own generator
    model = SteadyStateValue(system.n, system.train_domain, width=config.width, depth=config.depth).double()
    with torch.no_grad():  # c = 0 at the start: V0 itself
        last = [m for m in model.net.modules() if isinstance(m, torch.nn.Linear)][-1]
        last.weight.zero_()
        last.bias.zero_()
    tic = time.perf_counter()
    history = train_steady_state(correction_system(system, v0), model, config, seed=seed, progress=False)
    wall = time.perf_counter() - tic

    def value(x):
        return v0(x) + model(x)

    return value, wall, history


def measures(system, fn, x, errors_of) -> dict:
    """The errors of V = ``fn`` as its benchmark measures them (``errors_of``: :func:`dimension.true_errors` or
    :func:`rigid_body.errors` on a :class:`dimension.FunctionValue`), and E / E(V = 0) on the states x (the mean of
    E_e^2 over that of Q^2, :func:`pinnhjb.metrics.infinite_horizon_residual`'s ``E_flow / E_zero``)."""
    out = errors_of(FunctionValue(fn))
    check = ph.metrics.infinite_horizon_residual(system, fn, points=x)
    ratio = check["E_flow"] / check["E_zero"]
    return {"value": out["value_rel_error"], "grad": out["grad_mean_rel_error"], "E_ratio": ratio}


def row(name, system, sol, k, config, seed, x, errors_of, trained_on: str) -> dict:
    """The chain's first k stages, measured, polished and measured again; one row of the results.

    * ``name``: the row's name; ``system``: the chain's system; ``sol``: the chain.
    * ``k``: how many of its stages; 0: no chain, V0 = 0 (chapter 1's direct steady-state PINN, with the same
      network and recipe).
    * ``config``, ``seed``: the polish's recipe and seed.
    * ``x``, ``errors_of``: the error states and the benchmark's errors there (:func:`measures`).
    * ``trained_on``: where the chain trained (``index.where``).
    """
    v0 = sol.truncated(k).value_function() if k else (lambda z: torch.zeros(z.shape[0], dtype=z.dtype))
    before = measures(system, v0, x, errors_of)
    fn, wall, history = polish(system, v0, config, seed)
    after = measures(system, fn, x, errors_of)
    train_s = sol.truncated(k).wall_time if k else 0.0  # every attempt of its stages, on its own machine
    horizon = sol.stages[k - 1].end if k else 0.0
    out = dict(case=name, T=horizon, chain_train_s=train_s, chain_machine=trained_on, polish_s=wall)
    out["stop"] = history.stop_reason
    out.update({f"chain_{key}": val for key, val in before.items()})
    out.update({f"polished_{key}": val for key, val in after.items()})
    print(
        f"{name} T = {horizon:g}: value {before['value']:.2e} -> {after['value']:.2e}, "
        f"E/E0 {before['E_ratio']:.1e} -> {after['E_ratio']:.1e}, {wall:.0f} s",
        flush=True,
    )
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    p.add_argument(
        "--seed", type=int, default=0, help="seeds the polish's first weights and training points (default 0)"
    )
    p.add_argument("--out", type=Path, default=HERE / "results" / "repeats" / "polish", help="where to write")
    args = p.parse_args(argv)
    if args.threads < 1:
        p.error(f"--threads must be at least 1; got {args.threads}")
    if args.seed < 0:
        p.error(f"--seed must be a non-negative integer; got {args.seed}")
    torch.set_num_threads(args.threads)
    start = time.perf_counter()
    rows = []

    ladder_run = json.loads((LADDER / "dimension.json").read_text())
    ladder_seed = ladder_run["meta"]["seed"]
    system = ph.systems.lq_ladder(3)
    sol = ph.load(LADDER / "chains" / "lq_ladder-n6-default.pt", system=system)
    config = ph.TrainConfig.preset("default", dimension=system.n)
    x = dimension_states(system, 4096, ladder_seed)

    def exact(value):  # against V* on the ladder run's states, as dimension.py measures
        return true_errors(system, value, 4096, ladder_seed)

    for k in range(len(sol.stages) + 1):
        rows.append(row("lq_ladder n = 6", system, sol, k, config, args.seed, x, exact, where(ladder_run["meta"])))

    ref = paper.benchmark_reference("rigid_body")
    ok = np.asarray(ref.converged, dtype=bool)
    x = torch.as_tensor(ref.points[ok])

    def against_reference(value):  # as rigid_body.py measures
        return errors(value, ref)

    for run_name, folder in RIGID.items():
        run = paper.benchmark_run(name="rigid_body") if run_name == "main" else paper.benchmark_run(run_name)
        system = ph.systems.rigid_body(train_scale=run["meta"]["args"].get("train_scale"))
        sol = ph.load(paper.checkpoint_path(paper.artifacts_dir(), folder, 0), system=system)
        config = ph.TrainConfig.preset("default", dimension=system.n)
        stages = range(1, len(sol.stages) + 1) if run_name == "main" else [len(sol.stages)]
        name, trained_on = f"rigid body ({run_name})", where(run["meta"])
        for k in stages:  # the main chain after each stage, the other after its last
            rows.append(row(name, system, sol, k, config, args.seed, x, against_reference, trained_on))

    wall = time.perf_counter() - start
    meta = provenance(
        config=ph.TrainConfig.preset("default", dimension=6).to_dict(),
        seed=args.seed,
        threads=args.threads,
        machine=machine("cpu"),
        wall_s=wall,
        ladder_chain=str(LADDER.relative_to(HERE.parent)),
    )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "polish.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    lines = [
        "# A last pass on the steady-state HJB (generated by `benchmarks/polish.py`; do not edit)",
        "",
        f"The correction c = V* - V0 of each chain, trained on its own steady-state HJB by the default recipe "
        f"(3 x {meta['config']['width']}, Levenberg-Marquardt with its stall rule, c = 0 at the start), seed "
        f"{args.seed}, {args.threads} thread(s), {meta['machine']}; torch {torch.__version__}; created "
        f"{meta['created']}; {wall:.0f} s in all. Value error: max abs(V - V*) / max V*; gradient: mean relative "
        f"error; both against the exact V* (ladder) or the BVP reference (rigid body), on the same states as the "
        f"chain's benchmark.",
        "",
        "The chain's training is every attempt of its stages up to T (both starts where it tried both), timed on its",
        "own machine (last column); the polish's is this run's.",
        "",
        "| chain | T | chain's training s | value error | polished | gradient error | polished | E / E(V = 0) | "
        "polished | polish s | the chain trained on |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['case']} | {r['T']:g} | {r['chain_train_s']:.0f} | {r['chain_value']:.2e} | "
            f"{r['polished_value']:.2e} | {r['chain_grad']:.2e} | {r['polished_grad']:.2e} | "
            f"{r['chain_E_ratio']:.1e} | {r['polished_E_ratio']:.1e} | {r['polish_s']:.0f} | {r['chain_machine']} |"
        )
    (args.out / "polish.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
