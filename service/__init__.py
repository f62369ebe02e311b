"""The service: everything with state, over the numerics of :mod:`packings.workers`.

The database (:mod:`.db`, :mod:`.models`, :mod:`.store`, :mod:`.queries`), the run on Dask (:mod:`.run`,
:mod:`.coordinator`, :mod:`.tasks`, :mod:`.plugin`, :mod:`.dask_cluster`, :mod:`.dashboard`), the
catalogue's Python API (:mod:`.api`, :mod:`.selection`, :mod:`.export`), reports (:mod:`.stats`,
:mod:`.paper`, :mod:`.audit`, :mod:`.fit`, :mod:`.plots`) and the command line (:mod:`.cli`,
:mod:`.plot_commands`, :mod:`.options`).  Its public face is re-exported by :mod:`packings`.
"""
