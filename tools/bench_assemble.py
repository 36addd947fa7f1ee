#!/usr/bin/env python3
"""Peak memory of the map builder's last step: the tiles' meshes into one map folder.

Cuts an existing map folder into one mesh file per tile (as build-map's tile jobs leave them), then, each
in a fresh process so that its peak memory is its own:

- ``streamed``: :func:`rangemcl.mapping.assemble.assemble_map` (what build-map does), one tile at a time;
- ``in memory``: the tiles concatenated, :meth:`MeshMap.from_mesh`, :meth:`MeshMap.save` (what build-map
  did before), the peer.

and checks that both folders load to the same map. Prints time and peak memory of each, and their ratio.

    python tools/bench_assemble.py /tmp/maps/large_full_map
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

# each step runs in a fresh interpreter: PRELUDE, then its body, then EPILOGUE
PRELUDE = """
import json, sys, time
from pathlib import Path
import numpy as np
work = Path(sys.argv[1])
parts = sorted((work / "tiles").glob("*.npz"))
def hwm_mb():  # this process's own high-water mark (ru_maxrss would include the parent's, across fork + exec)
    for line in open("/proc/self/status"):
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
base = hwm_mb()
t0 = time.perf_counter()
"""

EPILOGUE = """
print(json.dumps({"seconds": time.perf_counter() - t0, "baseline_mb": base, "peak_mb": hwm_mb()}))
"""

STREAMED = """
from rangemcl.mapping.assemble import assemble_map
assemble_map(parts, work / "streamed", tile_size_m=float(sys.argv[2]), work_dir=work / "spool",
             meta={"created_by": "bench_assemble"}, drive_xy=None)
"""

IN_MEMORY = """
from rangemcl.maps.meshmap import MeshMap
vs, fs, gs, offset = [], [], [], 0
for p in parts:
    z = np.load(p)
    vs.append(z["vertices"]); fs.append(z["faces"] + offset); gs.append(z["is_ground"])
    offset += len(z["vertices"])
m = MeshMap.from_mesh(np.concatenate(vs), np.concatenate(fs), np.concatenate(gs),
                      tile_size_m=float(sys.argv[2]), meta={"created_by": "bench_assemble"})
m.save(work / "in_memory")
"""


def run(script: str, work: Path, tile_m: float) -> dict:
    proc = subprocess.run(
        [sys.executable, "-c", PRELUDE + script + EPILOGUE, str(work), str(tile_m)],
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        print(proc.stderr[-3000:], file=sys.stderr)
        raise SystemExit("a run failed")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("map_dir", type=Path)
    ap.add_argument("--work", type=Path, default=Path("/tmp/rangemcl-bench-assemble"))
    ap.add_argument("--repeat", type=int, default=1, help="runs of each (medians reported)")
    args = ap.parse_args()
    from rangemcl.maps.meshmap import MeshMap

    m = MeshMap.load(args.map_dir)
    shutil.rmtree(args.work, ignore_errors=True)
    (args.work / "tiles").mkdir(parents=True)
    largest = 0
    for k in range(len(m.tiles)):
        idx = m.tile_faces([k])
        used, inverse = np.unique(m.faces[idx], return_inverse=True)
        np.savez(
            args.work / "tiles" / f"{k:05d}.npz",
            vertices=m.vertices[used],
            faces=inverse.reshape(-1, 3).astype(np.int32),
            is_ground=m.is_ground[used],
        )
        largest = max(largest, len(idx))
    print(
        f"{args.map_dir}: {m.n_triangles:,} triangles, {m.n_vertices:,} vertices in {len(m.tiles)} tiles "
        f"(largest {largest:,} triangles)"
    )
    tile_m = m.tile_size_m
    del m
    rows = {"streamed": [], "in memory": []}
    for _ in range(args.repeat):
        for name, script in (("streamed", STREAMED), ("in memory", IN_MEMORY)):
            shutil.rmtree(args.work / ("streamed" if name == "streamed" else "in_memory"), ignore_errors=True)
            rows[name].append(run(script, args.work, tile_m))
    med = {
        name: {k: float(np.median([r[k] for r in rs])) for k in ("seconds", "baseline_mb", "peak_mb")}
        for name, rs in rows.items()
    }
    for name, r in med.items():
        print(
            f"{name:>10}: {r['seconds']:6.1f} s, peak {r['peak_mb']:6.0f} MB "
            f"(of which {r['baseline_mb']:.0f} MB before the step: Python and imports)"
        )
    s, p = med["streamed"], med["in memory"]
    above = (s["peak_mb"] - s["baseline_mb"]) / (p["peak_mb"] - p["baseline_mb"])
    print(
        f"streamed / in memory: time {s['seconds'] / p['seconds']:.2f}x, "
        f"memory above the baseline {above:.2f}x"
    )
    a, b = MeshMap.load(args.work / "streamed"), MeshMap.load(args.work / "in_memory")
    same = all(
        np.array_equal(x, y)
        for x, y in (
            (a.vertices, b.vertices),
            (a.faces, b.faces),
            (a.face_tile, b.face_tile),
        )
    ) and np.array_equal(a.ground.heights, b.ground.heights, equal_nan=True)
    print(f"both folders load to the same map: {same}")
    if not same:
        raise SystemExit(1)


if __name__ == "__main__":
    main()
