"""``packings plot ...``: the click group that draws the figures of :mod:`packings.service.plots` from the
database (subcommands ``counts``, ``gaps``, ``contacts``, ``probabilities N``, ``cluster ID ...`` and
``all``), the data read through :mod:`packings.service.queries` on a read-only session of
:func:`packings.service.api.connect`.  Registered under ``packings`` by :mod:`packings.service.cli`.

Loaded by every ``packings`` command (the group's options are read at import): it imports neither
matplotlib nor SQLAlchemy when it is loaded, only when a command draws or reads.
"""

from __future__ import annotations

import contextlib
from pathlib import Path

import click

from packings.service import plots
from packings.service.api import connect
from packings.service.errors import PackingsError
from packings.service.options import db_option, width_option
from packings.service.paper import paper_tables, paper_totals

DEFAULT_NAMES = {
    "counts": "counts.png",
    "gaps": "gaps.png",
    "contacts": "contacts.png",
    "probabilities": "probabilities.png",
}
KAPPAS = (0.1, 1e4)  #: the sticky parameters ``plot probabilities`` spans by default


n_option = click.option(
    "--n", "ns", multiple=True, metavar="N[,N...]", help="Only these n (repeat the option, or give a comma list)."
)


def _file_option(default_name: str):
    return click.option(
        "-o",
        "--output",
        default=None,
        metavar="PATH",
        help=f"The file to write (replaced whole), .png, .pdf or .svg by its name, or an existing "
        f"directory to write {default_name} in; default ./{default_name}.",
    )


def _parse_size(ctx, param, value: str | None) -> tuple[float, float] | None:
    if value is None:
        return None
    try:
        w, h = (float(v) for v in value.lower().replace("×", "x").split("x"))
    except ValueError:
        raise click.BadParameter(f"{value!r} is not WIDTHxHEIGHT in inches (e.g. 3.4x2.6)") from None
    if not (0 < w <= 100 and 0 < h <= 100):
        raise click.BadParameter(f"{value!r}: width and height must be more than 0 and at most 100 inches")
    return w, h


def _figure_options(f):
    """--size and --dpi, passed to the command as ``size`` and ``dpi``."""
    f = click.option(
        "--dpi",
        type=click.IntRange(10, 2400),
        default=None,
        help=f"Dots per inch of a PNG (and of the pictures inside a PDF or SVG)  [default: {plots.DPI}]",
    )(f)
    return click.option(
        "--size",
        default=None,
        metavar="WxH",
        callback=_parse_size,
        help=f"Figure size in inches, e.g. 3.4x2.6  [default: {plots.SIZE[0]}x{plots.SIZE[1]}; a row of clusters: "
        f"3.6 per cluster + 1 by 4.2]",
    )(f)


def parse_ns(values) -> set[int] | None:
    """The n given with ``--n`` (repeated and/or comma lists); None if none."""
    out: set[int] = set()
    for value in values:
        for part in str(value).split(","):
            part = part.strip()
            try:
                out.add(int(part))
            except ValueError:
                raise click.BadParameter(
                    f"{part!r} is not an integer (give e.g. --n 9 or --n 8,9,10)", param_hint="'--n'"
                ) from None
    return out or None


def _output_file(output: str | None, default_name: str) -> Path:
    path = Path(output) if output else Path(default_name)
    if output and path.is_dir():
        path = path / default_name
    try:
        plots.figure_format(path)
    except ValueError as e:
        raise click.ClickException(str(e)) from None
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
    from sqlalchemy.exc import SQLAlchemyError  # SQLAlchemy: not loaded by `packings --help`

    from packings.service.db import first_line

    try:
        with connect(db_url) as cat, cat.session() as s:
            yield s
    except PackingsError as e:
        raise click.ClickException(str(e)) from None
    except SQLAlchemyError as e:
        raise click.ClickException(f"database: {first_line(e)}") from None


def _counts(s, ns: set[int] | None) -> dict[int, dict[int, int]]:
    """{n: {contacts: clusters}} of the stored clusters (only ``ns`` if given)."""
    from packings.service.queries import counts_by_n  # SQLAlchemy: not loaded by `packings --help`

    if ns is None:
        return counts_by_n(s)
    out: dict[int, dict[int, int]] = {}
    for n in sorted(ns):
        out.update(counts_by_n(s, n))
    return out


def _incomplete(s) -> tuple[dict[int, int], set[int]]:
    """{n: M} of the n held only by runs restricted by --min-contacts, and the n whose counts are partial."""
    from packings.service.queries import incomplete_ns  # SQLAlchemy: not loaded by `packings --help`

    return incomplete_ns(s)


def _gaps(s, ns: set[int] | None) -> dict[int, list[float]]:
    """{n: [min_gap, ...]} of the stored clusters that have one (only ``ns`` if given)."""
    from packings.service.queries import min_gaps  # SQLAlchemy: not loaded by `packings --help`

    return min_gaps(s, ns)


def _nothing(ns: set[int] | None, what: str = "clusters") -> str:
    where = f" with n = {', '.join(map(str, sorted(ns)))}" if ns else ""
    return f"no {what}{where} in the database" + ("" if ns else ": run `packings enumerate N` first")


