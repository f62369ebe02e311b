"""Time in ``packings.workers.expand`` by class of cluster, against the code before and the numpy reference.

The clusters of n spheres fall into four classes by their m contacts and their
first-order flexes f (the null space of the pinned rigidity matrix):

* regular: m = 3n − 6 and f = 0 (first-order rigid, one subset of each size 1);
* singular: m = 3n − 6 and f > 0 (rigid only to second order);
* hypostatic: m < 3n − 6 (always singular);
* hyperstatic: m > 3n − 6.

The clusters come from a stored catalogue (``--db URL``: the clusters of ``--n``
in that database, e.g. the file a ``packings enumerate 12`` left), or, without
one, from the in-memory enumeration (``packings.workers.explore``, fine up to
n = 10).  From a catalogue each cluster is given the paths that arrived at it
(``expand(..., arrivals)``: docs/method.md): with
``--arrivals run`` (the default) those its run had stored, about, when its task read the
cluster (the transitions whose source's expansion was written before then, from
``expansions.finished_at``, ``seconds`` and ``worker``: :func:`_loaded`), so that it costs about
what it cost the run (the paths the run took from the other end are printed beside those the
sample takes); with ``all`` every one stored, what it would cost expanded last; with ``none``
none, what a run following every path pays.  The run is the newest complete one of n with
the same ``--max-break`` and ``--min-contacts``; its own time in ``expand`` by class
(``expansions.seconds``) is printed beside the sample's.

From each class a seeded random sample of about ``--sample`` clusters,
drawn apart for each number of contacts (at least one of each), is expanded
three ways in this process, alternating cluster by cluster,
so that all see the same load: as a run does, with every subset decided by an
SVD of what is left rather than by the first-order counts from the
self-stresses (``svd``: the code before them; its endpoints must be the same),
and with the numpy reference kernels.  A class's time is, for each number of
contacts, the mean time of its sampled clusters times their number, summed; its
share is of the sum over the classes, which is what ``expand`` costs a whole
run.  With ``--against FILE`` (a ``workers/_compiled.py`` of another version, e.g. ``git show
REV:workers/_compiled.py > before.py``) the compiled kernels of that file are timed too, in the
same process and alternating with the others: a change to the kernels measured as a ratio in one
run, with the attempts of the two compared one by one (outcome, steps and endpoint coordinates to
the last bit).  Unless ``--no-every``, expand is also timed following every path (``every``: the
code before it followed one path of each set that a symmetry of the cluster makes congruent), with
the paths whose outcome then differs counted.  Unless ``--no-unheld``, expand is timed following the paths
of subsets with a contact the rest holds at its length too (``unheld``: the code before the outcome
``held``), with the clusters whose other attempts or distinct clusters reached then differ counted.
With ``--parts`` each class's time is split (:func:`_parts`): the paths that keep a self-stress where
they start, by their stepping loop, first step and endpoint, the other paths, and the rest of expand
(deciding the subsets), with the dimension test's probes of the subsets apart; and the non-regular
classes' share is given again as it would be with those stressed paths and probes free, and with the
singular and hypostatic classes free besides (:func:`floors`): how far making those parts cheaper can
take it.  Also printed per class: the subsets of contacts tried per cluster (least
and most), the share of them whose set is not one-dimensional, and how many
sampled clusters gave the same endpoints, and how many reached the same distinct clusters, with both
backends.  Ratios measured in one run are what compare; absolute times
depend on the machine's load.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime as dt
import json
import os
import sys
import time
from collections import Counter

CLASSES = ("regular", "singular", "hypostatic", "hyperstatic")
#: --arrivals: the paths that arrived at a cluster that its expand call is given
ARRIVALS = ("run", "all", "none")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--n", type=int, default=10, help="number of spheres (default 10)")
    parser.add_argument(
        "--db",
        default=None,
        metavar="URL",
        help="a catalogue holding the clusters of N (default: enumerate N in memory, for N <= 10)",
    )
    parser.add_argument("--sample", type=int, default=20, help="clusters timed per class, about (default 20)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the sample (default 0)")
    parser.add_argument(
        "--numpy",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also time the numpy reference (default: yes)",
    )
    parser.add_argument(
        "--against",
        metavar="FILE",
        default=None,
        help="also time the compiled kernels of FILE, a workers/_compiled.py of another version "
        "(e.g. `git show REV:workers/_compiled.py > before.py`), in this process, and count "
        "the attempts that differ from the current code's",
    )
    parser.add_argument(
        "--every",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also time expand following every path, not one of each set a symmetry of the cluster "
        "makes congruent, and count the paths whose outcome differs (default: yes)",
    )
    parser.add_argument(
        "--unheld",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="also time expand following the paths of subsets with a contact the rest holds at "
        "its length (outcome held: docs/method.md), and count the attempts of other subsets "
        "and the clusters reached that differ (default: yes)",
    )
    parser.add_argument(
        "--max-break",
        type=int,
        default=None,
        metavar="K",
        help="break at most K contacts at once, as the run of a restricted catalogue did "
        "(`packings enumerate N --max-break K`; default: no cap)",
    )
    parser.add_argument(
        "--min-contacts",
        type=int,
        default=None,
        metavar="M",
        help="endpoints with fewer than M contacts are not kept, as in a run with "
        "`--min-contacts M` (default: all kept)",
    )
    parser.add_argument(
        "--arrivals",
        choices=ARRIVALS,
        default="run",
        help="with --db, the paths that arrived at each cluster that it is given: those its run had "
        "stored when it was expanded (run, the default), every one stored (all), or none",
    )
    parser.add_argument(
        "--parts",
        action="store_true",
        help="also split each class's time in expand (one more call per cluster, as a run makes it): "
        "the paths whose set keeps a self-stress (their steps, first step and endpoint), the "
        "other paths, and the rest (deciding the subsets; its probes apart), and the "
        "non-regular share were the stressed paths and probes free",
    )
    parser.add_argument(
        "--classes",
        nargs="+",
        choices=CLASSES,
        default=None,
        metavar="CLASS",
        help="time only these classes (default: every class present), e.g. `--classes regular singular` of "
        "a large n whose most hyperstatic clusters take minutes each (shares are then of those classes)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def cluster_class(n: int, m: int, flexes: int) -> str:
    """The class of a cluster of n spheres with m contacts and ``flexes`` first-order flexes."""
    if m < 3 * n - 6:
        return "hypostatic"
    if m > 3 * n - 6:
        return "hyperstatic"
    return "singular" if flexes > 0 else "regular"


def _from_database(url: str, n: int) -> list[tuple[object, str, int]]:
    """(core cluster, class, stored id) of every stored cluster of n spheres."""
    import packings

    with packings.connect(url) as cat:
        rows = list(cat.select(f"n={n}"))
    if not rows:
        raise SystemExit(f"no clusters of n = {n} in {url}: run `packings enumerate {n} --db {url}` first")
    from packings.workers.cluster import Cluster

    out = []
    for r in rows:
        c = Cluster(r.coords, tuple(tuple(int(v) for v in p) for p in r.contacts))
        out.append((c, cluster_class(n, c.m, int(r.flexes)), int(r.id)))
    return out


def _the_run(url: str, n: int, params) -> tuple[int, dict[str, tuple[int, float]]]:
    """(id, {class: (clusters expanded, seconds in expand)}) of the newest complete run of ``n`` in ``url``
    with ``params``' ``max_break`` and ``min_contacts``."""
    from sqlalchemy import select

    import packings
    from packings.service.models import COMPLETE, ClusterRow, ExpansionRow, Run

    with packings.connect(url) as cat, cat.session() as s:
        runs = [
            rid
            for rid, text in s.execute(
                select(Run.id, Run.params).where(Run.n == n, Run.status == COMPLETE).order_by(Run.id.desc())
            )
            if (json.loads(text).get("max_break"), json.loads(text).get("min_contacts"))
            == (params.max_break, params.min_contacts)
        ]
        if not runs:
            raise SystemExit(
                f"no complete run of n = {n} with --max-break {params.max_break} and --min-contacts "
                f"{params.min_contacts} in {url}: --arrivals none times expand without the paths "
                "that arrived"
            )
        times: dict[str, list] = {}
        for m, flexes, seconds in s.execute(
            select(ClusterRow.contacts, ClusterRow.flexes, ExpansionRow.seconds)
            .join(ClusterRow, ClusterRow.id == ExpansionRow.cluster_id)
            .where(ExpansionRow.run_id == runs[0])
        ):
            t = times.setdefault(cluster_class(n, m, flexes), [0, 0.0])
            t[0] += 1
            t[1] += seconds or 0.0
    return runs[0], {k: (v[0], v[1]) for k, v in times.items()}


