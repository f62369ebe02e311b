"""The packed attempts of one expansion (``attempts.data``): every subset tried from one cluster in one
run, in one compressed value rather than one row each.

An attempt is what a row of the former ``transitions`` table held (:class:`Attempt`): the contacts
broken, the direction followed, the outcome, the cluster reached (a stored cluster id, or None), the
steps of the path, the contacts formed at its endpoint, and where a path of the target may retrace it,
the endpoint's labels as the target is stored (``labels[i]``: the target's sphere that the endpoint's
sphere i is).

Format (version 1): one byte, the version, then the zlib-compressed columns, each a little-endian
numpy array, in this order::

    header   uint32[8]: n, attempts A, distinct targets T, labelled attempts L, broken pairs B,
                        formed pairs F, bytes of a step count, bytes of a pair count
    targets  int64[T]   the distinct clusters reached, in order of first appearance
    direction int8[A]   +1 / -1 along the tangent, 0 if no path was followed
    outcome  uint8[A]   index in OUTCOMES
    target   uint8/16/32[A]  1 + index in targets, 0 for none (the narrowest that holds T + 1)
    steps    uint16/32[A]
    broken   uint8/16[A]  pairs broken by each attempt (the offsets are their running sums)
    formed   uint8/16[A]  pairs formed by each attempt
    broken pairs uint8[2B]  (i, j), i < j, attempt after attempt
    formed pairs uint8[2F]
    labelled uint8[ceil(A / 8)]  which attempts have labels (numpy.packbits, big-endian bit order)
    labels   uint8[L * n]  the labels of those attempts, in attempt order

Columns compress better than rows: each holds a few repeating values.  Pure (numpy and zlib): the
service and migration 0008 both use it, and a later version must keep reading version 1.
"""

from __future__ import annotations

import functools
import zlib
from dataclasses import dataclass
from itertools import chain
from typing import Iterable, Sequence

import numpy as np

from packings.workers import outcomes as _o

VERSION = 1

#: every outcome an attempt may have (:mod:`packings.workers.outcomes`), numbered by position in the
#: stored data: APPEND ONLY, never reorder or remove a name (stored attempts would change meaning)
OUTCOMES: tuple[str, ...] = (
    _o.RIGID,
    _o.FLOPPY,
    _o.UNDECIDED_END,
    _o.UNPROVED,
    _o.PROJECTION_FAILED,
    _o.DIMENSION_CHANGED,
    _o.SHORTENS,
    _o.OVERLAP,
    _o.TOO_LONG,
    _o.CIRCULAR,
    _o.NOT_1D,
    _o.HELD,
    _o.NO_DIRECTION,
    _o.NO_TRIANGLE,
    _o.BELOW_MIN_CONTACTS,
    _o.REARRANGED,
)
_OUTCOME_CODE = {name: k for k, name in enumerate(OUTCOMES)}

Pairs = tuple[tuple[int, int], ...]


class CodecError(ValueError):
    """Attempts that cannot be packed (an unknown outcome, too many spheres) or data that is not packed
    attempts."""


@dataclass(frozen=True, slots=True)
class Attempt:
    """One attempt from a cluster (see the module's doc)."""

    broken: Pairs
    direction: int
    outcome: str
    target: int | None
    steps: int
    new_contacts: Pairs
    labels: tuple[int, ...] | None = None


def _width(largest: int, widths=(1, 2, 4)) -> int:
    for w in widths:
        if largest < 1 << (8 * w):
            return w
    raise CodecError(f"value {largest} too large to pack")


_UINT = {1: "<u1", 2: "<u2", 4: "<u4"}


