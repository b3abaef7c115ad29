"""Checkpoints: round trips, safe loading, mismatch detection, user systems, atomic writes."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import pinnhjb as ph
from pinnhjb.pinn import CallableTerminalCost, FiniteHorizonValue
from pinnhjb.solution import FiniteHorizonSolution, Stage
from pinnhjb.storage import FORMAT, CheckpointError
from pinnhjb.training import TrainHistory

FAST = dict(phases=(ph.Adam(steps=30, lr=5e-3),), eval_points_per_dim=11)
PROVENANCE_KEYS = {"torch", "numpy", "pinnhjb", "created"}


@pytest.fixture(scope="module")
def config():
    return ph.TrainConfig.preset("quick", **FAST)


@pytest.fixture(scope="module")
def two_stage(config):
    """Pendulum on [0, 0.5] extended to 1.0, with a quadratic terminal cost x'Px."""
    solver = ph.FiniteHorizonSolver(ph.systems.pendulum(), config, seed=4, device="cpu", progress=False)
    return solver.extend(solver.solve(0.5, terminal_cost=np.diag([1.0, 0.5])), to=1.0)


@pytest.fixture(scope="module")
def steady(config):
    return ph.SteadyStateSolver(ph.systems.pendulum(), config, seed=2, device="cpu", progress=False).solve()


@pytest.fixture(scope="module")
def saved(tmp_path_factory, two_stage, steady):
    folder = tmp_path_factory.mktemp("ckpt")
    return {"fh": ph.save(two_stage, folder / "fh.pt", note="test"), "ss": ph.save(steady, folder / "ss.pt")}


@pytest.fixture(scope="module")
def x_test():
    return np.random.default_rng(0).uniform(-1, 1, (50, 2))


def user_system(name="mine"):
    def f(x):
        return torch.stack([x[:, 1], -x[:, 0] - x[:, 1]], dim=-1)

    def g(x):
        out = torch.zeros(x.shape[0], 2, 1, dtype=x.dtype)
        out[:, 1, 0] = 1.0
        return out

    return ph.ControlAffineSystem(name, f, g, lambda x: (x**2).sum(-1), [[1.0]], domain=[[-1, 1], [-1, 1]])


def untrained_solution(system, config) -> FiniteHorizonSolution:
    torch.manual_seed(0)
    model = FiniteHorizonValue(system.n, 1.0, system.train_domain, width=config.width, depth=config.depth)
    model.float().requires_grad_(False)
    return FiniteHorizonSolution(system, config, [Stage(model, 0.0, TrainHistory(), seed=0)], {"kind": "zero"})


# ------------------------------------------------------------------------------ round trips
def test_finite_horizon_round_trip(saved, two_stage, x_test):
    loaded = ph.load(saved["fh"])
    assert isinstance(loaded, ph.FiniteHorizonSolution)
    assert loaded.system.spec() == two_stage.system.spec()
    assert loaded.config == two_stage.config
    assert loaded.horizons == two_stage.horizons and len(loaded.stages) == 2
    assert [s.seed for s in loaded.stages] == [s.seed for s in two_stage.stages]
    assert loaded.terminal_spec == two_stage.terminal_spec and loaded.terminal_spec["kind"] == "quadratic"
    assert loaded.interrupted is False
    for t in (0.0, 0.3, 0.5, 0.8, 1.0):
        np.testing.assert_array_equal(loaded.value(x_test, t), two_stage.value(x_test, t))
    np.testing.assert_array_equal(loaded.policy(x_test), two_stage.policy(x_test))
    for a, b in zip(loaded.stages, two_stage.stages):
        assert a.metrics == b.metrics
        assert a.history.to_dict() == b.history.to_dict()
    assert loaded.metrics == two_stage.metrics and "E" in loaded.metrics
    assert loaded.evaluate(11) == two_stage.evaluate(11)
    assert PROVENANCE_KEYS <= set(loaded.provenance) and loaded.provenance["note"] == "test"
    assert loaded.provenance["pinnhjb"] == ph.__version__
    assert loaded.provenance["torch"] == str(torch.__version__) and loaded.provenance["numpy"] == np.__version__


