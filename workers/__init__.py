"""Pure numerics of the enumeration: no database, no Dask.

Every function here is a pure function of numpy arrays and a :class:`Params`.
"""

from packings.workers.params import DEFAULT, Params

__all__ = ["Params", "DEFAULT"]
