"""The sticky-limit free energies against a direct Monte Carlo integration that uses none of their formulas.

For each rigid cluster of n spheres (``explore(n)``), the configuration integral of its basin under a
square well of width ε (every pair of its contacts at a distance in [1, 1 + ε], every other pair
farther than 1 + ε) is estimated by importance sampling in distance coordinates (:func:`basin_volume`),
and the reduced integral Q(ε) / ε^m, Q the integral of identical spheres per unit volume, is compared
with 8π² n^{3/2} z (``packings.workers.free_energy``): their ratio must tend to 1 as ε → 0.  The
Boltzmann factor e^{mβu} of the well's depth u is the same at every point of a basin, so the integral
of the square well is e^{mβu} Q(ε) and κ = ε e^{βu}.

The sampler.  Sphere 0 is fixed at the origin (the integral is per unit volume); the spheres are
placed in an order in which 0, 1, 2 touch and every later sphere k is fixed by its distances to three
spheres placed before it (its anchors, contacts first).  The coordinates are those 3n - 6 distances,
plus the direction of x_1 and the angle of x_2 about the axis x_0 x_1, which the integrand does not
depend on and which integrate to 8π².  Exactly, with V_k the volume of the tetrahedron of k and its
anchors a, b, c,

    dx_1 ... dx_{n-1} = r_01² dr_01 dΩ · (r_02 r_12 / r_01) dr_02 dr_12 dφ · ∏_k r_ka r_kb r_kc / (6 V_k) dr_ka dr_kb dr_kc

on each branch (the side of the plane a b c on which k lies: the reference configuration's side, one
labelled copy of the cluster; its mirror image is another; where k is nearly in that plane, as a sphere
in the plane of three it touches, both sides, drawn at random with weight 2).  A distance that is a contact is drawn
uniformly in [1, 1 + ε], any other in a window around its reference value wide enough that no sample
in the basin comes near its edges (checked: ``edge``).  The cluster's basin holds 2 n! / s labelled
copies (both mirror images of every relabelling, s the number of permutations that preserve every pair
distance, counted here by exhaustive search over the permutations); the integral of identical spheres
divides by n!.  None of the rigidity matrix, the moment of inertia, the symmetry group of
``identity`` or the formula for z is used.
"""

from __future__ import annotations

import itertools
import json
import math
import time

import numpy as np

from packings.workers.cluster import Cluster

#: a sphere whose tetrahedron with its anchors is flatter than this (|det|) may cross their plane within the
#: basin (a sphere in the plane of three spheres it touches, as in hypostatic clusters): both branches are drawn
FLAT = 0.1


def placement(cluster: Cluster) -> tuple[list[int], list[tuple[int, int, int]]]:
    """An order of the spheres (a contact triangle first) and, for each sphere after the third, three
    anchors placed before it.  Next comes a sphere that makes a tetrahedron that is not flat (:data:`FLAT`)
    with some placed triple, if there is one, then the one with most contacts to the placed spheres; its
    anchors are such a triple, then the one with most contacts to it, then the largest tetrahedron."""
    x = cluster.coords
    adj = cluster.adjacency()
    n = cluster.n
    a, b = next((i, j) for i, j in cluster.contacts if (adj[i] & adj[j]).any())
    c = int(np.flatnonzero(adj[a] & adj[b])[0])
    order = [a, b, c]
    anchors = []

    def volume(k, t):
        return abs(np.linalg.det(np.array([x[k] - x[t[0]], x[k] - x[t[1]], x[k] - x[t[2]]])))

    def solid(k):  # whether some triple of the placed spheres makes a tetrahedron with k that is not flat
        return any(volume(k, t) > FLAT for t in itertools.combinations(order, 3))

    while len(order) < n:
        k = max((s for s in range(n) if s not in order), key=lambda s: (solid(s), adj[s, order].sum(), -s))
        triple = max(
            itertools.combinations(order, 3),
            key=lambda t: (volume(k, t) > FLAT, int(adj[k, list(t)].sum()), volume(k, t)),
        )
        anchors.append(triple)
        order.append(k)
    return order, anchors


def _trilaterate(pa, pb, pc, ra, rb, rc, side):
    """The point at distances ra, rb, rc from pa, pb, pc on the ``side`` (+-1) of the plane pa pb pc where
    det[x - pa, x - pb, x - pc] has that sign; NaN where the spheres do not meet.  Vectorised over rows."""
    ex = pb - pa
    d = np.linalg.norm(ex, axis=1)
    ex = ex / d[:, None]
    t = pc - pa
    i = np.einsum("ij,ij->i", ex, t)
    ey = t - i[:, None] * ex
    j = np.linalg.norm(ey, axis=1)
    ey = ey / j[:, None]
    ez = np.cross(ex, ey)
    u = (ra**2 - rb**2 + d**2) / (2 * d)
    v = (ra**2 - rc**2 + i**2 + j**2) / (2 * j) - i * u / j
    w2 = ra**2 - u**2 - v**2
    w = np.sqrt(np.where(w2 >= 0, w2, np.nan))
    base = pa + u[:, None] * ex + v[:, None] * ey
    # det[x - pa, x - pb, x - pc] = (x - pa).((pb - pa) x (pc - pa)), and (pb - pa) x (pc - pa) is along +ez
    return base + (side * w)[:, None] * ez


