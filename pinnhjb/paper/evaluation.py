"""One trained case measured against its reference: E of the reference V_T, true errors of V and mu, and the
closed-loop cost of the learned policy, per horizon of a chain."""

from __future__ import annotations

import numpy as np
import torch

from ..metrics import infinite_horizon_cost
from .cases import CLOSED_LOOP, CLOSED_LOOP_SYSTEM, CONVERGED, INF

__all__ = [
    "reference_grid_residual",
    "true_errors",
    "closed_loop_metrics",
    "closed_loop_states",
    "closed_loop_setup",
    "stage_row",
    "stage_rows",
    "converged",
    "first_horizons",
]


def reference_grid_residual(system, ref) -> float:
    """The horizon check E of the reference V_T(., 0) on its own grid: the mean of E_e^2 from its gradient.

    V(0) = 0 exactly, so E has no boundary term. Points that did not converge are left out.

    * ``system``: the control-affine system.
    * ``ref``: a :class:`~pinnhjb.reference.ReferenceGrid`.
    """
    x = torch.as_tensor(ref.points, dtype=torch.float64)
    g = torch.as_tensor(ref.gradient, dtype=torch.float64)
    ok = torch.as_tensor(ref.converged)
    e = system.hamiltonian_min(x, g)[ok]
    return float((e**2).mean())


def true_errors(system, solution, ref) -> dict:
    """The errors of a solution's V(., 0) and mu(., 0) against a reference grid's V* and mu*.

    * ``system``: the control-affine system.
    * ``solution``: the learned solution.
    * ``ref``: a :class:`~pinnhjb.reference.ReferenceGrid` of V*; points that did not converge are left out.

    Returns a dict: ``value_max_error``, ``value_rmse``, ``policy_max_error``, ``policy_rmse``.
    """
    ok = np.asarray(ref.converged)
    x = ref.points[ok]
    dv = solution.value(x) - ref.value[ok]
    du = solution.policy(x) - ref.policy[ok]
    return {
        "value_max_error": float(np.abs(dv).max()),
        "value_rmse": float(np.sqrt(np.mean(dv**2))),
        "policy_max_error": float(np.abs(du).max()),
        "policy_rmse": float(np.sqrt(np.mean(du**2))),
    }


def closed_loop_metrics(system, solution, x0: np.ndarray, v_star: np.ndarray, settings: dict) -> dict:
    """The learned policy in closed loop: its cost to t = inf against V*, from every initial state.

    The cost is J to ``t_final`` plus the optimal cost still to come (:func:`pinnhjb.metrics.infinite_horizon_cost`),
    so the optimal policy scores J / V* = 1 from every state, however slowly its closed loop settles: a criterion
    the optimal policy itself passes, unlike a bound on ``abs(x(t_final))``.

    * ``system``: the control-affine system.
    * ``solution``: the learned solution.
    * ``x0``: (N, n) initial states.
    * ``v_star``: (N,), V* at ``x0``; states with V* <= 1e-6 (the origin) are left out.
    * ``settings``: ``t_final`` and ``dt`` of the runs (:data:`~pinnhjb.paper.cases.CLOSED_LOOP`).

    Returns a dict: ``cost_ratio_mean`` and ``cost_ratio_max`` (J / V*, infinite for a run that diverged),
    ``cost_within`` (the fraction of states with J / V* <= :data:`~pinnhjb.paper.cases.CONVERGED`'s bound),
    ``tail_share_max`` (the largest tail / J: small when the runs were long enough).
    """
    run = solution.closed_loop(x0, **settings)
    cost, tail = infinite_horizon_cost(system, run)
    keep = v_star > 1e-6
    ratio = cost[keep] / v_star[keep]
    with np.errstate(invalid="ignore"):
        share = np.where(np.isfinite(cost[keep]), tail[keep] / cost[keep], np.inf)
    return {
        "cost_ratio_mean": float(np.mean(ratio)),
        "cost_ratio_max": float(np.max(ratio)),
        "cost_within": float(np.mean(ratio <= CONVERGED["cost_ratio_max"])),
        "tail_share_max": float(np.max(share)),
    }


