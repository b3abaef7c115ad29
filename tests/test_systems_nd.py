"""The systems in more dimensions: rigid body (6-D attitude), LQ ladder (n = 2k) and converse (n even, exact V*)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

import pinnhjb as ph
from pinnhjb import lq, metrics, pinn, systems
from pinnhjb.systems import converse, fingerprint_difference, lq_ladder, rigid_body


def x64(a) -> torch.Tensor:
    return torch.as_tensor(np.asarray(a, dtype=float), dtype=torch.float64)


def uniform(system, count: int, seed: int, box=None) -> torch.Tensor:
    box = system.train_domain if box is None else np.asarray(box)
    return x64(np.random.default_rng(seed).uniform(box[:, 0], box[:, 1], (count, system.n)))


def corners(box: np.ndarray) -> torch.Tensor:
    n = box.shape[0]
    bits = (np.arange(2**n)[:, None] >> np.arange(n)) & 1
    return x64(np.where(bits == 1, box[:, 1], box[:, 0]))


# ------------------------------------------------------------------------------ all three
CASES = [
    (rigid_body, {}, 6, 3),
    (lq_ladder, {"k": 1}, 2, 1),
    (lq_ladder, {"k": 3}, 6, 3),
    (converse, {"n": 2}, 2, 1),
    (converse, {"n": 6}, 6, 3),
]


@pytest.mark.parametrize(("builder", "params", "n", "m"), CASES)
def test_builds_with_dimensions_origin_and_registry_round_trip(builder, params, n, m):
    system = builder(**params)
    assert (system.n, system.m) == (n, m)
    assert system.name == system.builder == builder.__name__
    assert system.params == params
    zero = torch.zeros(1, n, dtype=torch.float64)
    assert system.f(zero).abs().max().item() == 0.0
    assert system.Q(zero).item() == 0.0
    assert system.g(zero).shape == (1, n, m)
    assert np.all(system.train_domain[:, 0] <= system.domain[:, 0])
    assert np.all(system.train_domain[:, 1] >= system.domain[:, 1])
    again = ph.get_system(system.builder, **system.params)
    assert again.spec() == system.spec()
    assert fingerprint_difference(system.fingerprint(), again.fingerprint()) == []
    assert systems.SYSTEMS[builder.__name__] is builder


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda: lq_ladder(0), "lq_ladder: parameter k must be at least 1; got 0"),
        (lambda: lq_ladder(-2), "at least 1"),
        (lambda: lq_ladder(2.0), "lq_ladder: parameter k must be an integer; got 2.0"),
        (lambda: lq_ladder(True), "must be an integer"),
        (lambda: lq_ladder("3"), "must be an integer"),
        (lambda: converse(3), "converse: parameter n must be even"),
        (lambda: converse(0), "converse: parameter n must be at least 2; got 0"),
        (lambda: converse(4.0), "converse: parameter n must be an integer"),
        (lambda: converse(None), "must be an integer"),
        (lambda: ph.get_system("converse", n=5), "must be even"),
    ],
)
def test_bad_sizes_raise_before_anything_is_built(call, match, monkeypatch):
    def never(*args, **kwargs):
        raise AssertionError("built a system from a bad argument")

    monkeypatch.setattr(systems, "ControlAffineSystem", never)
    monkeypatch.setattr(systems, "_linear_quadratic", never)
    with pytest.raises(ValueError, match=match):
        call()


def test_numpy_integer_sizes_are_accepted_and_stored_as_int():
    assert lq_ladder(np.int64(2)).params == {"k": 2} and type(lq_ladder(np.int64(2)).params["k"]) is int
    assert converse(np.int32(4)).params == {"n": 4}


# ------------------------------------------------------------------------------ rigid body
# Tenavi/HJB_NN examples/satellite/problem_def.py, setup_problem.dynamics, transcribed for one state.
J_INV = np.diag([1 / 2, 1 / 3, 1 / 4])
B_W = np.array([[1.0, 1 / 20, 1 / 10], [1 / 15, 1.0, 1 / 10], [1 / 10, 1 / 15, 1.0]])
H = np.array([1.0, 1.0, 1.0])


def euler_E(v):
    sf, cf, ct, tt = np.sin(v[0]), np.cos(v[0]), np.cos(v[1]), np.tan(v[1])
    return np.array([[1.0, sf * tt, cf * tt], [0.0, cf, -sf], [0.0, sf / ct, cf / ct]])


def euler_R(v):
    sf, cf, st, ct, sp, cp = np.sin(v[0]), np.cos(v[0]), np.sin(v[1]), np.cos(v[1]), np.sin(v[2]), np.cos(v[2])
    return np.array(
        [
            [ct * cp, ct * sp, -st],
            [sf * st * cp - cf * sp, sf * st * sp + cf * cp, ct * sf],
            [cf * st * cp + sf * sp, cf * st * sp - sf * cp, ct * cf],
        ]
    )


def skew_S(w):
    return np.array([[0.0, w[2], -w[1]], [-w[2], 0.0, w[0]], [w[1], -w[0], 0.0]])


def reference_dynamics(x, u, h=H):
    v, w = x[:3], x[3:]
    return np.concatenate([euler_E(v) @ w, J_INV @ (skew_S(w) @ euler_R(v) @ h + B_W @ u)])


@pytest.fixture(scope="module")
def body():
    return rigid_body()


def test_rigid_body_boxes_weights_and_shapes(body):
    omega = np.array([[-np.pi / 3, np.pi / 3]] * 3 + [[-np.pi / 4, np.pi / 4]] * 3)
    np.testing.assert_allclose(body.domain, omega, rtol=1e-15)
    np.testing.assert_allclose(body.train_domain, 1.1 * omega, rtol=1e-15)
    assert body.train_domain[1, 1] < np.pi / 2  # theta stays away from the Euler-angle singularity
    np.testing.assert_allclose(body.R, np.eye(3) / 4)
    x = uniform(body, 7, 0)
    assert body.f(x).shape == (7, 6) and body.g(x).shape == (7, 6, 3) and body.Q(x).shape == (7,)
    v, w = x[:, :3], x[:, 3:]
    np.testing.assert_allclose(body.Q(x).numpy(), (0.5 * (v**2).sum(-1) + 5 * (w**2).sum(-1)).numpy(), rtol=1e-14)
    u = torch.tensor([[1.0, -2.0, 0.5]], dtype=torch.float64)
    assert body.running_cost(x[:1], u).item() == pytest.approx(body.Q(x[:1]).item() + (1 + 4 + 0.25) / 4)
    assert body.value_star is None and body.policy_star is None


def test_rigid_body_train_scale_sets_the_training_box_and_is_rebuilt_from_a_checkpoint(body, tmp_path):
    wide = rigid_body([1.5, 1.25, 1.5, 1.1, 1.1, 1.1])
    np.testing.assert_allclose(wide.train_domain[:, 1], body.domain[:, 1] * [1.5, 1.25, 1.5, 1.1, 1.1, 1.1])
    np.testing.assert_allclose(rigid_body(1.2).train_domain, 1.2 * body.domain)
    assert rigid_body().spec()["params"] == {}  # the default box: checkpoints made before the option load as before
    assert fingerprint_difference(wide.fingerprint(), body.fingerprint()) == ["train_domain"]
    config = ph.TrainConfig.preset("quick", phases=(), eval_points_per_dim=2)
    with warnings.catch_warnings():  # nothing trained: the solver may say so
        warnings.simplefilter("ignore", RuntimeWarning)
        sol = ph.FiniteHorizonSolver(wide, config, progress=False).solve(0.1)
    assert np.array_equal(ph.load(ph.save(sol, tmp_path / "wide.pt")).system.train_domain, wide.train_domain)


@pytest.mark.parametrize("build", [lambda s: lq_ladder(2, s), lambda s: converse(4, s)], ids=["ladder", "converse"])
def test_ladder_and_converse_train_scale_set_the_training_box(build, tmp_path):
    plain = build(None)
    np.testing.assert_allclose(plain.train_domain, 1.25 * plain.domain)  # the default box, unchanged
    assert "train_scale" not in plain.params  # checkpoints made before the option load as before
    wide = build(1.5)
    np.testing.assert_allclose(wide.train_domain, 1.5 * wide.domain)
    np.testing.assert_allclose(build([1, 1, 2, 2]).train_domain[:, 1], [1, 1, 2, 2])
    assert fingerprint_difference(wide.fingerprint(), plain.fingerprint()) == ["train_domain"]
    assert ph.systems.get_system(wide.builder, **wide.params).fingerprint() == wide.fingerprint()
    for bad, match in ((0.9, ">= 1"), ([1.5, 1.5], "one number or 4"), (float("inf"), ">= 1")):
        with pytest.raises(ValueError, match=match):
            build(bad)


@pytest.mark.parametrize(
    ("scale", "match"),
    [(0.9, ">= 1"), ([1.1, 1.1], "one number or 6"), (1.5, "below 1.5"), (float("nan"), ">= 1"), ("x", "or 6")],
)
def test_rigid_body_train_scale_refuses_bad_boxes(scale, match):
    with pytest.raises(ValueError, match=match):
        rigid_body(scale)


def test_rigid_body_finite_on_training_box(body):
    x = torch.cat([uniform(body, 4000, 1), corners(body.train_domain)])
    for key in ("f", "g", "Q"):
        assert torch.isfinite(getattr(body, key)(x)).all(), key
    body.check_finite(x, "the training box and its corners")


def test_rigid_body_matches_tenavi_dynamics(body):
    rng = np.random.default_rng(2)
    x = uniform(body, 20, 3)
    u = x64(rng.normal(size=(20, 3)))
    ours = body.dynamics(x, u).numpy()
    ref = np.stack([reference_dynamics(xi, ui) for xi, ui in zip(x.numpy(), u.numpy())])
    np.testing.assert_allclose(ours, ref, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(body.g(x).numpy()[0], np.vstack([np.zeros((3, 3)), J_INV @ B_W]), rtol=1e-15)


def test_rigid_body_linearization_is_tenavis_F_G_and_Q(body):
    lin = body.linearize()
    F = np.zeros((6, 6))
    F[:3, 3:] = np.eye(3)
    F[3:, 3:] = J_INV @ np.array([[0.0, -H[2], H[1]], [H[2], 0.0, -H[0]], [-H[1], H[0], 0.0]])
    np.testing.assert_allclose(lin.A, F, atol=1e-14)
    np.testing.assert_allclose(lin.B, np.vstack([np.zeros((3, 3)), J_INV @ B_W]), atol=1e-15)
    np.testing.assert_allclose(lin.Q, np.diag([0.5] * 3 + [5.0] * 3), atol=1e-13)

    # its LQR value: the ARE holds at P, and P is positive definite (the linearisation is stabilisable)
    P = body.lqr_value()
    residual = lq.are_residual(lin.A, lin.B, lin.Q, body.R, P)
    assert np.abs(residual).max() < 1e-10 * np.abs(P).max() and np.linalg.eigvalsh(P).min() > 0


def test_rigid_body_euler_conventions_are_consistent(body):
    # R(v) is a rotation, and along vdot = E(v) w the body-axes momentum R(v) h turns as d/dt R = S(w) R
    # (S(w) a = a x w): E and R belong to the same 3-2-1 convention. Checked on the package's matrices by autograd.
    x = uniform(body, 12, 4)
    v, w = x[:, :3], x[:, 3:]
    E, R = systems._euler_321(v)
    eye = torch.eye(3, dtype=torch.float64).expand(12, 3, 3)
    torch.testing.assert_close(R @ R.transpose(1, 2), eye, rtol=0, atol=1e-14)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(12, dtype=torch.float64), rtol=0, atol=1e-14)
    vdot = torch.einsum("bij,bj->bi", E, w)
    h = torch.tensor(H, dtype=torch.float64)
    _, dRh = torch.autograd.functional.jvp(lambda z: systems._euler_321(z)[1] @ h, (v,), (vdot,))
    expected = torch.linalg.cross(R @ h, w, dim=-1)
    torch.testing.assert_close(dRh, expected, rtol=0, atol=1e-13)
    # the same on the numpy transcription, by central differences
    for xi in x[:3].numpy():
        vi, wi = xi[:3], xi[3:]
        eps, d = 1e-6, euler_E(vi) @ wi
        dR = (euler_R(vi + eps * d) - euler_R(vi - eps * d)) / (2 * eps)
        np.testing.assert_allclose(dR, skew_S(wi) @ euler_R(vi), atol=1e-8)


def test_rigid_body_uncontrolled_motion_conserves_kinetic_energy(body):
    # J wdot = (R h) x w with u = 0, so w'J wdot = 0: w'Jw is constant along the RK4 trajectory
    x0 = uniform(body, 6, 5, box=body.domain / 2)
    run = metrics.closed_loop(body, lambda x: torch.zeros(x.shape[0], 3, dtype=x.dtype), x0, t_final=1.0, dt=0.01)
    w = run.x[:, :, 3:]
    energy = np.einsum("tbi,ij,tbj->tb", w, np.linalg.inv(J_INV), w)
    assert np.all(np.isfinite(energy)) and np.abs(w[-1] - w[0]).max() > 0.05  # the rates do change
    np.testing.assert_allclose(energy, np.broadcast_to(energy[0], energy.shape), rtol=1e-9)
    # and any attitude at rest is an equilibrium (all of h is in the wheels)
    rest = torch.cat([uniform(body, 5, 6)[:, :3], torch.zeros(5, 3, dtype=torch.float64)], dim=-1)
    assert body.f(rest).abs().max().item() == 0.0


# ------------------------------------------------------------------------------ LQ ladder
@pytest.mark.parametrize("k", [1, 2, 4, 8])
def test_lq_ladder_value_solves_are_and_closed_loop_is_hurwitz(k):
    system = lq_ladder(k)
    n = 2 * k
    assert (system.n, system.m) == (n, k)
    np.testing.assert_array_equal(system.domain, [[-1.0, 1.0]] * n)
    # the springs by hand: A = [[0, I], [-K, 0]], B = [[0], [I]]
    stiffness = 2 * np.eye(k) - np.eye(k, k=1) - np.eye(k, k=-1)
    stiffness[-1, -1] = 1.0
    A = np.block([[np.zeros((k, k)), np.eye(k)], [-stiffness, np.zeros((k, k))]])
    B = np.vstack([np.zeros((k, k)), np.eye(k)])
    lin = system.linearize()
    np.testing.assert_array_equal(lin.A, A)
    np.testing.assert_array_equal(lin.B, B)
    np.testing.assert_allclose(lin.Q, np.eye(n), atol=1e-14)
    np.testing.assert_array_equal(system.R, np.eye(k))
    # P from V* itself: half its Hessian (V* = x'Px); K from mu* = -Kx
    zero = torch.zeros(n, dtype=torch.float64)
    P = 0.5 * torch.autograd.functional.hessian(lambda z: system.value_star(z[None])[0], zero).numpy()
    K = -system.policy_star(torch.eye(n, dtype=torch.float64)).numpy().T
    np.testing.assert_allclose(P, P.T, atol=1e-14)
    assert np.linalg.eigvalsh(P).min() > 0
    residual = A.T @ P + P @ A - P @ B @ B.T @ P + np.eye(n)
    assert np.abs(residual).max() <= 1e-10 * max(1.0, np.abs(P).max() ** 2)
    np.testing.assert_allclose(K, B.T @ P, atol=1e-12)
    assert np.linalg.eigvals(A - B @ K).real.max() < -1e-3
    np.testing.assert_allclose(P, lq.care(A, B, np.eye(n), np.eye(k)), atol=1e-12)


# ------------------------------------------------------------------------------ converse
def hjb_relative_residual(system, x):
    _, p = pinn.gradient(system.value_star, x)
    fx, gx, qx = system.f(x), system.g(x), system.Q(x)
    res = system.hamiltonian_min(x, p, fx, gx, qx)
    gTp = torch.einsum("bnm,bn->bm", gx, p)
    scale = (p * fx).sum(-1).abs() + qx + 0.25 * torch.einsum("bi,ij,bj->b", gTp, system.R_inv_tensor(x), gTp)
    return res, scale, p


@pytest.mark.parametrize("n", [4, 8, 12])
def test_converse_value_solves_hjb_to_rounding(n):
    system = converse(n)
    x = torch.cat([uniform(system, 400, n), corners(system.domain)[:64]])
    res, scale, p = hjb_relative_residual(system, x)
    assert (scale > 0).all()
    assert (res.abs() <= 1e-10 * scale).all(), (res.abs() / scale).max().item()
    # not a vacuous identity: a perturbed V is not a solution
    _, q = pinn.gradient(lambda z: 1.1 * system.value_star(z), x)
    assert (system.hamiltonian_min(x, q).abs() / scale).max() > 1e-2
    # mu* is the policy of V*'s gradient, and Q > 0 off the origin
    torch.testing.assert_close(system.policy_from_gradient(x, p), system.policy_star(x), rtol=1e-13, atol=1e-13)
    assert (system.Q(x) > 0).all() and (system.value_star(x) > 0).all()


@pytest.mark.parametrize("n", [4, 8, 12])
def test_converse_open_loop_unstable_and_linear_part_is_lqr(n):
    system = converse(n)
    lin = system.linearize()
    assert np.linalg.eigvals(lin.A).real.max() > 0.1  # the control has work to do
    zero = torch.zeros(n, dtype=torch.float64)
    P = 0.5 * torch.autograd.functional.hessian(lambda z: system.value_star(z[None])[0], zero).numpy()
    np.testing.assert_allclose(lq.care(lin.A, lin.B, lin.Q, system.R), P, atol=1e-10)


@pytest.mark.parametrize("n", [4, 8, 12])
def test_converse_optimal_closed_loop_decays_with_cost_v_star(n):
    system = converse(n)
    x0 = uniform(system, 4, 10 + n, box=system.domain)
    run = metrics.closed_loop(system, system.policy_star, x0, t_final=8.0, dt=0.01)
    assert run.stabilized.all()
    norms = np.linalg.norm(run.x, axis=-1)
    assert np.all(norms[-1] < 1e-3 * norms[0])
    cost, tail = metrics.infinite_horizon_cost(system, run)
    assert np.all(tail < 1e-6 * cost)
    v0 = system.value_star(x0).numpy()
    np.testing.assert_allclose(cost, v0, rtol=1e-3)
    # V* decreases along the optimal trajectories
    values = np.stack([system.value_star(x64(xt)).numpy() for xt in run.x[::50]])
    assert np.all(np.diff(values, axis=0) < 0)


def test_default_width_rule_keeps_small_systems_and_widens_from_six():
    """The default recipe's width rule: unchanged below n = 6 (the paper's systems and their benchmarks), 3 x 40
    with more LM points than weights from n = 6 on; the solvers apply it to their system."""
    from pinnhjb.config import WIDE_FROM, default_network

    assert ph.TrainConfig.preset("default", dimension=2) == ph.TrainConfig.preset("default")
    wide = ph.TrainConfig.preset("default", dimension=WIDE_FROM)
    assert wide.width == 40 and wide.phase("lm").points == 4500 and wide.phase("lm").points_coarse == 2000
    weights = 8 * 40 + 2 * 41 * 40 + 41  # 3 x 40 on (x, t) with n = 6: 3641
    assert wide.phase("lm").points > weights > wide.phase("lm").points_coarse
    assert ph.FiniteHorizonSolver(ph.systems.rigid_body(), "default").config.width == 40
    assert ph.FiniteHorizonSolver(ph.systems.pendulum(), "default").config.width == 24
    assert ph.TrainConfig.preset("default", dimension=8, width=16).width == 16  # an override still wins
    with pytest.raises(ValueError, match="dimension must be an integer"):
        default_network(0)


def test_flat_origin_trains_by_lm_and_round_trips(tmp_path):
    """A short default (LM) chain with flat_origin on the quartic system: the residual form hands LM its
    structured Jacobian (with the mixed derivative at the origin), the learned policy vanishes at the origin, and a
    saved chain loads back with the flag and the same values."""
    from pinnhjb.residuals import FiniteHorizonHJB

    config = ph.TrainConfig.preset("default", flat_origin=True).with_phase("lm", steps=20, min_progress=None)
    solver = ph.FiniteHorizonSolver(ph.systems.quartic(), config, seed=0, device="cpu", progress=False)
    sol = solver.extend(solver.solve(0.5), to=1.0)
    assert FiniteHorizonHJB(sol.system, sol.stages[-1].model).jacobian() is not None
    zero = np.zeros((1, 2))
    assert np.abs(sol.gradient(zero)).max() < 1e-12 and np.abs(sol.policy(zero)).max() < 1e-12
    assert sol.metrics["E"] < sol.metrics["E_zero"]  # it learned
    back = ph.load(ph.save(sol, tmp_path / "flat.pt"), device="cpu")
    assert back.config.flat_origin and back.stages[-1].model.flat_origin
    x = np.random.default_rng(0).uniform(-1, 1, (32, 2))
    np.testing.assert_array_equal(back.value(x), sol.value(x))
    with pytest.raises(ValueError, match="flat_origin"):
        ph.TrainConfig.preset("adam_lbfgs", ansatz=False, flat_origin=True)
