"""The n-D benchmark scripts (benchmarks/dimension.py, benchmarks/rigid_body.py) end to end on tiny settings: what
they write, and that a sweep in worker processes writes the same rows as a serial one. Their numbers are measured
in ``benchmarks/``, never here."""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import torch

import pinnhjb as ph

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _module(name: str):
    sys.path.insert(0, str(BENCHMARKS))  # the scripts import benchmarks/_common.py as a sibling
    try:
        spec = importlib.util.spec_from_file_location(f"{name}_benchmark", BENCHMARKS / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCHMARKS))
    return module


def test_dimension_rows_are_the_same_in_workers(tmp_path):
    """As a script (its run function is pickled from __main__): serial and two worker processes, same rows."""
    tiny = ["--ladder", "2", "--converse", "", "--compare", "", "--step", "0.5", "--max-horizon", "0.5"]
    tiny += ["--points", "256", "--threads", "1", "--no-progress", "--lm-steps", "5"]
    rows = {}
    for name, extra in (("serial", []), ("workers", ["--workers", "2"])):
        cmd = [sys.executable, str(BENCHMARKS / "dimension.py"), *tiny, "--out", str(tmp_path / name), *extra]
        subprocess.run(cmd, check=True, capture_output=True, timeout=300)
        rows[name] = json.loads((tmp_path / name / "dimension.json").read_text())["rows"]
    for a, b in zip(rows["serial"], rows["workers"], strict=True):
        assert {k: v for k, v in a.items() if k != "wall_s"} == {k: v for k, v in b.items() if k != "wall_s"}
    row = rows["serial"][0]
    assert row["system"] == "lq_ladder" and row["n"] == 2 and row["recipe"] == "default"
    assert 0 < row["value_rel_error"] < 1  # a trained network, measured against the exact V*
    page = (tmp_path / "serial" / "dimension.md").read_text()
    assert "Goal max relative V error <= 1e-4" in page and (tmp_path / "serial" / "dimension.png").stat().st_size
    assert [c["T"] for c in row["chain"]] == [0.5] and row["chain"][0]["rejected_losses"] == []
    assert row["chain"][-1]["value_rel_error"] == row["value_rel_error"]  # the last stage's is the row's
    assert 0 < row["horizon_floor"] < 1  # V_0.5 is far from V*, whatever the network
    dimension = _module("dimension")
    refused = (["--workers", "0"], ["--retries", "-1"], ["--loop-share", "1"], ["--min-progress", "0.5"])
    refused += (["--retries", "1", "--retry-factor", "0.5"], ["--retry-against", "best"])
    for bad in refused:
        with pytest.raises(SystemExit):  # refused before any run
            dimension.main([*tiny, "--out", str(tmp_path / "bad"), *bad])


def test_dimension_retry_rule_reaches_the_config_and_the_page(tmp_path):
    dimension = _module("dimension")
    tiny = ["--ladder", "2", "--converse", "", "--compare", "", "--step", "0.5", "--max-horizon", "0.5"]
    tiny += ["--points", "256", "--threads", "1", "--no-progress", "--lm-steps", "3", "--out", str(tmp_path)]
    dimension.main([*tiny, "--retries", "1", "--retry-factor", "3", "--retry-against", "best"])
    record = json.loads((tmp_path / "dimension.json").read_text())
    assert (record["meta"]["config"]["retry_factor"], record["meta"]["config"]["retry_against"]) == (3, "best")
    assert len(record["rows"][0]["chain"][0]["rejected_losses"]) == 1  # the first stage: tried 1 + retries times
    page = (tmp_path / "dimension.md").read_text()
    assert "over 3x the chain's lowest stage loss (retry_factor, retry_against)" in page


def test_dimension_lm_points_set_every_n_and_are_checked_before_any_run(tmp_path, capsys):
    dimension = _module("dimension")
    tiny = ["--converse", "", "--compare", "", "--step", "0.5", "--max-horizon", "0.5", "--points", "256"]
    tiny += ["--threads", "1", "--no-progress", "--lm-steps", "3"]
    with pytest.raises(SystemExit):  # n = 8's rule has 2000 coarse points, more than 1000
        dimension.main(["--ladder", "2,8", *tiny, "--lm-points", "1000", "--out", str(tmp_path / "bad")])
    assert "n = 8:" in capsys.readouterr().err and not (tmp_path / "bad").exists()
    dimension.main(["--ladder", "2", *tiny, "--lm-points", "900", "--lm-coarse", "none", "--out", str(tmp_path)])
    lm = json.loads((tmp_path / "dimension.json").read_text())["meta"]["configs"]["default"]["phases"][0]
    assert (lm["points"], lm["points_coarse"], lm["steps"]) == (900, None, 3)
    assert "900 LM points per iteration at every n" in (tmp_path / "dimension.md").read_text()


