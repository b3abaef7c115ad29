"""Independent runs on an executor (pinnhjb.executor): serial, local processes, a Dask cluster; same results.

The runs are tiny (quick preset, 20 Adam steps, no L-BFGS). Every parallel result is compared bit for bit with a
serial run at the same torch thread count (1).
"""

from __future__ import annotations

import shutil
import sys

import numpy as np
import pytest
import torch

import pinnhjb as ph
from pinnhjb import cli
from pinnhjb.executor import check, executor, map_runs
from pinnhjb.paper import reproduce

TASKS = [("pendulum", 0), ("quartic", 1)]


def tiny_run(task: tuple) -> dict:
    """Train a tiny one-stage PINN for (system, seed); its weights, E and the thread count it ran at."""
    name, seed = task
    config = ph.TrainConfig.preset("quick", eval_points_per_dim=11).with_phase("adam", steps=20).without_phase("lbfgs")
    solver = ph.FiniteHorizonSolver(ph.get_system(name), config=config, seed=seed, device="cpu", progress=False)
    sol = solver.solve(0.5)
    weights = torch.cat([p.detach().reshape(-1) for m in sol._models() for p in m.parameters()])
    return {"task": task, "weights": weights.numpy(), "E": sol.metrics["E"], "threads": torch.get_num_threads()}


def fails_on_quartic(task: tuple) -> str:
    """Raise for the quartic task; the system's name otherwise."""
    if task[0] == "quartic":
        raise FloatingPointError(f"diverged: {task}")
    return task[0]


def _same(a: list[dict], b: list[dict]):
    assert [r["task"] for r in a] == [r["task"] for r in b] == TASKS  # task order, whatever finished first
    for x, y in zip(a, b):
        assert np.array_equal(x["weights"], y["weights"]) and x["E"] == y["E"], x["task"]


@pytest.fixture(scope="module")
def serial():
    return map_runs(tiny_run, TASKS, threads=1, progress=False)


@pytest.mark.parametrize(
    "kw, error, match",
    [
        ({"workers": 0}, ValueError, r"workers must be an integer >= 1; got 0"),
        ({"workers": 2.0}, TypeError, r"workers must be an integer"),
        ({"workers": True}, TypeError, r"workers must be an integer"),
        ({"threads": 0}, ValueError, r"threads must be an integer >= 1"),
        ({"scheduler": "localhost:8786"}, ValueError, r"not a Dask address.*did you mean 'tcp://localhost:8786'"),
        ({"scheduler": "http://host:8786"}, ValueError, r"unknown scheme 'http'"),
        ({"scheduler": "tcp://host"}, ValueError, r"expected tcp://HOST:PORT"),
        ({"scheduler": "tcp://host:99999"}, ValueError, r"port 1..65535"),
        ({"scheduler": 8786}, TypeError, r"address string"),
        ({"workers": 2, "scheduler": "tcp://host:8786"}, ValueError, r"either workers=2 .* or scheduler"),
    ],
)
def test_bad_arguments_are_refused_before_any_run(kw, error, match, tmp_path):
    calls = []
    with pytest.raises(error, match=match):
        map_runs(calls.append, TASKS, progress=False, **kw)
    assert not calls
    with pytest.raises(error, match=match):
        reproduce.run(out=tmp_path / "r", seeds=1, quick=True, only=["quartic_steady"], progress=False, **kw)
    assert not (tmp_path / "r").exists()  # no reference grid, no checkpoint


def test_a_scheduler_without_distributed_names_the_pip_command(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import distributed -> ImportError
    with pytest.raises(ImportError, match=r"pip install distributed==[\d.]+ dask==[\d.]+"):
        check(scheduler="tcp://127.0.0.1:8786")
    assert check(workers=3) == "processes" and check(workers=1) == "serial" and check() == "serial"


def test_the_command_line_refuses_bad_workers_and_scheduler(tmp_path, capsys):
    for extra, match in [
        (["--workers", "0"], "--workers / --scheduler / --threads: workers must be an integer >= 1"),
        (["--workers", "2", "--scheduler", "tcp://h:8786"], "not both"),
        (["--scheduler", "h:8786"], "did you mean 'tcp://h:8786'"),
    ]:
        assert cli.main(["reproduce", "--quick", "--no-progress", "--out", str(tmp_path / "r"), *extra]) == 2
        assert match in capsys.readouterr().err
    assert not (tmp_path / "r").exists()


def test_a_failing_run_names_its_task_and_keeps_the_finished_results():
    for kw in ({}, {"workers": 2}):
        with pytest.raises(FloatingPointError, match="diverged") as info:  # the run's own exception type
            map_runs(fails_on_quartic, TASKS, progress=False, label=lambda t: f"system {t[0]}, seed {t[1]}", **kw)
        note = "\n".join(info.value.__notes__)
        assert "in run 2 of 2 (system quartic, seed 1)" in note and "1 run(s) finished" in note, kw
        assert info.value.finished == {0: "pendulum"}


def test_a_function_that_does_not_pickle_is_refused_before_any_run():
    with pytest.raises(TypeError, match="module-level function"):
        map_runs(lambda t: t, TASKS, workers=2, progress=False)


def test_serial_runs_keep_this_process_thread_count_unless_given(serial):
    before = torch.get_num_threads()
    with executor(threads=2) as ex:
        assert ex.submit(torch.get_num_threads).result() == 2
    assert torch.get_num_threads() == before
    assert [r["threads"] for r in serial] == [1, 1]


def test_local_processes_train_the_same_weights_as_a_serial_run(serial):
    parallel = map_runs(tiny_run, TASKS, workers=2, progress=False)
    assert [r["threads"] for r in parallel] == [1, 1]  # one torch thread per worker by default
    _same(serial, parallel)


def test_a_dask_cluster_trains_the_same_weights_as_a_serial_run(serial):
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as c:
        parallel = map_runs(tiny_run, TASKS, scheduler=c.scheduler_address, progress=False)
    assert [r["threads"] for r in parallel] == [1, 1]
    _same(serial, parallel)


def _checkpoint(path) -> dict:
    """A checkpoint's contents without its provenance (time stamps, command line)."""
    payload = torch.load(path, weights_only=False)
    payload.pop("provenance", None)
    return payload


def _equal(a, b) -> bool:
    """Equal contents, bit for bit, but for wall times (keys with ``wall`` in their name)."""
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a if "wall" not in k)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b))
    if isinstance(a, torch.Tensor):
        return isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b)
    if isinstance(a, np.ndarray):
        return np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
    return a == b or (a != a and b != b)  # NaN == NaN here


def test_reproduce_with_workers_writes_what_a_serial_run_writes(tmp_path):
    only = ["pendulum_steady", "quartic_steady"]
    serial, parallel = tmp_path / "serial", tmp_path / "parallel"
    a = reproduce.run(out=serial, seeds=1, quick=True, only=only, progress=False, threads=1)
    shutil.copytree(serial / "reference", parallel / "reference")  # grids are reused: train only
    b = reproduce.run(out=parallel, seeds=1, quick=True, only=only, progress=False, workers=2)
    untimed = [{k: v for k, v in r.items() if "time" not in k} for r in a["records"]]
    assert untimed == [{k: v for k, v in r.items() if "time" not in k} for r in b["records"]]
    assert [r["case"] for r in b["records"]] == only
    assert b["meta"]["runs"] == {"workers": 2, "scheduler": False, "threads": 1} and "runs" not in a["meta"]
    for case in only:
        path = ph.paper.checkpoint_path(serial, case, 0)
        assert _equal(_checkpoint(path), _checkpoint(ph.paper.checkpoint_path(parallel, case, 0))), case
