"""A process pool that stops its workers at once when the work is interrupted.

``concurrent.futures.ProcessPoolExecutor`` used as a context manager waits for every submitted job when the
block raises: a ``rangemcl build-map`` or ``simbed trials`` stopped by Ctrl-C or SIGTERM would go on
computing (or leave orphaned workers) instead of cleaning up and exiting. :func:`process_pool` terminates
the running workers on any exception (``KeyboardInterrupt`` included; the jobs not finished end with
``BrokenProcessPool``) and otherwise shuts the pool down normally; its workers die with the parent
whatever kills it (SIGKILL included: Linux's parent-death signal), so no worker outlives a killed run.
It stays a ``ProcessPoolExecutor``, so a worker that dies (killed for memory, say) still raises
``BrokenProcessPool`` rather than hanging.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import multiprocessing
import os
import signal
import sys
import threading
from collections.abc import Iterator
from concurrent.futures import InvalidStateError, ProcessPoolExecutor
from contextlib import contextmanager
from multiprocessing.connection import wait


@contextmanager
def process_pool(workers: int, context: str | None = None) -> Iterator[ProcessPoolExecutor]:
    """``ProcessPoolExecutor(workers)`` (start method ``context``: None = the platform's default) whose
    workers are terminated when the ``with`` block raises."""
    before = set(multiprocessing.active_children())
    mp_context = multiprocessing.get_context(context) if context else None
    pool = ProcessPoolExecutor(
        workers, mp_context=mp_context, initializer=_worker_init, initargs=(os.getpid(),)
    )
    try:
        _start_workers(pool, workers)
        yield pool
    except BaseException:
        # the pool's manager thread sees its workers die and fails what was pending; what it raises while
        # this teardown kills them (CPython 3.11: "InvalidStateError: CANCELLED" for the futures
        # Executor.map cancelled, and others when a stop lands just after the workers started) is a
        # consequence of the teardown: kept off the user's terminal from before the first kill on
        manager = getattr(pool, "_executor_manager_thread", None)
        previous = threading.excepthook

        def quiet(args) -> None:
            if not (isinstance(args.exc_value, InvalidStateError) or args.thread is manager):
                previous(args)

        threading.excepthook = quiet
        try:
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
        finally:
            threading.excepthook = previous
        for p in mine:
            p.join()  # children started in the block that were not the pool's own
        raise
    pool.shutdown(wait=True)


_STOP_SIGNALS = {signal.SIGINT, signal.SIGTERM}


def _ready() -> bool:
    return True


def _start_workers(pool: ProcessPoolExecutor, workers: int) -> None:
    """Start every worker now, with Ctrl-C and SIGTERM held back meanwhile (they act right after): a
    stop that lands while a worker is being spawned leaves it reading a half-written start-up message
    and printing a traceback ("EOFError: Ran out of input") on the user's terminal. The signals are
    held back by handlers that note them, not by a signal mask: Python runs its handlers in the main
    thread whichever thread the kernel hands the signal to, and threads started earlier (thread pools,
    progress bars) do not share the main thread's mask."""
    held: list[int] = []
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in _STOP_SIGNALS:
            previous[sig] = signal.signal(sig, lambda signum, _frame: held.append(signum))
    try:
        # spawn every worker now: with the spawn and forkserver start methods the pool otherwise starts
        # them one by one as jobs come and find no idle worker, so a worker could start later, unguarded
        launch = getattr(pool, "_launch_processes", None)
        if launch is not None and getattr(pool, "_executor_manager_thread", None) is None:
            launch()
        for f in [pool.submit(_ready) for _ in range(workers)]:
            f.result()
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if held:
        os.kill(os.getpid(), held[0])  # now, with the usual handler


def _worker_init(parent_pid: int) -> None:
    # a forked worker inherits the parent's handlers: the console scripts' SIGTERM handler (SIGTERM ->
    # KeyboardInterrupt) would turn terminate() into an exception the worker reports and survives, and
    # the handlers of _start_workers would hold its stops back
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.signal(signal.SIGINT, signal.default_int_handler)
    die_with_parent(parent_pid)


def die_with_parent(parent_pid: int) -> None:
    """Have the kernel kill this process when its parent dies, however the parent dies (SIGKILL
    included: no handler of the parent's runs then). Linux ``prctl(PR_SET_PDEATHSIG)``; elsewhere a no-op.
    If the parent is already gone, exit now."""
    if not sys.platform.startswith("linux"):
        return
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGKILL, 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        return
    if os.getppid() != parent_pid:  # the parent died before the call: nobody would signal us
        os._exit(1)


KILL_AT_ENV = "RANGEMCL_KILL_AT"


def kill_point(name: str) -> None:
    """A named moment of a long run at which the tests kill it outright: when ``$RANGEMCL_KILL_AT`` is
    ``name``, the process sends itself SIGKILL here (no handler, no cleanup runs, as with ``kill -9`` or
    a power cut). Nothing happens otherwise."""
    if os.environ.get(KILL_AT_ENV) == name:
        os.kill(os.getpid(), signal.SIGKILL)


# The watchdog of :func:`descendants_die_with_me`, run as ``python -c``: it watches the process that
# started it (argv[1], its parent) and, every interval (argv[2] s), notes that process's descendants (pid
# and start time, from /proc). Its stdin carries markers (a line each) and, at a normal end of the block,
# an end line (a NUL byte) before it closes. Its stdin closing without that line, or the parent's pid
# changing (a forked child may keep the pipe open), means the parent died (killed, SIGKILL included): it
# kills every process it last saw below it that is still the same process (same start time), and every
# process whose command line or environment holds one of the markers, then exits. (The closed pipe is not
# checked against the parent's pid: a dying process closes its files before it is reparented, so for a
# moment a killed parent still looked alive, and the watchdog took the death for a normal end.)
_WATCHDOG = r"""
import os, select, signal, sys, time
watched, interval = int(sys.argv[1]), float(sys.argv[2])
def table():
    rows = {}
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    s = f.read()
            except OSError:
                continue
            rest = s[s.rindex(")") + 2:].split()
            rows[int(d)] = (int(rest[1]), rest[19])  # ppid, start time
    return rows
def below(rows, roots):
    seen, todo = {}, list(roots)
    while todo:
        p = todo.pop()
        for q, (pp, start) in rows.items():
            if pp == p and q not in seen and q != os.getpid():
                seen[q] = start
                todo.append(q)
    return seen
def signal_all(procs, sig):
    for p in procs:
        try:
            os.kill(p, sig)
        except OSError:
            pass
def marked(rows):
    found = {}
    for p, (_, start) in rows.items():
        if p == os.getpid():
            continue
        for part in ("cmdline", "environ"):
            try:
                with open(f"/proc/{p}/{part}", "rb") as f:
                    text = f.read().decode(errors="replace")
            except OSError:
                continue
            if any(m in text for m in markers):
                found[p] = start
                break
    return found
last, markers, buf, eof = {}, [], b"", False
fd = sys.stdin.fileno()
while True:
    ready, _, _ = select.select([] if eof else [fd], [], [], interval)
    if ready:
        chunk = os.read(fd, 65536)
        buf, eof = buf + chunk, not chunk
    *lines, buf = buf.split(b"\n")
    for line in lines:
        if line == b"\0":  # the block ended normally
            sys.exit(0)
        if line.strip():
            markers.append(line.strip().decode(errors="replace"))
    rows = table()
    if not eof and os.getppid() == watched:  # a dead parent (even one not yet reaped) has handed us on
        last.update(below(rows, [watched]))
        last = {p: s for p, s in last.items() if rows.get(p, (0, None))[1] == s}
        continue
    # what lives of the last look, what carries a marker, and what those started since: stopped first
    # (so that none starts another meanwhile) until the set stops growing, then killed
    doomed = {}
    for _ in range(20):
        rows = table()
        grown = {p: s for p, s in last.items() if rows.get(p, (0, None))[1] == s}
        grown.update(marked(rows) if markers else {})
        grown.update(below(rows, list(grown)))
        signal_all(grown, signal.SIGSTOP)
        if grown.keys() == doomed.keys():
            break
        doomed = last = grown
    signal_all(doomed, signal.SIGKILL)
    sys.exit(0)
"""


class _Watchdog:
    def __init__(self, pipe):
        self._pipe = pipe

    def also(self, marker: str) -> None:
        """Kill too, on this process's death, every process whose command line or environment holds
        ``marker`` (for those started after the watchdog's last look whose parent died first)."""
        if self._pipe is not None and marker.strip() and "\n" not in marker and "\0" not in marker:
            self._pipe.write(marker.strip().encode() + b"\n")
            self._pipe.flush()

    def end(self) -> None:
        """The block ended normally: the watchdog exits without killing anything."""
        if self._pipe is not None:
            with contextlib.suppress(OSError):  # a watchdog already gone
                self._pipe.write(b"\0\n")
                self._pipe.flush()


@contextmanager
def descendants_die_with_me(interval_s: float = 0.2) -> Iterator[_Watchdog]:
    """Within the block, a watchdog process kills this process's descendants if this process dies,
    however it dies (SIGKILL included). For children that ``die_with_parent`` cannot reach: the processes
    of a local Ray instance (GCS, raylet, its agents and workers), of which some would otherwise outlive a
    killed driver by a minute or more. A process started less than ``interval_s`` before the death whose
    parent died first escapes the tree: ``also(marker)`` names it by its command line or by an environment
    entry that it inherited (a child forked but not yet exec'd still has its parent's command line).
    Linux only (/proc); elsewhere a no-op."""
    if not sys.platform.startswith("linux"):
        yield _Watchdog(None)
        return
    import subprocess

    dog = subprocess.Popen(
        [sys.executable, "-c", _WATCHDOG, str(os.getpid()), str(interval_s)],
        stdin=subprocess.PIPE,
        start_new_session=True,  # a Ctrl-C to the terminal's group is the driver's to handle, not its
    )
    watchdog = _Watchdog(dog.stdin)
    try:
        yield watchdog
    finally:
        watchdog.end()
        with contextlib.suppress(OSError):
            dog.stdin.close()
        dog.wait()
