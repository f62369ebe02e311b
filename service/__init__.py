"""packings: every rigid cluster of n identical hard spheres, enumerated into a SQL database.

    import packings
    cat = packings.connect("sqlite:///packings.db")    # a catalogue, as ase.db.connect
    result = packings.enumerate(9, "sqlite:///packings.db")

:func:`connect` and :func:`enumerate` are :mod:`packings.api`'s (which loads
nothing heavy until called: every Dask worker imports this package); the
numerics are in :mod:`packings.workers`.
"""

from __future__ import annotations

from importlib import metadata as _metadata

from packings.api import Catalogue, Row, connect, enumerate  # noqa: A004 - the package's verb, as `packings enumerate`
from packings.errors import PackingsError

try:
    __version__ = _metadata.version("packings")
except _metadata.PackageNotFoundError:  # not installed: run from a source tree
    __version__ = "0+unknown"

__all__ = ["Catalogue", "PackingsError", "Row", "connect", "enumerate", "__version__"]
