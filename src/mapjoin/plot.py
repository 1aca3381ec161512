"""Figures: maps and trajectories, Theorem 2's two-minima region, and one join's cost curve.

matplotlib is an optional extra (``pip install 'mapjoin-slam[plot]'``), imported only when a
figure is drawn. Figures are ``matplotlib.figure.Figure`` objects drawn by the Agg
renderer, never pyplot: headless, and without touching the global backend of a program
that imports mapjoin. :func:`save` writes PNG, SVG or PDF, chosen by the file's extension.

What a figure shows is computed here with numpy (``two_minima_region``, ``join_curve``,
``join_problem``) and tagged on the artists (``gid``), so that tests can check the drawn
data against the theory and against brute force.
"""

from __future__ import annotations

import io
import itertools
import math
import os
import re
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING

import numpy as np

from . import io as mapio
from .errors import InputError, JoinError, MapjoinError, counted
from .distribution import install_hint
from .joining import check_chain, join_sequential
from .covariance import CovarianceMode, spherical_variances
from .maps import GlobalMap, GroundTruth, LocalMap
from .onestep import OneStepProblem, Solver, analyse_minima, constants, cost, solve
from .se2 import wrap

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from matplotlib.figure import Figure

__all__ = [
    "FIGURE_FORMATS",
    "JoinCurve",
    "chained_local_maps",
    "figure_format",
    "join_curve",
    "join_figure",
    "join_problem",
    "map_figure",
    "minima_figure",
    "save",
    "two_minima_region",
]

FIGURE_FORMATS: tuple[str, ...] = ("png", "svg", "pdf")
INSTALL_HINT = install_hint("plot")
#: probability inside the drawn uncertainty ellipses; for 2 degrees of freedom the
#: chi-square quantile is -2 ln(1 - p) in closed form (5.991 for 95%)
ELLIPSE_PROBABILITY = 0.95
_WEIGHTS = "spherical weights"  # what a map without covariances holds (GlobalMap.has_covariances)
#: matplotlib's warning for a character its font cannot draw ("Glyph 7 (\\x07) missing from font(s) ...")
_MISSING_GLYPH = re.compile(r"Glyph (\d+) ")
_SURROGATE = re.compile("[\ud800-\udfff]")
DPI = 150
#: |C_phi| below which one minimum is certain for every a (docs/method.md#the-arcsin-bound): atan(pi), 72.3 degrees
ONE_MINIMUM_C_PHI = math.atan(math.pi)

# map styles in overlay order: colour, feature marker, trajectory line style (truth is grey)
_STYLES = tuple(zip(("#1f77b4", "#d62728", "#2ca02c", "#9467bd", "#ff7f0e", "#8c564b", "#e377c2", "#17becf"),
                    ("o", "x", "^", "s", "+", "D", "v", "*"),
                    ("-", "--", ":", "-.", "-", "--", ":", "-.")))
_TRUTH_COLOUR = "0.45"


def _matplotlib() -> ModuleType:
    """The ``matplotlib`` package with the submodules used here, or a MapjoinError with the install hint."""
    try:
        import matplotlib
        import matplotlib.collections
        import matplotlib.figure
        import matplotlib.lines
        import matplotlib.ticker
    except ImportError as error:
        raise MapjoinError(f"figures need matplotlib, an optional extra: {INSTALL_HINT}") from error
    return matplotlib


# ---------------------------------------------------------------------------------------
# Files


def figure_format(path: str) -> str:
    """The format of a figure file from its extension (png, svg or pdf); InputError otherwise."""
    suffix = os.path.splitext(path)[1].lower().lstrip(".")
    if suffix not in FIGURE_FORMATS:
        got = f"the extension '.{suffix}'" if suffix else "no extension"
        raise InputError(f"cannot tell the figure format from {got}; expected "
                         f"{', '.join('.' + f for f in FIGURE_FORMATS)}", path)
    return suffix


def _literal(text: str) -> str:
    """Text from the user or a file (a label, a map's or file's name) drawn as it is: its ``$`` not read as
    mathtext (an unbalanced ``$`` or an unknown TeX command stops the drawing with a parse error), and a lone
    surrogate (a byte of a file name that is not UTF-8, as Python passes it on) drawn as U+FFFD, since the font
    engine refuses it."""
    return _SURROGATE.sub("\ufffd", text).replace("$", r"\$")


