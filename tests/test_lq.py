"""Tests for pinnhjb.lq: LQ ground truth of the steady-state (eq:HJB) and finite-horizon (eq:HJBT) HJB."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla
from scipy.integrate import solve_ivp

from pinnhjb import lq
from pinnhjb.lq import are_residual, are_solutions, care, lqr_gain, riccati_ode

# 2-state: unstable, Hamiltonian eigenvalues +-1.126, +-2.175 (distinct, real)
A2 = np.array([[1.0, 1.0], [0.0, 2.0]])
B2 = np.array([[0.0], [1.0]])
Q2 = np.eye(2)
R2 = np.array([[1.0]])
# 3-state, two inputs
A3 = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [-1.0, 2.0, -3.0]])
B3 = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
Q3 = np.diag([1.0, 2.0, 0.5])
R3 = np.array([[1.0, 0.2], [0.2, 2.0]])
# 3-state, one input, Hamiltonian eigenvalues +-1.018, +-2.029, +-3.138 (distinct, real)
A3r = np.array([[-1.0, 1.0, 0.0], [0.0, -2.0, 1.0], [0.0, 0.0, -3.0]])
B3r = np.array([[0.0], [0.0], [1.0]])
# lightly damped oscillator: Hamiltonian eigenvalues +-0.678 +-0.977i (complex)
A_osc = np.array([[0.0, 1.0], [-1.0, -0.1]])

EXAMPLES = {"2-state": (A2, B2, Q2, R2), "3-state": (A3, B3, Q3, R3)}


def min_eig(M: np.ndarray) -> float:
    return float(np.linalg.eigvalsh((M + M.T) / 2).min())


# ------------------------------------------------------------------------------------ ARE
@pytest.mark.parametrize("name", EXAMPLES)
def test_care_matches_scipy_and_solves_are(name: str) -> None:
    A, B, Q, R = EXAMPLES[name]
    P = care(A, B, Q, R)
    np.testing.assert_allclose(P, sla.solve_continuous_are(A, B, Q, R), rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(P, P.T)
    assert np.abs(are_residual(A, B, Q, R, P)).max() < 1e-9
    K = lqr_gain(B, R, P)
    np.testing.assert_allclose(K, np.linalg.solve(R, B.T @ P), rtol=1e-12)
    assert np.all(np.linalg.eigvals(A - B @ K).real < 0)


def _check_solutions(A, B, Q, R, expected: int) -> None:
    sols = are_solutions(A, B, Q, R)
    assert len(sols) == expected
    assert [s.stabilizing for s in sols] == [True] + [False] * (expected - 1)
    np.testing.assert_allclose(sols[0].P, care(A, B, Q, R), rtol=1e-9, atol=1e-10)
    for s in sols:
        assert np.isrealobj(s.P)
        np.testing.assert_array_equal(s.P, s.P.T)
        assert np.abs(are_residual(A, B, Q, R, s.P)).max() < 1e-8
        np.testing.assert_allclose(s.eigenvalues, s.chosen, atol=1e-8)
        assert s.stabilizing == bool(np.all(s.eigenvalues.real < 0))
    for i in range(expected):  # all distinct
        for j in range(i):
            assert np.abs(sols[i].P - sols[j].P).max() > 1e-6
    # the stabilizing solution is the maximal one: P_care >= P for every symmetric solution
    assert all(min_eig(sols[0].P - s.P) > -1e-9 for s in sols)


def test_are_solutions_2_state_real() -> None:
    _check_solutions(A2, B2, Q2, R2, expected=4)


def test_are_solutions_3_state_real() -> None:
    _check_solutions(A3r, B3r, np.eye(3), np.eye(1), expected=8)


def test_are_solutions_complex_hamiltonian() -> None:
    _check_solutions(A_osc, B2, np.eye(2), np.eye(1), expected=2)


def test_are_solutions_rejects_degenerate_hamiltonian() -> None:
    # decoupled identical modes: Hamiltonian eigenvalues +-sqrt(2), each double
    with pytest.raises(ValueError, match="repeated eigenvalues"):
        are_solutions(-np.eye(2), np.eye(2), np.eye(2), np.eye(2))
    # Q = 0 with a marginally stable mode: eigenvalue 0 on the imaginary axis
    with pytest.raises(ValueError, match="imaginary axis"):
        are_solutions(np.array([[0.0]]), np.array([[1.0]]), np.array([[0.0]]), np.array([[1.0]]))


# ------------------------------------------------------------------------- Riccati ODE
@pytest.mark.parametrize("name", EXAMPLES)
def test_zero_terminal_cost_increases_to_care(name: str) -> None:
    """Lemma le:inc: with phi = 0, P_T(0) increases with T and is bounded by (converges to) P_care."""
    A, B, Q, R = EXAMPLES[name]
    P_star = care(A, B, Q, R)
    P0 = [riccati_ode(A, B, Q, R, T).at(0.0) for T in (0.5, 1.0, 2.0, 4.0, 8.0)]
    for P_short, P_long in zip(P0, P0[1:]):
        assert min_eig(P_long - P_short) >= -1e-10
        assert min_eig(P_long - P_short) > 0 or np.allclose(P_long, P_star, atol=1e-6)
    assert all(min_eig(P_star - P) >= -1e-10 for P in P0)
    np.testing.assert_allclose(riccati_ode(A, B, Q, R, 30.0).at(0.0), P_star, atol=1e-6)


@pytest.mark.parametrize("name", EXAMPLES)
def test_terminal_cost_above_value_converges_from_above(name: str) -> None:
    """Lemma le:ucon2 / eq:final with psi(x) = |x|^2: P* <= P_T(0) <= P* + Phi(T)'Phi(T), x*(T) = Phi(T) x.

    The decrease need not be monotone here (the Riccati residual at P* + I is indefinite); the
    bounds, convergence and the sandwich eq:sandwich between phi = 0 and phi = psi + V* must hold.
    """
    A, B, Q, R = EXAMPLES[name]
    n = A.shape[0]
    P_star = care(A, B, Q, R)
    A_cl = A - B @ lqr_gain(B, R, P_star)
    for T in (0.5, 1.0, 2.0, 4.0, 8.0):
        P_upper = riccati_ode(A, B, Q, R, T, P_T=P_star + np.eye(n)).at(0.0)
        Phi = sla.expm(A_cl * T)
        assert min_eig(P_upper - P_star) >= -1e-10
        assert min_eig(P_star + Phi.T @ Phi - P_upper) >= -1e-10
        P_mid = riccati_ode(A, B, Q, R, T, P_T=np.eye(n)).at(0.0)
        P_lower = riccati_ode(A, B, Q, R, T).at(0.0)
        assert min_eig(P_mid - P_lower) >= -1e-10 and min_eig(P_upper - P_mid) >= -1e-10
    P_long = riccati_ode(A, B, Q, R, 30.0, P_T=P_star + np.eye(n)).at(0.0)
    np.testing.assert_allclose(P_long, P_star, atol=1e-6)


@pytest.mark.parametrize("name", EXAMPLES)
def test_terminal_cost_twice_value_decreases_to_care(name: str) -> None:
    """phi = psi + V* with psi = V* (P_T = 2 P*): Riccati residual (1-c)Q + (c-c^2) P*GP* <= 0 at c = 2,
    so P_T(0) decreases monotonically with T to P*."""
    A, B, Q, R = EXAMPLES[name]
    P_star = care(A, B, Q, R)
    assert np.linalg.eigvalsh(are_residual(A, B, Q, R, 2 * P_star)).max() <= 1e-10
    P0 = [riccati_ode(A, B, Q, R, T, P_T=2 * P_star).at(0.0) for T in (0.5, 1.0, 2.0, 4.0, 8.0)]
    for P_short, P_long in zip(P0, P0[1:]):
        assert min_eig(P_short - P_long) >= -1e-10
    assert all(min_eig(P - P_star) >= -1e-10 for P in P0)
    np.testing.assert_allclose(riccati_ode(A, B, Q, R, 30.0, P_T=2 * P_star).at(0.0), P_star, atol=1e-6)


@pytest.mark.parametrize("name", EXAMPLES)
def test_value_solves_finite_horizon_hjb(name: str) -> None:
    """V_T(x, t) = x'P(t)x satisfies eq:HJBT (in the paper's gradient form) and V_T(x, T) = x'P_T x."""
    A, B, Q, R = EXAMPLES[name]
    n = A.shape[0]
    rng = np.random.default_rng(0)
    P_T = np.diag(rng.uniform(0.0, 2.0, n))
    T = 3.0
    sol = riccati_ode(A, B, Q, R, T, P_T=P_T)
    x = rng.uniform(-2.0, 2.0, (50, n))
    t = rng.uniform(0.0, T, 50)

    P = sol.at(t)
    grad = 2 * np.einsum("nij,nj->ni", P, x)  # grad_x V_T
    dVdt = np.einsum("ni,nij,nj->n", x, sol.derivative(t), x)
    G = B @ np.linalg.solve(R, B.T)
    hjb = (
        dVdt
        + np.einsum("ni,ni->n", grad, x @ A.T)
        + np.einsum("ni,ij,nj->n", x, Q, x)
        - 0.25 * np.einsum("ni,ij,nj->n", grad, G, grad)
    )
    assert np.abs(hjb).max() < 1e-8

    # dP/dt from the ODE identity agrees with a central difference of the dense output
    h = 1e-4
    t_in = np.clip(t, 2 * h, T - 2 * h)
    fd = (sol.at(t_in + h) - sol.at(t_in - h)) / (2 * h)
    np.testing.assert_allclose(fd, sol.derivative(t_in), rtol=1e-6, atol=1e-6)

    terminal = np.einsum("ni,ij,nj->n", x, P_T, x)
    np.testing.assert_allclose(sol.value(x, T), terminal, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sol.value(x, t), np.einsum("ni,nij,nj->n", x, P, x), rtol=1e-12)
    # eq:muTstar: mu_T = -1/2 R^{-1} B' grad_x V_T
    mu = -0.5 * np.linalg.solve(R, B.T @ grad.T).T
    np.testing.assert_allclose(sol.policy(x, t), mu, rtol=1e-10, atol=1e-12)


