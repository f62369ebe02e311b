"""Who drives a run: a coordinator's name (``host:pid:token``), whether it is alive, and the error for a
run that a live one holds.  Light (no SQLAlchemy, numpy or numerics): ``packings enumerate`` asks before
it starts anything, and the store asks when a coordinator takes a run over."""

from __future__ import annotations

import datetime as dt
import os
import socket

from packings.service.errors import PackingsError

#: a coordinator on another host whose heartbeat is older than this is taken to be gone
HEARTBEAT_STALE_SECONDS = 120


class RunBusy(PackingsError):
    """Another live coordinator is driving this run."""


def utcnow() -> dt.datetime:
    """Now, in UTC, without a time zone (as the database's DateTime columns hold it)."""
    return dt.datetime.now(dt.timezone.utc).replace(tzinfo=None)


def process_name() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def coordinator_alive(owner: str | None, heartbeat: dt.datetime | None) -> bool:
    """Whether the coordinator ``owner`` (host:pid:token) is alive: its process on this host, or a
    heartbeat from another host within HEARTBEAT_STALE_SECONDS."""
    if not owner:
        return False
    host, pid, *_ = owner.split(":") + ["", ""]
    if host == socket.gethostname():
        try:
            os.kill(int(pid), 0)
        except (ValueError, ProcessLookupError):
            return False
        except PermissionError:
            return True
        return True
    if heartbeat is None:
        return False
    return (utcnow() - heartbeat).total_seconds() < HEARTBEAT_STALE_SECONDS


def busy(
    run_id: int, n: int, coordinator: str | None, heartbeat: dt.datetime | None, owner: str | None = None
) -> RunBusy | None:
    """The error for run ``run_id`` of n if a live coordinator other than ``owner`` holds it, else None."""
    if coordinator and coordinator != owner and coordinator_alive(coordinator, heartbeat):
        return RunBusy(
            f"run {run_id} (n = {n}) is being driven by coordinator {coordinator}; "
            "wait for it to finish or stop it first"
        )
    return None