def test_steady_state_round_trip(saved, steady, x_test):
    loaded = ph.load(saved["ss"])
    assert isinstance(loaded, ph.SteadyStateSolution)
    assert loaded.config == steady.config and loaded.seed == steady.seed
    np.testing.assert_array_equal(loaded.value(x_test), steady.value(x_test))
    np.testing.assert_array_equal(loaded.policy(x_test), steady.policy(x_test))
    assert loaded.metrics == steady.metrics and "E" in loaded.metrics
    assert loaded.history.to_dict() == steady.history.to_dict()
    assert PROVENANCE_KEYS <= set(loaded.provenance)


def test_loaded_solution_can_be_extended(saved, two_stage, config):
    loaded = ph.load(saved["fh"])
    solver = ph.FiniteHorizonSolver(
        loaded.system, config.with_phase("adam", steps=2), seed=4, device="cpu", progress=False
    )
    longer = solver.extend(loaded, to=1.5)
    x = torch.rand(8, 2)
    with torch.no_grad():
        assert torch.equal(longer.stages[2].model.terminal_cost(x), two_stage.stages[1].model(x, 0.0))


def test_file_is_plain_weights_only_data(saved):
    for path in saved.values():
        raw = torch.load(path, weights_only=True)
        assert raw["format"] == FORMAT and raw["version"] == 1
        assert raw["system"]["builder"] == "pendulum"
    raw = torch.load(saved["fh"], weights_only=True)
    assert raw["kind"] == "finite_horizon" and len(raw["stages"]) == 2
    assert all(isinstance(v, torch.Tensor) for v in raw["stages"][0]["state"].values())


def test_no_temporary_files_left_behind(saved, tmp_path, steady):
    assert sorted(p.name for p in saved["fh"].parent.iterdir()) == ["fh.pt", "ss.pt"]
    target = tmp_path / "sub" / "again.pt"  # parent folders are created
    for _ in range(2):  # overwriting is fine too
        assert ph.save(steady, target) == target
    assert [p.name for p in target.parent.iterdir()] == ["again.pt"]


@pytest.fixture(scope="module")
def lq_float64(tmp_path_factory):
    """A float64 solution (two Adam steps, so its weights are not float32 numbers) on a registered LQ system."""
    A, B = np.array([[0.0, 1.0], [-1.0, 0.5]]), np.array([[0.0], [1.0]])
    system = ph.systems.linear_quadratic(A, B, np.eye(2), [[1.0]], domain=[[-1, 1], [-1, 1]], name="osc")
    config = ph.TrainConfig.preset("quick", dtype="float64", phases=(ph.Adam(steps=2, lr=5e-3),), eval_points_per_dim=5)
    sol = ph.FiniteHorizonSolver(system, config, device="cpu", progress=False).solve(0.5)
    return sol, ph.save(sol, tmp_path_factory.mktemp("lq") / "lq.pt")


def test_lq_float64_round_trip(lq_float64):
    sol, path = lq_float64
    loaded = ph.load(path)  # rebuilt from the registry: no system= needed
    assert loaded.system.name == "osc" and loaded.system.spec() == sol.system.spec()
    assert loaded.dtype == torch.float64
    x = np.random.default_rng(1).uniform(-1, 1, (10, 2))
    np.testing.assert_allclose(loaded.value(x), sol.value(x), rtol=1e-5)
    assert loaded.metrics == sol.metrics and "value_max_error" in loaded.metrics  # the LQ system knows V*


