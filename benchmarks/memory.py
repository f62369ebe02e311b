"""Memory of one expansion: what `expand` holds for a cluster with many contacts.

The cluster is the close-packed fragment of n spheres with the most contacts that
packings.workers.seeds.close_packed_seed builds (n = 13: fcc, 36 contacts, three self-stresses,
subsets of up to four contacts, about 67,000 attempts; n = 12: 32 contacts, about 5,500).  It
is expanded once in a fresh Python process, so that the process's peak resident memory is its
own, with tracemalloc tracing Python's allocations: what the Expansion keeps when it is done
(retained, and per attempt: a worker holds this until the write-back) and the largest amount
traced at once (peak), with the process's peak resident size before and after.  tracemalloc
makes `expand` two to four times slower; the seconds are those of the traced call.

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


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--n", type=int, default=13, help="spheres of the close-packed fragment expanded (default 13)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


def measure(n: int) -> dict:
    """One expansion of the close-packed fragment of n spheres, measured in a fresh process."""
    r = subprocess.run([sys.executable, "-c", _CHILD, str(n)], capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(r.stderr.strip().splitlines()[-1] if r.stderr.strip() else f"exit {r.returncode}")
    return json.loads(r.stdout.strip().splitlines()[-1])


def run(args: argparse.Namespace) -> int:
    row = measure(args.n)
    if args.json:
        print(json.dumps(row))
        return 0
    print(f"expand of the close-packed fragment of n = {row['n']} ({row['contacts']} contacts): "
          f"{row['attempts']:,} attempts, {row['paths']:,} paths followed and {row['paths_by_symmetry']:,} taken as "
          f"images by a symmetry, {row['rigid_endpoints']:,} rigid endpoints "
          f"({row['distinct']:,} distinct), {row['seconds']} s traced")
    print(f"  retained {row['retained_mib']} MiB ({row['retained_bytes_per_attempt']} B an attempt), "
          f"traced peak {row['traced_peak_mib']} MiB, "
          f"process peak {row['max_rss_mib_before']} -> {row['max_rss_mib_after']} MiB")
    return 0
