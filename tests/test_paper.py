"""The reproduction command (quick mode, pinnhjb.paper) and the committed artifacts it wrote.

Every committed checkpoint is re-evaluated: its stored E must still come out of the current code, so a stale
artifact (trained by older code, or edited by hand) fails here.
"""

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

import pinnhjb as ph
from pinnhjb import paper
from pinnhjb.paper import artifacts, reproduce, tables

ROOT = Path(__file__).resolve().parents[1]
ARTIFACTS = ROOT / "artifacts"
CHECKPOINTS = sorted((ARTIFACTS / "checkpoints").glob("*/seed*.pt"))


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("artifacts")
    result = reproduce.run(out=out, seeds=1, quick=True, only=["pendulum_extension", "quartic_steady"], progress=False)
    return out, result


def test_quick_run_writes_checkpoints_references_and_tables(quick_run):
    out, result = quick_run
    assert paper.checkpoint_path(out, "pendulum_extension", 0).exists()
    assert paper.checkpoint_path(out, "quartic_steady", 0).exists()
    refs = sorted(p.name for p in (out / "reference").glob("*.npz"))
    assert "pendulum_inf.npz" in refs and "pendulum_T1.npz" in refs and "pendulum_T2.npz" in refs
    table = (out / "results" / "reproduce.md").read_text()
    assert "| pendulum_extension | 1 | 1 | 0.0453 |" in table  # T, seeds, then the paper's number beside ours
    payload = json.loads((out / "results" / "reproduce.json").read_text())
    assert {"torch", "numpy", "pinnhjb", "created", "wall_time", "config"} <= set(payload["meta"])
    with open(out / "results" / "reproduce.csv") as fh:
        assert fh.readline().startswith("case,T,seeds,paper_E")


def test_quick_run_reports_true_errors_and_closed_loop(quick_run):
    _, result = quick_run
    rows = {(r["case"], r["T"]): r for r in result["summary"]}
    pend = rows[("pendulum_extension", 2.0)]
    assert pend["value_max_error"]["mean"] > 0  # measured against the reference V*, not skipped
    assert "E_reference_VT" in pend and pend["value_rel_error"]["mean"] > 0 and pend["E_ratio"]["mean"] > 0
    assert 0.0 <= pend["cost_within"]["mean"] <= 1.0 and pend["cost_ratio_max"]["mean"] >= 1.0 - 1e-3
    steady = rows[("quartic_steady", math.inf)]
    assert steady["E"]["mean"] > 0 and "cost_ratio_mean" in steady
    assert "cost_ratio_max" not in rows[("pendulum_extension", 1.0)]  # the final policy only, unless 'until'


class _Exact:
    """A stand-in solution that steers with the known optimal policy."""

    def __init__(self, system):
        self.system = system

    def closed_loop(self, x0, t_final, dt):
        return ph.metrics.closed_loop(self.system, self.system.policy_star, x0, t_final=t_final, dt=dt)


def test_the_closed_loop_criterion_is_one_the_optimal_policy_passes():
    """A slow LQ problem (time constant about 9 s) run for 20 s: the optimal policy leaves most states far from
    the origin, so a bound on abs(x(t_final)) fails it; its cost to t = inf is V*(x0) from every state."""
    system = ph.systems.linear_quadratic([[-0.05]], [[1.0]], [[1.0]], [[100.0]], domain=[[-1.0, 1.0]])
    x0 = np.linspace(-1, 1, 21)[:, None]
    v_star = system.value_star(torch.as_tensor(x0)).numpy()
    settings = {"t_final": 20.0, "dt": 0.05}
    m = paper.evaluation.closed_loop_metrics(system, _Exact(system), x0, v_star, settings)
    assert m["cost_within"] == 1.0 and abs(m["cost_ratio_max"] - 1) < 1e-6 and m["cost_ratio_mean"] >= 1 - 1e-6
    assert m["tail_share_max"] > 0.01  # the tail is not negligible here: it is what makes the criterion fair
    run = _Exact(system).closed_loop(x0, **settings)
    assert run.fraction_stabilized < 0.2
    # a policy with half the optimal gain fails it
    half = ph.metrics.closed_loop(system, lambda x: 0.5 * system.policy_star(x), x0, **settings)
    cost, _ = ph.metrics.infinite_horizon_cost(system, half)
    assert np.max(cost[v_star > 1e-6] / v_star[v_star > 1e-6]) > 1.01


