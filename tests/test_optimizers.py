"""pinnhjb.optimizers: phases as objects, a new optimiser in one class plus its registration, stored configs."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import ClassVar

import pytest
import torch

import pinnhjb as ph
from pinnhjb.optimizers import PHASES, Objective, Phase, PhaseOutcome, Tracker, register

ROOT = Path(__file__).resolve().parents[1]


@dataclasses.dataclass(frozen=True)
class SignDescent(Phase):
    """A toy optimiser: theta <- theta - step_size * sign(grad), on fresh points every step."""

    name: ClassVar[str] = "sign_descent"
    steps: int = 40
    step_size: float = 1e-3

    def run(self, objective: Objective, tracker: Tracker) -> PhaseOutcome:
        loss = None
        for k in range(1, self.steps + 1):
            for p in objective.params:
                p.grad = None
            loss = objective.loss(objective.sample(objective.batch_size))
            loss.backward()
            with torch.no_grad():
                for p in objective.params:
                    p -= self.step_size * p.grad.sign()
            tracker.advance(k, loss.item(), self.name)
        tracker.done += self.steps
        return PhaseOutcome(loss.item(), self.steps, "sign_descent_steps")


@pytest.fixture
def toy_registered():
    register(SignDescent)
    yield SignDescent
    PHASES.pop(SignDescent.name)


def test_a_new_optimiser_is_one_class_and_a_registration_line(toy_registered, tmp_path):
    config = ph.TrainConfig(width=8, depth=2, pool_size=2000, batch_size=256, eval_points_per_dim=11)
    config = config.replace(phases=(SignDescent(steps=40),))
    solver = ph.FiniteHorizonSolver(ph.systems.pendulum(), config, seed=0, device="cpu", progress=False)
    sol = solver.solve(0.5)
    h = sol.stages[0].history
    assert set(h.phase) == {"sign_descent", "final"} and h.stop_reason == "sign_descent_steps"
    assert h.final_loss < h.loss[0]  # it trained
    # the checkpoint stores the phase by its registered name and loads it back
    ph.save(sol, tmp_path / "toy.pt")
    assert ph.load(tmp_path / "toy.pt").config.phases == (SignDescent(steps=40),)


def test_an_unregistered_or_clashing_phase_is_refused():
    with pytest.raises(KeyError, match="unknown optimiser phase 'sign_descent'"):
        ph.TrainConfig.from_dict({**ph.TrainConfig().to_dict(), "phases": [{"name": "sign_descent", "steps": 3}]})

    @dataclasses.dataclass(frozen=True)
    class Impostor(Phase):
        name: ClassVar[str] = "adam"
        steps: int = 1

    with pytest.raises(ValueError, match="already registered"):
        register(Impostor)
    with pytest.raises(TypeError, match="subclass of Phase"):
        register(dict)


def test_phases_round_trip_through_their_dicts():
    for preset in ("default", "adam_lbfgs", "quick"):
        config = ph.TrainConfig.preset(preset)
        assert ph.TrainConfig.from_dict(config.to_dict()) == config
    paper = ph.TrainConfig.preset("paper", system="third_order")
    assert ph.TrainConfig.from_dict(paper.to_dict()) == paper
    assert paper.to_dict()["phases"] == [{"name": "adam", **dataclasses.asdict(paper.phase("adam"))}]


def _stored_checkpoints() -> list[Path]:
    return sorted((ROOT / "artifacts").rglob("*.pt"))


def test_every_stored_checkpoint_migrates_to_the_phases_it_ran():
    """Checkpoints stored before the optimiser phases have flat optimiser fields (lm_steps, lm_points, ...): each
    loads, and its config is the one phase it ran, with the stored settings. The stored ones under artifacts/,
    and the configs of the generation with ``lm_points_coarse`` kept in tests/data (those checkpoints were
    retrained since)."""
    paths = _stored_checkpoints()
    assert len(paths) >= 30
    legacy = json.loads((ROOT / "tests" / "data" / "legacy_configs.json").read_text())["configs"]
    configs = [(p, torch.load(p, map_location="cpu", weights_only=False)["config"]) for p in paths]
    configs += [(f"tests/data/legacy_configs.json[{k}]", c) for k, c in enumerate(legacy)]
    kinds = set()
    for path, stored in configs:
        if "phases" in stored:  # stored with phases: it reads back as it was written
            assert ph.TrainConfig.from_dict(stored).to_dict() == stored, path
            continue
        assert "phases" not in stored and stored["adam_steps"] == 0 and stored["lbfgs_steps"] == 0, path
        expected = ph.LevenbergMarquardt(
            steps=stored["lm_steps"],
            points=stored["lm_points"],
            points_coarse=stored.get("lm_points_coarse"),  # stored before the point schedule: points throughout,
            damping=stored["lm_damping"],
            min_progress=stored["lm_min_progress"],
            stall_windows=stored.get("lm_stall_windows", 3),  # and a stall span of three windows
        )
        config = ph.TrainConfig.from_dict(stored)  # what ph.load does (test_storage and test_paper load them)
        assert config.phases == (expected,), path
        kinds.add("lm_points_coarse" in stored)
        assert ph.TrainConfig.from_dict(config.to_dict()) == config
    assert kinds == {True, False}  # both generations of stored config are covered
