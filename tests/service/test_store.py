"""The frontier and the write-back: leases, idempotence, failures, resume, concurrency."""

from __future__ import annotations

import multiprocessing as mp
import os
import re
import socket
from collections import Counter

import numpy as np
import pytest
from sqlalchemy import event, func, select

from packings.service import queries, store
from packings.service.db import make_engine, sessions
from packings.service.models import (
    DONE,
    FAILED,
    LEASED,
    PENDING,
    AttemptsRow,
    ClusterRow,
    Edge,
    ExpansionRow,
    Run,
)
from packings.service.owners import RunBusy
from packings.service.paths_codec import Attempt
from packings.service.tasks import run_expansion
from packings.workers.params import Params
from tests.helpers import catalogue, embeddings, fill_database, store_chains, wait_for

OWNER = f"{socket.gethostname()}:{os.getpid()}:test"


def snapshot(engine) -> dict:
    """Every row of every table, for comparing database states exactly."""
    out = {}
    with sessions(engine)() as s:
        for model in (Run, ClusterRow, ExpansionRow, AttemptsRow, Edge):
            cols = [c for c in model.__table__.columns if c.name not in ("heartbeat_at",)]
            out[model.__tablename__] = sorted(tuple(r) for r in s.execute(select(*cols)).all())
    return out


@pytest.fixture
def run8(engine):
    S = sessions(engine)
    info = store.start_run(S, 8, Params(), OWNER)
    return S, info


def test_a_new_run_holds_the_seed_and_one_pending_expansion(run8):
    S, info = run8
    assert info.created
    with S() as s:
        assert queries.frontier(s, info.id) == {PENDING: 1}
        c = s.execute(select(ClusterRow)).scalar_one()
        assert c.n == 8 and c.contacts == 18 and c.embedding == 0 and not c.singular
        core = c.to_core()
        assert core.coords.dtype == np.float64 and core.m == 18


def test_coordinates_read_back_bit_exactly(run8):
    from packings.workers.seeds import seed_cluster

    S, _ = run8
    with S() as s:
        c = s.execute(select(ClusterRow)).scalar_one()
        assert np.array_equal(c.to_core().coords, seed_cluster(8).coords)


def test_claim_leases_with_fresh_tokens(run8):
    S, info = run8
    [(eid, token)] = store.claim(S, info.id, OWNER, 5)
    assert store.claim(S, info.id, OWNER, 5) == []
    with S() as s:
        e = s.get(ExpansionRow, eid)
        assert e.status == LEASED and e.lease_token == token and e.attempts == 1 and e.lease_owner == OWNER


def _plan(engine, query) -> str:
    """The backend's plan of ``query`` (SQLite's EXPLAIN QUERY PLAN), as text. PostgreSQL's is its generic
    plan, the one made for any value of the parameters, which a statement prepared and run many times may
    be given: prepared with $1, $2, ... for the bound values and explained under force_generic_plan."""
    from sqlalchemy import text

    compiled = query.compile(engine)
    if engine.dialect.name == "sqlite":
        sql = str(query.compile(engine, compile_kwargs={"literal_binds": True}))
        with engine.connect() as c:
            return "\n".join(" ".join(map(str, r)) for r in c.execute(text("EXPLAIN QUERY PLAN " + sql)))
    names: list[str] = []

    def number(m) -> str:
        if m.group(1) not in names:
            names.append(m.group(1))
        return f"${names.index(m.group(1)) + 1}"

    sql = re.sub(r"%\((\w+)\)s", number, str(compiled))
    values = ", ".join(f"'{v}'" if isinstance(v, str) else str(v) for v in (compiled.params[k] for k in names))
    with engine.begin() as c:
        c.exec_driver_sql("SET LOCAL plan_cache_mode = force_generic_plan")
        c.exec_driver_sql(f"PREPARE claim_plan AS {sql}")
        rows = c.exec_driver_sql(f"EXPLAIN EXECUTE claim_plan({values})").all()
        c.exec_driver_sql("DEALLOCATE claim_plan")
    return "\n".join(r[0] for r in rows)


