"""The speed benchmark's bookkeeping (benchmarks/speed.py), on made-up traces: which runs it plans, which run of a
method counts as its best chain step. No training here: the benchmark itself is timed in
``benchmarks/``, never in the test suite."""

import importlib.util
import os
import sys
from pathlib import Path

import pytest

SPEED = Path(__file__).resolve().parents[1] / "benchmarks" / "speed.py"


def script(name: str):
    """benchmarks/<name>.py as a module (the scripts import their siblings, e.g. _common.py, by name)."""
    spec = importlib.util.spec_from_file_location(f"{name}_benchmark", SPEED.parent / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(SPEED.parent))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(SPEED.parent))
    return module


@pytest.fixture(scope="module")
def speed():
    before = os.environ.get("CUDA_VISIBLE_DEVICES")
    module = script("speed")
    assert os.environ.get("CUDA_VISIBLE_DEVICES") == before  # importing it hides no GPU (only main(--device cpu))
    return module


def run(method, step, times, final_E=1e-5, train_time=None):
    """A finished run in the summary's format. ``times``: training s to each of the paper final E, 1e-3,
    1.5e-4 (None: not reached)."""
    pf, t3, t4 = times
    last = max([t for t in times if t is not None], default=10.0)
    return {
        "status": "ok",
        "method": method,
        "step": step,
        "description": method,
        "setup_time": 0.0,
        "train_time": train_time or last,
        "eval_time": 0.0,
        "time_to": {"0.001": t3, "0.00015": t4},
        "time_to_including_setup": {"0.001": t3, "0.00015": t4},
        "time_to_paper_final_E": pf,
        "time_to_paper_final_E_including_setup": pf,
        "final": {"E": final_E, "E_boundary": 0.0, "value_max_error": 1e-2, "policy_max_error": 1e-2},
    }


def test_chain_lengths_divide_the_horizon(speed):
    assert speed.chain_lengths(0.5) == [0.5] * 8
    assert speed.chain_lengths(2.0) == [2.0, 2.0]
    assert speed.chain_lengths(4.0) == [4.0]
    for bad in (1.5, 3.0, 5.0):
        with pytest.raises(ValueError, match="must divide"):
            speed.chain_lengths(bad)


def test_plan_runs_every_chain_method_once_per_step(speed):
    plan = speed.variants(["deepxde", "default", "paper", "deepxde-chain-small"], [0.5, 2.0])
    assert plan == [
        ("paper", "paper", 0.5),
        ("default@0.5", "default", 0.5),
        ("default@2", "default", 2.0),
        ("deepxde", "deepxde", None),
        ("deepxde-chain-small@0.5", "deepxde-chain-small", 0.5),
        ("deepxde-chain-small@2", "deepxde-chain-small", 2.0),
    ]
    assert "one stage [0, 4]" in speed.describe("default", 4.0)
    assert "chain 1 -> 4 in 1 s steps" in speed.describe("deepxde-chain", 1.0)


def test_best_run_is_the_first_to_reach_the_target(speed):
    methods = {
        "default@0.5": run("default", 0.5, (40.0, 40.0, 50.0)),
        "default@2": run("default", 2.0, (20.0, 20.0, 20.0)),
        "default@1": run("default", 1.0, (None, None, None), train_time=99.0),
    }
    to_pf = lambda d: d["time_to_paper_final_E"]  # noqa: E731
    assert speed.best_run(methods, "default", to_pf) == ("default@2", 20.0)
    never = {"x@0.5": run("x", 0.5, (None,) * 3, train_time=5.0), "x@1": run("x", 1.0, (None,) * 3, train_time=9.0)}
    assert speed.best_run(never, "x", to_pf) == ("x@1", None)  # the longest run, and no time
    assert speed.best_run(methods, "deepxde", to_pf) == (None, None)


def test_best_step_table_gives_each_target_its_own_best_run(speed):
    methods = {
        "default@0.5": run("default", 0.5, (45.0, 45.0, 52.0)),
        "default@2": run("default", 2.0, (21.0, 21.0, 60.0)),
        "deepxde-chain-small@1": run("deepxde-chain-small", 1.0, (30.0, 30.0, None)),
    }
    best = speed.best_steps(methods, 1.4e-3)
    assert best["0.00015"]["default"] == {"run": "default@0.5", "time": 52.0}
    assert best["0.00015"]["deepxde-chain-small"] == {"run": "deepxde-chain-small@1", "time": None}
    lines = speed.best_step_table(best, 1.4e-3)
    rows = {line.split(" | ")[0].strip("| "): line for line in lines if line.startswith("| ")}
    assert "21.0 (default@2)" in rows["default"] and "52.0 (default@0.5)" in rows["default"]
    assert "30.0 (deepxde-chain-small@1): 1.43x" in rows["deepxde-chain-small"]
    assert "not reached" in rows["deepxde-chain-small"]


