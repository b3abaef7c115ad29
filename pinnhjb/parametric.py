"""One value network for a whole family of systems: a scalar parameter p as an input, p over a range.

A family ``xdot = f(x, p) + g(x, p) u`` with cost ``Q(x, p) + u' R(p) u`` is one control-affine system on the
state ``z = (x, s)`` that never moves s, with s = log10(p / p_c) or s = p - p_c about the middle p_c of the
range (so that the augmented Omega holds the origin, where V = 0). R(p) is brought to one weight R0 by the
change of input ``u~ = M(p) u``, ``M = R0^{-1/2} R(p)^{1/2}``: then ``u' R(p) u = u~' R0 u~`` and
``g u = (g M^{-1}) u~``. So

    f_z = (f(x, p), 0),   g_z = (g(x, p) M(p)^{-1}, 0),   Q_z = Q(x, p),   R = R0,

on Omega x [s_lo, s_hi]. Its finite-horizon HJB :eq:`eq-hjbt` holds on every slice s = const separately (no
derivative in s appears), and its value on that slice is V_T(x; p). Training samples s uniformly (p log-uniformly
where the range spans decades), and every solver, residual, optimiser and checkpoint works on it unchanged.

* :class:`ParametricFamily`: f, g, Q and R as functions of p; :meth:`~ParametricFamily.at` gives one member as
  an ordinary system (for a reference solution, say).
* :class:`WeightFamily`: the common case R = r R0 of one system, r over a range.
* :class:`FamilyMember`: a trained family read at one p, with the interface of a solution.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from .systems import ControlAffineSystem

__all__ = ["ParametricFamily", "WeightFamily", "FamilyMember"]


def _spd_sqrt(M: torch.Tensor, power: float) -> torch.Tensor:
    """M^power of a batch of symmetric positive definite matrices (N, m, m), by eigendecomposition."""
    w, U = torch.linalg.eigh(M)
    return U @ torch.diag_embed(w**power) @ U.transpose(-1, -2)


@dataclass(frozen=True, eq=False)
class ParametricFamily:
    """The systems ``xdot = f(x, p) + g(x, p) u``, cost ``Q(x, p) + u'R(p)u``, for every p in ``p_range``.

    * ``name``: a label.
    * ``f``: batched torch callable, (x (N, n), p (N,)) -> (N, n).
    * ``g``: batched torch callable, (x, p) -> (N, n, m).
    * ``Q``: batched torch callable, (x, p) -> (N,).
    * ``R``: the control weight, an (m, m) matrix that does not depend on p, or a batched torch callable
      p (N,) -> (N, m, m), symmetric positive definite for every p in range.
    * ``domain``: Omega of x, a box (n, 2).
    * ``p_range``: (p_lo, p_hi), p_lo < p_hi, both finite.
    * ``train_domain``: the training box of x; None: ``domain``.
    * ``log``: sample s = log10 p uniformly (p log-uniformly; needs p_lo > 0); None: when p_lo > 0 and
      p_hi >= 10 p_lo (the range spans a decade or more); False: s = p, uniform.
    * ``system`` (set from the rest): the augmented system on ``(x, s)`` to hand to a solver.

    :meth:`value`, :meth:`gradient`, :meth:`policy` and :meth:`member` read a solution of ``system`` at any p in
    range; :meth:`at` builds one member as an ordinary system.
    """

    name: str
    f: Callable
    g: Callable
    Q: Callable
    R: object
    domain: object
    p_range: tuple[float, float]
    train_domain: object = None
    log: bool | None = None
    system: ControlAffineSystem = field(init=False, repr=False)

    def __post_init__(self):
        for key in ("f", "g", "Q"):
            if not callable(getattr(self, key)):
                raise TypeError(f"family '{self.name}': {key} must be a batched torch callable (x, p)")
        try:
            lo, hi = (float(v) for v in self.p_range)
        except (TypeError, ValueError):
            raise ValueError(f"p_range must be two numbers (p_lo, p_hi); got {self.p_range!r}") from None
        if not (-math.inf < lo < hi < math.inf):
            raise ValueError(f"p_range must satisfy p_lo < p_hi, both finite; got {self.p_range!r}")
        log = (lo > 0 and hi >= 10 * lo) if self.log is None else bool(self.log)
        if log and lo <= 0:
            raise ValueError(f"log=True samples log10 p, which needs p_lo > 0; got p_range={self.p_range!r}")
        object.__setattr__(self, "p_range", (lo, hi))
        object.__setattr__(self, "log", log)
        if callable(self.R):
            probe = torch.tensor([lo, self.p_of(torch.tensor(0.0)).item(), hi], dtype=torch.float64)  # s = 0: p_c
            Rp = self.R(probe)
            if not isinstance(Rp, torch.Tensor) or Rp.ndim != 3 or Rp.shape[0] != 3 or Rp.shape[1] != Rp.shape[2]:
                raise ValueError(f"family '{self.name}': R(p) must return (N, m, m) for p of shape (N,)")
            sym = torch.allclose(Rp, Rp.transpose(-1, -2), rtol=1e-12, atol=1e-12)
            if not sym or bool((torch.linalg.eigvalsh(Rp) <= 0).any()):
                raise ValueError(f"family '{self.name}': R(p) must be symmetric positive definite at p_lo, mid, p_hi")
            object.__setattr__(self, "_R0_root", _spd_sqrt(torch.as_tensor(self.R0)[None], 0.5)[0].numpy())
        object.__setattr__(self, "system", self._augmented())

    # ------------------------------------------------------------------ the parameter and its coordinate
    @property
    def centre(self) -> float:
        """The middle of the range in the coordinate's scale: (log10 p_lo + log10 p_hi) / 2, or (p_lo + p_hi) / 2."""
        lo, hi = self.p_range
        return (math.log10(lo) + math.log10(hi)) / 2 if self.log else (lo + hi) / 2

    @property
    def s_range(self) -> tuple[float, float]:
        """The range of the last coordinate s, symmetric about 0."""
        lo, hi = self.p_range
        c = self.centre
        return (math.log10(lo) - c, math.log10(hi) - c) if self.log else (lo - c, hi - c)

    def p_of(self, s: torch.Tensor) -> torch.Tensor:
        """p from the coordinate s."""
        return torch.pow(10.0, s + self.centre) if self.log else s + self.centre

    @property
    def R0(self) -> np.ndarray:
        """The augmented system's weight: R itself when constant, else R(p) at the middle of the s range."""
        if not callable(self.R):
            return np.atleast_2d(np.asarray(self.R, dtype=float))
        mid = self.p_of(torch.zeros(1, dtype=torch.float64))  # s = 0 is the middle p_c
        return self.R(mid)[0].detach().numpy()

    def _input_map(self, s: torch.Tensor):
        """M(p)^{-1} (N, m, m) with u = M^{-1} u~, or None when R does not depend on p."""
        if not callable(self.R):
            return None
        root = torch.as_tensor(self._R0_root, dtype=s.dtype, device=s.device)  # R0^{1/2}
        return _spd_sqrt(self.R(self.p_of(s)).to(s.dtype), -0.5) @ root

    @staticmethod
    def _map(M, v: torch.Tensor) -> torch.Tensor:
        """``M v`` for the input map: a scalar per state (N,), or (N, m, m)."""
        return v * M[:, None] if M.ndim == 1 else (M @ v[..., None])[..., 0]

    def _label(self) -> str:
        lo, hi = self.p_range
        return f"{self.name} over p in [{lo:g}, {hi:g}]"

    def _augmented(self) -> ControlAffineSystem:
        n = np.asarray(self.domain, dtype=float).reshape(-1, 2).shape[0]
        s_box = [list(self.s_range)]

        def f(z):
            return torch.cat([self.f(z[:, :n], self.p_of(z[:, n])), torch.zeros_like(z[:, n:])], dim=-1)

        def g(z):
            gx = self.g(z[:, :n], self.p_of(z[:, n]))
            M = self._input_map(z[:, n])
            if M is not None:
                gx = gx * M[:, None, None] if M.ndim == 1 else gx @ M
            return torch.cat([gx, torch.zeros(z.shape[0], 1, gx.shape[-1], dtype=z.dtype, device=z.device)], dim=1)

        def Q(z):
            return self.Q(z[:, :n], self.p_of(z[:, n]))

        domain = np.asarray(self.domain, dtype=float).reshape(-1, 2)
        train = domain if self.train_domain is None else np.asarray(self.train_domain, dtype=float).reshape(-1, 2)
        return ControlAffineSystem(
            self._label(), f, g, Q, R=self.R0, domain=np.vstack([domain, s_box]), train_domain=np.vstack([train, s_box])
        )

    @property
    def n(self) -> int:
        """The dimension of x (the augmented state has n + 1)."""
        return self.system.n - 1

    def _check(self, p) -> np.ndarray:
        lo, hi = self.p_range
        arr = np.asarray(p.detach().cpu() if isinstance(p, torch.Tensor) else p, dtype=float)
        tol = 1e-12 * max(abs(lo), abs(hi))
        if not np.all((arr >= lo - tol) & (arr <= hi + tol)):
            raise ValueError(f"p must lie in p_range [{lo:g}, {hi:g}]; got {p}")
        return arr

    def _s(self, arr: np.ndarray) -> np.ndarray:
        return np.log10(arr) - self.centre if self.log else arr - self.centre

    # ------------------------------------------------------------------ reading a trained family
    def states(self, x, p) -> np.ndarray | torch.Tensor:
        """The augmented states ``(x, s)``.

        * ``x``: (N, n) states (numpy or torch).
        * ``p``: a parameter in ``p_range``, or (N,) parameters.
        """
        s = self._s(self._check(p))
        if isinstance(x, torch.Tensor):
            s = torch.as_tensor(s, dtype=x.dtype, device=x.device).expand(x.shape[0])
            return torch.cat([x, s[:, None]], dim=-1)
        x = np.asarray(x, dtype=float)
        return np.column_stack([x, np.broadcast_to(s, (x.shape[0],))])

    def value(self, solution, x, p, t: float = 0.0, horizon: float | None = None):
        """V(x, t) of the member p, read from ``solution`` (a solution of ``system``).

        * ``solution``: a finite-horizon or steady-state solution of ``system``.
        * ``x``: (N, n) states.
        * ``p``: the parameter, or (N,) parameters.
        * ``t``, ``horizon``: as in :meth:`pinnhjb.solution.FiniteHorizonSolution.value`.

        Returns (N,).
        """
        kw = {} if horizon is None else {"horizon": horizon}
        return solution.value(self.states(x, p), t, **kw)

    def gradient(self, solution, x, p, t: float = 0.0, horizon: float | None = None):
        """grad_x V(x, t) of the member p; arguments as in :meth:`value`. Returns (N, n)."""
        kw = {} if horizon is None else {"horizon": horizon}
        return solution.gradient(self.states(x, p), t, **kw)[:, : self.n]

    def policy(self, solution, x, p, t: float = 0.0, horizon: float | None = None):
        """The member's policy ``mu = -1/2 R(p)^{-1} g(x, p)' grad_x V``; arguments as in :meth:`value`.

        Returns (N, m).
        """
        kw = {} if horizon is None else {"horizon": horizon}
        z = self.states(x, p)
        u_tilde = solution.policy(z, t, **kw)
        s = torch.as_tensor(np.asarray(z)[:, -1] if not isinstance(z, torch.Tensor) else z[:, -1], dtype=torch.float64)
        M = self._input_map(s)
        if M is None:
            return u_tilde
        u = self._map(M, torch.as_tensor(u_tilde, dtype=torch.float64).to(M.device))
        return u.to(u_tilde.dtype).to(u_tilde.device) if isinstance(u_tilde, torch.Tensor) else u.numpy()

    def at(self, p: float) -> ControlAffineSystem:
        """The member p as an ordinary system (its f, g, Q at p, and R(p)): for a reference or a per-p solver.

        * ``p``: the parameter, in ``p_range``.
        """
        p = float(self._check(p))
        n = self.n

        def full(x):
            return torch.full((x.shape[0],), p, dtype=x.dtype, device=x.device)

        R = self.R(torch.tensor([p], dtype=torch.float64))[0].detach().numpy() if callable(self.R) else self.R
        box = self.system.domain[:n]
        return ControlAffineSystem(
            f"{self.name} (p = {p:g})",
            lambda x: self.f(x, full(x)),
            lambda x: self.g(x, full(x)),
            lambda x: self.Q(x, full(x)),
            R=R,
            domain=box,
            train_domain=self.system.train_domain[:n],
        )

    def member(self, solution, p: float) -> FamilyMember:
        """The member p as read from ``solution``: an object with the solution interface.

        * ``solution``: a solution of ``system``.
        * ``p``: the parameter, in ``p_range``.
        """
        return FamilyMember(self, solution, float(self._check(p)), self.at(p))


