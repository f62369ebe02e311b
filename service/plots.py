"""Figures of the stored catalogue, as PNG files: ``packings plot ...``.

Two layers:

* pure figure functions, which take plain data and an output path and write
  one PNG: :func:`plot_counts`, :func:`plot_gap_cdf`, :func:`plot_by_contacts`
  and :func:`plot_cluster`;
* the ``plot`` click group (subcommands ``counts``, ``gaps``, ``contacts``,
  ``cluster ID`` and ``all``), which reads the data from the database and
  calls them.

Every PNG is :data:`WIDTH_IN` x :data:`HEIGHT_IN` inches at :data:`DPI` dots per
inch, that is :data:`SIZE_PX` = 960 x 720 pixels, whatever is in it (no tight
bounding box that would change the size).  Files are written to a temporary
name beside the target and renamed, so a failure never leaves a half-written
file and an existing file is replaced whole.

matplotlib is imported only inside the functions (``packings --help`` does not
load it), and figures are drawn on matplotlib's Agg canvas directly
(``matplotlib.figure.Figure`` with ``FigureCanvasAgg``), never through pyplot:
no display is needed and no global backend or figure state is touched, so the
functions are safe to call from a notebook or a thread.
"""

from __future__ import annotations

import contextlib
import os
from pathlib import Path

import click

from packings.fit import fit_factorial, predicted

WIDTH_IN, HEIGHT_IN, DPI = 6.4, 4.8, 150
SIZE_PX = (960, 720)  #: (width, height) in pixels of every PNG written here
RADIUS = 0.5  #: sphere radius: the unit of length is the sphere diameter
#: per-sphere properties a cluster picture can be coloured by, and their colour-bar labels
COLOR_BY = {
    "degree": "contacts per sphere",
    "height": "height z − mean z (diameters)",
    "distance": "distance from the centroid (diameters)",
}
CMAP = "viridis"  #: colour map of the cluster pictures (its darkest 15 % left out, for the sticks to show)
GHOST = 0.3  #: opacity of the contacts drawn through the spheres in a cluster picture
STICK_COLOR = "0.1"
DEFAULT_NAMES = {"counts": "counts.png", "gaps": "gaps.png", "contacts": "contacts.png"}


# --------------------------------------------------------------------------- writing


