"""Catalysis in the database (packings.service.catalysis) and `packings catalyse`."""

from __future__ import annotations

import json
import socket
from pathlib import Path

import numpy as np
import pytest
from sqlalchemy import func, select, text

from packings.service import store
from packings.service.catalysis import (
    NoParents,
    catalyse,
    close_packed_pass,
    count_stored,
    covered,
    format_report,
)
from packings.service.db import sessions
from packings.service.models import (
    COMPLETE,
    DONE,
    FOUND_CATALYSIS,
    FOUND_CLOSE_PACKED,
    FOUND_SEED,
    PASS_DELETED,
    PASS_GLUED,
    PENDING,
    RUNNING,
    CatalysisPass,
    ClusterRow,
    ExpansionRow,
    Run,
)
from packings.workers.cluster import Cluster as Core
from packings.workers.params import Params
from packings.workers.rigidity import rigidity
from tests.helpers import fill_database, one_line_error
from tests.helpers import packings as cli

DATA = Path(__file__).parent.parent / "data"


def url_of(engine) -> str:
    return engine.url.render_as_string(hide_password=False)


def test_catalysis_of_8_from_9_finds_nothing_new(engine):
    """Every rigid remainder of the 52 clusters of 9 is one of the 13 clusters of 8 already stored."""
    run8 = fill_database(engine, 8)
    fill_database(engine, 9)
    S = sessions(engine)
    with S() as s:
        before = s.execute(select(ClusterRow.id).order_by(ClusterRow.id)).scalars().all()
    r = catalyse(S, 8, Params())
    assert (r.run_id, r.parents, r.remainders) == (run8, 52, 52 * 9)
    assert r.rigid == r.already_stored > 0
    assert r.new == [] and r.expansions_added == 0 and not r.run_reopened
    with S() as s:
        assert s.execute(select(ClusterRow.id).order_by(ClusterRow.id)).scalars().all() == before
        assert s.get(Run, run8).status == COMPLETE


def test_no_parents_is_an_error_and_writes_nothing(engine):
    fill_database(engine, 6)
    S = sessions(engine)
    try:
        catalyse(S, 6, Params())
    except NoParents as e:
        assert "packings enumerate 7" in str(e)
    else:
        raise AssertionError("no clusters of 7 are stored")
    with S() as s:
        assert s.execute(select(Run.n)).scalars().all() == [6]


def _complete_after_the_seed(engine, n: int) -> int:
    """A run of n whose seed's expansion is marked done and which is marked complete, without following
    a path: a catalogue of n holding only its seed (a stand-in for a run that missed clusters)."""
    S = sessions(engine)
    info = store.start_run(S, n, Params(), "test:0:seed")
    with S.begin() as s:
        s.execute(
            ExpansionRow.__table__.update()
            .where(ExpansionRow.run_id == info.id)
            .values(status=DONE, outcomes="{}", paths=0)
        )
    assert store.finish_run(S, info.id, "test:0:seed", 0.0) == COMPLETE
    return info.id


def test_catalysis_adds_new_clusters_with_their_origin_and_enumerate_expands_them(engine):
    """Into a complete run of 6 that holds only its seed (the polytetrahedron), catalysis from the 5 clusters
    of 7 adds the octahedron, found_by = catalysis with a parent of 7, pending in the run, which is marked
    running again; `packings enumerate 6` then expands it and completes the run, and says catalysis is
    possible as clusters of 7 are stored."""
    run6 = _complete_after_the_seed(engine, 6)
    fill_database(engine, 7)
    S = sessions(engine)
    r = catalyse(S, 6, Params())
    assert r.run_id == run6 and r.parents == 5 and len(r.new) == 1 and r.run_reopened
    new = r.new[0]
    assert new.contacts == 12 and r.expansions_added == 1
    # the report of a pass that reopened the run says so; within enumerate, whose paths expand what the pass
    # added before the report is printed under "complete", it says that instead
    assert format_report(r).endswith(f"1 expansion added to run {run6} (marked running again)")
    assert format_report(r, expanded=True).endswith(f"1 expansion added to run {run6}, and expanded")
    with S() as s:
        row = s.get(ClusterRow, new.id)
        assert (row.found_by, row.source_id, row.found_in_run) == (FOUND_CATALYSIS, new.parent_id, run6)
        assert s.get(ClusterRow, new.parent_id).n == 7
        assert s.get(Run, run6).status == RUNNING
        exp = s.execute(select(ExpansionRow).where(ExpansionRow.cluster_id == new.id)).scalar_one()
        assert (exp.run_id, exp.status) == (run6, PENDING)
    again = catalyse(S, 6, Params())  # idempotent: everything is stored now
    assert again.new == [] and again.expansions_added == 0
    r = cli("enumerate", "6", "--quiet", "--workers", "1", "--db", url_of(engine))
    assert r.returncode == 0, r.stderr
    assert "n = 6: 2 rigid clusters" in r.stdout
    assert "packings catalyse" not in r.stdout and "--glued" not in r.stdout  # no hint: the run is complete
    with S() as s:
        assert s.get(Run, run6).status == COMPLETE
        exp = s.execute(select(ExpansionRow).where(ExpansionRow.cluster_id == new.id)).scalar_one()
        assert exp.status == DONE and exp.paths > 0


