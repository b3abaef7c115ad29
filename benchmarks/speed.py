"""Speed benchmark: time to a target accuracy on the quartic system (T = 4), ours vs the paper's recipe vs DeepXDE.

One run trains, in this one process, one after the other (so every method sees the same machine state):

* ``paper``          the paper's Section 6 recipe (``TrainConfig.preset("paper", system="quartic")``): soft
                     terminal/origin terms, fixed data, inverse-time Adam, T = 0.5 extended to 4 in 0.5 s steps,
                     each stage capped at ``--paper-stage-seconds``. Every ratio is taken against this run.
* ``default``        our default recipe (``TrainConfig.preset("default")``: 3 x 24 tanh in float64, Levenberg-
                     Marquardt on fresh points, stall rule) on an extension chain.
* ``adam_lbfgs``     our first-order recipe (``TrainConfig.preset("adam_lbfgs")``: 3 x 100 in float32, Adam then
                     L-BFGS), same code and chain: the optimiser's share.
* ``deepxde``        DeepXDE (PyTorch backend) in its natural set-up: the whole horizon in one stage on
                     ``GeometryXTime(Hypercube, TimeDomain)`` in reversed time s = T - t, the terminal condition
                     V(x, s=0) = 0 and V(0, s) = 0 soft ``PointSetBC`` s; the total optimiser
                     budget of the ``adam_lbfgs`` chain (8 x Adam steps, then 8 x L-BFGS iterations).
* ``deepxde-chain``  DeepXDE on an extension chain, built by hand with DeepXDE's API: every stage a
                     ``TimePDE`` on [0, step] whose terminal condition is a ``PointSetBC`` with values from the
                     previous stage's ``model.predict`` at its t = 0, warm-started, with ``adam_lbfgs``'s
                     per-stage budget and network (3 x 100).
* ``deepxde-chain-small``  the same DeepXDE chain on our default's network (3 x 24).

Chain step. The paper's recipe runs the paper's chain (T = 0.5 -> 4 in 0.5 s steps). Every other chain method
(``default``, ``adam_lbfgs``, ``deepxde-chain``, ``deepxde-chain-small``) runs once for each step of ``--steps``
(0.5, 1, 2 and 4 s by default, 4 s being one stage; the first stage is one step long, the per-stage budget does not
change with the step), as runs named ``method@step``: the step that reaches a target first differs between
optimisers (a long stage is harder to train), so the best-step table compares every method at its own best step, ours
included. The one-stage ``deepxde`` run gets the 0.5 s chain's whole budget (``deepxde-chain@4`` is one stage with
one stage's budget).

DeepXDE offers first-order optimisers and L-BFGS, not Levenberg-Marquardt, so its runs get the ``adam_lbfgs``
recipe's optimiser settings: inputs scaled to [-1, 1], float32, that recipe's number of fresh flow points per Adam
step, learning rate and cosine decay, then L-BFGS on its number of fixed points; ``paper`` uses the paper's own
network (3 x 250 for this system), data, optimiser and stop rule. E is the horizon check (eq-e), mean over a 101 x 101
grid of Omega of E_e(x)^2 plus V(0)^2, computed for every method by the one function :func:`measure`
(``pinnhjb.metrics``); E is checked after every stage of a chain and every ``--checkpoint-every`` Adam steps /
``--lbfgs-checkpoint-every`` L-BFGS iterations of the one-stage run, with the training clock paused. Times to a
target count training only; set-up (data, cached terminal costs, DeepXDE's data and ``compile``) is reported
apart.

    benchmarks/.venv/bin/python benchmarks/speed.py                        # everything (DeepXDE's venv)
    .venv/bin/python benchmarks/speed.py --methods paper,default --steps 1 # without DeepXDE, 1 s chains
    benchmarks/.venv/bin/python benchmarks/speed.py --budget-scale 0.01 --out /tmp/speed-smoke   # smoke test

Writes ``speed.md`` and ``speed.json`` to ``benchmarks/results/`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
import traceback
from pathlib import Path

import _deepxde as dxd  # benchmarks/_deepxde.py: the scripts run as benchmarks/<name>.py
import torch
from _common import machine

import pinnhjb as ph
from pinnhjb.metrics import infinite_horizon_residual, optimality_errors
from pinnhjb.paper import CASES as PAPER_CASES  # the paper's cases, with its quoted numbers
from pinnhjb.storage import provenance

RESULTS = Path(__file__).resolve().parent / "results"
METHODS = ("paper", "default", "adam_lbfgs", "deepxde", "deepxde-chain", "deepxde-chain-small")
ONE_STAGE = ("deepxde",)  # trains [0, T] at once; every other method but `paper` runs once per chain step
TARGETS = (1e-3, 1.5e-4)
HORIZON, PAPER_STEP = 4.0, 0.5  # the paper's quartic extension run: T = 0.5 -> 4 in 0.5 s steps
STEPS = (0.5, 1.0, 2.0, 4.0)  # chain steps (first stage = one step) given to every chain method but the paper's
N_STAGES = int(round(HORIZON / PAPER_STEP))
# the paper's reported final E at T = 4 (Section 6.2), quoted once in pinnhjb.paper.CASES
PAPER_E_QUARTIC = next(c for c in PAPER_CASES if c.name == "quartic_extension").paper[HORIZON]

DESCRIPTIONS = {
    "paper": "paper's recipe (preset `paper`), {chain}",
    "default": "ours (preset `default`: Levenberg-Marquardt, 3 x 24), {chain}",
    "adam_lbfgs": "ours, first-order (preset `adam_lbfgs`: Adam + L-BFGS, 3 x 100), {chain}",
    "deepxde": "DeepXDE, one stage [0, 4], soft terminal condition, 3 x 100",
    "deepxde-chain": "DeepXDE, {chain} (PointSetBC from predict), 3 x 100",
    "deepxde-chain-small": "DeepXDE, {chain} (PointSetBC from predict), 3 x 24 (our default's network)",
}


def chain_lengths(step: float) -> list[float]:
    """Stage lengths of the chain 0 -> HORIZON in ``step`` s steps (the first stage is one step long)."""
    n = int(round(HORIZON / step))
    if n < 1 or abs(n * step - HORIZON) > 1e-9:
        raise ValueError(f"a chain step must divide T = {HORIZON:g}; got {step:g}")
    return [step] * n


def variants(methods, steps) -> list[tuple[str, str, float | None]]:
    """(run name, method, chain step) of every run, in METHODS order: the paper's recipe on its own 0.5 s chain,
    DeepXDE's one stage once, every other method once per step (run name ``method@step``)."""
    out = []
    for m in METHODS:
        if m not in methods:
            continue
        if m == "paper":
            out.append((m, m, PAPER_STEP))
        elif m in ONE_STAGE:
            out.append((m, m, None))
        else:
            out += [(f"{m}@{s:g}", m, s) for s in steps]
    return out


