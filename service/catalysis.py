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

With ``glued``, the parents are made, not read: :func:`packings.workers.catalysis.moved_remainders`
moves each sphere of every stored cluster of n onto each of its contact triangles, so that no run of
n + 1 is needed; a remainder whose contact graph and pair distances are those of a stored cluster,
or of one decided earlier in the pass, is not decided again.

The parents are decided in this process, or (the command line) by Dask tasks, a batch of parents each
(:func:`catalysis_task`), on a local cluster or an existing one, on the Dask driver the expansions of
``packings enumerate`` run on (:class:`packings.service.driver.Driver`; here :class:`_Pass`): a task
carries the parents' ids, reads them with its worker's engine and stores what it found, as an
expansion's task writes its results back; the caller adds up what the tasks report.  A batch is
idempotent, so nothing is leased: one lost with its worker (or its scheduler) is sent again, one whose
task raised is tried again up to ``max_attempts`` times in all, then the pass stops in one line
(:class:`packings.service.errors.PassFailed`); a cluster left without workers stops it too
(:class:`packings.service.errors.SchedulerError`).

With ``close_packed`` (:func:`close_packed_pass`), there are no parents: every close-packed fragment
of n spheres with at least that many contacts (:func:`packings.workers.fragments.close_packed`) is
decided as a remainder is, and the rigid ones not yet stored are stored with ``found_by =
'close-packed'`` and no source.  The fragments are listed and decided in this process.

