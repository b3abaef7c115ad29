"""Training (Algorithm 1), horizon extension (Theorem 2), solve_until, the steady-state baseline, TrainConfig.

Every run is a few dozen Adam steps of the quick preset: enough to see the loss move, not to be accurate.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

import pinnhjb as ph
from pinnhjb.pinn import ValueTerminalCost


def adam(**changes) -> tuple:
    """The quick preset's Adam phase for 30 steps (with ``changes``), as a recipe."""
    return (ph.Adam(**{"steps": 30, "lr": 5e-3, **changes}),)


FAST = dict(phases=adam(), eval_points_per_dim=11)
PAPER_STYLE = dict(
    FAST,
    phases=adam(schedule="inverse_time", lr_decay=0.002),
    ansatz=False,
    sampling="fixed",
    n_flow=1024,
    n_boundary=256,
    n_origin=256,
    warm_start=False,
)


def solver(config=None, seed=0, system=None, **overrides):
    config = config or ph.TrainConfig.preset("quick", **{**FAST, **overrides})
    return ph.FiniteHorizonSolver(system or ph.systems.pendulum(), config, seed=seed, device="cpu", progress=False)


def assert_same_weights(a: torch.nn.Module, b: torch.nn.Module):
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    for key in sa:
        assert torch.equal(sa[key], sb[key]), key


@pytest.fixture(scope="module")
def pendulum():
    return ph.systems.pendulum()


@pytest.fixture(scope="module")
def base(pendulum):
    """One stage on [0, 0.5] with the default-style (ansatz) recipe, seed 0."""
    return solver(system=pendulum).solve(0.5)


@pytest.fixture(scope="module")
def chain(pendulum, base):
    """``base`` extended to T = 1.5 in steps of 0.5 (three stages)."""
    return solver(system=pendulum).extend(base, to=1.5, step=0.5)


@pytest.fixture(scope="module")
def x_test():
    return np.random.default_rng(0).uniform(-1, 1, (64, 2))


# ------------------------------------------------------------------------------ the loss goes down
def test_ansatz_training_lowers_the_loss(base):
    hist = base.stages[0].history
    assert hist.phase[0] == "adam" and hist.step[0] == 1 and hist.phase[-1] == "final"
    assert hist.stop_reason == "adam_steps"
    assert all(math.isfinite(v) for v in hist.loss)
    assert hist.final_loss < 0.8 * hist.loss[0]
    assert base.stages[0].model.ansatz


def test_paper_style_training_lowers_the_loss(pendulum):
    sol = solver(system=pendulum, **PAPER_STYLE).solve(0.5)
    stage = sol.stages[0]
    assert not stage.model.ansatz
    assert sol.config.sampling == "fixed" and sol.config.phase("adam").schedule == "inverse_time"
    assert stage.history.final_loss < 0.9 * stage.history.loss[0]
    # V(0) = 0 is only a soft target here, so E carries a (nonnegative) boundary term
    assert sol.metrics["E_boundary"] >= 0.0 and sol.metrics["E"] >= sol.metrics["E_flow"]


def test_paper_stop_rule_ends_after_one_epoch(pendulum):
    # every mini-batch loss below a huge threshold: stop at the end of the first epoch of 1024 / 256 batches
    sol = solver(
        system=pendulum,
        **{
            **PAPER_STYLE,
            "phases": adam(steps=1000, schedule="inverse_time", lr_decay=0.002, stop_loss=1e9),
            "log_every": 1,
        },
    ).solve(0.5)
    hist = sol.stages[0].history
    assert hist.stop_reason == "stop_loss"
    assert [s for s, ph_ in zip(hist.step, hist.phase) if ph_ == "adam"] == [1, 2, 3, 4]


def test_max_time_caps_adam(pendulum):
    sol = solver(system=pendulum, max_time=1e-9, phases=adam(steps=1000)).solve(0.5)
    assert sol.stages[0].history.stop_reason == "max_time"
    assert sol.stages[0].history.step[-1] == 1


class _RecordingBar:
    """Stands in for tqdm: records every loss shown in the postfix and every update."""

    def __init__(self, *args, **kwargs):
        self.shown, self.n = [], 0

    def set_postfix(self, loss, refresh=True):
        self.shown.append(loss)

    def update(self, k=1):
        self.n += k

    def close(self):
        pass


