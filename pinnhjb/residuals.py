"""The PDE residuals the PINNs minimise: one object per PDE form, registered by name.

Each form owns its batched residual (Adam, L-BFGS and evaluation), its per-point form (Levenberg-Marquardt
accepts or rejects a step on it) and, where it has one, its structured Jacobian (:mod:`pinnhjb.jacobian`). The
physics stays in :meth:`pinnhjb.systems.ControlAffineSystem.hamiltonian_min`; a form says how the value's
derivatives enter it (:meth:`Residual.pde`).

* :class:`FiniteHorizonHJB` (``"hjbt"``): F_e :eq:`eq-fe` of the finite-horizon HJB :eq:`eq-hjbt` under the hard
  ansatz of :class:`~pinnhjb.pinn.FiniteHorizonValue`, where F_b :eq:`eq-fb` and F_in :eq:`eq-fin` vanish by
  construction.
* :class:`SoftFiniteHorizonHJB` (``"hjbt_soft"``): the paper's soft-constraint form, F_e, F_b and F_in in the
  loss :eq:`eq-mse`.
* :class:`SteadyStateHJB` (``"hjb"``): the steady-state pointwise residual E_e :eq:`eq-ee` of the steady-state HJB
  :eq:`eq-hjb`, summed into the horizon check E :eq:`eq-e` by :mod:`pinnhjb.metrics`.

A new form is one new class plus a registration line: subclass one of these (often only :meth:`Residual.pde`
changes) and decorate it with :func:`register`; then ``train_finite_horizon(..., residual="its name")``.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import ClassVar

import torch
from torch import nn
from torch.func import functional_call, grad

from .jacobian import residual_jacobian
from .pinn import gradient, value_and_gradients

Tensor = torch.Tensor

__all__ = [
    "Residual",
    "FiniteHorizonHJB",
    "SoftFiniteHorizonHJB",
    "SteadyStateHJB",
    "RESIDUALS",
    "register",
    "get_residual",
]

RESIDUALS: dict[str, type[Residual]] = {}

_CHUNK = 16384  # points per autograd pass in :meth:`SteadyStateHJB.field`


def register(name: str):
    """Class decorator that registers a residual form under ``name`` (and sets its ``name``).

    * ``name``: the key :func:`get_residual` and ``train_finite_horizon(..., residual=name)`` take.
    """

    def decorate(cls: type[Residual]) -> type[Residual]:
        if not (isinstance(cls, type) and issubclass(cls, Residual)):
            raise TypeError(f"register({name!r}) needs a subclass of Residual; got {cls!r}")
        if RESIDUALS.get(name, cls) is not cls:
            raise ValueError(f"a residual form {name!r} is already registered ({RESIDUALS[name].__name__})")
        cls.name = name
        RESIDUALS[name] = cls
        return cls

    return decorate


def get_residual(form: str | type[Residual]) -> type[Residual]:
    """The residual class registered under a name (a class is returned as it is).

    * ``form``: a registered name such as ``"hjbt"``, or a :class:`Residual` subclass.
    """
    if isinstance(form, type) and issubclass(form, Residual):
        return form
    if form not in RESIDUALS:
        raise KeyError(f"unknown residual form {form!r}; registered: {sorted(RESIDUALS)}")
    return RESIDUALS[form]


class Residual:
    """A PDE form on a value model: its residual, batched and per point, and its Jacobian in the weights.

    * ``system``: the :class:`~pinnhjb.systems.ControlAffineSystem` whose f, g, Q, R enter the PDE.
    * ``model``: the value model the residual is taken of.

    Training batches carry cached data (``x``, ``fx``, ``gx``, ``qx`` and, under a terminal cost, ``phi`` and
    ``dphi``: :class:`pinnhjb.training.StatePool`).
    """

    name: ClassVar[str] = ""
    ansatz: ClassVar[bool | None] = None  # the model's ansatz flag this form trains (None: any)
    time_dependent: ClassVar[bool] = True  # whether its collocation points carry a time

    def __init__(self, system, model):
        self.system = system
        self.model = model

    def pde(self, *args, **kwargs) -> Tensor:  # pragma: no cover - abstract
        """The residual from the value's derivatives, per point."""
        raise NotImplementedError

    def loss(self, *batch) -> Tensor:  # pragma: no cover - abstract
        """The training loss on one batch: a mean of squared residuals :eq:`eq-mse`."""
        raise NotImplementedError

    def point_arguments(self, data: dict, t: Tensor | None) -> tuple:
        """The per-point arguments of :meth:`point_residual`, batched, from cached data.

        * ``data``: cached states and their f, g, Q (and terminal cost) from :class:`~pinnhjb.training.StatePool`.
        * ``t``: the points' times (None for a form without time).
        """
        raise NotImplementedError(f"the residual form {self.name!r} has no per-point form (no Levenberg-Marquardt)")

    def point_residual(self, flat) -> Callable[..., Tensor]:
        """One point's residual as a function ``(theta, *point) -> scalar`` of the flat weights.

        * ``flat``: the :class:`~pinnhjb.gauss_newton.FlatParameters` of the model's network.
        """
        raise NotImplementedError(f"the residual form {self.name!r} has no per-point form (no Levenberg-Marquardt)")

    def jacobian(self) -> Callable[..., tuple[Tensor, Tensor]] | None:
        """``(theta, *batch) -> (r, J)`` by the structured Jacobian, or None (LM then uses ``vmap(jacrev)``)."""
        return None


