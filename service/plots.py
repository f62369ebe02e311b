"""Figures of the stored catalogue, for a screen or a paper: the figure functions of ``packings plot ...``
(:mod:`packings.service.plot_commands` reads the data from the database and calls them).

Each takes plain data and returns a matplotlib figure: :func:`plot_counts`, :func:`plot_gap_cdf`,
:func:`plot_by_contacts`, :func:`plot_probabilities`, :func:`plot_cluster` and :func:`plot_clusters`
(several side by side).  Each draws on a new figure of ``size`` inches at ``dpi``, or on the caller's
matplotlib axes ``ax=`` (a notebook's); given a ``path``, it also writes the figure there, in the format
its suffix names (:data:`FORMATS`).

A figure is :data:`SIZE` inches at :data:`DPI` dots per inch unless told
otherwise, whatever is in it (no tight bounding box that would change the size):
a PNG is 960 x 720 pixels.  Files are written to a temporary name beside the
target and renamed, so a failure never leaves a half-written file and an
existing file is replaced whole.

matplotlib and numpy are imported only inside the functions: the plot commands, which every
``packings`` command loads (``packings --help`` too), read this module's constants, and importing
matplotlib takes longer than the whole of ``packings --help``.  New figures are drawn on matplotlib's
Agg canvas directly (``matplotlib.figure.Figure`` with ``FigureCanvasAgg``), never through pyplot:
no display is needed and no global backend or figure state is touched, so the
functions are safe to call from a notebook or a thread.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Sequence

from packings.service.export import replace_file
from packings.service.fit import fit_factorial, predicted

# matplotlib, numpy, scipy and the numerics are imported in the functions that use them: the plot commands
# load this module for every `packings` command (the module doc).

SIZE, DPI = (6.4, 4.8), 150  #: a figure's default size in inches, and its dots per inch
FORMATS = ("png", "pdf", "svg")  #: what a figure can be written as, by the file name's suffix
RADIUS = 0.5  #: sphere radius: the unit of length is the sphere diameter
STICK_RADIUS = 0.14  #: the spheres' radius in the ``sticks`` style, where every contact shows
STYLES = ("spheres", "sticks")
#: per-sphere properties a cluster picture can be coloured by, and their colour-bar labels
COLOR_BY = {
    "degree": "contacts per sphere",
    "height": "height z − mean z (diameters)",
    "distance": "distance from the centroid (diameters)",
}
CMAP = "viridis"  #: colour map of the cluster pictures (its darkest 15 % left out, for the sticks to show)
GHOST = 0.3  #: opacity of the contacts drawn through the spheres in a cluster picture
STICK_COLOR = "0.1"
GAP_COLOR = "#d62728"  #: the closest pair of spheres not in contact: a dashed line in this colour


# --------------------------------------------------------------------------- writing


def new_figure(size: tuple[float, float] | None = None, dpi: float | None = None):
    """A blank figure of ``size`` inches (default :data:`SIZE`) at ``dpi`` (default :data:`DPI`) on an Agg
    canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    w, h = size or SIZE
    if not (w > 0 and h > 0):
        raise ValueError(f"a figure's size must be positive, got {w} x {h} inches")
    if dpi is not None and not dpi > 0:
        raise ValueError(f"dots per inch must be positive, got {dpi}")
    fig = Figure(figsize=(w, h), dpi=dpi or DPI)
    FigureCanvasAgg(fig)
    return fig


def figure_format(path: str | os.PathLike) -> str:
    """The format a figure is written in to ``path``: its suffix, one of :data:`FORMATS`."""
    fmt = Path(path).suffix.lower().lstrip(".")
    if fmt not in FORMATS:
        raise ValueError(f"cannot write {path}: give a name ending in " + ", ".join("." + f for f in FORMATS))
    return fmt


def save(fig, path: str | os.PathLike) -> Path:
    """Write ``fig`` in the format of ``path``'s suffix (:func:`figure_format`), at the figure's own size
    and dots per inch, to a temporary file beside ``path``, then rename it over ``path``; on any failure
    nothing is left."""
    fmt = figure_format(path)
    return replace_file(path, lambda f: fig.savefig(f, format=fmt, dpi=fig.dpi), binary=True)


def _canvas(ax, size, dpi, path, **subplot):
    """(figure, axes) to draw on: the caller's ``ax`` or a new figure's only axes; checks ``path``'s
    format first, so that nothing is drawn for a file that cannot be written."""
    if path is not None:
        figure_format(path)
    if ax is not None:
        return ax.figure, ax
    fig = new_figure(size, dpi)
    return fig, fig.add_subplot(**subplot)