def test_first_horizons_and_convergence():
    rows = [
        {"T": 0.5, "E_ratio": 0.5, "value_rel_error": 0.5, "cost_ratio_max": 1.2},
        {"T": 2.5, "E_ratio": 1e-4, "value_rel_error": 0.05, "cost_ratio_max": 1.005},
        {"T": 4.5, "E_ratio": 1e-5, "value_rel_error": 0.005, "cost_ratio_max": 1.001},
    ]
    assert paper.evaluation.first_horizons(rows) == {
        "E_ratio": 2.5,
        "value_rel_error": 4.5,
        "cost_ratio_max": 2.5,
        "all": 4.5,
    }
    assert paper.evaluation.converged(rows[-1]) and not paper.evaluation.converged(rows[1])
    assert not paper.evaluation.converged({"T": 1.0, "E_ratio": 0.0})  # a missing measure is not a pass


def test_references_are_reused(quick_run):
    out, _ = quick_run
    path = out / "reference" / "pendulum_inf.npz"
    before = path.stat().st_mtime_ns
    reproduce.run(out=out, seeds=1, quick=True, only=["pendulum_steady"], progress=False)
    assert path.stat().st_mtime_ns == before


def test_unknown_case_is_rejected():
    with pytest.raises(KeyError, match="unknown case"):
        paper.cases(only=["nope"])
    known = paper.cases()[0].name
    for load in (
        lambda: paper.stage_metric("nope", "E"),
        lambda: paper.reference_residual("nope", 1.0),
        lambda: paper.load_reference("nope"),
        lambda: paper.load_case("nope"),
    ):
        with pytest.raises(KeyError, match=rf"unknown case 'nope'.*{known}"):
            load()


def test_every_case_has_a_committed_checkpoint():
    missing = [c.name for c in paper.CASES if not paper.checkpoint_path(ARTIFACTS, c.name, 0).exists()]
    assert not missing, f"no committed checkpoint for {missing}: run `python -m pinnhjb reproduce`"


@pytest.mark.parametrize("path", CHECKPOINTS, ids=[f"{p.parent.name}/{p.stem}" for p in CHECKPOINTS])
def test_committed_checkpoint_metrics_still_hold(path):
    sol = ph.load(path, device="cpu")
    if isinstance(sol, ph.FiniteHorizonSolution):
        views = [sol.truncated(k + 1) for k in range(len(sol.stages))]
    else:
        views = [sol]
    for view in views:
        stored = view.metrics
        again = view.evaluate(view.config.eval_points_per_dim)
        for key in ("E", "value_max_error", "policy_max_error"):
            if key in stored:
                assert again[key] == pytest.approx(stored[key], rel=1e-3, abs=1e-9), (path, key)
    assert np.isfinite(sol.metrics["E"])


def test_tables_can_be_rewritten_from_records(quick_run):
    out, _ = quick_run
    table = out / "results" / "reproduce.md"
    table.unlink()
    result = tables.rewrite_tables(out)
    text = table.read_text()
    assert "The reference method, checked where V* is known (quartic_inf.npz" in text
    assert result["meta"]["reference_wall_time"] > 0 and result["meta"]["cases_wall_time"] > 0


def test_rerunning_one_seed_keeps_the_other_seeds_rows(quick_run):
    out, _ = quick_run
    result = reproduce.run(out=out, seeds=2, first_seed=1, quick=True, only=["quartic_steady"], progress=False)
    seeds = sorted(r["seed"] for r in result["records"] if r["case"] == "quartic_steady")
    assert seeds == [0, 1]
    assert any(r["case"] == "pendulum_extension" for r in result["records"])


def test_load_case_retrains_in_place_once_when_asked(quick_run, monkeypatch):
    out, _ = quick_run
    calls = []
    monkeypatch.setattr(reproduce, "run", lambda **kw: calls.append(kw))
    monkeypatch.setattr(artifacts, "_RETRAINED", set())
    paper.load_case("quartic_steady", out=out)
    assert calls == []
    for _ in range(2):
        sol = paper.load_case("quartic_steady", seed=0, out=out, retrain=True)
    assert calls == [dict(out=out, seeds=1, only=["quartic_steady"], first_seed=0)]
    assert isinstance(sol, ph.SteadyStateSolution)
    with pytest.raises(KeyError, match="unknown case"):
        paper.load_case("nope", out=out)