def test_enumerate_glued_adds_what_no_path_reached_expands_it_and_records_the_passes(engine, paper_counts):
    """Into a complete run of 7 that holds only its seed, `enumerate 7 --no-glued` adds nothing and makes no
    pass.  `enumerate 7`, glued by default, moves a sphere of each stored cluster onto each contact triangle:
    the first pass stores two clusters (found_by = catalysis), which it moves in their turn; the run expands
    them and its paths reach the last two, which a second pass, over the clusters stored since, moves to find
    nothing new.  The catalogue is the paper's, both passes are recorded, and the same command again makes
    no pass.  No run prints a hint about passes."""
    run7 = _complete_after_the_seed(engine, 7)
    url = url_of(engine)
    S = sessions(engine)
    r = cli("enumerate", "7", "--no-glued", "--quiet", "--workers", "1", "--json", "--db", url)
    assert r.returncode == 0, r.stderr
    assert json.loads(r.stdout)["catalysis"] == [] and json.loads(r.stdout)["total"] == 1
    r = cli("enumerate", "7", "--no-glued", "--quiet", "--workers", "1", "--db", url)
    assert r.returncode == 0, r.stderr
    assert "n = 7: 1 rigid cluster\n" in r.stdout and "--glued" not in r.stdout
    assert "fewer than the paper: 1 with 15 contacts (the paper 5)" in r.stdout
    with S() as s:
        assert s.execute(select(func.count()).select_from(CatalysisPass)).scalar_one() == 0
    r = cli("enumerate", "7", "--quiet", "--workers", "1", "--json", "--db", url)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert (out["run"], out["status"]) == (run7, "complete")
    assert out["by_contacts"] == paper_counts["clusters_by_contacts"]["7"]
    with S() as s:
        ids = s.execute(select(ClusterRow.id).where(ClusterRow.n == 7).order_by(ClusterRow.id)).scalars().all()
        found_by = dict(s.execute(select(ClusterRow.id, ClusterRow.found_by)).all())
        records = s.execute(select(CatalysisPass).order_by(CatalysisPass.id)).scalars().all()
        assert {e.status for e in s.execute(select(ExpansionRow)).scalars()} == {DONE}
        assert s.get(Run, run7).status == COMPLETE
    first, second = out["catalysis"]
    assert (first["after"], first["parents"], first["last_parent"], first["expansions_added"]) == (0, 3, ids[2], 2)
    assert [f["id"] for f in first["new"]] == ids[1:3]
    assert [found_by[i] for i in ids] == [FOUND_SEED, FOUND_CATALYSIS, FOUND_CATALYSIS, "path", "path"]
    assert (second["after"], second["parents"], second["last_parent"], second["new"]) == (ids[2], 2, ids[4], [])
    assert [(x.run_id, x.kind, x.spheres, x.after, x.last_parent, x.parents, x.new) for x in records] == [
        (run7, PASS_GLUED, 1, 0, ids[2], 3, 2),
        (run7, PASS_GLUED, 1, ids[2], ids[4], 2, 0),
    ]
    assert all(x.finished_at >= x.started_at for x in records)
    assert covered(S, run7) == ids[4] and count_stored(S, 7, ids[4]) == 0
    again = json.loads(cli("enumerate", "7", "--quiet", "--workers", "1", "--json", "--db", url).stdout)
    assert again["catalysis"] == [] and again["by_contacts"] == out["by_contacts"]
    r = cli("enumerate", "7", "--quiet", "--workers", "1", "--db", url)
    assert r.returncode == 0 and "--glued" not in r.stdout and "as the paper" in r.stdout
    with S() as s:
        assert s.execute(select(func.count()).select_from(CatalysisPass)).scalar_one() == 2


