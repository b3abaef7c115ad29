"""pinnhjb.parametric: one network for every control weight r R0, r over a range."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import pinnhjb as ph
from pinnhjb.lq import riccati_ode
from pinnhjb.parametric import WeightFamily

A, B, Q = np.array([[0.0, 1.0], [-1.0, -0.5]]), np.array([[0.0], [1.0]]), np.eye(2)


@pytest.fixture(scope="module")
def family():
    base = ph.systems.linear_quadratic(A, B, Q, [[1.0]], domain=[[-1, 1], [-1, 1]])
    return WeightFamily(base, (0.1, 10.0))


@pytest.fixture(scope="module")
def trained(family):
    """One stage on [0, 1] over r in [0.1, 10] (the default recipe, a few seconds)."""
    cfg = ph.TrainConfig.preset("default", eval_points_per_dim=11)
    return ph.FiniteHorizonSolver(family.system, cfg, seed=0, device="cpu", progress=False).solve(1.0)


def test_the_augmented_hamiltonian_is_the_one_of_each_weight(family):
    """min_u H of the augmented system at (x, log10 r) equals that of the base system with weight r R0 (no
    training: the identity the whole module rests on)."""
    gen = torch.Generator().manual_seed(0)
    x = 2 * torch.rand(50, 2, generator=gen, dtype=torch.float64) - 1
    p = torch.randn(50, 3, generator=gen, dtype=torch.float64)
    for r in (0.1, 0.5, 1.0, 7.0):
        z = family.states(x, r)
        weighted = ph.systems.linear_quadratic(A, B, Q, [[r]], domain=[[-1, 1], [-1, 1]])
        torch.testing.assert_close(
            family.system.hamiltonian_min(z, p), weighted.hamiltonian_min(x, p[:, :2]), rtol=1e-12, atol=1e-12
        )


def test_one_network_gives_the_exact_lq_value_and_policy_at_every_weight(family, trained):
    x = family.base.grid(11).numpy()
    for r in (0.1, 0.3, 1.0, 3.0, 10.0):
        exact = riccati_ode(A, B, Q, [[r]], 1.0)
        v = exact.value(x, 0.0)
        assert np.abs(family.value(trained, x, r) - v).max() <= 5e-3 * np.abs(v).max(), r
        u = exact.policy(x, 0.0)
        assert np.abs(family.policy(trained, x, r) - u).max() <= 1e-2 * np.abs(u).max(), r
    # the policy read back is mu = -1/2 (r R0)^-1 g' grad_x V, from the gradient read back
    r = 2.0
    grad = family.gradient(trained, x, r)
    np.testing.assert_allclose(family.policy(trained, x, r)[:, 0], -0.5 / r * grad[:, 1], rtol=1e-10, atol=1e-12)
    # and one weight per state works too
    rs = np.linspace(0.1, 10.0, x.shape[0])
    per_state = family.value(trained, x, rs)
    np.testing.assert_allclose(per_state[:3], [family.value(trained, x[k : k + 1], rs[k])[0] for k in range(3)])


def test_bad_ranges_and_weights_are_refused(family):
    base = family.base
    for bad in [(0.0, 1.0), (2.0, 1.0), (1.0, float("inf")), ("a", 1.0), (1.0,)]:
        with pytest.raises(ValueError, match="r_range"):
            WeightFamily(base, bad)
    with pytest.raises(TypeError, match="ControlAffineSystem"):
        WeightFamily("pendulum", (0.1, 10.0))
    with pytest.raises(ValueError, match=r"r must lie in r_range \[0.1, 10\]"):
        family.states(np.zeros((1, 2)), 20.0)


def test_a_member_reads_like_a_solution_of_its_own_system(family, trained):
    x = family.base.grid(5).numpy()
    member = family.member(trained, 3.0)
    assert member.system.R.tolist() == [[3.0]] and member.system.n == 2 and member.horizon == 1.0
    np.testing.assert_array_equal(member.value(x), family.value(trained, x, 3.0))
    np.testing.assert_array_equal(member.policy(x), family.policy(trained, x, 3.0))
    # its residual is its own system's: the augmented E_e at (x, log10 r) against a direct evaluation
    z = torch.as_tensor(family.states(x, 3.0)).requires_grad_(True)
    v = trained.stages[0].model(z, 0.0)
    (grad,) = torch.autograd.grad(v.sum(), z)
    direct = member.system.hamiltonian_min(torch.as_tensor(x), grad[:, :2])
    np.testing.assert_allclose(member.residual_field(x), direct.detach().numpy(), rtol=1e-10, atol=1e-12)
    with pytest.raises(ValueError, match="r must lie in r_range"):
        family.member(trained, 0.01)


def test_the_family_extends_like_any_system(family, trained):
    """Theorem 2's extension works on the family unchanged: V_2 at every weight from the chain [0, 1] + [1, 2]."""
    cfg = ph.TrainConfig.preset("default", eval_points_per_dim=11)
    chain = ph.FiniteHorizonSolver(family.system, cfg, seed=0, device="cpu", progress=False).extend(trained, to=2.0)
    x = family.base.grid(11).numpy()
    for r in (0.1, 1.0, 10.0):
        v = riccati_ode(A, B, Q, [[r]], 2.0).value(x, 0.0)
        assert np.abs(family.value(chain, x, r) - v).max() <= 5e-3 * np.abs(v).max(), r
        np.testing.assert_array_equal(family.value(chain, x, r, horizon=1.0), family.value(trained, x, r))
