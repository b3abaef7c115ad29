"""Figures in one style: the paper's surfaces (Figures 1-7), loss curves, time-to-accuracy lines and bars.

Every function takes plain data or a solution object and returns a matplotlib ``Figure``; nothing is shown or
saved here. Figures are drawn for the book's content column: at most :data:`WIDTH` inches wide at 100 dpi, at
most two 3-D panels a row, fonts of 10 pt and more. Call :func:`use_book_style` once per notebook.
"""

from __future__ import annotations

import math

import matplotlib as mpl
import matplotlib.pyplot as plt
import numpy as np

__all__ = [
    "WIDTH",
    "use_book_style",
    "panels",
    "grid_2d",
    "slice_mesh",
    "surface",
    "surfaces",
    "value_policy_residual",
    "value_and_error",
    "policy_and_error",
    "loss_curve",
    "time_to_accuracy",
    "grouped_bars",
    "value_slices",
    "manoeuvres",
    "loop_residual",
    "against_dimension",
    "carried_error",
    "averaged_error",
    "beyond_samples",
    "goal_line",
    "steady_against_finite",
    "VALUE_ERROR",
    "AFTER_STAGE",
]

#: The chapters' value error, as an axis label.
VALUE_ERROR = r"$\max|\hat V-V^\star|/\max V^\star$"
#: The x-axis of a chain's stage-by-stage figures.
AFTER_STAGE = "horizon $T$ after the stage (s)"
CMAP = "viridis"
DIVERGING = "RdBu_r"
#: Inches: the widest figure the content column shows at full size (700 CSS px; one inch = 100 CSS px).
WIDTH = 7.0
STYLE = {
    "figure.dpi": 100,
    "font.size": 11,
    "axes.titlesize": 11,
    "axes.labelsize": 11,
    "xtick.labelsize": 10,
    "ytick.labelsize": 10,
    "legend.fontsize": 10,
    "figure.titlesize": 12,
    "savefig.bbox": "tight",
}


def use_book_style(retina: bool = True) -> None:
    """Set the book's fonts (``STYLE``) and, in a notebook, PNG output at twice the resolution.

    * ``retina``: emit 2x PNGs, sharp on high-density screens and displayed at their size in inches x 100 px.
    """
    mpl.rcParams.update(STYLE)
    if retina:
        try:
            from matplotlib_inline.backend_inline import set_matplotlib_formats
        except ImportError:  # not in IPython: nothing to configure
            return
        set_matplotlib_formats("retina")


def panels(k: int, ncols: int = 2, height: float = 3.0, **subplot_kw):
    """A figure of ``k`` 2-D panels, ``ncols`` a row, as wide as the column; returns (fig, list of k axes).

    * ``k``: the number of panels; unused cells of the last row are removed.
    * ``ncols``: panels per row (at most 3 keeps tick labels readable).
    * ``height``: inches per row.
    * ``subplot_kw``: passed to ``plt.subplots`` (e.g. ``sharey=True``).
    """
    ncols = max(1, min(ncols, k))
    nrows = math.ceil(k / ncols)
    width = WIDTH if ncols > 1 else min(WIDTH, 5.5)
    fig, axes = plt.subplots(nrows, ncols, figsize=(width, height * nrows), squeeze=False, **subplot_kw)
    axes = list(axes.ravel())
    for ax in axes[k:]:
        ax.remove()
    return fig, axes[:k]


def grid_2d(system, points_per_dim: int = 41):
    """A mesh over Omega of a 2-D system; returns (X1, X2, points (N, 2)).

    * ``system``: a system with n = 2.
    * ``points_per_dim``: points along each axis.
    """
    if system.n != 2:
        raise ValueError(f"surface plots need a 2-D state; system '{system.name}' has n={system.n}")
    return slice_mesh(system, (0, 1), None, points_per_dim)


def slice_mesh(system, axes: tuple[int, int] = (0, 1), fixed=None, points_per_dim: int = 31):
    """A mesh over a plane through Omega; returns (X1, X2, points (N, n)).

    * ``system``: the control-affine system.
    * ``axes``: the two coordinates that span Omega.
    * ``fixed``: where every other coordinate is held: a scalar for all of them or an (n,) array; None: 0.
    * ``points_per_dim``: points along each axis.
    """
    i, j = axes
    if not (0 <= i < system.n and 0 <= j < system.n and i != j):
        raise ValueError(f"axes must be two different coordinates of the {system.n}-D state; got {axes}")
    base = np.broadcast_to(np.asarray(0.0 if fixed is None else fixed, dtype=float), (system.n,))
    (a, b), (c, d) = system.domain[i], system.domain[j]
    x1, x2 = np.meshgrid(np.linspace(a, b, points_per_dim), np.linspace(c, d, points_per_dim), indexing="ij")
    pts = np.tile(base, (x1.size, 1))
    pts[:, i], pts[:, j] = x1.ravel(), x2.ravel()
    return x1, x2, pts


