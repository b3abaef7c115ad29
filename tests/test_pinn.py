"""Value networks and residuals: the hard-constraint ansatz, F_e against the Riccati ODE, autograd gradients."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn

import pinnhjb as ph
from pinnhjb import lq
from pinnhjb.pinn import (MLP, FiniteHorizonValue, QuadraticTerminalCost, SteadyStateValue, ValueTerminalCost,
                          ZeroTerminalCost, flow_residual, hjb_residual, value_and_gradients)

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


# ------------------------------------------------------------------------------ F_e on the LQ ground truth
EXAMPLES = {
    "2-state": (np.array([[1.0, 1.0], [0.0, 2.0]]), np.array([[0.0], [1.0]]), np.eye(2), np.array([[1.0]])),
    "3-state-2-inputs": (np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 2.0, -3.0]]),
                         np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]), np.diag([1.0, 2.0, 0.5]),
                         np.array([[1.0, 0.2], [0.2, 2.0]])),
}


class RiccatiValue(nn.Module):
    """V(x, t) = x'(P(t) + shift)x with P(t) from the Riccati ODE and dV/dt = x'P'(t)x.

    P(t) comes from numpy, so the time derivative is attached by the identity
    v = x'Px + (t - stop_grad(t)) x'P'x: the value is unchanged, d/dt = x'P'x, d/dx = 2Px.
    """

    def __init__(self, riccati: lq.RiccatiSolution, shift=None):
        super().__init__()
        self.riccati = riccati
        n = riccati.A.shape[0]
        self.shift = torch.zeros(n, n, dtype=torch.float64) if shift is None else torch.as_tensor(shift)

    def forward(self, x, t):
        t_np = t.detach().numpy()
        P = torch.as_tensor(self.riccati.at(t_np)) + self.shift
        dP = torch.as_tensor(self.riccati.derivative(t_np))
        return (torch.einsum("bi,bij,bj->b", x, P, x)
                + (t - t.detach()) * torch.einsum("bi,bij,bj->b", x, dP, x))


@pytest.mark.parametrize("name", EXAMPLES)
def test_riccati_value_has_zero_flow_residual(name):
    A, B, Q, R = EXAMPLES[name]
    n = A.shape[0]
    T = 2.0
    riccati = lq.riccati_ode(A, B, Q, R, T, P_T=np.eye(n))
    system = ph.systems.linear_quadratic(A, B, Q, R, domain=[[-1, 1]] * n)
    rng = np.random.default_rng(0)
    x = torch.tensor(rng.uniform(-1, 1, (100, n)))
    t = torch.tensor(rng.uniform(0, T, 100))

    exact = flow_residual(system, RiccatiValue(riccati), x, t)
    assert exact.shape == (100,)
    assert exact.abs().max() < 1e-9

    # dP/dt from the ODE identity is the actual rate of change of the dense solution (central difference)
    h = 1e-4
    t_in = np.clip(t.numpy(), 2 * h, T - 2 * h)
    fd = (riccati.at(t_in + h) - riccati.at(t_in - h)) / (2 * h)
    np.testing.assert_allclose(fd, riccati.derivative(t_in), atol=1e-6)

    perturbed = flow_residual(system, RiccatiValue(riccati, shift=0.1 * np.eye(n)), x, t)
    assert perturbed.abs().max() > 1e-2
    assert (perturbed**2).mean() > 1e6 * (exact**2).mean()


def test_care_value_has_zero_steady_state_residual_and_flow_residual():
    A, B, Q, R = EXAMPLES["2-state"]
    system = ph.systems.linear_quadratic(A, B, Q, R, domain=[[-1, 1]] * 2)
    P = torch.as_tensor(lq.care(A, B, Q, R))

    class Stationary(nn.Module):
        def forward(self, x, t):
            return torch.einsum("bi,ij,bj->b", x, P, x) + 0.0 * t

    x = states(50)
    assert flow_residual(system, Stationary(), x, 0.7).abs().max() < 1e-10
    assert hjb_residual(system, lambda z: Stationary()(z, torch.zeros(z.shape[0], dtype=z.dtype)), x).abs().max() < 1e-10


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
        fd_x = torch.stack([(model(x + h * e, t) - model(x - h * e, t)) / (2 * h)
                            for e in torch.eye(2, dtype=torch.float64)], dim=-1)
        fd_t = (model(x, t + h) - model(x, t - h)) / (2 * h)
    np.testing.assert_allclose(gx.numpy(), fd_x.numpy(), atol=1e-7)
    np.testing.assert_allclose(gt.numpy(), fd_t.numpy(), atol=1e-7)
    assert gx.abs().max() > 1e-3 and gt.abs().max() > 1e-3


def test_flow_residual_is_dvdt_plus_min_hamiltonian():
    system = ph.systems.pendulum()
    model = model64(1.0, QuadraticTerminalCost(np.eye(2)))
    # this model's training box BOX differs from the pendulum's; that is fine for a pointwise identity
    x = states(20)
    t = torch.full((20,), 0.4, dtype=torch.float64)
    _, gx, gt = value_and_gradients(model, x, t)
    by_hand = (gt + (gx * system.f(x)).sum(-1) + system.Q(x)
               - 0.25 * (gx[:, 1] * (81.0 / 16.0)) ** 2)  # g = [0, 1/J]', R = 1
    np.testing.assert_allclose(flow_residual(system, model, x, t).numpy(), by_hand.numpy(), rtol=1e-12, atol=1e-12)


def test_create_graph_allows_training_through_the_residual():
    system = ph.systems.pendulum()
    model = model64(1.0)
    x = states(16)
    res = flow_residual(system, model, x, 0.5, create_graph=True)
    (res**2).mean().backward()
    grads = [p.grad for p in model.net.parameters()]
    assert all(g is not None for g in grads) and any(g.abs().max() > 0 for g in grads)


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