def _done(fig, path, own: bool):
    """Lay out a figure made here (a caller's is theirs to lay out), write it if asked; the figure."""
    if own:
        fig.tight_layout()
    if path is not None:
        save(fig, path)
    return fig


def _colors(k: int):
    """k colours along a sequential colour map (n is ordered), dark to light."""
    from matplotlib import colormaps

    cmap = colormaps["viridis"]
    return [cmap(0.45 if k == 1 else 0.9 * i / (k - 1)) for i in range(k)]


def _integer_ticks(axis, lo: int, hi: int) -> None:
    """A tick at every integer from lo to hi, or fewer integers if that is more than 12."""
    from matplotlib.ticker import MaxNLocator, MultipleLocator

    axis.set_major_locator(MultipleLocator(1) if hi - lo <= 12 else MaxNLocator(integer=True))


def _log_ticks(axis, lo: float, hi: float) -> None:
    """Plain numbers (1, 10, 100; 0.01) on a log axis spanning lo..hi, with
    2 and 5 between the powers of ten when it spans less than three decades."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    subs = (1.0, 2.0, 5.0) if hi / lo < 1e3 else (1.0,)
    axis.set_major_locator(LogLocator(base=10, subs=subs))
    axis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:,.0f}" if v >= 1 else f"{v:.3g}"))
    axis.set_minor_formatter(NullFormatter())


# --------------------------------------------------------------------------- the figures


def plot_counts(
    totals: dict[int, int],
    path: str | os.PathLike | None = None,
    *,
    restricted=None,
    partial=(),
    ax=None,
    size: tuple[float, float] | None = None,
    dpi: float | None = None,
    paper=None,
):
    """The number of clusters against n (log scale, one marker per n, the count
    written above it) with the fitted curve b·(n − 5)! of
    :func:`packings.service.fit.fit_factorial` (b in the legend).  ``restricted``: {n:
    fewest contacts kept} for the n whose totals count only the clusters with
    that many contacts or more (runs restricted by ``--min-contacts``): drawn
    hollow, marked "≥ M contacts", and left out of the fit.  ``partial``: the n
    whose totals are not complete (:func:`packings.service.queries.incomplete_ns`): drawn
    hollow in grey, marked "partial", and left out of the fit.  ``paper``: {n: the
    paper's count} to compare (:func:`packings.service.paper.paper_totals`), drawn as
    crosses at the n plotted.  Returns the figure."""
    totals = {int(n): int(t) for n, t in totals.items() if t and t > 0}
    if not totals:
        raise ValueError("no clusters to plot")
    restricted = {int(n): int(m) for n, m in (restricted or {}).items() if int(n) in totals}
    partial = {int(n) for n in partial if int(n) in totals and int(n) not in restricted}
    ns = sorted(totals)
    full = [n for n in ns if n not in restricted and n not in partial]
    fig, ax_ = _canvas(ax, size, dpi, path)
    ax_.set_yscale("log")
    _draw_counts(ax_, totals, full, restricted, partial, paper)
    _draw_fit(ax_, totals, full)
    ax_.set_xlabel("n (spheres)")
    ax_.set_ylabel("number of rigid clusters")
    ax_.set_title("Rigid clusters of n spheres")
    ax_.set_xlim(min(ns) - 0.6, max(ns) + 0.6)
    _integer_ticks(ax_.xaxis, min(ns), max(ns))
    lo, hi = min(totals.values()), max(totals.values())
    ax_.set_ylim(lo / 2, hi * 4)  # room for the counts above the markers
    _log_ticks(ax_.yaxis, lo / 2, hi * 4)
    ax_.grid(True, which="major", alpha=0.3)
    ax_.legend(loc="upper left", fontsize=8)
    return _done(fig, path, ax is None)


def _draw_counts(
    ax_, totals: dict[int, int], full: list[int], restricted: dict[int, int], partial: set[int], paper
) -> None:
    """:func:`plot_counts`' markers: the full counts, the restricted and the partial ones hollow, the paper's
    crosses; each count written above its marker."""
    ns = sorted(totals)
    if full:
        ax_.plot(full, [totals[n] for n in full], "o", ms=7, color="C0", zorder=3, label="rigid clusters")
    if restricted:
        part = sorted(restricted)
        ax_.plot(
            part,
            [totals[n] for n in part],
            "o",
            ms=7,
            mfc="none",
            mec="C2",
            mew=1.5,
            zorder=3,
            label="clusters with ≥ M contacts only (--min-contacts M)",
        )
    if partial:
        part = sorted(partial)
        ax_.plot(
            part,
            [totals[n] for n in part],
            "o",
            ms=7,
            mfc="none",
            mec="0.45",
            mew=1.5,
            zorder=3,
            label="partial counts (no full run of n complete)",
        )
    shown = sorted(n for n in (paper or {}) if n in totals)
    if shown:
        ax_.plot(
            shown,
            [paper[n] for n in shown],
            "x",
            ms=9,
            mew=1.5,
            color="C3",
            zorder=4,
            label="the paper (Holmes-Cerfon 2016, Table 1)",
        )
    for n in ns:
        text = f"{totals[n]:,}" + (
            f"\n(≥ {restricted[n]})" if n in restricted else "\n(partial)" if n in partial else ""
        )
        ax_.annotate(
            text, (n, totals[n]), textcoords="offset points", xytext=(0, 8), ha="center", fontsize=8, color="0.25"
        )


def _draw_fit(ax_, totals: dict[int, int], full: list[int]) -> None:
    """:func:`plot_counts`' fitted curve b·(n − 5)! of the full counts, if there is one."""
    import numpy as np

    ns = sorted(totals)
    fit = fit_factorial({n: totals[n] for n in full})
    if fit is not None:
        xs = np.arange(max(min(ns), 5), max(ns) + 1)
        used = fit["ns"]
        over = f"n = {used[0]}" + (f"–{used[-1]}" if len(used) > 1 else "")
        ax_.plot(
            xs,
            [predicted(fit["b"], x) for x in xs],
            "--",
            color="C1",
            lw=1.5,
            zorder=2,
            label=f"fit {fit['b']:.2f}·(n − 5)!  ({over})",
        )


def plot_gap_cdf(
    gaps: dict[int, list[float]],
    path: str | os.PathLike | None = None,
    *,
    ax=None,
    size: tuple[float, float] | None = None,
    dpi: float | None = None,
):
    """The cumulative distribution of the clusters' minimum gaps (the smallest
    distance between spheres not in contact, minus 1), one line per n, on a log
    x axis.  Gaps that are missing, not finite or not positive are left out.
    Returns the figure."""
    import numpy as np

    series = {}
    for n, values in gaps.items():
        v = np.array([g for g in values if g is not None], dtype=float)
        v = np.sort(v[np.isfinite(v) & (v > 0)])
        if len(v):
            series[int(n)] = v
    if not series:
        raise ValueError("no minimum gaps to plot")
    fig, ax_ = _canvas(ax, size, dpi, path)
    for (n, v), color in zip(sorted(series.items()), _colors(len(series))):
        k = len(v)
        x = np.r_[v[0], v]
        y = np.r_[0.0, np.arange(1, k + 1) / k]
        ax_.step(x, y, where="post", color=color, lw=1.8, label=f"n = {n} ({k})")
    ax_.set_xscale("log")
    lo, hi = min(v[0] for v in series.values()), max(v[-1] for v in series.values())
    ax_.set_xlim(lo / 1.5, hi * 1.5)
    _log_ticks(ax_.xaxis, lo / 1.5, hi * 1.5)
    ax_.set_ylim(0, 1.03)
    ax_.set_xlabel("minimum gap between spheres not in contact (diameters)")
    ax_.set_ylabel("fraction of clusters with min gap ≤ x")
    ax_.set_title("Minimum gaps: cumulative distribution")
    ax_.grid(True, which="major", alpha=0.3)
    ax_.legend(title="n (clusters)", loc="upper left", fontsize=8, title_fontsize=8)
    return _done(fig, path, ax is None)


def plot_by_contacts(
    by_n: dict[int, dict[int, int]],
    path: str | os.PathLike | None = None,
    *,
    restricted=None,
    partial=(),
    ax=None,
    size: tuple[float, float] | None = None,
    dpi: float | None = None,
    paper=None,
):
    """The number of clusters by number of contacts, one series per n, against
    contacts − (3n − 6) (0: isostatic; negative: hypostatic), log y.  ``restricted``: {n:
    M} for the n whose clusters were counted only from M contacts up (as in
    :func:`plot_counts`): their legend says "≥ M"; ``partial``: the n whose counts are not
    complete, "partial" in the legend.  ``paper``: {n: the paper's counts by
    number of contacts} to compare (:func:`packings.service.paper.paper_tables`), drawn as crosses
    in the colour of their n, for the n drawn.  Returns the figure."""
    series = {int(n): {int(m): int(c) for m, c in d.items() if c and c > 0} for n, d in by_n.items()}
    series = {n: d for n, d in series.items() if d}
    restricted = {int(n): int(m) for n, m in (restricted or {}).items() if int(n) in series}
    partial = {int(n) for n in partial if int(n) not in restricted}
    if not series:
        raise ValueError("no clusters to plot")
    theirs = {n: {int(m): int(c) for m, c in (paper or {}).get(n, {}).items() if c > 0} for n in series}
    fig, ax_ = _canvas(ax, size, dpi, path)
    ax_.set_yscale("log")
    ax_.axvline(0, color="0.6", lw=1, ls="--", zorder=1)
    markers = "osD^v<>ph*"
    for i, ((n, d), color) in enumerate(zip(sorted(series.items()), _colors(len(series)))):
        ms = sorted(d)
        ax_.plot(
            [m - (3 * n - 6) for m in ms],
            [d[m] for m in ms],
            marker=markers[i % len(markers)],
            ms=6,
            lw=1.5,
            color=color,
            zorder=3,
            label=f"n = {n} ({sum(d.values()):,}"
            + (f", ≥ {restricted[n]} contacts)" if n in restricted else ", partial)" if n in partial else ")"),
        )
        if theirs[n]:
            ps = sorted(theirs[n])
            ax_.plot(
                [m - (3 * n - 6) for m in ps], [theirs[n][m] for m in ps], "x", ms=9, mew=1.3, color=color, zorder=4
            )
    if any(theirs.values()):
        ax_.plot([], [], "x", ms=9, mew=1.3, color="0.3", label="the paper (Holmes-Cerfon 2016, Table 1)")
    excess = [m - (3 * n - 6) for n, d in (*series.items(), *theirs.items()) for m in d]
    lo, hi = min(min(excess), -1), max(max(excess), 1)
    ax_.set_xlim(lo - 0.5, hi + 0.5)
    _integer_ticks(ax_.xaxis, lo, hi)
    counts = [c for d in (*series.values(), *theirs.values()) for c in d.values()]
    ax_.set_ylim(min(counts) / 2, max(counts) * 2)
    _log_ticks(ax_.yaxis, min(counts) / 2, max(counts) * 2)
    ax_.set_xlabel("contacts − (3n − 6)    (0: isostatic)")
    ax_.set_ylabel("number of rigid clusters")
    ax_.set_title("Rigid clusters by number of contacts")
    ax_.grid(True, which="major", alpha=0.3)
    ax_.legend(title="n (clusters)", fontsize=8, title_fontsize=8, loc="best")
    return _done(fig, path, ax is None)


def plot_probabilities(
    kappas,
    by_contacts: dict[int, Sequence[float]],
    path: str | os.PathLike | None = None,
    *,
    n: int,
    width: float | None = None,
    singular: Sequence[float] | None = None,
    ax=None,
    size: tuple[float, float] | None = None,
    dpi: float | None = None,
):
    """Equilibrium probability against the sticky parameter κ (log x), one line per number of contacts m
    (:func:`packings.service.probabilities.curves`), and the singular clusters together, dashed, if given:
    the clusters with more contacts take over as κ grows, as κ^m.  ``width``: the square well's, named in
    the title (None: the sticky limit).  Returns the figure."""
    if not by_contacts:
        raise ValueError("no probabilities to plot")
    fig, ax_ = _canvas(ax, size, dpi, path)
    ax_.set_xscale("log")
    for (m, p), color in zip(sorted(by_contacts.items()), _colors(len(by_contacts))):
        ax_.plot(kappas, p, lw=1.8, color=color, label=f"{m} contacts")
    if singular is not None:
        ax_.plot(kappas, singular, lw=1.4, ls="--", color="0.25", label="singular clusters")
    ax_.set_xlim(min(kappas), max(kappas))
    ax_.set_ylim(-0.02, 1.02)
    ax_.set_xlabel("sticky parameter κ")
    ax_.set_ylabel("equilibrium probability")
    where = "sticky limit" if width is None else f"square well of width {width:g}"
    ax_.set_title(f"Clusters of {n} spheres in equilibrium ({where})")
    ax_.grid(True, which="major", alpha=0.3)
    ax_.legend(fontsize=8, loc="best")
    return _done(fig, path, ax is None)


def sphere_values(coords, contacts, color_by: str = "degree"):
    """Per-sphere values for :func:`plot_cluster` and their label: ``degree``
    (contacts of each sphere), ``height`` (z about the mean z) or ``distance``
    (from the centroid)."""
    import numpy as np

    x = np.asarray(coords, dtype=float)
    if color_by == "degree":
        pairs = np.asarray(list(contacts), dtype=int).reshape(-1, 2)
        values = np.bincount(pairs.ravel(), minlength=len(x)).astype(float)
    elif color_by == "height":
        values = x[:, 2] - x[:, 2].mean()
    elif color_by == "distance":
        values = np.linalg.norm(x - x.mean(axis=0), axis=1)
    else:
        raise ValueError(f"unknown property {color_by!r}: use one of {', '.join(COLOR_BY)}")
    return values, COLOR_BY[color_by]


def _towards_viewer(elev: float, azim: float):
    import numpy as np

    e, a = np.radians(elev), np.radians(azim)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


def best_view(coords, elevations=(15.0, 25.0, 35.0), step: float = 5.0) -> tuple[float, float]:
    """(elev, azim) in degrees, z up, under which the spheres hide each other
    least: the smallest sum over pairs of the overlap ``max(0, 1 − d)`` of their
    projected centres' distance d (in diameters); ties go to the first."""
    import numpy as np

    x = np.asarray(coords, dtype=float)
    best, where = np.inf, (elevations[0], -60.0)
    for elev in elevations:
        for azim in np.arange(-180.0, 180.0, step):
            eye = _towards_viewer(elev, azim)
            p = x - np.outer(x @ eye, eye)
            d = np.sqrt(((p[:, None, :] - p[None, :, :]) ** 2).sum(-1))
            hidden = np.triu(np.clip(1.0 - d, 0.0, None), k=1).sum()
            if hidden < best - 1e-9:
                best, where = hidden, (float(elev), float(azim))
    return where


def closest_pair(coords, contacts) -> tuple[int, int, float] | None:
    """(i, j, gap) of the two spheres not in contact that are closest, gap = their distance − 1 (in
    diameters); None if every pair touches (:meth:`packings.workers.cluster.Cluster.closest_pair`)."""
    import numpy as np

    from packings.workers.cluster import Cluster

    return Cluster(np.asarray(coords, dtype=float), tuple((int(i), int(j)) for i, j in contacts)).closest_pair()


def _checked(coords, contacts, values):
    """(centred n x 3 coordinates, contact pairs, per-sphere values or None), or ValueError."""
    import numpy as np

    x = np.asarray(coords, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3 or len(x) == 0:
        raise ValueError(f"coordinates must be n x 3 with n >= 1, got shape {x.shape}")
    n = len(x)
    pairs = [(int(i), int(j)) for i, j in contacts]
    if any(not (0 <= i < n and 0 <= j < n) for i, j in pairs):
        raise ValueError(f"a contact names a sphere outside 0..{n - 1}")
    if values is not None:
        values = np.asarray(values, dtype=float).reshape(-1)
        if len(values) != n:
            raise ValueError(f"values must have one entry per sphere ({n}), got {len(values)}")
    return x - x.mean(axis=0), pairs, values


def _color_scale(values):
    """(colour map, norm, ticks) for per-sphere values: integer values (contacts per sphere) get one
    colour each and integer ticks."""
    import numpy as np
    from matplotlib import colormaps
    from matplotlib.colors import BoundaryNorm, ListedColormap, Normalize

    lo, hi = float(np.min(values)), float(np.max(values))
    base = colormaps[CMAP]
    if np.allclose(values, np.round(values)) and hi - lo <= 24:
        levels = np.arange(round(lo), round(hi) + 1)
        cmap = ListedColormap(base(np.linspace(0.15, 0.95, len(levels)) if len(levels) > 1 else [0.6]))
        return cmap, BoundaryNorm(np.r_[levels - 0.5, levels[-1] + 0.5], cmap.N), levels
    if hi - lo < 1e-12:
        lo, hi = lo - 0.5, hi + 0.5
    return ListedColormap(base(np.linspace(0.15, 0.95, 256))), Normalize(lo, hi), None


def _draw_cluster(ax, x, pairs, values, cmap, norm, elev, azim, *, alpha, ghost, style, labels, gap, extent) -> None:
    """One cluster on 3D axes ``ax``, centred coordinates ``x``: see :func:`plot_cluster`."""
    import numpy as np

    radius = RADIUS if style == "spheres" else STICK_RADIUS
    # The view: towards the viewer (eye), right and up on the screen; the light from the upper left, in front.
    eye = _towards_viewer(elev, azim)
    a = np.radians(azim)
    right = np.array([-np.sin(a), np.cos(a), 0.0])
    up = np.cross(eye, right)
    light = -0.45 * right + 0.6 * up + 0.66 * eye
    light /= np.linalg.norm(light)
    half = light + eye
    half /= np.linalg.norm(half)

    # The hemisphere facing the viewer (a little more, so no gap shows at the rim), as unit normals.
    theta = np.linspace(0.0, np.radians(92.0), 15)[:, None]
    phi = np.linspace(0.0, 2 * np.pi, 49)[None, :]
    normals = np.cos(theta)[..., None] * eye + np.sin(theta)[..., None] * (
        np.cos(phi)[..., None] * right + np.sin(phi)[..., None] * up
    )
    # shading at the middle of each face (plot_surface takes the colour of a face from its first corner)
    mid = normals[:-1, :-1] + normals[1:, :-1] + normals[:-1, 1:] + normals[1:, 1:]
    mid /= np.linalg.norm(mid, axis=-1, keepdims=True)
    diffuse = np.clip(mid @ light, 0.0, None)
    specular = np.clip(mid @ half, 0.0, None) ** 24
    diffuse = np.pad(diffuse, ((0, 1), (0, 1)), mode="edge")[..., None]
    specular = np.pad(specular, ((0, 1), (0, 1)), mode="edge")[..., None]
    rim = np.cos(np.linspace(0, 2 * np.pi, 65))[:, None] * right + np.sin(np.linspace(0, 2 * np.pi, 65))[:, None] * up

    ax.view_init(elev=elev, azim=azim)
    n = len(x)
    items = [(float(x[i] @ eye), 0, i) for i in range(n)]
    items += [(float((x[i] + x[j]) @ eye / 2), 1, (i, j)) for i, j in pairs]
    for z, (_, kind, what) in enumerate(sorted(items, key=lambda t: (t[0], t[1]))):
        if kind == 0:
            c = x[what]
            rgb = np.asarray(cmap(norm(values[what]))[:3])
            shaded = np.clip(rgb * (0.42 + 0.58 * diffuse) + 0.45 * specular, 0.0, 1.0)
            colors = np.concatenate([shaded, np.full(shaded.shape[:2] + (1,), alpha)], axis=-1)
            p = c + radius * normals
            ax.plot_surface(
                p[..., 0],
                p[..., 1],
                p[..., 2],
                facecolors=colors,
                shade=False,
                linewidth=0,
                antialiased=False,
                rcount=theta.size,
                ccount=phi.size,
                zorder=z,
            )
            o = c + radius * rim
            ax.plot(o[:, 0], o[:, 1], o[:, 2], color=tuple(0.45 * rgb), lw=0.8, alpha=min(1.0, alpha + 0.2), zorder=z)
        else:
            i, j = what
            ax.plot(*zip(x[i], x[j]), color=STICK_COLOR, lw=3.0, solid_capstyle="round", zorder=z)
    _draw_over(ax, x, pairs, len(items) + 1, radius, eye, up, ghost=ghost, style=style, labels=labels, gap=gap)
    ax.set_xlim(-extent, extent)
    ax.set_ylim(-extent, extent)
    ax.set_zlim(-extent, extent)
    ax.set_box_aspect((1, 1, 1), zoom=1.6)
    ax.set_axis_off()


def _draw_over(ax, x, pairs, top: int, radius: float, eye, up, *, ghost, style, labels, gap) -> None:
    """What :func:`_draw_cluster` draws over the spheres and sticks, from depth ``top`` up: the sticks again,
    faint (``spheres`` style), the closest gap, the spheres' numbers."""
    from matplotlib import patheffects

    n = len(x)
    # every stick again, faint, over everything: the contacts hidden by the spheres in front show through
    if style == "spheres":
        for i, j in pairs:
            ax.plot(*zip(x[i], x[j]), color=STICK_COLOR, lw=2.2, alpha=ghost, solid_capstyle="round", zorder=top)
    outline = [patheffects.withStroke(linewidth=2.5, foreground="white")]
    if gap:
        near = closest_pair(x, pairs)
        if near is not None:
            i, j, g = near
            ax.plot(*zip(x[i], x[j]), color=GAP_COLOR, lw=1.6, ls="--", zorder=top + 1)
            at = (x[i] + x[j]) / 2 + 0.6 * radius * up
            ax.text(
                *at,
                f"gap {g:.3g}",
                color=GAP_COLOR,
                fontsize=8,
                ha="center",
                va="bottom",
                zorder=top + 2,
                path_effects=outline,
            )
    if labels:
        for i in range(n):
            ax.text(
                *(x[i] + 1.02 * radius * eye),
                str(i),
                fontsize=8 if style == "spheres" else 7,
                ha="center",
                va="center",
                color="black",
                zorder=top + 3,
                path_effects=outline,
            )


def _colorbar(fig, cmap, norm, ticks, label, **where) -> None:
    from matplotlib.cm import ScalarMappable

    bar = fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), ticks=ticks, **where)
    bar.outline.set_linewidth(0.5)
    if label:
        bar.set_label(label)


