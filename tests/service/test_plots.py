"""Figures (packings.service.plots): the pure figure functions on synthetic data, and
``packings plot ...`` on a filled catalogue (SQLite and PostgreSQL)."""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import click
import numpy as np
import pytest
from click.testing import CliRunner
from PIL import Image
from sqlalchemy import select

from packings.service.models import ClusterRow
from packings.service.plot_commands import plot
from packings.service.plots import (
    aligned,
    best_view,
    closest_pair,
    plot_by_contacts,
    plot_cluster,
    plot_clusters,
    plot_counts,
    plot_gap_cdf,
    save,
    sphere_values,
)
from tests.helpers import fill_database, filled_catalog, two_geometries

catalog = filled_catalog(7, 8)

PAPER_BY_CONTACTS = {
    5: {9: 1},
    6: {12: 2},
    7: {15: 5},
    8: {18: 13},
    9: {21: 52},
    10: {23: 1, 24: 259, 25: 3},
    11: {25: 2, 26: 18, 27: 1618, 28: 20, 29: 1},
}
S = 1 / math.sqrt(2)
OCTAHEDRON = np.array([[S, 0, 0], [-S, 0, 0], [0, S, 0], [0, -S, 0], [0, 0, S], [0, 0, -S]])
OCTAHEDRON_CONTACTS = [(i, j) for i in range(6) for j in range(i + 1, 6) if j != i + 1 or i % 2]


def pixels(path, size=(960, 720)) -> np.ndarray:
    """The PNG's pixels, after checking it has ``size`` (the default figure's) and is not a single flat
    colour."""
    with Image.open(path) as im:
        assert im.format == "PNG"
        assert im.size == size
        a = np.asarray(im.convert("RGB"), dtype=float)
    assert a.std() > 0
    return a


def drawn(draw, *args, path, **kw) -> np.ndarray:
    """Draw to ``path`` and return its pixels; the function returns the figure it wrote."""
    from matplotlib.figure import Figure

    assert isinstance(draw(*args, path, **kw), Figure)
    return pixels(path)


def files(directory: Path) -> list[str]:
    return sorted(p.name for p in directory.iterdir())


def invoke(*args):
    """``packings plot ARGS`` through the click group itself (as `main` would run it once registered)."""
    return CliRunner().invoke(plot, [str(a) for a in args], catch_exceptions=False)


def one_line_error(r, *words, code: int = 1):
    assert r.exit_code == code, (r.exit_code, r.stdout, r.stderr)
    assert r.stdout == ""
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("Error: "), r.stderr
    assert all(w in lines[0] for w in words), lines[0]


# --------------------------------------------------------------------------- the pure functions


def test_plot_counts(tmp_path):
    drawn(plot_counts, {n: sum(d.values()) for n, d in PAPER_BY_CONTACTS.items()}, path=tmp_path / "counts.png")
    drawn(plot_counts, {4: 1}, path=tmp_path / "one.png")  # nothing to fit: markers only
    assert files(tmp_path) == ["counts.png", "one.png"]


def test_the_counts_figure_draws_the_papers_counts_where_asked():
    """Crosses at the paper's counts for the n drawn (not for an n the catalogue lacks), in the legend."""
    fig = plot_counts({7: 5, 8: 12, 9: 40}, restricted={9: 21}, paper={6: 2, 7: 5, 8: 13, 9: 52})
    [ax] = fig.axes
    [crosses] = [line for line in ax.get_lines() if line.get_marker() == "x"]
    assert list(crosses.get_xdata()) == [7, 8, 9] and list(crosses.get_ydata()) == [5, 13, 52]
    assert "the paper (Holmes-Cerfon 2016, Table 1)" in [t.get_text() for t in ax.get_legend().get_texts()]
    [ax] = plot_counts({7: 5}).axes
    assert not [line for line in ax.get_lines() if line.get_marker() == "x"]


def test_the_contacts_figure_draws_the_papers_counts_in_the_colour_of_their_n():
    """n = 10 drawn with one cluster fewer than the paper at 24 contacts: the paper's three points as crosses
    of n = 10's colour, the one the catalogue lacks (23) included; n = 9, which the paper's data given lacks,
    has none."""
    fig = plot_by_contacts({9: {21: 52}, 10: {24: 258, 25: 3}}, paper={10: {23: 1, 24: 259, 25: 3}})
    [ax] = fig.axes
    lines = [line for line in ax.get_lines() if len(line.get_xdata())]
    [crosses] = [line for line in lines if line.get_marker() == "x"]
    [ten] = [line for line in lines if line.get_label().startswith("n = 10")]
    assert list(crosses.get_xdata()) == [-1, 0, 1] and list(crosses.get_ydata()) == [1, 259, 3]
    assert crosses.get_color() == ten.get_color()
    assert ax.get_xlim()[0] <= -1.5
    assert "the paper (Holmes-Cerfon 2016, Table 1)" in [t.get_text() for t in ax.get_legend().get_texts()]
    [ax] = plot_by_contacts({9: {21: 52}}).axes
    assert not [line for line in ax.get_lines() if line.get_marker() == "x"]


