"""The ``packings`` page of the Dask dashboard: a run's progress, read from its database.

Importing this module adds the page (``/packings``, a Bokeh document) and its data
(``/packings.json``) to every Dask scheduler created afterwards in the process:
``packings enumerate`` imports it before it starts its local cluster, and a scheduler
of many machines loads it as a preload::

    PACKINGS_DB=postgresql://user@db-host/packings dask scheduler --preload packings.service.dashboard

What the page shows comes from a thread that reads the database every
:data:`POLL_SECONDS` (never the scheduler's event loop, which a query would stall)
while the page or its JSON has been looked at in the last :data:`IDLE_SECONDS`, and
then at most :data:`READ_SHARE` of its time: the thread shares the coordinator's
cores with the workers, and at n = 13 one read takes a few tenths of a second
(docs/performance.md).  The JSON, asked for after nobody has looked for a while, waits
for a new read (at most :data:`FRESH_SECONDS`) rather than give what was read when
somebody last looked: a script that polls it now and then gets the run as it is.
What it shows:
the run being driven (the one whose coordinator is alive, else the latest), its
clusters by number of contacts and the paper's count of them where it gives one,
its frontier (pending, leased, done, failed), the faults recovered, expansions per
second over the last minute, an estimate of the time left (pending expansions over
that rate: a lower bound, since the frontier grows while a run goes on), the
expansions of each worker still in the cluster (those gone, lost or retired, are named
apart), and the failed expansions with their errors.  The JSON is the same snapshot.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import logging
import os
import threading
import time
from collections import deque

from packings.service.owners import coordinator_alive
from packings.service.paper import paper_totals

# SQLAlchemy, the store and the tasks are imported where the page is read, Dask's dashboard and Bokeh where
# it is served: `packings enumerate` imports this module just before it starts its local cluster.

log = logging.getLogger(__name__)

POLL_SECONDS = 1.0  #: how often the database is read while the page is looked at
READ_SHARE = 0.05  #: the largest share of the time the reads may take (a read of t s waits t / READ_SHARE - t after)
IDLE_SECONDS = 120.0  #: with neither the page nor its JSON asked for in this long, the database is not read
RATE_WINDOW = 60.0  #: seconds over which expansions per second are measured
FRESH_SECONDS = 10.0  #: how long the JSON waits for a new read when reading had stopped
PAGE = "/packings"


class Watcher(threading.Thread):
    """Reads the database every POLL_SECONDS into :attr:`snapshot` (a dict; empty before the first read)."""

    def __init__(self, url: str, scheduler=None):
        super().__init__(name="packings-dashboard", daemon=True)
        self.url = url
        self.scheduler = scheduler  #: the scheduler serving the page: which workers are still there
        self.snapshot: dict = {}
        self.history: deque[tuple[float, int]] = deque()  # (monotonic time, expansions done)
        self.reads = 0
        self._engine = None
        self._viewed = time.monotonic()  # the first IDLE_SECONDS count as looked at
        self._looked = threading.Event()

    def looked_at(self) -> dict:
        """The snapshot, for the page or its JSON: reading goes on (or starts again at once) for IDLE_SECONDS."""
        self._viewed = time.monotonic()
        self._looked.set()
        return self.snapshot

    async def fresh(self, timeout: float | None = None) -> dict:
        """As :meth:`looked_at`, but where reading had stopped (or not yet begun) the snapshot of a read
        made after this call, awaited for at most ``timeout`` (default :data:`FRESH_SECONDS`) without
        holding up the caller's event loop; past it, the snapshot there is."""
        stale = not self.reads or time.monotonic() - self._viewed > IDLE_SECONDS  # reading stopped
        reads = self.reads
        snapshot = self.looked_at()
        if not stale:
            return snapshot
        end = time.monotonic() + (FRESH_SECONDS if timeout is None else timeout)
        while self.reads == reads and time.monotonic() < end:
            await asyncio.sleep(0.02)
        return self.snapshot

    def run(self) -> None:
        """For as long as the process lives (a daemon thread: the scheduler's process)."""
        while True:
            start = time.monotonic()
            pause = POLL_SECONDS
            try:
                self.snapshot = self.read()
            except Exception as e:  # noqa: BLE001 - shown on the page; the next read may succeed
                self.snapshot = {**self.snapshot, "error": f"{type(e).__name__}: {str(e).splitlines()[0][:200]}"}
            else:  # the first read's time is mostly imports and the engine's start: not what reads cost
                took = time.monotonic() - start
                if self.reads:
                    pause = max(POLL_SECONDS, took / READ_SHARE) - took
            self.reads += 1
            time.sleep(pause)
            while True:  # nobody looks: wait until somebody does
                self._looked.clear()
                if time.monotonic() - self._viewed <= IDLE_SECONDS:
                    break
                self._looked.wait()

    def read(self) -> dict:
        from packings.service.db import make_engine, sessions

        if self._engine is None:
            self._engine = make_engine(self.url)
        with sessions(self._engine, readonly=True)() as s:
            data = read_run(s)
        if data.get("run") is not None:
            live = live_workers(self.scheduler)
            if live is not None:  # a worker that left (lost or retired) is no longer listed, but counted
                data["workers_live"] = len(live)
                data["workers_gone"] = sorted(w["worker"] for w in data["workers"] if w["worker"] not in live)
                data["workers"] = [w for w in data["workers"] if w["worker"] in live]
            now = time.monotonic()
            if self.history and self.history[-1][1] > data["frontier"]["done"]:
                self.history.clear()  # another run
            self.history.append((now, data["frontier"]["done"]))
            while now - self.history[0][0] > RATE_WINDOW:
                self.history.popleft()
            (t0, d0), (t1, d1) = self.history[0], self.history[-1]
            rate = (d1 - d0) / (t1 - t0) if t1 > t0 else 0.0
            pending = data["frontier"]["pending"] + data["frontier"]["leased"]
            data["rate"] = round(rate, 2)
            data["eta_seconds"] = round(pending / rate, 0) if rate > 0 else None
        return data


