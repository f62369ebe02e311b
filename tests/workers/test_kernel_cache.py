"""kernel_cache: whether the first run compiles, told from numba's index files."""

from __future__ import annotations

import os

from packings.workers import kernel_cache
from packings.workers.kernel_cache import kernels_cached


def _source(tmp_path):
    src = tmp_path / "_compiled.py"
    src.write_text("x = 1\n")
    os.utime(src, (1000, 1000))
    return src


def test_no_cache_means_compiling(tmp_path, monkeypatch):
    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    assert kernels_cached(_source(tmp_path)) is False
    (tmp_path / "__pycache__").mkdir()
    assert kernels_cached(_source(tmp_path)) is False


def test_index_files_stamped_with_the_source_are_a_warm_cache(tmp_path, monkeypatch):
    import hashlib
    import pickle

    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    src = _source(tmp_path)
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    for name in ("_compiled.residual-10.py311.nbi", "_compiled.project-40.py311.nbi"):
        stamp = hashlib.sha256(src.read_bytes()).digest()
        (cache / name).write_bytes(pickle.dumps("0.68.1") + pickle.dumps((stamp, {})))
    assert kernels_cached(src) is True
    src.write_text("x = 2\n")  # the source changed since: numba compiles again
    assert kernels_cached(src) is False


def test_a_cache_elsewhere_cannot_be_told(tmp_path, monkeypatch):
    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    assert kernels_cached(_source(tmp_path)) is None


def test_the_installed_kernels_are_cached_once_a_process_has_warmed_them_up():
    from packings.workers.expand import warm_up

    warm_up()
    if os.environ.get("NUMBA_CACHE_DIR") is None and os.access(kernel_cache.SOURCE.parent, os.W_OK):
        assert kernels_cached() is True


def test_the_index_files_an_older_version_left_do_not_make_a_warm_cache_cold(tmp_path, monkeypatch):
    """Upgrading the package leaves the old kernels' index files (named after their old lines, stamped
    with the old source) beside the ones the new version's warm-up writes: the cache is warm."""
    import hashlib
    import pickle

    monkeypatch.delenv("NUMBA_CACHE_DIR", raising=False)
    src = _source(tmp_path)
    cache = tmp_path / "__pycache__"
    cache.mkdir()
    old = hashlib.sha256(b"an older version").digest()
    (cache / "_compiled.residual-10.py311.nbi").write_bytes(pickle.dumps("0.68.1") + pickle.dumps((old, {})))
    assert kernels_cached(src) is False  # only the old version's: the next warm-up compiles
    new = hashlib.sha256(src.read_bytes()).digest()
    (cache / "_compiled.residual-12.py311.nbi").write_bytes(pickle.dumps("0.68.1") + pickle.dumps((new, {})))
    assert kernels_cached(src) is True
