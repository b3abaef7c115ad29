"""pinnhjb.plots: what the chapters draw (plane slices of a 3-D solution, exact LQ fields, time-to-accuracy
lines, grouped bars)."""

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

import pinnhjb as ph  # noqa: E402
from pinnhjb import plots  # noqa: E402


def test_slice_mesh_holds_the_other_coordinates():
    system = ph.systems.third_order(R=1.0)
    x1, x2, pts = plots.slice_mesh(system, axes=(0, 2), fixed=0.05, points_per_dim=7)
    assert x1.shape == (7, 7) and pts.shape == (49, 3)
    assert np.all(pts[:, 1] == 0.05)
    assert np.allclose(pts[:, 0], x1.ravel()) and np.allclose(pts[:, 2], x2.ravel())
    assert pts[:, 0].min() == pytest.approx(-0.2) and pts[:, 2].max() == pytest.approx(0.2)
    with pytest.raises(ValueError, match="two different coordinates"):
        plots.slice_mesh(system, axes=(1, 1))


def test_value_policy_residual_slice_draws_three_panels():
    sol = ph.FiniteHorizonSolver(ph.systems.third_order(R=1.0), config="quick", seed=0, progress=False).solve(0.5)
    fig = plots.value_policy_residual(sol, fixed=0.0, points_per_dim=5)
    assert len(fig.axes) == 3 and fig.axes[0].get_xlabel() == "$x_1$" and fig.axes[0].get_ylabel() == "$x_2$"
    plt.close(fig)


def test_quadratic_fields_are_exact():
    A = np.array([[0.0, 1.0], [2.0, -1.0]])
    B = np.array([[0.0], [1.0]])
    Q, R = np.eye(2), np.array([[0.3]])
    x = np.random.default_rng(0).normal(size=(6, 2))
    star = ph.metrics.quadratic_fields(A, B, Q, R, ph.lq.care(A, B, Q, R), x)
    assert np.abs(star["residual"]).max() < 1e-9  # V* solves the steady-state HJB
    ode = ph.lq.riccati_ode(A, B, Q, R, 1.0)
    fields = ph.metrics.quadratic_fields(A, B, Q, R, ode.at(0.0), x)
    assert np.allclose(fields["policy"], ode.policy(x, 0.0))
    assert np.allclose(fields["value"], ode.value(x, 0.0))
    dP = ode.derivative(0.0)  # E_e(x; V_T(., 0)) = -dV_T/dt at t = 0
    assert np.allclose(fields["residual"], -np.einsum("ni,ij,nj->n", x, dP, x))


def test_carried_error_draws_each_series_the_diagonal_and_the_goal():
    rng = np.random.default_rng(0)
    before = rng.normal(size=50) * 1e-4
    fig = plots.carried_error(before, {"learned": before * 0.9, "exact": before * 0.3}, goal=1e-4)
    (ax,) = fig.axes
    assert len(ax.collections) == 2 and [line.get_label() for line in ax.lines][:1] == ["kept where it was"]
    assert sum(1 for line in ax.lines if line.get_linestyle() == ":") == 2  # plus and minus the goal
    plt.close(fig)
    with pytest.raises(ValueError, match="shape of before"):
        plots.carried_error(before, {"bad": before[:3]})


def test_averaged_error_draws_the_members_the_mean_of_the_first_k_and_the_goal():
    rng = np.random.default_rng(0)
    errors = rng.normal(size=(4, 200)) * 1e-4
    fig = plots.averaged_error(errors, goal=1e-4, labels=["a", "b", "c", "d"])
    left, right = fig.axes
    assert left.get_xlabel() == "a's error" and [c.get_label() for c in left.collections] == ["b", "c", "d"]
    each, mean, independent, goal = right.lines
    assert list(each.get_ydata()) == list(np.abs(errors).max(axis=1))
    assert mean.get_ydata()[-1] == np.abs(errors.mean(axis=0)).max() and goal.get_ydata()[0] == 1e-4
    plt.close(fig)
    with pytest.raises(ValueError, match="K >= 2 members"):
        plots.averaged_error(errors[:1])
    with pytest.raises(ValueError, match="name the 4 members"):
        plots.averaged_error(errors, labels=["a"])


def test_beyond_samples_draws_each_chain_the_diagonal_and_the_goal_on_both_axes():
    fig = plots.beyond_samples([1e-4, 2e-4, 3e-3], [1.5e-4, 5e-4, 3e-3], [6, 8, 12], goal=1e-4, highlight=[0])
    ax = fig.axes[0]
    assert ax.get_xscale() == ax.get_yscale() == "log"
    labels = [c.get_label() for c in ax.collections]
    assert labels == ["$n=6$", "$n=8$", "$n=12$", "highlighted"]
    assert [list(c.get_offsets()[:, 1]) for c in ax.collections[:3]] == [[1.5e-4], [5e-4], [3e-3]]
    diagonal, across, up = ax.lines  # y = x, and the goal on the x and on the y axis
    assert list(diagonal.get_xdata()) == list(diagonal.get_ydata())
    assert across.get_xdata()[0] == 1e-4 and up.get_ydata()[0] == 1e-4
    plt.close(fig)
    with pytest.raises(ValueError, match=r"\(K,\) alike"):
        plots.beyond_samples([1e-4], [1e-4, 2e-4], [6])
    with pytest.raises(ValueError, match="positive"):
        plots.beyond_samples([0.0], [1e-4], [6])