def live_workers(scheduler) -> set[str] | None:
    """The addresses of ``scheduler``'s workers now (read from another thread than its event loop, which
    may change them meanwhile: asked again then), None without a scheduler."""
    if scheduler is None:
        return None
    for _ in range(10):
        try:
            return set(list(scheduler.workers))
        except RuntimeError:  # changed while read
            continue
    return None


def read_run(s) -> dict:
    """The snapshot of the run being driven (one session's reads)."""
    from sqlalchemy import func, select  # see the note on the imports above

    from packings.service import queries
    from packings.service.models import FAILED, PASS_GLUED, CatalysisPass, ExpansionRow, Run
    from packings.service.tasks import summary

    runs = s.execute(select(Run).order_by(Run.started_at.desc(), Run.id.desc())).scalars().all()
    run = next((r for r in runs if coordinator_alive(r.coordinator, r.heartbeat_at)), None)
    run = run or (runs[0] if runs else None)
    at = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
    if run is None:
        return {"run": None, "at": at}
    f = queries.frontier(s, run.id)
    frontier = {k: int(f.get(k, 0)) for k in ("pending", "leased", "done", "failed")}
    workers = [
        {"worker": w, "done": int(k), "seconds": round(float(t or 0.0), 1)}
        for w, k, t in s.execute(
            select(ExpansionRow.worker, func.count(), func.sum(ExpansionRow.seconds))
            .where(ExpansionRow.run_id == run.id, ExpansionRow.status == "done")
            .group_by(ExpansionRow.worker)
            .order_by(ExpansionRow.worker)
        )
    ]
    failed = [
        {"expansion": i, "error": summary(e or "")}
        for i, e in s.execute(
            select(ExpansionRow.id, ExpansionRow.error)
            .where(ExpansionRow.run_id == run.id, ExpansionRow.status == FAILED)
            .order_by(ExpansionRow.id)
            .limit(50)
        )
    ]
    by_contacts = queries.run_counts(s, run.id)
    least = json.loads(run.params or "{}").get("min_contacts")
    passes = s.execute(
        select(func.count())
        .select_from(CatalysisPass)
        .where(CatalysisPass.run_id == run.id, CatalysisPass.kind == PASS_GLUED)
    ).scalar_one()
    return {
        "run": run.id,
        "n": run.n,
        "status": queries.shown_status(run),
        "at": at,
        "clusters": sum(by_contacts.values()),
        "by_contacts": {str(m): k for m, k in by_contacts.items()},
        "min_contacts": least,
        "paper": paper_totals([run.n], {run.n: least} if least else None).get(run.n),
        "frontier": frontier,
        "glued_passes": int(passes),
        **queries.faults(s, run.id),
        "workers": workers,
        "failed": failed,
        "seconds": round(run.seconds or 0.0, 1),
    }


