"""What the fork server of a local cluster's workers loads before it forks them.

``packings enumerate`` starts its local cluster's worker processes from a fork
server (:func:`packings.service.cli.start_fork_server`) that imports this module once:
the tasks' modules, and with them Dask, SQLAlchemy and the numerical code, and
the compiled kernels, warmed up.  Each worker forked from it starts with all of
that loaded, rather than importing and loading it again itself.  Importing the
module anywhere else does the same for that process.
"""

from packings.service.plugin import prepare_process

#: what the warm-up took in the process that imported this module (the fork server)
warm_up_seconds = prepare_process()
