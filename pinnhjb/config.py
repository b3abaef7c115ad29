"""Training configuration: one dataclass, two recipes (``default`` = ours, ``paper`` = Section 6's).

:meth:`TrainConfig.preset` returns either recipe; ``paper`` takes the system's name because the paper
uses a different network, learning rate, decay and stopping threshold per example (Section 6).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from .pinn import ACTIVATIONS

__all__ = ["TrainConfig", "PAPER_SETTINGS", "PRESETS"]

# The paper's Section 6 settings per example. Omitted entries (third-order learning rate and decay)
# are not stated in the paper; we reuse the quartic system's values and say so in the book.
PAPER_SETTINGS: dict[str, dict] = {
    "pendulum": dict(
        width=100, depth=3, n_flow=10000, n_boundary=1600, n_origin=1600, lr=0.005, lr_decay=0.002, stop_loss=1e-3
    ),
    "quartic": dict(
        width=250, depth=3, n_flow=10000, n_boundary=1600, n_origin=1600, lr=0.01, lr_decay=0.003, stop_loss=1e-4
    ),
    "third_order": dict(
        width=500, depth=3, n_flow=20000, n_boundary=27000, n_origin=27000, lr=0.01, lr_decay=0.003, stop_loss=1e-4
    ),
}


@dataclass(frozen=True)
class TrainConfig:
    """How one stage (one horizon, or the steady-state baseline) is trained.

    Network: ``width`` x ``depth`` MLP with ``activation``; ``ansatz`` enforces v(x,T) = phi(x) and
    v(0,t) = 0 exactly (else they are the soft terms MSE_b, MSE_in of eq. (MSE)); ``dtype``.

    Data: ``sampling="resample"`` draws ``batch_size`` fresh flow points every step (states from a pool
    of ``pool_size`` points on which f, g, Q and the terminal cost are cached, times fresh);
    ``sampling="fixed"`` is the paper's: one data set of ``n_flow`` / ``n_boundary`` / ``n_origin`` points,
    epochs of mini-batches of ``batch_size`` flow points. Under the ansatz with resampling, each fresh time is
    shared by ``points_per_time`` points of the batch, so the origin term N(0, t) is evaluated once per time
    (about half the cost of a step at 16); ``None`` gives every point its own time.

    Optimiser, in three phases any of which may be switched off (0 steps): Adam for at most ``adam_steps``
    steps from ``lr`` with ``schedule`` ``"cosine"`` (to ``lr * lr_final_ratio``) or ``"inverse_time"``
    (lr / (1 + lr_decay * k), the paper's); the paper's stop rule (every mini-batch loss of an epoch below
    ``stop_loss``) when set; then ``lbfgs_steps`` L-BFGS iterations on ``lbfgs_points`` fixed flow points;
    then at most ``lm_steps`` Levenberg-Marquardt iterations (:mod:`pinnhjb.gauss_newton`, ansatz only), damping
    starting at ``lm_damping``, each on fresh points: ``lm_points_coarse`` of them (fewer than the weights: a
    cheap step that stalls at a noise floor) until the loss stalls, then ``lm_points`` until it stalls again;
    the loss has stalled when it fell by less than the factor ``lm_min_progress`` over the last
    ``lm_stall_windows`` windows of 10 iterations (``lm_points_coarse=None``, or ``lm_min_progress=None`` (never
    stall, run ``lm_steps``): ``lm_points`` throughout). ``max_time`` caps wall seconds per stage.
    ``warm_start`` initialises each extension stage from the previous stage's weights.
    ``eval_points_per_dim`` sets the grid over Omega on which E is reported after each stage.

    Our default is a small network (3 x 24 tanh, float64, about 1300 weights) trained by Levenberg-Marquardt
    alone on 700 then 1500 points per iteration (its cost per iteration grows with the square of the number of
    weights: keep the network small); the ``adam_lbfgs`` preset is a first-order recipe
    (3 x 100, float32, Adam then L-BFGS).
    """

    width: int = 24
    depth: int = 3
    activation: str = "tanh"
    ansatz: bool = True
    dtype: str = "float64"
    sampling: str = "resample"
    batch_size: int = 2000
    pool_size: int = 40000
    points_per_time: int | None = 16
    n_flow: int = 10000
    n_boundary: int = 1600
    n_origin: int = 1600
    adam_steps: int = 0
    lr: float = 2e-3
    schedule: str = "cosine"
    lr_final_ratio: float = 0.01
    lr_decay: float = 0.0
    stop_loss: float | None = None
    max_time: float | None = None
    lbfgs_steps: int = 0
    lbfgs_points: int = 4000
    lm_steps: int = 300
    lm_points: int = 1500
    lm_points_coarse: int | None = 700
    lm_damping: float = 1e-3
    lm_min_progress: float | None = 2.0
    lm_stall_windows: int = 2
    warm_start: bool = True
    eval_points_per_dim: int | None = None
    log_every: int = 25

    def __post_init__(self):
        def integer(v, low, none=False):
            if v is None:
                return none
            return not isinstance(v, bool) and isinstance(v, (int, np.integer)) and v >= low

        def real(v, low=None, high=None, low_open=False, none=False, inf=False):
            if v is None:
                return none
            if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
                return False
            v = float(v)
            if math.isnan(v) or (math.isinf(v) and not inf):
                return False
            if low is not None and (v <= low if low_open else v < low):
                return False
            return high is None or v <= high

        checks = {  # field: (valid, what is expected)
            "width": (integer(self.width, 1), "an integer >= 1"),
            "depth": (integer(self.depth, 1), "an integer >= 1"),
            "batch_size": (integer(self.batch_size, 1), "an integer >= 1"),
            "pool_size": (integer(self.pool_size, 1), "an integer >= 1"),
            "points_per_time": (integer(self.points_per_time, 1, none=True), "an integer >= 1 or None"),
            "n_flow": (integer(self.n_flow, 1), "an integer >= 1"),
            "n_boundary": (integer(self.n_boundary, 1), "an integer >= 1"),
            "n_origin": (integer(self.n_origin, 1), "an integer >= 1"),
            "adam_steps": (integer(self.adam_steps, 0), "an integer >= 0"),
            "lbfgs_steps": (integer(self.lbfgs_steps, 0), "an integer >= 0"),
            "lbfgs_points": (integer(self.lbfgs_points, 1), "an integer >= 1"),
            "lm_steps": (integer(self.lm_steps, 0), "an integer >= 0"),
            "lm_points": (integer(self.lm_points, 1), "an integer >= 1"),
            "lm_points_coarse": (integer(self.lm_points_coarse, 1, none=True), "an integer >= 1 or None"),
            "lm_stall_windows": (integer(self.lm_stall_windows, 1), "an integer >= 1"),
            "eval_points_per_dim": (integer(self.eval_points_per_dim, 2, none=True), "an integer >= 2 or None"),
            "log_every": (integer(self.log_every, 1), "an integer >= 1"),
            "lr": (real(self.lr, 0, low_open=True), "a finite number > 0"),
            "lr_final_ratio": (real(self.lr_final_ratio, 0, 1), "a number in [0, 1]"),
            "lr_decay": (real(self.lr_decay, 0), "a finite number >= 0"),
            "stop_loss": (real(self.stop_loss, 0, low_open=True, none=True), "a finite number > 0 or None"),
            "max_time": (real(self.max_time, 0, low_open=True, none=True, inf=True), "a number of seconds > 0 or None"),
            "lm_damping": (real(self.lm_damping, 0, low_open=True), "a finite number > 0"),
            "lm_min_progress": (real(self.lm_min_progress, 1, none=True), "a finite number >= 1 or None"),
            "ansatz": (isinstance(self.ansatz, bool), "True or False"),
            "warm_start": (isinstance(self.warm_start, bool), "True or False"),
            "activation": (
                isinstance(self.activation, str) and self.activation in ACTIVATIONS,
                f"one of {sorted(ACTIVATIONS)}",
            ),
            "dtype": (self.dtype in ("float32", "float64"), "'float32' or 'float64'"),
            "sampling": (self.sampling in ("resample", "fixed"), "'resample' or 'fixed'"),
            "schedule": (
                self.schedule in ("cosine", "inverse_time", "constant"),
                "'cosine', 'inverse_time' or 'constant'",
            ),
        }
        bad = [k for k, (ok, _) in checks.items() if not ok]
        if bad:
            raise ValueError(
                f"invalid TrainConfig field(s) {bad}: "
                + "; ".join(f"{k}={getattr(self, k)!r} (expected {checks[k][1]})" for k in bad)
            )
        if self.lm_points_coarse is not None and self.lm_points_coarse >= self.lm_points:
            raise ValueError(
                f"lm_points_coarse={self.lm_points_coarse} must be fewer than lm_points={self.lm_points} "
                "(the coarse level comes first); set lm_points_coarse=None to use lm_points throughout"
            )
        if self.lm_steps > 0 and not self.ansatz:
            raise ValueError("lm_steps > 0 needs ansatz=True (Levenberg-Marquardt minimises the flow residual only)")
        if self.sampling == "fixed" and self.n_flow < self.batch_size:
            raise ValueError(f"n_flow={self.n_flow} must be at least batch_size={self.batch_size}")

    @classmethod
    def preset(cls, name: str = "default", system: str | None = None, **overrides) -> TrainConfig:
        """``default`` (ours), ``adam_lbfgs`` (ours, first-order), ``paper`` (Section 6, needs ``system``), or
        ``quick`` (tests, smoke runs)."""
        if name not in PRESETS:
            raise KeyError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
        base = dict(PRESETS[name])
        if name == "paper":
            if system not in PAPER_SETTINGS:
                raise KeyError(
                    f"the paper preset exists for {sorted(PAPER_SETTINGS)} only (the paper's Section 6 "
                    f"sets network, learning rate and threshold per example); got system={system!r}: "
                    f"borrow one example's settings with TrainConfig.preset('paper', system='pendulum'), "
                    f"or use 'default'"
                )
            base.update(PAPER_SETTINGS[system])
        base.update(overrides)
        return cls(**base)

    def replace(self, **changes) -> TrainConfig:
        return replace(self, **changes)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown TrainConfig field(s) {sorted(unknown)}")
        # A config stored before the Levenberg-Marquardt phase existed was trained without it; one stored before
        # the point schedule was trained on lm_points throughout, with a stall span of three windows.
        return cls(**{"lm_steps": 0, "lm_points_coarse": None, "lm_stall_windows": 3, **d})


# What the first-order recipes share and the default does not have.
_FIRST_ORDER = dict(width=100, dtype="float32", lm_steps=0)

PRESETS: dict[str, dict] = {
    # Ours: hard constraints, a 3 x 24 network in float64, Levenberg-Marquardt on fresh points, warm-started
    # extension.
    "default": dict(),
    # First-order: hard constraints, 3 x 100 in float32, fresh points every step, cosine Adam, L-BFGS polish.
    "adam_lbfgs": dict(_FIRST_ORDER, adam_steps=2500, lbfgs_steps=800),
    # Section 6: soft loss MSE_e + MSE_b + MSE_in, fixed data, Adam with inverse-time decay per
    # mini-batch of 500, stop when every mini-batch loss is below the threshold; capped by steps/time.
    "paper": dict(
        _FIRST_ORDER,
        ansatz=False,
        sampling="fixed",
        batch_size=500,
        schedule="inverse_time",
        adam_steps=20000,
        lbfgs_steps=0,
        warm_start=False,
        max_time=600.0,
    ),
    # A few seconds per stage: for tests and smoke runs, not for accuracy.
    "quick": dict(
        _FIRST_ORDER,
        width=32,
        depth=2,
        batch_size=256,
        pool_size=4096,
        adam_steps=150,
        lr=5e-3,
        lbfgs_steps=20,
        lbfgs_points=512,
        eval_points_per_dim=21,
    ),
}
