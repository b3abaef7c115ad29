"""The residual objects of pinnhjb.residuals: F_e, F_b, F_in and E_e on known solutions, their batched, per-point
and whole-model forms against each other, their structured Jacobians against torch.func's vmap(jacrev(...)), and
a new PDE form added by one class and a registration line."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch import nn
from torch.func import jacrev, vmap

import pinnhjb as ph
from pinnhjb import lq, residuals, training
from pinnhjb.gauss_newton import FlatParameters, levenberg_marquardt
from pinnhjb.pinn import FiniteHorizonValue, QuadraticTerminalCost, SteadyStateValue, value_and_gradients
from pinnhjb.residuals import FiniteHorizonHJB, SoftFiniteHorizonHJB, SteadyStateHJB

BOX = [[-1.5, 1.5], [-1.0, 2.0]]
N_POINTS = 40


def model64(horizon, terminal=None, seed=0, **kw) -> FiniteHorizonValue:
    torch.manual_seed(seed)
    return FiniteHorizonValue(2, horizon, BOX, terminal, width=16, depth=2, **kw).double()


def states(count=64, seed=1) -> torch.Tensor:
    return torch.tensor(np.random.default_rng(seed).uniform(-1.5, 1.5, (count, 2)))


def batch_of(residual, system, gen, count=N_POINTS, need_phi_grad=True):
    """Cached states and times in the training layout, and the per-point arguments built from them."""
    pool = training.StatePool(
        system,
        system.sample(count, gen, dtype=torch.float64),
        getattr(residual.model, "terminal_cost", None),
        need_phi_grad=need_phi_grad,
    )
    data = pool.take(torch.arange(count))
    t = None
    if residual.time_dependent:
        t = residual.model.horizon * torch.rand(count, generator=gen, dtype=torch.float64)
    return data, t


def perturbed(module, gen):
    """The module's flat weights, moved off their initial values (biases are zero at first in some layers)."""
    theta = FlatParameters(module).get()
    return theta + 0.3 * torch.randn(theta.shape, generator=gen, dtype=theta.dtype)


# ------------------------------------------------------------------------------ F_e, E_e on the LQ ground truth
EXAMPLES = {
    "2-state": (np.array([[1.0, 1.0], [0.0, 2.0]]), np.array([[0.0], [1.0]]), np.eye(2), np.array([[1.0]])),
    "3-state-2-inputs": (
        np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 2.0, -3.0]]),
        np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]),
        np.diag([1.0, 2.0, 0.5]),
        np.array([[1.0, 0.2], [0.2, 2.0]]),
    ),
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
        return torch.einsum("bi,bij,bj->b", x, P, x) + (t - t.detach()) * torch.einsum("bi,bij,bj->b", x, dP, x)


@pytest.mark.parametrize("name", EXAMPLES)
def test_riccati_value_has_zero_f_e(name):
    A, B, Q, R = EXAMPLES[name]
    n = A.shape[0]
    T = 2.0
    riccati = lq.riccati_ode(A, B, Q, R, T, P_T=np.eye(n))
    system = ph.systems.linear_quadratic(A, B, Q, R, domain=[[-1, 1]] * n)
    rng = np.random.default_rng(0)
    x = torch.tensor(rng.uniform(-1, 1, (100, n)))
    t = torch.tensor(rng.uniform(0, T, 100))

    exact = FiniteHorizonHJB(system, RiccatiValue(riccati)).evaluate(x, t)
    assert exact.shape == (100,)
    assert exact.abs().max() < 1e-9

    # dP/dt from the ODE identity is the actual rate of change of the dense solution (central difference)
    h = 1e-4
    t_in = np.clip(t.numpy(), 2 * h, T - 2 * h)
    fd = (riccati.at(t_in + h) - riccati.at(t_in - h)) / (2 * h)
    np.testing.assert_allclose(fd, riccati.derivative(t_in), atol=1e-6)

    perturbed = FiniteHorizonHJB(system, RiccatiValue(riccati, shift=0.1 * np.eye(n))).evaluate(x, t)
    assert perturbed.abs().max() > 1e-2
    assert (perturbed**2).mean() > 1e6 * (exact**2).mean()