def _options(style: str) -> None:
    if style not in STYLES:
        raise ValueError(f"unknown style {style!r}: use one of {', '.join(STYLES)}")


def plot_cluster(
    coords,
    contacts,
    path: str | os.PathLike | None = None,
    values=None,
    label: str | None = None,
    title: str | None = None,
    elev: float | None = None,
    azim: float | None = None,
    alpha: float = 1.0,
    ghost: float = GHOST,
    *,
    style: str = "spheres",
    labels: bool = False,
    gap: bool = True,
    ax=None,
    size: tuple[float, float] | None = None,
    dpi: float | None = None,
):
    """A 3D picture of one cluster, each contact a stick between the two centres,
    spheres coloured by ``values`` (one per sphere; default the number of contacts
    of each sphere) with a colour bar labelled ``label`` (default "contacts per
    sphere" for the default values).  Returns the figure.

    ``style`` ``spheres`` draws the spheres to scale (radius 0.5); ``sticks``
    draws them small, so that every contact shows.  ``labels`` writes each
    sphere's number (its index in ``coords``).  ``gap`` draws the closest pair
    of spheres not in contact as a dashed line, with its gap (distance − 1).

    Orthographic view from (``elev``, ``azim``) degrees with z up, equal aspect
    ratio, no axes; by default (None) the view that hides the least, from
    :func:`best_view`.  Each sphere is the hemisphere facing the viewer, drawn with
    ``plot_surface`` (a 14 x 48 mesh) in colours shaded by a light from the upper
    left (ambient, diffuse and a specular highlight), outlined, and ``alpha``
    opaque.  The sticks lie inside the touching spheres: each is drawn in
    its place among the spheres (so those in front hide it) and, in the
    ``spheres`` style, again, faint (``ghost``), over everything, so the contacts
    behind spheres show through.  Spheres and sticks are drawn back to front by
    the depth of their centres (midpoints), which is right for equal spheres
    that do not overlap.  ``ax`` must be 3D axes (``projection="3d"``).

    (Over 80 lines by its options and this description only: the drawing is :func:`_draw_cluster`'s.)
    """
    import numpy as np

    _options(style)
    x, pairs, values = _checked(coords, contacts, values)
    if values is None:
        values, default_label = sphere_values(x, pairs, "degree")
        label = default_label if label is None else label
    if ax is not None and getattr(ax, "name", "") != "3d":
        raise ValueError("a cluster is drawn on 3D axes: make them with projection='3d'")
    cmap, norm, ticks = _color_scale(values)
    if elev is None or azim is None:
        best = best_view(x)
        elev, azim = best[0] if elev is None else elev, best[1] if azim is None else azim
    fig, ax_ = _canvas(ax, size, dpi, path, projection="3d", proj_type="ortho", computed_zorder=False)
    extent = float(np.max(np.linalg.norm(x, axis=1))) + RADIUS
    _draw_cluster(
        ax_,
        x,
        pairs,
        values,
        cmap,
        norm,
        elev,
        azim,
        alpha=alpha,
        ghost=ghost,
        style=style,
        labels=labels,
        gap=gap,
        extent=extent,
    )
    if ax is None:
        ax_.set_position([0.0, 0.0, 0.8, 0.93 if title else 1.0])
        _colorbar(fig, cmap, norm, ticks, label, cax=fig.add_axes([0.83, 0.22, 0.025, 0.56]))
        if title:
            fig.suptitle(title, y=0.96)
    else:
        _colorbar(fig, cmap, norm, ticks, label, ax=ax_, shrink=0.6)
        if title:
            ax_.set_title(title)
    if path is not None:
        save(fig, path)
    return fig


