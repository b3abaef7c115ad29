"""Levenberg-Marquardt (damped Gauss-Newton) on a PINN's residuals: the step of our default recipe's optimiser.

Under the ansatz the loss of Algorithm 1 is a mean of squared residuals, mean_i F_e(x_i, t_i; theta)^2, so its
Gauss-Newton model needs only the Jacobian J (N x P) of the residual vector in the weights. Each iteration:

* draws fresh collocation points;
* forms J: by default ``vmap`` of ``jacrev`` of one point's residual (the residual holds first derivatives of the
  network, so J holds mixed second derivatives); training passes the residual form's faster structured Jacobian
  (:meth:`pinnhjb.residuals.Residual.jacobian`);
* solves, by Cholesky, in the smaller of the two spaces::

      (J'J + lambda I) delta = -J'r,   or, when N < P,   delta = -J'(JJ' + lambda I)^{-1} r

  (on a CPU, a Gram matrix of side 2048 or more is formed in 4 x 4 blocks, the upper ones only: torch has no
  symmetric rank-k product, and this one does about 5/8 of the flops of one plain product; ``benchmarks/lm_step.py``
  times both);

* keeps the step when it lowers the loss on the same points (lambda shrinks), else raises lambda and retries
  (Levenberg's rule).

The number of points may grow in a schedule, e.g. (700, 1500) for a network of about 1300 weights. The early
iterations take fewer points than weights: the dual solve is cheap (its cost grows with N^2 P instead of N P^2)
and fits each batch almost exactly, so the loss stalls at a noise floor. The iterations then move to more points
than weights, where a step fits the residual rather than one batch. :class:`pinnhjb.optimizers.LevenbergMarquardt`
is the phase that runs it; ``benchmarks/`` times it.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import nn
from torch.func import jacrev, vmap

Tensor = torch.Tensor

__all__ = ["FlatParameters", "levenberg_marquardt", "LMResult", "DivergenceError", "gram"]

#: A CPU Gram matrix at least this wide is formed in blocks (:func:`gram`).
GRAM_BLOCKS_FROM = 2048


def gram(A: Tensor, blocks: int | None = None) -> Tensor:
    """``A'A``, P x P for A of shape N x P (the LM step's J'J, or JJ' as ``gram(J.T)``).

    * ``A``: (N, P).
    * ``blocks``: split the columns into this many blocks and form only the products of the upper blocks
      (b (b + 1) / 2 of b^2), mirroring the rest; None: 4 blocks on a CPU when P >= ``GRAM_BLOCKS_FROM``,
      else one product.
    """
    P = A.shape[1]
    if blocks is None:
        blocks = 4 if A.device.type == "cpu" and P >= GRAM_BLOCKS_FROM else 1
    if blocks <= 1:
        return A.T @ A
    edges = [P * i // blocks for i in range(blocks + 1)]
    cols = [A[:, a:b] for a, b in zip(edges, edges[1:])]
    G = torch.empty(P, P, dtype=A.dtype, device=A.device)
    for i, (a, b) in enumerate(zip(edges, edges[1:])):
        for j in range(i, blocks):
            c, d = edges[j], edges[j + 1]
            block = cols[i].T @ cols[j]
            G[a:b, c:d] = block
            if j > i:
                G[c:d, a:b] = block.T
    return G


class DivergenceError(FloatingPointError):
    """Training produced a non-finite loss or step: raised by every optimiser (Adam, L-BFGS, Levenberg-Marquardt)
    with the stage (``stage``, the progress label such as ``"pendulum T=0->1"``), the optimiser and the
    iteration in its message and attributes, instead of returning an untrained network."""

    def __init__(self, stage: str, optimiser: str, iteration: int, what: str, hint: str = ""):
        self.stage, self.optimiser, self.iteration = stage, optimiser, iteration
        hint = hint or (
            "check the scale of the system (f, g, Q, R: overflow?) and that f, g, Q are finite on the training box"
        )
        super().__init__(f"stage {stage}: {optimiser} diverged at iteration {iteration}: {what}; {hint}")


class FlatParameters:
    """A module's weights as one flat vector ``theta``, and the module as a function of ``theta``."""

    def __init__(self, module: nn.Module):
        self.module = module
        named = list(module.named_parameters())
        self.names = [k for k, _ in named]
        self.shapes = [p.shape for _, p in named]
        self.sizes = [p.numel() for _, p in named]

    def get(self) -> Tensor:
        """The weights as one flat vector (a copy)."""
        return torch.cat([p.detach().reshape(-1) for p in self.module.parameters()])

    def set(self, theta: Tensor) -> None:
        """Copy the flat vector ``theta`` into the module's weights."""
        with torch.no_grad():
            for p, chunk in zip(self.module.parameters(), torch.split(theta, self.sizes)):
                p.copy_(chunk.view(p.shape))

    def unflatten(self, theta: Tensor, prefix: str = "") -> dict:
        """``theta`` as a parameter dict for ``torch.func.functional_call`` (names under ``prefix``)."""
        return {prefix + k: c.view(s) for k, s, c in zip(self.names, self.shapes, torch.split(theta, self.sizes))}