def surface(
    ax,
    x1,
    x2,
    z,
    title: str = "",
    diverging: bool = False,
    limit=None,
    axis_labels: tuple[str, str] = ("$x_1$", "$x_2$"),
    zlabel: str | None = None,
):
    """One 3-D surface of ``z`` on the mesh (x1, x2) in the 3-D axes ``ax``, in the book's style.

    * ``ax``: matplotlib 3-D axes.
    * ``x1``, ``x2``: the mesh, as from :func:`slice_mesh`.
    * ``z``: the field, any shape with ``x1.size`` entries.
    * ``diverging``: True for an error (white at zero, a symmetric colour scale).
    * ``limit``: None or (lo, hi) for the vertical axis and the colour scale (fixed across compared frames).
    * ``axis_labels``, ``zlabel``: the axes' labels; ``title``: the panel's title.
    """
    z = np.asarray(z, dtype=float).reshape(x1.shape)
    if diverging:  # errors: white at zero, symmetric colour scale
        m = max(abs(limit[0]), abs(limit[1])) if limit else (float(np.abs(z).max()) or 1.0)
        style = {"cmap": DIVERGING, "vmin": -m, "vmax": m}
    else:
        style = {"cmap": CMAP, **({"vmin": limit[0], "vmax": limit[1]} if limit else {})}
    ax.plot_surface(x1, x2, z, linewidth=0, antialiased=True, **style)
    if limit:
        ax.set_zlim(*limit)
    ax.set_xlabel(axis_labels[0], labelpad=-2)
    ax.set_ylabel(axis_labels[1], labelpad=-2)
    ax.tick_params(pad=0)
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        axis.set_major_locator(mpl.ticker.MaxNLocator(4, steps=[1, 2, 2.5, 5, 10]))
    if zlabel:
        ax.set_zlabel(zlabel)
    ax.set_title(title)
    ax.view_init(elev=28, azim=-130)
    return ax


def surfaces(
    x1,
    x2,
    fields: list[np.ndarray],
    titles: list[str],
    suptitle: str = "",
    zlabels=None,
    diverging: list[bool] | None = None,
    axis_labels: tuple[str, str] = ("$x_1$", "$x_2$"),
    limits: list | None = None,
    ncols: int = 2,
):
    """3-D surfaces of fields on the mesh (x1, x2), as in the paper's figures, ``ncols`` a row.

    * ``x1``, ``x2``: the mesh, as from :func:`slice_mesh`.
    * ``fields``, ``titles``: one array (any shape with x1.size entries) and one title per panel.
    * ``diverging``: per panel, True for an error (white at zero, a symmetric colour scale).
    * ``limits``: per panel, None or (lo, hi) for the vertical axis and the colour scale; fix them when frames
      of an explorer are compared, so that a shrinking field looks smaller.
    * ``ncols``: panels per row (2 keeps 3-D axes readable in the content column).
    """
    k = len(fields)
    ncols = max(1, min(ncols, k))
    nrows = math.ceil(k / ncols)
    width = WIDTH if ncols > 1 else 0.6 * WIDTH
    fig = plt.figure(figsize=(width, 3.2 * nrows + (0.35 if suptitle else 0.0)))
    grid = fig.add_gridspec(nrows, 2 * ncols)
    for i, (z, title) in enumerate(zip(fields, titles)):
        row, col = divmod(i, ncols)
        shift = ncols - min(ncols, k - row * ncols)  # a short last row is centred (half-panel steps)
        ax = fig.add_subplot(grid[row, shift + 2 * col : shift + 2 * col + 2], projection="3d")
        surface(
            ax,
            x1,
            x2,
            z,
            title,
            diverging=bool(diverging and diverging[i]),
            limit=limits[i] if limits else None,
            axis_labels=axis_labels,
            zlabel=zlabels[i] if zlabels else None,
        )
    if suptitle:
        fig.suptitle(suptitle)
    fig.subplots_adjust(left=0.02, right=0.95, bottom=0.04, top=0.9 if suptitle else 0.95, wspace=0.12, hspace=0.2)
    return fig


def _t_label(sol) -> str:
    T = getattr(sol, "horizon", math.inf)
    return r"\infty" if T == math.inf else f"{T:g}"


