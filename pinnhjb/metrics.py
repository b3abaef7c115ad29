"""Checks of a learned value function (Section 5.1) and of its policy in closed loop.

* :func:`infinite_horizon_residual`: the horizon check E :eq:`eq-e`, the mean square of the steady-state
  residual :eq:`eq-ee` over Omega plus V(0)^2, on a grid while it has at most :data:`GRID_MAX_POINTS` points
  (every case of the book), else by seeded Monte Carlo with its standard error;
* :func:`optimality_errors`: errors of V and mu against a known V*, mu*;
* :func:`largest_value_error`: how large abs(V - V*) / max V* gets on Omega beyond a sample of it (its vertices,
  an ascent);
* :func:`closed_loop`: simulate the policy and accumulate the cost :eq:`eq-cost`, so that a policy is judged by
  what it does; :func:`infinite_horizon_cost` adds the cost still to come after the run;
* :func:`residual_along_loop`: where a learned value's error comes from, without a reference: along the closed
  loop of its own policy, ``V(x0) = J_T + V(x(T)) - int_0^T E_e(x(t)) dt`` exactly.

A ``value_fn`` is a batched torch callable x (N, n) -> V(x) (N,), differentiable in x; points are float64 on
the CPU (the solution objects move them to their own device and precision and back).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from scipy.integrate import simpson

from . import lq
from .pinn import gradient
from .residuals import SteadyStateHJB

Tensor = torch.Tensor
ValueFn = Callable[[Tensor], Tensor]

__all__ = [
    "default_points_per_dim",
    "evaluation_grid",
    "evaluation_states",
    "infinite_horizon_residual",
    "residual_spread",
    "optimality_errors",
    "largest_value_error",
    "LargestError",
    "known_policy",
    "policy_of",
    "closed_loop",
    "ClosedLoopResult",
    "infinite_horizon_cost",
    "residual_along_loop",
    "LoopResidual",
    "quadratic_fields",
    "GRID_MAX_POINTS",
    "MC_SAMPLES",
    "uses_grid",
]

#: The largest grid E is measured on (65536 points: 1001 points in 1-D, 101^2, 21^3, 9^4 and 9^5 grids fit).
GRID_MAX_POINTS = 2**16
#: The Monte Carlo sample size above that (standard error about 0.6% of the spread of E_e^2).
MC_SAMPLES = 2**15
MC_SEED = 0
_BATCH = 16384


def default_points_per_dim(n: int) -> int:
    """The grid resolution for E in dimension ``n``: 1001 in 1-D, 101 per axis in 2-D (the reports' 101 x 101
    grid), 21 in 3-D, 9 above."""
    return {1: 1001, 2: 101, 3: 21}.get(n, 9)


def _points_per_dim(system, points_per_dim) -> int:
    if points_per_dim is None:
        return default_points_per_dim(system.n)
    if isinstance(points_per_dim, bool) or not isinstance(points_per_dim, (int, np.integer)) or points_per_dim < 2:
        raise ValueError(
            f"points_per_dim must be an integer >= 2 (points per axis of the grid over Omega) or None "
            f"(the default for n={system.n}: {default_points_per_dim(system.n)}); got {points_per_dim!r}"
        )
    return int(points_per_dim)


def uses_grid(system, points_per_dim: int | None = None) -> bool:
    """Whether E is measured on the grid (``points_per_dim**n <= GRID_MAX_POINTS``) rather than by Monte Carlo.

    * ``system``: the control-affine system.
    * ``points_per_dim``: grid points per axis; None: :func:`default_points_per_dim`.
    """
    return _points_per_dim(system, points_per_dim) ** system.n <= GRID_MAX_POINTS


def evaluation_grid(system, points_per_dim: int | None = None, dtype=torch.float64, device=None) -> Tensor:
    """The grid over Omega on which E is reported; refuses one above :data:`GRID_MAX_POINTS` points.

    * ``system``: the control-affine system.
    * ``points_per_dim``: grid points per axis; None: :func:`default_points_per_dim`.
    * ``dtype``, ``device``: of the result.
    """
    ppd = _points_per_dim(system, points_per_dim)
    if ppd**system.n > GRID_MAX_POINTS:
        raise ValueError(
            f"a grid of {ppd}^{system.n} points exceeds GRID_MAX_POINTS={GRID_MAX_POINTS}; E is then "
            f"measured by Monte Carlo (infinite_horizon_residual with points=None)"
        )
    return system.grid(ppd, dtype=dtype, device=device)


def _monte_carlo_batches(system, samples: int = MC_SAMPLES, seed: int = MC_SEED, batch: int = _BATCH):
    """Seeded uniform points of Omega, float64 on the CPU, in batches (the same points on every call)."""
    gen = torch.Generator().manual_seed(seed)
    lo = torch.as_tensor(system.domain[:, 0], dtype=torch.float64)
    hi = torch.as_tensor(system.domain[:, 1], dtype=torch.float64)
    done = 0
    while done < samples:
        k = min(batch, samples - done)
        yield lo + (hi - lo) * torch.rand(k, system.n, generator=gen, dtype=torch.float64)
        done += k


def evaluation_states(system, points_per_dim: int | None = None) -> Tensor:
    """The states E is measured on, as :func:`infinite_horizon_residual` with ``points=None`` draws them: the grid
    of :func:`evaluation_grid`, or, above :data:`GRID_MAX_POINTS` grid points, the :data:`MC_SAMPLES` seeded
    uniform states of Omega (float64, CPU).

    * ``system``: the control-affine system.
    * ``points_per_dim``: grid points per axis; None: :func:`default_points_per_dim`.
    """
    if uses_grid(system, points_per_dim):
        return evaluation_grid(system, points_per_dim)
    return torch.cat(list(_monte_carlo_batches(system)))


def _chunks(x: Tensor, size: int = 16384):
    return torch.split(x, size)


def infinite_horizon_residual(
    system, value_fn: ValueFn, points: Tensor | None = None, points_per_dim: int | None = None
) -> dict:
    """The horizon check ``E = mean_i E_e(x_i)^2 + V(0)^2`` :eq:`eq-e`.

    * ``system``: the control-affine system.
    * ``value_fn``: V, a batched torch callable (N, n) -> (N,).
    * ``points``: (N, n) states; None: a grid over Omega, or seeded Monte Carlo points of Omega (evaluated in
      batches) when the grid would exceed :data:`GRID_MAX_POINTS` points.
    * ``points_per_dim``: the grid's points per axis; None: :func:`default_points_per_dim`.

    Returns a dict:

    * ``E``: the sum of the two parts below.
    * ``E_flow``: the mean of E_e^2; ``E_boundary``: V(0)^2.
    * ``E_zero``: E of the trivial V = 0 on the same points (the mean of Q^2); on small boxes E is only
      meaningful next to it.
    * ``E_stderr``, ``E_samples``: Monte Carlo only, the standard error and the sample size.
    """
    if points is None and not uses_grid(system, points_per_dim):
        return _monte_carlo_residual(system, value_fn)
    if points is None:
        points = evaluation_grid(system, points_per_dim)
    e = SteadyStateHJB(system, value_fn).field(points)
    with torch.no_grad():
        v0 = value_fn(torch.zeros(1, system.n, dtype=points.dtype, device=points.device))
        e_zero = (system.Q(points) ** 2).mean()
    flow = float((e**2).mean())
    boundary = float(v0.reshape(()) ** 2)
    return {"E": flow + boundary, "E_flow": flow, "E_boundary": boundary, "E_zero": float(e_zero)}


def _monte_carlo_residual(system, value_fn: ValueFn, samples: int = MC_SAMPLES) -> dict:
    total = total_sq = zero = 0.0
    residual = SteadyStateHJB(system, value_fn)
    for xc in _monte_carlo_batches(system, samples):
        e2 = residual.field(xc) ** 2
        total += float(e2.sum())
        total_sq += float((e2**2).sum())
        with torch.no_grad():
            zero += float((system.Q(xc) ** 2).sum())
    with torch.no_grad():
        v0 = value_fn(torch.zeros(1, system.n, dtype=torch.float64))
    flow = total / samples
    var = max(total_sq / samples - flow**2, 0.0) * samples / max(samples - 1, 1)
    boundary = float(v0.reshape(()) ** 2)
    return {
        "E": flow + boundary,
        "E_flow": flow,
        "E_boundary": boundary,
        "E_zero": zero / samples,
        "E_stderr": math.sqrt(var / samples),
        "E_samples": samples,
    }


def residual_spread(
    system, field: Callable[[Tensor], Tensor], points_per_dim: int | None = None, top: float = 1e-3
) -> dict:
    """How E's mean square :eq:`eq-e` is spread over the states it is measured on: ``abs(E_e)`` per RMS of Q on
    :func:`evaluation_states`, whose mean square is ``E_flow / E_zero`` of :func:`infinite_horizon_residual`.

    * ``system``: the control-affine system.
    * ``field``: E_e at states, a callable (N, n) -> (N,), for example a solution's ``residual_field``.
    * ``points_per_dim``: as in :func:`evaluation_states`.
    * ``top``: the fraction of the states, those of the largest residuals, whose share of the sum is reported.

    Returns a dict: ``scaled`` (N,) numpy array, ``abs(E_e)`` / RMS of Q at each state; ``q_rms``, that RMS of Q
    (to scale other residuals alike); ``max`` and ``q99``, its largest value and its 99th percentile;
    ``top_share``, the share of the sum of squares from the states at or above its ``1 - top`` quantile.
    """
    if not 0 < top < 1:
        raise ValueError(f"top must be in (0, 1); got {top}")
    x = evaluation_states(system, points_per_dim)
    with torch.no_grad():
        q_rms = float((system.Q(x) ** 2).mean()) ** 0.5
    e = field(x)
    r = np.abs(e.detach().cpu().numpy() if isinstance(e, Tensor) else np.asarray(e)) / q_rms
    sq = r**2
    return {
        "scaled": r,
        "q_rms": q_rms,
        "max": float(r.max()),
        "q99": float(np.quantile(r, 0.99)),
        "top_share": float(sq[r >= np.quantile(r, 1 - top)].sum() / sq.sum()),
    }


def policy_of(system, value_fn: ValueFn) -> Callable[[Tensor], Tensor]:
    """The policy of a value function, ``mu(x) = -1/2 R^{-1} g(x)' grad V(x)`` :eq:`eq-mustar`.

    * ``system``: the control-affine system.
    * ``value_fn``: V, a batched torch callable (N, n) -> (N,).

    Returns a batched callable x (N, n) -> (N, m).
    """

    def mu(x: Tensor) -> Tensor:
        _, g = gradient(value_fn, x)
        return system.policy_from_gradient(x, g).detach()

    return mu


def known_policy(system) -> Callable[[Tensor], Tensor] | None:
    """mu*: the system's ``policy_star``, else the policy of its ``value_star`` (:func:`policy_of`, by autograd),
    else None."""
    if system.policy_star is not None:
        return system.policy_star
    return None if system.value_star is None else policy_of(system, system.value_star)


def optimality_errors(
    system, value_fn: ValueFn, points: Tensor | None = None, points_per_dim: int | None = None
) -> dict:
    """The errors of V and its policy mu against the system's known V* and mu*.

    Raises a ValueError when the system has no known V*.

    * ``system``: the control-affine system, with ``value_star`` (and ``policy_star``; None: mu* is the policy
      of V*, ``-1/2 R^{-1} g' grad V*`` by autograd, :func:`policy_of`).
    * ``value_fn``: V, a batched torch callable (N, n) -> (N,).
    * ``points``: (N, n) states; None: as in :func:`infinite_horizon_residual`.
    * ``points_per_dim``: the grid's points per axis; None: :func:`default_points_per_dim`.

    Returns a dict: ``value_max_error`` (the largest ``abs(V - V*)``), ``value_rmse``, ``value_mse``, and the
    same three for mu (``policy_...``, the largest over points and inputs).
    """
    if system.value_star is None:
        raise ValueError(f"system '{system.name}' has no known V*; errors need a reference (see pinnhjb.reference)")
    mu_star = known_policy(system)
    if points is None and uses_grid(system, points_per_dim):
        points = evaluation_grid(system, points_per_dim)
    batches = _chunks(points) if points is not None else _monte_carlo_batches(system)
    mu = policy_of(system, value_fn)
    dv, du = [], []
    for xc in batches:
        with torch.no_grad():
            dv.append(value_fn(xc).detach() - system.value_star(xc))
        du.append(mu(xc) - mu_star(xc))
    dv, du = torch.cat(dv), torch.cat(du)
    return {
        "value_max_error": float(dv.abs().max()),
        "value_rmse": float(dv.pow(2).mean().sqrt()),
        "value_mse": float(dv.pow(2).mean()),
        "policy_max_error": float(du.abs().max()),
        "policy_rmse": float(du.pow(2).mean().sqrt()),
        "policy_mse": float(du.pow(2).mean()),
    }


@dataclass(frozen=True)
class LargestError:
    """The largest relative value error ``max abs(V - V*) / max V*`` over Omega, looked for three ways, each over
    more states than the one before (:func:`largest_value_error`).

    * ``sampled``: over the given states alone (what the benchmarks report).
    * ``vertices``: over those and the 2^n vertices of Omega; None above ``max_vertex_dim``.
    * ``ascended``: over all of those and the ends of a bounded ascent of ``abs(V - V*)`` (L-BFGS-B in Omega)
      from the states and vertices with the largest errors.
    * ``state``: (n,) where ``ascended`` is reached.
    * ``scale``: max V* over every state looked at, the denominator of ``vertices`` and ``ascended`` (``sampled``'s
      is max V* over the given states).
    * ``at_vertex``: whether ``state`` is a vertex of Omega (every coordinate at a bound, to 1e-9).
    """

    sampled: float
    vertices: float | None
    ascended: float
    state: np.ndarray
    scale: float
    at_vertex: bool


def _vertices(domain: np.ndarray) -> Tensor:
    n = len(domain)
    bits = (torch.arange(2**n).unsqueeze(1) >> torch.arange(n)) & 1
    lo, hi = (torch.as_tensor(domain[:, k], dtype=torch.float64) for k in (0, 1))
    return lo + bits.to(torch.float64) * (hi - lo)


def largest_value_error(
    system, value_fn: ValueFn, x: Tensor, starts: int = 10, max_vertex_dim: int = 16
) -> LargestError:
    """How large ``abs(V - V*) / max V*`` gets on Omega, beyond a sample of it. A maximum over seeded uniform
    states misses the corners of an n-D box, where the error and V* often peak: it is first taken over ``x``, then
    over Omega's 2^n vertices too, then after a bounded ascent (scipy's L-BFGS-B on ``abs(V - V*)``, in Omega, the
    gradient by autograd) from the ``starts`` states and the ``starts`` vertices with the largest errors. Each is a
    maximum over the states looked at, and so a lower bound of the maximum over Omega.

    Raises a ValueError, before any work, when the system has no known V* or ``x`` is not (N, n).

    * ``system``: the control-affine system, with ``value_star``; Omega is its ``domain``.
    * ``value_fn``: V, a batched torch callable (N, n) -> (N,), differentiable in x (e.g. a solution's
      ``value_function()``).
    * ``x``: (N, n) states of Omega, float64 (e.g. a benchmark's seeded states).
    * ``starts``: how many of the largest errors to start an ascent from, among ``x`` and among the vertices.
    * ``max_vertex_dim``: above this n the vertices (2^n) are left out.

    Returns a :class:`LargestError`.
    """
    from scipy.optimize import minimize

    if system.value_star is None:
        raise ValueError(f"system '{system.name}' has no known V*; the largest error needs it")
    x = torch.as_tensor(x, dtype=torch.float64)
    if x.ndim != 2 or x.shape[1] != system.n or len(x) == 0:
        raise ValueError(f"x must be (N, {system.n}) states with N >= 1; got shape {tuple(x.shape)}")
    domain = np.asarray(system.domain, dtype=float)

    def errors(z: Tensor) -> tuple[Tensor, Tensor]:
        with torch.no_grad():
            vs = torch.cat([system.value_star(c) for c in _chunks(z)])
            return torch.cat([value_fn(c).detach() for c in _chunks(z)]) - vs, vs

    err, vs = errors(x)
    sampled = float(err.abs().max() / vs.abs().max())
    pool, pool_err, pool_vs = [x], [err], [vs]
    vertices = None
    if system.n <= max_vertex_dim:
        corners = _vertices(domain)
        err_c, vs_c = errors(corners)
        pool, pool_err, pool_vs = pool + [corners], pool_err + [err_c], pool_vs + [vs_c]
        scale_c = float(torch.cat([vs, vs_c]).abs().max())
        vertices = float(torch.cat([err, err_c]).abs().max() / scale_c)
    seeds = torch.cat([z[torch.argsort(e.abs(), descending=True)[:starts]] for z, e in zip(pool, pool_err)])

    def ascend(x0: np.ndarray) -> np.ndarray:
        sign = float(torch.sign(errors(torch.as_tensor(x0[None]))[0])[0]) or 1.0

        def loss(z):
            zt = torch.tensor(z[None], requires_grad=True)
            e = -sign * (value_fn(zt) - system.value_star(zt)).sum()
            (g,) = torch.autograd.grad(e, zt)
            return float(e.detach()), g[0].numpy().astype(float)

        return minimize(loss, x0, jac=True, method="L-BFGS-B", bounds=list(map(tuple, domain))).x

    ends = torch.as_tensor(np.stack([ascend(s.numpy()) for s in seeds]))
    err_e, vs_e = errors(ends)
    all_x = torch.cat(pool + [ends])
    all_err, all_vs = torch.cat(pool_err + [err_e]), torch.cat(pool_vs + [vs_e])
    scale = float(all_vs.abs().max())
    k = int(all_err.abs().argmax())
    state = all_x[k].numpy()
    at_vertex = bool((np.isclose(state, domain[:, 0], atol=1e-9) | np.isclose(state, domain[:, 1], atol=1e-9)).all())
    return LargestError(sampled, vertices, float(all_err.abs()[k] / scale), state, scale, at_vertex)


@dataclass
class ClosedLoopResult:
    """Trajectories of the closed loop from a batch of initial states.

    * ``t``: (K+1,) times.
    * ``x``: (K+1, N, n) states.
    * ``u``: (K+1, N, m) inputs.
    * ``cost``: (N,), the cost J accumulated to ``t_final``.
    * ``stabilized``: (N,) bool, ``norm(x(t_final))`` below ``tol``.
    """

    t: np.ndarray
    x: np.ndarray
    u: np.ndarray
    cost: np.ndarray
    stabilized: np.ndarray

    @property
    def fraction_stabilized(self) -> float:
        """The fraction of the initial states whose trajectory was stabilized."""
        return float(np.mean(self.stabilized))


def closed_loop(
    system,
    policy: Callable[..., Tensor],
    x0,
    t_final: float = 20.0,
    dt: float = 0.01,
    tol: float = 1e-3,
    time_varying: bool = False,
) -> ClosedLoopResult:
    """Simulate ``xdot = f(x) + g(x) policy(x)`` and ``dJ/dt = Q(x) + u'Ru`` with classical RK4, batched.

    The running cost is integrated with the state, so ``cost`` approximates J(policy; x0) of :eq:`eq-cost`
    truncated at ``t_final``: choose it long enough for the tail to vanish (``stabilized`` tells whether it did).

    * ``system``: the control-affine system.
    * ``policy``: a batched callable x (N, n) -> u (N, m).
    * ``x0``: (N, n) initial states, a tensor or an array.
    * ``t_final``: the simulated time.
    * ``dt``: the RK4 step.
    * ``tol``: a trajectory counts as stabilized when ``norm(x(t_final)) < tol``.
    * ``time_varying``: call ``policy(x, t)`` instead, e.g. a finite-horizon mu_T(x, t) along its horizon.

    Returns a :class:`ClosedLoopResult`.
    """
    x = system.check_states(torch.as_tensor(x0), "x0").to(torch.float64)
    if not (t_final > 0 and dt > 0):
        raise ValueError(f"t_final and dt must be positive; got t_final={t_final}, dt={dt}")
    steps = int(round(t_final / dt))

    def rhs(z, t):
        xs = z[:, :-1]
        u = (policy(xs, t) if time_varying else policy(xs)).to(torch.float64)
        return torch.cat([system.dynamics(xs, u), system.running_cost(xs, u).unsqueeze(-1)], dim=-1), u

    z = torch.cat([x, torch.zeros(x.shape[0], 1, dtype=x.dtype)], dim=-1)
    xs, us = [x.clone()], []
    for k in range(steps):
        t = k * dt
        k1, u = rhs(z, t)
        k2, _ = rhs(z + 0.5 * dt * k1, t + 0.5 * dt)
        k3, _ = rhs(z + 0.5 * dt * k2, t + 0.5 * dt)
        k4, _ = rhs(z + dt * k3, t + dt)
        z = z + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
        if not torch.all(torch.isfinite(z)):
            z = torch.where(torch.isfinite(z), z, torch.full_like(z, float("inf")))
        xs.append(z[:, :-1].clone())
        us.append(u)
    us.append(rhs(z, steps * dt)[1])
    xt = torch.stack(xs).numpy()
    final = np.linalg.norm(xt[-1], axis=-1)
    return ClosedLoopResult(
        t=np.linspace(0.0, steps * dt, steps + 1),
        x=xt,
        u=torch.stack(us).numpy(),
        cost=z[:, -1].numpy(),
        stabilized=np.isfinite(final) & (final < tol),
    )


def infinite_horizon_cost(system, run: ClosedLoopResult) -> tuple[np.ndarray, np.ndarray]:
    """The cost :eq:`eq-cost` of a closed-loop run to t = inf: J to ``t_final`` plus a tail x_f' P x_f.

    P is the LQR value matrix of the linearisation at the origin
    (:meth:`~pinnhjb.systems.ControlAffineSystem.linearize`, :func:`pinnhjb.lq.care`). Near the origin
    V* = x'Px + O(abs(x)^3), so once a run has come close, the tail is the optimal cost still to come from x_f,
    and the optimal policy's J + tail is V*(x0) up to the integration error. A run that has not come close has a
    tail that is large against J (check the returned ``tail``); a run that diverged has an infinite cost.

    * ``system``: the control-affine system the run simulated.
    * ``run``: a :class:`ClosedLoopResult` of :func:`closed_loop`.

    Returns ``(cost, tail)``, each (N,).
    """
    P = system.lqr_value()
    x_f = run.x[-1]
    with np.errstate(invalid="ignore", over="ignore"):
        tail = np.einsum("ni,ij,nj->n", x_f, P, x_f)
        cost = run.cost + tail
    bad = ~np.isfinite(cost)
    cost[bad], tail[bad] = np.inf, np.inf
    return cost, tail


@dataclass(frozen=True)
class LoopResidual:
    """A value function's residual along the closed loops of its own policy (:func:`residual_along_loop`).

    * ``run``: the :class:`ClosedLoopResult` (times, states, inputs, cost J to ``t_final``).
    * ``residual``: (K+1, N), E_e :eq:`eq-ee` at every state of every loop.
    * ``value_start``, ``value_end``: (N,), V at each loop's first and last state.
    * ``reach``: (K+1, N), how far each state reaches from the training box's centre per half-width, above 1
      outside the box (:meth:`~pinnhjb.systems.ControlAffineSystem.box_reach`).
    """

    run: ClosedLoopResult
    residual: np.ndarray
    value_start: np.ndarray
    value_end: np.ndarray
    reach: np.ndarray

    @property
    def outside(self) -> np.ndarray:
        """(K+1, N) bool: the state is outside the training box (``reach > 1``)."""
        return self.reach > 1

    @property
    def gap(self) -> np.ndarray:
        """``J_T + V(x(T)) - V(x0)`` (N,): what the value misses of the cost its own policy pays."""
        return self.run.cost + self.value_end - self.value_start

    @property
    def integral(self) -> np.ndarray:
        """``int_0^T E_e(x(t)) dt`` (N,) by Simpson's rule: equal to :attr:`gap` up to the quadrature."""
        return simpson(self.residual, x=self.run.t, axis=0)

    @property
    def integral_outside(self) -> np.ndarray:
        """The part of :attr:`integral` accrued while the loop is outside the training box (N,)."""
        return simpson(np.where(self.outside, self.residual, 0.0), x=self.run.t, axis=0)


def residual_along_loop(system, value_fn: ValueFn, x0, t_final: float = 20.0, dt: float = 0.01) -> LoopResidual:
    """The residual E_e :eq:`eq-ee` of ``value_fn`` along the closed loops of its own policy, from ``x0``.

    That policy attains the minimum in E_e, so along its loop ``dV/dt = E_e - Q - u'Ru``, and integrating,
    ``V(x0) = J_T + V(x(T)) - int_0^T E_e dt``: the value misses the cost its policy pays by the residual
    integrated along the loop. With ``J_T + V(x(T))`` close to V* (a good policy is optimal to second order),
    this accounts for the value error at ``x0`` without a reference, and ``outside`` tells how much of it
    accrues where the loop leaves the training box, where no residual was trained.

    * ``system``: the control-affine system.
    * ``value_fn``: V, a batched torch callable (N, n) -> (N,).
    * ``x0``: (N, n) initial states.
    * ``t_final``, ``dt``: as in :func:`closed_loop`.

    Returns a :class:`LoopResidual`.
    """
    run = closed_loop(system, policy_of(system, value_fn), x0, t_final=t_final, dt=dt)
    states = torch.as_tensor(run.x.reshape(-1, system.n))
    residual = SteadyStateHJB(system, value_fn).field(states).numpy().reshape(run.x.shape[:2])
    with torch.no_grad():
        ends = value_fn(torch.as_tensor(run.x[[0, -1]].reshape(-1, system.n))).numpy().reshape(2, -1)
    return LoopResidual(
        run=run, residual=residual, value_start=ends[0], value_end=ends[1], reach=system.box_reach(run.x)
    )


def quadratic_fields(A, B, Q, R, P, x) -> dict:
    """The exact LQ counterparts of a learned solution's fields, for ``V(x) = x'Px``; numpy in and out.

    * ``A``, ``B``, ``Q``, ``R``: the linear-quadratic problem.
    * ``P``: (n, n), the value's matrix.
    * ``x``: (N, n) states.

    Returns a dict: ``value`` ``x'Px`` (N,); ``policy`` ``-R^{-1} B'P x`` (N, m) (:func:`pinnhjb.lq.lqr_gain`);
    ``residual`` ``E_e(x; V) = x' (A'P + PA + Q - P B R^{-1} B'P) x`` (N,) :eq:`eq-ee`, the ARE residual
    (:func:`pinnhjb.lq.are_residual`) as a quadratic form, zero for every solution of the ARE.
    """
    x = np.asarray(x, dtype=float)

    def quad(M):
        return np.einsum("ni,ij,nj->n", x, np.asarray(M, dtype=float), x)

    return {"value": quad(P), "policy": -x @ lq.lqr_gain(B, R, P).T, "residual": quad(lq.are_residual(A, B, Q, R, P))}