_WATCHERS: dict[str, Watcher] = {}
_CURRENT: list[Watcher] = []


def watch(url: str, scheduler=None) -> Watcher:
    """Show the runs of the database at ``url`` on the page (one watching thread per database), with
    only the workers still in ``scheduler``'s cluster listed."""
    w = _WATCHERS.get(url)
    if w is None or not w.is_alive():
        w = _WATCHERS[url] = Watcher(url, scheduler)
        w.start()
    w.scheduler = scheduler or w.scheduler
    _CURRENT[:] = [w]
    return w


def current() -> dict:
    """What the page shows (which keeps the watching thread reading)."""
    return _CURRENT[0].looked_at() if _CURRENT else _NO_DATABASE


async def current_fresh() -> dict:
    """What the JSON shows: :func:`current`, read anew if reading had stopped (:meth:`Watcher.fresh`)."""
    return await _CURRENT[0].fresh() if _CURRENT else _NO_DATABASE


_NO_DATABASE = {"run": None, "error": "no database: set PACKINGS_DB"}


# --------------------------------------------------------------------------- the page


def _html(d: dict) -> str:
    if d.get("run") is None:
        return f"<h2>packings</h2><p>{d.get('error') or 'no run in the database yet'}</p>"
    fr = d["frontier"]
    eta = d.get("eta_seconds")
    left = "—" if eta is None else str(dt.timedelta(seconds=int(eta)))
    found = f"{d['clusters']:,}"
    if d.get("paper") is not None:
        least = f" with at least {d['min_contacts']} contacts" if d.get("min_contacts") else ""
        found += f" (the paper has {d['paper']:,}{least}{_glued_note(d)})"
    rows = [
        ("run", f"{d['run']} (n = {d['n']}), {d['status']}"),
        ("clusters found", found),
        ("expansions", f"{fr['done']} done, {fr['pending']} pending, {fr['leased']} leased, {fr['failed']} failed"),
        (
            "faults recovered",
            f"{d['retries']} retries (expansions whose task was lost with a worker), "
            f"{d['isolated_failures']} isolated failures",
        ),
        ("expansions per second", d.get("rate", "—")),
        ("time left, at least", left + " (the frontier still grows)"),
        ("read at", d["at"]),
    ]
    gone = d.get("workers_gone")
    if gone is not None:
        left = f"; gone (lost or retired): {', '.join(gone)}" if gone else ""
        rows.insert(4, ("Dask workers", f"{d['workers_live']} in the cluster{left}"))
    if d.get("error"):
        rows.append(("database", d["error"]))
    cells = "".join(f"<tr><th style='text-align:left;padding-right:1em'>{k}</th><td>{v}</td></tr>" for k, v in rows)
    return f"<h2>packings: n = {d['n']}</h2><table>{cells}</table>"


def _glued_note(d: dict) -> str:
    """Why a full run has fewer clusters than the paper, where a glued catalysis pass is what adds the rest
    (the paths alone miss a cluster at n = 11 and at n = 13): what is true of it at this moment."""
    if d.get("min_contacts") or d["clusters"] >= d["paper"]:
        return ""
    passes = d.get("glued_passes", 0)
    if passes:
        return f"; {passes} glued pass{'es' if passes != 1 else ''} made" + (
            f", {'its' if passes == 1 else 'their'} finds being expanded" if d["status"] == "running" else ""
        )
    if d["status"] == "running":
        return "; the paths alone miss some: a glued pass follows them (unless --no-glued) and adds those"
    return f"; the paths alone miss some: the glued pass after them (`packings enumerate {d['n']}`) adds those"


