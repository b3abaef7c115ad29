"""Checkpoints: a solved model with its system, configuration, seed, versions, wall time and metrics.

Writes are atomic and loads cannot run code (``torch.load(..., weights_only=True)``). Every checkpoint stores
the system's :meth:`~pinnhjb.systems.ControlAffineSystem.fingerprint`, and :func:`load` refuses a system or an
architecture that does not match, saying what differs; a checkpoint without a fingerprint is matched by
registry name and parameters (a built-in) or by n and m (a user's system). A file with missing keys, non-finite
weights or stages that do not chain is a :class:`CheckpointError`.

Test-only switch: the environment variable ``PINNHJB_PERTURB_WEIGHTS``, a relative size eps such as ``1e-13``,
makes :func:`load` multiply every weight and bias w by ``1 + eps * z``, z standard normal from a fixed seed
(the same on every load and machine). The notebook tests run a second time under it, to show that their
printed outputs do not depend on rounding (another CPU, another BLAS). Unset or empty: weights load exactly.
"""

from __future__ import annotations

import datetime as _dt
import math
import os
import platform
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

from .config import TrainConfig
from .pinn import FiniteHorizonValue, QuadraticTerminalCost, SteadyStateValue, ValueTerminalCost, ZeroTerminalCost
from .solution import AveragedSolution, FiniteHorizonSolution, Stage, SteadyStateSolution
from .systems import fingerprint_difference, fingerprint_summary, get_system
from .training import DTYPES, TrainHistory, resolve_device

FORMAT = "pinnhjb-checkpoint"
FORMAT_VERSION = 1

__all__ = ["save", "load", "provenance", "CheckpointError"]


class CheckpointError(ValueError):
    """A checkpoint that cannot be read, or that does not match the system or architecture asked for."""


def provenance(**extra) -> dict:
    """The versions and time stamp recorded with every artifact; ``extra`` key/values are added."""
    from . import __version__

    info = {
        "pinnhjb": __version__,
        "torch": str(torch.__version__),
        "numpy": np.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join(sys.argv),
    }
    info.update(extra)
    return info


PERTURB_ENV = "PINNHJB_PERTURB_WEIGHTS"
PERTURB_SEED = 20261201


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _atomic_torch_save(obj, path: Path):
    if path.is_dir():
        raise IsADirectoryError(f"cannot save a checkpoint to {path}: it is an existing folder; give a file path")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            torch.save(obj, fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600: give the file a new file's usual permissions
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    for stale in path.parent.glob(glob_escape(path.name) + ".*.tmp"):  # left by a killed save of this path
        try:
            stale.unlink()
        except OSError:
            pass


def glob_escape(name: str) -> str:
    """``name`` with glob's special characters escaped."""
    import glob

    return glob.escape(name)


def _plain(d: dict) -> dict:
    """Metrics as plain floats/ints/strings/bools (what weights_only loading accepts)."""
    out = {}
    for k, v in d.items():
        if isinstance(v, (np.floating, np.integer)):
            v = v.item()
        elif isinstance(v, dict):
            v = _plain(v)
        out[k] = v
    return out


def _state(model) -> dict:
    return {k: v.detach().cpu() for k, v in model.net.state_dict().items()}


def save(solution, path, **extra) -> Path:
    """Save a solution to a checkpoint file, atomically.

    A temporary file in the same folder is renamed into place; it gets the permissions the umask gives a new
    file, and temporary files that a killed save of the same path left behind are removed.

    * ``solution``: a :class:`~pinnhjb.solution.FiniteHorizonSolution` or
      :class:`~pinnhjb.solution.SteadyStateSolution`.
    * ``path``: the file to write.
    * ``extra``: key/values added to the provenance record.

    Returns the path. A user's own system (not in the registry) is stored by name and dimensions only: pass it
    to :func:`load` again.
    """
    if not isinstance(solution, (FiniteHorizonSolution, SteadyStateSolution)):
        members = " (save its members one by one)" if isinstance(solution, AveragedSolution) else ""
        raise TypeError(f"cannot save a {type(solution).__name__}{members}")
    path = Path(path)
    spec = solution.system.spec()
    base = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "system": spec,
        "fingerprint": solution.system.fingerprint(),
        "config": solution.config.to_dict(),
        "dtype": str(solution.dtype).replace("torch.", ""),
        "provenance": provenance(**extra),
    }
    if isinstance(solution, FiniteHorizonSolution):
        if solution.terminal_spec.get("kind") == "callable":
            raise CheckpointError(
                "a solution whose first terminal cost is a Python callable cannot be saved; "
                "use a matrix (x'Px), zero, or CallableTerminalCost(fn, name=...)"
            )
        base.update(
            kind="finite_horizon",
            terminal=solution.terminal_spec,
            interrupted=solution.interrupted,
            wall_time=solution.wall_time,
            stages=[
                {
                    "start": s.start,
                    "length": s.length,
                    "seed": s.seed,
                    "state": _state(s.model),
                    "history": s.history.to_dict(),
                    "metrics": _plain(s.metrics),
                    **({"rejected": [_plain(a) for a in s.rejected]} if s.rejected else {}),
                }
                for s in solution.stages
            ],
        )
    else:
        base.update(
            kind="steady_state",
            seed=solution.seed,
            state=_state(solution.model),
            history=solution.history.to_dict(),
            metrics=_plain(solution.metrics),
            wall_time=solution.wall_time,
        )
    _atomic_torch_save(base, path)
    return path


