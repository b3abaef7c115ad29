"""Control-affine systems as data: ``xdot = f(x) + g(x) u`` :eq:`eq-sys` with cost ``Q(x) + u'Ru`` :eq:`eq-cost`.

A :class:`ControlAffineSystem` holds batched torch callables f, g, Q, the control weight R, the set Omega where
results are judged, the training box, and optionally the known V* and mu*; it checks them when built. The
built-ins are the paper's Section 6 with its constants: :func:`pendulum`, :func:`quartic`, :func:`third_order`
and :func:`linear_quadratic`; and three in more dimensions: :func:`rigid_body` (6-D attitude control),
:func:`lq_ladder` (a chain of k masses, n = 2k, exact V*) and :func:`converse` (nonlinear, n even, exact V*).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any, NamedTuple

import numpy as np
import torch

Tensor = torch.Tensor
BatchFn = Callable[[Tensor], Tensor]

__all__ = [
    "ControlAffineSystem",
    "Linearization",
    "fingerprint_difference",
    "fingerprint_summary",
    "pendulum",
    "quartic",
    "third_order",
    "linear_quadratic",
    "rigid_body",
    "lq_ladder",
    "converse",
    "get_system",
    "SYSTEMS",
]


class Linearization(NamedTuple):
    """The linearisation at the origin: ``xdot ~ A x + B u`` and ``Q(x) ~ x'Qx``.

    * ``A``: (n, n), ``df/dx(0)``.
    * ``B``: (n, m), ``g(0)``.
    * ``Q``: (n, n), half the Hessian of Q at 0.
    """

    A: np.ndarray
    B: np.ndarray
    Q: np.ndarray


def _as_box(box, n: int | None, what: str) -> np.ndarray:
    try:
        arr = np.asarray(box, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} must be a box of numbers, rows [low, high]; got {box!r}") from exc
    if arr.ndim == 1 and arr.shape == (2,) and n is not None:
        arr = np.tile(arr, (n, 1))
    if arr.ndim != 2 or arr.shape[1] != 2:
        raise ValueError(f"{what} must be a box of shape (n, 2) (rows [low, high]) or (2,); got shape {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{what} has {arr.shape[0]} rows but the state has dimension n={n}")
    if not np.all(np.isfinite(arr)) or np.any(arr[:, 1] <= arr[:, 0]):
        raise ValueError(f"{what} needs finite bounds with low < high in every row; got {arr.tolist()}")
    return arr


@dataclass(frozen=True, eq=False)
class ControlAffineSystem:
    """A control-affine system :eq:`eq-sys` with a cost quadratic in u :eq:`eq-cost`.

    Construction probes every function with a small batch and fails with a message naming the function and
    the shape it returned; checks that f, g and Q are finite on the training box, f(0) = 0 and Q(0) = 0; and
    warns when Omega does not contain the origin or the training box does not contain Omega.

    * ``name``: a label; the built-ins use their registry name, so that checkpoints can rebuild them.
    * ``f``: batched torch callable, x (N, n) -> (N, n).
    * ``g``: batched torch callable, x (N, n) -> (N, n, m).
    * ``Q``: batched torch callable, x (N, n) -> (N,), positive definite.
    * ``R``: (m, m) symmetric positive definite control weight.
    * ``domain``: Omega, the box (n, 2) where E and the errors are measured.
    * ``train_domain``: the box (n, 2) sampled in training; None: ``domain`` (the paper enlarges it).
    * ``value_star``: the known V*, x (N, n) -> (N,), for error reports; None if unknown.
    * ``policy_star``: the known mu*, x (N, n) -> (N, m); None if unknown.
    * ``params``: the keyword arguments that rebuild a built-in through :func:`get_system` (storage uses
      them); None for a user's own system.
    * ``builder``: the registry name that rebuilds a built-in; None for a user's own system.
    * ``n``, ``m``: the state and input dimensions, set from ``domain`` and ``R``.
    """

    name: str
    f: BatchFn
    g: BatchFn
    Q: BatchFn
    R: Any
    domain: Any
    train_domain: Any = None
    value_star: BatchFn | None = None
    policy_star: BatchFn | None = None
    params: dict | None = None
    builder: str | None = None
    n: int = field(init=False)
    m: int = field(init=False)

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise TypeError(f"name must be a non-empty string; got {self.name!r}")
        for key in ("f", "g", "Q"):
            if not callable(getattr(self, key)):
                raise TypeError(
                    f"system '{self.name}': {key} must be a batched torch callable; got "
                    f"{type(getattr(self, key)).__name__}"
                )
        try:
            flat = np.ndim(self.domain) == 1
        except ValueError:  # ragged rows: _as_box says so
            flat = False
        dom = _as_box(self.domain, 1 if flat else None, "domain (Omega)")
        if flat:
            object.__setattr__(self, "_flat_domain", True)  # n = 1 taken from a flat [low, high]: see _hint
        n = dom.shape[0]
        train = _as_box(dom if self.train_domain is None else self.train_domain, n, "train_domain")
        try:
            R = np.atleast_2d(np.asarray(self.R, dtype=float))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"R must be a square (m, m) matrix of numbers; got {self.R!r}") from exc
        if R.ndim != 2 or R.shape[0] != R.shape[1]:
            raise ValueError(f"R must be a square (m, m) matrix; got shape {R.shape}")
        if not np.all(np.isfinite(R)):
            raise ValueError("R contains NaN or infinite entries")
        if not np.allclose(R, R.T, rtol=1e-10, atol=1e-12):
            raise ValueError("R must be symmetric")
        if np.linalg.eigvalsh(R).min() <= 0:
            raise ValueError(f"R must be positive definite; its eigenvalues are {np.linalg.eigvalsh(R).tolist()}")
        m = R.shape[0]
        object.__setattr__(self, "domain", dom)
        object.__setattr__(self, "train_domain", train)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "_R_inv", np.linalg.inv(R))
        object.__setattr__(self, "n", n)
        object.__setattr__(self, "m", m)
        self._check_functions()
        self._check_boxes()

    # ------------------------------------------------------------------ validation
    def _hint(self) -> str:
        if getattr(self, "_flat_domain", False):
            return (
                f" (the state dimension n=1 was taken from the flat domain {self.domain[0].tolist()}; for an "
                f"n-dimensional system give domain as n rows, e.g. [[-1, 1]] * n)"
            )
        return ""

    def _check_functions(self):
        n, m = self.n, self.m
        gen = torch.Generator().manual_seed(0)
        lo = torch.as_tensor(self.train_domain[:, 0])
        hi = torch.as_tensor(self.train_domain[:, 1])
        probe = lo + (hi - lo) * torch.rand(5, n, generator=gen, dtype=torch.float64)
        expected = {"f": (5, n), "g": (5, n, m), "Q": (5,), "value_star": (5,), "policy_star": (5, m)}
        for key, shape in expected.items():
            fn = getattr(self, key)
            if fn is None:
                continue
            try:
                out = fn(probe)
            except Exception as exc:  # noqa: BLE001 - re-raised with context
                raise ValueError(
                    f"system '{self.name}': {key}(x) failed on a probe batch x of shape (5, {n}): {exc}{self._hint()}"
                ) from exc
            if not isinstance(out, torch.Tensor):
                raise TypeError(f"system '{self.name}': {key}(x) must return a torch.Tensor; got {type(out).__name__}")
            if key == "g" and out.ndim == 3 and out.shape[:2] == (5, n) and out.shape[2] != m:
                raise ValueError(
                    f"system '{self.name}': R is {m} x {m} but g(x) has m={out.shape[2]} columns "
                    f"(shape {tuple(out.shape)} for x of shape (5, {n})); R must be m x m with m the "
                    f"number of inputs, g's last dimension"
                )
            if tuple(out.shape) != shape:
                raise ValueError(
                    f"system '{self.name}': {key}(x) returned shape {tuple(out.shape)} for x of shape (5, {n}); "
                    f"expected {shape}{self._hint()}"
                )
            bad = ~torch.isfinite(out.reshape(5, -1)).all(-1)
            if torch.any(bad):
                raise ValueError(
                    f"system '{self.name}': {key}(x) is NaN or infinite at {int(bad.sum())} of 5 states "
                    f"of a probe batch, e.g. x = {probe[bad][0].tolist()}"
                )
        zero = torch.zeros(1, n, dtype=torch.float64)
        f0 = self.f(zero)
        if not f0.abs().max() <= 1e-10:  # NaN fails too
            raise ValueError(f"system '{self.name}': f(0) must be 0 (the origin is an equilibrium); got {f0.tolist()}")
        q0 = self.Q(zero)
        if not q0.abs().max() <= 1e-10:
            raise ValueError(f"system '{self.name}': Q(0) must be 0 (Q positive definite); got {q0.item()}")
        if torch.any(self.Q(probe) < 0):
            raise ValueError(f"system '{self.name}': Q(x) is negative on a probe point; Q must be positive definite")
        self.check_finite(
            self.sample(512, torch.Generator().manual_seed(1), dtype=torch.float64),
            "a probe of 512 states of the training box",
        )

    def check_finite(self, x: Tensor, where: str):
        """Raise a ValueError naming the function and a state where f, g or Q is NaN or infinite.

        * ``x``: (N, n) states.
        * ``where``: what ``x`` is, for the message.
        """
        with torch.no_grad():
            for key in ("f", "g", "Q"):
                out = getattr(self, key)(x)
                bad = ~torch.isfinite(out.reshape(out.shape[0], -1)).all(-1)
                if torch.any(bad):
                    first = x[bad][0].detach().cpu().tolist()
                    raise ValueError(
                        f"system '{self.name}': {key}(x) is NaN or infinite at {int(bad.sum())} of "
                        f"{x.shape[0]} states of {where}, e.g. x = {first}; f, g, Q must be finite on "
                        f"the whole training box {self.train_domain.tolist()}"
                    )

    def _check_boxes(self):
        dom, train = self.domain, self.train_domain
        if np.any(dom[:, 0] > 0) or np.any(dom[:, 1] < 0):
            warnings.warn(
                f"system '{self.name}': Omega {dom.tolist()} does not contain the origin, the equilibrium "
                f"the value function is anchored at (V(0) = 0)",
                UserWarning,
                stacklevel=4,
            )
        if np.any(train[:, 0] > dom[:, 0]) or np.any(train[:, 1] < dom[:, 1]):
            warnings.warn(
                f"system '{self.name}': the training box {train.tolist()} does not contain Omega "
                f"{dom.tolist()}; E and the errors are measured on Omega, partly outside what was trained "
                f"(usually the training box is Omega or larger)",
                UserWarning,
                stacklevel=4,
            )

    def linearize(self) -> Linearization:
        """The linearisation at the origin, by autograd in float64 on the CPU.

        With :func:`pinnhjb.lq.care` (and ``self.R``) it gives the LQR value ``x'Px`` of the linearised problem.
        Returns a :class:`Linearization` of numpy arrays.
        """
        zero = torch.zeros(self.n, dtype=torch.float64)
        try:
            A = torch.autograd.functional.jacobian(lambda z: self.f(z[None])[0], zero)
            H = torch.autograd.functional.hessian(lambda z: self.Q(z[None])[0], zero)
        except Exception as exc:  # noqa: BLE001 - re-raised with context
            raise ValueError(
                f"system '{self.name}': linearize() differentiates f and Q by autograd, which failed: {exc}"
            ) from exc
        B = self.g(zero[None])[0]
        return Linearization(A.detach().numpy().copy(), B.detach().numpy().copy(), 0.5 * H.detach().numpy())

    def lqr_value(self) -> np.ndarray:
        """P of the linearisation's LQR value ``x'Px``: :func:`pinnhjb.lq.care` of :meth:`linearize` and ``R``.

        Near the origin V*(x) = x'Px + O(abs(x)^3). Returns an (n, n) numpy array; fails as
        :func:`~pinnhjb.lq.care` does where the linearisation is not stabilisable.
        """
        from . import lq  # local import: lq is numpy/scipy only

        lin = self.linearize()
        return lq.care(lin.A, lin.B, lin.Q, self.R)

    # ------------------------------------------------------------------ core operators
    def R_tensor(self, like: Tensor) -> Tensor:
        return torch.as_tensor(self.R, dtype=like.dtype, device=like.device)

    def R_inv_tensor(self, like: Tensor) -> Tensor:
        return torch.as_tensor(self._R_inv, dtype=like.dtype, device=like.device)

    def box_reach(self, x) -> np.ndarray:
        """How far each state reaches from the training box's centre, per box half-width:
        ``max_i abs(x_i - centre_i) / halfwidth_i``, above 1 outside the box.

        * ``x``: states (..., n), anything numpy reads (e.g. the (K+1, N, n) states of a closed loop).

        Returns a float array of shape (...).
        """
        x = np.asarray(x, dtype=float)
        box = self.train_domain
        centre, half = box.mean(axis=1), (box[:, 1] - box[:, 0]) / 2
        return np.abs((x - centre) / half).max(axis=-1)

    def outside_training_box(self, x) -> np.ndarray:
        """Whether each state lies outside the training box, where no residual is trained (:meth:`box_reach` > 1).

        * ``x``: states (..., n), anything numpy reads (e.g. the (K+1, N, n) states of a closed loop).

        Returns a bool array of shape (...).
        """
        return self.box_reach(x) > 1

    def check_states(self, x: Tensor, what: str = "x") -> Tensor:
        """Validate a batch of states: a tensor of shape (N, n) with finite entries.

        * ``x``: the states, a tensor or anything numpy reads.
        * ``what``: its name, for the message.

        Returns ``x`` as a tensor.
        """
        if not isinstance(x, torch.Tensor):
            x = torch.as_tensor(np.asarray(x))
        if x.ndim != 2 or x.shape[1] != self.n:
            raise ValueError(f"{what} must have shape (N, {self.n}) for system '{self.name}'; got {tuple(x.shape)}")
        if not torch.all(torch.isfinite(x)):
            raise ValueError(f"{what} contains NaN or infinite entries")
        return x

    def policy_from_gradient(self, x: Tensor, grad_v: Tensor) -> Tensor:
        """The policy of a value's gradient, ``mu(x) = -1/2 R^{-1} g(x)' grad V(x)``: :eq:`eq-mustar`, :eq:`eq-mut`.

        * ``x``: (N, n) states.
        * ``grad_v``: (N, n), the value's gradient at ``x``.

        Returns (N, m).
        """
        gTp = torch.einsum("bnm,bn->bm", self.g(x), grad_v)
        return -0.5 * gTp @ self.R_inv_tensor(x).T

    def hamiltonian_min(
        self, x: Tensor, grad_v: Tensor, fx: Tensor | None = None, gx: Tensor | None = None, qx: Tensor | None = None
    ) -> Tensor:
        """``min_u H(x, u, p) = p'f + Q - 1/4 p' g R^{-1} g' p``: the left side of the steady-state HJB :eq:`eq-hjb`.

        With ``p = grad_x V(x, t)`` and ``+ dV/dt`` it is the flow residual :eq:`eq-fe`; with V_T(., 0) it is the
        steady-state residual :eq:`eq-ee`.

        * ``x``: (N, n) states.
        * ``grad_v``: (N, n), p.
        * ``fx``, ``gx``, ``qx``: f, g and Q at ``x`` when already computed; None: computed here.

        Returns (N,).
        """
        fx = self.f(x) if fx is None else fx
        gx = self.g(x) if gx is None else gx
        qx = self.Q(x) if qx is None else qx
        gTp = torch.einsum("bnm,bn->bm", gx, grad_v)
        quad = torch.einsum("bi,ij,bj->b", gTp, self.R_inv_tensor(x), gTp)
        return (grad_v * fx).sum(-1) + qx - 0.25 * quad

    def dynamics(self, x: Tensor, u: Tensor) -> Tensor:
        """``xdot = f(x) + g(x) u`` :eq:`eq-sys` for states x (N, n) and inputs u (N, m); returns (N, n)."""
        return self.f(x) + torch.einsum("bnm,bm->bn", self.g(x), u)

    def running_cost(self, x: Tensor, u: Tensor) -> Tensor:
        """``Q(x) + u'Ru``, the integrand of :eq:`eq-cost`, for x (N, n) and u (N, m); returns (N,)."""
        return self.Q(x) + torch.einsum("bi,ij,bj->b", u, self.R_tensor(u), u)

    # ------------------------------------------------------------------ sampling helpers
    def grid(self, points_per_dim: int, dtype=torch.float64, device=None, box: np.ndarray | None = None) -> Tensor:
        """A tensor-product grid over Omega.

        * ``points_per_dim``: points along each axis.
        * ``dtype``, ``device``: of the result.
        * ``box``: (n, 2); None: Omega.

        Returns (points_per_dim**n, n).
        """
        box = self.domain if box is None else box
        axes = [torch.linspace(float(lo), float(hi), points_per_dim, dtype=dtype, device=device) for lo, hi in box]
        mesh = torch.meshgrid(*axes, indexing="ij")
        return torch.stack([m.reshape(-1) for m in mesh], dim=-1)

    def sample(
        self, count: int, generator: torch.Generator, dtype=torch.float32, device=None, box: np.ndarray | None = None
    ) -> Tensor:
        """Uniform samples from the training box.

        * ``count``: how many.
        * ``generator``: the torch generator that draws them.
        * ``dtype``, ``device``: of the result.
        * ``box``: (n, 2); None: the training box.

        Returns (count, n).
        """
        box = self.train_domain if box is None else box
        lo = torch.as_tensor(box[:, 0], dtype=dtype, device=device)
        hi = torch.as_tensor(box[:, 1], dtype=dtype, device=device)
        u = torch.rand(count, self.n, generator=generator, dtype=dtype, device=generator.device)
        return lo + (hi - lo) * u.to(device)

    def fingerprint(self) -> dict:
        """What identifies this system in a checkpoint, as plain lists.

        The name, n, m, R, Omega, the training box, and f, g, Q on :data:`FINGERPRINT_PROBES` fixed states of
        Omega (float64, CPU). Compared by :func:`fingerprint_difference`.
        """
        u = np.random.default_rng(20261201).uniform(-1.0, 1.0, (FINGERPRINT_PROBES, self.n))
        centre, half = self.domain.mean(axis=1), (self.domain[:, 1] - self.domain[:, 0]) / 2
        x = torch.as_tensor(centre + half * u, dtype=torch.float64)
        with torch.no_grad():
            values = {k: getattr(self, k)(x).detach().cpu().double().numpy().tolist() for k in ("f", "g", "Q")}
        return {
            "name": self.name,
            "n": self.n,
            "m": self.m,
            "R": self.R.tolist(),
            "domain": self.domain.tolist(),
            "train_domain": self.train_domain.tolist(),
            "probes": x.numpy().tolist(),
            **values,
        }

    def spec(self) -> dict:
        """What storage needs to rebuild this system: its registry name and parameters."""
        return {
            "name": self.name,
            "builder": self.builder,
            "params": dict(self.params) if self.params is not None else None,
            "n": self.n,
            "m": self.m,
        }

    def __repr__(self):
        return (
            f"ControlAffineSystem(name={self.name!r}, n={self.n}, m={self.m}, R={self.R.tolist()}, "
            f"domain={self.domain.tolist()}, known V*={self.value_star is not None})"
        )


