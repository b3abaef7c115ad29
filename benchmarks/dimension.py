"""Error and cost against the state dimension n, from the residual alone (issue #18, items 3 and 4).

Systems with an exact V* (:mod:`pinnhjb.systems`): the LQ ladder ``lq_ladder(k)`` (n = 2k, V* by CARE) and the
nonlinear ``converse(n)`` (V* in closed form). For each, the default recipe solves on [0, step] and extends one
stage at a time (``solve_until``) until E / E(V = 0) <= ``--ratio`` or ``--max-horizon``; then the true errors of
the value are measured on ``--points`` seeded uniform states of Omega:

* max abs(V - V*) / max V* and the mean relative error of grad V;
* the training wall time, and a least-squares exponent of wall time against n (log-log) per family;
* for the default recipe, where its largest errors come from (``--budget-states``: the residual along their
  learned closed loops, inside the training box or not) and, for each stage after the first, how much of its
  error it carried from its terminal cost (``carried``); ``--save`` stores its chains. ``--train-scale``,
  ``--flat-origin`` and ``--cold-start`` or ``--best-start`` change its training box, its ansatz and its warm
  start;
* **Carried on.** ``--resume DIR`` extends the chains a run saved (``DIR`` its ``--out``, with ``--save``: every
  stage is saved as it ends, so a run cut short counts too) to ``--max-horizon``, with the same settings (checked
  before any work), its stages and wall time continued;
* **The mean of chains.** ``--mean RUN RUN ...`` trains nothing: it measures the mean V = (1/K) sum_k V_k
  (:class:`pinnhjb.AveragedSolution`) of the chains K stored runs of one recipe saved (``--save``; the runs differ
  in seed alone), on the states of every member's seed, and writes it as a run whose rows are the mean's (the worst
  of those states) and whose wall time is its members' summed;
* at the dimensions ``--compare``, our first-order recipe ``adam_lbfgs`` and DeepXDE beside the default, on both
  systems. DeepXDE (``deepxde``) is the chain a user would build with its API (:mod:`_deepxde`: 3 x 100 in float32,
  ``adam_lbfgs``'s Adam and L-BFGS budgets a stage, soft conditions), extended with the same stages and the same
  stopping rule on E as ours; it runs in the benchmarks' own environment (``benchmarks/.venv``, see
  ``requirements-deepxde.txt``), and its rows read "not installed" elsewhere.

Every (system, n, recipe) is an independent run: ``--workers N`` runs N at a time in local processes and
``--scheduler tcp://HOST:PORT`` on a Dask cluster (:func:`pinnhjb.executor.map_runs`), with the same rows as a
serial run at the same ``--threads``.

    .venv/bin/python benchmarks/dimension.py                       # ladder n = 2 ... 16, converse n = 2 ... 12
    .venv/bin/python benchmarks/dimension.py --ladder 2,4 --converse 4 --compare "" --out /tmp/dim
    .venv/bin/python benchmarks/dimension.py --mean RUN RUN --out /tmp/dim-mean   # runs saved with --save
    benchmarks/.venv/bin/python benchmarks/dimension.py --ladder 6 --converse 6 --against deepxde --width 24 \
        --max-horizon 8 --workers 2 --threads 1 --out benchmarks/results/repeats/deepxde-n6  # DeepXDE, its venv

Writes ``dimension.md``, ``dimension.json`` (config, seed, versions, wall times) and the figure
``dimension.png`` (error and wall time against n) to ``benchmarks/results/``.
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings
from pathlib import Path

import _deepxde as dxd  # benchmarks/_deepxde.py: the scripts run as benchmarks/<name>.py
import numpy as np
import torch
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
from pinnhjb.executor import map_runs
from pinnhjb.metrics import infinite_horizon_residual
from pinnhjb.paper import dimension_rows, dimension_states
from pinnhjb.pinn import gradient
from pinnhjb.storage import provenance


def true_errors(system, sol, points: int, seed: int) -> dict:
    """max abs(V - V*) / max V* and the mean relative error of grad V over seeded uniform states of Omega."""
    x = dimension_states(system, points, seed)
    v_star, g_star = (t.detach() for t in gradient(system.value_star, x))
    v = torch.as_tensor(sol.value(x.numpy()))
    g = torch.as_tensor(sol.gradient(x.numpy()))
    rel_g = (g - g_star).norm(dim=-1) / g_star.norm(dim=-1).clamp_min(1e-12)
    return {
        "value_rel_error": float((v - v_star).abs().max() / v_star.abs().max()),
        "grad_mean_rel_error": float(rel_g.mean()),
    }


def carried(errors: list[np.ndarray], k: int) -> float | None:
    """How much of stage k's error is its terminal cost's, state by state: the correlation of V - V* after stage k
    with V - V* after stage k - 1 (its terminal cost), ``errors[j - 1]`` being V - V* after stage j on the states
    of :func:`true_errors`. Near 1: the stage hands its terminal cost's error on where it sits, where an exact stage
    would move it to where the optimal loops have gone by then. None for the first stage."""
    return None if k < 2 else float(np.corrcoef(errors[k - 1], errors[k - 2])[0, 1])


def horizon_floor(system, horizon: float, points: int, seed: int) -> float | None:
    """For a linear system (the LQ ladder), the error that the horizon alone leaves over the states of
    :func:`true_errors` (:func:`pinnhjb.lq.horizon_gap`: the exact V_T(., 0) from the zero terminal cost against
    V*); None for a nonlinear system (no exact V_T)."""
    if system.builder != "lq_ladder":
        return None
    A, B, Q = system.linearize()
    return ph.lq.horizon_gap(A, B, Q, system.R, horizon, dimension_states(system, points, seed).numpy())


BUILDERS = {  # (n, train_scale) -> the system; train_scale None: the builder's box (Omega enlarged 1.25x)
    "lq_ladder": lambda n, scale=None: ph.systems.lq_ladder(n // 2, scale),
    "converse": lambda n, scale=None: ph.systems.converse(n, scale),
}
RECIPES = ("default", "adam_lbfgs", "deepxde")  # pinnhjb's presets, and DeepXDE


def _start_kept(stage) -> dict:
    """With the best start (``warm_start="best"``): the start a stage kept and the other attempt's E ratio."""
    other = other_attempt(stage)
    return {} if other is None else {"started_warm": stage.started_warm, "other_E_ratio": other["E_ratio"]}


