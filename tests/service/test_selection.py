"""The selection language: parsing, its errors, and the rows it selects on both backends."""

from __future__ import annotations

from collections import Counter
from types import SimpleNamespace

import numpy as np
import pytest
from sqlalchemy import select

from packings.service import queries
from packings.service import selection as sel
from packings.service.models import ClusterRow, ExpansionRow
from packings.service.selection import SelectionError, Term, parse
from tests.helpers import filled_catalog

catalog = filled_catalog(7)


# --------------------------------------------------------------------------- parsing


@pytest.mark.parametrize(
    "text, terms",
    [
        ("", []),
        ("   ", []),
        (None, []),
        ("n=10,contacts<24,singular", [Term("n", "=", 10), Term("contacts", "<", 24), Term("singular", "=", True)]),
        ("n=9", [Term("n", "=", 9)]),
        ("!singular,min_gap>0.1", [Term("singular", "=", False), Term("min_gap", ">", 0.1)]),
        ("not singular", [Term("singular", "=", False)]),
        ("hyperstatic", [Term("hyperstatic", "=", True)]),
        ("! hypostatic , isostatic", [Term("hypostatic", "=", False), Term("isostatic", "=", True)]),
        (" n >= 7 , m != 15 ", [Term("n", ">=", 7), Term("contacts", "!=", 15)]),
        ("N<=8,M>3", [Term("n", "<=", 8), Term("contacts", ">", 3)]),
        ("excess=-1", [Term("excess", "=", -1)]),
        ("min_gap", [Term("min_gap", "!=", None)]),
        ("!margin", [Term("margin", "=", None)]),
        ("margin>=1e-3,min_gap<1", [Term("margin", ">=", 0.001), Term("min_gap", "<", 1.0)]),
        ("certificate=00ab12", [Term("certificate", "=", "00ab12")]),
        ("certificate='00ab12'", [Term("certificate", "=", "00ab12")]),
        ('rigid_kind!="prestress"', [Term("rigid_kind", "!=", "prestress")]),
        ("rigid_method=e_k", [Term("rigid_method", "=", "e_k")]),
        ("run=1,found_in_run=2", [Term("run", "=", 1), Term("found_in_run", "=", 2)]),
        ("run!=3", [Term("run", "!=", 3)]),
        (
            "id>4,embedding=0,flexes=1,stresses>0",
            [Term("id", ">", 4), Term("embedding", "=", 0), Term("flexes", "=", 1), Term("stresses", ">", 0)],
        ),
    ],
)
def test_parse(text, terms):
    assert parse(text) == terms


@pytest.mark.parametrize(
    "value, expected",
    [("true", True), ("TRUE", True), ("yes", True), ("1", True), ("false", False), ("No", False), ("0", False)],
)
def test_bool_values(value, expected):
    assert parse(f"singular={value}") == [Term("singular", "=", expected)]
    assert parse(f"hyperstatic!={value}") == [Term("hyperstatic", "!=", expected)]


@pytest.mark.parametrize(
    "text, message",
    [
        ("foo=1", "unknown key 'foo'"),
        ("stacking=fcc", "known keys: id, n, contacts"),
        ("lattice<fcc", "operator '<' does not apply to lattice"),
        ("lattice=bcc", "bad value 'bcc' for lattice: expected one of fcc, hcp, both, random, 2d, none"),
        ("rigid_method=guess", "expected one of first-order, single-flex, single-stress, e_k, sdp"),
        ("geometries=two", "expected an integer"),
        ("n==10", "bad operator '=='"),
        ("n=>10", "bad operator '=>'"),
        ("n~10", "bad operator '~'"),
        ("n<>10", "bad operator '<>'"),
        ("n=x", "bad value 'x' for n: expected an integer"),
        ("n=1.5", "expected an integer"),
        ("contacts=", "missing value"),
        ("min_gap>abc", "expected a number"),
        ("min_gap<nan", "finite"),
        ("margin>inf", "finite"),
        ("singular=maybe", "expected true or false"),
        ("singular<1", "operator '<' does not apply to singular"),
        ("certificate>abc", "does not apply to certificate"),
        ("run<2", "does not apply to run"),
        ("run=one", "expected an integer"),
        ("n", "n is not a boolean key"),
        ("run", "run is not a boolean key"),
        ("!n=7", "cannot negate a comparison"),
        ("not n>7", "cannot negate a comparison"),
        ("n=7,,singular", "empty term"),
        ("n=7,", "empty term"),
        ("=7", "cannot read '=7'"),
        ("7<n", "cannot read"),
        ("n 7", "cannot read"),
        ("!", "cannot read"),
    ],
)
def test_errors_are_one_line(text, message):
    with pytest.raises(SelectionError) as err:
        sel.where(text)
    assert message in str(err.value)
    assert "\n" not in str(err.value)
    assert isinstance(err.value, ValueError)


