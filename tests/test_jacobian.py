"""The structured Jacobian of pinnhjb.jacobian against torch.func's vmap(jacrev(...)) of the same residuals."""
from __future__ import annotations

import pytest
import torch
from torch.func import jacrev, vmap

import pinnhjb as ph
from pinnhjb.gauss_newton import FlatParameters, levenberg_marquardt
from pinnhjb.jacobian import residual_jacobian
from pinnhjb.pinn import FiniteHorizonValue, MLP, QuadraticTerminalCost, SteadyStateValue
from pinnhjb.training import (_finite_horizon_jacobian, _finite_horizon_point_residual, _steady_state_jacobian,
                              _steady_state_point_residual)

N_POINTS = 40


def _batch(system, gen, model=None, with_time=True):
    """A batch in the layout of the Levenberg-Marquardt samplers: (x, t, grad phi, f, g, Q) or (x, f, g, Q)."""
    x = system.sample(N_POINTS, gen, dtype=torch.float64)
    data = (system.f(x), system.g(x), system.Q(x))
    if not with_time:
        return (x, *data)
    t = model.horizon * torch.rand(N_POINTS, generator=gen, dtype=torch.float64)
    xg = x.clone().requires_grad_(True)
    phi = model.terminal_cost(xg)
    dphi = torch.autograd.grad(phi.sum(), xg)[0] if phi.requires_grad else torch.zeros_like(x)
    return (x, t, dphi, *data)


def _perturbed(module, gen):
    """The module's flat weights, moved off their initial values (biases are zero at first in some layers)."""
    theta = FlatParameters(module).get()
    return theta + 0.3 * torch.randn(theta.shape, generator=gen, dtype=theta.dtype)


@pytest.mark.parametrize("activation", ["tanh", "sigmoid", "silu"])
@pytest.mark.parametrize("system_name, depth", [("quartic", 3), ("third_order", 1)])
def test_finite_horizon_jacobian_matches_jacrev(system_name, depth, activation):
    gen = torch.Generator().manual_seed(0)
    system = ph.get_system(system_name)
    model = FiniteHorizonValue(system.n, 1.5, system.train_domain, width=7, depth=depth, activation=activation,
                               terminal_cost=QuadraticTerminalCost(torch.eye(system.n).numpy() * 0.7)).double()
    flat = FlatParameters(model.net)
    theta, batch = _perturbed(model.net, gen), _batch(system, gen, model)
    point = _finite_horizon_point_residual(system, model, flat)
    dims = (None,) + (0,) * len(batch)
    r_ref, J_ref = vmap(point, in_dims=dims)(theta, *batch), vmap(jacrev(point), in_dims=dims)(theta, *batch)
    r, J = _finite_horizon_jacobian(system, model)(theta, *batch)
    assert J.shape == (N_POINTS, theta.numel())
    assert torch.allclose(r, r_ref, rtol=1e-12, atol=1e-12)
    assert torch.allclose(J, J_ref, rtol=1e-10, atol=1e-12)


def test_steady_state_jacobian_matches_jacrev():
    gen = torch.Generator().manual_seed(1)
    system = ph.systems.pendulum()
    model = SteadyStateValue(system.n, system.train_domain, width=9, depth=2).double()
    flat = FlatParameters(model.net)
    theta, batch = _perturbed(model.net, gen), _batch(system, gen, with_time=False)
    point = _steady_state_point_residual(system, model, flat)
    dims = (None,) + (0,) * len(batch)
    r, J = _steady_state_jacobian(system, model)(theta, *batch)
    assert torch.allclose(r, vmap(point, in_dims=dims)(theta, *batch), rtol=1e-12, atol=1e-12)
    assert torch.allclose(J, vmap(jacrev(point), in_dims=dims)(theta, *batch), rtol=1e-10, atol=1e-12)


def test_levenberg_marquardt_takes_the_same_steps_with_either_jacobian():
    gen = torch.Generator().manual_seed(2)
    system = ph.systems.quartic()
    model = FiniteHorizonValue(system.n, 1.0, system.train_domain, width=6, depth=2).double()
    flat = FlatParameters(model.net)
    pool = _batch(system, gen, model)
    sample = lambda n: tuple(a[:n] for a in pool)  # noqa: E731 - the same points every iteration
    point = _finite_horizon_point_residual(system, model, flat)
    runs = [levenberg_marquardt(flat.get(), point, sample, steps=6, points=N_POINTS, jacobian=jac)
            for jac in (None, _finite_horizon_jacobian(system, model))]
    assert runs[0].steps == runs[1].steps == 6 and runs[0].rejected == runs[1].rejected
    assert runs[1].loss < 0.5 * float(point(flat.get(), *(a[0] for a in pool)) ** 2 + 1)  # it trained
    assert torch.allclose(runs[0].theta, runs[1].theta, rtol=1e-8, atol=1e-10)
    assert runs[0].loss == pytest.approx(runs[1].loss, rel=1e-8)


def test_bad_input_is_refused():
    net = MLP(3, width=4, depth=1).double()
    theta = FlatParameters(net).get()
    z, dz = torch.zeros(6, 3, dtype=torch.float64), torch.zeros(6, 2, 3, dtype=torch.float64)
    ok = lambda out, dout: out  # noqa: E731
    with pytest.raises(ValueError, match="need z"):
        residual_jacobian(net, theta, z, dz[:, :, :2], ok)
    with pytest.raises(ValueError, match="weights"):
        residual_jacobian(net, theta[:-1], z, dz, ok)
    with pytest.raises(ValueError, match="blocks"):
        residual_jacobian(net, theta, z, dz, ok, copies=4)
    with pytest.raises(ValueError, match="expected"):
        residual_jacobian(net, theta, z, dz, ok, copies=2)  # 6 rows in two blocks feed 3 residuals, not 6
    r, J = residual_jacobian(net, theta, z, dz, lambda out, dout: out[:3] + out[3:], copies=2)
    assert r.shape == (3,) and J.shape == (3, theta.numel())