def chain_name(system, recipe: str) -> str:
    """The file a run's chain is saved to under ``OUT/chains/`` (``--save``) and resumed from (``--resume``)."""
    return f"{system.name}-n{system.n}-{recipe}.pt"


def run(task: dict) -> dict:
    """One (system, n, recipe) run: train by extension until the E bound or the horizon cap, then the true errors.

    * ``task``: ``system`` (a key of :data:`BUILDERS`), ``n``, ``recipe`` (one of :data:`RECIPES`), ``step``,
      ``ratio``, ``max_horizon``, ``points``, ``seed``, ``progress``, ``device`` (where the networks train),
      ``train_scale`` (the training box; None: the builder's), ``flat_origin`` (grad V(0, t) = 0 built into the
      ansatz, :class:`~pinnhjb.TrainConfig`), ``warm_start`` (True, False: each stage from fresh weights, or
      ``"best"``: both, the lower E kept; default True),
      ``terminal`` (the first stage's terminal cost: ``"zero"``, the paper's, or ``"lqr"``, the linearisation's LQR
      value x'Px; default zero),
      ``budget`` (how many of the largest errors get :func:`_common.loop_budget`; 0: none), ``save`` (a folder for
      the chain, written after every stage so that a run cut short keeps what it trained, with its wall time so
      far and the run's ``settings`` and ``machine``; or None), ``resume`` (a chain saved so, extended from its
      last stage with its wall time carried on; or None).
    """
    if task["recipe"] == "deepxde":
        return run_deepxde(task)
    system, step = BUILDERS[task["system"]](task["n"], task.get("train_scale")), task["step"]
    config = ph.TrainConfig.preset(task["recipe"], dimension=system.n)
    if task["width"] is not None:
        config = config.replace(width=task["width"])
    if task.get("depth") is not None:
        config = config.replace(depth=task["depth"])
    config = config.replace(retries=task["retries"], loop_share=task.get("loop_share", 0.0))
    config = config.replace(**{key: task[key] for key in ("retry_factor", "retry_against") if key in task})
    if task.get("flat_origin"):
        config = config.replace(flat_origin=True)
    config = config.replace(warm_start=task.get("warm_start", True))
    if task.get("lm"):  # the default recipe's stopping rule, from the command line
        config = config.with_phase("lm", **task["lm"])
    solver = ph.FiniteHorizonSolver(system, config, seed=task["seed"], device=task["device"], progress=task["progress"])
    path = Path(task["save"]) / chain_name(system, task["recipe"]) if task.get("save") else None
    resumed = None  # --resume: the stored chain, carried on from its last stage with its wall time
    if task.get("resume"):
        resumed = ph.load(task["resume"], system=system, device=task["device"], config=config)
    before = 0.0 if resumed is None else resumed.provenance["wall_s"]
    start, saving = time.perf_counter(), 0.0
    with warnings.catch_warnings():  # a late stage can be no better than its terminal cost: that is convergence
        warnings.simplefilter("ignore", RuntimeWarning)
        phi = first_terminal_cost(system, task.get("terminal", "zero"))
        sol = (
            solver.solve(step, terminal_cost=phi)
            if resumed is None
            else solver.extend(resumed, to=resumed.horizon + step)
        )
        zero = sol.metrics["E_zero"]
        while True:
            if path is not None:  # after every stage, so that a run cut short keeps the stages it trained
                tic = time.perf_counter()
                elapsed = before + tic - start - saving  # with the settings, what --resume carries on
                ph.save(sol, path, wall_s=elapsed, settings=task["settings"], machine=task["machine"])
                saving += time.perf_counter() - tic
            if sol.metrics["E"] <= task["ratio"] * zero or sol.horizon >= task["max_horizon"] - 1e-9:
                break
            sol = solver.extend(sol, to=sol.horizon + step)
    wall = before + time.perf_counter() - start - saving
    weights = sum(p.numel() for p in sol.stages[0].model.parameters())  # the first has no terminal network
    x = dimension_states(system, task["points"], task["seed"]).numpy()  # the states of true_errors, V* there
    v_star = system.value_star(torch.as_tensor(x)).detach().numpy()
    errors = [sol.truncated(k).value(x) - v_star for k in range(1, len(sol.stages) + 1)]
    chain = [  # each stage: its horizon, E, final training loss, the losses of the attempts not kept, true errors
        dict(
            T=s.end,
            E_ratio=s.metrics["E"] / s.metrics["E_zero"],
            final_loss=s.history.final_loss,
            rejected_losses=[a["final_loss"] for a in s.rejected],
            **true_errors(system, sol.truncated(k), task["points"], task["seed"]),
            carried=carried(errors, k),
            **_start_kept(s),
        )
        for k, s in enumerate(sol.stages, start=1)
    ]
    measured = dict(T=sol.horizon, stages=len(sol.stages), E_ratio=sol.metrics["E"] / zero, wall_s=wall)
    measured["rejected"] = sum(len(c["rejected_losses"]) for c in chain)
    last = {k: chain[-1][k] for k in ("value_rel_error", "grad_mean_rel_error")}  # the whole chain's errors
    row = dict(_row(task, system, weights, measured, last), chain=chain)
    if task.get("budget"):  # where the largest errors come from: the residual along their loops, inside the box?
        row["budget"] = loop_budget(sol, x, v_star, task["budget"])
    return row