# ====================================================================== fingerprints

#: How many fixed states of Omega a fingerprint evaluates f, g and Q on.
FINGERPRINT_PROBES = 8


def fingerprint_difference(stored: dict, current: dict, rtol: float = 1e-7) -> list[str]:
    """The fields in which two fingerprints differ; empty when they match.

    * ``stored``: the fingerprint saved with a checkpoint.
    * ``current``: the fingerprint of the system at hand.
    * ``rtol``: relative tolerance on f, g, Q (the same functions on another CPU or BLAS agree to rounding).
    """
    diffs = [k for k in ("name", "n", "m") if stored.get(k) != current.get(k)]
    if diffs:
        return diffs
    for key in ("R", "domain", "train_domain", "probes", "f", "g", "Q"):
        a, b = np.asarray(stored.get(key), dtype=float), np.asarray(current.get(key), dtype=float)
        tight = key in ("R", "domain", "train_domain", "probes")
        scale = max(1.0, float(np.max(np.abs(a)))) if a.size else 1.0
        if a.shape != b.shape or not np.allclose(
            a, b, rtol=1e-12 if tight else rtol, atol=1e-12 * scale if tight else rtol * 1e-3 * scale
        ):
            diffs.append(key)
    return diffs


def fingerprint_summary(fp: dict) -> str:
    """A one-line account of a fingerprint ``fp``: name, n, m, R, boxes, and a digest of f, g, Q on the probes."""
    import hashlib

    def digest(key):
        arr = np.asarray(fp.get(key), dtype=float)
        text = np.array2string(arr.ravel(), precision=6, separator=",", threshold=10**6)
        return f"{key}:{hashlib.sha1(text.encode()).hexdigest()[:8]}"

    return (
        f"{{name={fp.get('name')!r}, n={fp.get('n')}, m={fp.get('m')}, R={fp.get('R')}, "
        f"domain={fp.get('domain')}, train_domain={fp.get('train_domain')}, "
        f"{', '.join(digest(k) for k in ('f', 'g', 'Q'))}}}"
    )