def save(figure: Figure, path: str) -> str:
    """Render ``figure`` into ``path`` (format from the extension), atomically like every mapjoin output.

    Returns the characters of its text that the font has no glyph for (drawn as boxes; a label or map
    name may hold any character), for the caller to say in one line: matplotlib would warn once per
    character, through Python's warnings."""
    buffer = io.BytesIO()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        figure.savefig(buffer, format=figure_format(path), dpi=DPI)
    mapio.write_output(buffer.getvalue(), path)
    missing = []
    for warning in caught:
        glyph = _MISSING_GLYPH.match(str(warning.message))
        if glyph is None:
            warnings.warn_explicit(warning.message, warning.category, warning.filename, warning.lineno)
        elif chr(int(glyph.group(1))) not in missing:
            missing.append(chr(int(glyph.group(1))))
    return "".join(missing)


# ---------------------------------------------------------------------------------------
# Maps


def map_figure(maps: Sequence[GlobalMap], labels: Sequence[str], truth: GroundTruth | None = None,
               ellipses: bool = False) -> Figure:
    """Features and end-pose trajectories of global maps overlaid (e.g. fast vs exact join, Fig. 5).

    Each trajectory starts at the origin, the first map's start pose. The truth is drawn for
    the features some map holds and for every pose. With ``ellipses`` the 95% uncertainty
    region of every feature and pose position is drawn: an ellipse from the full marginal
    covariance when the map has one; else a circle of the same scale from its spherical
    weight, labelled as such: a fast join's weights are not covariances, so such a circle
    is no 95% region.
    """
    mpl = _matplotlib()
    figure = mpl.figure.Figure(layout="constrained")
    ax = figure.add_subplot()
    handles = []
    if truth is not None:
        mapped = np.isin(truth.feature_ids, np.concatenate([m.feature_ids for m in maps]))
        ax.scatter(*truth.features[mapped].T, s=24, marker="+", color=_TRUTH_COLOUR, linewidths=0.8,
                   gid="truth-features")
        ax.plot(*truth.poses[:, :2].T, color=_TRUTH_COLOUR, linestyle=(0, (4, 2)), linewidth=1.0, gid="truth-poses")
        handles.append(mpl.lines.Line2D([], [], color=_TRUTH_COLOUR, marker="+", linestyle=(0, (4, 2)),
                                        label=f"ground truth ({_literal(os.path.basename(truth.name) or truth.name)}): "
                                              f"the {mapped.sum()} mapped of {counted(len(mapped), 'feature')}, "
                                              f"{counted(len(truth.pose_ids), 'pose')}"))
    size = float(np.clip(4000 / max(1, max(len(m.feature_ids) for m in maps)), 3, 18))
    for global_map, label, (colour, marker, line) in zip(maps, labels, itertools.cycle(_STYLES)):
        hollow = marker in "o^sDv"  # filled shapes drawn hollow, so that overlaid maps stay visible
        ax.scatter(*global_map.features.T, s=size, marker=marker, linewidths=0.8, gid="features",
                   **({"facecolors": "none", "edgecolors": colour} if hollow else {"color": colour}))
        trajectory = np.vstack([np.zeros(2), global_map.poses[:, :2]])
        ax.plot(*trajectory.T, color=colour, linestyle=line, linewidth=1.1, gid="poses")
        text = (f"{_literal(label)}: {counted(len(global_map.feature_ids), 'feature')}, "
                f"{counted(len(global_map.pose_ids), 'pose')}")
        if ellipses:
            text += _draw_ellipses(ax, global_map, colour)
        handles.append(mpl.lines.Line2D([], [], color=colour, marker=marker, linestyle=line,
                                        markerfacecolor="none" if hollow else colour, label=text))
    ax.plot([0], [0], marker="*", color="k", markersize=10, linestyle="none", gid="origin")
    handles.append(mpl.lines.Line2D([], [], color="k", marker="*", markersize=10, linestyle="none",
                                    label="start pose of map 1 (the origin)"))
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, linewidth=0.4, alpha=0.5)
    legend = figure.legend(handles=handles, loc="outside lower center", fontsize="small", frameon=False)
    # a figure shaped like the map (8 inches wide), plus room for the legend's lines
    shape = (ax.dataLim.height + 1e-9) / (ax.dataLim.width + 1e-9)
    lines = sum(text.get_text().count("\n") + 1 for text in legend.get_texts())
    figure.set_size_inches(8, float(np.clip(7 * shape, 3, 9)) + 0.8 + 0.2 * lines)
    return figure