@pytest.mark.parametrize("phase", ["adam", "lbfgs", "lm"])
def test_progress_bar_shows_the_latest_loss(pendulum, monkeypatch, phase):
    bars = []
    monkeypatch.setattr("pinnhjb.optimizers.tqdm", lambda *a, **k: bars.append(_RecordingBar()) or bars[-1])
    steps = {
        "adam": dict(phases=adam(steps=7)),
        "lbfgs": dict(phases=(ph.LBFGS(steps=7, points=512),)),
        "lm": dict(phases=(ph.LevenbergMarquardt(steps=7, points=64, points_coarse=None, min_progress=None),)),
    }[phase]
    config = ph.TrainConfig.preset("quick", **{**FAST, "log_every": 5, "dtype": "float64", **steps})
    sol = ph.FiniteHorizonSolver(pendulum, config, seed=0, device="cpu", progress=True).solve(0.5)
    (bar,) = [b for b in bars if b.n]
    assert len(bar.shown) == bar.n > 0  # every step updates the loss shown, not only every log_every
    if phase != "lbfgs":  # (L-BFGS's final loss is re-evaluated after its last closure call)
        assert bar.shown[-1] == f"{sol.stages[0].history.final_loss:.3e}"


def test_metrics_are_attached_after_each_stage(base, chain):
    for key in ("E", "E_flow", "E_boundary", "E_zero"):
        assert math.isfinite(base.metrics[key])
    assert base.metrics["E_boundary"] == 0.0  # V(0) = 0 under the ansatz
    assert [row["horizon"] for row in chain.summary()] == [0.5, 1.0, 1.5]
    assert all("E" in row for row in chain.summary())
    assert chain.metrics == chain.stages[-1].metrics


# ------------------------------------------------------------------------------ reproducibility
@pytest.mark.parametrize("recipe", [FAST, PAPER_STYLE], ids=["ansatz", "paper-style"])
def test_same_seed_repeats_bit_for_bit(pendulum, recipe):
    a = solver(system=pendulum, seed=3, **recipe).solve(0.5)
    b = solver(system=pendulum, seed=3, **recipe).solve(0.5)
    assert_same_weights(a.stages[0].model, b.stages[0].model)
    assert a.stages[0].history.loss == b.stages[0].history.loss
    assert a.metrics == b.metrics


def test_rerun_of_the_fixture_repeats(pendulum, base):
    again = solver(system=pendulum, seed=0).solve(0.5)
    assert_same_weights(base.stages[0].model, again.stages[0].model)
    assert base.stages[0].history.loss == again.stages[0].history.loss


def test_different_seed_differs(pendulum, base, x_test):
    other = solver(system=pendulum, seed=1).solve(0.5)
    assert other.stages[0].seed == 1 and base.stages[0].seed == 0
    w0 = base.stages[0].model.net.state_dict()
    w1 = other.stages[0].model.net.state_dict()
    assert any(not torch.equal(w0[k], w1[k]) for k in w0)
    assert base.stages[0].history.loss != other.stages[0].history.loss
    assert np.abs(base.value(x_test) - other.value(x_test)).max() > 1e-4


# ------------------------------------------------------------------------------ horizon extension
def test_extension_chain_layout(base, chain):
    assert chain.horizon == pytest.approx(1.5)
    assert chain.horizons == pytest.approx([0.5, 1.0, 1.5])
    assert [s.start for s in chain.stages] == pytest.approx([0.0, 0.5, 1.0])
    assert [s.length for s in chain.stages] == pytest.approx([0.5, 0.5, 0.5])
    assert [s.seed for s in chain.stages] == [0, 1, 2]  # stage k uses seed + k
    assert chain.stages[0] is base.stages[0]  # the original stage is reused, not retrained
    assert len(base.stages) == 1  # ... and the input solution is left alone
    assert not chain.interrupted


def test_extension_terminal_data_is_previous_stage_at_zero(chain, x_test):
    x = torch.as_tensor(x_test, dtype=torch.float32)
    for k in range(1, len(chain.stages)):
        model = chain.stages[k].model
        assert isinstance(model.terminal_cost, ValueTerminalCost)
        with torch.no_grad():
            phi = model.terminal_cost(x)
            previous = chain.stages[k - 1].model(x, 0.0)
            at_end = model(x, model.horizon)
        assert torch.equal(phi, previous)
        assert torch.equal(at_end, previous)  # v(x, T) = phi(x) exactly under the ansatz


