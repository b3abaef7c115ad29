"""Checkpoints: a solved model with its system, configuration, seed, versions, wall time and metrics.

Writes are atomic (a temporary file in the same folder, then ``os.replace``); loads use
``torch.load(..., weights_only=True)`` so a checkpoint cannot run code. Loading into a system or an
architecture that does not match fails with a message saying what differs.
"""
from __future__ import annotations

import datetime as _dt
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from .config import TrainConfig
from .pinn import FiniteHorizonValue, QuadraticTerminalCost, SteadyStateValue, ValueTerminalCost, ZeroTerminalCost
from .solution import FiniteHorizonSolution, Stage, SteadyStateSolution
from .systems import get_system
from .training import DTYPES, TrainHistory, resolve_device

FORMAT = "pinnhjb-checkpoint"
FORMAT_VERSION = 1

__all__ = ["save", "load", "provenance", "CheckpointError"]


class CheckpointError(ValueError):
    """A checkpoint that cannot be read, or that does not match the system or architecture asked for."""


def provenance(**extra) -> dict:
    """Versions and time stamp recorded with every artifact."""
    from . import __version__

    info = {"pinnhjb": __version__, "torch": str(torch.__version__), "numpy": np.__version__,
            "python": platform.python_version(), "platform": platform.platform(),
            "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
            "command": " ".join(sys.argv)}
    info.update(extra)
    return info