def test_time_to_accuracy_draws_one_line_per_run_and_the_targets():
    fig = plots.time_to_accuracy(
        {"a": ([1.0, 5.0, 30.0], [1.0, 1e-2, 1e-5]), "b": ([8.0, 300.0], [0.5, 3e-2])}, targets={"paper": 1.5e-4}
    )
    ax = fig.axes[0]
    assert ax.get_yscale() == "log" and [line.get_label() for line in ax.lines] == ["a", "b", "paper"]
    assert list(ax.lines[0].get_ydata()) == [1.0, 1e-2, 1e-5] and ax.lines[2].get_ydata()[0] == 1.5e-4
    plt.close(fig)
    with pytest.raises(ValueError, match="one length"):
        plots.time_to_accuracy({"bad": ([1.0, 2.0], [1.0])})


def test_time_to_accuracy_draws_each_runs_time_goal_in_its_colour():
    fig = plots.time_to_accuracy(
        {"gpu": ([10.0, 50.0], [2e-2, 1e-3]), "cpu": ([500.0, 2000.0], [2e-2, 1e-3])},
        ylabel="value error",
        deadlines={"gpu": 180.0, "cpu": 1800.0},
    )
    ax = fig.axes[0]
    goal = {line.get_label(): line for line in ax.lines[2:]}
    assert set(goal) == {"gpu: time goal", "cpu: time goal"} and ax.get_ylabel() == "value error"
    assert goal["gpu: time goal"].get_xdata()[0] == 180.0
    assert goal["cpu: time goal"].get_color() == ax.lines[1].get_color() != ax.lines[0].get_color()
    plt.close(fig)
    with pytest.raises(ValueError, match="not among the traces"):
        plots.time_to_accuracy({"gpu": ([1.0], [1.0])}, deadlines={"tpu": 5.0})


def test_grouped_bars_draw_each_value_and_mark_the_missing():
    fig = plots.grouped_bars({"ours": {"CPU": 10.0, "GPU": 5.0}, "theirs": {"CPU": 25.0, "GPU": None}}, "s")
    ax = fig.axes[0]
    heights = sorted(round(p.get_height(), 6) for p in ax.patches)
    assert heights == [5.0, 10.0, 25.0]  # three bars: the missing value draws none
    assert [t.get_text() for t in ax.texts] == ["none"] and ax.get_yscale() == "log"
    assert [t.get_text() for t in ax.get_xticklabels()] == ["ours", "theirs"]
    plt.close(fig)
    with pytest.raises(ValueError, match="empty"):
        plots.grouped_bars({}, "s")


def test_loop_residual_shades_where_the_loops_leave_the_box():
    A, B = np.array([[1.0, 1.0], [0.0, 2.0]]), np.array([[0.0], [1.0]])
    system = ph.systems.linear_quadratic(A, B, np.eye(2), np.eye(1), domain=[[-1, 1], [-1, 1]])
    P = ph.lq.care(A, B, np.eye(2), np.eye(1)) + 0.2 * np.eye(2)
    loops = ph.metrics.residual_along_loop(
        system, lambda x: ((x @ ph.pinn.torch.as_tensor(P)) * x).sum(-1), np.array([[1.0, 1.0], [0.1, 0.0]]), 4.0
    )
    fig = plots.loop_residual(loops, [0, 1], t_max=3.0)
    top, bottom = fig.axes
    assert len(top.lines) >= 2 and len(top.collections) == 2  # a curve and a shading per loop
    assert bottom.get_xlim() == (0.0, 3.0) and bottom.get_xlabel() == "$t$ (s)"
    plt.close(fig)


def test_goal_line_draws_the_bound_and_names_it_at_the_left_edge():
    fig, ax = plt.subplots()
    ax.semilogy([0, 10], [1e-2, 1e-5])
    ax.set_xlim(2, 8)
    line = plots.goal_line(ax, 1e-4, label="value goal", color="C1")
    assert list(line.get_ydata()) == [1e-4, 1e-4]
    (note,) = ax.texts
    assert note.get_text() == "value goal" and note.xy == (0, 1e-4)  # axes fraction 0: wherever xlim is
    assert note.get_color() == line.get_color() == "C1"
    plots.goal_line(ax, 1e-3, label="")  # a line with no name
    assert len(ax.lines) == 3 and len(ax.texts) == 1
    with pytest.raises(ValueError, match="positive on a log axis"):
        plots.goal_line(ax, 0.0)
    plt.close(fig)


def test_the_first_figure_shows_what_the_landing_page_says():
    """book/intro.md's figure (drawn at build time by matplotlib's plot directive) from the stored quartic runs:
    along its line the steady-state PINN takes negative values, the finite-horizon one lies on V* to within 1%
    of its largest value, and the legend gives each one's E / E(V = 0) and the horizon."""
    from pinnhjb import paper

    system = ph.systems.quartic()
    steady, finite = paper.load_case("quartic_steady", seed=0), paper.load_case("quartic_extension", seed=0)
    fig = plots.steady_against_finite(system, steady, finite)
    ax = fig.axes[0]
    lines = {line.get_label(): line.get_ydata() for line in ax.get_lines() if not line.get_label().startswith("_")}
    red, blue = (next(v for k, v in lines.items() if k.startswith(p)) for p in ("steady", "finite"))
    (star,) = (line.get_ydata() for line in ax.get_lines() if line.get_linestyle() == "--")  # named on the plot
    assert any(t.get_text().startswith("$V^\\star$") for t in ax.texts)
    assert red.min() < 0 < star.min() + 1e-12  # no value function: V* >= 0, the steady-state PINN is not
    assert np.abs(blue - star).max() < 0.01 * star.max()
    labels = list(lines)
    assert f"{steady.metrics['E'] / steady.metrics['E_zero']:.0e}" in labels[0]
    assert f"T={finite.horizon:g}" in labels[1]
    plt.close(fig)
    with pytest.raises(ValueError, match="no known V"):
        plots.steady_against_finite(ph.systems.rigid_body(), steady, finite)
