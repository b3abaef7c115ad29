"""Issue 14: every careless-user case, as one table (input, expected error or warning, words in the message).

Each row of :data:`CASES` is ``(id, action, expected, words)``: ``action(ctx)`` does what a user did, ``expected``
is the exception or warning class it must raise, ``words`` a regex its message must match. Rows expecting an
error that must come *before* training run with training disabled (:func:`no_training`), so the test proves the
order. Then a few table rows of accepted inputs (``OK``), and the behaviours that are not an error or a warning
(chains of any length, E in any dimension, checkpoints, the perturbation switch) as short tests. Every training
run here is a tiny network for a few iterations (well under a second).
"""

from __future__ import annotations

import contextlib
import io
import math
import os
import stat
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
import torch

import pinnhjb as ph
from pinnhjb import cli, metrics
from pinnhjb.gauss_newton import DivergenceError
from pinnhjb.pinn import FiniteHorizonValue, ValueTerminalCost
from pinnhjb.residuals import SteadyStateHJB
from pinnhjb.solution import FiniteHorizonSolution, Stage
from pinnhjb.storage import PERTURB_ENV, CheckpointError
from pinnhjb.training import StatePool, TrainHistory

# ------------------------------------------------------------------------------ tiny systems and configs
LM = ph.TrainConfig.preset(
    "default",
    width=4,
    depth=1,
    phases=(ph.LevenbergMarquardt(steps=3, points=64, points_coarse=None),),
    pool_size=256,
    eval_points_per_dim=5,
)
ADAM = ph.TrainConfig.preset(
    "quick",
    width=4,
    depth=1,
    phases=(ph.Adam(steps=3, lr=5e-3),),
    pool_size=256,
    batch_size=32,
    eval_points_per_dim=5,
)
LBFGS = ADAM.replace(phases=(ph.LBFGS(steps=2, points=32),))
CLI_TINY = [
    "--preset",
    "quick",
    "--set",
    "adam.steps=2",
    "--set",
    "lbfgs=off",
    "--set",
    "width=4",
    "--set",
    "depth=1",
    "--set",
    "pool_size=256",
    "--set",
    "batch_size=32",
    "--set",
    "eval_points_per_dim=5",
    "--device",
    "cpu",
    "--no-progress",
]


def f_pend(x):
    return torch.stack([x[:, 1], -torch.sin(x[:, 0]) - 0.1 * x[:, 1]], -1)


def g_one(x):
    return torch.tensor([[0.0], [1.0]], dtype=x.dtype, device=x.device).expand(x.shape[0], 2, 1)


def q_sq(x):
    return (x**2).sum(-1)


def system(name="mine", f=f_pend, g=g_one, Q=q_sq, R=((1.0,),), domain=((-1, 1), (-1, 1)), train_domain=None):
    return ph.ControlAffineSystem(name, f, g, Q, R=[list(r) for r in R], domain=domain, train_domain=train_domain)


def scaled(q_scale=1.0, R=1.0):
    return system(Q=lambda x: q_scale * q_sq(x), R=((R,),))


def f_nan_far(x):  # NaN on part of the training box (x1 > 1.2), fine on Omega
    out = f_pend(x)
    return torch.where((x[:, :1] > 1.2), torch.full_like(out, float("nan")), out)


def solver(sys_=None, config=LM, seed=0):
    return ph.FiniteHorizonSolver(sys_ or system(), config, seed=seed, device="cpu", progress=False)


def no_training(s):
    """The solver, with training replaced by a failure: an error expected before training must come first."""

    def fail(*args, **kwargs):
        raise AssertionError("training started before the bad argument was reported")

    s._train_stage = fail
    return s


def one_stage(s=None, horizon=0.5):
    return (s or solver()).solve(horizon)


def run_cli(argv) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            rc = cli.main(argv)
        except SystemExit as exc:  # argparse: usage errors exit 2 with the message on stderr
            rc = exc.code if isinstance(exc.code, int) else 1
            if isinstance(exc.code, str):
                print(exc.code, file=err)
    return rc, err.getvalue()


class CliError(Exception):
    """What a non-zero CLI exit looks like in the table: the return code and stderr."""


