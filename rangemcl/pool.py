"""A process pool that stops its workers at once when the work is interrupted.

``concurrent.futures.ProcessPoolExecutor`` used as a context manager waits for every submitted job when the
block raises: a ``rangemcl build-map`` or ``simbed trials`` stopped by Ctrl-C or SIGTERM would go on
computing (or leave orphaned workers) instead of cleaning up and exiting. :func:`process_pool` cancels the
jobs not started and terminates the running workers on any exception (``KeyboardInterrupt`` included),
and otherwise shuts the pool down normally. It stays a ``ProcessPoolExecutor``, so a worker that dies
(killed for memory, say) still raises ``BrokenProcessPool`` rather than hanging.
"""

from __future__ import annotations

import multiprocessing
import signal
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager


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
        pool.shutdown(wait=False, cancel_futures=True)
        mine = [p for p in multiprocessing.active_children() if p not in before]
        for p in mine:
            p.terminate()
        for p in mine:
            p.join(timeout=10)
            if p.is_alive():
                p.kill()
                p.join()
        raise
    pool.shutdown(wait=True)


def _default_sigterm() -> None:
    # a forked worker inherits the console scripts' SIGTERM handler (SIGTERM -> KeyboardInterrupt), which
    # would turn terminate() into an exception the worker reports and survives
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