def test_riccati_solution_grid_and_time_invariance() -> None:
    """Stored grid is ascending in [0, T]; P for horizon T at time 0 equals P for horizon 8 at 8 - T."""
    t_eval = np.linspace(0.0, 8.0, 17)
    long = riccati_ode(A2, B2, Q2, R2, 8.0, t_eval=t_eval[::-1])
    np.testing.assert_array_equal(long.t, t_eval)
    assert long.P.shape == (17, 2, 2)
    np.testing.assert_allclose(long.P, long.at(t_eval), rtol=1e-14)
    np.testing.assert_allclose(long.P[-1], 0.0, atol=1e-14)
    for T in (0.5, 2.0):
        short = riccati_ode(A2, B2, Q2, R2, T)
        np.testing.assert_allclose(short.at(0.0), long.at(8.0 - T), rtol=1e-8, atol=1e-10)
    radau = riccati_ode(A2, B2, Q2, R2, 8.0, method="Radau")
    np.testing.assert_allclose(radau.at(0.0), long.at(0.0), rtol=1e-7)
    default = riccati_ode(A2, B2, Q2, R2, 8.0)
    assert default.t[0] == 0.0 and default.t[-1] == 8.0 and np.all(np.diff(default.t) > 0)
    with pytest.raises(ValueError, match="horizon"):
        long.at(8.5)


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("args", "match"),
    [
        ((np.ones((2, 3)), B2, Q2, R2), r"^A must .*got shape \(2, 3\)"),
        ((A2, np.ones((3, 1)), Q2, R2), r"^B must .*\(n=2, m\).*got shape \(3, 1\)"),
        ((A2, np.ones(2), Q2, R2), r"^B must .*got shape \(2,\)"),
        ((A2, B2, np.eye(3), R2), r"^Q must .*got shape \(3, 3\)"),
        ((A2, B2, Q2, np.eye(2)), r"^R must .*\(m=1, m=1\).*got shape \(2, 2\)"),
        ((A2, B2, np.array([[1.0, 1.0], [0.0, 1.0]]), R2), r"^Q must be symmetric"),
        ((A2, B2, -np.eye(2), R2), r"^Q must be positive semidefinite"),
        ((A2, np.eye(2), Q2, np.array([[1.0, 0.5], [0.0, 1.0]])), r"^R must be symmetric"),
        ((A2, np.eye(2), Q2, np.diag([1.0, -1.0])), r"^R must be positive definite"),
        ((A2, B2, Q2, np.zeros((1, 1))), r"^R must be positive definite"),
        ((np.array([[np.nan, 0.0], [0.0, 1.0]]), B2, Q2, R2), r"^A must have finite entries"),
        ((A2, np.array([[np.inf], [1.0]]), Q2, R2), r"^B must have finite entries"),
        ((A2, B2, Q2, np.array([[np.nan]])), r"^R must have finite entries"),
    ],
)
@pytest.mark.parametrize("func", [care, are_solutions, lambda *a: riccati_ode(*a, horizon=1.0)])
def test_bad_input_names_argument(func, args, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        func(*args)


def test_bad_input_other_arguments() -> None:
    with pytest.raises(ValueError, match=r"^P must .*got shape \(3, 3\)"):
        are_residual(A2, B2, Q2, R2, np.eye(3))
    with pytest.raises(ValueError, match=r"^P must have finite entries"):
        lqr_gain(B2, R2, np.full((2, 2), np.nan))
    with pytest.raises(ValueError, match=r"^R must be positive definite"):
        lqr_gain(B2, -R2, np.eye(2))
    with pytest.raises(ValueError, match=r"^P_T must be positive semidefinite"):
        riccati_ode(A2, B2, Q2, R2, 1.0, P_T=-np.eye(2))
    with pytest.raises(ValueError, match=r"^P_T must .*got shape \(3, 3\)"):
        riccati_ode(A2, B2, Q2, R2, 1.0, P_T=np.eye(3))
    for horizon in (0.0, -1.0, np.inf, np.nan):
        with pytest.raises(ValueError, match="horizon"):
            riccati_ode(A2, B2, Q2, R2, horizon)
    with pytest.raises(ValueError, match="horizon"):
        riccati_ode(A2, B2, Q2, R2, 1.0, t_eval=[0.0, 2.0])
    with pytest.raises(ValueError, match=r"^x must"):
        riccati_ode(A2, B2, Q2, R2, 1.0).value(np.ones((4, 3)), 0.0)


# --------------------------------------------------------------------- convergence bound (Theorem 1)
def test_convergence_bound_holds_and_error_vanishes_with_the_horizon():
    A = np.array([[0.0, 1.0], [2.0, -1.0]])
    B = np.array([[0.0], [1.0]])
    Q, R = np.eye(2), np.eye(1)
    side = np.linspace(-1.0, 1.0, 11)
    x0 = np.stack(np.meshgrid(side, side, indexing="ij"), -1).reshape(-1, 2)
    rows = [lq.convergence_bound(A, B, Q, R, np.eye(2), T, x0) for T in (0.5, 1.0, 2.0, 4.0, 8.0)]
    for r in rows:
        assert r["error"] <= max(r["lower"], r["upper"]) + 1e-9  # eq. (sandwich)
        assert max(r["lower"], r["upper"]) <= r["bound"] + 1e-9  # eqs. (ineq2), (final)
    errors = [r["error"] for r in rows]
    assert all(b < a for a, b in zip(errors, errors[1:])) and errors[-1] < 1e-3


def test_horizon_gap_is_the_scalar_closed_form_and_the_sandwichs_lower_end():
    # scalar: with beta = sqrt(a^2 + q/r), P_T(0) = q sinh(beta T) / (beta cosh(beta T) - a sinh(beta T)) and
    # P* = r (a + beta), so the gap is the same relative number at every state
    a, q, r, T = 0.5, 2.0, 0.5, 1.5
    beta = np.sqrt(a**2 + q / r)
    p_T = q * np.sinh(beta * T) / (beta * np.cosh(beta * T) - a * np.sinh(beta * T))
    p_star = r * (a + beta)
    x = np.array([[0.3], [-1.0], [0.7]])
    gap = lq.horizon_gap([[a]], [[1.0]], [[q]], [[r]], T, x)
    assert gap == pytest.approx(abs(p_T - p_star) / p_star, rel=1e-8)
    A = np.array([[0.0, 1.0], [2.0, -1.0]])
    B, x0 = np.array([[0.0], [1.0]]), np.random.default_rng(0).uniform(-1, 1, (50, 2))
    low = lq.convergence_bound(A, B, np.eye(2), np.eye(1), np.zeros((2, 2)), 2.0, x0)["lower"]
    v_star = np.einsum("ni,ij,nj->n", x0, care(A, B, np.eye(2), np.eye(1)), x0)
    assert lq.horizon_gap(A, B, np.eye(2), np.eye(1), 2.0, x0) == pytest.approx(low / v_star.max(), rel=1e-12)


def test_transition_matches_simulated_closed_loop():
    A = np.array([[0.0, 1.0], [2.0, -1.0]])
    B = np.array([[0.0], [1.0]])
    sol = lq.riccati_ode(A, B, np.eye(2), np.eye(1), 2.0)
    x0 = np.array([0.3, -0.2])
    ode = solve_ivp(lambda t, x: A @ x + (B @ sol.policy(x[None], t)[0]), (0.0, 2.0), x0, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(sol.transition() @ x0, ode.y[:, -1], atol=1e-7)