# ====================================================================== built-in systems


def _positive(value, name: str, system: str) -> float:
    """A built-in's scalar parameter as a positive finite float, or a ValueError naming it."""
    if (
        isinstance(value, (bool, str))
        or not isinstance(value, (int, float, np.integer, np.floating))
        or not 0 < float(value) < np.inf
    ):
        raise ValueError(f"{system}: parameter {name} must be a positive finite number; got {value!r}")
    return float(value)


def pendulum(R: float = 1.0) -> ControlAffineSystem:
    """The torsional pendulum of Section 6.1: M = 1/3 kg, l = 2/3 m, J = 4/3 M l^2, f_d = 0.2, g = 9.8.

    ``f(x) = [x2, (-M g l sin x1 - f_d x2)/J]``, ``g(x) = [0, 1/J]'``, ``Q(x) = x1^2 + x2^2``, Omega = [-1, 1]^2,
    trained on [-1.5, 1.5]^2 as in the paper.

    * ``R``: the control weight (the paper: 1).
    """
    R = _positive(R, "R", "pendulum")
    M, l, fd, grav = 1.0 / 3.0, 2.0 / 3.0, 0.2, 9.8
    J = 4.0 / 3.0 * M * l**2

    def f(x):
        return torch.stack([x[:, 1], (-M * grav * l * torch.sin(x[:, 0]) - fd * x[:, 1]) / J], dim=-1)

    def g(x):
        out = torch.zeros(x.shape[0], 2, 1, dtype=x.dtype, device=x.device)
        out[:, 1, 0] = 1.0 / J
        return out

    def Q(x):
        return (x**2).sum(-1)

    return ControlAffineSystem(
        "pendulum",
        f,
        g,
        Q,
        [[R]],
        domain=[[-1, 1], [-1, 1]],
        train_domain=[[-1.5, 1.5], [-1.5, 1.5]],
        params={"R": float(R)},
        builder="pendulum",
    )


