"""Theorem 3 on a trained model: a known error injected into the terminal cost of one extension stage.

On the quartic system V* is known and is a fixed point of the extension: with terminal cost V* the exact
extended value is V* again, with policy mu*. One extension stage of length ``delta = T' - T`` trained with the
perturbed terminal cost ``V* + e`` (``e`` a known function) is then bounded point by point by the error bound
:eq:`eq-error-bound`::

    abs(V_hat_T'(x0, 0) - V*(x0)) <= max(abs(e(x_T'(delta))), abs(e(x_hat_T'(delta)))),

where ``x_T'`` follows mu* and ``x_hat_T'`` the stage's own time-varying learned policy. A trained stage also
has its own network error; the stage trained with ``e = 0`` measures it.

``python -m pinnhjb.paper.theorem3 [--out artifacts/theorem3]`` trains the stages of :data:`ERRORS` (seeded,
fixed step counts, about 20 s each on two CPU cores) and stores them; the terminal cost is code, so a
checkpoint stores it by name and :func:`load` passes the same function back.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from ..config import TrainConfig
from ..metrics import closed_loop
from ..pinn import CallableTerminalCost
from ..solution import FiniteHorizonSolution
from ..solver import FiniteHorizonSolver
from ..storage import load as _load
from ..storage import save as _save
from ..systems import quartic
from .artifacts import artifacts_dir

__all__ = [
    "ERRORS",
    "FORMULAS",
    "DELTA",
    "SEED",
    "config",
    "terminal_cost",
    "train",
    "save",
    "load",
    "path",
    "rollout",
    "bound_check",
    "summary",
    "exact_stage",
    "load_exact",
]

Tensor = torch.Tensor

#: The injected terminal errors e(x): none (the control), one with e(0) = 0, the same plus a constant.
#:
#: :meta hide-value:
ERRORS: dict[str, Callable[[Tensor], Tensor]] = {
    "none": lambda x: torch.zeros(x.shape[0], dtype=x.dtype, device=x.device),
    "vanishing": lambda x: 0.3 * (x[:, 0] ** 2 - x[:, 1] ** 2),
    "offset": lambda x: 0.3 * (x[:, 0] ** 2 - x[:, 1] ** 2) + 0.2,
}
#: Each error's formula, as the checkpoints name it.
FORMULAS = {"none": "e(x) = 0", "vanishing": "e(x) = 0.3 (x1^2 - x2^2)", "offset": "e(x) = 0.3 (x1^2 - x2^2) + 0.2"}
#: The extension's length T' - T.
DELTA = 1.0
#: The training seed.
SEED = 0
DEFAULT_DIR = Path("artifacts") / "theorem3"


def config() -> TrainConfig:
    """The recipe: one stage of the default recipe (seeded, no wall-clock stop), evaluated on a 41 x 41 grid."""
    return TrainConfig.preset("default", eval_points_per_dim=41)


def terminal_cost(error: str) -> CallableTerminalCost:
    """The terminal cost ``phi = V* + e``: the exact V_T (V*, a fixed point of the extension) with an error.

    * ``error``: a key of :data:`ERRORS`.
    """
    system, e = quartic(), ERRORS[error]
    return CallableTerminalCost(lambda x: system.value_star(x) + e(x), name=f"V*(x) + {FORMULAS[error]}")


def train(error: str, seed: int = SEED, delta: float = DELTA, progress: bool = False) -> FiniteHorizonSolution:
    """Train one extension stage with terminal cost V* + e, on the CPU, in the recipe of :func:`config`.

    * ``error``: a key of :data:`ERRORS`.
    * ``seed``: the training seed.
    * ``delta``: the stage's length.
    * ``progress``: show a progress bar.
    """
    if error not in ERRORS:
        raise KeyError(f"unknown error {error!r}; choose one of {sorted(ERRORS)}")
    solver = FiniteHorizonSolver(quartic(), config=config(), seed=seed, device="cpu", progress=progress)
    return solver.solve(horizon=delta, terminal_cost=terminal_cost(error))


def path(error: str, out: Path | None = None) -> Path:
    """The checkpoint of an error's stage: ``<out>/quartic_<error>.pt``; ``out`` None: the artifacts' theorem3."""
    if out is None:
        out = artifacts_dir() / "theorem3"
    return Path(out) / f"quartic_{error}.pt"


def save(sol: FiniteHorizonSolution, error: str, out: Path | None = None, **extra) -> Path:
    """Store a stage's networks and metrics; the terminal cost V* + e is stored by name (see :func:`load`).

    * ``sol``: the trained stage.
    * ``error``: its key of :data:`ERRORS`.
    * ``out``: the folder, as in :func:`path`.
    * ``extra``: added to the provenance record.
    """
    return _save(
        sol,
        path(error, out),
        seed=sol.stages[0].seed,
        case="theorem3",
        theorem3_error=error,
        theorem3_terminal=f"V*(x) + {FORMULAS[error]}",
        theorem3_delta=sol.horizon,
        **extra,
    )


def load(error: str, out: Path | None = None) -> FiniteHorizonSolution:
    """A stored stage with its terminal cost V* + e re-attached; ``error`` and ``out`` as in :func:`path`."""
    return _load(path(error, out), device="cpu", terminal_cost=terminal_cost(error))


def rollout(system, policy: Callable[[Tensor, float], Tensor], x0, t_final: float, dt: float = 0.01) -> np.ndarray:
    """The end states (N, n) at ``t_final`` under a time-varying policy, by :func:`pinnhjb.metrics.closed_loop`.

    * ``system``: the control-affine system.
    * ``policy``: ``(x, t) -> u``.
    * ``x0``: (N, n) initial states.
    * ``t_final``: the end time.
    * ``dt``: the RK4 step.
    """
    return closed_loop(system, policy, x0, t_final=t_final, dt=dt, time_varying=True).x[-1]


def bound_check(sol: FiniteHorizonSolution, error: str, points_per_dim: int = 21, dt: float = 0.01) -> dict:
    """Both sides of the error bound :eq:`eq-error-bound` on a grid over Omega, for a stage trained with V* + e.

    * ``sol``: the trained stage.
    * ``error``: its key of :data:`ERRORS`.
    * ``points_per_dim``: grid points along each axis.
    * ``dt``: the RK4 step of the closed loops.

    Returns a dict of arrays over the grid:

    * ``x0``: the grid.
    * ``error``: ``abs(V_hat_T'(x0, 0) - V*(x0))`` (the exact V_T' is V*).
    * ``bound``: ``max(abs(e(x_T'(delta))), abs(e(x_hat_T'(delta))))``, with x_T' under mu* and x_hat_T' under
      the stage's learned policy.
    * ``e_start``: ``abs(e(x0))``, the error before the extension.
    """
    system, e = sol.system, ERRORS[error]
    x0 = system.grid(points_per_dim).numpy()
    delta = sol.horizon
    ends_opt = rollout(system, lambda x, t: system.policy_star(x), x0, delta, dt)
    ends_hat = rollout(system, lambda x, t: sol.policy(x, t), x0, delta, dt)
    err = np.abs(sol.value(x0) - system.value_star(torch.as_tensor(x0)).numpy())
    with torch.no_grad():
        bound = np.maximum(np.abs(e(torch.as_tensor(ends_opt)).numpy()), np.abs(e(torch.as_tensor(ends_hat)).numpy()))
        e_start = np.abs(e(torch.as_tensor(x0)).numpy())
    return {"x0": x0, "error": err, "bound": bound, "e_start": e_start}


def summary(check: dict, network_error: float) -> dict:
    """Scalars of a :func:`bound_check`.

    * ``check``: the result of :func:`bound_check`.
    * ``network_error``: the stage's own network error (the largest error of the ``e = 0`` stage).

    Returns a dict: the largest error, the largest bound, the largest ``abs(e)`` before the extension, the
    fraction of points where the bound alone holds, and whether bound + ``network_error`` holds everywhere.
    """
    err, bound = check["error"], check["bound"]
    return {
        "max_error": float(err.max()),
        "max_bound": float(bound.max()),
        "max_e_start": float(check["e_start"].max()),
        "fraction_within_bound": float(np.mean(err <= bound)),
        "within_bound_plus_network": bool(np.all(err <= bound + network_error)),
    }


def exact_stage(error: str, points_per_dim: int = 21, delta: float = DELTA, tol: float = 1e-8) -> dict:
    """The exact perturbed extension on the grid, independent of any network.

    Per-point Pontryagin BVPs (:func:`pinnhjb.reference.solve_point`) with terminal cost V* + e.

    * ``error``: a key of :data:`ERRORS`.
    * ``points_per_dim``: grid points along each axis.
    * ``delta``: the stage's length.
    * ``tol``: the BVP tolerance.

    Returns a dict of arrays: ``x0``; ``value``, the exact V_hat_T'(x0, 0); ``end``, x_hat_T'(delta) on the
    exact perturbed optimal trajectory; ``end_opt``, x_T'(delta) under mu*; ``converged``.
    """
    import warnings

    from ..reference import solve_point

    system = quartic()
    phi = terminal_cost(error)
    x0 = system.grid(points_per_dim).numpy()
    value, end, ok = np.full(len(x0), np.nan), np.full_like(x0, np.nan), np.zeros(len(x0), dtype=bool)
    order = np.argsort(np.linalg.norm(x0, axis=1), kind="stable")  # from the origin out, each point warm-started
    solved: dict[int, dict] = {}  # from its nearest solved neighbour
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for k in order:
            near = min(solved, key=lambda j: np.linalg.norm(x0[j] - x0[k])) if solved else None
            res = solve_point(
                system, x0[k], horizon=delta, terminal_cost=phi, tol=tol, guess=None if near is None else solved[near]
            )
            if res["converged"]:
                value[k], end[k], ok[k] = res["value"], res["solution"].sol(delta)[: system.n], True
                solved[k] = res
    end_opt = rollout(system, lambda x, t: system.policy_star(x), x0, delta, dt=0.001)
    return {"x0": x0, "value": value, "end": end, "end_opt": end_opt, "converged": ok}


def exact_path(error: str, out: Path | None = None) -> Path:
    """Where :func:`exact_stage`'s arrays are stored; arguments as in :func:`path`."""
    return path(error, out).with_name(f"quartic_{error}_exact.npz")


