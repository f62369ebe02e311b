"""Median wall time of following one path, compiled kernels against the numpy reference.

For each n, a fixed set of rigid clusters is built cheaply and deterministically
(the polytetrahedron seed and the first distinct rigid clusters one expansion of
it reaches), every path those clusters start is listed (packings.workers.expand.path_starts),
and a seeded random sample of them is followed with both backends in the same
process, alternating path by path.  One path's cost is one call of
packings.workers.paths.follow_path (stepping, endpoint projection and rigidity test).
The first-call cost is that of packings.workers.expand.warm_up() at the start: numba
compiling every kernel, or loading them from its on-disk cache (--cold forces
a compile into a fresh cache directory).
"""

from __future__ import annotations

import argparse
import atexit
import json
import os
import platform
import shutil
import statistics
import sys
import tempfile
import time

DEFAULT_SIZES = (10, 12, 14)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--sizes",
        type=int,
        nargs="+",
        default=list(DEFAULT_SIZES),
        metavar="N",
        help="numbers of spheres (default: 10 12 14)",
    )
    parser.add_argument("--paths", type=int, default=60, help="paths sampled per n (default 60)")
    parser.add_argument(
        "--clusters",
        type=int,
        default=4,
        help="clusters per n: the seed and the first rigid clusters it reaches (default 4)",
    )
    parser.add_argument("--seed", type=int, default=0, help="seed of the path sample (default 0)")
    parser.add_argument("--quick", action="store_true", help="fewer paths (12 per n) and clusters (2 per n)")
    parser.add_argument(
        "--cold",
        action="store_true",
        help="compile into a fresh numba cache directory, so the first call pays for compilation",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def _clusters(n: int, count: int, params):
    """The seed of n spheres and the first ``count - 1`` distinct rigid clusters its expansion reaches."""
    from packings.workers.expand import expand
    from packings.workers.identity import ClusterIndex
    from packings.workers.paths import RIGID
    from packings.workers.seeds import seed_cluster

    seed = seed_cluster(n, params)
    index = ClusterIndex()
    index.add(seed, params.tol_d)
    for e in expand(seed, params).endpoints:
        if len(index) >= count:
            break
        if e.outcome == RIGID:
            index.add(e.cluster, params.tol_d)
    return list(index)


def _sample(n: int, clusters: int, paths: int, seed: int, params):
    import numpy as np

    from packings.workers.expand import path_starts

    starts = [p for c in _clusters(n, clusters, params) for p in path_starts(c, params)]
    rng = np.random.default_rng([seed, n])
    pick = np.sort(rng.choice(len(starts), size=min(paths, len(starts)), replace=False))
    return [starts[i] for i in pick], len(starts)


def _time_paths(starts, params) -> dict:
    from packings.workers import kernels

    cost = {"numba": [], "numpy": []}
    cpu = {"numba": [], "numpy": []}
    outcomes = {"numba": [], "numpy": []}
    for p in starts:
        for name in ("numba", "numpy"):
            with kernels.backend(name):
                c0, t0 = time.process_time(), time.perf_counter()
                end = p.follow(params)
                cost[name].append(time.perf_counter() - t0)
                cpu[name].append(time.process_time() - c0)
            outcomes[name].append(end.outcome)
    same = sum(a == b for a, b in zip(outcomes["numba"], outcomes["numpy"]))
    return {
        "median_ms_numpy": 1e3 * statistics.median(cost["numpy"]),
        "median_ms_compiled": 1e3 * statistics.median(cost["numba"]),
        "mean_ms_numpy": 1e3 * statistics.fmean(cost["numpy"]),
        "mean_ms_compiled": 1e3 * statistics.fmean(cost["numba"]),
        # process CPU time: less sensitive than wall time to other load on the machine
        "median_cpu_ms_numpy": 1e3 * statistics.median(cpu["numpy"]),
        "median_cpu_ms_compiled": 1e3 * statistics.median(cpu["numba"]),
        "same_outcome": same,
    }


def run(args: argparse.Namespace) -> int:
    if args.cold:  # must happen before numba is imported; the fresh cache is removed at exit
        cache = tempfile.mkdtemp(prefix="packings-numba-")
        atexit.register(shutil.rmtree, cache, True)
        os.environ["NUMBA_CACHE_DIR"] = cache
    import numba

    from packings.workers import kernels
    from packings.workers.expand import warm_up
    from packings.workers.params import Params

    if not kernels.numba_available():
        print("numba is not available: nothing to compare", file=sys.stderr)
        return 1
    params = Params()
    paths = 12 if args.quick else args.paths
    clusters = 2 if args.quick else args.clusters
    with kernels.backend("numba"):
        first_call = warm_up()
    rows = []
    for n in args.sizes:
        with kernels.backend("numba"):  # building the sample is not measured
            starts, available = _sample(n, clusters, paths, args.seed, params)
        row = {"n": n, "clusters": clusters, "paths_available": available, "paths": len(starts)}
        row.update(_time_paths(starts, params))
        row["ratio"] = row["median_ms_numpy"] / row["median_ms_compiled"]
        rows.append(row)
        if not args.json:
            print(f"n = {n}: {len(starts)} paths timed", file=sys.stderr)
    result = {
        "first_call_seconds": first_call,
        "cold_cache": bool(args.cold),
        "seed": args.seed,
        "numba": numba.__version__,
        "python": platform.python_version(),
        "cpus": os.cpu_count(),
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "rows": rows,
    }
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"first compiled call (warm_up, {'compile' if args.cold else 'compile or cache load'}): {first_call:.2f} s")
    print(f"{'n':>3} {'paths':>6} {'numpy ms':>10} {'compiled ms':>12} {'ratio':>7} {'same outcome':>13}")
    for r in rows:
        print(
            f"{r['n']:>3} {r['paths']:>6} {r['median_ms_numpy']:>10.2f} {r['median_ms_compiled']:>12.3f} "
            f"{r['ratio']:>7.1f} {r['same_outcome']:>8}/{r['paths']}"
        )
    print("(median wall time of one packings.workers.paths.follow_path call; ratio = numpy / compiled;")
    if hasattr(os, "getloadavg"):
        print(
            f" load average at the end {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs; --json adds CPU-time medians)"
        )
    return 0
