"""Everything that happens to one cluster: the unit of work a Dask task runs."""

from __future__ import annotations

import time
from collections import Counter
from dataclasses import dataclass, field
from itertools import chain, combinations, islice
from typing import Iterable, Iterator, Mapping

import numpy as np

from packings.workers import kernels
from packings.workers.cluster import Cluster, pair
from packings.workers.dimension import (
    Dimension,
    StressBasis,
    after_breaking,
    left_after_breaking,
    may_decide,
    ranks_after_breaking,
    solution_dimension,
)
from packings.workers.identity import ClusterIndex, certificate, forget_canonical, same_geometry, symmetries
from packings.workers.outcomes import (  # noqa: F401 - the outcomes of an attempt beyond a path's, named here too
    BELOW_MIN_CONTACTS,
    CIRCULAR,
    DIMENSION_CHANGED,
    HELD,
    NO_DIRECTION,
    NO_TRIANGLE,
    NOT_1D,
    REARRANGED,
    RIGID,
)
from packings.workers.params import Params
from packings.workers.paths import PathEnd, follow_path
from packings.workers.rigidity import FirstTriangles, Rigidity, contact_triangle


@dataclass(frozen=True, slots=True)
class Arrival:
    """A path that came to a first-order rigid cluster B from a first-order rigid cluster A, breaking the
    contacts ``formed`` of A and forming the contacts ``contacts`` of B: the path B follows breaking
    ``contacts`` is the same curve back, and ends at A forming ``formed`` (docs/method.md).  All in B's
    labels; each set of pairs sorted."""

    contacts: tuple[tuple[int, int], ...]  #: the contacts of B the path formed: breaking them retraces the path
    target: int  #: A, as the caller names clusters (the service: its stored id); opaque here
    formed: tuple[tuple[int, int], ...]  #: the contacts the path back forms at A (A's broken ones, relabelled)
    steps: int  #: steps of the path that came
    labels: tuple[int, ...]  #: sphere i of the path back's endpoint is sphere labels[i] of A


def _pairs(t, pairs) -> tuple[tuple[int, int], ...]:
    """``pairs`` with sphere i relabelled ``t[i]``, sorted."""
    return tuple(sorted(pair(t[a], t[b]) for a, b in pairs))


def arrivals(rows: Iterable[tuple]) -> dict[tuple[tuple[int, int], ...], Arrival]:
    """The arrivals at a cluster B, by the contacts whose break retraces each, from the paths that ended
    at B: rows ``(source, broken, new_contacts, steps, labels)`` of paths each from a first-order rigid
    cluster (``source``) to B, ``labels[i]`` being the sphere of B that sphere i of the path's endpoint
    is (:func:`packings.workers.identity.alignment`).  A set of contacts whose arrivals disagree (another
    cluster, or other contacts formed at it) gets none: its path is followed."""
    found = []
    for source, broken, new, steps, labels in rows:
        if not broken or not new:
            continue
        t = [int(k) for k in labels]
        back = [0] * len(t)
        for i, k in enumerate(t):
            back[k] = i
        found.append(Arrival(_pairs(t, new), source, _pairs(t, broken), int(steps), tuple(back)))
    return _by_contacts(found)


def _by_contacts(found: Iterable[Arrival]) -> dict[tuple[tuple[int, int], ...], Arrival]:
    """``found`` by contacts, the first of each; contacts whose arrivals disagree (another cluster, or
    other contacts formed) get none."""
    out: dict[tuple[tuple[int, int], ...], Arrival] = {}
    clash = set()
    for a in found:
        old = out.setdefault(a.contacts, a)
        if (old.target, old.formed) != (a.target, a.formed):
            clash.add(a.contacts)
    for c in clash:
        del out[c]
    return out


