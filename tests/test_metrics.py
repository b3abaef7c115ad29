"""pinnhjb.metrics: the horizon check E (eq-e), errors against V* and mu*, and the closed loop (cost of a policy
by RK4)."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
import torch
from scipy.integrate import simpson

import pinnhjb as ph
from pinnhjb import lq, metrics
from pinnhjb.residuals import SteadyStateHJB

A = np.array([[1.0, 1.0], [0.0, 2.0]])  # open-loop unstable
B = np.array([[0.0], [1.0]])
Q = np.diag([1.0, 0.5])
R = np.array([[2.0]])


@pytest.fixture(scope="module")
def lq_system():
    return ph.systems.linear_quadratic(A, B, Q, R, domain=[[-1, 1], [-1, 1]])


X0 = np.array([[0.5, -0.3], [1.0, 1.0], [-1.0, 0.2], [0.0, 0.8]])


def test_closed_loop_with_lqr_policy_costs_x0_P_x0(lq_system):
    P = lq.care(A, B, Q, R)
    result = metrics.closed_loop(lq_system, lq_system.policy_star, X0, t_final=20.0, dt=0.01)
    np.testing.assert_allclose(result.cost, np.einsum("bi,ij,bj->b", X0, P, X0), rtol=1e-3)
    assert result.stabilized.all() and result.fraction_stabilized == 1.0
    assert result.x.shape == (2001, 4, 2) and result.u.shape == (2001, 4, 1) and result.t.shape == (2001,)
    np.testing.assert_array_equal(result.x[0], X0)
    assert result.t[-1] == pytest.approx(20.0)
    np.testing.assert_allclose(result.u[0], -X0 @ lq.lqr_gain(B, R, P).T, rtol=1e-12)


def test_closed_loop_without_control_diverges(lq_system):
    result = metrics.closed_loop(
        lq_system, lambda x: torch.zeros(x.shape[0], 1, dtype=x.dtype), X0[:2], t_final=5.0, dt=0.01
    )
    assert not result.stabilized.any() and result.fraction_stabilized == 0.0
    assert (result.cost > 1e3).all()


def test_closed_loop_of_learned_value_uses_its_policy(lq_system):
    # V = x'Px as a "learned" value function: policy_of recovers the LQR policy by autograd
    P = torch.as_tensor(lq.care(A, B, Q, R))
    mu = metrics.policy_of(lq_system, lambda x: torch.einsum("bi,ij,bj->b", x, P, x))
    x = torch.as_tensor(X0)
    np.testing.assert_allclose(mu(x).numpy(), lq_system.policy_star(x).numpy(), rtol=1e-12)


def test_closed_loop_checks_arguments(lq_system):
    with pytest.raises(ValueError, match="positive"):
        metrics.closed_loop(lq_system, lq_system.policy_star, X0, t_final=0.0)
    with pytest.raises(ValueError, match="positive"):
        metrics.closed_loop(lq_system, lq_system.policy_star, X0, dt=-0.1)
    with pytest.raises(ValueError, match="shape"):
        metrics.closed_loop(lq_system, lq_system.policy_star, np.zeros((2, 3)))


def test_residual_along_loop_integrates_to_the_value_gap(lq_system):
    # V = x'(P + D)x: along its own policy's loops E_e is the ARE residual's quadratic form, and
    # V(x0) = J_T + V(x(T)) - int E_e dt holds for any V; for V* itself (D = 0) both sides vanish
    P = lq.care(A, B, Q, R)
    gaps = []
    for D in (np.zeros((2, 2)), np.array([[0.3, -0.1], [-0.1, 0.2]])):
        M = torch.as_tensor(P + D)
        loops = metrics.residual_along_loop(
            lq_system, lambda x: torch.einsum("bi,ij,bj->b", x, M, x), X0, t_final=8.0, dt=0.005
        )
        assert loops.residual.shape == loops.outside.shape == (1601, 4)
        fields = metrics.quadratic_fields(A, B, Q, R, P + D, loops.run.x.reshape(-1, 2))
        np.testing.assert_allclose(loops.residual, fields["residual"].reshape(1601, 4), atol=1e-12)
        np.testing.assert_allclose(loops.value_start, fields["value"][:4], rtol=1e-12)
        np.testing.assert_allclose(loops.gap, loops.integral, atol=1e-6)
        box = lq_system.train_domain
        outside = np.any((loops.run.x < box[:, 0]) | (loops.run.x > box[:, 1]), axis=-1)
        np.testing.assert_array_equal(loops.outside, outside)
        inside_only = simpson(np.where(outside, 0.0, loops.residual), x=loops.run.t, axis=0)
        np.testing.assert_allclose(loops.integral_outside + inside_only, loops.integral, atol=1e-12)
        gaps.append(np.abs(loops.gap))
    assert gaps[0].max() < 1e-6 and gaps[1].min() > 1e3 * gaps[0].max()
    assert loops.outside.any() and not loops.outside.all()  # X0 has loops that leave the box, and ones that stay


@pytest.mark.parametrize("name", ["lq", "quartic"])
def test_optimality_errors_of_value_star_vanish(name, lq_system):
    system = lq_system if name == "lq" else ph.systems.quartic()
    errors = metrics.optimality_errors(system, system.value_star)
    assert set(errors) == {
        "value_max_error",
        "value_rmse",
        "value_mse",
        "policy_max_error",
        "policy_rmse",
        "policy_mse",
    }
    assert all(v < 1e-12 for v in errors.values())


def test_optimality_errors_detect_a_wrong_value(lq_system):
    errors = metrics.optimality_errors(lq_system, lambda x: 1.5 * lq_system.value_star(x), points_per_dim=11)
    grid = lq_system.grid(11)
    assert errors["value_max_error"] == pytest.approx(0.5 * lq_system.value_star(grid).max().item(), rel=1e-12)
    assert errors["policy_max_error"] == pytest.approx(0.5 * lq_system.policy_star(grid).abs().max().item(), rel=1e-12)
    assert errors["value_mse"] == pytest.approx(errors["value_rmse"] ** 2, rel=1e-12)


def test_optimality_errors_without_policy_star_use_the_policy_of_value_star():
    """A system that gives V* but not mu*: mu* is the policy of V* (autograd), so the errors match the ones with the
    closed-form mu*, and evaluate() reports them instead of failing."""
    quartic = ph.systems.quartic()
    bare = dataclasses.replace(quartic, policy_star=None)
    value = lambda x: 1.1 * quartic.value_star(x)  # noqa: E731
    full, partial = (metrics.optimality_errors(s, value, points_per_dim=11) for s in (quartic, bare))
    assert full.keys() == partial.keys()
    for key in full:
        assert partial[key] == pytest.approx(full[key], rel=1e-10, abs=1e-15), key
    grid = quartic.grid(5)
    torch.testing.assert_close(metrics.known_policy(bare)(grid), quartic.policy_star(grid), rtol=1e-12, atol=1e-14)
    assert metrics.known_policy(ph.systems.pendulum()) is None


def test_optimality_errors_need_a_known_value():
    with pytest.raises(ValueError, match="no known V"):
        metrics.optimality_errors(ph.systems.pendulum(), lambda x: (x**2).sum(-1))


@pytest.mark.parametrize("system", [ph.systems.pendulum(), ph.systems.third_order()], ids=["pendulum", "third_order"])
def test_residual_of_zero_value_is_E_zero(system):
    out = metrics.infinite_horizon_residual(system, lambda x: 0.0 * x.sum(-1))
    grid = metrics.evaluation_grid(system)
    assert grid.shape == (metrics.default_points_per_dim(system.n) ** system.n, system.n)
    expected = float((system.Q(grid) ** 2).mean())
    assert out["E_zero"] == pytest.approx(expected, rel=1e-12)
    assert out["E"] == pytest.approx(expected, rel=1e-12)
    assert out["E_flow"] == out["E"] and out["E_boundary"] == 0.0


def test_residual_counts_value_at_origin():
    system = ph.systems.quartic()
    out = metrics.infinite_horizon_residual(system, lambda x: system.value_star(x) + 0.1, points_per_dim=21)
    assert out["E_boundary"] == pytest.approx(0.01, rel=1e-12)  # V(0)^2
    assert out["E_flow"] < 1e-20  # a constant shift leaves grad V unchanged
    assert out["E"] == pytest.approx(0.01, rel=1e-12)


def test_residual_on_given_points_and_field():
    system = ph.systems.quartic()
    pts = torch.tensor([[0.0, 0.0], [0.3, -0.2], [1.0, 1.0]], dtype=torch.float64)
    field = SteadyStateHJB(system, lambda x: (x**2).sum(-1)).field(pts)
    # E_e(x; |x|^2) = 2x'f + Q - (x2 sin x1)^2 (grad V = 2x, R = 1)
    x1, x2 = pts[:, 0], pts[:, 1]
    by_hand = 2 * (pts * system.f(pts)).sum(-1) + system.Q(pts) - (x2 * torch.sin(x1)) ** 2
    np.testing.assert_allclose(field.numpy(), by_hand.numpy(), rtol=1e-12, atol=1e-15)
    out = metrics.infinite_horizon_residual(system, lambda x: (x**2).sum(-1), points=pts)
    assert out["E_flow"] == pytest.approx(float((by_hand**2).mean()), rel=1e-12)
    with pytest.raises(ValueError, match="points"):
        SteadyStateHJB(system, lambda x: (x**2).sum(-1)).field(torch.zeros(3, 3, dtype=torch.float64))


def test_default_grid_sizes():
    assert metrics.default_points_per_dim(2) == 101
    assert metrics.default_points_per_dim(3) == 21
    grid = metrics.evaluation_grid(ph.systems.quartic(), 5)
    assert grid.dtype == torch.float64
    np.testing.assert_allclose(grid.min(0).values.numpy(), [-1.2, -1.2])
    np.testing.assert_allclose(grid.max(0).values.numpy(), [1.2, 1.2])


def _corners_max(system, fn) -> float:
    corners = torch.tensor(list(itertools.product(*np.asarray(system.domain))), dtype=torch.float64)
    return float(fn(corners).abs().max())


def test_largest_value_error_finds_the_error_at_a_vertex_and_inside():
    """Uniform states of a 6-D box miss its corners: an error that peaks at a vertex is found there, and one that
    peaks inside (a narrow bump no sample is near) by the ascent; each number is a max over the states looked at."""
    system = ph.systems.lq_ladder(3)
    x = system.sample(512, torch.Generator().manual_seed(0), dtype=torch.float64, box=system.domain)
    scale = _corners_max(system, system.value_star)

    def at_vertex(z):
        return system.value_star(z) + 1e-3 * z.sum(-1) ** 2

    found = metrics.largest_value_error(system, at_vertex, x, starts=3)
    sampled = float((1e-3 * x.sum(-1) ** 2).max() / system.value_star(x).max())
    assert found.sampled == pytest.approx(sampled, rel=1e-12)
    assert found.vertices == pytest.approx(1e-3 * 36 / scale, rel=1e-12) and found.at_vertex
    assert found.ascended == pytest.approx(found.vertices, rel=1e-12) and found.scale == pytest.approx(scale)
    assert found.sampled < found.vertices and float(x.sum(-1).abs().max()) < 5  # no sample near a corner
    centre = torch.tensor([0.3, -0.2, 0.1, 0.4, -0.5, 0.2], dtype=torch.float64)
    nearest = int((x - centre).norm(dim=-1).argmin())

    def bump(z):  # peaks at an inner state; its tail reaches the nearest sample, and the ascent climbs from it
        return system.value_star(z) + 1e-2 * torch.exp(-(z - centre).pow(2).sum(-1) / 0.1)

    found = metrics.largest_value_error(system, bump, x[nearest : nearest + 1], starts=1)
    assert found.ascended == pytest.approx(1e-2 / scale, rel=1e-6) and not found.at_vertex
    assert np.allclose(found.state, centre.numpy(), atol=1e-3)
    assert found.vertices < 0.1 * found.ascended  # the vertices are far from the bump


def test_largest_value_error_checks_its_inputs_first():
    system = ph.systems.lq_ladder(1)
    with pytest.raises(ValueError, match=r"\(N, 2\)"):
        metrics.largest_value_error(system, system.value_star, torch.zeros(3, 4, dtype=torch.float64))
    with pytest.raises(ValueError, match="no known V"):
        metrics.largest_value_error(ph.systems.pendulum(), system.value_star, torch.zeros(3, 2, dtype=torch.float64))