def test_the_contacts_figure_says_which_n_were_counted_from_m_contacts_up():
    """An n only restricted runs hold is labelled with its M, as in the counts figure; a full n is not, and an
    M given for an n not drawn is ignored."""
    fig = plot_by_contacts(
        {10: {24: 259}, 14: {39: 79, 40: 4}}, restricted={14: 39, 15: 43}, paper={14: {39: 79, 40: 4}}
    )
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert "n = 14 (83, ≥ 39 contacts)" in labels and "n = 10 (259)" in labels
    assert not [label for label in labels if "15" in label]


def test_the_commands_compare_with_the_paper_from_the_fewest_contacts_kept(catalog, monkeypatch, tmp_path):
    """`plot counts`, `plot contacts` and `plot all` pass the paper's counts of the n they draw, from M
    contacts up for an n only restricted runs hold."""
    from packings.service import plots
    from packings.service.paper import paper_tables, paper_totals

    assert paper_totals([7, 8, 9, 15], {9: 21}) == {7: 5, 8: 13, 9: 52}
    assert paper_totals([10, 14], {10: 24, 14: 39}) == {10: 262, 14: 83}
    assert paper_tables([10, 14, 15], {14: 39}) == {10: {23: 1, 24: 259, 25: 3}, 14: {39: 79, 40: 4}}
    seen = []
    for name in ("plot_counts", "plot_by_contacts"):
        real = getattr(plots, name)
        monkeypatch.setattr(plots, name, lambda *a, _real=real, **kw: seen.append(kw["paper"]) or _real(*a, **kw))
    assert invoke("counts", "--db", catalog.url, "-o", tmp_path / "c.png").exit_code == 0
    assert invoke("contacts", "--db", catalog.url, "-o", tmp_path / "k.png").exit_code == 0
    assert invoke("all", "--db", catalog.url, "-o", tmp_path).exit_code == 0
    totals, tables = {7: 5, 8: 13}, {7: {15: 5}, 8: {18: 13}}
    assert seen == [totals, tables, totals, tables]


def test_the_counts_figure_leaves_partial_counts_out_of_the_fit():
    """n = 9 partial (no run of it complete): hollow, "(partial)" under its count, and the fit is of n = 7 and
    8 alone, as without n = 9; n = 10 restricted stays as it was."""
    fig = plot_counts({7: 5, 8: 13, 9: 20, 10: 262}, restricted={10: 24}, partial={9, 10})
    [ax] = fig.axes
    labels = [t.get_text() for t in ax.get_legend().get_texts()]
    [alone] = [
        t
        for t in (t.get_text() for t in plot_counts({7: 5, 8: 13}).axes[0].get_legend().get_texts())
        if t.startswith("fit")
    ]
    assert "partial counts (no full run of n complete)" in labels and alone in labels
    [hollow] = [line for line in ax.get_lines() if line.get_label().startswith("partial")]
    assert list(hollow.get_xdata()) == [9] and hollow.get_markerfacecolor() == "none"
    assert "20\n(partial)" in [t.get_text() for t in ax.texts] and "262\n(≥ 24)" in [t.get_text() for t in ax.texts]