def _loaded(rows) -> dict[int, dt.datetime]:
    """When each expansion's task was read, about, from rows (cluster id, worker, finished_at, seconds) of
    a run's expansions: a Dask task reads its expansions at once, expands them in turn and writes them back
    in one transaction (``packings.service.tasks.expand_task``), so those a worker finished within milliseconds of
    each other are one task, read about their expand calls' time before the first was written."""
    out: dict[int, dt.datetime] = {}
    task: list = []
    last = (None, None)  # the worker and time of the row before

    def close():
        if task:
            start = min(at for _, at, _ in task) - dt.timedelta(seconds=sum(sec for _, _, sec in task))
            out.update((cid, start) for cid, _, _ in task)
            task.clear()

    for cid, worker, at, seconds in sorted((r for r in rows if r[2] is not None), key=lambda r: (r[1] or "", r[2])):
        if task and (worker != last[0] or at - last[1] > _ONE_WRITE):
            close()
        task.append((cid, at, seconds or 0.0))
        last = (worker, at)
    close()
    return out


#: expansions of one worker written at most this far apart are of one transaction, one task
_ONE_WRITE = dt.timedelta(milliseconds=3)


def arrivals_of(url: str, run_id: int, mode: str, ids) -> dict[int, tuple[tuple[tuple, ...], int]]:
    """For each stored cluster id of ``ids``: the rows of :attr:`packings.service.store.Task.arrivals`, those run
    ``run_id`` had stored, about, when its task read the cluster (``mode`` "run": the transitions to it whose
    source's expansion was written before then, :func:`_loaded`), or every one stored (``mode`` "all"); and
    the paths the run took from the other end expanding it (``paths_retraced`` of ``expansions.outcomes``)."""
    from sqlalchemy import select

    import packings
    from packings.service.models import ExpansionRow
    from packings.service.queries import arrivals_at

    ids = sorted(set(ids))
    out: dict[int, list] = {cid: [] for cid in ids}
    with packings.connect(url) as cat, cat.session() as s:
        rows = s.execute(
            select(ExpansionRow.cluster_id, ExpansionRow.worker, ExpansionRow.finished_at, ExpansionRow.seconds).where(
                ExpansionRow.run_id == run_id
            )
        ).all()
        took = {
            cid: json.loads(outcomes or "{}").get("paths_retraced", 0)
            for cid, outcomes in s.execute(
                select(ExpansionRow.cluster_id, ExpansionRow.outcomes).where(
                    ExpansionRow.run_id == run_id, ExpansionRow.cluster_id.in_(ids)
                )
            )
        }
        finished = {cid: at for cid, _, at, _ in rows}
        loaded = _loaded(rows) if mode == "run" else {}
        for (_, target), came_to in arrivals_at(s, {(run_id, cid) for cid in ids}).items():
            for source, broken, new, steps, labels in came_to:
                if mode == "run":
                    read, came = loaded.get(target), finished.get(source)
                    if read is None or came is None or came > read:
                        continue
                out[target].append((source, broken, new, steps, labels))
    return {cid: (tuple(rows), took.get(cid, 0)) for cid, rows in out.items()}