def cli_fails(argv, *, saved=None):
    def action(ctx):
        args = [a.format(tmp=ctx.tmp) for a in argv]
        rc, err = run_cli(args)
        if saved is not None:
            assert not (ctx.tmp / saved).exists(), "an untrained or partial network was saved"
        if rc not in (0, None):
            raise CliError(f"rc={rc}: {err}")
        return rc

    return action


def read_only_folder(ctx):
    folder = ctx.tmp / "ro"
    folder.mkdir()
    (folder / "file").write_text("")
    return str(folder / "file" / "x.pt")  # below a file: not creatable, even for root


def chain_with_broken_third_stage(ctx):
    state = {"scale": 1.0}
    sys_ = system(f=lambda x: state["scale"] * f_pend(x))
    s = solver(sys_)
    first = s.solve(0.5)

    def callback(sol):
        if len(sol.stages) == 2:
            state["scale"] = float("nan")  # the system breaks after stage 2 was trained and saved

    try:
        s.extend(first, to=1.5, step=0.5, callback=callback)
    except ValueError as exc:
        kept = exc.partial_solution
        assert len(kept.stages) == 2 and kept.horizon == pytest.approx(1.0) and "E" in kept.metrics
        assert "partial_solution" in "".join(exc.__notes__)
        raise


def saved_checkpoint(ctx, sys_=None, name="a.pt"):
    sys_ = sys_ or system()
    torch.manual_seed(0)
    model = FiniteHorizonValue(sys_.n, 0.5, sys_.train_domain, width=4, depth=1).double().requires_grad_(False)
    sol = FiniteHorizonSolution(sys_, LM, [Stage(model, 0.0, TrainHistory(), seed=0)], {"kind": "zero"})
    return ph.save(sol, ctx.tmp / name)


def edited_checkpoint(ctx, edit):
    path = saved_checkpoint(ctx)
    raw = torch.load(path, weights_only=True)
    edit(raw)
    torch.save(raw, path)
    return path


def two_stage_checkpoint(ctx):
    sys_ = system()
    torch.manual_seed(0)
    m1 = FiniteHorizonValue(2, 0.5, sys_.train_domain, width=4, depth=1).double().requires_grad_(False)
    m2 = FiniteHorizonValue(2, 0.5, sys_.train_domain, ValueTerminalCost(m1), width=4, depth=1).double()
    sol = FiniteHorizonSolution(
        sys_,
        LM,
        [Stage(m1, 0.0, TrainHistory(), 0), Stage(m2.requires_grad_(False), 0.5, TrainHistory(), 1)],
        {"kind": "zero"},
    )
    return ph.save(sol, ctx.tmp / "two.pt")


def interrupted_inside_save(ctx):
    """Ctrl-C inside the save of stage 2: the file must hold every returned stage, flagged interrupted."""
    real, calls = cli.save, []

    def save(sol, path, **kw):
        calls.append(len(getattr(sol, "stages", [])))
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(sol, path, **kw)

    ctx.monkeypatch.setattr(cli, "save", save)
    out = ctx.tmp / "c.pt"
    rc, err = run_cli(
        ["train", "pendulum", "--horizon", "0.5", "--extend-to", "1.5", "--step", "0.5", "--out", str(out), *CLI_TINY]
    )
    loaded = ph.load(out)
    assert rc == 130 and loaded.interrupted is True
    assert f"holds the stages up to T = {loaded.horizon:g}" in err and loaded.horizon == pytest.approx(1.0)