def test_the_commands_label_partial_and_restricted_n(sqlite_url, monkeypatch, tmp_path):
    """`plot counts`, `plot contacts` and `plot all` pass the n that only restricted runs hold ("≥ M") and
    those with no run complete ("partial"): the contacts figure's legend says so, and the counts figure fits
    only the n counted in full."""
    import socket

    from packings.service import plots, store
    from packings.service.db import open_database, sessions
    from packings.workers.params import Params

    engine = open_database(sqlite_url, create=True)
    try:
        fill_database(engine, 7)
        fill_database(engine, 9, Params(min_contacts=21, max_break=3))
        store.start_run(sessions(engine), 8, Params(), f"{socket.gethostname()}:{2**22 + 12345}:gone")
    finally:
        engine.dispose()
    seen = {"plot_counts": [], "plot_by_contacts": []}
    for name, kept in seen.items():
        real = getattr(plots, name)
        monkeypatch.setattr(
            plots, name, lambda *a, _real=real, _kept=kept, **kw: _kept.append(_real(*a, **kw)) or _kept[-1]
        )
    assert invoke("counts", "--db", sqlite_url, "-o", tmp_path / "c.png").exit_code == 0
    assert invoke("contacts", "--db", sqlite_url, "-o", tmp_path / "k.png").exit_code == 0
    assert invoke("all", "--db", sqlite_url, "-o", tmp_path).exit_code == 0
    assert len(seen["plot_counts"]) == len(seen["plot_by_contacts"]) == 2
    for fig in seen["plot_by_contacts"]:
        labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
        assert labels[:3] == ["n = 7 (5)", "n = 8 (1, partial)", "n = 9 (52, ≥ 21 contacts)"], labels
    for fig in seen["plot_counts"]:
        labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
        assert [label for label in labels if label.startswith("fit")] == ["fit 2.50·(n − 5)!  (n = 7)"], labels


def test_plot_gap_cdf(tmp_path):
    rng = np.random.default_rng(0)
    gaps = {n: list(np.exp(rng.normal(-2 - 0.2 * n, 1.0, size=20 * n))) for n in (8, 9, 10)}
    gaps[11] = [0.05, None, float("nan"), 0.0, -1.0]  # only the one positive gap is drawn
    drawn(plot_gap_cdf, gaps, path=tmp_path / "gaps.png")


def test_plot_by_contacts(tmp_path):
    drawn(plot_by_contacts, PAPER_BY_CONTACTS, path=tmp_path / "contacts.png")
    drawn(plot_by_contacts, {7: {15: 5}}, path=tmp_path / "single.png")


@pytest.mark.parametrize(
    "draw, empty",
    [
        (plot_counts, {}),
        (plot_counts, {7: 0}),
        (plot_gap_cdf, {}),
        (plot_gap_cdf, {8: [None, 0.0]}),
        (plot_by_contacts, {}),
        (plot_by_contacts, {8: {}}),
    ],
)
def test_nothing_to_draw(tmp_path, draw, empty):
    with pytest.raises(ValueError, match="no "):
        draw(empty, tmp_path / "x.png")
    assert files(tmp_path) == []


def test_sphere_values():
    degree, label = sphere_values(OCTAHEDRON, OCTAHEDRON_CONTACTS, "degree")
    assert len(OCTAHEDRON_CONTACTS) == 12 and list(degree) == [4] * 6 and label == "contacts per sphere"
    height, _ = sphere_values(OCTAHEDRON + [0, 0, 3], OCTAHEDRON_CONTACTS, "height")
    assert height == pytest.approx([0, 0, 0, 0, S, -S])
    distance, _ = sphere_values(OCTAHEDRON + 1, OCTAHEDRON_CONTACTS, "distance")
    assert distance == pytest.approx([S] * 6)
    with pytest.raises(ValueError, match="unknown property"):
        sphere_values(OCTAHEDRON, OCTAHEDRON_CONTACTS, "mass")


def test_plot_cluster(tmp_path):
    x = np.array([[0, 0, 0], [1, 0, 0], [0.5, math.sqrt(3) / 2, 0], [0.5, math.sqrt(3) / 6, math.sqrt(2 / 3)]])
    tetra = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    default = drawn(plot_cluster, x, tetra, path=tmp_path / "default.png")
    by_height = drawn(
        plot_cluster, x, tetra, path=tmp_path / "height.png", values=x[:, 2], label="z", title="tetrahedron"
    )
    assert not np.array_equal(default, by_height)
    # the same picture wherever the cluster sits: it is centred
    assert np.abs(default - drawn(plot_cluster, x + 7.5, tetra, path=tmp_path / "moved.png")).mean() < 0.5
    drawn(plot_cluster, OCTAHEDRON, OCTAHEDRON_CONTACTS, path=tmp_path / "octahedron.png", elev=10, azim=30)
    drawn(plot_cluster, [[0, 0, 0]], [], path=tmp_path / "one.png")


@pytest.mark.parametrize(
    "kw, message",
    [
        (dict(coords=np.zeros((3, 2))), "n x 3"),
        (dict(contacts=[(0, 9)]), "outside"),
        (dict(values=[1, 2]), "one entry per sphere"),
    ],
)
def test_plot_cluster_rejects_bad_input(tmp_path, kw, message):
    args = dict(coords=OCTAHEDRON, contacts=OCTAHEDRON_CONTACTS) | kw
    with pytest.raises(ValueError, match=message):
        plot_cluster(args.pop("coords"), args.pop("contacts"), tmp_path / "x.png", **args)
    assert files(tmp_path) == []