def describe(method: str, step: float | None) -> str:
    if step is None:
        return DESCRIPTIONS[method]
    chain = f"chain {step:g} -> {HORIZON:g} in {step:g} s steps" if step < HORIZON else f"one stage [0, {HORIZON:g}]"
    return DESCRIPTIONS[method].format(chain=chain)


# ---------------------------------------------------------------------- shared pieces


def measure(system, value_fn) -> dict:
    """E (eq-e, 101 x 101 grid over Omega) and the true errors against V*, mu*: the ONE function used
    for every method. ``value_fn``: batched torch callable x (N, 2) float64 on the CPU -> V(x, 0) (N,),
    differentiable (it moves x to its model's device and back). The grid is made on the CPU whatever the default
    device (DeepXDE's runs on a GPU set it to CUDA)."""
    with torch.device("cpu"):
        out = infinite_horizon_residual(system, value_fn)
        out.update(optimality_errors(system, value_fn))
    return out


def sync():
    """Wait for queued GPU work, so a clock read after it counts that work (no-op on the CPU)."""
    if torch.cuda.is_available() and torch.cuda.is_initialized():
        torch.cuda.synchronize()


def scaled(n: int, scale: float) -> int:
    """A step count times the budget scale (0 stays 0, anything else at least 1)."""
    return 0 if n == 0 else max(1, int(round(n * scale)))


class Clock:
    """Accumulates training wall time between start() and stop()."""

    def __init__(self):
        self.total = 0.0
        self._since = None

    def start(self):
        sync()
        self._since = time.perf_counter()

    def stop(self):
        sync()
        if self._since is not None:
            self.total += time.perf_counter() - self._since
            self._since = None

    @property
    def elapsed(self) -> float:
        return self.total + (time.perf_counter() - self._since if self._since is not None else 0.0)