def test_unknown_key_lists_every_key():
    with pytest.raises(SelectionError) as err:
        parse("colour=red")
    assert all(k in str(err.value) for k in sel.KEYS)


@pytest.mark.parametrize(
    "sort, message", [("bogus", "unknown key 'bogus'"), ("run", "cannot sort by run"), ("-", "unknown key")]
)
def test_bad_sort_keys(sort, message):
    with pytest.raises(SelectionError, match=message):
        sel.order_by(sort)


def test_describe_keys_names_every_key_and_alias():
    text = sel.describe_keys()
    lines = text.splitlines()
    assert len(lines) == len(sel.KEYS)
    assert [line.split()[0] for line in lines] == list(sel.KEYS)
    assert "contacts (m)" in text


def test_a_new_key_is_one_registry_entry(monkeypatch):
    monkeypatch.setitem(sel.KEYS, "stacking", sel.Key(str, "test key", expr=lambda: ClusterRow.rigid_kind))
    assert parse("stacking=fcc") == [Term("stacking", "=", "fcc")]
    assert "stacking" in sel.describe_keys()
    assert "rigid_kind" in str(sel.where("stacking=fcc"))


# --------------------------------------------------------------------------- the rows selected

#: rows the enumeration does not produce at n = 7 (singular, hypo/hyperstatic,
#: missing min_gap, margins), so that every key has something to tell apart
SYNTHETIC = [
    dict(
        n=9,
        contacts=22,
        certificate="0123",
        embedding=0,
        rigid_kind="prestress",
        rigid_method="sdp",
        margin=0.25,
        flexes=1,
        stresses=2,
        singular=True,
        min_gap=None,
        lattice="fcc",
        sigma=1,
        chiral=True,
        z_reason="singular",
    ),
    dict(
        n=9,
        contacts=20,
        certificate="0123",
        embedding=1,
        rigid_kind="prestress",
        rigid_method="e_k",
        margin=0.01,
        flexes=2,
        stresses=1,
        singular=True,
        min_gap=0.05,
        lattice="both",
        sigma=2,
        chiral=False,
        z_reason="hypostatic",
        eps_power=0.0,
        log_z_square_well=-7.5,
    ),
    dict(
        n=9,
        contacts=21,
        certificate="abc",
        embedding=0,
        rigid_kind="first-order",
        rigid_method="first-order",
        margin=None,
        flexes=0,
        stresses=0,
        singular=False,
        min_gap=0.5,
        lattice=None,
    ),
    dict(
        n=9,
        contacts=21,
        certificate="abcd",
        embedding=0,
        rigid_kind="first-order",
        rigid_method="first-order",
        margin=None,
        flexes=0,
        stresses=0,
        singular=False,
        min_gap=0.5,
        lattice="hcp",
    ),
]


@pytest.fixture(scope="module")
def rows(catalog):
    """Every cluster row, after adding the synthetic ones (once per backend)."""
    from packings.service.db import sessions

    rng = np.random.default_rng(1)
    with sessions(catalog.engine).begin() as s:
        for values in SYNTHETIC:
            x = rng.random((values["n"], 3))
            s.add(
                ClusterRow(
                    **values,
                    coords=x.astype("<f8").tobytes(),
                    contact_list="[[0, 1]]",
                    found_in_run=None,
                    found_by="seed",
                )
            )
    with sessions(catalog.engine)() as s:
        return s.execute(select(ClusterRow).order_by(ClusterRow.id)).scalars().all()


@pytest.fixture(scope="module")
def frontier(catalog, rows):
    """Run 1's frontier (``ids``) and, counted here from the transitions, the paths leaving each
    cluster (``out``), reaching it from another (``into``), circular (``circ``), and the geometries
    of each contact graph (``geom``)."""
    from packings.service.db import sessions

    with sessions(catalog.engine)() as s:
        ids = set(s.execute(select(ExpansionRow.cluster_id).where(ExpansionRow.run_id == catalog.runs[7])).scalars())
        moving = [(t.source_id, t.target_id, t.outcome) for t in queries.transitions(s) if t.direction != 0]
    return SimpleNamespace(
        ids=ids,
        out=Counter(a for a, _, _ in moving),
        into=Counter(b for a, b, _ in moving if b is not None and b != a),
        circ=Counter(a for a, _, o in moving if o == "circular"),
        rear=Counter(a for a, _, o in moving if o == "rearranged"),
        geom=Counter((c.n, c.certificate) for c in rows),
    )