def test_a_claim_reads_the_pending_expansions_from_their_index_lowest_first(run8, engine):
    """With 20,000 expansions done before 2,000 pending ones (as in a long run), a claim takes the lowest
    pending ids, reading them from an index in order (PostgreSQL: ix_expansions_pending, in the plan made for
    any run id and limit too), neither sorting nor walking the ids of those done (what PostgreSQL did with
    ix_expansions_run_status alone, and would do with the status bound as a parameter)."""
    from benchmarks.frontier import fill

    S, info = run8
    store.claim(S, info.id, OWNER, 1)  # the seed's expansion, out of the way
    fill(engine, info.id, pending=2000, done=20000)
    with S() as s:
        pending = s.scalars(
            select(ExpansionRow.id)
            .where(ExpansionRow.run_id == info.id, ExpansionRow.status == PENDING)
            .order_by(ExpansionRow.id)
        ).all()
    plan = _plan(engine, store.claimable(info.id, 64))
    if engine.dialect.name == "sqlite":  # either index gives the pending ids in order (SQLite's end in the rowid)
        assert "ix_expansions_pending" in plan or "ix_expansions_run_status (run_id=? AND status=?)" in plan, plan
    else:
        assert "ix_expansions_pending" in plan, plan
    assert "TEMP B-TREE" not in plan and "Sort" not in plan and "pkey" not in plan, plan
    assert [i for i, _ in store.claim(S, info.id, OWNER, 64)] == pending[:64]
    assert [i for i, _ in store.claim(S, info.id, OWNER, 64)] == pending[64:128]


def test_a_task_run_twice_changes_nothing_the_second_time(run8, engine):
    S, info = run8
    [(eid, token)] = store.claim(S, info.id, OWNER, 1)
    first = run_expansion(S, eid, token)
    assert first["new_clusters"] > 0 and not first.get("stale")
    after_once = snapshot(engine)
    second = run_expansion(S, eid, token)
    assert second == {"expansion": eid, "stale": True}
    assert snapshot(engine) == after_once
    # also the write-back itself, given a result computed before the first write landed: its inserts
    # are rolled back when the lease turns out to be gone
    from packings.workers.expand import expand
    from packings.workers.seeds import seed_cluster

    seed = seed_cluster(8, Params())
    task = store.Task(eid, info.id, 1, seed, Params())
    assert store.record_expansion(S, task, token, expand(seed, Params()), 0.0, "w") is None
    assert snapshot(engine) == after_once


@pytest.mark.parametrize("n, count, hyperstatic", [(9, 52, 0), (10, 263, 3)])
def test_a_run_takes_each_path_that_arrived_from_its_end_and_stores_what_following_it_gives(
    engine, n, count, hyperstatic
):
    """A run of n = 9 (every cluster but one regular) or n = 10 (three hyperstatic clusters too) follows
    each path between two first-order rigid clusters from one end only: where a path arrived at a cluster
    before it was expanded, that cluster's attempt on the contacts formed is taken from it
    (the attempts' labels, store.load_tasks' arrivals).  Every attempt stored is what following
    every path gives: the same outcome, a rigid endpoint the stored target, the same contacts formed, and
    labels relabelling the endpoint onto the target as stored."""
    import json

    from packings.workers import kernels
    from packings.workers.expand import expand
    from packings.workers.identity import same_geometry

    params = Params()
    run_id = fill_database(engine, n)
    with sessions(engine)() as s:
        d = queries.run_diagnostics(s, run_id)
        stored_clusters = {r.id: r for r in s.execute(select(ClusterRow).where(ClusterRow.n == n)).scalars()}
        rows = list(queries.transitions(s, run=run_id))
        took = {
            cid: json.loads(o).get("paths_retraced", 0)
            for cid, o in s.execute(
                select(ExpansionRow.cluster_id, ExpansionRow.outcomes).where(ExpansionRow.run_id == run_id)
            )
        }
    assert len(stored_clusters) == count and d["paths_retraced"] > 0.2 * d["paths_followed"]
    many = {cid for cid, r in stored_clusters.items() if r.contacts > 3 * n - 6}
    assert len(many) == hyperstatic
    if hyperstatic:  # hyperstatic clusters took paths from the other end too
        assert sum(took[cid] for cid in many) > 0
    clusters = {cid: r.to_core() for cid, r in stored_clusters.items()}
    stored = {(t.source_id, t.broken, t.direction): (t.outcome, t.target_id, t.new_contacts, t.labels) for t in rows}
    assert len(stored) == len(rows)
    labelled = Counter()
    for cid, c in clusters.items():
        for e in expand(c, params).endpoints:  # every path followed
            out, target, new, labels = stored.pop((cid, tuple(map(tuple, e.broken)), e.direction))
            assert out == e.outcome and new == tuple(map(tuple, e.new_contacts))
            if out == "rigid":
                assert same_geometry(e.cluster, clusters[target], params.tol_d)
            if labels is not None:
                y = clusters[target].coords[list(labels)]
                x = e.cluster.coords
                assert kernels.aligned_max_error(x - x.mean(axis=0), y - y.mean(axis=0)) <= params.tol_d
                labelled[(cid in many, target in many)] += 1
    assert not stored and sum(labelled.values()) >= d["paths_retraced"]
    if hyperstatic:  # paths between a hyperstatic cluster and a regular one, both ways, are retraceable too
        assert labelled[(True, False)] > 0 and labelled[(False, True)] > 0, labelled
    assert labelled[(True, True)] == 0  # and paths between two hyperstatic ones are not