def packings_doc(scheduler, extra, doc) -> None:
    """The Bokeh document of the page."""
    from bokeh.layouts import column, row
    from bokeh.models import ColumnDataSource, DataRange1d, DataTable, Div, TableColumn
    from bokeh.plotting import figure

    header = Div(text=_html(current()), width=700, styles={"padding-top": "40px"})  # below the navigation bar
    contacts = ColumnDataSource({"contacts": [], "clusters": []})
    bars = figure(
        title="clusters by number of contacts", x_range=[], height=280, width=460, tools="", toolbar_location=None
    )
    bars.vbar(x="contacts", top="clusters", source=contacts, width=0.8)
    states = ["pending", "leased", "done", "failed"]
    frontier = ColumnDataSource({"state": states, "expansions": [0] * 4})
    fbars = figure(title="frontier", x_range=states, height=280, width=360, tools="", toolbar_location=None)
    fbars.vbar(x="state", top="expansions", source=frontier, width=0.8)
    rate = ColumnDataSource({"t": [], "rate": []})
    line = figure(  # from zero: a steady rate's small swings are not drawn as a collapse
        title="expansions per second",
        height=220,
        width=820,
        x_axis_type="datetime",
        y_range=DataRange1d(start=0),
        tools="",
        toolbar_location=None,
    )
    line.line(x="t", y="rate", source=rate)
    workers = ColumnDataSource({"worker": [], "done": [], "seconds": []})
    wtable = DataTable(
        source=workers,
        height=160,
        width=820,
        columns=[
            TableColumn(field="worker", title="worker"),
            TableColumn(field="done", title="expansions done"),
            TableColumn(field="seconds", title="seconds in expand"),
        ],
    )
    failures = ColumnDataSource({"expansion": [], "error": []})
    ftable = DataTable(
        source=failures,
        height=140,
        width=820,
        columns=[TableColumn(field="expansion", title="failed expansion"), TableColumn(field="error", title="error")],
    )

    def update() -> None:
        d = current()
        header.text = _html(d)
        if d.get("run") is None:
            return
        keys = list(d["by_contacts"])
        if list(bars.x_range.factors) != keys:
            bars.x_range.factors = keys
        contacts.data = {"contacts": keys, "clusters": list(d["by_contacts"].values())}
        frontier.data = {"state": states, "expansions": [d["frontier"][k] for k in states]}
        if "rate" in d:
            rate.stream({"t": [dt.datetime.now()], "rate": [d["rate"]]}, rollover=600)
        workers.data = {k: [w[k] for w in d["workers"]] for k in ("worker", "done", "seconds")}
        failures.data = {k: [f[k] for f in d["failed"]] for k in ("expansion", "error")}

    update()
    doc.add_periodic_callback(update, int(POLL_SECONDS * 1000))
    doc.title = "Dask: packings"
    doc.add_root(column(header, row(bars, fbars), line, wtable, ftable))
    from distributed.dashboard.components.scheduler import BOKEH_THEME, env

    doc.template = env.get_template("simple.html")
    doc.template_variables.update(extra)
    doc.theme = BOKEH_THEME


def _json_handler():
    from tornado import web

    class SnapshotHandler(web.RequestHandler):
        async def get(self) -> None:
            snapshot = await current_fresh()
            self.set_header("Content-Type", "application/json")
            self.write(json.dumps(snapshot))

    return SnapshotHandler


def serve_json(scheduler) -> None:
    """Add ``/packings.json`` to ``scheduler``'s web server."""
    scheduler.http_application.add_handlers(r".*", [(PAGE + r"\.json", _json_handler())])
    scheduler.packings_page = True  # packings.service.plugin.serves_page


def _register() -> None:
    """Add the page to the dashboard of every scheduler created from now on in this process, and to
    its navigation bar."""
    try:
        import distributed.dashboard.scheduler as dashboard
    except ImportError:  # no Bokeh: Dask serves no dashboard at all
        return
    if PAGE in dashboard.applications:
        return
    dashboard.applications[PAGE] = packings_doc
    pages_of = dashboard.template_variables

    def template_variables(scheduler):
        out = pages_of(scheduler)
        if "packings" not in out["pages"]:
            out["pages"].insert(0, "packings")
        return out

    dashboard.template_variables = template_variables


_register()


def dask_setup(scheduler) -> None:
    """``dask scheduler --preload packings.service.dashboard``: watch ``$PACKINGS_DB`` and serve the JSON; keep what
    the scheduler remembers of tasks long gone bounded (:class:`packings.service.plugin.TaskLeftovers`), also
    once it is started again, before a coordinator gives it the plugin again."""
    from packings.service.plugin import TaskLeftovers

    scheduler.add_plugin(TaskLeftovers())
    url = os.environ.get("PACKINGS_DB")
    if url:
        watch(url, scheduler)
    else:
        log.warning("packings.service.dashboard: PACKINGS_DB is not set; the packings page shows nothing")
    serve_json(scheduler)