@dataclass(frozen=True, slots=True)  # slots: an expansion may hold hundreds of thousands
class Endpoint:
    """One attempt: the broken contacts, the direction taken, and what came of it.

    ``cluster`` is set for rigid endpoints (outcome ``rigid`` or ``circular``)
    and for other endpoints that were projected.  ``dim`` is the dimension of
    the solution set after breaking; ``direction`` is +1 or -1 relative to the
    tangent basis vector (0 when no path was followed).
    """

    broken: tuple[tuple[int, int], ...]
    direction: int
    outcome: str
    dim: int | None = None
    steps: int = 0
    cluster: Cluster | None = None
    rigidity: Rigidity | None = None
    new_contacts: tuple[tuple[int, int], ...] = ()
    first_step_dim: int | None = None  #: dimension of the path's set after its first step
    #: True when this attempt was not made but is the image of an earlier one under a symmetry of the
    #: source (the subset's image, the endpoint relabelled alike): :func:`expand` with ``symmetric``
    image: bool = False
    #: the arrival whose path this attempt's retraces, when it was not followed (outcome rigid, ``cluster``
    #: None, the endpoint the cluster ``reached.target``): :func:`expand` with ``arrivals``
    reached: Arrival | None = None


@dataclass(frozen=True)
class Expansion:
    """The result of :func:`expand`: every subset tried and every endpoint reached.

    ``same_as[i]`` is, for a rigid endpoint ``i`` (outcome ``rigid``), the first rigid endpoint that
    is the same cluster (``i`` itself for the first), and None for the other endpoints: many paths
    from one cluster end at the same cluster, and this is where they are told apart.
    """

    source: Cluster
    endpoints: tuple[Endpoint, ...] = field(default_factory=tuple)
    same_as: tuple[int | None, ...] = ()
    #: the source is first-order rigid (no flex of its pinned rigidity matrix; regular clusters and most
    #: hyperstatic ones): its paths may be taken from their other ends (:class:`Arrival`)
    first_order_rigid: bool = False

    @property
    def subsets_tried(self) -> int:
        return len({e.broken for e in self.endpoints})

    @property
    def paths_followed(self) -> int:
        """Paths followed: attempts with a direction, less those taken as images of others
        (:attr:`paths_by_symmetry`) and those taken from the other end (:attr:`paths_retraced`)."""
        return sum(1 for e in self.endpoints if e.direction != 0 and not e.image and e.reached is None)

    @property
    def paths_retraced(self) -> int:
        """Attempts with a direction whose path was not followed, as a path that arrived retraces it
        (:class:`Arrival`); their images under a symmetry count in :attr:`paths_by_symmetry`."""
        return sum(1 for e in self.endpoints if e.reached is not None and not e.image)

    def retraceable(self, i: int) -> bool:
        """Whether endpoint ``i`` is an arrival at a first-order rigid cluster (:class:`Arrival`): a path
        followed (or its image) from this first-order rigid cluster to a rigid endpoint that is first-order
        rigid too, with contacts formed, one of the two regular (3n - 6 contacts, no self-stress).  Paths
        between two hyperstatic clusters are followed from both ends: one taken from the other end there
        often is not what following it gives (docs/method.md)."""
        e = self.endpoints[i]
        r = e.rigidity
        if not (
            self.first_order_rigid
            and e.outcome == RIGID
            and e.cluster is not None
            and r is not None
            and r.flexes == 0
            and len(e.new_contacts) > 0
        ):
            return False
        regular = 3 * self.source.n - 6
        return self.source.m == regular or (e.cluster.m == regular and r.stresses == 0)

    @property
    def paths_by_symmetry(self) -> int:
        """Attempts with a direction whose path was not followed, as the image of a path followed under a
        symmetry of the source gives its endpoint."""
        return sum(1 for e in self.endpoints if e.direction != 0 and e.image)

    @property
    def widened_paths(self) -> int:
        """Paths whose set was more than one-dimensional after the first step (and went on)."""
        return sum(
            1
            for e in self.endpoints
            if e.first_step_dim is not None and e.first_step_dim > 1 and e.outcome != DIMENSION_CHANGED
        )

    def outcomes(self) -> Counter:
        return Counter(e.outcome for e in self.endpoints)

    def rigid_endpoints(self) -> list[Endpoint]:
        """Endpoints that are candidate clusters (rigid and not the source)."""
        return [e for e in self.endpoints if e.outcome == RIGID]

    def distinct(self) -> list[int]:
        """The rigid endpoints that are distinct clusters: the first of each (indices into ``endpoints``)."""
        return [i for i, j in enumerate(self.same_as) if j == i]