def _check_system(ckpt: dict, system, path=None):
    spec = ckpt["system"]
    _require(spec, ("name", "n", "m"), "system", path)
    stored_fp = ckpt.get("fingerprint")
    if system is None:
        if not spec.get("builder"):
            raise CheckpointError(f"checkpoint was trained on user system '{spec['name']}': pass system= to load()")
        params = dict(spec.get("params") or {})
        if spec["builder"] == "lq" and stored_fp is None and params.get("train_domain", 0) is None:
            params["train_domain"] = params.get("domain")  # no fingerprint, train_domain None: it trained on Omega
        try:
            system = get_system(spec["builder"], **params)
        except Exception as exc:  # noqa: BLE001 - re-raised with context
            raise CheckpointError(f"{path}: cannot rebuild its system {spec['builder']}({params}): {exc}") from exc
        _check_fingerprint(stored_fp, system, path)
        return system
    mine = system.spec()
    if (mine["n"], mine["m"]) != (spec["n"], spec["m"]):
        raise CheckpointError(
            f"checkpoint is for system '{spec['name']}' with n={spec['n']}, m={spec['m']}; "
            f"the system given has n={mine['n']}, m={mine['m']}"
        )
    if spec.get("builder") and (mine["builder"], mine["params"]) != (spec["builder"], spec["params"]):
        raise CheckpointError(
            f"checkpoint is for system {spec['builder']}({spec['params']}); the system given is "
            f"{mine['builder'] or mine['name']}({mine['params']})"
        )
    _check_fingerprint(stored_fp, system, path)
    return system


def _check_fingerprint(stored: dict | None, system, path):
    """Refuse a system whose fingerprint differs from the stored one (none stored: no check)."""
    if stored is None:
        return
    current = system.fingerprint()
    try:
        diffs = fingerprint_difference(stored, current)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: its stored system fingerprint is malformed: {exc}") from exc
    if diffs:
        raise CheckpointError(
            f"{path} was trained on another system: the fingerprints differ in {diffs}.\n"
            f"  stored in the checkpoint: {fingerprint_summary(stored)}\n"
            f"  system given/rebuilt:     {fingerprint_summary(current)}\n"
            f"Pass the system the checkpoint was trained on (same name, R, boxes, f, g, Q)."
        )


def _require(d, keys, where: str, path):
    if not isinstance(d, dict):
        raise CheckpointError(f"{path}: '{where}' should be a dict; got {type(d).__name__}")
    missing = [k for k in keys if k not in d]
    if missing:
        raise CheckpointError(f"{path}: the checkpoint is incomplete: '{where}' lacks the key(s) {missing}")


