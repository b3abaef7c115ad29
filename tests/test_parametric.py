"""pinnhjb.parametric: one network for a family of systems, a control weight r R0 or any parameter p over a range."""

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


# ---------------------------------------------------------------------- a parameter in f, g, Q and R


def _general_family():
    """p in f, g, Q and a 2 x 2 R(p): every place a parameter can enter."""

    def f(x, p):
        return torch.stack([x[:, 1], -p * x[:, 0] - 0.5 * x[:, 1] + 0.1 * x[:, 0] ** 3], dim=-1)

    def g(x, p):
        out = torch.zeros(x.shape[0], 2, 2, dtype=x.dtype)
        out[:, 0, 0], out[:, 1, 1], out[:, 1, 0] = 1.0, 1.0 + p, 0.2 * p
        return out

    def Q(x, p):
        return (1.0 + p) * x[:, 0] ** 2 + x[:, 1] ** 2

    def R(p):
        out = torch.zeros(p.shape[0], 2, 2, dtype=p.dtype)
        out[:, 0, 0], out[:, 1, 1], out[:, 0, 1], out[:, 1, 0] = 1.0 + p, 2.0, 0.3 * p, 0.3 * p
        return out

    return ph.parametric.ParametricFamily("general", f, g, Q, R, domain=[[-1, 1], [-1, 1]], p_range=(0.5, 2.0))


def test_a_parameter_anywhere_gives_each_members_hamiltonian():
    """min_u H and the policy map of the augmented system at (x, s) are those of the member ``at(p)``, with p in f,
    g, Q and a full R(p) (no training)."""
    family = _general_family()
    assert family.log is False and family.s_range == (-0.75, 0.75) and family.centre == 1.25
    gen = torch.Generator().manual_seed(1)
    x = 2 * torch.rand(40, 2, generator=gen, dtype=torch.float64) - 1
    lam = torch.randn(40, 3, generator=gen, dtype=torch.float64)
    for p in (0.5, 1.1, 2.0):
        member = family.at(p)
        torch.testing.assert_close(
            family.system.hamiltonian_min(family.states(x, p), lam), member.hamiltonian_min(x, lam[:, :2])
        )
        # the minimising input read back through the input map is the member's own
        z = family.states(x, p)
        u_tilde = family.system.policy_from_gradient(z, lam)
        s = z[:, -1]
        u = family._map(family._input_map(s), u_tilde)
        torch.testing.assert_close(u, member.policy_from_gradient(x, lam[:, :2]))


class _Lam:
    """A stand-in solution whose gradient is a fixed field, to test the policy read back without training."""

    def __init__(self, system):
        self.system = system

    def gradient(self, z, t=0.0):
        z = torch.as_tensor(z, dtype=torch.float64)
        return torch.stack([z[:, 0] + z[:, 1], z[:, 1] - 2 * z[:, 0], z[:, 2]], dim=-1).numpy()

    def policy(self, z, t=0.0):
        z = torch.as_tensor(z, dtype=torch.float64)
        return self.system.policy_from_gradient(z, torch.as_tensor(self.gradient(z))).numpy()


def test_the_policy_read_back_is_the_members_minimiser():
    family = _general_family()
    sol = _Lam(family.system)
    x = family.at(1.0).grid(4).numpy()
    for p in (0.5, 1.7):
        grad = torch.as_tensor(family.gradient(sol, x, p))
        expect = family.at(p).policy_from_gradient(torch.as_tensor(x), grad).numpy()
        np.testing.assert_allclose(family.policy(sol, x, p), expect, rtol=1e-10, atol=1e-12)


def test_one_network_over_a_dynamics_and_weight_parameter_gives_each_exact_lq_value():
    """xdot = p x + u, cost x^2 + (2 + p) u^2, p in [-1, 1] (uniform): one stage on [0, 2] against the exact
    Riccati V_2 of each p."""
    family = ph.parametric.ParametricFamily(
        "scalar",
        lambda x, p: p[:, None] * x,
        lambda x, p: torch.ones(x.shape[0], 1, 1, dtype=x.dtype),
        lambda x, p: x[:, 0] ** 2,
        R=lambda p: (2.0 + p)[:, None, None],
        domain=[[-1, 1]],
        p_range=(-1.0, 1.0),
    )
    assert family.log is False
    cfg = ph.TrainConfig.preset("default", eval_points_per_dim=11)
    sol = ph.FiniteHorizonSolver(family.system, cfg, seed=0, device="cpu", progress=False).solve(2.0)
    x = np.linspace(-1, 1, 21)[:, None]
    for p in (-1.0, -0.3, 0.0, 0.6, 1.0):
        exact = riccati_ode([[p]], [[1.0]], [[1.0]], [[2.0 + p]], 2.0)
        v, u = exact.value(x, 0.0), exact.policy(x, 0.0)
        assert np.abs(family.value(sol, x, p) - v).max() <= 5e-3 * np.abs(v).max(), p
        assert np.abs(family.policy(sol, x, p) - u).max() <= 1e-2 * np.abs(u).max(), p
        assert np.abs(family.member(sol, p).value(x) - v).max() <= 5e-3 * np.abs(v).max(), p


def test_bad_families_are_refused_before_training():
    fam = _general_family()
    with pytest.raises(ValueError, match="p_range"):
        ph.parametric.ParametricFamily("x", fam.f, fam.g, fam.Q, fam.R, fam.domain, p_range=(2.0, 1.0))
    with pytest.raises(ValueError, match="log=True samples log10 p"):
        ph.parametric.ParametricFamily("x", fam.f, fam.g, fam.Q, fam.R, fam.domain, p_range=(-1.0, 1.0), log=True)
    with pytest.raises(ValueError, match="symmetric positive definite"):
        ph.parametric.ParametricFamily(
            "x",
            fam.f,
            fam.g,
            fam.Q,
            lambda p: -torch.eye(2, dtype=p.dtype).expand(p.shape[0], 2, 2),
            fam.domain,
            (1, 2),
        )
    with pytest.raises(TypeError, match="f must be a batched torch callable"):
        ph.parametric.ParametricFamily("x", None, fam.g, fam.Q, fam.R, fam.domain, (1, 2))
    with pytest.raises(ValueError, match=r"p must lie in p_range \[0.5, 2\]"):
        fam.at(3.0)
    # log-uniform by default where the range spans a decade
    wide = ph.parametric.ParametricFamily("x", fam.f, fam.g, fam.Q, [[1.0, 0.0], [0.0, 1.0]], fam.domain, (0.1, 10.0))
    assert wide.log and wide.s_range == (-1.0, 1.0)
