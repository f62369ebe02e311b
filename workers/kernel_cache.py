"""Whether numba's on-disk cache holds the compiled kernels, told without importing numba.

The kernels of :mod:`packings.workers._compiled` are compiled with ``cache=True``: the first
process on an installation compiles them (about a minute on two cores) and writes them to the
``__pycache__`` folder beside the module, where later processes load them in about a second.
Numba keeps one index file (``*.nbi``) per kernel, stamped with the SHA-256 digest of the source
file (the digest's 32 bytes appear as they are in the pickled index), and ignores an index whose
stamp is not the source's.  The command line asks this before its workers warm up, to say that the
first run compiles.

Compiling leaves hundreds of MiB of the compiler's memory in the process that compiled, where loading
the kernels from the cache leaves none (docs/performance.md); every process forked from it (a local
cluster's workers, from their fork server) would count those pages in its own resident memory, and
Dask's memory limits act on that.  So a warm-up that finds the cache cold has a child process compile
and write the cache, and loads the kernels from it (:func:`compile_apart`).
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

SOURCE = Path(__file__).with_name("_compiled.py")


def cache_directory(source: Path = SOURCE) -> Path | None:
    """The folder where numba keeps the kernels of ``source``, or None where it would use another than the
    first it tries (that one is not writable, nor can be made).

    Beside the source (``__pycache__``), or with ``NUMBA_CACHE_DIR`` in that folder, under numba's name
    for the source's folder: the folder's name and the SHA-1 digest of its absolute path."""
    root = os.environ.get("NUMBA_CACHE_DIR")
    if root:
        folder = os.path.dirname(os.path.abspath(source))
        cache = Path(root) / f"{os.path.basename(folder)}_{hashlib.sha1(folder.encode()).hexdigest()}"
    else:
        cache = source.parent / "__pycache__"
    existing = cache
    while not existing.is_dir():  # numba makes the folders that are missing
        if existing.exists() or existing.parent == existing:
            return None
        existing = existing.parent
    return cache if os.access(existing, os.W_OK) else None


def kernels_cached(source: Path = SOURCE) -> bool | None:
    """True if the cache of ``source`` (:func:`cache_directory`) has an index file stamped with the source
    as it is now; False if it has none, or only stale ones (the next warm-up compiles); None where this
    cannot be told (numba cannot write where it looks first, and uses another folder).

    The warm-up compiles every kernel at once, so one current index means all of them are cached.  An
    index is named after its kernel's line in the source: a new version of the package leaves the
    old version's index files behind, stale, beside the new ones, and numba ignores them."""
    cache = cache_directory(source)
    if cache is None:
        return None
    indexes = list(cache.glob(f"{source.stem}.*.nbi")) if cache.is_dir() else []
    digest = hashlib.sha256(source.read_bytes()).digest()
    return any(digest in p.read_bytes() for p in indexes)


#: what the child process of :func:`compile_apart` runs: the warm-up, compiling in that process
COMPILE = "from packings.workers.expand import warm_up; warm_up(apart=False)"


def compile_apart() -> bool:
    """Where the cache is cold (:func:`kernels_cached` is False), compile the kernels in a child process,
    which writes them to the cache, and return whether the cache now holds them; False at once otherwise.

    The caller then loads them from the cache, its memory spared the compiler's.  The child inherits
    the environment (the cache folder, the threads).  Should it fail, or the cache stay cold, the caller
    compiles them itself, as without it."""
    if kernels_cached() is not False:
        return False
    try:
        done = subprocess.run(
            [sys.executable, "-c", COMPILE],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            check=False,
        )
    except OSError:
        return False
    return done.returncode == 0 and kernels_cached() is True
