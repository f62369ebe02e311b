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
  both enantiomers, each with weight 1/σ, as the papers count them as two states of equal weight.
  With χ the ratios between the clusters of this package are the ratios of their equilibrium
  probabilities.

Normalisation.  Constants common to every cluster of n spheres are dropped: the translational volume
V, the 8π² of the rotation group, the n^{3/2} of fixing the centre of mass and the n! of relabelling
identical spheres.  Exactly: the configuration integral of identical spheres over the cluster's basin
(every configuration with exactly the cluster's contacts in the well, any labelling, both mirror
images), per unit volume, is

    (1 / n!) ∫_basin e^{-βU} dx_1 ... dx_{n-1} (x_0 fixed)  =  8π² n^{3/2} κ^m z (1 + O(ε)),

:func:`log_frame_constant` being log(8π² n^{3/2}); benchmarks/free_energy.py checks this by a direct
Monte Carlo integration that uses none of the formulas.  Probabilities of the clusters of one n at
the same κ are Z_a / Σ_b Z_b (:func:`equilibrium_shares`), which needs only z and m.

Where the formula does not apply the value is None with the reason (:attr:`FreeEnergy.reason`):

* ``singular``: first-order flexible (fewer than 3n - 6 nonzero singular values), held by a
  pre-stress.  The harmonic integral diverges; the partition function grows as κ^m ε^{-a/2} for
  a flexes and its coefficient depends on the shape of the potential (Kallus & Holmes-Cerfon,
  Phys. Rev. E 95, 022130 (2017)).  Not implemented.
* ``hypostatic``: fewer than 3n - 6 contacts, rigid only at second order: the same as singular.
* ``hyperstatic``: more than 3n - 6 contacts.  The m contact distances are not independent
  coordinates: the partition function is not κ^m times a geometric factor but depends on the range
  of the potential too (for a square well, e^{mβu} ε^{3n-6} times the volume of a polytope).  Not
  implemented.
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
    "free_energy",
    "symmetry_numbers",
    "inertia_tensor",
    "contact_singular_values",
    "log_frame_constant",
    "equilibrium_shares",
]

REGULAR = "regular"  #: 3n - 6 contacts, first-order rigid: the formula applies
SINGULAR = "singular"
HYPOSTATIC = "hypostatic"
HYPERSTATIC = "hyperstatic"

_REASONS = {
    SINGULAR: "singular: first-order flexible, so the harmonic integral diverges (Z ~ κ^m ε^(-a/2), whose "
    "coefficient depends on the shape of the potential: Kallus & Holmes-Cerfon 2017; not implemented)",
    HYPOSTATIC: "hypostatic: fewer than 3n-6 contacts, rigid only at second order (Z ~ κ^m ε^(-a/2) as for "
    "singular clusters: Kallus & Holmes-Cerfon 2017; not implemented)",
    HYPERSTATIC: "hyperstatic: more than 3n-6 contacts, so Z is not κ^m times a geometric factor but depends "
    "on the range of the potential as well (Kallus & Holmes-Cerfon 2017; not implemented)",
}


@dataclass(frozen=True)
class FreeEnergy:
    """The sticky-limit geometric factor of one cluster and its parts (module docstring).

    ``z`` and ``log_z`` are None, and ``reason`` says why, where the formula does not apply
    (``kind`` other than ``regular``).  ``log_z = log_vibrational + log_rotational + log_symmetry``
    where they are all given.
    """

    kind: str  #: regular, singular, hypostatic or hyperstatic
    z: float | None
    log_z: float | None
    sigma: int  #: symmetry number: proper rotations among the cluster's symmetries
    chiral: bool  #: no improper symmetry: the mirror image is another configuration, counted in z (χ = 2)
    log_vibrational: float | None  #: -Σ log λ_i over the 3n - 6 nonzero singular values (None if fewer)
    log_rotational: float  #: ½ log det I
    log_symmetry: float  #: log(χ / σ)
    reason: str | None = None

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def inertia_tensor(coords: np.ndarray) -> np.ndarray:
    """The moment of inertia tensor of unit masses at ``coords`` about their centre of mass."""
    x = np.asarray(coords, dtype=np.float64)
    x = x - x.mean(axis=0)
    return np.einsum("ij,ij->", x, x) * np.eye(3) - x.T @ x


