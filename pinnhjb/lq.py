"""Linear-quadratic ground truth: algebraic and differential Riccati equations (numpy/scipy only).

For ``xdot = A x + B u`` with cost ``x'Qx + u'Ru`` the HJB equations of the paper have quadratic
solutions, so every claim of the paper can be checked exactly in the LQ case:

* Steady-state HJB (eq:HJB). With ``V(x) = x'Px`` it reduces to the algebraic Riccati equation
  (ARE) ``A'P + PA + Q - P B R^{-1} B' P = 0``. *Every* symmetric ARE solution gives a solution of
  eq:HJB with ``V(0) = 0`` -- the non-uniqueness that motivates the paper -- but only the
  stabilizing one (:func:`care`) is the optimal value ``V*``; :func:`are_solutions` enumerates them.
* Finite-horizon HJB (eq:HJBT) with terminal cost ``phi(x) = x' P_T x``. ``V_T(x, t) = x'P(t)x``
  where ``-dP/dt = A'P + PA + Q - P B R^{-1} B' P``, ``P(T) = P_T`` (:func:`riccati_ode`), the
  optimal value of eq:costT, with policy ``mu_T(x, t) = -R^{-1} B' P(t) x`` (eq:muTstar).
* Convergence (Theorem th:ucon). For ``P_T = 0``, ``P(0)`` increases monotonically with the horizon
  to the CARE solution (Lemma le:inc). For ``phi = psi + V*`` (``P_T = P_psi + P_care``) it
  converges from above, ``P_care <= P(0) <= P_care + Phi' P_psi Phi`` with ``Phi`` the optimal
  closed-loop transition matrix over [0, T] (Lemma le:ucon2, eq:final); the decrease is monotone
  when ``P_T`` has a negative semidefinite Riccati residual (e.g. ``P_T = c P_care``, c >= 1), not
  in general. Any PSD ``P_T`` lies between the two cases (eq:sandwich).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from itertools import product
from typing import Literal

import numpy as np
import scipy.linalg as sla
from numpy.typing import ArrayLike, NDArray
from scipy.integrate import OdeSolution, solve_ivp

__all__ = [
    "care",
    "lqr_gain",
    "are_residual",
    "are_solutions",
    "ARESolution",
    "riccati_ode",
    "RiccatiSolution",
    "convergence_bound",
]

Array = NDArray[np.float64]

_SYM_RTOL = 1e-8  # relative tolerance for "symmetric" and "positive semidefinite" inputs


# --------------------------------------------------------------------------------------------
# validation and shared algebra
# --------------------------------------------------------------------------------------------
def _matrix(name: str, value: ArrayLike, shape: tuple[str, str], dims: dict[str, int]) -> Array:
    """``value`` as a finite 2-D float array whose dimensions match the symbols in ``shape``.

    ``dims`` maps symbols (``"n"``, ``"m"``) to sizes already fixed by earlier arguments; the
    sizes of this argument are added to it.
    """
    M = np.asarray(value, dtype=float)
    bound = dict(dims)
    if M.ndim != 2 or not all(bound.setdefault(s, d) == d for s, d in zip(shape, M.shape)):
        want = ", ".join(f"{s}={dims[s]}" if s in dims else s for s in shape)
        raise ValueError(f"{name} must be a 2-D array of shape ({want}), got shape {M.shape}")
    if not np.isfinite(M).all():
        raise ValueError(f"{name} must have finite entries, got NaN or inf in {name}")
    dims.update(bound)
    return M


def _symmetric(name: str, M: Array, definite: bool) -> Array:
    """Check that ``M`` is symmetric positive (semi)definite; return its symmetric part."""
    scale = max(1.0, float(np.abs(M).max()))
    asym = float(np.abs(M - M.T).max())
    if asym > _SYM_RTOL * scale:
        raise ValueError(f"{name} must be symmetric, got max |{name} - {name}'| = {asym:.3g}")
    M = (M + M.T) / 2
    lam = float(np.linalg.eigvalsh(M).min())
    if lam <= (0.0 if definite else -_SYM_RTOL * scale):
        kind = "positive definite" if definite else "positive semidefinite"
        raise ValueError(f"{name} must be {kind}, got minimum eigenvalue {lam:.3g}")
    return M


def _validate(A: ArrayLike, B: ArrayLike, Q: ArrayLike, R: ArrayLike) -> tuple[Array, Array, Array, Array]:
    """Check A (n x n), B (n x m), Q (n x n symmetric PSD), R (m x m symmetric PD), all finite."""
    dims: dict[str, int] = {}
    A_ = _matrix("A", A, ("n", "n"), dims)
    B_ = _matrix("B", B, ("n", "m"), dims)
    Q_ = _symmetric("Q", _matrix("Q", Q, ("n", "n"), dims), definite=False)
    R_ = _symmetric("R", _matrix("R", R, ("m", "m"), dims), definite=True)
    return A_, B_, Q_, R_


def _gain_matrix(B: Array, R: Array) -> Array:
    """``G = B R^{-1} B'``, the quadratic coefficient of the Riccati equations."""
    return B @ sla.solve(R, B.T, assume_a="pos")