def break_sizes(m: int, rank: int, params: Params) -> range:
    """Sizes of the subsets to break: 1 .. max(1, m - rank + 1), at most max_break when one is set.

    ``rank`` is the rank of the pinned rigidity matrix.  For a regular cluster it
    is 3n - 6 and this is the paper's m - (3n - 6) + 1 (with single breaks for
    hypostatic clusters).  A singular cluster has rank < 3n - 6: each missing
    rank is a linear flex held by a stress, and breaking one more contact can
    still leave a one-dimensional set, so it gets one more size per flex.
    """
    top = max(1, m - rank + 1)
    if params.max_break is not None:
        top = min(top, params.max_break)
    return range(1, top + 1)


def cluster_rank(cluster: Cluster, params: Params) -> int:
    """Rank of the rigidity matrix of ``cluster`` with a contact triangle pinned: 3n - 6 - #flexes."""
    edges = cluster.edges()
    tri = contact_triangle(edges)
    x = kernels.to_frame(cluster.coords, tri).ravel()
    return (
        3 * cluster.n
        - 6
        - kernels.null_spaces(x, edges, kernels.free_coordinates(cluster.n, tri), params.tol_n).V.shape[1]
    )


@dataclass(frozen=True)
class PathStart:
    """One path to follow: the arguments of :func:`packings.workers.paths.follow_path` and what they came from."""

    broken_contacts: tuple[tuple[int, int], ...]  #: the broken subset B
    direction: int  #: +1 or -1 relative to the tangent basis vector
    x: np.ndarray  #: the cluster in the frame of the pinned triangle (flat)
    keep: np.ndarray  #: contacts kept (m - |B| x 2)
    broken: np.ndarray  #: contacts broken (|B| x 2)
    tangent: np.ndarray  #: the signed tangent direction
    free: np.ndarray  #: free coordinates
    #: rows of ``keep`` that a rigid part holds at their length along the path (:attr:`Dimension.held_rows`), or None
    held_rows: np.ndarray | None = None

    def follow(self, params: Params) -> PathEnd:
        return follow_path(self.x, self.keep, self.broken, self.tangent, self.free, params, self.held_rows)


@dataclass(frozen=True)
class Image:
    """A subset whose attempts are those of an earlier subset relabelled: ``broken`` is ``relabel``'s image
    of ``of`` (sphere ``i`` of ``of``'s attempts is sphere ``relabel[i]`` of this subset's)."""

    broken: tuple[tuple[int, int], ...]
    of: tuple[tuple[int, int], ...]
    relabel: np.ndarray


class _Orbits:
    """The subsets of a cluster's contacts under its symmetries (:func:`packings.workers.identity.symmetries`).

    Subsets of one size are tried in lexicographic order of their contacts' indices, so the first of
    each orbit is its smallest member: that one is tried, and each other member is its image.
    """

    def __init__(self, cluster: Cluster, perms: np.ndarray) -> None:
        at = {p: q for q, p in enumerate(cluster.contacts)}
        self.perms = perms[1:]
        #: the contact index each contact goes to under each symmetry but the identity (first)
        self.moves = np.array(
            [[at[pair(int(t[i]), int(t[j]))] for i, j in cluster.contacts] for t in self.perms], dtype=np.int64
        ).reshape(len(self.perms), cluster.m)

    def firsts(self, chunk: list[tuple[int, ...]]) -> list[tuple[tuple[int, ...], np.ndarray] | None]:
        """For each subset of ``chunk`` (subsets of one size, each sorted): None if it is the first of its orbit;
        else that first subset and the relabelling that takes it to the subset.  Read off together: each subset's
        images sorted, and the first symmetry giving the smallest of them in lexicographic order."""
        if not chunk:
            return []
        idx = np.array(chunk, dtype=np.int64)
        images = np.sort(self.moves[:, idx], axis=2)  # symmetry x subset x contact
        g, smaller = _lexicographic_min(images, idx)
        out: list[tuple[tuple[int, ...], np.ndarray] | None] = [None] * len(chunk)
        for c in np.flatnonzero(smaller).tolist():
            perm = self.perms[g[c]]
            inverse = np.empty_like(perm)  # symmetry g takes idx to best: its inverse takes best to idx
            inverse[perm] = np.arange(inverse.size)
            out[c] = (tuple(images[g[c], c].tolist()), inverse)
        return out


