"""The sticky-sphere partition function of a rigid cluster: Z = κ^m z, the geometric factor z.

Pure numpy; no database or Dask imports.

The sticky limit
----------------
n spheres of diameter 1 with a pair potential U(r) that is hard below r = 1 and attractive over a
range ε above it.  In the sticky limit (ε → 0 with the strength of the attraction held) every
contact contributes the same factor, the sticky parameter

    κ = ∫_well e^{-βU(r)} dr   (the radial integral of the Boltzmann factor over the well, in units
                                of the diameter),

which is Baxter's 1/(12 τ) and, for a square well of depth u and width ε, κ = ε e^{βu}.  The
partition function of a cluster with m contacts is then Z = κ^m z + o(κ^m) where z depends only on
the geometry (Holmes-Cerfon, Gortler & Brenner, PNAS 110, E5 (2013); Meng, Arkus, Brenner &
Manoharan, Science 327, 560 (2010)):

    z = (χ / σ) · sqrt(det I) / ∏_{i=1}^{3n-6} λ_i

* λ_i are the 3n - 6 nonzero singular values of the rigidity matrix R (row k = contact (i, j) holds
  the unit vector x_i - x_j in sphere i's columns and its negative in j's: the Jacobian of the
  contact distances, :func:`packings.workers.kernels.rigidity_matrix` at contact).  The vibrational
  part: near the cluster the contact distances are a linear function of the 3n - 6 internal
  coordinates with this Jacobian, so the internal configurations with every contact in the well
  fill a volume ε^m / ∏ λ_i.
* I is the moment of inertia tensor about the centre of mass, unit masses (Σ |x|² 1 - x xᵀ).  The
  rotational part: the rotations of the cluster sweep a three-dimensional orbit of volume
  8π² sqrt(det I) in configuration space.
* σ is the symmetry number: the number of permutations of the spheres realised by a proper
  rotation of the cluster (its rotational point group), so that rotated copies of one configuration
  are not counted σ times.
* χ = 2 for a chiral cluster, 1 otherwise.  This package counts a cluster and its mirror image as
  one cluster (Holmes-Cerfon, SIAM Review 2016); the partition function of that one cluster holds
  both enantiomers, two states of weight 1/σ each.  With χ the ratios between the clusters of this
  package are the ratios of their equilibrium probabilities; z / χ is the factor of one enantiomer.

Normalisation.  Constants common to every cluster of n spheres are dropped: the translational volume
V, the 8π² of the rotation group, the n^{3/2} of fixing the centre of mass and the n! of relabelling
identical spheres.  Exactly: the configuration integral of identical spheres over the cluster's basin
(every configuration with exactly the cluster's contacts in the well, any labelling, both mirror
images), per unit volume, is

    (1 / n!) ∫_basin e^{-βU} dx_1 ... dx_{n-1} (x_0 fixed)  =  8π² n^{3/2} κ^m z (1 + O(ε)),

:func:`log_frame_constant` being log(8π² n^{3/2}); benchmarks/free_energy.py checks this by a direct
Monte Carlo integration that uses none of the formulas.  Probabilities of the clusters of one n at
the same κ are Z_a / Σ_b Z_b (:func:`equilibrium_shares`), which needs only z and m.

Where the formula does not apply z is None with the reason (:attr:`FreeEnergy.reason`):

* ``singular``: first-order flexible (a > 0 flexes: fewer than 3n - 6 nonzero singular values), held
  by a pre-stress.  The harmonic integral diverges: along a flex the contacts open only to second
  order, so the cluster reaches a distance of order ε^{1/2} along it.
* ``hypostatic``: fewer than 3n - 6 contacts, rigid only at second order: the same.
* ``hyperstatic``: more than 3n - 6 contacts.  The m contact distances are not independent
  coordinates, so the basin is not a product of one factor a contact.

Their partition functions are not κ^m times a geometric factor: they depend on the range of the
potential too (Kallus & Holmes-Cerfon, Phys. Rev. E 95, 022130 (2017)).  For a square well of width ε
and a cluster with one self-stress w (b = 1) and a ≤ 2 flexes this module gives the leading term

    Z = κ^m ε^{a/2 - 1} z_sw,   z_sw = (χ / σ) · sqrt(det I) / ∏_{i=1}^{m-1} λ_i · C_a · J_a

(:attr:`FreeEnergy.square_well`, :attr:`FreeEnergy.eps_power`; for a regular cluster z_sw = z and the
power is 0).  Derivation, with the internal coordinates split into u (orthogonal to the flexes, where
R is injective onto the hyperplane w⊥ of R^m) and t (an orthonormal basis of the a flexes): the contact
gaps are s = R u + ½ tᵀ Q t + ..., with Q_k the second-order term |Δv|² of contact k along the flexes,
so wᵀ s = ½ tᵀ M t with M = Σ_k w_k Q_k, positive definite (pre-stress stability; w unit, its sign
chosen so).  For fixed t, u covers the slice {s ∈ [0, ε]^m : wᵀ s = ½ tᵀ M t} divided by ∏ λ_i;
integrating over t,

    C_a = 2^{a/2} π^{a/2} / (Γ(a/2) sqrt(det M)),   J_a = E[(wᵀ σ)_+^{a/2 - 1}],  σ uniform in [0, 1]^m

(a = 0: C_0 = 1 and J_0 the density of wᵀ σ at 0; a = 2: J_2 = P(wᵀ σ > 0)).  J_a is where the shape
of the well enters: for another potential σ_k has the distribution of the normalised Boltzmann
factor across the well instead of the uniform one.  J_a is computed from the distribution of wᵀ σ,
built on a grid one term at a time (:func:`square_well_moment`).  Clusters with more than one self-stress or more than two
flexes get no value (``square_well`` None); nor do those with J_a = 0 (a stress w that wᵀσ cannot
satisfy the slice's equation with except at one point, e.g. all of one sign with no flex: their leading
term is of a higher order in ε); nor does any cluster for potentials other than the square well.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import orthogonal_procrustes

from packings.workers import kernels
from packings.workers.cluster import Cluster
from packings.workers.identity import symmetries
from packings.workers.params import DEFAULT, Params

__all__ = [
    "FreeEnergy",
    "REGULAR",
    "SINGULAR",
    "HYPOSTATIC",
    "HYPERSTATIC",
    "REASONS",
    "free_energy",
    "flexes_and_stresses",
    "square_well_moment",
    "symmetry_numbers",
    "inertia_tensor",
    "log_frame_constant",
    "equilibrium_shares",
    "shares",
]

REGULAR = "regular"  #: 3n - 6 contacts, first-order rigid: the formula applies
SINGULAR = "singular"
HYPOSTATIC = "hypostatic"
HYPERSTATIC = "hyperstatic"

REASONS = {  #: why z is None, by kind (the column clusters.z_reason holds the kind)
    SINGULAR: "singular: first-order flexible, so Z is not κ^m z: it goes as κ^m ε^(a/2-b) for a flexes and b "
    "self-stresses, with a coefficient that depends on the shape of the potential (Kallus & Holmes-Cerfon 2017)",
    HYPOSTATIC: "hypostatic: fewer than 3n-6 contacts, rigid only at second order, so Z is not κ^m z: it goes as "
    "κ^m ε^(a/2-b) for a flexes and b self-stresses, with a coefficient that depends on the shape of the potential "
    "(Kallus & Holmes-Cerfon 2017)",
    HYPERSTATIC: "hyperstatic: more than 3n-6 contacts, so Z is not κ^m z: it grows as κ^m ε^(-b) for b self-stresses, "
    "with a coefficient that depends on the shape of the potential (Kallus & Holmes-Cerfon 2017)",
}


@dataclass(frozen=True)
class FreeEnergy:
    """The sticky-limit geometric factor of one cluster and its parts (module docstring).

    ``z`` and ``log_z`` are None, and ``reason`` says why, where the formula Z = κ^m z does not apply
    (``kind`` other than ``regular``).  ``log_z = log_vibrational + log_rotational + log_symmetry``
    where it is given.  ``square_well`` is the coefficient of the leading term Z = κ^m ε^eps_power
    square_well of a square well of width ε (equal to z for a regular cluster; None where not
    computed).
    """

    kind: str  #: regular, singular, hypostatic or hyperstatic
    z: float | None
    log_z: float | None
    sigma: int  #: symmetry number: proper rotations among the cluster's symmetries
    chiral: bool  #: no improper symmetry: the mirror image is another configuration, counted in z (χ = 2)
    flexes: int  #: a: first-order flexes (nontrivial null vectors of R)
    stresses: int  #: b: self-stresses (left null vectors of R)
    log_vibrational: float  #: -Σ log λ_i over the nonzero singular values of R
    log_rotational: float  #: ½ log det I
    log_symmetry: float  #: log(χ / σ)
    eps_power: float | None = None  #: a/2 - 1 (b = 1), 0 (regular)
    square_well: float | None = None
    reason: str | None = None

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def inertia_tensor(coords: np.ndarray) -> np.ndarray:
    """The moment of inertia tensor of unit masses at ``coords`` about their centre of mass."""
    x = np.asarray(coords, dtype=np.float64)
    x = x - x.mean(axis=0)
    return np.einsum("ij,ij->", x, x) * np.eye(3) - x.T @ x


def symmetry_numbers(cluster: Cluster, tol_d: float = DEFAULT.tol_d) -> tuple[int, int]:
    """(proper, all): how many orthogonal maps take the cluster onto itself relabelled by one of its
    symmetries (:func:`packings.workers.identity.symmetries`, permutations that are isometries,
    reflections allowed), the proper rotations among them, and all of them.  A permutation t of a
    cluster that spans space is realised by one map, proper or improper by the sign of the determinant
    of the orthogonal matrix that aligns the cluster onto itself relabelled by t.  A cluster that lies
    in a plane (within ``tol_d``: three spheres, or a floppy chain) is its own mirror image through that
    plane, so each t is realised by a proper map and an improper one; the alignment alone would give
    either, as rounding falls."""
    perms = symmetries(cluster, tol_d)
    x = cluster.coords - cluster.coords.mean(axis=0)
    if np.linalg.svd(x, compute_uv=False)[-1] <= tol_d:  # the distance of the spheres from their plane
        return len(perms), 2 * len(perms)
    proper = 0
    for t in perms:
        q, _ = orthogonal_procrustes(x, x[t])
        proper += bool(np.linalg.det(q) > 0.0)
    return proper, len(perms)


def log_frame_constant(n: int) -> float:
    """log(8π² n^{3/2}): the configuration integral of the basin of a cluster of n identical spheres,
    per unit volume, is 8π² n^{3/2} κ^m z in the sticky limit (module docstring)."""
    return math.log(8.0 * math.pi**2) + 1.5 * math.log(n)


def trivial_motions(coords: np.ndarray) -> np.ndarray:
    """An orthonormal basis (3n x 6) of the translations and infinitesimal rotations of ``coords``."""
    x = np.asarray(coords, dtype=np.float64)
    x = x - x.mean(axis=0)
    n = x.shape[0]
    cols = []
    for axis in np.eye(3):
        cols.append(np.tile(axis, n))  # translation
        cols.append(np.cross(axis, x).ravel())  # rotation about the centre of mass
    q, _ = np.linalg.qr(np.array(cols).T)
    return q


def flexes_and_stresses(coords: np.ndarray, contacts, tol_n: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(nonzero singular values of R, an orthonormal basis (3n x a) of its flexes orthogonal to the trivial
    motions, an orthonormal basis (m x b) of its self-stresses), R the rigidity matrix with rows scaled to
    the Jacobian of the contact distances; singular values below ``tol_n`` count as zero."""
    x = np.asarray(coords, dtype=np.float64)
    edges = np.array(contacts, dtype=np.int64).reshape(-1, 2)
    d = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1)
    r = kernels.rigidity_matrix_numpy(x.ravel(), edges) / d[:, None]
    u, sv, vt = np.linalg.svd(r, full_matrices=True)
    rank = int(np.count_nonzero(sv >= tol_n))
    null = vt[rank:].T
    t = trivial_motions(x)
    rest = null - t @ (t.T @ null)
    q, s, _ = np.linalg.svd(rest, full_matrices=False)
    flexes = q[:, : int(np.count_nonzero(s > 0.5))]  # the null space holds the 6 trivial motions: the rest is unit
    return sv[:rank], flexes, u[:, rank:]