def test_the_core_knows_nothing_of_the_paper():
    """Only the command line and the package's lazy imports reach pinnhjb.paper; no core module imports it."""
    import ast

    core = [p for p in (ROOT / "pinnhjb").glob("*.py") if p.name not in ("cli.py", "__init__.py", "__main__.py")]
    assert core
    for path in core:
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                names = [node.module or ""] + [a.name for a in node.names]
            elif isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            else:
                continue
            assert not any(
                n.split(".")[-1] in ("paper", "reproduce", "theorem3") or n.startswith("paper") for n in names
            ), (path.name, names)
    assert not (ROOT / "pinnhjb" / "reproduce.py").exists() and not (ROOT / "pinnhjb" / "theorem3.py").exists()


def test_benchmark_loaders_read_what_the_benchmarks_stored(tmp_path):
    """The loaders chapters 8 to 10 call: a stored run (main, a repeat, a GPU run) and the reference with the most
    states; what is missing is a FileNotFoundError naming where it was looked for."""
    out = tmp_path / "artifacts"
    results = tmp_path / "benchmarks" / "results"
    (results / "repeats" / "run-a").mkdir(parents=True)
    (results / "cuda_nd" / "run-b").mkdir(parents=True)
    (results / "rigid_body.json").write_text(json.dumps({"which": "main"}))
    (results / "dimension.json").write_text(json.dumps({"which": "main dimension"}))
    (results / "repeats" / "run-a" / "dimension.json").write_text(json.dumps({"which": "repeat"}))
    (results / "cuda_nd" / "run-b" / "rigid_body.json").write_text(json.dumps({"which": "gpu"}))
    assert paper.results_dir(out) == results
    assert paper.benchmark_run(out=out) == {"which": "main"}
    assert paper.benchmark_run("run-a", "dimension", out=out) == {"which": "repeat"}
    assert paper.benchmark_run("run-b", folder="cuda_nd", out=out) == {"which": "gpu"}
    assert paper.benchmark_runs(out=out) == {"main run": {"which": "main"}, "cuda_nd/run-b": {"which": "gpu"}}
    assert paper.benchmark_runs("dimension", out=out) == {
        "main run": {"which": "main dimension"},
        "repeats/run-a": {"which": "repeat"},
    }
    (results / "cuda").mkdir()  # a run one folder down, of a benchmark without a main run
    (results / "cuda" / "speed.json").write_text(json.dumps({"which": "cuda speed"}))
    assert paper.benchmark_runs("speed", out=out) == {"cuda": {"which": "cuda speed"}}
    stored = paper.results_dir() / "repeats" / "ladder-n6-features-start-seed0"  # a saved chain of the repository
    chain = paper.dimension_chain(stored.name, "lq_ladder", 6)
    assert (
        chain.system.n == 6
        and chain.horizon == paper.dimension_rows(paper.benchmark_run(stored.name, "dimension"))[("lq_ladder", 6)]["T"]
    )
    with pytest.raises(FileNotFoundError):
        paper.dimension_chain("run-a", "lq_ladder", 4, out=out)  # a run that saved no chain
    record = {
        "rows": [  # the last measured row of each (system, n) and recipe
            {"system": "lq_ladder", "n": 4, "value_rel_error": 1.0},
            {"system": "lq_ladder", "n": 4, "recipe": "default", "value_rel_error": 2.0},
            {"system": "lq_ladder", "n": 4, "recipe": "default", "value_rel_error": None},
            {"system": "lq_ladder", "n": 4, "recipe": "adam_lbfgs", "value_rel_error": 3.0},
            {"system": "converse", "n": 4, "recipe": "default", "value_rel_error": 4.0},
        ]
    }
    assert {k: r["value_rel_error"] for k, r in paper.dimension_rows(record).items()} == {
        ("lq_ladder", 4): 2.0,
        ("converse", 4): 4.0,
    }
    assert list(paper.dimension_rows(record, "adam_lbfgs")) == [("lq_ladder", 4)]
    assert paper.dimension_rows(record, "deepxde") == {}
    with pytest.raises(FileNotFoundError, match="run-a/rigid_body.json"):
        paper.benchmark_run("run-a", out=out)
    with pytest.raises(FileNotFoundError, match=r"reference/rigid_body_inf_\*\.npz"):
        paper.benchmark_reference("rigid_body", out=out)
    stored = paper.load_reference("pendulum_one_stage", paper.INF, ARTIFACTS)
    (out / "reference").mkdir(parents=True)
    for points in (9, 10):  # 10 > 9 as numbers, not as strings
        stored.save(paper.benchmark_reference_path("rigid_body", paper.INF, points, out))
    stored.save(paper.benchmark_reference_path("rigid_body", 20.0, 11, out))
    assert (out / "reference" / "rigid_body_T20_11.npz").is_file()  # the name benchmarks/rigid_body.py writes
    (out / "reference" / "rigid_body_inf_9.npz").write_bytes(b"not a grid")  # never read: the larger one is
    got = paper.benchmark_reference("rigid_body", out=out)
    assert np.array_equal(got.value, stored.value, equal_nan=True)
    assert paper.benchmark_reference("rigid_body", 20.0, out=out).horizon == stored.horizon


