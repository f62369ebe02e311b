"""The schema: Alembic is its only source, and a database at another schema is refused."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import create_engine, inspect, text

from packings.service.db import (
    DatabaseError,
    current_revision,
    head_revision,
    make_engine,
    migrate,
    open_database,
    parse_url,
)
from packings.service.models import Base
from tests.helpers import embeddings, fill_database, one_line_error, pg_database, store_chains
from tests.helpers import packings as cli


def test_migrations_head_matches_the_models(engine):
    from alembic.autogenerate import compare_metadata
    from alembic.migration import MigrationContext

    with engine.connect() as conn:
        diff = compare_metadata(MigrationContext.configure(conn, opts={"compare_type": True}), Base.metadata)
    assert diff == []
    assert current_revision(engine) == head_revision()


def test_new_database_is_created_at_head_only_when_allowed(sqlite_url, tmp_path):
    with pytest.raises(DatabaseError, match="no database"):
        open_database(sqlite_url)
    assert list(tmp_path.iterdir()) == []
    eng = open_database(sqlite_url, create=True)
    assert current_revision(eng) == head_revision()
    assert {"runs", "clusters", "expansions", "attempts", "edges"} <= set(inspect(eng).get_table_names())
    eng.dispose()


def test_sqlite_settings(sqlite_url):
    eng = open_database(sqlite_url, create=True)
    with eng.connect() as c:
        assert c.exec_driver_sql("PRAGMA journal_mode").scalar() == "wal"
        assert c.exec_driver_sql("PRAGMA busy_timeout").scalar() >= 10_000
        assert c.exec_driver_sql("PRAGMA foreign_keys").scalar() == 1
    eng.dispose()


def test_foreign_tables_are_refused_and_left_alone(db_url):
    eng = create_engine(parse_url(db_url))
    with eng.begin() as c:
        c.execute(text("CREATE TABLE minima (id INTEGER PRIMARY KEY, energy FLOAT)"))
    with pytest.raises(DatabaseError, match="not a packings database"):
        open_database(db_url, create=True)
    assert inspect(eng).get_table_names() == ["minima"]
    r = cli("stats", "--db", db_url)
    assert "not a packings database" in one_line_error(r)
    r = cli("enumerate", "6", "--db", db_url, "--quiet")
    assert "not a packings database" in one_line_error(r)
    assert inspect(eng).get_table_names() == ["minima"]
    eng.dispose()


def test_older_and_unknown_schemas_are_refused_with_the_fix(engine):
    url = engine.url.render_as_string(hide_password=False)
    with engine.begin() as c:
        c.execute(text("UPDATE alembic_version SET version_num = 'ffffffff'"))
    r = cli("stats", "--db", url)
    assert "upgrade packings" in one_line_error(r)
    r = cli("db", "upgrade", "--db", url)  # an unknown (newer) schema is not touched
    line = one_line_error(r)
    assert "does not know" in line and "upgrade packings" in line
    # pretend the database is at a revision older than head
    import packings.service.db as db

    real = db.known_revisions
    db.known_revisions = lambda: real() | {"ffffffff"}
    try:
        with pytest.raises(DatabaseError, match="packings db upgrade"):
            open_database(url)
    finally:
        db.known_revisions = real


def test_db_upgrade_and_version(db_url):
    r = cli("db", "version", "--db", db_url)
    assert r.returncode == 0 and "database: none" in r.stdout and "empty" in r.stdout
    r = cli("db", "upgrade", "--db", db_url)
    assert r.returncode == 0, r.stderr
    assert head_revision() in r.stdout
    r = cli("db", "version", "--db", db_url)
    assert r.returncode == 0 and "up to date" in r.stdout
    r = cli("db", "upgrade", "--db", db_url)  # again: nothing to do, no error
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize(
    "url, words",
    [
        ("sqlite//packings.db", "malformed database URL"),
        ("mysql://root@localhost/x", "unsupported database"),
        ("postgresql://nobody@127.0.0.1:1/nothing", "cannot connect"),
        ("sqlite:////nonexistent-dir/sub/packings.db", "does not exist"),
        # a database that only this process would see: the workers could not (refused before Dask starts)
        ("sqlite://", "in-memory SQLite database"),
        ("sqlite:///", "in-memory SQLite database"),
        ("sqlite:///:memory:", "in-memory SQLite database"),
        ("sqlite+aiosqlite:///x.db", "asyncio driver"),
        ("postgresql+asyncpg://u@127.0.0.1/test", "asyncio driver"),
        ("postgresql+pg8000://u@127.0.0.1/test", "'postgresql+pg8000' is not installed"),
        ("postgresql+nosuch://u@127.0.0.1/test", "unknown database driver"),
    ],
)
def test_bad_database_urls_are_one_line(url, words, tmp_path):
    r = cli("enumerate", "6", "--db", url, "--quiet", cwd=tmp_path)
    assert words in one_line_error(r)
    assert list(tmp_path.iterdir()) == []


def test_query_commands_do_not_create_a_database(tmp_path):
    for cmd in (["stats"], ["status"]):
        r = cli(*cmd, cwd=tmp_path)
        assert "no database" in one_line_error(r)
    assert list(tmp_path.iterdir()) == []


def test_the_default_database_comes_from_the_environment(tmp_path, sqlite_url):
    import os

    env = {**os.environ, "PACKINGS_DB": sqlite_url}
    cwd = tmp_path / "elsewhere"
    cwd.mkdir()
    r = cli("db", "upgrade", cwd=cwd, env=env)
    assert r.returncode == 0, r.stderr
    assert current_revision(make_engine(sqlite_url)) == head_revision()
    r = cli("stats", cwd=cwd, env=env)
    assert r.returncode == 0 and "no clusters" in r.stdout
    assert list(cwd.iterdir()) == []


def test_sqlite_readers_do_not_wait_for_a_writer(sqlite_url):
    """Writers begin IMMEDIATE (one at a time); readonly sessions begin DEFERRED and read a snapshot."""
    import threading

    from packings.service.db import sessions
    from packings.service.models import Run

    eng = open_database(sqlite_url, create=True)
    writer = sessions(eng)
    result = []
    with writer.begin() as w:
        w.add(Run(n=5, params="{}", code_version="t"))
        w.flush()  # holds the write lock, uncommitted

        def read():
            with sessions(eng, readonly=True)() as r:
                result.append(r.query(Run).count())

        t = threading.Thread(target=read)
        t.start()
        t.join(timeout=20)
        assert not t.is_alive() and result == [0]
        # a second writer would wait: BEGIN IMMEDIATE on another connection times out
        import sqlite3

        raw = sqlite3.connect(eng.url.database, timeout=0.2, isolation_level=None)
        with pytest.raises(sqlite3.OperationalError, match="locked"):
            raw.execute("BEGIN IMMEDIATE")
        raw.close()
    eng.dispose()


def test_a_readonly_session_reads_one_snapshot(db_url):
    """Every read of a readonly session sees the database as at its first read, whatever writers commit
    meanwhile (the dashboard counts clusters and expansions in separate statements)."""
    from packings.service.db import sessions
    from packings.service.models import Run

    eng = open_database(db_url, create=True)
    with sessions(eng, readonly=True)() as r:
        before = r.query(Run).count()
        with sessions(eng).begin() as w:
            w.add(Run(n=5, params="{}", code_version="t"))
        assert r.query(Run).count() == before == 0
    with sessions(eng, readonly=True)() as r:
        assert r.query(Run).count() == 1  # a new session sees the commit
    eng.dispose()


def test_sqlite_writers_queue_for_the_lock_and_keep_the_busy_timeout(sqlite_url, monkeypatch):
    """A writer waits (polling) for another's write lock and gets it once that one commits; if the
    lock is not given back within the busy timeout, BEGIN fails with SQLite's "database is locked".
    Either way the connection's busy timeout is the configured one afterwards."""
    import threading

    from sqlalchemy.exc import OperationalError

    import packings.service.db
    from packings.service.db import sessions

    eng = open_database(sqlite_url, create=True)
    holder = make_engine(sqlite_url)
    S = sessions(eng)
    taken, release, order = threading.Event(), threading.Event(), []

    def hold():
        with sessions(holder).begin() as h:
            h.execute(text("SELECT 1"))  # BEGIN IMMEDIATE: the write lock
            taken.set()
            release.wait(30)
            order.append("holder commits")

    t = threading.Thread(target=hold)
    t.start()
    taken.wait(30)
    threading.Timer(0.2, release.set).start()
    with S.begin() as s:
        s.execute(text("SELECT 1"))
        order.append("writer begins")
        assert s.execute(text("PRAGMA busy_timeout")).scalar() == packings.service.db.SQLITE_BUSY_TIMEOUT_MS
    t.join(30)
    assert order == ["holder commits", "writer begins"]

    monkeypatch.setattr(packings.service.db, "SQLITE_BUSY_TIMEOUT_MS", 200)
    taken.clear()
    release.clear()
    t = threading.Thread(target=hold)
    t.start()
    taken.wait(30)
    with pytest.raises(OperationalError, match="locked"):
        with S.begin() as s:
            s.execute(text("SELECT 1"))
    release.set()
    t.join(30)
    with eng.connect() as c:  # every pooled connection has its busy timeout back
        assert c.exec_driver_sql("PRAGMA busy_timeout").scalar() == 200
    holder.dispose()
    eng.dispose()