def square_well_moment(w: np.ndarray, a: int, points: int = 1 << 15) -> float:
    """J_a of the module docstring for a unit vector w: E[(wᵀσ)_+^{a/2 - 1}] (a = 1), the density of wᵀσ
    at 0 (a = 0) or P(wᵀσ > 0) (a = 2), σ uniform in [0, 1]^m.

    The distribution of h = wᵀσ is built one term at a time, the largest |w_k| first, on a grid of ``points``
    over its range: with F the distribution function of the first terms, adding w_k σ_k gives the density
    (F(x - lo) - F(x - hi)) / |w_k| ([lo, hi] the range of w_k σ_k), integrated again by the trapezoidal
    rule; F is interpolated linearly, so the error is of the order of the squared grid step.  A term
    narrower than a few grid steps would divide that step's rounding by a small |w_k|: it is taken as its
    mean w_k / 2 instead, a shift of h (its spread, w_k² / 12 in variance, is below the grid's
    resolution).  E[h_+^{-1/2}] = 2 ∫_0^∞ p(t²) dt.
    """
    if a not in (0, 1, 2):
        raise ValueError("J_a is computed for a = 0, 1, 2 only")
    w = np.asarray(w, dtype=np.float64)
    w = w[np.argsort(-np.abs(w), kind="stable")]
    narrow = np.abs(w) < 8.0 * float(np.abs(w).sum()) / points
    shift = 0.5 * float(w[narrow].sum())  # h = (the wide terms' sum) + shift
    w = w[~narrow]
    lo_k, hi_k = np.minimum(w, 0.0), np.maximum(w, 0.0)
    lo, hi = float(lo_k.sum()), float(hi_k.sum())
    x = np.linspace(lo, hi, points)
    step = x[1] - x[0]
    cdf = np.clip((x - lo_k[0]) / abs(w[0]), 0.0, 1.0)
    density = np.where((x >= lo_k[0]) & (x <= hi_k[0]), 1.0 / abs(w[0]), 0.0)
    for k in range(1, w.size):
        density = (np.interp(x - lo_k[k], x, cdf, 0.0, 1.0) - np.interp(x - hi_k[k], x, cdf, 0.0, 1.0)) / abs(w[k])
        cdf = np.concatenate([[0.0], np.cumsum(0.5 * (density[1:] + density[:-1]) * step)])
    if a == 0:
        return float(np.interp(-shift, x, density, 0.0, 0.0))
    if a == 2:
        return float(1.0 - np.interp(-shift, x, cdf, 0.0, 1.0))
    if hi + shift <= 0.0:
        return 0.0
    t = np.linspace(0.0, math.sqrt(hi + shift), points)
    f = np.interp(t * t - shift, x, density, 0.0, 0.0)
    return float(2.0 * (t[1] - t[0]) * (f.sum() - 0.5 * (f[0] + f[-1])))