def _riccati_rhs(A: Array, G: Array, Q: Array, P: Array) -> Array:
    """``A'P + PA + Q - P G P``; broadcasts over a leading stack axis of ``P``."""
    return A.T @ P + P @ A + Q - P @ G @ P


def _sym(P: Array) -> Array:
    return (P + np.swapaxes(P, -1, -2)) / 2


# --------------------------------------------------------------------------------------------
# algebraic Riccati equation (steady-state HJB, eq:HJB)
# --------------------------------------------------------------------------------------------
def care(A: ArrayLike, B: ArrayLike, Q: ArrayLike, R: ArrayLike) -> Array:
    """Stabilizing solution ``P`` of ``A'P + PA + Q - P B R^{-1} B' P = 0``.

    ``V*(x) = x'Px`` is the optimal value of the infinite-horizon problem, the solution of the
    steady-state HJB eq:HJB selected by stability (the ARE has other symmetric solutions, see
    :func:`are_solutions`). Computed by ``scipy.linalg.solve_continuous_are``; requires
    (A, B) stabilizable and (Q, A) detectable.
    """
    A_, B_, Q_, R_ = _validate(A, B, Q, R)
    return _sym(sla.solve_continuous_are(A_, B_, Q_, R_))


def lqr_gain(B: ArrayLike, R: ArrayLike, P: ArrayLike) -> Array:
    """``K = R^{-1} B' P`` (m x n), so that ``u = -K x = -1/2 R^{-1} B' grad V`` (eq:mustar)."""
    dims: dict[str, int] = {}
    B_ = _matrix("B", B, ("n", "m"), dims)
    R_ = _symmetric("R", _matrix("R", R, ("m", "m"), dims), definite=True)
    P_ = _matrix("P", P, ("n", "n"), dims)
    return sla.solve(R_, B_.T @ P_, assume_a="pos")


def are_residual(A: ArrayLike, B: ArrayLike, Q: ArrayLike, R: ArrayLike, P: ArrayLike) -> Array:
    """The ARE residual ``A'P + PA + Q - P B R^{-1} B' P`` (n x n); zero iff x'Px solves eq:HJB."""
    A_, B_, Q_, R_ = _validate(A, B, Q, R)
    P_ = _matrix("P", P, ("n", "n"), {"n": A_.shape[0]})
    return _riccati_rhs(A_, _gain_matrix(B_, R_), Q_, P_)


@dataclass(frozen=True, eq=False)
class ARESolution:
    """One real symmetric solution of the ARE, i.e. one quadratic solution x'Px of eq:HJB.

    P : (n, n) symmetric solution.
    eigenvalues : closed-loop eigenvalues of ``A - B R^{-1} B' P`` (``np.sort_complex`` order).
    stabilizing : all closed-loop eigenvalues have negative real part (then P = :func:`care`).
    chosen : the Hamiltonian eigenvalues whose invariant subspace gave P (same order; equal
        to ``eigenvalues`` up to rounding, since ``H [I; P] = [I; P] (A - B R^{-1} B' P)``).
    """

    P: Array
    eigenvalues: NDArray[np.complex128]
    stabilizing: bool
    chosen: NDArray[np.complex128]