def _from_memory(n: int, params) -> list[tuple[object, str, None]]:
    """(core cluster, class, None) of every cluster the in-memory enumeration of n finds."""
    from packings.workers.expand import cluster_rank
    from packings.workers.explore import explore

    out = []
    for c in explore(n, params).clusters:
        flexes = 3 * n - 6 - cluster_rank(c, params)
        out.append((c, cluster_class(n, c.m, flexes), None))
    return out


#: what is timed: name -> (kernel backend, decide subsets by the first-order counts, follow one path of
#: each set of paths a symmetry of the cluster makes congruent, leave held subsets unfollowed)
VARIANTS = {
    "numba": ("numba", True, True, True),  # the code a run uses
    "svd": ("numba", False, True, True),  # every subset decided by an SVD of what is left, as before the counts
    "numpy": ("numpy", True, True, True),  # the numpy reference kernels
    "against": ("numba", True, True, True),  # as "numba", with the kernels of --against FILE (kernels_from)
    "every": ("numba", True, False, True),  # as "numba", every path followed, as before the symmetries
    "unheld": ("numba", True, True, False),  # as "numba", the paths of subsets with a held contact followed too
}


#: the variant that runs the kernels of ``--against FILE`` (:data:`VARIANTS`)
AGAINST = "against"


def load_kernels(path: str):
    """The compiled kernels of ``path`` (a ``workers/_compiled.py`` of any version) as a module of their own."""
    import importlib.util

    if not os.path.isfile(path):
        raise SystemExit(f"--against: no such file: {path}")
    name = "packings_benchmark_against_compiled"
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    # importable by its name while it runs: numba's on-disk cache records each kernel's module by name and
    # imports it when it loads the kernel again (a module it cannot import fails the second run)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as exc:  # not Python, or not a kernels module of any version
        del sys.modules[name]
        raise SystemExit(f"--against: cannot load {path}: {type(exc).__name__}: {exc}") from None
    return module


@contextlib.contextmanager
def kernels_from(module):
    """Run the compiled backend with ``module``'s kernels in place of the package's: the two places that hold
    the compiled module (:mod:`packings.workers.kernels` once it has loaded it, and
    :mod:`packings.workers.paths`) point at ``module`` until the block ends."""
    from packings.workers import kernels, paths

    saved = kernels._numba(), paths._compiled
    kernels._compiled = paths._compiled = module
    try:
        yield
    finally:
        kernels._compiled, paths._compiled = saved


def _time(cluster, params, variant: str, against=None, came: tuple = ()):
    """(seconds, expansion) of one expand call as ``variant`` (:data:`VARIANTS`; :data:`AGAINST` with the
    kernels module ``against``), given the rows ``came`` of the paths that arrived at ``cluster``, as a
    worker calls it (``packings.service.tasks.expand``; the ``svd`` variant, deciding no subset by the
    cluster's own SVD, takes none from the other end)."""
    from packings.workers import kernels
    from packings.workers.expand import arrivals, expand

    backend, first_order, symmetric, held = VARIANTS[variant]
    swap = kernels_from(against) if variant == AGAINST else contextlib.nullcontext()
    with kernels.backend(backend), swap:
        t0 = time.perf_counter()
        ex = expand(cluster, params, first_order, symmetric, arrivals=arrivals(came), held=held)
        return time.perf_counter() - t0, ex


#: what :func:`_parts` splits a path's time into (beside the whole path): the compiled stepping loop, the first
#: step's dimension and tangent where the loop hands it to Python, and the endpoint (its rigidity included)
PATH_PARTS = ("steps", "first_step", "endpoint")