def _square_well_log(flexes: np.ndarray, stresses: np.ndarray, edges: np.ndarray, n: int) -> float | None:
    """log(C_a J_a) of the module docstring (b = 1, a <= 2); None if the stress form is not definite, or
    if J_a = 0: a self-stress whose every nonzero entry has the sign that keeps wᵀσ from the value it must
    take (e.g. all of one sign with no flex), so that the slice of the well is one point and the leading
    term is of a higher order in ε than this module computes."""
    a = flexes.shape[1]
    w = stresses[:, 0]
    if a == 0:
        return _log_positive(square_well_moment(w, 0))
    dv = flexes.reshape(n, 3, a)
    dv = dv[edges[:, 0]] - dv[edges[:, 1]]  # (m, 3, a)
    m_form = np.einsum("k,kxa,kxb->ab", w, dv, dv)
    ev = np.linalg.eigvalsh(m_form)
    if ev[0] < 0:  # the other sign of w, if that makes it definite
        w, m_form, ev = -w, -m_form, -ev[::-1]
    if ev[0] <= 0:
        return None
    log_c = 0.5 * a * math.log(2.0 * math.pi) - math.lgamma(0.5 * a) - 0.5 * float(np.log(ev).sum())
    moment = _log_positive(square_well_moment(w, a))
    return None if moment is None else log_c + moment


