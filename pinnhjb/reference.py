"""Independent reference values by open-loop optimal control: Pontryagin two-point boundary-value problems.

For one initial state ``x0``, the optimal value of the finite-horizon cost :eq:`eq-costt` follows from the
minimum principle. The minimizing control is ``u = -1/2 R^{-1} g(x)' lam``, the open-loop form of
:eq:`eq-mustar` and :eq:`eq-mut`. With ``Hmin(x, lam) = lam'f + Q - 1/4 lam' g R^{-1} g' lam`` the extremal
solves the Hamiltonian system::

    xdot = dHmin/dlam,   lamdot = -dHmin/dx,   x(0) = x0,   lam(T) = grad phi(x(T)).

The running cost is carried as an extra state ``c`` (``cdot = Q + u'Ru``, ``c(0) = 0``), so
``V_T(x0, 0) = c(T) + phi(x(T))``, ``grad_x V_T(x0, 0) = lam(0)`` and ``mu_T(x0, 0) = -1/2 R^{-1} g(x0)' lam(0)``.
``scipy.integrate.solve_bvp`` solves it with exact Jacobians: torch autograd on the system's own callables,
never finite differences.

The infinite horizon :eq:`eq-cost` is truncated at ``t_inf`` with the terminal cost ``x'Px``, P the ARE
solution of the linearisation at the origin. Near the origin this is the optimal cost-to-go up to terms of
order ``norm(x)^3``, so the truncation error is of order ``norm(x(t_inf))^3``, which is checked (``tail_tol``).

Nothing here depends on the PINN code: only numpy/scipy and the system's callables f, g, Q, R.
"""

from __future__ import annotations

import copy
import json
import math
import os
import time
import warnings
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import scipy
import scipy.linalg as sla
import torch
from scipy.integrate import solve_bvp

__all__ = ["ReferenceGrid", "solve_point", "reference_grid", "reference_points", "replay_cost"]

_DT = torch.float64


# ============================================================================ autograd helpers
def _grad(out: torch.Tensor, inp: torch.Tensor, create_graph: bool = False) -> torch.Tensor:
    """d(out.sum())/d inp, zeros where ``out`` does not depend on ``inp``."""
    if not out.requires_grad:
        return torch.zeros_like(inp)
    (gr,) = torch.autograd.grad(out.sum(), inp, create_graph=create_graph, retain_graph=True, allow_unused=True)
    return torch.zeros_like(inp) if gr is None else gr


