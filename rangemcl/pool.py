"""A process pool that stops its workers at once when the work is interrupted.

``concurrent.futures.ProcessPoolExecutor`` used as a context manager waits for every submitted job when the
block raises: a ``rangemcl build-map`` or ``simbed trials`` stopped by Ctrl-C or SIGTERM would go on
computing (or leave orphaned workers) instead of cleaning up and exiting. :func:`process_pool` terminates
the running workers on any exception (``KeyboardInterrupt`` included; the jobs not finished end with
``BrokenProcessPool``) and otherwise shuts the pool down normally. It stays a ``ProcessPoolExecutor``, so a
worker that dies (killed for memory, say) still raises ``BrokenProcessPool`` rather than hanging.
"""

from __future__ import annotations

import multiprocessing
import signal
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from multiprocessing.connection import wait


@contextmanager
def process_pool(workers: int, context: str | None = None) -> Iterator[ProcessPoolExecutor]:
    """``ProcessPoolExecutor(workers)`` (start method ``context``: None = the platform's default) whose
    workers are terminated when the ``with`` block raises."""
    before = set(multiprocessing.active_children())
    mp_context = multiprocessing.get_context(context) if context else None
    pool = ProcessPoolExecutor(workers, mp_context=mp_context, initializer=_default_sigterm)
    try:
        yield pool
    except BaseException:
        mine = [p for p in multiprocessing.active_children() if p not in before]
        for p in mine:
            p.terminate()
        # wait for the exits on the sentinels, not with join(): the pool's manager thread, seeing its
        # workers die, reaps them itself, and two threads reaping one child leave it listed as running
        for p in mine:
            if not wait([p.sentinel], timeout=10):
                p.kill()
                wait([p.sentinel])
        # the manager thread fails the pending jobs (BrokenProcessPool), reaps the workers and ends;
        # shutdown waits for it (a first shutdown(wait=False) would forget the thread and not wait)
        pool.shutdown(wait=True, cancel_futures=True)
        for p in mine:
            p.join()  # children started in the block that were not the pool's own
        raise
    pool.shutdown(wait=True)


def _default_sigterm() -> None:
    # a forked worker inherits the console scripts' SIGTERM handler (SIGTERM -> KeyboardInterrupt), which
    # would turn terminate() into an exception the worker reports and survives
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
