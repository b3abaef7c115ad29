"""pinnhjb.solution and the solver's evaluation hook: results are declared dataclasses, built once with their metrics.

Every run is a few Adam steps of the quick preset (the numbers do not matter here, only who computes them and when).
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

import pinnhjb as ph
from pinnhjb.solution import FiniteHorizonSolution, Stage, SteadyStateSolution
from pinnhjb.training import TrainHistory

FAST = dict(phases=(ph.Adam(steps=5, lr=5e-3),), eval_points_per_dim=11)


def config(**overrides) -> ph.TrainConfig:
    return ph.TrainConfig.preset("quick", **{**FAST, **overrides})


def field_names(cls) -> set[str]:
    return {f.name for f in dataclasses.fields(cls)}


@pytest.fixture(scope="module")
def pendulum():
    return ph.systems.pendulum()


class Recorder:
    """An evaluation hook that records the horizon and the stage count it was called on."""

    def __init__(self, metrics=None):
        self.calls = []
        self.metrics = metrics

    def __call__(self, solution) -> dict:
        n = len(solution.stages) if isinstance(solution, FiniteHorizonSolution) else 0
        self.calls.append((n, float(getattr(solution, "horizon", math.inf)), dict(solution.metrics)))
        return {"E": 1.0 / n, "E_zero": 10.0} if self.metrics is None else dict(self.metrics)


@pytest.mark.parametrize(
    "cls, fields",
    [
        (Stage, {"model", "start", "history", "seed", "metrics", "rejected"}),
        (TrainHistory, {"step", "loss", "wall", "phase", "stop_reason", "wall_time", "final_loss"}),
        (FiniteHorizonSolution, {"system", "config", "stages", "terminal_spec", "interrupted", "tol", "provenance"}),
        (SteadyStateSolution, {"system", "config", "model", "history", "seed", "metrics", "provenance"}),
    ],
)
def test_results_declare_every_field_and_document_it(cls, fields):
    assert dataclasses.is_dataclass(cls) and field_names(cls) == fields
    for name in fields:
        assert f"``{name}``" in cls.__doc__, (cls.__name__, name)


def test_stage_history_and_solution_are_frozen(pendulum):
    sol = ph.FiniteHorizonSolver(pendulum, config(), device="cpu", progress=False, evaluate=Recorder()).solve(0.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        sol.interrupted = True
    marked = dataclasses.replace(sol, interrupted=True)  # a changed solution is a new one
    assert marked.interrupted and not sol.interrupted and marked.stages == sol.stages
    stage = sol.stages[0]
    with pytest.raises(dataclasses.FrozenInstanceError):
        stage.metrics = {}
    with pytest.raises(dataclasses.FrozenInstanceError):
        stage.history.final_loss = 0.0
    again = dataclasses.replace(stage, metrics={"E": 1.0})  # a changed stage is a new one
    assert again.metrics == {"E": 1.0} and stage.metrics != again.metrics and again.model is stage.model


def test_results_own_their_metrics_and_history():
    metrics, loss = {"E": 1.0}, [3.0, 2.0]
    history = TrainHistory(step=[1, 2], loss=loss)
    stage = Stage(torch.nn.Identity(), 0.0, history, 0, metrics)
    metrics["E"], loss[0] = 99.0, 99.0
    assert stage.metrics == {"E": 1.0} and history.loss == [3.0, 2.0]


def test_solver_metrics_come_from_the_hook_once_per_stage(pendulum):
    hook = Recorder()
    solver = ph.FiniteHorizonSolver(pendulum, config(), device="cpu", progress=False, evaluate=hook)
    seen = []
    sol = solver.solve(0.5)
    sol = solver.extend(sol, to=1.5, step=0.5, callback=lambda s: seen.append(dict(s.metrics)))
    # called once per stage, on the chain ending with the new stage, before that stage had metrics
    assert [(n, h) for n, h, _ in hook.calls] == [(1, 0.5), (2, 1.0), (3, 1.5)]
    assert all(before == {} for _, _, before in hook.calls)
    assert [s.metrics for s in sol.stages] == [
        {"E": 1.0, "E_zero": 10.0},
        {"E": 0.5, "E_zero": 10.0},
        {"E": 1 / 3, "E_zero": 10.0},
    ]
    assert seen == [{"E": 0.5, "E_zero": 10.0}, {"E": 1 / 3, "E_zero": 10.0}]  # the callback sees them attached
    assert sol.metrics == sol.stages[-1].metrics and sol.provenance is None and sol.tol is None


def test_default_hook_is_the_solution_grid_evaluation(pendulum):
    solver = ph.FiniteHorizonSolver(pendulum, config(), device="cpu", progress=False)
    with pytest.warns(RuntimeWarning, match="no better than E of V = 0"):
        sol = solver.solve(0.5)
    assert sol.metrics == sol.evaluate(11) == solver.evaluate(sol)


def test_hook_can_skip_evaluation_and_solve_until_uses_its_E(pendulum):
    skip = ph.FiniteHorizonSolver(pendulum, config(), device="cpu", progress=False, evaluate=lambda sol: {})
    assert skip.solve(0.5).metrics == {}
    hook = Recorder()  # E = 1 / k after k stages: tol 0.4 is met at the third stage
    until = ph.FiniteHorizonSolver(pendulum, config(), device="cpu", progress=False, evaluate=hook)
    sol = until.solve_until(tol=0.4, step=0.5, max_horizon=5.0)
    assert len(sol.stages) == 3 and sol.converged is True and sol.tol == 0.4
    assert [row["converged"] for row in sol.summary()] == [False, False, True]


def test_steady_state_metrics_come_from_the_hook(pendulum):
    hook = Recorder(metrics={"E": 0.5, "E_zero": 1.0})
    sol = ph.SteadyStateSolver(pendulum, config(), device="cpu", progress=False, evaluate=hook).solve()
    assert len(hook.calls) == 1 and hook.calls[0][2] == {}
    assert sol.metrics == {"E": 0.5, "E_zero": 1.0} and sol.converged is None and sol.provenance is None


@pytest.mark.parametrize("bad, match", [(3, "evaluate must be a callable"), (lambda sol: [1.0], "must return a dict")])
def test_a_bad_hook_is_refused(pendulum, bad, match):
    with pytest.raises(TypeError, match=match):
        ph.FiniteHorizonSolver(pendulum, config(), device="cpu", progress=False, evaluate=bad).solve(0.5)


def test_a_failing_hook_keeps_the_trained_stage(pendulum):
    def fail(sol):
        raise FloatingPointError("evaluation failed")

    with pytest.raises(FloatingPointError) as info:
        ph.FiniteHorizonSolver(pendulum, config(), device="cpu", progress=False, evaluate=fail).solve(0.5)
    partial = info.value.partial_solution
    assert len(partial.stages) == 1 and partial.metrics == {}


def test_loaded_solution_carries_its_provenance_and_stored_metrics(pendulum, tmp_path):
    solver = ph.FiniteHorizonSolver(pendulum, config(), device="cpu", progress=False, evaluate=Recorder())
    sol = solver.solve(0.5)
    loaded = ph.load(ph.save(sol, tmp_path / "s.pt", note="hook"), system=pendulum)
    assert loaded.metrics == {"E": 1.0, "E_zero": 10.0}  # the stored metrics, not recomputed
    assert loaded.provenance["note"] == "hook" and loaded.tol is None and loaded.converged is None
    derived = dataclasses.replace(loaded, tol=2.0)
    assert derived.converged is True and loaded.tol is None and derived.stages == loaded.stages
    np.testing.assert_array_equal(derived.value(np.zeros((1, 2))), loaded.value(np.zeros((1, 2))))


# ------------------------------------------------------------------------------ every horizon from one chain
LQ = dict(A=np.array([[0.0, 1.0], [-1.0, -0.5]]), B=np.array([[0.0], [1.0]]), Q=np.eye(2), R=np.array([[1.0]]))


@pytest.fixture(scope="module")
def lq_chain():
    """An LQ system's chain to T = 2 (two Levenberg-Marquardt stages on a 2 x 16 network, a few seconds)."""
    system = ph.systems.linear_quadratic(**LQ, domain=[[-1, 1], [-1, 1]])
    cfg = ph.TrainConfig.preset("default", width=16, depth=2, eval_points_per_dim=11).with_phase("lm", steps=100)
    solver = ph.FiniteHorizonSolver(system, cfg, seed=0, device="cpu", progress=False)
    return solver.extend(solver.solve(1.0), to=2.0)