class WeightFamily(ParametricFamily):
    """The systems ``base`` with control weight ``r * base.R`` for every r in ``r_range``, as one family.

    * ``base``: the system at r = 1.
    * ``r_range``: (r_lo, r_hi), 0 < r_lo < r_hi; r is sampled log-uniformly.

    The input map is the scalar ``M^{-1} = 1 / sqrt(r)`` (``g_z = g / sqrt(r)``, R0 = ``base.R``); ``p`` is r.
    """

    def __init__(self, base: ControlAffineSystem, r_range: tuple[float, float]):
        if not isinstance(base, ControlAffineSystem):
            raise TypeError(f"base must be a ControlAffineSystem; got {type(base).__name__}")
        try:
            lo, hi = (float(v) for v in r_range)
        except (TypeError, ValueError):
            raise ValueError(f"r_range must be two numbers (r_lo, r_hi); got {r_range!r}") from None
        if not (0 < lo < hi < math.inf):
            raise ValueError(f"r_range must satisfy 0 < r_lo < r_hi < inf; got {r_range!r}")
        object.__setattr__(self, "base", base)
        super().__init__(
            base.name,
            lambda x, p: base.f(x),
            lambda x, p: base.g(x),
            lambda x, p: base.Q(x),
            R=base.R,
            domain=base.domain,
            p_range=(lo, hi),
            train_domain=base.train_domain,
            log=True,
        )

    def __repr__(self) -> str:
        return f"WeightFamily(base={self.base.name!r}, r_range={self.r_range})"

    @property
    def r_range(self) -> tuple[float, float]:
        """The range of r (``p_range``)."""
        return self.p_range

    def _input_map(self, s: torch.Tensor):
        return torch.pow(10.0, -0.5 * (s + self.centre))  # 1 / sqrt(r), a scalar per state

    def _label(self) -> str:
        lo, hi = self.p_range
        return f"{self.base.name} over R = r R0, r in [{lo:g}, {hi:g}]"

    def _check(self, p) -> np.ndarray:
        try:
            return super()._check(p)
        except ValueError:
            lo, hi = self.p_range
            raise ValueError(f"r must lie in r_range [{lo:g}, {hi:g}]; got {p}") from None

    def at(self, p: float) -> ControlAffineSystem:
        """The base system with weight ``p * base.R`` (its name says so).

        * ``p``: the weight r, in ``r_range``.
        """
        r = float(self._check(p))
        return replace(self.base, name=f"{self.base.name} (R = {r:g} R0)", R=r * self.base.R, params=None, builder=None)


