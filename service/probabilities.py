"""Equilibrium occupation probabilities of the stored clusters of one n: ``packings stats --kappa``,
``packings plot probabilities``, :meth:`packings.service.api.Catalogue.probabilities`.

The probability of cluster a among the clusters of n at sticky parameter κ is Z_a / Σ_b Z_b with the
stored partition functions (docs/method.md, "Free energies in the sticky limit"):

* the sticky limit, Z = κ^m z (``clusters.log_z``): defined only where every cluster of n is regular
  (first-order rigid with 3n − 6 contacts; n ≤ 8), since for the others Z is not κ^m times a number;
* a square well of width ε (``width``), Z = κ^m ε^p z_sw to leading order (``clusters.eps_power``,
  ``clusters.log_z_square_well``): defined where every cluster has that term (one self-stress at most,
  at most two flexes, and a stress that leaves the well more than a point: every cluster of n ≤ 10).

Where some cluster has no value the probabilities are not given, never computed over the others: the
error says how many clusters lack it and why.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np
from sqlalchemy import select
from sqlalchemy.orm import Session

from packings.service.errors import NotFound, UsageError
from packings.service.export import counted, table
from packings.service.models import ClusterRow
from packings.workers.free_energy import shares

#: how many of the most probable clusters ``packings stats --kappa`` lists
MOST_PROBABLE = 5


class UndefinedProbabilities(UsageError):
    """The probabilities of the clusters of n are not defined by what is stored (the message, one line, says why)."""


@dataclass(frozen=True)
class Weights:
    """The clusters of one n and their partition functions' terms: Z_a = κ^m_a ε^power_a e^log_a."""

    n: int
    width: float | None  #: None: the sticky limit (every power 0); else a square well of this width
    ids: np.ndarray
    contacts: np.ndarray
    singular: np.ndarray  #: bool: first-order flexible, held by a pre-stress
    log: np.ndarray
    power: np.ndarray

    def at(self, kappa) -> np.ndarray:
        """Each cluster's probability at κ = ``kappa`` (a scalar: one row; an array of K: K rows)."""
        log_eps = 0.0 if self.width is None else math.log(self.width)
        return shares(self.log, self.contacts, np.log(kappa), log_eps, self.power)


def weights(s: Session, n: int, width: float | None = None) -> Weights:
    """The terms of every stored cluster of n: the sticky limit if ``width`` is None, else a square well of
    that width; :class:`UndefinedProbabilities` if some cluster has none (or none is stored)."""
    if width is not None and not (0.0 < width < 1.0):
        raise UsageError(f"the well's width must be between 0 and 1 sphere diameter, not {width:g}")
    rows = s.execute(
        select(
            ClusterRow.id,
            ClusterRow.contacts,
            ClusterRow.singular,
            ClusterRow.sigma,
            ClusterRow.log_z,
            ClusterRow.z_reason,
            ClusterRow.eps_power,
            ClusterRow.log_z_square_well,
        )
        .where(ClusterRow.n == n)
        .order_by(ClusterRow.id)
    ).all()
    if not rows:
        raise NotFound(f"no clusters with n = {n} in the database")
    unknown = sum(1 for r in rows if r.sigma is None)
    if unknown:
        raise UndefinedProbabilities(
            f"n = {n}: {counted(unknown, 'cluster')} stored by an older version "
            f"{'has' if unknown == 1 else 'have'} no partition function yet: run `packings db backfill`"
        )
    if width is None:
        _refuse(
            n,
            [r for r in rows if r.log_z is None],
            "Z is not κ^m z for {them}, so the sticky limit gives no "
            "probabilities; give the width of a square well (--width)",
        )
        log, power = [r.log_z for r in rows], [0.0] * len(rows)
    else:
        _refuse(
            n,
            [r for r in rows if r.log_z_square_well is None],
            "no square well's leading term is computed for {them} (more than one self-stress, more than two "
            "flexes, or a stress that leaves the well a single point), so no probabilities are given",
        )
        log, power = [r.log_z_square_well for r in rows], [r.eps_power for r in rows]
    return Weights(
        n,
        width,
        np.array([r.id for r in rows]),
        np.array([r.contacts for r in rows]),
        np.array([bool(r.singular) for r in rows]),
        np.array(log, dtype=np.float64),
        np.array(power, dtype=np.float64),
    )


def _refuse(n: int, missing: list, why: str) -> None:
    """:class:`UndefinedProbabilities` naming how many clusters of n lack a value, by kind, and ``why``
    (``{them}``: it or them), if any does."""
    if missing:
        kinds = Counter(r.z_reason for r in missing)
        said = ", ".join(counted(k, f"{reason} cluster") for reason, k in sorted(kinds.items()))
        raise UndefinedProbabilities(f"n = {n}: {said}: " + why.format(them="it" if len(missing) == 1 else "them"))


def probabilities(s: Session, n: int, kappa: float, width: float | None = None) -> dict:
    """Each cluster's and each number of contacts' equilibrium probability among the stored clusters of n at
    sticky parameter ``kappa`` (and a square well of ``width``, or the sticky limit): a JSON-ready dict."""
    if not (kappa > 0.0 and math.isfinite(kappa)):
        raise UsageError(f"the sticky parameter κ must be a positive number, not {kappa:g}")
    w = weights(s, n, width)
    p = w.at(kappa)
    order = np.argsort(-p, kind="stable")
    by_contacts: dict[str, float] = {}
    for m in sorted(set(w.contacts.tolist())):
        by_contacts[str(m)] = float(p[w.contacts == m].sum())
    return {
        "n": n,
        "kappa": kappa,
        "width": width,
        "by_contacts": by_contacts,
        "clusters": [{"id": int(w.ids[i]), "contacts": int(w.contacts[i]), "probability": float(p[i])} for i in order],
    }


def format_probabilities(d: dict, most: int = MOST_PROBABLE) -> str:
    """``packings stats --kappa``'s text: by number of contacts, and the most probable clusters."""
    where = "the sticky limit" if d["width"] is None else f"a square well of width {d['width']:g}"
    head = f"equilibrium probabilities at κ = {d['kappa']:g} ({where}):"
    counts = Counter(c["contacts"] for c in d["clusters"])
    rows = [[m, counts[int(m)], f"{p:.4g}"] for m, p in d["by_contacts"].items()]
    top = [[c["id"], c["contacts"], f"{c['probability']:.4g}"] for c in d["clusters"][:most]]
    return "\n".join(
        [
            head,
            table(["contacts", "clusters", "probability"], rows),
            f"the {min(most, len(d['clusters']))} most probable:",
            table(["id", "contacts", "probability"], top),
        ]
    )


def curves(s: Session, n: int, kappas, width: float | None = None) -> dict:
    """What ``packings plot probabilities`` draws: at each of ``kappas``, the probability of each number of
    contacts ({m: array}) and of the singular clusters together (an array, None if n has none)."""
    w = weights(s, n, width)
    p = w.at(np.asarray(kappas, dtype=np.float64))
    return {
        "by_contacts": {int(m): p[:, w.contacts == m].sum(axis=1) for m in sorted(set(w.contacts.tolist()))},
        "singular": p[:, w.singular].sum(axis=1) if w.singular.any() else None,
    }