def test_one_chain_gives_every_shorter_horizon_of_the_exact_lq_value(lq_chain):
    """V_tau(x, 0) = V_T(x, T - tau) for a time-invariant system: 40 horizons in (0, 2] from one chain, each
    against the exact Riccati value and policy (pinnhjb.lq.riccati_ode)."""
    x = lq_chain.system.grid(11).numpy()
    for tau in np.linspace(0.05, 2.0, 40):
        exact = ph.lq.riccati_ode(LQ["A"], LQ["B"], LQ["Q"], LQ["R"], tau)
        v_exact = exact.value(x, 0.0)
        assert np.abs(lq_chain.value(x, horizon=tau) - v_exact).max() <= 2e-3 * np.abs(v_exact).max(), tau
        assert np.abs(lq_chain.policy(x, horizon=tau) - exact.policy(x, 0.0)).max() <= 5e-3, tau
        # the horizon is the time T - tau of the chain, and nothing else
        np.testing.assert_array_equal(lq_chain.value(x, horizon=tau), lq_chain.value(x, t=2.0 - tau))
        np.testing.assert_array_equal(lq_chain.gradient(x, horizon=tau), lq_chain.gradient(x, t=2.0 - tau))
    # horizon T is the chain's own V_T(., 0); horizon 0 is the terminal cost (here 0)
    np.testing.assert_array_equal(lq_chain.value(x, horizon=2.0), lq_chain.value(x))
    assert np.abs(lq_chain.value(x, horizon=0.0)).max() < 1e-12


