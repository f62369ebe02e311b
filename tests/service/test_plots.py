"""Figures (packings.plots): the pure figure functions on synthetic data, and
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

from packings.models import ClusterRow
from packings.plots import (
    SIZE_PX,
    best_view,
    plot,
    plot_by_contacts,
    plot_cluster,
    plot_counts,
    plot_gap_cdf,
    save_png,
    sphere_values,
)
from tests.service.querydb import filled_catalog

catalog = filled_catalog(7, 8)

PAPER_BY_CONTACTS = {5: {9: 1}, 6: {12: 2}, 7: {15: 5}, 8: {18: 13}, 9: {21: 52}, 10: {23: 1, 24: 259, 25: 3},
                     11: {25: 2, 26: 18, 27: 1618, 28: 20, 29: 1}}
S = 1 / math.sqrt(2)
OCTAHEDRON = np.array([[S, 0, 0], [-S, 0, 0], [0, S, 0], [0, -S, 0], [0, 0, S], [0, 0, -S]])
OCTAHEDRON_CONTACTS = [(i, j) for i in range(6) for j in range(i + 1, 6) if j != i + 1 or i % 2]


def pixels(path) -> np.ndarray:
    """The PNG's pixels, after checking it is one of the fixed size and not a single flat colour."""
    with Image.open(path) as im:
        assert im.format == "PNG"
        assert im.size == SIZE_PX == (960, 720)
        a = np.asarray(im.convert("RGB"), dtype=float)
    assert a.std() > 0
    return a


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
    path = plot_counts({n: sum(d.values()) for n, d in PAPER_BY_CONTACTS.items()}, tmp_path / "counts.png")
    assert path == tmp_path / "counts.png"
    pixels(path)
    pixels(plot_counts({4: 1}, tmp_path / "one.png"))  # nothing to fit: markers only
    assert files(tmp_path) == ["counts.png", "one.png"]


def test_plot_gap_cdf(tmp_path):
    rng = np.random.default_rng(0)
    gaps = {n: list(np.exp(rng.normal(-2 - 0.2 * n, 1.0, size=20 * n))) for n in (8, 9, 10)}
    gaps[11] = [0.05, None, float("nan"), 0.0, -1.0]  # only the one positive gap is drawn
    pixels(plot_gap_cdf(gaps, tmp_path / "gaps.png"))


def test_plot_by_contacts(tmp_path):
    pixels(plot_by_contacts(PAPER_BY_CONTACTS, tmp_path / "contacts.png"))
    pixels(plot_by_contacts({7: {15: 5}}, tmp_path / "single.png"))


@pytest.mark.parametrize("draw, empty", [(plot_counts, {}), (plot_counts, {7: 0}), (plot_gap_cdf, {}),
                                         (plot_gap_cdf, {8: [None, 0.0]}), (plot_by_contacts, {}),
                                         (plot_by_contacts, {8: {}})])
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
    default = pixels(plot_cluster(x, tetra, tmp_path / "default.png"))
    by_height = pixels(plot_cluster(x, tetra, tmp_path / "height.png", values=x[:, 2], label="z", title="tetrahedron"))
    assert not np.array_equal(default, by_height)
    # the same picture wherever the cluster sits: it is centred
    assert np.abs(default - pixels(plot_cluster(x + 7.5, tetra, tmp_path / "moved.png"))).mean() < 0.5
    pixels(plot_cluster(OCTAHEDRON, OCTAHEDRON_CONTACTS, tmp_path / "octahedron.png", elev=10, azim=30))
    pixels(plot_cluster([[0, 0, 0]], [], tmp_path / "one.png"))


@pytest.mark.parametrize("kw, message", [(dict(coords=np.zeros((3, 2))), "n x 3"),
                                         (dict(contacts=[(0, 9)]), "outside"),
                                         (dict(values=[1, 2]), "one entry per sphere")])
def test_plot_cluster_rejects_bad_input(tmp_path, kw, message):
    args = dict(coords=OCTAHEDRON, contacts=OCTAHEDRON_CONTACTS) | kw
    with pytest.raises(ValueError, match=message):
        plot_cluster(args.pop("coords"), args.pop("contacts"), tmp_path / "x.png", **args)
    assert files(tmp_path) == []


def test_best_view_looks_across_a_line():
    """A row of spheres along x is seen from the side, not end on."""
    x = np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)]
    elev, azim = best_view(x)
    eye = np.array([math.cos(math.radians(elev)) * math.cos(math.radians(azim)),
                    math.cos(math.radians(elev)) * math.sin(math.radians(azim)), math.sin(math.radians(elev))])
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


def test_save_png_size(tmp_path):
    from matplotlib.figure import Figure

    pixels(save_png(_busy(Figure(figsize=(6.4, 4.8))), tmp_path / "f.png"))


def _busy(fig):
    fig.add_subplot().plot([0, 1], [1, 0])
    return fig


def test_importing_the_commands_does_not_load_matplotlib():
    code = "import sys, packings.plots; assert 'matplotlib' not in sys.modules, 'matplotlib imported'"
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr


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

    every, comma, repeated, seven = draw("every"), draw("comma", "--n", "7,8"), \
        draw("repeated", "--n", "7", "--n", "8"), draw("seven", "--n", "7")
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
    from packings.db import sessions

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
    from packings.db import open_database

    url = f"sqlite:///{tmp_path / 'empty.db'}"
    open_database(url, create=True).dispose()
    out = tmp_path / "out"
    out.mkdir()
    for args in (["counts", "-o", out / "c.png"], ["gaps", "-o", out / "g.png"], ["contacts", "-o", out / "c.png"],
                 ["all", "-o", out]):
        one_line_error(invoke(*args, "--db", url), "no clusters", "in the database")
    assert files(out) == []


def test_unknown_id_and_n(catalog, tmp_path):
    one_line_error(invoke("cluster", 99999, "--db", catalog.url, "-o", tmp_path / "c.png"), "no cluster with id 99999")
    one_line_error(invoke("counts", "--n", "12", "--db", catalog.url, "-o", tmp_path / "c.png"),
                   "no clusters with n = 12 in the database")
    one_line_error(invoke("all", "--n", "5,12", "--db", catalog.url, "-o", tmp_path),
                   "no clusters with n = 5, 12 in the database")
    r = invoke("counts", "--n", "seven", "--db", catalog.url, "-o", tmp_path / "c.png")
    assert r.exit_code == 2 and "'seven' is not an integer" in r.stderr
    assert files(tmp_path) == []


def test_bad_output(catalog, tmp_path):
    missing = tmp_path / "nope"
    one_line_error(invoke("counts", "--db", catalog.url, "-o", missing / "c.png"),
                   f"directory {missing} does not exist")
    one_line_error(invoke("cluster", 1, "--db", catalog.url, "-o", missing / "c.png"), "does not exist")
    one_line_error(invoke("all", "--db", catalog.url, "-o", missing), f"cannot write to {missing}")
    (tmp_path / "file.png").write_bytes(b"x")
    one_line_error(invoke("all", "--db", catalog.url, "-o", tmp_path / "file.png"), "not a directory")
    one_line_error(invoke("counts", "--db", catalog.url, "-o", tmp_path / "c.pdf"), "only PNG")
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
    import packings.cli as cli_module

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

    for args, words in [(["cluster", 99999, "--db", catalog.url], "no cluster with id 99999"),
                        (["counts", "--db", "mysql://u@h/db"], "unsupported database"),
                        (["counts", "--n", "x", "--db", catalog.url], "'x' is not an integer"),
                        (["all", "--db", catalog.url, "-o", tmp_path / "nope"], "does not exist")]:
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