def test_run_config_leaves_out_named_settings_and_refuses_a_name_that_is_not_one():
    """``paper.run_config``: two stored runs that differ in one setting compare equal without it; a run stored
    before a setting existed lacks it and is compared without it; a name that is not a TrainConfig field (a
    misspelling, or the seed, kept in ``meta``) is a KeyError rather than a comparison that drops nothing."""
    config = dataclasses.asdict(ph.TrainConfig())
    older = {key: value for key, value in config.items() if key != "flat_origin"}
    run = {"meta": {"config": config, "seed": 0}}
    other = {"meta": {"config": {**config, "warm_start": "best"}, "seed": 1}}
    assert paper.run_config(run) == config and paper.run_config(run) is not config
    assert paper.run_config(run) != paper.run_config(other)
    assert paper.run_config(run, "warm_start") == paper.run_config(other, "warm_start")
    assert "warm_start" not in paper.run_config(run, "warm_start")
    assert paper.run_config({"meta": {"config": older}}, "flat_origin") == paper.run_config(run, "flat_origin")
    for wrong in ("seed", "warm_starts"):
        with pytest.raises(KeyError, match=wrong):
            paper.run_config(run, "width", wrong)


def _rigid(value, grad, wall, device="cpu", settled=100):
    stage = {"T": 16.0, "E_ratio": 1e-6, "value_rel_error": value, "grad_mean_rel_error": grad}
    loop = {"states": 100, "settled": settled, "cost_ratio_max": 1.0002}
    return {"meta": {"args": {"device": device}}, "infinite": {"stages": [stage], "wall_s": wall, "closed_loop": loop}}


def _dimension(*rows):
    return {"rows": [{"system": s, "n": n, "value_rel_error": v} for s, n, v in rows]}