# ------------------------------------------------------------------------------ the table
CASES = [
    # --- system definitions
    ("R-wrong-size", lambda c: system(R=((1.0, 0.0), (0.0, 1.0))), ValueError, r"R is 2 x 2 but g\(x\) has m=1"),
    ("flat-domain-for-2d", lambda c: system(domain=[-1, 1]), ValueError, r"n=1 was taken from the flat domain"),
    ("ragged-domain", lambda c: system(domain=[[-1, 1], [-1]]), ValueError, r"domain \(Omega\) must be a box"),
    (
        "train-box-inside-omega",
        lambda c: system(train_domain=[[-0.5, 0.5], [-0.5, 0.5]]),
        UserWarning,
        r"training box .* does not contain Omega",
    ),
    (
        "omega-without-origin",
        lambda c: system(domain=[[0.5, 1.0], [-1, 1]]),
        UserWarning,
        r"does not contain the origin",
    ),
    (
        "f-nan-on-part-of-box",
        lambda c: system(f=f_nan_far, train_domain=[[-1.5, 1.5]] * 2),
        ValueError,
        r"f\(x\) is NaN or infinite at \d+ of \d+ states .* e\.g\. x = ",
    ),
    (
        "f-nan-in-training-pool",
        lambda c: StatePool(system(), torch.tensor([[0.1, 0.2], [np.nan, 0.0]], dtype=torch.float64)),
        ValueError,
        r"f\(x\) is NaN or infinite at 1 of 2 training states",
    ),
    (
        "f0-nan",
        lambda c: system(f=lambda x: f_pend(x) + torch.where((x == 0).all(-1, keepdim=True), float("nan"), 0.0)),
        ValueError,
        r"f\(0\) must be 0 .* got \[\[nan",
    ),
    ("name-not-string", lambda c: system(name=3), TypeError, r"name must be a non-empty string; got 3"),
    ("R-not-numbers", lambda c: system(R=(("a",),)), ValueError, r"R must be a square \(m, m\) matrix of numbers"),
    ("builtin-R-abc", lambda c: ph.systems.pendulum(R="abc"), ValueError, r"pendulum: parameter R must be a positive"),
    # --- solver construction and configs
    ("seed-1.7", lambda c: solver(seed=1.7), ValueError, r"seed must be an integer .* got 1\.7"),
    ("seed-2**70", lambda c: solver(seed=2**70), ValueError, r"seed must be an integer .* got 1180591620717411303424"),
    ("seed-bool", lambda c: solver(seed=True), ValueError, r"seed must be an integer"),
    ("device-tpu", lambda c: ph.FiniteHorizonSolver(system(), device="tpu"), ValueError, r"device must .* 'tpu'"),
    ("width-2.5", lambda c: ph.TrainConfig(width=2.5), ValueError, r"width=2\.5 \(expected an integer >= 1\)"),
    ("batch-size-True", lambda c: ph.TrainConfig(batch_size=True), ValueError, r"batch_size=True \(expected an int"),
    ("lm-damping-inf", lambda c: ph.LevenbergMarquardt(damping=math.inf), ValueError, r"damping=inf \(expected a fin"),
    ("lr-nan", lambda c: ph.Adam(lr=math.nan), ValueError, r"lr=nan"),
    ("phase-not-a-phase", lambda c: ph.TrainConfig(phases=("adam",)), ValueError, r"phases=\('adam',\)"),
    ("eval-points-1", lambda c: ph.TrainConfig(eval_points_per_dim=1), ValueError, r"eval_points_per_dim=1"),
    ("ansatz-string", lambda c: ph.TrainConfig(ansatz="yes"), ValueError, r"ansatz='yes' \(expected True or False\)"),
    (
        "paper-on-user-system",
        lambda c: solver(config="paper"),
        ValueError,
        r"config='paper' .* system 'mine' is not one of them: use config='default'",
    ),
    (
        "system-not-a-system",
        lambda c: ph.FiniteHorizonSolver("pendulum"),
        TypeError,
        r"system must be a ControlAffineSystem",
    ),
    # --- solver calls: all refused before any training
    (
        "horizon-string",
        lambda c: no_training(solver()).solve("2"),
        ValueError,
        r"horizon must be a positive finite number; got '2' of type str",
    ),
    ("horizon-nan", lambda c: no_training(solver()).solve(math.nan), ValueError, r"horizon must be a positive finite"),
    (
        "terminal-wrong-shape",
        lambda c: no_training(solver()).solve(0.5, terminal_cost=np.eye(3)),
        ValueError,
        r"terminal_cost .* must be \(2, 2\); got shape \(3, 3\)",
    ),
    (
        "extend-to-inf",
        lambda c: no_training(solver()).extend(c.base, to=math.inf),
        ValueError,
        r"to \(the extension target\) must be a finite number that must exceed the current horizon T=0\.5; got inf",
    ),
    (
        "extend-to-string",
        lambda c: no_training(solver()).extend(c.base, to="2"),
        ValueError,
        r"to \(the extension target\) .* got '2' of type str",
    ),
    (
        "extend-step-1e-6",
        lambda c: no_training(solver()).extend(c.base, to=4.0, step=1e-6),
        ValueError,
        r"step=1e-06 .* would train 3500000 stages, more than MAX_STAGES_PER_CALL",
    ),
    (
        "extend-step-negative",
        lambda c: no_training(solver()).extend(c.base, to=2.0, step=-1),
        ValueError,
        r"step must be a positive finite number; got -1",
    ),
    (
        "solve-until-max-below-step",
        lambda c: no_training(solver()).solve_until(1e-3, step=2.0, max_horizon=1.0),
        ValueError,
        r"first horizon \(step=2\) exceeds max_horizon=1",
    ),
    (
        "solve-until-max-nan",
        lambda c: no_training(solver()).solve_until(1e-3, step=1.0, max_horizon=math.nan),
        ValueError,
        r"max_horizon must be a positive number \(inf allowed\); got nan",
    ),
    (
        "solve-until-step-0",
        lambda c: no_training(solver()).solve_until(1e-3, step=0),
        ValueError,
        r"step must be a positive finite number; got 0",
    ),
    (
        "solve-until-tol-negative",
        lambda c: no_training(solver()).solve_until(-1.0, step=1.0),
        ValueError,
        r"tol must be a positive finite number; got -1",
    ),
    ("evaluate-points-per-dim-1", lambda c: c.base.evaluate(1), ValueError, r"points_per_dim must be an integer >= 2"),
    # --- divergence: an error naming the stage, optimiser and iteration; a useless stage: a warning
    (
        "overflow-R-1e-300-LM",
        lambda c: one_stage(solver(scaled(R=1e-300))),
        DivergenceError,
        r"stage mine T=0->0\.5: Levenberg-Marquardt diverged at iteration 1: the loss is inf",
    ),
    (
        "overflow-Q-1e200-LM",
        lambda c: one_stage(solver(scaled(q_scale=1e200))),
        DivergenceError,
        r"Levenberg-Marquardt diverged at iteration 1",
    ),
    (
        "overflow-R-1e-300-Adam",
        lambda c: one_stage(solver(scaled(R=1e-300), ADAM)),
        DivergenceError,
        r"stage mine T=0->0\.5: Adam diverged at iteration 1",
    ),
    (
        "overflow-R-1e-300-LBFGS",
        lambda c: one_stage(solver(scaled(R=1e-300), LBFGS)),
        DivergenceError,
        r"L-BFGS diverged at iteration 1",
    ),
    (
        "saturated-network",
        lambda c: one_stage(
            solver(scaled(q_scale=1e6, R=1e-8), LM.replace(width=24, depth=3).with_phase("lm", steps=4))
        ),
        RuntimeWarning,
        r"stage 1 \(mine T=0->0\.5\): E = .* is no better than E of V = 0",
    ),
    (
        "solve-until-not-converged",
        lambda c: solver().solve_until(1e-30, step=0.5, max_horizon=0.5),
        RuntimeWarning,
        r"stopped at max_horizon=0\.5 without meeting tol=1e-30: E = .* \(converged=False\)",
    ),
    ("later-stage-fails-keeps-earlier", chain_with_broken_third_stage, ValueError, r"f\(x\) is NaN or infinite"),
    # --- checkpoints
    (
        "load-other-user-system-R",
        lambda c: ph.load(saved_checkpoint(c), system=scaled(R=2.0)),
        CheckpointError,
        r"fingerprints differ in \['R', 'Q'\]|fingerprints differ in \['R'\]",
    ),
    (
        "load-other-user-system-f",
        lambda c: ph.load(saved_checkpoint(c), system=system(f=lambda x: 2 * f_pend(x))),
        CheckpointError,
        r"(?s)differ in \['f'\].*stored in the checkpoint: \{name='mine'.*system given/rebuilt: +\{name",
    ),
    (
        "load-other-user-system-name",
        lambda c: ph.load(saved_checkpoint(c), system=system(name="other")),
        CheckpointError,
        r"differ in \['name'\]",
    ),
    (
        "load-other-domain",
        lambda c: ph.load(saved_checkpoint(c), system=system(domain=[[-2, 2], [-2, 2]])),
        CheckpointError,
        r"differ in \['domain', 'train_domain', 'probes'",
    ),
    (
        "checkpoint-missing-key",
        lambda c: ph.load(edited_checkpoint(c, lambda r: r.pop("stages")), system=system()),
        CheckpointError,
        r"incomplete: 'checkpoint' lacks the key\(s\) \['stages'\]",
    ),
    (
        "checkpoint-stage-missing-key",
        lambda c: ph.load(edited_checkpoint(c, lambda r: r["stages"][0].pop("length")), system=system()),
        CheckpointError,
        r"'stages\[0\]' lacks the key\(s\) \['length'\]",
    ),
    (
        "checkpoint-nan-weights",
        lambda c: ph.load(
            edited_checkpoint(c, lambda r: r["stages"][0]["state"]["layers.0.weight"].fill_(float("nan"))),
            system=system(),
        ),
        CheckpointError,
        r"stage 1: the stored weight 'layers\.0\.weight' holds NaN",
    ),
    (
        "checkpoint-inconsistent-starts",
        lambda c: ph.load(edited_checkpoint(c, lambda r: r["stages"][0].update(start=0.25)), system=system()),
        CheckpointError,
        r"stage starts are inconsistent: stage 1 starts at T=0\.25, but .* end at T=0",
    ),
    ("checkpoint-is-a-folder", lambda c: ph.load(c.tmp), CheckpointError, r"is a folder, not a checkpoint"),
    ("save-onto-a-folder", lambda c: ph.save(c.base, c.tmp), IsADirectoryError, r"it is an existing folder"),
    # --- command line: refused before training, nothing saved
    (
        "cli-out-under-a-file",
        lambda c: cli_fails(["train", "pendulum", "--out", read_only_folder(c), *CLI_TINY])(c),
        CliError,
        r"rc=2: error: --out .*: cannot create a file there: .* is not a folder",
    ),
    (
        "cli-out-existing-folder",
        cli_fails(["train", "pendulum", "--out", "{tmp}", *CLI_TINY]),
        CliError,
        r"rc=2: error: --out .* is an existing folder",
    ),
    (
        "cli-param-R-abc",
        cli_fails(["train", "pendulum", "--param", "R=abc", "--out", "{tmp}/x.pt", *CLI_TINY], saved="x.pt"),
        CliError,
        r"--param R=abc: pendulum: parameter R must be a positive finite number; got 'abc'",
    ),
    (
        "cli-param-unknown",
        cli_fails(["train", "pendulum", "--param", "mass=2", "--out", "{tmp}/x.pt", *CLI_TINY]),
        CliError,
        r"--param mass=2: system pendulum has no parameter 'mass' \(its parameters: R\)",
    ),
    (
        "cli-set-width-2.5",
        cli_fails(["train", "pendulum", "--out", "{tmp}/x.pt", *CLI_TINY, "--set", "width=2.5"]),
        CliError,
        r"width=2\.5 \(expected an integer >= 1\)",
    ),
    (
        "cli-extend-to-below-horizon",
        cli_fails(
            ["train", "pendulum", "--horizon", "2", "--extend-to", "1", "--out", "{tmp}/x.pt", *CLI_TINY], saved="x.pt"
        ),
        CliError,
        r"--extend-to 1 must exceed --horizon 2",
    ),
    (
        "cli-lone-step",
        cli_fails(["train", "pendulum", "--step", "0.5", "--out", "{tmp}/x.pt", *CLI_TINY], saved="x.pt"),
        CliError,
        r"--step 0\.5 is the increment of an extension: give --extend-to as well",
    ),
    (
        "cli-steady-state-with-horizon",
        cli_fails(
            ["train", "pendulum", "--steady-state", "--horizon", "2", "--out", "{tmp}/x.pt", *CLI_TINY], saved="x.pt"
        ),
        CliError,
        r"--steady-state .* has no horizon: drop --horizon",
    ),
    (
        "cli-negative-step",
        cli_fails(
            ["train", "pendulum", "--extend-to", "3", "--step", "-1", "--out", "{tmp}/x.pt", *CLI_TINY], saved="x.pt"
        ),
        CliError,
        r"--step must be a positive finite number; got -1",
    ),
    (
        "cli-tiny-step",
        cli_fails(
            ["train", "pendulum", "--extend-to", "3", "--step", "1e-6", "--out", "{tmp}/x.pt", *CLI_TINY], saved="x.pt"
        ),
        CliError,
        r"would train more than 10000 stages",
    ),
    (
        "cli-diverges-saves-nothing",
        cli_fails(["train", "pendulum", "--param", "R=1e-300", "--out", "{tmp}/x.pt", *CLI_TINY], saved="x.pt"),
        CliError,
        r"rc=2: error: stage pendulum T=0->1: Adam diverged at iteration 1",
    ),
    (
        "cli-points-per-dim-0",
        cli_fails(["evaluate", "unused.pt", "--points-per-dim", "0"]),
        CliError,
        r"(?s)rc=2: .*--points-per-dim: expected an integer >= 2",
    ),
    (
        "cli-points-per-dim-1",
        cli_fails(["evaluate", "unused.pt", "--points-per-dim", "1"]),
        CliError,
        r"--points-per-dim: expected an integer >= 2 \(points per axis of the grid\); got 1",
    ),
    (
        "cli-points-per-dim-minus-3",
        cli_fails(["evaluate", "unused.pt", "--points-per-dim", "-3"]),
        CliError,
        r"--points-per-dim: expected an integer >= 2",
    ),
    (
        "cli-reproduce-seeds-0",
        cli_fails(["reproduce", "--seeds", "0", "--out", "{tmp}/r"]),
        CliError,
        r"--seeds must be at least 1",
    ),
    (
        "reproduce-run-seeds-0",
        lambda c: ph.paper.reproduce.run(out=c.tmp / "r", seeds=0),
        ValueError,
        r"0 <= first_seed < seeds .*got first_seed=0, seeds=0",
    ),
]

