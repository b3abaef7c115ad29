"""Tests for pinnhjb.reference: open-loop (Pontryagin BVP) reference values of eq. (2) and eq:costT."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from pinnhjb import systems
from pinnhjb.lq import care, riccati_ode
from pinnhjb.reference import ReferenceGrid, reference_grid, reference_points, replay_cost, solve_point

# unstable 2-state, one input; 3-state, two inputs (coupled R)
LQ2 = (np.array([[1.0, 1.0], [0.0, 2.0]]), np.array([[0.0], [1.0]]), np.eye(2), np.array([[1.0]]))
LQ3 = (
    np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 2.0, -3.0]]),
    np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]),
    np.diag([1.0, 2.0, 0.5]),
    np.array([[1.0, 0.2], [0.2, 2.0]]),
)


def _lq_system(A, B, Q, R):
    return systems.linear_quadratic(A, B, Q, R, domain=[[-1, 1]] * A.shape[0])


@pytest.fixture(scope="module")
def quartic():
    return systems.quartic()


@pytest.mark.parametrize(
    "x0", [(1.2, 1.2), (-1.2, 1.2), (1.2, -1.2), (-1.2, -1.2), (0.0, 1.2), (0.7, -0.4), (-0.1, 0.05)]
)
def test_quartic_matches_known_value_and_policy(quartic, x0):
    res = solve_point(quartic, np.array(x0))
    X = torch.tensor([x0], dtype=torch.float64)
    assert res["converged"] and res["status"] == 0 and res["residual"] <= 1e-8
    assert res["tail_norm"] < 1e-6
    assert abs(res["value"] - quartic.value_star(X).item()) < 1e-5
    assert np.abs(res["policy"] - quartic.policy_star(X).numpy()[0]).max() < 1e-4
    grad_star = np.array([x0[0], 2 * x0[1] + 4 * x0[1] ** 3])
    assert np.abs(res["gradient"] - grad_star).max() < 1e-4
    assert abs(res["hamiltonian"]) < 1e-6  # the steady-state HJB (4) along the extremal


@pytest.mark.parametrize("lq", [LQ2, LQ3], ids=["2-state", "3-state"])
def test_lq_infinite_and_finite_horizon_match_riccati(lq):
    A, B, Q, R = lq
    system = _lq_system(A, B, Q, R)
    P = care(A, B, Q, R)
    P1 = riccati_ode(A, B, Q, R, 1.0).at(0.0)
    x0 = np.linspace(-0.9, 0.8, A.shape[0])
    inf = solve_point(system, x0)
    fin = solve_point(system, x0, horizon=1.0)
    assert inf["converged"] and fin["converged"]
    assert abs(inf["value"] - x0 @ P @ x0) < 1e-7
    assert np.abs(inf["gradient"] - 2 * P @ x0).max() < 1e-6
    assert np.abs(inf["policy"] - (-np.linalg.solve(R, B.T @ P @ x0))).max() < 1e-6
    assert abs(fin["value"] - x0 @ P1 @ x0) < 1e-7
    assert np.abs(fin["policy"] - (-np.linalg.solve(R, B.T @ P1 @ x0))).max() < 1e-6
    assert fin["value"] < inf["value"]  # Lemma 1: V_T(x, 0) <= V*(x) for phi = 0


def test_terminal_cost_matrix_and_callable_agree_with_riccati():
    A, B, Q, R = LQ2
    system = _lq_system(A, B, Q, R)
    P_T = np.array([[2.0, 0.5], [0.5, 1.0]])
    P0 = riccati_ode(A, B, Q, R, 0.7, P_T=P_T).at(0.0)
    x0 = np.array([0.5, -0.3])
    P_t = torch.as_tensor(P_T)
    by_matrix = solve_point(system, x0, horizon=0.7, terminal_cost=P_T)
    by_callable = solve_point(system, x0, horizon=0.7, terminal_cost=lambda x: torch.einsum("bi,ij,bj->b", x, P_t, x))
    for res in (by_matrix, by_callable):
        assert res["converged"]
        assert abs(res["value"] - x0 @ P0 @ x0) < 1e-7


def test_pendulum_finite_horizon_value_increases_with_horizon():
    system = systems.pendulum()
    x0 = np.array([0.8, -0.5])
    values = [solve_point(system, x0, horizon=T)["value"] for T in (0.5, 1.0, 2.0, 4.0)]
    v_inf = solve_point(system, x0)
    assert v_inf["converged"]
    assert np.all(np.diff(values) > 0), values  # Lemma 1 (le:inc)
    assert values[-1] < v_inf["value"]


def test_origin_has_zero_value(quartic):
    res = solve_point(quartic, np.zeros(2))
    assert res["converged"]
    assert res["value"] == pytest.approx(0.0, abs=1e-14)
    assert np.abs(res["gradient"]).max() < 1e-14 and np.abs(res["policy"]).max() < 1e-14


@pytest.mark.parametrize("bad", [np.zeros(3), np.zeros((1, 2)), np.zeros((2, 2)), np.array([0.1, np.nan])])
def test_bad_initial_state_raises(quartic, bad):
    with pytest.raises(ValueError):
        solve_point(quartic, bad)


def test_bad_horizon_raises(quartic):
    with pytest.raises(ValueError):
        solve_point(quartic, np.ones(2), horizon=-1.0)
    with pytest.raises(ValueError):
        solve_point(quartic, np.ones(2), terminal_cost=np.eye(2))  # phi only with a finite horizon


def test_grid_save_load_round_trip(quartic, tmp_path):
    grid = reference_grid(quartic, points_per_dim=3, progress=False)
    X = torch.as_tensor(grid.points)
    assert grid.points.shape == (9, 2) and grid.converged.all() and (grid.status == 0).all()
    assert np.abs(grid.value - quartic.value_star(X).numpy()).max() < 1e-5
    assert np.abs(grid.policy - quartic.policy_star(X).numpy()).max() < 1e-4
    path = tmp_path / "ref.npz"
    grid.save(path)
    back = ReferenceGrid.load(path)
    for key in ("points", "value", "gradient", "policy", "converged", "max_bvp_residual", "status"):
        np.testing.assert_array_equal(getattr(back, key), getattr(grid, key))
    assert back.horizon == math.inf and back.system == quartic.spec()
    assert back.wall_time == grid.wall_time and back.info["tol"] == 1e-8
    assert set(back.info["versions"]) == {"numpy", "scipy", "torch"}


def test_short_truncation_is_extended_or_flagged(quartic):
    x0 = np.array([1.2, -1.2])
    v_star = quartic.value_star(torch.as_tensor(x0[None])).item()
    res = solve_point(quartic, x0, t_inf=2.0)  # tail check fails, t_inf doubles until it passes
    assert res["converged"] and res["t_inf"] > 2.0 and abs(res["value"] - v_star) < 1e-5
    with pytest.warns(RuntimeWarning, match="did not converge"):
        res = solve_point(quartic, x0, t_inf=2.0, max_extensions=0)
    assert not res["converged"] and res["tail_norm"] > 1e-3
    with pytest.warns(RuntimeWarning, match="did not converge"):
        grid = reference_grid(quartic, points_per_dim=3, progress=False, t_inf=2.0, max_extensions=0)
    assert not grid.converged.all() and np.isnan(grid.value[~grid.converged]).all()
    assert grid.converged[4] and grid.value[4] == 0.0  # the origin (centre of the 3x3 grid)
    with pytest.raises(RuntimeError, match="did not converge"):
        reference_grid(quartic, points_per_dim=3, progress=False, t_inf=2.0, max_extensions=0, strict=True)


def test_value_error_skips_failed_points_and_scales_by_the_largest_value(quartic):
    grid = reference_grid(quartic, points_per_dim=3, progress=False)
    ok = np.ones(9, dtype=bool)
    ok[[2, 6]] = False  # two points as a failed solve leaves them
    grid = dataclasses.replace(grid, converged=ok, value=np.where(ok, grid.value, np.nan))

    class Shifted:  # V* plus a constant
        def __init__(self, shift):
            self.shift = shift

        def value(self, x):
            return quartic.value_star(torch.as_tensor(x)).numpy() + self.shift

    top = np.abs(grid.value[ok]).max()
    signed = grid.value_error(Shifted(-0.01), signed=True)
    assert signed.shape == (ok.sum(),) and np.isfinite(signed).all()
    # the converged points' V* to the BVP's accuracy, minus the shift, per the largest value
    np.testing.assert_allclose(signed, -0.01 / top, atol=1e-5 / top)
    np.testing.assert_array_equal(grid.value_error(Shifted(-0.01)), np.abs(signed))


def test_seeded_points_match_exact_value_and_replay(quartic, tmp_path):
    """reference_points at seeded states: V* to the BVP's accuracy, and each open-loop control re-integrated gives
    the value it claims (the check the 6-D rigid body's reference relies on)."""
    ref = reference_points(quartic, 12, seed=3, progress=False)
    X = torch.as_tensor(ref.points)
    assert ref.points.shape == (12, 2) and ref.converged.all()
    assert np.all(np.abs(ref.points) <= np.abs(quartic.domain).max())
    assert np.abs(ref.value - quartic.value_star(X).numpy()).max() < 1e-5
    assert np.abs(ref.replay_value - ref.value).max() < 1e-6 * ref.value.max()
    rel = np.abs(ref.replay_value - ref.value) / ref.value
    assert ref.replay_error == rel.max() < 1e-5  # the check, as the benchmark and chapter 8 read it
    again = reference_points(quartic, 12, seed=3, progress=False, replay=False)
    np.testing.assert_array_equal(again.points, ref.points)  # the seed fixes the states
    assert again.replay_value is None and again.replay_error is None
    assert ref.info["seed"] == 3 and ref.info["points"] == 12
    path = tmp_path / "pts.npz"
    ref.save(path)
    back = ReferenceGrid.load(path)
    np.testing.assert_array_equal(back.replay_value, ref.replay_value)
    assert back.info["seed"] == 3


def test_replay_detects_a_wrong_value(quartic):
    """The replay is independent of the BVP's cost row: a perturbed costate gives a different cost."""
    res = solve_point(quartic, np.array([0.8, -0.6]))
    exact = replay_cost(res["_problem"], res)
    assert abs(exact - res["value"]) < 1e-7
    sol = res["solution"]
    wrong = dict(res, solution=type("S", (), {"sol": lambda self, t: sol.sol(t) * 1.1, "x": sol.x})())
    assert abs(replay_cost(res["_problem"], wrong) - res["value"]) > 1e-3


def test_seeded_points_refuse_bad_count(quartic):
    with pytest.raises(ValueError, match="points must be an integer"):
        reference_points(quartic, 0, progress=False)