@dataclass(frozen=True)
class LMResult:
    """What :func:`levenberg_marquardt` returns.

    * ``theta``: the final weights.
    * ``loss``: the loss of the last accepted iteration.
    * ``damping``: the final damping lambda.
    * ``steps``: the iterations run.
    * ``rejected``: the steps rejected (and retried with more damping).
    * ``stop_reason``: ``"lm_steps"`` (ran ``steps``), ``"stalled"`` or ``"max_time"``.
    """

    theta: Tensor
    loss: float
    damping: float
    steps: int
    rejected: int
    stop_reason: str


def levenberg_marquardt(
    theta: Tensor,
    point_residual: Callable[..., Tensor],
    sample: Callable[[int], tuple],
    steps: int,
    points: int | Sequence[int],
    damping: float = 1e-3,
    max_time: float | None = None,
    on_step: Callable[[int, float, float], None] | None = None,
    max_retries: int = 12,
    min_progress: float | None = None,
    window: int = 10,
    stall_windows: int = 2,
    desc: str = "LM",
    jacobian: Callable[..., tuple[Tensor, Tensor]] | None = None,
    adaptive: float = 0.0,
    candidates: int = 4,
) -> LMResult:
    """Minimise ``mean_i point_residual(theta, *batch_i)^2`` over fresh batches from ``sample(points)``.

    * ``theta``: the starting weights, one flat vector.
    * ``point_residual``: ``(theta, *args) ->`` one point's residual (a scalar), ``args`` the point's data.
    * ``sample``: a number of points -> a tuple of tensors whose first dimension indexes the points.
    * ``steps``: at most this many iterations.
    * ``points``: the points per iteration, or a growing schedule (n_1, n_2, ...): each stall moves on to the next
      count (the stall rule starts afresh there), and only a stall at the last one stops.
    * ``damping``: the initial damping lambda.
    * ``max_time``: stop after this many seconds (None: no cap).
    * ``on_step``: called as ``on_step(k, loss, damping)`` after each iteration.
    * ``max_retries``: rejected steps (damping raised) before an iteration gives up.
    * ``min_progress``: stop once the loss has stalled: its geometric mean over a window fell by less than this
      factor over the last ``stall_windows`` windows (the points are fresh each time); None: no stall rule.
    * ``window``: the iterations of one window.
    * ``stall_windows``: the windows of the stall rule.
    * ``desc``: the stage's label, for errors.
    * ``jacobian``: ``(theta, *batch) -> (r, J)``, the batch's residual vector and its Jacobian by a faster route
      than the default ``vmap(jacrev(point_residual))`` (it must agree with it: :mod:`pinnhjb.jacobian`).
    * ``adaptive``: the share of each iteration's points chosen by their residual: of ``candidates`` times as many
      fresh points, those with the largest ``abs(residual)`` at the current weights (residual-based adaptive
      refinement); the rest are drawn as usual. The loss is then a mean over a batch weighted to where the
      residual is large, above the mean over Omega. 0: every point drawn as usual.
    * ``candidates``: the fresh points scored for each point chosen by its residual (an integer >= 2).

    The residual forms of :mod:`pinnhjb.residuals` give ``point_residual(flat)``, ``jacobian()`` and, for
    ``sample``, ``point_arguments(data, t)``. Returns an :class:`LMResult`.
    """
    schedule = [int(n) for n in points] if isinstance(points, Sequence) else [int(points)]
    if (
        steps < 0
        or not schedule
        or min(schedule) < 1
        or not 0 < damping < math.inf
        or window < 1
        or stall_windows < 1
        or any(b <= a for a, b in zip(schedule, schedule[1:]))
        or not 0 <= adaptive < 1
        or int(candidates) != candidates
        or candidates < 2
    ):
        raise ValueError(
            f"need steps >= 0, points >= 1 (a schedule must grow), damping > 0, window >= 1, "
            f"stall_windows >= 1 (damping finite), 0 <= adaptive < 1, an integer candidates >= 2; got {steps}, "
            f"{points}, {damping}, {window}, {stall_windows}, {adaptive}, {candidates}"
        )
    start = time.perf_counter()
    theta = theta.detach().clone()
    P = theta.numel()
    lam = float(damping)
    loss = float("nan")
    rejected = done = 0
    stop = "lm_steps"
    log_losses: list[float] = []
    window_means: list[float] = []
    level = 0
    residuals = None
    for _ in range(steps):
        size = schedule[level]
        chosen = min(int(round(adaptive * size)), size - 1)
        batch = sample(size - chosen)
        dims = (None,) + (0,) * len(batch)
        if residuals is None:  # the batch's layout is known from the first sample
            residuals = vmap(point_residual, in_dims=dims)
        if chosen:
            pool = sample(int(candidates) * chosen)
            with torch.no_grad():
                top = torch.topk(residuals(theta, *pool).abs(), chosen).indices
            batch = tuple(torch.cat([a, b[top]]) for a, b in zip(batch, pool))
        if jacobian is None:
            J = vmap(jacrev(point_residual), in_dims=dims)(theta, *batch)
            r = residuals(theta, *batch)
        else:
            r, J = jacobian(theta, *batch)
        loss = (r @ r).item() / r.numel()
        if not torch.isfinite(r).all():
            raise DivergenceError(desc, "Levenberg-Marquardt", done + 1, "the residuals became non-finite")
        if not math.isfinite(loss):
            raise DivergenceError(desc, "Levenberg-Marquardt", done + 1, f"the loss is {loss} (overflow)")
        dual = r.numel() < P  # solve in the smaller of the two spaces
        G = gram(J.T) if dual else gram(J)
        # a non-finite entry of J makes its row's or column's sum of squares on G's diagonal non-finite: checking
        # the diagonal is checking J, at a fraction of the cost
        if not torch.isfinite(G.diagonal()).all():
            raise DivergenceError(
                desc, "Levenberg-Marquardt", done + 1, "the Jacobian became non-finite (or its squares overflowed)"
            )
        rhs = r if dual else J.T @ r
        eye = torch.eye(G.shape[0], dtype=G.dtype, device=G.device)
        for _ in range(max_retries):
            chol, info = torch.linalg.cholesky_ex(G + lam * eye)
            if info.item() == 0:
                y = torch.cholesky_solve(rhs.unsqueeze(-1), chol).squeeze(-1)
                delta = -(J.T @ y) if dual else -y
                if not torch.isfinite(delta).all():
                    raise DivergenceError(desc, "Levenberg-Marquardt", done + 1, "the step became non-finite")
                r_new = residuals(theta + delta, *batch)
                new = (r_new @ r_new).item() / r.numel()
                if new < loss:  # accept, trust the quadratic model more
                    theta = theta + delta
                    loss, lam = new, max(lam / 3.0, 1e-12)
                    break
            rejected += 1
            lam *= 4.0
        done += 1
        if on_step is not None:
            on_step(done, loss, lam)
        if max_time is not None and time.perf_counter() - start > max_time:
            stop = "max_time"
            break
        if min_progress is not None:
            log_losses.append(math.log(max(loss, 1e-300)))
            if len(log_losses) == window:
                window_means.append(sum(log_losses) / window)
                log_losses.clear()
                if len(window_means) > stall_windows and window_means[-1 - stall_windows] - window_means[-1] < math.log(
                    min_progress
                ):
                    if level + 1 == len(schedule):
                        stop = "stalled"
                        break
                    level += 1
                    window_means.clear()
    return LMResult(theta=theta, loss=loss, damping=lam, steps=done, rejected=rejected, stop_reason=stop)