def value_policy_residual(
    sol,
    points_per_dim: int = 41,
    suptitle: str = "",
    axes: tuple[int, int] = (0, 1),
    fixed=None,
    limits: list | None = None,
):
    """V(., 0), mu(., 0) and the squared steady-state residual E_e^2 :eq:`eq-ee`: the paper's Figures 1-3.

    * ``sol``: a solution.
    * ``points_per_dim``: mesh points along each axis.
    * ``suptitle``: the figure's title.
    * ``axes``, ``fixed``: for n > 2, the plane through Omega spanned by ``axes``, the other coordinates held at
      ``fixed`` (see :func:`slice_mesh`), e.g. x3 = 0 of a 3-D system.
    * ``limits``: per panel, None or (lo, hi), as in :func:`surfaces`.
    """
    x1, x2, pts = slice_mesh(sol.system, axes, fixed, points_per_dim)
    T = _t_label(sol)
    v, u, e = sol.value(pts), sol.policy(pts)[:, 0], sol.residual_field(pts) ** 2
    return surfaces(
        x1,
        x2,
        [v, u, e],
        [rf"$\hat V_{{{T}}}(x,0)$", rf"$\hat\mu_{{{T}}}(x,0)$", rf"$E_e(x;\hat V_{{{T}}})^2$"],
        suptitle,
        axis_labels=(f"$x_{axes[0] + 1}$", f"$x_{axes[1] + 1}$"),
        limits=limits,
    )


def _reference_on(sol, pts, reference, which: str):
    system = sol.system
    if reference is None:
        import torch

        from .metrics import known_policy

        fn = system.value_star if which == "value" else known_policy(system)
        if fn is None:
            raise ValueError(f"system '{system.name}' has no known V*; pass a reference grid")
        out = fn(torch.as_tensor(pts)).numpy()
        return out if which == "value" else out[:, 0]
    return reference.value if which == "value" else reference.policy[:, 0]


def _mesh(sol, reference, points_per_dim):
    """The plotting mesh: a grid over Omega, or the reference grid's own points when one is given."""
    if reference is None:
        return grid_2d(sol.system, points_per_dim)
    pts = reference.points
    side = round(math.sqrt(pts.shape[0]))
    return pts[:, 0].reshape(side, side), pts[:, 1].reshape(side, side), pts


def value_and_error(sol, reference=None, points_per_dim: int = 41, suptitle: str = ""):
    """The learned V(., 0) and its error ``V - V*`` (the paper's Figures 4 and 6), for a 2-D system.

    * ``sol``: a solution.
    * ``reference``: a :class:`~pinnhjb.reference.ReferenceGrid` that gives V* on its own points; None: the
      system's known V*.
    * ``points_per_dim``: mesh points along each axis, without a reference.
    * ``suptitle``: the figure's title.
    """
    x1, x2, pts = _mesh(sol, reference, points_per_dim)
    T = _t_label(sol)
    v = sol.value(pts)
    return surfaces(
        x1,
        x2,
        [v, v - _reference_on(sol, pts, reference, "value")],
        [rf"$\hat V_{{{T}}}(x,0)$", rf"$\hat V_{{{T}}}(x,0) - V^\star(x)$"],
        suptitle,
        diverging=[False, True],
    )


def policy_and_error(sol, reference=None, points_per_dim: int = 41, suptitle: str = ""):
    """The learned mu(., 0) and its error ``mu - mu*`` (the paper's Figures 5 and 7); arguments as in
    :func:`value_and_error`."""
    x1, x2, pts = _mesh(sol, reference, points_per_dim)
    T = _t_label(sol)
    u = sol.policy(pts)[:, 0]
    return surfaces(
        x1,
        x2,
        [u, u - _reference_on(sol, pts, reference, "policy")],
        [rf"$\hat\mu_{{{T}}}(x,0)$", rf"$\hat\mu_{{{T}}}(x,0) - \mu^\star(x)$"],
        suptitle,
        diverging=[False, True],
    )


def loss_curve(history, title: str = ""):
    """The training loss against the step (Adam, then L-BFGS, then Levenberg-Marquardt), on a log scale.

    * ``history``: a :class:`~pinnhjb.training.TrainHistory`.
    * ``title``: the figure's title.
    """
    fig, ax = plt.subplots(figsize=(5.5, 3.4))
    steps, losses, phases = np.array(history.step), np.array(history.loss), np.array(history.phase)
    labels = {"adam": "Adam", "lbfgs": "L-BFGS", "lm": "Levenberg-Marquardt"}
    for phase, label in labels.items():
        m = phases == phase
        if m.any():
            ax.semilogy(steps[m], losses[m], label=label, marker="." if m.sum() < 60 else None)
    ax.set_xlabel("iteration (L-BFGS: function evaluations)")
    ax.set_ylabel("loss (MSE)")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return fig


