"""Value networks (Section 3), their terminal costs, and the autograd helpers the residuals use.

:class:`FiniteHorizonValue` is ``v_T(x, t)`` for the finite-horizon HJB :eq:`eq-hjbt`. With ``ansatz=True`` (the
default) it is ``v(x, t) = phi(x) + (T - t)/T * (N(x, t) - N(0, t))``, so that the terminal condition
:eq:`eq-fb` and the origin condition :eq:`eq-fin` (when phi(0) = 0) hold exactly; with ``ansatz=False`` it is
the paper's plain network ``N(x, t)`` and both conditions enter the loss. :class:`SteadyStateValue` is ``V(x)``
for the direct steady-state PINN. Derivatives come from autograd, never from finite differences.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch
from torch import nn

Tensor = torch.Tensor

#: The activations a network may use, by name: ``"tanh"`` (the paper's), ``"sigmoid"``, ``"softplus"``, ``"silu"``,
#: ``"gelu"``.
ACTIVATIONS: dict[str, type[nn.Module]] = {
    "tanh": nn.Tanh,
    "sigmoid": nn.Sigmoid,
    "softplus": nn.Softplus,
    "silu": nn.SiLU,
    "gelu": nn.GELU,
}

#: sigma'(h) from h and y = sigma(h), for the activations that have a closed form (torch differentiates the others).
ACTIVATION_DERIVATIVES: dict[type[nn.Module], Callable[[Tensor, Tensor], Tensor]] = {
    nn.Tanh: lambda h, y: 1.0 - y * y,
    nn.Sigmoid: lambda h, y: y * (1.0 - y),
}

__all__ = [
    "ACTIVATION_DERIVATIVES",
    "MLP",
    "FiniteHorizonValue",
    "SteadyStateValue",
    "ZeroTerminalCost",
    "QuadraticTerminalCost",
    "ValueTerminalCost",
    "CallableTerminalCost",
    "value_and_gradients",
    "gradient",
]


class MLP(nn.Module):
    """A fully connected network R^d -> R (the paper's: 3 hidden layers of 100 tanh units).

    * ``in_dim``: d.
    * ``width``: units per hidden layer.
    * ``depth``: hidden layers.
    * ``activation``: a key of :data:`ACTIVATIONS`.
    """

    def __init__(self, in_dim: int, width: int = 100, depth: int = 3, activation: str = "tanh"):
        super().__init__()
        if activation not in ACTIVATIONS:
            raise ValueError(f"unknown activation {activation!r}; choose one of {sorted(ACTIVATIONS)}")
        if width < 1 or depth < 1:
            raise ValueError(f"width and depth must be positive; got width={width}, depth={depth}")
        layers: list[nn.Module] = []
        d = in_dim
        for _ in range(depth):
            layers += [nn.Linear(d, width), ACTIVATIONS[activation]()]
            d = width
        layers.append(nn.Linear(d, 1))
        self.layers = nn.Sequential(*layers)

    def forward(self, z: Tensor) -> Tensor:
        return self.layers(z).squeeze(-1)

    def zero_output_(self) -> MLP:
        """Zero the last layer in place, so that the network is 0 everywhere and keeps its hidden layers (the
        ``"features"`` start of :class:`~pinnhjb.config.TrainConfig`'s ``warm_start``). Returns the network."""
        with torch.no_grad():
            self.layers[-1].weight.zero_()
            self.layers[-1].bias.zero_()
        return self

    def tangent(self, z: Tensor, dz: Tensor) -> tuple[Tensor, Tensor]:
        """The output and its derivative along ``dz`` at ``z`` (both (M, d)): forward mode, layer by layer, with
        the closed-form derivatives of :data:`ACTIVATION_DERIVATIVES` (``torch.func.jvp`` of other activations).
        Plain torch operations, so it composes with autograd and with torch.func's vmap, grad and jacrev; at the
        sizes used here several times faster than ``torch.func.jvp`` of the whole network. Returns (M,), (M,)."""
        a, da = z, dz
        for layer in self.layers:
            if isinstance(layer, nn.Linear):
                a, da = layer(a), da @ layer.weight.T
            elif type(layer) in ACTIVATION_DERIVATIVES:
                y = layer(a)
                a, da = y, ACTIVATION_DERIVATIVES[type(layer)](a, y) * da
            else:
                a, da = torch.func.jvp(layer, (a,), (da,))
        return a.squeeze(-1), da.squeeze(-1)


class _Scaled(nn.Module):
    """Shared input scaling: states mapped from the training box to [-1, 1]^n."""

    def __init__(self, train_domain):
        super().__init__()
        box = torch.as_tensor(np.asarray(train_domain, dtype=float), dtype=torch.get_default_dtype())
        self.register_buffer("center", (box[:, 0] + box[:, 1]) / 2)
        self.register_buffer("halfwidth", (box[:, 1] - box[:, 0]) / 2)

    def scale_x(self, x: Tensor) -> Tensor:
        return (x - self.center) / self.halfwidth

    def scale_x_derivative(self, like: Tensor) -> Tensor:
        """d scale_x / d x, a diagonal: 1 / halfwidth, shape (n,), in ``like``'s dtype and device."""
        return 1.0 / self.halfwidth.to(like)


# ---------------------------------------------------------------------- terminal costs


class ZeroTerminalCost(nn.Module):
    """The terminal cost phi = 0 (the paper's choice in all its simulations)."""

    def forward(self, x: Tensor) -> Tensor:
        return torch.zeros(x.shape[0], dtype=x.dtype, device=x.device)

    def spec(self) -> dict:
        return {"kind": "zero"}


class QuadraticTerminalCost(nn.Module):
    """The terminal cost ``phi(x) = x'Px``, e.g. psi + V* in the LQ illustrations of :prf:ref:`lem-uniform-above`.

    * ``P``: (n, n).
    """

    def __init__(self, P):
        super().__init__()
        self.register_buffer("P", torch.as_tensor(np.asarray(P, dtype=float)))

    def forward(self, x: Tensor) -> Tensor:
        return torch.einsum("bi,ij,bj->b", x, self.P.to(x.dtype), x)

    def spec(self) -> dict:
        return {"kind": "quadratic", "P": self.P.tolist()}


class CallableTerminalCost(nn.Module):
    """A terminal cost phi given by a user's function.

    Code is not stored in a checkpoint: without ``name`` such a solution cannot be saved; with a ``name`` it is
    saved under that name, and :func:`pinnhjb.storage.load` then asks for the same function back
    (``terminal_cost=``) instead of silently using another phi.

    * ``fn``: a batched torch callable x (N, n) -> (N,).
    * ``name``: the name it is saved under; None: not savable.
    """

    def __init__(self, fn: Callable[[Tensor], Tensor], name: str | None = None):
        super().__init__()
        self.fn = fn
        self.name = name

    def forward(self, x: Tensor) -> Tensor:
        return self.fn(x)

    def spec(self) -> dict:
        return {"kind": "callable"} if self.name is None else {"kind": "named", "name": self.name}


class ValueTerminalCost(nn.Module):
    """The terminal cost ``phi(x) = V_T(x, 0)`` of a previous, frozen stage: the horizon extension's :eq:`eq-hjbinc`.

    The previous stage is held by reference, not registered as a submodule: a chain of K stages is K flat
    modules, not K nested ones, so moving, freezing or printing a stage never recurses through the whole chain
    (and a chain of any length stays below Python's recursion limit). :meth:`FiniteHorizonValue.forward`
    walks the chain iteratively.

    * ``previous``: the previous stage's :class:`FiniteHorizonValue`; its weights are frozen.
    """

    def __init__(self, previous: FiniteHorizonValue):
        super().__init__()
        object.__setattr__(self, "previous", previous)  # not a submodule: see the class docstring
        for p in self.previous.parameters():
            p.requires_grad_(False)

    def extra_repr(self) -> str:
        return f"previous stage of length {self.previous.horizon:g}"

    def forward(self, x: Tensor) -> Tensor:
        t = torch.zeros(x.shape[0], dtype=x.dtype, device=x.device)
        return self.previous(x, t)

    def spec(self) -> dict:
        return {"kind": "previous_stage"}


# ---------------------------------------------------------------------- value networks


class FiniteHorizonValue(_Scaled):
    """The value network ``v_T(x, t)`` on Omega x [0, T] of Algorithm 1 (the ansatz: see the module's description).

    * ``n``: the state dimension.
    * ``horizon``: T > 0, the stage's own length.
    * ``train_domain``: the training box (n, 2); states are scaled from it to [-1, 1].
    * ``terminal_cost``: phi, a module such as :class:`ZeroTerminalCost`; None: phi = 0.
    * ``width``, ``depth``, ``activation``: the :class:`MLP`.
    * ``ansatz``: build the terminal and origin conditions into the network.
    * ``flat_origin``: under the ansatz, also build ``grad_x v(0, t) = 0`` into it (the correction loses its linear
      part at the origin, ``x' grad_x N(0, t)``), so the policy vanishes at the origin when phi's gradient does.
    """

    def __init__(
        self,
        n: int,
        horizon: float,
        train_domain,
        terminal_cost: nn.Module | None = None,
        width: int = 100,
        depth: int = 3,
        activation: str = "tanh",
        ansatz: bool = True,
        flat_origin: bool = False,
    ):
        super().__init__(train_domain)
        if not horizon > 0:
            raise ValueError(f"horizon must be positive; got {horizon}")
        self.n = n
        self.horizon = float(horizon)
        self.ansatz = bool(ansatz)
        self.flat_origin = bool(flat_origin)
        if self.flat_origin and not self.ansatz:
            raise ValueError("flat_origin builds grad v(0, t) = 0 into the ansatz: it needs ansatz=True")
        self.terminal_cost = ZeroTerminalCost() if terminal_cost is None else terminal_cost
        self.net = MLP(n + 1, width, depth, activation)

    def net_inputs(self, x: Tensor, t: Tensor) -> Tensor:
        """The network's input for (x, t): x scaled from the training box and t from [0, T], to [-1, 1]."""
        tau = 2.0 * t.reshape(-1, 1) / self.horizon - 1.0
        return torch.cat([self.scale_x(x), tau], dim=-1)

    def input_scale(self, like: Tensor) -> Tensor:
        """d net_inputs / d (x, t), a diagonal: (1 / halfwidth, 2 / T), shape (n + 1,)."""
        return torch.cat(
            [self.scale_x_derivative(like), torch.full((1,), 2.0 / self.horizon, dtype=like.dtype, device=like.device)]
        )

    def raw(self, x: Tensor, t: Tensor) -> Tensor:
        """The bare network N(x, t), inputs scaled to [-1, 1]."""
        return self.net(self.net_inputs(x, t))

    def correction(self, x: Tensor, t: Tensor) -> Tensor:
        """``v - phi`` under the ansatz, ``(T - t)/T (N(x, t) - N(0, t))`` (minus ``x' grad_x N(0, t)`` with
        ``flat_origin``); the bare N(x, t) otherwise."""
        if not self.ansatz:
            return self.raw(x, t)
        s = (self.horizon - t) / self.horizon
        zero = torch.zeros_like(x)
        if not self.flat_origin:
            return s * (self.raw(x, t) - self.raw(zero, t))
        # N(0, t) and x' grad_x N(0, t) in one forward-mode pass (composes with autograd and torch.func)
        dz = torch.cat([x * self.scale_x_derivative(x), torch.zeros_like(x[:, :1])], dim=-1)
        n_0, slope = self.net.tangent(self.net_inputs(zero, t), dz)
        return s * (self.raw(x, t) - n_0 - slope)

    def chain(self) -> list[FiniteHorizonValue]:
        """This stage and the earlier stages its value depends on (through terminal costs V_prev(., 0)), newest
        first; a stage without the ansatz ends the chain (its value does not include its terminal cost)."""
        models = [self]
        while (
            models[-1].ansatz
            and isinstance(models[-1].terminal_cost, ValueTerminalCost)
            and models[-1].terminal_cost.previous.ansatz
        ):
            models.append(models[-1].terminal_cost.previous)
        return models

    def forward(self, x: Tensor, t: Tensor | float) -> Tensor:
        """The value v(x, t) for states x (N, n) and a time t (scalar or (N,)); returns (N,)."""
        t = _broadcast_time(t, x)
        if not self.ansatz:
            return self.correction(x, t)
        # v_K(x, t) = c_K(x, t) + (c_{K-1}(x, 0) + (... + (c_1(x, 0) + phi_1(x)))): the corrections newest first,
        # then phi_1, then the sums innermost first, the order of the nested expression (so values and autograd's
        # gradients are bit-identical to it), in a loop: one network pass per stage and no recursion, whatever
        # the chain's length.
        models = self.chain()
        zero = None
        corrections = []
        for model in models:
            if model is self:
                tm = t
            else:
                if zero is None:
                    zero = _broadcast_time(torch.zeros(x.shape[0], dtype=x.dtype, device=x.device), x)
                tm = zero
            corrections.append(model.correction(x, tm))
        value = models[-1].terminal_cost(x)
        for c in reversed(corrections):
            value = c + value
        return value

    def correction_derivatives(
        self, x: Tensor, t: Tensor, origin_times: Tensor | None = None, origin_index: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """grad_x and d/dt of :meth:`correction` per point, kept differentiable in the weights (for training).

        * ``x``: (N, n) states.
        * ``t``: (N,) times.
        * ``origin_times``: (K,) distinct times, with ``t = origin_times[origin_index]``: the origin term N(0, t)
          of the ansatz is then evaluated at the K times only and gathered, the same function and derivatives
          at about half the cost of a training step when K << N. None: N(0, t_i) at every point.
        * ``origin_index``: (N,), see ``origin_times``.

        Returns grad_x (N, n) and d/dt (N,).
        """
        x = x.detach().requires_grad_(True)
        t = t.detach().requires_grad_(True)
        if not self.ansatz or self.flat_origin:  # the generic route: autograd through the correction
            out = self.raw(x, t) if not self.ansatz else self.correction(x, t)
            gx, gt = torch.autograd.grad(out.sum(), (x, t), create_graph=True)
            return gx, gt
        if origin_times is None:
            origin_times, origin_index = t, torch.arange(t.shape[0], device=t.device)
        origin_times = origin_times.detach().requires_grad_(True)
        n_x = self.raw(x, t)
        n_0 = self.raw(torch.zeros(origin_times.shape[0], x.shape[1], dtype=x.dtype, device=x.device), origin_times)
        # Each output depends on its own row only, so one backward gives every per-point derivative.
        gx, nt_x, nt_0 = torch.autograd.grad(n_x.sum() + n_0.sum(), (x, t, origin_times), create_graph=True)
        return self.ansatz_derivatives(t, n_x, n_0[origin_index], gx, nt_x, nt_0[origin_index])

    def ansatz_derivatives(
        self,
        t: Tensor,
        n_x: Tensor,
        n_0: Tensor,
        gx: Tensor,
        nt_x: Tensor,
        nt_0: Tensor,
        flat: tuple[Tensor, Tensor, Tensor] | None = None,
    ) -> tuple[Tensor, Tensor]:
        """grad_x and d/dt of the correction (T - t)/T (N(x, t) - N(0, t)) from N(x, t), N(0, t), grad_x N(x, t),
        d/dt N(x, t) and d/dt N(0, t) per point.

        * ``flat``: for ``flat_origin``, ``(grad_x N(0, t), slope, d/dt slope)`` per point, the slope
          x' grad_x N(0, t); the correction then also subtracts the slope. None: without it.
        """
        s = (self.horizon - t) / self.horizon
        if flat is None:
            return s.unsqueeze(-1) * gx, s * (nt_x - nt_0) - (n_x - n_0) / self.horizon
        gx_0, slope, slope_t = flat
        return s.unsqueeze(-1) * (gx - gx_0), s * (nt_x - nt_0 - slope_t) - (n_x - n_0 - slope) / self.horizon


class SteadyStateValue(_Scaled):
    """The value network V(x) of the direct steady-state PINN on :eq:`eq-hjb`.

    * ``n``: the state dimension.
    * ``train_domain``: the training box (n, 2).
    * ``width``, ``depth``, ``activation``: the :class:`MLP`.
    * ``ansatz``: ``N(x) - N(0)``, so that V(0) = 0 exactly; False: ``N(x)``, as the paper.
    """

    def __init__(
        self, n: int, train_domain, width: int = 100, depth: int = 3, activation: str = "tanh", ansatz: bool = True
    ):
        super().__init__(train_domain)
        self.n = n
        self.ansatz = bool(ansatz)
        self.net = MLP(n, width, depth, activation)

    def forward(self, x: Tensor, t: Tensor | float | None = None) -> Tensor:
        """The value V(x) for states x (N, n); ``t`` is ignored. Returns (N,)."""
        out = self.net(self.scale_x(x))
        if self.ansatz:
            out = out - self.net(self.scale_x(torch.zeros_like(x[:1])))
        return out


def _broadcast_time(t, x: Tensor) -> Tensor:
    if not isinstance(t, torch.Tensor):
        return torch.full((x.shape[0],), float(t), dtype=x.dtype, device=x.device)
    t = t.to(dtype=x.dtype, device=x.device).reshape(-1)
    return t.expand(x.shape[0]) if t.numel() == 1 else t


# ---------------------------------------------------------------------- autograd helpers


def gradient(fn: Callable[[Tensor], Tensor], x: Tensor, create_graph: bool = False) -> tuple[Tensor, Tensor]:
    """The values fn(x) (N,) and their gradient in x (N, n), by autograd.

    * ``fn``: a batched callable (N, n) -> (N,).
    * ``x``: (N, n) states.
    * ``create_graph``: keep the graph, to differentiate the gradient again.
    """
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        v = fn(x)
        if not v.requires_grad:  # V does not depend on x (e.g. phi = 0)
            return v, torch.zeros_like(x)
        (g,) = torch.autograd.grad(v.sum(), x, create_graph=create_graph, allow_unused=True)
    return v, torch.zeros_like(x) if g is None else g


def value_and_gradients(model: FiniteHorizonValue, x: Tensor, t: Tensor | float, create_graph: bool = False):
    """v(x, t), grad_x v and dv/dt, by autograd in one backward pass.

    * ``model``: the value network.
    * ``x``: (N, n) states.
    * ``t``: scalar or (N,) times.
    * ``create_graph``: keep the graph, to differentiate again.
    """
    with torch.enable_grad():
        x = x.detach().requires_grad_(True)
        t = _broadcast_time(t, x).detach().requires_grad_(True)
        v = model(x, t)
        gx, gt = torch.autograd.grad(v.sum(), (x, t), create_graph=create_graph)
    return v, gx, gt