def _excess(c):
    return c.contacts - (3 * c.n - 6)


def _gt(v, x):
    return v is not None and v > x


CASES = {
    "": lambda c, f: True,
    "n=7": lambda c, f: c.n == 7,
    "n=9": lambda c, f: c.n == 9,
    "n=10,contacts<24,singular": lambda c, f: False,
    "n=9,contacts<22,singular": lambda c, f: c.n == 9 and c.contacts < 22 and c.singular,
    "!singular,min_gap>0.1": lambda c, f: not c.singular and _gt(c.min_gap, 0.1),
    "not singular": lambda c, f: not c.singular,
    "singular=yes": lambda c, f: c.singular,
    "singular!=true": lambda c, f: not c.singular,
    "hyperstatic": lambda c, f: _excess(c) > 0,
    "hypostatic": lambda c, f: _excess(c) < 0,
    "isostatic": lambda c, f: _excess(c) == 0,
    "!isostatic": lambda c, f: _excess(c) != 0,
    "isostatic=0": lambda c, f: _excess(c) != 0,
    "excess>=0,m>15": lambda c, f: _excess(c) >= 0 and c.contacts > 15,
    "contacts<=15": lambda c, f: c.contacts <= 15,
    "min_gap": lambda c, f: c.min_gap is not None,
    "!min_gap": lambda c, f: c.min_gap is None,
    "min_gap<0.3": lambda c, f: c.min_gap is not None and c.min_gap < 0.3,
    "min_gap!=0.05": lambda c, f: c.min_gap != 0.05,
    "margin": lambda c, f: c.margin is not None,
    "margin!=0.25": lambda c, f: c.margin != 0.25,
    "margin<=0.25,margin>0.01": lambda c, f: c.margin is not None and 0.01 < c.margin <= 0.25,
    "certificate=0123": lambda c, f: c.certificate == "0123",
    "certificate!='0123'": lambda c, f: c.certificate != "0123",
    "rigid_kind=prestress": lambda c, f: c.rigid_kind == "prestress",
    "rigid_method!=first-order": lambda c, f: c.rigid_method != "first-order",
    "flexes>=1,stresses=1": lambda c, f: c.flexes >= 1 and c.stresses == 1,
    "embedding=1": lambda c, f: c.embedding == 1,
    "id>2,id<=6": lambda c, f: 2 < c.id <= 6,
    "found_in_run=1": lambda c, f: c.found_in_run == 1,
    "found_in_run!=1": lambda c, f: c.found_in_run != 1,
    "found_in_run": lambda c, f: c.found_in_run is not None,
    "found_by=seed": lambda c, f: c.found_by == "seed",
    "found_by!=path,n=9": lambda c, f: c.n == 9 and c.found_by != "path",
    "source_id": lambda c, f: c.source_id is not None,
    "source_id=1": lambda c, f: c.source_id == 1,
    "run=1": lambda c, f: c.id in f.ids,
    "run!=1": lambda c, f: c.id not in f.ids,
    "lattice=fcc": lambda c, f: c.lattice == "fcc",
    "lattice!=fcc": lambda c, f: c.lattice != "fcc",
    "lattice": lambda c, f: c.lattice is not None,
    "!lattice": lambda c, f: c.lattice is None,
    "close_packed": lambda c, f: c.lattice not in (None, "none"),
    "!close_packed,n=9": lambda c, f: c.n == 9 and c.lattice in (None, "none"),
    "fcc": lambda c, f: c.lattice in ("fcc", "both"),
    "hcp,!fcc": lambda c, f: c.lattice == "hcp",
    "static=hypostatic": lambda c, f: _excess(c) < 0,
    "static!=isostatic": lambda c, f: _excess(c) != 0,
    "geometries=2": lambda c, f: f.geom[c.n, c.certificate] == 2,
    "geometries<2": lambda c, f: f.geom[c.n, c.certificate] < 2,
    "paths_out>0": lambda c, f: f.out[c.id] > 0,
    "paths_out>=9": lambda c, f: f.out[c.id] >= 9,
    "paths_in=0": lambda c, f: f.into[c.id] == 0,
    "paths_in>2": lambda c, f: f.into[c.id] > 2,
    "circular>0": lambda c, f: f.circ[c.id] > 0,
    "rearranged>0": lambda c, f: f.rear[c.id] > 0,
    "rearranged>=2": lambda c, f: f.rear[c.id] >= 2,
    "sigma=2": lambda c, f: c.sigma == 2,
    "sigma>1,n=7": lambda c, f: c.n == 7 and _gt(c.sigma, 1),
    "!sigma": lambda c, f: c.sigma is None,
    "chiral": lambda c, f: c.chiral is True,
    "!chiral": lambda c, f: c.chiral is False,
    "log_z": lambda c, f: c.log_z is not None,
    "log_z<-3": lambda c, f: c.log_z is not None and c.log_z < -3,
    "z_reason=singular": lambda c, f: c.z_reason == "singular",
    "z_reason": lambda c, f: c.z_reason is not None,
    "eps_power=0": lambda c, f: c.eps_power == 0,
    "log_z_square_well<-5": lambda c, f: c.log_z_square_well is not None and c.log_z_square_well < -5,
    "reached": lambda c, f: f.into[c.id] > 0,
    "!reached,n=7": lambda c, f: c.n == 7 and f.into[c.id] == 0,
    "run=1,n=9": lambda c, f: False,
    "run=99": lambda c, f: False,
}


