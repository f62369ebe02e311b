"""Wall time of a whole ``packings enumerate N`` on the embedded default, and where it goes.

For each N and each number of workers K, runs ``packings enumerate N --workers K``
as a user would (its own process, a LocalCluster of K single-threaded worker
processes, a fresh SQLite file), and reports:

* wall: the command's wall time, start to exit (Python start-up, Dask start-up,
  the workers' warm-up and the run itself);
* run: the coordinator's own time for the run (what the command prints);
* in expand: the time the workers spent inside ``packings.workers.expand`` (the sum of
  ``expansions.seconds``), divided by K (so it is comparable with the run time);
* outside (of the wall time): 1 − in expand / wall, the share of the command's
  wall time that the workers spend outside ``packings.workers.expand``: starting Python
  and Dask and warming the workers up, the database, Dask between tasks,
  serialisation, idle workers at the end, shutting down;
* outside (of the run): 1 − in expand / run, the same share of the
  coordinator's run only (from the first claim to the last result);
* peak RSS of the largest worker process and of the coordinator, sampled every
  0.2 s;
* the counts by number of contacts.

With two values of K for the same N, the speed-up wall(K=1) / wall(K=2) is
printed too.  Each run uses its own temporary database, deleted afterwards
(``--keep DIR`` keeps them).
"""

from __future__ import annotations

import argparse
import json
import os
import sqlite3
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--sizes",
        type=int,
        nargs="+",
        default=[10, 11],
        metavar="N",
        help="numbers of spheres (default: 10 11; add 12 when you have the time)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        nargs="+",
        default=[2],
        metavar="K",
        help="worker processes to compare (default: 2; e.g. --workers 1 2 for the speed-up)",
    )
    parser.add_argument("--keep", metavar="DIR", default=None, help="keep the databases in DIR")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of a table")


class _PeakRSS(threading.Thread):
    """Samples the resident memory of a process and of its descendants until stopped."""

    def __init__(self, pid: int, every: float = 0.2):
        super().__init__(daemon=True)
        self.pid, self.every = pid, every
        self.coordinator = 0
        self.worker = 0
        self.stopped = threading.Event()
        self.start()

    def run(self) -> None:
        import psutil

        try:
            root = psutil.Process(self.pid)
        except psutil.Error:
            return
        while not self.stopped.is_set():
            try:
                self.coordinator = max(self.coordinator, root.memory_info().rss)
                for child in root.children(recursive=True):
                    try:
                        name = " ".join(child.cmdline())
                        if "multiprocessing" in name or "spawn" in name or "forkserver" in name:
                            self.worker = max(self.worker, child.memory_info().rss)
                    except psutil.Error:
                        pass
            except psutil.Error:
                return
            self.stopped.wait(self.every)

    def stop(self) -> None:
        self.stopped.set()
        self.join()


def _packings() -> list[str]:
    return [sys.executable, "-m", "packings.service.cli"]


def run_one(n: int, k: int, directory: Path) -> dict:
    db = directory / f"n{n}-k{k}.db"
    for suffix in ("", "-wal", "-shm"):
        Path(f"{db}{suffix}").unlink(missing_ok=True)
    cmd = [*_packings(), "enumerate", str(n), "--workers", str(k), "--db", f"sqlite:///{db}", "--json", "--quiet"]
    t0 = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    rss = _PeakRSS(proc.pid)
    out, err = proc.communicate()
    wall = time.perf_counter() - t0
    rss.stop()
    if proc.returncode != 0:
        raise SystemExit(f"benchmark: `{' '.join(cmd)}` failed: {err.strip().splitlines()[-1] if err.strip() else ''}")
    result = json.loads(out)
    with sqlite3.connect(db) as c:
        in_expand, expansions, paths = c.execute(
            "SELECT SUM(seconds), COUNT(*), SUM(paths) FROM expansions WHERE run_id = ?", (result["run"],)
        ).fetchone()
    run = result["seconds"]
    per_worker = (in_expand or 0.0) / k
    return {
        "n": n,
        "workers": k,
        "wall_s": round(wall, 2),
        "run_s": run,
        "in_expand_s": round(per_worker, 3),
        "outside_share_of_wall": round(1.0 - per_worker / wall, 4),
        "outside_share_of_run": round(1.0 - per_worker / run, 4) if run else None,
        "expansions": expansions,
        "paths": paths,
        "ms_per_path_in_expand": round(1000.0 * (in_expand or 0.0) / paths, 3) if paths else None,
        "peak_worker_rss_mib": round(rss.worker / 2**20, 1),
        "peak_coordinator_rss_mib": round(rss.coordinator / 2**20, 1),
        "total": result["total"],
        "by_contacts": result["by_contacts"],
        "status": result["status"],
    }


def run(args: argparse.Namespace) -> int:
    rows = []
    with tempfile.TemporaryDirectory(prefix="packings-bench-") as tmp:
        directory = Path(args.keep) if args.keep else Path(tmp)
        directory.mkdir(parents=True, exist_ok=True)
        for n in args.sizes:
            for k in args.workers:
                if not args.json:
                    print(f"enumerate {n} with {k} worker(s) ...", file=sys.stderr, flush=True)
                rows.append(run_one(n, k, directory))
    speedups = {}
    for n in args.sizes:
        by_k = {r["workers"]: r["wall_s"] for r in rows if r["n"] == n}
        if 1 in by_k and 2 in by_k:
            speedups[str(n)] = round(by_k[1] / by_k[2], 3)
    report = {"cpu_count": os.cpu_count(), "runs": rows, "speedup_1_to_2_workers": speedups}
    if args.json:
        print(json.dumps(report))
        return 0
    cols = [
        "n",
        "workers",
        "wall_s",
        "run_s",
        "in_expand_s",
        "outside_share_of_wall",
        "outside_share_of_run",
        "expansions",
        "paths",
        "ms_per_path_in_expand",
        "peak_worker_rss_mib",
        "peak_coordinator_rss_mib",
        "total",
    ]
    widths = [max(len(c), *(len(str(r[c])) for r in rows)) for c in cols]
    print("  ".join(c.rjust(w) for c, w in zip(cols, widths)))
    for r in rows:
        print("  ".join(str(r[c]).rjust(w) for c, w in zip(cols, widths)))
    for r in rows:
        print(f"n = {r['n']}, {r['workers']} worker(s): {r['total']} clusters, by contacts {r['by_contacts']}")
    for n, s in speedups.items():
        print(f"n = {n}: one worker / two workers, wall time ratio {s}")
    return 0