def test_an_expansions_outcomes_leave_out_the_counts_of_none_and_the_diagnostics_give_them(engine):
    """expansions.outcomes holds no zero count (a count of none is left out, as an outcome no attempt had
    is); the run's diagnostics still give every path count, 0 where the run had none, and sum the rest."""
    import json

    run_id = fill_database(engine, 8)
    with sessions(engine)() as s:
        stored = [json.loads(o) for o in s.execute(select(ExpansionRow.outcomes)).scalars()]
        d = queries.run_diagnostics(s, run_id)
    assert len(stored) == 13 and all(v > 0 for o in stored for v in o.values())
    assert any("paths_retraced" not in o for o in stored)
    for key in ("paths_by_symmetry", "paths_retraced", "widened_paths"):
        assert d[key] == sum(o.get(key, 0) for o in stored)
    assert d["rigid"] == sum(o.get("rigid", 0) for o in stored) > 0


def test_a_task_reads_the_paths_that_arrived_through_the_key_of_edges(sqlite_url):
    """store.load_tasks reads a cluster's arrivals by the key of edges (target first), then the attempts
    rows of those sources by their unique index: no scan of either table (a tenth of a second a task at
    the end of n = 12 with a scan, the whole n = 13 run's millions later)."""
    import packings.service.db

    engine = packings.service.db.open_database(sqlite_url, create=True)
    with engine.connect() as conn:
        sql = queries._ARRIVALS_DATA.params(cids=[1, 2, 3], runs=[1]).compile(
            engine, compile_kwargs={"literal_binds": True}
        )
        plan = [str(row) for row in conn.exec_driver_sql(f"EXPLAIN QUERY PLAN {sql}").all()]
    assert any("SEARCH edges USING PRIMARY KEY (target_id=?)" in row for row in plan), plan
    assert any("SEARCH attempts USING INDEX" in row and "(source_id=? AND run_id=?)" in row for row in plan), plan
    assert not any("SCAN" in row and "TEMP" not in row for row in plan), plan


def test_a_task_is_read_without_the_write_lock(sqlite_url, monkeypatch):
    """Workers read their task with read-only sessions: on SQLite those begin DEFERRED, so a task is
    read while another worker holds the write lock (a write session would wait for it)."""
    from sqlalchemy.exc import OperationalError

    import packings.service.db

    monkeypatch.setattr(packings.service.db, "SQLITE_BUSY_TIMEOUT_MS", 200)  # so that waiting for the lock fails fast
    engine = packings.service.db.open_database(sqlite_url, create=True)
    S = sessions(engine)
    info = store.start_run(S, 8, Params(), OWNER)
    [(eid, token)] = store.claim(S, info.id, OWNER, 1)
    other = make_engine(sqlite_url)
    with sessions(other).begin() as holder:  # BEGIN IMMEDIATE: the write lock, held by "another worker"
        holder.execute(select(func.count()).select_from(Run))
        task = store.load_task(sessions(engine, readonly=True), eid, token)
        assert task is not None and task.expansion_id == eid and task.cluster.n == 8
        with pytest.raises(OperationalError, match="locked"):
            store.load_task(S, eid, token)
    other.dispose()
    engine.dispose()


def test_write_back_is_all_or_nothing(run8, engine, monkeypatch):
    S, info = run8
    [(eid, token)] = store.claim(S, info.id, OWNER, 1)
    before = snapshot(engine)
    real = store.ensure_expansions
    inserted = []

    def dying(session, run_id, cluster_ids, new=()):
        inserted.extend([*cluster_ids, *new])  # the clusters' rows are inserted by now (Core statements, no flush)
        raise RuntimeError("worker died mid-write")

    monkeypatch.setattr(store, "ensure_expansions", dying)
    with pytest.raises(RuntimeError):
        run_expansion(S, eid, token)
    assert len(inserted) >= 2  # the clusters were written (flushed) before the failure ...
    assert snapshot(engine) == before  # ... and none of them is left
    monkeypatch.setattr(store, "ensure_expansions", real)
    assert not run_expansion(S, eid, token).get("stale")