QUARTIC_STATE_COSTS = ("consistent", "paper")


def quartic(state_cost: str = "consistent") -> ControlAffineSystem:
    """The system with a known quartic value function of Section 6.2 (from Vrabie & Lewis 2009).

    ``f(x) = [-x1 + x2 + 2 x2^3, -(x1 + x2)/2 + x2 (1 + 2 x2^2) sin^2(x1) / 2]``, ``g(x) = [0, sin x1]'``,
    R = 1, ``V*(x) = x1^2/2 + x2^2 + x2^4``, ``mu*(x) = -sin(x1)(x2 + 2 x2^3)``, Omega = [-1.2, 1.2]^2, trained
    on [-1.5, 1.5]^2.

    **Erratum.** The paper prints ``Q(x) = x1^2 + x2^2 + x2^4``, but the stated V* solves the HJB :eq:`eq-hjb`
    only for ``Q(x) = x1^2 + x2^2 + 2 x2^4``: with the printed Q the HJB residual of V* is exactly ``-x2^4``.

    * ``state_cost``: ``"consistent"``, the Q for which V* is optimal; or ``"paper"``, the printed Q (then V*
      and mu* are not optimal and are not attached).
    """
    if state_cost not in QUARTIC_STATE_COSTS:
        raise ValueError(f"state_cost must be one of {QUARTIC_STATE_COSTS}; got {state_cost!r}")
    c4 = 2.0 if state_cost == "consistent" else 1.0

    def f(x):
        x1, x2 = x[:, 0], x[:, 1]
        return torch.stack(
            [-x1 + x2 + 2 * x2**3, -0.5 * (x1 + x2) + 0.5 * x2 * (1 + 2 * x2**2) * torch.sin(x1) ** 2], dim=-1
        )

    def g(x):
        out = torch.zeros(x.shape[0], 2, 1, dtype=x.dtype, device=x.device)
        out[:, 1, 0] = torch.sin(x[:, 0])
        return out

    def Q(x):
        return x[:, 0] ** 2 + x[:, 1] ** 2 + c4 * x[:, 1] ** 4

    def value_star(x):
        return 0.5 * x[:, 0] ** 2 + x[:, 1] ** 2 + x[:, 1] ** 4

    def policy_star(x):
        return (-torch.sin(x[:, 0]) * (x[:, 1] + 2 * x[:, 1] ** 3)).unsqueeze(-1)

    known = state_cost == "consistent"
    return ControlAffineSystem(
        "quartic",
        f,
        g,
        Q,
        [[1.0]],
        domain=[[-1.2, 1.2], [-1.2, 1.2]],
        train_domain=[[-1.5, 1.5], [-1.5, 1.5]],
        value_star=value_star if known else None,
        policy_star=policy_star if known else None,
        params={"state_cost": state_cost},
        builder="quartic",
    )