def test_best_view_looks_across_a_line():
    """A row of spheres along x is seen from the side, not end on."""
    x = np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)]
    elev, azim = best_view(x)
    eye = np.array(
        [
            math.cos(math.radians(elev)) * math.cos(math.radians(azim)),
            math.cos(math.radians(elev)) * math.sin(math.radians(azim)),
            math.sin(math.radians(elev)),
        ]
    )
    assert abs(eye[0]) < 0.1


def test_a_failed_write_leaves_the_old_file(tmp_path, monkeypatch):
    from matplotlib.figure import Figure

    path = tmp_path / "counts.png"
    path.write_bytes(b"old")

    def broken(self, f, **kw):
        f.write(b"\x89PNG half")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(Figure, "savefig", broken)
    with pytest.raises(OSError):
        plot_counts({7: 5, 8: 13}, path)
    assert path.read_bytes() == b"old" and files(tmp_path) == ["counts.png"]
    monkeypatch.undo()
    plot_counts({7: 5, 8: 13}, path)  # replaced whole
    pixels(path)
    assert files(tmp_path) == ["counts.png"]


def test_save_writes_at_the_figures_size(tmp_path):
    from matplotlib.figure import Figure

    pixels(save(_busy(Figure(figsize=(6.4, 4.8), dpi=150)), tmp_path / "f.png"))
    pixels(save(_busy(Figure(figsize=(2, 1), dpi=100)), tmp_path / "g.png"), size=(200, 100))


def _busy(fig):
    fig.add_subplot().plot([0, 1], [1, 0])
    return fig


def test_importing_the_commands_does_not_load_matplotlib():
    code = "import sys, packings.service.plot_commands; assert 'matplotlib' not in sys.modules, 'matplotlib imported'"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


# --------------------------------------------------------------------------- figures for a paper

TETRA = np.array([[0, 0, 0], [1, 0, 0], [0.5, math.sqrt(3) / 2, 0], [0.5, math.sqrt(3) / 6, math.sqrt(2 / 3)]])
#: a tetrahedron with a fifth sphere on one face: one pair (3, 4) not in contact, 1/3 apart... of a gap
BIPYRAMID = np.r_[TETRA, [[0.5, math.sqrt(3) / 6, -math.sqrt(2 / 3)]]]
BIPYRAMID_CONTACTS = [(i, j) for i in range(4) for j in range(i + 1, 4)] + [(0, 4), (1, 4), (2, 4)]


@pytest.mark.parametrize("suffix, magic", [(".png", b"\x89PNG"), (".pdf", b"%PDF"), (".svg", b"<?xml")])
def test_the_format_follows_the_file_name(tmp_path, suffix, magic):
    for draw, data in [(plot_counts, {7: 5, 8: 13}), (plot_by_contacts, {8: {18: 13}}), (plot_cluster, OCTAHEDRON)]:
        path = tmp_path / (draw.__name__ + suffix)
        draw(data, OCTAHEDRON_CONTACTS, path) if draw is plot_cluster else draw(data, path)
        assert path.read_bytes().startswith(magic), path
    if suffix == ".svg":
        assert "<svg" in path.read_text()


def test_a_format_it_cannot_write_is_refused_before_drawing(tmp_path):
    for name in ("x.jpg", "x", "x.png.txt"):
        with pytest.raises(ValueError, match=r"\.png, \.pdf, \.svg"):
            plot_counts({7: 5}, tmp_path / name)
        with pytest.raises(ValueError, match=r"\.png, \.pdf, \.svg"):
            plot_cluster(OCTAHEDRON, OCTAHEDRON_CONTACTS, tmp_path / name)
    assert files(tmp_path) == []


def test_size_and_dpi(tmp_path):
    plot_counts({7: 5, 8: 13}, tmp_path / "a.png", size=(3.4, 2.6), dpi=200)
    pixels(tmp_path / "a.png", size=(680, 520))
    plot_cluster(OCTAHEDRON, OCTAHEDRON_CONTACTS, tmp_path / "b.png", size=(2, 2), dpi=100)
    pixels(tmp_path / "b.png", size=(200, 200))
    with pytest.raises(ValueError, match="positive"):
        plot_counts({7: 5}, size=(0, 2))


