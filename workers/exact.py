"""Whether a computed cluster stands for an exact one: Kantorovich's theorem on its contact equations.

Newton's method stops when the sum of the squared contact residuals is below ``tol``; a point
can pass that test and yet be near no solution at all (a shallow valley of the residual near a
singular configuration).  For a cluster with no flex, the theorem turns the computed point into
a proof: with a triangle pinned as the rigidity test pins it, 3n - 6 independent contact equations
in the 3n - 6 free coordinates have a root within ``radius`` of the point, and no other within
``unique``.  The endpoint rule asks for this before it calls an endpoint first-order rigid
(:func:`packings.workers.paths.endpoint_rigidity`); the audit asks it of every stored cluster with no flex
and compares the exact clusters of one contact graph (:func:`not_told_apart`).  docs/method.md,
"Exact clusters".

Floating-point arithmetic with its rounding bounded, not interval arithmetic.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from packings.workers import kernels
from packings.workers.cluster import Cluster, upper_pairs
from packings.workers.identity import _Canonical, _canonical, _group
from packings.workers.params import DEFAULT, Params
from packings.workers.rigidity import contact_triangle

PROVED = "proved"  #: a root exists within ``radius`` and its non-contact pairs provably do not touch
GAP = "gap"  #: a root exists within ``radius``, but a non-contact pair may touch or overlap in it
TOO_FAR = "too-far"  #: h > 1/2: the point is too far from a root, or too ill-conditioned, for the theorem
SINGULAR = "singular"  #: a singular value of the pinned rigidity matrix below tol_n: a flex, nothing to prove
NOT_RIGID = "too-few-contacts"  #: fewer than 3n - 6 contacts (or no triangle to pin): a flex whatever the point

#: relative size of the rounding allowed for in the computed singular values (LAPACK: a few eps ||J||)
SVD_ROUNDING = 1e-12
#: absolute rounding allowed for in each computed residual |x_i - x_j|^2 - 1 of a contact (a few eps)
RESIDUAL_ROUNDING = 1e-14


@dataclass(frozen=True)
class Exact:
    """What :func:`kantorovich` proved about a point ``x0`` (flat, in the frame of its pinned triangle).

    A root exists (``status`` PROVED or GAP): a configuration ``x*`` whose chosen 3n - 6 contacts
    (all of them when there are 3n - 6) are at distance exactly 1, with the pinned rigidity matrix
    of those contacts of full rank at ``x*`` (first-order rigid), ``|x* - x0| <= radius`` (2-norm
    over all coordinates), and no other root of those equations within ``unique`` of ``x0``.  With
    more than 3n - 6 contacts the others are not proved to touch: at ``x*`` they are within
    ``others`` of it (a bound on |distance^2 - 1|).  PROVED adds that every non-contact pair is at
    distance at least 1 + ``gap`` > 1 at ``x*``.  ``h`` is Kantorovich's β L η (the theorem needs h
    <= 1/2).
    """

    status: str
    h: float | None = None
    radius: float | None = None
    unique: float | None = None
    gap: float | None = None  #: lower bound of the root's smallest non-contact gap (distance - 1); None if none
    others: float = 0.0  #: bound on |f| at the root of the contacts beyond the 3n - 6 proved (0 if none)

    @property
    def exists(self) -> bool:
        """A root of (3n - 6 independent) contact equations is proved to lie within ``radius``."""
        return self.status in (PROVED, GAP)

    @property
    def proved(self) -> bool:
        return self.status == PROVED


def _lipschitz(edges: np.ndarray) -> float:
    """L = 4 sqrt(Δ), a Lipschitz constant of J = 2 R_f for the contacts ``edges`` (Δ the largest number
    of them at one sphere): ||J(u)||_F^2 = 8 Σ |u_i - u_j|^2 <= 16 Δ |u|^2."""
    return 4.0 * math.sqrt(int(np.bincount(np.asarray(edges).ravel()).max()))


def kantorovich(x: np.ndarray, edges: np.ndarray, free: np.ndarray, tol_n: float = DEFAULT.tol_n) -> Exact:
    """Kantorovich's theorem on the contact equations at ``x`` (flat, pinned frame of ``free``).

    F(y) = (|x_i - x_j|^2 - 1 for 3n - 6 contacts) in the 3n - 6 free coordinates y: every contact
    when there are 3n - 6, else the rows a pivoted QR factorisation picks as the best conditioned.
    The Jacobian J = 2 R_f is Lipschitz with constant L = 4 sqrt(Δ) (Δ the largest number of those
    contacts at one sphere: ||J(u)||_F^2 = 8 Σ |u_i - u_j|^2 <= 16 Δ |u|^2).  With β >= ||J(x)^-1||
    = 1 / σ_min and η >= ||J(x)^-1 F(x)||, both with the rounding of their computation allowed for,
    and h = β L η <= 1/2, a root lies within t* = 2η / (1 + sqrt(1 - 2h)) of x and no other within
    (1 + sqrt(1 - 2h)) / (β L); ||J(x*) - J(x)|| <= L t* < 1/β keeps J(x*) invertible.  A pair moves
    apart or together by at most sqrt(2) t*, which bounds the root's gaps and, for contacts beyond
    the 3n - 6, their residuals: |f(x*)| <= |f(x)| + 2 sqrt(2) d t* + 2 t*^2.  A singular value of R_f
    below ``tol_n`` (a flex, as the rigidity test counts it) is reported as SINGULAR.
    """
    x = np.asarray(x, dtype=np.float64).ravel()
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    k = free.size
    if edges.shape[0] < k or k == 0:
        return Exact(NOT_RIGID)
    jac = 2.0 * kernels.rigidity_matrix_numpy(x, edges)[:, free]
    f = kernels.residual_numpy(x, edges)
    rows = np.arange(edges.shape[0])
    if edges.shape[0] > k:
        rows = np.sort(scipy.linalg.qr(jac.T, mode="r", pivoting=True)[1][:k])
    s = np.linalg.svd(jac[rows], compute_uv=False)
    smin = float(s[-1] - SVD_ROUNDING * s[0])
    if smin <= 0.0 or s[-1] / 2.0 < tol_n:  # the rigidity test's singular values are R's, J = 2R
        return Exact(SINGULAR)
    beta = 1.0 / smin
    lip = _lipschitz(edges[rows])
    eta = beta * (float(np.linalg.norm(f[rows])) + RESIDUAL_ROUNDING * math.sqrt(k))
    h = float(beta * lip * eta)
    if h > 0.5:
        return Exact(TOO_FAR, h=h)
    root = math.sqrt(1.0 - 2.0 * h)
    radius = 2.0 * eta / (1.0 + root)
    unique = (1.0 + root) / (beta * lip)
    move = math.sqrt(2.0) * radius
    n = x.size // 3
    pairs = upper_pairs(n)
    touching = np.zeros((n, n), dtype=bool)
    touching[edges[:, 0], edges[:, 1]] = touching[edges[:, 1], edges[:, 0]] = True
    apart = kernels.pair_distances_flat(x, pairs[~touching[pairs[:, 0], pairs[:, 1]]])
    gap = float(apart.min()) - 1.0 - move if apart.size else None  # None: every pair touches
    rest = np.setdiff1d(np.arange(edges.shape[0]), rows)
    others = 0.0
    if rest.size:
        dr = kernels.pair_distances_flat(x, edges[rest])
        others = float(np.max(np.abs(f[rest]) + RESIDUAL_ROUNDING + 2.0 * dr * move + move * move))
    return Exact(PROVED if gap is None or gap > 0.0 else GAP, h=h, radius=radius, unique=unique, gap=gap, others=others)


def root_exists(
    x: np.ndarray, edges: np.ndarray, free: np.ndarray, tol_n: float = DEFAULT.tol_n, sigma_min: float | None = None
) -> bool:
    """Whether :func:`kantorovich` proves a root near ``x`` (``.exists``), cheaply where it can.

    ``sigma_min``: a lower bound of the smallest singular value of R_f that the caller already has
    (the compiled rigidity test's certificate, or its SVD).  With 3n - 6 contacts, β = 1 / (2
    sigma_min) bounds ||J^-1|| and h <= β L β (|F| + rounding) needs only the residuals: at a regular
    point (|F| at round-off) that settles it, with no SVD.  Otherwise the whole theorem decides.
    """
    edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
    if sigma_min is not None and sigma_min > 0.0 and edges.shape[0] == free.size:
        beta = 1.0 / (2.0 * sigma_min)
        lip = _lipschitz(edges)
        f = float(np.linalg.norm(kernels.residual(x, edges)))
        if beta * lip * beta * (f + RESIDUAL_ROUNDING * math.sqrt(free.size)) <= 0.5:
            return True
    return kantorovich(x, edges, free, tol_n).exists


def exact_cluster(cluster: Cluster, params: Params = DEFAULT) -> Exact:
    """:func:`kantorovich` for a stored cluster, pinned at its :func:`contact_triangle` as the rigidity
    test pins it."""
    edges = cluster.edges()
    tri = contact_triangle(edges) if cluster.n >= 3 else None
    if tri is None:
        return Exact(NOT_RIGID)
    x = kernels.to_frame(cluster.coords, tri).ravel()
    return kantorovich(x, edges, kernels.free_coordinates(cluster.n, tri), params.tol_n)


def distance_lower_bound(a: _Canonical, b: _Canonical) -> float:
    """A lower bound of min over automorphisms s, rotations and reflections Q and translations t of
    ||x_a - x_b[s] Q - t||_F, for two clusters of one contact graph in canonical form
    (:func:`packings.workers.identity._canonical`: centred, canonically ordered, distances sorted).

    First from the sorted pair distances (a pair's distance changes by at most sqrt(2) times the
    Frobenius distance, and sorting does not increase the largest difference); where that is not
    enough to tell them apart, the orthogonal Procrustes minimum for each automorphism of a's graph,
    ||x_a||^2 + ||x_b||^2 - 2 Σ σ(x_b[s]^T x_a), less its rounding.
    """
    by_distances = float(np.max(np.abs(a.sorted_dist - b.sorted_dist), initial=0.0)) / math.sqrt(2.0)
    norms = float(np.sum(a.x * a.x) + np.sum(b.x * b.x))
    best = np.inf
    for s in _group(a):
        _, trace = scipy.linalg.orthogonal_procrustes(a.x, b.x[s], check_finite=False)  # Σ σ(x_a^T x_b[s])
        sq = norms - 2.0 * float(trace)
        best = min(best, math.sqrt(max(0.0, sq - 1e-12 * norms)))
    return max(by_distances, best)


def not_told_apart(clusters: list[Cluster], exacts: list[Exact]) -> list[tuple[int, int, float]]:
    """The pairs (i, j), i < j, of ``clusters`` (all of one contact graph) whose exact clusters
    cannot be proved different, each with its :func:`distance_lower_bound`; pairs with a cluster
    whose root is not proved are left out (nothing to compare).

    Both in canonical order: if the roots were congruent, the congruence would map contacts to
    contacts, so for some automorphism s of the canonical graph, rotation or reflection Q and
    translation t, ||x_i - x_j[s] Q - t||_F <= radius_i + radius_j.  A lower bound above that sum
    proves them different.
    """
    canon = [_canonical(c) for c in clusters]
    if len({(c.n, c.cert) for c in canon}) > 1:
        raise ValueError("not_told_apart needs clusters of one contact graph (certificate)")
    out = []
    for j in range(len(clusters)):
        for i in range(j):
            ea, eb = exacts[i], exacts[j]
            if not (ea.exists and eb.exists):
                continue
            bound = distance_lower_bound(canon[i], canon[j])
            if not bound > ea.radius + eb.radius:
                out.append((i, j, bound))
    return out
