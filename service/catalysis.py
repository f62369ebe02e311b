"""Catalysis in the database: clusters of n spheres found by deleting spheres from the stored clusters of n + k.

:func:`catalyse` reads every stored cluster of n + k spheres (of any run), keeps the rigid remainders
after deleting each set of k spheres (:mod:`packings.workers.catalysis`, the endpoint rule of the enumeration),
and stores those not yet in the catalogue with ``found_by = 'catalysis'`` and ``source_id`` = the
parent, in the run of n with the given parameters (found, or created and seeded as ``packings
enumerate`` would), each with a pending expansion in that run: ``packings enumerate n`` afterwards
expands them, so that everything reachable from them by paths is found too.  A remainder already
stored by another run of n gets an expansion in this run as well, as the write-back does for a path's
endpoint.  A run that was complete and gets expansions is marked running again (the coordinator
expands the pending expansions of any run it resumes, complete or not).

Writes are batched: one transaction per batch of parents, taking the certificate locks
(:func:`packings.store.lock_certificates`) as a write-back does, so catalysis may run while the run is
being enumerated, and an interrupted catalysis keeps what it committed (running it again finds those
stored: it is idempotent).
"""

from __future__ import annotations

import uuid
from dataclasses import asdict, dataclass, field
from typing import Callable

from sqlalchemy import func, select, update
from sqlalchemy.orm import sessionmaker

from packings import store
from packings.owners import process_name
from packings.models import FOUND_CATALYSIS, RUNNING, ClusterRow, Run, core_cluster
from packings.workers.catalysis import remainder_count, rigid_remainders
from packings.workers.identity import certificate_key
from packings.workers.params import Params

BATCH = 200  #: parents per transaction


class NoParents(Exception):
    """No clusters of n + k spheres are stored."""


@dataclass(frozen=True)
class Found:
    """A cluster catalysis stored: its id, the parent's id and the parent's spheres deleted."""

    id: int
    parent_id: int
    deleted: tuple[int, ...]
    contacts: int
    lattice: str


@dataclass
class CatalysisReport:
    """What :func:`catalyse` did: parents read, remainders tested (every deleted set of every parent),
    rigid remainders (by the endpoint rule), rigid remainders already stored, and the new clusters."""

    n: int
    spheres: int
    run_id: int
    parents: int = 0
    remainders: int = 0
    rigid: int = 0
    already_stored: int = 0
    new: list[Found] = field(default_factory=list)
    expansions_added: int = 0
    run_reopened: bool = False

    def to_dict(self) -> dict:
        return asdict(self)


def count_stored(Session_: sessionmaker, n: int) -> int:
    with Session_() as s:
        return s.execute(select(func.count()).select_from(ClusterRow).where(ClusterRow.n == n)).scalar_one()


def run_for(Session_: sessionmaker, n: int, params: Params) -> int:
    """The id of the run of (n, params): the stored one, or a new one created and seeded by
    :func:`packings.store.start_run` (as ``packings enumerate`` would) and let go at once."""
    pj = params.to_json()
    with Session_() as s:
        run_id = s.execute(select(Run.id).where(Run.n == n, Run.params == pj)).scalar_one_or_none()
    if run_id is not None:
        return run_id
    owner = f"{process_name()}:catalysis-{uuid.uuid4().hex[:8]}"
    info = store.start_run(Session_, n, params, owner)
    with Session_.begin() as s:
        s.execute(update(Run).where(Run.id == info.id, Run.coordinator == owner).values(coordinator=None))
    return info.id


def catalyse(Session_: sessionmaker, n: int, params: Params, spheres: int = 1, batch: int = BATCH,
             on_progress: Callable[[int, int], None] | None = None) -> CatalysisReport:
    """Delete ``spheres`` spheres from every stored cluster of n + ``spheres`` and store the new rigid
    remainders in the run of (n, params) (module doc).  ``on_progress(parents done, parents)`` after
    each batch.  Raises :class:`NoParents` when no cluster of n + spheres is stored."""
    total = count_stored(Session_, n + spheres)
    if total == 0:
        raise NoParents(f"no clusters of {n + spheres} spheres stored: run `packings enumerate {n + spheres}` first")
    run_id = run_for(Session_, n, params)
    report = CatalysisReport(n, spheres, run_id)
    last = 0
    while True:
        with Session_() as s:
            rows = s.execute(select(ClusterRow.id, ClusterRow.coords, ClusterRow.contact_list)
                             .where(ClusterRow.n == n + spheres, ClusterRow.id > last).order_by(ClusterRow.id).limit(batch)).all()
        if not rows:
            break
        last = rows[-1].id
        found = []
        for pid, coords, contact_list in rows:
            parent = core_cluster(n + spheres, coords, contact_list)
            report.parents += 1
            report.remainders += remainder_count(parent.n, spheres)
            for r in rigid_remainders(parent, spheres, params):
                found.append((pid, r, certificate_key(r.cluster)))
        report.rigid += len(found)
        if found:
            _store(Session_, n, run_id, params, found, report)
        if on_progress is not None:
            on_progress(report.parents, total)
    return report


def _store(Session_: sessionmaker, n: int, run_id: int, params: Params, found, report: CatalysisReport) -> None:
    """One transaction: the rigid remainders ``found`` ((parent id, Remainder, certificate)) inserted or
    matched, expansions for those new to the run, the run reopened if it was not running."""
    with Session_.kw["bind"].begin() as s:
        keys = {(n, cert) for _, _, cert in found}
        store.lock_certificates(s, keys)
        stored = store.stored_with(s, n, {cert for _, cert in keys})
        inserted, others = [], []
        for pid, r, cert in found:
            rows = stored[cert]
            cid, is_new = store.insert_or_match(s, r.cluster, r.rigidity, run_id, params.tol_d, rows,
                                                found_by=FOUND_CATALYSIS, source_id=pid)
            if is_new:
                inserted.append(cid)
                report.new.append(Found(cid, pid, r.deleted, r.cluster.m, store.lattice_value(r.cluster)))
            else:
                report.already_stored += 1
                if next(x.found_in_run for x in rows if x.id == cid) != run_id:
                    others.append(cid)
        added = store.ensure_expansions(s, run_id, others, new=inserted) if (inserted or others) else 0
        report.expansions_added += added
        if added:
            reopened = s.execute(update(Run).where(Run.id == run_id, Run.status != RUNNING).values(status=RUNNING))
            report.run_reopened |= reopened.rowcount > 0


def format_report(r: CatalysisReport) -> str:
    """The report as a few lines of text."""
    lines = [f"catalysis of n = {r.n} from n = {r.n + r.spheres} (deleting {r.spheres} sphere"
             f"{'s' if r.spheres != 1 else ''}), run {r.run_id}:",
             f"  parents {r.parents}, remainders tested {r.remainders}, rigid {r.rigid}, "
             f"already stored {r.already_stored}, new {len(r.new)}"]
    for f in r.new:
        lines.append(f"  new cluster {f.id}: {f.contacts} contacts, lattice {f.lattice}, "
                     f"from cluster {f.parent_id} without sphere{'s' if len(f.deleted) > 1 else ''} "
                     + ", ".join(map(str, f.deleted)))
    if r.expansions_added:
        lines.append(f"  {r.expansions_added} expansion{'s' if r.expansions_added != 1 else ''} added to run "
                     f"{r.run_id}" + (" (marked running again)" if r.run_reopened else ""))
    return "\n".join(lines)
