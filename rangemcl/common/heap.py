"""What a long-running localizer does so that memory it frees goes back to the system.

The localizer's map tiles come and go: a tile is read (float64 vertices, faces), checked, turned into a
Warp BVH in a loader thread, and evicted later. With glibc's defaults the arrays freed on the way stay in
the process's heap, and the next tile's BVH, whose arrays Warp allocates larger than it writes, lands on
those already-touched pages, so the resident size grows beyond what the tiles hold (measured on
``town_large``'s 60 tiles: 607 MiB resident for BVHs that take 416 MiB when built into fresh memory;
``docs/architecture.md``, "Design decisions and why"). Two remedies, both no-ops where glibc is absent:

- :func:`return_freed_memory`: allocations from 8 MiB up come from ``mmap`` and go back when freed.
- :func:`trim_freed_memory`: ``malloc_trim(0)``, which hands the whole free pages inside every malloc
  arena back to the system; the tile loader calls it after each tile (a few milliseconds).
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
import sys

MMAP_THRESHOLD = 8 << 20  # bytes: allocations this large come from mmap (return_freed_memory)


@functools.cache
def _libc():
    """glibc, or None (another C library or platform)."""
    if not sys.platform.startswith("linux"):
        return None
    name = ctypes.util.find_library("c")
    if not name:
        return None
    try:
        libc = ctypes.CDLL(name)
        libc.mallopt, libc.malloc_trim  # noqa: B018 (glibc's, not musl's)
    except (OSError, AttributeError):
        return None
    return libc


def return_freed_memory() -> None:
    """Ask glibc to serve allocations from 8 MiB up by mmap, so that an evicted tile's large arrays (its
    BVH, its vertices) go back to the system: with the default threshold, which grows with the largest
    block freed, evicted tiles left the resident size at 3x the live bytes (``docs/architecture.md``,
    "Design decisions and why"). At 1 MiB the localizer's per-frame arrays were mmapped too and a frame
    took 1.2x as long (measured on the dense map of ``tools/bench_large_map.py``); at 8 MiB the frame time
    is that of the default."""
    libc = _libc()
    if libc is not None:
        with contextlib.suppress(OSError):
            libc.mallopt(-3, MMAP_THRESHOLD)  # M_MMAP_THRESHOLD


def trim_freed_memory() -> None:
    """Give the free pages of every malloc arena back to the system (``malloc_trim(0)``)."""
    libc = _libc()
    if libc is not None:
        with contextlib.suppress(OSError):
            libc.malloc_trim(0)