def aligned(clusters: Sequence[tuple]) -> list | None:
    """The coordinates of ``clusters`` ((coords, contacts) pairs) moved so that they lie as the first
    does, if they all have one contact graph: each is rotated and moved (no reflection) so that one
    contact triangle, the same in all under the graph's canonical labelling (nauty), lies where the
    first cluster's does.  None if their contact graphs differ (or have no triangle)."""
    import numpy as np
    from scipy.spatial.transform import Rotation

    from packings.workers.cluster import Cluster
    from packings.workers.identity import canonical_labelling, certificate_key

    cores = [Cluster(np.asarray(x, dtype=float), tuple((min(i, j), max(i, j)) for i, j in c)) for x, c in clusters]
    if len({(c.n, certificate_key(c)) for c in cores}) != 1:
        return None
    first = cores[0]
    p0 = canonical_labelling(first)
    rank = np.empty(first.n, dtype=np.int64)
    rank[p0] = np.arange(first.n)
    touching = {(int(rank[i]), int(rank[j])) for i, j in first.contacts}
    touching |= {(j, i) for i, j in touching}
    triangle = next(
        (
            (a, b, c)
            for a, b in sorted(touching)
            if a < b
            for c in range(b + 1, first.n)
            if (a, c) in touching and (b, c) in touching
        ),
        None,
    )
    if triangle is None:
        return None
    target = first.coords[p0[list(triangle)]]
    out = []
    for core in cores:
        x = core.coords
        src = x[canonical_labelling(core)[list(triangle)]]
        # the proper rotation taking the triangle (about its centroid) onto the target's (Kabsch, by scipy)
        rotation, _ = Rotation.align_vectors(target - target.mean(axis=0), src - src.mean(axis=0))
        out.append(rotation.apply(x - src.mean(axis=0)) + target.mean(axis=0))
    return out


