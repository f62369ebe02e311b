"""The errors a user can cause and fix.  Each message is one line, which the
command line prints as ``packings: error: ...`` and the Python API raises as is."""


class PackingsError(Exception):
    """An error a user can cause and fix; its message is one line naming the problem and the fix."""


class UsageError(PackingsError, ValueError):
    """A bad argument: an n out of range, options that exclude each other, a bad selection."""


class SchedulerError(PackingsError):
    """The Dask scheduler given does not answer."""


class NotFound(PackingsError, KeyError):
    """No stored cluster has the id asked for."""

    def __str__(self) -> str:  # KeyError's str() is the repr of its argument
        return str(self.args[0]) if self.args else ""


class StorageError(PackingsError):
    """The database cannot be written: its disk is full, or it is read-only.  A run stops, with its
    leases put back, and the same command resumes it once space is freed."""


class PassFailed(PackingsError):
    """A catalysis pass stopped: the task of a batch of its parents raised as many times as it may be tried.
    What the pass stored stays (a pass is idempotent); it is not recorded as run to its end, so the same
    command makes it again."""


class Interrupted(PackingsError):
    """Ctrl-C: the run stopped with its leases put back; the same command resumes it (exit status 130)."""

    exit_status = 130

    def __init__(self, message: str = "interrupted; run the same command to resume"):
        super().__init__(message)


class Terminated(Interrupted):
    """SIGTERM, as a process manager stops a program (``docker compose stop``, systemd, ``kill``): the
    same as Ctrl-C, with exit status 143 (128 + SIGTERM)."""

    exit_status = 143

    def __init__(self, message: str = "terminated (SIGTERM); run the same command to resume"):
        super().__init__(message)


class SigTerm(KeyboardInterrupt):
    """What the command line's SIGTERM handler raises in its main thread: a KeyboardInterrupt, so that
    a run unwinds as from Ctrl-C (its leases put back, its local cluster closed)."""