def _write(draw, *args, path: Path, **options) -> None:
    try:
        draw(*args, path, **options)
    except OSError as e:
        raise click.ClickException(f"cannot write {path}: {e.strerror or e}") from None
    click.echo(str(path))


@click.group("plot", context_settings={"help_option_names": ["-h", "--help"]})
def plot() -> None:
    """Draw figures of the stored clusters as PNG, PDF or SVG files (by the file name).

    A figure is 6.4 x 4.8 inches at 150 dots per inch (a PNG of 960 x 720 pixels)
    unless --size and --dpi say otherwise.  Each command prints the path of every
    file it wrote.
    """


@plot.command("counts", short_help="Clusters against n, log scale, with the fit b·(n − 5)!.")
@db_option
@n_option
@_file_option(DEFAULT_NAMES["counts"])
@_figure_options
def counts_cmd(db_url: str | None, ns: tuple[str, ...], output: str | None, size, dpi) -> None:
    """The number of stored clusters against n (log scale), with the fit b·(n − 5)!."""
    ns_ = parse_ns(ns)
    path = _output_file(output, DEFAULT_NAMES["counts"])
    with _reading(db_url) as s:
        counts, (restricted, partial) = _counts(s, ns_), _incomplete(s)
    if not counts:
        raise click.ClickException(_nothing(ns_))
    _write(
        plots.plot_counts,
        {n: sum(d.values()) for n, d in counts.items()},
        path=path,
        restricted=restricted,
        partial=partial,
        size=size,
        dpi=dpi,
        paper=paper_totals(counts, restricted),
    )


@plot.command("gaps", short_help="Cumulative distribution of the minimum gaps, one line per n.")
@db_option
@n_option
@_file_option(DEFAULT_NAMES["gaps"])
@_figure_options
def gaps_cmd(db_url: str | None, ns: tuple[str, ...], output: str | None, size, dpi) -> None:
    """The cumulative distribution of the clusters' minimum gaps, one line per n."""
    ns_ = parse_ns(ns)
    path = _output_file(output, DEFAULT_NAMES["gaps"])
    with _reading(db_url) as s:
        gaps = _gaps(s, ns_)
    if not gaps:
        raise click.ClickException(_nothing(ns_, "clusters with a minimum gap"))
    _write(plots.plot_gap_cdf, gaps, path=path, size=size, dpi=dpi)


@plot.command("contacts", short_help="Clusters by contacts − (3n − 6), one series per n.")
@db_option
@n_option
@_file_option(DEFAULT_NAMES["contacts"])
@_figure_options
def contacts_cmd(db_url: str | None, ns: tuple[str, ...], output: str | None, size, dpi) -> None:
    """The number of stored clusters by contacts − (3n − 6), one series per n."""
    ns_ = parse_ns(ns)
    path = _output_file(output, DEFAULT_NAMES["contacts"])
    with _reading(db_url) as s:
        counts, (restricted, partial) = _counts(s, ns_), _incomplete(s)
    if not counts:
        raise click.ClickException(_nothing(ns_))
    _write(
        plots.plot_by_contacts,
        counts,
        path=path,
        restricted=restricted,
        partial=partial,
        size=size,
        dpi=dpi,
        paper=paper_tables(counts, restricted),
    )


@plot.command("probabilities", short_help="Equilibrium probability against κ, by number of contacts.")
@click.argument("n", type=int)
@db_option
@width_option
@click.option(
    "--kappa",
    "kappa_range",
    type=click.FloatRange(min=0.0, min_open=True),
    nargs=2,
    default=KAPPAS,
    show_default=True,
    metavar="LO HI",
    help="The range of the sticky parameter κ (log scale).",
)
@_file_option(DEFAULT_NAMES["probabilities"])
@_figure_options
def probabilities_cmd(
    n: int, db_url: str | None, width: float | None, kappa_range, output: str | None, size, dpi
) -> None:
    """The equilibrium probability of the stored clusters of N against the sticky parameter κ, by number of
    contacts, from their partition functions (`packings stats --kappa` gives the numbers at one κ)."""
    import numpy as np  # numpy, and SQLAlchemy through probabilities: not loaded by `packings --help`

    from packings.service.probabilities import curves

    lo, hi = kappa_range
    if not lo < hi:
        raise click.BadParameter(f"{lo:g} {hi:g}: LO must be below HI", param_hint="'--kappa'")
    path = _output_file(output, DEFAULT_NAMES["probabilities"])
    kappas = np.geomspace(lo, hi, 200)
    with _reading(db_url) as s:
        got = curves(s, n, kappas, width)
    _write(
        plots.plot_probabilities,
        kappas,
        got["by_contacts"],
        path=path,
        n=n,
        width=width,
        singular=got["singular"],
        size=size,
        dpi=dpi,
    )