def _how_found(engine) -> dict[int, tuple[str, int | None]]:
    with engine.connect() as c:
        return {i: (f, s) for i, f, s in c.execute(text("SELECT id, found_by, source_id FROM clusters"))}


def _old_transitions(source) -> list[dict]:
    """The attempts of ``source`` (at head) as rows of the ``transitions`` table of revisions before 0008."""
    from packings.service.queries import transitions

    with source.connect() as src:
        return [
            {
                "run_id": t.run_id,
                "source_id": t.source_id,
                "broken": json.dumps([list(p) for p in t.broken]),
                "direction": t.direction,
                "outcome": t.outcome,
                "target_id": t.target_id,
                "steps": t.steps,
                "new_contacts": json.dumps([list(p) for p in t.new_contacts]),
                "target_labels": None if t.labels is None else json.dumps(list(t.labels)),
            }
            for t in transitions(src)
        ]


def _copy_as_0002(source, target) -> None:
    """Every row of ``source`` (at head) into ``target`` (at 0002): the columns 0002 has, the attempts
    as its ``transitions``."""
    from sqlalchemy import MetaData

    old = MetaData()
    old.reflect(target, only=["runs", "clusters", "expansions", "transitions"])
    transitions = _old_transitions(source)
    with source.connect() as src, target.begin() as dst:
        for name in ("runs", "clusters", "expansions"):
            table = old.tables[name]
            # the contacts as JSON text (as contact_pairs reads), as revisions before 0011 hold them
            renamed = {"contact_pairs": "contact_list"}
            rows = [
                {renamed.get(k, k): v for k, v in r.items() if renamed.get(k, k) in table.c}
                for r in src.execute(Base.metadata.tables[name].select()).mappings()
            ]
            if name == "clusters":  # the coordinates as JSON too, as revisions before 0009 hold them
                for r in rows:
                    r["coords_json"] = json.dumps(np.frombuffer(r["coords"], dtype="<f8").reshape(r["n"], 3).tolist())
            dst.execute(table.insert(), rows)
        table = old.tables["transitions"]
        dst.execute(table.insert(), [{k: v for k, v in r.items() if k in table.c} for r in transitions])