def contact_singular_values(coords: np.ndarray, contacts) -> np.ndarray:
    """Singular values (descending) of the rigidity matrix with rows scaled to the Jacobian of the contact
    distances (row k divided by |x_i - x_j|, which is 1 at contact)."""
    x = np.asarray(coords, dtype=np.float64)
    edges = np.array(contacts, dtype=np.int64).reshape(-1, 2)
    if edges.shape[0] == 0:
        return np.zeros(0)
    r = kernels.rigidity_matrix_numpy(x.ravel(), edges)
    d = np.linalg.norm(x[edges[:, 0]] - x[edges[:, 1]], axis=1)
    return np.linalg.svd(r / d[:, None], compute_uv=False)


def symmetry_numbers(cluster: Cluster, tol_d: float = DEFAULT.tol_d) -> tuple[int, int]:
    """(proper, all): how many of the cluster's symmetries (:func:`packings.workers.identity.symmetries`,
    permutations that are isometries, reflections allowed) are realised by a proper rotation, and how
    many there are.  A permutation t is told proper or improper by the sign of the determinant of the
    orthogonal matrix that aligns the cluster onto itself relabelled by t."""
    perms = symmetries(cluster, tol_d)
    x = cluster.coords - cluster.coords.mean(axis=0)
    proper = 0
    for t in perms:
        q, _ = orthogonal_procrustes(x, x[t])
        proper += bool(np.linalg.det(q) > 0.0)
    return proper, len(perms)


def log_frame_constant(n: int) -> float:
    """log(8π² n^{3/2}): the configuration integral of the basin of a cluster of n identical spheres,
    per unit volume, is 8π² n^{3/2} κ^m z in the sticky limit (module docstring)."""
    return math.log(8.0 * math.pi**2) + 1.5 * math.log(n)


def free_energy(cluster: Cluster, params: Params = DEFAULT) -> FreeEnergy:
    """The geometric factor z of the sticky-limit partition function Z = κ^m z of a rigid cluster, its
    parts and its symmetry number; z None with the reason where the formula does not apply.

    Singular values below ``params.tol_n`` count as zero (as in the rigidity test); symmetries are
    those of :func:`packings.workers.identity.symmetries` within ``params.tol_d``.
    """
    n, m = cluster.n, cluster.m
    dof = 3 * n - 6
    sv = contact_singular_values(cluster.coords, cluster.contacts)
    nonzero = sv[sv >= params.tol_n]
    proper, full = symmetry_numbers(cluster, params.tol_d)
    chiral = proper == full
    log_symmetry = math.log(2.0 if chiral else 1.0) - math.log(proper)
    sign, logdet = np.linalg.slogdet(inertia_tensor(cluster.coords))
    log_rotational = 0.5 * float(logdet) if sign > 0 else -math.inf
    log_vibrational = -float(np.log(nonzero).sum()) if nonzero.size >= dof else None
    if m < dof:
        kind = HYPOSTATIC
    elif nonzero.size < dof:
        kind = SINGULAR
    elif m > dof:
        kind = HYPERSTATIC
    else:
        kind = REGULAR
    if kind != REGULAR:
        return FreeEnergy(
            kind, None, None, proper, chiral, log_vibrational, log_rotational, log_symmetry, _REASONS[kind]
        )
    log_z = log_vibrational + log_rotational + log_symmetry
    return FreeEnergy(kind, math.exp(log_z), log_z, proper, chiral, log_vibrational, log_rotational, log_symmetry)


def equilibrium_shares(energies: list[FreeEnergy], contacts: list[int], log_kappa: float = 0.0) -> list[float] | None:
    """The equilibrium probability of each cluster among ``energies`` (clusters of one n, with these numbers
    of contacts) at sticky parameter e^{log_kappa}: κ^m z / Σ κ^m z.  None if some z is None (a share
    that leaves out a cluster would look valid and be wrong)."""
    if any(e.log_z is None for e in energies):
        return None
    logs = np.array([e.log_z + m * log_kappa for e, m in zip(energies, contacts)])
    w = np.exp(logs - logs.max())
    return (w / w.sum()).tolist()
