#!/usr/bin/env python3
"""The map store of tiles (format 2) against the format it replaces: size on disk, time to open, time and
peak memory to load the whole map, time to read one tile.

Takes a map folder of format 1 (``mesh.ply`` + ``tiles.npz``, the older single-file format),
copies it and upgrades the copy (``rangemcl map-upgrade``), then measures both, each step in a fresh
interpreter so that its peak memory (``ru_maxrss``) is its own, alternating the formats ``--repeats``
times:

- ``open``: format 2 reads ``map.yaml`` and ``tiles.json`` only (:meth:`TileStore.open`); format 1 has no
  such step (its ``MeshMap.load`` reads everything);
- ``load``: :meth:`MeshMap.load`, the whole map in memory (what ``rangemcl localize`` does today);
- ``tile``: median time to read one tile (format 2, every tile once; checksum included).

    python tools/bench_map_store.py out/demo/map
    python tools/bench_map_store.py DATA/large_full_map --repeats 2

Medians; the machine is shared, so compare the ratios of one run.
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

STEP = r"""
import json, resource, sys, time
from pathlib import Path
from rangemcl.maps.meshmap import MeshMap
from rangemcl.maps.store import TileStore
kind, d = sys.argv[1], Path(sys.argv[2])
t = time.perf_counter()  # after the imports: the map's own time
out = {}
if kind == "open":
    s = TileStore.open(d)
    out["tiles"] = len(s.entries)
elif kind == "load":
    m = MeshMap.load(d)
    out["triangles"] = m.n_triangles
elif kind == "tile":
    s = TileStore.open(d)
    times = []
    for k in range(len(s.entries)):
        t0 = time.perf_counter()
        s.read(k)
        times.append(time.perf_counter() - t0)
    times.sort()
    out["tile_median_s"] = times[len(times) // 2]
    out["tile_max_s"] = times[-1]
out["seconds"] = time.perf_counter() - t
out["peak_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
print(json.dumps(out))
"""


def step(kind: str, map_dir: Path) -> dict:
    r = subprocess.run([sys.executable, "-c", STEP, kind, str(map_dir)], capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(
            f"{kind} {map_dir}: {r.stderr.strip().splitlines()[-1] if r.stderr.strip() else r.returncode}"
        )
    return json.loads(r.stdout.strip().splitlines()[-1])


def disk_bytes(d: Path) -> int:
    names = {"mesh.ply", "tiles.npz", "tiles.json", "ground.npz", "drive.npz", "map.yaml"}
    files = [p for p in d.iterdir() if p.name in names] + list((d / "tiles").glob("*.npz"))
    return sum(p.stat().st_size for p in files if p.is_file())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("map", type=Path, help="a map folder of format 1")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument(
        "--work", type=Path, default=None, help="where the upgraded copy goes (default: a temp folder)"
    )
    a = ap.parse_args()
    if not (a.map / "mesh.ply").is_file():
        sys.exit(f"{a.map}: not a map folder of format 1 (no mesh.ply)")
    work = a.work or Path(tempfile.mkdtemp(prefix="bench-map-store-"))
    v2 = work / "map_v2"
    shutil.rmtree(v2, ignore_errors=True)
    shutil.copytree(a.map, v2)
    t = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; from rangemcl.cli import main; sys.argv[0]='rangemcl'; main()",
            "map-upgrade",
            str(v2),
        ],
        capture_output=True,
        text=True,
    )
    if t.returncode != 0:
        sys.exit(t.stderr)
    rows: dict[str, list[dict]] = {"v1 load": [], "v2 open": [], "v2 load": [], "v2 tile": []}
    for _ in range(a.repeats):
        rows["v1 load"].append(step("load", a.map))
        rows["v2 open"].append(step("open", v2))
        rows["v2 load"].append(step("load", v2))
        rows["v2 tile"].append(step("tile", v2))
    med = {k: {f: statistics.median(r[f] for r in v) for f in v[0]} for k, v in rows.items()}
    size1, size2 = disk_bytes(a.map), disk_bytes(v2)
    print(f"map {a.map}: {med['v1 load']['triangles']:,.0f} triangles, {med['v2 open']['tiles']:.0f} tiles")
    print(
        f"on disk:  format 1 {size1 / 1e6:.1f} MB, format 2 {size2 / 1e6:.1f} MB (ratio {size2 / size1:.2f})"
    )
    print(
        f"open:     format 2 index only {med['v2 open']['seconds'] * 1e3:.1f} ms, "
        f"peak {med['v2 open']['peak_mb']:.0f} MB"
    )
    print(
        f"load:     format 1 {med['v1 load']['seconds']:.2f} s, peak {med['v1 load']['peak_mb']:.0f} MB; "
        f"format 2 {med['v2 load']['seconds']:.2f} s, peak {med['v2 load']['peak_mb']:.0f} MB "
        f"(time ratio {med['v2 load']['seconds'] / med['v1 load']['seconds']:.2f}, "
        f"peak ratio {med['v2 load']['peak_mb'] / med['v1 load']['peak_mb']:.2f})"
    )
    print(
        f"one tile: median {med['v2 tile']['tile_median_s'] * 1e3:.1f} ms, "
        f"slowest {med['v2 tile']['tile_max_s'] * 1e3:.1f} ms (read, checksum, checks)"
    )
    print(json.dumps({"disk_bytes": [size1, size2], **med}))
    if a.work is None:
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