def third_order(R: float = 1.0) -> ControlAffineSystem:
    """The third-order system of Section 6.3: K = 0.05, C = 3.5, a = 5.5, b = 4, ``Q(x) = x'x``.

    ``f(x) = [-2 x1 + x2^3, -C x2 + x3, -K (a x2^3 + b x2 + x1^3)]``, ``g(x) = [0, 0, K]'``,
    Omega = [-0.2, 0.2]^3. The paper states no enlarged training set for this case; it is trained on
    [-0.25, 0.25]^3 (the quartic system's 1.25x margin) and judged on Omega.

    * ``R``: the control weight (the paper varies it: Table 2).
    """
    R = _positive(R, "R", "third_order")
    K, C, a, b = 0.05, 3.5, 5.5, 4.0

    def f(x):
        x1, x2, x3 = x[:, 0], x[:, 1], x[:, 2]
        return torch.stack([-2 * x1 + x2**3, -C * x2 + x3, -K * (a * x2**3 + b * x2 + x1**3)], dim=-1)

    def g(x):
        out = torch.zeros(x.shape[0], 3, 1, dtype=x.dtype, device=x.device)
        out[:, 2, 0] = K
        return out

    def Q(x):
        return (x**2).sum(-1)

    return ControlAffineSystem(
        "third_order",
        f,
        g,
        Q,
        [[R]],
        domain=[[-0.2, 0.2]] * 3,
        train_domain=[[-0.25, 0.25]] * 3,
        params={"R": float(R)},
        builder="third_order",
    )


def linear_quadratic(A, B, Q, R, domain, train_domain=None, name: str = "lq") -> ControlAffineSystem:
    """The linear system ``xdot = A x + B u`` with cost ``x'Qx + u'Ru``, with its known V* and mu*.

    ``V*(x) = x'Px`` with P the stabilizing ARE solution (:func:`pinnhjb.lq.care`), ``mu*(x) = -R^{-1} B' P x``.

    * ``A``: (n, n).
    * ``B``: (n, m), or (n,) for one input.
    * ``Q``: (n, n), symmetric positive semidefinite.
    * ``R``: (m, m), symmetric positive definite.
    * ``domain``: Omega, a box (n, 2).
    * ``train_domain``: the training box; None: Omega enlarged by 25% about its centre (the quartic and
      third-order systems' margin), so that E is judged inside what was trained. Pass ``domain`` to train on
      Omega itself.
    * ``name``: the system's label.
    """
    return _linear_quadratic(A, B, Q, R, domain, train_domain, name)