def test_care_value_has_zero_e_e_and_f_e():
    A, B, Q, R = EXAMPLES["2-state"]
    system = ph.systems.linear_quadratic(A, B, Q, R, domain=[[-1, 1]] * 2)
    P = torch.as_tensor(lq.care(A, B, Q, R))

    class Stationary(nn.Module):
        def forward(self, x, t):
            return torch.einsum("bi,ij,bj->b", x, P, x) + 0.0 * t

    x = states(50)
    assert FiniteHorizonHJB(system, Stationary()).evaluate(x, 0.7).abs().max() < 1e-10
    steady = SteadyStateHJB(system, lambda z: Stationary()(z, torch.zeros(z.shape[0], dtype=z.dtype)))
    assert steady.evaluate(x).abs().max() < 1e-10


def test_f_e_is_dvdt_plus_min_hamiltonian():
    system = ph.systems.pendulum()
    model = model64(1.0, QuadraticTerminalCost(np.eye(2)))
    # this model's training box BOX differs from the pendulum's; that is fine for a pointwise identity
    x = states(20)
    t = torch.full((20,), 0.4, dtype=torch.float64)
    _, gx, gt = value_and_gradients(model, x, t)
    by_hand = (
        gt + (gx * system.f(x)).sum(-1) + system.Q(x) - 0.25 * (gx[:, 1] * (81.0 / 16.0)) ** 2
    )  # g = [0, 1/J]', R = 1
    np.testing.assert_allclose(
        FiniteHorizonHJB(system, model).evaluate(x, t).numpy(), by_hand.numpy(), rtol=1e-12, atol=1e-12
    )


def test_create_graph_allows_training_through_the_residual():
    system = ph.systems.pendulum()
    model = model64(1.0)
    x = states(16)
    res = FiniteHorizonHJB(system, model).evaluate(x, 0.5, create_graph=True)
    (res**2).mean().backward()
    grads = [p.grad for p in model.net.parameters()]
    assert all(g is not None for g in grads) and any(g.abs().max() > 0 for g in grads)


# ------------------------------------------------------------------------------ structured Jacobians vs jacrev
@pytest.mark.parametrize("flat_origin", [False, True])
@pytest.mark.parametrize("activation", ["tanh", "sigmoid", "silu"])
@pytest.mark.parametrize("system_name, depth", [("quartic", 3), ("third_order", 1)])
def test_finite_horizon_jacobian_matches_jacrev(system_name, depth, activation, flat_origin):
    """The structured Jacobian (with flat_origin: its mixed second derivative at the origin) is jacrev's."""
    gen = torch.Generator().manual_seed(0)
    system = ph.get_system(system_name)
    model = FiniteHorizonValue(
        system.n,
        1.5,
        system.train_domain,
        width=7,
        depth=depth,
        activation=activation,
        terminal_cost=QuadraticTerminalCost(torch.eye(system.n).numpy() * 0.7),
        flat_origin=flat_origin,
    ).double()
    res = FiniteHorizonHJB(system, model)
    flat = FlatParameters(model.net)
    theta = perturbed(model.net, gen)
    batch = res.point_arguments(*batch_of(res, system, gen))
    point = res.point_residual(flat)
    dims = (None,) + (0,) * len(batch)
    r_ref, J_ref = vmap(point, in_dims=dims)(theta, *batch), vmap(jacrev(point), in_dims=dims)(theta, *batch)
    r, J = res.jacobian()(theta, *batch)
    assert J.shape == (N_POINTS, theta.numel())
    assert torch.allclose(r, r_ref, rtol=1e-12, atol=1e-12)
    assert torch.allclose(J, J_ref, rtol=1e-10, atol=1e-12)


def test_steady_state_jacobian_matches_jacrev():
    gen = torch.Generator().manual_seed(1)
    system = ph.systems.pendulum()
    model = SteadyStateValue(system.n, system.train_domain, width=9, depth=2).double()
    res = SteadyStateHJB(system, model)
    flat = FlatParameters(model.net)
    theta = perturbed(model.net, gen)
    batch = res.point_arguments(*batch_of(res, system, gen, need_phi_grad=False))
    point = res.point_residual(flat)
    dims = (None,) + (0,) * len(batch)
    r, J = res.jacobian()(theta, *batch)
    assert torch.allclose(r, vmap(point, in_dims=dims)(theta, *batch), rtol=1e-12, atol=1e-12)
    assert torch.allclose(J, vmap(jacrev(point), in_dims=dims)(theta, *batch), rtol=1e-10, atol=1e-12)