def test_dimension_train_scale_flat_origin_depth_budget_and_save(tmp_path, capsys):
    """--train-scale sets every system's training box, --flat-origin the ansatz, --depth the hidden layers,
    --save stores the chains (loadable, with that box and ansatz), --budget-states follows the largest errors
    along their loops and each stage after the first says how much of its error it carried; wrong values are
    refused before any run."""
    import numpy as np

    import pinnhjb as ph

    dimension = _module("dimension")
    tiny = ["--ladder", "2", "--converse", "", "--compare", "", "--step", "0.5", "--max-horizon", "0.5"]
    tiny += ["--points", "256", "--threads", "1", "--no-progress", "--lm-steps", "3"]
    for bad, says in (
        (["--train-scale", "0.9"], "train_scale must be >= 1"),
        (["--budget-states", "-1"], ">= 0"),
        (["--depth", "0"], "--depth must be an integer >= 1; got 0"),
    ):
        with pytest.raises(SystemExit):
            dimension.main([*tiny, *bad, "--out", str(tmp_path / "bad")])
        assert says in capsys.readouterr().err and not (tmp_path / "bad").exists()
    more = ["--train-scale", "1.5", "--flat-origin", "--cold-start", "--budget-states", "3", "--save"]
    more += ["--max-horizon", "1", "--depth", "2"]
    dimension.main([*tiny, *more, "--out", str(tmp_path)])
    record = json.loads((tmp_path / "dimension.json").read_text())
    (row,) = record["rows"]
    config = record["meta"]["configs"]["default"]
    assert record["meta"]["train_scale"] == 1.5 and config["flat_origin"] and not config["warm_start"]
    assert record["meta"]["depth"] == config["depth"] == 2 and row["weights"] == 3 * 24 + 24 + 24 * 24 + 24 + 25
    sol = ph.load(tmp_path / "chains" / "lq_ladder-n2-default.pt")
    np.testing.assert_allclose(sol.system.train_domain, 1.5 * sol.system.domain)
    assert sol.horizon == row["T"] == 1.0 and all(s.model.flat_origin for s in sol.stages)
    assert sol.config.depth == 2
    first, second = row["chain"]
    assert first["carried"] is None and -1 <= second["carried"] <= 1
    budget = row["budget"]
    assert budget["states"] == 3 and len(budget["share_outside"]) == len(budget["reach_max"]) == 3
    assert max(np.abs(budget["value_error"])) == pytest.approx(row["value_rel_error"], rel=1e-9)  # the largest
    page = (tmp_path / "dimension.md").read_text()
    assert "trained on Omega enlarged 1.5x" in page and "lq_ladder n = 2: of the 3 largest errors" in page
    assert "(flat_origin)" in page and "each stage from fresh weights (no warm start)" in page
    assert "widths by its rule, 2 hidden layers" in page
    assert "the last stage's error, state by state, correlates" in page


TINY_LADDER = [  # dimension.py: the ladder at n = 2, two stages of a few LM iterations, no comparison
    *("--ladder", "2", "--converse", "", "--compare", "", "--step", "0.5", "--max-horizon", "1"),
    *("--points", "256", "--threads", "1", "--no-progress", "--lm-steps", "3", "--budget-states", "0"),
]


def test_dimension_best_start_keeps_the_lower_E_and_says_so(tmp_path, capsys):
    dimension = _module("dimension")
    tiny = TINY_LADDER  # read only
    with pytest.raises(SystemExit):
        dimension.main([*tiny, "--best-start", "--cold-start", "--out", str(tmp_path / "bad")])
    assert "choose one" in capsys.readouterr().err and not (tmp_path / "bad").exists()
    dimension.main([*tiny, "--best-start", "--out", str(tmp_path)])
    record = json.loads((tmp_path / "dimension.json").read_text())
    assert record["meta"]["configs"]["default"]["warm_start"] == "best"
    first, second = record["rows"][0]["chain"]
    assert "started_warm" not in first and second["E_ratio"] <= second["other_E_ratio"]
    kept = "warm" if second["started_warm"] else "fresh"
    page = (tmp_path / "dimension.md").read_text()
    assert f"lq_ladder n = 2: the start kept at T = 1: {kept} (E ratio" in page
    (tmp_path / "dimension.md").unlink()  # the page made again from the JSON alone is the same page
    dimension.main(["--render", str(tmp_path)])
    assert (tmp_path / "dimension.md").read_text() == page
    record["meta"].pop("depth")  # a run stored before --depth or --features-start renders as before
    record["meta"].pop("features_start")
    (tmp_path / "dimension.json").write_text(json.dumps(record))
    dimension.main(["--render", str(tmp_path)])
    assert (tmp_path / "dimension.md").read_text() == page
    record["meta"].pop("best_start")
    (tmp_path / "dimension.json").write_text(json.dumps(record))
    with pytest.raises(SystemExit):
        dimension.main(["--render", str(tmp_path)])
    assert "older dimension.py (its meta has no best_start)" in capsys.readouterr().err
    assert (tmp_path / "dimension.md").read_text() == page  # a refused render leaves the page as it was


