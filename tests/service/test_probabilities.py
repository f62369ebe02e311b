"""The partition function stored with every cluster, and the equilibrium probabilities read from it:
``Catalogue.probabilities``, ``packings stats --kappa``, ``packings plot probabilities``."""

from __future__ import annotations

import json
import math

import pytest
from sqlalchemy import select, text

from packings.service.api import Catalogue
from packings.service.db import sessions
from packings.service.errors import PackingsError
from packings.service.models import ClusterRow
from packings.workers.free_energy import free_energy
from tests.helpers import filled_catalog, ok, one_line_error, packings

catalog = filled_catalog(6, 7, 9)


def _rows(engine, n: int) -> list[ClusterRow]:
    with sessions(engine)() as s:
        return list(s.execute(select(ClusterRow).where(ClusterRow.n == n).order_by(ClusterRow.id)).scalars())


def test_every_new_cluster_stores_its_partition_function(catalog):
    """A run stores, with every cluster it finds, what packings.workers.free_energy computes of it: z where
    Z = κ^m z, else NULL and the reason, and the square well's leading term where it has one."""
    for n in (6, 7, 9):
        for row in _rows(catalog.engine, n):
            fe = free_energy(row.to_core())
            assert (row.sigma, row.chiral) == (fe.sigma, fe.chiral)
            assert (row.log_z is None) == (fe.log_z is None) == (row.z_reason is not None)
            if fe.log_z is not None:
                assert row.log_z == pytest.approx(fe.log_z, abs=1e-12)
            else:
                assert row.z_reason == fe.kind
            assert row.eps_power == fe.eps_power
            assert row.log_z_square_well == pytest.approx(math.log(fe.square_well), abs=1e-12)
    nine = _rows(catalog.engine, 9)
    singular = [r for r in nine if r.singular]
    assert len(singular) == 1 and singular[0].z_reason == "singular" and singular[0].eps_power == -0.5
    assert all(r.z_reason is None and r.eps_power == 0.0 for r in nine if not r.singular)


def test_the_octahedron_is_one_cluster_of_six_in_twenty_five(catalog):
    """Meng et al. (Science 2010): the octahedron (σ = 24) against the polytetrahedron (σ = 2), both with 12
    contacts, 1 : 24 whatever κ is."""
    with Catalogue(catalog.url) as cat:
        by_sigma = {r.sigma: r.id for r in cat.select("n=6")}
        assert sorted(by_sigma) == [2, 24]
        for kappa in (0.5, 30.0):
            p = cat.probabilities(6, kappa)
            share = {c["id"]: c["probability"] for c in p["clusters"]}
            assert share[by_sigma[24]] == pytest.approx(1 / 25, rel=1e-9)
            assert p["by_contacts"] == {"12": pytest.approx(1.0)}
            assert p["clusters"][0]["id"] == by_sigma[2]  # the most probable first


def test_probabilities_need_every_cluster_to_have_a_value(catalog):
    """n = 9 holds a singular cluster, whose Z is not κ^m z: the sticky limit gives no probabilities (never
    ones that leave it out), a square well does, and gives the singular cluster more the narrower it is
    (Z ∝ ε^(-1/2) against ε^0)."""
    with Catalogue(catalog.url) as cat:
        with pytest.raises(PackingsError, match="1 singular cluster.*--width"):
            cat.probabilities(9, 10.0)
        singular = next(r.id for r in cat.select("n=9,singular"))

        def share(width: float) -> float:
            p = cat.probabilities(9, 10.0, width)
            assert sum(c["probability"] for c in p["clusters"]) == pytest.approx(1.0)
            return next(c["probability"] for c in p["clusters"] if c["id"] == singular)

        wide, narrow = share(0.01), share(0.0001)
        odds = (narrow / (1 - narrow)) / (wide / (1 - wide))
        assert odds == pytest.approx(10.0, rel=1e-9)  # (0.0001 / 0.01)^(-1/2)
        with pytest.raises(PackingsError, match="no clusters with n = 12"):
            cat.probabilities(12, 1.0)


def test_stats_with_kappa(catalog):
    out = ok("stats", "--kappa", "10", "--db", catalog.url)
    assert "equilibrium probabilities at κ = 10 (the sticky limit):" in out
    assert "n = 9: 1 singular cluster" in out  # said in n = 9's block, the others given
    rows = json.loads(ok("stats", "--kappa", "10", "--json", "--db", catalog.url))
    assert [sorted(r["probabilities"]) for r in rows] == [
        ["by_contacts", "clusters", "kappa", "n", "width"],
        ["by_contacts", "clusters", "kappa", "n", "width"],
        ["undefined"],
    ]
    one_line_error(packings("stats", "--kappa", "10", "--n", "9", "--db", catalog.url), "singular", "--width")
    out = ok("stats", "--kappa", "10", "--width", "0.01", "--n", "9", "--db", catalog.url)
    assert "(a square well of width 0.01)" in out and "the 5 most probable:" in out
    one_line_error(packings("stats", "--width", "0.01", "--db", catalog.url), "--kappa")
    one_line_error(packings("stats", "--kappa", "0", "--db", catalog.url), "--kappa")


def test_plot_probabilities(catalog, tmp_path):
    path = tmp_path / "p.png"
    assert ok("plot", "probabilities", "7", "-o", str(path), "--db", catalog.url).strip() == str(path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    one_line_error(
        packings("plot", "probabilities", "9", "-o", str(tmp_path / "q.png"), "--db", catalog.url), "--width"
    )
    assert not (tmp_path / "q.png").exists()
    path = tmp_path / "w.svg"
    ok("plot", "probabilities", "9", "--width", "0.01", "--kappa", "1", "100", "-o", str(path), "--db", catalog.url)
    assert "singular clusters" in path.read_text()
    one_line_error(packings("plot", "probabilities", "9", "--kappa", "5", "1", "--db", catalog.url), "LO")


def test_selection_keys_of_the_partition_function(catalog):
    assert ok("select", "n=6,sigma=24", "--count", "--db", catalog.url).strip() == "1"
    assert ok("select", "n=9,z_reason=singular", "--count", "--db", catalog.url).strip() == "1"
    assert ok("select", "n=7,chiral", "--count", "--db", catalog.url).strip() == "1"


def test_backfill_computes_the_partition_function_of_older_rows(engine):
    """Rows stored before revision 0010 have no partition function: probabilities say so, and `packings
    db backfill` computes it, the same as a run stores it."""
    from tests.helpers import fill_database

    fill_database(engine, 6)
    url = engine.url.render_as_string(hide_password=False)
    before = {r.id: (r.sigma, r.chiral, r.log_z) for r in _rows(engine, 6)}
    with engine.begin() as c:
        c.execute(text("UPDATE clusters SET sigma = NULL, chiral = NULL, log_z = NULL, log_z_square_well = NULL"))
    with Catalogue(url) as cat, pytest.raises(PackingsError, match="packings db backfill"):
        cat.probabilities(6, 1.0)
    assert ok("db", "backfill", "--db", url).strip() == "computed the facts of 2 clusters"
    after = {r.id: (r.sigma, r.chiral, r.log_z) for r in _rows(engine, 6)}
    assert after == before