# Accepted inputs (they must train or load without error).
OK = [
    ("horizon-np-float32", lambda c: one_stage(horizon=np.float32(0.5))),
    ("horizon-tensor", lambda c: one_stage(horizon=torch.tensor(0.5))),
    ("seed-np-int64", lambda c: solver(seed=np.int64(3))),
    ("solve-until-max-horizon-inf", lambda c: solver().solve_until(1e6, step=0.5, max_horizon=math.inf)),
    (
        "load-stored-artifact-without-fingerprint",
        lambda c: ph.load(sorted(c.root.glob("artifacts/checkpoints/pendulum_extension/seed0.pt"))[0]),
    ),
    ("cli-ctrl-c-inside-a-save", interrupted_inside_save),
]


@pytest.fixture(scope="module")
def base():
    return one_stage()


@pytest.fixture
def ctx(tmp_path, monkeypatch, base):
    from pathlib import Path

    return SimpleNamespace(tmp=tmp_path, monkeypatch=monkeypatch, base=base, root=Path(__file__).resolve().parents[1])


@pytest.mark.parametrize("action, expected, words", [c[1:] for c in CASES], ids=[c[0] for c in CASES])
def test_case(action, expected, words, ctx):
    if issubclass(expected, Warning):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # only the expected warning counts below
            with pytest.warns(expected, match=words):
                action(ctx)
    else:
        with pytest.raises(expected, match=words):
            action(ctx)