def time_to_accuracy(
    traces: dict,
    targets: dict | None = None,
    title: str = "",
    ylabel: str = "E (infinite-horizon residual)",
    deadlines: dict | None = None,
):
    """The horizon check E :eq:`eq-e` (or another error) against training wall seconds, one line per run, checks
    marked.

    * ``traces``: label -> (seconds, E), e.g. from ``benchmarks/results/speed.json``.
    * ``targets``: label -> an E drawn as a dashed horizontal line.
    * ``title``: the figure's title.
    * ``ylabel``: what the traces' second entries are.
    * ``deadlines``: label -> seconds, drawn as a vertical line in the colour of the trace of that label.
    """
    fig, ax = plt.subplots(figsize=(WIDTH, 4.6))
    unknown = set(deadlines or {}) - set(traces)
    if unknown:
        raise ValueError(f"deadlines for runs not among the traces: {sorted(unknown)}")
    colours = {}
    for label, (seconds, E) in traces.items():
        seconds, E = np.asarray(seconds, dtype=float), np.asarray(E, dtype=float)
        if seconds.shape != E.shape or seconds.ndim != 1:
            raise ValueError(f"{label}: seconds and E must be 1-D of one length; got {seconds.shape}, {E.shape}")
        colours[label] = ax.semilogy(seconds, E, marker="o", markersize=3, label=label)[0].get_color()
    for k, (label, value) in enumerate((targets or {}).items()):
        ax.axhline(value, color="0.3", linestyle=("--", ":", "-.")[k % 3], linewidth=1, label=label)
    for label, seconds in (deadlines or {}).items():
        ax.axvline(seconds, color=colours[label], linestyle=":", linewidth=1.2, label=f"{label}: time goal")
    ax.set_xscale("log")  # seconds to hundreds of seconds on one axis
    ax.set_xlabel("training wall time (s)")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)  # below: covers no curve
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return fig


def grouped_bars(values: dict, ylabel: str, title: str = "", log: bool = True):
    """Grouped bars, one colour per bar label (e.g. methods by machine).

    * ``values``: group label -> {bar label -> value or None}; None draws no bar and writes "none" at the axis
      (not run, or never reached).
    * ``ylabel``: the vertical axis's label.
    * ``title``: the figure's title.
    * ``log``: a log scale.
    """
    if not values:
        raise ValueError("nothing to plot: values is empty")
    bars = list(dict.fromkeys(k for group in values.values() for k in group))
    width = 0.8 / len(bars)
    fig, ax = plt.subplots(figsize=(WIDTH, 3.6))
    for j, bar in enumerate(bars):
        xs = [i + (j - (len(bars) - 1) / 2) * width for i in range(len(values))]
        ys = [group.get(bar) for group in values.values()]
        ax.bar([x for x, y in zip(xs, ys) if y is not None], [y for y in ys if y is not None], width, label=bar)
        for x, y in zip(xs, ys):
            if y is None:
                ax.annotate(
                    "none",
                    (x, 0),
                    xytext=(0, 3),
                    textcoords="offset points",
                    ha="center",
                    fontsize=10,
                    xycoords=("data", "axes fraction"),
                )
    ax.set_xticks(range(len(values)), list(values))
    if log:
        ax.set_yscale("log")
    ax.set_ylabel(ylabel)
    ax.grid(True, axis="y", which="both", alpha=0.3)
    ax.legend()
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return fig