class Run:
    """One method's record: checkpoints (training time, E, errors), set-up and evaluation times."""

    def __init__(self, name: str):
        self.name = name
        self.trace: list[dict] = []
        self.setup_time = 0.0
        self.train_time = 0.0
        self.eval_time = 0.0
        self.info: dict = {}

    def checkpoint(self, train_time: float, setup_time: float, metrics: dict, **where):
        row = {
            "train_time": float(train_time),
            "train_plus_setup": float(train_time + setup_time),
            "E": float(metrics["E"]),
            "E_boundary": float(metrics["E_boundary"]),
            "value_max_error": float(metrics["value_max_error"]),
            "policy_max_error": float(metrics["policy_max_error"]),
            **where,
        }
        self.trace.append(row)
        where_s = ", ".join(f"{k}={v:g}" if isinstance(v, float) else f"{k}={v}" for k, v in where.items())
        print(
            f"  [{self.name}] {where_s}: E={row['E']:.3e}  max|V-V*|={row['value_max_error']:.3e}  "
            f"train {train_time:.1f} s (+ setup {setup_time:.1f} s)",
            flush=True,
        )

    def time_to(self, target: float, key: str = "train_time") -> float | None:
        for row in self.trace:
            if math.isfinite(row["E"]) and row["E"] <= target:
                return row[key]
        return None

    def final(self) -> dict:
        return self.trace[-1] if self.trace else {}


# ---------------------------------------------------------------------- pinnhjb (paper, default)


class TimedMeasure:
    """The solver's evaluation hook (``FiniteHorizonSolver(..., evaluate=TimedMeasure(system))``): each stage's
    metrics by :func:`measure`, timed (they run outside each stage's training clock, ``history.wall_time``).

    * ``system``: the system the solutions solve.

    ``eval_time`` holds the seconds spent in it so far.
    """

    def __init__(self, system):
        self.system = system
        self.eval_time = 0.0

    def __call__(self, solution) -> dict:
        t0 = time.perf_counter()
        out = measure(self.system, solution.value_function())  # V_T(x, 0), on the networks' device
        self.eval_time += time.perf_counter() - t0
        return out


def pinnhjb_config(method: str, args) -> ph.TrainConfig:
    s = args.budget_scale
    if method == "paper":
        cfg = ph.TrainConfig.preset("paper", system="quartic", max_time=args.paper_stage_seconds * s)
    else:
        cfg = ph.TrainConfig.preset(method)
    return cfg.replace(phases=tuple(p.replace(steps=scaled(p.steps, s)) for p in cfg.phases))


def run_pinnhjb(name: str, method: str, step: float, args, system) -> Run:
    cfg = pinnhjb_config(method, args)
    run = Run(name)
    run.info = {
        "method": method,
        "step": step,
        "config": cfg.to_dict(),
        "stages": len(chain_lengths(step)),
        "horizon": HORIZON,
    }
    timed = TimedMeasure(system)
    solver = ph.FiniteHorizonSolver(
        system, config=cfg, seed=args.seed, device=args.device, progress=False, evaluate=timed
    )
    start = time.perf_counter()

    def on_stage(sol):
        train = sol.wall_time  # sum of the stages' training wall times
        setup = time.perf_counter() - start - train - timed.eval_time
        run.checkpoint(
            train,
            setup,
            sol.metrics,
            T=float(sol.horizon),
            stage=len(sol.stages),
            stop=sol.stages[-1].history.stop_reason,
        )

    sol = solver.solve(step)
    on_stage(sol)
    if step < HORIZON:
        sol = solver.extend(sol, to=HORIZON, step=step, callback=on_stage)
    run.train_time = sol.wall_time
    run.eval_time = timed.eval_time
    run.setup_time = time.perf_counter() - start - run.train_time - run.eval_time
    return run


# ---------------------------------------------------------------------- DeepXDE


class _DdeCheckpoint:
    """Factory for a DeepXDE callback that checks E every ``every`` batches, with the training clock paused."""

    def __new__(cls, dde, every, on_check):
        class Checkpoint(dde.callbacks.Callback):
            def __init__(self):
                super().__init__()
                self.count = 0

            def on_batch_end(self):
                self.count += 1
                if every and self.count % every == 0:
                    on_check()

        return Checkpoint()


def run_deepxde(name: str, method: str, step: float | None, args, system, dde) -> Run:
    """One DeepXDE run, on ``args.device``. DeepXDE puts its nets and data on torch's default device, which its
    import sets to CUDA where there is one (a torch function mode that sees every operation); ``main`` clears that,
    so only DeepXDE's GPU runs are under it, as they would be without us. Its CPU runs are under no mode (one costs
    a small network's thousands of tiny steps much of their time)."""
    with torch.device(args.device) if args.device != "cpu" else contextlib.nullcontext():
        return train_deepxde(name, method, step, args, system, dde)