def _log_positive(x: float) -> float | None:
    """log x, or None where x is not positive (to the grid's precision: below 1e-12)."""
    return math.log(x) if x > 1e-12 and math.isfinite(x) else None


def free_energy(cluster: Cluster, params: Params = DEFAULT) -> FreeEnergy:
    """The geometric factor z of the sticky-limit partition function Z = κ^m z of a rigid cluster, its
    parts and its symmetry number; z None with the reason where the formula does not apply, and then the
    square well's leading term where the module computes it.

    Singular values below ``params.tol_n`` count as zero (as in the rigidity test); symmetries are
    those of :func:`packings.workers.identity.symmetries` within ``params.tol_d``.
    """
    n, m = cluster.n, cluster.m
    dof = 3 * n - 6
    edges = cluster.edges()
    sv, flexes, stresses = flexes_and_stresses(cluster.coords, cluster.contacts, params.tol_n)
    a, b = flexes.shape[1], stresses.shape[1]
    proper, full = symmetry_numbers(cluster, params.tol_d)
    chiral = proper == full
    log_symmetry = math.log(2.0 if chiral else 1.0) - math.log(proper)
    sign, logdet = np.linalg.slogdet(inertia_tensor(cluster.coords))
    log_rotational = 0.5 * float(logdet) if sign > 0 else -math.inf
    log_vibrational = -float(np.log(sv).sum())
    parts = dict(sigma=proper, chiral=chiral, flexes=a, stresses=b)
    logs = dict(log_vibrational=log_vibrational, log_rotational=log_rotational, log_symmetry=log_symmetry)
    kind = HYPOSTATIC if m < dof else SINGULAR if a > 0 else HYPERSTATIC if m > dof else REGULAR
    if kind == REGULAR:
        log_z = log_vibrational + log_rotational + log_symmetry
        z = math.exp(log_z)
        return FreeEnergy(kind, z, log_z, **parts, **logs, eps_power=0.0, square_well=z)
    coefficient = power = None
    if b == 1 and a <= 2:
        log_sw = _square_well_log(flexes, stresses, edges, n)
        if log_sw is not None:
            coefficient = math.exp(log_vibrational + log_rotational + log_symmetry + log_sw)
            power = 0.5 * a - 1.0
    return FreeEnergy(kind, None, None, **parts, **logs, eps_power=power, square_well=coefficient, reason=REASONS[kind])


