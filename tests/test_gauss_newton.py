"""Levenberg-Marquardt (pinnhjb.gauss_newton) and the default recipe that uses it."""

from __future__ import annotations

import pytest
import torch

import pinnhjb as ph
from pinnhjb.gauss_newton import FlatParameters, levenberg_marquardt

# 8 x 2 on (x, t): 113 weights; the coarse level's 60 points are fewer (the dual solve), the last level's 200 more
LM = ph.LevenbergMarquardt(steps=12, points=200, points_coarse=60)
TINY_LM = dict(width=8, depth=2, phases=(LM,), eval_points_per_dim=11, pool_size=2000)


def _linear_problem(n_points: int, n_params: int, seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    A = torch.randn(n_points, n_params, generator=gen, dtype=torch.float64)
    b = torch.randn(n_points, generator=gen, dtype=torch.float64)

    def point_residual(theta, a, bi):
        return a @ theta - bi

    return A, b, point_residual, (lambda size: (A, b))


@pytest.mark.parametrize("n_points, n_params", [(40, 10), (10, 40)])
def test_linear_least_squares_reaches_the_minimum_norm_solution(n_points, n_params):
    """On a linear problem one undamped Gauss-Newton step is the least-squares solution; both the primal
    (N > P) and the dual (N < P) solves must get there."""
    A, b, point_residual, sample = _linear_problem(n_points, n_params)
    theta0 = torch.zeros(n_params, dtype=torch.float64)
    res = levenberg_marquardt(theta0, point_residual, sample, steps=30, points=n_points, damping=1e-8)
    expected = torch.linalg.lstsq(A, b, driver="gelsd").solution
    if n_points > n_params:
        assert torch.allclose(res.theta, expected, atol=1e-6)
    else:  # interpolation: the residual vanishes
        assert res.loss < 1e-12
        assert torch.allclose(A @ res.theta, b, atol=1e-6)
    assert res.steps <= 30 and res.stop_reason in ("lm_steps", "stalled")


def test_rejected_steps_raise_the_damping_and_never_raise_the_loss():
    """A nonlinear residual (Rosenbrock as least squares): every accepted step lowers the loss on its batch."""

    def point_residual(theta, w, c):
        return w[0] * (theta[1] - theta[0] ** 2) * c + w[1] * (1 - theta[0])

    W = torch.tensor([[10.0, 0.0], [0.0, 1.0]], dtype=torch.float64)
    C = torch.ones(2, dtype=torch.float64)
    losses = []
    res = levenberg_marquardt(
        torch.tensor([-1.2, 1.0], dtype=torch.float64),
        point_residual,
        lambda n: (W, C),
        steps=60,
        points=2,
        damping=1.0,
        on_step=lambda k, loss, lam: losses.append(loss),
    )
    assert all(b <= a for a, b in zip(losses, losses[1:]))
    assert torch.allclose(res.theta, torch.ones(2, dtype=torch.float64), atol=1e-6)


def test_stall_rule_stops_a_run_that_makes_no_progress():
    A, b, point_residual, sample = _linear_problem(40, 10)
    exact = torch.linalg.lstsq(A, b).solution
    res = levenberg_marquardt(exact, point_residual, sample, steps=500, points=40, min_progress=2.0, window=5)
    assert res.stop_reason == "stalled" and res.steps == 15  # three windows of five, no progress after the first
    longer = levenberg_marquardt(
        exact, point_residual, sample, steps=500, points=40, min_progress=2.0, window=5, stall_windows=3
    )
    assert longer.stop_reason == "stalled" and longer.steps == 20
    full = levenberg_marquardt(exact, point_residual, sample, steps=25, points=40)
    assert full.steps == 25 and full.stop_reason == "lm_steps"


def test_a_point_schedule_moves_on_at_each_stall_and_stops_at_the_last():
    """points=(20, 30, 40): each stall moves to the next count, the stall rule starts afresh there, and only the
    stall at 40 points stops the run."""
    A, b, point_residual, _ = _linear_problem(40, 10)
    exact = torch.linalg.lstsq(A, b).solution
    sizes = []

    def sample(n):
        sizes.append(n)
        return A[:n], b[:n]

    res = levenberg_marquardt(exact, point_residual, sample, steps=500, points=(20, 30, 40), min_progress=2.0, window=5)
    assert res.stop_reason == "stalled" and sizes == [20] * 15 + [30] * 15 + [40] * 15
    sizes.clear()
    levenberg_marquardt(exact, point_residual, sample, steps=10, points=(20, 40))  # no stall rule: no stall
    assert sizes == [20] * 10
    with pytest.raises(ValueError, match="schedule must grow"):
        levenberg_marquardt(exact, point_residual, sample, steps=3, points=(40, 20))


def test_adaptive_points_are_the_candidates_with_the_largest_residuals():
    """Fit a constant c to points x in [0, 1] (residual c - x): one undamped step lands on the batch's mean. From
    c = 0, the points chosen by residual are the largest x among the candidates, so the mean moves up."""
    gen = torch.Generator().manual_seed(0)
    sizes = []

    def sample(n):
        sizes.append(n)
        return (torch.rand(n, generator=gen, dtype=torch.float64),)

    def point_residual(theta, x):
        return theta[0] - x

    start = torch.zeros(1, dtype=torch.float64)
    plain = levenberg_marquardt(start, point_residual, sample, steps=1, points=4000, damping=1e-12)
    assert sizes == [4000] and abs(plain.theta.item() - 0.5) < 0.02
    sizes.clear()
    # half drawn as usual (mean 1/2), half the top quarter of 4 x 2000 candidates (mean 7/8)
    tilted = levenberg_marquardt(start, point_residual, sample, steps=1, points=4000, damping=1e-12, adaptive=0.5)
    assert sizes == [2000, 8000] and abs(tilted.theta.item() - (0.5 + 0.875) / 2) < 0.02
    for bad in ({"adaptive": 1.0}, {"adaptive": -0.1}, {"candidates": 1}, {"candidates": 2.5}):
        with pytest.raises(ValueError, match="adaptive"):
            levenberg_marquardt(start, point_residual, sample, steps=1, points=10, **bad)
    with pytest.raises(ValueError, match=r"adaptive.*\[0, 1\)"):
        ph.optimizers.LevenbergMarquardt(adaptive=1.0)
    # stored only when set: a config written before the field reads back as it was
    assert "adaptive" not in ph.optimizers.LevenbergMarquardt().to_dict()
    phase = ph.optimizers.LevenbergMarquardt(adaptive=0.3, candidates=8)
    assert ph.optimizers.phase_from_dict(phase.to_dict()) == phase


def test_bad_arguments_and_non_finite_residuals_are_refused():
    A, b, point_residual, sample = _linear_problem(5, 3)
    theta = torch.zeros(3, dtype=torch.float64)
    with pytest.raises(ValueError, match="damping"):
        levenberg_marquardt(theta, point_residual, sample, steps=3, points=5, damping=0.0)
    bad = (A, torch.full_like(b, float("nan")))
    with pytest.raises(FloatingPointError, match="non-finite"):
        levenberg_marquardt(theta, point_residual, lambda n: bad, steps=3, points=5)


def test_flat_parameters_round_trip():
    net = ph.pinn.MLP(3, 5, 2)
    flat = FlatParameters(net)
    theta = flat.get()
    assert theta.numel() == sum(p.numel() for p in net.parameters())
    flat.set(theta * 0 + 0.5)
    assert all(torch.all(p == 0.5) for p in net.parameters())
    assert set(flat.unflatten(theta, "net.")) == {"net." + k for k, _ in net.named_parameters()}


def test_default_recipe_is_levenberg_marquardt_and_refuses_the_soft_loss():
    cfg = ph.TrainConfig()
    assert cfg == ph.TrainConfig.preset("default")
    assert cfg.phases == (ph.LevenbergMarquardt(),) and cfg.ansatz and cfg.dtype == "float64"
    assert [p.name for p in ph.TrainConfig.preset("adam_lbfgs").phases] == ["adam", "lbfgs"]
    assert [p.name for p in ph.TrainConfig.preset("paper", system="pendulum").phases] == ["adam"]
    with pytest.raises(ValueError, match="needs ansatz=True"):
        ph.TrainConfig(ansatz=False)
    with pytest.raises(ValueError, match="min_progress"):
        ph.LevenbergMarquardt(min_progress=0.5)
    with pytest.raises(ValueError, match="points_coarse"):
        ph.LevenbergMarquardt(points=500)  # the coarse level (700 points) must have fewer points than the last
    assert ph.LevenbergMarquardt(points=500, points_coarse=None).points == 500


def test_a_config_stored_before_levenberg_marquardt_loads_without_it():
    paper = ph.TrainConfig.preset("paper", system="pendulum")
    old = _flat(paper)
    for key in ("lm_steps", "lm_points", "lm_damping", "lm_min_progress"):
        old.pop(key)
    assert ph.TrainConfig.from_dict(old) == paper
    before_schedule = _flat(ph.TrainConfig())
    for key in ("lm_points_coarse", "lm_stall_windows"):
        before_schedule.pop(key)
    cfg = ph.TrainConfig.from_dict(before_schedule)  # trained on lm_points throughout, stall span of three windows
    assert cfg.phases == (ph.LevenbergMarquardt(points_coarse=None, stall_windows=3),)
    assert ph.TrainConfig.from_dict(ph.TrainConfig().to_dict()) == ph.TrainConfig()


def _flat(config: ph.TrainConfig) -> dict:
    """``config`` as a checkpoint stored it when the optimisers were flat fields (every field, unused ones too)."""
    d = {k: v for k, v in config.to_dict().items() if k != "phases"}
    d.update(adam_steps=0, lr=2e-3, schedule="cosine", lr_final_ratio=0.01, lr_decay=0.0, stop_loss=None)
    d.update(lbfgs_steps=0, lbfgs_points=4000)
    d.update(lm_steps=0, lm_points=1500, lm_points_coarse=700, lm_damping=1e-3, lm_min_progress=2.0)
    d.update(lm_stall_windows=2)
    for p in config.phases:
        prefix = {"adam": "", "lbfgs": "lbfgs_", "lm": "lm_"}[p.name]
        for key, value in p.to_dict().items():
            if key == "steps":
                d[f"{p.name}_steps"] = value
            elif key != "name":
                d[prefix + key] = value
    return d


def test_a_levenberg_marquardt_stage_beats_adam_on_the_same_network():
    """Same tiny network, same seed: a dozen LM iterations leave a far smaller residual than 150 Adam steps."""
    pendulum = ph.systems.pendulum()
    lm = ph.FiniteHorizonSolver(pendulum, ph.TrainConfig(**TINY_LM), seed=0, device="cpu", progress=False).solve(1.0)
    adam_cfg = ph.TrainConfig(**{**TINY_LM, "phases": (ph.Adam(steps=150, lr=5e-3),), "batch_size": 200})
    adam = ph.FiniteHorizonSolver(pendulum, adam_cfg, seed=0, device="cpu", progress=False).solve(1.0)
    h = lm.stages[0].history
    assert "lm" in h.phase and h.loss[-1] < 0.05 * h.loss[0]
    assert lm.stages[0].history.final_loss < 0.1 * adam.stages[0].history.final_loss
    assert torch.isfinite(torch.tensor(lm.metrics["E"]))


def test_levenberg_marquardt_is_deterministic_and_extends():
    pendulum = ph.systems.pendulum()
    runs = []
    for _ in range(2):
        solver = ph.FiniteHorizonSolver(pendulum, ph.TrainConfig(**TINY_LM), seed=3, device="cpu", progress=False)
        runs.append(solver.extend(solver.solve(0.5), to=1.0))
    a, b = (r.stages[-1].model.net.state_dict() for r in runs)
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert runs[0].horizon == 1.0 and len(runs[0].stages) == 2


def test_steady_state_baseline_trains_with_levenberg_marquardt():
    cfg = ph.TrainConfig(
        **{**TINY_LM, "phases": (LM.replace(points_coarse=None),)}
    )  # 12 iterations: too few to leave a coarse level
    sol = ph.SteadyStateSolver(ph.systems.pendulum(), cfg, seed=0, device="cpu", progress=False).solve()
    h = sol.history
    assert "lm" in h.phase and h.final_loss < 0.25 * h.loss[0]


@pytest.mark.parametrize("min_progress, expected", [(2.0, (60, 200)), (None, (200,))])
def test_training_passes_the_point_schedule_only_with_the_stall_rule(monkeypatch, min_progress, expected):
    """The coarse level ends on a stall: without the stall rule a stage would never leave it, so it trains on
    the last level's points throughout."""
    seen = []
    real = ph.optimizers.levenberg_marquardt

    def spy(theta, point_residual, sample, steps, points, **kw):
        seen.append(tuple(points))
        return real(theta, point_residual, sample, steps, points, **kw)

    monkeypatch.setattr("pinnhjb.optimizers.levenberg_marquardt", spy)
    cfg = ph.TrainConfig(**{**TINY_LM, "phases": (LM.replace(steps=3, min_progress=min_progress),)})
    ph.FiniteHorizonSolver(ph.systems.pendulum(), cfg, seed=0, device="cpu", progress=False).solve(0.5)
    assert seen == [expected]


def test_max_time_stops_the_levenberg_marquardt_phase():
    lm = LM.replace(steps=10_000, min_progress=None)
    cfg = ph.TrainConfig(**{**TINY_LM, "phases": (lm,), "max_time": 0.5})
    sol = ph.FiniteHorizonSolver(ph.systems.pendulum(), cfg, seed=0, device="cpu", progress=False).solve(1.0)
    assert sol.stages[0].history.stop_reason == "max_time"
    assert sol.stages[0].history.step[-1] < 10_000


@pytest.mark.parametrize("blocks", [None, 1, 3, 4])
def test_gram_in_blocks_is_the_plain_product(blocks):
    """gram(A) is A'A whether formed in one product or from its upper blocks (P not a multiple of the blocks)."""
    from pinnhjb.gauss_newton import gram

    A = torch.randn(50, 37, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    G = gram(A, blocks)
    torch.testing.assert_close(G, A.T @ A, rtol=1e-13, atol=1e-12)
    torch.testing.assert_close(G, G.T, rtol=0, atol=1e-12)


def test_a_non_finite_jacobian_is_refused_with_the_stage():
    """A finite residual whose Jacobian is not (sqrt at 0) stops LM with DivergenceError, found on J'J's diagonal."""
    from pinnhjb.gauss_newton import DivergenceError

    a = torch.linspace(0.5, 1.5, 8, dtype=torch.float64)
    with pytest.raises(DivergenceError, match="stage toy.*Jacobian became non-finite"):
        levenberg_marquardt(
            torch.zeros(3, dtype=torch.float64),
            lambda theta, ai: torch.sqrt(theta).sum() * ai,
            lambda size: (a,),
            steps=2,
            points=8,
            desc="toy",
        )