def _perturbation() -> float | None:
    """eps of the test-only switch ``PINNHJB_PERTURB_WEIGHTS`` (see the module docstring); None when unset."""
    raw = os.environ.get(PERTURB_ENV, "").strip()
    if not raw:
        return None
    try:
        eps = float(raw)
    except ValueError:
        raise ValueError(f"{PERTURB_ENV} must be a relative size such as 1e-13; got {raw!r}") from None
    if not math.isfinite(eps) or eps < 0:
        raise ValueError(f"{PERTURB_ENV} must be a finite size >= 0 such as 1e-13; got {raw!r}")
    return eps


def _checked_state(state, what: str, path, perturb: tuple | None) -> dict:
    """The stored weights, checked finite, and perturbed when the test-only switch is set."""
    if not isinstance(state, dict) or not all(isinstance(v, torch.Tensor) for v in state.values()):
        raise CheckpointError(f"{path}: {what}: the stored weights are not a dict of tensors")
    for key, value in state.items():
        if value.is_floating_point() and not torch.isfinite(value).all():
            raise CheckpointError(f"{path}: {what}: the stored weight '{key}' holds NaN or infinite values")
    if perturb is None:
        return state
    eps, gen = perturb
    out = {}
    for key, value in state.items():
        if value.is_floating_point():
            z = torch.randn(value.shape, generator=gen, dtype=torch.float64)
            value = (value.double() * (1.0 + eps * z)).to(value.dtype)
        out[key] = value
    return out


def _check_stages(stages, path):
    """Every stage has its keys, a positive finite length, and starts where the previous one ended (0 first)."""
    if not isinstance(stages, list) or not stages:
        raise CheckpointError(f"{path}: the checkpoint holds no stages")
    end = 0.0
    for i, st in enumerate(stages):
        _require(st, ("start", "length", "seed", "state", "history", "metrics"), f"stages[{i}]", path)
        try:
            start, length = float(st["start"]), float(st["length"])
        except (TypeError, ValueError):
            raise CheckpointError(
                f"{path}: stage {i + 1} has a non-numeric start or length: {st['start']!r}, {st['length']!r}"
            ) from None
        if not (math.isfinite(length) and length > 0):
            raise CheckpointError(f"{path}: stage {i + 1} has length {length!r}; expected a positive finite number")
        if not abs(start - end) <= 1e-9 * max(1.0, abs(end)):
            raise CheckpointError(
                f"{path}: stage starts are inconsistent: stage {i + 1} starts at T={start:g}, but "
                f"the stages before it end at T={end:g}"
            )
        end = start + length


def _history(d, what: str, path) -> TrainHistory:
    try:
        return TrainHistory.from_dict(d)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: {what}: the stored training history is malformed: {exc}") from exc


def _metrics(d, what: str, path) -> dict:
    if not isinstance(d, dict):
        raise CheckpointError(f"{path}: {what}: the stored metrics should be a dict; got {type(d).__name__}")
    return d


def _load_state(model, state: dict, what: str):
    try:
        model.net.load_state_dict(state)
    except RuntimeError as exc:
        raise CheckpointError(
            f"{what}: the stored weights do not fit the architecture in the checkpoint's config: {exc}"
        ) from exc


def _terminal(term: dict, given, path):
    """The first stage's terminal cost from its stored spec (and the caller's function for a named one)."""
    if term["kind"] == "named":
        if given is None or getattr(given, "name", None) != term["name"]:
            raise CheckpointError(
                f"{path} was trained with the terminal cost {term['name']!r}, which is code: pass "
                f"terminal_cost=CallableTerminalCost(fn, name={term['name']!r})"
            )
        return given
    if given is not None:
        raise CheckpointError(f"{path} stores its own terminal cost ({term['kind']}); do not pass terminal_cost")
    return QuadraticTerminalCost(term["P"]) if term["kind"] == "quadratic" else ZeroTerminalCost()