def _two_finished(S, info) -> list:
    """Two expansions of the run, leased and expanded, not yet written back (as a task holds them)."""
    from packings.service.tasks import run_loaded

    [(eid, token)] = store.claim(S, info.id, OWNER, 1)
    run_expansion(S, eid, token)  # the seed: the clusters it reaches become pending
    leases = store.claim(S, info.id, OWNER, 2)
    assert len(leases) == 2
    tasks = store.load_tasks(S, leases)
    return [run_loaded(tasks[e], t) for e, t in leases]


def test_the_write_back_computes_no_facts_while_it_holds_the_lock(run8, engine, monkeypatch):
    """A new cluster's facts (gap, lattice, serialised coordinates) are computed before the write-back's
    transaction begins; inside it only SQL and the geometric match run.  The clusters stored have the
    facts a direct computation gives."""
    from sqlalchemy import event

    S, info = run8
    finished = _two_finished(S, info)
    with S() as s:  # closed before the write-back: an open SQLite session holds the write lock
        before = set(s.execute(select(ClusterRow.id)).scalars())
    in_transaction, during = [False], []
    event.listen(engine, "begin", lambda conn: in_transaction.__setitem__(0, True))
    for end in ("commit", "rollback"):
        event.listen(engine, end, lambda conn: in_transaction.__setitem__(0, False))
    real = store.cluster_values

    def watched(c, rig):
        during.append(in_transaction[0])
        return real(c, rig)

    monkeypatch.setattr(store, "cluster_values", watched)
    summaries = store.record_expansions(S, finished, "w")
    new = sum(x["new_clusters"] for x in summaries)
    assert new > 0 and len(during) >= new and not any(during)
    with S() as s:
        for row in s.execute(select(ClusterRow).where(ClusterRow.id.notin_(before))).scalars():
            core = row.to_core()
            assert row.lattice == store.lattice_value(core)
            assert row.min_gap == pytest.approx(core.min_gap(), rel=0, abs=0)


def test_a_tasks_expansions_are_written_back_together_or_not_at_all(run8, engine, monkeypatch):
    """One transaction for a task: when writing its second expansion fails, nothing of the first is
    left either (not its new clusters, not its attempts, not its being done)."""
    S, info = run8
    first, second = _two_finished(S, info)
    before = snapshot(engine)
    in_first = len(store.distinct_endpoints(first.expansion)[0])
    real, calls = store.insert_or_match, []

    def dying(session, c, *a, **kw):
        calls.append(c)
        if len(calls) > in_first:  # the second expansion's first endpoint
            raise RuntimeError("worker died mid-write")
        return real(session, c, *a, **kw)

    monkeypatch.setattr(store, "insert_or_match", dying)
    with pytest.raises(RuntimeError):
        store.record_expansions(S, [first, second], "w")
    assert in_first >= 1 and len(calls) == in_first + 1
    assert snapshot(engine) == before
    monkeypatch.setattr(store, "insert_or_match", real)
    summaries = store.record_expansions(S, [first, second], "w")
    assert [s["expansion"] for s in summaries] == [first.task.expansion_id, second.task.expansion_id]
    with S() as s:
        assert {s.get(ExpansionRow, f.task.expansion_id).status for f in (first, second)} == {DONE}
        sources = set(s.execute(select(AttemptsRow.source_id)).scalars())
    assert {first.task.cluster_id, second.task.cluster_id} <= sources


def test_a_stale_expansion_is_left_out_of_its_tasks_write_back(run8, engine):
    """A task's expansion whose lease went to another is not written; the others of the task are."""
    S, info = run8
    live, stale = _two_finished(S, info)
    with S.begin() as s:
        s.get(ExpansionRow, stale.task.expansion_id).lease_token = "another-task"
    summaries = store.record_expansions(S, [live, stale], "w")
    assert summaries[1] is None and summaries[0]["expansion"] == live.task.expansion_id
    with S() as s:
        assert s.get(ExpansionRow, live.task.expansion_id).status == DONE
        e = s.get(ExpansionRow, stale.task.expansion_id)
        assert e.status == LEASED and e.lease_token == "another-task" and e.outcomes is None
        sources = set(s.execute(select(AttemptsRow.source_id)).scalars())
    assert live.task.cluster_id in sources and stale.task.cluster_id not in sources