def chained_local_maps(maps: Sequence[LocalMap], name: str) -> GlobalMap:
    """Local maps placed by their start poses alone, without a join (docs/method.md#notation: each map
    is in the frame of its start pose, the end pose of the map before): map 1 at the origin, map k at the
    composition of the end poses of maps 1..k-1, so that a figure shows the drift a join corrects. A feature
    several maps hold is drawn where the first of them puts it; the variances are the local maps' own, not a
    global map's (so no uncertainty is drawn from them: join them first)."""
    check_chain(maps)
    ends = np.array([m.end_pose for m in maps])
    headings = np.cumsum(ends[:, 2])
    turn = np.exp(1j * np.concatenate([[0.0], headings[:-1]]))           # each map's start heading
    end_xy = np.cumsum(turn * (ends[:, 0] + 1j * ends[:, 1]))
    start_xy = np.concatenate([[0j], end_xy[:-1]])
    owner = np.repeat(np.arange(len(maps)), [len(m.feature_ids) for m in maps])
    local = np.concatenate([m.features for m in maps]).reshape(-1, 2)
    placed = start_xy[owner] + turn[owner] * (local[:, 0] + 1j * local[:, 1])
    ids, first = np.unique(np.concatenate([m.feature_ids for m in maps]), return_index=True)
    return GlobalMap(feature_ids=ids, features=np.column_stack([placed.real, placed.imag])[first],
                     feature_variances=np.concatenate([m.feature_variances for m in maps])[first],
                     pose_ids=np.array([m.end_id for m in maps]),
                     poses=np.column_stack([end_xy.real, end_xy.imag, wrap(headings)]),
                     pose_variances=np.array([m.pose_variances for m in maps]), name=name)


def _draw_ellipses(ax: Axes, global_map: GlobalMap, colour: str) -> str:
    """Draw the 95% regions of features and poses (circles of that scale from weights); the legend
    text saying what they are drawn from."""
    mpl = _matplotlib()
    scale = -2.0 * math.log(1.0 - ELLIPSE_PROBABILITY)
    sources = []
    pose_blocks = None if global_map.pose_covariances is None else global_map.pose_covariances[:, :2, :2]
    for kind, positions, full, variances in (
            ("features", global_map.features, global_map.feature_covariances, global_map.feature_variances),
            ("poses", global_map.poses[:, :2], pose_blocks, global_map.pose_variances[:, 0])):
        blocks = full if full is not None else variances[:, None, None] * np.eye(2)
        values, vectors = np.linalg.eigh(blocks)  # ascending: the last column is the major axis
        width, height = 2 * np.sqrt(scale * np.clip(values, 0, None)).T[::-1]
        angle = np.degrees(np.arctan2(vectors[:, 1, 1], vectors[:, 0, 1]))
        ax.add_collection(mpl.collections.EllipseCollection(
            width, height, angle, units="xy", offsets=positions, offset_transform=ax.transData,
            facecolors="none", edgecolors=colour, linewidths=0.6, alpha=0.8, gid=f"ellipses-{kind}"))
        reach = np.sqrt(scale * np.diagonal(blocks, axis1=1, axis2=2))  # half the bounding box of each
        ax.update_datalim(np.vstack([positions - reach, positions + reach]))
        sources.append("full covariances" if full is not None else _WEIGHTS)
    if sources[0] == sources[1]:
        if sources[0] == _WEIGHTS:
            return f"\ncircles at the 95% scale of the {_WEIGHTS} (not uncertainty regions)"
        return f"\n95% ellipses from {sources[0]}"
    return f"\n95% regions: features from {sources[0]}, poses from {sources[1]}"


# ---------------------------------------------------------------------------------------
# Theorem 2: the (C_phi, a) plane