def test_a_pass_after_an_id_reads_only_the_clusters_stored_since_and_is_recorded(engine):
    """catalyse(..., after=i) takes as parents only the clusters with a larger id; the glued passes that ran
    to their end say up to which id every cluster was a parent (covered), the passes deleting spheres
    do not count there."""
    run7 = fill_database(engine, 7)
    S = sessions(engine)
    with S() as s:
        ids = s.execute(select(ClusterRow.id).where(ClusterRow.n == 7).order_by(ClusterRow.id)).scalars().all()
    assert covered(S, run7) == 0 and count_stored(S, 7, ids[2]) == 2
    r = catalyse(S, 7, Params(), glued=True, after=ids[2])
    assert (r.run_id, r.parents, r.after, r.last_parent) == (run7, 2, ids[2], ids[-1]) and r.new == []
    assert covered(S, run7) == ids[-1]
    none = catalyse(S, 7, Params(), glued=True, after=ids[-1])
    assert (none.parents, none.last_parent) == (0, None) and covered(S, run7) == ids[-1]
    fill_database(engine, 8)
    catalyse(S, 7, Params())  # deleting a sphere from each cluster of 8
    with S() as s:
        kinds = s.execute(select(CatalysisPass.kind, CatalysisPass.after).order_by(CatalysisPass.id)).all()
    assert [tuple(k) for k in kinds] == [(PASS_GLUED, ids[2]), (PASS_GLUED, ids[-1]), (PASS_DELETED, 0)]
    assert covered(S, run7) == ids[-1]


def test_catalyse_command(engine, tmp_path):
    fill_database(engine, 6)
    url = url_of(engine)
    line = one_line_error(cli("catalyse", "6", "--db", url))
    assert "no clusters of 7 spheres stored: run `packings enumerate 7` first (n = 7 has about 2 times" in line
    assert line.endswith("or `packings catalyse 6 --glued`, which makes its parents from the stored clusters of 6")
    line = one_line_error(cli("catalyse", "5", "--spheres", "2", "--db", url, "--quiet"))
    assert "packings enumerate 7" in line
    for n in ("3", "500"):
        assert "n" in one_line_error(cli("catalyse", n, "--db", url))
    fill_database(engine, 7)
    r = cli("catalyse", "6", "--db", url, "--quiet")
    assert r.returncode == 0, r.stderr
    assert "parents 5, remainders tested 35" in r.stdout and "new 0" in r.stdout
    assert "packings enumerate 6` to expand" not in r.stdout
    r = cli("catalyse", "6", "--db", url, "--json")
    out = json.loads(r.stdout)
    assert out["parents"] == 5 and out["new"] == [] and out["rigid"] == out["already_stored"]
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    assert "no database" in one_line_error(cli("catalyse", "6", "--db", f"sqlite:///{elsewhere / 'none.db'}"))
    assert list(elsewhere.iterdir()) == []  # nothing created


def test_a_close_packed_pass_stores_the_octahedron_without_parents(engine):
    """Into a complete run of 6 that holds only its seed (the polytetrahedron), the close-packed fragments of
    6 with 12 contacts add the octahedron, found_by = close-packed with no source, pending in the run,
    which is marked running again; a second pass finds it stored; enumerate then completes the run."""
    run6 = _complete_after_the_seed(engine, 6)
    S = sessions(engine)
    r = close_packed_pass(S, 6, Params(), 12)
    assert (r.run_id, r.parents, r.rigid, r.already_stored) == (run6, 1, 1, 0) and r.run_reopened
    assert len(r.new) == 1 and (r.new[0].contacts, r.new[0].parent_id, r.new[0].lattice) == (12, None, "both")
    with S() as s:
        row = s.get(ClusterRow, r.new[0].id)
        assert (row.found_by, row.source_id, row.found_in_run) == (FOUND_CLOSE_PACKED, None, run6)
        exp = s.execute(select(ExpansionRow).where(ExpansionRow.cluster_id == row.id)).scalar_one()
        assert (exp.run_id, exp.status) == (run6, PENDING)
    again = close_packed_pass(S, 6, Params(), 12)
    assert again.new == [] and again.already_stored == 1 and again.expansions_added == 0
    r = cli("enumerate", "6", "--quiet", "--workers", "1", "--db", url_of(engine))
    assert r.returncode == 0, r.stderr
    assert "n = 6: 2 rigid clusters" in r.stdout


