"""Auditing a catalogue for junk clusters: ``packings audit``.

A stored cluster whose smallest non-contact gap is a few ``tol_a``, or whose
pre-stress margin is within a few times its threshold, may be a "near copy": a
stored cluster with a near contact left out (docs/method.md).
:func:`audit` lists, per n:

(a) every cluster with a non-contact pair within ``tol_a0`` of touching, and what
    adding the pair gives (each pair alone, then all of a cluster's near pairs
    together: :func:`packings.workers.audit.what_adding_gives`): its status and, when it is
    rigid, the stored cluster it is (certificate, then geometry within ``tol_d``)
    or none;
(b) every cluster decided by the pre-stress test whose margin is below
    ``PRESTRESS_FACTOR`` x ``tol_psd``;
(c) every two stored clusters of one contact graph whose geometries differ by less
    than ``CLOSE_FACTOR`` x ``tol_d`` (:func:`packings.workers.identity.geometry_distance`);
(d) exact clusters: every cluster with no flex for which Kantorovich's theorem
    does not prove a root of its contact equations nearby whose other pairs do not
    touch (:func:`packings.workers.exact.exact_cluster`; with more than 3n - 6
    contacts, of 3n - 6 independent ones), and every two clusters of one contact
    graph whose roots it cannot prove different, with a summary per n (how many
    proved, how close, the smallest exact gap).

A clean catalogue has (a), (c) and (d)'s two lists empty.  Genuine clusters can have small gaps
too (at n = 13 down to about 6e-5), which is why (a) says what adding the pair
gives: a near copy is a cluster whose near pair, added, gives a stored cluster.
The tolerances are those of the first run of each n (else ``Params()``).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field

from sqlalchemy import func, or_, select
from sqlalchemy.orm import Session

from packings.service.export import table
from packings.service.models import ClusterRow, Run, core_cluster
from packings.service.store import stored_with
from packings.workers.audit import RIGID, near_pairs, what_adding_gives
from packings.workers.exact import exact_cluster, not_told_apart
from packings.workers.identity import certificate_key, find_match, geometry_distance
from packings.workers.params import Params
from packings.workers.rigidity import PRESTRESS

PRESTRESS_FACTOR = 10.0  #: list (b): pre-stress margins below this many tol_psd
CLOSE_FACTOR = 100.0  #: list (c): geometries of one contact graph closer than this many tol_d


@dataclass(frozen=True)
class NearRow:
    """List (a): what adding ``pairs`` to stored cluster ``id`` gives."""

    id: int
    n: int
    contacts: int
    pairs: list[list[int]]  #: one near pair, or all of the cluster's near pairs together
    gap: float  #: the smallest gap among ``pairs`` (distance - 1)
    status: str  #: packings.workers.audit: rigid, not-rigid, does-not-project, overlap
    new_contacts: int | None  #: contacts of the projected cluster (None if it did not project)
    moved: float | None  #: largest coordinate change after alignment (None if it did not project)
    match: int | None  #: id of the stored cluster it is (rigid only; None: not stored)


@dataclass(frozen=True)
class PrestressRow:
    """List (b): a cluster decided by the pre-stress test with a small margin."""

    id: int
    n: int
    contacts: int
    method: str
    margin: float | None
    tol_psd: float
    min_gap: float | None


@dataclass(frozen=True)
class CloseRow:
    """List (c): two stored clusters of one contact graph with close geometries (``b`` stored later)."""

    n: int
    certificate: str
    a: int
    b: int
    distance: float  #: geometry_distance(b, a): b aligned onto a, as the store compared it with a
    tol_d: float


@dataclass(frozen=True)
class ExactSummary:
    """List (d)'s summary for one n: the clusters with no flex and what was proved of them."""

    clusters: int  #: clusters with no flex (first-order rigid)
    proved: int
    max_radius: float | None  #: the largest distance within which a root was proved to lie
    min_gap: float | None  #: the smallest lower bound of a proved root's non-contact gap
    max_others: float | None  #: with more than 3n - 6 contacts, the largest bound on |f| of the others at the root
    pairs: int  #: pairs of proved clusters of one contact graph compared (all told apart unless listed)


@dataclass(frozen=True)
class UnprovedRow:
    """List (d): a cluster with no flex whose root was not proved (packings.workers.exact statuses)."""

    id: int
    n: int
    contacts: int
    status: str
    h: float | None
    gap: float | None


@dataclass(frozen=True)
class UnseparatedRow:
    """List (d): two proved clusters of one contact graph whose roots may be the same cluster."""

    n: int
    certificate: str
    a: int
    b: int
    bound: float  #: lower bound of their distance (Frobenius, best alignment and automorphism)
    radii: float  #: the two radii within which their roots lie, summed


