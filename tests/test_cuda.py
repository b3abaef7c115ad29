"""The package on a GPU: the same calls train and evaluate on CUDA, give what the CPU gives for the same seed, and
a checkpoint written there loads on the CPU. Skipped where CUDA is absent (CI); run on a machine with a GPU."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import pinnhjb as ph

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")

# 8 x 2 network; Levenberg-Marquardt in float64 on a fixed number of steps (no stall rule: both devices do the
# same iterations), and the first-order path in float32
LM = dict(
    width=8,
    depth=2,
    phases=(ph.LevenbergMarquardt(steps=8, points=200, points_coarse=None, min_progress=None),),
    eval_points_per_dim=11,
    pool_size=2000,
)
ADAM = dict(
    width=16,
    depth=2,
    phases=(ph.Adam(steps=40, lr=5e-3), ph.LBFGS(steps=5, points=512)),
    batch_size=128,
    eval_points_per_dim=11,
    pool_size=2000,
)


@pytest.fixture(scope="module")
def x_test():
    return np.random.default_rng(0).uniform(-1, 1, (64, 2))


def _both(system, config, horizon=1.0):
    return [
        ph.FiniteHorizonSolver(system, config, seed=3, device=d, progress=False).solve(horizon) for d in ("cpu", "cuda")
    ]


def test_default_device_is_cuda_when_present():
    assert ph.FiniteHorizonSolver(ph.systems.pendulum(), "quick", progress=False).device.type == "cuda"


def test_levenberg_marquardt_on_cuda_matches_the_cpu(x_test):
    cpu, gpu = _both(ph.systems.pendulum(), ph.TrainConfig(**LM))
    assert gpu.device.type == "cuda" and cpu.device.type == "cpu"
    # same initial weights and points (drawn on the CPU), float64: the two runs differ only by rounding
    assert np.allclose(gpu.value(x_test), cpu.value(x_test), rtol=1e-6, atol=1e-8)
    assert gpu.metrics["E"] == pytest.approx(cpu.metrics["E"], rel=1e-4)
    assert gpu.metrics["E"] < gpu.stages[0].history.loss[0]  # and it trained


@pytest.mark.parametrize("preset", ["adam_lbfgs", "paper"])
def test_first_order_recipes_on_cuda_train_and_evaluate(preset, x_test):
    """Our first-order recipe (ansatz, fresh points) and the paper's (soft terms, fixed data) in float32."""
    extra = {"system": "quartic"} if preset == "paper" else {}
    cpu, gpu = _both(ph.systems.quartic(), ph.TrainConfig.preset(preset, **extra, **ADAM), horizon=0.5)
    h = gpu.stages[0].history
    assert h.loss[-1] < h.loss[0]
    v = gpu.value(x_test)
    assert v.shape == (64,) and np.isfinite(v).all()
    # float32 on different hardware: the same run up to rounding growth over 45 steps
    assert np.abs(v - cpu.value(x_test)).max() < 0.05 * np.abs(cpu.value(x_test)).max() + 1e-3


def test_extension_and_checkpoint_from_cuda_to_cpu(tmp_path, x_test):
    solver = ph.FiniteHorizonSolver(ph.systems.pendulum(), ph.TrainConfig(**LM), seed=1, device="cuda", progress=False)
    sol = solver.extend(solver.solve(0.5), to=1.0)
    path = ph.save(sol, tmp_path / "gpu.pt")
    back = ph.load(path, device="cpu")
    assert back.device.type == "cpu"
    assert np.allclose(back.value(x_test), sol.value(x_test), rtol=1e-12, atol=1e-12)
    assert back.evaluate(11)["E"] == pytest.approx(sol.evaluate(11)["E"], rel=1e-9)
    moved = sol.to("cpu")  # the same round trip, in one call
    assert moved.device.type == "cpu" and moved.to("cpu") is moved and sol.device.type == "cuda"
    assert np.allclose(moved.value(x_test), sol.value(x_test), rtol=1e-12, atol=1e-12)
    assert moved.to("cuda").device.type == "cuda"


def test_rigid_body_recipe_on_cuda_matches_the_cpu():
    """The 6-D path of issue #18 on the GPU: the structured Jacobian with grad V(0, t) = 0 built in (its mixed
    channel), training states along the LQR loops, the LQR terminal cost and E by Monte Carlo, as on the CPU."""
    system = ph.systems.rigid_body()
    config = ph.TrainConfig.preset("default", dimension=system.n).replace(
        width=8,
        depth=2,
        flat_origin=True,
        loop_share=0.3,
        pool_size=2000,
        eval_points_per_dim=3,
        phases=(ph.LevenbergMarquardt(steps=6, points=300, points_coarse=None, min_progress=None),),
    )
    terminal = system.lqr_value()
    cpu, gpu = (
        ph.FiniteHorizonSolver(system, config, seed=2, device=d, progress=False).solve(1.0, terminal_cost=terminal)
        for d in ("cpu", "cuda")
    )
    x = np.random.default_rng(1).uniform(-0.5, 0.5, (32, 6))
    assert gpu.device.type == "cuda"
    assert np.allclose(gpu.value(x), cpu.value(x), rtol=1e-6, atol=1e-8)
    assert np.allclose(gpu.gradient(x), cpu.gradient(x), rtol=1e-5, atol=1e-7)
    assert gpu.metrics["E"] == pytest.approx(cpu.metrics["E"], rel=1e-4)
