"""The process pool used by build-map and the trial suites: results as a plain pool gives them, and an
interrupted block stops its workers at once instead of waiting for their jobs."""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import time

import pytest

from rangemcl.common.pool import process_pool


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
from rangemcl.common.pool import process_pool

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


_ORPHANS = r"""
import os, signal, subprocess, sys, time
from rangemcl.common.pool import descendants_die_with_me

mark, pids = sys.argv[1], sys.argv[2]
with descendants_die_with_me(interval_s=60.0) as dog:  # no look after the marker's: only it finds them
    dog.also(mark)
    time.sleep(0.5)
    spawned = []
    for env in ({**os.environ, "ORPHAN_MARK": mark.split("=", 1)[1]}, dict(os.environ)):
        # a process whose parent exits at once: orphaned before the watchdog ever looks at it
        out = subprocess.run(
            [sys.executable, "-c",
             "import os, subprocess, sys; "
             "p = subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(120)'], "
             "start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL); print(p.pid)"],
            env=env, capture_output=True, text=True, check=True)
        spawned.append(out.stdout.strip())
    with open(pids, "w") as f:
        f.write(" ".join(spawned))
    os.kill(os.getpid(), signal.SIGKILL)
"""


def test_the_watchdog_kills_an_orphan_by_its_inherited_environment(tmp_path):
    """A process whose parent died before the watchdog looked is no longer below the killed process; an
    environment entry it inherited, named with ``also``, still finds it. One without the entry (the
    control) lives on: without the marker the watchdog would have missed both."""
    import signal
    import subprocess
    import sys
    import uuid

    if not sys.platform.startswith("linux"):
        pytest.skip("the watchdog reads /proc")
    mark = f"ORPHAN_MARK={uuid.uuid4().hex}"
    pids_file = tmp_path / "pids"
    run = subprocess.run(
        [sys.executable, "-c", _ORPHANS, mark, str(pids_file)], capture_output=True, text=True
    )
    assert run.returncode == -signal.SIGKILL, run.stderr
    marked, control = (int(p) for p in pids_file.read_text().split())
    try:
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and _alive(marked):
            time.sleep(0.05)
        assert not _alive(marked)
        assert _alive(control)
    finally:
        for pid in (marked, control):
            with contextlib.suppress(OSError):
                os.kill(pid, signal.SIGKILL)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            state = f.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state not in ("Z", "X")


_BLOCK = r"""
import signal, subprocess, sys, time
from rangemcl.common.pool import descendants_die_with_me

how, pids = sys.argv[1], sys.argv[2]
with descendants_die_with_me(interval_s=0.05):
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    with open(pids, "w") as f:
        f.write(str(child.pid))
    time.sleep(0.5)  # the watchdog has seen it below us
    if how == "kill":
        import os
        os.kill(os.getpid(), signal.SIGKILL)
"""


@pytest.mark.parametrize("how", ["end", "kill"])
def test_the_watchdog_kills_descendants_only_when_its_process_dies(tmp_path, how):
    """A child below the block's process: killed with that process's SIGKILL, left alone at the block's
    normal end (repeated: the end and the death were once told apart by a race)."""
    import signal
    import subprocess
    import sys

    if not sys.platform.startswith("linux"):
        pytest.skip("the watchdog reads /proc")
    for _ in range(3):
        pids_file = tmp_path / "pid"
        run = subprocess.run(
            [sys.executable, "-c", _BLOCK, how, str(pids_file)], capture_output=True, text=True
        )
        child = int(pids_file.read_text())
        try:
            if how == "kill":
                assert run.returncode == -signal.SIGKILL, run.stderr
                deadline = time.monotonic() + 5.0
                while time.monotonic() < deadline and _alive(child):
                    time.sleep(0.05)
                assert not _alive(child)
            else:
                assert run.returncode == 0, run.stderr
                time.sleep(0.5)
                assert _alive(child)
        finally:
            with contextlib.suppress(OSError):
                os.kill(child, signal.SIGKILL)