def test_catalyse_close_packed_command(engine):
    fill_database(engine, 7)
    url = url_of(engine)
    r = cli("catalyse", "7", "--close-packed", "15", "--db", url, "--quiet")
    assert r.returncode == 0, r.stderr
    assert "close-packed fragments of n = 7 with at least 15 contacts" in r.stdout and "new 0" in r.stdout
    out = json.loads(cli("catalyse", "7", "--close-packed", "15", "--db", url, "--json").stdout)
    assert out["close_packed"] == 15 and out["new"] == [] and out["rigid"] == out["already_stored"] > 0
    for extra in (["--glued"], ["--spheres", "2"], ["--workers", "2"], ["--scheduler", "tcp://127.0.0.1:1"]):
        line = one_line_error(cli("catalyse", "7", "--close-packed", "15", *extra, "--db", url))
        assert "--close-packed lists fragments in this process" in line
    # no run of 10 restricted to 26 contacts, and no close-packed fragment to seed one: one line, nothing written
    with sessions(engine)() as s:
        runs = s.execute(select(func.count()).select_from(Run)).scalar_one()
    line = one_line_error(cli("catalyse", "10", "--close-packed", "26", "--min-contacts", "26", "--db", url))
    assert "no cluster of 10 spheres with at least 26 contacts to start from" in line
    with sessions(engine)() as s:
        assert s.execute(select(func.count()).select_from(Run)).scalar_one() == runs


def test_a_run_restricted_to_the_maximum_of_10_finds_the_papers_clusters_with_that_many(engine, paper_counts):
    """M(10) = 25 is more than the beam search's seed has: the run starts from the listed close-packed
    fragment, and its paths (at most 3 contacts broken) find the paper's 3 clusters with 25 contacts,
    every one of them among the close-packed fragments (a pass finds them all stored)."""
    run = fill_database(engine, 10, Params(min_contacts=25, max_break=3))
    S = sessions(engine)
    with S() as s:
        rows = s.execute(select(ClusterRow).where(ClusterRow.found_in_run == run)).scalars().all()
    assert len(rows) == paper_counts["clusters_by_contacts"]["10"]["25"] == 3
    assert {r.contacts for r in rows} == {25} and sum(r.found_by == FOUND_SEED for r in rows) == 1
    r = close_packed_pass(S, 10, Params(min_contacts=25, max_break=3), 25)
    assert (r.run_id, r.parents, r.rigid, r.already_stored, r.new) == (run, 3, 3, 3, [])


def test_the_lost_cluster_of_11_is_found_from_its_parent_of_12(engine):
    """The stored n = 12 parent of the cluster of 11 that no path reaches: catalysis into an empty
    catalogue of 11 (a new run, seeded) stores it, with 26 contacts, an hcp fragment, found by catalysis."""
    data = json.loads((DATA / "n11_catalysis.json").read_text())
    parent = Core(np.array(data["parent"]["coords"]), tuple(map(tuple, data["parent"]["contacts"])))
    S = sessions(engine)
    with S.begin() as s:
        pid, _ = store.insert_or_match(
            s,
            parent,
            rigidity(parent.coords, parent.contacts, Params()),
            None,
            Params().tol_d,
            found_by="path",
            source_id=None,
        )
    r = catalyse(S, 11, Params())
    lost = [f for f in r.new if tuple(f.deleted) == tuple(data["deleted"])]
    assert len(lost) == 1 and (lost[0].contacts, lost[0].lattice, lost[0].parent_id) == (26, "hcp", pid)
    with S() as s:
        row = s.get(ClusterRow, lost[0].id)
        assert (row.n, row.found_by, row.source_id, row.lattice) == (11, FOUND_CATALYSIS, pid, "hcp")
        assert row.certificate == data["certificate"]
        assert s.execute(text("SELECT count(*) FROM expansions WHERE cluster_id = :i"), {"i": row.id}).scalar() == 1