def are_solutions(A: ArrayLike, B: ArrayLike, Q: ArrayLike, R: ArrayLike, tol: float = 1e-9) -> list[ARESolution]:
    """All real symmetric ARE solutions, the stabilizing one first.

    Each is a solution ``V(x) = x'Px`` of the steady-state HJB eq:HJB with ``V(0) = 0``, but only
    the stabilizing one is the optimal value ``V*`` -- the non-uniqueness that makes the paper
    solve the finite-horizon eq:HJBT instead.

    Method: the Hamiltonian ``H = [[A, -B R^{-1} B'], [-Q, -A']]`` has spectrum symmetric about
    the imaginary axis. Choosing one eigenvalue from every pair ``(lambda, -lambda)``, keeping
    complex-conjugate pairs together, spans an n-dimensional invariant subspace ``[X; Y]``;
    when X is invertible (``cond(X) < 1/tol``), ``P = Y X^{-1}`` solves the ARE. P is kept when it
    is real, symmetric and has relative ARE residual below ``10 tol``. For 2n distinct real
    eigenvalues this yields up to ``2^n`` solutions; exactly one is stabilizing.

    Raises ValueError when H has eigenvalues on the imaginary axis or repeated eigenvalues
    (within ``sqrt(tol)`` relative: a double eigenvalue is only resolved to about sqrt(eps)),
    since the enumeration needs distinct eigenvalues off the axis.
    """
    A_, B_, Q_, R_ = _validate(A, B, Q, R)
    if not 0 < tol < 1:
        raise ValueError(f"tol must be in (0, 1), got {tol}")
    n = A_.shape[0]
    G = _gain_matrix(B_, R_)
    w, V = sla.eig(np.block([[A_, -G], [-Q_, -A_.T]]))
    scale = max(1.0, float(np.abs(w).max()))
    near = np.sqrt(tol) * scale
    if np.any(np.abs(w.real) <= near):
        raise ValueError(f"the Hamiltonian has eigenvalues on the imaginary axis: {np.sort_complex(w)}")
    gaps = np.abs(w[:, None] - w[None, :]) + np.diag(np.full(2 * n, np.inf))
    if gaps.min() <= near:
        raise ValueError(
            "the Hamiltonian has repeated eigenvalues; enumerating ARE solutions needs distinct "
            f"eigenvalues, got {np.sort_complex(w)}"
        )
    stable = np.flatnonzero(w.real < 0)
    unstable = np.flatnonzero(w.real > 0)
    partner = {int(i): int(unstable[np.argmin(np.abs(w[unstable] + w[i]))]) for i in stable}
    # units of choice: real eigenvalues alone, complex ones with their conjugate
    units: list[tuple[int, ...]] = []
    for i in stable:
        if abs(w[i].imag) <= near:
            units.append((int(i),))
        elif w[i].imag > 0:
            units.append((int(i), int(stable[np.argmin(np.abs(w[stable] - np.conj(w[i])))])))
    if len(stable) != n or len(set(partner.values())) != n or sum(map(len, units)) != n:
        raise ValueError(f"the Hamiltonian spectrum is not symmetric about the imaginary axis: {w}")

    G_norm, A_norm, Q_norm = (np.linalg.norm(M, 2) for M in (G, A_, Q_))
    found: list[ARESolution] = []
    for flips in product((False, True), repeat=len(units)):
        idx = [partner[i] if flip else i for unit, flip in zip(units, flips) for i in unit]
        X, Y = V[:n, idx], V[n:, idx]
        if np.linalg.cond(X) >= 1 / tol:
            continue
        Pc = sla.solve(X.T, Y.T).T  # Y X^{-1}
        P_scale = max(1.0, float(np.abs(Pc).max()))
        P = Pc.real
        if np.abs(Pc.imag).max() > near * P_scale or np.abs(P - P.T).max() > near * P_scale:
            continue
        P = _sym(P)
        P_norm = np.linalg.norm(P, 2)
        residual = np.linalg.norm(_riccati_rhs(A_, G, Q_, P), 2)
        if residual > 10 * tol * (Q_norm + 2 * A_norm * P_norm + G_norm * P_norm**2):
            continue
        if any(np.allclose(P, s.P, rtol=near, atol=near) for s in found):
            continue
        closed = np.linalg.eigvals(A_ - G @ P)
        found.append(
            ARESolution(
                P=P,
                eigenvalues=np.sort_complex(closed),
                stabilizing=bool(np.all(closed.real < 0)),
                chosen=np.sort_complex(w[idx]),
            )
        )
    return sorted(found, key=lambda s: (int(np.sum(s.eigenvalues.real >= 0)), -float(np.trace(s.P))))