def test_dimension_features_start_begins_each_stage_at_its_terminal_cost_and_says_so(tmp_path, capsys):
    dimension = _module("dimension")
    tiny = TINY_LADDER  # read only
    with pytest.raises(SystemExit):
        dimension.main([*tiny, "--features-start", "--cold-start", "--out", str(tmp_path / "bad")])
    assert "--cold-start and --features-start: choose one" in capsys.readouterr().err
    dimension.main([*tiny, "--features-start", "--save", "--out", str(tmp_path)])
    record = json.loads((tmp_path / "dimension.json").read_text())
    assert record["meta"]["configs"]["default"]["warm_start"] == "features" and record["meta"]["features_start"]
    sol = ph.load(tmp_path / "chains" / "lq_ladder-n2-default.pt", ph.systems.lq_ladder(1))
    assert sol.config.warm_start == "features" and len(sol.stages) == 2
    page = (tmp_path / "dimension.md").read_text()
    assert "each stage from the stage before with its last layer zero (it starts at its terminal cost)" in page


def test_dimension_mean_measures_the_mean_of_saved_chains_on_every_member_s_states(tmp_path, capsys):
    """--mean: the mean of two saved chains of one recipe, measured on both seeds' states (the worst its row), its
    wall time the members' summed, the page made again from its JSON; refused before any work: one run, one seed
    twice, another recipe, a run without chains, a mean of means, training flags, the main results folder."""
    dimension = _module("dimension")
    tiny = TINY_LADDER  # read only
    runs = [str(tmp_path / f"seed{seed}") for seed in (0, 1)]
    for seed, out in zip((0, 1), runs):
        dimension.main([*tiny, "--save", "--seed", str(seed), "--out", out])
    dimension.main([*tiny, "--seed", "2", "--out", str(tmp_path / "unsaved")])
    dimension.main([*tiny, "--save", "--seed", "2", "--lm-steps", "4", "--out", str(tmp_path / "other")])
    assert dimension.main(["--mean", *runs, "--threads", "1", "--out", str(tmp_path / "mean")]) == 0
    record = json.loads((tmp_path / "mean" / "dimension.json").read_text())
    (row,) = record["rows"]
    system = ph.systems.lq_ladder(1)
    chains = [ph.load(tmp_path / f"seed{seed}" / "chains" / "lq_ladder-n2-default.pt", system) for seed in (0, 1)]
    mean = ph.AveragedSolution(chains)
    errors = [dimension.true_errors(system, mean, 256, seed)["value_rel_error"] for seed in (0, 1)]
    assert [o["value_rel_error"] for o in row["on_seeds"]] == pytest.approx(errors, rel=1e-9)
    assert row["value_rel_error"] == max(errors) and row["T"] == 1 and len(row["members"]) == 2
    members = [json.loads((tmp_path / f"seed{seed}" / "dimension.json").read_text())["rows"][0] for seed in (0, 1)]
    assert row["wall_s"] == pytest.approx(sum(m["wall_s"] for m in members))
    page = (tmp_path / "mean" / "dimension.md").read_text()
    assert "the mean of chains (generated by `benchmarks/dimension.py --mean`" in page
    assert f"| lq_ladder | 2 | the mean (the worst) | | | 1 | {row['E_ratio']:.1e} | {max(errors):.2e} |" in page
    (tmp_path / "mean" / "dimension.md").unlink()  # the page made again from the JSON alone is the same page
    dimension.main(["--render", str(tmp_path / "mean")])
    assert (tmp_path / "mean" / "dimension.md").read_text() == page
    out = ["--out", str(tmp_path / "refused")]
    for bad, says in (
        ([runs[0]], "two or more stored runs"),
        ([runs[0], runs[0]], "differ in seed"),
        ([runs[0], str(tmp_path / "other")], "differs from"),
        ([runs[0], str(tmp_path / "unsaved")], "cannot load the chain"),
        ([runs[0], str(tmp_path / "mean")], "is itself a mean"),
        ([runs[0], str(tmp_path / "nowhere")], "no stored run at"),
        ([*runs, "--width", "9"], "--width would be ignored"),
        ([*runs, "--out", str(BENCHMARKS / "results")], "pass --out"),
    ):
        with pytest.raises(SystemExit):
            dimension.main([*out, "--mean", *bad])  # a later --out in bad wins
        assert says in capsys.readouterr().err, says
    assert not (tmp_path / "refused").exists()