@dataclass
class AuditReport:
    """The four lists of :func:`audit`, and the tolerances used for each n."""

    tolerances: dict[int, dict[str, float]] = field(default_factory=dict)  #: n -> tol_a0, tol_psd, tol_d
    near: list[NearRow] = field(default_factory=list)
    prestress: list[PrestressRow] = field(default_factory=list)
    close: list[CloseRow] = field(default_factory=list)
    exact: dict[int, ExactSummary] = field(default_factory=dict)
    unproved: list[UnprovedRow] = field(default_factory=list)
    unseparated: list[UnseparatedRow] = field(default_factory=list)

    @property
    def near_clusters(self) -> list[int]:
        """Ids of the clusters in list (a)."""
        return sorted({r.id for r in self.near})

    @property
    def near_copies(self) -> dict[int, list[int]]:
        """{id: stored clusters that adding one or more of its near pairs gives}, for list (a)."""
        out: dict[int, set[int]] = {}
        for r in self.near:
            if r.match is not None:
                out.setdefault(r.id, set()).add(r.match)
        return {k: sorted(v) for k, v in sorted(out.items())}

    @property
    def clean(self) -> bool:
        """No near pair, no close geometries, every cluster with no flex proved and every two proved ones of
        one contact graph told apart (lists (a), (c) and (d) empty)."""
        return not self.near and not self.close and not self.unproved and not self.unseparated

    def to_dict(self) -> dict:
        return {
            "tolerances": {str(n): t for n, t in self.tolerances.items()},
            "near": [asdict(r) for r in self.near],
            "prestress": [asdict(r) for r in self.prestress],
            "close": [asdict(r) for r in self.close],
            "exact": {str(n): asdict(e) for n, e in self.exact.items()},
            "unproved": [asdict(r) for r in self.unproved],
            "unseparated": [asdict(r) for r in self.unseparated],
            "near_copies": {str(k): v for k, v in self.near_copies.items()},
            "clean": self.clean,
        }


def run_params(s: Session, n: int) -> Params:
    """The parameters of the first run of n (lowest id), else the defaults: the tolerances that decided
    what was stored."""
    text = s.execute(select(Run.params).where(Run.n == n).order_by(Run.id).limit(1)).scalar_one_or_none()
    return Params() if text is None else Params.from_dict(json.loads(text))


def audit(s: Session, n: int | None = None) -> AuditReport:
    """The audit of every n in the database (or only ``n``), smallest n first."""
    q = select(ClusterRow.n).distinct().order_by(ClusterRow.n)
    ns = s.execute(q if n is None else q.where(ClusterRow.n == n)).scalars().all()
    report = AuditReport()
    for k in ns:
        params = run_params(s, k)
        report.tolerances[k] = {"tol_a0": params.tol_a0, "tol_psd": params.tol_psd, "tol_d": params.tol_d}
        report.near += near_rows(s, k, params)
        report.prestress += prestress_rows(s, k, params)
        report.close += close_rows(s, k, params)
        report.exact[k], unproved, unseparated = exact_rows(s, k, params)
        report.unproved += unproved
        report.unseparated += unseparated
    return report


def near_rows(s: Session, n: int, params: Params) -> list[NearRow]:
    """List (a) for n: the clusters with a non-contact pair within tol_a0 of touching (those whose stored
    min_gap says so, or is not computed yet), each near pair alone and all together."""
    q = (
        select(ClusterRow.id, ClusterRow.contacts, ClusterRow.coords, ClusterRow.contact_list)
        .where(ClusterRow.n == n, or_(ClusterRow.min_gap < params.tol_a0, ClusterRow.min_gap.is_(None)))
        .order_by(ClusterRow.id)
    )
    rows = []
    for id_, m, coords, contact_list in s.execute(q).all():
        c = core_cluster(n, coords, contact_list)
        near = near_pairs(c, params.tol_a0)
        gaps = {p.pair: p.gap for p in near}
        for added in what_adding_gives(c, near, params):
            match = _stored_as(s, added.cluster, params) if added.status == RIGID else None
            rows.append(
                NearRow(
                    id=id_,
                    n=n,
                    contacts=m,
                    pairs=[list(p) for p in added.pairs],
                    gap=min(gaps[p] for p in added.pairs),
                    status=added.status,
                    new_contacts=None if added.cluster is None else added.cluster.m,
                    moved=added.moved,
                    match=match,
                )
            )
    return rows


def _stored_as(s: Session, c, params: Params) -> int | None:
    """The id of the stored cluster that ``c`` is (same certificate, same geometry within tol_d), else None."""
    cert = certificate_key(c)
    stored = stored_with(s, c.n, [cert])[cert]
    k = find_match(c, [r.cluster for r in stored], params.tol_d)
    return None if k is None else stored[k].id