def _lexicographic_min(images: np.ndarray, own: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each column c of ``images`` (G x C x k, rows sorted tuples), the first g whose tuple is the smallest in
    lexicographic order, and whether that tuple is smaller than ``own[c]``."""
    G, C, k = images.shape
    alive = np.ones((G, C), dtype=bool)  # the symmetries whose tuple ties the smallest so far on the first places
    for j in range(k):
        col = np.where(alive, images[:, :, j], np.iinfo(np.int64).max)
        alive &= col == col.min(axis=0)
    g = alive.argmax(axis=0)
    best = images[g, np.arange(C)]
    differ = best != own
    first = differ.argmax(axis=1)  # the first place where the smallest image and the subset differ
    rows = np.arange(C)
    smaller = differ.any(axis=1) & (best[rows, first] < own[rows, first])
    return g, smaller


#: subsets of one size taken at a time: their symmetries are sought, and their first-order counts read, together
_BATCH = 1024


def _attempts(
    cluster: Cluster,
    params: Params,
    first_order: bool = True,
    perms: np.ndarray | None = None,
    arrivals: Mapping[tuple[tuple[int, int], ...], Arrival] | None = None,
    source: dict | None = None,
    held: bool = True,
) -> Iterator[Endpoint | PathStart | Image]:
    """Every (broken subset, direction) of ``cluster`` in order: an Endpoint where no path is followed, else a PathStart.

    Given the cluster's symmetries ``perms`` (:func:`packings.workers.identity.symmetries`), a subset that
    is the image of an earlier one under one of them (:class:`_Orbits`) is an :class:`Image` of it
    instead, decided and followed no further.

    With ``first_order``, a subset whose first-order count after breaking already decides that its set
    is not one-dimensional (no flex left; or no stress left and a number of flexes other than one) is
    decided from the self-stresses of the whole cluster's rigidity matrix in that frame
    (:func:`packings.workers.dimension.counts_after_breaking`), not from an SVD of what is left; the
    outcome is the same (where rounding could make them differ, the SVD decides).  Where that count is
    one flex and no stress, the tangent too comes from the cluster's SVD in that frame
    (:func:`packings.workers.dimension.tangent_after_breaking`; every single break of a regular
    cluster is such a subset): the direction the SVD of what is left gives, up to sign and rounding.  The
    counts of a size that needs no tangent are read for up to :data:`_BATCH` subsets at once
    (:func:`packings.workers.dimension.ranks_after_breaking`, the same numbers).  Where the count leaves a
    flex and a stress in a first-order rigid cluster, V and W of what is left come from the same SVD
    (:func:`packings.workers.dimension.left_after_breaking`) and may decide the set without its own SVD
    (:func:`packings.workers.dimension.solution_dimension`, as that SVD decides it).

    With ``arrivals`` at a first-order rigid cluster, a subset with an arrival, whose break leaves a set
    that the first-order count (or an SVD) finds smooth and one-dimensional, with one direction that
    lengthens the subset, is an Endpoint at the arrival's cluster (:attr:`Endpoint.reached`), not followed.
    ``source["first_order_rigid"]`` is set to whether the cluster is first-order rigid (with
    ``first_order`` only).

    With ``held``, a subset B that leaves one flex to first order, and has a contact q such that B less q
    was tried and leaves a one-dimensional set, is an Endpoint ``held``, not followed: q's row lies in the
    span of what is left, so B's set lies on the smooth curve of any rank(R∖B) of its independent rows,
    and so does the curve B less q leaves, which is therefore B's whole set near x.  Along it q keeps its
    length exactly: B's path is the path of B less q, which is followed, and following it again only
    asks rounding whether q opens (docs/method.md).

    It is one generator, longer than 80 lines, on purpose: the frames and stress bases it caches, the orbits,
    the arrivals and the held subsets are state that every subset's decision reads and adds to, in the loop
    every expansion runs; split into functions, that state would be passed through every call.
    """
    n, m = cluster.n, cluster.m
    all_edges, pairs = cluster.edges(), cluster.contacts
    frames: dict[tuple[int, int, int], tuple[np.ndarray, np.ndarray]] = {}  # the cluster in each pinned frame
    bases: dict[tuple[int, int, int], StressBasis] = {}  # its rigidity matrix's SVD in that frame

    def frame(tri):
        if tri not in frames:
            frames[tri] = (kernels.to_frame(cluster.coords, tri).ravel(), kernels.free_coordinates(n, tri))
        return frames[tri]

    def basis(tri):
        if tri not in bases:
            x, free = frame(tri)
            bases[tri] = StressBasis.of(kernels.null_spaces(x, all_edges, free, params.tol_n), params.tol_n)
        return bases[tri]

    own_tri = contact_triangle(all_edges)
    if first_order:
        own = basis(own_tri)
        rank = 3 * n - 6 - own.flexes
        # Which subset sizes the cluster's own SVD can decide: with a self-stress, those may_decide allows; and
        # the size whose count can be one flex and no stress (f + |B| - s = 1), which it gives the tangent of.
        stressed, one_flex = own.W.shape[1] > 0, own.W.shape[1] + 1 - own.flexes
        rigid = own.flexes == 0
    else:
        rank, stressed, one_flex = cluster_rank(cluster, params), False, 0
        rigid = False
    if source is not None:
        source["first_order_rigid"] = rigid
    retrace = arrivals if rigid and arrivals else None
    # The first triangle of what is left is the cluster's own unless a broken contact is one of its sides:
    # every contact before its first side had no triangle, and deleting contacts makes none.
    own_sides = set() if own_tri is None else {tuple(sorted(p)) for p in combinations(own_tri, 2)}
    orbits = _Orbits(cluster, perms) if perms is not None and len(perms) > 1 else None
    triangles = FirstTriangles(pairs)  # the first triangle of what is left, as contact_triangle(keep) finds it
    one_d: set[tuple[int, ...]] = set()  # the subsets tried whose set is one-dimensional (an image's too)
    for k in break_sizes(m, rank, params):
        # Where the counts of this size come from the cluster's own SVD without vectors (not the size whose count
        # can be one flex and no stress), they are read off in batches (ranks_after_breaking): the same numbers.
        batched = first_order and stressed and own_tri is not None and k > 1 and k != one_flex and may_decide(own, k)
        combos = combinations(range(m), k)
        while chunk := list(islice(combos, _BATCH)):
            firsts = orbits.firsts(chunk) if orbits is not None else [None] * len(chunk)
            ranks: dict[tuple[int, ...], int] = {}
            if batched:
                tried = [
                    idx
                    for idx, first in zip(chunk, firsts)
                    if first is None and not own_sides.intersection(pairs[q] for q in idx)
                ]
                got = ranks_after_breaking(own, tried, params.tol_n)
                if got is not None:
                    ranks = dict(zip(tried, got.tolist()))
            for idx, first in zip(chunk, firsts):
                if first is not None:
                    if first[0] in one_d:
                        one_d.add(idx)
                    yield Image(tuple(pairs[q] for q in idx), tuple(pairs[q] for q in first[0]), first[1])
                    continue
                broken = all_edges[list(idx)]
                kept = np.ones(m, dtype=bool)
                kept[list(idx)] = False
                keep = all_edges[kept]
                bt = tuple(pairs[q] for q in idx)  # the cluster's own contact tuples, shared
                tri = triangles.after_deleting(idx) if own_sides.intersection(bt) or own_tri is None else own_tri
                if tri is None:
                    yield Endpoint(bt, 0, NO_TRIANGLE)
                    continue
                x, free = frame(tri)
                dim = ns = flexes = stresses = None
                if idx in ranks:  # the frame is own_tri: the ranks are read only where no side of it is broken
                    r = ranks[idx]
                    counts, t = (None if r < 0 else (own.flexes + k - r, own.W.shape[1] - r)), None
                elif k == one_flex or (stressed and may_decide(basis(tri), k)):
                    counts, t = after_breaking(basis(tri), idx, params.tol_n)
                else:
                    counts = t = None
                if counts is not None:
                    flexes, stresses = counts
                    if flexes == 0 or (stresses == 0 and flexes != 1):
                        yield Endpoint(bt, 0, NOT_1D, flexes if stresses == 0 else 0)
                        continue
                    if t is not None:
                        dim = Dimension(1, t[:, None], "regular")
                if flexes is None:
                    ns = kernels.null_spaces(x, keep, free, params.tol_n)
                    flexes = ns.V.shape[1]
                if held and flexes == 1 and k > 1 and any(sub in one_d for sub in combinations(idx, k - 1)):
                    one_d.add(idx)
                    yield Endpoint(bt, 0, HELD, 1)
                    continue
                if dim is None:
                    # A flex and a stress left, counted from the cluster's SVD: V and W of what is left from it too,
                    # where they may decide the set without its SVD.  A cluster with a flex (singular, hypostatic) has
                    # its stress spread over all of it, and its sets seldom fall to a rigid part or to the cheap cases
                    # of the pre-stress test (docs/method.md): they take the SVD at once.
                    left = left_after_breaking(basis(tri), idx, params.tol_n) if stresses and rigid else None
                    dim = solution_dimension(x, keep, free, params, ns=ns, limit=1, left=left)
                if dim.dim != 1:
                    yield Endpoint(bt, 0, NOT_1D, dim.dim)
                    continue
                one_d.add(idx)
                v = dim.tangents[:, 0]
                g = np.array([_lengthening(x, v, i, j) for i, j in broken])
                signs = [s for s in (1, -1) if np.all(s * g > -params.tol_n)]
                if not signs:
                    yield Endpoint(bt, 0, NO_DIRECTION, 1)
                    continue
                # a smooth curve (R less the subset has full row rank) with one way out: the way the arrival came
                if retrace is not None and len(signs) == 1 and dim.method == "regular" and bt in retrace:
                    a = retrace[bt]
                    yield Endpoint(bt, signs[0], RIGID, 1, a.steps, new_contacts=a.formed, reached=a)
                    continue
                for s in signs:
                    yield PathStart(bt, s, x, keep, broken, s * v, free, dim.held_rows)


def path_starts(cluster: Cluster, params: Params) -> list[PathStart]:
    """The paths :func:`expand` follows from ``cluster``, in its order, without following them."""
    return [a for a in _attempts(cluster, params) if isinstance(a, PathStart)]


def expand(
    cluster: Cluster,
    params: Params,
    first_order: bool = True,
    symmetric: bool = True,
    arrivals: Mapping[tuple[tuple[int, int], ...], Arrival] | None = None,
    held: bool = True,
) -> Expansion:
    """Break every admissible subset of contacts of ``cluster`` and follow every path.

    A pure function of its inputs.  For every subset B whose removal leaves a
    solution set of dimension exactly 1, each direction of the tangent that
    lengthens all broken contacts (to first order; both if some are unchanged to
    first order) is followed to its endpoint.  ``first_order`` False decides
    every subset by an SVD of what is left (the reference :func:`_attempts` is
    measured and tested against); the result is the same.

    With ``symmetric`` (the default), a subset that a symmetry of ``cluster`` takes an earlier subset
    to gets the earlier subset's attempts relabelled (:attr:`Endpoint.image`): the same outcomes and
    the same clusters reached, congruent paths being followed once.  ``symmetric`` False follows
    every path (the reference it is tested against).

    With ``arrivals`` (:func:`arrivals`) at a first-order rigid cluster, the path that breaks an arrival's
    contacts is not followed: it retraces the path that arrived, and its attempt ends at the cluster that path
    came from (:attr:`Endpoint.reached`; docs/method.md).

    With ``held`` (the default), a subset with a broken contact that the rest holds at its length is not
    followed (outcome ``held``, :func:`_attempts`): its path is that of a smaller subset.  ``held`` False
    follows it (the reference it is tested against): the same clusters are reached.
    """
    cert = certificate(cluster)
    out: list[Endpoint] = []
    made: dict[tuple, list[int]] = {}  # with symmetries: where each subset's attempts are in out
    images: dict[int, int] = {}  # attempt -> the earlier attempt it is the image of
    perms = symmetries(cluster, params.tol_d) if symmetric else None
    symmetric = perms is not None and len(perms) > 1
    if arrivals and symmetric:
        arrivals = _closed(arrivals, perms)
    source: dict = {}
    for a in _attempts(cluster, params, first_order, perms, arrivals, source, held):
        if isinstance(a, Image):
            for i in made[a.of]:
                images[len(out)] = i
                out.append(_image(out[i], a.broken, a.relabel))
            continue
        if symmetric:
            made.setdefault(a.broken if isinstance(a, Endpoint) else a.broken_contacts, []).append(len(out))
        if isinstance(a, Endpoint):
            out.append(a)
        else:
            out.append(_classify(cluster, cert, a.broken_contacts, a.direction, a.follow(params), params))
    first = same_as(out, params.tol_d, images)
    ex = Expansion(cluster, tuple(out), first, source.get("first_order_rigid", False))
    for i, e in enumerate(out):  # only the distinct rigid endpoints are compared again (the write-back), and
        if e.cluster is not None and first[i] != i and not ex.retraceable(i):  # the arrivals relabelled
            forget_canonical(e.cluster)
    return ex


def same_as(endpoints, tol_d: float, images: dict[int, int] | None = None) -> tuple[int | None, ...]:
    """:attr:`Expansion.same_as` of these endpoints: rigid endpoints that are the same cluster (same
    certificate, same geometry within ``tol_d``) point at the first of them.  ``images`` maps an
    endpoint that is an earlier one relabelled (the same cluster) to that one, not compared again."""
    index = ClusterIndex()
    first: list[int] = []  # endpoint index of each cluster of the index
    out: list[int | None] = []
    for i, e in enumerate(endpoints):
        if e.outcome != RIGID or e.cluster is None:  # not compared: an attempt retraced (Endpoint.reached)
            out.append(None)
            continue
        if images and i in images:
            out.append(out[images[i]])
            continue
        k, is_new = index.add(e.cluster, tol_d)
        if is_new:
            first.append(i)
        out.append(first[k])
    return tuple(out)


def _image(e: Endpoint, broken: tuple[tuple[int, int], ...], relabel: np.ndarray) -> Endpoint:
    """Attempt ``e`` with sphere ``i`` relabelled ``relabel[i]``: the attempt on ``broken``, its image."""
    t = relabel.tolist()
    c = reached = None
    if e.cluster is not None:
        coords = np.empty_like(e.cluster.coords)
        coords[relabel] = e.cluster.coords
        c = Cluster(coords, _pairs(t, e.cluster.contacts))
    if e.reached is not None:
        reached = _relabelled(e.reached, t)
    return Endpoint(
        broken,
        e.direction,
        e.outcome,
        e.dim,
        e.steps,
        c,
        e.rigidity,
        _pairs(t, e.new_contacts),
        e.first_step_dim,
        image=True,
        reached=reached,
    )


def _relabelled(a: Arrival, t: list[int]) -> Arrival:
    """Arrival ``a`` with sphere ``i`` relabelled ``t[i]``: sphere ``t[i]`` of the path back's endpoint is
    sphere ``i`` of ``a``'s."""
    labels = [0] * len(t)
    for i, k in enumerate(t):
        labels[k] = a.labels[i]
    return Arrival(_pairs(t, a.contacts), a.target, _pairs(t, a.formed), a.steps, tuple(labels))


def _closed(
    found: Mapping[tuple[tuple[int, int], ...], Arrival], perms: np.ndarray
) -> dict[tuple[tuple[int, int], ...], Arrival]:
    """The arrivals ``found`` with their images under the symmetries ``perms`` of the cluster (a symmetry
    takes the path back of one to the path back of its image), so that the first subset of each orbit,
    the one followed, has one whenever a member does; contacts given disagreeing ones have none."""
    images = (_relabelled(a, t) for t in perms[1:].tolist() for a in found.values())
    return _by_contacts(chain(found.values(), images))


def _lengthening(x: np.ndarray, v: np.ndarray, i: int, j: int) -> float:
    """d/ds |x_i - x_j|^2 / 2 along v: (x_i - x_j).(v_i - v_j)."""
    return float((x[3 * i : 3 * i + 3] - x[3 * j : 3 * j + 3]) @ (v[3 * i : 3 * i + 3] - v[3 * j : 3 * j + 3]))


def _classify(source: Cluster, cert: bytes, broken, sign: int, end: PathEnd, params: Params) -> Endpoint:
    c = Cluster(end.coords, end.contacts) if end.coords is not None else None
    outcome = end.outcome
    if outcome == RIGID:
        if certificate(c) == cert and same_geometry(source, c, params.tol_d):
            outcome = CIRCULAR if same_labelled(source, c, params.tol_d) else REARRANGED
        elif params.min_contacts is not None and c.m < params.min_contacts:
            outcome = BELOW_MIN_CONTACTS
    return Endpoint(broken, sign, outcome, 1, end.steps, c, end.rigidity, end.new_contacts, end.first_step_dim)


def same_labelled(a: Cluster, b: Cluster, tol_d: float) -> bool:
    """Whether ``b`` is ``a`` with every sphere where it was: the same contacts, and the coordinates within
    ``tol_d`` once aligned with sphere i on sphere i by a proper rotation.  A path that ends so is the
    paper's circle; one that ends at ``a`` only up to a relabelling, or at its mirror image with the same
    labels (another configuration, which only a reflection brings back), reached another isomer."""
    if sorted(a.contacts) != sorted(b.contacts):
        return False
    x, y = a.coords - a.coords.mean(axis=0), b.coords - b.coords.mean(axis=0)
    u, _, vt = np.linalg.svd(x.T @ y)
    d = np.ones(3)
    d[2] = np.sign(np.linalg.det(u @ vt))  # the best proper rotation (Kabsch)
    r = (u * d) @ vt
    return float(np.max(np.abs(x @ r - y))) <= tol_d


def warm_up(apart: bool = True) -> float:
    """Compile (or load from numba's on-disk cache) every compiled kernel; returns the seconds taken.

    Runs each kernel once on a small cluster (a path of the 6-sphere
    polytetrahedron with one contact broken, a projection with an extra linear
    row, the rank certificate), so that the first real path does not pay for
    compilation.  Call it once per process (e.g. per Dask worker).  It lives here, above
    every module whose kernels it runs, not in :mod:`kernels`, the lowest layer.  Does nothing
    (returns 0.0) when the numpy backend is selected.

    With ``apart``, a cold cache is filled by a child process first, and this one loads the kernels from
    it (:func:`packings.workers.kernel_cache.compile_apart`): the compiler's memory goes with the child.
    """
    if kernels.get_backend() != "numba":
        return 0.0
    from packings.workers.kernel_cache import compile_apart
    from packings.workers.seeds import seed_cluster

    start = time.perf_counter()
    if apart:
        compile_apart()
    params = Params()
    c = seed_cluster(6, params)
    edges = c.edges()
    keep, broken = edges[:-1], edges[-1:]
    tri = contact_triangle(keep)
    x = kernels.to_frame(c.coords, tri).ravel()
    free = kernels.free_coordinates(c.n, tri)
    kernels.residual(x, edges)
    kernels.rigidity_matrix(x, edges)
    kernels.pair_distances_flat(x, edges)
    dim = solution_dimension(x, keep, free, params)
    kw = params.newton()
    v = dim.tangents[:, 0]
    kernels.project(x + params.ds * v, keep, free, extra=(v[free][None, :], np.array([v[free] @ x[free]])), **kw)
    kernels.project(x, edges, free, polish=True, **kw)
    kernels.regular_flexes(x, edges, free, params.tol_n)
    left = contact_triangle([(i - 1, j - 1) for i, j in c.contacts if i and j])  # c without sphere 0
    kernels.floppy_without(c.coords, edges, np.array([0]), np.array([left]), params.tol_n)
    for s in (1.0, -1.0):
        follow_path(x, keep, broken, s * v, free, params)
    same_geometry(
        c, Cluster(c.coords[::-1] + 1.0, tuple((c.n - 1 - j, c.n - 1 - i) for i, j in c.contacts)), params.tol_d
    )
    return time.perf_counter() - start