def test_levenberg_marquardt_takes_the_same_steps_with_either_jacobian():
    gen = torch.Generator().manual_seed(2)
    system = ph.systems.quartic()
    model = FiniteHorizonValue(system.n, 1.0, system.train_domain, width=6, depth=2).double()
    res = FiniteHorizonHJB(system, model)
    flat = FlatParameters(model.net)
    pool = res.point_arguments(*batch_of(res, system, gen))
    sample = lambda n: tuple(a[:n] for a in pool)  # noqa: E731 - the same points every iteration
    point = res.point_residual(flat)
    runs = [
        levenberg_marquardt(flat.get(), point, sample, steps=6, points=N_POINTS, jacobian=jac)
        for jac in (None, res.jacobian())
    ]
    assert runs[0].steps == runs[1].steps == 6 and runs[0].rejected == runs[1].rejected
    assert runs[1].loss < 0.5 * float(point(flat.get(), *(a[0] for a in pool)) ** 2 + 1)  # it trained
    assert torch.allclose(runs[0].theta, runs[1].theta, rtol=1e-8, atol=1e-10)
    assert runs[0].loss == pytest.approx(runs[1].loss, rel=1e-8)


# ------------------------------------------------------------------------------ one residual, three routes
@pytest.mark.parametrize("shared", [False, True])
def test_f_e_batched_per_point_and_whole_model_agree(shared):
    """The training residual (cached f, g, Q, grad phi), the per-point form LM accepts steps on, the structured
    Jacobian's residual and autograd of the whole model are one F_e."""
    gen = torch.Generator().manual_seed(3)
    system = ph.systems.pendulum()
    model = FiniteHorizonValue(
        2, 0.8, system.train_domain, QuadraticTerminalCost(np.diag([1.0, 0.5])), width=10, depth=2
    ).double()
    res = FiniteHorizonHJB(system, model)
    data, t = batch_of(res, system, gen)
    shared_times = None
    if shared:
        times = 0.8 * torch.rand(8, generator=gen, dtype=torch.float64)
        index = torch.arange(N_POINTS) % 8
        t, shared_times = times[index], (times, index)
    batched = res.residual(data, t, shared_times).detach()
    theta = FlatParameters(model.net).get()
    args = res.point_arguments(data, t)
    per_point = vmap(res.point_residual(FlatParameters(model.net)), in_dims=(None,) + (0,) * len(args))(theta, *args)
    r, _ = res.jacobian()(theta, *args)
    whole = res.evaluate(data["x"], t)
    for other in (per_point, r, whole):
        torch.testing.assert_close(batched, other.detach(), rtol=1e-12, atol=1e-12)
    assert res.loss(data, t, None, None, shared_times).item() == pytest.approx(float((batched**2).mean()), rel=1e-14)


def test_e_e_batched_per_point_whole_model_and_field_agree():
    gen = torch.Generator().manual_seed(4)
    system = ph.systems.quartic()
    model = SteadyStateValue(2, system.train_domain, width=10, depth=2).double()
    res = SteadyStateHJB(system, model)
    data, _ = batch_of(res, system, gen, need_phi_grad=False)
    batched = res.residual(data).detach()
    theta = FlatParameters(model.net).get()
    args = res.point_arguments(data, None)
    per_point = vmap(res.point_residual(FlatParameters(model.net)), in_dims=(None,) + (0,) * len(args))(theta, *args)
    for other in (per_point, res.jacobian()(theta, *args)[0], res.evaluate(data["x"]), res.field(data["x"])):
        torch.testing.assert_close(batched, other.detach(), rtol=1e-12, atol=1e-12)
    # the soft model adds V(0)^2, E's second term (eq-e)
    soft = SteadyStateHJB(system, SteadyStateValue(2, system.train_domain, width=10, depth=2, ansatz=False).double())
    v0 = soft.model(torch.zeros(1, 2, dtype=torch.float64)).detach()
    expected = float((soft.residual(data).detach() ** 2).mean() + v0[0] ** 2)
    assert soft.loss(data).item() == pytest.approx(expected, rel=1e-14)


