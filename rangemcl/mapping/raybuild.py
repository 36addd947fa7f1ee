"""The tile jobs of ``rangemcl build-map --backend ray``: one Ray task per tile, on a local Ray instance or
a cluster.

Each task is bounded by its own tile: it thins the tile's spooled points and reconstructs its mesh in a
fresh worker process (``max_calls=1``, so that a task's peak memory is its tile's alone and nothing one
tile allocated stays for the next). The driver writes each mesh into the build's work area as it arrives
(:func:`rangemcl.mapping.pipeline.write_tile`), so a build interrupted or killed part-way resumes with
``--resume`` from the tiles it had, exactly as with the process pool.

A task on the driver's node reads the spooled chunks from the work area directly; a task on another
node asks a reader actor pinned to the driver's node for them, one chunk at a time, so a cluster needs no
shared filesystem (every node needs this package installed, as for ``simbed trials --backend ray``).
"""

from __future__ import annotations

import contextlib
import io
import os
import resource
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

from rangemcl.common.pool import descendants_die_with_me
from rangemcl.errors import InputError

_OWNER_VAR = "RANGEMCL_RAY_OWNER"  # marks the processes of a local Ray instance this build started


def _ray():
    try:
        import ray
    except ImportError:
        raise InputError("backend 'ray' needs Ray: pip install 'simbed-rangemcl[ray]'") from None
    return ray


class ChunkReader:
    """Serves the spooled chunk files of one build's work area to tasks on other nodes."""

    def __init__(self, root: str):
        self.root = Path(root).resolve()

    def read(self, path: str) -> bytes:
        p = Path(path).resolve()
        if self.root not in p.parents:
            raise ValueError(f"{path}: not in the build's work area {self.root}")
        return p.read_bytes()


def tile_task(mesh_tile: Callable, job, driver_node: str, reader, via_reader: bool = False):
    """A Ray task: the mesh of one tile, ``mesh_tile(job, sources) -> (vertices, faces, is_ground,
    stats)``; the stats carry the worker's peak memory (``peak_rss_mb``). ``via_reader`` makes a task on
    the driver's node fetch its chunks as a remote node's would (tests)."""
    import ray

    if via_reader or ray.get_runtime_context().get_node_id() != driver_node:
        sources = (io.BytesIO(ray.get(reader.read.remote(str(p)))) for p in job.chunks)
    else:
        sources = job.chunks
    v, f, is_ground, stats = mesh_tile(job, sources)
    stats["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return v, f, is_ground, stats


def run_tiles(
    jobs: list,
    mesh_tile: Callable,
    write: Callable,
    *,
    work_dir: Path,
    workers: int,
    address: str | None = None,
    via_reader: bool = False,
) -> Iterator[dict]:
    """Build ``jobs`` (``TileJob``) as Ray tasks, each ``mesh_tile(job, sources)`` (the builder's tile job, a
    module-level function that the workers import), and ``write(job, v, f, is_ground, stats)`` each result
    as it arrives; yields the written stats. ``address`` None starts a local instance of ``workers`` CPUs (and
    shuts it down afterwards); otherwise the tasks go to that cluster (``"auto"``: the one this machine
    belongs to). An interruption cancels the tasks not finished."""
    if not jobs:
        return
    ray = _ray()
    started = not ray.is_initialized()
    with contextlib.ExitStack() as stack:
        # a local instance's processes die with this one, even when it is killed outright
        watchdog = stack.enter_context(descendants_die_with_me()) if started else None
        if watchdog is not None and address is None:
            stack.enter_context(_owner_mark(watchdog))
        yield from _run(
            ray, jobs, mesh_tile, write, work_dir, workers, address, via_reader, started, watchdog
        )


@contextlib.contextmanager
def _owner_mark(watchdog) -> Iterator[None]:
    """An environment entry that every process of the local Ray instance inherits, named to the watchdog:
    a worker the raylet forks as this process dies is orphaned before the watchdog's next look, and its
    command line may still be the raylet's; its environment carries the mark from the fork on."""
    token = uuid.uuid4().hex
    os.environ[_OWNER_VAR] = token
    watchdog.also(f"{_OWNER_VAR}={token}")
    try:
        yield
    finally:
        os.environ.pop(_OWNER_VAR, None)


def _run(ray, jobs, mesh_tile, write, work_dir, workers, address, via_reader, started, watchdog):
    from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

    if started:
        try:
            ray.init(
                address=address,
                num_cpus=None if address else workers,
                include_dashboard=False,
                log_to_driver=False,
                logging_level="ERROR",
            )
        except (ConnectionError, RuntimeError, ValueError, OSError) as err:
            raise InputError(f"Ray at {address or 'a local instance'}: {err}") from None
    pending: list = []
    try:
        if watchdog is not None and address is None:
            # its workers carry the session's name (a worker the raylet starts as this process dies is
            # orphaned before the watchdog sees it)
            watchdog.also(f"--session-name={ray.get_runtime_context().get_session_name()}")
        here = ray.get_runtime_context().get_node_id()
        reader = (
            ray.remote(num_cpus=0)(ChunkReader)
            .options(scheduling_strategy=NodeAffinitySchedulingStrategy(node_id=here, soft=False))
            .remote(str(work_dir))
        )
        task = ray.remote(num_cpus=1, max_calls=1)(tile_task)
        by_ref = {task.remote(mesh_tile, j, here, reader, via_reader): j for j in jobs}
        pending = list(by_ref)
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            job = by_ref[ready[0]]
            try:
                v, f, is_ground, stats = ray.get(ready[0])
            except ray.exceptions.RayError as err:
                first = str(err).strip().splitlines()[-1] if str(err).strip() else type(err).__name__
                raise RuntimeError(f"tile {job.tile[0]}_{job.tile[1]}: the Ray task failed: {first}") from err
            yield write(job, v, f, is_ground, stats)
    finally:
        for ref in pending:
            ray.cancel(ref, force=True)
        if started:
            ray.shutdown()