def _linear_quadratic(A, B, Q, R, domain, train_domain, name, params=None, builder="lq") -> ControlAffineSystem:
    """:func:`linear_quadratic`, rebuilt through the registry as ``builder`` with ``params``.

    * ``A``, ``B``, ``Q``, ``R``, ``domain``, ``train_domain``, ``name``: as in :func:`linear_quadratic`.
    * ``params``: the keyword arguments that rebuild it through ``builder``; None: those of ``"lq"``.
    * ``builder``: its registry name.
    """
    from . import lq  # local import: lq is numpy/scipy only

    domain = _as_box(domain, np.atleast_2d(np.asarray(A, dtype=float)).shape[0], "domain (Omega)")
    if train_domain is None:
        centre, half = domain.mean(axis=1), (domain[:, 1] - domain[:, 0]) / 2
        train_domain = np.stack([centre - 1.25 * half, centre + 1.25 * half], axis=1)

    A = np.atleast_2d(np.asarray(A, dtype=float))
    B = np.asarray(B, dtype=float)
    B = B.reshape(-1, 1) if B.ndim == 1 else B
    Qm = np.atleast_2d(np.asarray(Q, dtype=float))
    Rm = np.atleast_2d(np.asarray(R, dtype=float))
    P = lq.care(A, B, Qm, Rm)
    K = np.linalg.solve(Rm, B.T @ P)

    def mat(M, like):
        return torch.as_tensor(M, dtype=like.dtype, device=like.device)

    def f(x):
        return x @ mat(A, x).T

    def g(x):
        return mat(B, x).expand(x.shape[0], *B.shape)

    def Qf(x):
        return torch.einsum("bi,ij,bj->b", x, mat(Qm, x), x)

    def value_star(x):
        return torch.einsum("bi,ij,bj->b", x, mat(P, x), x)

    def policy_star(x):
        return -x @ mat(K, x).T

    if params is None:
        params = {
            "A": A.tolist(),
            "B": B.tolist(),
            "Q": Qm.tolist(),
            "R": Rm.tolist(),
            "domain": np.asarray(domain, dtype=float).tolist(),
            "train_domain": None if train_domain is None else np.asarray(train_domain, dtype=float).tolist(),
            "name": name,
        }
    return ControlAffineSystem(
        name,
        f,
        g,
        Qf,
        Rm,
        domain=domain,
        train_domain=train_domain,
        value_star=value_star,
        policy_star=policy_star,
        params=params,
        builder=builder,
    )