def value_slices(sol, planes, points, errors, labels, points_per_dim: int = 41):
    """The learned V(., 0) on planes through the origin, each beside the reference points' errors in its coordinates.

    * ``sol``: a solution with ``value`` and ``system`` (e.g. a loaded checkpoint).
    * ``planes``: pairs (i, j) of coordinates, one row of two panels per pair; the others are held at 0.
    * ``points``: (N, n) reference states, drawn by their coordinates i and j (projected, not on the plane).
    * ``errors``: (N,) the error at each of them, e.g. (V - V_ref) / max V_ref; a symmetric colour scale.
    * ``labels``: the names of the n coordinates (mathtext), for the axes.
    * ``points_per_dim``: mesh points along each axis of a plane.
    """
    points, errors = np.asarray(points, dtype=float), np.asarray(errors, dtype=float)
    fig, axes = plt.subplots(len(planes), 2, figsize=(WIDTH, 3.1 * len(planes)), squeeze=False)
    top = float(np.abs(errors).max()) or 1.0
    for (i, j), (left, right) in zip(planes, axes):
        x1, x2, pts = slice_mesh(sol.system, (i, j), 0.0, points_per_dim)
        v = np.asarray(sol.value(pts), dtype=float).reshape(x1.shape)
        cs = left.contourf(x1, x2, v, levels=12, cmap=CMAP)
        left.contour(x1, x2, v, levels=cs.levels, colors="k", linewidths=0.4, alpha=0.5)
        fig.colorbar(cs, ax=left, format="%.2g")
        left.set_title(r"$\hat V(x,0)$, others $=0$")
        sc = right.scatter(
            points[:, i], points[:, j], c=errors, s=14, cmap=DIVERGING, vmin=-top, vmax=top, edgecolors="none"
        )
        fig.colorbar(sc, ax=right, format="%.2g")  # 2 digits: ticks 0.015 and 0.01 differ
        right.set_title(r"$(\hat V-V_{\rm ref})/\max V_{\rm ref}$ at its states")
        for ax in (left, right):
            ax.set_xlim(*sol.system.domain[i])
            ax.set_ylim(*sol.system.domain[j])
            ax.set_xlabel(labels[i])
            ax.set_ylabel(labels[j], labelpad=0)
    fig.tight_layout()
    return fig


def loop_residual(loops, which, t_max=None):
    """The residual E_e along closed loops (top, shaded where the loop is outside the training box) and how far
    each loop reaches from the box's centre per half-width (bottom, ``loops.reach``: above 1 outside).

    * ``loops``: a :class:`pinnhjb.metrics.LoopResidual`.
    * ``which``: the indices of the loops to draw.
    * ``t_max``: the last time shown; None: the whole run.
    """
    t, reach = loops.run.t, loops.reach
    fig, (top, bottom) = plt.subplots(2, 1, figsize=(WIDTH, 5.2), sharex=True, height_ratios=(3, 2))
    for c, k in enumerate(which):
        colour = f"C{c}"
        top.plot(t, loops.residual[:, k], color=colour, label=f"loop {c + 1}")
        top.fill_between(
            t, 0, loops.residual[:, k], where=loops.outside[:, k], color=colour, alpha=0.3, lw=0, interpolate=True
        )
        bottom.plot(t, reach[:, k], color=colour)
    top.axhline(0, color="k", lw=0.6)
    top.set_ylabel(r"$E_e(x(t))$")
    top.legend(frameon=False)
    top.set_title("shaded: the loop is outside the training box")
    bottom.axhline(1, color="k", ls="--", lw=0.8)
    bottom.set_ylabel("largest coordinate\n/ box half-width")
    bottom.set_xlabel("$t$ (s)")
    for ax in (top, bottom):
        ax.grid(alpha=0.3)
    if t_max is not None:
        bottom.set_xlim(0, t_max)
    fig.tight_layout()
    return fig


def manoeuvres(cases, state_labels, control_labels, t_max=None):
    """Closed-loop trajectories (solid) against optimal ones (dashed): per case a row of states and controls.

    * ``cases``: one dict per row: ``title``, and ``learned`` and ``optimal``, each a tuple (t, x, u) with t
      (K,), x (K, k) the states to draw, u (K, m) the controls.
    * ``state_labels``, ``control_labels``: the names of the k states and m controls (mathtext), one colour each.
    * ``t_max``: the last time shown; None: the longest run.
    """
    fig, axes = plt.subplots(len(cases), 2, figsize=(WIDTH, 2.9 * len(cases) + 0.5), squeeze=False, sharex=True)
    for case, (left, right) in zip(cases, axes):
        for name, style in (("learned", "-"), ("optimal", "--")):
            t, x, u = (np.asarray(a, dtype=float) for a in case[name])
            for k in range(x.shape[1]):
                left.plot(t, x[:, k], style, color=f"C{k}", lw=1.3)
            for k in range(u.shape[1]):
                right.plot(t, u[:, k], style, color=f"C{k + x.shape[1]}", lw=1.3)
        left.set_title(f"{case['title']}: states")
        right.set_title(f"{case['title']}: controls")
        for ax in (left, right):
            ax.grid(alpha=0.3)
            ax.axhline(0, color="k", lw=0.6)
            if t_max is not None:
                ax.set_xlim(0, t_max)
    for ax in axes[-1]:
        ax.set_xlabel("$t$ (s)")
    handles = [plt.Line2D([], [], color="k", ls=s, label=n) for n, s in (("learned", "-"), ("optimal", "--"))]
    handles += [plt.Line2D([], [], color=f"C{k}", label=lab) for k, lab in enumerate(state_labels)]
    handles += [
        plt.Line2D([], [], color=f"C{k + len(state_labels)}", label=lab) for k, lab in enumerate(control_labels)
    ]
    fig.legend(handles=handles, loc="lower center", ncol=4, frameon=False, handlelength=1.6, columnspacing=1.0)
    fig.tight_layout(rect=(0, 0.5 / (2.9 * len(cases) + 0.5) + 0.04, 1, 1))
    return fig