@pytest.mark.parametrize("text", list(CASES))
def test_selection_selects_exactly_the_matching_rows(catalog, rows, frontier, text):
    from packings.service.db import sessions

    assert catalog.runs[7] == 1  # the cases name run 1
    expected = [c.id for c in rows if CASES[text](c, frontier)]
    with sessions(catalog.engine)() as s:
        got = s.execute(select(ClusterRow.id).where(sel.where(text)).order_by(ClusterRow.id)).scalars().all()
    assert got == expected


def test_every_key_is_exercised():
    used = {t.key for text in CASES for t in parse(text)}
    assert used == set(sel.KEYS)


def test_the_data_tells_keys_apart(rows, frontier):
    """The cases are not vacuous: each side of the main distinctions has rows."""
    assert len(frontier.ids) == 5 and len(rows) == 9
    assert {_excess(c) for c in rows} == {-1, 0, 1}
    assert {c.singular for c in rows} == {True, False}
    assert {c.min_gap is None for c in rows} == {True, False}
    assert {c.lattice for c in rows} == {"fcc", "both", "hcp", "none", None}
    assert set(frontier.geom.values()) == {1, 2}
    for counts in (frontier.out, frontier.into, frontier.rear):  # no circle below n = 10 (test_expand)
        assert {counts[c.id] > 0 for c in rows} == {True, False}
    assert {c.sigma is None for c in rows} == {c.log_z is None for c in rows} == {True, False}
    assert {c.chiral for c in rows} == {True, False, None}
    assert {c.z_reason for c in rows} == {"singular", "hypostatic", None}
    assert len({frontier.into[c.id] for c in rows}) > 2


def test_certificate_of_a_stored_cluster(catalog, rows):
    from packings.service.db import sessions

    target = rows[2]
    with sessions(catalog.engine)() as s:
        got = s.execute(sel.query(f"certificate={target.certificate},embedding={target.embedding}")).scalars().all()
    assert [c.id for c in got] == [target.id]


@pytest.mark.parametrize(
    "sort, key",
    [
        (None, lambda c: (c.n, c.contacts, c.id)),
        ("id", lambda c: c.id),
        ("-contacts", lambda c: (-c.contacts, c.id)),
        ("min_gap", lambda c: (c.min_gap is None, c.min_gap or 0.0, c.id)),
        ("-margin", lambda c: (c.margin is None, -(c.margin or 0.0), c.id)),
    ],
)
def test_sort_and_limit(catalog, rows, sort, key):
    from packings.service.db import sessions

    expected = [c.id for c in sorted(rows, key=key)]
    with sessions(catalog.engine)() as s:
        assert [c.id for c in s.execute(sel.query(sort=sort)).scalars()] == expected
        assert [c.id for c in s.execute(sel.query(sort=sort, limit=3)).scalars()] == expected[:3]
        assert [c.id for c in s.execute(sel.query("n=7", sort=sort, n=7)).scalars()] == [i for i in expected if i <= 5]