def basin_volume(
    cluster: Cluster, eps: float, samples: int, rng: np.random.Generator, window: float, chunk: int = 200_000
) -> dict:
    """Monte Carlo estimate of the volume (sphere 0 fixed) of the labelled copy of ``cluster``'s basin
    under a square well of width ``eps``: configurations near it, up to rotation, whose pairs within 1 + eps
    are exactly its contacts.  Non-contact coordinates are drawn within ``window`` of their reference
    value.  Returns the estimate, its standard error, the acceptance and ``edge``: the largest
    |offset| / half-width of a non-contact coordinate over the accepted samples (near 1: window too small)."""
    order, anchors = placement(cluster)
    x = cluster.coords
    n = cluster.n
    contact = cluster.adjacency()
    # the distance coordinates: (sphere, other) pairs in sampling order
    coords = [(order[1], order[0]), (order[2], order[0]), (order[2], order[1])]
    sides = []  # the reference's side of each sphere, 0 where it is flat: then a side at random, weight 2
    for k, (a, b, c) in zip(order[3:], anchors):
        coords += [(k, a), (k, b), (k, c)]
        det = np.linalg.det(np.array([x[k] - x[a], x[k] - x[b], x[k] - x[c]]))
        sides.append(0.0 if abs(det) < FLAT else float(np.sign(det)))
    ref = np.array([np.linalg.norm(x[i] - x[j]) for i, j in coords])
    is_contact = np.array([bool(contact[i, j]) for i, j in coords])
    lo = np.where(is_contact, 1.0, ref - window)
    hi = np.where(is_contact, 1.0 + eps, ref + window)
    log_box = float(np.log(hi - lo).sum()) + math.log(8.0 * math.pi**2)
    iu, ju = np.triu_indices(n, 1)
    pair_contact = contact[iu, ju]
    total = total2 = 0.0
    accepted = 0
    edge = 0.0
    done = 0
    while done < samples:
        size = min(chunk, samples - done)
        r = lo + (hi - lo) * rng.random((size, len(coords)))
        p = np.full((size, n, 3), np.nan)
        p[:, order[0]] = 0.0
        r01, r02, r12 = r[:, 0], r[:, 1], r[:, 2]
        p[:, order[1]] = np.column_stack([np.zeros(size), np.zeros(size), r01])
        zc = (r02**2 - r12**2 + r01**2) / (2 * r01)
        rho2 = r02**2 - zc**2
        p[:, order[2]] = np.column_stack([np.sqrt(np.where(rho2 > 0, rho2, np.nan)), np.zeros(size), zc])
        weight = r01 * r02 * r12
        for q, (k, (a, b, c)) in enumerate(zip(order[3:], anchors)):
            ra, rb, rc = r[:, 3 + 3 * q], r[:, 4 + 3 * q], r[:, 5 + 3 * q]
            side = np.full(size, sides[q]) if sides[q] else rng.choice([-1.0, 1.0], size)
            p[:, k] = _trilaterate(p[:, a], p[:, b], p[:, c], ra, rb, rc, side)
            with np.errstate(invalid="ignore"):  # NaN rows: spheres that do not meet, rejected below
                tet = np.stack([p[:, k] - p[:, a], p[:, k] - p[:, b], p[:, k] - p[:, c]], axis=1)
                six_v = np.abs(np.linalg.det(tet))
            weight = weight * ra * rb * rc / six_v * (1.0 if sides[q] else 2.0)
        d = np.linalg.norm(p[:, iu] - p[:, ju], axis=2)
        with np.errstate(invalid="ignore"):
            ok = np.all(np.where(pair_contact, (d >= 1.0) & (d <= 1.0 + eps), d > 1.0 + eps), axis=1)
        ok &= np.isfinite(weight)
        wk = np.where(ok, weight, 0.0)
        total += float(wk.sum())
        total2 += float((wk * wk).sum())
        accepted += int(ok.sum())
        if ok.any() and (~is_contact).any():
            off = np.abs(r[ok][:, ~is_contact] - ref[~is_contact]) / window
            edge = max(edge, float(off.max()))
        done += size
    mean = total / samples
    var = max(total2 / samples - mean * mean, 0.0)
    scale = math.exp(log_box)
    return {
        "volume": scale * mean,
        "error": scale * math.sqrt(var / samples),
        "acceptance": accepted / samples,
        "edge": edge,
    }