def test_every_plot_function_draws_on_a_callers_axes_and_returns_the_figure(tmp_path):
    """A notebook's figure with four axes: each function draws on the one it is given, writes nothing
    unless told, and returns that figure."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 8))
    FigureCanvasAgg(fig)
    axes = [
        fig.add_subplot(2, 2, 1),
        fig.add_subplot(2, 2, 2),
        fig.add_subplot(2, 2, 3),
        fig.add_subplot(2, 2, 4, projection="3d"),
    ]
    assert plot_counts({7: 5, 8: 13}, ax=axes[0]) is fig
    assert plot_gap_cdf({8: [0.1, 0.2]}, ax=axes[1]) is fig
    assert plot_by_contacts({8: {18: 13}}, ax=axes[2]) is fig
    assert plot_cluster(TETRA, BIPYRAMID_CONTACTS[:6], ax=axes[3], labels=True) is fig
    assert [len(a.lines) > 0 for a in axes] == [True] * 4
    assert axes[0].get_title() == "Rigid clusters of n spheres" and axes[1].get_xscale() == "log"
    assert files(tmp_path) == []
    with pytest.raises(ValueError, match="3D axes"):
        plot_cluster(TETRA, BIPYRAMID_CONTACTS[:6], ax=axes[0])
    path = tmp_path / "notebook.png"
    assert plot_counts({7: 5}, path, ax=axes[0]) is fig  # with a path: the caller's whole figure
    pixels(path, size=(1000, 800))


def _texts(fig) -> list[str]:
    return [t.get_text() for ax in fig.axes for t in ax.texts]


def test_the_closest_pair_not_in_contact_is_dashed_with_its_gap():
    i, j, gap = closest_pair(BIPYRAMID, BIPYRAMID_CONTACTS)
    assert (i, j) == (3, 4) and gap == pytest.approx(2 * math.sqrt(2 / 3) - 1)
    assert closest_pair(TETRA, BIPYRAMID_CONTACTS[:6]) is None
    fig = plot_cluster(BIPYRAMID, BIPYRAMID_CONTACTS)
    dashed = [line for line in fig.axes[0].lines if line.get_linestyle() == "--"]
    assert len(dashed) == 1
    ends = np.array(dashed[0].get_data_3d()).T
    x = BIPYRAMID - BIPYRAMID.mean(axis=0)
    assert sorted(map(tuple, np.round(ends, 9))) == sorted(map(tuple, np.round(x[[3, 4]], 9)))
    assert _texts(fig) == [f"gap {gap:.3g}"] == ["gap 0.633"]
    assert not [
        line
        for line in plot_cluster(BIPYRAMID, BIPYRAMID_CONTACTS, gap=False).axes[0].lines
        if line.get_linestyle() == "--"
    ]


def test_labels_number_the_spheres():
    assert sorted(_texts(plot_cluster(OCTAHEDRON, OCTAHEDRON_CONTACTS, labels=True)), key=lambda t: (len(t), t)) == [
        "0",
        "1",
        "2",
        "3",
        "4",
        "5",
        "gap 0.414",
    ]
    assert _texts(plot_cluster(OCTAHEDRON, OCTAHEDRON_CONTACTS)) == ["gap 0.414"]


def test_the_sticks_style_shows_every_contact(tmp_path):
    """Small spheres: less of the picture is sphere, and no faint second pass of the sticks is needed."""
    spheres = drawn(plot_cluster, OCTAHEDRON, OCTAHEDRON_CONTACTS, path=tmp_path / "spheres.png", elev=20, azim=30)
    sticks = drawn(
        plot_cluster, OCTAHEDRON, OCTAHEDRON_CONTACTS, path=tmp_path / "sticks.png", elev=20, azim=30, style="sticks"
    )
    coloured = [np.mean(np.ptp(a, axis=2) > 60) for a in (spheres, sticks)]  # saturated: sphere colour
    assert coloured[1] < coloured[0] / 3
    with pytest.raises(ValueError, match="unknown style"):
        plot_cluster(OCTAHEDRON, OCTAHEDRON_CONTACTS, style="balls")


def _moved(x, seed: int, reflect: bool = False):
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    if (np.linalg.det(q) < 0) != reflect:
        q[:, 0] *= -1
    return x @ q.T + rng.uniform(-5, 5, size=3)


def test_clusters_of_one_contact_graph_are_aligned_on_a_contact_triangle():
    """A moved, turned and relabelled copy of a cluster lies on the original once aligned; the two
    geometries of one n = 11 contact graph share a contact triangle and differ elsewhere; clusters of
    different graphs are not aligned."""
    rng = np.random.default_rng(3)
    p = rng.permutation(5)
    inverse = np.argsort(p)
    copy = (_moved(BIPYRAMID, 1)[p], [(int(inverse[i]), int(inverse[j])) for i, j in BIPYRAMID_CONTACTS])
    a, b = aligned([(BIPYRAMID, BIPYRAMID_CONTACTS), copy])
    assert np.allclose(a, BIPYRAMID)
    assert np.allclose(np.sort(b, axis=0), np.sort(BIPYRAMID, axis=0), atol=1e-9)  # the same spheres
    g, h = two_geometries()
    x, y = aligned([(g.coords, g.contacts), (_moved(h.coords, 2), h.contacts)])
    near = np.min(np.linalg.norm(x[:, None] - y[None], axis=-1), axis=1)
    assert np.sum(near < 1e-9) >= 3 and near.max() > 0.1
    assert aligned([(BIPYRAMID, BIPYRAMID_CONTACTS), (OCTAHEDRON, OCTAHEDRON_CONTACTS)]) is None


def test_several_clusters_side_by_side(tmp_path):
    g, h = two_geometries()
    fig = plot_clusters(
        [(g.coords, g.contacts), (_moved(h.coords, 5), h.contacts)],
        tmp_path / "two.png",
        titles=["a", "b"],
        labels=True,
    )
    pixels(tmp_path / "two.png", size=(1230, 630))
    three_d = [ax for ax in fig.axes if ax.name == "3d"]
    assert [ax.get_title() for ax in three_d] == ["a", "b"]
    assert three_d[0].elev == three_d[1].elev and three_d[0].azim == three_d[1].azim  # one view
    assert len(fig.axes) == 3  # one colour bar
    assert sum(t.isdigit() for t in _texts(fig)) == 22
    apart = plot_clusters([(BIPYRAMID, BIPYRAMID_CONTACTS), (OCTAHEDRON, OCTAHEDRON_CONTACTS)])
    assert len([ax for ax in apart.axes if ax.name == "3d"]) == 2
    with pytest.raises(ValueError, match="2 titles for 1"):
        plot_clusters([(BIPYRAMID, BIPYRAMID_CONTACTS)], titles=["a", "b"])


# --------------------------------------------------------------------------- the commands


def test_counts_gaps_contacts(catalog, tmp_path):
    for name in ("counts", "gaps", "contacts"):
        path = tmp_path / f"my-{name}.png"
        r = invoke(name, "--db", catalog.url, "-o", path)
        assert r.exit_code == 0, r.stderr
        assert r.stdout == f"{path}\n"
        pixels(path)
    assert files(tmp_path) == ["my-contacts.png", "my-counts.png", "my-gaps.png"]  # no temporary file left


def test_default_names_and_directories(catalog, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    r = invoke("counts", "--db", catalog.url)
    assert r.exit_code == 0 and r.stdout == "counts.png\n", r.stderr
    (tmp_path / "figs").mkdir()
    r = invoke("gaps", "--db", catalog.url, "-o", "figs")  # an existing directory: the default name in it
    assert r.exit_code == 0 and r.stdout == str(Path("figs") / "gaps.png") + "\n", r.stderr
    pixels(tmp_path / "counts.png")
    pixels(tmp_path / "figs" / "gaps.png")


def test_n_restricts(catalog, tmp_path):
    def draw(name, *ns):
        path = tmp_path / f"{name}.png"
        r = invoke("counts", "--db", catalog.url, "-o", path, *ns)
        assert r.exit_code == 0, r.stderr
        return pixels(path)

    every, comma, repeated, seven = (
        draw("every"),
        draw("comma", "--n", "7,8"),
        draw("repeated", "--n", "7", "--n", "8"),
        draw("seven", "--n", "7"),
    )
    assert np.array_equal(every, comma) and np.array_equal(comma, repeated)
    assert not np.array_equal(every, seven)
    r = invoke("contacts", "--db", catalog.url, "-o", tmp_path / "c.png", "--n", "8")
    assert r.exit_code == 0, r.stderr


def test_all(catalog, tmp_path):
    r = invoke("all", "--db", catalog.url, "-o", tmp_path)
    assert r.exit_code == 0, r.stderr
    names = ["counts.png", "gaps.png", "contacts.png"]
    assert r.stdout.splitlines() == [str(tmp_path / n) for n in names]
    assert files(tmp_path) == sorted(names)
    for n in names:
        pixels(tmp_path / n)
    # the same figures as the single commands
    r = invoke("gaps", "--db", catalog.url, "-o", tmp_path / "single.png")
    assert np.array_equal(pixels(tmp_path / "single.png"), pixels(tmp_path / "gaps.png"))


def test_cluster_color_by(catalog, tmp_path, monkeypatch):
    from packings.service.db import sessions

    with sessions(catalog.engine, readonly=True)() as s:
        cid = s.execute(select(ClusterRow.id).where(ClusterRow.n == 8).order_by(ClusterRow.id)).scalars().first()
    pictures = {}
    for by in ("degree", "height", "distance"):
        path = tmp_path / f"{by}.png"
        r = invoke("cluster", cid, "--db", catalog.url, "--color-by", by, "-o", path)
        assert r.exit_code == 0, r.stderr
        assert r.stdout == f"{path}\n"
        pictures[by] = pixels(path)
    assert not np.array_equal(pictures["degree"], pictures["height"])
    assert not np.array_equal(pictures["degree"], pictures["distance"])
    assert not np.array_equal(pictures["height"], pictures["distance"])
    monkeypatch.chdir(tmp_path)
    r = invoke("cluster", cid, "--db", catalog.url)  # default: degree, ./cluster-ID.png
    assert r.exit_code == 0 and r.stdout == f"cluster-{cid}.png\n", r.stderr
    assert np.array_equal(pixels(tmp_path / f"cluster-{cid}.png"), pictures["degree"])
    r = invoke("cluster", cid, "--db", catalog.url, "--color-by", "mass")
    assert r.exit_code == 2 and "'mass' is not one of" in r.stderr


# --------------------------------------------------------------------------- errors


def test_no_clusters(tmp_path):
    from packings.service.db import open_database

    url = f"sqlite:///{tmp_path / 'empty.db'}"
    open_database(url, create=True).dispose()
    out = tmp_path / "out"
    out.mkdir()
    for args in (
        ["counts", "-o", out / "c.png"],
        ["gaps", "-o", out / "g.png"],
        ["contacts", "-o", out / "c.png"],
        ["all", "-o", out],
    ):
        one_line_error(invoke(*args, "--db", url), "no clusters", "in the database")
    assert files(out) == []


def test_unknown_id_and_n(catalog, tmp_path):
    one_line_error(invoke("cluster", 99999, "--db", catalog.url, "-o", tmp_path / "c.png"), "no cluster with id 99999")
    one_line_error(
        invoke("counts", "--n", "12", "--db", catalog.url, "-o", tmp_path / "c.png"),
        "no clusters with n = 12 in the database",
    )
    one_line_error(
        invoke("all", "--n", "5,12", "--db", catalog.url, "-o", tmp_path), "no clusters with n = 5, 12 in the database"
    )
    r = invoke("counts", "--n", "seven", "--db", catalog.url, "-o", tmp_path / "c.png")
    assert r.exit_code == 2 and "'seven' is not an integer" in r.stderr
    assert files(tmp_path) == []


def test_bad_output(catalog, tmp_path):
    missing = tmp_path / "nope"
    one_line_error(
        invoke("counts", "--db", catalog.url, "-o", missing / "c.png"), f"directory {missing} does not exist"
    )
    one_line_error(invoke("cluster", 1, "--db", catalog.url, "-o", missing / "c.png"), "does not exist")
    one_line_error(invoke("all", "--db", catalog.url, "-o", missing), f"cannot write to {missing}")
    (tmp_path / "file.png").write_bytes(b"x")
    one_line_error(invoke("all", "--db", catalog.url, "-o", tmp_path / "file.png"), "not a directory")
    one_line_error(invoke("counts", "--db", catalog.url, "-o", tmp_path / "c.jpg"), ".png, .pdf, .svg")
    assert files(tmp_path) == ["file.png"]


def test_bad_database(tmp_path):
    out = tmp_path / "c.png"
    one_line_error(invoke("counts", "--db", "mysql://u@h/db", "-o", out), "unsupported database 'mysql'")
    one_line_error(invoke("counts", "--db", "no-such-thing", "-o", out), "malformed database URL")
    one_line_error(invoke("gaps", "--db", f"sqlite:///{tmp_path / 'none.db'}", "-o", out), "no database at")
    one_line_error(invoke("cluster", 1, "--db", f"sqlite:///{tmp_path / 'none.db'}", "-o", out), "no database at")
    assert files(tmp_path) == []  # neither a figure nor a database


def test_errors_through_packings_main(catalog, tmp_path, monkeypatch, capsys):
    """Once registered under ``packings``, errors are the usual one line ``packings: error: ...``."""
    import packings.service.cli as cli_module

    group = click.Group("packings", commands={**cli_module.cli.commands, "plot": plot})
    monkeypatch.setattr(cli_module, "cli", group)

    def packings(*args):
        try:
            cli_module.main([str(a) for a in args])
            code = 0
        except SystemExit as e:
            code = e.code
        out, err = capsys.readouterr()
        return code, out, err

    for args, words in [
        (["cluster", 99999, "--db", catalog.url], "no cluster with id 99999"),
        (["counts", "--db", "mysql://u@h/db"], "unsupported database"),
        (["counts", "--n", "x", "--db", catalog.url], "'x' is not an integer"),
        (["all", "--db", catalog.url, "-o", tmp_path / "nope"], "does not exist"),
    ]:
        code, out, err = packings("plot", *args)
        assert code != 0 and out == "", (args, code, out, err)
        lines = err.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("packings: error: ") and words in lines[0], err
    code, out, err = packings("plot", "counts", "--db", catalog.url, "-o", tmp_path / "c.png")
    assert code == 0 and out == f"{tmp_path / 'c.png'}\n", err
    assert files(tmp_path) == ["c.png"]


def test_help_lists_the_subcommands():
    r = invoke("--help")
    assert r.exit_code == 0
    for name in ("counts", "gaps", "contacts", "cluster", "all"):
        assert f"  {name} " in r.stdout


def test_cluster_command_writes_several_clusters_formats_and_sizes(catalog, tmp_path, monkeypatch):
    from packings.service.db import sessions

    with sessions(catalog.engine, readonly=True)() as s:
        a, b = s.execute(select(ClusterRow.id).where(ClusterRow.n == 8).order_by(ClusterRow.id)).scalars().all()[:2]
    monkeypatch.chdir(tmp_path)
    r = invoke("cluster", a, b, "--db", catalog.url, "--labels", "--style", "sticks", "--size", "6x3", "--dpi", "80")
    assert r.exit_code == 0 and r.stdout == f"cluster-{a}-{b}.png\n", r.stderr
    pixels(tmp_path / f"cluster-{a}-{b}.png", size=(480, 240))
    r = invoke("cluster", a, "--db", catalog.url, "-o", "one.pdf")
    assert r.exit_code == 0 and (tmp_path / "one.pdf").read_bytes().startswith(b"%PDF"), r.stderr
    r = invoke("counts", "--db", catalog.url, "-o", "c.svg", "--size", "3.4x2.6")
    assert r.exit_code == 0 and "<svg" in (tmp_path / "c.svg").read_text(), r.stderr
    r = invoke("all", "--db", catalog.url, "--format", "pdf")
    assert r.exit_code == 0 and r.stdout.split() == ["counts.pdf", "gaps.pdf", "contacts.pdf"], r.stderr
    one_line_error(invoke("cluster", a, 99999, "--db", catalog.url), "no cluster with id 99999")
    for bad in ("3", "x by y", "0x2", "1x200"):
        r = invoke("counts", "--db", catalog.url, "--size", bad)
        assert r.exit_code == 2 and "--size" in r.stderr, (bad, r.stderr)
    assert invoke("cluster", "--db", catalog.url).exit_code == 2  # at least one ID
    assert sorted(files(tmp_path)) == sorted(
        ["c.svg", f"cluster-{a}-{b}.png", "contacts.pdf", "counts.pdf", "gaps.pdf", "one.pdf"]
    )


def test_a_row_of_the_api_draws_on_a_notebooks_axes(catalog, tmp_path):
    """docs/cli.md's example: a row from packings.connect drawn beside the counts, saved as PDF."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    import packings

    fig = Figure(figsize=(9, 4))
    FigureCanvasAgg(fig)
    with packings.connect(catalog.url) as cat:
        row = cat.get(1)
        assert plot_counts({n: cat.count(n=n) for n in (7, 8)}, ax=fig.add_subplot(1, 2, 1)) is fig
    assert plot_cluster(row.coords, row.contacts, ax=fig.add_subplot(1, 2, 2, projection="3d"), labels=True) is fig
    labels = [t.get_text() for t in fig.axes[1].texts if t.get_text().isdigit()]
    assert labels == [str(i) for i in range(len(row.coords))]
    fig.savefig(tmp_path / "both.pdf")
    assert (tmp_path / "both.pdf").read_bytes().startswith(b"%PDF")
