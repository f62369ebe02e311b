"""Whether numba's on-disk cache holds the compiled kernels, told without importing numba.

The kernels of :mod:`packings.workers._compiled` are compiled with ``cache=True``: the first
process on an installation compiles them (about a minute on two cores) and writes them to the
``__pycache__`` folder beside the module, where later processes load them in about a second.
Numba keeps one index file (``*.nbi``) per kernel, stamped with the SHA-256 digest of the source
file (the digest's 32 bytes appear as they are in the pickled index), and ignores an index whose
stamp is not the source's.  The command line asks this before its workers warm up, to say that the
first run compiles.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

SOURCE = Path(__file__).with_name("_compiled.py")


def kernels_cached(source: Path = SOURCE) -> bool | None:
    """True if the cache beside ``source`` has an index file stamped with the source as it is now; False
    if it has none, or only stale ones (the next warm-up compiles); None where this cannot be told (a
    cache directory set by ``NUMBA_CACHE_DIR``, or a folder numba cannot write, where it uses another).

    The warm-up compiles every kernel at once, so one current index means all of them are cached.  An
    index is named after its kernel's line in the source: a new version of the package leaves the
    old version's index files behind, stale, beside the new ones, and numba ignores them."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    cache = source.parent / "__pycache__"
    if not os.access(cache if cache.is_dir() else source.parent, os.W_OK):
        return None
    indexes = list(cache.glob(f"{source.stem}.*.nbi")) if cache.is_dir() else []
    digest = hashlib.sha256(source.read_bytes()).digest()
    return any(digest in p.read_bytes() for p in indexes)