def test_float64_round_trip_is_exact(lq_float64):
    sol, path = lq_float64
    loaded = ph.load(path)
    for a, b in zip(loaded.stages, sol.stages):
        for key, value in b.model.net.state_dict().items():
            assert torch.equal(a.model.net.state_dict()[key], value), key
    x = np.random.default_rng(1).uniform(-1, 1, (10, 2))
    np.testing.assert_array_equal(loaded.value(x), sol.value(x))


# ------------------------------------------------------------------------------ mismatches and bad files
def test_load_into_system_of_other_dimension(saved):
    with pytest.raises(CheckpointError, match=r"n=2.*n=3"):
        ph.load(saved["fh"], system=ph.systems.third_order())


def test_load_into_system_with_other_parameters(saved):
    with pytest.raises(CheckpointError, match=r"pendulum\(\{'R': 1.0\}\).*pendulum\(\{'R': 2.0\}\)"):
        ph.load(saved["fh"], system=ph.systems.pendulum(R=2.0))
    with pytest.raises(CheckpointError, match="quartic"):
        ph.load(saved["ss"], system=ph.systems.quartic())
    assert ph.load(saved["fh"], system=ph.systems.pendulum()).horizon == 1.0  # the right one is accepted


def test_load_with_other_architecture(saved, config):
    with pytest.raises(CheckpointError, match="width"):
        ph.load(saved["fh"], config=config.replace(width=64))
    with pytest.raises(CheckpointError, match="ansatz"):
        ph.load(saved["ss"], config=config.replace(ansatz=False))
    ph.load(saved["fh"], config=config.with_phase("adam", lr=1.0))  # training-only fields may differ


def test_stored_weights_that_do_not_fit_the_config(saved, tmp_path):
    raw = torch.load(saved["ss"], weights_only=True)
    raw["config"]["width"] = 16
    torch.save(raw, tmp_path / "bad.pt")
    with pytest.raises(CheckpointError, match="do not fit"):
        ph.load(tmp_path / "bad.pt")


def test_corrupt_and_foreign_files(saved, tmp_path):
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"this is not a checkpoint")
    with pytest.raises(CheckpointError, match="not a readable pinnhjb checkpoint"):
        ph.load(garbage)
    truncated = tmp_path / "truncated.pt"
    truncated.write_bytes(saved["fh"].read_bytes()[:2000])
    with pytest.raises(CheckpointError):
        ph.load(truncated)
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(3)}, foreign)
    with pytest.raises(CheckpointError, match="not a pinnhjb checkpoint"):
        ph.load(foreign)
    torch.save([1, 2, 3], foreign)
    with pytest.raises(CheckpointError, match="not a pinnhjb checkpoint"):
        ph.load(foreign)
    future = torch.load(saved["ss"], weights_only=True)
    future["version"] = 99
    torch.save(future, tmp_path / "future.pt")
    with pytest.raises(CheckpointError, match="version 99"):
        ph.load(tmp_path / "future.pt")


def test_checkpoint_that_would_run_code_is_refused(tmp_path):
    path = tmp_path / "pickle.pt"
    torch.save({"format": FORMAT, "payload": TrainHistory()}, path)  # an arbitrary class: needs full unpickling
    with pytest.raises(CheckpointError, match="not a readable"):
        ph.load(path)


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        ph.load(tmp_path / "nowhere.pt")


# ------------------------------------------------------------------------------ user systems, unsavable solutions
def test_user_system_needs_system_on_load(tmp_path, config):
    system = user_system()
    sol = untrained_solution(system, config)
    path = ph.save(sol, tmp_path / "mine.pt")
    with pytest.raises(CheckpointError, match="user system 'mine'.*pass system="):
        ph.load(path)
    loaded = ph.load(path, system=system)
    assert loaded.system is system
    x = np.random.default_rng(0).uniform(-1, 1, (10, 2))
    np.testing.assert_array_equal(loaded.value(x, 0.5), sol.value(x, 0.5))
    with pytest.raises(CheckpointError, match="n=3"):
        ph.load(path, system=ph.systems.third_order())