class FunctionValue:
    """A value V(x) given as a batched float64 torch callable (a DeepXDE chain's V(., 0), a polished value) with the
    ``value``/``gradient`` of a Solution, on numpy states, for :func:`true_errors`."""

    def __init__(self, fn):
        self.fn = fn

    def value(self, x: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return self.fn(torch.as_tensor(x)).numpy()

    def gradient(self, x: np.ndarray) -> np.ndarray:
        return gradient(self.fn, torch.as_tensor(x))[1].numpy()


def run_deepxde(task: dict) -> dict:
    """:func:`run` for DeepXDE: the chain of :func:`_deepxde.chain` with ``adam_lbfgs``'s network and budgets,
    stopped by the same rule on E (measured by the same function as ours); a row with ``status`` "not installed"
    where DeepXDE is not importable."""
    system, step = BUILDERS[task["system"]](task["n"], task.get("train_scale")), task["step"]
    dde, missing = dxd.import_deepxde()
    if dde is None:
        return {"system": system.name, "recipe": "deepxde", "n": system.n, "m": system.m, "status": missing}
    torch.set_default_device(None)  # DeepXDE's import may set CUDA: this benchmark is CPU
    config = ph.TrainConfig.preset("adam_lbfgs")
    ratios = []

    def until(fn, T):
        metrics = infinite_horizon_residual(system, fn)
        ratios.append(metrics["E"] / metrics["E_zero"])
        return ratios[-1] <= task["ratio"] or T >= task["max_horizon"] - 1e-9

    lengths = [step] * math.ceil(task["max_horizon"] / step - 1e-9)
    start = time.perf_counter()
    model, length, stages = dxd.chain(dde, system, config, lengths, task["seed"], until)
    wall = time.perf_counter() - start
    weights = sum(p.numel() for p in model.net.parameters())
    measured = dict(T=stages[-1]["T"], stages=len(stages), E_ratio=ratios[-1], wall_s=wall)
    errors = true_errors(system, FunctionValue(dxd.value_fn(model.net, length)), task["points"], task["seed"])
    return _row(task, system, weights, measured, errors)


def _row(task: dict, system, weights: int, measured: dict, errors: dict) -> dict:
    """One run's row: what it was, what it measured (``measured``: T, stages, E_ratio, wall_s; ``errors``: the
    true errors of :func:`true_errors`), printed too."""
    row = {
        "system": system.name,
        "recipe": task["recipe"],
        "n": system.n,
        "m": system.m,
        "weights": weights,
        "step": task["step"],
        **measured,
        **errors,
        "horizon_floor": horizon_floor(system, measured["T"], task["points"], task["seed"]),
    }
    print(
        f"{system.name} n={system.n} {task['recipe']}: T={row['T']:g} E/E0={row['E_ratio']:.1e} "
        f"V err={row['value_rel_error']:.1e} grad err={row['grad_mean_rel_error']:.1e} {row['wall_s']:.0f} s",
        flush=True,
    )
    return row


def _diagnosis_lines(rows: list[dict]) -> list[str]:
    """The results page's lines on each default run: the start each stage kept (``--best-start``), how much of
    the last stage's error it carried from its terminal cost (``carried``), and where the largest errors come
    from (``row["budget"]``)."""
    lines = []
    for r in rows:
        chosen = [c for c in r.get("chain", []) if "started_warm" in c]
        if chosen:
            lines.append(
                f"{r['system']} n = {r['n']}: the start kept at T = "
                + ", ".join(
                    f"{c['T']:g}: {'warm' if c['started_warm'] else 'fresh'} (E ratio {c['E_ratio']:.1e} against "
                    f"{c['other_E_ratio']:.1e}, value error {c['value_rel_error']:.1e})"
                    for c in chosen
                )
                + "."
            )
        if r.get("chain") and r["chain"][-1].get("carried") is not None:
            lines.append(
                f"{r['system']} n = {r['n']}: the last stage's error, state by state, correlates "
                f"{r['chain'][-1]['carried']:.3f} with its terminal cost's (the stage before)."
            )
        if b := r.get("budget"):
            err, share = np.abs(b["value_error"]), np.asarray(b["share_outside"])
            lines.append(
                f"{r['system']} n = {r['n']}: of the {b['states']} largest errors ({err.min():.1e} to {err.max():.1e} "
                f"of max V*), {b['leave_box']} have learned closed loops that leave the training box (reach at most "
                f"{max(b['reach_max']):.2f} of its half-width); the residual outside accounts for up to "
                f"{share.max() + 0.0:.0%} of a loop's integral (the integral over {b['t_final']:g} s: "
                f"{min(b['integral']):.1e} to {max(b['integral']):.1e} of max V*)."
            )
    return [""] + lines if lines else []


def _sci(value) -> str:
    """A table cell: ``value`` as 1.2e-03, or a dash for None."""
    return "-" if value is None else f"{value:.1e}"


def exponent(rows: list[dict]) -> float | None:
    """The slope of log(wall time) against log(n) by least squares; None below two points."""
    if len(rows) < 2:
        return None
    return float(np.polyfit(np.log([r["n"] for r in rows]), np.log([r["wall_s"] for r in rows]), 1)[0])


def _deepxde_version() -> str | None:
    """DeepXDE's version where it is importable here (the runs import it themselves)."""
    dde, _ = dxd.import_deepxde()
    return None if dde is None else dde.__version__


def figure(rows: list[dict], path) -> None:
    """Error and wall time against n, one line per (system, recipe), log-log: ``dimension.png``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax_e, ax_t) = plt.subplots(1, 2, figsize=(9, 3.6), layout="constrained")
    for (name, recipe), marker in zip(sorted({(r["system"], r["recipe"]) for r in rows}), "osD^v<>ph"):
        sel = sorted((r for r in rows if (r["system"], r["recipe"]) == (name, recipe)), key=lambda r: r["n"])
        n = [r["n"] for r in sel]
        ax_e.loglog(n, [r["value_rel_error"] for r in sel], marker=marker, label=f"{name} ({recipe})")
        ax_t.loglog(n, [r["wall_s"] for r in sel], marker=marker)
    ax_e.axhline(1e-4, color="k", lw=0.8, ls=":")
    ax_e.set(xlabel="state dimension n", ylabel="max |V - V*| / max V*")
    ax_t.set(xlabel="state dimension n", ylabel="wall time (s)")
    fig.legend(loc="outside lower center", ncols=2, fontsize="small")
    fig.savefig(path, dpi=120)
    plt.close(fig)


FEATURES = "each stage from the stage before with its last layer zero (it starts at its terminal cost), "
PAGE_KEYS = {  # what write_page needs in a run's meta (lm_points: from the config; RESUME_DEFAULTS: their default)
    *("seed", "threads", "workers", "machine", "torch", "created", "config", "deepxde", "against", "compare"),
    *("step", "converse_step", "ratio", "max_horizon", "points", "width", "retries", "loop_share", "train_scale"),
    *("flat_origin", "cold_start", "best_start"),
}


def _resumed_clause(meta: dict) -> str:
    """The page's words on ``--resume``: the run carried on, and where its stored stages ran."""
    if not meta.get("resumed_from"):
        return ""
    where = " and ".join(m or "an unrecorded machine" for m in meta["resumed_machines"])
    clause = f"the chains of `{meta['resumed_from']}` carried on (their stages and wall time, on {where}, continued"
    return f"{clause} here), "


def _retry_rule(config: dict) -> str:
    """The page's words on the retry rule, when not the default one (a rise of the final training loss over
    ``retry_factor`` against the previous stage's)."""
    default = ph.TrainConfig()
    factor = config.get("retry_factor", default.retry_factor)
    against = config.get("retry_against", default.retry_against)
    if (factor, against) == (default.retry_factor, default.retry_against):
        return ""
    base = "the chain's lowest stage loss" if against == "best" else "the previous stage's loss"
    return f", a stage failing when its final loss is over {factor:g}x {base} (retry_factor, retry_against)"


def write_page(record: dict, out: Path) -> list[str]:
    """Write ``out/dimension.md`` and ``out/dimension.png`` from a run's ``record`` (its ``dimension.json``) alone,
    so that a stored page can be made again from its JSON (``--render``); returns the page's lines."""
    if {"meta", "rows", "exponents", "not_run"} - set(record):
        raise ValueError("the record lacks meta, rows, exponents or not_run (an older dimension.py's, or not one)")
    if "members" in record["meta"]:
        return mean_page(record, out)
    meta, rows, missing, fits = record["meta"], record["rows"], record["not_run"], record["exponents"]
    default = [r for r in rows if r["recipe"] == "default"]
    lacking = sorted(PAGE_KEYS - set(meta))
    if lacking:
        raise ValueError(f"the run was stored by an older dimension.py (its meta has no {', '.join(lacking)})")
    lm = next(phase for phase in meta["config"]["phases"] if phase["name"] == "lm")
    given = lm["points"] if lm["points"] != ph.TrainConfig.preset("default").phase("lm").points else None
    # runs stored before lm_points: from the config; before later settings: RESUME_DEFAULTS
    a = argparse.Namespace(**{"lm_points": given, **RESUME_DEFAULTS, **meta})
    dx_version = f", DeepXDE {a.deepxde}" if a.deepxde else ""
    beside = f"{' and '.join(f'`{r}`' for r in a.against)} beside it at n = {','.join(map(str, a.compare))}"
    rule = lm_rule(a.config)  # the default recipe's LM stopping rule, when not the recipe's own
    retry = _retry_rule(a.config)  # when a failed stage is tried again, when not the default rule
    layers = a.config["depth"]  # the default recipe's hidden layers
    lines = [
        "# Error and cost against the dimension (generated by `benchmarks/dimension.py`; do not edit)",
        "",
        f"The default recipe (one network per system, "
        f"{f'{layers} x {a.width} at every n' if a.width else 'widths by its rule'}"
        f"{f', {a.depth} hidden layers' if a.depth and not a.width else ''}"
        f"{f', {a.lm_points} LM points per iteration at every n' if a.lm_points else ''}; "
        f"{beside if a.compare else 'alone'}"
        f"{dx_version}), "
        f"stages of {a.step:g} s (the converse system "
        f"{a.converse_step:g} s: its open loop is fast and unstable) until E / E(V = 0) <= "
        f"{a.ratio:g} or T = {a.max_horizon:g}, "
        f"{f'a failed stage tried up to {a.retries} more times (retries){retry}, ' if a.retries else ''}"
        f"{f'{a.loop_share:.0%} of the training states along LQR loops (loop_share), ' if a.loop_share else ''}"
        f"trained on Omega enlarged {a.train_scale or 1.25:g}x, "
        f"{'grad V(0, t) = 0 built into the ansatz (flat_origin), ' if a.flat_origin else ''}"
        f"{f'the first terminal cost {TERMINALS[a.terminal]}, ' if a.terminal != 'zero' else ''}"
        f"{'each stage from fresh weights (no warm start), ' if a.cold_start else ''}"
        f"{'each stage from the stage before and from fresh weights, the lower E kept, ' if a.best_start else ''}"
        f"{FEATURES if a.features_start else ''}"
        f"{f'LM{rule}, ' if rule else ''}"
        f"{_resumed_clause(meta)}seed {a.seed}, {a.threads} thread(s) per run, "
        f"{a.workers or 1} run(s) at a time, {a.machine}; torch "
        f"{a.torch}; created {a.created}. Errors against the exact V* on {a.points} seeded uniform "
        "states of Omega.",
        "",
        "| system | recipe | n | m | weights | step | T | E / E(V = 0) | max abs(V - V*) / max V* | "
        "mean rel. error of grad V | wall s (training and measuring E) | attempts not kept | "
        "exact V_T's error (the horizon alone) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        lines.append(
            f"| {r['system']} | {r['recipe']} | {r['n']} | {r['m']} | {r['weights']} | {r['step']:g} | {r['T']:g} | "
            f"{r['E_ratio']:.1e} | {r['value_rel_error']:.1e} | {r['grad_mean_rel_error']:.1e} | {r['wall_s']:.0f} | "
            f"{r.get('rejected', 0)} | {_sci(r.get('horizon_floor'))} |"
        )
    lines += [f"| {r['system']} | {r['recipe']} | {r['n']} | {r['m']} | {r['status']} |||||||||" for r in missing]
    lines += _diagnosis_lines(rows)
    lines.append("")
    for name, slope in fits.items():
        if slope is not None:
            lines.append(f"Wall time against n, {name} (default): exponent {slope:.2f} (least squares on log-log).")
    goal = [r for r in default if r["system"] == "lq_ladder"]
    worst = max(goal, key=lambda r: r["value_rel_error"], default=None)
    if worst is not None:
        met = "met" if worst["value_rel_error"] <= 1e-4 else "missed"
        lines.append(
            f"Goal max relative V error <= 1e-4 at every n of the ladder: {met} (worst {worst['value_rel_error']:.1e} "
            f"at n = {worst['n']})."
        )
    conv12 = [r for r in default if r["system"] == "converse" and r["n"] == 12]
    if conv12:
        met = "met" if conv12[0]["value_rel_error"] <= 1e-3 else "missed"
        lines.append(f"Goal max relative V error <= 1e-3, converse n = 12: {met} ({conv12[0]['value_rel_error']:.1e}).")
    lines.append("")
    lines.append("![error and wall time against n](dimension.png)")
    figure(rows, out / "dimension.png")
    (out / "dimension.md").write_text("\n".join(lines) + "\n")
    return lines


RESUME_SAME = (  # the settings a run carried on with --resume shares with the run that saved its chains
    *("seed", "threads", "step", "converse_step", "ratio", "points", "width", "retries", "loop_share"),
    *("train_scale", "flat_origin", "budget_states", "lm_points", "config", "device", "terminal", "depth"),
)
# settings added since: what a chain saved before them was trained with
RESUME_DEFAULTS = {"terminal": "zero", "depth": None, "features_start": False}


def _resumed(p, args, tasks: list[dict], settings: dict) -> list[str]:
    """Check ``--resume DIR`` before any work: every run is the default recipe's, its chain saved under
    ``DIR/chains/`` with these ``settings`` and ending below ``--max-horizon``; sets each task's ``resume`` and
    returns the machines the stored stages ran on."""
    if any(t["recipe"] != "default" for t in tasks):
        p.error("--resume carries the default recipe's chains on: pass --compare ''")
    machines = []
    for task in tasks:
        system = BUILDERS[task["system"]](task["n"], task["train_scale"])
        path = args.resume / "chains" / chain_name(system, "default")
        try:
            sol = ph.load(path, system=system, device="cpu")
        except (OSError, ValueError) as exc:
            p.error(f"--resume: cannot load the chain of {task['system']} n = {task['n']}: {exc}")
        stored = sol.provenance.get("settings")
        if stored is None or "wall_s" not in sol.provenance:
            p.error(f"--resume: {path} was saved without its settings and wall time (an older dimension.py)")
        if differ := [key for key in RESUME_SAME if stored.get(key, RESUME_DEFAULTS.get(key)) != settings[key]]:
            p.error(f"--resume: {path} was trained with other settings: {', '.join(differ)}")
        if sol.horizon >= args.max_horizon - 1e-9:
            p.error(f"--resume: {path} ends at T = {sol.horizon:g}; raise --max-horizon ({args.max_horizon:g})")
        if sol.metrics["E"] <= args.ratio * sol.metrics["E_zero"]:
            p.error(f"--resume: {path} already meets E / E(V = 0) <= {args.ratio:g}")
        task["resume"] = str(path)
        machines.append(sol.provenance.get("machine"))
    return sorted(set(machines))


# the members of a mean share these settings (the seed apart: RESUME_SAME less what a check may change)
MEAN_SAME = tuple(k for k in RESUME_SAME if k not in ("seed", "threads", "budget_states"))
MEAN_SAME += ("cold_start", "best_start", "features_start")
MEAN_OPTIONS = {"mean", "out", "no_progress", "threads"}  # what a mean takes beside --mean (none of the training's)


def _members(p, args) -> tuple[list[dict], dict]:
    """The stored runs ``--mean`` names, checked before any work: one recipe (the same settings but the seed),
    different seeds, the same default-recipe rows (system, n), each row's chain saved and ending where its row
    did. Returns the runs' records and, by (system, n), the system and the loaded chains."""
    runs = stored_members(p, args, MEAN_OPTIONS, "dimension.json", lambda run: "members" in run["meta"])
    one_recipe(p, args.mean, runs, lambda run: {k: run["meta"].get(k, RESUME_DEFAULTS.get(k)) for k in MEAN_SAME})
    first = runs[0]["meta"]
    keys = [sorted(dimension_rows(run)) for run in runs]
    if not keys[0]:
        p.error(f"--mean: {args.mean[0]} has no measured row of the default recipe")
    for folder, k in zip(args.mean[1:], keys[1:]):
        if k != keys[0]:
            p.error(f"--mean: {folder} measured other systems or n than {args.mean[0]}: {k} against {keys[0]}")
    cases = {}
    for key in keys[0]:
        system = BUILDERS[key[0]](key[1], first["train_scale"])
        chains = []
        for folder, run in zip(args.mean, runs):
            path = folder / "chains" / chain_name(system, "default")
            try:
                sol = ph.load(path, system=system, device="cpu")
            except (OSError, ValueError) as exc:
                p.error(f"--mean: cannot load the chain {path} (its run saves chains with --save): {exc}")
            end = dimension_rows(run)[key]["T"]
            if abs(sol.horizon - end) > 1e-9:
                p.error(f"--mean: the chain {path} ends at T = {sol.horizon:g}, its run's row at T = {end:g}")
            chains.append(sol)
        if len({round(c.horizon, 9) for c in chains}) > 1:
            p.error(f"--mean: the chains of {key[0]} n = {key[1]} end at different T: a mean is of one T")
        cases[key] = (system, chains)
    return runs, cases


def mean_main(p, args) -> int:
    """``--mean``: the mean of stored chains, measured on the states of every member's seed; written as a run
    whose rows are the mean's (the worst of those states) and whose wall time is its members' summed."""
    runs, cases = _members(p, args)
    first = runs[0]["meta"]
    recipe = ph.TrainConfig.from_dict(first["config"])
    seeds = [run["meta"]["seed"] for run in runs]
    start, rows = time.perf_counter(), []
    for (name, n), (system, chains) in cases.items():
        members = [dimension_rows(run)[(name, n)] for run in runs]
        mean = ph.AveragedSolution(chains)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            ev = mean.evaluate(recipe.eval_points_per_dim)
        on = [{"seed": seed, **true_errors(system, mean, first["points"], seed)} for seed in seeds]
        row = {
            "system": name,
            "recipe": "default",
            "n": n,
            "m": system.m,
            "weights": sum(m["weights"] for m in members),
            "step": members[0]["step"],
            "T": chains[0].horizon,
            "stages": members[0]["stages"],
            "E_ratio": ev["E"] / ev["E_zero"],
            "wall_s": sum(m["wall_s"] for m in members),
            "rejected": sum(m.get("rejected", 0) for m in members),
            "value_rel_error": max(o["value_rel_error"] for o in on),
            "grad_mean_rel_error": max(o["grad_mean_rel_error"] for o in on),
            "horizon_floor": members[0].get("horizon_floor"),
            "on_seeds": on,
            "members": [
                {"run": str(folder), "seed": seed, "machine": run["meta"]["machine"], "threads": run["meta"]["threads"]}
                | {k: m[k] for k in ("T", "E_ratio", "value_rel_error", "grad_mean_rel_error", "wall_s")}
                for folder, seed, run, m in zip(args.mean, seeds, runs, members)
            ],
        }
        print(f"{name} n={n} the mean of {len(chains)}: {row['value_rel_error']:.2e} (worst of seeds {seeds})")
        rows.append(row)
    meta = {k: first[k] for k in PAGE_KEYS | set(MEAN_SAME) if k in first}
    meta.update(provenance(), seed=seeds, threads=args.threads, machine=machine("cpu"), workers=None)
    meta.update(members=[str(f) for f in args.mean], check_wall_s=time.perf_counter() - start)
    record = {"meta": meta, "rows": rows, "exponents": {}, "not_run": []}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "dimension.json").write_text(json.dumps(record))
    print("\n".join(write_page(record, args.out)))
    return 0