def closed_loop_states(system, ref_points: np.ndarray, per_dim: int) -> np.ndarray:
    """A coarse sub-grid of the V* reference grid, every k-th point per axis; returns the points' indices.

    * ``system``: the control-affine system.
    * ``ref_points``: the reference grid's points.
    * ``per_dim``: about how many points per axis to keep.
    """
    full = round(ref_points.shape[0] ** (1 / system.n))
    k = max(1, (full - 1) // (per_dim - 1))
    idx = np.arange(0, full, k)
    mesh = np.stack(np.meshgrid(*[idx] * system.n, indexing="ij"), -1).reshape(-1, system.n)
    flat = np.ravel_multi_index(mesh.T, (full,) * system.n)
    return flat


def closed_loop_setup(case, system, refs, mode: str) -> dict:
    """The closed-loop runs that judge a case's policies: initial states, V* there, and the run settings.

    The known V* on an 11-per-axis grid of Omega where there is one (quartic), else a sub-grid of the V*
    reference grid (11 per axis in 2-D, all 5^3 points in 3-D), without the points whose reference did not
    converge.

    * ``case``: the :class:`~pinnhjb.paper.cases.Case`.
    * ``system``: its system.
    * ``refs``: horizon -> :class:`~pinnhjb.reference.ReferenceGrid`.
    * ``mode``: ``"full"`` or ``"quick"``.

    Returns a dict: ``x0``, ``v_star`` and ``settings``, the runs' ``t_final`` and ``dt``.
    """
    if system.value_star is not None:
        x0 = system.grid(11).numpy()
        v_star = system.value_star(torch.as_tensor(x0)).numpy()
    else:
        ref = refs[INF]
        idx = closed_loop_states(system, ref.points, 11 if system.n == 2 else 5)
        idx = idx[np.asarray(ref.converged)[idx]]
        x0, v_star = ref.points[idx], ref.value[idx]
    settings = CLOSED_LOOP[mode] if mode == "quick" else CLOSED_LOOP_SYSTEM.get(case.system, CLOSED_LOOP[mode])
    return {"x0": x0, "v_star": v_star, "settings": dict(settings)}


def stage_row(system, view, refs, loop: dict | None = None) -> dict:
    """The results table's row of one horizon of a chain (or of a steady-state solution).

    * ``system``: the system.
    * ``view``: the solution up to this horizon (:meth:`~pinnhjb.solution.FiniteHorizonSolution.truncated`).
    * ``refs``: horizon -> :class:`~pinnhjb.reference.ReferenceGrid` (or None).
    * ``loop``: the :func:`closed_loop_setup` to run the policy from; None: no closed loop.

    Returns the solution's metrics with ``T``, ``E_ratio`` (E / E(V = 0)), the errors against the reference V*
    (``value_rel_error``: max abs(V - V*_ref) / max abs(V*_ref)), E of the reference V_T and the closed loop's
    :func:`closed_loop_metrics`, each where it applies.
    """
    horizon = getattr(view, "horizon", INF)
    row = {"T": horizon if horizon == INF else round(float(horizon), 9), **view.metrics}
    if row.get("E_zero"):
        row["E_ratio"] = row["E"] / row["E_zero"]
    if system.value_star is None and refs.get(INF) is not None:
        ref = refs[INF]
        row.update(true_errors(system, view, ref))
        row["value_rel_error"] = row["value_max_error"] / float(np.abs(ref.value[np.asarray(ref.converged)]).max())
    if horizon != INF and refs.get(row["T"]) is not None:
        row["E_reference_VT"] = reference_grid_residual(system, refs[row["T"]])
    if loop is not None:
        row.update(closed_loop_metrics(system, view, loop["x0"], loop["v_star"], loop["settings"]))
    return row


def converged(row: dict) -> bool:
    """Whether a :func:`stage_row` meets every bound of :data:`~pinnhjb.paper.cases.CONVERGED`."""
    return all(key in row and row[key] <= bound for key, bound in CONVERGED.items())


def first_horizons(rows: list[dict]) -> dict:
    """The first horizon of a chain's rows at which each bound of :data:`~pinnhjb.paper.cases.CONVERGED` holds.

    * ``rows``: one seed's :func:`stage_rows`, in order.

    Returns ``{key: T or None}`` for every key of ``CONVERGED``, and ``"all"``: the first T where all hold.
    """
    out = {key: next((r["T"] for r in rows if key in r and r[key] <= bound), None) for key, bound in CONVERGED.items()}
    out["all"] = next((r["T"] for r in rows if converged(r)), None)
    return out


def stage_rows(case, system, sol, refs, loop: dict) -> list[dict]:
    """The results table's rows of one trained solution, one per horizon it reached.

    * ``case``: the :class:`~pinnhjb.paper.cases.Case`.
    * ``system``: its system.
    * ``sol``: the trained solution.
    * ``refs``: horizon -> :class:`~pinnhjb.reference.ReferenceGrid` (or None).
    * ``loop``: the :func:`closed_loop_setup`; the final policy is run from it (every horizon's, for a case
      extended ``until`` it converges).
    """
    if case.kind == "steady":
        return [stage_row(system, sol, refs, loop)]
    k_last = len(sol.stages)
    return [
        stage_row(system, sol.truncated(k), refs, loop if (case.until or k == k_last) else None)
        for k in range(1, k_last + 1)
    ]