def against_dimension(rows, fits: dict | None = None):
    """Errors (left) and training wall time (right) against the state dimension n, log-log, one colour per system.

    * ``rows``: dicts with ``system``, ``n``, ``value_rel_error``, ``grad_mean_rel_error`` and ``wall_s``.
    * ``fits``: system -> (slope, intercept) of log(wall time) against log(n), drawn as a dotted line marked
      with its power of n.
    """
    systems = list(dict.fromkeys(r["system"] for r in rows))
    fig, (err, wall) = plt.subplots(1, 2, figsize=(WIDTH, 3.6))
    for k, name in enumerate(systems):
        own = sorted((r for r in rows if r["system"] == name), key=lambda r: r["n"])
        n = np.array([r["n"] for r in own], dtype=float)
        err.loglog(n, [r["value_rel_error"] for r in own], "o-", color=f"C{k}", label=f"{name}: value")
        err.loglog(n, [r["grad_mean_rel_error"] for r in own], "s--", color=f"C{k}", mfc="none", label=f"{name}: grad")
        wall.loglog(n, [r["wall_s"] for r in own], "o-", color=f"C{k}")
        if fits and name in fits:
            slope, intercept = fits[name]
            wall.loglog(n, np.exp(intercept) * n**slope, ":", color=f"C{k}", lw=1.2)
            wall.annotate(
                f"$n^{{{slope:.2f}}}$",
                (n[-1], np.exp(intercept) * n[-1] ** slope),
                xytext=(-4, 6),
                textcoords="offset points",
                ha="right",
                color=f"C{k}",
            )
    err.set_ylabel("relative error")
    wall.set_ylabel("training wall time (s)")
    for ax in (err, wall):
        ax.set_xlabel("state dimension $n$")
        ns = sorted({r["n"] for r in rows})
        ax.set_xticks(ns, [str(v) for v in ns])
        ax.xaxis.set_minor_locator(mpl.ticker.NullLocator())
        ax.grid(alpha=0.3, which="both")
    fig.legend(*err.get_legend_handles_labels(), loc="lower center", ncol=2, frameon=False, handlelength=1.8)
    fig.tight_layout(rect=(0, 0.17, 1, 1))
    return fig