def _atomic_torch_save(obj, path: Path):
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            torch.save(obj, fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _plain(d: dict) -> dict:
    """Metrics as plain floats/ints/strings/bools (what weights_only loading accepts)."""
    out = {}
    for k, v in d.items():
        if isinstance(v, (np.floating, np.integer)):
            v = v.item()
        out[k] = v
    return out


def _state(model) -> dict:
    return {k: v.detach().cpu() for k, v in model.net.state_dict().items()}


def save(solution, path, **extra) -> Path:
    """Save a :class:`FiniteHorizonSolution` or :class:`SteadyStateSolution` to ``path`` (atomic).

    A user's own system (not in the registry) is stored by name and dimensions only; pass it to
    :func:`load` again. ``extra`` key/values are added to the provenance record."""
    if not isinstance(solution, (FiniteHorizonSolution, SteadyStateSolution)):
        raise TypeError(f"cannot save a {type(solution).__name__}")
    path = Path(path)
    spec = solution.system.spec()
    base = {"format": FORMAT, "version": FORMAT_VERSION, "system": spec, "config": solution.config.to_dict(),
            "dtype": str(solution.dtype).replace("torch.", ""), "provenance": provenance(**extra)}
    if isinstance(solution, FiniteHorizonSolution):
        if solution.terminal_spec.get("kind") == "callable":
            raise CheckpointError("a solution whose first terminal cost is a Python callable cannot be saved; "
                                  "use a matrix (x'Px), zero, or CallableTerminalCost(fn, name=...)")
        base.update(kind="finite_horizon", terminal=solution.terminal_spec, interrupted=solution.interrupted,
                    wall_time=solution.wall_time,
                    stages=[{"start": s.start, "length": s.length, "seed": s.seed, "state": _state(s.model),
                             "history": s.history.to_dict(), "metrics": _plain(s.metrics)}
                            for s in solution.stages])
    else:
        base.update(kind="steady_state", seed=solution.seed, state=_state(solution.model),
                    history=solution.history.to_dict(), metrics=_plain(solution.metrics),
                    wall_time=solution.wall_time)
    _atomic_torch_save(base, path)
    return path


def _check_system(ckpt: dict, system):
    spec = ckpt["system"]
    if system is None:
        if not spec.get("builder"):
            raise CheckpointError(f"checkpoint was trained on user system '{spec['name']}': pass system= to load()")
        return get_system(spec["builder"], **(spec["params"] or {}))
    mine = system.spec()
    if (mine["n"], mine["m"]) != (spec["n"], spec["m"]):
        raise CheckpointError(f"checkpoint is for system '{spec['name']}' with n={spec['n']}, m={spec['m']}; "
                              f"the system given has n={mine['n']}, m={mine['m']}")
    if spec.get("builder") and (mine["builder"], mine["params"]) != (spec["builder"], spec["params"]):
        raise CheckpointError(f"checkpoint is for system {spec['builder']}({spec['params']}); the system given is "
                              f"{mine['builder'] or mine['name']}({mine['params']})")
    return system


def _load_state(model, state: dict, what: str):
    try:
        model.net.load_state_dict(state)
    except RuntimeError as exc:
        raise CheckpointError(f"{what}: the stored weights do not fit the architecture in the checkpoint's "
                              f"config: {exc}") from exc


def _terminal(term: dict, given, path):
    """The first stage's terminal cost from its stored spec (and the caller's function for a named one)."""
    if term["kind"] == "named":
        if given is None or getattr(given, "name", None) != term["name"]:
            raise CheckpointError(f"{path} was trained with the terminal cost {term['name']!r}, which is code: pass "
                                  f"terminal_cost=CallableTerminalCost(fn, name={term['name']!r})")
        return given
    if given is not None:
        raise CheckpointError(f"{path} stores its own terminal cost ({term['kind']}); do not pass terminal_cost")
    return QuadraticTerminalCost(term["P"]) if term["kind"] == "quadratic" else ZeroTerminalCost()


def load(path, system=None, device=None, config: TrainConfig | None = None, terminal_cost=None):
    """Load a solution saved by :func:`save`. ``system`` is rebuilt from the registry when omitted (and
    checked against the checkpoint when given); ``config``, if given, must match the stored architecture.
    ``terminal_cost`` (a :class:`~pinnhjb.pinn.CallableTerminalCost` of the same name) is required for, and
    only for, a checkpoint saved with a named callable terminal cost."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint at {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001
        raise CheckpointError(f"{path} is not a readable pinnhjb checkpoint: {exc}") from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a pinnhjb checkpoint")
    if ckpt.get("version") != FORMAT_VERSION:
        raise CheckpointError(f"{path} has checkpoint format version {ckpt.get('version')}; this pinnhjb reads "
                              f"version {FORMAT_VERSION}")
    system = _check_system(ckpt, system)
    stored = TrainConfig.from_dict(ckpt["config"])
    if config is not None:
        arch = ("width", "depth", "activation", "ansatz")
        diff = {k: (getattr(stored, k), getattr(config, k)) for k in arch if getattr(stored, k) != getattr(config, k)}
        if diff:
            raise CheckpointError(f"architecture mismatch (stored, requested): {diff}")
    dev = resolve_device(device)
    dtype = DTYPES[ckpt["dtype"]]
    net_kw = dict(width=stored.width, depth=stored.depth, activation=stored.activation, ansatz=stored.ansatz)

    if ckpt["kind"] == "steady_state":
        model = SteadyStateValue(system.n, system.train_domain, **net_kw).to(dev, dtype)
        _load_state(model, ckpt["state"], "steady-state model")
        model = model.eval().requires_grad_(False)
        sol = SteadyStateSolution(system, stored, model, TrainHistory.from_dict(ckpt["history"]), ckpt["seed"],
                                  ckpt["metrics"])
    else:
        term = ckpt["terminal"]
        terminal = _terminal(term, terminal_cost, path)
        stages: list[Stage] = []
        for i, st in enumerate(ckpt["stages"]):
            phi = terminal if i == 0 else ValueTerminalCost(stages[-1].model)
            model = FiniteHorizonValue(system.n, st["length"], system.train_domain, phi, **net_kw).to(dev, dtype)
            _load_state(model, st["state"], f"stage {i + 1}")
            model = model.eval().requires_grad_(False)
            stages.append(Stage(model=model, start=st["start"], history=TrainHistory.from_dict(st["history"]),
                                seed=st["seed"], metrics=st["metrics"]))
        sol = FiniteHorizonSolution(system, stored, stages, term, interrupted=ckpt.get("interrupted", False))
    sol.provenance = ckpt["provenance"]
    return sol