def test_a_result_for_a_lease_given_to_another_is_rejected(run8, engine):
    S, info = run8
    [(eid, old)] = store.claim(S, info.id, OWNER, 1)
    # a new coordinator takes the run over (the first one is gone): the lease goes back to pending
    with S.begin() as s:
        s.get(Run, info.id).coordinator = f"{socket.gethostname()}:999999999:gone"  # a process that is not alive
    new_owner = f"{socket.gethostname()}:{os.getpid()}:new"
    info2 = store.start_run(S, 8, Params(), new_owner)
    assert not info2.created and info2.id == info.id
    with S() as s:
        assert queries.frontier(s, info.id) == {PENDING: 1}
    [(eid2, new)] = store.claim(S, info.id, new_owner, 1)
    assert eid2 == eid and new != old
    before = snapshot(engine)
    assert run_expansion(S, eid, old)["stale"]
    assert snapshot(engine) == before
    assert not run_expansion(S, eid, new).get("stale")


def test_a_live_coordinator_keeps_its_run(run8):
    S, info = run8
    with pytest.raises(RunBusy, match="being driven"):
        store.start_run(S, 8, Params(), f"{socket.gethostname()}:{os.getpid()}:other")


def test_failed_tasks_are_retried_then_marked_failed(run8):
    S, info = run8
    for attempt in (1, 2, 3):
        [(eid, token)] = store.claim(S, info.id, OWNER, 1)
        status = store.release(S, eid, token, f"ValueError: boom {attempt}", max_attempts=3)
        assert status == (FAILED if attempt == 3 else PENDING)
    assert store.claim(S, info.id, OWNER, 1) == []
    with S() as s:
        e = s.get(ExpansionRow, eid)
        assert e.status == FAILED and e.attempts == 3 and e.error == "ValueError: boom 3"
    assert store.finish_run(S, info.id, OWNER, 1.0) == "incomplete"
    assert store.release(S, eid, token, "late", 3) is None  # no longer leased: ignored


def test_the_whole_run_in_process_gives_the_paper_counts(engine, paper_counts):
    run_id = fill_database(engine, 8)
    with sessions(engine)() as s:
        assert queries.run_counts(s, run_id) == {18: 13}
        assert s.get(Run, run_id).status == "complete"
        d = queries.run_diagnostics(s, run_id)
        assert d["expansions"] == 13 and d["failed_tasks"] == 0 and d["paths_followed"] > 0
        # a path not followed, as the image of one followed under a symmetry of its cluster, is a transition too
        every = list(queries.transitions(s, run=run_id))
        with_path = sum(t.direction != 0 for t in every)
        assert s.execute(select(func.sum(AttemptsRow.paths)).where(AttemptsRow.run_id == run_id)).scalar() == with_path
        assert d["paths_by_symmetry"] > 0 and d["paths_retraced"] > 0
        assert d["paths_followed"] + d["paths_by_symmetry"] + d["paths_retraced"] == with_path
        # every rigid transition points at a stored cluster of the run, and every cluster is reached
        assert not [t for t in every if t.outcome == "rigid" and t.target_id is None]
        assert s.execute(select(func.count()).select_from(ClusterRow).where(ClusterRow.n == 8)).scalar() == 13
    assert paper_counts["totals"]["8"] == 13


def _insert_all(url: str, clusters: list[dict], seed: int, barrier) -> list[tuple[int, bool]]:
    """One process: insert every cluster (relabelled, rotated, in its own order), one transaction each."""
    from packings.workers.cluster import Cluster as Core
    from packings.workers.identity import certificate_key
    from packings.workers.rigidity import rigidity

    rng = np.random.default_rng(seed)
    engine = make_engine(url)
    S = sessions(engine)
    params = Params()
    barrier.wait()
    out = []
    for k in rng.permutation(len(clusters)):
        c = Core.from_dict(clusters[k])
        p = rng.permutation(c.n)
        inv = np.argsort(p)
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        c = Core(c.coords[p] @ q.T + rng.normal(size=3), tuple((int(inv[i]), int(inv[j])) for i, j in c.contacts))
        rig = rigidity(c.coords, c.contacts, params)
        with S.begin() as s:
            store.lock_certificates(s, [(c.n, certificate_key(c))])
            out.append(store.insert_or_match(s, c, rig, None, params.tol_d, found_by="seed", source_id=None))
    engine.dispose()
    return out


