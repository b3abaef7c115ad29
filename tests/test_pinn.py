"""Value networks: the hard-constraint ansatz, terminal costs, autograd gradients (the residuals are in
test_residuals.py)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from pinnhjb.pinn import (
    ACTIVATION_DERIVATIVES,
    MLP,
    FiniteHorizonValue,
    QuadraticTerminalCost,
    SteadyStateValue,
    ValueTerminalCost,
    ZeroTerminalCost,
    value_and_gradients,
)

BOX = [[-1.5, 1.5], [-1.0, 2.0]]
P_PHI = np.array([[2.0, 0.3], [0.3, 1.0]])


def model64(horizon, terminal=None, seed=0, **kw) -> FiniteHorizonValue:
    torch.manual_seed(seed)
    return FiniteHorizonValue(2, horizon, BOX, terminal, width=16, depth=2, **kw).double()


def states(count=64, seed=1) -> torch.Tensor:
    return torch.tensor(np.random.default_rng(seed).uniform(-1.5, 1.5, (count, 2)))


# ------------------------------------------------------------------------------ the ansatz
@pytest.mark.parametrize("T", [1.0, 0.7, 3.3])
def test_ansatz_meets_terminal_and_origin_conditions_quadratic(T):
    phi = QuadraticTerminalCost(P_PHI)
    model = model64(T, phi)
    x = states()
    v_T = model(x, T)
    np.testing.assert_allclose(v_T.detach().numpy(), phi(x).numpy(), rtol=0, atol=1e-14)
    zero = torch.zeros(7, 2, dtype=torch.float64)
    t = torch.linspace(0, T, 7, dtype=torch.float64)
    assert model(zero, t).abs().max() <= 1e-14
    # ... while the network is not trivial: v differs from phi away from t = T
    assert (model(x, 0.0) - phi(x)).abs().max() > 1e-3


def test_ansatz_meets_conditions_with_previous_stage_as_terminal_cost():
    previous = model64(0.8, QuadraticTerminalCost(P_PHI), seed=11)
    terminal = ValueTerminalCost(previous)
    assert not any(p.requires_grad for p in previous.parameters())  # the previous stage is frozen
    model = model64(0.5, terminal, seed=12)
    x = states()
    np.testing.assert_allclose(model(x, 0.5).detach().numpy(), previous(x, 0.0).detach().numpy(), rtol=0, atol=1e-14)
    zero = torch.zeros(5, 2, dtype=torch.float64)
    assert model(zero, torch.linspace(0, 0.5, 5, dtype=torch.float64)).abs().max() <= 1e-14
    # and the chain is not constant: the two networks differ
    assert (model(x, 0.0) - previous(x, 0.0)).abs().max() > 1e-3


def test_soft_model_is_the_bare_network():
    model = model64(1.0, QuadraticTerminalCost(P_PHI), ansatz=False)
    x = states(10)
    t = torch.rand(10, dtype=torch.float64)
    assert torch.equal(model(x, t), model.raw(x, t))
    # no conditions are built in: v(x, T) != phi(x), v(0, t) != 0 for a random network
    assert (model(x, 1.0) - model.terminal_cost(x)).abs().max() > 1e-3
    assert model(torch.zeros(1, 2, dtype=torch.float64), 0.3).abs().item() > 1e-6


def test_zero_terminal_cost_and_time_broadcasting():
    model = model64(2.0)
    assert isinstance(model.terminal_cost, ZeroTerminalCost)
    x = states(9)
    assert torch.equal(model(x, 2.0), torch.zeros(9, dtype=torch.float64))
    t = torch.full((9,), 0.25, dtype=torch.float64)
    assert torch.equal(model(x, 0.25), model(x, t))
    assert torch.equal(model(x, torch.tensor(0.25)), model(x, t))


def test_steady_state_ansatz_vanishes_at_origin():
    torch.manual_seed(0)
    model = SteadyStateValue(2, BOX, width=16, depth=2).double()
    assert model(torch.zeros(3, 2, dtype=torch.float64)).abs().max() == 0.0
    assert model(states(5)).abs().max() > 1e-4


def test_network_arguments_are_checked():
    with pytest.raises(ValueError, match="activation"):
        MLP(3, activation="relu6")
    with pytest.raises(ValueError, match="width"):
        MLP(3, width=0)
    with pytest.raises(ValueError, match="horizon"):
        FiniteHorizonValue(2, 0.0, BOX)
    with pytest.raises(ValueError, match="horizon"):
        FiniteHorizonValue(2, float("nan"), BOX)


# ------------------------------------------------------------------------------ autograd gradients
def test_value_and_gradients_match_torch_func_and_finite_differences():
    model = model64(1.3, QuadraticTerminalCost(P_PHI), activation="tanh")
    x = states(12)
    t = torch.tensor(np.random.default_rng(2).uniform(0, 1.3, 12))
    v, gx, gt = value_and_gradients(model, x, t)
    assert not gx.requires_grad and not gt.requires_grad  # no graph through the gradients by default
    np.testing.assert_array_equal(v.detach().numpy(), model(x, t).detach().numpy())

    # torch.func, one sample at a time
    def single(xi, ti):
        return model(xi.unsqueeze(0), ti.reshape(1)).squeeze(0)

    gx_f, gt_f = torch.func.vmap(torch.func.grad(single, argnums=(0, 1)))(x, t)
    np.testing.assert_allclose(gx.numpy(), gx_f.detach().numpy(), rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(gt.numpy(), gt_f.detach().numpy(), rtol=1e-12, atol=1e-13)

    # central differences in float64 (test-side only)
    h = 1e-6
    with torch.no_grad():
        fd_x = torch.stack(
            [(model(x + h * e, t) - model(x - h * e, t)) / (2 * h) for e in torch.eye(2, dtype=torch.float64)], dim=-1
        )
        fd_t = (model(x, t + h) - model(x, t - h)) / (2 * h)
    np.testing.assert_allclose(gx.numpy(), fd_x.numpy(), atol=1e-7)
    np.testing.assert_allclose(gt.numpy(), fd_t.numpy(), atol=1e-7)
    assert gx.abs().max() > 1e-3 and gt.abs().max() > 1e-3


def test_freshly_built_model_can_be_evaluated():
    model = FiniteHorizonValue(2, 1.0, BOX, width=8, depth=1)
    assert model(torch.zeros(3, 2), 0.5).shape == (3,)


@pytest.mark.parametrize("shared", [False, True])
def test_correction_derivatives_match_autograd_of_the_value(shared):
    """The training path (origin term at shared times, manual chain rule in t) equals autograd of v - phi."""
    torch.manual_seed(0)
    model = FiniteHorizonValue(2, 0.7, [[-1, 1], [-2, 2]]).double()
    x = torch.randn(12, 2, dtype=torch.float64)
    times = torch.rand(4, dtype=torch.float64) * 0.7
    index = torch.arange(12) % 4
    t = times[index]
    _, gx, gt = value_and_gradients(model, x, t)
    dx, dt = model.correction_derivatives(x, t, *((times, index) if shared else (None, None)))
    torch.testing.assert_close(dx, gx, rtol=0, atol=1e-12)
    torch.testing.assert_close(dt, gt, rtol=0, atol=1e-12)


# ------------------------------------------------------------------------------ flat_origin
def test_flat_origin_pins_the_gradient_at_the_origin():
    """flat_origin: v(0, t) = 0 and grad_x v(0, t) = grad phi(0) = 0 at every t, the terminal condition still exact,
    the network still free elsewhere; its training derivatives (the generic route) agree with autograd of v."""
    phi = QuadraticTerminalCost(P_PHI)
    model = model64(1.3, phi, flat_origin=True)
    plain = model64(1.3, phi)
    zero = torch.zeros(6, 2, dtype=torch.float64)
    t = torch.linspace(0, 1.3, 6, dtype=torch.float64)
    _, g0, _ = value_and_gradients(model, zero, t)
    _, g0_plain, _ = value_and_gradients(plain, zero, t)
    assert model(zero, t).abs().max() <= 1e-14 and g0.abs().max() <= 1e-13
    assert g0_plain.abs().max() > 1e-3  # without it the gradient at the origin is free
    x = states()
    np.testing.assert_allclose(model(x, 1.3).detach().numpy(), phi(x).numpy(), rtol=0, atol=1e-14)
    assert (model(x, 0.0) - phi(x)).abs().max() > 1e-3
    ts = torch.rand(x.shape[0], dtype=torch.float64) * 1.3
    _, gx, gt = value_and_gradients(model, x, ts)
    dx, dt = model.correction_derivatives(x, ts)
    torch.testing.assert_close(dx + 2 * x @ torch.as_tensor(P_PHI), gx, rtol=0, atol=1e-12)
    torch.testing.assert_close(dt, gt, rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="needs ansatz=True"):
        model64(1.0, flat_origin=True, ansatz=False)


@pytest.mark.parametrize("activation", ["tanh", "sigmoid", "softplus", "silu", "gelu"])
def test_mlp_tangent_is_forward_mode_and_composes_with_jacrev(activation):
    """MLP.tangent (flat_origin's slope x' grad_x N(0, t)) equals torch.func.jvp of the network, with the closed-form
    activation derivatives or jvp's for the rest, and its Jacobian in the weights by vmap(jacrev) equals autograd's
    (the route LM takes for a flat_origin model)."""
    torch.manual_seed(1)
    net = MLP(3, width=7, depth=2, activation=activation).double()
    z, dz = torch.randn(5, 3, dtype=torch.float64), torch.randn(5, 3, dtype=torch.float64)
    out, dout = net.tangent(z, dz)
    ref_out, ref_dout = torch.func.jvp(net, (z,), (dz,))
    torch.testing.assert_close(out, ref_out, rtol=0, atol=1e-14)
    torch.testing.assert_close(dout, ref_dout, rtol=0, atol=1e-13)
    assert (type(net.layers[1]) in ACTIVATION_DERIVATIVES) == (activation in ("tanh", "sigmoid"))
    slope = _Slope(net)
    params = dict(slope.named_parameters())

    def one(p, zi, dzi):
        return torch.func.functional_call(slope, p, (zi[None], dzi[None]))[0]

    jac = torch.func.vmap(torch.func.jacrev(one), in_dims=(None, 0, 0))(params, z, dz)
    for name, w in params.items():
        (expect,) = torch.autograd.grad(slope(z[2:3], dz[2:3]).sum(), w, allow_unused=True, materialize_grads=True)
        torch.testing.assert_close(jac[name][2], expect, rtol=0, atol=1e-13)


class _Slope(torch.nn.Module):
    """MLP.tangent's derivative as a module's forward, for functional_call."""

    def __init__(self, net):
        super().__init__()
        self.net = net

    def forward(self, z, dz):
        return self.net.tangent(z, dz)[1]
