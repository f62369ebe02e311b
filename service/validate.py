"""The parameters a user gives, checked in one place for the command line and the Python API.

Each check raises :class:`~packings.service.errors.UsageError` with one line naming the problem (the
command line prints it as ``packings: error: ...`` with exit status 2).  The command line's option types
take their bounds from :data:`RANGES` (:func:`int_range`), so both refuse the same values.
"""

from __future__ import annotations

import socket

from packings.service.errors import UsageError

#: beyond this the catalogue cannot be enumerated on any machine (the count grows like (n-5)!)
MAX_N = 24

#: the inclusive bounds of each integer parameter of a run (None: unbounded)
RANGES: dict[str, tuple[int, int | None]] = {
    "workers": (1, 512),  # processes of a local cluster
    "max_break": (1, 10),  # contacts broken at once
    "max_attempts": (1, 100),  # tries per expansion before it is marked failed
    "spheres": (1, 10),  # spheres deleted from each parent by catalysis
    "close_packed": (0, None),  # least contacts of a close-packed fragment
    "jobs": (1, 512),  # Slurm jobs kept running
    "cores": (1, 1024),  # cores of one Slurm job (a worker process each)
}


def check_n(n: int) -> None:
    """Refuse an n that cannot be enumerated."""
    if not isinstance(n, int) or isinstance(n, bool):
        raise UsageError(f"n must be an integer (got {n!r})")
    if n < 4:
        raise UsageError(f"n must be at least 4 (got {n}): smaller clusters have no contact triangle to pin")
    if n > MAX_N:
        raise UsageError(f"n = {n} is too large: at most {MAX_N} (the number of clusters grows like (n-5)!)")


def check_range(name: str, value: int | None) -> None:
    """Refuse a value of the parameter ``name`` outside :data:`RANGES` (None, the default, passes)."""
    if value is None:
        return
    low, high = RANGES[name]
    if not isinstance(value, int) or isinstance(value, bool) or value < low or (high is not None and value > high):
        bounds = f"between {low} and {high}" if high is not None else f"at least {low}"
        raise UsageError(f"{name} must be {bounds} (got {value!r})")


def check_cluster_choice(
    workers: int | None, scheduler: str | None, *, slurm: bool = False, options: bool = False
) -> None:
    """Refuse more than one of a local cluster's ``workers``, an existing ``scheduler`` and Slurm's
    jobs (named as the command line's options with ``options``)."""
    w, s, j = ("--workers", "--scheduler", "--slurm") if options else ("workers", "scheduler", "slurm")
    if slurm and (workers is not None or scheduler is not None):
        raise UsageError(f"{j} starts its own workers: not with {w} or {s}")
    if workers is not None and scheduler is not None:
        raise UsageError(f"give either {w} (a local cluster) or {s} (an existing one), not both")


def check_dashboard_address(address: str, *, option: bool = False) -> None:
    """Refuse a dashboard address that a local cluster could not serve on: it is ``HOST:PORT`` (or
    ``:PORT``, every interface; ``[v6 address]:PORT``), PORT a number from 0 (any free port) to 65535 and
    HOST one this machine can resolve (named as the command line's option with ``option``)."""
    name = "--dashboard-address" if option else "dashboard_address"
    host, sep, port = str(address).rpartition(":")
    if not sep or not port.isdigit() or int(port) > 65535:
        raise UsageError(f"{name} must be HOST:PORT with PORT from 0 to 65535, e.g. 127.0.0.1:8787 (got {address!r})")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if host:
        try:
            socket.getaddrinfo(host, int(port), type=socket.SOCK_STREAM)
        except (OSError, UnicodeError):
            raise UsageError(f"{name} {address!r}: no such host {host!r} on this machine") from None


def check_run(
    n: int,
    *,
    workers: int | None = None,
    scheduler=None,
    slurm: bool = False,
    max_break=None,
    max_attempts=None,
    dashboard_address: str | None = None,
) -> None:
    """The checks of a run's parameters (:func:`packings.service.run.enumerate`); ``scheduler`` may be an
    address or a Dask cluster object, ``slurm`` says whether Slurm's jobs were asked for."""
    check_n(n)
    check_cluster_choice(workers, scheduler, slurm=slurm)
    for name, value in (("workers", workers), ("max_break", max_break), ("max_attempts", max_attempts)):
        check_range(name, value)
    if dashboard_address is not None:
        check_dashboard_address(dashboard_address)


def int_range(name: str):
    """The click type of the command line's option for ``name``: an integer within :data:`RANGES`."""
    import click

    low, high = RANGES[name]
    return click.IntRange(low, high)