def test_the_value_function_is_the_value_and_differentiable(lq_chain, lq_chain_seed1):
    """value_function: the same V as value(), at t or at a horizon, with autograd's gradient the solution's
    gradient(); for an averaged solution too."""
    x = torch.as_tensor(lq_chain.system.grid(7).numpy())
    for sol in (lq_chain, ph.AveragedSolution([lq_chain, lq_chain_seed1])):
        for kwargs in ({}, {"t": 0.5}):
            fn = sol.value_function(**kwargs)
            xg = x.clone().requires_grad_(True)
            v = fn(xg)
            (g,) = torch.autograd.grad(v.sum(), xg)
            torch.testing.assert_close(v.detach(), sol.value(x, **kwargs), rtol=1e-12, atol=1e-14)
            torch.testing.assert_close(g, sol.gradient(x, **kwargs), rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(lq_chain.value_function(horizon=1.0)(x), lq_chain.value(x, horizon=1.0))
    with pytest.raises(ValueError, match=r"horizon must lie in \[0, 2\]"):
        lq_chain.value_function(horizon=3.0)


def test_a_horizon_outside_the_chain_or_beside_t_is_refused(lq_chain, pendulum):
    x = np.zeros((1, 2))
    with pytest.raises(ValueError, match=r"horizon must lie in \[0, 2\]"):
        lq_chain.value(x, horizon=2.5)
    with pytest.raises(ValueError, match=r"horizon must lie in \[0, 2\]"):
        lq_chain.policy(x, horizon=-0.1)
    with pytest.raises(ValueError, match="give t or horizon, not both"):
        lq_chain.value(x, t=0.5, horizon=1.0)
    with pytest.raises(TypeError, match="horizon must be a number"):
        lq_chain.gradient(x, horizon="long")
    steady = ph.SteadyStateSolver(pendulum, config(), seed=0, device="cpu", progress=False).solve()
    with pytest.raises(TypeError, match="SteadyStateSolution has no horizon"):
        steady.value(x, horizon=1.0)


def test_the_horizon_check_and_residual_field_of_a_shorter_horizon(lq_chain):
    """evaluate and residual_field at horizon tau are those of the chain cut at tau, when tau is a stage end."""
    short = lq_chain.truncated(1)  # its horizon is 1
    at_1 = lq_chain.evaluate(11, horizon=1.0)
    assert at_1["E"] == pytest.approx(short.evaluate(11)["E"], rel=1e-9)
    assert at_1["value_max_error"] == pytest.approx(short.evaluate(11)["value_max_error"], rel=1e-9)
    x = lq_chain.system.grid(5).numpy()
    np.testing.assert_allclose(lq_chain.residual_field(x, horizon=1.0), short.residual_field(x), rtol=1e-9, atol=1e-12)
    assert lq_chain.evaluate(11, horizon=1.5)["E"] > lq_chain.evaluate(11)["E"]  # a shorter horizon, a larger E


# ------------------------------------------------------------------------------ the mean of independent chains
@pytest.fixture(scope="module")
def lq_chain_seed1(lq_chain):
    """The chain of ``lq_chain`` trained again from seed 1."""
    solver = ph.FiniteHorizonSolver(lq_chain.system, lq_chain.config, seed=1, device="cpu", progress=False)
    return solver.extend(solver.solve(1.0), to=2.0)


def test_an_averaged_solution_is_the_mean_of_its_members(lq_chain, lq_chain_seed1):
    pair = (lq_chain, lq_chain_seed1)
    mean = ph.AveragedSolution(list(pair))
    assert mean.members == pair and mean.system is lq_chain.system and mean.converged is None
    assert mean.metrics == {} and mean.wall_time == pytest.approx(sum(m.wall_time for m in pair))
    assert repr(mean) == "AveragedSolution(system='lq', members=2)"
    x = lq_chain.system.grid(7).numpy()
    for what in ("value", "gradient", "policy"):  # the policy is linear in grad V
        expected = (getattr(lq_chain, what)(x) + getattr(lq_chain_seed1, what)(x)) / 2
        np.testing.assert_allclose(getattr(mean, what)(x), expected, rtol=1e-12, atol=1e-14)
    for t in (0.5, 2.0):  # the members' value at the same t
        expected = (lq_chain.value(x, t) + lq_chain_seed1.value(x, t)) / 2
        np.testing.assert_allclose(mean.value(x, t), expected, rtol=1e-12, atol=1e-14)
    # its largest error against V* is at most its members' (the mean of the errors): measured, not stored
    errors = [s.evaluate(11)["value_max_error"] for s in (mean, *pair)]
    assert errors[0] <= max(errors[1:])
    assert mean.closed_loop(x[:3], t_final=1.0).x.shape[1:] == (3, 2)
    assert mean.to("cpu") is mean


def test_an_averaged_solution_refuses_what_it_cannot_mean(lq_chain, pendulum, tmp_path):
    with pytest.raises(ValueError, match="non-empty list of solutions"):
        ph.AveragedSolution([])
    with pytest.raises(TypeError, match="members must be FiniteHorizonSolution or SteadyStateSolution; got str"):
        ph.AveragedSolution([lq_chain, "chain.pt"])
    steady = ph.SteadyStateSolver(pendulum, config(), seed=0, device="cpu", progress=False).solve()
    with pytest.raises(ValueError, match="members must solve one system"):
        ph.AveragedSolution([lq_chain, steady])
    mean = ph.AveragedSolution([lq_chain])
    with pytest.raises(TypeError, match="AveragedSolution has no horizon"):
        mean.value(np.zeros((1, 2)), horizon=1.0)
    with pytest.raises(TypeError, match=r"cannot save a AveragedSolution \(save its members one by one\)"):
        ph.save(mean, tmp_path / "mean.pt")