def mean_page(record: dict, out: Path) -> list[str]:
    """Write ``out/dimension.md`` for a ``--mean`` run from its record: the members, the mean on each member's
    states, and the ladder's goal; returns the page's lines."""
    meta, rows = record["meta"], record["rows"]
    lines = [
        "# Error against the dimension: the mean of chains (generated by `benchmarks/dimension.py --mean`; do not "
        "edit)",
        "",
        f"The mean V = (1/K) sum_k V_k (`ph.AveragedSolution`) of the K = {len(meta['members'])} chains below, one "
        f"recipe from seeds {', '.join(map(str, meta['seed']))}, each trained and saved by its own stored run (its "
        "page gives the recipe); nothing is trained here. Its wall time is the members' training time, summed (each "
        f"on its own machine). Measured on {meta['machine']} in {meta['check_wall_s']:.0f} s; torch {meta['torch']}; "
        f"created {meta['created']}. Errors against the exact V* on {meta['points']} seeded uniform states of Omega: "
        "each member on its own seed's states (its run's row), the mean on every member's, the worst of them "
        "its row.",
        "",
        "| system | n | chain | seed | machine | T | E / E(V = 0) | max abs(V - V*) / max V* | "
        "mean rel. error of grad V | wall s |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        head = f"| {r['system']} | {r['n']} |"
        for m in r["members"]:
            lines.append(
                f"{head} `{m['run']}` | {m['seed']} | {m['machine']}; {m['threads']} thread(s) | {m['T']:g} | "
                f"{m['E_ratio']:.1e} | {m['value_rel_error']:.2e} | {m['grad_mean_rel_error']:.1e} | "
                f"{m['wall_s']:.0f} |"
            )
        for o in r["on_seeds"]:
            lines.append(
                f"{head} the mean, on seed {o['seed']}'s states | | | {r['T']:g} | | {o['value_rel_error']:.2e} | "
                f"{o['grad_mean_rel_error']:.1e} | |"
            )
        lines.append(
            f"{head} the mean (the worst) | | | {r['T']:g} | {r['E_ratio']:.1e} | {r['value_rel_error']:.2e} | "
            f"{r['grad_mean_rel_error']:.1e} | {r['wall_s']:.0f} (sum) |"
        )
    ladder = [r for r in rows if r["system"] == "lq_ladder"]
    if ladder:
        worst = max(ladder, key=lambda r: r["value_rel_error"])
        met = "met" if worst["value_rel_error"] <= 1e-4 else "missed"
        lines += [
            "",
            f"Goal max relative V error <= 1e-4 on the ladder, the mean: {met} at n = "
            f"{', '.join(str(r['n']) for r in ladder)} (worst {worst['value_rel_error']:.2e} at n = {worst['n']}).",
        ]
    (out / "dimension.md").write_text("\n".join(lines) + "\n")
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--ladder", default="2,4,6,8,12,16", help="state dimensions n of the LQ ladder (even)")
    p.add_argument("--converse", default="2,4,6,8,12", help="state dimensions n of the converse system (even)")
    p.add_argument("--compare", default="6", help="dimensions at which --against run too (both systems)")
    p.add_argument("--against", default="adam_lbfgs,deepxde", help="the recipes beside the default at --compare")
    p.add_argument("--width", type=int, default=None, help="the default recipe's width at every n (default: its rule)")
    p.add_argument("--depth", type=int, default=None, help="the default recipe's hidden layers at every n (default: 3)")
    p.add_argument("--step", type=float, default=2.0, help="the stage length (the ladder)")
    p.add_argument("--converse-step", type=float, default=0.5, help="the stage length of the converse system")
    p.add_argument("--ratio", type=float, default=1e-6, help="stop at E / E(V = 0) <= this")
    p.add_argument(
        "--max-horizon",
        type=float,
        default=12.0,
        help="the longest horizon (the ladder's rows report the error its exact V_T leaves there: horizon_floor)",
    )
    p.add_argument("--points", type=int, default=4096, help="uniform states of Omega for the true errors")
    p.add_argument(
        "--retries",
        type=int,
        default=0,
        help="the default recipe's retries of a failed stage (TrainConfig.retries; the first stage is always "
        "tried 1 + retries times)",
    )
    p.add_argument(
        "--retry-factor",
        type=float,
        default=ph.TrainConfig().retry_factor,
        help="with --retries: the rise of a stage's final training loss that fails it (TrainConfig.retry_factor)",
    )
    p.add_argument(
        "--retry-against",
        choices=ph.config.RETRY_AGAINST,
        default=ph.TrainConfig().retry_against,
        help="with --retries: the loss that rise is measured from, the previous stage's or the chain's lowest "
        "(TrainConfig.retry_against)",
    )
    p.add_argument(
        "--loop-share",
        type=float,
        default=0.0,
        help="the default recipe's share of training states along the linearisation's LQR loops from Omega "
        "(TrainConfig.loop_share)",
    )
    p.add_argument(
        "--train-scale",
        type=float,
        default=None,
        help="the training box: Omega enlarged about the origin by this factor (default: the systems' 1.25)",
    )
    p.add_argument(
        "--budget-states",
        type=int,
        default=10,
        help="the default recipe's largest errors whose closed loops get the residual budget (0: none)",
    )
    p.add_argument(
        "--flat-origin",
        action="store_true",
        help="the default recipe with grad V(0, t) = 0 built into the ansatz too (TrainConfig.flat_origin)",
    )
    p.add_argument(
        "--terminal",
        choices=tuple(TERMINALS),
        default="zero",
        help="the default recipe's first terminal cost: 0 (the paper's), or x'Px, the linearisation's LQR value "
        "(not on the LQ ladder, whose V* it is)",
    )
    add_start_arguments(p, note="; the default recipe only")
    p.add_argument(
        "--save", action="store_true", help="store the default recipe's chains under OUT/chains/, after every stage"
    )
    p.add_argument(
        "--resume",
        type=Path,
        default=None,
        metavar="DIR",
        help="a run's --out folder whose chains (saved with --save) this run extends to --max-horizon, with the same "
        "settings (checked before any work); the default recipe only (--compare '')",
    )
    add_lm_arguments(p)
    p.add_argument(
        "--lm-points",
        type=int,
        default=None,
        help="the default recipe's LM points per iteration at every n (its last level; default: the width rule's)",
    )
    add_mean_argument(
        p,
        "train nothing: measure the mean (ph.AveragedSolution) of the chains two or more stored runs of one "
        "recipe saved (their --out folders, run with --save; they differ in seed alone)",
    )
    p.add_argument(
        "--render",
        type=Path,
        default=None,
        metavar="DIR",
        help="make DIR/dimension.md and dimension.png again from DIR/dimension.json (a stored run) and stop",
    )
    args = parse(p, argv, device=True)
    if args.render is not None:
        try:
            record = json.loads((args.render / "dimension.json").read_text())
            print("\n".join(write_page(record, args.render)))
        except (OSError, ValueError) as exc:
            p.error(f"--render {args.render}: {exc}")
        return 0
    if args.mean is not None:
        return mean_main(p, args)
    settings = lm_settings(args)  # the default recipe's LM stopping rule
    if args.lm_points is not None:
        settings["points"] = args.lm_points
    try:
        default_config = ph.TrainConfig.preset("default").with_phase("lm", **settings)
    except ValueError as exc:
        p.error(str(exc))
    if args.flat_origin:
        default_config = default_config.replace(flat_origin=True)
    if args.depth is not None:
        try:
            default_config = default_config.replace(depth=args.depth)
        except ValueError:
            p.error(f"--depth must be an integer >= 1; got {args.depth}")
    default_config = default_config.replace(warm_start=warm_start_of(p, args))
    if args.retries < 0:
        p.error(f"--retries must be an integer >= 0; got {args.retries}")
    rule = {"retry_factor": args.retry_factor, "retry_against": args.retry_against}
    try:
        ruled = default_config.replace(**rule)
    except ValueError as exc:
        p.error(str(exc).replace("retry_factor", "--retry-factor"))
    if ruled != default_config and not args.retries:
        p.error(
            "--retry-factor and --retry-against decide when a stage is tried again, and --retries is 0: "
            "pass --retries 1 or more"
        )
    default_config = ruled
    if not 0 <= args.loop_share < 1:
        p.error(f"--loop-share must be in [0, 1); got {args.loop_share}")
    sizes = {
        "lq_ladder": [int(n) for n in args.ladder.split(",") if n],
        "converse": [int(n) for n in args.converse.split(",") if n],
    }
    if any(n % 2 for ns in sizes.values() for n in ns):
        p.error("every n must be even (the ladder has n = 2k; the converse system m = n/2 inputs)")
    if args.terminal == "lqr" and sizes["lq_ladder"]:
        p.error(
            "--terminal lqr: the LQ ladder's V* is its LQR value x'Px, so its chain would start at the answer; "
            "use it with --ladder ''"
        )
    if args.budget_states < 0:
        p.error(f"--budget-states must be >= 0; got {args.budget_states}")
    try:  # every system built once, with its training box, before any run
        for name, ns in sizes.items():
            for n in ns:
                BUILDERS[name](n, args.train_scale)
    except ValueError as exc:
        p.error(f"--train-scale: {exc}")
    for n in sorted({n for ns in sizes.values() for n in ns}):  # the LM settings at every n's width rule
        try:
            ph.TrainConfig.preset("default", dimension=n).with_phase("lm", **settings)
        except ValueError as exc:
            p.error(f"n = {n}: {exc}")
    compare = {int(n) for n in args.compare.split(",") if n}
    against = [r for r in args.against.split(",") if r]
    if unknown := set(against) - set(RECIPES[1:]):
        p.error(f"--against: unknown recipe(s) {sorted(unknown)}; choose from {', '.join(RECIPES[1:])}")
    if args.device == "cuda" and "deepxde" in against and compare:
        p.error(
            "--device cuda: DeepXDE runs on the CPU here; leave it out (--against adam_lbfgs) or compare on a GPU "
            "with benchmarks/speed.py --device cuda"
        )
    common = dict(
        ratio=args.ratio,
        max_horizon=args.max_horizon,
        points=args.points,
        seed=args.seed,
        retries=args.retries,
        device=args.device,
        train_scale=args.train_scale,
        save=str(args.out / "chains") if args.save else None,
    )
    width = {"default": args.width, "adam_lbfgs": None, "deepxde": None}
    depth = {"default": args.depth, "adam_lbfgs": None, "deepxde": None}
    loops = {"default": args.loop_share, "adam_lbfgs": 0.0, "deepxde": 0.0}
    lm = {"default": settings, "adam_lbfgs": None, "deepxde": None}
    common["progress"] = not args.no_progress and args.workers is None and args.scheduler is None
    steps = {"lq_ladder": args.step, "converse": args.converse_step}
    tasks = [
        dict(
            common,
            system=name,
            n=n,
            recipe=recipe,
            step=steps[name],
            width=width[recipe],
            depth=depth[recipe],
            loop_share=loops[recipe],
            lm=lm[recipe],
            budget=args.budget_states if recipe == "default" else 0,
            flat_origin=args.flat_origin and recipe == "default",
            terminal=args.terminal if recipe == "default" else "zero",
            **(rule if recipe == "default" else {}),
            warm_start=default_config.warm_start if recipe == "default" else True,
        )
        for name, ns in sizes.items()
        for n in ns
        for recipe in ["default"] + (against if n in compare else [])
    ]
    meta = {
        **provenance(),
        "seed": args.seed,
        "threads": args.threads,
        "machine": machine(args.device),
        "device": args.device,
        "step": args.step,
        "converse_step": args.converse_step,
        "ratio": args.ratio,
        "max_horizon": args.max_horizon,
        "points": args.points,
        "compare": sorted(compare),
        "against": against,
        "width": args.width,
        "depth": args.depth,
        "retries": args.retries,
        "loop_share": args.loop_share,
        "train_scale": args.train_scale,
        "flat_origin": args.flat_origin,
        "terminal": args.terminal,
        "cold_start": args.cold_start,
        "best_start": args.best_start,
        "features_start": args.features_start,
        "lm_points": args.lm_points,
        "budget_states": args.budget_states,
        "workers": args.workers,
        "config": default_config.to_dict(),
        "configs": {"default": default_config.to_dict(), "adam_lbfgs": ph.TrainConfig.preset("adam_lbfgs").to_dict()},
        "deepxde": _deepxde_version() if "deepxde" in against else None,
    }
    same = {key: meta[key] for key in RESUME_SAME}  # what a resumed run must share with its stored chains
    for task in tasks:
        task.update(settings=same, machine=meta["machine"])
    if args.resume is not None:
        meta["resumed_from"] = str(args.resume)
        meta["resumed_machines"] = _resumed(p, args, tasks, same)
    rows = map_runs(
        run,
        tasks,
        workers=args.workers,
        scheduler=args.scheduler,
        threads=args.threads,
        progress=not args.no_progress,
        desc="dimension runs",
        label=lambda t: f"{t['system']} n={t['n']} {t['recipe']}",
    )
    meta["created"] = provenance()["created"]  # when the runs ended
    missing = [r for r in rows if "status" in r]
    rows = [r for r in rows if "status" not in r]
    default = [r for r in rows if r["recipe"] == "default"]
    fits = {name: exponent([r for r in default if r["system"] == name]) for name in sizes}
    args.out.mkdir(parents=True, exist_ok=True)
    record = {"meta": meta, "rows": rows, "exponents": fits, "not_run": missing}
    (args.out / "dimension.json").write_text(json.dumps(record))
    print("\n".join(write_page(record, args.out)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