def test_tables_of_an_interrupted_run_say_so(speed, tmp_path):
    """The tables are rewritten after every run; until the last one they carry how many of the planned runs ran."""
    meta = {
        "budget_scale": 1.0,
        "steps": [2.0],
        "machine": "m",
        "torch": "t",
        "threads": 2,
        "deepxde": "d",
        "pinnhjb": "p",
        "seed": 0,
        "paper_stage_seconds": 60.0,
        "created": "now",
        "checkpoint_every": 500,
        "lbfgs_checkpoint_every": 100,
    }
    summary = {"paper_final_E": None, "methods": {"default@2": run("default", 2.0, (5.0, 5.0, 5.0))}, "best": {}}
    speed.write_tables(summary, {**meta, "runs_done": 1, "runs_planned": 3}, tmp_path)
    assert "Interrupted: 1 of 3 planned runs done" in (tmp_path / "speed.md").read_text()
    speed.write_tables(summary, {**meta, "runs_done": 3, "runs_planned": 3}, tmp_path)
    assert "Interrupted" not in (tmp_path / "speed.md").read_text()


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="CUDA is available here")
def test_cuda_benchmark_without_cuda_is_refused(speed, capsys):
    with pytest.raises(SystemExit):
        speed.main(["--device", "cuda", "--methods", "default"])
    assert "CUDA is not available" in capsys.readouterr().err


def test_deepxde_cpu_runs_are_under_no_torch_function_mode(speed, monkeypatch):
    """A device mode sees every torch operation; on the CPU it costs DeepXDE's many small steps much of their time,
    so its CPU runs must have none (its GPU runs get the one its own import would set)."""
    from types import SimpleNamespace

    from torch.overrides import _get_current_function_mode_stack

    seen = []
    monkeypatch.setattr(speed, "train_deepxde", lambda *a: seen.append(len(_get_current_function_mode_stack())))
    speed.run_deepxde("x", "deepxde-chain", 1.0, SimpleNamespace(device="cpu"), None, None)
    assert seen == [0]


def test_timed_measure_is_the_solvers_public_evaluation_hook(speed):
    """The benchmark's per-stage metrics go through the solver's public ``evaluate=`` hook (no private override):
    the hook returns :func:`measure` of the chain's V_T(., 0) and adds up the time spent in it. No training: an
    untrained stage."""
    import torch

    import pinnhjb as ph
    from pinnhjb.pinn import FiniteHorizonValue, ZeroTerminalCost
    from pinnhjb.solution import Stage
    from pinnhjb.training import TrainHistory

    system = ph.systems.quartic()
    torch.manual_seed(0)
    model = FiniteHorizonValue(2, 0.5, system.train_domain, ZeroTerminalCost(), width=4, depth=1).double()
    sol = ph.FiniteHorizonSolution(
        system,
        ph.TrainConfig.preset("default"),
        [Stage(model.requires_grad_(False), 0.0, TrainHistory(), 0)],
        {"kind": "zero"},
    )
    hook = speed.TimedMeasure(system)
    out = hook(sol)
    assert out == speed.measure(system, sol.value_function()) and hook.eval_time > 0.0
    assert {"E", "E_boundary", "value_max_error", "policy_max_error"} <= set(out)
    assert out["E"] == sol.evaluate(101)["E"]  # the same E as the package's own evaluation on the 101 x 101 grid
    # the package's solver is used as it is, not subclassed to override a private method
    assert not any(
        isinstance(v, type) and issubclass(v, ph.FiniteHorizonSolver)
        for v in vars(speed).values()
        if v is not ph.FiniteHorizonSolver
    )


def test_results_index_is_generated():
    """``benchmarks/results/index.md`` is what ``benchmarks/index.py`` makes of the stored runs, so none of its
    numbers is typed; a stored run added without rewriting the page fails here."""
    index = script("index")
    page = index.render()
    assert (SPEED.parent / "results" / "index.md").read_text() == page
    assert "| `repeats/ladder-n6-best-start` |" in page and "| `main run` |" in page
    assert index.main(["--check"]) == 0
    with pytest.raises(SystemExit):  # a wrong folder is a usage error, not a stale page
        index.main(["--check", "--results", str(SPEED.parent / "no-such-folder")])
    meta = {"command": "benchmarks/dimension.py --ladder  --note two words --out /tmp/x --no-progress --seed 1"}
    assert index.command(meta) == 'benchmarks/dimension.py --ladder "" --seed 1'


def test_polish_correction_solves_the_derived_hjb():
    """benchmarks/polish.py: for V0 = V* - c, the derived system's steady-state HJB residual at c is the original
    system's at V* (zero on the LQ ladder, to rounding), and at c = 0 it is V0's own residual E_e(x; V0)."""
    import torch

    import pinnhjb as ph
    from pinnhjb.pinn import gradient

    module = script("polish")
    system = ph.systems.lq_ladder(2)
    x = system.sample(64, torch.Generator().manual_seed(0), dtype=torch.float64)

    def bump(z):  # a smooth correction c with c(0) = 0
        return 0.3 * torch.sin(z).pow(2).sum(-1)

    def v0(z):
        return system.value_star(z) - bump(z)

    derived = module.correction_system(system, v0)
    g_c = gradient(bump, x)[1]
    g_star = gradient(system.value_star, x)[1]
    assert system.hamiltonian_min(x, g_star).abs().max() < 1e-12  # V* solves the ladder's HJB
    assert derived.hamiltonian_min(x, g_c).abs().max() < 1e-12
    g_0 = gradient(v0, x)[1]
    own = system.hamiltonian_min(x, g_0)
    assert own.abs().max() > 1e-3  # V0 is not V*
    assert torch.allclose(derived.hamiltonian_min(x, torch.zeros_like(x)), own, rtol=1e-12, atol=1e-14)
