"""Memory of one expansion (what `expand` holds for a cluster with many contacts), or of a glued pass's record.

The cluster is the close-packed fragment of n spheres with the most contacts that
packings.workers.seeds.close_packed_seed builds (n = 13: fcc, 36 contacts, three self-stresses,
subsets of up to four contacts, about 67,000 attempts; n = 12: 32 contacts, about 5,500).  It
is expanded once in a fresh Python process, so that the process's peak resident memory is its
own, with tracemalloc tracing Python's allocations: what the Expansion keeps when it is done
(retained, and per attempt: a worker holds this until the write-back) and the largest amount
traced at once (peak), with the process's peak resident size before and after.  tracemalloc
makes `expand` two to four times slower; the seconds are those of the traced call.

With ``--glued --db URL``, the record a worker of a glued catalysis pass keeps instead
(packings.workers.catalysis.Seen): the stored clusters of n are read from the database and added
to a record, then a sphere of each of the first ``--parents`` of them is moved onto each contact
triangle (moved_remainders), the remainders decided or found in the record as in the pass.  It
reports the record's bytes (traced) per cluster it holds, and the seconds, untraced and again
traced: the record's footprint at a worker's full pass is about that many bytes times the
remainders the worker decides plus the stored clusters.

Compare two versions of the code by running this from each one's environment, side by side.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys

_CHILD = r"""
import gc, json, resource, sys, time, tracemalloc
from packings.workers.expand import expand, warm_up
from packings.workers.params import DEFAULT
from packings.workers.seeds import close_packed_seed

warm_up()
c = close_packed_seed(int(sys.argv[1]), DEFAULT)
gc.collect()
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
tracemalloc.start()
t = time.perf_counter()
ex = expand(c, DEFAULT)
seconds = time.perf_counter() - t
gc.collect()
retained, peak = tracemalloc.get_traced_memory()
tracemalloc.stop()
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"n": c.n, "contacts": c.m, "attempts": len(ex.endpoints), "paths": ex.paths_followed,
                  "paths_by_symmetry": ex.paths_by_symmetry,
                  "rigid_endpoints": len(ex.rigid_endpoints()), "distinct": len(ex.distinct()),
                  "seconds": round(seconds, 2), "retained_mib": round(retained / 2**20, 2),
                  "retained_bytes_per_attempt": round(retained / max(len(ex.endpoints), 1)),
                  "traced_peak_mib": round(peak / 2**20, 2),
                  "max_rss_mib_before": round(before / 1024, 1), "max_rss_mib_after": round(after / 1024, 1)}))
"""


_GLUED_CHILD = r"""
import gc, json, resource, sys, time, tracemalloc
import packings
from packings.workers.catalysis import Seen, moved_remainders
from packings.workers.cluster import Cluster
from packings.workers.expand import warm_up
from packings.workers.params import DEFAULT

url, n, parents = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
with packings.connect(url) as cat:
    stored = [Cluster(r.coords, tuple(tuple(int(v) for v in p) for p in r.contacts)) for r in cat.select(f"n={n}")]
if not stored:
    raise SystemExit(f"no clusters of n = {n} in {url}: run `packings enumerate {n} --db {url}` first")

def one_pass():
    seen = Seen(DEFAULT.tol_d)
    for c in stored:
        seen.add(c)
    t = time.perf_counter()
    decided = again = 0
    for c in stored[:parents]:
        for mv in moved_remainders(c, DEFAULT, seen):
            decided += not mv.seen
            again += mv.seen
    return seen, decided, again, time.perf_counter() - t

warm_up()
seconds = one_pass()[3]  # untraced
gc.collect()
before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
tracemalloc.start()
seen, decided, again, traced = one_pass()
entries = len(seen)
gc.collect()
retained, peak = tracemalloc.get_traced_memory()
del seen
gc.collect()
held = retained - tracemalloc.get_traced_memory()[0]
tracemalloc.stop()
after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
print(json.dumps({"n": n, "stored": len(stored), "parents": min(parents, len(stored)), "decided": decided,
                  "not_again": again, "seconds": round(seconds, 2), "seconds_traced": round(traced, 2),
                  "record_mib": round(held / 2**20, 2), "record_clusters": entries,
                  "record_bytes_per_cluster": round(held / max(entries, 1)),
                  "traced_peak_mib": round(peak / 2**20, 2),
                  "max_rss_mib_before": round(before / 1024, 1), "max_rss_mib_after": round(after / 1024, 1)}))
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--n", type=int, default=13, help="spheres of the close-packed fragment expanded (default 13)")
    parser.add_argument(
        "--glued", action="store_true", help="measure a glued pass's record of remainders seen instead (needs --db)"
    )
    parser.add_argument("--db", help="with --glued: the database holding the clusters of n")
    parser.add_argument(
        "--parents",
        type=int,
        default=2000,
        help="with --glued: how many stored clusters have a sphere moved (default 2000)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def _child(*argv: str) -> dict:
    """Run a measuring script in a fresh process; its last line of output, as JSON."""
    r = subprocess.run([sys.executable, "-c", *argv], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit {r.returncode}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def measure_glued(url: str, n: int, parents: int) -> dict:
    """A glued pass's record over the first ``parents`` stored clusters of n in ``url``, in a fresh process."""
    return _child(_GLUED_CHILD, url, str(n), str(parents))


def measure(n: int) -> dict:
    """One expansion of the close-packed fragment of n spheres, measured in a fresh process."""
    return _child(_CHILD, str(n))


def run(args: argparse.Namespace) -> int:
    if args.glued:
        if not args.db:
            raise SystemExit("--glued needs --db URL, a database holding the clusters of n")
        row = measure_glued(args.db, args.n, args.parents)
        if args.json:
            print(json.dumps(row))
            return 0
        print(
            f"glued pass over {row['parents']:,} of the {row['stored']:,} stored clusters of n = {row['n']}: "
            f"{row['decided']:,} remainders decided, {row['not_again']:,} not again; "
            f"{row['seconds']} s ({row['seconds_traced']} s traced)"
        )
        print(
            f"  record {row['record_mib']} MiB for {row['record_clusters']:,} clusters "
            f"({row['record_bytes_per_cluster']} B a cluster), traced peak {row['traced_peak_mib']} MiB, "
            f"process peak {row['max_rss_mib_before']} -> {row['max_rss_mib_after']} MiB"
        )
        return 0
    row = measure(args.n)
    if args.json:
        print(json.dumps(row))
        return 0
    print(
        f"expand of the close-packed fragment of n = {row['n']} ({row['contacts']} contacts): "
        f"{row['attempts']:,} attempts, {row['paths']:,} paths followed and {row['paths_by_symmetry']:,} taken as "
        f"images by a symmetry, {row['rigid_endpoints']:,} rigid endpoints "
        f"({row['distinct']:,} distinct), {row['seconds']} s traced"
    )
    print(
        f"  retained {row['retained_mib']} MiB ({row['retained_bytes_per_attempt']} B an attempt), "
        f"traced peak {row['traced_peak_mib']} MiB, "
        f"process peak {row['max_rss_mib_before']} -> {row['max_rss_mib_after']} MiB"
    )
    return 0