def load(path, system=None, device=None, config: TrainConfig | None = None, terminal_cost=None):
    """Load a solution saved by :func:`save`.

    * ``path``: the checkpoint file.
    * ``system``: the system it was trained on, checked against the stored fingerprint; None: rebuilt from the
      registry (built-ins only).
    * ``device``: where the networks go; None: CUDA when present.
    * ``config``: a :class:`~pinnhjb.config.TrainConfig` that must match the stored architecture; None: the
      stored one.
    * ``terminal_cost``: a :class:`~pinnhjb.pinn.CallableTerminalCost` of the same name; required for, and only
      for, a checkpoint saved with a named callable terminal cost.

    Returns the solution; its ``metrics`` are the stored ones (not recomputed) and its ``provenance`` is the
    checkpoint's record.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint at {path}")
    if path.is_dir():
        raise CheckpointError(f"{path} is a folder, not a checkpoint file")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001
        raise CheckpointError(f"{path} is not a readable pinnhjb checkpoint: {exc}") from exc
    if not isinstance(ckpt, dict) or ckpt.get("format") != FORMAT:
        raise CheckpointError(f"{path} is not a pinnhjb checkpoint")
    if ckpt.get("version") != FORMAT_VERSION:
        raise CheckpointError(
            f"{path} has checkpoint format version {ckpt.get('version')}; this pinnhjb reads version {FORMAT_VERSION}"
        )
    _require(ckpt, ("system", "config", "dtype", "kind", "provenance"), "checkpoint", path)
    kind = ckpt["kind"]
    if kind not in ("steady_state", "finite_horizon"):
        raise CheckpointError(f"{path}: unknown checkpoint kind {kind!r}; expected 'finite_horizon' or 'steady_state'")
    _require(
        ckpt,
        ("seed", "state", "history", "metrics") if kind == "steady_state" else ("terminal", "stages"),
        "checkpoint",
        path,
    )
    if ckpt["dtype"] not in DTYPES:
        raise CheckpointError(f"{path}: unknown dtype {ckpt['dtype']!r}; expected one of {sorted(DTYPES)}")
    if kind == "finite_horizon":
        _check_stages(ckpt["stages"], path)
    system = _check_system(ckpt, system, path)
    try:
        stored = TrainConfig.from_dict(ckpt["config"])
    except (TypeError, ValueError) as exc:
        raise CheckpointError(f"{path}: its stored config is not valid: {exc}") from exc
    if config is not None:
        arch = ("width", "depth", "activation", "ansatz", "flat_origin")
        diff = {k: (getattr(stored, k), getattr(config, k)) for k in arch if getattr(stored, k) != getattr(config, k)}
        if diff:
            raise CheckpointError(f"architecture mismatch (stored, requested): {diff}")
    dev = resolve_device(device)
    dtype = DTYPES[ckpt["dtype"]]
    net_kw = dict(width=stored.width, depth=stored.depth, activation=stored.activation, ansatz=stored.ansatz)
    fin_kw = dict(net_kw, flat_origin=stored.flat_origin)

    eps = _perturbation()
    perturb = None if eps is None else (eps, torch.Generator().manual_seed(PERTURB_SEED))
    if kind == "steady_state":
        model = SteadyStateValue(system.n, system.train_domain, **net_kw).to(dev, dtype)
        _load_state(model, _checked_state(ckpt["state"], "steady-state model", path, perturb), "steady-state model")
        model = model.eval().requires_grad_(False)
        sol = SteadyStateSolution(
            system,
            stored,
            model,
            _history(ckpt["history"], "history", path),
            ckpt["seed"],
            _metrics(ckpt["metrics"], "metrics", path),
            provenance=ckpt["provenance"],
        )
    else:
        term = ckpt["terminal"]
        _require(term, ("kind",), "terminal", path)
        terminal = _terminal(term, terminal_cost, path)
        stages: list[Stage] = []
        for i, st in enumerate(ckpt["stages"]):
            phi = terminal if i == 0 else ValueTerminalCost(stages[-1].model)
            model = FiniteHorizonValue(system.n, st["length"], system.train_domain, phi, **fin_kw).to(dev, dtype)
            _load_state(model, _checked_state(st["state"], f"stage {i + 1}", path, perturb), f"stage {i + 1}")
            model = model.eval().requires_grad_(False)
            stages.append(
                Stage(
                    model=model,
                    start=st["start"],
                    history=_history(st["history"], f"stage {i + 1}", path),
                    seed=st["seed"],
                    metrics=_metrics(st["metrics"], f"stage {i + 1}", path),
                    rejected=st.get("rejected", ()),
                )
            )
        sol = FiniteHorizonSolution(
            system, stored, stages, term, interrupted=ckpt.get("interrupted", False), provenance=ckpt["provenance"]
        )
    return sol