@pytest.mark.parametrize("action", [c[1] for c in OK], ids=[c[0] for c in OK])
def test_accepted(action, ctx):
    action(ctx)


def test_the_table_has_every_case_once():
    ids = [c[0] for c in CASES] + [c[0] for c in OK]
    assert len(ids) == len(set(ids))


# ------------------------------------------------------------------------------ behaviours
def test_solve_until_reports_convergence_in_summary():
    with pytest.warns(RuntimeWarning, match="without meeting tol"):
        sol = solver().solve_until(1e-30, step=0.5, max_horizon=1.0)
    assert sol.converged is False and [r["converged"] for r in sol.summary()] == [False, False]
    met = solver().solve_until(1e6, step=0.5)
    assert met.converged is True and met.summary()[-1]["converged"] is True


def test_converged_exists_on_every_result(ctx):
    assert ctx.base.converged is None and "converged" not in ctx.base.summary()[0]
    steady = ph.SteadyStateSolver(system(), LM, device="cpu", progress=False)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        assert steady.solve().converged is None


def test_chains_of_any_length_evaluate_without_recursion():
    """1000 stages (the recursion limit was hit at about 122): value and gradient, each stage once."""
    sys_ = system()
    torch.manual_seed(0)
    models = [FiniteHorizonValue(2, 0.01, sys_.train_domain, width=2, depth=1).double().requires_grad_(False)]
    for _ in range(999):
        models.append(
            FiniteHorizonValue(2, 0.01, sys_.train_domain, ValueTerminalCost(models[-1]), width=2, depth=1)
            .double()
            .requires_grad_(False)
        )
    calls = []
    for m in models:
        m.net.register_forward_hook(lambda *a: calls.append(1))
    x = torch.rand(3, 2, dtype=torch.float64).requires_grad_(True)
    v = models[-1](x, 0.0)
    (g,) = torch.autograd.grad(v.sum(), x)
    assert torch.isfinite(v).all() and torch.isfinite(g).all()
    assert len(calls) == 2 * len(models)  # N(x, t) and N(0, t) of the ansatz: one pass per stage each
    sol = FiniteHorizonSolution(
        sys_, LM, [Stage(m, 0.01 * k, TrainHistory(), k) for k, m in enumerate(models)], {"kind": "zero"}
    )
    assert sol.horizon == pytest.approx(10.0) and np.isfinite(sol.value(np.zeros((1, 2)) + 0.1, t=3.0)).all()


