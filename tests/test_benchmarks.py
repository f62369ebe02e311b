"""The benchmarks a user runs from the README (``python -m benchmarks ...``) run and report what they say."""

from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

from tests.helpers import pg_database

ROOT = Path(__file__).resolve().parents[1]


def benchmark(*args: str) -> dict:
    r = subprocess.run(
        [sys.executable, "-m", "benchmarks", *args, "--json"], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stderr
    return json.loads(r.stdout)


def enumerate_into(url: str, n: int, *args: str) -> subprocess.CompletedProcess:
    """``packings enumerate n`` into the database ``url`` on one worker, which must succeed."""
    r = subprocess.run(
        [sys.executable, "-m", "packings.service.cli", "enumerate", str(n), *args, "--db", url, "--workers", "1"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 0, r.stderr
    return r


def test_the_enumerate_benchmark_reports_the_shares_outside_expand(paper_counts):
    report = benchmark("enumerate", "--sizes", "7", "--workers", "1")
    [row] = report["runs"]
    assert row["n"] == 7 and row["workers"] == 1 and row["status"] == "complete"
    assert row["by_contacts"] == paper_counts["clusters_by_contacts"]["7"]
    # the command's wall time holds the run, and the run the time in expand: both shares follow
    assert 0.0 < row["in_expand_s"] < row["run_s"] < row["wall_s"]
    # both rounded: in expand to 1 ms, the share to 1e-4 (a run of n = 7 spends only about 10 ms in expand)
    assert abs(row["outside_share_of_wall"] - (1.0 - row["in_expand_s"] / row["wall_s"])) <= 5e-4 / row["wall_s"] + 1e-4
    assert 0.0 < row["outside_share_of_run"] < row["outside_share_of_wall"] < 1.0


def test_the_paths_benchmark_compares_the_backends_on_the_same_paths():
    report = benchmark("paths", "--quick")
    assert report["first_call_seconds"] > 0.0
    assert [r["n"] for r in report["rows"]] == [10, 12, 14]
    for r in report["rows"]:  # which backend is faster is the benchmark's to report, not a test's to require
        assert r["paths"] > 0 and r["same_outcome"] == r["paths"]
        assert r["median_ms_compiled"] > 0.0 and r["median_ms_numpy"] > 0.0
        assert r["ratio"] == pytest.approx(r["median_ms_numpy"] / r["median_ms_compiled"])


def test_the_soak_benchmark_reports_faults_against_an_undisturbed_run():
    report = benchmark("soak", "--n", "8", "--backends", "sqlite", "--seed", "3")
    rows = report["rows"]
    assert [r["faults"] for r in rows] == ["none", "workers killed", "coordinator killed"]
    for r in rows:
        assert r["exit"] == 0 and r["expected"] == r["seen"] == 13 and r["same_clusters"]
        assert r["failed"] == r["leased"] == r["duplicates"] == 0 and r["stopped"] == ""
    assert rows[0]["time_ratio"] == 1.0 and rows[2]["seconds"] > 0
    assert report["early_stops"] == {
        "sqlite, none": [0, 1],
        "sqlite, workers killed": [0, 1],
        "sqlite, coordinator killed": [0, 1],
    }


def test_the_soak_repeats_the_faults_asked_for_each_on_a_fresh_database():
    report = benchmark("soak", "--n", "7", "--backends", "sqlite", "--faults", "workers", "--repeat", "2")
    assert [r["faults"] for r in report["rows"]] == ["none", "workers killed", "workers killed"]
    assert all(r["exit"] == 0 and r["seen"] == r["expected"] == 5 and r["same_clusters"] for r in report["rows"])
    assert report["early_stops"] == {"sqlite, none": [0, 1], "sqlite, workers killed": [0, 2]}


def test_the_soak_refuses_a_kind_of_faults_it_does_not_know():
    r = subprocess.run(
        [sys.executable, "-m", "benchmarks", "soak", "--faults", "disk"], capture_output=True, text=True, cwd=ROOT
    )
    assert r.returncode != 0 and r.stderr.strip() == "soak: unknown kind of faults disk (workers, coordinator)"


def test_the_soak_keeps_why_a_run_stopped():
    """A run that fails keeps its last line on standard error, which the soak's table prints."""
    from benchmarks.soak import undisturbed

    status, line = undisturbed(8, "sqlite://", 1)
    assert status != 0 and line.startswith("packings: error: ") and "in-memory" in line


def test_the_classes_benchmark_times_expand_by_class_with_both_backends():
    """n = 9: 51 regular clusters and one singular (52, the paper's count); every sampled cluster gives the
    same endpoints and reaches the same clusters with both backends, and the shares of each backend add up
    to one."""
    report = benchmark("classes", "--n", "9", "--sample", "3")
    rows = {r["class"]: r for r in report["rows"]}
    assert set(rows) == {"regular", "singular"} and rows["regular"]["clusters"] + rows["singular"]["clusters"] == 52
    assert rows["regular"]["subsets_min"] == rows["regular"]["subsets_max"] == 21  # one per contact, 3n - 6
    assert rows["singular"]["subsets_max"] > 21 and rows["singular"]["not_1d_share"] > 0.5
    for b in ("numba", "svd", "numpy"):
        assert abs(sum(r[f"share_{b}"] for r in rows.values()) - 1.0) < 1e-9
    for r in rows.values():
        assert r["same_endpoints"] == r["same_clusters_reached"] == r["sampled"]
        assert r["mean_ms_numba"] > 0 and r["mean_ms_numpy"] > 0
        assert r["mean_ms_svd"] > 0 and r["svd_ratio"] > 0 and r["svd_paths_differing"] == 0


def test_the_classes_benchmark_times_only_the_classes_asked_for():
    """--classes singular: n = 9's one singular cluster alone, its share the whole; a class n = 9 lacks is refused."""
    report = benchmark("classes", "--n", "9", "--sample", "1", "--no-numpy", "--no-every", "--classes", "singular")
    [row] = report["rows"]
    assert row["class"] == "singular" and row["clusters"] == row["sampled"] == 1 and row["share_numba"] == 1.0
    r = subprocess.run(
        [sys.executable, "-m", "benchmarks", "classes", "--n", "9", "--classes", "hypostatic"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode == 1 and "no cluster of n = 9 in the classes hypostatic" in r.stderr


def test_the_classes_benchmark_expands_as_a_restricted_run_does():
    """--max-break and --min-contacts expand as `enumerate --max-break K --min-contacts M` would: n = 9's singular
    cluster, whose 21 contacts get pairs too in a full run, gets its 21 single breaks only."""
    report = benchmark(
        "classes", "--n", "9", "--sample", "1", "--no-numpy", "--no-every", "--max-break", "1", "--min-contacts", "21"
    )
    assert report["max_break"] == 1 and report["min_contacts"] == 21
    rows = {r["class"]: r for r in report["rows"]}
    assert rows["singular"]["subsets_min"] == rows["singular"]["subsets_max"] == 21


def test_the_classes_benchmark_times_following_every_path_against_one_of_each_congruent_set():
    """n = 8, all 13 clusters: some have symmetries, whose images are counted, and following every path
    instead reaches the same outcomes; --no-every leaves the variant out."""
    [row] = benchmark("classes", "--n", "8", "--sample", "20", "--no-numpy")["rows"]
    assert row["sampled"] == 13 and row["paths_by_symmetry"] > 0
    assert row["mean_ms_every"] > 0 and row["every_ratio"] > 0 and row["every_paths_differing"] == 0
    [row] = benchmark("classes", "--n", "8", "--sample", "2", "--no-numpy", "--no-every", "--no-unheld")["rows"]
    assert "mean_ms_every" not in row and "every_paths_differing" not in row and "mean_ms_unheld" not in row


def test_the_classes_benchmark_times_following_the_paths_of_held_subsets_too(tmp_path):
    """The unheld variant (the paths of subsets with a contact the rest holds followed as well) is timed beside
    the run's code on the same clusters, and no cluster's other attempts or clusters reached differ: n = 11's
    cluster with 29 contacts, broken up to three at a time, has hundreds of held subsets."""
    url = f"sqlite:///{tmp_path / 'c.db'}"
    restricted = ("--min-contacts", "29", "--max-break", "3")
    enumerate_into(url, 11, *restricted, "--quiet")
    [row] = benchmark("classes", "--n", "11", "--db", url, *restricted, "--sample", "1", "--no-numpy", "--no-every")[
        "rows"
    ]
    assert row["class"] == "hyperstatic" and row["held"] > 100
    assert row["mean_ms_unheld"] > 0 and row["unheld_ratio"] > 0 and row["unheld_clusters_differing"] == 0


SHIM = """
import packings.workers._compiled as _real

globals().update({k: v for k, v in vars(_real).items() if not k.startswith("__")})


def follow_steps(*args):  # every path ends as if its projection had failed
    return (ST_PROJECTION_FAILED,) + tuple(_real.follow_steps(*args)[1:])
"""


def test_the_classes_benchmark_times_the_kernels_of_another_file_against_the_current_ones(tmp_path):
    """``--against FILE`` times FILE's kernels beside the package's and compares every attempt: none differs
    when FILE is the package's own _compiled.py, and every path does when FILE changes where paths end."""
    import packings.workers._compiled as compiled

    same = benchmark("classes", "--n", "8", "--sample", "2", "--no-numpy", "--against", compiled.__file__)
    [row] = same["rows"]
    assert same["against"] == compiled.__file__ and row["class"] == "regular"
    assert row["attempts"] == 2 * 18 and row["against_attempts_differing"] == 0
    assert row["mean_ms_against"] > 0 and row["against_ratio"] > 0
    assert abs(row["share_against"] - 1.0) < 1e-9
    copy = tmp_path / "copy.py"  # a file of its own: compiled on the first run, from numba's cache on the second
    copy.write_text(Path(compiled.__file__).read_text())
    for _ in range(2):
        [row] = benchmark("classes", "--n", "8", "--sample", "1", "--no-numpy", "--against", str(copy))["rows"]
        assert row["against_attempts_differing"] == 0 and row["attempts"] == 18
    assert list((tmp_path / "__pycache__").glob("copy.*.nbi"))
    shim = tmp_path / "failing.py"
    shim.write_text(SHIM)
    other = benchmark("classes", "--n", "8", "--sample", "2", "--no-numpy", "--against", str(shim))
    [row] = other["rows"]
    assert row["attempts"] == 2 * 18 and row["against_attempts_differing"] > 0
    r = subprocess.run(
        [sys.executable, "-m", "benchmarks", "classes", "--n", "8", "--against", str(tmp_path / "none.py")],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode != 0 and "no such file" in r.stderr
    broken = tmp_path / "broken.py"
    broken.write_text("def follow_steps(:\n")
    r = subprocess.run(
        [sys.executable, "-m", "benchmarks", "classes", "--n", "8", "--against", str(broken)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode != 0 and r.stderr.strip().startswith("--against: cannot load") and "Traceback" not in r.stderr


def test_the_classes_benchmark_splits_the_time_of_expand_between_the_paths_and_the_rest():
    """--parts at n = 10: a path keeps a self-stress exactly where the counts leave one. A regular cluster's single
    breaks leave 3n - 7 independent contacts, so none of its paths does. A hypostatic cluster has f = 3n - 6 - m + s
    >= s + 1 flexes, and breaking B leaves f + |B| - r flexes and s - r stresses (r = rank W_B): a set with no
    stress left has two flexes or more and is not one-dimensional, so every path it follows keeps a stress.
    The shares of each class add up to one; the probes that decide subsets are part of the rest, none in a regular
    cluster (every set its single breaks leave has full row rank), some in a hypostatic one (sets with a stress and
    several flexes). The floors of the non-regular share: each below the share as measured and the next below it."""
    result = benchmark("classes", "--n", "10", "--sample", "1", "--no-numpy", "--no-every", "--no-unheld", "--parts")
    rows = {r["class"]: r for r in result["rows"]}
    assert set(rows) == {"regular", "singular", "hypostatic", "hyperstatic"}
    regular, hypostatic = rows["regular"]["parts"], rows["hypostatic"]["parts"]
    assert regular["stressed"]["per_cluster"] == 0 and regular["plain"]["per_cluster"] > 0
    assert hypostatic["plain"]["per_cluster"] == 0 and hypostatic["stressed"]["per_cluster"] > 0
    assert hypostatic["stressed"]["ms_per_path"] > 0 and hypostatic["stressed"]["steps_per_path"] > 0
    for r in rows.values():
        p = r["parts"]
        assert p["ms_each"] > 0 and 0.0 < p["rest_share"] < 1.0
        assert abs(p["stressed"]["share"] + p["plain"]["share"] + p["rest_share"] - 1.0) < 1e-9
        for kind in ("stressed", "plain"):
            parts = sum(p[kind][f"{part}_share"] for part in ("steps", "first_step", "endpoint"))
            assert 0.0 <= parts <= p[kind]["share"] + 1e-9
        assert 0.0 <= p["probes"]["share"] < p["rest_share"]
    assert regular["probes"]["per_cluster"] == 0 and regular["probes"]["share"] == 0.0
    assert hypostatic["probes"]["per_cluster"] > 0 and hypostatic["probes"]["ms_each"] > 0
    floors = result["floors"]
    assert floors["seconds"] == "total_s_numba"  # no run stored: the sample's own times
    assert 0.0 < floors["hyperstatic_only"] < floors["free"] < floors["share"] < 1.0
    [row] = benchmark("classes", "--n", "8", "--sample", "1", "--no-numpy", "--no-every", "--no-unheld")["rows"]
    assert "parts" not in row


def test_the_floors_of_the_non_regular_share():
    """floors() takes each class's stressed paths and probes off its time, then the singular and hypostatic
    classes altogether: worked by hand on made-up times."""
    from benchmarks.classes import floors

    def row(name, seconds, stressed, probes):
        return {
            "class": name,
            "run_s": seconds,
            "parts": {"stressed": {"share": stressed}, "probes": {"share": probes}},
        }

    rows = [
        row("regular", 60.0, 0.0, 0.0),
        row("singular", 20.0, 0.5, 0.25),
        row("hypostatic", 10.0, 0.5, 0.3),
        row("hyperstatic", 30.0, 0.2, 0.1),
    ]
    f = floors(rows, "run_s")
    assert f["share"] == 60.0 / 120.0
    left = 20.0 * 0.25 + 10.0 * 0.2 + 30.0 * 0.7  # 28
    assert abs(f["free"] - left / (60.0 + left)) < 1e-12
    assert abs(f["hyperstatic_only"] - 21.0 / 81.0) < 1e-12


def test_the_parts_of_expand_are_timed_by_wrappers_that_are_put_back():
    """Under the wrappers of --parts expand gives the same attempts, to the last bit, as without them; the paths'
    parts add up to no more than the paths; and the functions wrapped are the package's again afterwards."""
    from benchmarks.classes import _attempt_keys, _instrumented, _parts
    from packings.workers import dimension, expand, paths
    from packings.workers.params import Params
    from packings.workers.seeds import seed_cluster

    def wrapped():
        return (
            expand.PathStart.follow,
            paths._endpoint,
            paths._svd_tangent,
            paths._compiled.follow_steps,
            dimension._probe,
        )

    params = Params()
    before = wrapped()
    cluster = seed_cluster(8, params)  # regular: 18 = 3n - 6 contacts, first-order rigid
    split: dict = {}
    with _instrumented(split):
        timed = expand.expand(cluster, params)
    assert wrapped() == before
    assert _attempt_keys(timed) == _attempt_keys(expand.expand(cluster, params))
    assert split["plain"]["paths"] == timed.paths_followed > 0 and "stressed" not in split
    split = _parts(cluster, params)
    assert wrapped() == before
    plain = split["plain"]
    assert split["seconds"] > 0 and plain["path_steps"] > 0
    assert 0.0 < plain["steps"] + plain["endpoint"] <= plain["seconds"] <= split["seconds"]


def test_the_probes_of_parts_are_those_that_decide_subsets(monkeypatch):
    """--parts counts a probe of the dimension test as deciding a subset only outside a path: at the hypostatic
    n = 10 cluster, whose paths' first steps probe too, the probes it counts are exactly those made outside
    follow_path (told apart here by the call stack), and some are made inside."""
    import inspect

    from benchmarks.classes import _instrumented
    from packings.workers import dimension, expand
    from packings.workers.cluster import Cluster
    from packings.workers.params import Params

    fixtures = json.loads((ROOT / "tests" / "data" / "clusters_n10.json").read_text())
    cluster = Cluster.from_dict(fixtures["n10_m23_prestress"])
    made = Counter()
    probe = dimension._probe

    def counted(*args, **kwargs):
        made["in a path" if any(f.function == "follow_path" for f in inspect.stack(0)) else "deciding"] += 1
        return probe(*args, **kwargs)

    monkeypatch.setattr(dimension, "_probe", counted)
    split: dict = {}
    with _instrumented(split):
        expand.expand(cluster, Params())
    assert split["probes"]["calls"] == made["deciding"] > 0 and made["in a path"] > 0
    assert split["probes"]["seconds"] > 0


def test_the_classes_of_a_cluster():
    from benchmarks.classes import cluster_class

    assert cluster_class(12, 30, 0) == "regular" and cluster_class(12, 30, 2) == "singular"
    assert cluster_class(12, 29, 3) == "hypostatic" and cluster_class(12, 31, 0) == "hyperstatic"


def test_the_classes_benchmark_samples_every_number_of_contacts_in_proportion():
    """As the hyperstatic clusters of n = 12 (174 with 31 contacts, 8 with 32, 1 with 33): each number of
    contacts in proportion to its clusters, at least one each, none twice, the same for the same seed."""
    from types import SimpleNamespace

    import numpy as np

    from benchmarks.classes import _stratified

    members = [SimpleNamespace(m=m) for m in [31] * 174 + [32] * 8 + [33] * 1]
    pick = _stratified(members, 20, np.random.default_rng(0))
    assert pick == sorted(set(pick)) and pick == _stratified(members, 20, np.random.default_rng(0))
    assert Counter(members[i].m for i in pick) == {31: 19, 32: 1, 33: 1}
    assert len(_stratified(members, 1000, np.random.default_rng(1))) == len(members)


def test_the_classes_benchmark_reads_a_stored_catalogue(tmp_path):
    url = f"sqlite:///{tmp_path / 'c.db'}"
    enumerate_into(url, 8, "--quiet")
    report = benchmark("classes", "--n", "8", "--db", url, "--sample", "2", "--no-numpy")
    assert report["source"] == url and [(r["class"], r["clusters"], r["sampled"]) for r in report["rows"]] == [
        ("regular", 13, 2)
    ]
    assert "mean_ms_numpy" not in report["rows"][0] and report["rows"][0]["share_numba"] == 1.0
    r = subprocess.run(
        [sys.executable, "-m", "benchmarks", "classes", "--n", "9", "--db", url],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode != 0 and "no clusters of n = 9" in r.stderr


def test_the_memory_benchmark_reports_what_one_expansion_holds():
    """n = 10's close-packed fragment (24 contacts, regular: one attempt a contact), in a fresh process."""
    row = benchmark("memory", "--n", "10")
    assert row["n"] == 10 and row["contacts"] == 24 and row["attempts"] == 24
    # a close-packed fragment has symmetries: most of its paths are images of the few followed
    assert row["paths_by_symmetry"] > row["paths"] > 0
    assert (
        row["rigid_endpoints"] >= row["distinct"] > 0
        and row["paths"] + row["paths_by_symmetry"] >= row["rigid_endpoints"]
    )
    assert 0 < row["retained_mib"] <= row["traced_peak_mib"] and row["retained_bytes_per_attempt"] > 0
    assert row["max_rss_mib_after"] >= row["max_rss_mib_before"] > 0


@pytest.fixture(scope="module")
def run_of_9(tmp_path_factory) -> tuple[str, dict]:
    """(URL, diagnostics) of a complete run of n = 9 on one worker."""
    url = f"sqlite:///{tmp_path_factory.mktemp('nine') / 'c.db'}"
    return url, json.loads(enumerate_into(url, 9, "--json").stdout)["diagnostics"]


def test_the_classes_benchmark_gives_each_cluster_the_paths_that_had_arrived_when_its_run_expanded_it(run_of_9):
    """On one worker no other task writes while a task runs, so the arrivals read back from the run's
    timestamps are the ones its tasks read: every cluster then takes as many paths from the other end as
    it did in the run."""
    import packings
    from benchmarks.classes import _from_database, arrivals_of
    from packings.workers.expand import arrivals, expand
    from packings.workers.params import Params

    url, diagnostics = run_of_9
    with packings.connect(url) as cat:
        [run] = cat.runs()
    clusters = {cid: c for c, _, cid in _from_database(url, 9)}
    ids = sorted(clusters)
    came = arrivals_of(url, run["run"], "run", ids)
    every = arrivals_of(url, run["run"], "all", ids)
    took = given = 0
    for cid in ids:
        rows, recorded = came[cid]
        assert all(r in every[cid][0] for r in rows)
        assert expand(clusters[cid], Params(), arrivals=arrivals(rows)).paths_retraced == recorded
        took += recorded
        given += len(rows)
    assert took == diagnostics["paths_retraced"] > 0
    # a path that arrived after its cluster was expanded is not given: the cluster followed it itself
    assert sum(len(every[cid][0]) for cid in ids) > given
    # n = 9: 51 regular clusters and a singular one, every one sampled
    report = benchmark("classes", "--n", "9", "--db", url, "--sample", "60", "--no-numpy", "--no-every")
    row, singular = report["rows"]
    assert report["arrivals"] == "run" and report["run"] == run["run"]
    assert (row["class"], row["sampled"], row["run_expanded"], singular["class"], singular["run_expanded"]) == (
        "regular",
        51,
        51,
        "singular",
        1,
    )
    assert row["paths_retraced_each"] == row["run_paths_retraced_each"] == took / 51
    assert singular["paths_retraced_each"] == singular["run_paths_retraced_each"] == 0
    assert row["run_s"] > 0 and row["run_share"] + singular["run_share"] == pytest.approx(1.0)
    none = benchmark(
        "classes", "--n", "9", "--db", url, "--sample", "60", "--no-numpy", "--no-every", "--arrivals", "none"
    )["rows"][0]
    last = benchmark(
        "classes", "--n", "9", "--db", url, "--sample", "60", "--no-numpy", "--no-every", "--arrivals", "all"
    )["rows"][0]
    assert none["paths_retraced_each"] == 0 < row["paths_retraced_each"] < last["paths_retraced_each"]


def test_the_classes_benchmark_reads_when_each_task_read_its_clusters():
    """A task's expansions are written together: it read them the sum of their expand times before the
    first was written.  Another worker's, or the same worker's written later, are another task."""
    import datetime as dt

    from benchmarks.classes import _loaded

    t = dt.datetime(2026, 1, 1)
    ms = dt.timedelta(milliseconds=1)
    rows = [
        (1, "a", t + 1000 * ms, 0.5),
        (2, "a", t + 1001 * ms, 0.25),
        (3, "b", t + 1001 * ms, 0.1),
        (4, "a", t + 1400 * ms, 0.1),
        (5, "a", None, None),
    ]
    assert _loaded(rows) == {1: t + 250 * ms, 2: t + 250 * ms, 3: t + 901 * ms, 4: t + 1300 * ms}


def test_the_classes_benchmark_refuses_arrivals_without_a_run_of_the_same_parameters(run_of_9):
    url, _ = run_of_9
    r = subprocess.run(
        [sys.executable, "-m", "benchmarks", "classes", "--n", "9", "--db", url, "--max-break", "1"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode != 0 and "no complete run of n = 9 with --max-break 1" in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1


def test_the_retrace_benchmark_counts_the_paths_a_complete_run_follows_from_both_ends(run_of_9):
    url, diagnostics = run_of_9
    report = benchmark("retrace", "--n", "9", "--db", url)
    assert report["paths_followed"] == diagnostics["paths_followed"]
    assert report["paths_retraced"] == diagnostics["paths_retraced"] > 0
    assert report["attempts_with_direction"] == (
        diagnostics["paths_followed"] + diagnostics["paths_by_symmetry"] + diagnostics["paths_retraced"]
    )
    # the run took from the other end most of the paths it could: not where the path back's cluster was
    # expanded before the path arrived, and a symmetry's images count as paths_by_symmetry instead
    assert report["retracing"] >= report["paths_retraced"] >= 0.5 * report["retracing"]
    # n = 9's 52 clusters are regular but one (singular), and every path between two of them has its reverse
    assert report["ordered_pairs"] > 100 and report["rule_holds"] == report["ordered_pairs"]
    assert report["rule_fails"] == report["no_reverse"] == 0
    # one path of each pair is counted: at most half of the attempts between the clusters counted
    assert 0 < 2 * report["retracing"] <= report["retraceable"] <= report["attempts_with_direction"]
    r = subprocess.run(
        [sys.executable, "-m", "benchmarks", "retrace", "--n", "10", "--db", url],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode != 0 and "no complete run of n = 10" in r.stderr


def test_the_network_benchmark_reports_the_network_of_a_run(run_of_9):
    """n = 9: one component holding the 52 clusters, every path that reached a cluster counted once, no
    circle, and a route from the seed along the paths' directions whose every step is an edge."""
    import networkx as nx

    import packings

    url, diagnostics = run_of_9
    (report,) = benchmark("network", "--n", "9", "--db", url)
    assert (report["clusters"], report["components"], report["circular"]) == (52, 1, 0)
    assert report["rearranged"] == diagnostics["rearranged"] > 0
    assert report["paths"] == diagnostics["rigid"] + diagnostics["rearranged"]  # the paths that reached a cluster
    with packings.connect(url) as cat:
        g = cat.network(9)
    assert report["diameter"] == nx.diameter(nx.Graph(g.to_undirected())) > 1
    route = [x["id"] for x in report["route"]]
    assert g.nodes[route[0]]["found_by"] == "seed" and all(g.has_edge(a, b) for a, b in zip(route, route[1:]))


def test_the_progress_benchmark_projects_a_complete_run_onto_its_own_time(run_of_9, tmp_path):
    """n = 9 (the paper's 52, all with 21 contacts): every stored cluster expanded, the projection to the
    paper's counts is the run's own time in expand, its rows add up to the run's expansions, and the size
    is the SQLite file's."""
    from sqlalchemy import func, select

    import packings
    from packings.service.models import ExpansionRow

    url, _ = run_of_9
    r = benchmark("progress", "--n", "9", "--db", url, "--workers", "2")
    with packings.connect(url) as cat, cat.session() as s:
        total = s.execute(select(func.sum(ExpansionRow.seconds))).scalar()
    assert r["status"] == "complete" and r["clusters"] == 52 and r["expansions"] == {"done": 52}
    assert sum(row["expanded"] for row in r["rows"]) == sum(row["stored"] for row in r["rows"]) == 52
    assert {row["contacts"] for row in r["rows"]} == {21}
    p = r["projection"]
    assert p["not_yet_expanded"] == {} and p["paper_total"] == 52
    assert p["expand_seconds"] == pytest.approx(total) and p["hours_on_workers"] == pytest.approx(total / 2 / 3600)
    assert r["database_bytes"] >= Path(url.removeprefix("sqlite:///")).stat().st_size > 0
    r3 = benchmark("progress", "--n", "9", "--db", url, "--workers", "3", "--window", "1000")
    assert r3["projection"]["hours_on_workers"] == pytest.approx(total / 3 / 3600)
    # a window longer than the run: the recent figures are the whole run's
    assert sum(row["recent_expanded"] for row in r3["rows"]) == 52
    assert all(row["recent_mean_s"] == pytest.approx(row["mean_s"]) for row in r3["rows"])


def test_the_memory_benchmark_measures_a_glued_pass_record(run_of_9):
    """n = 9's 52 clusters in a record, then a sphere of 20 of them moved: the record holds every stored
    cluster and every remainder decided (not those certified floppy), a 16-byte digest each in a table half
    full at most (at least 1,024 slots): no more than 16 bytes a slot, where the float64 distances alone would
    be 288 bytes a cluster."""
    url, _ = run_of_9
    row = benchmark("memory", "--glued", "--n", "9", "--db", url, "--parents", "20")
    assert (row["n"], row["stored"], row["parents"]) == (9, 52, 20)
    assert row["decided"] > 0 and row["not_again"] > 0 and row["seconds"] > 0
    assert 0 < row["record_mib"] <= row["traced_peak_mib"]
    assert row["stored"] <= row["record_clusters"] <= row["stored"] + row["decided"]
    slots = max(1024, 4 * row["record_clusters"])  # a table is grown once it would be more than half full
    assert 0 < row["record_bytes_per_cluster"] * row["record_clusters"] <= 16 * slots + 1024
    r = subprocess.run(
        [sys.executable, "-m", "benchmarks", "memory", "--glued", "--n", "9"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert r.returncode != 0 and "--glued needs --db" in r.stderr


def test_the_free_energy_benchmark_tables_monte_carlo_against_the_formula():
    """n = 5 at two widths of the well: one row per width, the Monte Carlo integral of the trigonal bipyramid's
    basin within a few standard errors and a few ε of 8π² n^{3/2} z, and closer at the smaller width."""
    rows = benchmark("free_energy", "--sizes", "5", "--eps", "0.01", "0.0001", "--samples", "20000")["rows"]
    assert [(r["n"], r["m"], r["sigma"], r["eps"]) for r in rows] == [(5, 9, 6, 0.01), (5, 9, 6, 0.0001)]
    for r in rows:
        assert abs(r["ratio"] - 1.0) <= 4.0 * r["ratio_error"] + 3.0 * r["eps"] and r["edge"] < 0.9
    assert abs(rows[1]["ratio"] - 1.0) < abs(rows[0]["ratio"] - 1.0)


def test_the_replay_benchmark_replays_a_run_and_its_check_catches_a_dropped_expansion(run_of_9, tmp_path):
    """n = 9 recorded from a complete run and replayed through the coordinator on one and on two workers:
    the same catalogue, nothing left over.  Replayed with one cluster's recorded result dropped (its
    expansion answered with no attempt), the check against the true recording says so."""
    import pickle

    from benchmarks.replay import check, load, save

    url, _ = run_of_9
    recording = tmp_path / "n9.pickle"
    report = benchmark(
        "replay", "--n", "9", "--source", url, "--recording", str(recording), "--db", f"sqlite:///{tmp_path / 'r.db'}",
        "--writers", "1", "2",
    )  # fmt: skip
    assert (report["recorded"], report["left_out"]) == (52, 0)
    assert [(r["writers"], r["expansions"], r["clusters"], r["problems"]) for r in report["rows"]] == [
        (1, 52, 52, []),
        (2, 52, 52, []),
    ]
    assert not (tmp_path / "r_k1.db").exists()  # removed without --keep
    for r in report["rows"]:  # the coordinator's process sampled from the run's start to its end
        assert (
            0 < r["rss_start_mib"] <= r["rss_peak_mib"]
            and r["rss_quarter_mib"] <= r["rss_peak_mib"] >= r["rss_end_mib"]
        )

    rec = load(recording)
    dropped = next(k for k in sorted(rec.sources) if k != rec.seed)
    rec.sources[dropped] = pickle.dumps([])
    save(rec, tmp_path / "dropped.pickle")
    replayed = f"sqlite:///{tmp_path / 'd.db'}"
    report = benchmark(
        "replay", "--n", "9", "--recording", str(tmp_path / "dropped.pickle"), "--db", replayed, "--writers", "2",
        "--keep",
    )  # fmt: skip
    assert report["rows"][0]["expansions"] == 52  # every expansion was done, one of them wrongly
    problems = check(load(recording), replayed)
    assert problems and "another number of attempts" in problems[-1]


@pytest.mark.parametrize("backend", ["sqlite", "postgresql"])
def test_the_frontier_benchmark_times_claims_with_and_without_the_pending_index(backend):
    """Each size: the variants without and with ix_expansions_pending alternated, each claim taking its k
    (the pending count falls by k a claim), the times and the memory reported."""
    if backend == "postgresql":
        with pg_database():  # skips (or fails, where PostgreSQL is required) without a server
            pass
    report = benchmark("frontier", "--backends", backend, "--pending", "3000", "--claims", "5", "--k", "16")
    rows = report["rows"]
    assert [(r["backend"], r["index"]) for r in rows] == [(backend, i) for i in (False, True, False, True)]
    for i, r in enumerate(rows):
        assert r["pending"] == 3000 and r["done"] == 1500
        assert r["pending_after"] == 3000 - 5 * 16 * (i + 1)  # every claimed batch marked done
        assert r["claim_ms"] > 0.0 and r["progress_ms"] > 0.0 and r["rss_mib"] > 0.0