def _dimension(value, name: str, system: str, least: int, even: bool = False) -> int:
    """A built-in's integer size parameter, checked before anything is built, or a ValueError naming it."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{system}: parameter {name} must be an integer; got {value!r} ({type(value).__name__})")
    if value < least:
        raise ValueError(f"{system}: parameter {name} must be at least {least}; got {value}")
    if even and value % 2:
        raise ValueError(f"{system}: parameter {name} must be even (m = {name}/2 inputs); got {value}")
    return int(value)


def _euler_321(v: Tensor) -> tuple[Tensor, Tensor]:
    """The 3-2-1 Euler-angle matrices of Tenavi/HJB_NN's ``examples/satellite/problem_def.py``, batched.

    * ``v``: (N, 3) Euler angles (phi, theta, psi): roll, pitch, yaw.

    Returns ``(E, R)``, each (N, 3, 3): the kinematics ``vdot = E(v) w`` of body rates w, and the rotation
    ``R(v) = R1(phi) R2(theta) R3(psi)`` from inertial to body axes (the direction cosine matrix).
    """
    sf, cf = torch.sin(v[:, 0]), torch.cos(v[:, 0])
    st, ct, tt = torch.sin(v[:, 1]), torch.cos(v[:, 1]), torch.tan(v[:, 1])
    sp, cp = torch.sin(v[:, 2]), torch.cos(v[:, 2])
    one, zero = torch.ones_like(sf), torch.zeros_like(sf)
    E = torch.stack(
        [
            torch.stack([one, sf * tt, cf * tt], -1),
            torch.stack([zero, cf, -sf], -1),
            torch.stack([zero, sf / ct, cf / ct], -1),
        ],
        -2,
    )
    R = torch.stack(
        [
            torch.stack([ct * cp, ct * sp, -st], -1),
            torch.stack([sf * st * cp - cf * sp, sf * st * sp + cf * cp, ct * sf], -1),
            torch.stack([cf * st * cp + sf * sp, cf * st * sp - sf * cp, ct * cf], -1),
        ],
        -2,
    )
    return E, R


#: The rigid body's constants (Tenavi/HJB_NN, examples/satellite/problem_def.py): inverse inertia, input
#: matrix, total angular momentum in inertial axes, and the cost weights W1, W2, W3.
RIGID_BODY_CONSTANTS = MappingProxyType(
    {
        "J_inv": ((1 / 2, 0.0, 0.0), (0.0, 1 / 3, 0.0), (0.0, 0.0, 1 / 4)),
        "B": ((1.0, 1 / 20, 1 / 10), (1 / 15, 1.0, 1 / 10), (1 / 10, 1 / 15, 1.0)),
        "h": (1.0, 1.0, 1.0),
        "W": (1.0, 10.0, 0.5),
    }
)


def rigid_body(train_scale=None) -> ControlAffineSystem:
    """The 6-D rigid-body (satellite) attitude problem of Nakamura-Zimmerer, Gong & Kang (SIAM J. Sci. Comput. 2021).

    The constants and conventions are those of their code, Tenavi/HJB_NN ``examples/satellite/problem_def.py``
    (``RIGID_BODY_CONSTANTS``). State ``x = (v, w)``: Euler angles ``v = (phi, theta, psi)`` (roll, pitch,
    yaw; 3-2-1 sequence) and body rates ``w = (w1, w2, w3)``; three inputs (torques of momentum wheels).

    ``vdot = E(v) w`` with ``E = [[1, sin(phi) tan(theta), cos(phi) tan(theta)], [0, cos(phi), -sin(phi)],
    [0, sin(phi)/cos(theta), cos(phi)/cos(theta)]]``; ``wdot = J^{-1} (S(w) R(v) h + B u)`` with
    ``J^{-1} = diag(1/2, 1/3, 1/4)``, ``B = [[1, 1/20, 1/10], [1/15, 1, 1/10], [1/10, 1/15, 1]]``, ``h = (1, 1, 1)``
    the total angular momentum (body and wheels) in inertial axes, conserved, ``R(v) = R1(phi) R2(theta) R3(psi)``
    the inertial-to-body rotation (so ``R(v) h`` is that momentum in body axes; ``R`` as printed in their code,
    not ``R'``), and ``S(w) a = a x w`` (their ``S = [[0, w3, -w2], [-w3, 0, w1], [w2, -w1, 0]]``, i.e.
    ``-[w]x``). With ``vdot = E w`` it satisfies ``d/dt R(v) = S(w) R(v)``: the body-axes momentum turns against
    the body's rotation. The term ``S(w) R(v) h`` is linear in w, so f(0) = 0 holds with h != 0 as it stands: the
    origin (attitude 0, body at rest) is an equilibrium with all of h stored in the wheels; like their code, nothing
    is subtracted or changed for it. With u = 0 the kinetic energy ``w' J w / 2`` is conserved (``w'(a x w) = 0``).

    Cost from their weights W1 = 1, W2 = 10, W3 = 0.5: ``Q(x) = W1/2 |v|^2 + W2/2 |w|^2 = |v|^2/2 + 5 |w|^2``,
    ``R = W3/2 I = I/4``. Omega = [-pi/3, pi/3]^3 x [-pi/4, pi/4]^3, their box of initial states; trained on Omega
    enlarged 1.1x (abs(theta) <= 1.1 pi/3 < pi/2, away from the Euler-angle singularity). V* is not known.

    * ``train_scale``: the training box as Omega enlarged about the origin by this factor, one number or one per
      coordinate, each >= 1, the pitch's below 1.5 (abs(theta) < pi/2); None: 1.1 for every coordinate.
    """
    scale = _rigid_body_train_scale(train_scale)
    c = RIGID_BODY_CONSTANTS
    J_inv, Bw, h = np.asarray(c["J_inv"]), np.asarray(c["B"]), np.asarray(c["h"])
    w1, w2, w3 = c["W"]
    G = np.vstack([np.zeros((3, 3)), J_inv @ Bw])

    def mat(M, like):
        return torch.as_tensor(M, dtype=like.dtype, device=like.device)

    def f(x):
        v, w = x[:, :3], x[:, 3:]
        E, R = _euler_321(v)
        vdot = torch.einsum("bij,bj->bi", E, w)
        Rh = torch.einsum("bij,j->bi", R, mat(h, x))
        wdot = torch.linalg.cross(Rh, w, dim=-1) @ mat(J_inv, x).T  # S(w) R h = (R h) x w
        return torch.cat([vdot, wdot], dim=-1)

    def g(x):
        return mat(G, x).expand(x.shape[0], 6, 3)

    def Q(x):
        return w1 / 2 * (x[:, :3] ** 2).sum(-1) + w2 / 2 * (x[:, 3:] ** 2).sum(-1)

    omega = np.array([[-np.pi / 3, np.pi / 3]] * 3 + [[-np.pi / 4, np.pi / 4]] * 3)
    return ControlAffineSystem(
        "rigid_body",
        f,
        g,
        Q,
        w3 / 2 * np.eye(3),
        domain=omega,
        train_domain=_scaled(omega, scale, 1.1),
        params={} if scale is None else {"train_scale": scale},
        builder="rigid_body",
    )


def _train_scale(train_scale, n: int, what: str) -> list[float] | None:
    """A builder's ``train_scale`` checked and as n floats (one per coordinate); None stays None (its default box).

    * ``train_scale``: one number or n, each finite and >= 1 (the training box contains Omega).
    * ``n``: the state dimension.
    * ``what``: the builder's name, for the error.
    """
    if train_scale is None:
        return None
    try:
        scale = np.broadcast_to(np.asarray(train_scale, dtype=float), (n,)).tolist()
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what}: train_scale must be one number or {n}; got {train_scale!r}") from exc
    if not all(np.isfinite(a) and a >= 1.0 for a in scale):
        raise ValueError(f"{what}: train_scale must be >= 1 (the training box contains Omega); got {scale}")
    return scale


def _scaled(omega: np.ndarray, scale: list[float] | None, default: float) -> np.ndarray:
    """The training box: Omega (centred on the origin) enlarged by ``scale`` per coordinate, or by ``default``."""
    return (default if scale is None else np.asarray(scale)[:, None]) * np.asarray(omega, dtype=float)


def _rigid_body_train_scale(train_scale) -> list[float] | None:
    """:func:`rigid_body`'s ``train_scale`` checked and as six floats; None stays None (the default box)."""
    scale = _train_scale(train_scale, 6, "rigid_body")
    if scale is not None and scale[1] * np.pi / 3 >= np.pi / 2:
        raise ValueError(
            f"train_scale for the pitch theta must be below 1.5 (abs(theta) < pi/2, where the Euler angles are "
            f"singular); got {scale[1]}"
        )
    return scale


def lq_ladder(k: int, train_scale=None) -> ControlAffineSystem:
    """A chain of k unit masses on a line and unit springs, one force per mass: linear, n = 2k, m = k, V* by CARE.

    Mass 1 is tied to a wall and each mass to its neighbours; mass k's right end is free. Positions q and
    velocities qdot of the masses, in that order: ``x = (q_1, ..., q_k, qdot_1, ..., qdot_k)``,
    ``A = [[0, I], [-K, 0]]`` with K the stiffness matrix (tridiagonal, 2 on the diagonal but 1 in the last row,
    -1 beside it), ``B = [[0], [I]]``. Undamped: every mass is actuated, so (A, B) is controllable and Q = I
    makes the problem regular without damping. Q = I, R = I, Omega = [-1, 1]^n, trained on [-1.25, 1.25]^n
    (:func:`linear_quadratic`'s margin); ``V*(x) = x'Px``, ``mu*(x) = -B'Px`` with P from :func:`pinnhjb.lq.care`.

    * ``k``: the number of masses, an integer >= 1.
    * ``train_scale``: the training box as Omega enlarged about the origin by this factor, one number or one per
      coordinate, each >= 1; None: 1.25.
    """
    k = _dimension(k, "k", "lq_ladder", 1)
    scale = _train_scale(train_scale, 2 * k, "lq_ladder")
    omega = np.array([[-1.0, 1.0]] * (2 * k))
    stiffness = 2.0 * np.eye(k) - np.eye(k, k=1) - np.eye(k, k=-1)
    stiffness[-1, -1] = 1.0
    A = np.block([[np.zeros((k, k)), np.eye(k)], [-stiffness, np.zeros((k, k))]])
    B = np.vstack([np.zeros((k, k)), np.eye(k)])
    params = {"k": k} if scale is None else {"k": k, "train_scale": scale}
    train = _scaled(omega, scale, 1.25)
    return _linear_quadratic(A, B, np.eye(2 * k), np.eye(k), omega, train, "lq_ladder", params, "lq_ladder")