def carried_error(before, after: dict, goal: float | None = None, title: str = ""):
    """What a stage of a chain hands on: each state's error after the stage against its terminal cost's error at
    the same state, one scatter per series, with the diagonal (the error kept where it was) and the goal.

    * ``before``: (N,) the terminal cost's errors (e.g. V - V* of the chain one stage shorter, per max V*).
    * ``after``: label -> (N,) errors at the same states after the stage, e.g. the learned stage's and what an
      exact stage would hand on (the terminal cost's error where the optimal loop has gone by the stage's end).
    * ``goal``: an error bound drawn as dotted lines at plus and minus it; None: none.
    * ``title``: the figure's title.
    """
    before = np.asarray(before, dtype=float)
    if before.ndim != 1:
        raise ValueError(f"before must be 1-D; got shape {before.shape}")
    fig, ax = plt.subplots(figsize=(WIDTH * 0.75, 4.4))
    for (label, errors), marker in zip(after.items(), "o^sv", strict=False):
        errors = np.asarray(errors, dtype=float)
        if errors.shape != before.shape:
            raise ValueError(f"{label}: errors must have the shape of before {before.shape}; got {errors.shape}")
        ax.scatter(before, errors, s=4, marker=marker, alpha=0.5, label=label, rasterized=True)
    span = float(np.max(np.abs(before)))
    ax.plot([-span, span], [-span, span], color="0.3", linestyle="--", linewidth=1, label="kept where it was")
    if goal is not None:
        for sign in (1, -1):
            ax.axhline(sign * goal, color="k", linestyle=":", linewidth=1, label="goal" if sign > 0 else None)
    ax.ticklabel_format(style="sci", scilimits=(-2, 2))
    ax.set_xlabel("terminal cost's error (per max V*)")
    ax.set_ylabel("error after the stage (per max V*)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=2, frameon=False, markerscale=3)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    return fig


def averaged_error(errors, goal: float | None = None, labels=None):
    """What averaging independently trained solutions does to the largest error: left, every other member's errors
    against the first's, state by state (uncorrelated errors fill the square, shared ones lie along the diagonal);
    right, the largest error of the mean of the first k members against k, beside each member's own and what
    independent errors of equal size would give (the members' mean largest error over the square root of k).

    * ``errors``: (K, N) each member's errors at the same N states (e.g. V - V* per max V*), K >= 2.
    * ``goal``: an error bound drawn as a dashed line on the right; None: none.
    * ``labels``: K names of the members; None: "member 1", ...
    """
    errors = np.asarray(errors, dtype=float)
    if errors.ndim != 2 or errors.shape[0] < 2:
        raise ValueError(f"errors must be (K, N) with K >= 2 members; got shape {errors.shape}")
    k = np.arange(1, errors.shape[0] + 1)
    labels = list(labels) if labels is not None else [f"member {i}" for i in k]
    if len(labels) != len(k):
        raise ValueError(f"labels must name the {len(k)} members; got {len(labels)}")
    fig, (left, right) = plt.subplots(1, 2, figsize=(WIDTH, 3.6))
    for other, label in zip(errors[1:], labels[1:], strict=True):
        left.scatter(errors[0], other, s=3, alpha=0.4, label=label, rasterized=True)
    span = float(np.abs(errors).max())
    left.plot([-span, span], [-span, span], color="0.3", linestyle="--", linewidth=1)
    left.set_xlabel(f"{labels[0]}'s error")
    left.set_ylabel("another member's error")
    left.legend(fontsize="small", markerscale=3)
    left.ticklabel_format(style="sci", scilimits=(-2, 2))
    own = np.abs(errors).max(axis=1)
    mean = np.array([np.abs(errors[:i].mean(axis=0)).max() for i in k])
    right.plot(np.ones_like(own), own, "o", color="0.5", ms=4, label="each member")
    right.plot(k, mean, "s-", ms=5, label="mean of the first k")
    right.plot(k, own.mean() / np.sqrt(k), ":", color="0.3", label=r"independent: $1/\sqrt{k}$")
    if goal is not None:
        right.axhline(goal, color="k", linestyle="--", linewidth=0.8, label="goal")
    right.set_yscale("log")
    right.set_xticks(k)
    right.set_xlabel("members averaged, k")
    right.set_ylabel("largest error")
    right.legend(fontsize="small")
    for ax in (left, right):
        ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig


def beyond_samples(sampled, largest, n, goal: float | None = None, highlight=None, highlight_label: str = ""):
    """Each chain's largest value error on its sampled states (x) against the largest found on all of Omega, with
    its vertices and after an ascent (y; :func:`pinnhjb.metrics.largest_value_error`), one colour per n, on log
    axes with the diagonal y = x (a chain on it errs no more off its states) and the goal on both axes: a chain
    left of the goal and above it meets the goal on its states but not on Omega.

    * ``sampled``, ``largest``: (K,) the two numbers of K chains.
    * ``n``: (K,) each chain's state dimension.
    * ``goal``: the error bound, drawn dashed on both axes; None: none.
    * ``highlight``: indices of chains to ring; None: none.
    * ``highlight_label``: what the legend calls the ringed chains ("" : "highlighted").
    """
    sampled, largest, n = (np.asarray(a, dtype=float) for a in (sampled, largest, n))
    if not (sampled.shape == largest.shape == n.shape and sampled.ndim == 1 and len(sampled)):
        raise ValueError(f"sampled, largest and n must be (K,) alike; got {sampled.shape}, {largest.shape}, {n.shape}")
    if (sampled <= 0).any() or (largest <= 0).any():
        raise ValueError("the errors must be positive (log axes)")
    fig, ax = plt.subplots(figsize=(WIDTH * 0.75, 4.6))
    for dim in np.unique(n):
        on = n == dim
        ax.scatter(sampled[on], largest[on], s=28, label=f"$n={dim:g}$", zorder=3)
    lo = min(sampled.min(), largest.min()) / 1.5
    hi = max(sampled.max(), largest.max()) * 1.5
    ax.plot([lo, hi], [lo, hi], color="0.3", linestyle=":", linewidth=1, label="$y = x$")
    if highlight is not None:
        ix = np.atleast_1d(np.asarray(highlight, dtype=int))
        ax.scatter(
            sampled[ix],
            largest[ix],
            s=140,
            facecolors="none",
            edgecolors="k",
            zorder=4,
            label=highlight_label or "highlighted",
        )
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    if goal is not None:
        ax.axvline(goal, color="k", linestyle="--", linewidth=0.8)
        goal_line(ax, goal)
    ax.set_xlabel("largest error on the sampled states")
    ax.set_ylabel(r"largest error on $\Omega$")
    ax.legend(fontsize="small", loc="lower right")  # below the diagonal: no chain there
    ax.grid(True, which="both", alpha=0.3)
    fig.tight_layout()
    return fig


def goal_line(ax, goal: float, label: str = "goal", color="k"):
    """A dashed horizontal line at ``goal`` on ``ax``, named just above it at the left edge of the axes (where
    the x-limits are). Returns the line.

    * ``ax``: the axes.
    * ``goal``: the height, in data units (e.g. an error bound); positive on a log axis.
    * ``label``: the name written on the line; "" writes none.
    * ``color``: the line's and the name's colour.
    """
    goal = float(goal)
    if not math.isfinite(goal) or (ax.get_yscale() == "log" and goal <= 0):
        raise ValueError(f"goal must be finite (and positive on a log axis); got {goal!r}")
    line = ax.axhline(goal, color=color, lw=0.8, ls="--")
    if label:
        ax.annotate(
            label,
            (0, goal),
            xycoords=("axes fraction", "data"),
            xytext=(4, 3),
            textcoords="offset points",
            fontsize="small",
            color=color,
        )
    return line


def steady_against_finite(system, steady, finite, points: int = 241):
    """The book's first figure: a PINN trained on the steady-state HJB, one trained on the finite-horizon HJB
    (its ``V_T(x, 0)``), and the optimal value, along the line through the origin and the state of Omega where
    the steady-state PINN's value is lowest (found on ``system.grid(61)``). Sized for a phone's column as well
    as a desktop's. Returns the figure.

    * ``system``: a system with a known ``V*`` (``system.value_star``), its Omega a box around the origin.
    * ``steady``: the steady-state solution; its legend gives its ``E / E(V = 0)`` from ``steady.metrics``.
    * ``finite``: the finite-horizon solution (a chain's last stage); its legend gives its horizon and its
      ``E / E(V = 0)``.
    * ``points``: states along the line, from one edge of Omega to the other.
    """
    import torch

    if system.value_star is None:
        raise ValueError(f"{system.name} has no known V*: the figure compares both PINNs with it")
    grid = system.grid(61).cpu().numpy()
    low = grid[np.argmin(steady.value(grid))]
    direction = low / np.abs(low).max()
    half = np.abs(np.asarray(system.domain, dtype=float)).min(axis=1)  # from the origin to Omega's nearer edge
    edge = float(np.min(half / np.maximum(np.abs(direction), 1e-12)))
    s = np.linspace(-edge, edge, points)
    xs = s[:, None] * direction[None, :]
    v_star = system.value_star(torch.as_tensor(xs)).cpu().numpy()

    def ratio(sol) -> float:  # E / E(V = 0), from the solution's stored metrics
        return sol.metrics["E"] / sol.metrics["E_zero"]

    fig, ax = plt.subplots(figsize=(4.4, 3.8))
    ax.axhline(0, color="0.6", lw=0.8)
    ax.plot(s, steady.value(xs), color="C3", lw=2, label=f"steady-state: {ratio(steady):.0e}")
    label = rf"finite-horizon, $T={finite.horizon:g}$: {ratio(finite):.0e}"
    ax.plot(s, finite.value(xs), color="C0", lw=4, alpha=0.5, label=label)
    ax.plot(s, v_star, "k--", lw=1.2)
    at = int(np.argmin(np.abs(v_star[points // 2 :] - v_star.max() / 3))) + points // 2  # a third of the way up
    ax.annotate(
        r"$V^\star$ (dashed)",
        (s[at], v_star[at]),
        xytext=(-16, 0),
        textcoords="offset points",
        ha="right",
        va="center",
        fontsize="medium",
    )
    coords = ",\\ ".join(f"{c:.2g}" for c in direction)
    ax.set_xlabel(rf"$s$, the state $x = s\,({coords})$")
    ax.set_ylabel("value")
    low, high = ax.get_ylim()
    ax.set_ylim(low, high + 0.4 * (high - low))  # room above the curves for the legend
    ax.legend(
        frameon=False,
        fontsize="medium",
        loc="upper center",
        title_fontsize="medium",
        title=r"a PINN on the HJB; its $E/E(V\equiv0)$",
    )
    fig.tight_layout()
    return fig
