"""Per-point Jacobians of first-order PDE residuals of an :class:`~pinnhjb.pinn.MLP`, in its flat weights, fast.

Levenberg-Marquardt (:mod:`pinnhjb.gauss_newton`) needs J = d r / d theta (N x P) of the residual vector r. The
plain way, ``vmap(jacrev(point_residual))``, is exact and general, but for small networks most of its time is
the overhead of batching many tiny operations. For a residual that uses only the network's value and its first
input derivatives (the residuals :eq:`eq-fe` and :eq:`eq-ee` of :mod:`pinnhjb.residuals`), J has a structure
that makes it cheap:

* forward: propagate the inputs z (M, d) and K input tangents dz (M, K, d) through the layers, keeping every
  linear layer's input (a, da) and output (h = a W' + b, dh = da W');
* one reverse pass of sum_i r_i gives, per row, the cotangents of h and dh (each residual r_i depends on its own
  rows only, so the gradient of the sum holds every row's own derivative);
* a layer's rows of J are then sums of outer products, ``dr/dW = g_h a' + sum_k g_dh[k] da[k]'`` and
  ``dr/db = g_h``: one batched product per layer, (o x (K + 1)) times ((K + 1) x i) per residual.

Several network rows may feed one residual (the ansatz evaluates N(x, t) and N(0, t) per point): with
``copies = R`` the M = R N rows are R blocks of N, row i of every block feeding residual i, and the sums above run
over the blocks too.

A residual may also use one mixed second derivative along two of the tangents, d^2 N / (du dv) (the
``flat_origin`` ansatz's d/dt of its slope x' grad_x N(0, t)): a third channel ``dda`` rides along, zero at the
input, ``ddh = dda W'`` through a linear layer and ``sigma''(h) dh_u dh_v + sigma'(h) ddh`` through an activation;
it enters J like a tangent, ``g_ddh dda'``. Tested against ``vmap(jacrev(...))`` to rounding.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from .pinn import ACTIVATION_DERIVATIVES, MLP

Tensor = torch.Tensor

__all__ = ["residual_jacobian"]


def _activation_derivative(layer: nn.Module, h: Tensor, y: Tensor) -> Tensor:
    """sigma'(h) of an elementwise activation (closed form where known, else by autograd), differentiable."""
    known = ACTIVATION_DERIVATIVES.get(type(layer))
    if known is not None:
        return known(h, y)
    (d,) = torch.autograd.grad(y.sum(), h, create_graph=True)
    return d


def residual_jacobian(
    mlp: MLP,
    theta: Tensor,
    z: Tensor,
    dz: Tensor,
    residual_of: Callable[..., Tensor],
    copies: int = 1,
    mixed: tuple[int, int] | None = None,
) -> tuple[Tensor, Tensor]:
    """The residuals r (N,) and their Jacobian J (N, P) in the network's flat weights.

    * ``mlp``: the network.
    * ``theta``: (P,), its weights flattened in ``mlp.parameters()`` order (as
      :class:`pinnhjb.gauss_newton.FlatParameters` does).
    * ``z``: (M, d) network inputs.
    * ``dz``: (M, K, d), K input tangents per row (e.g. d z / d (x, t)).
    * ``residual_of``: ``(out, dout) -> r`` maps the network's outputs (M,) and their directional derivatives
      (M, K) to the residuals (N,), row by row; with ``mixed``, ``(out, dout, ddout) -> r``.
    * ``copies``: M / N; row m of the network may feed residual m mod N only.
    * ``mixed``: ``(u, v)``, two tangent indices: also hand ``residual_of`` the mixed second derivatives along
      ``dz[:, u]`` and ``dz[:, v]`` (M,). None: first derivatives only.

    Returns r and J, both detached.
    """
    if z.ndim != 2 or dz.ndim != 3 or dz.shape[0] != z.shape[0] or dz.shape[2] != z.shape[1]:
        raise ValueError(f"need z (M, d) and dz (M, K, d); got {tuple(z.shape)} and {tuple(dz.shape)}")
    if copies < 1 or z.shape[0] % copies:
        raise ValueError(f"{z.shape[0]} network rows are not {copies} blocks of equal size")
    if mixed is not None and not all(0 <= k < dz.shape[1] for k in mixed):
        raise ValueError(f"mixed needs two tangent indices below {dz.shape[1]}; got {mixed}")
    sizes = [p.numel() for p in mlp.parameters()]
    if theta.numel() != sum(sizes):
        raise ValueError(f"theta has {theta.numel()} entries; the network has {sum(sizes)} weights")
    with torch.enable_grad():
        weights = iter(torch.split(theta.detach().requires_grad_(True), sizes))
        # the mixed channel rides along as one more tangent (its input is zero: the inputs are linear in x, t)
        a = z.detach()
        da = dz.detach() if mixed is None else torch.cat([dz.detach(), torch.zeros_like(dz[:, :1])], dim=1)
        tape = []  # (a, da, h, dh) of every linear layer
        for layer in mlp.layers:
            if isinstance(layer, nn.Linear):
                W = next(weights).view(layer.out_features, layer.in_features)
                b = next(weights)
                h, dh = torch.addmm(b, a, W.T), da @ W.T
                tape.append((a, da, h, dh))
                a, da = h, dh
            else:
                y = layer(a)
                d1 = _activation_derivative(layer, a, y)
                if mixed is None:
                    da = d1.unsqueeze(1) * da
                else:  # sigma'' dh_u dh_v + sigma' ddh
                    (d2,) = torch.autograd.grad(d1.sum(), a, create_graph=True)
                    dd = d2 * da[:, mixed[0]] * da[:, mixed[1]] + d1 * da[:, -1]
                    da = torch.cat([d1.unsqueeze(1) * da[:, :-1], dd.unsqueeze(1)], dim=1)
                a = y
        out, dout = a.squeeze(-1), da.squeeze(-1)
        r = residual_of(out, dout) if mixed is None else residual_of(out, dout[:, :-1], dout[:, -1])
        cot = torch.autograd.grad(
            r.sum(), [t for (_, _, h, dh) in tape for t in (h, dh)], allow_unused=True, materialize_grads=True
        )
    N = z.shape[0] // copies
    if r.shape != (N,):
        raise ValueError(
            f"residual_of gave shape {tuple(r.shape)}; expected ({N},) for {z.shape[0]} rows in {copies} block(s)"
        )

    def per_residual(u: Tensor) -> Tensor:  # (M, C, w) -> (N, copies * C, w): every row next to its residual's
        return u.reshape(copies, N, *u.shape[1:]).transpose(0, 1).reshape(N, -1, u.shape[-1])

    blocks = []
    for k, (a, da, _, _) in enumerate(tape):
        g_h, g_dh = cot[2 * k], cot[2 * k + 1]
        U = per_residual(torch.cat([g_h.unsqueeze(1), g_dh], dim=1))  # (N, C, out)
        A = per_residual(torch.cat([a.detach().unsqueeze(1), da.detach()], dim=1))  # (N, C, in)
        blocks += [torch.bmm(U.transpose(1, 2), A).reshape(N, -1), g_h.reshape(copies, N, -1).sum(0)]
    return r.detach(), torch.cat(blocks, dim=1)