def converse(n: int, train_scale=None) -> ControlAffineSystem:
    """A nonlinear system in n dimensions (n even) with a known V*, built by the converse-HJB method.

    Chosen: ``V*(x) = x'Px + 1/2 sum_i x_i^4`` with P = I plus 1/4 on the first off-diagonals (eigenvalues in
    (1/2, 3/2); V* strictly convex, radially unbounded, its gradient ``p = 2Px + 2x^3`` zero only at 0); m = n/2
    inputs, input j driving ``x_{2j+1}`` (0-based) with unit gain; R = I/4; K = I/2; S the
    skew-symmetric matrix with 1 above the diagonal inside each pair (2j, 2j+1), 1/2 between pairs (2j+1, 2j+2),
    minus its transpose. With ``G(x) = g R^{-1} g'``:

    ``Q(x) = 1/2 p'Kp = |p|^2/4`` (positive definite, Q(0) = 0) and ``f(x) = -1/2 K p + S p + 1/4 G p``
    (f(0) = 0 as p(0) = 0). Then ``p'f = -Q + 0 + 1/4 p'Gp`` (``p'Sp = 0``), so the HJB
    ``p'f + Q - 1/4 p'Gp = 0`` :eq:`eq-hjb` holds exactly; ``mu*(x) = -1/2 R^{-1} g'p = -2 g'p`` and the closed
    loop ``f + g mu* = -1/2 K p + S p - 1/4 G p`` gives ``dV*/dt = -Q - 1/4 p'Gp = -(Q + mu*'R mu*) < 0``: V* is a
    Lyapunov function, the closed loop is globally asymptotically stable, and V* is the optimal cost. The open
    loop is unstable (its linearisation has eigenvalues with real part about +0.5). Omega = [-1, 1]^n, trained
    on [-1.25, 1.25]^n.

    The gain is constant on purpose: with a gain ``1 + x_{2j}^2/2`` the term ``1/4 G p`` grows like x^7, the open
    loop escapes in finite time, and the default recipe stalls at E / E(V = 0) near 1e-2 with a value error larger
    than V* itself, already at n = 2, where with this constant gain it reaches a relative value error below 1e-4.

    * ``n``: the state dimension, an even integer >= 2.
    * ``train_scale``: the training box as Omega enlarged about the origin by this factor, one number or one per
      coordinate, each >= 1; None: 1.25.
    """
    n = _dimension(n, "n", "converse", 2, even=True)
    scale = _train_scale(train_scale, n, "converse")
    m = n // 2
    P = np.eye(n) + 0.25 * (np.eye(n, k=1) + np.eye(n, k=-1))
    S = np.zeros((n, n))
    S[np.arange(n - 1), np.arange(1, n)] = np.where(np.arange(n - 1) % 2 == 0, 1.0, 0.5)
    S = S - S.T
    R = 0.25 * np.eye(m)
    R_inv = np.linalg.inv(R)
    k_drift = 0.5  # K = k_drift I
    rows, cols = 2 * np.arange(m) + 1, np.arange(m)

    def mat(M, like):
        return torch.as_tensor(M, dtype=like.dtype, device=like.device)

    def grad_v(x):
        return 2 * x @ mat(P, x) + 2 * x**3

    def g(x):
        out = torch.zeros(x.shape[0], n, m, dtype=x.dtype, device=x.device)
        out[:, rows, cols] = 1.0
        return out

    def f(x):
        p = grad_v(x)
        gx = g(x)
        Gp = torch.einsum("bnm,bm->bn", gx, torch.einsum("bnm,bn->bm", gx, p) @ mat(R_inv, x).T)
        return -0.5 * k_drift * p + p @ mat(S, x).T + 0.25 * Gp

    def Q(x):
        return 0.5 * k_drift * (grad_v(x) ** 2).sum(-1)

    def value_star(x):
        return torch.einsum("bi,ij,bj->b", x, mat(P, x), x) + 0.5 * (x**4).sum(-1)

    def policy_star(x):
        return -0.5 * torch.einsum("bnm,bn->bm", g(x), grad_v(x)) @ mat(R_inv, x).T

    return ControlAffineSystem(
        "converse",
        f,
        g,
        Q,
        R,
        domain=[[-1.0, 1.0]] * n,
        train_domain=_scaled([[-1.0, 1.0]] * n, scale, 1.25),
        value_star=value_star,
        policy_star=policy_star,
        params={"n": n} if scale is None else {"n": n, "train_scale": scale},
        builder="converse",
    )


#: The registry of built-in systems: name -> builder.
#:
#: :meta hide-value:
SYSTEMS: dict[str, Callable[..., ControlAffineSystem]] = {
    "pendulum": pendulum,
    "quartic": quartic,
    "third_order": third_order,
    "lq": linear_quadratic,
    "rigid_body": rigid_body,
    "lq_ladder": lq_ladder,
    "converse": converse,
}


def get_system(name: str, /, **params) -> ControlAffineSystem:
    """Build a registered system by name.

    * ``name``: ``"pendulum"``, ``"quartic"``, ``"third_order"``, ``"lq"``, ``"rigid_body"``, ``"lq_ladder"`` or
      ``"converse"`` (the keys of :data:`SYSTEMS`).
    * ``params``: the builder's keyword arguments.
    """
    if name not in SYSTEMS:
        raise KeyError(f"unknown system {name!r}; known systems: {sorted(SYSTEMS)}")
    return SYSTEMS[name](**params)