def pack(n: int, attempts: Sequence[Attempt]) -> bytes:
    """``attempts`` (of a cluster of ``n`` spheres) packed: :func:`unpack` gives them back.  Each column
    is made from a list in one go (an expansion may have hundreds of thousands of attempts)."""
    if not 0 < n < 256:
        raise CodecError(f"cannot pack attempts of {n} spheres (1 to 255)")
    a = len(attempts)
    try:
        outcome = [_OUTCOME_CODE[t.outcome] for t in attempts]
    except KeyError as e:
        raise CodecError(f"unknown outcome {e.args[0]!r}: add it at the end of paths_codec.OUTCOMES") from None
    targets: dict[int, int] = {}
    target = [0 if t.target is None else 1 + targets.setdefault(int(t.target), len(targets)) for t in attempts]
    nb = [len(t.broken) for t in attempts]
    nf = [len(t.new_contacts) for t in attempts]
    broken = list(chain.from_iterable(chain.from_iterable(t.broken for t in attempts)))
    formed = list(chain.from_iterable(chain.from_iterable(t.new_contacts for t in attempts)))
    labelled = [t.labels is not None for t in attempts]
    labels = list(chain.from_iterable(t.labels for t in attempts if t.labels is not None))
    if len(labels) != n * sum(labelled):
        raise CodecError(f"labels of other than {n} spheres in attempts of {n}")
    for name, values in (("pairs", broken), ("pairs", formed), ("labels", labels)):
        if values and not 0 <= min(values) <= max(values) < n:
            raise CodecError(f"{name} outside spheres 0..{n - 1}")
    steps = np.array([t.steps for t in attempts], dtype=np.int64)
    if a and not 0 <= steps.min() <= steps.max() < 1 << 32:
        raise CodecError("steps outside 0..2**32 - 1")
    steps_w = _width(int(steps.max()) if a else 0, (2, 4))
    count_w = _width(max(nb + nf, default=0), (1, 2))
    target_w = _width(len(targets))
    header = np.array(
        [n, a, len(targets), sum(labelled), len(broken) // 2, len(formed) // 2, steps_w, count_w], dtype="<u4"
    )
    columns = (
        header,
        np.fromiter(targets, dtype="<i8", count=len(targets)),
        np.array([t.direction for t in attempts], dtype="<i1"),
        np.array(outcome, dtype="<u1"),
        np.array(target, dtype=_UINT[target_w]),
        steps.astype(_UINT[steps_w]),
        np.array(nb, dtype=_UINT[count_w]),
        np.array(nf, dtype=_UINT[count_w]),
        np.array(broken, dtype="<u1"),
        np.array(formed, dtype="<u1"),
        np.packbits(np.array(labelled, dtype=bool)),
        np.array(labels, dtype="<u1"),
    )
    return bytes([VERSION]) + zlib.compress(b"".join(c.tobytes() for c in columns), 9)


@dataclass(frozen=True)
class Packed:
    """Attempts unpacked as columns (numpy arrays; see the module's doc), for reading a few of many
    without making an object of each: :meth:`attempt` makes one, :meth:`to` selects by target."""

    n: int
    targets: np.ndarray  #: int64[T]
    direction: np.ndarray  #: int8[A]
    outcome: np.ndarray  #: uint8[A], index in OUTCOMES
    target: np.ndarray  #: int64[A], index in targets, -1 for none
    steps: np.ndarray
    broken_at: np.ndarray  #: int64[A + 1]: attempt k's broken pairs are broken[broken_at[k]:broken_at[k + 1]]
    broken: np.ndarray  #: uint8[B, 2]
    formed_at: np.ndarray
    formed: np.ndarray  #: uint8[F, 2]
    labels_at: np.ndarray  #: int64[A]: the row of attempt k's labels in ``labels``, -1 for none
    labels: np.ndarray  #: uint8[L, n]

    def __len__(self) -> int:
        return len(self.direction)

    def target_id(self, k: int) -> int | None:
        t = int(self.target[k])
        return None if t < 0 else int(self.targets[t])

    @functools.cached_property
    def _attempts(self) -> list[Attempt]:
        """Every attempt, made from the columns as Python lists in one go."""
        targets = [None, *self.targets.tolist()]
        labels = [None, *map(tuple, self.labels.tolist())]
        return [
            Attempt(b, d, OUTCOMES[o], targets[t + 1], st, f, labels[r + 1])
            for b, d, o, t, st, f, r in zip(
                _split(self.broken, self.broken_at),
                self.direction.tolist(),
                self.outcome.tolist(),
                self.target.tolist(),
                self.steps.tolist(),
                _split(self.formed, self.formed_at),
                self.labels_at.tolist(),
            )
        ]

    def attempt(self, k: int) -> Attempt:
        return self._attempts[k]

    def one(self, k: int) -> Attempt:
        """Attempt ``k`` alone, made from its columns without making the others (:meth:`attempt` makes them
        all once): a task reads the few attempts of each expansion that arrived at its cluster."""
        b0, b1, f0, f1 = (
            int(x) for x in (self.broken_at[k], self.broken_at[k + 1], self.formed_at[k], self.formed_at[k + 1])
        )
        t, r = int(self.target[k]), int(self.labels_at[k])
        return Attempt(
            tuple(map(tuple, self.broken[b0:b1].tolist())),
            int(self.direction[k]),
            OUTCOMES[int(self.outcome[k])],
            None if t < 0 else int(self.targets[t]),
            int(self.steps[k]),
            tuple(map(tuple, self.formed[f0:f1].tolist())),
            None if r < 0 else tuple(self.labels[r].tolist()),
        )

    def __iter__(self):
        return iter(self._attempts)

    def to(self, target: int, labelled: bool = False) -> np.ndarray:
        """The positions of the attempts that reached cluster ``target`` (with labels only, if
        ``labelled``), in order."""
        hit = np.flatnonzero(self.targets == target)
        if not len(hit):
            return hit
        mask = self.target == hit[0]
        if labelled:
            mask &= self.labels_at >= 0
        return np.flatnonzero(mask)


def _split(pairs: np.ndarray, at: np.ndarray) -> list[tuple[tuple[int, int], ...]]:
    """The pairs of each attempt: ``pairs[at[k]:at[k + 1]]`` as a tuple of (i, j) tuples, for each k."""
    every = list(zip(pairs[:, 0].tolist(), pairs[:, 1].tolist()))
    bounds = at.tolist()
    return [tuple(every[i:j]) for i, j in zip(bounds, bounds[1:])]


def unpack(data: bytes) -> Packed:
    """The attempts that :func:`pack` packed into ``data``."""
    if not data or data[0] != VERSION:
        raise CodecError(f"packed attempts of an unknown version {data[:1]!r} (this code reads {VERSION})")
    try:
        raw = zlib.decompress(data[1:])
    except zlib.error as e:
        raise CodecError(f"packed attempts that do not decompress: {e}") from None
    at = 0

    def take(dtype: str, count: int) -> np.ndarray:
        nonlocal at
        size = np.dtype(dtype).itemsize * count
        if at + size > len(raw):
            raise CodecError("packed attempts cut short")
        out = np.frombuffer(raw, dtype=dtype, count=count, offset=at)
        at += size
        return out

    n, a, t, nl, b, f, steps_w, count_w = (int(v) for v in take("<u4", 8))
    if steps_w not in (2, 4) or count_w not in (1, 2):
        raise CodecError("packed attempts with a bad header")
    targets = take("<i8", t)
    direction = take("<i1", a)
    outcome = take("<u1", a)
    target = take(_UINT[_width(t)], a).astype(np.int64) - 1
    steps = take(_UINT[steps_w], a)
    nb = take(_UINT[count_w], a)
    nf = take(_UINT[count_w], a)
    broken = take("<u1", 2 * b).reshape(b, 2)
    formed = take("<u1", 2 * f).reshape(f, 2)
    labelled = np.unpackbits(take("<u1", (a + 7) // 8), count=a).astype(bool)
    labels = take("<u1", nl * n).reshape(nl, n)
    if at != len(raw) or int(nb.sum()) != b or int(nf.sum()) != f or int(labelled.sum()) != nl:
        raise CodecError("packed attempts whose columns disagree")
    if a and int(outcome.max()) >= len(OUTCOMES):
        raise CodecError("packed attempts with an outcome this code does not know")
    labels_at = np.full(a, -1, dtype=np.int64)
    labels_at[labelled] = np.arange(nl)
    return Packed(
        n,
        targets,
        direction,
        outcome,
        target,
        steps,
        np.concatenate(([0], np.cumsum(nb, dtype=np.int64))),
        broken,
        np.concatenate(([0], np.cumsum(nf, dtype=np.int64))),
        formed,
        labels_at,
        labels,
    )


@dataclass(frozen=True)
class Summary:
    """What the ``attempts`` and ``edges`` rows hold beside the packed data, so that counting paths reads
    no packed data: the attempts, those with a direction (paths), the circular ones, and for each
    cluster reached its paths and how many of them carry labels."""

    attempts: int
    paths: int
    circular: int
    rearranged: int
    edges: dict[int, tuple[int, int]]  #: target id -> (paths, labelled)


def summary(attempts: Iterable[Attempt]) -> Summary:
    count = paths = circular = rearranged = 0
    edges: dict[int, list[int]] = {}
    for t in attempts:
        count += 1
        paths += t.direction != 0
        circular += t.direction != 0 and t.outcome == _o.CIRCULAR
        rearranged += t.direction != 0 and t.outcome == _o.REARRANGED
        if t.target is not None:
            e = edges.setdefault(int(t.target), [0, 0])
            e[0] += 1
            e[1] += t.labels is not None
    return Summary(count, paths, circular, rearranged, {k: (p, lab) for k, (p, lab) in edges.items()})
