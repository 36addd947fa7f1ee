#!/usr/bin/env python3
"""``rangemcl build-map`` with the process pool against ``--backend ray`` (a local Ray instance), and a Ray
build killed with SIGKILL part-way through its tiles and resumed.

    python tools/bench_build_backends.py --seq out/demo/mapping_drive --truth out/truth.ply \
        --out /tmp/rangemcl-backends [--config settings.yaml] [--kill-after 0.5]

Runs, each through the console script in its own process: (1) the pool build, (2) the Ray build, (3) a Ray
build sent SIGKILL once ``--kill-after`` of the tiles are in its work area, the processes of its process
group and Ray session listed 2 s after the kill, then ``--resume``. Prints, and writes as JSON: wall time
and peak memory of each build, tile sets and triangle counts, whether every map file is the same bytes,
``rangemcl map-quality`` of each map against the truth, the tiles the resumed run took from the killed one
and the processes left behind by the kill.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path


def build(seq: Path, out: Path, extra: list[str], config: Path | None) -> dict:
    cmd = ["rangemcl", "build-map", str(seq), "--out", str(out), *extra]
    if config:
        cmd += ["--config", str(config)]
    t0 = time.monotonic()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.monotonic() - t0
    if r.returncode != 0:
        sys.exit(f"{' '.join(cmd)} failed:\n{r.stderr}")
    report = json.loads((out / "report.json").read_text())
    return {
        "command": " ".join(cmd),
        "wall_s": round(wall, 1),
        "peak_main_mb": round(report["peak_rss_main_mb"]),
        "peak_tile_job_mb": round(report["peak_rss_tile_jobs_mb"]),
        "tiles_resumed": report["tiles_resumed"],
        "stdout": r.stdout.strip(),
    }


def tiles(m: Path) -> dict:
    index = json.loads((m / "tiles.json").read_text())
    return {"_".join(map(str, t["ij"])): t["triangles"] for t in index["tiles"]}


def same_files(a: Path, b: Path) -> bool:
    def files(m):
        return sorted(str(p.relative_to(m)) for p in m.rglob("*") if p.is_file() and p.name != "report.json")

    return files(a) == files(b) and all((a / n).read_bytes() == (b / n).read_bytes() for n in files(a))


def quality(m: Path, truth: Path, seq: Path) -> dict:
    out = m.with_suffix(".quality.json")
    r = subprocess.run(
        [
            "rangemcl",
            "map-quality",
            str(m),
            "--truth",
            str(truth),
            "--reference",
            str(seq),
            "--json",
            str(out),
        ],
        capture_output=True,
        text=True,
    )
    if r.returncode != 0:
        sys.exit(r.stderr)
    return json.loads(out.read_text())


def killed_then_resumed(seq: Path, out: Path, config: Path | None, share: float) -> dict:
    cmd = ["rangemcl", "build-map", str(seq), "--out", str(out), "--backend", "ray"]
    if config:
        cmd += ["--config", str(config)]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    work = out / ".build"
    total = None
    while proc.poll() is None:
        state = work / "state.json"
        if total is None and state.is_file():
            total = len(json.loads(state.read_text())["chunks"])
        done = len(list(work.glob("mesh_*.json"))) if work.is_dir() else 0
        if total and done >= max(1, round(share * total)):
            break
        time.sleep(0.2)
    if proc.poll() is not None:
        sys.exit("the build ended before it could be killed: lower --kill-after")
    done = len(list(work.glob("mesh_*.json")))
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait()
    time.sleep(2.0)
    left = []
    for p in Path("/proc").iterdir():
        if not p.name.isdigit():
            continue
        try:
            line = (p / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            ours = os.getpgid(int(p.name)) == proc.pid or ("ray" in line and "session_" in line)
            if ours and "zombie" not in (p / "status").read_text().lower():
                left.append(line[:120])
        except OSError:
            continue
    resumed = build(seq, out, ["--backend", "ray", "--resume"], config)
    return {
        "tile_jobs": total,
        "tile_jobs_done_at_kill": done,
        "processes_left_2s_after_kill": left,
        **resumed,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seq", type=Path, required=True, help="A mapping drive.")
    ap.add_argument("--truth", type=Path, required=True, help="The true static mesh (simbed export-mesh).")
    ap.add_argument("--out", type=Path, default=Path("/tmp/rangemcl-backends"))
    ap.add_argument("--config", type=Path, default=None, help="build-map settings for all three builds.")
    ap.add_argument("--kill-after", type=float, default=0.5, help="Share of the tile jobs done at the kill.")
    args = ap.parse_args()
    shutil.rmtree(args.out, ignore_errors=True)
    args.out.mkdir(parents=True)
    pool, ray_, killed = args.out / "pool", args.out / "ray", args.out / "ray_killed"
    res = {"pool": build(args.seq, pool, [], args.config)}
    res["ray"] = build(args.seq, ray_, ["--backend", "ray"], args.config)
    res["ray_killed_then_resumed"] = killed_then_resumed(args.seq, killed, args.config, args.kill_after)
    t = {k: tiles(m) for k, m in (("pool", pool), ("ray", ray_), ("ray_killed", killed))}
    res["tiles"] = t["pool"]
    res["same_tiles_and_triangles"] = t["pool"] == t["ray"] == t["ray_killed"]
    res["same_bytes_ray"] = same_files(pool, ray_)
    res["same_bytes_ray_killed"] = same_files(pool, killed)
    res["quality"] = {k: quality(m, args.truth, args.seq) for k, m in (("pool", pool), ("ray", ray_))}
    (args.out / "backends.json").write_text(json.dumps(res, indent=2))
    for k in ("pool", "ray", "ray_killed_then_resumed"):
        r = res[k]
        print(
            f"{k:<24} {r['wall_s']:>7.1f} s  peak main {r['peak_main_mb']} MB, "
            f"tile job {r['peak_tile_job_mb']} MB"
            + (f", resumed {r['tiles_resumed']} tiles" if r["tiles_resumed"] else "")
        )
    k = res["ray_killed_then_resumed"]
    print(
        f"killed with {k['tile_jobs_done_at_kill']}/{k['tile_jobs']} tile jobs done; "
        f"left: {k['processes_left_2s_after_kill']}"
    )
    print(
        f"tiles: {len(res['tiles'])}, triangles {sum(res['tiles'].values()):,}; same tiles and triangles: "
        f"{res['same_tiles_and_triangles']}; same bytes: ray {res['same_bytes_ray']}, killed+resumed "
        f"{res['same_bytes_ray_killed']}"
    )
    for key in ("surface_dist_median_m", "vertex_dist_median_m", "completeness"):
        print(f"{key:<24} pool {res['quality']['pool'][key]:.5f}  ray {res['quality']['ray'][key]:.5f}")
    print(f"wrote {args.out / 'backends.json'}")


if __name__ == "__main__":
    main()