def train_deepxde(name: str, method: str, step: float | None, args, system, dde) -> Run:
    """One DeepXDE run on the current device (see :func:`run_deepxde`)."""
    cfg = pinnhjb_config("adam_lbfgs", args)  # the budget, optimiser and data sizes of our first-order recipe
    if method == "deepxde-chain-small":
        default = ph.TrainConfig.preset("default")
        cfg = cfg.replace(width=default.width, depth=default.depth, activation=default.activation)
    s = args.budget_scale
    one_stage = method == "deepxde"
    lengths = [HORIZON] if one_stage else chain_lengths(step)
    mult = N_STAGES if one_stage else 1  # the one-stage run gets the whole 0.5 s chain's budget
    adam, lbfgs = cfg.phase("adam"), cfg.phase("lbfgs")
    adam_steps, lbfgs_steps = adam.steps * mult, lbfgs.steps * mult
    every = scaled(args.checkpoint_every, s) if one_stage else 0
    lbfgs_every = scaled(args.lbfgs_checkpoint_every, s) if one_stage else lbfgs_steps
    run = Run(name)
    run.info = {
        "method": method,
        "step": step,
        "deepxde": dde.__version__,
        "stages": len(lengths),
        "horizon": HORIZON,
        "adam_steps": adam_steps,
        "lbfgs_steps": lbfgs_steps,
        "lr": adam.lr,
        "lr_final": adam.lr * adam.lr_final_ratio,
        "flow_points_per_adam_step": cfg.batch_size,
        "lbfgs_points": lbfgs.points,
        "warm_start": not one_stage,
        "checkpoint_every": every,
        "lbfgs_checkpoint_every": lbfgs_every,
        "float": "float32",
        "initializer": "Glorot normal",
        "width": cfg.width,
        "depth": cfg.depth,
    }
    clock = Clock()
    pde = dxd.pde(dde, system)
    nb_adam, nb_lbfgs = dxd.soft_points(cfg, cfg.batch_size), dxd.soft_points(cfg, lbfgs.points)
    start = time.perf_counter()
    net = prev = None
    T_done = 0.0

    def check(**where):
        clock.stop()
        t0 = time.perf_counter()
        metrics = measure(system, dxd.value_fn(net, length))
        run.eval_time += time.perf_counter() - t0
        setup = time.perf_counter() - start - clock.total - run.eval_time
        run.checkpoint(clock.total, setup, metrics, **where)
        clock.start()

    def final_check(**where):
        """A last check when training ended between checkpoints (or L-BFGS stopped early)."""
        last = run.trace[-1] if run.trace else {}
        if (last.get("phase"), last.get("step")) != (where["phase"], where["step"]):
            clock.start()
            check(**where)
            clock.stop()

    for k, length in enumerate(lengths):
        dde.config.set_random_seed(args.seed + k)
        geom = dxd.geometry(dde, system, length)
        net = dxd.network(dde, system, length, cfg.width, cfg.depth, cfg.activation)
        if prev is not None:
            net.load_state_dict(prev.net.state_dict())  # warm start, as our chains
        points = dxd.stage_points(system, cfg, length, prev, lengths[k - 1] if k else None)

        def bcs(nb, batched):
            return dxd.point_bcs(dde, points, nb, batched), 0

        # ---- Adam: batch_size fresh flow points every step (PDEPointResampler), cosine decay as adam_lbfgs.
        t0 = time.perf_counter()
        ic_bcs, n_init = bcs(nb_adam, batched=True)
        data = dde.data.TimePDE(
            geom, pde, ic_bcs, num_domain=cfg.batch_size, num_initial=n_init, train_distribution="pseudo"
        )
        model = dde.Model(data, net)
        model.compile("adam", lr=adam.lr, decay=("cosine", adam_steps, adam.lr * adam.lr_final_ratio), verbose=0)
        resampler = dde.callbacks.PDEPointResampler(period=1, pde_points=True, bc_points=True)
        ckpt = _DdeCheckpoint(dde, every, lambda: check(T=T_done + length, phase="adam", step=ckpt.count))
        run.info.setdefault("setup_per_phase", []).append(time.perf_counter() - t0)
        clock.start()
        model.train(iterations=adam_steps, display_every=adam_steps, callbacks=[resampler, ckpt], verbose=0)
        clock.stop()
        if one_stage and lbfgs_steps == 0:
            final_check(T=T_done + length, phase="adam", step=adam_steps)
        # ---- L-BFGS: lbfgs_points fixed flow points, adam_lbfgs's L-BFGS settings.
        if lbfgs_steps > 0:
            t0 = time.perf_counter()
            ic_bcs, n_init = bcs(nb_lbfgs, batched=False)
            data = dde.data.TimePDE(
                geom, pde, ic_bcs, num_domain=lbfgs.points, num_initial=n_init, train_distribution="pseudo"
            )
            dde.optimizers.set_LBFGS_options(maxcor=50, ftol=1e-15, gtol=1e-12, maxiter=lbfgs_steps)
            # E checkpoints of the one-stage run: DeepXDE calls the callbacks once per torch LBFGS.step, i.e.
            # every ``iter_per_step`` iterations (1000 by default); make that the checkpoint interval.
            # DeepXDE takes a step that advanced exactly one iteration for convergence and stops, and a step also
            # ends at 1.25 x iter_per_step evaluations: keep the interval at 10 or more (only tiny budgets differ).
            per_step = min(lbfgs_steps, max(10, lbfgs_every))
            dde.optimizers.config.LBFGS_options.update(iter_per_step=per_step, fun_per_step=int(per_step * 1.25))
            model = dde.Model(data, net)
            model.compile("L-BFGS", verbose=0)
            lb = _DdeCheckpoint(
                dde,
                1 if one_stage else 0,
                lambda: check(T=T_done + length, phase="lbfgs", step=adam_steps + n_iter(model)),
            )
            run.info["setup_per_phase"].append(time.perf_counter() - t0)
            clock.start()
            model.train(callbacks=[lb], verbose=0)
            clock.stop()
            run.info.setdefault("lbfgs_iterations_done", []).append(n_iter(model))
            if one_stage:
                final_check(T=T_done + length, phase="lbfgs", step=adam_steps + n_iter(model))
        T_done += length
        if not one_stage:
            clock.start()
            check(T=T_done, stage=k + 1)
            clock.stop()
        prev = model
    run.train_time = clock.total
    run.setup_time = time.perf_counter() - start - run.train_time - run.eval_time
    return run