def test_chain_value_matches_truncated_solutions(chain, x_test):
    # V_{T_K}(x, t) at t = T_K - T_{k} is V_{T_k}(x, 0)
    for k in range(1, len(chain.stages)):
        t = chain.horizon - chain.stages[k - 1].end
        np.testing.assert_array_equal(chain.value(x_test, t), chain.truncated(k).value(x_test, 0.0))
    last = chain.stages[-1].length
    np.testing.assert_array_equal(chain.value(x_test, last), chain.truncated(len(chain.stages) - 1).value(x_test))
    # and the extension did change the value at t = 0
    assert np.abs(chain.value(x_test) - chain.truncated(1).value(x_test)).max() > 1e-4


def test_value_time_outside_horizon_is_rejected(chain, x_test):
    with pytest.raises(ValueError, match=r"t must lie in \[0, 1.5\]"):
        chain.value(x_test, 1.6)
    with pytest.raises(ValueError, match="t must lie"):
        chain.value(x_test, -0.1)
    with pytest.raises(ValueError, match="k must be"):
        chain.truncated(4)


def test_warm_start_copies_previous_weights(pendulum):
    first = solver(system=pendulum, phases=adam(steps=3)).solve(0.5)
    extended = solver(system=pendulum, phases=()).extend(first, to=1.0)
    assert_same_weights(extended.stages[1].model.net, first.stages[0].model.net)


def test_extend_rejects_bad_targets(pendulum, base):
    s = solver(system=pendulum)
    with pytest.raises(ValueError, match="must exceed the current horizon"):
        s.extend(base, to=0.5)
    with pytest.raises(ValueError, match="must exceed the current horizon"):
        s.extend(base, to=0.2)
    with pytest.raises(ValueError, match="must exceed"):
        s.extend(base, to=float("nan"))
    with pytest.raises(ValueError, match="step must be a positive finite number"):
        s.extend(base, to=1.0, step=0.0)
    with pytest.raises(ValueError, match="step must be a positive finite number"):
        s.extend(base, to=1.0, step=-0.5)
    with pytest.raises(TypeError):
        s.extend("not a solution", to=1.0)


def test_extend_rejects_solution_of_another_system(base):
    with pytest.raises(ValueError, match="system"):
        solver(system=ph.systems.pendulum(R=2.0)).extend(base, to=1.0)


@pytest.mark.parametrize("horizon", [0.0, -1.0, float("nan"), float("inf"), "1.0"])
def test_solve_rejects_bad_horizon(pendulum, horizon):
    with pytest.raises(ValueError, match="horizon must be a positive finite number"):
        solver(system=pendulum).solve(horizon)


def test_interrupted_extension_keeps_completed_stages(pendulum, base):
    seen = []

    def callback(sol):
        seen.append(sol.horizon)
        raise KeyboardInterrupt

    with pytest.warns(UserWarning, match="interrupted"):
        sol = solver(system=pendulum).extend(base, to=2.0, step=0.5, callback=callback)
    assert seen == [1.0]
    assert sol.interrupted is True
    assert len(sol.stages) == 2 and sol.horizon == pytest.approx(1.0)
    assert sol.stages[0] is base.stages[0]
    assert "E" in sol.metrics  # the completed stage was evaluated before the interrupt


# ------------------------------------------------------------------------------ solve_until
def test_solve_until_stops_when_tolerance_is_met(pendulum):
    sol = solver(system=pendulum).solve_until(tol=1e6, step=0.5, max_horizon=5.0)
    assert len(sol.stages) == 1 and sol.horizon == pytest.approx(0.5)
    assert sol.converged is True


def test_solve_until_stops_at_max_horizon(pendulum):
    horizons = []
    sol = solver(system=pendulum).solve_until(
        tol=1e-30, step=0.5, max_horizon=1.2, callback=lambda s: horizons.append(s.horizon)
    )
    assert sol.horizons == pytest.approx([0.5, 1.0, 1.2])
    assert horizons == pytest.approx([0.5, 1.0, 1.2])
    assert sol.converged is False
    with pytest.raises(ValueError, match="tol must be a positive finite number"):
        solver(system=pendulum).solve_until(tol=0.0, step=0.5)