Writes are batched: one transaction per batch of parents, taking the certificate locks
(:func:`packings.service.store.lock_certificates`) as a write-back does, so catalysis may run while the run is
being enumerated, and an interrupted catalysis keeps what it committed (running it again finds those
stored: it is idempotent).
"""

from __future__ import annotations

import json
import logging
import threading
import uuid
from collections import Counter, deque
from dataclasses import asdict, dataclass, field
from itertools import islice
from typing import TYPE_CHECKING, Callable

import numpy as np
from sqlalchemy import func, select, update
from sqlalchemy.orm import sessionmaker

from packings.service import store
from packings.service.driver import Driver
from packings.service.errors import PassFailed
from packings.service.models import (
    FOUND_CATALYSIS,
    FOUND_CLOSE_PACKED,
    PASS_DELETED,
    PASS_GLUED,
    RUNNING,
    CatalysisPass,
    ClusterRow,
    Run,
    core_cluster,
)
from packings.service.owners import process_name, utcnow
from packings.workers.cluster import Cluster
from packings.workers.fragments import close_packed
from packings.workers.identity import certificate_key
from packings.workers.params import Params
from packings.workers.rigidity import Rigidity

if TYPE_CHECKING:
    from packings.workers.catalysis import Seen

# packings.workers.catalysis (the endpoint rule, and with it the path-following code and numba's compiled
# kernels) is imported by the functions that decide remainders: a coordinator whose workers decide them
# never loads it.  Dask is imported when a pass on Dask starts (its driver, :mod:`packings.service.driver`) or its
# task runs: a pass decided in this process (`packings catalyse --close-packed`, :func:`catalyse` without a
# client) needs none of it.

log = logging.getLogger(__name__)

BATCH = 200  #: parents per transaction
#: a parent as a pass reads it (:class:`_Rows`, :func:`rows_of`): id, coordinates, contact list
PARENT_COLUMNS = (ClusterRow.id, ClusterRow.coords, ClusterRow.contact_list)


class NoParents(Exception):
    """No clusters of n + k spheres are stored."""


@dataclass(frozen=True)
class Found:
    """A cluster catalysis stored: its id, the parent's id and the parent's spheres deleted (with
    ``glued``: the parent is the stored cluster of n, and its sphere ``deleted`` was moved onto the
    contact triangle ``moved_onto``; a close-packed fragment has no parent: None and ())."""

    id: int
    parent_id: int | None
    deleted: tuple[int, ...]
    contacts: int
    lattice: str
    moved_onto: tuple[int, int, int] | None = None


@dataclass
class CatalysisReport:
    """What :func:`catalyse` did: parents read, remainders tested (every deleted set of every parent;
    with ``glued``, those decided), rigid remainders (by the endpoint rule), rigid remainders already
    stored, and the new clusters; with ``glued``, ``seen``: remainders not decided, as a stored cluster
    or one decided earlier has their contact graph and pair distances.  With ``close_packed`` (the
    fewest contacts of the fragments listed), ``parents`` and ``remainders`` are the fragments."""

    n: int
    spheres: int
    run_id: int
    glued: bool = False
    close_packed: int | None = None
    seen: int = 0
    certified: int = 0  #: with ``glued``: of the remainders tested, those certified floppy from their glued cluster
    parents: int = 0
    remainders: int = 0
    rigid: int = 0
    already_stored: int = 0
    new: list[Found] = field(default_factory=list)
    expansions_added: int = 0
    run_reopened: bool = False
    after: int = 0  #: the parents read were the stored clusters with a larger id
    last_parent: int | None = None  #: the largest parent id read (None: none read)

    def to_dict(self) -> dict:
        return asdict(self)

    def add(self, w: Written) -> None:
        """What one transaction of the pass stored."""
        self.new.extend(w.new)
        self.already_stored += w.already_stored
        self.expansions_added += w.expansions_added
        self.run_reopened |= w.run_reopened


def count_stored(Session_: sessionmaker, n: int, after: int = 0) -> int:
    """How many clusters of n are stored (with ``after``: with an id above it)."""
    with Session_() as s:
        return s.execute(
            select(func.count()).select_from(ClusterRow).where(ClusterRow.n == n, ClusterRow.id > after)
        ).scalar_one()


def parents_stored(Session_: sessionmaker, source: int) -> int:
    """How many clusters of ``source`` spheres (a pass's parents) are stored; :class:`NoParents` if none."""
    total = count_stored(Session_, source)
    if total == 0:
        raise NoParents(f"no clusters of {source} spheres stored: run `packings enumerate {source}` first")
    return total


def run_for(Session_: sessionmaker, n: int, params: Params) -> int:
    """The id of the run of (n, params): the stored one, or a new one created and seeded by
    :func:`packings.service.store.start_run` (as ``packings enumerate`` would) and let go at once."""
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


def covered(Session_: sessionmaker, run_id: int) -> int:
    """The largest cluster id up to which glued passes into ``run_id`` that ran to their end have read every
    stored parent (0: none ran): a pass after them need read only the clusters stored since."""
    with Session_() as s:
        rows = s.execute(
            select(CatalysisPass.after, CatalysisPass.last_parent).where(
                CatalysisPass.run_id == run_id, CatalysisPass.kind == PASS_GLUED
            )
        ).all()
    return max((max(a, last or 0) for a, last in rows), default=0)


class _Rows:
    """The stored clusters of n (id, coords, contact list) with an id above ``after``, ``batch`` at a time,
    by id; iterated again, it goes on after the last id it gave (clusters stored since are read then).
    With ``ids_only``, each row is the id alone (a Dask task reads the rest itself: :func:`catalysis_task`)."""

    def __init__(self, Session_: sessionmaker, n: int, batch: int, after: int = 0, ids_only: bool = False):
        self.Session_, self.n, self.batch, self.last = Session_, n, batch, after
        self.columns = (ClusterRow.id,) if ids_only else PARENT_COLUMNS

    def __iter__(self):
        while True:
            with self.Session_() as s:
                rows = s.execute(
                    select(*self.columns)
                    .where(ClusterRow.n == self.n, ClusterRow.id > self.last)
                    .order_by(ClusterRow.id)
                    .limit(self.batch)
                ).all()
            if not rows:
                return
            self.last = rows[-1].id
            yield rows


def rows_of(Session_: sessionmaker, ids: list[int]) -> list:
    """The stored clusters ``ids`` as :class:`_Rows` gives them (id, coords, contact list), by id."""
    with Session_() as s:
        return s.execute(select(*PARENT_COLUMNS).where(ClusterRow.id.in_(ids)).order_by(ClusterRow.id)).all()


def stored_seen(Session_: sessionmaker, n: int, tol_d: float, batch: int = BATCH) -> Seen:
    """Every stored cluster of n (of any run), as :class:`packings.workers.catalysis.Seen` has them: the
    remainders a pass of ``glued`` does not decide again."""
    from packings.workers.catalysis import Seen

    seen = Seen(tol_d)
    for rows in _Rows(Session_, n, batch):
        for _, coords, contact_list in rows:  # plain clusters: their canonical forms are not kept
            seen.add(
                Cluster(np.frombuffer(coords, dtype="<f8").reshape(n, 3), tuple(map(tuple, json.loads(contact_list))))
            )
    return seen


@dataclass(frozen=True)
class Kept:
    """A rigid remainder as it is stored: the parent's id (None for a close-packed fragment), the parent's
    spheres deleted, the remainder's cluster, rigidity and certificate, and (``glued``) the contact triangle
    its moved sphere was put on."""

    parent_id: int | None
    deleted: tuple[int, ...]
    cluster: Cluster
    rigidity: Rigidity
    certificate: str
    moved_onto: tuple[int, int, int] | None = None

    @classmethod
    def of(cls, parent_id: int | None, r, moved_onto: tuple[int, int, int] | None = None) -> Kept:
        """From a rigid :class:`packings.workers.catalysis.Remainder` ``r``."""
        return cls(parent_id, r.deleted, r.cluster, r.rigidity, certificate_key(r.cluster), moved_onto)


@dataclass
class Written:
    """What one transaction of :func:`_store` did: the clusters it inserted, the rigid remainders it matched
    to stored clusters, the expansions it added and whether it marked the run running again."""

    new: list[Found] = field(default_factory=list)
    already_stored: int = 0
    expansions_added: int = 0
    run_reopened: bool = False


@dataclass
class Decided:
    """What one batch of parents gave: the rigid remainders (:class:`Kept`, until they are stored: then
    ``written``), how many they were, the parents, the remainders decided and (``glued``) those seen
    already and those of the decided certified floppy from their glued cluster alone."""

    found: list = field(default_factory=list)
    parents: int = 0
    remainders: int = 0
    seen: int = 0
    certified: int = 0
    rigid: int = 0
    written: Written | None = None

    def store(self, Session_: sessionmaker, n: int, run_id: int, params: Params) -> Decided:
        """The rigid remainders stored (:func:`_store`) and dropped, ``written`` saying what that did."""
        if self.found:
            self.written = _store(Session_, n, run_id, params, self.found)
            self.found = []
        return self


def decide(rows, n: int, params: Params, spheres: int = 1, glued: bool = False, seen: Seen | None = None) -> Decided:
    """The remainders of one batch of stored parents ``rows`` ((id, coords, contact list) as stored: of n +
    ``spheres`` spheres, or with ``glued`` of n, whose spheres are moved one at a time, ``seen`` being the
    remainders not to decide again, which grows with those decided).  Pure computation: the same in this
    process or in a Dask task (:func:`catalysis_task`)."""
    from packings.workers.catalysis import moved_remainders, remainder_count, rigid_remainders

    source = n if glued else n + spheres
    out = Decided()
    for pid, coords, contact_list in rows:
        parent = core_cluster(source, coords, contact_list)
        out.parents += 1
        if glued:
            for mv in moved_remainders(parent, params, seen):
                if mv.seen:
                    out.seen += 1
                    continue
                out.remainders += 1
                out.certified += mv.floppy > 0
                if mv.remainder is not None and mv.remainder.rigid:
                    out.found.append(Kept.of(pid, mv.remainder, mv.triangle))
            continue
        out.remainders += remainder_count(parent.n, spheres)
        for r in rigid_remainders(parent, spheres, params):
            out.found.append(Kept.of(pid, r))
    out.rigid = len(out.found)
    return out


def catalyse(
    Session_: sessionmaker,
    n: int,
    params: Params,
    spheres: int = 1,
    batch: int = BATCH,
    on_progress: Callable[[int, int], None] | None = None,
    glued: bool = False,
    client=None,
    plugin=None,
    after: int = 0,
    max_attempts: int = 3,
    workerless_timeout: float | None = None,
    revive: Callable[[], int] | None = None,
) -> CatalysisReport:
    """Delete ``spheres`` spheres from every stored cluster of n + ``spheres`` (with ``glued``: move one
    sphere of every stored cluster of n) and store the new rigid remainders in the run of (n, params)
    (module doc).  The parents are read by id as the pass goes, so that with ``glued`` the clusters it
    stores are moved in their turn.  ``on_progress(parents done, parents)`` after each batch.  Raises
    :class:`NoParents` when no cluster of n + spheres (with ``glued``: of n) is stored.

    With a Dask ``client`` (whose workers have the :class:`packings.service.plugin.DatabasePlugin` ``plugin``,
    or the one of that name), each batch of parents is decided and stored by a task on a worker
    (:func:`catalysis_task`), two per worker thread at a time, on the Dask driver (:class:`_Pass`): a batch
    lost with its worker is sent again, one whose task raised is tried ``max_attempts`` times in all before
    the pass stops (:class:`packings.service.errors.PassFailed`), and after ``workerless_timeout`` seconds
    without a worker (None: it waits) the pass stops with :class:`packings.service.errors.SchedulerError`;
    ``revive`` replaces lost workers (:meth:`packings.service.dask_cluster.dask_client.revive_workers`), and
    the plugin (if given, not its name) is registered again with a scheduler reached again.  With
    ``glued`` each worker process keeps its own record of what it has seen (the stored clusters, then
    what it decided), so that a remainder may be decided once per worker rather than once: what is
    stored is the same.

    With ``after``, the parents are the stored clusters with a larger id (:func:`covered`: those stored
    since the glued passes before).  A pass that runs to its end is recorded (table ``catalysis_passes``)
    with the largest parent id it read; an interrupted one is not (what it stored stays)."""
    if glued and spheres != 1:
        raise ValueError("catalysis of glued clusters moves one sphere")
    source = n if glued else n + spheres
    total = parents_stored(Session_, source)  # NoParents when none is stored
    if after:  # only those stored since the passes before are read
        total = count_stored(Session_, source, after)
    run_id = run_for(Session_, n, params)
    report = CatalysisReport(n, spheres, run_id, glued=glued, after=after)
    started = utcnow()
    parents = _Rows(Session_, source, batch, after, ids_only=client is not None)

    def absorb(d: Decided) -> None:
        report.parents += d.parents
        report.remainders += d.remainders
        report.seen += d.seen
        report.certified += d.certified
        report.rigid += d.rigid
        if d.written is not None:
            report.add(d.written)
        if on_progress is not None:
            on_progress(report.parents, total)

    if client is None:
        seen = stored_seen(Session_, n, params.tol_d, batch) if glued else None
        for rows in parents:
            absorb(decide(rows, n, params, spheres, glued, seen).store(Session_, n, run_id, params))
    else:
        work = (n, params, spheres, glued)
        _Pass(client, plugin, parents, work, run_id, absorb, max_attempts, workerless_timeout, revive).drive()
    report.last_parent = parents.last if parents.last > after else None
    _record(Session_, report, started)
    return report


def _record(Session_: sessionmaker, r: CatalysisReport, started) -> None:
    """The pass ``r``, run to its end, as a row of ``catalysis_passes``."""
    with Session_.begin() as s:
        s.add(
            CatalysisPass(
                run_id=r.run_id,
                kind=PASS_GLUED if r.glued else PASS_DELETED,
                spheres=r.spheres,
                after=r.after,
                last_parent=r.last_parent,
                parents=r.parents,
                remainders=r.remainders,
                rigid=r.rigid,
                new=len(r.new),
                started_at=started,
                finished_at=utcnow(),
            )
        )


def close_packed_pass(
    Session_: sessionmaker,
    n: int,
    params: Params,
    min_contacts: int,
    batch: int = BATCH,
    on_progress: Callable[[int, int], None] | None = None,
) -> CatalysisReport:
    """Every close-packed fragment of n spheres with at least ``min_contacts`` contacts (module doc), decided
    by the endpoint rule (:func:`packings.workers.catalysis.remainder` with nothing deleted); the rigid ones
    (with at least ``params.min_contacts`` contacts if that is set) not yet stored go into the run of
    (n, params), each with an expansion, one transaction per ``batch``.  ``on_progress(done, fragments)``."""
    from packings.workers.catalysis import remainder

    fragments = close_packed(n, min_contacts, params)
    run_id = run_for(Session_, n, params)
    report = CatalysisReport(n, 0, run_id, close_packed=min_contacts)
    for a in range(0, len(fragments), batch):
        chunk = fragments[a : a + batch]
        found = []
        for f in chunk:
            r = remainder(f.cluster, (), params)
            if r.rigid:
                found.append(Kept.of(None, r))
        report.parents += len(chunk)
        report.remainders += len(chunk)
        report.rigid += len(found)
        if found:
            report.add(_store(Session_, n, run_id, params, found, FOUND_CLOSE_PACKED))
        if on_progress is not None:
            on_progress(report.parents, len(fragments))
    return report


class _Pass(Driver):
    """A catalysis pass's parents decided and stored by Dask tasks (:func:`catalysis_task`), a batch of parent
    ids each, on the Dask driver (:class:`packings.service.driver.Driver`: two tasks per worker thread in
    flight, the scheduler reached again when it is lost, the watchdog); ``absorb`` each result here as it
    completes.  ``parents`` (:class:`_Rows`) reads the stored parents' ids as the pass goes, so that, as in
    one process, the clusters that tasks store become parents in their turn: each claim reads it again
    after the last id it gave.

    A batch is idempotent (storing is insert-or-match under the certificate locks), so nothing is leased:
    its tries are kept here.  A batch lost to the infrastructure is sent again without counting a try
    (once it has killed its workers, :class:`~distributed.scheduler.KilledWorker`, each time more it does
    counts); a batch whose task raised is tried again, ``max_attempts`` times in all, then the pass stops
    with :class:`packings.service.errors.PassFailed` (what was stored stays, and the pass is not recorded)."""

    resume = "what the pass stored stays; run the same command again to make the pass"
    PER_WORKER = 2  #: tasks in flight per worker thread: a task is a batch of parents, seconds of work

    def __init__(
        self,
        client,
        plugin,
        parents: _Rows,
        work: tuple,
        run_id: int,
        absorb: Callable[[Decided], None],
        max_attempts: int,
        workerless_timeout: float | None,
        revive: Callable[[], int] | None,
    ):
        named = plugin is None or isinstance(plugin, str)  # a name alone: the caller registers it again if need be
        label = f"catalysis pass into run {run_id}"
        super().__init__(client, label, self.PER_WORKER, workerless_timeout, revive, None if named else plugin, log)
        self.plugin_name = getattr(plugin, "name", plugin)
        self.parents, self.work, self.run_id, self.absorb = parents, work, run_id, absorb
        self.max_attempts = max_attempts
        self.pass_id = uuid.uuid4().hex  # each worker's record of what it has seen is this pass's alone
        self.again: deque[list[int]] = deque()  #: batches to send again, first
        self.tries: Counter = Counter()  #: the tries of each batch (by its ids) that raised, or killed again
        self.killed: set[tuple] = set()  #: the batches lost once with their workers (KilledWorker)

    def claim(self, tasks: int) -> list:
        """The batches to send again, then the next ones read (:class:`_Rows`), ``tasks`` in all at most."""
        out = [self.again.popleft() for _ in range(min(tasks, len(self.again)))]
        if tasks > len(out):
            out += [[r.id for r in rows] for rows in islice(self.parents, tasks - len(out))]
        return out

    def submit(self, ids: list[int]):
        n, params, spheres, glued = self.work
        fut = self.client.submit(
            catalysis_task, ids, n, params, spheres, glued, self.plugin_name, self.pass_id, self.run_id, pure=False
        )
        fut.ids = ids  # type: ignore[attr-defined]
        return fut

    def succeeded(self, fut) -> None:
        self.absorb(fut.result())

    def lost(self, fut, exc: BaseException | None, connection: bool = False) -> None:
        """The batch sent again, uncounted (counted if it killed its workers before)."""
        from distributed.scheduler import KilledWorker

        from packings.service.tasks import error_line

        why = "task cancelled" if exc is None else error_line(exc)
        key = tuple(fut.ids)
        if isinstance(exc, KilledWorker):
            if key in self.killed:  # it killed its workers again: that is the batch's doing
                self.tried(fut, f"lost its workers again: {why}")
                return
            self.killed.add(key)
        self.again.append(fut.ids)
        log.warning("%s: a task of %d parent(s) was lost (%s); sent again", self.label, len(fut.ids), why)

    def failed(self, fut, exc: BaseException) -> None:
        """The batch tried again, or the pass stopped: at once if the database cannot be written."""
        from packings.service.coordinator import cannot_write, not_writable
        from packings.service.tasks import error_line

        line = error_line(exc)
        full = cannot_write(line)
        if full is not None:
            raise not_writable(full)
        self.tried(fut, line)

    def tried(self, fut, why: str) -> None:
        """One more try of ``fut``'s batch used up by ``why``: sent again, or the pass stopped
        (:class:`packings.service.errors.PassFailed`) once it has had ``max_attempts``."""
        ids = fut.ids
        key = tuple(ids)
        self.tries[key] += 1
        if self.tries[key] >= self.max_attempts:
            raise PassFailed(
                f"{self.label}: the task of {len(ids)} parent(s) (cluster ids {ids[0]} to {ids[-1]}) failed "
                f"{self.tries[key]} time(s): {why}; {self.resume}"
            )
        log.warning(
            "%s: the task of %d parent(s) failed (%s): try %d of %d, sent again",
            self.label,
            len(ids),
            why,
            self.tries[key],
            self.max_attempts,
        )
        self.again.append(ids)

    def abandon(self, e: BaseException) -> None:
        """The tasks still in flight cancelled: what they would store is the next pass's to store."""
        try:
            self.cancel_flight()
        except Exception:  # noqa: BLE001 - the scheduler is gone: nothing of theirs reaches it
            pass


_SEEN_LOCK = threading.Lock()


def catalysis_task(
    ids: list[int], n: int, params, spheres: int, glued: bool, plugin: str, pass_id: str, run_id: int
) -> Decided:
    """The Dask task of a catalysis pass: :func:`decide` of one batch of stored parents (``ids``, read here
    with this worker's engine), its rigid remainders stored here into the run ``run_id`` in one transaction
    (as an expansion's task writes its results back), and what that did returned.  So the coordinator and
    the scheduler never hold the parents' coordinates, and the coordinator never loads the numerical code
    (the endpoint rule, the identity's compiled kernels).  With ``glued``, this worker process's record of
    what it has seen in the pass ``pass_id`` (the stored clusters of n, read once with this worker's engine, then what
    its tasks decided) is kept between its tasks, and dropped when another pass begins."""
    from distributed import get_worker

    p = get_worker().plugins[plugin]
    rows = rows_of(p.readers, ids)
    seen = None
    if glued:
        with _SEEN_LOCK:  # one worker's threads build it once
            kept = getattr(p, "catalysis_seen", None)
            if kept is None or kept[0] != pass_id:
                p.catalysis_seen = None  # the last pass's, freed before this one's is read
                p.catalysis_seen = kept = (pass_id, stored_seen(p.readers, n, params.tol_d))
        seen = kept[1]
    return decide(rows, n, params, spheres, glued, seen).store(p.sessions, n, run_id, params)


def _store(
    Session_: sessionmaker, n: int, run_id: int, params: Params, found, found_by: str = FOUND_CATALYSIS
) -> Written:
    """One transaction: the rigid remainders ``found`` (:class:`Kept`) inserted or matched, expansions for
    those new to the run, the run reopened if it was not running; what it did."""
    with Session_.kw["bind"].begin() as s:
        keys = {(n, k.certificate) for k in found}
        store.lock_certificates(s, keys)
        stored = store.stored_with(s, n, {cert for _, cert in keys})
        inserted, others, w = [], [], Written()
        for k in found:
            rows = stored[k.certificate]
            cid, is_new = store.insert_or_match(
                s, k.cluster, k.rigidity, run_id, params.tol_d, rows, found_by=found_by, source_id=k.parent_id
            )
            if is_new:
                inserted.append(cid)
                w.new.append(
                    Found(cid, k.parent_id, k.deleted, k.cluster.m, store.lattice_value(k.cluster), k.moved_onto)
                )
            else:
                w.already_stored += 1
                if next(x.found_in_run for x in rows if x.id == cid) != run_id:
                    others.append(cid)
        added = store.ensure_expansions(s, run_id, others, new=inserted) if (inserted or others) else 0
        w.expansions_added = added
        if added:
            reopened = s.execute(update(Run).where(Run.id == run_id, Run.status != RUNNING).values(status=RUNNING))
            w.run_reopened = reopened.rowcount > 0
    return w


def format_report(r: CatalysisReport, expanded: bool = False) -> str:
    """The report as a few lines of text; ``expanded``: the expansions it added have been expanded since (the
    glued passes of ``packings enumerate``, whose run is complete again when they are reported)."""
    if r.close_packed is not None:
        lines = [
            f"close-packed fragments of n = {r.n} with at least {r.close_packed} contacts, run {r.run_id}:",
            f"  fragments {r.parents}, rigid {r.rigid}, already stored {r.already_stored}, new {len(r.new)}",
        ]
    elif r.glued:
        lines = [
            f"catalysis of n = {r.n} by moving one sphere of each stored cluster onto a contact triangle, "
            f"run {r.run_id}:",
            f"  clusters {r.parents}, remainders tested {r.remainders} (certified floppy together: {r.certified}; "
            f"not again: {r.seen}), rigid {r.rigid}, "
            f"already stored {r.already_stored}, new {len(r.new)}",
        ]
    else:
        lines = [
            f"catalysis of n = {r.n} from n = {r.n + r.spheres} (deleting {r.spheres} sphere"
            f"{'s' if r.spheres != 1 else ''}), run {r.run_id}:",
            f"  parents {r.parents}, remainders tested {r.remainders}, rigid {r.rigid}, "
            f"already stored {r.already_stored}, new {len(r.new)}",
        ]
    for f in r.new:
        origin = (
            "a close-packed fragment"
            if f.parent_id is None
            else f"from cluster {f.parent_id} with sphere {f.deleted[0]} moved onto contact triangle "
            f"{tuple(f.moved_onto)}"
            if f.moved_onto is not None
            else f"from cluster {f.parent_id} without sphere{'s' if len(f.deleted) > 1 else ''} "
            + ", ".join(map(str, f.deleted))
        )
        lines.append(f"  new cluster {f.id}: {f.contacts} contacts, lattice {f.lattice}, {origin}")
    if r.expansions_added:
        lines.append(
            f"  {r.expansions_added} expansion{'s' if r.expansions_added != 1 else ''} added to run "
            f"{r.run_id}" + (", and expanded" if expanded else " (marked running again)" if r.run_reopened else "")
        )
    return "\n".join(lines)
