"""The process pool used by build-map and the trial suites: results as a plain pool gives them, and an
interrupted block stops its workers at once instead of waiting for their jobs."""

from __future__ import annotations

import multiprocessing
import os
import time

import pytest

from rangemcl.pool import process_pool


def _square(x: int) -> int:
    return x * x


def _pid_then_sleep(seconds: float) -> int:
    time.sleep(seconds)
    return os.getpid()


@pytest.mark.parametrize("context", [None, "spawn"])
def test_results_in_order(context):
    with process_pool(2, context) as pool:
        assert list(pool.map(_square, range(7))) == [x * x for x in range(7)]
    assert not multiprocessing.active_children()


@pytest.mark.parametrize("context", [None, "spawn"])
def test_interrupt_terminates_running_workers(context):
    # repeated: the pool's own manager thread reaps the dying workers too, a race that once left a dead
    # worker listed as running in about 1 run of 4
    for _ in range(3):
        _interrupt_once(context)


def _interrupt_once(context):
    before = set(multiprocessing.active_children())
    clock = time.perf_counter()
    with pytest.raises(KeyboardInterrupt), process_pool(2, context) as pool:
        futures = [pool.submit(_pid_then_sleep, 60) for _ in range(6)]
        time.sleep(1.0)  # both workers are inside a 60 s job
        raise KeyboardInterrupt
    assert time.perf_counter() - clock < 20  # a plain executor would wait about 3 x 60 s
    assert set(multiprocessing.active_children()) <= before
    assert all(f.cancelled() or f.done() for f in futures)


_STOP_DURING_SPAWN = r"""
import os, signal, sys, threading
from concurrent.futures import ProcessPoolExecutor
from rangemcl.pool import process_pool

spawned = []


def stop(signum, frame):  # the console scripts' SIGTERM handler
    raise KeyboardInterrupt


def spawn_after_a_stop(self, original=ProcessPoolExecutor._spawn_process):
    # SIGTERM, sent from another thread, is pending when the worker is spawned: Python runs its handler
    # in the main thread at the next instruction, in the middle of writing the start-up message
    if not spawned:
        t = threading.Thread(target=os.kill, args=(os.getpid(), signal.SIGTERM))
        t.start()
        t.join()
    original(self)
    spawned.append(1)


if __name__ == "__main__":  # a spawned worker imports this file too: only the parent sets things up
    signal.signal(signal.SIGTERM, stop)
    # a thread started earlier (as a thread pool's) lives on with the signal mask of its start: the
    # kernel hands it the signal whatever the main thread blocks
    threading.Thread(target=threading.Event().wait, daemon=True).start()
    ProcessPoolExecutor._spawn_process = spawn_after_a_stop
    try:
        with process_pool(2, "spawn"):
            print("not stopped")
    except KeyboardInterrupt:
        print(f"stopped after {len(spawned)} workers")
"""


def test_a_stop_while_workers_spawn_waits_for_them(tmp_path):
    """SIGTERM landing while a spawned worker is being started acts once every worker is up: the stop
    still happens, and no worker prints a half-read start-up message's traceback on the terminal."""
    import subprocess
    import sys

    script = tmp_path / "stop_during_spawn.py"
    script.write_text(_STOP_DURING_SPAWN)
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "stopped after 2 workers"
    assert "Traceback" not in r.stderr, r.stderr