def _figure():
    """A blank figure of the fixed size on an Agg canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(WIDTH_IN, HEIGHT_IN), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def save_png(fig, path: str | os.PathLike) -> Path:
    """Write ``fig`` as a PNG of :data:`SIZE_PX` to a temporary file beside
    ``path``, then rename it over ``path``; on any failure nothing is left."""
    from packings.export import replace_file

    return replace_file(path, lambda f: fig.savefig(f, format="png", dpi=DPI), binary=True)


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


def plot_counts(totals: dict[int, int], path: str | os.PathLike) -> Path:
    """The number of clusters against n (log scale, one marker per n, the count
    written above it) with the fitted curve b·(n − 5)! of
    :func:`packings.fit.fit_factorial` (b in the legend)."""
    import numpy as np

    totals = {int(n): int(t) for n, t in totals.items() if t and t > 0}
    if not totals:
        raise ValueError("no clusters to plot")
    ns = sorted(totals)
    fig = _figure()
    ax = fig.add_subplot()
    ax.set_yscale("log")
    ax.plot(ns, [totals[n] for n in ns], "o", ms=7, color="C0", zorder=3, label="rigid clusters")
    for n in ns:
        ax.annotate(f"{totals[n]:,}", (n, totals[n]), textcoords="offset points", xytext=(0, 8), ha="center",
                    fontsize=8, color="0.25")
    fit = fit_factorial(totals)
    if fit is not None:
        xs = np.arange(max(min(ns), 5), max(ns) + 1)
        used = fit["ns"]
        over = f"n = {used[0]}" + (f"–{used[-1]}" if len(used) > 1 else "")
        ax.plot(xs, [predicted(fit["b"], x) for x in xs], "--", color="C1", lw=1.5, zorder=2,
                label=f"fit {fit['b']:.2f}·(n − 5)!  ({over})")
    ax.set_xlabel("n (spheres)")
    ax.set_ylabel("number of rigid clusters")
    ax.set_title("Rigid clusters of n spheres")
    ax.set_xlim(min(ns) - 0.6, max(ns) + 0.6)
    _integer_ticks(ax.xaxis, min(ns), max(ns))
    lo, hi = min(totals.values()), max(totals.values())
    ax.set_ylim(lo / 2, hi * 4)  # room for the counts above the markers
    _log_ticks(ax.yaxis, lo / 2, hi * 4)
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(loc="upper left")
    fig.tight_layout()
    return save_png(fig, path)


def plot_gap_cdf(gaps: dict[int, list[float]], path: str | os.PathLike) -> Path:
    """The cumulative distribution of the clusters' minimum gaps (the smallest
    distance between spheres not in contact, minus 1), one line per n, on a log
    x axis.  Gaps that are missing, not finite or not positive are left out."""
    import numpy as np

    series = {}
    for n, values in gaps.items():
        v = np.array([g for g in values if g is not None], dtype=float)
        v = np.sort(v[np.isfinite(v) & (v > 0)])
        if len(v):
            series[int(n)] = v
    if not series:
        raise ValueError("no minimum gaps to plot")
    fig = _figure()
    ax = fig.add_subplot()
    for (n, v), color in zip(sorted(series.items()), _colors(len(series))):
        k = len(v)
        x = np.r_[v[0], v]
        y = np.r_[0.0, np.arange(1, k + 1) / k]
        ax.step(x, y, where="post", color=color, lw=1.8, label=f"n = {n} ({k})")
    ax.set_xscale("log")
    lo, hi = min(v[0] for v in series.values()), max(v[-1] for v in series.values())
    ax.set_xlim(lo / 1.5, hi * 1.5)
    _log_ticks(ax.xaxis, lo / 1.5, hi * 1.5)
    ax.set_ylim(0, 1.03)
    ax.set_xlabel("minimum gap between spheres not in contact (diameters)")
    ax.set_ylabel("fraction of clusters with min gap ≤ x")
    ax.set_title("Minimum gaps: cumulative distribution")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(title="n (clusters)", loc="upper left", fontsize=8, title_fontsize=8)
    fig.tight_layout()
    return save_png(fig, path)


def plot_by_contacts(by_n: dict[int, dict[int, int]], path: str | os.PathLike) -> Path:
    """The number of clusters by number of contacts, one series per n, against
    contacts − (3n − 6) (0: isostatic; negative: hypostatic), log y."""
    series = {int(n): {int(m): int(c) for m, c in d.items() if c and c > 0} for n, d in by_n.items()}
    series = {n: d for n, d in series.items() if d}
    if not series:
        raise ValueError("no clusters to plot")
    fig = _figure()
    ax = fig.add_subplot()
    ax.set_yscale("log")
    ax.axvline(0, color="0.6", lw=1, ls="--", zorder=1)
    markers = "osD^v<>ph*"
    for i, ((n, d), color) in enumerate(zip(sorted(series.items()), _colors(len(series)))):
        ms = sorted(d)
        ax.plot([m - (3 * n - 6) for m in ms], [d[m] for m in ms], marker=markers[i % len(markers)], ms=6, lw=1.5,
                color=color, zorder=3, label=f"n = {n} ({sum(d.values()):,})")
    excess = [m - (3 * n - 6) for n, d in series.items() for m in d]
    lo, hi = min(min(excess), -1), max(max(excess), 1)
    ax.set_xlim(lo - 0.5, hi + 0.5)
    _integer_ticks(ax.xaxis, lo, hi)
    counts = [c for d in series.values() for c in d.values()]
    ax.set_ylim(min(counts) / 2, max(counts) * 2)
    _log_ticks(ax.yaxis, min(counts) / 2, max(counts) * 2)
    ax.set_xlabel("contacts − (3n − 6)    (0: isostatic)")
    ax.set_ylabel("number of rigid clusters")
    ax.set_title("Rigid clusters by number of contacts")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(title="n (clusters)", fontsize=8, title_fontsize=8, loc="best")
    fig.tight_layout()
    return save_png(fig, path)


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


def plot_cluster(coords, contacts, path: str | os.PathLike, values=None, label: str | None = None,
                 title: str | None = None, elev: float | None = None, azim: float | None = None,
                 alpha: float = 1.0, ghost: float = GHOST) -> Path:
    """A 3D picture of one cluster: spheres of radius 0.5 to scale, each contact a
    stick between the two centres, spheres coloured by ``values`` (one per
    sphere; default the number of contacts of each sphere) with a colour bar
    labelled ``label`` (default "contacts per sphere" for the default values).

    Orthographic view from (``elev``, ``azim``) degrees with z up, equal aspect
    ratio, no axes; by default (None) the view that hides the least, from
    :func:`best_view`.  Each sphere is the hemisphere facing the viewer, drawn with
    ``plot_surface`` (a 14 x 48 mesh) in colours shaded by a light from the upper
    left (ambient, diffuse and a specular highlight), outlined, and ``alpha``
    opaque.  The sticks lie inside the touching spheres: each is drawn in
    its place among the spheres (so those in front hide it) and again, faint
    (``ghost``), over everything, so the contacts behind spheres show through.
    Spheres and sticks are drawn back to front by the depth of their centres
    (midpoints), which is right for equal spheres that do not overlap.
    """
    import numpy as np
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import BoundaryNorm, ListedColormap, Normalize

    x = np.asarray(coords, dtype=float)
    if x.ndim != 2 or x.shape[1] != 3 or len(x) == 0:
        raise ValueError(f"coordinates must be n x 3 with n >= 1, got shape {x.shape}")
    n = len(x)
    pairs = [(int(i), int(j)) for i, j in contacts]
    if any(not (0 <= i < n and 0 <= j < n) for i, j in pairs):
        raise ValueError(f"a contact names a sphere outside 0..{n - 1}")
    if values is None:
        values, default_label = sphere_values(x, pairs, "degree")
        label = default_label if label is None else label
    values = np.asarray(values, dtype=float).reshape(-1)
    if len(values) != n:
        raise ValueError(f"values must have one entry per sphere ({n}), got {len(values)}")
    x = x - x.mean(axis=0)

    # Colours: integer values (e.g. contacts per sphere) get one colour each and integer ticks.
    lo, hi = float(values.min()), float(values.max())
    base = colormaps[CMAP]
    if np.allclose(values, np.round(values)) and hi - lo <= 24:
        levels = np.arange(round(lo), round(hi) + 1)
        cmap = ListedColormap(base(np.linspace(0.15, 0.95, len(levels)) if len(levels) > 1 else [0.6]))
        norm = BoundaryNorm(np.r_[levels - 0.5, levels[-1] + 0.5], cmap.N)
        ticks = levels
    else:
        if hi - lo < 1e-12:
            lo, hi = lo - 0.5, hi + 0.5
        cmap, norm, ticks = ListedColormap(base(np.linspace(0.15, 0.95, 256))), Normalize(lo, hi), None

    if elev is None or azim is None:
        best = best_view(x)
        elev, azim = best[0] if elev is None else elev, best[1] if azim is None else azim
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
    normals = (np.cos(theta)[..., None] * eye + np.sin(theta)[..., None]
               * (np.cos(phi)[..., None] * right + np.sin(phi)[..., None] * up))
    # shading at the middle of each face (plot_surface takes the colour of a face from its first corner)
    mid = normals[:-1, :-1] + normals[1:, :-1] + normals[:-1, 1:] + normals[1:, 1:]
    mid /= np.linalg.norm(mid, axis=-1, keepdims=True)
    diffuse = np.clip(mid @ light, 0.0, None)
    specular = np.clip(mid @ half, 0.0, None) ** 24
    diffuse = np.pad(diffuse, ((0, 1), (0, 1)), mode="edge")[..., None]
    specular = np.pad(specular, ((0, 1), (0, 1)), mode="edge")[..., None]
    rim = np.cos(np.linspace(0, 2 * np.pi, 65))[:, None] * right + np.sin(np.linspace(0, 2 * np.pi, 65))[:, None] * up

    fig = _figure()
    ax = fig.add_subplot(projection="3d", proj_type="ortho", computed_zorder=False)
    ax.view_init(elev=elev, azim=azim)
    items = [(float(x[i] @ eye), 0, i) for i in range(n)]
    items += [(float((x[i] + x[j]) @ eye / 2), 1, (i, j)) for i, j in pairs]
    for z, (_, kind, what) in enumerate(sorted(items, key=lambda t: (t[0], t[1]))):
        if kind == 0:
            c = x[what]
            rgb = np.asarray(cmap(norm(values[what]))[:3])
            shaded = np.clip(rgb * (0.42 + 0.58 * diffuse) + 0.45 * specular, 0.0, 1.0)
            colors = np.concatenate([shaded, np.full(shaded.shape[:2] + (1,), alpha)], axis=-1)
            p = c + RADIUS * normals
            ax.plot_surface(p[..., 0], p[..., 1], p[..., 2], facecolors=colors, shade=False, linewidth=0,
                            antialiased=False, rcount=theta.size, ccount=phi.size, zorder=z)
            o = c + RADIUS * rim
            ax.plot(o[:, 0], o[:, 1], o[:, 2], color=tuple(0.45 * rgb), lw=0.8, alpha=min(1.0, alpha + 0.2),
                    zorder=z)
        else:
            i, j = what
            ax.plot(*zip(x[i], x[j]), color=STICK_COLOR, lw=3.0, solid_capstyle="round", zorder=z)
    # every stick again, faint, over everything: the contacts hidden by the spheres in front show through
    for i, j in pairs:
        ax.plot(*zip(x[i], x[j]), color=STICK_COLOR, lw=2.2, alpha=ghost, solid_capstyle="round",
                zorder=len(items) + 1)

    r = float(np.max(np.linalg.norm(x, axis=1))) + RADIUS
    ax.set_xlim(-r, r)
    ax.set_ylim(-r, r)
    ax.set_zlim(-r, r)
    ax.set_box_aspect((1, 1, 1), zoom=1.6)
    ax.set_axis_off()
    ax.set_position([0.0, 0.0, 0.8, 0.93 if title else 1.0])
    cax = fig.add_axes([0.83, 0.22, 0.025, 0.56])
    bar = fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), cax=cax, ticks=ticks)
    bar.outline.set_linewidth(0.5)
    if label:
        bar.set_label(label)
    if title:
        fig.suptitle(title, y=0.96)
    return save_png(fig, path)


# --------------------------------------------------------------------------- the command line

db_option = click.option(
    "--db", "db_url", default=None, metavar="URL",
    help="Database URL (default: $PACKINGS_DB, else sqlite:///packings.db).",
)
n_option = click.option("--n", "ns", multiple=True, metavar="N[,N...]",
                        help="Only these n (repeat the option, or give a comma list).")


def _file_option(default_name: str):
    return click.option("-o", "--output", default=None, metavar="PATH",
                        help=f"The .png file to write (replaced whole), or an existing directory to write "
                             f"{default_name} in; default ./{default_name}.")


def parse_ns(values) -> set[int] | None:
    """The n given with ``--n`` (repeated and/or comma lists); None if none."""
    out: set[int] = set()
    for value in values:
        for part in str(value).split(","):
            part = part.strip()
            try:
                out.add(int(part))
            except ValueError:
                raise click.BadParameter(f"{part!r} is not an integer (give e.g. --n 9 or --n 8,9,10)",
                                         param_hint="'--n'") from None
    return out or None


def _output_file(output: str | None, default_name: str) -> Path:
    path = Path(output) if output else Path(default_name)
    if output and path.is_dir():
        path = path / default_name
    if path.suffix.lower() != ".png":
        raise click.ClickException(f"cannot write {path}: only PNG is written; give a name ending in .png")
    parent = path.parent
    if not parent.is_dir():
        raise click.ClickException(f"cannot write {path}: directory {parent} does not exist")
    return path


def _output_dir(output: str | None) -> Path:
    path = Path(output) if output else Path(".")
    if not path.exists():
        raise click.ClickException(f"cannot write to {path}: directory does not exist")
    if not path.is_dir():
        raise click.ClickException(f"cannot write to {path}: not a directory")
    return path


@contextlib.contextmanager
def _reading(db_url: str | None):
    """A read-only session on an existing database (``packings show``'s), with
    database errors as one-line click errors (the message ``packings``' main
    prints for them), so the group reports them alike on its own."""
    from sqlalchemy.exc import SQLAlchemyError

    from packings.api import connect
    from packings.db import first_line
    from packings.errors import PackingsError

    try:
        with connect(db_url) as cat, cat.session() as s:
            yield s
    except PackingsError as e:
        raise click.ClickException(str(e)) from None
    except SQLAlchemyError as e:
        raise click.ClickException(f"database: {first_line(e)}") from None


def load_counts(s, ns: set[int] | None) -> dict[int, dict[int, int]]:
    """{n: {contacts: clusters}} of the stored clusters (only ``ns`` if given)."""
    from packings.store import counts_by_n

    if ns is None:
        return counts_by_n(s)
    out: dict[int, dict[int, int]] = {}
    for n in sorted(ns):
        out.update(counts_by_n(s, n))
    return out


def load_gaps(s, ns: set[int] | None) -> dict[int, list[float]]:
    """{n: [min_gap, ...]} of the stored clusters that have one (only ``ns`` if given)."""
    from sqlalchemy import select

    from packings.models import ClusterRow

    q = select(ClusterRow.n, ClusterRow.min_gap).where(ClusterRow.min_gap.is_not(None))
    if ns is not None:
        q = q.where(ClusterRow.n.in_(sorted(ns)))
    out: dict[int, list[float]] = {}
    for n, gap in s.execute(q.order_by(ClusterRow.n, ClusterRow.min_gap)):
        out.setdefault(int(n), []).append(float(gap))
    return out


def _nothing(ns: set[int] | None, what: str = "clusters") -> str:
    where = f" with n = {', '.join(map(str, sorted(ns)))}" if ns else ""
    return f"no {what}{where} in the database" + ("" if ns else ": run `packings enumerate N` first")


def _write(draw, *args, path: Path) -> None:
    try:
        draw(*args, path)
    except OSError as e:
        raise click.ClickException(f"cannot write {path}: {e.strerror or e}") from None
    click.echo(str(path))


@click.group("plot", context_settings={"help_option_names": ["-h", "--help"]})
def plot() -> None:
    """Draw figures of the stored clusters as PNG files (960 x 720 pixels).

    Each command prints the path of every file it wrote.
    """


@plot.command("counts", short_help="Clusters against n, log scale, with the fit b·(n − 5)!.")
@db_option
@n_option
@_file_option(DEFAULT_NAMES["counts"])
def counts_cmd(db_url: str | None, ns: tuple[str, ...], output: str | None) -> None:
    """The number of stored clusters against n (log scale), with the fit b·(n − 5)!."""
    ns_ = parse_ns(ns)
    path = _output_file(output, DEFAULT_NAMES["counts"])
    with _reading(db_url) as s:
        counts = load_counts(s, ns_)
    if not counts:
        raise click.ClickException(_nothing(ns_))
    _write(plot_counts, {n: sum(d.values()) for n, d in counts.items()}, path=path)


@plot.command("gaps", short_help="Cumulative distribution of the minimum gaps, one line per n.")
@db_option
@n_option
@_file_option(DEFAULT_NAMES["gaps"])
def gaps_cmd(db_url: str | None, ns: tuple[str, ...], output: str | None) -> None:
    """The cumulative distribution of the clusters' minimum gaps, one line per n."""
    ns_ = parse_ns(ns)
    path = _output_file(output, DEFAULT_NAMES["gaps"])
    with _reading(db_url) as s:
        gaps = load_gaps(s, ns_)
    if not gaps:
        raise click.ClickException(_nothing(ns_, "clusters with a minimum gap"))
    _write(plot_gap_cdf, gaps, path=path)


@plot.command("contacts", short_help="Clusters by contacts − (3n − 6), one series per n.")
@db_option
@n_option
@_file_option(DEFAULT_NAMES["contacts"])
def contacts_cmd(db_url: str | None, ns: tuple[str, ...], output: str | None) -> None:
    """The number of stored clusters by contacts − (3n − 6), one series per n."""
    ns_ = parse_ns(ns)
    path = _output_file(output, DEFAULT_NAMES["contacts"])
    with _reading(db_url) as s:
        counts = load_counts(s, ns_)
    if not counts:
        raise click.ClickException(_nothing(ns_))
    _write(plot_by_contacts, counts, path=path)


@plot.command("cluster", short_help="One cluster in 3D: spheres to scale, contacts as sticks.")
@click.argument("cluster_id", metavar="ID", type=int)
@db_option
@click.option("--color-by", type=click.Choice(list(COLOR_BY)), default="degree", show_default=True,
              help="Colour the spheres by their number of contacts (degree), height z, or distance from the "
                   "centroid.")
@click.option("-o", "--output", default=None, metavar="PATH",
              help="The .png file to write (replaced whole), or an existing directory; default ./cluster-ID.png.")
def cluster_cmd(cluster_id: int, db_url: str | None, color_by: str, output: str | None) -> None:
    """Cluster ID in 3D: spheres to scale, contacts as sticks, coloured by a per-sphere property."""
    from packings.models import ClusterRow

    path = _output_file(output, f"cluster-{cluster_id}.png")
    with _reading(db_url) as s:
        c = s.get(ClusterRow, cluster_id)
        if c is None:
            raise click.ClickException(f"no cluster with id {cluster_id}")
        core, n, m = c.to_core(), c.n, c.contacts
    values, label = sphere_values(core.coords, core.contacts, color_by)
    title = f"cluster {cluster_id}: n = {n}, {m} contacts (3n−6{m - (3 * n - 6):+d})"
    try:
        plot_cluster(core.coords, core.contacts, path, values=values, label=label, title=title)
    except OSError as e:
        raise click.ClickException(f"cannot write {path}: {e.strerror or e}") from None
    click.echo(str(path))


@plot.command("all", short_help="counts.png, gaps.png and contacts.png into a directory.")
@db_option
@n_option
@click.option("-o", "--output", default=None, metavar="DIR",
              help="An existing directory to write counts.png, gaps.png and contacts.png in (each replaced "
                   "whole); default the current directory.")
def all_cmd(db_url: str | None, ns: tuple[str, ...], output: str | None) -> None:
    """counts.png, gaps.png and contacts.png, from one read of the database."""
    ns_ = parse_ns(ns)
    directory = _output_dir(output)
    with _reading(db_url) as s:
        counts, gaps = load_counts(s, ns_), load_gaps(s, ns_)
    if not counts:
        raise click.ClickException(_nothing(ns_))
    _write(plot_counts, {n: sum(d.values()) for n, d in counts.items()}, path=directory / DEFAULT_NAMES["counts"])
    if gaps:
        _write(plot_gap_cdf, gaps, path=directory / DEFAULT_NAMES["gaps"])
    else:  # only clusters in which every pair touches (n <= 4)
        click.echo(f"packings: warning: {_nothing(ns_, 'clusters with a minimum gap')}; "
                   f"{DEFAULT_NAMES['gaps']} not written", err=True)
    _write(plot_by_contacts, counts, path=directory / DEFAULT_NAMES["contacts"])