def test_revision_0003_backfills_how_stored_clusters_were_found(engine, tmp_path):
    """Runs of n = 7 and 8 copied into a database at revision 0002 (this code's rows without the two
    columns) are upgraded to 0003: each run's seed (the cluster of its first expansion) becomes 'seed'
    with no source, every other cluster 'path' with the source of the first transition from another
    cluster that reached it: what the write-back had recorded.  Seeds are reached by paths too, so being
    reached is not the test."""
    fill_database(engine, 7)
    fill_database(engine, 8)
    written = _how_found(engine)
    seeds = {i for i, (f, _) in written.items() if f == "seed"}
    assert len(seeds) == 2 and len(written) == 18
    assert all(s is not None for f, s in written.values() if f == "path")
    with engine.connect() as c:
        reached = set(c.execute(text("SELECT target_id FROM edges WHERE target_id <> source_id")).scalars())
    assert seeds & reached
    with _another(engine, tmp_path) as target:
        migrate(target, "0002")
        _copy_as_0002(engine, target)
        assert current_revision(target) == "0002"
        migrate(target, "head")
        assert current_revision(target) == head_revision()
        assert _how_found(target) == written
        cols = {c["name"]: c for c in inspect(target).get_columns("clusters")}
        assert not cols["found_by"]["nullable"] and cols["source_id"]["nullable"]
        fks = {
            tuple(fk["constrained_columns"]): fk["referred_table"]
            for fk in inspect(target).get_foreign_keys("clusters")
        }
        assert fks[("source_id",)] == "clusters"
        with pytest.raises(Exception, match="(?i)foreign key"):  # source_id must name a stored cluster
            with target.begin() as c:
                c.execute(text("UPDATE clusters SET source_id = 99999 WHERE id = :i"), {"i": min(written)})