def test_dimension_goals_take_the_closest_stored_run(tmp_path):
    """Issue #18's goals (chapter 8's table, ``benchmarks/results/index.md``): the lowest number of any stored run,
    the CPU-time goal's value only among runs within 30 minutes, the GPU's time from its fastest run."""
    out, results = tmp_path / "artifacts", tmp_path / "benchmarks" / "results"
    runs = {
        "": _rigid(9e-3, 7e-3, 300.0),
        "repeats/slow": _rigid(9e-4, 3e-3, 4000.0),
        "repeats/quick": _rigid(2e-3, 1e-3, 1500.0),
        "cuda_nd/gpu": _rigid(1.5e-3, 2e-3, 50.0, device="cuda"),
    }
    for where, record in runs.items():
        (results / where).mkdir(parents=True, exist_ok=True)
        (results / where / "rigid_body.json").write_text(json.dumps(record))
    (results / "dimension.json").write_text(json.dumps(_dimension(("lq_ladder", 4, 6e-4), ("converse", 12, 0.3))))
    (results / "repeats" / "l").mkdir()
    (results / "repeats" / "l" / "dimension.json").write_text(
        json.dumps(_dimension(("lq_ladder", 4, 5e-5), ("lq_ladder", 8, 2e-3)))
    )
    goals = {g.key: g for g in paper.dimension_goals(out)}
    assert len(goals) == 7 + 2 + 1  # the rigid body's, the ladder's n = 4 and 8, the converse n = 12
    v = goals["value error"]
    assert (v.main, v.closest, v.run, v.met) == (9e-3, 9e-4, "repeats/slow", True)
    assert goals["gradient error"].run == "repeats/quick"
    q = goals["value error within 30 min"]
    assert (q.closest, q.run, q.met) == (2e-3, "repeats/quick", False)
    gpu = goals["time on one GPU"]
    assert (gpu.main, gpu.closest, gpu.met) == (None, 50.0, True) and gpu.show() == "50 s (value error 1.50e-03)"
    assert gpu.show(note=False) == "50 s"
    assert goals["closed loops settle"].show("main") == "100" and goals["closed loops settle"].show() == "–"
    assert goals["time on 2 CPU cores"].met and goals["time on 2 CPU cores"].show("main") == "300 s"
    four, eight = goals["ladder n = 4"], goals["ladder n = 8"]
    assert (four.main, four.closest, four.run, four.met) == (6e-4, 5e-5, "repeats/l", True)
    assert (eight.main, eight.met) == (None, False)
    assert goals["converse n = 12"].closest == 0.3 and not goals["converse n = 12"].met
    # a missed goal says by how much (the closest over the goal's bound); a met one, or one without a bound, not
    assert q.missed_by == pytest.approx(2e-3 / 1e-3) and goals["converse n = 12"].missed_by == pytest.approx(300)
    assert eight.missed_by == pytest.approx(2e-3 / 1e-4)
    assert v.missed_by is None and goals["closed loops settle"].missed_by is None
    assert (q.verdict, eight.verdict, v.verdict) == ("no, 2 x", "no, 20 x", "yes")
    # each names its system, as chapter 8 groups them
    assert [g.system for g in goals.values()] == ["rigid body"] * 7 + ["LQ ladder"] * 2 + ["converse system"]
    assert four.aim == r"$n=4$: value error $\leq10^{-4}$" and v.aim == r"value error $\leq10^{-3}$"
    assert v.note == ""  # one chain
    # a mean of chains (benchmarks/rigid_body.py --mean) is a run too, and the goals say so
    mean = _rigid(8e-4, 2e-3, 3000.0)
    mean["infinite"]["members"] = [{"seed": 0}, {"seed": 1}]
    (results / "repeats" / "mean").mkdir()
    (results / "repeats" / "mean" / "rigid_body.json").write_text(json.dumps(mean))
    goals = {g.key: g for g in paper.dimension_goals(out)}
    v = goals["value error"]
    assert (v.closest, v.run, v.met) == (8e-4, "repeats/mean", True)
    assert v.show() == "8.00e-04 (the mean of 2 chains, 3000 s of training summed)"
    assert goals["value error within 30 min"].run == "repeats/quick"  # its time is its members' summed
    assert goals["ladder n = 4"].note == ""  # one chain
    # and so is a mean of the ladder's chains (benchmarks/dimension.py --mean)
    ladder = _dimension(("lq_ladder", 8, 9e-5))
    ladder["rows"][0].update(members=[{"seed": 0}, {"seed": 1}], wall_s=1500.0)
    (results / "repeats" / "ladder-mean").mkdir()
    (results / "repeats" / "ladder-mean" / "dimension.json").write_text(json.dumps(ladder))
    eight = {g.key: g for g in paper.dimension_goals(out)}["ladder n = 8"]
    assert (eight.closest, eight.run, eight.met) == (9e-5, "repeats/ladder-mean", True)
    assert eight.show() == "9.00e-05 (the mean of 2 chains, 1500 s of training summed)"
    assert eight.largest is None and goals["ladder n = 4"].largest is None  # no chain measured beyond its states
    # the largest error on Omega (benchmarks/largest_error.py), the lowest over the measured chains, must meet the
    # goal too; a missed goal is missed by it
    rows = [
        {"run": "repeats/ladder-mean", "system": "lq_ladder", "n": 8, "ascended": 3e-4},
        {"run": "repeats/l", "system": "lq_ladder", "n": 8, "ascended": 5e-3},
        {"run": "repeats/l", "system": "lq_ladder", "n": 4, "ascended": 8e-5},
        {"run": "", "system": "converse", "n": 12, "ascended": 0.25},
    ]
    (results / "largest_error.json").write_text(json.dumps({"meta": {}, "rows": rows}))
    goals = {g.key: g for g in paper.dimension_goals(out)}
    eight, four, conv = goals["ladder n = 8"], goals["ladder n = 4"], goals["converse n = 12"]
    assert (eight.closest, eight.largest, eight.largest_run, eight.met) == (9e-5, 3e-4, "repeats/ladder-mean", False)
    assert eight.missed_by == pytest.approx(3) and eight.verdict == "no, 3 x"
    assert (four.largest, four.met) == (8e-5, True)
    assert (conv.largest, conv.met) == (0.25, False) and conv.missed_by == pytest.approx(250)


def test_dimension_states_are_the_seeded_uniform_states_of_omega():
    system = ph.systems.lq_ladder(2)
    x = paper.dimension_states(system, 50, 3)
    assert x.shape == (50, 4) and x.dtype == torch.float64
    assert torch.equal(x, paper.dimension_states(system, 50, 3))  # the same seed, the same states
    assert not torch.equal(x, paper.dimension_states(system, 50, 4))
    lo, hi = (torch.as_tensor(system.domain[:, i]) for i in (0, 1))
    assert bool(((x >= lo) & (x <= hi)).all())