def test_long_chain_saves_and_loads(tmp_path):
    sys_ = system()
    torch.manual_seed(0)
    stages, prev = [], None
    for k in range(300):
        m = (
            FiniteHorizonValue(
                2, 0.1, sys_.train_domain, None if prev is None else ValueTerminalCost(prev), width=2, depth=1
            )
            .double()
            .requires_grad_(False)
        )
        stages.append(Stage(m, 0.1 * k, TrainHistory(), k))
        prev = m
    sol = FiniteHorizonSolution(sys_, LM.replace(width=2, depth=1), stages, {"kind": "zero"})
    loaded = ph.load(ph.save(sol, tmp_path / "long.pt"), system=sys_)
    x = np.array([[0.3, -0.2]])
    np.testing.assert_array_equal(loaded.value(x), sol.value(x))


def test_extension_moves_a_chain_loaded_elsewhere_to_the_solver_device_and_dtype(ctx):
    float32 = solver(config=LM.replace(dtype="float32"))
    longer = float32.extend(ctx.base, to=1.0)
    assert {s.model.net.layers[0].weight.dtype for s in longer.stages} == {torch.float32}


def test_E_in_high_dimension_is_monte_carlo_with_its_standard_error():
    n = 8
    sys_ = ph.ControlAffineSystem(
        "n8", lambda x: -x, lambda x: torch.ones(x.shape[0], n, 1, dtype=x.dtype), q_sq, [[1.0]], domain=[[-1, 1]] * n
    )
    assert not metrics.uses_grid(sys_)
    out = metrics.infinite_horizon_residual(sys_, lambda x: 0.5 * q_sq(x))
    assert out["E_samples"] == metrics.MC_SAMPLES and 0 < out["E_stderr"] < 0.05 * out["E"]
    assert out == metrics.infinite_horizon_residual(sys_, lambda x: 0.5 * q_sq(x))  # seeded: the same every time
    with pytest.raises(ValueError, match="exceeds GRID_MAX_POINTS"):
        metrics.evaluation_grid(sys_)
    states = metrics.evaluation_states(sys_)  # E's own states: their mean square residual is E's flow part
    assert states.shape == (metrics.MC_SAMPLES, n) and bool((states.abs() <= 1).all())
    on_states = metrics.infinite_horizon_residual(sys_, lambda x: 0.5 * q_sq(x), points=states)
    assert on_states == pytest.approx({k: out[k] for k in on_states}, rel=1e-12)
    field = SteadyStateHJB(sys_, lambda x: 0.5 * q_sq(x)).field  # where E's mean square comes from
    spread = metrics.residual_spread(sys_, field)
    assert np.mean(spread["scaled"] ** 2) == pytest.approx(out["E_flow"] / out["E_zero"], rel=1e-12)
    assert spread["max"] == spread["scaled"].max() > spread["q99"] > 0
    assert spread["q_rms"] ** 2 == pytest.approx(out["E_zero"], rel=1e-12)  # V = 0 leaves Q as its residual
    assert 1e-3 < spread["top_share"] < 1  # a thousandth of the states: more than their count's share of E
    with pytest.raises(ValueError, match="top must be in"):
        metrics.residual_spread(sys_, field, top=1.0)