def test_concurrent_inserts_of_overlapping_clusters_make_no_duplicates(engine):
    """Several processes insert the same 13 clusters (each relabelled and moved) at once."""
    clusters = [c.to_dict() for c in catalogue(8).clusters]
    url = engine.url.render_as_string(hide_password=False)
    ctx = mp.get_context("spawn")
    k = 4
    with ctx.Manager() as m:
        barrier = m.Barrier(k)
        with ctx.Pool(k) as pool:
            results = pool.starmap(_insert_all, [(url, clusters, seed, barrier) for seed in range(k)])
    with sessions(engine)() as s:
        rows = s.execute(select(ClusterRow.certificate, ClusterRow.embedding)).all()
    assert len(rows) == 13 and len(set(rows)) == 13
    new = [is_new for r in results for _, is_new in r]
    assert sum(new) == 13 and len(new) == 13 * k
    assert len({cid for r in results for cid, _ in r}) == 13


def test_the_coordinator_heartbeat_runs_on_its_own(run8, monkeypatch):
    """The run's heartbeat advances while the coordinator waits for long tasks."""
    from packings.service import coordinator

    S, info = run8
    monkeypatch.setattr(coordinator, "HEARTBEAT_SECONDS", 0.05)
    with S() as s:
        first = s.get(Run, info.id).heartbeat_at
    beat = coordinator._Heartbeat(S, info.id, OWNER)

    def beaten() -> bool:
        with S() as s:
            return s.get(Run, info.id).heartbeat_at > first

    try:
        wait_for(beaten, timeout=60, what="the heartbeat advances")
    finally:
        beat.stop()


def test_a_second_run_reaches_the_clusters_another_run_stored(engine):
    """Runs of the same n share clusters: a run with other parameters finds every cluster stored
    already, stores none again, and gives each its own expansion (those found by another run are
    checked for one; those it inserts get one at once)."""
    import dataclasses

    first = fill_database(engine, 8)
    other = dataclasses.replace(Params(), probe_stall=Params().probe_stall + 1)  # changes no result
    second = fill_database(engine, 8, params=other)
    assert second != first
    with sessions(engine)() as s:
        assert s.execute(select(func.count()).select_from(ClusterRow)).scalar_one() == 13
        for run in (first, second):
            assert queries.frontier(s, run) == {DONE: 13}
            assert queries.run_counts(s, run) == {18: 13}
        found = dict(s.execute(select(ClusterRow.found_in_run, func.count()).group_by(ClusterRow.found_in_run)).all())
        assert found == {first: 13}
        tried = {
            run: s.execute(select(func.sum(AttemptsRow.attempts)).where(AttemptsRow.run_id == run)).scalar_one()
            for run in (first, second)
        }
        assert tried[first] == tried[second] > 0


def test_attempts_are_inserted_and_read_back_on_every_backend(run8, engine, monkeypatch):
    """store.insert_attempts writes one attempts row per expansion (the driver's executemany on SQLite, a
    Core insert elsewhere, a chunk at a time: here chunks of 2) and its edges; queries.transitions reads each
    attempt back as it was given, from its source, from its target and from its run, in order."""
    import packings.service.db

    S, info = run8
    with S() as s:
        seed = s.execute(select(ClusterRow.id)).scalar_one()
    one = [
        Attempt(((0, 1),), 1, "rigid", seed, 7, ((2, 5),), (1, 0, 2, 3, 4, 5, 6, 7)),
        Attempt(((0, 1), (2, 3)), -1, "circular", seed, 3, ()),
        *[Attempt(((k, 7),), 0, "not-1d", None, 0, ()) for k in range(5)],
    ]
    # two more runs: (source, run) is the key
    other, third = (store.start_run(S, 8, Params(max_break=k), OWNER).id for k in (2, 3))
    monkeypatch.setattr(packings.service.db, "INSERT_CHUNK", 2)
    statements = []

    def count(conn, cursor, statement, *args):
        if statement.lstrip().upper().startswith(("INSERT INTO ATTEMPTS", "INSERT INTO EDGES")):
            statements.append(statement.split()[2].lower())

    event.listen(engine, "before_cursor_execute", count)
    try:
        with engine.begin() as conn:
            store.insert_attempts(conn, ((run, seed, 8, one) for run in (info.id, other, third)))
            store.insert_attempts(conn, [])
    finally:
        event.remove(engine, "before_cursor_execute", count)
    assert statements.count("attempts") == 2 and statements.count("edges") == 2  # 3 rows in chunks of 2
    with S() as s:
        for run in (info.id, other, third):
            back = list(queries.transitions(s, run=run))
            assert [t.attempt for t in back] == list(range(len(one)))
            assert [
                Attempt(t.broken, t.direction, t.outcome, t.target_id, t.steps, t.new_contacts, t.labels) for t in back
            ] == one
        assert [t.attempt for t in queries.transitions(s, target=seed)] == [0, 1] * 3
        assert len(list(queries.transitions(s, source=seed))) == 3 * len(one)
        assert sorted(tuple(r) for r in s.execute(select(Edge.run_id, Edge.paths, Edge.labelled))) == [
            (run, 2, 1) for run in sorted((info.id, other, third))
        ]
        counts = s.execute(select(AttemptsRow.attempts, AttemptsRow.paths, AttemptsRow.circular)).all()
        assert counts == [(7, 2, 1)] * 3
        assert queries.arrivals_at(s, {(info.id, seed)}) == {
            (info.id, seed): [(seed, ((0, 1),), ((2, 5),), 7, one[0].labels)]
        }