class _another:
    """An empty database on the same backend as ``engine`` (an engine), disposed of (and dropped) after."""

    def __init__(self, engine, tmp_path):
        self.engine, self.tmp_path = engine, tmp_path

    def __enter__(self):
        if self.engine.dialect.name == "sqlite":
            self.pg = None
            self.target = make_engine(f"sqlite:///{self.tmp_path / 'old.db'}")
        else:
            self.pg = pg_database()
            self.target = make_engine(self.pg.__enter__())
        return self.target

    def __exit__(self, *exc):
        self.target.dispose()
        if self.pg is not None:
            self.pg.__exit__(*exc)
        return False


def test_db_upgrade_migrates_a_0002_database_holding_clusters(engine, tmp_path):
    """A database at 0002 with a run in it is refused with the fix, and `packings db upgrade` brings it
    to head with the clusters' origins filled in."""
    fill_database(engine, 6)
    with _another(engine, tmp_path) as old:
        migrate(old, "0002")
        _copy_as_0002(engine, old)
        url = old.url.render_as_string(hide_password=False)
        assert "packings db upgrade" in one_line_error(cli("stats", "--db", url))
        r = cli("db", "upgrade", "--db", url)
        assert r.returncode == 0, r.stderr
        assert current_revision(old) == head_revision()
        assert _how_found(old) == _how_found(engine)
        assert sorted(f for f, _ in _how_found(old).values()) == ["path", "seed"]


def _table_counts(engine) -> dict:
    with engine.connect() as c:
        out = {t: c.execute(text(f"SELECT count(*) FROM {t}")).scalar() for t in ("runs", "clusters", "expansions")}
        packed = "attempts" in inspect(c).get_table_names()
        out["attempts"] = c.execute(
            text("SELECT sum(attempts) FROM attempts" if packed else "SELECT count(*) FROM transitions")
        ).scalar()
        out["by_contacts"] = sorted(
            c.execute(text("SELECT n, contacts, count(*) FROM clusters GROUP BY n, contacts")).all()
        )
        out["done"] = c.execute(text("SELECT count(*) FROM expansions WHERE status = 'done'")).scalar()
    return out


def test_migrations_go_down_and_up_on_a_populated_database(engine):
    """Every revision down to the first and back up, one at a time, on a database holding an n = 8
    run (expansions and transitions referring to its clusters, which SQLite's table rebuilds must not
    trip over): the same rows after, and the schema is head again."""
    fill_database(engine, 8)
    before = _table_counts(engine)
    revisions = ["0012", "0011", "0010", "0009", "0008", "0007", "0006", "0005", "0004", "0003", "0002", "0001"]
    for revision in revisions[1:]:
        migrate(engine, revision, down=True)
        assert current_revision(engine) == revision
        assert _table_counts(engine) == before
    for revision in reversed(revisions[:-1]):
        migrate(engine, revision)
        assert current_revision(engine) == revision
        assert _table_counts(engine) == before
    assert current_revision(engine) == head_revision()


def _transition_rows(engine) -> list[tuple]:
    """Every row of ``transitions`` (revision 0007 or before) but its id, in the order of the ids."""
    with engine.connect() as c:
        return [
            tuple(r)
            for r in c.execute(
                text(
                    "SELECT run_id, source_id, broken, direction, outcome, target_id, steps, new_contacts, "
                    "target_labels FROM transitions ORDER BY id"
                )
            )
        ]