@plot.command("cluster", short_help="Clusters in 3D, side by side: spheres, contacts, the closest gap.")
@click.argument("cluster_ids", metavar="ID...", type=int, nargs=-1, required=True)
@db_option
@click.option(
    "--color-by",
    type=click.Choice(list(plots.COLOR_BY)),
    default="degree",
    show_default=True,
    help="Colour the spheres by their number of contacts (degree), height z, or distance from the centroid.",
)
@click.option(
    "--style",
    type=click.Choice(plots.STYLES),
    default="spheres",
    show_default=True,
    help="spheres: to scale; sticks: small spheres, so that every contact shows.",
)
@click.option("--labels", is_flag=True, help="Number the spheres (as in the cluster's coordinates and contacts).")
@click.option(
    "-o",
    "--output",
    default=None,
    metavar="PATH",
    help="The file to write (replaced whole), .png, .pdf or .svg by its name, or an existing directory; "
    "default ./cluster-ID[-ID...].png.",
)
@_figure_options
def cluster_cmd(
    cluster_ids: tuple[int, ...],
    db_url: str | None,
    color_by: str,
    style: str,
    labels: bool,
    output: str | None,
    size,
    dpi,
) -> None:
    """Clusters ID... in 3D, side by side: spheres coloured by a per-sphere property, contacts as sticks,
    and the closest pair of spheres not in contact dashed, with its gap.  Clusters with one contact
    graph (the geometries of one graph, say) are turned to lie alike on a common contact triangle
    and seen from the same view."""
    from packings.service.models import ClusterRow  # SQLAlchemy: not loaded by `packings --help`

    path = _output_file(output, "cluster-" + "-".join(map(str, cluster_ids)) + ".png")
    rows = []
    with _reading(db_url) as s:
        for cid in cluster_ids:
            c = s.get(ClusterRow, cid)
            if c is None:
                raise click.ClickException(f"no cluster with id {cid}")
            rows.append((cid, c.to_core(), c.n, c.contacts, c.embedding))
    clusters = [(core.coords, core.contacts) for _, core, *_ in rows]
    values, label = zip(*(plots.sphere_values(x, pairs, color_by) for x, pairs in clusters))
    titles = [f"cluster {cid}: n = {n}, {m} contacts (3n−6{m - (3 * n - 6):+d})" for cid, _, n, m, _ in rows]
    try:
        if len(rows) == 1:
            plots.plot_cluster(
                *clusters[0],
                path,
                values=values[0],
                label=label[0],
                title=titles[0],
                style=style,
                labels=labels,
                size=size,
                dpi=dpi,
            )
        else:
            same = plots.aligned(clusters) is not None
            if same:
                titles = [f"cluster {cid} (embedding {e})" for cid, _, _, _, e in rows]
            n, m = rows[0][2], rows[0][3]
            plots.plot_clusters(
                clusters,
                path,
                values=values,
                label=label[0],
                titles=titles,
                title=f"one contact graph: n = {n}, {m} contacts, aligned on a contact triangle" if same else None,
                style=style,
                labels=labels,
                size=size,
                dpi=dpi,
            )
    except OSError as e:
        raise click.ClickException(f"cannot write {path}: {e.strerror or e}") from None
    click.echo(str(path))


@plot.command("all", short_help="counts, gaps and contacts figures into a directory.")
@db_option
@n_option
@click.option(
    "-o",
    "--output",
    default=None,
    metavar="DIR",
    help="An existing directory to write counts.png, gaps.png and contacts.png in (each replaced "
    "whole); default the current directory.",
)
@click.option(
    "--format",
    "fmt",
    type=click.Choice(plots.FORMATS),
    default="png",
    show_default=True,
    help="Write counts.FORMAT, gaps.FORMAT and contacts.FORMAT.",
)
@_figure_options
def all_cmd(db_url: str | None, ns: tuple[str, ...], output: str | None, fmt: str, size, dpi) -> None:
    """counts.png, gaps.png and contacts.png (or .pdf, .svg), from one read of the database."""
    names = {k: Path(v).with_suffix("." + fmt).name for k, v in DEFAULT_NAMES.items()}
    ns_ = parse_ns(ns)
    directory = _output_dir(output)
    with _reading(db_url) as s:
        counts, gaps, (restricted, partial) = _counts(s, ns_), _gaps(s, ns_), _incomplete(s)
    if not counts:
        raise click.ClickException(_nothing(ns_))
    options = {"size": size, "dpi": dpi}
    _write(
        plots.plot_counts,
        {n: sum(d.values()) for n, d in counts.items()},
        path=directory / names["counts"],
        restricted=restricted,
        partial=partial,
        paper=paper_totals(counts, restricted),
        **options,
    )
    if gaps:
        _write(plots.plot_gap_cdf, gaps, path=directory / names["gaps"], **options)
    else:  # only clusters in which every pair touches (n <= 4)
        click.echo(
            f"packings: warning: {_nothing(ns_, 'clusters with a minimum gap')}; {names['gaps']} not written", err=True
        )
    _write(
        plots.plot_by_contacts,
        counts,
        path=directory / names["contacts"],
        restricted=restricted,
        partial=partial,
        paper=paper_tables(counts, restricted),
        **options,
    )