def _glued_parent_of_11(engine):
    """tests/data/n11_glued.json, its cluster of 11 stored: (the data, sessions, the cluster's id)."""
    data = json.loads((DATA / "n11_glued.json").read_text())
    c = Core(np.array(data["cluster"]["coords"]), tuple(map(tuple, data["cluster"]["contacts"])))
    S = sessions(engine)
    with S.begin() as s:
        pid, _ = store.insert_or_match(
            s, c, rigidity(c.coords, c.contacts, Params()), None, Params().tol_d, found_by="path", source_id=None
        )
    return data, S, pid


def test_moving_one_sphere_stores_the_lost_cluster_of_11_from_a_cluster_of_11(engine):
    """tests/data/n11_glued.json: with --glued no cluster of 12 is needed; the lost cluster is stored with
    the cluster of 11 it came from as its source, and a second pass finds it stored (and does not decide
    it again)."""
    data, S, pid = _glued_parent_of_11(engine)
    r = catalyse(S, 11, Params(), glued=True)
    assert r.glued and r.seen > 0 and r.remainders > 0
    lost = [f for f in r.new if (f.moved_onto, f.deleted) == (tuple(data["triangle"]), (data["sphere"],))]
    assert len(lost) == 1
    f = lost[0]
    assert (f.contacts, f.lattice, f.parent_id) == (26, "hcp", pid)
    with S() as s:
        row = s.get(ClusterRow, f.id)
        assert (row.n, row.found_by, row.source_id, row.certificate) == (11, FOUND_CATALYSIS, pid, data["certificate"])
        assert s.execute(text("SELECT count(*) FROM expansions WHERE cluster_id = :i"), {"i": row.id}).scalar() == 1
        stored = s.execute(select(func.count()).select_from(ClusterRow)).scalar_one()
    again = catalyse(S, 11, Params(), glued=True)
    assert again.new == [] and again.parents == stored
    with S() as s:
        assert s.execute(select(func.count()).select_from(ClusterRow)).scalar_one() == stored


def test_moving_one_sphere_of_the_clusters_of_7_finds_nothing_new(engine):
    run7 = fill_database(engine, 7)
    S = sessions(engine)
    r = catalyse(S, 7, Params(), glued=True)
    assert (r.run_id, r.parents) == (run7, 5) and r.seen > 0
    assert r.new == [] and r.rigid == r.already_stored and r.expansions_added == 0
    with S() as s:
        assert s.get(Run, run7).status == COMPLETE


def test_catalyse_glued_command(engine):
    url = url_of(engine)
    assert "--spheres must be 1" in one_line_error(cli("catalyse", "6", "--glued", "--spheres", "2", "--db", url))
    fill_database(engine, 6)
    line = one_line_error(cli("catalyse", "7", "--glued", "--db", url))
    assert "no clusters of 7 spheres stored: run `packings enumerate 7` first" in line
    r = cli("catalyse", "6", "--glued", "--db", url, "--quiet")
    assert r.returncode == 0, r.stderr
    assert "by moving one sphere" in r.stdout and "clusters 2," in r.stdout and "new 0" in r.stdout
    out = json.loads(cli("catalyse", "6", "--glued", "--db", url, "--json", "--workers", "1").stdout)
    assert out["glued"] and out["parents"] == 2 and out["new"] == []
    with socket.socket() as taken:  # the dashboard where it is asked for, another port where that is taken
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = cli("catalyse", "6", "--glued", "--db", url, "--workers", "1", "--dashboard-address", f"127.0.0.1:{port}")
    assert r.returncode == 0, r.stderr
    assert f"packings: dashboard port {port} is taken; serving it on " in r.stderr
    assert "clusters of 6: 100%" in r.stderr and "2/2" in r.stderr  # the pass's bar, off a terminal too
    assert "clusters of 6" not in cli("catalyse", "6", "--glued", "--db", url, "--workers", "1", "--quiet").stderr
    line = one_line_error(cli("catalyse", "6", "--glued", "--db", url, "--workers", "2", "--scheduler", "tcp://h:1"))
    assert "not both" in line