def n_iter(model) -> int:
    state = model.opt.state_dict()["state"]
    return int(state[0]["n_iter"]) if state else 0


# ---------------------------------------------------------------------- tables


def _ratio(a, b, a_total, b_total):
    """Speed-up b/a of a method (time a, or None: not reached within a_total) against the paper (b, b_total)."""
    if a is not None and b is not None and a > 0:
        return b / a, f"{b / a:.2f}"
    if a is not None and b is None and a > 0:
        return None, f"> {b_total / a:.2f}"  # the paper did not get there within its whole budget
    if a is None and b is not None and a_total > 0:
        return None, f"< {b / a_total:.2f}"
    return None, "–"


def summarize(runs: dict, statuses: dict, plan: dict) -> dict:
    """``statuses``/``plan``: run name -> "ok" or why not / (method, chain step), in run order."""
    paper = runs.get("paper")
    targets = list(TARGETS)
    paper_final = paper.final().get("E") if paper and paper.trace else None
    out = {}
    for name, status in statuses.items():
        method, step = plan[name]
        if name not in runs:
            out[name] = {"status": status, "method": method, "step": step}
            continue
        r = runs[name]
        fin = r.final()
        d = {
            "status": status,
            "method": method,
            "step": step,
            "description": describe(method, step),
            "setup_time": r.setup_time,
            "train_time": r.train_time,
            "eval_time": r.eval_time,
            "time_to": {f"{t:g}": r.time_to(t) for t in targets},
            "time_to_including_setup": {f"{t:g}": r.time_to(t, "train_plus_setup") for t in targets},
            "final": {k: fin.get(k) for k in ("E", "E_boundary", "value_max_error", "policy_max_error")},
            "info": r.info,
            "trace": r.trace,
        }
        if paper_final is not None:
            d["time_to_paper_final_E"] = r.time_to(paper_final)
            d["time_to_paper_final_E_including_setup"] = r.time_to(paper_final, "train_plus_setup")
        if paper is not None and paper.trace and name != "paper":
            pf = paper.final()
            ratios = {}
            for t in targets:
                ratios[f"speedup_to_{t:g}"] = _ratio(r.time_to(t), paper.time_to(t), r.train_time, paper.train_time)[1]
            ratios["speedup_to_paper_final_E"] = _ratio(
                r.time_to(paper_final), paper.time_to(paper_final), r.train_time, paper.train_time
            )[1]
            for k in ("E", "value_max_error", "policy_max_error"):
                ratios[f"final_{k}_ratio"] = fin[k] / pf[k] if pf.get(k) else None
            ratios["train_time_ratio"] = r.train_time / paper.train_time if paper.train_time else None
            d["vs_paper"] = ratios
        out[name] = d
    return {"paper_final_E": paper_final, "methods": out, "best": best_steps(out, paper_final)}


def _t(v):
    return "not reached" if v is None else f"{v:.1f}"