@dataclass(frozen=True)
class FamilyMember:
    """One member of a :class:`ParametricFamily`, read from a trained solution of the family's system.

    * ``family``: the family.
    * ``solution``: the trained solution of ``family.system``.
    * ``p``: the parameter (the weight r of a :class:`WeightFamily`).
    * ``system``: the member as an ordinary system (:meth:`ParametricFamily.at`).

    :meth:`value`, :meth:`gradient`, :meth:`policy` and :meth:`residual_field` take states x (N, n) of the
    member, as a solution of it would.
    """

    family: ParametricFamily
    solution: object
    p: float
    system: ControlAffineSystem

    @property
    def r(self) -> float:
        """The parameter, by the name a :class:`WeightFamily` gives it."""
        return self.p

    @property
    def horizon(self) -> float:
        """The solution's horizon (``inf`` for a steady-state solution)."""
        return getattr(self.solution, "horizon", math.inf)

    def value(self, x, t: float = 0.0, horizon: float | None = None):
        """V(x, t) of this member; as :meth:`pinnhjb.solution.FiniteHorizonSolution.value`."""
        return self.family.value(self.solution, x, self.p, t, horizon)

    def gradient(self, x, t: float = 0.0, horizon: float | None = None):
        """grad_x V(x, t) of this member. Returns (N, n)."""
        return self.family.gradient(self.solution, x, self.p, t, horizon)

    def policy(self, x, t: float = 0.0, horizon: float | None = None):
        """mu(x, t) of this member. Returns (N, m)."""
        return self.family.policy(self.solution, x, self.p, t, horizon)

    def residual_field(self, x, horizon: float | None = None):
        """The steady-state residual E_e :eq:`eq-ee` of this member's system at states ``x`` (N, n).

        The family's residual at (x, s) is the member's: f and g have no component along s, and the change of
        input leaves min_u H unchanged.
        """
        kw = {} if horizon is None else {"horizon": horizon}
        return self.solution.residual_field(self.family.states(x, self.p), **kw)