def prestress_rows(s: Session, n: int, params: Params) -> list[PrestressRow]:
    """List (b) for n: clusters decided by the pre-stress test with margin below PRESTRESS_FACTOR tol_psd."""
    q = (
        select(ClusterRow.id, ClusterRow.contacts, ClusterRow.rigid_method, ClusterRow.margin, ClusterRow.min_gap)
        .where(
            ClusterRow.n == n,
            ClusterRow.rigid_kind == PRESTRESS,
            or_(ClusterRow.margin < PRESTRESS_FACTOR * params.tol_psd, ClusterRow.margin.is_(None)),
        )
        .order_by(ClusterRow.margin, ClusterRow.id)
    )
    return [
        PrestressRow(id_, n, m, method, margin, params.tol_psd, gap) for id_, m, method, margin, gap in s.execute(q)
    ]


def close_rows(s: Session, n: int, params: Params) -> list[CloseRow]:
    """List (c) for n: every two stored clusters of one contact graph whose geometry_distance (the later
    stored aligned onto the earlier) is below CLOSE_FACTOR tol_d."""
    certs = (
        s.execute(
            select(ClusterRow.certificate)
            .where(ClusterRow.n == n)
            .group_by(ClusterRow.certificate)
            .having(func.count() > 1)
            .order_by(ClusterRow.certificate)
        )
        .scalars()
        .all()
    )
    rows = []
    for cert, stored in stored_with(s, n, certs).items():
        stored = sorted(stored, key=lambda r: r.id)
        for j, b in enumerate(stored):
            for a in stored[:j]:
                d = geometry_distance(b.cluster, a.cluster)
                if d < CLOSE_FACTOR * params.tol_d:
                    rows.append(CloseRow(n, cert, a.id, b.id, d, params.tol_d))
    return rows


def exact_rows(s: Session, n: int, params: Params) -> tuple[ExactSummary, list[UnprovedRow], list[UnseparatedRow]]:
    """List (d) for n: Kantorovich's theorem on every cluster with no flex, then every two proved clusters
    of one contact graph compared."""
    q = (
        select(ClusterRow.id, ClusterRow.certificate, ClusterRow.coords, ClusterRow.contact_list)
        .where(ClusterRow.n == n, ClusterRow.flexes == 0)
        .order_by(ClusterRow.id)
    )
    by_cert: dict[str, list] = {}
    unproved = []
    for id_, cert, coords, contact_list in s.execute(q).all():
        c = core_cluster(n, coords, contact_list)
        e = exact_cluster(c, params)
        if not e.proved:
            unproved.append(UnprovedRow(id_, n, c.m, e.status, e.h, e.gap))
        by_cert.setdefault(cert, []).append((id_, c, e))
    proved = [e for group in by_cert.values() for _, _, e in group if e.proved]
    unseparated, pairs = [], 0
    for cert, group in by_cert.items():
        if len(group) < 2:
            continue
        k = sum(e.proved for _, _, e in group)
        pairs += k * (k - 1) // 2
        for i, j, bound in not_told_apart([c for _, c, _ in group], [e for _, _, e in group]):
            unseparated.append(
                UnseparatedRow(n, cert, group[i][0], group[j][0], bound, group[i][2].radius + group[j][2].radius)
            )
    summary = ExactSummary(
        clusters=sum(len(g) for g in by_cert.values()),
        proved=len(proved),
        max_radius=max((e.radius for e in proved), default=None),
        min_gap=min((e.gap for e in proved if e.gap is not None), default=None),
        max_others=max((e.others for e in proved), default=None),
        pairs=pairs,
    )
    return summary, unproved, unseparated


# --------------------------------------------------------------------------- text


def _g(x: float | None) -> str | None:
    return None if x is None else f"{x:.3g}"


def format_audit(r: AuditReport) -> str:
    """Three sections, each a count line and a table, then "clean" or what is not."""
    out = []
    tol = ", ".join(
        f"n = {n}: tol_a0 {t['tol_a0']:g}, tol_psd {t['tol_psd']:g}, tol_d {t['tol_d']:g}"
        for n, t in r.tolerances.items()
    )
    ns = len(r.tolerances)
    out.append(f"audit of {ns} value{'s' if ns != 1 else ''} of n ({tol})" if ns else "audit: no clusters")
    out += _near_section(r) + _prestress_section(r) + _close_section(r) + _exact_section(r)
    out.append("\n" + verdict(r))
    return "\n".join(out)


