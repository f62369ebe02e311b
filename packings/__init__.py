"""packings: every rigid cluster of n identical hard spheres, enumerated into a SQL database.

    import packings
    cat = packings.connect("sqlite:///packings.db")    # a catalogue, as ase.db.connect
    result = packings.enumerate(9, "sqlite:///packings.db")

The package is three layers (docs/architecture.md): :mod:`packings.workers`, the pure numerics a
Dask worker runs; :mod:`packings.service`, everything with state (the database, the run on Dask, the
command line, reports); :mod:`packings.migrations`, the schema's migrations.  This module is only the
public face: :func:`connect`, :func:`enumerate`, :class:`Catalogue`, :class:`Row` and
:class:`PackingsError`, loaded when first used, so that importing the numerics
(``import packings.workers.expand``) loads nothing of the service.
"""

from __future__ import annotations

from importlib import import_module
from importlib import metadata as _metadata
from pkgutil import extend_path

# In a checkout this folder holds only this file, beside service/ and workers/.  Where the checkout's
# root comes first on sys.path (``python -m`` run there, a notebook started there), this file is the
# one imported; extend_path lets the subpackages then come from the installed package.
__path__ = extend_path(__path__, __name__)

#: each public name and the module that defines it
_PUBLIC = {
    "Catalogue": "packings.service.api",
    "Row": "packings.service.api",
    "connect": "packings.service.api",
    "enumerate": "packings.service.run",
    "PackingsError": "packings.service.errors",
}

try:
    __version__ = _metadata.version("packings")
except _metadata.PackageNotFoundError:  # not installed: run from a source tree
    __version__ = "0+unknown"

__all__ = ["Catalogue", "PackingsError", "Row", "connect", "enumerate", "__version__"]


def __getattr__(name: str):
    """The public names, imported on first use (PEP 562)."""
    try:
        module = _PUBLIC[name]
    except KeyError:
        raise AttributeError(f"module 'packings' has no attribute {name!r}") from None
    value = getattr(import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *_PUBLIC})
