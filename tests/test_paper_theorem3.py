"""The Theorem 3 experiment (pinnhjb.paper.theorem3): the stored stages reload and their stored metrics still hold."""

from pathlib import Path

import numpy as np
import pytest
import scipy.linalg as sla
import torch
from scipy.integrate import solve_ivp

import pinnhjb as ph
from pinnhjb.paper import theorem3

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "artifacts" / "theorem3"


@pytest.mark.parametrize("error", sorted(theorem3.ERRORS))
def test_stored_stage_reloads_and_its_metrics_still_hold(error):
    sol = theorem3.load(error, OUT)
    assert sol.provenance["theorem3_error"] == error and sol.horizon == theorem3.DELTA
    again = sol.evaluate(sol.config.eval_points_per_dim)
    for key in ("E", "value_max_error", "policy_max_error"):
        assert again[key] == pytest.approx(sol.metrics[key], rel=1e-3, abs=1e-9), key
    stored = sol.provenance["evaluation"]
    now = theorem3.summary(theorem3.bound_check(sol, error), 0.0)
    for key in ("max_error", "max_bound", "max_e_start"):
        assert now[key] == pytest.approx(stored[key], rel=1e-3, abs=1e-9), key


def test_terminal_cost_is_reattached():
    """Without V* + e re-attached the stage would answer the correction alone; with it, V(x, T') = V* + e."""
    sol = theorem3.load("offset", OUT)
    x = torch.tensor([[0.3, -0.4], [0.0, 0.0]], dtype=torch.float64)
    expected = sol.system.value_star(x) + theorem3.ERRORS["offset"](x)
    assert np.allclose(sol.value(x.numpy(), t=sol.horizon), expected.numpy(), atol=1e-5)


def test_exact_grids_are_complete_and_a_constant_passes_whole():
    exact = {name: theorem3.load_exact(name, OUT) for name in theorem3.ERRORS}
    assert all(e["converged"].all() for e in exact.values())
    v_star = ph.systems.quartic().value_star(torch.as_tensor(exact["none"]["x0"])).numpy()
    assert np.allclose(exact["none"]["value"], v_star, atol=1e-6)  # V* is a fixed point of the extension
    assert np.allclose(exact["offset"]["value"] - exact["vanishing"]["value"], 0.2, atol=1e-6)


def test_rollout_matches_the_matrix_exponential():
    A = np.array([[0.0, 1.0], [-2.0, -0.5]])
    system = ph.systems.linear_quadratic(A, np.array([[0.0], [1.0]]), np.eye(2), np.eye(1), [[-1, 1], [-1, 1]])
    x0 = np.array([[1.0, 0.0], [0.2, -0.7]])
    K = np.array([[0.5, 0.3]])
    end = theorem3.rollout(system, lambda x, t: -(1 + t) * x @ torch.as_tensor(K.T), x0, 1.0, dt=0.01)
    # a time-varying gain: compare with scipy's integration of the same closed loop
    sol = solve_ivp(
        lambda t, y: (A - (1 + t) * np.array([[0.0], [1.0]]) @ K) @ y, (0, 1), x0[1], rtol=1e-11, atol=1e-12
    )
    assert np.allclose(end[1], sol.y[:, -1], atol=1e-8)
    zero = theorem3.rollout(system, lambda x, t: torch.zeros(x.shape[0], 1, dtype=x.dtype), x0, 1.0)
    assert np.allclose(zero, x0 @ sla.expm(A).T, atol=1e-8)


def test_unknown_error_is_rejected():
    with pytest.raises(KeyError, match="unknown error"):
        theorem3.train("nope")