def test_horizon_floor_is_the_riccati_ode_s_error_and_falls_with_the_horizon():
    import pinnhjb as ph

    dimension = _module("dimension")
    ladder = ph.systems.lq_ladder(2)
    floors = [dimension.horizon_floor(ladder, T, 512, 0) for T in (2.0, 8.0, 12.0)]
    assert floors[0] > floors[1] > floors[2] > 0
    assert dimension.horizon_floor(ph.systems.converse(2), 8.0, 512, 0) is None  # nonlinear: no exact V_T


def test_dimension_deepxde_rows_say_when_it_is_missing(tmp_path):
    """DeepXDE beside the default at n = 2: a measured row where DeepXDE is installed (benchmarks/.venv), a row that
    says "not installed" where it is not (the project's environment); an unknown recipe is a usage error."""
    tiny = ["--ladder", "2", "--converse", "", "--compare", "2", "--against", "deepxde", "--step", "0.5"]
    tiny += ["--max-horizon", "0.5", "--points", "256", "--threads", "1", "--no-progress", "--lm-steps", "5"]
    tiny += ["--out", str(tmp_path)]
    bad = subprocess.run(
        [sys.executable, str(BENCHMARKS / "dimension.py"), *tiny, "--against", "deepxde,lbfgs"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert bad.returncode == 2 and "unknown recipe(s) ['lbfgs']" in bad.stderr
    assert not (tmp_path / "dimension.json").exists()
    if importlib.util.find_spec("deepxde") is not None:
        return  # DeepXDE's own environment: a real DeepXDE run takes minutes (benchmarks/dimension.py measures it)
    subprocess.run([sys.executable, str(BENCHMARKS / "dimension.py"), *tiny], check=True, capture_output=True)
    record = json.loads((tmp_path / "dimension.json").read_text())
    assert [r["recipe"] for r in record["rows"]] == ["default"]
    assert record["not_run"] == [
        {"system": "lq_ladder", "recipe": "deepxde", "n": 2, "m": 1, "status": "not installed"}
    ]
    assert "| lq_ladder | deepxde | 2 | 1 | not installed |" in (tmp_path / "dimension.md").read_text()


def test_rigid_body_writes_reference_checkpoint_and_goals(tmp_path):
    rigid_body = _module("rigid_body")
    args = ["--reference-points", "4", "--width", "8", "--points", "200", "--step", "0.5", "--max-horizon", "0.5"]
    args += ["--closed-loop", "3", "--t-final", "2", "--dt", "0.05", "--skip-finite", "--save", "--threads", "1"]
    args += ["--no-progress", "--artifacts", str(tmp_path / "artifacts"), "--out", str(tmp_path / "out")]
    args += ["--min-progress", "none", "--lm-steps", "5"]  # no stall rule: exactly 5 LM iterations
    args += ["--pool-size", "300"]
    assert rigid_body.main(args) == 0
    assert (tmp_path / "artifacts" / "reference" / "rigid_body_inf_4.npz").exists()
    assert (tmp_path / "artifacts" / "checkpoints" / "rigid_body_inf" / "seed0.pt").exists()
    result = json.loads((tmp_path / "out" / "rigid_body.json").read_text())
    assert result["meta"]["reference"]["replay_max_rel"] < 1e-6  # the reference's own check
    assert [(r["T"], r["iterations"], r["stop_reason"]) for r in result["infinite"]["stages"]] == [(0.5, 5, "lm_steps")]
    assert result["infinite"]["closed_loop"]["states"] == 3
    page = (tmp_path / "out" / "rigid_body.md").read_text()
    assert "| max abs(V - V_ref) / max V_ref <= 1e-3 |" in page and "3 x 8 network" in page
    assert "(no stall rule: 5 iterations per stage," in page and "| 5 (lm_steps) |" in page
    assert ", CPU; torch" in page and result["meta"]["machine"].endswith(", CPU")  # where it trained
    assert "| under 30 minutes on 2 CPU cores |" in page  # the time goal of the device it ran on
    assert result["meta"]["config"]["pool_size"] == 300 and ", 300 training states per stage (pool_size;" in page
    for bad in (["--stall-windows", "0"], ["--pool-size", "0"], ["--adaptive", "1"]):  # refused before any run
        with pytest.raises(SystemExit):
            rigid_body.main([*args, *bad])
    # carried on from the stored run: its stage kept, one more trained with the same settings, one chain
    more = [*args, "--max-horizon", "1", "--resume", str(tmp_path / "out"), "--out", str(tmp_path / "more")]
    assert rigid_body.main(more) == 0
    carried = json.loads((tmp_path / "more" / "rigid_body.json").read_text())["infinite"]
    assert [r["T"] for r in carried["stages"]] == [0.5, 1.0]
    assert carried["stages"][0] == result["infinite"]["stages"][0]
    assert carried["wall_s"] > result["infinite"]["wall_s"]  # the stored run's time carried on
    assert rigid_body.main([*args, "--max-horizon", "1", "--out", str(tmp_path / "straight")]) == 0
    straight = json.loads((tmp_path / "straight" / "rigid_body.json").read_text())["infinite"]["stages"]
    for key in ("E_ratio", "value_rel_error"):  # the same stage as one uninterrupted run trains
        assert straight[1][key] == pytest.approx(carried["stages"][1][key], rel=1e-6)
    assert f"the stored run `{tmp_path / 'out'}` carried on" in (tmp_path / "more" / "rigid_body.md").read_text()
    chain = tmp_path / "straight.pt"  # kept aside: each run below stores its own chain where this one was
    shutil.copy(tmp_path / "artifacts" / "checkpoints" / "rigid_body_inf" / "seed0.pt", chain)
    cold = [*args, "--max-horizon", "1.5", "--resume", str(tmp_path / "straight"), "--resume-chain", str(chain)]
    cold += ["--cold-start"]
    cold += ["--out", str(tmp_path / "cold")]  # carried on from fresh weights: allowed, and said
    assert rigid_body.main(cold) == 0
    page = (tmp_path / "cold" / "rigid_body.md").read_text()
    assert "each stage from fresh weights (no warm start) from here on" in page
    best = [*args, "--max-horizon", "1.5", "--resume", str(tmp_path / "straight"), "--resume-chain", str(chain)]
    best += ["--best-start"]
    assert rigid_body.main([*best, "--out", str(tmp_path / "best")]) == 0  # both starts tried, the lower E kept
    row = json.loads((tmp_path / "best" / "rigid_body.json").read_text())["infinite"]["stages"][-1]
    fresh = json.loads((tmp_path / "cold" / "rigid_body.json").read_text())["infinite"]["stages"][-1]
    tried_fresh = row["other"] if row["started_warm"] else row  # the --cold-start stage, trained again
    assert tried_fresh["E_ratio"] == pytest.approx(fresh["E_ratio"], rel=1e-6)
    assert row["E_ratio"] < row["other"]["E_ratio"]
    page = (tmp_path / "best" / "rigid_body.md").read_text()
    assert "the lower E kept (warm_start='best') from here on" in page
    assert f"| {'warm' if row['started_warm'] else 'fresh'} ({row['other']['E_ratio']:.1e}, " in page
    with pytest.raises(SystemExit):  # one start rule at a time
        rigid_body.main([*best, "--cold-start", "--out", str(tmp_path / "both")])
    for bad in (["--points", "250"], ["--seed", "1"], ["--max-horizon", "0.5"]):  # other settings: refused
        with pytest.raises(SystemExit):
            rigid_body.main([*more, *bad])
    longer = [*args, "--max-horizon", "1.5", "--resume", str(tmp_path / "straight"), "--resume-chain", str(chain)]
    longer += ["--lm-steps", "7", "--adaptive", "0.5", "--out", str(tmp_path / "longer")]
    assert rigid_body.main(longer) == 0  # longer stages, half of each iteration's points chosen by their residual
    run = json.loads((tmp_path / "longer" / "rigid_body.json").read_text())
    assert [r["iterations"] for r in run["infinite"]["stages"]] == [5, 5, 7]
    assert ph.TrainConfig.from_dict(run["meta"]["config"]).phase("lm").adaptive == 0.5
    page = (tmp_path / "longer" / "rigid_body.md").read_text()
    assert "5 LM iterations each, those here 7; its stages drew each iteration's points as usual, those here " in page
    assert "(50% of each iteration's points chosen where the residual is largest; no stall rule: 7 " in page


def test_rigid_body_mean_checks_the_mean_of_stored_chains_as_a_run(tmp_path, capsys):
    rigid_body = _module("rigid_body")
    args = ["--reference-points", "4", "--width", "8", "--points", "200", "--step", "0.5", "--max-horizon", "0.5"]
    args += ["--closed-loop", "3", "--t-final", "2", "--dt", "0.05", "--skip-finite", "--save", "--threads", "1"]
    args += ["--no-progress", "--artifacts", str(tmp_path / "artifacts"), "--min-progress", "none"]
    args += ["--lm-steps", "3", "--pool-size", "300"]
    for seed in (0, 1):
        assert rigid_body.main([*args, "--seed", str(seed), "--out", str(tmp_path / f"s{seed}")]) == 0
    runs = [str(tmp_path / f"s{seed}") for seed in (0, 1)]
    common = ["--reference-points", "4", "--closed-loop", "3", "--t-final", "2", "--dt", "0.05", "--no-progress"]
    common += ["--artifacts", str(tmp_path / "artifacts")]
    assert rigid_body.main([*common, "--mean", *runs, "--out", str(tmp_path / "mean")]) == 0
    result = json.loads((tmp_path / "mean" / "rigid_body.json").read_text())
    members = [json.loads((tmp_path / f"s{seed}" / "rigid_body.json").read_text()) for seed in (0, 1)]
    (row,) = result["infinite"]["stages"]
    assert row["T"] == 0.5 and row["stop_reason"] == "mean of 2"
    assert result["infinite"]["wall_s"] == pytest.approx(sum(m["infinite"]["wall_s"] for m in members))
    assert [m["seed"] for m in result["infinite"]["members"]] == [0, 1] == result["meta"]["seed"]
    # the mean's error, recomputed from the two stored chains
    ref = ph.reference.ReferenceGrid.load(tmp_path / "artifacts" / "reference" / "rigid_body_inf_4.npz")
    chains = [ph.load(tmp_path / "artifacts" / "checkpoints" / "rigid_body_inf" / f"seed{s}.pt") for s in (0, 1)]
    mean_err = ref.value_error(ph.AveragedSolution(chains)).max()
    assert row["value_rel_error"] == pytest.approx(mean_err, rel=1e-9)
    assert result["infinite"]["closed_loop"]["states"] == 3
    page = (tmp_path / "mean" / "rigid_body.md").read_text()
    assert "the mean of chains (generated by `benchmarks/rigid_body.py --mean`" in page
    assert f"| the mean | | | 0.5 | {row['E_ratio']:.1e} | {row['value_rel_error']:.2e} |" in page
    assert "| max abs(V - V_ref) / max V_ref <= 1e-3 |" in page
    # refused before any work: one run, a run twice (one seed), another recipe, a mean of means, the main page,
    # chains that do not match, a mean carried on
    assert rigid_body.main([*args, "--seed", "2", "--width", "9", "--out", str(tmp_path / "w9")]) == 0
    bad = [
        (["--mean", runs[0]], "two or more stored runs"),
        (["--mean", runs[0], runs[0]], "differ in seed"),
        (["--mean", runs[0], str(tmp_path / "w9")], "the training config"),
        (["--mean", runs[0], str(tmp_path / "mean")], "is itself a mean"),
        (["--mean", runs[0], str(tmp_path / "nowhere")], "no stored run at"),
        (["--mean", *runs, "--mean-chains", "a.pt"], "one chain per run"),
        (["--mean", *runs, "--width", "9", "--skip-finite"], "--skip-finite, --width would be ignored"),
    ]
    for extra, message in bad:
        with pytest.raises(SystemExit):
            rigid_body.main([*common, *extra, "--out", str(tmp_path / "x")])
        assert message in capsys.readouterr().err
    with pytest.raises(SystemExit):
        rigid_body.main([*common, "--mean", *runs])
    assert "--mean: pass --out" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        rigid_body.main([*args, "--max-horizon", "1", "--resume", str(tmp_path / "mean"), "--out", str(tmp_path / "x")])
    assert "is a mean of chains (--mean), not one chain" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_time_goal_follows_the_device():
    rigid_body = _module("rigid_body")
    assert rigid_body._time_goal(200.0, "cpu") == "| under 30 minutes on 2 CPU cores | 200 s | yes |"
    assert rigid_body._time_goal(200.0, "cuda") == "| under 3 minutes on one GPU | 200 s | no |"


@pytest.mark.skipif(__import__("torch").cuda.is_available(), reason="CUDA is available here")
@pytest.mark.parametrize("name", ["rigid_body", "dimension"])
def test_cuda_without_cuda_is_refused_before_any_run(name, tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_:
        _module(name).main(["--device", "cuda", "--out", str(tmp_path)])
    assert exit_.value.code == 2 and "CUDA is not available" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_dimension_on_cuda_leaves_deepxde_to_the_cpu_benchmark(monkeypatch, tmp_path, capsys):
    """DeepXDE is compared on the CPU only: with --device cuda it is a usage error (even where a GPU is present)."""
    import torch

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    with pytest.raises(SystemExit) as exit_:
        _module("dimension").main(["--device", "cuda", "--against", "deepxde", "--out", str(tmp_path)])
    assert exit_.value.code == 2 and "DeepXDE runs on the CPU here" in capsys.readouterr().err


def test_cuda_script_is_valid_and_calls_what_exists():
    """benchmarks/cuda.sh runs only on a lent GPU: here, that it parses and that every script and test file it
    calls is there, with options those scripts take."""
    script = BENCHMARKS / "cuda.sh"
    subprocess.run(["bash", "-n", str(script)], check=True)
    text = script.read_text()
    root = BENCHMARKS.parent
    for path in ("tests/test_cuda.py", "benchmarks/rigid_body.py", "benchmarks/dimension.py"):
        assert path in text and (root / path).exists()
    helps = {
        name: subprocess.run(
            [sys.executable, str(BENCHMARKS / f"{name}.py"), "--help"], capture_output=True, text=True, check=True
        ).stdout
        for name in ("rigid_body", "dimension")
    }
    for option in ("--mean", "--seed", "--save", "--artifacts", "--closed-loop", "--budget-states"):
        assert option in text and option in helps["rigid_body"]
    assert (root / "artifacts" / "reference" / "rigid_body_inf_1000.npz").exists()  # the mean part copies it
    for option in ("--device", "--skip-finite", "--note", "--out", "--no-progress", "--width", "--points"):
        assert option in helps["rigid_body"]
    for option in ("--min-progress", "--lm-steps", "--train-scale", "--max-time", "--closed-loop", "--t-final"):
        assert option in helps["rigid_body"]
    for option in ("--device", "--ladder", "--converse", "--compare", "--out", "--max-horizon"):
        assert option in helps["dimension"]


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks what cuda.sh does where CUDA is absent")
def test_cuda_script_checks_its_parts_and_skips_long_runs_after_a_failed_tiny_one(tmp_path):
    script = str(BENCHMARKS / "cuda.sh")
    env = {**os.environ, "OUT": str(tmp_path), "PYTHON": sys.executable}
    bad = subprocess.run(["bash", script, "rigid", "gpu"], capture_output=True, text=True, env=env)
    assert bad.returncode == 2 and "unknown part 'gpu'" in bad.stderr and not (tmp_path / "log.txt").exists()
    # no CUDA here: the tiny rigid-body run is a usage error, and no long rigid-body run starts
    subprocess.run(
        ["bash", script, "rigid", "best", "mean"], capture_output=True, text=True, env=env, cwd=BENCHMARKS.parent
    )
    log = (tmp_path / "log.txt").read_text()
    assert log.count("benchmarks/rigid_body.py") == 1 and "--lm-steps 5" in log
    assert "CUDA is not available" in log and not (tmp_path / "rigid_body").exists()
    assert not list(tmp_path.glob("rigid_body_best*"))


def test_dimension_save_keeps_every_stage_of_a_run_cut_short(tmp_path, monkeypatch):
    """With --save the chain is written after every stage: a run stopped during its second stage leaves the
    first on disk, loadable, with its wall time so far; --resume carries it on."""
    import pinnhjb as ph

    dimension = _module("dimension")

    def cut(self, sol, to, **kwargs):
        raise KeyboardInterrupt("cut short during the second stage")

    monkeypatch.setattr(ph.FiniteHorizonSolver, "extend", cut)
    tiny = ["--ladder", "2", "--converse", "", "--compare", "", "--step", "0.5", "--max-horizon", "1"]
    tiny += ["--points", "256", "--threads", "1", "--no-progress", "--lm-steps", "3", "--save"]
    with pytest.raises(KeyboardInterrupt):
        dimension.main([*tiny, "--out", str(tmp_path)])
    sol = ph.load(tmp_path / "chains" / "lq_ladder-n2-default.pt")
    assert sol.horizon == 0.5 and len(sol.stages) == 1 and sol.provenance["wall_s"] > 0
    monkeypatch.undo()
    dimension.main([*tiny, "--resume", str(tmp_path), "--out", str(tmp_path / "on")])
    (row,) = json.loads((tmp_path / "on" / "dimension.json").read_text())["rows"]
    assert row["T"] == 1.0 and row["stages"] == 2 and row["wall_s"] > sol.provenance["wall_s"]


def test_dimension_resume_carries_a_saved_chain_on_as_one_run_would(tmp_path, capsys):
    """--resume extends the chains a --save run stored, to the same chain and errors as one uninterrupted run,
    its wall time carried on; other settings, a horizon no further, other recipes or no chain are usage errors
    before any work."""
    dimension = _module("dimension")
    tiny = ["--ladder", "2", "--converse", "", "--compare", "", "--step", "0.5", "--points", "256"]
    tiny += ["--threads", "1", "--no-progress", "--lm-steps", "3", "--budget-states", "0"]
    dimension.main([*tiny, "--max-horizon", "1", "--out", str(tmp_path / "straight")])
    dimension.main([*tiny, "--max-horizon", "0.5", "--save", "--out", str(tmp_path / "half")])
    resume = ["--resume", str(tmp_path / "half")]
    for bad, says in (
        (["--max-horizon", "1", "--lm-steps", "4"], "other settings: config"),
        (["--max-horizon", "1", "--seed", "1"], "other settings: seed"),
        (["--max-horizon", "0.5"], "ends at T = 0.5; raise --max-horizon (0.5)"),
        (["--max-horizon", "1", "--compare", "2"], "the default recipe's chains"),
        (["--max-horizon", "1", "--ladder", "4"], "cannot load the chain of lq_ladder n = 4"),
    ):
        with pytest.raises(SystemExit):
            dimension.main([*tiny, *resume, *bad, "--out", str(tmp_path / "bad")])
        assert says in capsys.readouterr().err and not (tmp_path / "bad").exists()
    dimension.main([*tiny, *resume, "--max-horizon", "1", "--out", str(tmp_path / "carried")])
    straight, half, carried = (
        json.loads((tmp_path / name / "dimension.json").read_text())["rows"][0]
        for name in ("straight", "half", "carried")
    )
    assert carried["T"] == straight["T"] == 1.0 and carried["stages"] == 2
    for key in ("value_rel_error", "grad_mean_rel_error", "E_ratio"):
        assert carried[key] == pytest.approx(straight[key], rel=1e-6)
    assert carried["wall_s"] > half["wall_s"]
    page = (tmp_path / "carried" / "dimension.md").read_text()
    assert f"the chains of `{tmp_path / 'half'}` carried on" in page


def test_dimension_terminal_lqr_starts_the_converse_chain_from_x_P_x(tmp_path, capsys):
    """--terminal lqr gives the converse chain's first stage the linearisation's LQR value as its terminal cost
    (stored with the chain, named on the page, kept by --resume); on the LQ ladder, whose V* that is, it is
    refused before any run, and a chain saved before the option resumes as the zero terminal cost it had."""
    import numpy as np

    dimension = _module("dimension")
    tiny = ["--ladder", "", "--converse", "2", "--compare", "", "--converse-step", "0.5", "--points", "256"]
    tiny += ["--threads", "1", "--no-progress", "--lm-steps", "3", "--budget-states", "0"]
    with pytest.raises(SystemExit):
        dimension.main([*tiny, "--ladder", "2", "--terminal", "lqr", "--out", str(tmp_path / "bad")])
    assert "start at the answer" in capsys.readouterr().err and not (tmp_path / "bad").exists()
    dimension.main([*tiny, "--terminal", "lqr", "--max-horizon", "0.5", "--save", "--out", str(tmp_path / "lqr")])
    sol = ph.load(tmp_path / "lqr" / "chains" / "converse-n2-default.pt")
    x = torch.tensor([[0.3, -0.2], [0.0, 0.5]], dtype=torch.float64)
    P = torch.as_tensor(sol.system.lqr_value())
    np.testing.assert_allclose(sol.stages[0].model.terminal_cost(x).detach(), ((x @ P) * x).sum(-1), rtol=1e-12)
    assert (
        "the first terminal cost x'Px (the linearisation's LQR value)"
        in (tmp_path / "lqr" / "dimension.md").read_text()
    )
    resume = ["--resume", str(tmp_path / "lqr"), "--max-horizon", "1"]
    with pytest.raises(SystemExit):  # a chain from x'Px does not carry on as one from zero
        dimension.main([*tiny, *resume, "--out", str(tmp_path / "bad")])
    assert "other settings: terminal" in capsys.readouterr().err
    dimension.main([*tiny, *resume, "--terminal", "lqr", "--out", str(tmp_path / "on")])
    (row,) = json.loads((tmp_path / "on" / "dimension.json").read_text())["rows"]
    assert row["T"] == 1.0 and row["stages"] == 2
    dimension.main([*tiny, "--max-horizon", "0.5", "--save", "--out", str(tmp_path / "zero")])
    chain = tmp_path / "zero" / "chains" / "converse-n2-default.pt"
    stored = ph.load(chain)
    stored.provenance["settings"].pop("terminal")  # as a chain saved before --terminal was
    ph.save(stored, chain, **{k: v for k, v in stored.provenance.items() if k in ("wall_s", "settings", "machine")})
    dimension.main([*tiny, "--resume", str(tmp_path / "zero"), "--max-horizon", "1", "--out", str(tmp_path / "z1")])
    (row,) = json.loads((tmp_path / "z1" / "dimension.json").read_text())["rows"]
    assert row["T"] == 1.0 and "first terminal cost" not in (tmp_path / "z1" / "dimension.md").read_text()


def test_largest_error_measures_stored_chains_beyond_their_states(tmp_path, capsys):
    """benchmarks/largest_error.py on one stored chain: its own states give the number it stored, and Omega's
    vertices a number at least as large in abs(V - V*) (the chapters' goals read this table)."""
    module = _module("largest_error")
    module.main(["--only", "ladder-n4-best-start", "--starts", "2", "--out", str(tmp_path)])
    rows = json.loads((tmp_path / "largest_error.json").read_text())["rows"]
    stored = json.loads((BENCHMARKS / "results" / "repeats" / "ladder-n4-best-start" / "dimension.json").read_text())
    assert [r["run"] for r in rows] == ["repeats/ladder-n4-best-start"]
    (row,) = rows
    assert row["sampled"] == pytest.approx(stored["rows"][-1]["value_rel_error"], rel=1e-6) == row["stored"]
    assert row["ascended"] >= row["vertices"] > 0 and row["states"] == stored["meta"]["points"]
    assert "ladder-n4-best-start" in (tmp_path / "largest_error.md").read_text()
    with pytest.raises(SystemExit):  # nothing to measure is a usage error, before any work
        module.main(["--only", "no-such-run", "--out", str(tmp_path / "none")])
    assert not (tmp_path / "none").exists()
    capsys.readouterr()