class _Problem:
    """The Hamiltonian system of one system / horizon / terminal cost, evaluated with autograd.

    All system callables are batched row-wise (row k of the output depends on row k of the input
    only), so the gradient of a sum over the batch is the batch of per-point gradients.
    """

    def __init__(self, system, horizon: float, terminal_cost, t_inf: float):
        self.system = system
        self.n, self.m = system.n, system.m
        self.R = np.asarray(system.R, dtype=float)
        self.Rinv = np.linalg.inv(self.R)
        self.Rinv_t = torch.as_tensor(self.Rinv, dtype=_DT)
        self._linearize()
        if math.isinf(horizon):
            if not (np.isfinite(t_inf) and t_inf > 0):
                raise ValueError(f"t_inf must be a finite positive number; got {t_inf}")
            if terminal_cost is not None:
                raise ValueError("terminal_cost is only used with a finite horizon")
            self.T = float(t_inf)
            self.P_T = self.P_lqr.copy()  # phi(x) = x'P_lqr x: the linearization's cost-to-go
            self.phi = None
        else:
            if not (np.isfinite(horizon) and horizon > 0):
                raise ValueError(f"horizon must be positive (finite or math.inf); got {horizon}")
            self.T = float(horizon)
            self.P_T, self.phi = None, None
            if terminal_cost is None:
                self.P_T = np.zeros((self.n, self.n))
            elif callable(terminal_cost):
                self.phi = terminal_cost
                out = terminal_cost(torch.zeros(2, self.n, dtype=_DT))
                if not isinstance(out, torch.Tensor) or tuple(out.shape) != (2,):
                    raise ValueError("terminal_cost must be a batched torch callable (N, n) -> (N,)")
            else:
                P = np.asarray(terminal_cost, dtype=float)
                if P.shape != (self.n, self.n) or not np.all(np.isfinite(P)):
                    raise ValueError(
                        f"terminal_cost as a matrix must be a finite ({self.n}, {self.n}) array; got shape {P.shape}"
                    )
                self.P_T = (P + P.T) / 2  # phi(x) = x'P_T x

    # ------------------------------------------------------------------ linearization / LQR guess
    def _linearize(self):
        n, s = self.n, self.system
        z = torch.zeros(n, dtype=_DT)
        A = torch.autograd.functional.jacobian(lambda v: s.f(v[None])[0], z).numpy()
        B = s.g(z[None])[0].detach().numpy()
        Ql = 0.5 * torch.autograd.functional.hessian(lambda v: s.Q(v[None])[0], z).numpy()
        Ql = (Ql + Ql.T) / 2
        P = None
        try:
            P = sla.solve_continuous_are(A, B, Ql, self.R)
        except (np.linalg.LinAlgError, ValueError):
            if np.all(np.linalg.eigvals(A).real < 0):  # B may be uncontrollable but A stable
                P = sla.solve_continuous_lyapunov(A.T, -Ql)
        if P is None or not np.all(np.isfinite(P)):
            warnings.warn(
                f"system '{s.name}': no stabilizing Riccati solution for the linearization at 0; "
                "the infinite-horizon tail uses phi = 0 and the LQR initial guess is the open loop",
                RuntimeWarning,
                stacklevel=3,
            )
            P = np.zeros((n, n))
        self.A, self.B, self.Q_lin = A, B, Ql
        self.P_lqr = (P + P.T) / 2
        self.K = self.Rinv @ B.T @ self.P_lqr
        self.A_cl = A - B @ self.K

    def _lin_flow(self, t: np.ndarray, dx: np.ndarray) -> np.ndarray:
        """expm(A_cl t) dx for every t: (n, len(t)) (eigendecomposition; expm per node if defective)."""
        w, V = self._eig
        if V is not None:
            return (V @ (np.exp(np.outer(w, t)) * np.linalg.solve(V, dx)[:, None])).real
        return np.stack([sla.expm(tk * self.A_cl) @ dx for tk in t], axis=1)

    @property
    def _eig(self):
        if not hasattr(self, "_eig_cache"):
            w, V = np.linalg.eig(self.A_cl)
            self._eig_cache = (w, V if np.linalg.cond(V) < 1e8 else None)
        return self._eig_cache

    def lqr_guess(self, x0: np.ndarray, nodes: int = 60):
        t = self.T * np.linspace(0.0, 1.0, nodes) ** 2
        x = self._lin_flow(t, x0)
        lam = 2 * self.P_lqr @ x
        u = -self.K @ x
        rate = np.einsum("ik,ij,jk->k", x, self.Q_lin, x) + np.einsum("ik,ij,jk->k", u, self.R, u)
        c = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(t))])
        return t, np.vstack([x, lam, c])

    def shifted_guess(self, prev: dict, x0: np.ndarray):
        """A neighbour's solution moved to ``x0`` by the linear closed-loop sensitivity (cut, or
        continued by the LQR closed loop, when its horizon differs from this one)."""
        sol, n = prev["solution"], self.n
        t = sol.x
        if t[-1] >= self.T * (1 - 1e-12):
            t = np.append(t[t < self.T * (1 - 1e-9)], self.T)
            y = sol.sol(t).copy()
        else:
            y_end = sol.y[:, -1]
            t_extra = t[-1] + (self.T - t[-1]) * np.linspace(0.0, 1.0, 30)[1:] ** 2
            x_extra = self._lin_flow(t_extra - t[-1], y_end[:n])
            togo = lambda x: np.einsum("ik,ij,jk->k", x, self.P_lqr, x)  # noqa: E731
            c_extra = y_end[2 * n] + togo(y_end[:n, None]) - togo(x_extra)
            t = np.concatenate([t, t_extra])
            y = np.hstack([sol.y, np.vstack([x_extra, 2 * self.P_lqr @ x_extra, c_extra])])
        dx = self._lin_flow(t, x0 - np.asarray(prev["x0"], dtype=float))
        y[:n] += dx
        y[n : 2 * n] += 2 * self.P_lqr @ dx
        return t, y

    def extended(self, T: float) -> _Problem:
        """The same infinite-horizon truncation with a longer ``t_inf``."""
        other = copy.copy(self)
        other.T = float(T)
        return other

    # ------------------------------------------------------------------ the Hamiltonian system
    def _parts(self, x: torch.Tensor, lam: torch.Tensor):
        s = self.system
        fx, gx, qx = s.f(x), s.g(x), s.Q(x)
        gTl = torch.einsum("knm,kn->km", gx, lam)
        quad = torch.einsum("ki,ij,kj->k", gTl, self.Rinv_t, gTl)  # lam' g R^-1 g' lam
        hmin = (lam * fx).sum(-1) + qx - 0.25 * quad
        rate = qx + 0.25 * quad  # Q + u'Ru at u = -1/2 R^-1 g' lam
        return hmin, rate

    def _leaves(self, y: np.ndarray):
        n = self.n
        yt = torch.as_tensor(np.ascontiguousarray(y[: 2 * n].T), dtype=_DT)
        x = yt[:, :n].clone().requires_grad_(True)
        lam = yt[:, n:].clone().requires_grad_(True)
        return x, lam

    def rhs(self, t, y):
        x, lam = self._leaves(y)
        hmin, rate = self._parts(x, lam)
        dx, dl = _grad(hmin, x), _grad(hmin, lam)
        return np.vstack([dl.detach().numpy().T, -dx.detach().numpy().T, rate.detach().numpy()[None]])

    def rhs_jac(self, t, y):
        n, k = self.n, y.shape[1]
        x, lam = self._leaves(y)
        hmin, rate = self._parts(x, lam)
        gx, gl = _grad(hmin, x, True), _grad(hmin, lam, True)
        jac = np.zeros((2 * n + 1, 2 * n + 1, k))
        for i in range(n):  # rows of xdot = dHmin/dlam and lamdot = -dHmin/dx
            jac[i, :n] = _grad(gl[:, i], x).detach().numpy().T
            jac[i, n : 2 * n] = _grad(gl[:, i], lam).detach().numpy().T
            jac[n + i, :n] = -_grad(gx[:, i], x).detach().numpy().T
            jac[n + i, n : 2 * n] = -_grad(gx[:, i], lam).detach().numpy().T
        jac[2 * n, :n] = _grad(rate, x).detach().numpy().T
        jac[2 * n, n : 2 * n] = _grad(rate, lam).detach().numpy().T
        return jac

    # ------------------------------------------------------------------ terminal cost
    def phi_value(self, xT: np.ndarray) -> float:
        if self.phi is None:
            return float(xT @ self.P_T @ xT)
        return float(self.phi(torch.as_tensor(xT, dtype=_DT)[None])[0])

    def phi_grad(self, xT: np.ndarray) -> np.ndarray:
        if self.phi is None:
            return 2 * self.P_T @ xT
        v = torch.as_tensor(xT, dtype=_DT)[None].clone().requires_grad_(True)
        return _grad(self.phi(v), v)[0].detach().numpy()

    def phi_hess(self, xT: np.ndarray) -> np.ndarray:
        if self.phi is None:
            return 2 * self.P_T
        return torch.autograd.functional.hessian(lambda v: self.phi(v[None])[0], torch.as_tensor(xT, dtype=_DT)).numpy()

    def bc(self, x0):
        n = self.n

        def bc(ya, yb):
            return np.concatenate([ya[:n] - x0, yb[n : 2 * n] - self.phi_grad(yb[:n]), ya[2 * n : 2 * n + 1]])

        def bc_jac(ya, yb):
            d = 2 * n + 1
            Ja, Jb = np.zeros((d, d)), np.zeros((d, d))
            Ja[:n, :n] = np.eye(n)
            Ja[2 * n, 2 * n] = 1.0
            Jb[n : 2 * n, n : 2 * n] = np.eye(n)
            Jb[n : 2 * n, :n] = -self.phi_hess(yb[:n])
            return Ja, Jb

        return bc, bc_jac

    # ------------------------------------------------------------------ one BVP solve
    def solve(self, x0: np.ndarray, t: np.ndarray, y: np.ndarray, tol: float, max_nodes: int):
        bc, bc_jac = self.bc(x0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # overflow in a diverging Newton step
            sol = solve_bvp(
                self.rhs, bc, t, y, fun_jac=self.rhs_jac, bc_jac=bc_jac, tol=tol, bc_tol=tol, max_nodes=max_nodes
            )
        return sol


# ============================================================================ one initial state
def _check_x0(system, x0) -> np.ndarray:
    if isinstance(x0, torch.Tensor):
        x0 = x0.detach().cpu().numpy()
    x = np.asarray(x0, dtype=float)
    if x.shape != (system.n,):
        raise ValueError(f"x0 must have shape ({system.n},) for system '{system.name}'; got {x.shape}")
    if not np.all(np.isfinite(x)):
        raise ValueError("x0 contains NaN or infinite entries")
    return x


def _result(prob: _Problem, x0: np.ndarray, sol, tol: float, tail_tol: float, infinite: bool) -> dict:
    n = prob.n
    y0, yT = sol.y[:, 0], sol.y[:, -1]
    xT = yT[:n]
    value = float(yT[2 * n]) + prob.phi_value(xT)
    lam0 = y0[n : 2 * n].copy()
    g0 = prob.system.g(torch.as_tensor(x0, dtype=_DT)[None])[0].detach().numpy()
    policy = -0.5 * prob.Rinv @ g0.T @ lam0
    residual = float(np.max(sol.rms_residuals)) if sol.rms_residuals is not None and sol.rms_residuals.size else np.inf
    bc_res = float(np.max(np.abs(prob.bc(x0)[0](y0, yT))))
    tail = float(np.linalg.norm(xT)) if infinite else float("nan")
    # Hmin is constant along an extremal; for the infinite-horizon problem it is ~0 (the HJB (4)).
    hmin = float(prob._parts(*(torch.as_tensor(v, dtype=_DT)[None] for v in (x0, lam0)))[0][0])
    finite = np.all(np.isfinite([value, *lam0, *policy]))
    converged = bool(
        sol.status == 0
        and finite
        and residual <= tol * (1 + 1e-9)
        and bc_res <= 10 * tol
        and (not infinite or tail <= tail_tol)
    )
    return {
        "x0": x0,
        "value": value,
        "gradient": lam0,
        "policy": policy,
        "converged": converged,
        "status": int(sol.status),
        "message": sol.message,
        "residual": residual,
        "bc_residual": bc_res,
        "tail_norm": tail,
        "hamiltonian": hmin,
        "nodes": int(sol.x.size),
        "solution": sol,
    }


def _solve(prob: _Problem, x0, guess, tol, max_nodes, tail_tol, infinite) -> dict:
    """Try the given warm start, then the LQR guess, then continuation along the ray s*x0."""
    attempts = []
    if guess is not None:
        attempts.append(("warm", prob.shifted_guess(guess, x0)))
    attempts.append(("lqr", prob.lqr_guess(x0)))
    best = None
    for _, (t, y) in attempts:
        res = _result(prob, x0, prob.solve(x0, t, y, tol, max_nodes), tol, tail_tol, infinite)
        if res["converged"]:
            return res
        best = best or res
    # continuation from a small multiple of x0 (where the LQR guess is accurate) out to x0
    prev = None
    for s in (0.25, 0.5, 0.75, 1.0):
        xs = s * x0
        t, y = prob.shifted_guess(prev, xs) if prev is not None else prob.lqr_guess(xs)
        res = _result(prob, xs, prob.solve(xs, t, y, tol, max_nodes), tol, tail_tol, infinite)
        if not res["converged"]:
            return best
        prev = res
    return prev


def solve_point(
    system,
    x0,
    horizon: float = math.inf,
    terminal_cost=None,
    t_inf: float = 25.0,
    tol: float = 1e-8,
    guess: dict | None = None,
    max_nodes: int = 100_000,
    tail_tol: float = 1e-3,
    max_extensions: int = 3,
    _problem: _Problem | None = None,
) -> dict:
    """The optimal value, gradient and policy at one initial state, by the minimum principle.

    A result that did not converge is returned, flagged, with a RuntimeWarning.

    * ``system``: a :class:`~pinnhjb.systems.ControlAffineSystem`; only f, g, Q, R, n and m are used.
    * ``x0``: the initial state, shape (n,).
    * ``horizon``: ``math.inf`` for V*(x0) of the infinite-horizon cost :eq:`eq-cost`, or T > 0 for
      V_T(x0, 0) of the finite-horizon cost :eq:`eq-costt`.
    * ``terminal_cost``: phi, for a finite horizon: None (phi = 0), a batched torch callable (N, n) -> (N,),
      or an (n, n) matrix P_T meaning ``phi(x) = x'P_T x``.
    * ``t_inf``: where the infinite horizon is truncated (see the module's description).
    * ``tol``: the ``solve_bvp`` tolerance on the collocation and boundary residuals.
    * ``guess``: a previous result of this function, as a warm start shifted to ``x0``; on failure the LQR
      guess and then continuation along the ray ``s x0``, s = 1/4 .. 1, are tried.
    * ``max_nodes``: the most mesh nodes ``solve_bvp`` may use.
    * ``tail_tol``: infinite horizon only; the solve is flagged unless ``norm(x(t_inf)) <= tail_tol``.
    * ``max_extensions``: infinite horizon only; while the tail check fails, ``t_inf`` is doubled up to this
      many times (slow systems such as :func:`~pinnhjb.systems.third_order` need ``t_inf`` near 100).

    Returns a dict:

    * ``value``: V(x0).
    * ``gradient``: ``lam(0) = grad_x V(x0)``.
    * ``policy``: ``-1/2 R^{-1} g(x0)' lam(0)``, :eq:`eq-mustar` (or :eq:`eq-mut` at t = 0).
    * ``converged``: bool; BVP status 0, residuals within ``tol`` and a small tail.
    * ``status``, ``message``: from ``solve_bvp``.
    * ``residual``: the largest collocation rms residual; ``bc_residual``: the boundary residual.
    * ``tail_norm``: ``norm(x(t_inf))``.
    * ``hamiltonian``: Hmin at t = 0 (near 0 for the infinite horizon).
    * ``nodes``, ``x0``.
    * ``t_inf``: the truncation used; None for a finite horizon.
    * ``solution``: the ``solve_bvp`` result, rows x, lam and the accumulated cost.
    """
    x0 = _check_x0(system, x0)
    prob = _problem if _problem is not None else _Problem(system, horizon, terminal_cost, t_inf)
    infinite = math.isinf(horizon)
    res = _solve(prob, x0, guess, tol, max_nodes, tail_tol, infinite)
    for _ in range(max_extensions if infinite else 0):
        if res["converged"] or res["status"] != 0 or not res["tail_norm"] > tail_tol:
            break
        prob = prob.extended(2 * prob.T)  # the state has not reached the origin yet: lengthen t_inf
        res = _solve(prob, x0, res if np.allclose(res["x0"], x0) else guess, tol, max_nodes, tail_tol, infinite)
    res["t_inf"] = prob.T if infinite else None
    res["_problem"] = prob
    if not res["converged"]:
        warnings.warn(
            f"reference BVP did not converge at x0={x0.tolist()}: status {res['status']} "
            f"({res['message']}), residual {res['residual']:.2e}, tail {res['tail_norm']:.2e}",
            RuntimeWarning,
            stacklevel=2,
        )
    return res


# ============================================================================ grids
@dataclass(eq=False)
class ReferenceGrid:
    """Reference values on a grid, as :func:`reference_grid` computes them.

    Points that did not converge hold NaN and ``converged = False``.

    * ``points``: (N, n) states.
    * ``value``: (N,), V* (the cost :eq:`eq-cost`) or V_T(., 0) (the cost :eq:`eq-costt`).
    * ``gradient``: (N, n), grad V.
    * ``policy``: (N, m), :eq:`eq-mustar` (or :eq:`eq-mut` at t = 0).
    * ``horizon``: ``math.inf`` or T.
    * ``converged``: (N,) bool.
    * ``max_bvp_residual``: (N,), each solve's largest collocation residual.
    * ``wall_time``: seconds.
    * ``system``: the system's :meth:`~pinnhjb.systems.ControlAffineSystem.spec`.
    * ``status``: (N,), the ``solve_bvp`` status (0 = success).
    * ``info``: the settings of the solve (grid, box, tolerances, ``t_inf``, terminal cost, method).
    * ``replay_value``: (N,) or None, :func:`reference_points` only: the cost of each point's open-loop control
      re-integrated by a separate integrator (:func:`replay_cost`), to compare with ``value``.
    """

    points: np.ndarray
    value: np.ndarray
    gradient: np.ndarray
    policy: np.ndarray
    horizon: float
    converged: np.ndarray
    max_bvp_residual: np.ndarray
    wall_time: float
    system: dict
    status: np.ndarray | None = None
    info: dict = field(default_factory=dict)
    replay_value: np.ndarray | None = None

    _ARRAYS = ("points", "value", "gradient", "policy", "converged", "max_bvp_residual", "status", "replay_value")

    def save(self, path) -> None:
        """Write a .npz file at ``path``: every array, and a JSON ``metadata`` string (system, horizon, settings,
        library versions, wall time, creation time)."""
        meta = {
            "system": self.system,
            "horizon": "inf" if math.isinf(self.horizon) else float(self.horizon),
            "wall_time": float(self.wall_time),
            "info": self.info,
            "versions": {"numpy": np.__version__, "scipy": scipy.__version__, "torch": torch.__version__},
            "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
        }
        arrays = {k: np.asarray(getattr(self, k)) for k in self._ARRAYS if getattr(self, k) is not None}
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(path.name + ".tmp")
        with open(tmp, "wb") as fh:  # atomic: write aside, then rename
            np.savez(fh, metadata=np.array(json.dumps(meta)), **arrays)
        os.replace(tmp, path)

    def value_error(self, solution, signed: bool = False) -> np.ndarray:
        """The learned value's error at each converged point, per the largest reference value.

        * ``solution``: anything with ``value(x)`` on (N, n) numpy states (a
          :class:`~pinnhjb.solution.FiniteHorizonSolution`, a chain).
        * ``signed``: ``(V - value) / max abs(value)``; otherwise its absolute value.

        Returns an (N_converged,) array, in the order of ``points[converged]``. Its maximum is the benchmarks'
        ``value_rel_error``.
        """
        ok = np.asarray(self.converged, dtype=bool)
        v_ref = self.value[ok]
        err = (np.asarray(solution.value(self.points[ok]), dtype=float) - v_ref) / np.max(np.abs(v_ref))
        return err if signed else np.abs(err)

    @property
    def replay_error(self) -> float | None:
        """The reference's own check: max over the converged points of abs(replay_value - value) / abs(value);
        None without replayed costs (:func:`reference_grid`)."""
        if self.replay_value is None:
            return None
        keep = np.asarray(self.converged, dtype=bool)
        return float(np.max(np.abs(self.replay_value[keep] - self.value[keep]) / np.abs(self.value[keep])))

    @classmethod
    def load(cls, path) -> ReferenceGrid:
        """Read a grid that :meth:`save` wrote at ``path``."""
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(str(data["metadata"]))
            arrays = {k: data[k] for k in cls._ARRAYS if k in data.files}
        horizon = math.inf if meta["horizon"] == "inf" else float(meta["horizon"])
        info = dict(meta.get("info", {}), versions=meta.get("versions"), created=meta.get("created"))
        return cls(horizon=horizon, wall_time=float(meta["wall_time"]), system=meta["system"], info=info, **arrays)


def reference_grid(
    system,
    points_per_dim: int = 41,
    horizon: float = math.inf,
    terminal_cost=None,
    box=None,
    progress: bool = True,
    strict: bool = False,
    **kw,
) -> ReferenceGrid:
    """:func:`solve_point` on a tensor-product grid of Omega.

    Points are swept by distance from the origin; each is warm-started from its nearest solved grid neighbour
    (see :func:`solve_point` for the fallbacks).

    * ``system``: the control-affine system.
    * ``points_per_dim``: grid points along each axis.
    * ``horizon``, ``terminal_cost``: as in :func:`solve_point`.
    * ``box``: (n, 2); None: Omega.
    * ``progress``: show a progress bar.
    * ``strict``: raise a RuntimeError when a point fails; otherwise failed points are NaN with
      ``converged = False``, and a RuntimeWarning says how many.
    * ``kw``: ``t_inf``, ``tol``, ``max_nodes``, ``tail_tol``, passed to :func:`solve_point`.

    Returns a :class:`ReferenceGrid`.
    """
    if box is not None:
        box = np.asarray(box, dtype=float)
    pts = system.grid(points_per_dim, box=box).detach().cpu().numpy().astype(float)
    box_ = system.domain if box is None else box
    shape = (points_per_dim,) * system.n
    strides = np.array([int(np.prod(shape[i + 1 :])) for i in range(system.n)])

    def neighbours(k: int, solved: dict) -> list[int]:  # solved grid neighbours along each axis
        idx = np.array(np.unravel_index(k, shape))
        return [
            int(k + s * strides[d])
            for d in range(system.n)
            for s in (-1, 1)
            if 0 <= idx[d] + s < points_per_dim and int(k + s * strides[d]) in solved
        ]

    sweep = _sweep(system, pts, box_, neighbours, horizon, terminal_cost, progress, strict, "grid", False, kw)
    sweep["info"] = {"points_per_dim": points_per_dim, **sweep["info"]}
    return ReferenceGrid(**sweep)


def reference_points(
    system,
    points: int = 1000,
    seed: int = 0,
    horizon: float = math.inf,
    terminal_cost=None,
    box=None,
    progress: bool = True,
    strict: bool = False,
    replay: bool = True,
    **kw,
) -> ReferenceGrid:
    """:func:`solve_point` at seeded uniform random states of Omega: the reference of a system whose dimension
    rules out a grid (:func:`~pinnhjb.systems.rigid_body`, n = 6).

    Points are swept by distance from the origin; each is warm-started from the nearest point already solved.

    * ``system``: the control-affine system.
    * ``points``: how many states, uniform in the box.
    * ``seed``: the seed of numpy's generator that draws them (``numpy.random.default_rng``).
    * ``horizon``, ``terminal_cost``: as in :func:`solve_point`.
    * ``box``: (n, 2); None: Omega.
    * ``progress``, ``strict``: as in :func:`reference_grid`.
    * ``replay``: the reference's own check. Each solved point's open-loop control u(t) is fed back into the
      dynamics by a separate integrator (``scipy.integrate.solve_ivp``, DOP853, rtol 1e-10), its cost summed and
      the same terminal cost added: ``replay_value`` holds that cost, which must equal ``value``.
    * ``kw``: ``t_inf``, ``tol``, ``max_nodes``, ``tail_tol``, passed to :func:`solve_point`.

    Returns a :class:`ReferenceGrid` whose ``info`` records the seed and the number of points.
    """
    box_ = np.asarray(system.domain if box is None else box, dtype=float)
    if not (isinstance(points, int) and points >= 1):
        raise ValueError(f"points must be an integer >= 1; got {points!r}")
    rng = np.random.default_rng(seed)
    pts = box_[:, 0] + (box_[:, 1] - box_[:, 0]) * rng.random((points, system.n))
    scale = np.maximum(np.abs(box_).max(axis=1), 1e-12)

    def nearest(k: int, solved: dict) -> list[int]:  # the nearest solved point, in units of the box
        if not solved:
            return []
        keys = np.fromiter(solved, dtype=int)
        return [int(keys[np.argmin(np.linalg.norm((pts[keys] - pts[k]) / scale, axis=1))])]

    sweep = _sweep(system, pts, box_, nearest, horizon, terminal_cost, progress, strict, "points", replay, kw)
    sweep["info"] = {"points": points, "seed": seed, **sweep["info"]}
    return ReferenceGrid(**sweep)


def replay_cost(problem, res: dict, rtol: float = 1e-10) -> float:
    """The cost of one reference solution's open-loop control, re-integrated: the check that ``res["value"]``
    is a cost the control really achieves.

    * ``problem``: ``res["_problem"]`` from :func:`solve_point` (it carries the horizon and terminal cost).
    * ``res``: a converged result of :func:`solve_point`.
    * ``rtol``: the integrator's relative tolerance (absolute: ``rtol / 100``).

    The control ``u(t) = -1/2 R^{-1} g(x(t))' lam(t)`` is read off the BVP solution as a function of time only;
    the state is integrated afresh under it (``solve_ivp``, DOP853) with the running cost, and the terminal cost
    at the end is added (for the infinite horizon, the LQR tail ``x'Px`` at ``t_inf``).
    """
    from scipy.integrate import solve_ivp

    prob, sol, n = problem, res["solution"], res["x0"].size
    s = prob.system

    def control(t):
        y = sol.sol(t)
        x = torch.as_tensor(y[:n], dtype=_DT)[None]
        return -0.5 * prob.Rinv @ (s.g(x)[0].detach().numpy().T @ y[n : 2 * n])

    def rhs(t, z):
        x = torch.as_tensor(z[:n], dtype=_DT)[None]
        u = control(t)
        dx = s.f(x)[0].detach().numpy() + s.g(x)[0].detach().numpy() @ u
        return np.append(dx, float(s.Q(x)[0]) + u @ prob.R @ u)

    out = solve_ivp(rhs, (0.0, sol.x[-1]), np.append(res["x0"], 0.0), method="DOP853", rtol=rtol, atol=rtol / 100)
    return float(out.y[n, -1]) + prob.phi_value(out.y[:n, -1])


def _sweep(system, pts, box_, neighbours, horizon, terminal_cost, progress, strict, what, replay, kw) -> dict:
    """Solve every point of ``pts`` outward from the origin, warm-starting each from the nearest of
    ``neighbours(k, solved)``: the loop shared by :func:`reference_grid` and :func:`reference_points`."""
    from tqdm.auto import tqdm

    N, n = pts.shape
    start = time.perf_counter()
    prob = _Problem(system, horizon, terminal_cost, kw.get("t_inf", 25.0))
    scale = np.maximum(np.abs(box_).max(axis=1), 1e-12)
    order = np.argsort(np.linalg.norm(pts / scale, axis=1), kind="stable")
    value, status = np.full(N, np.nan), np.full(N, -1, dtype=int)
    grad, pol = np.full((N, n), np.nan), np.full((N, system.m), np.nan)
    conv, resid = np.zeros(N, dtype=bool), np.full(N, np.nan)
    replayed = np.full(N, np.nan)
    solved: dict[int, dict] = {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for k in tqdm(order, desc=f"reference {system.name}", disable=not progress, leave=False):
            nbrs = neighbours(int(k), solved)
            guess = solved[min(nbrs, key=lambda j: np.linalg.norm(pts[j] - pts[k]))] if nbrs else None
            res = solve_point(system, pts[k], horizon=horizon, guess=guess, _problem=prob, **kw)
            status[k], resid[k] = res["status"], res["residual"]
            if res["_problem"].T > prob.T:  # t_inf had to grow: farther points start from the longer one
                prob = res["_problem"]
            if res["converged"]:
                conv[k] = True
                value[k], grad[k], pol[k] = res["value"], res["gradient"], res["policy"]
                solved[int(k)] = res
                if replay:
                    replayed[k] = replay_cost(res["_problem"], res)
    wall = time.perf_counter() - start
    if not conv.all():
        msg = f"reference {what}: {int((~conv).sum())} of {N} points did not converge (set to NaN)"
        if strict:
            raise RuntimeError(msg)
        warnings.warn(msg, RuntimeWarning, stacklevel=3)
    info = {
        "box": np.asarray(box_).tolist(),
        "tol": kw.get("tol", 1e-8),
        "t_inf": prob.T if math.isinf(horizon) else None,
        "tail_tol": kw.get("tail_tol", 1e-3),
        "max_nodes": kw.get("max_nodes", 100_000),
        "terminal_cost": None
        if terminal_cost is None
        else ("callable" if callable(terminal_cost) else np.asarray(terminal_cost).tolist()),
        "method": "Pontryagin BVP, scipy.integrate.solve_bvp, autograd Jacobians",
    }
    out = {
        "points": pts,
        "value": value,
        "gradient": grad,
        "policy": pol,
        "horizon": float(horizon),
        "converged": conv,
        "max_bvp_residual": resid,
        "wall_time": wall,
        "system": system.spec(),
        "status": status,
        "info": info,
    }
    if replay:
        out["replay_value"] = replayed
    return out