@pytest.mark.parametrize("n, per_dim", [(1, None), (2, None), (2, 41), (3, None), (3, 21), (4, None)])
def test_small_cases_keep_their_exact_grid(n, per_dim):
    sys_ = ph.ControlAffineSystem(
        f"n{n}",
        lambda x: -x,
        lambda x: torch.ones(x.shape[0], n, 1, dtype=x.dtype),
        q_sq,
        [[1.0]],
        domain=[[-1, 1]] * n,
    )
    assert metrics.uses_grid(sys_, per_dim)
    out = metrics.infinite_horizon_residual(sys_, lambda x: 0.5 * q_sq(x), points_per_dim=per_dim)
    assert "E_samples" not in out
    grid = metrics.evaluation_grid(sys_, per_dim)
    assert out == metrics.infinite_horizon_residual(sys_, lambda x: 0.5 * q_sq(x), points=grid)
    assert torch.equal(metrics.evaluation_states(sys_, per_dim), grid)


def test_checkpoint_fingerprint_round_trip_and_tolerance(ctx):
    path = saved_checkpoint(ctx)
    raw = torch.load(path, weights_only=True)
    fp = raw["fingerprint"]
    assert {"name", "n", "m", "R", "domain", "train_domain", "probes", "f", "g", "Q"} <= set(fp)
    ph.load(path, system=system())  # the same system, rebuilt: accepted
    raw["fingerprint"]["f"] = (np.asarray(fp["f"]) * (1 + 1e-12)).tolist()  # another CPU's rounding: accepted
    torch.save(raw, path)
    ph.load(path, system=system())