def two_minima_region(a_max: float, samples: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Theorem 2's two-minima region of the (C_phi, a) plane up to ``a_max``: two closed polygons.

    Returns (C_phi > 0 lobe, C_phi < 0 lobe) as (k, 2) arrays of (C_phi, a) vertices. The
    boundaries are where the count changes: a second minimum is born at an inflection
    (h = g = 0, conditions (18)/(19) as equalities: a = sqrt(1 + x^2), C_phi = pi + atan(x) - x
    for x in [0, pi]), or it leaves through the wrap point varphi = pi (|a sin C_phi| = pi,
    condition (20); (17) for C_phi < 0). The lobes meet at C_phi = +-atan(pi), a = sqrt(1 + pi^2)
    and reach a -> infinity at C_phi = +-pi. ``a_max`` must be at least 10.
    """
    if not a_max >= 10:
        raise ValueError(f"a_max must be >= 10, got {a_max!r}")
    x = np.linspace(0.0, math.pi, samples)
    born = np.column_stack([math.pi + np.arctan(x) - x, np.hypot(1.0, x)])  # from (pi, 1) to the tip
    near = np.linspace(ONE_MINIMUM_C_PHI, math.pi / 2, samples // 2)[1:]
    far = math.pi - np.arcsin(math.pi / np.geomspace(math.pi, a_max, samples))[1:]
    c_phi = np.concatenate([near, far])
    leaves = np.column_stack([c_phi, math.pi / np.sin(c_phi)])  # from the tip up to a_max
    positive = np.vstack([born, leaves, [[math.pi, a_max]]])
    return positive, positive * (-1.0, 1.0)


def minima_figure(points: mapio.MinimaTable) -> Figure:
    """Every join of a report in the (C_phi, a) plane over Theorem 2's two-minima region (the paper's Fig. 3).

    A table without a join column (a ``check-minima --batch``) has problems numbered by row.
    """
    mpl = _matplotlib()
    what, numbers = ("join", points.join) if points.join is not None else ("problem", np.arange(1, len(points.a) + 1))
    counts = np.array([analyse_minima(a, c).count for a, c in zip(points.a.tolist(), points.c_phi.tolist())],
                      dtype=np.int64)
    positive = points.a[points.a > 0]
    bottom = 10.0 ** math.floor(math.log10(min(0.5, positive.min() / 2) if positive.size else 0.5))
    top = 10.0 ** math.ceil(math.log10(max(100.0, 2 * points.a.max())))
    figure = mpl.figure.Figure(figsize=(8, 6), layout="constrained")
    ax = figure.add_subplot()
    ax.set_yscale("log")
    for index, polygon in enumerate(two_minima_region(top)):
        ax.fill(*polygon.T, facecolor="#f4a582", edgecolor="#b2182b", linewidth=0.8, alpha=0.7, gid="two-minima",
                label="two minima possible (Theorem 2)" if index == 0 else None)
    ax.axhline(1.0, color="0.5", linestyle=":", linewidth=0.8)
    for sign in (-1, 1):
        ax.axvline(sign * ONE_MINIMUM_C_PHI, color="0.5", linestyle=":", linewidth=0.8)
    ax.text(0.0, 1.15 * bottom, "one minimum for a < 1 or |C$_\\varphi$| < atan $\\pi$ (72.3°)", ha="center",
            va="bottom", fontsize="small", color="0.35")
    shown = np.maximum(points.a, bottom)
    for count, style in ((1, {"marker": "o", "s": 16, "color": "#2166ac", "alpha": 0.7, "linewidths": 0}),
                         (2, {"marker": "D", "s": 40, "color": "#b2182b", "edgecolors": "k", "linewidths": 0.6})):
        chosen = counts == count
        label = f"{counted(int(chosen.sum()), what)} with {'one minimum' if count == 1 else 'two minima'}"
        ax.scatter(points.c_phi[chosen], shown[chosen], zorder=3, clip_on=False, gid=f"minima-{count}",
                   label=label, **style)
    for number, c, a in list(zip(numbers[counts == 2], points.c_phi[counts == 2], shown[counts == 2]))[:30]:
        ax.annotate(str(number), (c, a), textcoords="offset points", xytext=(5, 4), fontsize="x-small")
    if (points.a < bottom).any():
        ax.text(0.99, 0.01, "a = 0 drawn at the bottom edge", transform=ax.transAxes, ha="right",
                fontsize="x-small", color="0.35")
    ax.set_xlim(-math.pi, math.pi)
    ax.set_ylim(bottom, top)
    ax.xaxis.set_major_locator(mpl.ticker.FixedLocator([-math.pi, -math.pi / 2, 0, math.pi / 2, math.pi]))
    ax.xaxis.set_major_formatter(mpl.ticker.FixedFormatter(["$-\\pi$", "$-\\pi/2$", "0", "$\\pi/2$", "$\\pi$"]))
    ax.set_xlabel("$C_\\varphi = \\mathrm{wrap}(z_\\varphi - \\varphi_0)$ (rad)")
    ax.set_ylabel("$a = a_0\\, p_\\varphi$ (dimensionless, log scale)")
    ax.set_title(f"{_literal(points.source)}: {counted(len(counts), what)}, {int((counts == 2).sum())} with two "
                 "minima", fontsize="medium")
    ax.grid(True, which="major", linewidth=0.4, alpha=0.5)
    figure.legend(loc="outside lower center", fontsize="small", frameon=False, ncols=3)
    return figure


# ---------------------------------------------------------------------------------------
# One join: f_1(phi)


def join_problem(maps: Sequence[LocalMap], join: int, covariance: CovarianceMode) -> OneStepProblem:
    """The one-step problem of join ``join`` (1-based, as numbered in a report) of the chain ``maps``.

    Map 0 is the global map of maps 1..join joined sequentially (its features and its end
    pose, the start of the incoming map); map 1 is map join + 1. Its solution is the join
    ``join_sequential(maps)`` made. A join number out of range raises InputError naming the
    argument (``where="join="``).
    """
    if not 1 <= join < len(maps):
        raise InputError(f"expected a join number from 1 to {len(maps) - 1} for {len(maps)} maps, got {join}",
                         None, "join=")
    check_chain(maps[:join + 1])
    so_far = join_sequential(maps[:join], covariance).global_map
    incoming = maps[join]
    common = np.isin(incoming.feature_ids, so_far.feature_ids)
    if not common.any():
        raise JoinError(f"{incoming.name} shares no feature with the maps before it: its join is placed by the "
                        "start pose alone and has no cost curve")
    rows = np.searchsorted(so_far.feature_ids, incoming.feature_ids[common])  # ids are sorted and unique
    return OneStepProblem(z0=so_far.features[rows], var0=so_far.feature_variances[rows],
                          z1=incoming.features[common], var1=spherical_variances(incoming, covariance)[0][common],
                          odometry=so_far.poses[-1], odometry_variances=so_far.pose_variances[-1])


@dataclass(frozen=True)
class JoinCurve:
    """f_1 of a one-step problem sampled over [z_phi - pi, z_phi + pi), split into its two terms.

    ``features`` is c0 - 2 a0 cos(phi - phi0) (Theorem 1), ``link`` is wrap(z_phi - phi)^2 / p_phi,
    ``cost`` their sum. ``minima`` are every local minimum (phi, f_1), the global one
    (phi*) first; ``phi0`` is the features' own optimum, placed in the interval; ``width``
    is phi*'s, 1/sqrt(f_1''(phi*)/2), the change of phi that raises f_1 by 1.
    """

    phi: np.ndarray
    cost: np.ndarray
    features: np.ndarray
    link: np.ndarray
    minima: tuple[tuple[float, float], ...]
    z_phi: float
    phi0: float
    a: float
    c_phi: float
    width: float


def join_curve(problem: OneStepProblem, solver: Solver = "bisection", samples: int = 4001) -> JoinCurve:
    """Sample f_1 uniformly, and densely within 5 widths (1/sqrt(f_1''/2)) of each minimum."""
    k = constants(problem)
    solution = solve(problem, solver)
    z_phi, p_phi = float(problem.odometry[2]), float(problem.odometry_variances[1])
    minima = [solution.phi] + ([solution.other_phi] if solution.other_phi is not None else [])
    minima = [z_phi + wrap(phi - z_phi) for phi in minima]  # into [z_phi - pi, z_phi + pi)
    widths = [1.0 / math.sqrt(max(k.a0 * math.cos(m - k.phi0) + 1.0 / p_phi, 1e-12)) for m in minima]
    grid = z_phi - math.pi + 2 * math.pi * np.arange(samples) / samples
    dense = [m + w * np.linspace(-5, 5, 201) for m, w in zip(minima, widths)]
    phi = np.unique(np.concatenate([grid, *dense, minima]))
    phi = phi[(phi >= z_phi - math.pi) & (phi < z_phi + math.pi)]
    return JoinCurve(phi=phi, cost=cost(problem, phi, k), features=k.c0 - 2.0 * k.a0 * np.cos(phi - k.phi0),
                     link=wrap(z_phi - phi) ** 2 / p_phi, minima=tuple((m, cost(problem, m, k)) for m in minima),
                     z_phi=z_phi, phi0=z_phi - solution.minima.c_phi, a=solution.minima.a,
                     c_phi=solution.minima.c_phi, width=widths[0])


def join_figure(curve: JoinCurve, title: str) -> Figure:
    """f_1(phi) with its feature and link terms, the minima, phi*, z_phi and phi0; a zoom on phi* when narrow."""
    mpl = _matplotlib()
    star = curve.minima[0][0]
    half = max(6 * curve.width, 1.4 * abs(star - curve.z_phi), 1.4 * abs(star - curve.phi0))
    zoom = half < math.pi / 4
    figure = mpl.figure.Figure(figsize=(8, 7.5 if zoom else 5), layout="constrained")
    axes = figure.subplots(2 if zoom else 1, 1, squeeze=False)[:, 0]
    count = len(curve.minima)
    certificate = "2 minima" if count == 2 else "1 minimum (certified unique)"
    figure.suptitle(f"{_literal(title)}\na = {curve.a:.6g}, C$_\\varphi$ = {curve.c_phi:+.4g} rad: {certificate}",
                    fontsize="medium")
    for panel, ax in enumerate(axes):
        inside = slice(None) if panel == 0 else (curve.phi >= star - half) & (curve.phi <= star + half)
        phi = curve.phi[inside]
        # in the zoom each term is raised by the other's value at phi* (so both meet f_1 there),
        # which shows the two pulls on the scale of f_1 near its minimum
        raise_features, raise_link = (0.0, 0.0) if panel == 0 else (
            float(np.interp(star, curve.phi, curve.link)), float(np.interp(star, curve.phi, curve.features)))
        ax.plot(phi, curve.cost[inside], color="k", linewidth=1.4, label="$f_1(\\varphi)$",
                gid="f1" if panel == 0 else None)
        ax.plot(phi, curve.features[inside] + raise_features, color="#2166ac", linestyle=(0, (1, 1.5)),
                linewidth=1.2, label="features: $c_0 - 2 a_0 \\cos(\\varphi - \\varphi_0)$")
        ax.plot(phi, curve.link[inside] + raise_link, color="#1b7837", linestyle="--", linewidth=1.2,
                label="orientation link: wrap$(z_\\varphi - \\varphi)^2 / p_\\varphi$")
        ax.plot(*np.transpose(curve.minima), linestyle="none", marker="o", markersize=8, markerfacecolor="none",
                markeredgecolor="#b2182b", markeredgewidth=1.5,
                label="local minima" if count == 1 else f"local minima (other: {curve.minima[1][0]:+.6f} rad)",
                gid="minima" if panel == 0 else None)
        ax.axvline(star, color="#b2182b", linewidth=1.0, label=f"$\\varphi^*$ = {star:+.6f} rad")
        ax.axvline(curve.z_phi, color="#1b7837", linewidth=0.8, linestyle=":",
                   label=f"$z_\\varphi$ = {curve.z_phi:+.6f} rad (odometry)")
        ax.axvline(curve.phi0, color="#2166ac", linewidth=0.8, linestyle=":",
                   label=f"$\\varphi_0$ = {curve.phi0:+.6f} rad (features alone)")
        if panel == 0:
            ax.set_xlim(curve.z_phi - math.pi, curve.z_phi + math.pi)
            ax.set_xlabel("$\\varphi$ (rad), over $[z_\\varphi - \\pi, z_\\varphi + \\pi)$")
        else:
            ax.set_xlim(star - half, star + half)
            visible = curve.cost[inside]
            margin = 0.08 * (visible.max() - visible.min()) or 1.0
            ax.set_ylim(visible.min() - margin, visible.max() + margin)
            ax.set_title(f"zoom on $\\varphi^*$ ($\\pm${half:.3g} rad), the two terms shifted to meet "
                         "$f_1$ at $\\varphi^*$", fontsize="small")
            ax.set_xlabel("$\\varphi$ (rad)")
        ax.set_ylabel("cost ($\\chi^2$, dimensionless)")
        ax.grid(True, linewidth=0.4, alpha=0.5)
    handles, labels = axes[0].get_legend_handles_labels()
    figure.legend(handles, labels, loc="outside lower center", fontsize="small", frameon=False, ncols=2)
    return figure

