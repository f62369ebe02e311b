"""kernel_cache: whether the first run compiles, told from numba's index files."""

from __future__ import annotations

import os

import pytest

from packings.workers import kernel_cache
from packings.workers.kernel_cache import kernels_cached


def _source(tmp_path):
    src = tmp_path / "_compiled.py"
    src.write_text("x = 1\n")
    os.utime(src, (1000, 1000))
    return src


def _index(cache, source: bytes, name="_compiled.residual-10.py311.nbi"):
    """Write an index file stamped with the digest of ``source`` (a source file's bytes), as numba does."""
    import hashlib
    import pickle

    cache.mkdir(parents=True, exist_ok=True)
    stamp = hashlib.sha256(source).digest()
    (cache / name).write_bytes(pickle.dumps("0.68.1") + pickle.dumps((stamp, {})))


def test_no_cache_means_compiling(tmp_path, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    assert kernels_cached(_source(tmp_path)) is False
    (tmp_path / "__pycache__").mkdir()
    assert kernels_cached(_source(tmp_path)) is False


def test_index_files_stamped_with_the_source_are_a_warm_cache(tmp_path, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    src = _source(tmp_path)
    for name in ("_compiled.residual-10.py311.nbi", "_compiled.project-40.py311.nbi"):
        _index(tmp_path / "__pycache__", src.read_bytes(), name)
    assert kernels_cached(src) is True
    src.write_text("x = 2\n")  # the source changed since: numba compiles again
    assert kernels_cached(src) is False


def test_a_cache_set_by_numba_cache_dir_is_looked_for_where_numba_keeps_it(tmp_path, monkeypatch):
    """Under NUMBA_CACHE_DIR numba keeps a source's kernels in a folder named after the source's folder and
    the SHA-1 digest of its absolute path; index files anywhere else do not make the cache warm."""
    import hashlib

    from numba.core.caching import UserProvidedCacheLocator

    root = tmp_path / "numba-cache"
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(root))
    src = _source(tmp_path)
    assert kernels_cached(src) is False  # the folder does not exist yet: numba will make it
    _index(tmp_path / "__pycache__", src.read_bytes())  # beside the source, where numba does not look now
    assert kernels_cached(src) is False
    folder = f"{tmp_path.name}_{hashlib.sha1(str(tmp_path).encode()).hexdigest()}"
    assert kernel_cache.cache_directory(src) == root / folder
    assert UserProvidedCacheLocator.get_suitable_cache_subpath(str(src)) == folder  # numba's own name for it
    _index(root / folder, src.read_bytes())
    assert kernels_cached(src) is True


def test_a_cache_numba_cannot_make_cannot_be_told(tmp_path, monkeypatch):
    (tmp_path / "a-file").write_text("")
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "a-file" / "cache"))
    assert kernels_cached(_source(tmp_path)) is None


def test_the_installed_kernels_are_cached_once_a_process_has_warmed_them_up():
    """Wherever numba keeps the installed kernels (beside the package, or under NUMBA_CACHE_DIR), a warm-up
    leaves them there; only where numba cannot write where it looks first can this not be told."""
    from packings.workers.expand import warm_up

    warm_up()
    if kernel_cache.cache_directory() is None:
        pytest.skip("numba cannot write where it looks first for the installed kernels: kernels_cached cannot tell")
    assert kernels_cached() is True


def test_the_index_files_an_older_version_left_do_not_make_a_warm_cache_cold(tmp_path, monkeypatch):
    """Upgrading the package leaves the old kernels' index files (named after their old lines, stamped
    with the old source) beside the ones the new version's warm-up writes: the cache is warm."""
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    src = _source(tmp_path)
    cache = tmp_path / "__pycache__"
    _index(cache, b"an older version", "_compiled.residual-10.py311.nbi")
    assert kernels_cached(src) is False  # only the old version's: the next warm-up compiles
    _index(cache, src.read_bytes(), "_compiled.residual-12.py311.nbi")
    assert kernels_cached(src) is True


_PEAK = """
import json, sys
{body}
from packings.workers.kernel_cache import kernels_cached
high = [int(line.split()[1]) for line in open("/proc/self/status") if line.startswith("VmHWM")][0]
print(json.dumps([high, kernels_cached()]))
"""


def test_a_cold_warm_up_leaves_the_compilers_memory_to_a_child(tmp_path):
    """Two fresh processes, each on a cold cache of its own: the fork server's preload (a warm-up that has a
    child compile) peaks far below a warm-up that compiles in its own process, and fills the cache."""
    import json
    import subprocess
    import sys

    if not os.path.exists("/proc/self/status"):
        pytest.skip("peak memory is read from /proc, which this system lacks")
    bodies = {
        "apart": "import packings.service.preload",
        "here": "from packings.workers.expand import warm_up; warm_up(apart=False)",
    }
    procs = {}
    for name, body in bodies.items():
        env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / name), OMP_NUM_THREADS="1")
        env.pop("PACKINGS_KERNELS", None)
        procs[name] = subprocess.Popen(
            [sys.executable, "-c", _PEAK.format(body=body)], env=env, stdout=subprocess.PIPE, text=True
        )
    peak = {}
    for name, proc in procs.items():
        out, _ = proc.communicate(timeout=900)
        assert proc.returncode == 0
        peak[name], cached = json.loads(out.strip().splitlines()[-1])
        assert cached is True, name
    assert peak["apart"] < peak["here"] - 150 * 1024, peak  # kB: the compiler's memory stayed in the child
