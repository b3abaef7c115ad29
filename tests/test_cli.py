"""Command line: ``python -m pinnhjb train|evaluate``, called in-process through ``pinnhjb.cli.main``."""

from __future__ import annotations

import contextlib
import io
import json
import re
import sys

import pytest
import torch

import pinnhjb as ph
from pinnhjb import cli

TRAIN = [
    "--preset",
    "quick",
    "--set",
    "adam.steps=20",
    "--set",
    "lbfgs=off",
    "--set",
    "eval_points_per_dim=11",
    "--device",
    "cpu",
    "--no-progress",
]


def run(argv) -> int:
    """cli.main's return code as a shell would see it: argparse and --param format errors exit through
    SystemExit, whose message (a string code) the interpreter prints to stderr with status 1."""
    try:
        return cli.main(argv)
    except SystemExit as exc:
        if isinstance(exc.code, str):
            print(exc.code, file=sys.stderr)
            return 1
        return exc.code


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """Train pendulum on [0, 0.5], extend to 1.0 in one step of 0.5; return (return code, stdout, path)."""
    path = tmp_path_factory.mktemp("cli") / "pendulum.pt"
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        rc = cli.main(
            [
                "train",
                "pendulum",
                "--horizon",
                "0.5",
                "--extend-to",
                "1.0",
                "--step",
                "0.5",
                "--seed",
                "3",
                "--out",
                str(path),
                *TRAIN,
            ]
        )
    return rc, out.getvalue(), path


def test_train_writes_checkpoint_and_reports_each_stage(trained):
    rc, out, path = trained
    assert rc == 0
    assert path.exists()
    stages = re.findall(r"T = ([\d.]+): E = ([\d.e+-]+)", out)
    assert [T for T, _ in stages] == ["0.5", "1"]
    assert all(float(E) >= 0 for _, E in stages)
    sol = ph.load(path)
    assert sol.horizons == [0.5, 1.0] and [s.seed for s in sol.stages] == [3, 4]
    assert sol.config.phases == (ph.Adam(steps=20, lr=5e-3),)  # adam.steps=20, lbfgs=off
    assert sol.provenance["seed"] == 3
    # the printed E of the last stage is the stored metric
    assert float(stages[-1][1]) == pytest.approx(sol.metrics["E"], rel=1e-4)


def test_evaluate_prints_E(trained, capsys):
    _, _, path = trained
    assert run(["evaluate", str(path), "--points-per-dim", "11", "--device", "cpu", "--json"]) == 0
    out = capsys.readouterr().out
    assert f"{path}: system pendulum, T = 1" in out
    report = json.loads(out[out.index("{") :])
    assert report["stored"] == ph.load(path).metrics
    assert report["metrics"]["E"] >= 0 and set(report["metrics"]) >= {"E", "E_flow", "E_boundary", "E_zero"}


def test_evaluate_metric_lines_reach_current_stdout(trained, capsys):
    _, _, path = trained
    assert run(["evaluate", str(path), "--points-per-dim", "11", "--device", "cpu"]) == 0
    assert re.search(r"^\s+E = [\d.e+-]+$", capsys.readouterr().out, flags=re.MULTILINE)


def test_train_steady_state(tmp_path, capsys):
    path = tmp_path / "ss.pt"
    assert run(["train", "quartic", "--steady-state", "--out", str(path), *TRAIN]) == 0
    assert "steady-state PINN for quartic" in capsys.readouterr().out
    assert isinstance(ph.load(path), ph.SteadyStateSolution)


def test_train_with_system_parameter(tmp_path):
    path = tmp_path / "r2.pt"
    assert run(["train", "pendulum", "--param", "R=2.0", "--horizon", "0.25", "--out", str(path), *TRAIN]) == 0
    assert ph.load(path).system.params == {"R": 2.0}


@pytest.mark.parametrize(
    "argv",
    [
        ["train", "pendulum", "--param", "R", "--out", "unused.pt"],  # not KEY=VALUE
        ["train", "pendulum", "--set", "adam_steps", "--out", "unused.pt"],  # not KEY=VALUE
        ["train", "nope", "--out", "unused.pt"],  # unknown system
        ["train", "lq", "--out", "unused.pt"],  # needs matrices: not offered
        ["train", "pendulum", "--preset", "fastest", "--out", "unused.pt"],  # unknown preset
        ["train", "pendulum", "--param", "R=-1", "--out", "unused.pt"],  # R not positive definite
        ["train", "pendulum", "--set", "width=0", "--out", "unused.pt"],  # invalid TrainConfig value
        ["train", "pendulum", "--horizon", "0", "--out", "unused.pt", *TRAIN],
        ["train", "pendulum"],  # --out is required
        ["frobnicate"],
    ],
)
def test_bad_arguments_give_nonzero_return_code(argv, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert run(argv) != 0
    assert capsys.readouterr().err  # and say why
    assert not (tmp_path / "unused.pt").exists()


def test_evaluate_missing_or_corrupt_checkpoint(tmp_path, capsys):
    assert run(["evaluate", str(tmp_path / "missing.pt")]) == 2
    assert "no checkpoint" in capsys.readouterr().err
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"garbage")
    assert run(["evaluate", str(bad)]) == 2
    assert "not a readable pinnhjb checkpoint" in capsys.readouterr().err


@pytest.mark.parametrize(
    "extra",
    [
        pytest.param(["--param", "mass=2"], id="unknown-param-key"),
        pytest.param(["--set", "momentum=0.9"], id="unknown-set-field"),
        pytest.param(["--set", "adam_steps=5"], id="flat-optimiser-field"),
        pytest.param(["--set", "lm.steps=5"], id="phase-not-in-recipe"),
        pytest.param(["--set", "adam.momentum=0.9"], id="unknown-phase-field"),
        pytest.param(["--set", "adam.lr=-1"], id="invalid-phase-value"),
        pytest.param(["--set", "sgd=off"], id="drop-missing-phase"),
        pytest.param(
            ["--device", "cuda"],
            id="cuda-unavailable",
            marks=[pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")],
        ),
    ],
)
def test_user_errors_are_reported_cleanly(extra, tmp_path, capsys):
    assert cli.main(["train", "pendulum", "--out", str(tmp_path / "x.pt"), *TRAIN, *extra]) == 2
    assert capsys.readouterr().err.startswith("error: ")