# --------------------------------------------------------------------------------------------
# differential Riccati equation (finite-horizon HJB, eq:HJBT)
# --------------------------------------------------------------------------------------------
def _eval_dense(dense: OdeSolution, horizon: float, n: int, t: ArrayLike) -> Array:
    """Symmetric P(t) from the flattened dense output, for t in [0, horizon]."""
    t_arr = np.asarray(t, dtype=float)
    slack = 1e-12 * max(1.0, horizon)
    if t_arr.size and not np.all((t_arr >= -slack) & (t_arr <= horizon + slack)):
        got = f"[{t_arr.min()}, {t_arr.max()}]"
        raise ValueError(f"t must lie in [0, horizon={horizon}], got values in {got}")
    flat = dense(np.clip(t_arr.ravel(), 0.0, horizon))  # (n*n, k)
    return _sym(flat.T.reshape(t_arr.shape + (n, n)))


@dataclass(frozen=True, eq=False)
class RiccatiSolution:
    """Solution of ``-dP/dt = A'P + PA + Q - P B R^{-1} B' P`` on [0, horizon], ``P(horizon) = P_T``.

    ``V_T(x, t) = x'P(t)x`` is the exact solution of eq:HJBT with ``phi(x) = x'P_T x``.

    t : (k,) ascending times in [0, horizon]; P : (k, n, n) symmetric P(t) at those times.
    ``at``, ``derivative``, ``value`` and ``policy`` evaluate the dense output at any t.
    """

    t: Array
    P: Array
    horizon: float
    A: Array
    B: Array
    Q: Array
    R: Array
    dense: OdeSolution = field(repr=False)

    def at(self, t: ArrayLike) -> Array:
        """P(t): shape (n, n) for scalar t, ``t.shape + (n, n)`` for an array."""
        return _eval_dense(self.dense, self.horizon, self.A.shape[0], t)

    def derivative(self, t: ArrayLike) -> Array:
        """dP/dt = -(A'P + PA + Q - P B R^{-1} B' P) at P = P(t); same shapes as :meth:`at`."""
        return -_riccati_rhs(self.A, _gain_matrix(self.B, self.R), self.Q, self.at(t))

    def _points(self, x: ArrayLike, t: ArrayLike) -> tuple[Array, Array]:
        """x as (N, n) and P(t) broadcast to (N, n, n)."""
        x_ = np.asarray(x, dtype=float)
        n = self.A.shape[0]
        if x_.ndim != 2 or x_.shape[1] != n:
            raise ValueError(f"x must have shape (N, n={n}), got shape {x_.shape}")
        return x_, self.at(np.broadcast_to(np.asarray(t, dtype=float), (x_.shape[0],)))

    def value(self, x: ArrayLike, t: ArrayLike) -> Array:
        """``V_T(x, t) = x'P(t)x`` for x (N, n) and scalar or (N,) t; returns (N,)."""
        x_, P = self._points(x, t)
        return np.einsum("ni,nij,nj->n", x_, P, x_)

    def policy(self, x: ArrayLike, t: ArrayLike) -> Array:
        """``mu_T(x, t) = -R^{-1} B' P(t) x`` (eq:muTstar) for x (N, n); returns (N, m)."""
        x_, P = self._points(x, t)
        Px = np.einsum("nij,nj->ni", P, x_)
        return -sla.solve(self.R, self.B.T @ Px.T, assume_a="pos").T

    def transition(self, t: float | None = None) -> Array:
        """Phi(t): the closed loop under the optimal time-varying policy maps x(0) to x(t) = Phi(t) x(0).

        Integrates ``dPhi/dt = (A - B R^{-1} B' P(t)) Phi``, ``Phi(0) = I`` with ``solve_ivp``; default
        ``t = horizon`` (so ``x_T(T) = Phi x0``, the end point in the bound after Theorem 1)."""
        t_end = self.horizon if t is None else float(t)
        if not 0.0 <= t_end <= self.horizon:
            raise ValueError(f"t must lie in [0, {self.horizon}], got {t}")
        n = self.A.shape[0]
        if t_end == 0.0:
            return np.eye(n)
        G = _gain_matrix(self.B, self.R)

        def rhs(tau: float, y: Array) -> Array:
            return ((self.A - G @ self.at(tau)) @ y.reshape(n, n)).ravel()

        sol = solve_ivp(rhs, (0.0, t_end), np.eye(n).ravel(), method="DOP853", rtol=1e-10, atol=1e-12)
        if not sol.success:
            raise RuntimeError(f"closed-loop transition integration failed: {sol.message}")
        return sol.y[:, -1].reshape(n, n)