@contextlib.contextmanager
def _instrumented(split: dict):
    """Time every path that expand follows, and its parts (:data:`PATH_PARTS`), into ``split``: for each kind of
    path ("stressed": the contacts it keeps have a self-stress where it starts, the SVD of their pinned rigidity
    matrix counting a singular value below tol_n, so that each step of the compiled loop fails the rank guard
    wherever the stress persists; "plain": the others) the count, the seconds of whole paths, of each part and
    the steps taken; under "probes" the calls and seconds of the dimension test's probes outside the paths (those
    that decide the subsets; a path's first step counts its own); and under "overhead" the seconds spent telling
    the kinds apart, which the caller takes off.  The functions wrapped are put back when the block ends."""
    import numpy as np

    from packings.workers import dimension, expand, kernels, paths

    compiled = paths._compiled
    saved = expand.PathStart.follow, paths._endpoint, paths._svd_tangent, compiled.follow_steps, dimension._probe
    follow, endpoint, first_step, steps, probe = saved
    inside = Counter()
    probes = split.setdefault("probes", {"calls": 0, "seconds": 0.0})
    following = False  # inside a path: its probes are its first step's

    def timed(f, part):
        def call(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return f(*args, **kwargs)
            finally:
                inside[part] += time.perf_counter() - t0

        return call

    def timed_probe(*args, **kwargs):
        if following:
            return probe(*args, **kwargs)
        t0 = time.perf_counter()
        try:
            return probe(*args, **kwargs)
        finally:
            probes["calls"] += 1
            probes["seconds"] += time.perf_counter() - t0

    def timed_follow(start, params):
        nonlocal following
        inside.clear()
        following = True
        t0 = time.perf_counter()
        try:
            end = follow(start, params)
        finally:
            following = False
        seconds = time.perf_counter() - t0
        t1 = time.perf_counter()
        ns = kernels.null_spaces(start.x, np.asarray(start.keep).reshape(-1, 2), start.free, params.tol_n)
        kind = split.setdefault(
            "stressed" if ns.W.shape[1] else "plain",
            {"paths": 0, "seconds": 0.0, "path_steps": 0, **{p: 0.0 for p in PATH_PARTS}},
        )
        kind["paths"] += 1
        kind["seconds"] += seconds
        kind["path_steps"] += end.steps
        for part in PATH_PARTS:
            kind[part] += inside[part]
        split["overhead"] = split.get("overhead", 0.0) + time.perf_counter() - t1
        return end

    expand.PathStart.follow = timed_follow
    paths._endpoint, paths._svd_tangent = timed(endpoint, "endpoint"), timed(first_step, "first_step")
    compiled.follow_steps = timed(steps, "steps")
    dimension._probe = timed_probe
    try:
        yield
    finally:
        expand.PathStart.follow, paths._endpoint, paths._svd_tangent, compiled.follow_steps, dimension._probe = saved


def _parts(cluster, params, came: tuple = ()) -> dict:
    """One expand call of ``cluster`` as a run makes it, its time split by :func:`_instrumented`: "seconds" the
    whole call less the time spent telling the kinds of path apart, "stressed" and "plain" the paths of each kind
    (absent where there is none), "probes" the probes that decided subsets."""
    from packings.workers import kernels
    from packings.workers.expand import arrivals, expand

    split: dict = {}
    with kernels.backend("numba"), _instrumented(split):
        t0 = time.perf_counter()
        expand(cluster, params, arrivals=arrivals(came))
        seconds = time.perf_counter() - t0
    split["seconds"] = seconds - split.pop("overhead", 0.0)
    return split


def _attempt_keys(ex) -> list[tuple]:
    """Every attempt of an expansion as (subset, direction, outcome, steps, new contacts, endpoint coordinates'
    bytes): what must be the same, to the last bit, after a change that moves no number."""
    return [
        (
            e.broken,
            e.direction,
            e.outcome,
            e.steps,
            e.new_contacts,
            None if e.cluster is None else e.cluster.coords.tobytes(),
        )
        for e in ex.endpoints
    ]


def _path_outcomes(endpoints) -> Counter:
    """(subset, outcome) of every path followed, counted."""
    return Counter((e.broken, e.outcome) for e in endpoints if e.direction != 0)


def _reached(ex) -> Counter:
    """The distinct clusters an expansion reached, by their certificates."""
    from packings.workers.identity import certificate_hex

    return Counter(certificate_hex(ex.endpoints[j].cluster) for j in ex.distinct())


def _stratified(members, sample: int, rng) -> list[int]:
    """Indices of a seeded sample of ``members``, drawn apart for each number of contacts: in proportion to
    how many clusters have it, at least one each (so about ``sample`` in all, more where a class has many
    numbers of contacts).  A hyperstatic cluster with more contacts costs many times one with fewer (its
    subsets grow as C(m, k)): a sample blind to them weighs the few dearest ones by chance."""
    by_m: dict[int, list[int]] = {}
    for i, c in enumerate(members):
        by_m.setdefault(c.m, []).append(i)
    pick = []
    for m in sorted(by_m):
        idx = by_m[m]
        k = min(len(idx), max(1, round(sample * len(idx) / len(members))))
        pick.extend(idx[j] for j in rng.choice(len(idx), size=k, replace=False))
    return sorted(pick)


def _variants(numpy: bool, against, every: bool, unheld: bool) -> list[str]:
    """The variants (:data:`VARIANTS`) that :func:`measure` times, in the order each cluster runs them."""
    return (
        ["numba", "svd"]
        + ([AGAINST] if against is not None else [])
        + (["numpy"] if numpy else [])
        + (["every"] if every else [])
        + (["unheld"] if unheld else [])
    )


@dataclasses.dataclass
class _Tally:
    """What :func:`measure` adds up over a class's sampled clusters."""

    totals: dict  #: variant -> the class's whole time: each number of contacts by its own mean
    subsets: list = dataclasses.field(default_factory=list)  #: subsets tried, per sampled cluster
    not_1d: int = 0
    same: int = 0
    same_reached: int = 0
    svd_differ: int = 0
    against_differ: int = 0
    attempts: int = 0
    images: int = 0
    every_differ: int = 0
    retraced: int = 0
    run_retraced: int = 0
    held: int = 0
    unheld_differ: int = 0
    #: --parts: the class's time and its kinds of path and probes (:func:`_add_parts`)
    split: dict = dataclasses.field(
        default_factory=lambda: {
            "seconds": 0.0,
            "weighted": Counter(),
            "stressed": Counter(),
            "plain": Counter(),
            "probes": Counter(),
        }
    )


def _compare(t: _Tally, results: dict, numpy: bool, every: bool, unheld: bool, against) -> None:
    """Add to ``t`` one sampled cluster's counts and how its variants' expansions (``results``: variant ->
    (seconds, expansion)) differ from the compiled one's, asserting what must not differ."""
    from packings.workers.expand import HELD, NOT_1D

    ex = results["numba"][1]
    t.subsets.append(ex.subsets_tried)
    t.not_1d += sum(1 for e in ex.endpoints if e.outcome == NOT_1D)
    if numpy:
        a, b = results["numba"][1], results["numpy"][1]
        t.same += [e.outcome for e in a.endpoints] == [e.outcome for e in b.endpoints]
        t.same_reached += _reached(a) == _reached(b)
    # deciding subsets by the first-order counts decides every subset the same way; a path it
    # follows starts along the same tangent only to rounding (and sign: the direction labels may
    # be swapped), so a marginal one may end otherwise
    svd = results["svd"][1].endpoints
    assert [(e.broken, e.direction == 0) for e in ex.endpoints] == [(e.broken, e.direction == 0) for e in svd]
    assert [e.outcome for e in ex.endpoints if e.direction == 0] == [e.outcome for e in svd if e.direction == 0]
    t.svd_differ += sum((_path_outcomes(ex.endpoints) - _path_outcomes(svd)).values())
    t.attempts += len(ex.endpoints)
    t.images += ex.paths_by_symmetry
    t.retraced += ex.paths_retraced
    if every:  # the same subsets; each path's outcome as the path of its image's subset ended
        everyone = results["every"][1].endpoints
        assert [e.broken for e in ex.endpoints] == [e.broken for e in everyone]
        t.every_differ += sum((_path_outcomes(ex.endpoints) - _path_outcomes(everyone)).values())
    if unheld:  # every attempt of a subset not held the same to the bit, and the same clusters reached
        other = results["unheld"][1]
        kept = {e.broken for e in ex.endpoints if e.outcome == HELD}
        t.held += len(kept)
        t.unheld_differ += _reached(ex) != _reached(other) or [k for k in _attempt_keys(ex) if k[0] not in kept] != [
            k for k in _attempt_keys(other) if k[0] not in kept
        ]
    if against is not None:
        mine, theirs = _attempt_keys(ex), _attempt_keys(results[AGAINST][1])
        t.against_differ += sum(a != b for a, b in zip(mine, theirs)) + abs(len(mine) - len(theirs))


def _add_parts(split: dict, one: dict, scale: float) -> None:
    """Add one sampled cluster's split (:func:`_parts`) to its class's ``split``, its times weighted by ``scale``
    (the clusters with as many contacts each sampled one stands for)."""
    split["seconds"] += one["seconds"] * scale
    for kind in ("stressed", "plain", "probes"):
        for key, value in one.get(kind, {}).items():
            split[kind][key] += value  # the sample's own paths and probes: counts, ms each
            if key not in ("paths", "path_steps", "calls"):
                split["weighted"][(kind, key)] += value * scale


def _sample_class(members, pick, keys, given, params, backends, against, numpy, every, unheld, parts) -> _Tally:
    """Expand the sampled clusters ``pick`` of one class's ``members`` as each variant of ``backends``, in turn
    cluster by cluster, given the paths that arrived at each (``given``, by key), and tally what is measured."""
    weight = Counter(c.m for c in members)  # clusters with as many contacts
    picked = Counter(members[i].m for i in pick)
    t = _Tally(totals={b: 0.0 for b in backends})
    for i in pick:
        came_rows, took = given.get(keys[i], ((), 0))
        t.run_retraced += took
        results = {b: _time(members[i], params, b, against, came_rows) for b in backends}
        scale = weight[members[i].m] / picked[members[i].m]  # each number of contacts by its own mean
        for b, (s, _) in results.items():
            t.totals[b] += s * scale
        _compare(t, results, numpy, every, unheld, against)
        if parts:  # one more call, apart from the others: its wrappers cost a little
            _add_parts(t.split, _parts(members[i], params, came_rows), scale)
    return t


def _class_row(name: str, members, pick, t: _Tally, backends, numpy, against, every, unheld, parts) -> dict:
    """The row of :func:`measure` of the class ``name`` from its tally ``t``."""
    row = {
        "class": name,
        "clusters": len(members),
        "sampled": len(pick),
        "subsets_min": min(t.subsets),
        "subsets_max": max(t.subsets),
        "not_1d_share": t.not_1d / max(1, sum(t.subsets)),
        "svd_paths_differing": t.svd_differ,
        "attempts": t.attempts,
    }
    for b in backends:
        row[f"mean_ms_{b}"] = 1e3 * t.totals[b] / len(members)
        row[f"total_s_{b}"] = t.totals[b]
    row["svd_ratio"] = row["mean_ms_svd"] / row["mean_ms_numba"]
    row["paths_by_symmetry"] = t.images
    row["paths_retraced_each"] = t.retraced / len(pick)
    row["run_paths_retraced_each"] = t.run_retraced / len(pick)  # what the run took on the same clusters
    if every:
        row["every_ratio"] = row["mean_ms_every"] / row["mean_ms_numba"]
        row["every_paths_differing"] = t.every_differ
    if unheld:
        row["unheld_ratio"] = row["mean_ms_unheld"] / row["mean_ms_numba"]
        row["held"] = t.held
        row["unheld_clusters_differing"] = t.unheld_differ
    if against is not None:
        row["against_ratio"] = row[f"mean_ms_{AGAINST}"] / row["mean_ms_numba"]
        row["against_attempts_differing"] = t.against_differ
    if parts:
        row["parts"] = _parts_row(t.split, len(members), len(pick))
    if numpy:
        row["same_endpoints"] = t.same
        row["same_clusters_reached"] = t.same_reached
        row["ratio"] = row["mean_ms_numpy"] / row["mean_ms_numba"]
    return row


def measure(
    clusters: list[tuple[object, str, object]],
    params,
    sample: int,
    seed: int,
    numpy: bool,
    against=None,
    every: bool = False,
    came=None,
    unheld: bool = False,
    parts: bool = False,
) -> list[dict]:
    """One row per class present: counts, mean seconds per cluster per backend, subsets, not-1d share, paths
    taken from the other end; with ``against`` (a kernels module, :func:`load_kernels`) also its time and the
    attempts that differ; with ``every``, the time of following every path and the paths whose outcome
    differs; with ``unheld``, the time of following the paths of held subsets too, and the clusters whose other
    attempts or distinct clusters reached differ; with ``parts``, where the time goes (:func:`_parts`, a row's
    "parts").  ``clusters``: (cluster, class, key); ``came(keys)``: for each of the clusters ``keys``, the rows of
    the paths that arrived at it and the paths its run took from the other end (:func:`arrivals_of`); every
    cluster given none without it."""
    import numpy as np

    backends = _variants(numpy, against, every, unheld)
    rng = np.random.default_rng(seed)
    rows = []
    for name in CLASSES:
        members = [c for c, k, _ in clusters if k == name]
        if not members:
            continue
        pick = _stratified(members, sample, rng)
        keys = [key for _, k, key in clusters if k == name]
        given = came([keys[i] for i in pick]) if came is not None else {}
        t = _sample_class(members, pick, keys, given, params, backends, against, numpy, every, unheld, parts)
        rows.append(_class_row(name, members, pick, t, backends, numpy, against, every, unheld, parts))
    for b in backends:
        whole = sum(r[f"total_s_{b}"] for r in rows) or 1.0
        for r in rows:
            r[f"share_{b}"] = r[f"total_s_{b}"] / whole
    return rows


def _parts_row(split: dict, clusters: int, sampled: int) -> dict:
    """A class's "parts": ``ms_each`` the mean time of its instrumented expand calls (each number of contacts by
    its own mean, as the class's time), and for each kind of path its ``share`` of that time, its parts' shares
    (:data:`PATH_PARTS`), the paths ``per_cluster``, ``ms_per_path`` and ``steps_per_path`` of the sample; the
    ``rest_share``, what deciding the subsets (and everything else expand does) takes, and of it ``probes``: the
    ``share`` of the dimension test's probes that decide subsets, their calls ``per_cluster`` and ``ms_each``."""
    whole = split["seconds"] or 1.0
    row = {"ms_each": 1e3 * split["seconds"] / clusters}
    rest = 1.0
    for kind in ("stressed", "plain"):
        mine = split[kind]
        share = split["weighted"][(kind, "seconds")] / whole
        rest -= share
        row[kind] = {
            "share": share,
            **{f"{p}_share": split["weighted"][(kind, p)] / whole for p in PATH_PARTS},
            "per_cluster": mine["paths"] / sampled,
            "ms_per_path": 1e3 * mine["seconds"] / mine["paths"] if mine["paths"] else 0.0,
            "steps_per_path": mine["path_steps"] / mine["paths"] if mine["paths"] else 0.0,
        }
    row["rest_share"] = rest
    mine = split["probes"]
    row["probes"] = {
        "share": split["weighted"][("probes", "seconds")] / whole,
        "per_cluster": mine["calls"] / sampled,
        "ms_each": 1e3 * mine["seconds"] / mine["calls"] if mine["calls"] else 0.0,
    }
    return row


def floors(rows: list[dict], seconds: str) -> dict:
    """What --parts says of the non-regular classes' share of ``expand`` (the classes' time ``seconds``: a row's
    ``run_s`` or ``total_s_numba``), were the dearest parts of their work free: ``share`` as it is; ``free``
    with every class's stressed paths and subset-deciding probes taking no time (each class's time times the share
    its parts leave); ``hyperstatic_only`` with that and the singular and hypostatic classes taking no time at
    all, what the hyperstatic class's plain paths and the rest of its subsets cost beside the regular class."""
    left = {
        r["class"]: r[seconds] * (1.0 - r["parts"]["stressed"]["share"] - r["parts"]["probes"]["share"]) for r in rows
    }
    whole = {r["class"]: r[seconds] for r in rows}

    def share(times: dict, others) -> float:
        total = sum(times.values())
        return sum(times[c] for c in others if c in times) / total if total else 0.0

    irregular = CLASSES[1:]  # all but regular
    hyper = {c: t for c, t in left.items() if c in ("regular", "hyperstatic")}
    return {
        "seconds": seconds,
        "share": share(whole, irregular),
        "free": share(left, irregular),
        "hyperstatic_only": share(hyper, irregular),
    }


def run(args: argparse.Namespace) -> int:
    """Measure the classes of ``args.n`` and print a table of them, or with ``--json`` one JSON object."""
    from packings.workers import kernels
    from packings.workers.params import Params

    if not kernels.numba_available():
        print("numba is not available: nothing to measure", file=sys.stderr)
        return 1
    if args.sample < 1:
        print("--sample must be at least 1", file=sys.stderr)
        return 2
    params = Params(max_break=args.max_break, min_contacts=args.min_contacts)
    against = load_kernels(args.against) if args.against else None
    clusters = _clusters_to_measure(args, params, against)
    if args.classes:
        clusters = [c for c in clusters if c[1] in args.classes]
        if not clusters:
            print(f"no cluster of n = {args.n} in the classes {', '.join(args.classes)}", file=sys.stderr)
            return 1
    mode = args.arrivals if args.db else "none"  # the in-memory enumeration stores no paths
    run_id, run_times, came = None, {}, None
    if mode != "none":
        run_id, run_times = _the_run(args.db, args.n, params)
        came = lambda keys: arrivals_of(args.db, run_id, mode, keys)  # noqa: E731
    rows = measure(
        clusters, params, args.sample, args.seed, args.numpy, against, args.every, came, args.unheld, args.parts
    )
    result = _result(args, mode, run_id, run_times, rows)
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    _print_table(args, len(clusters), result)
    return 0


def _clusters_to_measure(args: argparse.Namespace, params, against) -> list[tuple[object, str, object]]:
    """(cluster, class, key) of every cluster of ``args.n``, from ``--db`` or the in-memory enumeration, after
    compiling the kernels (those of ``against`` too) so that no timed call pays for it."""
    from packings.workers import kernels
    from packings.workers.expand import warm_up

    with kernels.backend("numba"):
        warm_up()
        if against is not None:
            with kernels_from(against):
                try:
                    warm_up()
                except AttributeError as exc:  # a version older than the code that calls it
                    raise SystemExit(f"--against: {args.against} lacks a kernel the current code calls ({exc})")
        return _from_database(args.db, args.n) if args.db else _from_memory(args.n, params)


def _result(args: argparse.Namespace, mode: str, run_id, run_times: dict, rows: list[dict]) -> dict:
    """The JSON object of :func:`run`: what was measured and how, and the ``rows`` of :func:`measure`, each given
    its class's time in the run ``run_id`` (``run_times``: class -> (clusters expanded, seconds))."""
    whole = sum(seconds for _, seconds in run_times.values()) or 1.0
    for r in rows:
        expanded, seconds = run_times.get(r["class"], (0, 0.0))
        r["run_expanded"], r["run_s"], r["run_share"] = expanded, seconds, seconds / whole
    result = {
        "n": args.n,
        "source": args.db or "in-memory enumeration",
        "seed": args.seed,
        "against": args.against,
        "arrivals": mode,
        "run": run_id,
        "max_break": args.max_break,
        "min_contacts": args.min_contacts,
        "cpus": os.cpu_count(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "rows": rows,
    }
    if args.parts:
        result["floors"] = floors(rows, "run_s" if run_id is not None else "total_s_numba")
    return result


def _print_table(args: argparse.Namespace, clusters: int, result: dict) -> None:
    """The text of :func:`run`: a title, a line per class, the legend, --parts' table and the svd variant's
    differing paths (``clusters``: how many were measured)."""
    run_id, rows = result["run"], result["rows"]
    limits = "".join(
        f", {name} {value}"
        for name, value in (("--max-break", args.max_break), ("--min-contacts", args.min_contacts))
        if value is not None
    )
    given = {
        "run": f"the paths that arrived at each before run {run_id} expanded it",
        "all": f"every path of run {run_id} that arrived at each",
        "none": "no path that arrived",
    }[result["arrivals"]]
    print(
        f"n = {args.n}: {clusters} clusters ({result['source']}{limits}); time in expand by class, "
        f"a sample of up to {args.sample} each, given {given}"
    )
    print(_header(args, run_id))
    for r in rows:
        print(_row_line(args, run_id, r))
    print(_legend(args, run_id))
    if args.parts:
        _print_parts(rows, result["floors"])
    differ = sum(r["svd_paths_differing"] for r in rows)
    if differ:
        print(
            f"{differ} path(s) of the sample ended otherwise with the svd variant (same subsets and directions; "
            "their tangents agree only to rounding)"
        )


def _header(args: argparse.Namespace, run_id) -> str:
    """The table's header: the columns of the variants ``args`` asks for, and of the run ``run_id`` if any."""
    head = (
        f"{'class':<12}{'clusters':>9}{'sampled':>8}{'ms each':>10}{'share':>8}{'subsets':>13}{'not 1-d':>9}"
        f"{'retraced':>9}"
    )
    if run_id is not None:
        head += f"{'in run':>7}{'run s':>9}{'run share':>10}"
    head += f"{'svd ms':>9}{'svd share':>10}{'svd/':>6}"
    if args.against:
        head += f"{'before ms':>10}{'before/':>8}{'differ':>11}"
    if args.every:
        head += f"{'every ms':>10}{'every/':>7}{'images':>8}{'differ':>7}"
    if args.unheld:
        head += f"{'unheld ms':>10}{'unheld/':>8}{'held':>8}{'differ':>7}"
    if args.numpy:
        head += f"{'numpy ms':>10}{'numpy share':>12}{'ratio':>7}{'same':>7}{'same cl':>8}"
    return head


def _row_line(args: argparse.Namespace, run_id, r: dict) -> str:
    """The table's line of the row ``r`` of :func:`measure`, under :func:`_header`."""
    line = (
        f"{r['class']:<12}{r['clusters']:>9}{r['sampled']:>8}{r['mean_ms_numba']:>10.1f}"
        f"{r['share_numba']:>8.0%}{str(r['subsets_min']) + '-' + str(r['subsets_max']):>13}"
        f"{r['not_1d_share']:>9.0%}{r['paths_retraced_each']:>9.1f}"
    )
    if run_id is not None:
        line += f"{r['run_paths_retraced_each']:>7.1f}{r['run_s']:>9.1f}{r['run_share']:>10.0%}"
    line += f"{r['mean_ms_svd']:>9.1f}{r['share_svd']:>10.0%}{r['svd_ratio']:>6.2f}"
    if args.against:
        line += (
            f"{r['mean_ms_' + AGAINST]:>10.1f}{r['against_ratio']:>8.3f}"
            f"{str(r['against_attempts_differing']) + '/' + str(r['attempts']):>11}"
        )
    if args.every:
        line += (
            f"{r['mean_ms_every']:>10.1f}{r['every_ratio']:>7.2f}{r['paths_by_symmetry']:>8}"
            f"{r['every_paths_differing']:>7}"
        )
    if args.unheld:
        line += (
            f"{r['mean_ms_unheld']:>10.1f}{r['unheld_ratio']:>8.2f}{r['held']:>8}{r['unheld_clusters_differing']:>7}"
        )
    if args.numpy:
        line += (
            f"{r['mean_ms_numpy']:>10.1f}{r['share_numpy']:>12.0%}{r['ratio']:>7.1f}"
            f"{str(r['same_endpoints']) + '/' + str(r['sampled']):>7}"
            f"{str(r['same_clusters_reached']) + '/' + str(r['sampled']):>8}"
        )
    return line


def _legend(args: argparse.Namespace, run_id) -> str:
    """The legend under the table: what each column of :func:`_header` holds."""
    return (
        "(ms each: mean wall time of one expand call; share: of the whole run's time in expand, the mean "
        "times the class's clusters; retraced: paths taken from the other end, per cluster"
        + (
            "; in run: those the run took expanding the same clusters; run s, run share: the run's own time in "
            "expand, expansions.seconds"
            if run_id is not None
            else ""
        )
        + "; svd: every subset decided by an SVD of what is left, not by the "
        "first-order counts, and no path taken from the other end; svd/ = svd / ms each; ratio = numpy / compiled"
        + (
            "; before: the kernels of --against, before/ = before / ms each, differ: attempts not the same "
            "to the last bit, of all"
            if args.against
            else ""
        )
        + (
            "; every: every path followed, not one of each set congruent by a symmetry of the cluster, every/ = "
            "every / ms each, images: paths taken as images, differ: paths whose outcome is not the one following "
            "every path gave"
            if args.every
            else ""
        )
        + (
            "; unheld: the paths of subsets with a contact the rest holds followed too, unheld/ = unheld / ms each, "
            "held: subsets held, differ: clusters whose other attempts or clusters reached differ"
            if args.unheld
            else ""
        )
        + (
            "; same: sampled clusters whose attempts all end as with numpy, same cl: whose distinct clusters "
            "reached are the same (certificates) as with numpy"
            if args.numpy
            else ""
        )
        + ")"
    )


def _print_parts(rows: list[dict], floor: dict) -> None:
    """The table of --parts: where each class's time in expand goes, and the floors of the non-regular share."""
    print()
    print(
        f"{'class':<12}{'ms each':>9}{'stressed':>10}{'each':>7}{'ms':>7}{'steps':>7}{'loop':>7}"
        f"{'first':>7}{'end':>7}{'plain':>8}{'each':>7}{'ms':>7}{'rest':>7}{'probes':>8}{'each':>7}{'ms':>7}"
    )
    for r in rows:
        p = r["parts"]
        st, pl, pr = p["stressed"], p["plain"], p["probes"]
        print(
            f"{r['class']:<12}{p['ms_each']:>9.1f}{st['share']:>10.0%}{st['per_cluster']:>7.1f}"
            f"{st['ms_per_path']:>7.2f}"
            f"{st['steps_per_path']:>7.0f}{st['steps_share']:>7.0%}{st['first_step_share']:>7.0%}"
            f"{st['endpoint_share']:>7.0%}{pl['share']:>8.0%}{pl['per_cluster']:>7.1f}{pl['ms_per_path']:>7.2f}"
            f"{p['rest_share']:>7.0%}{pr['share']:>8.0%}{pr['per_cluster']:>7.0f}{pr['ms_each']:>7.2f}"
        )
    print(
        "(--parts: one more expand call per sampled cluster, timed by parts; stressed: the paths whose contacts "
        "kept have a self-stress where they start, their share of the class's time, paths per cluster (each), ms "
        "and steps a path, and the shares of the class's time in their stepping loop (loop), their first step "
        "where Python decides it (first) and their endpoints (end); plain: the other paths; rest: deciding the "
        "subsets and the rest of expand; probes: of the rest, the dimension test's probes that decide subsets, "
        "their share, calls per cluster (each) and ms a call)"
    )
    whose = "the run's" if floor["seconds"] == "run_s" else "the sample's"
    print(
        f"non-regular classes' share of {whose} time in expand: {floor['share']:.1%}; with every stressed path "
        f"and every probe deciding a subset free, {floor['free']:.1%}; with that and the singular and hypostatic "
        f"classes free altogether (the hyperstatic class's plain paths and the rest of its subsets beside the "
        f"regular class), {floor['hyperstatic_only']:.1%}"
    )