def test_a_cluster_written_back_is_read_back_as_the_same_object(run8, engine, monkeypatch):
    """A row inserted from a cluster is read back (stored_with) as that very cluster, so what was computed
    from it (its canonical form) is not computed again; the clusters kept are bounded."""
    import packings.service.models as models
    from packings.workers.expand import expand
    from packings.workers.identity import certificate_key

    S, info = run8
    with S() as s:
        seed = s.execute(select(ClusterRow)).scalar_one().to_core()
    ex = expand(seed, Params())
    new = [ex.endpoints[i].cluster for i in ex.distinct()]
    with engine.begin() as conn:
        for c in new:
            store.insert_or_match(
                conn, c, ex.endpoints[0].rigidity, info.id, Params().tol_d, found_by="path", source_id=None
            )
    with engine.connect() as conn:
        stored = store.stored_with(conn, 8, {certificate_key(c) for c in new})
    read = [r.cluster for rows in stored.values() for r in rows]
    assert all(any(r is c for r in read) for c in new)
    monkeypatch.setattr(models, "CORE_CLUSTERS", 3)
    monkeypatch.setattr(models, "_CORE", {})
    for c in new:
        models.core_cluster(8, np.ascontiguousarray(c.coords, dtype="<f8").tobytes(), store.contacts_json(c.contacts))
    assert len(models._CORE) <= 3


@pytest.mark.parametrize(
    "pairs",
    [(), ((0, 1),), ((0, 1), (2, 5)), [(3, 4), (1, 9)], ((np.int64(2), np.int64(7)),), [[0, 3]], ((0, 1), [2, 3])],
)
def test_contacts_are_written_as_json_writes_them(pairs):
    """Whatever the pairs are given as, the text is json.dumps's, and it reads back as the pairs; pairs given
    as a tuple of tuples are remembered: asked again, the cache answers, with the same text."""
    import json

    store._contacts_json.cache_clear()
    written = json.dumps([[int(i), int(j)] for i, j in pairs])
    assert store.contacts_json(pairs) == written and json.loads(written) == [[int(i), int(j)] for i, j in pairs]
    assert store.contacts_json(pairs) == written  # a second time
    remembered = isinstance(pairs, tuple) and all(isinstance(p, tuple) for p in pairs)
    assert store._contacts_json.cache_info().hits == (1 if remembered else 0)


def test_a_missed_heartbeat_is_logged_and_counted(monkeypatch, caplog):
    """The coordinator's heartbeat thread goes on after a failed beat, and says so in the log."""
    import logging

    import packings.service.coordinator as coordinator

    def failing(*args):
        raise RuntimeError("database is locked")

    monkeypatch.setattr(coordinator, "HEARTBEAT_SECONDS", 0.01)
    monkeypatch.setattr(coordinator.store, "heartbeat", failing)
    with caplog.at_level(logging.WARNING, logger="packings.service.coordinator"):
        beat = coordinator._Heartbeat(None, 7, "here:1")
        try:
            wait_for(lambda: beat.missed >= 2, timeout=60, interval=0.01, what="two heartbeats missed")
        finally:
            beat.stop()
    assert beat.missed >= 2 and beat.is_alive() is False
    assert any(
        "run 7: heartbeat 1 missed" in r.getMessage() and "database is locked" in r.getMessage() for r in caplog.records
    )


def test_a_stored_traceback_has_a_one_line_summary():
    from packings.service.tasks import error_text, summary

    try:
        raise ValueError("boom\nsecond line of the message")
    except ValueError as exc:
        text = error_text(exc)
    assert text.startswith("Traceback (most recent call last)") and "test_a_stored_traceback" in text
    assert summary(text) == "ValueError: boom"
    assert summary("KilledWorker: lost\ndetails") == "KilledWorker: lost" and summary("") == ""