@pytest.mark.parametrize("mask", [0o022, 0o077, 0o002])
def test_checkpoints_respect_the_umask(ctx, mask):
    old = os.umask(mask)
    try:
        path = saved_checkpoint(ctx, name=f"m{mask:o}.pt")
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == 0o666 & ~mask


def test_stale_temporary_files_are_removed(ctx):
    stale = ctx.tmp / "a.pt.k1ll3d.tmp"
    stale.write_bytes(b"half a checkpoint")
    other = ctx.tmp / "b.pt.x.tmp"
    other.write_bytes(b"another file's")
    saved_checkpoint(ctx)
    assert not stale.exists() and other.exists()


@pytest.fixture(scope="module")
def artifact_states():
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "artifacts" / "checkpoints" / "quartic_extension" / "seed0.pt"
    raw = torch.load(path, weights_only=True)
    return path, [st["state"] for st in raw["stages"]]


def test_perturbation_switch(artifact_states, monkeypatch):
    path, states = artifact_states
    monkeypatch.delenv(PERTURB_ENV, raising=False)
    exact = ph.load(path)
    for stage, state in zip(exact.stages, states):
        for key, value in state.items():
            assert torch.equal(stage.model.net.state_dict()[key], value)
    monkeypatch.setenv(PERTURB_ENV, "1e-13")
    a, b = ph.load(path), ph.load(path)
    changed = 0
    for sa, sb, state in zip(a.stages, b.stages, states):
        for key, value in state.items():
            w = sa.model.net.state_dict()[key]
            assert torch.equal(w, sb.model.net.state_dict()[key])  # the same draw on every load
            rel = ((w - value).abs() / value.abs().clamp_min(1e-300)).max().item()
            assert rel <= 1e-13 * 8  # |z| < 8 for every draw of this size
            changed += int(not torch.equal(w, value))
    singles = sum(s[k].numel() == 1 for s in states for k in s)  # a one-number tensor may round back to itself
    assert changed >= sum(len(s) for s in states) - singles
    monkeypatch.setenv(PERTURB_ENV, "abc")
    with pytest.raises(ValueError, match=f"{PERTURB_ENV} must be a relative size"):
        ph.load(path)


def test_frictions():
    assert ph.reference.__name__ == "pinnhjb.reference"  # after a bare import pinnhjb
    A, B, Q = ph.systems.pendulum().linearize()
    M, l, grav, fd = 1 / 3, 2 / 3, 9.8, 0.2
    J = 4 / 3 * M * l**2
    np.testing.assert_allclose(A, [[0, 1], [-M * grav * l / J, -fd / J]], rtol=1e-12)
    np.testing.assert_allclose(B, [[0], [1 / J]], rtol=1e-12)
    np.testing.assert_allclose(Q, np.eye(2), rtol=1e-12)
    lq = ph.systems.linear_quadratic(
        np.zeros((2, 2)) - np.eye(2), [[0.0], [1.0]], np.eye(2), [[1.0]], domain=[[-1, 1], [-2, 2]]
    )
    np.testing.assert_allclose(lq.train_domain, [[-1.25, 1.25], [-2.5, 2.5]])  # like the built-ins: beyond Omega