def _e(v, spec=".3e"):
    return "–" if v is None else format(v, spec)


def write_tables(summary: dict, meta: dict, out_dir: Path):
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "speed.json").write_text(json.dumps({"meta": meta, **summary}, indent=1))
    methods = summary["methods"]
    pf = summary["paper_final_E"]
    smoke = meta["budget_scale"] != 1.0
    lines = ["# Speed benchmark (generated by `benchmarks/speed.py`; do not edit)", ""]
    if smoke:
        lines += [f"**Reduced budget (`--budget-scale {meta['budget_scale']:g}`): a smoke test, not a result.**", ""]
    if meta.get("runs_done", 0) < meta.get("runs_planned", 0):
        lines += [f"**Interrupted: {meta['runs_done']} of {meta['runs_planned']} planned runs done.**", ""]
    lines += [
        f"Quartic system, T = 4. The paper's recipe runs its own chain (T = 0.5 -> 4 in 0.5 s steps); every other "
        f"chain method runs once per chain step in {', '.join(f'{s:g}' for s in meta['steps'])} s (run "
        "`method@step`; the first stage is one step long, the per-stage budget is the same for every step). "
        f"Machine: {meta['machine']}; "
        f"torch {meta['torch']} ({meta['threads']} thread(s)); DeepXDE {meta['deepxde']}; pinnhjb {meta['pinnhjb']}; "
        f"seed {meta['seed']}; paper recipe capped at {meta['paper_stage_seconds'] * meta['budget_scale']:g} s per "
        f"stage; created {meta['created']}.",
        "",
        "E is the horizon check (the book's eq-e): mean over a 101 x 101 grid of Omega = [-1.2, 1.2]^2 of E_e(x)^2, "
        "plus V(0)^2, "
        "computed by the same function for every method and checked after every stage (chains) or every "
        f"{meta['checkpoint_every']} Adam steps / {meta['lbfgs_checkpoint_every']} L-BFGS iterations (one stage, "
        "before budget scaling), training clock paused. Times are training wall seconds to the first check at "
        "or below the target; set-up is apart. Errors are max over the same grid against V*, mu*.",
        "",
    ]
    pf_head = f"t(E ≤ paper final {pf:.2e}) s" if pf is not None else "t(E ≤ paper final) s"
    lines += [
        f"| method | setup s | training s | t(E ≤ 1e-3) s | t(E ≤ 1.5e-4) s | {pf_head} | final E | "
        "max abs V err | max abs mu err |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for name, d in methods.items():
        if "final" not in d:
            lines.append(f"| {name} | {d['status']} | | | | | | | |")
            continue
        f = d["final"]
        lines.append(
            f"| {name}: {d['description']} | {d['setup_time']:.1f} | {d['train_time']:.1f} | "
            f"{_t(d['time_to']['0.001'])} | {_t(d['time_to']['0.00015'])} | "
            f"{_t(d.get('time_to_paper_final_E'))} | {_e(f['E'])} | {_e(f['value_max_error'])} | "
            f"{_e(f['policy_max_error'])} |"
        )
    lines += [
        "",
        "Against the paper's recipe (speed-up = paper's training time to the target / the method's; "
        "'> x': the paper never got there, x uses its whole budget; '< x': the method never got there):",
        "",
        "| method | speed-up to 1e-3 | speed-up to 1.5e-4 | speed-up to paper's final E | final E ratio | "
        "max abs V err ratio | training time ratio |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, d in methods.items():
        v = d.get("vs_paper")
        if not v:
            continue
        lines.append(
            f"| {name} | {v['speedup_to_0.001']} | {v['speedup_to_0.00015']} | "
            f"{v['speedup_to_paper_final_E']} | {_e(v['final_E_ratio'], '.3g')} | "
            f"{_e(v['final_value_max_error_ratio'], '.3g')} | {_e(v['train_time_ratio'], '.3g')} |"
        )
    lines += [
        "",
        "Including set-up (training + set-up seconds to the target):",
        "",
        "| method | to 1e-3 | to 1.5e-4 | to paper's final E |",
        "|---|---|---|---|",
    ]
    for name, d in methods.items():
        if "final" in d:
            w = d["time_to_including_setup"]
            lines.append(
                f"| {name} | {_t(w['0.001'])} | {_t(w['0.00015'])} | "
                f"{_t(d.get('time_to_paper_final_E_including_setup'))} |"
            )
    lines += best_step_table(summary.get("best", {}), pf)
    lines += ["", f"Paper's reported final E for this run: {PAPER_E_QUARTIC:g} (quoted). Full traces: `speed.json`."]
    (out_dir / "speed.md").write_text("\n".join(lines) + "\n")


def best_run(methods: dict, method: str, time_to):
    """(run name, time) of ``method``'s run that reached a target first (``time_to(run)``: its training time to
    the target, or None), or (its longest run, None) when none did, or (None, None) when it did not run."""
    runs = {n: d for n, d in methods.items() if d.get("method") == method and "final" in d}
    if not runs:
        return None, None
    reached = {n: time_to(d) for n, d in runs.items() if time_to(d) is not None}
    if reached:
        name = min(reached, key=reached.get)
        return name, reached[name]
    return max(runs, key=lambda n: runs[n]["train_time"]), None


def best_steps(methods: dict, pf) -> dict:
    """Target ("0.001", "0.00015", "paper_final_E") -> method -> {"run", "time"}: the method's run that reached the
    target first and its training seconds (time None: no run did; run is then its longest). Stored in speed.json."""
    getters = {f"{t:g}": (lambda d, key=f"{t:g}": d["time_to"][key]) for t in TARGETS}
    if pf is not None:
        getters["paper_final_E"] = lambda d: d.get("time_to_paper_final_E")
    families = [m for m in METHODS if any(d.get("method") == m and "final" in d for d in methods.values())]
    return {
        target: {m: dict(zip(("run", "time"), best_run(methods, m, get))) for m in families}
        for target, get in getters.items()
    }


def best_step_table(best: dict, pf) -> list[str]:
    """``best_steps`` as a table, with our default's speed-up over each method (its time / ours)."""
    if not best or "default" not in next(iter(best.values())):
        return []
    label = {target: f"E ≤ {target}" for target in best}
    if "paper_final_E" in best:
        label["paper_final_E"] = f"E ≤ paper final {pf:.2e}"
    lines = [
        "",
        "Each method at its best chain step for each target (training s, the run that got there first; "
        "speed-up: that time / our default's best time):",
        "",
        "| method | " + " | ".join(label[t] for t in best) + " |",
        "|---|" + "---|" * len(best),
    ]
    for m in next(iter(best.values())):
        cells = []
        for row in best.values():
            name, t = row[m]["run"], row[m]["time"]
            ours = row["default"]["time"]
            if t is None:
                cells.append("not reached")  # the run named is then the longest one, not a winner
            elif m == "default" or ours is None:
                cells.append(f"{t:.1f} ({name})")
            else:
                cells.append(f"{t:.1f} ({name}): {t / ours:.2f}x")
        lines.append(f"| {m} | " + " | ".join(cells) + " |")
    return lines


# ---------------------------------------------------------------------- main


def warm_up(device: str = "cpu") -> float:
    """Pay one-time lazy costs before any clock runs: the first ``torch.optim.Adam`` of a process imports
    torch._dynamo (about 1.5 s here), which would otherwise land in whichever method runs first; on a GPU, the
    CUDA context and the cuBLAS / cuSOLVER handles (a few Levenberg-Marquardt iterations in float64 and float32)."""
    from pinnhjb.gauss_newton import levenberg_marquardt

    t0 = time.perf_counter()
    for dtype in (torch.float64, torch.float32):
        w = torch.randn(5, 4, dtype=dtype, device=device)
        for n in (3, 5):  # fewer and more points than weights: both of its solves
            levenberg_marquardt(
                torch.zeros(4, dtype=dtype, device=device),
                lambda th, a: (a * th).sum() - 1.0,
                lambda k: (w[:k],),
                steps=2,
                points=n,
            )
    net = torch.nn.Sequential(torch.nn.Linear(3, 8), torch.nn.Tanh(), torch.nn.Linear(8, 1)).to(device)
    x = torch.randn(16, 3, requires_grad=True, device=device)
    for opt in (torch.optim.Adam(net.parameters(), lr=1e-3), torch.optim.LBFGS(net.parameters(), max_iter=2)):

        def closure():
            opt.zero_grad()
            (g,) = torch.autograd.grad(net(x).sum(), x, create_graph=True)
            loss = (g**2).mean()
            loss.backward()
            return loss

        opt.step(closure)
    torch.optim.lr_scheduler.LambdaLR(torch.optim.Adam(net.parameters()), lambda k: 1.0)
    sync()
    return time.perf_counter() - t0


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--methods", default=",".join(METHODS), help=f"comma-separated subset of {','.join(METHODS)}")
    p.add_argument(
        "--steps",
        default=",".join(f"{s:g}" for s in STEPS),
        help="chain steps (s) for every chain method but the paper's recipe; each must divide T = 4",
    )
    p.add_argument(
        "--budget-scale",
        type=float,
        default=1.0,
        help="multiplies every step count and time cap (0.01-0.02: a smoke test)",
    )
    p.add_argument(
        "--paper-stage-seconds",
        type=float,
        default=60.0,
        help="wall-clock cap per stage of the paper recipe (its stop rule may never fire)",
    )
    p.add_argument(
        "--checkpoint-every",
        type=int,
        default=500,
        help="Adam steps between E checks in the one-stage DeepXDE run (scaled by --budget-scale)",
    )
    p.add_argument(
        "--lbfgs-checkpoint-every",
        type=int,
        default=100,
        help="L-BFGS iterations between E checks in the one-stage DeepXDE run (scaled)",
    )
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (the same for every method)")
    p.add_argument(
        "--device",
        choices=("cpu", "cuda"),
        default="cpu",
        help="where every method trains (cpu: GPUs are hidden from torch and DeepXDE)",
    )
    p.add_argument("--out", type=Path, default=RESULTS, help="folder for speed.md and speed.json")
    p.add_argument(
        "--rewrite",
        action="store_true",
        help="no training: recompute the derived tables of the run stored in --out/speed.json",
    )
    args = p.parse_args(argv)
    if args.rewrite:
        stored = json.loads((args.out / "speed.json").read_text())
        summary = {"paper_final_E": stored["paper_final_E"], "methods": stored["methods"]}
        summary["best"] = best_steps(summary["methods"], summary["paper_final_E"])
        write_tables(summary, stored["meta"], args.out)
        print((args.out / "speed.md").read_text())
        return 0
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        p.error(f"unknown method(s) {bad}; choose from {','.join(METHODS)}")
    if not args.budget_scale > 0:
        p.error("--budget-scale must be positive")
    try:
        steps = sorted({float(v) for v in args.steps.split(",") if v.strip()})
        for step in steps:
            chain_lengths(step)
    except ValueError as exc:
        p.error(f"--steps: {exc}")
    if not steps:
        p.error("--steps: give at least one chain step")
    if args.device == "cpu":
        os.environ["CUDA_VISIBLE_DEVICES"] = ""  # before DeepXDE's import, which makes CUDA the default device
    elif not torch.cuda.is_available():
        p.error("--device cuda: CUDA is not available on this machine")
    torch.set_num_threads(args.threads)
    system = ph.systems.quartic()

    dde, dde_import, dde_missing = None, None, "not installed"
    if any(m.startswith("deepxde") for m in methods):
        t0 = time.perf_counter()
        dde, dde_missing = dxd.import_deepxde()
        dde_import = time.perf_counter() - t0
        torch.set_num_threads(args.threads)  # in case the import touched it
        torch.set_default_device(None)  # no device mode outside DeepXDE's own GPU runs (run_deepxde)

    warm = warm_up(args.device)
    meta = provenance(
        seed=args.seed,
        threads=torch.get_num_threads(),
        budget_scale=args.budget_scale,
        paper_stage_seconds=args.paper_stage_seconds,
        checkpoint_every=args.checkpoint_every,
        lbfgs_checkpoint_every=args.lbfgs_checkpoint_every,
        methods=methods,
        steps=steps,
        deepxde=(dde.__version__ if dde is not None else "not installed"),
        deepxde_import_seconds=dde_import,
        warm_up_seconds=warm,
        scipy=__import__("scipy").__version__,
        device=args.device,
        machine=machine(args.device),
        targets=list(TARGETS),
        paper_reported_final_E=PAPER_E_QUARTIC,
    )
    runs, statuses, plan = {}, {}, {}
    todo = variants(methods, steps)
    for name, m, step in todo:
        plan[name] = (m, step)
        print(f"== {name}: {describe(m, step)}", flush=True)
        if m.startswith("deepxde") and dde is None:
            statuses[name] = dde_missing
            continue
        try:
            runs[name] = (
                run_deepxde(name, m, step, args, system, dde)
                if m.startswith("deepxde")
                else run_pinnhjb(name, m, step, args, system)
            )
            statuses[name] = "ok"
        except Exception as exc:  # noqa: BLE001 - one failed method must not lose the others' numbers
            traceback.print_exc()
            statuses[name] = f"error: {type(exc).__name__}: {exc}"
        # the tables so far, after every run: an interrupted benchmark keeps what it measured
        write_tables(
            summarize(runs, statuses, plan), {**meta, "runs_done": len(plan), "runs_planned": len(todo)}, args.out
        )
    print((args.out / "speed.md").read_text())
    return 1 if any(s.startswith("error") for s in statuses.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