def distance_symmetries(cluster: Cluster, tol: float = 1e-6) -> int:
    """The number of permutations of the spheres that preserve every pair distance (rotations and
    reflections), by exhaustive search: sphere i is sent to each sphere whose distances to the images of
    spheres 0, ..., i - 1 are theirs to sphere i, every branch followed to the end."""
    x = cluster.coords
    d = np.linalg.norm(x[:, None] - x[None, :], axis=2)
    n = cluster.n

    def extend(image: list[int]) -> int:
        i = len(image)
        if i == n:
            return 1
        return sum(
            extend(image + [j])
            for j in range(n)
            if j not in image and all(abs(d[image[k], j] - d[k, i]) <= tol for k in range(i))
        )

    return extend([])


def reduced_integral(
    cluster: Cluster, eps: float, samples: int, rng: np.random.Generator, power: float = 0.0, flexes: int = 0
):
    """(Q / ε^(m + power), its standard error, the sampler's report): Q the configuration integral of
    ``cluster``'s basin for identical spheres per unit volume, (1/n!) (2 n!/s) times the labelled copy's
    volume.  ``power`` is the cluster's eps_power (0 for a regular cluster, a/2 - 1 for one with a flexes
    and one self-stress).  The windows of the non-contact coordinates are 4 ε wide on each side, or
    3 sqrt(ε) for a cluster with flexes (which it reaches to a distance of order sqrt(ε))."""
    window = 3.0 * math.sqrt(eps) if flexes else 4.0 * eps
    est = basin_volume(cluster, eps, samples, rng, window)
    scale = 2.0 / distance_symmetries(cluster) / eps ** (cluster.m + power)
    return scale * est["volume"], scale * est["error"], est


def table(
    sizes=(4, 5, 6, 7), epsilons=(0.1, 0.03, 0.01, 0.003, 0.001), samples=400_000, seed=0, singular=False
) -> list[dict]:
    """The convergence table: for each rigid cluster of each n and each ε, Q/ε^(m + p) against
    8π² n^{3/2} z_sw (z for a regular cluster, p its eps_power); with ``singular`` n = 9's singular cluster too."""
    from packings.workers.explore import explore
    from packings.workers.free_energy import REGULAR, free_energy, log_frame_constant

    rng = np.random.default_rng(seed)
    cases = [(n, index, c) for n in sizes for index, c in enumerate(explore(n).clusters)]
    if singular:
        cases += [(9, i, c) for i, c in enumerate(explore(9).clusters) if free_energy(c).kind != REGULAR]
    rows = []
    for n, index, c in cases:
        fe = free_energy(c)
        predicted = math.exp(log_frame_constant(n)) * fe.square_well
        for eps in epsilons:
            start = time.perf_counter()
            q, err, est = reduced_integral(c, eps, samples, rng, fe.eps_power, fe.flexes)
            rows.append(
                {
                    "n": n,
                    "cluster": index,
                    "kind": fe.kind,
                    "m": c.m,
                    "sigma": fe.sigma,
                    "power": fe.eps_power,
                    "eps": eps,
                    "mc": q,
                    "mc_error": err,
                    "formula": predicted,
                    "ratio": q / predicted,
                    "ratio_error": err / predicted,
                    "acceptance": round(est["acceptance"], 4),
                    "edge": round(est["edge"], 3),
                    "seconds": round(time.perf_counter() - start, 2),
                }
            )
    return rows


def add_arguments(p) -> None:
    p.add_argument("--sizes", type=int, nargs="+", default=[4, 5, 6, 7], help="numbers of spheres (default 4 5 6 7)")
    p.add_argument(
        "--eps", type=float, nargs="+", default=[0.1, 0.03, 0.01, 0.003, 0.001], help="widths of the square well"
    )
    p.add_argument("--samples", type=int, default=400_000, help="Monte Carlo samples per cluster and width")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--singular", action="store_true", help="add n = 9's singular cluster (Z ~ κ^m ε^(-1/2))")
    p.add_argument("--json", action="store_true", help="print the table as JSON")


def run(args) -> int:
    rows = table(tuple(args.sizes), tuple(args.eps), args.samples, args.seed, args.singular)
    if args.json:
        print(json.dumps({"rows": rows}, indent=2))
        return 0
    print("Q/eps^(m+p) (Monte Carlo, square well of width eps) against 8 pi^2 n^(3/2) z (sticky-limit formula)")
    head = (
        f"{'n':>2} {'#':>2} {'kind':>9} {'m':>3} {'sigma':>5} {'p':>4} {'eps':>7} {'MC':>12} {'+-':>10} "
        f"{'formula':>12} {'ratio':>8} {'+-':>7}"
    )
    print(head + f" {'accept':>7} {'edge':>5}")
    for r in rows:
        print(
            f"{r['n']:>2} {r['cluster']:>2} {r['kind']:>9} {r['m']:>3} {r['sigma']:>5} {r['power']:>4g} {r['eps']:>7g} "
            f"{r['mc']:>12.5g} "
            f"{r['mc_error']:>10.2g} {r['formula']:>12.5g} {r['ratio']:>8.4f} {r['ratio_error']:>7.4f} "
            f"{r['acceptance']:>7.4f} {r['edge']:>5.2f}"
        )
    return 0