# ------------------------------------------------------------------------------ steady-state baseline
def test_steady_state_solver(pendulum):
    config = ph.TrainConfig.preset("quick", **FAST)
    sol = ph.SteadyStateSolver(pendulum, config, seed=0, device="cpu", progress=False).solve()
    assert sol.value(np.zeros((1, 2)))[0] == 0.0
    assert sol.metrics["E_boundary"] == 0.0
    assert sol.history.final_loss < sol.history.loss[0]
    x = np.random.default_rng(0).uniform(-1, 1, (10, 2))
    assert sol.policy(x).shape == (10, 1) and sol.gradient(x).shape == (10, 2)
    assert np.abs(sol.value(x)).max() > 0


# ------------------------------------------------------------------------------ TrainConfig
@pytest.mark.parametrize(
    "field, value",
    [
        ("width", 0),
        ("depth", 0),
        ("batch_size", 0),
        ("pool_size", 0),
        ("log_every", 0),
        ("dtype", "float16"),
        ("sampling", "random"),
        ("phases", (ph.Adam(), "lbfgs")),
        ("retries", -1),
        ("retries", 1.5),
        ("retry_factor", 0.5),
        ("retry_factor", float("nan")),
        ("retry_against", "last"),
        ("loop_share", -0.1),
        ("loop_share", 1.0),
        ("loop_time", 0.0),
        ("loop_policy", "optimal"),
    ],
)
def test_train_config_rejects_bad_fields(field, value):
    with pytest.raises(ValueError, match=field):
        ph.TrainConfig(**{field: value})


@pytest.mark.parametrize(
    "phase, field, value",
    [
        (ph.Adam, "steps", 0),
        (ph.Adam, "lr", 0.0),
        (ph.Adam, "lr", float("nan")),
        (ph.Adam, "schedule", "step"),
        (ph.Adam, "stop_loss", -1.0),
        (ph.LBFGS, "steps", -1),
        (ph.LBFGS, "points", 0),
        (ph.LevenbergMarquardt, "steps", 1.5),
        (ph.LevenbergMarquardt, "damping", 0.0),
        (ph.LevenbergMarquardt, "min_progress", 0.5),
    ],
)
def test_phases_reject_bad_fields(phase, field, value):
    with pytest.raises(ValueError, match=rf"invalid {phase.__name__} field\(s\) \['{field}'\]"):
        phase(**{field: value})


def test_flat_optimiser_fields_are_refused_with_the_phase_to_use():
    with pytest.raises(TypeError, match=r"with_phase\('adam', steps=...\)"):
        ph.TrainConfig.preset("quick", adam_steps=7)
    with pytest.raises(TypeError, match=r"with_phase\('lm', damping=...\)"):
        ph.TrainConfig().replace(lm_damping=1e-2)
    with pytest.raises(KeyError, match="no 'adam' phase"):
        ph.TrainConfig().with_phase("adam", steps=3)
    with pytest.raises(ValueError, match="unknown LevenbergMarquardt field"):
        ph.TrainConfig().with_phase("lm", step=3)


def test_train_config_fixed_data_needs_enough_flow_points():
    with pytest.raises(ValueError, match="n_flow"):
        ph.TrainConfig(sampling="fixed", n_flow=100, batch_size=500)


def test_train_config_presets():
    with pytest.raises(KeyError, match="unknown preset"):
        ph.TrainConfig.preset("fastest")
    with pytest.raises(KeyError, match="paper preset"):
        ph.TrainConfig.preset("paper", system="lq")
    paper = ph.TrainConfig.preset("paper", system="quartic")
    adam_phase = paper.phase("adam")
    assert (paper.width, adam_phase.lr, adam_phase.stop_loss, paper.ansatz, paper.sampling) == (
        250,
        0.01,
        1e-4,
        False,
        "fixed",
    )
    quick = ph.TrainConfig.preset("quick").with_phase("adam", steps=7)
    assert quick.phase("adam") == ph.Adam(steps=7, lr=5e-3) and quick.width == 32
    assert quick.without_phase("lbfgs").phases == (ph.Adam(steps=7, lr=5e-3),)
    assert ph.TrainConfig.from_dict(quick.to_dict()) == quick
    assert quick.replace(width=8).width == 8
    with pytest.raises(ValueError, match="unknown TrainConfig field"):
        ph.TrainConfig.from_dict({**quick.to_dict(), "momentum": 0.9})
    with pytest.raises(TypeError):
        ph.TrainConfig.preset("quick", momentum=0.9)


