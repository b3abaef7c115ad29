"""Built-in systems (paper Section 6), the quartic erratum, LQ ground truth and construction checks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import pinnhjb as ph
from pinnhjb import metrics, pinn
from pinnhjb.residuals import SteadyStateHJB
from pinnhjb.systems import ControlAffineSystem


def x64(rows) -> torch.Tensor:
    return torch.tensor(rows, dtype=torch.float64)


# ------------------------------------------------------------------------------ built-in constants
def test_pendulum_constants_by_hand():
    # M = 1/3, l = 2/3, J = 4/3 M l^2 = 4/3 * 1/3 * 4/9 = 16/81, f_d = 0.2, g = 9.8
    sys = ph.systems.pendulum()
    x1, x2 = 0.5, -0.3
    J = 16.0 / 81.0
    mgl = (1.0 / 3.0) * 9.8 * (2.0 / 3.0)  # = 19.6 / 9
    expected_f = [x2, (-mgl * math.sin(x1) - 0.2 * x2) / J]
    f = sys.f(x64([[x1, x2]]))
    np.testing.assert_allclose(f.numpy()[0], expected_f, rtol=1e-14)
    assert expected_f[1] == pytest.approx(-4.98192, abs=1e-5)  # the number itself, worked out on paper
    g = sys.g(x64([[x1, x2]]))
    assert g.shape == (1, 2, 1)
    np.testing.assert_allclose(g.numpy()[0, :, 0], [0.0, 81.0 / 16.0], rtol=1e-14)
    assert sys.Q(x64([[x1, x2]])).item() == pytest.approx(0.25 + 0.09, rel=1e-14)
    np.testing.assert_array_equal(sys.R, [[1.0]])
    np.testing.assert_array_equal(sys.domain, [[-1, 1], [-1, 1]])
    np.testing.assert_array_equal(sys.train_domain, [[-1.5, 1.5], [-1.5, 1.5]])
    assert (sys.n, sys.m) == (2, 1)
    assert sys.value_star is None and sys.policy_star is None
    np.testing.assert_array_equal(ph.systems.pendulum(R=2.5).R, [[2.5]])


def test_third_order_constants_by_hand():
    # K = 0.05, C = 3.5, a = 5.5, b = 4
    sys = ph.systems.third_order(R=0.1)
    x1, x2, x3 = 0.1, -0.2, 0.15
    expected = [-2 * x1 + x2**3, -3.5 * x2 + x3, -0.05 * (5.5 * x2**3 + 4 * x2 + x1**3)]
    np.testing.assert_allclose(sys.f(x64([[x1, x2, x3]])).numpy()[0], expected, rtol=1e-14)
    np.testing.assert_allclose(sys.g(x64([[x1, x2, x3]])).numpy()[0, :, 0], [0.0, 0.0, 0.05])
    np.testing.assert_array_equal(sys.R, [[0.1]])
    np.testing.assert_array_equal(sys.domain, [[-0.2, 0.2]] * 3)
    assert (sys.n, sys.m) == (3, 1)


def test_quartic_definition_by_hand():
    sys = ph.systems.quartic()
    x1, x2 = 0.7, -0.4
    s = math.sin(x1)
    expected = [-x1 + x2 + 2 * x2**3, -0.5 * (x1 + x2) + 0.5 * x2 * (1 + 2 * x2**2) * s**2]
    x = x64([[x1, x2]])
    np.testing.assert_allclose(sys.f(x).numpy()[0], expected, rtol=1e-14)
    np.testing.assert_allclose(sys.g(x).numpy()[0, :, 0], [0.0, s], rtol=1e-14)
    assert sys.Q(x).item() == pytest.approx(x1**2 + x2**2 + 2 * x2**4, rel=1e-14)
    assert ph.systems.quartic("paper").Q(x).item() == pytest.approx(x1**2 + x2**2 + x2**4, rel=1e-14)
    assert sys.value_star(x).item() == pytest.approx(0.5 * x1**2 + x2**2 + x2**4, rel=1e-14)
    assert sys.policy_star(x).item() == pytest.approx(-s * (x2 + 2 * x2**3), rel=1e-14)


# ------------------------------------------------------------------------------ quartic erratum
def test_quartic_value_star_solves_hjb_with_consistent_cost():
    sys = ph.systems.quartic()  # state_cost="consistent"
    grid = sys.grid(101)
    assert grid.dtype == torch.float64 and grid.shape == (101 * 101, 2)
    out = metrics.infinite_horizon_residual(sys, sys.value_star, points=grid)
    assert out["E"] < 1e-12
    assert out["E_boundary"] == 0.0
    assert out["E_zero"] > 1.0  # the residual is small next to that of V = 0


def test_quartic_printed_cost_leaves_residual_minus_x2_to_the_fourth():
    paper = ph.systems.quartic(state_cost="paper")
    assert paper.value_star is None and paper.policy_star is None  # V* is not optimal for the printed Q
    value_star = ph.systems.quartic().value_star
    x = paper.grid(41)
    residual = SteadyStateHJB(paper, value_star).evaluate(x)
    np.testing.assert_allclose(residual.numpy(), -(x[:, 1] ** 4).numpy(), atol=1e-12)
    assert residual.abs().max() > 1.0  # clearly nonzero on Omega = [-1.2, 1.2]^2


def test_quartic_rejects_unknown_state_cost():
    with pytest.raises(ValueError, match="state_cost"):
        ph.systems.quartic(state_cost="printed")


def test_quartic_policy_star_is_policy_of_value_star():
    sys = ph.systems.quartic()
    x = sys.grid(21)
    _, grad = pinn.gradient(sys.value_star, x)
    x1, x2 = x[:, 0], x[:, 1]
    np.testing.assert_allclose(grad.numpy(), torch.stack([x1, 2 * x2 + 4 * x2**3], -1).numpy(), rtol=1e-14)
    mu = sys.policy_from_gradient(x, grad)
    assert mu.shape == (x.shape[0], 1)
    np.testing.assert_allclose(mu.numpy(), sys.policy_star(x).numpy(), atol=1e-14)


# ------------------------------------------------------------------------------ LQ
A = np.array([[1.0, 1.0], [0.0, 2.0]])
B = np.array([[0.0], [1.0]])


@pytest.fixture(scope="module")
def lq_system():
    return ph.systems.linear_quadratic(A, B, np.diag([1.0, 2.0]), [[0.5]], domain=[[-1, 1], [-2, 2]])


def test_lq_value_star_is_care_quadratic_with_zero_residual(lq_system):
    P = ph.lq.care(A, B, np.diag([1.0, 2.0]), [[0.5]])
    x = torch.tensor(np.random.default_rng(0).uniform(-1, 1, (20, 2)))
    np.testing.assert_allclose(
        lq_system.value_star(x).numpy(), np.einsum("bi,ij,bj->b", x.numpy(), P, x.numpy()), rtol=1e-13
    )
    out = metrics.infinite_horizon_residual(lq_system, lq_system.value_star)
    assert out["E"] < 1e-18 and out["E_zero"] > 0.1
    _, grad = pinn.gradient(lq_system.value_star, x)
    np.testing.assert_allclose(
        lq_system.policy_from_gradient(x, grad).numpy(), lq_system.policy_star(x).numpy(), atol=1e-12
    )
    # a perturbed quadratic is not a solution
    wrong = metrics.infinite_horizon_residual(lq_system, lambda z: 1.1 * lq_system.value_star(z))
    assert wrong["E"] > 1e-3


def test_lq_system_through_registry(lq_system):
    again = ph.get_system("lq", **lq_system.params)
    assert again.spec() == lq_system.spec()
    x = lq_system.grid(5)
    assert torch.equal(again.value_star(x), lq_system.value_star(x))


def test_get_system_builds_registered_systems():
    assert ph.get_system("pendulum", R=3.0).params == {"R": 3.0}
    assert ph.get_system("quartic", state_cost="paper").params == {"state_cost": "paper"}
    assert ph.get_system("third_order").n == 3
    with pytest.raises(KeyError) as info:
        ph.get_system("nope")
    msg = str(info.value)
    assert "nope" in msg
    for name in ("pendulum", "quartic", "third_order", "lq"):
        assert name in msg


# ------------------------------------------------------------------------------ construction errors
def _f(x):
    return -x


def _g(x):
    return torch.ones(x.shape[0], 2, 1, dtype=x.dtype)


def _Q(x):
    return (x**2).sum(-1)


def make(**overrides) -> ControlAffineSystem:
    kw = dict(name="mine", f=_f, g=_g, Q=_Q, R=[[1.0]], domain=[[-1, 1], [-1, 1]])
    kw.update(overrides)
    return ControlAffineSystem(**kw)


def test_valid_user_system():
    sys = make(train_domain=[-2, 2])  # a (2,) training box is tiled over the state
    assert (sys.n, sys.m) == (2, 1)
    np.testing.assert_array_equal(sys.train_domain, [[-2, 2], [-2, 2]])
    assert sys.spec() == {"name": "mine", "builder": None, "params": None, "n": 2, "m": 1}


def test_f_with_wrong_shape_is_named_with_its_shape():
    with pytest.raises(ValueError, match=r"f\(x\) returned shape \(5,\).*expected \(5, 2\)"):
        make(f=lambda x: x.sum(-1))


def test_g_with_wrong_shape():
    with pytest.raises(ValueError, match=r"g\(x\) returned shape \(5, 2\).*expected \(5, 2, 1\)"):
        make(g=lambda x: torch.ones_like(x))


def test_Q_with_wrong_shape_and_negative_Q():
    with pytest.raises(ValueError, match=r"Q\(x\) returned shape"):
        make(Q=lambda x: x**2)
    with pytest.raises(ValueError, match="negative"):
        make(Q=lambda x: -(x**2).sum(-1))


def test_function_returning_non_tensor_or_failing():
    with pytest.raises(TypeError, match=r"f\(x\) must return a torch.Tensor"):
        make(f=lambda x: x.numpy())
    with pytest.raises(ValueError, match=r"g\(x\) failed"):
        make(g=lambda x: x[:, 7])


def test_f_nonzero_at_origin():
    with pytest.raises(ValueError, match=r"f\(0\) must be 0"):
        make(f=lambda x: -x + 1.0)


def test_nan_output_rejected():
    with pytest.raises(ValueError, match="NaN"):
        make(f=lambda x: torch.where(x > 0, torch.nan, -x))


@pytest.mark.parametrize(
    "R, match",
    [
        ([[-1.0]], "positive definite"),
        ([[0.0]], "positive definite"),
        ([[1.0, 0.5], [0.0, 1.0]], "symmetric"),
        ([[float("nan")]], "NaN"),
        ([[1.0, 2.0]], "square"),
    ],
)
def test_bad_R(R, match):
    with pytest.raises(ValueError, match=match):
        make(R=R)


@pytest.mark.parametrize(
    "domain",
    [
        [[-1, 1, 0], [-1, 1, 0]],  # three columns
        [[[-1, 1]], [[-1, 1]]],  # three dimensions
        [[1, -1], [-1, 1]],  # low > high
        [[-1, np.inf], [-1, 1]],  # unbounded
    ],
)
def test_bad_domain(domain):
    with pytest.raises(ValueError, match="domain"):
        make(domain=domain)


def test_train_domain_with_wrong_dimension():
    with pytest.raises(ValueError, match="train_domain"):
        make(train_domain=[[-1, 1]] * 3)


def test_check_states():
    sys = ph.systems.pendulum()
    x = torch.zeros(4, 2)
    assert sys.check_states(x) is x
    assert isinstance(sys.check_states(np.zeros((3, 2))), torch.Tensor)
    with pytest.raises(ValueError, match=r"shape \(N, 2\).*\(4, 3\)"):
        sys.check_states(torch.zeros(4, 3))
    with pytest.raises(ValueError, match=r"\(2,\)"):
        sys.check_states(torch.zeros(2))
    with pytest.raises(ValueError, match="NaN"):
        sys.check_states(torch.tensor([[0.0, float("nan")]]))
    with pytest.raises(ValueError, match="NaN or infinite"):
        sys.check_states(torch.tensor([[0.0, float("inf")]]))


def test_box_reach_is_the_largest_coordinate_per_half_width_from_the_boxs_centre():
    system = ph.systems.linear_quadratic(
        np.zeros((2, 2)), np.eye(2), np.eye(2), np.eye(2), domain=[[0.0, 2.0], [-1.0, 3.0]]
    )
    box = system.train_domain
    centre, half = box.mean(axis=1), (box[:, 1] - box[:, 0]) / 2
    x = np.stack([centre, box[:, 1], centre + [0.5 * half[0], -1.5 * half[1]], box[:, 0] - 1e-9])
    np.testing.assert_allclose(system.box_reach(x), [0.0, 1.0, 1.5, 1.0], atol=1e-8)
    assert system.outside_training_box(x).tolist() == [False, False, True, True]
    assert system.box_reach(x.reshape(2, 2, 2)).shape == (2, 2)