def test_a_runs_time_is_kept_across_coordinators_and_recorded_while_it_runs(run8):
    """The heartbeat records the run's time so far (status shows it while the run goes on); letting
    the run go records it; the next coordinator starts from it."""
    S, info = run8
    assert info.seconds == 0.0
    store.heartbeat(S, info.id, OWNER, 4.5)
    with S() as s:
        assert s.get(Run, info.id).seconds == 4.5
    store.abandon(S, info.id, OWNER, 6.0)
    again = store.start_run(S, 8, Params(), OWNER + "-2")
    assert again.seconds == 6.0
    store.heartbeat(S, info.id, OWNER, 99.0)  # no longer the holder: changes nothing
    assert store.finish_run(S, info.id, OWNER + "-2", 7.25) in ("running", "complete")
    with S() as s:
        assert s.get(Run, info.id).seconds == 7.25


@pytest.mark.parametrize(
    "order, one_transaction",
    [((0, 1, 2, 3, 4), False), ((4, 3, 2, 1, 0), False), ((2, 4, 0, 3, 1), False), ((3, 0, 4, 1, 2), True)],
)
def test_embedding_numbers_follow_geometry_whatever_order_they_are_stored_in(engine, order, one_transaction):
    """Five geometries of one contact graph stored in any order, one write-back each or several in one
    (whose stored rows the store keeps up to date), get the same (certificate, embedding) keys: 0 for
    the most compact; the stored ones are renumbered as a new one goes between them."""
    S = sessions(engine)
    ids = store_chains(S, order, seed=sum(order[:2]), one_transaction=one_transaction)
    assert embeddings(S, ids) == {k: k for k in range(5)}


def _stored(engine, n: int) -> tuple[list, list]:
    """The clusters of n (key, coordinates) and the transitions (source key, attempt, target key, labels), by key."""
    with sessions(engine)() as s:
        keys = {
            r.id: (r.certificate, r.embedding) for r in s.execute(select(ClusterRow).where(ClusterRow.n == n)).scalars()
        }
        clusters = sorted((keys[r.id], r.coords) for r in s.execute(select(ClusterRow)).scalars())
        attempts = sorted(
            (
                keys[a.source_id],
                a.broken,
                a.direction,
                a.outcome,
                a.steps,
                a.new_contacts,
                keys.get(a.target_id),
                a.labels,
            )
            for a in queries.transitions(s)
        )
    return clusters, attempts


def test_the_write_back_matches_before_its_lock_and_stores_what_matching_under_it_stores(tmp_path, monkeypatch):
    """An endpoint that matched a stored cluster in the read before the transaction keeps that match, and the
    labels of its attempts made then, when its certificate's clusters are still those read: under the lock
    only the endpoints that matched nothing are matched again (here, run by run, each to be inserted).  The
    run of n = 9 stores the same clusters, attempts, targets and labels as with every match made under the
    lock."""
    from packings.service.db import open_database
    from packings.workers import identity

    in_transaction, under_lock = [False], Counter()

    def counted(name, f):
        def wrapper(*a, **kw):
            under_lock[name] += in_transaction[0]
            return f(*a, **kw)

        return wrapper

    monkeypatch.setattr(store, "find_match", counted("find_match", identity.find_match))
    monkeypatch.setattr(store, "alignment", counted("alignment", identity.alignment))
    real = store.premade
    results = {}
    for reuse in (True, False):
        engine = open_database(f"sqlite:///{tmp_path / f'{reuse}.db'}", create=True)
        event.listen(engine, "begin", lambda conn: in_transaction.__setitem__(0, True))
        for end in ("commit", "rollback"):
            event.listen(engine, end, lambda conn: in_transaction.__setitem__(0, False))
        if not reuse:  # nothing settled by the read: every endpoint matched and labelled under the lock
            monkeypatch.setattr(store, "premade", lambda *a: store.Premade(values=real(*a).values))
        under_lock.clear()
        fill_database(engine, 9)
        results[reuse] = _stored(engine, 9), dict(under_lock)
        engine.dispose()
    (with_read, counts), (without, counts_without) = results[True], results[False]
    assert with_read == without and len(with_read[0]) == 52
    # one task at a time: every endpoint matched in the read keeps its match; the others are inserted
    assert counts.get("find_match", 0) <= 52 < counts_without["find_match"]
    assert counts.get("alignment", 0) < counts_without["alignment"]