def _dask_pass(engine, n: int, batch: int = 200, **kw):
    """A pass of catalysis on a Dask cluster of two worker threads (of this process) with the database plugin."""
    from distributed import Client, LocalCluster

    from packings.service.plugin import DatabasePlugin

    plugin = DatabasePlugin(url_of(engine))
    with (
        LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        client.register_plugin(plugin)
        return catalyse(sessions(engine), n, Params(), batch=batch, client=client, plugin=plugin.name, **kw)


def test_a_pass_on_dask_workers_finds_what_a_pass_in_this_process_finds(engine):
    """Moving one sphere of the clusters of 7, one parent a task shared out between two workers (each
    with its own record of what it has seen): every moved sphere is decided or seen, as in one process,
    and the rigid remainders are the stored clusters, as in one process."""
    fill_database(engine, 7)
    S = sessions(engine)
    here = catalyse(S, 7, Params(), glued=True)
    there = _dask_pass(engine, 7, batch=1, glued=True)
    assert there.parents == here.parents == 5
    assert there.remainders + there.seen == here.remainders + here.seen
    assert there.remainders >= here.remainders  # two records of what was seen decide no less than one
    assert there.new == here.new == [] and there.rigid == there.already_stored
    fill_database(engine, 6)
    deleted = _dask_pass(engine, 6, batch=2)  # deleting a sphere from each cluster of 7: the 2 of 6 again
    assert (deleted.parents, deleted.remainders) == (5, 35) and deleted.new == []
    assert deleted.rigid == deleted.already_stored > 0


def test_the_lost_cluster_of_11_is_stored_by_a_pass_on_dask_workers(engine):
    """tests/data/n11_glued.json on Dask workers: the cluster no path reaches is stored with its origin, once,
    and the clusters found are moved in their turn; a second pass (a new record of what was seen) and a
    pass in this process find nothing more."""
    data, S, pid = _glued_parent_of_11(engine)
    r = _dask_pass(engine, 11, glued=True)
    lost = [f for f in r.new if (f.moved_onto, f.deleted) == (tuple(data["triangle"]), (data["sphere"],))]
    assert len(lost) == 1 and (lost[0].contacts, lost[0].lattice, lost[0].parent_id) == (26, "hcp", pid)
    with S() as s:
        row = s.get(ClusterRow, lost[0].id)
        assert (row.found_by, row.certificate) == (FOUND_CATALYSIS, data["certificate"])
        stored = s.execute(select(func.count()).select_from(ClusterRow)).scalar_one()
    again = _dask_pass(engine, 11, glued=True)
    assert again.new == [] and again.parents == stored and again.rigid == again.already_stored
    # the clusters found were moved in their turn, as one process moves them: it finds nothing more
    here = catalyse(S, 11, Params(), glued=True)
    assert here.new == [] and here.parents == stored


def test_a_task_carries_the_parents_ids_alone_and_stores_what_it_found(engine, monkeypatch):
    """A pass on Dask workers submits each batch as a list of cluster ids (the scheduler and the coordinator
    never hold the parents' coordinates), and the task stores the lost cluster of 11 itself: nothing is
    stored outside a worker."""
    from distributed import Client, get_worker

    import packings.service.catalysis as catalysis_module

    data, S, pid = _glued_parent_of_11(engine)
    submitted, real_submit, real_store = [], Client.submit, catalysis_module._store

    def submit(self, fn, *args, **kw):
        submitted.append((fn.__name__, args))
        return real_submit(self, fn, *args, **kw)

    def store_in_a_worker_only(*args, **kw):
        get_worker()  # ValueError outside a worker (the workers are threads of this process here)
        return real_store(*args, **kw)

    monkeypatch.setattr(Client, "submit", submit)
    monkeypatch.setattr(catalysis_module, "_store", store_in_a_worker_only)
    r = _dask_pass(engine, 11, batch=1, glued=True)
    lost = [
        f for f in r.new if (f.parent_id, f.moved_onto, f.deleted) == (pid, tuple(data["triangle"]), (data["sphere"],))
    ]
    assert len(lost) == 1 and (lost[0].contacts, lost[0].lattice) == (26, "hcp")
    assert r.rigid == len(r.new) + r.already_stored
    assert submitted and all(name == "catalysis_task" for name, _ in submitted)
    ids = [args[0] for _, args in submitted]
    assert ids[0] == [pid] and all(type(i) is int for batch in ids for i in batch)
    assert not any(isinstance(a, (bytes, np.ndarray)) for _, args in submitted for a in args)


def test_the_coordinator_of_a_pass_on_worker_processes_loads_no_numerical_code(engine, tmp_path):
    """The glued pass of tests/data/n11_glued.json on a local cluster of worker processes, driven by a
    process of its own: the lost cluster is stored, and that process never imported the endpoint rule, the
    path code or numba (about 170 MiB in every coordinator that did)."""
    data, S, pid = _glued_parent_of_11(engine)
    script = tmp_path / "coordinator.py"
    script.write_text(
        "import json, sys\n"
        "def main():\n"
        "    from distributed import Client, LocalCluster\n"
        "    from packings.service.catalysis import catalyse\n"
        "    from packings.service.db import make_engine, sessions\n"
        "    from packings.service.plugin import DatabasePlugin\n"
        "    from packings.workers.params import Params\n"
        "    url = sys.argv[1]\n"
        "    plugin = DatabasePlugin(url)\n"
        "    engine = make_engine(url)\n"
        "    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as c, \\\n"
        "            Client(c) as client:\n"
        "        client.register_plugin(plugin)\n"
        "        r = catalyse(sessions(engine), 11, Params(), client=client, plugin=plugin.name, glued=True)\n"
        "    engine.dispose()\n"
        "    print(json.dumps({'new': [[f.deleted, f.moved_onto] for f in r.new],\n"
        "                      'loaded': sorted(m for m in ('numba', 'packings.workers.catalysis',\n"
        "                                                   'packings.workers.paths', 'packings.workers._compiled')\n"
        "                                       if m in sys.modules)}))\n"
        "if __name__ == '__main__':\n"
        "    main()\n"
    )
    import subprocess
    import sys

    r = subprocess.run([sys.executable, str(script), url_of(engine)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert [data["sphere"]] in [d for d, onto in out["new"] if onto == data["triangle"]]
    assert out["loaded"] == []


def test_enumerate_glued_gives_each_pass_fresh_local_workers(engine, monkeypatch):
    """packings.enumerate(..., glued=True) replaces its local workers before each pass it makes (not before
    the paths, nor when no pass is due), and the catalogue is the same."""
    import packings
    import packings.service.dask_cluster as dc

    run7 = _complete_after_the_seed(engine, 7)
    calls, real = [], dc.dask_client.fresh_workers

    def fresh(self):
        calls.append(real(self))
        return calls[-1]

    monkeypatch.setattr(dc.dask_client, "fresh_workers", fresh)
    r = packings.enumerate(7, url_of(engine), workers=1, progress=False, glued=True)
    assert (r.run_id, r.status, r.total) == (run7, "complete", 5)
    assert len(r.catalysis) == 2 and calls == [True, True]
    again = packings.enumerate(7, url_of(engine), workers=1, progress=False, glued=True)
    assert again.catalysis == [] and calls == [True, True]


# --------------------------------------------------------------------------- a pass on Dask, with faults


def _kill_the_first_task_after(first: int, marker: str) -> None:
    """In a worker process: the first task anywhere in the cluster (``marker`` is made once) that reads a
    parent stored after cluster ``first`` (one the pass stored itself: mid-pass) kills its process."""
    import os

    import packings.service.catalysis as catalysis_module

    real = catalysis_module.rows_of

    def rows_of(Session_, ids):
        if max(ids) > first:
            try:
                os.close(os.open(marker, os.O_CREAT | os.O_EXCL))
            except FileExistsError:
                pass
            else:
                os._exit(1)
        return real(Session_, ids)

    catalysis_module.rows_of = rows_of


def _stored(engine, n: int) -> set[str]:
    with sessions(engine)() as s:
        return set(s.execute(select(ClusterRow.certificate).where(ClusterRow.n == n)).scalars())


def test_a_pass_on_dask_survives_a_worker_killed_mid_pass(engine, tmp_path):
    """A glued pass into a run of 8 that holds only its seed, on two worker processes, one of which dies in
    the first task that reads a cluster the pass stored (Dask told to give up on a task at its first lost
    worker, so that the loss reaches the pass): the batches it held are sent again, and the pass stores and
    reports what an undisturbed pass in one process does."""
    import dask
    from distributed import Client, LocalCluster

    from packings.service.db import open_database
    from packings.service.plugin import DatabasePlugin

    reference = open_database(f"sqlite:///{tmp_path / 'reference.db'}", create=True)
    try:
        _complete_after_the_seed(reference, 8)
        here = catalyse(sessions(reference), 8, Params(), glued=True)
        expected = _stored(reference, 8)
    finally:
        reference.dispose()
    assert here.new  # the pass finds clusters, which are parents in their turn
    _complete_after_the_seed(engine, 8)
    with sessions(engine)() as s:
        seed = s.execute(select(func.max(ClusterRow.id))).scalar_one()
    marker = str(tmp_path / "killed")
    plugin = DatabasePlugin(url_of(engine))
    with (
        dask.config.set({"distributed.scheduler.allowed-failures": 0}),
        LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        client.register_plugin(plugin)
        client.run(_kill_the_first_task_after, seed, marker)
        there = catalyse(sessions(engine), 8, Params(), batch=1, glued=True, client=client, plugin=plugin)
    assert Path(marker).exists()  # a worker was killed
    assert _stored(engine, 8) == expected
    assert (there.parents, len(there.new), there.rigid - there.already_stored) == (
        here.parents,
        len(here.new),
        here.rigid - here.already_stored,
    )
    assert there.remainders + there.seen == here.remainders + here.seen
    with sessions(engine)() as s:
        assert s.execute(select(func.count()).select_from(CatalysisPass)).scalar_one() == 1  # recorded


def test_a_batch_whose_task_always_fails_stops_the_pass_after_max_attempts_in_one_line(engine, monkeypatch):
    """The task of one batch of parents raises every time: it is tried max_attempts times in all, then the
    pass stops with PassFailed in one line; what the other batches stored stays, and the pass is not
    recorded (the same command makes it again)."""
    from distributed import Client, LocalCluster

    import packings.service.catalysis as catalysis_module
    from packings.service.errors import PassFailed
    from packings.service.plugin import DatabasePlugin

    _complete_after_the_seed(engine, 8)
    with sessions(engine)() as s:
        seed = s.execute(select(func.max(ClusterRow.id))).scalar_one()
    poison, tries, real = seed + 1, [], catalysis_module.rows_of  # the first cluster the pass stores

    def rows_of(Session_, ids):  # the workers are threads of this process: the patch reaches them
        if poison in ids:
            tries.append(ids)
            raise RuntimeError(f"injected: cluster {poison} cannot be read\nsecond line")
        return real(Session_, ids)

    monkeypatch.setattr(catalysis_module, "rows_of", rows_of)
    plugin = DatabasePlugin(url_of(engine))
    with (
        LocalCluster(n_workers=2, threads_per_worker=1, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        client.register_plugin(plugin)
        with pytest.raises(PassFailed) as failed:
            catalyse(sessions(engine), 8, Params(), batch=1, glued=True, client=client, plugin=plugin, max_attempts=2)
    line = str(failed.value)
    assert "\n" not in line and f"cluster ids {poison} to {poison}" in line and "failed 2 time(s)" in line
    assert "RuntimeError: injected" in line and "run the same command again" in line
    assert tries == [[poison], [poison]]
    assert count_stored(sessions(engine), 8) > 2  # the seed's batch stored the poisoned parent and others
    with sessions(engine)() as s:
        assert s.execute(select(func.count()).select_from(CatalysisPass)).scalar_one() == 0


def test_a_pass_on_a_cluster_without_workers_stops_after_the_workerless_timeout(engine):
    """As a run does (test_faults: a cluster left without workers): a pass on a cluster that has no worker
    stops with SchedulerError after ``workerless_timeout`` seconds, rather than wait for ever; nothing is
    stored and the pass is not recorded."""
    import threading

    from distributed import Client, LocalCluster

    from packings.service.errors import SchedulerError
    from packings.service.plugin import DatabasePlugin

    fill_database(engine, 6)
    before = count_stored(sessions(engine), 6)
    plugin, outcome = DatabasePlugin(url_of(engine)), []
    with (
        LocalCluster(n_workers=0, processes=False, dashboard_address=None) as cluster,
        Client(cluster) as client,
    ):
        client.register_plugin(plugin)

        def run() -> None:
            try:
                outcome.append(
                    catalyse(
                        sessions(engine), 6, Params(), glued=True, client=client, plugin=plugin, workerless_timeout=3.0
                    )
                )
            except Exception as e:  # noqa: BLE001 - what the pass raised is the outcome
                outcome.append(e)

        waiting = threading.Thread(target=run, daemon=True)
        waiting.start()
        waiting.join(timeout=120)
        assert not waiting.is_alive(), "the pass still waits for a worker"
    [e] = outcome
    assert isinstance(e, SchedulerError) and "no Dask worker for 3 s" in str(e) and "\n" not in str(e)
    assert count_stored(sessions(engine), 6) == before
    with sessions(engine)() as s:
        assert s.execute(select(func.count()).select_from(CatalysisPass)).scalar_one() == 0
