"""One trained case measured against its reference: E of the reference V_T, true errors of V and mu, and the
closed-loop cost of the learned policy, per horizon of a chain."""

from __future__ import annotations

import numpy as np
import torch

from .cases import CLOSED_LOOP, CLOSED_LOOP_SYSTEM, INF

__all__ = ["reference_grid_residual", "true_errors", "closed_loop_metrics", "closed_loop_states", "stage_rows"]


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
    """The learned policy in closed loop: the fraction stabilized, and its cost against V* where it stabilized.

    * ``system``: the control-affine system.
    * ``solution``: the learned solution.
    * ``x0``: (N, n) initial states.
    * ``v_star``: (N,), V* at ``x0``.
    * ``settings``: ``t_final`` and ``dt`` of the runs (:data:`~pinnhjb.paper.cases.CLOSED_LOOP`).

    Returns a dict: ``fraction_stabilized``, ``suboptimality_mean``, ``suboptimality_max`` (J / V*).
    """
    run = solution.closed_loop(x0, **settings)
    keep = (v_star > 1e-6) & run.stabilized  # a truncated cost of a run that did not settle says nothing
    ratio = run.cost[keep] / v_star[keep]
    finite = np.isfinite(ratio)
    return {
        "fraction_stabilized": run.fraction_stabilized,
        "suboptimality_mean": float(np.mean(ratio[finite])) if finite.any() else float("nan"),
        "suboptimality_max": float(np.max(ratio[finite])) if finite.any() else float("nan"),
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


def stage_rows(case, system, sol, refs, x0_idx, mode: str) -> list[dict]:
    """The results table's rows of one trained solution, one per horizon.

    * ``case``: the :class:`~pinnhjb.paper.cases.Case`.
    * ``system``: its system.
    * ``sol``: the trained solution.
    * ``refs``: horizon -> :class:`~pinnhjb.reference.ReferenceGrid` (or None).
    * ``x0_idx``: the closed loop's initial states, indices into the V* reference grid.
    * ``mode``: ``"full"`` or ``"quick"``.
    """
    rows = []
    views = [(INF, sol)] if case.kind == "steady" else [(h, sol.truncated(k + 1)) for k, h in enumerate(case.horizons)]
    for horizon, view in views:
        row = {"T": horizon, **{k: v for k, v in view.metrics.items()}}
        if system.value_star is None and refs.get(INF) is not None:
            row.update(true_errors(system, view, refs[INF]))
        if refs.get(horizon) is not None and horizon != INF:
            row["E_reference_VT"] = reference_grid_residual(system, refs[horizon])
        rows.append(row)
    # closed loop of the final policy only
    if system.value_star is not None:
        x0 = system.grid(11).numpy()
        v_star = system.value_star(torch.as_tensor(x0)).numpy()
    else:
        ref = refs[INF]
        x0, v_star = ref.points[x0_idx], ref.value[x0_idx]
    settings = CLOSED_LOOP[mode] if mode == "quick" else CLOSED_LOOP_SYSTEM.get(case.system, CLOSED_LOOP[mode])
    rows[-1].update(closed_loop_metrics(system, sol, x0, v_star, settings))
    return rows