def plot_clusters(
    clusters: Sequence[tuple],
    path: str | os.PathLike | None = None,
    *,
    values=None,
    label: str | None = None,
    titles: Sequence[str] | None = None,
    title: str | None = None,
    style: str = "spheres",
    labels: bool = False,
    gap: bool = True,
    align: bool = True,
    size: tuple[float, float] | None = None,
    dpi: float | None = None,
):
    """Several clusters ((coords, contacts) pairs) side by side, each as :func:`plot_cluster` draws one,
    at one scale and with one colour bar.  With ``align`` and one contact graph in all (say, the
    geometries of one graph), they are turned to lie alike (:func:`aligned`) and seen from the same
    view, so that their differences show.  ``values``: one array per cluster, default contacts per
    sphere.  The default size is 3.6 inches across per cluster (and a colour bar) by 4.2.  Returns
    the figure."""
    import numpy as np

    _options(style)
    if not clusters:
        raise ValueError("no clusters to plot")
    checked = [_checked(x, c, None) for x, c in clusters]
    if values is None:
        values = [sphere_values(x, pairs, "degree")[0] for x, pairs, _ in checked]
        label = COLOR_BY["degree"] if label is None else label
    values = [_checked(x, pairs, v)[2] for (x, pairs, _), v in zip(checked, values, strict=True)]
    if titles is not None and len(titles) != len(clusters):
        raise ValueError(f"{len(titles)} titles for {len(clusters)} clusters")
    moved = aligned([(x, pairs) for x, pairs, _ in checked]) if align and len(clusters) > 1 else None
    if moved is not None:
        centre = moved[0].mean(axis=0)
        xs = [x - centre for x in moved]
        view = best_view(xs[0])
        views = [view] * len(xs)
    else:
        xs = [x for x, _, _ in checked]
        views = [best_view(x) for x in xs]
    cmap, norm, ticks = _color_scale(np.concatenate(values))
    k = len(xs)
    if path is not None:
        figure_format(path)
    fig = new_figure(size or (3.6 * k + 1.0, 4.2), dpi)
    extent = max(float(np.max(np.linalg.norm(x, axis=1))) for x in xs) + RADIUS
    width = 0.88 / k
    for i, (x, (_, pairs, _), v, (elev, azim)) in enumerate(zip(xs, checked, values, views)):
        ax = fig.add_axes(
            [i * width, 0.0, width, 0.86 if title else 0.9], projection="3d", proj_type="ortho", computed_zorder=False
        )
        _draw_cluster(
            ax,
            x,
            pairs,
            v,
            cmap,
            norm,
            elev,
            azim,
            alpha=1.0,
            ghost=GHOST,
            style=style,
            labels=labels,
            gap=gap,
            extent=extent,
        )
        if titles is not None:
            ax.set_title(titles[i], fontsize=9)
    _colorbar(fig, cmap, norm, ticks, label, cax=fig.add_axes([0.9, 0.22, 0.018, 0.56]))
    if title:
        fig.suptitle(title, y=0.97)
    if path is not None:
        save(fig, path)
    return fig
