"""Linear-quadratic ground truth: the algebraic and differential Riccati equations (numpy/scipy only).

For ``xdot = A x + B u`` with cost ``x'Qx + u'Ru`` the paper's HJB equations have quadratic solutions, so
every claim of the paper can be checked exactly:

* the steady-state HJB :eq:`eq-hjb` becomes the algebraic Riccati equation (ARE); every symmetric solution
  solves it, only the stabilizing one (:func:`care`) is ``V*``; :func:`are_solutions` lists them all;
* the finite-horizon HJB :eq:`eq-hjbt` becomes the Riccati ODE (:func:`riccati_ode`);
* Theorem 1 and its bounds are checked exactly by :func:`convergence_bound`.
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
    "horizon_gap",
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
# algebraic Riccati equation (steady-state HJB, eq-hjb)
# --------------------------------------------------------------------------------------------
def care(A: ArrayLike, B: ArrayLike, Q: ArrayLike, R: ArrayLike) -> Array:
    """The stabilizing solution ``P`` of the ARE ``A'P + PA + Q - P B R^{-1} B' P = 0``.

    ``V*(x) = x'Px`` is the optimal value: the solution of the steady-state HJB :eq:`eq-hjb` that stability
    selects (the other ARE solutions: :func:`are_solutions`). Computed by ``scipy.linalg.solve_continuous_are``.

    * ``A``: (n, n); (A, B) stabilizable.
    * ``B``: (n, m).
    * ``Q``: (n, n), symmetric positive semidefinite; (Q, A) detectable.
    * ``R``: (m, m), symmetric positive definite.

    Returns P, (n, n) symmetric.
    """
    A_, B_, Q_, R_ = _validate(A, B, Q, R)
    return _sym(sla.solve_continuous_are(A_, B_, Q_, R_))


def lqr_gain(B: ArrayLike, R: ArrayLike, P: ArrayLike) -> Array:
    """The gain ``K = R^{-1} B' P`` (m, n), so that ``u = -K x = -1/2 R^{-1} B' grad V`` :eq:`eq-mustar`.

    * ``B``: (n, m).
    * ``R``: (m, m), symmetric positive definite.
    * ``P``: (n, n), the value's matrix.
    """
    dims: dict[str, int] = {}
    B_ = _matrix("B", B, ("n", "m"), dims)
    R_ = _symmetric("R", _matrix("R", R, ("m", "m"), dims), definite=True)
    P_ = _matrix("P", P, ("n", "n"), dims)
    return sla.solve(R_, B_.T @ P_, assume_a="pos")


def are_residual(A: ArrayLike, B: ArrayLike, Q: ArrayLike, R: ArrayLike, P: ArrayLike) -> Array:
    """The ARE residual ``A'P + PA + Q - P B R^{-1} B' P`` (n, n): zero iff ``x'Px`` solves :eq:`eq-hjb`.

    * ``A``, ``B``, ``Q``, ``R``: the problem, as in :func:`care`.
    * ``P``: (n, n), the candidate.
    """
    A_, B_, Q_, R_ = _validate(A, B, Q, R)
    P_ = _matrix("P", P, ("n", "n"), {"n": A_.shape[0]})
    return _riccati_rhs(A_, _gain_matrix(B_, R_), Q_, P_)


@dataclass(frozen=True, eq=False)
class ARESolution:
    """One real symmetric solution of the ARE: one quadratic solution ``x'Px`` of :eq:`eq-hjb`.

    * ``P``: (n, n), symmetric.
    * ``eigenvalues``: the closed-loop eigenvalues of ``A - B R^{-1} B' P``, in ``np.sort_complex`` order.
    * ``stabilizing``: all closed-loop eigenvalues have negative real part (then P is :func:`care`'s).
    * ``chosen``: the Hamiltonian eigenvalues whose invariant subspace gave P, in the same order; equal to
      ``eigenvalues`` up to rounding, since ``H [I; P] = [I; P] (A - B R^{-1} B' P)``.
    """

    P: Array
    eigenvalues: NDArray[np.complex128]
    stabilizing: bool
    chosen: NDArray[np.complex128]


def are_solutions(A: ArrayLike, B: ArrayLike, Q: ArrayLike, R: ArrayLike, tol: float = 1e-9) -> list[ARESolution]:
    """All real symmetric ARE solutions, the stabilizing one first.

    Each is a solution ``V(x) = x'Px`` of the steady-state HJB :eq:`eq-hjb` with ``V(0) = 0``, but only the
    stabilizing one is the optimal value ``V*``: the non-uniqueness that makes the paper solve the
    finite-horizon :eq:`eq-hjbt` instead.

    * ``A``, ``B``, ``Q``, ``R``: the problem, as in :func:`care`.
    * ``tol``: the relative tolerance of the enumeration, in (0, 1).

    Returns a list of :class:`ARESolution`.

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
# differential Riccati equation (finite-horizon HJB, eq-hjbt)
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
    """The solution of ``-dP/dt = A'P + PA + Q - P B R^{-1} B' P`` on [0, horizon] with ``P(horizon) = P_T``.

    ``V_T(x, t) = x'P(t)x`` is the exact solution of :eq:`eq-hjbt` with ``phi(x) = x'P_T x``. The methods
    evaluate the dense output at any t.

    * ``t``: (k,), ascending times in [0, horizon].
    * ``P``: (k, n, n), the symmetric P(t) at those times.
    * ``horizon``: T.
    * ``A``, ``B``, ``Q``, ``R``: the problem.
    * ``dense``: scipy's dense output of the integration.
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
        """The value ``V_T(x, t) = x'P(t)x``.

        * ``x``: (N, n) states.
        * ``t``: scalar or (N,) times.

        Returns (N,).
        """
        x_, P = self._points(x, t)
        return np.einsum("ni,nij,nj->n", x_, P, x_)

    def policy(self, x: ArrayLike, t: ArrayLike) -> Array:
        """The policy ``mu_T(x, t) = -R^{-1} B' P(t) x`` :eq:`eq-mut`.

        * ``x``: (N, n) states.
        * ``t``: scalar or (N,) times.

        Returns (N, m).
        """
        x_, P = self._points(x, t)
        Px = np.einsum("nij,nj->ni", P, x_)
        return -sla.solve(self.R, self.B.T @ Px.T, assume_a="pos").T

    def transition(self, t: float | None = None) -> Array:
        """The transition matrix Phi(t) of the optimal closed loop: ``x(t) = Phi(t) x(0)``.

        Integrates ``dPhi/dt = (A - B R^{-1} B' P(t)) Phi``, ``Phi(0) = I`` with ``solve_ivp``.

        * ``t``: the end time in [0, horizon]; None: the horizon, so that ``x_T(T) = Phi x0``, the end point
          in :eq:`eq-uniform-bound`.

        Returns Phi, (n, n).
        """
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
    """The exact LQ check of Theorem 1: how far V_T(., 0) is from V*, against the bound :eq:`eq-uniform-bound`.

    * ``A``, ``B``, ``Q``, ``R``: the problem, as in :func:`care`.
    * ``P_psi``: (n, n) symmetric PSD; the terminal cost is ``psi(x) = x' P_psi x``.
    * ``horizon``: T.
    * ``x0``: (N, n) initial states; every maximum below is over them.

    Returns a dict:

    * ``horizon``: T.
    * ``error``: ``max abs(V_T(x0, 0; psi) - V*(x0))``.
    * ``bound``: ``max(max psi(x*(T)), max V*(x_T(T; 0)))``, where x* is the optimal infinite-horizon closed
      loop and ``x_T(.; 0)`` the optimal closed loop with terminal cost 0.
    * ``lower``: ``max abs(V_T(., 0; 0) - V*)``, the lower end of the sandwich :eq:`eq-sandwich`.
    * ``upper``: ``max abs(V_T(., 0; psi + V*) - V*)``, its upper end.
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


def horizon_gap(A: ArrayLike, B: ArrayLike, Q: ArrayLike, R: ArrayLike, horizon: float, x0: ArrayLike) -> float:
    """What the horizon alone leaves of V*: ``max abs(V_T(x0, 0) - V*(x0)) / max V*(x0)`` for the terminal cost 0,
    exact (V_T from :func:`riccati_ode`, V* from :func:`care`); a learned V_T can come no closer to V* than this.

    * ``A``, ``B``, ``Q``, ``R``: the problem, as in :func:`care`.
    * ``horizon``: T.
    * ``x0``: (N, n) states; both maxima are over them.
    """
    A_, B_, Q_, R_ = _validate(A, B, Q, R)
    x = np.asarray(x0, dtype=float)
    v_star = np.einsum("ni,ij,nj->n", x, care(A_, B_, Q_, R_), x)
    v_T = riccati_ode(A_, B_, Q_, R_, horizon).value(x, 0.0)
    return float(np.abs(v_T - v_star).max() / np.abs(v_star).max())


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

    ``-dP/dt = A'P + PA + Q - P B R^{-1} B' P`` is :eq:`eq-hjbt` for ``V_T(x, t) = x'P(t)x`` with terminal
    cost ``phi(x) = x'P_T x``. With ``P_T = 0``, P(0) increases with the horizon to :func:`care`
    (:prf:ref:`lem-monotone`); with ``P_T = P_psi + care(...)`` it converges to it from above
    (:prf:ref:`lem-uniform-above`), monotonically only in special cases such as ``P_T = c care(...)``,
    c >= 1. Any PSD ``P_T`` lies between the two :eq:`eq-sandwich`. Uses ``scipy.integrate.solve_ivp``
    with dense output.

    * ``A``, ``B``, ``Q``, ``R``: the problem, as in :func:`care`.
    * ``horizon``: T > 0.
    * ``P_T``: (n, n) symmetric PSD terminal matrix; None: 0.
    * ``t_eval``: the times stored in the result, ascending within [0, horizon]; None: the solver's steps.
    * ``rtol``, ``atol``: the integrator's tolerances.
    * ``method``: ``"DOP853"`` or ``"Radau"`` (stiff problems).

    Returns a :class:`RiccatiSolution`.
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
