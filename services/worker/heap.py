"""The heap of the service's long-lived processes (the `spine worker` Celery process, `spine serve`),
kept out of the cyclic garbage collector's sight (``gc.freeze``) where it never becomes garbage.

What such a process imports and builds (modules, classes, the engine's compiled kernels, the Celery
app, the API: 100 000 to 350 000 objects) lives until it exits, and at exit the interpreter's last
collections walk every object the collector tracks (CPython ``Py_FinalizeEx``): measured on this
2-core machine, 0.9 s of CPU for an idle worker and 1.1 s for `spine serve`, 3 to 4 s of wall time
under the test suite's load, after they had already stopped. Frozen objects are skipped.

- ``freeze_startup_heap``: the worker's main process once it has loaded everything, before its pool
  forks, as the gc documentation advises for a process that forks without exec: no collection in a
  pool process writes to the objects it shares with its parent, and none scans them again.
- ``freeze_for_exit``: `spine serve` once uvicorn has stopped (the app is built inside uvicorn, in
  this process or in processes it spawns, so there is no start-up point to freeze at).

Objects that die later are freed as usual (reference counting); only a reference cycle made
entirely of frozen objects outlives its use.
"""

from __future__ import annotations

import gc


def freeze_startup_heap() -> int:
    """Collect what is garbage now, then freeze every object left; return how many are frozen."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


def freeze_for_exit() -> None:
    """Freeze every object, garbage or not: the process is about to exit, and the collection that
    would find its garbage is the one its exit is spared."""
    gc.freeze()