def _near_section(r: AuditReport) -> list[str]:
    """The near pairs: a count line, and a table of what adding each pair gives."""
    out = []
    near_ids = r.near_clusters
    out.append(
        f"\nnear pairs (gap < tol_a0): {len(near_ids)} cluster{'s' if len(near_ids) != 1 else ''}, "
        f"{len(r.near)} addition{'s' if len(r.near) != 1 else ''}"
    )
    if r.near:
        out.append(
            table(
                ["id", "n", "contacts", "pairs", "gap", "adding gives", "contacts'", "moved", "stored as"],
                [
                    [
                        x.id,
                        x.n,
                        x.contacts,
                        " ".join(f"{i}-{j}" for i, j in x.pairs),
                        _g(x.gap),
                        x.status,
                        x.new_contacts,
                        _g(x.moved),
                        x.match if x.match is not None else ("not stored" if x.status == RIGID else "-"),
                    ]
                    for x in r.near
                ],
            )
        )
    return out


def _prestress_section(r: AuditReport) -> list[str]:
    """The small pre-stress margins: a count line and a table."""
    out = []
    out.append(
        f"\npre-stress margins (< {PRESTRESS_FACTOR:g} tol_psd): {len(r.prestress)} "
        f"cluster{'s' if len(r.prestress) != 1 else ''}"
    )
    if r.prestress:
        out.append(
            table(
                ["id", "n", "contacts", "method", "margin", "/ tol_psd", "min_gap"],
                [
                    [
                        x.id,
                        x.n,
                        x.contacts,
                        x.method,
                        _g(x.margin),
                        None if x.margin is None else f"{x.margin / x.tol_psd:.3g}",
                        _g(x.min_gap),
                    ]
                    for x in r.prestress
                ],
            )
        )
    return out


def _close_section(r: AuditReport) -> list[str]:
    """The close geometries of one contact graph: a count line and a table."""
    out = []
    out.append(
        f"\nclose geometries of one contact graph (< {CLOSE_FACTOR:g} tol_d): {len(r.close)} "
        f"pair{'s' if len(r.close) != 1 else ''}"
    )
    if r.close:
        out.append(
            table(
                ["n", "a", "b", "distance", "/ tol_d", "certificate"],
                [
                    [
                        x.n,
                        x.a,
                        x.b,
                        _g(x.distance),
                        f"{x.distance / x.tol_d:.3g}",
                        x.certificate if len(x.certificate) <= 16 else x.certificate[:13] + "...",
                    ]
                    for x in r.close
                ],
            )
        )
    return out


def _exact_section(r: AuditReport) -> list[str]:
    """The exact clusters: a line per n of what is proved, the unproved roots and the pairs not told apart."""
    out = []
    out.append(
        "\nexact clusters (Kantorovich; clusters with no flex): "
        + "; ".join(
            f"n = {n}: {e.proved} of {e.clusters} proved"
            + (
                f" within {e.max_radius:.2g}"
                + (f", exact gaps >= {e.min_gap:.3g}" if e.min_gap is not None else "")
                + (f", other contacts' |f| <= {e.max_others:.2g}" if e.max_others else "")
                + f", {e.pairs} pair{'s' if e.pairs != 1 else ''} of one contact graph compared"
                if e.proved
                else ""
            )
            for n, e in r.exact.items()
        )
    )
    if r.unproved:
        out.append(
            table(
                ["id", "n", "contacts", "status", "h", "gap"],
                [[x.id, x.n, x.contacts, x.status, _g(x.h), _g(x.gap)] for x in r.unproved],
            )
        )
    if r.unseparated:
        out.append(
            table(
                ["n", "a", "b", "distance >=", "radii", "certificate"],
                [
                    [
                        x.n,
                        x.a,
                        x.b,
                        _g(x.bound),
                        _g(x.radii),
                        x.certificate if len(x.certificate) <= 16 else x.certificate[:13] + "...",
                    ]
                    for x in r.unseparated
                ],
            )
        )
    return out


def verdict(r: AuditReport) -> str:
    """ "clean", or what is not: the clusters with near pairs (and which of them are near copies of which
    stored cluster) and the pairs of close geometries."""
    if r.clean:
        return "clean" + (
            f" ({len(r.prestress)} small pre-stress margin{'s' if len(r.prestress) != 1 else ''})"
            if r.prestress
            else ""
        )
    parts = []
    if r.near:
        copies = r.near_copies
        k = len(r.near_clusters)
        parts.append(
            f"{k} cluster{'s' if k != 1 else ''} with a near pair, {len(copies)} of them near copies of "
            "stored clusters"
            + (": " + ", ".join(f"{i} -> {'/'.join(map(str, v))}" for i, v in copies.items()) if copies else "")
        )
    if r.close:
        parts.append(f"{len(r.close)} pair{'s' if len(r.close) != 1 else ''} of close geometries")
    if r.unproved:
        parts.append(f"{len(r.unproved)} cluster{'s' if len(r.unproved) != 1 else ''} with no flex and no root proved")
    if r.unseparated:
        parts.append(f"{len(r.unseparated)} pair{'s' if len(r.unseparated) != 1 else ''} of roots not told apart")
    return "not clean: " + "; ".join(parts)