def test_soft_form_is_mse_e_plus_mse_b_plus_mse_in():
    gen = torch.Generator().manual_seed(5)
    system = ph.systems.pendulum()
    phi = QuadraticTerminalCost(np.eye(2))
    model = FiniteHorizonValue(2, 1.2, system.train_domain, phi, width=10, depth=2, ansatz=False).double()
    res = SoftFiniteHorizonHJB(system, model)
    data, t = batch_of(res, system, gen, need_phi_grad=False)
    boundary, _ = batch_of(res, system, gen, count=15, need_phi_grad=False)
    t_origin = 1.2 * torch.rand(9, generator=gen, dtype=torch.float64)
    f_e = res.evaluate(data["x"], t)  # the plain network N(x, t) is the value: F_e of the whole model
    xb = boundary["x"]
    f_b = model(xb, 1.2) - phi(xb)
    f_in = model(torch.zeros(9, 2, dtype=torch.float64), t_origin)
    torch.testing.assert_close(res.residual(data, t).detach(), f_e, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(res.terminal_residual(boundary).detach(), f_b.detach(), rtol=0, atol=0)
    torch.testing.assert_close(res.origin_residual(t_origin, xb).detach(), f_in.detach(), rtol=0, atol=0)
    expected = float(((f_e**2).mean() + (f_b**2).mean() + (f_in**2).mean()).detach())
    assert res.loss(data, t, boundary, t_origin).item() == pytest.approx(expected, rel=1e-12)
    with pytest.raises(NotImplementedError, match="per-point"):
        res.point_residual(FlatParameters(model.net))
    assert res.jacobian() is None


def test_training_refuses_a_form_for_the_other_kind_of_model():
    system = ph.systems.quartic()
    cfg = ph.TrainConfig.preset("quick", phases=(ph.Adam(steps=1),), pool_size=64, batch_size=32)
    soft = FiniteHorizonValue(2, 0.5, system.train_domain, width=4, depth=1, ansatz=False)
    with pytest.raises(ValueError, match="ansatz"):
        training.train_finite_horizon(system, soft, cfg, progress=False, residual="hjbt")
    with pytest.raises(KeyError, match="registered"):
        training.train_finite_horizon(system, soft, cfg, progress=False, residual="no such form")


# ------------------------------------------------------------------------------ the registry
def test_registry_holds_the_three_forms():
    assert residuals.get_residual("hjbt") is FiniteHorizonHJB
    assert residuals.get_residual("hjbt_soft") is SoftFiniteHorizonHJB
    assert residuals.get_residual("hjb") is SteadyStateHJB
    assert residuals.get_residual(SteadyStateHJB) is SteadyStateHJB
    with pytest.raises(ValueError, match="already registered"):
        residuals.register("hjb")(FiniteHorizonHJB)
    with pytest.raises(TypeError, match="subclass"):
        residuals.register("not a residual")(dict)


def test_a_new_pde_form_is_one_class_and_a_registration_line(monkeypatch):
    """A linear PDE, dv/dt + grad v' f + Q = 0 (the cost of the uncontrolled flow), trains one tiny stage by
    Levenberg-Marquardt through the same sampling, per-point form and structured Jacobian as F_e."""
    monkeypatch.setattr(residuals, "RESIDUALS", dict(residuals.RESIDUALS))  # leave the registry as it was

    @residuals.register("uncontrolled_cost")
    class UncontrolledCost(FiniteHorizonHJB):
        def pde(self, x, grad_x, dt, fx=None, gx=None, qx=None):
            fx = self.system.f(x) if fx is None else fx
            qx = self.system.Q(x) if qx is None else qx
            return dt + (grad_x * fx).sum(-1) + qx

    system = ph.systems.quartic()
    gen = torch.Generator().manual_seed(6)
    torch.manual_seed(0)
    model = FiniteHorizonValue(2, 0.5, system.train_domain, width=8, depth=2).double()
    form = UncontrolledCost(system, model)
    # its structured Jacobian comes with it
    theta = perturbed(model.net, gen)
    args = form.point_arguments(*batch_of(form, system, gen))
    point = form.point_residual(FlatParameters(model.net))
    dims = (None,) + (0,) * len(args)
    r, J = form.jacobian()(theta, *args)
    torch.testing.assert_close(J, vmap(jacrev(point), in_dims=dims)(theta, *args), rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(r, vmap(point, in_dims=dims)(theta, *args), rtol=1e-12, atol=1e-12)

    x = system.sample(500, gen, dtype=torch.float64)
    t = 0.5 * torch.rand(500, generator=gen, dtype=torch.float64)
    before = float((form.evaluate(x, t) ** 2).mean())
    cfg = ph.TrainConfig.preset(
        "default",
        width=8,
        depth=2,
        pool_size=2000,
        phases=(ph.LevenbergMarquardt(steps=40, points=300, points_coarse=None, min_progress=None),),
    )
    history = training.train_finite_horizon(system, model, cfg, seed=0, progress=False, residual="uncontrolled_cost")
    after = float((form.evaluate(x, t) ** 2).mean())
    hjb = float((FiniteHorizonHJB(system, model).evaluate(x, t) ** 2).mean())
    assert history.final_loss < 2e-2 * before and after < 2e-2 * before
    # it solved its own PDE, not the HJB (which has the control term)
    assert hjb > 10 * after