def equilibrium_shares(energies: list[FreeEnergy], contacts: list[int], log_kappa: float = 0.0) -> list[float] | None:
    """The equilibrium probability of each cluster among ``energies`` (clusters of one n, with these numbers
    of contacts) at sticky parameter e^{log_kappa}: κ^m z / Σ κ^m z.  None if some z is None (a share
    that leaves out a cluster would look valid and be wrong)."""
    if any(e.log_z is None for e in energies):
        return None
    return shares(np.array([e.log_z for e in energies]), np.array(contacts), log_kappa).tolist()


def shares(log_z: np.ndarray, contacts: np.ndarray, log_kappa, log_eps: float = 0.0, eps_power=0.0) -> np.ndarray:
    """Equilibrium probabilities κ^m ε^p e^{log z} / Σ (the same) of clusters of one n, given their log
    coefficients ``log_z``, contacts m and ε powers p (0: the sticky limit), at each of the sticky parameters
    e^{log_kappa} (a scalar: one row of shares; an array of K: K rows).  Computed in logarithms, so that
    κ^m of m up to 3n is no overflow."""
    log_kappa = np.asarray(log_kappa, dtype=np.float64)
    logs = (
        np.asarray(log_z, dtype=np.float64)
        + np.multiply.outer(log_kappa, np.asarray(contacts, dtype=np.float64))
        + np.asarray(eps_power, dtype=np.float64) * log_eps
    )
    w = np.exp(logs - logs.max(axis=-1, keepdims=True))
    return w / w.sum(axis=-1, keepdims=True)