def test_callable_terminal_cost_cannot_be_saved(tmp_path, config):
    system = user_system()
    torch.manual_seed(0)
    model = FiniteHorizonValue(2, 1.0, system.train_domain, width=config.width, depth=config.depth).float()
    sol = FiniteHorizonSolution(system, config, [Stage(model, 0.0, TrainHistory(), seed=0)], {"kind": "callable"})
    with pytest.raises(CheckpointError, match="callable"):
        ph.save(sol, tmp_path / "callable.pt")
    assert list(tmp_path.iterdir()) == []


def test_save_rejects_non_solution_with_type_error(tmp_path):
    with pytest.raises(TypeError, match="cannot save"):
        ph.save("not a solution", tmp_path / "x.pt")


def test_to_the_device_it_is_on_is_itself(two_stage, steady):
    for sol in (two_stage, steady):
        assert sol.to("cpu") is sol and sol.to(torch.device("cpu")) is sol


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_to_cuda_without_cuda_is_refused(two_stage):
    with pytest.raises(RuntimeError, match="CUDA is not available"):
        two_stage.to("cuda")


@pytest.mark.parametrize("name", [None, "half |x|^2"])
def test_to_another_device_carries_a_callable_terminal_cost(tmp_path, config, name):
    """``Solution.to`` is a checkpoint round trip; a first terminal cost that is code goes along as the same
    function, and one without a name stays unnamed (so no more savable than before). The round trip is forced
    on the CPU by naming its device index."""
    system = user_system()
    phi = CallableTerminalCost(lambda x: 0.5 * (x**2).sum(-1), name=name)
    torch.manual_seed(0)
    model = FiniteHorizonValue(2, 1.0, system.train_domain, phi, width=config.width, depth=config.depth).float()
    sol = FiniteHorizonSolution(system, config, [Stage(model, 0.0, TrainHistory(), seed=0)], phi.spec())
    moved = sol.to(torch.device("cpu", 0))
    assert moved is not sol and moved.terminal_spec == sol.terminal_spec == phi.spec() and phi.name == name
    x = np.random.default_rng(0).uniform(-1, 1, (10, 2))
    np.testing.assert_array_equal(moved.value(x, 0.3), sol.value(x, 0.3))
    np.testing.assert_allclose(moved.value(x, 1.0), 0.5 * (x**2).sum(-1), rtol=1e-6)  # phi at T, in float32
    if name is None:
        with pytest.raises(CheckpointError, match="cannot be saved"):
            ph.save(moved, tmp_path / "moved.pt")


def test_named_callable_terminal_cost_is_saved_by_name_and_must_be_passed_back(tmp_path, config):
    system = user_system()
    phi = CallableTerminalCost(lambda x: 0.5 * (x**2).sum(-1), name="half |x|^2")
    torch.manual_seed(0)
    model = FiniteHorizonValue(2, 1.0, system.train_domain, phi, width=config.width, depth=config.depth).float()
    sol = FiniteHorizonSolution(system, config, [Stage(model, 0.0, TrainHistory(), seed=0)], phi.spec())
    path = ph.save(sol, tmp_path / "named.pt")
    with pytest.raises(CheckpointError, match="half \\|x\\|\\^2"):
        ph.load(path, system=system)  # no silent phi = 0
    with pytest.raises(CheckpointError, match="half"):
        ph.load(path, system=system, terminal_cost=CallableTerminalCost(phi.fn, name="another"))
    loaded = ph.load(path, system=system, terminal_cost=phi)
    x = np.random.default_rng(0).uniform(-1, 1, (10, 2))
    np.testing.assert_array_equal(loaded.value(x, 0.3), sol.value(x, 0.3))
    with pytest.raises(CheckpointError, match="do not pass"):
        ph.load(ph.save(untrained_solution(system, config), tmp_path / "plain.pt"), system=system, terminal_cost=phi)