def test_solver_accepts_preset_name(pendulum):
    assert ph.FiniteHorizonSolver(pendulum, "paper", progress=False, device="cpu").config.phase("adam").lr == 0.005
    with pytest.raises(TypeError, match="config"):
        ph.FiniteHorizonSolver(pendulum, 3, device="cpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="CUDA is available here")
def test_cuda_request_without_cuda_raises(pendulum):
    with pytest.raises(RuntimeError, match="CUDA is not available"):
        ph.FiniteHorizonSolver(pendulum, "quick", device="cuda")
    with pytest.raises(RuntimeError, match="CUDA is not available"):
        ph.SteadyStateSolver(pendulum, "quick", device="cuda")


# ------------------------------------------------------------------------------ regressions
def test_final_loss_is_the_last_adam_loss_regardless_of_logging(pendulum):
    every = solver(system=pendulum, log_every=1).solve(0.5).stages[0].history
    sparse = solver(system=pendulum, log_every=25).solve(0.5).stages[0].history
    logged = dict(zip(every.step, every.loss))
    assert [logged[s] for s in sparse.step[:-1]] == sparse.loss[:-1]  # same run, only the logging differs
    assert every.step[-2] == 30 and every.final_loss == every.loss[-2]
    assert sparse.final_loss == every.final_loss


def test_float64_warm_start_copies_previous_weights_exactly(pendulum):
    first = solver(system=pendulum, phases=adam(steps=3), dtype="float64").solve(0.5)
    extended = solver(system=pendulum, phases=(), dtype="float64").extend(first, to=1.0)
    assert_same_weights(extended.stages[1].model.net, first.stages[0].model.net)


def test_solution_closed_loop_runs_its_policy(chain):
    result = chain.closed_loop(np.array([[0.5, 0.0], [-0.5, 0.2]]), t_final=1.0, dt=0.05)
    assert result.x.shape == (21, 2, 2) and result.u.shape == (21, 2, 1)
    x0 = torch.tensor([[0.5, 0.0], [-0.5, 0.2]], dtype=torch.float64)
    np.testing.assert_allclose(result.u[0], chain.policy(x0).numpy(), rtol=1e-6)
    assert np.all(np.isfinite(result.cost)) and np.all(result.cost > 0)


# ------------------------------------------------------------------------------ retries (config.retries)
def scripted_losses(monkeypatch, losses):
    """Train as usual, but report the final losses ``losses`` in turn (a stage's loss decides its retries)."""
    real = ph.solver.train_finite_horizon
    seeds = []

    def train(*args, **kwargs):
        seeds.append(kwargs["seed"])
        return dataclasses.replace(real(*args, **kwargs), final_loss=losses[len(seeds) - 1])

    monkeypatch.setattr(ph.solver, "train_finite_horizon", train)
    return seeds


def test_first_stage_is_tried_one_plus_retries_times_and_keeps_the_lowest_loss(pendulum, monkeypatch):
    seeds = scripted_losses(monkeypatch, [3.0, 1.0, 2.0])
    sol = solver(system=pendulum, seed=7, retries=2).solve(0.5)
    assert seeds == [7, 1007, 2007] and sol.stages[0].seed == 1007  # solver seed 7, stage 0
    assert [a["seed"] for a in sol.stages[0].rejected] == [7, 2007]
    assert [a["final_loss"] for a in sol.stages[0].rejected] == [3.0, 2.0]
    assert sol.summary()[0]["rejected"] == 2


def test_extension_stage_is_retried_only_when_its_loss_rises(pendulum, monkeypatch):
    base = solver(system=pendulum).solve(0.5)  # one attempt without retries
    assert base.stages[0].rejected == () and "rejected" not in base.summary()[0]
    loss = base.stages[0].history.final_loss
    seeds = scripted_losses(monkeypatch, [5 * loss, 60 * loss, loss, 0.1 * loss])
    sol = solver(system=pendulum, retries=2).extend(base, to=1.5, step=0.5)
    # stage 2: 5x its previous stage's loss, below retry_factor = 10: kept; stage 3: 12x its previous stage's
    # (5 loss) fails, and its second attempt, below 10x, is kept and ends the retries
    assert seeds == [1, 2, 1002]
    assert sol.stages[1].rejected == () and sol.stages[2].seed == 1002
    assert [a["final_loss"] for a in sol.stages[2].rejected] == [60 * loss]


def test_retry_base_is_the_previous_loss_or_the_lowest_finite_one():
    losses = [4.0, 1.0, math.inf, 2.0]
    assert ph.solver.retry_base(losses) == ph.solver.retry_base(losses, "previous") == 2.0
    assert ph.solver.retry_base(losses, "best") == 1.0  # the inf is skipped
    assert math.isnan(ph.solver.retry_base([math.nan], "best"))  # none finite: the last one
    with pytest.raises(ValueError, match="at least one stage"):
        ph.solver.retry_base([], "best")
    with pytest.raises(ValueError, match="'previous' or 'best'"):
        ph.solver.retry_base(losses, "worst")


def test_retry_against_best_catches_a_loss_that_creeps_up(pendulum, monkeypatch, tmp_path):
    base = solver(system=pendulum).solve(0.5)
    loss = base.stages[0].history.final_loss
    # each stage 4x the one before, below retry_factor = 10: "previous" never retries; "best" compares stage 3's
    # 16 loss with the chain's lowest (stage 1's), fails it, and keeps its second attempt (2 loss)
    seeds = scripted_losses(monkeypatch, [4 * loss, 16 * loss, 2 * loss])
    sol = solver(system=pendulum, retries=1, retry_against="previous").extend(base, to=1.5, step=0.5)
    assert seeds == [1, 2] and all(s.rejected == () for s in sol.stages)
    monkeypatch.undo()
    seeds = scripted_losses(monkeypatch, [4 * loss, 16 * loss, 2 * loss])
    sol = solver(system=pendulum, retries=1, retry_against="best").extend(base, to=1.5, step=0.5)
    assert seeds == [1, 2, 1002] and sol.stages[1].rejected == ()
    assert sol.stages[2].seed == 1002 and [a["final_loss"] for a in sol.stages[2].rejected] == [16 * loss]
    loaded = ph.load(ph.save(sol, tmp_path / "best.pt"), pendulum)
    assert loaded.config.retry_against == "best"


def test_rejected_attempts_are_saved_and_loaded(pendulum, monkeypatch, tmp_path):
    scripted_losses(monkeypatch, [2.0, 1.0])
    sol = solver(system=pendulum, retries=1).solve(0.5)
    loaded = ph.load(ph.save(sol, tmp_path / "retried.pt"), pendulum)
    assert loaded.stages[0].rejected == sol.stages[0].rejected and len(loaded.stages[0].rejected) == 1
    assert loaded.config.retries == 1


# ------------------------------------------------------------------------------ states along loops (loop_share)
@pytest.fixture
def pools(monkeypatch):
    """The states of every StatePool built while the test runs, in order."""
    seen = []
    real = ph.training.StatePool.__init__

    def spy(self, system, states, *args, **kwargs):
        seen.append(states.clone())
        real(self, system, states, *args, **kwargs)

    monkeypatch.setattr(ph.training.StatePool, "__init__", spy)
    return seen


def test_loop_states_lie_on_lqr_loops_from_omega():
    # an LQ system, so the loops are those of the optimal policy: V* = x'Px never rises along them, and none
    # ends above V*'s largest value on Omega (at a corner), while some leave Omega (the open loop is unstable)
    A, B = np.array([[1.0, 1.0], [0.0, 2.0]]), np.array([[0.0], [1.0]])
    system = ph.systems.linear_quadratic(A, B, np.eye(2), np.eye(1), domain=[[-1, 1], [-1, 1]])
    gen = torch.Generator().manual_seed(3)
    x = ph.training.loop_states(system, 500, gen, 1.0).numpy()
    assert x.shape == (500, 2) and np.isfinite(x).all()
    P = ph.lq.care(A, B, np.eye(2), np.eye(1))
    corners = np.array([[1.0, 1.0], [1.0, -1.0]])
    top = np.einsum("bi,ij,bj->b", corners, P, corners).max()
    assert np.einsum("bi,ij,bj->b", x, P, x).max() <= top * (1 + 1e-9)
    assert (np.abs(x) > 1).any(axis=1).sum() > 0
    again = ph.training.loop_states(system, 500, torch.Generator().manual_seed(3), 1.0).numpy()
    np.testing.assert_array_equal(x, again)


@pytest.mark.filterwarnings("ignore:stage 1:RuntimeWarning")  # nothing is trained: only the pools are compared
def test_loop_share_replaces_a_share_of_the_pool(pendulum, pools):
    solver(system=pendulum, phases=()).solve(0.5)
    solver(system=pendulum, phases=(), loop_share=0.25, loop_time=2.0).solve(0.5)
    uniform, looped = pools
    k = round(0.25 * len(uniform))
    assert torch.equal(uniform[k:], looped[k:])  # the same uniform states, but the first quarter along loops
    assert not torch.equal(uniform[:k], looped[:k])
    box = torch.as_tensor(pendulum.train_domain)
    assert ((uniform >= box[:, 0]) & (uniform <= box[:, 1])).all()
    config = ph.TrainConfig.preset("quick", loop_share=0.25)
    assert ph.TrainConfig.from_dict(config.to_dict()) == config
    assert "loop_share" not in ph.TrainConfig().to_dict()  # stored configs read back unchanged


@pytest.mark.filterwarnings("ignore:stage:RuntimeWarning")  # nothing is trained: only the pools are compared
def test_loop_policy_terminal_follows_the_terminal_costs_policy(pools):
    # from x'Px of the CARE the terminal cost's policy is the LQR policy: the same loops to rounding; one stage
    # on, the terminal cost is that stage's (untrained) value, whose loops differ; from the terminal cost 0 (policy
    # u = 0) the LQR loops again
    A, B = np.array([[0.0, 1.0], [-1.0, 0.5]]), np.array([[0.0], [1.0]])
    system = ph.systems.linear_quadratic(A, B, np.eye(2), np.eye(1), domain=[[-1, 1], [-1, 1]])
    P = ph.lq.care(A, B, np.eye(2), np.eye(1))
    for policy in ("lqr", "terminal"):
        s = solver(system=system, phases=(), loop_share=0.5, loop_policy=policy, dtype="float64")
        s.extend(s.solve(0.5, terminal_cost=P), 1.0)
        s.solve(0.5)
    lqr, lqr_next, lqr_zero, terminal, terminal_next, terminal_zero = pools
    k = len(lqr) // 2
    torch.testing.assert_close(terminal, lqr, rtol=0, atol=1e-12)
    assert torch.equal(terminal_next[k:], lqr_next[k:]) and not torch.allclose(terminal_next[:k], lqr_next[:k])
    assert torch.equal(terminal_zero, lqr_zero)
    assert ph.TrainConfig.from_dict(ph.TrainConfig(loop_policy="terminal").to_dict()).loop_policy == "terminal"
    assert "loop_policy" not in ph.TrainConfig().to_dict()


# ------------------------------------------------------------------------------ warm_start="best"
def scripted_E(values):
    """An evaluate hook that reports the E values ``values`` in turn (and counts its calls)."""
    calls = []

    def evaluate(sol):
        calls.append(sol.horizon)
        return {"E": values[len(calls) - 1]}

    return evaluate, calls


def best_solver(pendulum, evaluate):
    config = ph.TrainConfig.preset("quick", **{**FAST, "phases": (), "warm_start": "best"})
    return ph.FiniteHorizonSolver(pendulum, config, seed=0, device="cpu", progress=False, evaluate=evaluate)


def test_best_start_trains_both_ways_and_keeps_the_lower_E(pendulum, tmp_path):
    # no training (phases=()): a warm stage keeps the previous weights, a fresh one its seeded initial weights
    evaluate, calls = scripted_E([1.0, 0.5, 0.3, 0.2, 0.4])
    sol = best_solver(pendulum, evaluate).extend(best_solver(pendulum, evaluate).solve(0.5), to=1.5, step=0.5)
    assert calls == [0.5, 1.0, 1.0, 1.5, 1.5]  # each extension stage evaluated twice: warm, then fresh
    first, second, third = sol.stages
    assert first.started_warm is None and first.rejected == () and first.other_attempt is None
    assert second.started_warm is False and second.metrics["E"] == 0.3  # the fresh attempt's lower E
    assert second.rejected[0]["warm_start"] is True and second.rejected[0]["metrics"] == {"E": 0.5}
    assert second.other_attempt is second.rejected[0] and third.other_attempt["warm_start"] is False
    assert third.started_warm is True and third.metrics["E"] == 0.2
    assert_same_weights(third.model.net, second.model.net)
    pairs = zip(second.model.net.parameters(), first.model.net.parameters())
    assert not all(torch.equal(a, b) for a, b in pairs)
    rows = sol.summary()
    assert [r.get("started_warm") for r in rows] == [None, False, True] and rows[1]["rejected"] == 1
    assert sol.wall_time == pytest.approx(
        sum(s.history.wall_time for s in sol.stages) + sum(s.rejected[0]["wall_time"] for s in sol.stages[1:])
    )
    loaded = ph.load(ph.save(sol, tmp_path / "best.pt"), pendulum)
    assert [s.started_warm for s in loaded.stages] == [None, False, True] and loaded.config.warm_start == "best"


def test_best_start_needs_E_from_the_hook_and_keeps_what_trained(pendulum):
    evaluate, _ = scripted_E([1.0, 0.5, 0.3])
    base = best_solver(pendulum, evaluate).solve(0.5)
    with pytest.raises(ValueError, match="warm_start='best' keeps the attempt with the lower E") as info:
        best_solver(pendulum, lambda sol: {"loss": 1.0}).extend(base, to=1.0)
    assert info.value.partial_solution.horizon == 1.0  # the warm attempt, trained and kept


@pytest.mark.parametrize("bad", ["cold", 1, None])
def test_warm_start_must_be_a_bool_best_or_features(bad):
    with pytest.raises(ValueError, match=r"warm_start=.*expected True, False, 'best' or 'features'"):
        ph.TrainConfig(warm_start=bad)


def test_features_start_needs_the_ansatz():
    with pytest.raises(ValueError, match=r"'features' needs ansatz=True"):
        ph.TrainConfig(warm_start="features", ansatz=False)


def test_features_start_begins_at_the_terminal_cost(pendulum, tmp_path):
    # warm_start="features": the previous stage's hidden layers, the last layer zero; untrained (phases=()), the
    # new stage is its terminal cost at every time, V = V_prev(., 0)
    first = solver(system=pendulum, phases=adam(steps=3)).solve(0.5)
    extended = solver(system=pendulum, phases=(), warm_start="features").extend(first, to=1.0)
    new, old = extended.stages[1].model.net.layers, first.stages[0].model.net.layers
    assert all(torch.equal(a, b) for a, b in zip(new[:-1].parameters(), old[:-1].parameters()))
    assert not new[-1].weight.any() and not new[-1].bias.any() and old[-1].weight.any()
    x = (torch.rand(64, 2) - 0.5).to(new[-1].weight.dtype)
    for t in (0.0, 0.25):
        assert torch.equal(extended.stages[1].model(x, t), first.stages[0].model(x, 0.0))
    loaded = ph.load(ph.save(extended, tmp_path / "features.pt"), pendulum)
    assert loaded.config.warm_start == "features"


@pytest.mark.parametrize("failure", [KeyboardInterrupt, RuntimeError])
def test_best_start_keeps_the_first_attempt_when_the_second_fails(pendulum, monkeypatch, failure):
    evaluate, _ = scripted_E([1.0, 0.5, 0.3])
    base = best_solver(pendulum, evaluate).solve(0.5)
    real, calls = ph.solver.train_finite_horizon, []

    def train(*args, **kwargs):  # the warm attempt trains, the fresh one fails
        calls.append(kwargs["desc"])
        if len(calls) == 2:
            raise failure("stopped")
        return real(*args, **kwargs)

    monkeypatch.setattr(ph.solver, "train_finite_horizon", train)
    if failure is KeyboardInterrupt:
        with pytest.warns(UserWarning, match="interrupted: returning the 2 completed stage"):
            sol = best_solver(pendulum, evaluate).extend(base, to=1.0)
        assert sol.interrupted and sol.horizon == 1.0 and sol.stages[-1].metrics == {"E": 0.5}
    else:
        with pytest.raises(RuntimeError, match="stopped") as info:
            best_solver(pendulum, evaluate).extend(base, to=1.0)
        assert info.value.partial_solution.horizon == 1.0
    assert calls[1].endswith(", fresh")