class _Correction(nn.Module):
    """``model.correction`` as a module's forward, so :func:`torch.func.functional_call` can swap its weights."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, x: Tensor, t: Tensor) -> Tensor:
        return self.model.correction(x, t)


@register("hjbt")
class FiniteHorizonHJB(Residual):
    """F_e :eq:`eq-fe` of the finite-horizon HJB :eq:`eq-hjbt` under the hard ansatz; F_b and F_in vanish exactly.

    * ``system``: the control-affine system.
    * ``model``: a :class:`~pinnhjb.pinn.FiniteHorizonValue` with ``ansatz=True`` to train; any module
      ``(x, t) -> v`` for :meth:`evaluate`.
    """

    ansatz = True

    def pde(
        self,
        x: Tensor,
        grad_x: Tensor,
        dt: Tensor,
        fx: Tensor | None = None,
        gx: Tensor | None = None,
        qx: Tensor | None = None,
    ) -> Tensor:
        """F_e = dv/dt + min_u H(x, u, grad_x v) :eq:`eq-fe`, per point (N,).

        * ``x``: states (N, n).
        * ``grad_x``: grad_x v at the points (N, n).
        * ``dt``: dv/dt at the points (N,).
        * ``fx``, ``gx``, ``qx``: f(x), g(x), Q(x) when cached (else computed from ``x``).
        """
        return dt + self.system.hamiltonian_min(x, grad_x, fx, gx, qx)

    def evaluate(self, x: Tensor, t: Tensor | float, create_graph: bool = False) -> Tensor:
        """F_e of the whole model (earlier stages and terminal cost included) by autograd, per point (N,).

        * ``x``: states (N, n).
        * ``t``: times, (N,) or a scalar.
        * ``create_graph``: keep the graph (to differentiate F_e further).
        """
        _, gx, gt = value_and_gradients(self.model, x, t, create_graph=create_graph)
        return self.pde(x, gx, gt)

    def residual(self, flow: dict, t: Tensor, shared_times: tuple | None = None) -> Tensor:
        """F_e on a training batch of cached states, differentiable in the weights (N,).

        * ``flow``: cached states (``x``, ``fx``, ``gx``, ``qx``, ``dphi``) of the batch.
        * ``t``: the points' times (N,).
        * ``shared_times``: ``(times, index)`` with ``t = times[index]`` (``TrainConfig.points_per_time``), or None.
        """
        x = flow["x"]
        gx, gt = self.model.correction_derivatives(x, t, *(shared_times or (None, None)))
        gx = gx + flow["dphi"]
        return self.pde(x, gx, gt, flow["fx"], flow["gx"], flow["qx"])

    def loss(
        self,
        flow: dict,
        t: Tensor,
        boundary: dict | None = None,
        t_origin: Tensor | None = None,
        shared_times: tuple | None = None,
    ) -> Tensor:
        """MSE_e, the whole of :eq:`eq-mse` under the ansatz: mean F_e^2 on one batch.

        * ``flow``, ``t``, ``shared_times``: as in :meth:`residual`.
        * ``boundary``, ``t_origin``: unused (F_b and F_in vanish by construction).
        """
        return (self.residual(flow, t, shared_times) ** 2).mean()

    def point_arguments(self, data: dict, t: Tensor | None) -> tuple:
        """``(x, t, grad phi, f, g, Q)``: the cached terminal gradient included, so earlier stages are not rerun.

        * ``data``: cached states of the batch.
        * ``t``: the points' times (N,).
        """
        return data["x"], t, data["dphi"], data["fx"], data["gx"], data["qx"]

    def point_residual(self, flat) -> Callable[..., Tensor]:
        """F_e of one point, ``(theta, x, t, grad phi, f, g, Q) -> scalar``, in the network's flat weights.

        * ``flat``: the :class:`~pinnhjb.gauss_newton.FlatParameters` of ``model.net``.
        """
        wrapper = _Correction(self.model)

        def correction(theta, x, t):
            return functional_call(wrapper, flat.unflatten(theta, "model.net."), (x.unsqueeze(0), t.reshape(1)))[0]

        def residual(theta, x, t, dphi, fx, gx, qx):
            gxc, gtc = grad(correction, argnums=(1, 2))(theta, x, t)
            return self.pde(x[None], (gxc + dphi)[None], gtc[None], fx[None], gx[None], qx[None])[0]

        return residual

    def jacobian(self) -> Callable[..., tuple[Tensor, Tensor]] | None:
        """The batched twin of :meth:`point_residual`: (r, J) by :func:`~pinnhjb.jacobian.residual_jacobian`, with
        N(x, t) and N(0, t) of the ansatz as two network rows per point. A ``flat_origin`` model's origin rows also
        carry the slope's direction (x, 0) as a tangent and d/dt of the slope x' grad_x N(0, t) as the mixed
        derivative along it and t."""
        model, n = self.model, self.system.n
        flat_origin = getattr(model, "flat_origin", False)

        def jacobian(theta, x, t, dphi, fx, gx, qx):
            N = x.shape[0]
            z = torch.cat([model.net_inputs(x, t), model.net_inputs(torch.zeros_like(x), t)])
            scale = model.input_scale(x)
            dz = torch.diag(scale).expand(2 * N, n + 1, n + 1)
            if not flat_origin:

                def residual_of(out, dout):
                    gxc, gtc = model.ansatz_derivatives(t, out[:N], out[N:], dout[:N, :n], dout[:N, n], dout[N:, n])
                    return self.pde(x, gxc + dphi, gtc, fx, gx, qx)

                return residual_jacobian(model.net, theta, z, dz, residual_of, copies=2)
            # the slope's direction: (x, 0) scaled at the origin rows (unused at the x rows)
            slope_dir = torch.cat([x * scale[:n], torch.zeros_like(x[:, :1])], dim=-1).repeat(2, 1)
            dz = torch.cat([dz, slope_dir.unsqueeze(1)], dim=1)

            def flat_residual_of(out, dout, ddout):
                flat = (dout[N:, :n], dout[N:, n + 1], ddout[N:])  # grad_x N(0, t), the slope, its d/dt
                gxc, gtc = model.ansatz_derivatives(
                    t, out[:N], out[N:], dout[:N, :n], dout[:N, n], dout[N:, n], flat=flat
                )
                return self.pde(x, gxc + dphi, gtc, fx, gx, qx)

            return residual_jacobian(model.net, theta, z, dz, flat_residual_of, copies=2, mixed=(n + 1, n))

        return jacobian


@register("hjbt_soft")
class SoftFiniteHorizonHJB(FiniteHorizonHJB):
    """The paper's soft-constraint form of :eq:`eq-hjbt`: F_e, F_b and F_in all in the loss :eq:`eq-mse`.

    The residuals are :eq:`eq-fe`, :eq:`eq-fb` and :eq:`eq-fin`.

    * ``system``: the control-affine system.
    * ``model``: a :class:`~pinnhjb.pinn.FiniteHorizonValue` with ``ansatz=False`` (the plain network N(x, t)).

    Trained by Adam and L-BFGS only: it has no per-point form, so no Levenberg-Marquardt.
    """

    ansatz = False

    def residual(self, flow: dict, t: Tensor, shared_times: tuple | None = None) -> Tensor:
        """F_e of the plain network on a training batch of cached states (N,).

        * ``flow``: cached states (``x``, ``fx``, ``gx``, ``qx``) of the batch.
        * ``t``: the points' times (N,).
        * ``shared_times``: unused (every point has its own time).
        """
        x = flow["x"]
        gx, gt = self.model.correction_derivatives(x, t)
        return self.pde(x, gx, gt, flow["fx"], flow["gx"], flow["qx"])

    def terminal_residual(self, boundary: dict) -> Tensor:
        """F_b = N(x, T) - phi(x) :eq:`eq-fb` on cached boundary states (N_b,).

        * ``boundary``: cached states ``x`` and their terminal cost ``phi``.
        """
        xb = boundary["x"]
        t_end = torch.full((xb.shape[0],), self.model.horizon, dtype=xb.dtype, device=xb.device)
        return self.model.raw(xb, t_end) - boundary["phi"]

    def origin_residual(self, t_origin: Tensor, like: Tensor) -> Tensor:
        """F_in = N(0, t) :eq:`eq-fin` at the given times (N_in,).

        * ``t_origin``: times (N_in,).
        * ``like``: states (any number, n) whose dimension, dtype and device the origin takes.
        """
        zero = torch.zeros(t_origin.shape[0], like.shape[1], dtype=like.dtype, device=like.device)
        return self.model.raw(zero, t_origin)

    def loss(
        self,
        flow: dict,
        t: Tensor,
        boundary: dict | None = None,
        t_origin: Tensor | None = None,
        shared_times: tuple | None = None,
    ) -> Tensor:
        """MSE_e + MSE_b + MSE_in :eq:`eq-mse` on one batch.

        * ``flow``, ``t``: the flow points, as in :meth:`residual`.
        * ``boundary``: cached terminal states for F_b.
        * ``t_origin``: times for F_in.
        * ``shared_times``: unused.
        """
        loss = (self.residual(flow, t) ** 2).mean()
        f_b = self.terminal_residual(boundary)
        f_in = self.origin_residual(t_origin, boundary["x"])
        return loss + (f_b**2).mean() + (f_in**2).mean()

    def point_arguments(self, data: dict, t: Tensor | None) -> tuple:
        return Residual.point_arguments(self, data, t)

    def point_residual(self, flat) -> Callable[..., Tensor]:
        return Residual.point_residual(self, flat)

    def jacobian(self) -> None:
        return None


@register("hjb")
class SteadyStateHJB(Residual):
    """E_e :eq:`eq-ee`, the pointwise residual of the steady-state HJB :eq:`eq-hjb`.

    Its mean square plus V(0)^2 is the horizon check E :eq:`eq-e`.

    * ``system``: the control-affine system.
    * ``model``: a :class:`~pinnhjb.pinn.SteadyStateValue` to train (per-point form and Jacobian: ansatz only);
      any batched value function ``x -> V(x)`` for :meth:`evaluate` and :meth:`field`.
    """

    time_dependent = False

    def pde(
        self, x: Tensor, grad_x: Tensor, fx: Tensor | None = None, gx: Tensor | None = None, qx: Tensor | None = None
    ) -> Tensor:
        """E_e = min_u H(x, u, grad V) :eq:`eq-ee`, per point (N,).

        * ``x``: states (N, n).
        * ``grad_x``: grad V at the points (N, n).
        * ``fx``, ``gx``, ``qx``: f(x), g(x), Q(x) when cached (else computed from ``x``).
        """
        return self.system.hamiltonian_min(x, grad_x, fx, gx, qx)

    def evaluate(self, x: Tensor, create_graph: bool = False) -> Tensor:
        """E_e of the value function by autograd, per point (N,).

        * ``x``: states (N, n).
        * ``create_graph``: keep the graph (to differentiate E_e further).
        """
        _, g = gradient(self.model, x, create_graph=create_graph)
        return self.pde(x, g)

    def field(self, points: Tensor) -> Tensor:
        """E_e at every point, detached, evaluated in chunks (for E and for plots), shape (N,).

        * ``points``: states (N, n), checked by ``system.check_states``.
        """
        self.system.check_states(points, "points")
        out = []
        for xc in torch.split(points, _CHUNK):
            _, g = gradient(self.model, xc)
            out.append(self.pde(xc, g).detach())
        return torch.cat(out)

    def residual(self, flow: dict) -> Tensor:
        """E_e on a training batch of cached states, differentiable in the weights (N,).

        * ``flow``: cached states (``x``, ``fx``, ``gx``, ``qx``) of the batch.
        """
        x = flow["x"].detach().requires_grad_(True)
        v = self.model(x)
        (gx,) = torch.autograd.grad(v.sum(), x, create_graph=True)
        return self.pde(x, gx, flow["fx"], flow["gx"], flow["qx"])

    def loss(self, flow: dict) -> Tensor:
        """Mean E_e^2 on one batch, plus V(0)^2 when the ansatz does not enforce V(0) = 0: the two terms of :eq:`eq-e`.

        * ``flow``: cached states of the batch.
        """
        loss = (self.residual(flow) ** 2).mean()
        if not self.model.ansatz:
            loss = loss + self.model(torch.zeros_like(flow["x"][:1])).pow(2).sum()
        return loss

    def point_arguments(self, data: dict, t: Tensor | None = None) -> tuple:
        """``(x, f, g, Q)`` of the batch.

        * ``data``: cached states of the batch.
        * ``t``: unused (no time).
        """
        return data["x"], data["fx"], data["gx"], data["qx"]

    def point_residual(self, flat) -> Callable[..., Tensor]:
        """E_e of one point, ``(theta, x, f, g, Q) -> scalar``, in the network's flat weights (ansatz only).

        * ``flat``: the :class:`~pinnhjb.gauss_newton.FlatParameters` of ``model.net``.
        """
        model = self.model

        def value(theta, x):
            return functional_call(model, flat.unflatten(theta, "net."), (x.unsqueeze(0),))[0]

        def residual(theta, x, fx, gx, qx):
            gv = grad(value, argnums=1)(theta, x)
            return self.pde(x[None], gv[None], fx[None], gx[None], qx[None])[0]

        return residual

    def jacobian(self) -> Callable[..., tuple[Tensor, Tensor]]:
        """The batched twin of :meth:`point_residual` (V = N(x) - N(0), so grad V = grad N(x))."""
        model, n = self.model, self.system.n

        def jacobian(theta, x, fx, gx, qx):
            dz = torch.diag(model.scale_x_derivative(x)).expand(x.shape[0], n, n)
            return residual_jacobian(
                model.net, theta, model.scale_x(x), dz, lambda out, dout: self.pde(x, dout, fx, gx, qx)
            )

        return jacobian
