"""Training configuration: the network, the data and the optimiser phases of one stage, and the named presets.

:meth:`TrainConfig.preset` builds ``default`` (ours: Levenberg-Marquardt), ``adam_lbfgs`` (ours, first-order),
``paper`` (Section 6's, which takes the system's name: the paper sets the network, learning rate, decay and
stopping threshold per example) and ``quick`` (tests and smoke runs).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

from .checks import integer, raise_invalid, real
from .optimizers import LBFGS, Adam, LevenbergMarquardt, Phase, get_phase, phase_from_dict
from .pinn import ACTIVATIONS

__all__ = ["TrainConfig", "PAPER_SETTINGS", "PRESETS", "WIDE_FROM", "LOOP_POLICIES", "default_network"]

# The paper's Section 6 settings per example: network and data (TrainConfig fields) and its Adam phase's learning
# rate, decay and stopping threshold. The third-order system's learning rate and decay are not stated in the
# paper; the quartic system's values are used, and the book says so.
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
_PAPER_ADAM = ("lr", "lr_decay", "stop_loss")  # the entries of PAPER_SETTINGS that set the Adam phase

# The flat optimiser fields of configs stored before the optimisers were phase objects, and the phase each sets.
_FLAT_PHASE_FIELDS = {
    "adam": {
        "adam_steps": "steps",
        "lr": "lr",
        "schedule": "schedule",
        "lr_final_ratio": "lr_final_ratio",
        "lr_decay": "lr_decay",
        "stop_loss": "stop_loss",
    },
    "lbfgs": {"lbfgs_steps": "steps", "lbfgs_points": "points"},
    "lm": {
        "lm_steps": "steps",
        "lm_points": "points",
        "lm_points_coarse": "points_coarse",
        "lm_damping": "damping",
        "lm_min_progress": "min_progress",
        "lm_stall_windows": "stall_windows",
    },
}


@dataclass(frozen=True)
class TrainConfig:
    """How one stage (one horizon, or the steady-state baseline) is trained: network, data, optimiser phases.

    Network:

    * ``width``, ``depth``: the MLP's hidden width and number of hidden layers.
    * ``activation``: its activation, a name in :data:`pinnhjb.pinn.ACTIVATIONS`.
    * ``ansatz``: enforce v(x, T) = phi(x) and v(0, t) = 0 exactly (:class:`~pinnhjb.pinn.FiniteHorizonValue`);
      False: they are the soft terms MSE_b and MSE_in of the loss :eq:`eq-mse`.
    * ``dtype``: ``"float32"`` or ``"float64"``.
    * ``flat_origin``: under the ansatz, also build ``grad_x v(0, t) = 0`` into the network
      (:class:`~pinnhjb.pinn.FiniteHorizonValue`), so the learned policy vanishes at the origin.

    Data:

    * ``sampling``: ``"resample"`` (fresh flow points every step: states from a pool on which f, g, Q and the
      terminal cost are cached, times fresh) or ``"fixed"`` (the paper's: one data set, epochs of mini-batches).
    * ``batch_size``: flow points per first-order step (a mini-batch with fixed data).
    * ``pool_size``: the states of the pool (resampling).
    * ``points_per_time``: under the ansatz with resampling, each fresh time is shared by this many points, so the
      origin term N(0, t) is evaluated once per time; None: every point its own time.
    * ``n_flow``, ``n_boundary``, ``n_origin``: the fixed data set's flow, terminal and origin points.
    * ``loop_share``: the share of the training states drawn along closed loops instead of uniformly in the
      training box: from uniform states of Omega, the loop of the policy ``loop_policy`` names (by default the
      linearisation's LQR policy), taken at a uniform time in [0, ``loop_time``]
      (:func:`pinnhjb.training.loop_states`). The value on Omega depends on the residual along the optimal loops,
      which can leave the training box; 0: all uniform. (The finite-horizon solver's pool; the steady-state
      baseline samples uniformly.)
    * ``loop_time``: the seconds of closed loop those states are drawn from.
    * ``loop_policy``: whose loops: ``"lqr"``, the linearisation's LQR policy; ``"terminal"``, the policy of the
      stage's terminal cost, which in a chain is the previous stage's learned value, so that the states follow
      the learned loops as they overshoot (a stage with terminal cost 0 falls back to the LQR loops).

    Optimiser:

    * ``phases``: the optimiser phases run in turn (:mod:`pinnhjb.optimizers`: :class:`~pinnhjb.optimizers.Adam`,
      :class:`~pinnhjb.optimizers.LBFGS`, :class:`~pinnhjb.optimizers.LevenbergMarquardt`, or a registered phase of
      your own); ``()`` trains nothing (a warm-started stage keeps the previous stage's weights).
    * ``max_time``: a cap on a stage's training wall seconds (phases not yet started when it passes are skipped),
      or None.
    * ``warm_start``: initialise each extension stage from the previous stage's weights. A warm stage can keep its
      terminal cost's error where it was instead of handing it on along the optimal loops as Theorem 3's exact
      stage does. From fresh weights (False) it does not, but each stage fits its whole correction again and can
      fit it worse (chapter 9, section 3). ``"best"``: train each extension stage both ways on the same points
      and keep the one with the lower E (the metrics' ``"E"``, the paper's own check, no reference needed); twice
      the training, and the attempt not kept is listed, with its metrics, in ``Stage.rejected``. ``"features"``:
      from the previous stage's weights with the last layer zero, so that the stage starts at its terminal cost
      (V = V_prev) and keeps the previous stage's hidden layers as its first features (chapter 9, section 3).
    * ``retries``: extra attempts at a stage whose training failed, each with a new seed (the stage's seed +
      1000 per attempt); the attempt with the lowest final training loss is kept. The first stage (the only one
      that starts from random weights, where a bad local minimum is likely) is always tried ``1 + retries``
      times; an extension stage is tried again only while its final loss is above ``retry_factor`` times the
      loss ``retry_against`` names. 0: one attempt per stage. The rejected attempts are listed in ``Stage.rejected``.
    * ``retry_factor``: the rise of the final training loss, against the loss ``retry_against`` names, that fails
      a stage.
    * ``retry_against``: ``"previous"``, the previous stage's final training loss; ``"best"``, the lowest final
      training loss of any stage of the chain so far, which also catches a loss that creeps up stage after stage,
      each rise below ``retry_factor`` (chapter 9, section 1).

    Reporting:

    * ``eval_points_per_dim``: the grid over Omega on which E is reported after each stage (None: the solver's).
    * ``log_every``: log the loss every this many iterations of each phase.

    The default is a small network (3 x 24 tanh, float64, about 1300 weights) trained by Levenberg-Marquardt alone.
    """

    width: int = 24
    depth: int = 3
    activation: str = "tanh"
    ansatz: bool = True
    dtype: str = "float64"
    flat_origin: bool = False
    sampling: str = "resample"
    batch_size: int = 2000
    pool_size: int = 40000
    points_per_time: int | None = 16
    n_flow: int = 10000
    n_boundary: int = 1600
    n_origin: int = 1600
    loop_share: float = 0.0
    loop_time: float = 1.5
    loop_policy: str = "lqr"
    phases: tuple[Phase, ...] = (LevenbergMarquardt(),)
    max_time: float | None = None
    warm_start: bool | str = True
    retries: int = 0
    retry_factor: float = 10.0
    retry_against: str = "previous"
    eval_points_per_dim: int | None = None
    log_every: int = 25

    def __post_init__(self):
        if isinstance(self.phases, list):
            object.__setattr__(self, "phases", tuple(self.phases))
        raise_invalid(
            self,
            {
                "width": (integer(self.width, 1), "an integer >= 1"),
                "depth": (integer(self.depth, 1), "an integer >= 1"),
                "batch_size": (integer(self.batch_size, 1), "an integer >= 1"),
                "pool_size": (integer(self.pool_size, 1), "an integer >= 1"),
                "points_per_time": (integer(self.points_per_time, 1, none=True), "an integer >= 1 or None"),
                "n_flow": (integer(self.n_flow, 1), "an integer >= 1"),
                "n_boundary": (integer(self.n_boundary, 1), "an integer >= 1"),
                "n_origin": (integer(self.n_origin, 1), "an integer >= 1"),
                "eval_points_per_dim": (integer(self.eval_points_per_dim, 2, none=True), "an integer >= 2 or None"),
                "log_every": (integer(self.log_every, 1), "an integer >= 1"),
                "retries": (integer(self.retries, 0), "an integer >= 0"),
                "retry_factor": (real(self.retry_factor, 1), "a finite number >= 1"),
                "retry_against": (self.retry_against in RETRY_AGAINST, " or ".join(map(repr, RETRY_AGAINST))),
                "loop_share": (real(self.loop_share, 0) and self.loop_share < 1, "a number in [0, 1)"),
                "loop_time": (real(self.loop_time, 0, low_open=True), "a number of seconds > 0"),
                "loop_policy": (self.loop_policy in LOOP_POLICIES, " or ".join(map(repr, LOOP_POLICIES))),
                "max_time": (
                    real(self.max_time, 0, low_open=True, none=True, inf=True),
                    "a number of seconds > 0 or None",
                ),
                "ansatz": (isinstance(self.ansatz, bool), "True or False"),
                "flat_origin": (
                    isinstance(self.flat_origin, bool) and (self.ansatz or not self.flat_origin),
                    "True or False (True needs ansatz=True)",
                ),
                "warm_start": (
                    isinstance(self.warm_start, bool)
                    or self.warm_start == "best"
                    or (self.warm_start == "features" and self.ansatz),
                    "True, False, 'best' or 'features' ('features' needs ansatz=True)",
                ),
                "activation": (
                    isinstance(self.activation, str) and self.activation in ACTIVATIONS,
                    f"one of {sorted(ACTIVATIONS)}",
                ),
                "dtype": (self.dtype in ("float32", "float64"), "'float32' or 'float64'"),
                "sampling": (self.sampling in ("resample", "fixed"), "'resample' or 'fixed'"),
                "phases": (
                    isinstance(self.phases, tuple) and all(isinstance(p, Phase) for p in self.phases),
                    "a tuple of optimiser phases such as (Adam(), LBFGS()) (pinnhjb.optimizers)",
                ),
            },
        )
        for p in self.phases:
            if p.needs_ansatz and not self.ansatz:
                raise ValueError(
                    f"the {type(p).__name__} phase needs ansatz=True (it minimises the flow residual only); "
                    f"with ansatz=False use first-order phases such as Adam"
                )
        if self.sampling == "fixed" and self.n_flow < self.batch_size:
            raise ValueError(f"n_flow={self.n_flow} must be at least batch_size={self.batch_size}")

    @classmethod
    def preset(
        cls, name: str = "default", system: str | None = None, dimension: int | None = None, **overrides
    ) -> TrainConfig:
        """A named recipe, with ``overrides`` of its fields.

        * ``name``: ``"default"`` (ours), ``"adam_lbfgs"`` (ours, first-order), ``"paper"`` (Section 6; needs
          ``system``) or ``"quick"`` (tests, smoke runs).
        * ``system``: the system's name, for ``"paper"``.
        * ``dimension``: the state dimension n, for the width rule of ``"default"`` (:func:`default_network`);
          None: the small network. The solvers pass their system's n.
        * ``overrides``: TrainConfig fields to change, e.g. ``width=32`` or ``phases=(Adam(steps=100),)``.
        """
        if name not in PRESETS:
            raise KeyError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
        base = dict(PRESETS[name])
        if name == "default" and dimension is not None:
            width, points, coarse = default_network(dimension)
            base.update(width=width, phases=(LevenbergMarquardt(points=points, points_coarse=coarse),))
        if name == "paper":
            if system not in PAPER_SETTINGS:
                raise KeyError(
                    f"the paper preset exists for {sorted(PAPER_SETTINGS)} only (the paper's Section 6 "
                    f"sets network, learning rate and threshold per example); got system={system!r}: "
                    f"borrow one example's settings with TrainConfig.preset('paper', system='pendulum'), "
                    f"or use 'default'"
                )
            settings = PAPER_SETTINGS[system]
            base.update({k: v for k, v in settings.items() if k not in _PAPER_ADAM})
            adam = {k: v for k, v in settings.items() if k in _PAPER_ADAM}
            base["phases"] = tuple(p.replace(**adam) if p.name == "adam" else p for p in base["phases"])
        _refuse_flat_fields(overrides)
        base.update(overrides)
        return cls(**base)

    def replace(self, **changes) -> TrainConfig:
        """A copy with ``changes`` (TrainConfig fields) applied and checked."""
        _refuse_flat_fields(changes)
        return replace(self, **changes)

    def phase(self, name: str) -> Phase:
        """The first phase named ``name`` (e.g. ``"adam"``, ``"lbfgs"``, ``"lm"``)."""
        for p in self.phases:
            if p.name == name:
                return p
        raise KeyError(f"this config has no {name!r} phase; its phases: {[p.name for p in self.phases]}")

    def with_phase(self, name: str, **changes) -> TrainConfig:
        """A copy whose phases named ``name`` have ``changes`` applied, e.g. ``with_phase("adam", steps=100)``.

        * ``name``: the phase's name.
        * ``changes``: fields of that phase.
        """
        self.phase(name)  # KeyError when there is none
        return replace(self, phases=tuple(p.replace(**changes) if p.name == name else p for p in self.phases))

    def without_phase(self, name: str) -> TrainConfig:
        """A copy without the phases named ``name``."""
        self.phase(name)
        return replace(self, phases=tuple(p for p in self.phases if p.name != name))

    def to_dict(self) -> dict:
        """The config as plain data (phases as dicts with their names), as checkpoints store it.

        A field added after checkpoints were first stored (``_ADDED_LATER``) is written only when it differs
        from its default, so every config stored before it reads back exactly as it was written."""
        d = {
            f.name: getattr(self, f.name)
            for f in fields(self)
            if f.name != "phases" and not (f.name in _ADDED_LATER and getattr(self, f.name) == f.default)
        }
        d["phases"] = [p.to_dict() for p in self.phases]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        """The config stored as ``d`` by :meth:`to_dict`; a config stored with flat optimiser fields
        (``adam_steps``, ``lr``, ``lbfgs_steps``, ``lm_steps``, ...) is migrated to the phases it ran.

        * ``d``: the stored dict.
        """
        d = dict(d)
        if "phases" in d:
            d["phases"] = tuple(phase_from_dict(p) for p in d["phases"])
        else:
            d["phases"] = _migrate_flat(d)
        names = {f.name for f in fields(cls)}
        unknown = set(d) - names
        if unknown:
            raise ValueError(f"unknown TrainConfig field(s) {sorted(unknown)}")
        return cls(**d)


def _migrate_flat(d: dict) -> tuple[Phase, ...]:
    """The phases a config with flat optimiser fields ran (popping those fields from ``d``): Adam when
    ``adam_steps > 0``, then L-BFGS when ``lbfgs_steps > 0``, then Levenberg-Marquardt when ``lm_steps > 0``. A
    config stored without the Levenberg-Marquardt fields ran without it; one stored without ``lm_points_coarse``
    ran on ``lm_points`` throughout with a stall span of three windows."""
    for key, value in (("lm_steps", 0), ("lm_points_coarse", None), ("lm_stall_windows", 3)):
        d.setdefault(key, value)
    phases = []
    for name, flat in _FLAT_PHASE_FIELDS.items():
        settings = {field: d.pop(key) for key, field in flat.items() if key in d}
        if settings.get("steps", 0) > 0:
            phases.append(get_phase(name)(**settings))
    return tuple(phases)


def _refuse_flat_fields(changes: dict) -> None:
    """A clear error for a flat optimiser field (``adam_steps=...``) given where phases are expected."""
    for name, flat in _FLAT_PHASE_FIELDS.items():
        for key, field in flat.items():
            if key in changes:
                raise TypeError(
                    f"{key!r} is not a TrainConfig field: the optimisers are phases; use "
                    f"config.with_phase({name!r}, {field}=...) or phases=(...) (pinnhjb.optimizers)"
                )


#: Fields added after checkpoints were first stored: :meth:`TrainConfig.to_dict` writes them only when set.
_ADDED_LATER = ("flat_origin", "retries", "retry_factor", "retry_against", "loop_share", "loop_time", "loop_policy")

#: What an extension stage's final training loss is compared with (``TrainConfig.retry_against``).
RETRY_AGAINST = ("previous", "best")

#: The policies whose closed loops ``TrainConfig.loop_share`` draws training states along.
LOOP_POLICIES = ("lqr", "terminal")

#: From this state dimension on, the default recipe widens its network (:func:`default_network`).
WIDE_FROM = 6


def default_network(n: int) -> tuple[int, int, int]:
    """The default recipe's width rule: ``(width, lm points, lm coarse points)`` for state dimension ``n``.

    * ``n``: the state dimension, an integer >= 1.

    Below :data:`WIDE_FROM` (the paper's systems, n <= 3, where the recipe was tuned) a 3 x 24 network (about
    1300 weights) with 1500 LM points (700 coarse). From n = 6 on, 3 x 40 (about 3600 weights) with 4500 points
    (2000 coarse), so that the last LM level still has more points than weights. Chosen by measurement on the 6-D
    rigid body (``benchmarks/rigid_body.py``; its results page and chapter 8 give the numbers): the 3 x 24 network's
    error levels off as the horizon grows, the 3 x 40 one goes lower at a few times the cost per stage. A
    Levenberg-Marquardt step with more points than weights costs about N P^2, so the rule stops there on CPUs.
    """
    if not (isinstance(n, int) and n >= 1):
        raise ValueError(f"the state dimension must be an integer >= 1; got {n!r}")
    return (24, 1500, 700) if n < WIDE_FROM else (40, 4500, 2000)


PRESETS: dict[str, dict] = {
    # Ours: hard constraints, a 3 x 24 network in float64, Levenberg-Marquardt on fresh points (700, then 1500 per
    # iteration once the loss stalls), warm-started extension.
    "default": dict(phases=(LevenbergMarquardt(),)),
    # First-order: hard constraints, 3 x 100 in float32, fresh points every step, cosine Adam, L-BFGS polish.
    "adam_lbfgs": dict(width=100, dtype="float32", phases=(Adam(steps=2500), LBFGS(steps=800))),
    # Section 6: soft loss MSE_e + MSE_b + MSE_in, fixed data, Adam with inverse-time decay per mini-batch of 500,
    # stop when every mini-batch loss of an epoch is below the threshold; capped by steps and time. Network, data,
    # learning rate, decay and threshold per example from PAPER_SETTINGS.
    "paper": dict(
        width=100,
        dtype="float32",
        ansatz=False,
        sampling="fixed",
        batch_size=500,
        phases=(Adam(steps=20000, schedule="inverse_time"),),
        warm_start=False,
        max_time=600.0,
    ),
    # A few seconds per stage: for tests and smoke runs, not for accuracy.
    "quick": dict(
        width=32,
        depth=2,
        dtype="float32",
        batch_size=256,
        pool_size=4096,
        phases=(Adam(steps=150, lr=5e-3), LBFGS(steps=20, points=512)),
        eval_points_per_dim=21,
    ),
}
