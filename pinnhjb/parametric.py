"""One value network for every control weight: the weight R = r R0 as an input, r over a range.

The cost u' (r R0) u with ``u~ = sqrt(r) u`` is ``u~' R0 u~``, and ``g u = (g / sqrt(r)) u~``. So the problem for every
r at once is one control-affine system on the state ``z = (x, s)``, ``s = log10 r``, that never moves s:

    f_z = (f(x), 0),   g_z = (g(x) / sqrt(10^s), 0),   Q_z = Q(x),   R = R0,

on Omega x [log10 r_lo, log10 r_hi]. Its finite-horizon HJB :eq:`eq-hjbt` holds on every slice s = const
separately (no derivative in s appears), and its value on that slice is V_T(x; r R0). Training samples s uniformly,
so r log-uniformly, and every solver, residual, optimiser and checkpoint works on it unchanged.
:class:`WeightFamily` builds it and reads the trained solution back at any r: value, gradient and policy
``u = u~ / sqrt(r)``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from .systems import ControlAffineSystem

__all__ = ["WeightFamily", "FamilyMember"]


@dataclass(frozen=True)
class WeightFamily:
    """The systems ``base`` with control weight ``r * base.R`` for every r in ``r_range``, as one system.

    * ``base``: the system at r = 1.
    * ``r_range``: (r_lo, r_hi), 0 < r_lo < r_hi.
    * ``system`` (set from the two): the augmented system (state ``(x, log10 r)``) to hand to a solver.

    :meth:`value`, :meth:`gradient` and :meth:`policy` read a solution of ``system`` at any r in the range.
    """

    base: ControlAffineSystem
    r_range: tuple[float, float]
    system: ControlAffineSystem = field(init=False, repr=False)

    def __post_init__(self):
        if not isinstance(self.base, ControlAffineSystem):
            raise TypeError(f"base must be a ControlAffineSystem; got {type(self.base).__name__}")
        try:
            lo, hi = (float(v) for v in self.r_range)
        except (TypeError, ValueError):
            raise ValueError(f"r_range must be two numbers (r_lo, r_hi); got {self.r_range!r}") from None
        if not (0 < lo < hi < math.inf):
            raise ValueError(f"r_range must satisfy 0 < r_lo < r_hi < inf; got {self.r_range!r}")
        object.__setattr__(self, "r_range", (lo, hi))
        object.__setattr__(self, "system", self._augmented())

    @property
    def s_range(self) -> tuple[float, float]:
        """The range of s = log10 r."""
        return (math.log10(self.r_range[0]), math.log10(self.r_range[1]))

    def _augmented(self) -> ControlAffineSystem:
        base = self.base
        n, m = base.n, base.m
        s_box = [list(self.s_range)]

        def f(z):
            return torch.cat([base.f(z[:, :n]), torch.zeros_like(z[:, n:])], dim=-1)

        def g(z):
            scale = torch.pow(10.0, -0.5 * z[:, n])  # 1 / sqrt(r)
            gx = base.g(z[:, :n]) * scale[:, None, None]
            return torch.cat([gx, torch.zeros(z.shape[0], 1, m, dtype=z.dtype, device=z.device)], dim=1)

        def Q(z):
            return base.Q(z[:, :n])

        lo, hi = self.r_range
        return ControlAffineSystem(
            f"{base.name} over R = r R0, r in [{lo:g}, {hi:g}]",
            f,
            g,
            Q,
            R=base.R,
            domain=np.vstack([base.domain, s_box]),
            train_domain=np.vstack([base.train_domain, s_box]),
        )

    def states(self, x, r) -> np.ndarray | torch.Tensor:
        """The augmented states ``(x, log10 r)``.

        * ``x``: (N, n) states (numpy or torch).
        * ``r``: a weight in ``r_range``, or (N,) weights.
        """
        lo, hi = self.r_range
        r_arr = np.asarray(r.detach().cpu() if isinstance(r, torch.Tensor) else r, dtype=float)
        if not np.all((r_arr >= lo * (1 - 1e-12)) & (r_arr <= hi * (1 + 1e-12))):
            raise ValueError(f"r must lie in r_range [{lo:g}, {hi:g}]; got {r}")
        if isinstance(x, torch.Tensor):
            s = torch.as_tensor(np.log10(r_arr), dtype=x.dtype, device=x.device).expand(x.shape[0])
            return torch.cat([x, s[:, None]], dim=-1)
        x = np.asarray(x, dtype=float)
        return np.column_stack([x, np.broadcast_to(np.log10(r_arr), (x.shape[0],))])

    def value(self, solution, x, r, t: float = 0.0, horizon: float | None = None):
        """V(x, t) of the system with weight ``r * base.R``, read from ``solution`` (a solution of ``system``).

        * ``solution``: a finite-horizon or steady-state solution of ``system``.
        * ``x``: (N, n) states.
        * ``r``: the weight, or (N,) weights.
        * ``t``, ``horizon``: as in :meth:`pinnhjb.solution.FiniteHorizonSolution.value`.

        Returns (N,).
        """
        kw = {} if horizon is None else {"horizon": horizon}
        return solution.value(self.states(x, r), t, **kw)

    def gradient(self, solution, x, r, t: float = 0.0, horizon: float | None = None):
        """grad_x V(x, t) at weight ``r``; arguments as in :meth:`value`. Returns (N, n)."""
        kw = {} if horizon is None else {"horizon": horizon}
        return solution.gradient(self.states(x, r), t, **kw)[:, : self.base.n]

    def policy(self, solution, x, r, t: float = 0.0, horizon: float | None = None):
        """The policy ``mu = -1/2 (r R0)^{-1} g(x)' grad_x V`` at weight ``r``; arguments as in :meth:`value`.

        Returns (N, m).
        """
        kw = {} if horizon is None else {"horizon": horizon}
        u_tilde = solution.policy(self.states(x, r), t, **kw)
        scale = np.sqrt(np.asarray(r, dtype=float))
        if isinstance(u_tilde, torch.Tensor):
            scale = torch.as_tensor(scale, dtype=u_tilde.dtype, device=u_tilde.device)
        scale = scale.reshape(-1, 1) if np.ndim(r) else scale
        return u_tilde / scale

    def member(self, solution, r: float) -> FamilyMember:
        """The system with weight ``r * base.R`` as read from ``solution``: an object with the solution interface.

        * ``solution``: a solution of ``system``.
        * ``r``: the weight, in ``r_range``.
        """
        self.states(np.zeros((1, self.base.n)), r)  # checks r
        system = replace(
            self.base, name=f"{self.base.name} (R = {r:g} R0)", R=r * self.base.R, params=None, builder=None
        )
        return FamilyMember(self, solution, float(r), system)


@dataclass(frozen=True)
class FamilyMember:
    """One weight of a :class:`WeightFamily`, read from a trained solution of the family's system.

    * ``family``: the family.
    * ``solution``: the trained solution of ``family.system``.
    * ``r``: the weight.
    * ``system``: the base system with weight ``r * R0``.

    :meth:`value`, :meth:`gradient`, :meth:`policy` and :meth:`residual_field` take states x (N, n) of the base
    system, as a solution of it would.
    """

    family: WeightFamily
    solution: object
    r: float
    system: ControlAffineSystem

    @property
    def horizon(self) -> float:
        """The solution's horizon (``inf`` for a steady-state solution)."""
        return getattr(self.solution, "horizon", math.inf)

    def value(self, x, t: float = 0.0, horizon: float | None = None):
        """V(x, t) at this weight; as :meth:`pinnhjb.solution.FiniteHorizonSolution.value`."""
        return self.family.value(self.solution, x, self.r, t, horizon)

    def gradient(self, x, t: float = 0.0, horizon: float | None = None):
        """grad_x V(x, t) at this weight. Returns (N, n)."""
        return self.family.gradient(self.solution, x, self.r, t, horizon)

    def policy(self, x, t: float = 0.0, horizon: float | None = None):
        """mu(x, t) at this weight. Returns (N, m)."""
        return self.family.policy(self.solution, x, self.r, t, horizon)

    def residual_field(self, x, horizon: float | None = None):
        """The steady-state residual E_e :eq:`eq-ee` of this weight's system at states ``x`` (N, n).

        The family's residual at (x, log10 r) is this system's: f and g have no component along s.
        """
        kw = {} if horizon is None else {"horizon": horizon}
        return self.solution.residual_field(self.family.states(x, self.r), **kw)