def _paths_read(engine) -> dict:
    """What the catalogue reads of the paths: every cluster's transitions both ways, links and path keys,
    the stats, and the arrivals a task of each cluster would read."""
    from sqlalchemy import select

    import packings
    from packings.service import queries
    from packings.service.models import ClusterRow
    from packings.service.selection import KEYS

    with packings.connect(engine.url.render_as_string(hide_password=False)) as cat:
        ids = [r.id for r in cat.select()]
        with cat.session() as s:
            runs = [r["run"] for r in cat.runs()]
            arrivals = queries.arrivals_at(s, {(r, c) for r in runs for c in ids})
            values = [KEYS[k].expr() for k in ("paths_out", "paths_in", "circular", "reached")]
            keys = [tuple(r) for r in s.execute(select(ClusterRow.id, *values).order_by(ClusterRow.id))]
        return {
            "leaving": {i: cat.transitions(i) for i in ids},
            "reaching": {i: cat.transitions(i, reaching=True) for i in ids},
            "links": {i: cat.links(i) for i in ids},
            "keys": keys,
            "stats": cat.stats(),
            "arrivals": arrivals,
        }


def test_revision_0008_packs_the_transitions_and_unpacks_them_back(engine):
    """A database holding runs of n = 7 and 8 at 0007 (one row per attempt) upgraded to 0008 reads the same
    transitions, links, path keys, stats and arrivals as the database written at head; the downgrade
    gives back the same transitions rows, in the same order, and the upgrade again the same packed rows."""
    fill_database(engine, 7)
    fill_database(engine, 8)
    written = _paths_read(engine)
    with engine.connect() as c:
        packed = [tuple(r) for r in c.execute(text("SELECT * FROM attempts ORDER BY id"))]
        edges = sorted(tuple(r) for r in c.execute(text("SELECT * FROM edges")))
    assert len(packed) == 18 and edges
    rows = [tuple(r.values()) for r in _old_transitions(engine)]
    migrate(engine, "0007", down=True)
    assert not {"attempts", "edges"} & set(inspect(engine).get_table_names())
    assert _transition_rows(engine) == rows
    assert sum(1 for r in rows if r[-1] is not None) > 0  # labels went down too
    migrate(engine, "head")
    with engine.connect() as c:
        assert [tuple(r) for r in c.execute(text("SELECT * FROM attempts ORDER BY id"))] == packed
        assert sorted(tuple(r) for r in c.execute(text("SELECT * FROM edges"))) == edges
    assert _paths_read(engine) == written
    assert "transitions" not in inspect(engine).get_table_names()


def test_revision_0008_refuses_outcomes_it_cannot_pack(engine):
    """A transitions table holding an outcome this code does not number is not converted: the upgrade
    stops with the outcome named, and leaves the database at 0007."""
    fill_database(engine, 7)
    migrate(engine, "0007", down=True)
    with engine.begin() as c:
        c.execute(text("UPDATE transitions SET outcome = 'vanished' WHERE id = (SELECT min(id) FROM transitions)"))
    with pytest.raises(Exception, match="vanished"):
        migrate(engine, "head")
    assert current_revision(engine) == "0007"
    assert "attempts" not in inspect(engine).get_table_names()


def test_revision_0009_drops_the_json_coordinates_and_the_downgrade_writes_them_again(engine):
    """The coordinates are stored once (clusters.coords) from 0009 on; going down to 0008 writes
    coords_json again, as the service wrote it: numbers that read back equal to coords, bit for bit."""
    fill_database(engine, 7)
    assert "coords_json" not in {c["name"] for c in inspect(engine).get_columns("clusters")}
    migrate(engine, "0008", down=True)
    with engine.connect() as c:
        rows = c.execute(text("SELECT n, coords, coords_json FROM clusters")).all()
    assert len(rows) == 5
    for n, coords, coords_json in rows:
        x = np.frombuffer(coords, dtype="<f8").reshape(n, 3)
        assert coords_json == json.dumps(x.tolist()) and np.array_equal(np.array(json.loads(coords_json)), x)
    assert not {c["name"]: c for c in inspect(engine).get_columns("clusters")}["coords_json"]["nullable"]
    migrate(engine, "head")
    assert "coords_json" not in {c["name"] for c in inspect(engine).get_columns("clusters")}