def convergence_bound(
    A: ArrayLike, B: ArrayLike, Q: ArrayLike, R: ArrayLike, P_psi: ArrayLike, horizon: float, x0: ArrayLike
) -> dict:
    """Exact LQ check of the uniform convergence of V_T(., 0) to V* (Theorem 1 and the bound after it).

    For terminal cost ``psi(x) = x' P_psi x`` returns, over the initial states ``x0`` (N, n):
    ``error`` = max |V_T(x0, 0; psi) - V*(x0)| and
    ``bound`` = max{ max psi(x*(T)), max V*(x_T(T; 0)) } where x* is the optimal infinite-horizon closed loop
    and x_T(.; 0) the optimal closed loop of the phi = 0 problem; also ``lower`` = max |V_T(.,0;0) - V*| and
    ``upper`` = max |V_T(.,0;psi+V*) - V*|, the two ends of the sandwich (eq. (sandwich)).
    """
    A_, B_, Q_, R_ = _validate(A, B, Q, R)
    x = np.asarray(x0, dtype=float)
    P_star = care(A_, B_, Q_, R_)
    P_psi_ = _symmetric("P_psi", _matrix("P_psi", P_psi, ("n", "n"), {"n": A_.shape[0]}), definite=False)

    def quad(P, X):
        return np.einsum("ni,ij,nj->n", X, P, X)

    v_star = quad(P_star, x)
    mid = riccati_ode(A_, B_, Q_, R_, horizon, P_T=P_psi_)
    low = riccati_ode(A_, B_, Q_, R_, horizon)
    high = riccati_ode(A_, B_, Q_, R_, horizon, P_T=P_psi_ + P_star)
    x_star_T = x @ sla.expm((A_ - _gain_matrix(B_, R_) @ P_star) * horizon).T
    x_zero_T = x @ low.transition().T
    return {
        "horizon": float(horizon),
        "error": float(np.max(np.abs(quad(mid.at(0.0), x) - v_star))),
        "lower": float(np.max(np.abs(quad(low.at(0.0), x) - v_star))),
        "upper": float(np.max(np.abs(quad(high.at(0.0), x) - v_star))),
        "bound": float(max(np.max(quad(P_psi_, x_star_T)), np.max(quad(P_star, x_zero_T)))),
    }


def riccati_ode(
    A: ArrayLike,
    B: ArrayLike,
    Q: ArrayLike,
    R: ArrayLike,
    horizon: float,
    P_T: ArrayLike | None = None,
    t_eval: ArrayLike | None = None,
    rtol: float = 1e-10,
    atol: float = 1e-12,
    method: Literal["DOP853", "Radau"] = "DOP853",
) -> RiccatiSolution:
    """Integrate the finite-horizon Riccati ODE backward from ``P(horizon) = P_T`` to t = 0.

    ``-dP/dt = A'P + PA + Q - P B R^{-1} B' P`` is eq:HJBT for ``V_T(x, t) = x'P(t)x`` with
    terminal cost ``phi(x) = x'P_T x`` (P_T symmetric PSD, default 0). With ``P_T = 0``, P(0)
    increases monotonically with the horizon to :func:`care` (Lemma le:inc); with
    ``P_T = P_psi + care(...)`` it converges to it from above (Lemma le:ucon2), monotonically
    only in special cases such as ``P_T = c care(...)``, c >= 1.

    Uses ``scipy.integrate.solve_ivp`` with dense output. ``t_eval`` (sorted ascending, within
    [0, horizon]) picks the times stored in the result; by default the solver's own steps.
    """
    A_, B_, Q_, R_ = _validate(A, B, Q, R)
    n = A_.shape[0]
    T = float(horizon)
    if not (np.isfinite(T) and T > 0):
        raise ValueError(f"horizon must be a finite positive number, got {horizon}")
    P_end = np.zeros((n, n))
    if P_T is not None:
        P_end = _symmetric("P_T", _matrix("P_T", P_T, ("n", "n"), {"n": n}), definite=False)
    G = _gain_matrix(B_, R_)

    def rhs(_: float, y: Array) -> Array:
        return -_riccati_rhs(A_, G, Q_, _sym(y.reshape(n, n))).ravel()

    sol = solve_ivp(rhs, (T, 0.0), P_end.ravel(), method=method, dense_output=True, rtol=rtol, atol=atol)
    if not sol.success:
        raise RuntimeError(f"Riccati ODE integration failed: {sol.message}")
    if t_eval is None:
        times = sol.t[::-1].copy()
    else:
        times = np.sort(np.asarray(t_eval, dtype=float).ravel())
    return RiccatiSolution(
        t=times, P=_eval_dense(sol.sol, T, n, times), horizon=T, A=A_, B=B_, Q=Q_, R=R_, dense=sol.sol
    )