def load_exact(error: str, out: Path | None = None) -> dict:
    """The stored :func:`exact_stage` arrays; arguments as in :func:`path`."""
    with np.load(exact_path(error, out)) as data:
        return {k: data[k] for k in data.files}


def main(argv=None):
    parser = argparse.ArgumentParser(description="Train and store the Theorem 3 stages on the quartic system.")
    parser.add_argument("--out", type=Path, default=DEFAULT_DIR)
    parser.add_argument("--exact-only", action="store_true", help="only (re)compute the exact BVP grids")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    Path(args.out).mkdir(parents=True, exist_ok=True)
    for error in ERRORS:
        ex = exact_stage(error)
        np.savez(exact_path(error, args.out), **ex)
        print(f"{error:9s} exact: {int(ex['converged'].sum())}/{len(ex['x0'])} points converged", flush=True)
    for error in [] if args.exact_only else ERRORS:
        sol = train(error, progress=False)
        check = bound_check(sol, error)
        stored = {k: v for k, v in summary(check, 0.0).items() if k != "within_bound_plus_network"}
        p = save(sol, error, args.out, evaluation=stored)
        print(
            f"{error:9s} -> {p}: wall {sol.wall_time:.1f} s, E = {sol.metrics['E']:.2e}, "
            f"max|V-V*| = {sol.metrics['value_max_error']:.3e}, max bound = {check['bound'].max():.3e}",
            flush=True,
        )


if __name__ == "__main__":
    main()