def test_revision_0011_packs_the_contact_lists_and_the_downgrade_writes_them_again(engine):
    """From 0011 on a cluster's contacts are two bytes a pair (clusters.contact_pairs), read as the same JSON
    text; going down to 0010 writes contact_list again exactly as the service wrote it, and up again the
    same bytes; what the catalogue gives is the same at both ends."""
    import packings

    fill_database(engine, 7)
    fill_database(engine, 8)
    url = engine.url.render_as_string(hide_password=False)
    with packings.connect(url) as cat:
        given = [r.record() for r in cat.select()]
    with engine.connect() as c:
        packed = c.execute(text("SELECT id, contact_pairs FROM clusters ORDER BY id")).all()
    assert len(packed) == 18 and all(len(bytes(p)) == 2 * m["contacts"] for (_, p), m in zip(packed, given))
    assert "contact_list" not in {c["name"] for c in inspect(engine).get_columns("clusters")}
    migrate(engine, "0010", down=True)
    with engine.connect() as c:
        texts = c.execute(text("SELECT id, contact_list FROM clusters ORDER BY id")).all()
    assert [t for _, t in texts] == [json.dumps(m["contact_list"]) for m in given]
    assert not {c["name"]: c for c in inspect(engine).get_columns("clusters")}["contact_list"]["nullable"]
    assert "contact_pairs" not in {c["name"] for c in inspect(engine).get_columns("clusters")}
    migrate(engine, "head")
    with engine.connect() as c:
        again = c.execute(text("SELECT id, contact_pairs FROM clusters ORDER BY id")).all()
    assert [(i, bytes(p)) for i, p in again] == [(i, bytes(p)) for i, p in packed]
    with packings.connect(url) as cat:
        assert [r.record() for r in cat.select()] == given


REPOSITORY = Path(__file__).resolve().parents[2]


def _alembic(*args: str):
    alembic = os.path.join(os.path.dirname(sys.executable), "alembic")
    return subprocess.run([alembic, *args], cwd=REPOSITORY, capture_output=True, text=True, timeout=300)


@pytest.mark.skipif(not (REPOSITORY / "alembic.ini").is_file(), reason="the alembic command needs the repository")
def test_the_alembic_command_logs_and_goes_both_ways(engine):
    fill_database(engine, 7)
    url = engine.url.render_as_string(hide_password=False)
    r = _alembic("-x", f"db={url}", "downgrade", "-1")
    assert r.returncode == 0, r.stderr
    assert f"Running downgrade {head_revision()} -> " in r.stderr  # env.py applies alembic.ini's logging
    r = _alembic("-x", f"db={url}", "upgrade", "head")
    assert r.returncode == 0 and f"-> {head_revision()}" in r.stderr, r.stderr
    assert current_revision(engine) == head_revision()


def test_alembic_sql_mode_honours_the_database_given():
    pg = _alembic("-x", "db=postgresql://u@127.0.0.1/x", "upgrade", "head", "--sql")
    lite = _alembic("-x", "db=sqlite:///x.db", "upgrade", "head", "--sql")
    assert pg.returncode == 0 and lite.returncode == 0, pg.stderr + lite.stderr
    assert "SERIAL" in pg.stdout and "SERIAL" not in lite.stdout  # PostgreSQL's DDL, not the ini's SQLite


def test_revision_0005_renumbers_the_stored_geometries_by_shape(engine):
    """A database whose geometries of one contact graph were numbered in the order found (before 0005)
    is renumbered in embedding order by the upgrade, whatever the old numbers; a downgrade leaves them."""
    from packings.service.db import sessions

    S = sessions(engine)
    ids = store_chains(S, (0, 1, 2, 3, 4), seed=3)
    migrate(engine, "0004", down=True)
    old = {0: 3, 1: 0, 2: 4, 3: 2, 4: 1}  # as an older run could have found them
    with engine.begin() as c:
        for k, cid in ids.items():
            c.execute(text("UPDATE clusters SET embedding = :e WHERE id = :i"), {"e": -1 - old[k], "i": cid})
        c.execute(text("UPDATE clusters SET embedding = -1 - embedding"))
    assert embeddings(S, ids) == old
    migrate(engine, "0005")
    assert embeddings(S, ids) == {k: k for k in range(5)}
    migrate(engine, "0004", down=True)
    assert embeddings(S, ids) == {k: k for k in range(5)}
    migrate(engine, "head")
