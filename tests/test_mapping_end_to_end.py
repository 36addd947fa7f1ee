"""A recorded drive through the map builder, measured against the scene's true surface; and the builder's
answers to bad sequences."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from rangemcl.config import load_config
from rangemcl.datasets.kitti import SequenceWriter, load_sequence
from rangemcl.errors import InputError
from rangemcl.mapping.pipeline import MapSettings, build_map
from rangemcl.mapping.quality import map_quality
from rangemcl.maps.meshmap import MeshMap, import_mesh
from simbed.record import record
from simbed.sim.geometry import write_ply
from simbed.sim.world import World


@pytest.fixture(scope="module")
def drive(tmp_path_factory):
    root = tmp_path_factory.mktemp("e2e")
    seq = root / "seq"
    record("town_small", "mapping", "os1-64", seq, frames=12, seed=3, progress=False)
    world = World("town_small")
    truth = root / "truth.ply"
    write_ply(truth, *world.static_triangles)
    return root, seq, truth


def fast_settings() -> MapSettings:
    s = MapSettings()
    s.poisson.depth = 8
    s.workers = 2
    return s


def test_map_from_a_drive_matches_the_true_surface(drive):
    root, seq, truth = drive
    out = root / "map"
    report = build_map(seq, out, fast_settings())
    m = MeshMap.load(out)
    assert report.scans_used == 12 and m.n_triangles == report.triangles > 10_000
    assert report.triangles < report.triangles_before_simplify  # ground simplification did something
    assert report.ground_triangles_after < 0.5 * report.ground_triangles_before
    t = import_mesh(truth)
    s = load_sequence(seq)
    ref = np.concatenate([s.scan(i) @ s.poses[i][:3, :3].T + s.poses[i][:3, 3] for i in range(len(s))])
    q = map_quality(m.vertices, m.faces, t.vertices, t.faces, reference_points=ref[::20])
    assert q["surface_dist_median_m"] < 0.05 and q["vertex_dist_median_m"] < 0.15
    assert q["completeness"] > 0.75
    # the ground lookup agrees with the true terrain under the drive
    xy = s.poses[:, :2, 3]
    z_truth = World("town_small").ground_height(xy[:, 0], xy[:, 1])
    assert np.abs(m.ground.height_at(xy[:, 0], xy[:, 1]) - z_truth).max() < 0.15
    # the run wrote its effective settings and a report
    assert load_config(MapSettings, out / "config.yaml") == fast_settings()
    saved = json.loads((out / "report.json").read_text())
    assert saved["scans_used"] == 12
    # tile jobs ran in spawned workers, so the two peaks are measured apart
    assert saved["peak_rss_tile_jobs_mb"] > 0 and saved["peak_rss_main_mb"] > 0
    assert saved["peak_rss_mb"] == max(saved["peak_rss_tile_jobs_mb"], saved["peak_rss_main_mb"])


def test_bad_scans_are_skipped_and_counted(drive, tmp_path):
    _, seq, _ = drive
    s = load_sequence(seq)
    bad = tmp_path / "bad"
    with SequenceWriter(bad, meta=dict(s.meta)) as w:
        for i in range(4):
            pts = s.scan(i).copy()
            if i == 1:
                pts[::10] = np.nan  # some NaN points
            if i == 2:
                pts[:] = np.nan  # no valid point at all
            w.add_frame(pts, pose=s.poses[i], time_s=float(s.times[i]))
    report = build_map(bad, tmp_path / "map", fast_settings())
    assert report.scans_skipped_empty == 1 and report.scans_used == 3
    assert report.points_nonfinite == len(s.scan(2)) + len(s.scan(1)[::10])


def test_bad_sequences_are_input_errors(drive, tmp_path):
    _, seq, _ = drive
    copy = tmp_path / "copy"
    shutil.copytree(seq, copy)
    (copy / "poses.txt").unlink()
    with pytest.raises(InputError, match="poses"):
        build_map(copy, tmp_path / "m1", fast_settings())
    shutil.rmtree(copy)
    shutil.copytree(seq, copy)
    scan = copy / "velodyne" / "000003.bin"
    scan.write_bytes(scan.read_bytes()[:-7])
    with pytest.raises(InputError, match=r"000003.bin.*truncated"):
        build_map(copy, tmp_path / "m2", fast_settings())
    blocker = tmp_path / "file"
    blocker.write_text("x")
    with pytest.raises(InputError, match="cannot write"):
        build_map(seq, blocker / "map", fast_settings())
    assert not (tmp_path / "m1").exists() and not (tmp_path / "m2").exists()


def test_cli_one_line_errors(tmp_path):
    code = "import sys; from rangemcl.cli import main; sys.argv[0] = 'rangemcl'; main()"
    out = subprocess.run(
        [sys.executable, "-c", code, "build-map", str(tmp_path / "nope"), "--out", str(tmp_path / "m")],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1 and "nope" in out.stderr
    cfg = tmp_path / "c.yaml"
    cfg.write_text("poisson:\n  dept: 8\n")
    out = subprocess.run(
        [
            sys.executable,
            "-c",
            code,
            "build-map",
            str(tmp_path),
            "--out",
            str(tmp_path / "m"),
            "--config",
            str(cfg),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 2 and "poisson.dept" in out.stderr and "depth" in out.stderr


def test_sigterm_keeps_the_work_for_resume_and_stops_the_workers(drive, tmp_path):
    """`kill` (SIGTERM) during the tile stage: build-map exits within seconds, leaves nothing in the
    system's temp folder and no worker behind, keeps its finished work in the map folder (said in one
    line); a plain rerun is refused naming --resume, and --resume (with another worker count) finishes a
    map identical, byte for byte, to an uninterrupted build."""
    import os
    import signal
    import time

    _, seq, _ = drive
    work = tmp_path / "tmp"
    work.mkdir()
    code = "import sys; from rangemcl.cli import main; sys.argv[0] = 'rangemcl'; main()"
    proc = subprocess.Popen(
        [sys.executable, "-c", code, "build-map", str(seq), "--out", str(tmp_path / "m")],
        env={**os.environ, "TMPDIR": str(work)},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )

    def children() -> set[int]:
        try:
            text = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text()
        except OSError:
            return set()
        return {int(p) for p in text.split()}

    deadline = time.monotonic() + 120
    while len(children()) < 2 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)  # the tile workers (and multiprocessing's resource tracker) have started
    workers = children()
    assert proc.poll() is None and len(workers) >= 2 and (tmp_path / "m" / ".build").is_dir()
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=30)
    assert proc.returncode != 0
    assert not list(work.iterdir()), err  # nothing in the system's temp folder
    assert not (tmp_path / "m" / "map.yaml").exists() and not (tmp_path / "m" / "tiles.json").exists()
    time.sleep(0.5)
    assert not [p for p in workers if os.path.exists(f"/proc/{p}") and "zombie" not in _state(p)]
    # the scan stage had finished: its work is kept in the map folder, and said so in one line
    assert (tmp_path / "m" / ".build" / "state.json").is_file()
    assert "--resume" in err and "Traceback" not in err

    def build(*extra):
        return subprocess.run(
            [sys.executable, "-c", code, "build-map", str(seq), *extra], capture_output=True, text=True
        )

    refused = build("--out", str(tmp_path / "m"))
    assert refused.returncode == 2 and "--resume" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1
    # resumed with another worker count (it does not change a tile's mesh: the same map, byte for byte)
    resumed = build("--out", str(tmp_path / "m"), "--resume", "--workers", "1")
    assert resumed.returncode == 0, resumed.stderr
    assert not (tmp_path / "m" / ".build").exists()  # the work area goes with the finished map
    assert MeshMap.load(tmp_path / "m").n_triangles > 10_000
    again = build("--out", str(tmp_path / "m"), "--resume")
    assert again.returncode == 2 and "nothing to resume" in again.stderr
    # the same map, byte for byte, as an uninterrupted build
    fresh = build("--out", str(tmp_path / "fresh"))
    assert fresh.returncode == 0, fresh.stderr
    names = sorted(str(p.relative_to(tmp_path / "fresh")) for p in (tmp_path / "fresh").rglob("*.npz"))
    assert "ground.npz" in names and any(n.startswith("tiles/") for n in names)
    assert "place_prior.npz" in names  # rendered as the build's last step
    for name in (*names, "tiles.json"):
        _same_file(tmp_path / "m" / name, tmp_path / "fresh" / name)
    # the place prior was the build's last step: the localizer and `rangemcl place-prior` find it stored
    assert "place prior built" in fresh.stdout
    from rangemcl.localization import build_localizer

    loc = build_localizer(MeshMap.load(tmp_path / "fresh"), threads=2)
    loc.place_prior()
    assert loc.prior_source == "loaded"
    again = subprocess.run(
        [sys.executable, "-c", code, "place-prior", str(tmp_path / "fresh")], capture_output=True, text=True
    )
    assert again.returncode == 0 and "place prior loaded" in again.stdout, again.stderr
    info = subprocess.run(
        [sys.executable, "-c", code, "map-info", str(tmp_path / "fresh")], capture_output=True, text=True
    )
    assert info.returncode == 0 and f"{len(loc.prior.xy)} cells of 2 m" in info.stdout, info.stderr
    missing = subprocess.run(
        [sys.executable, "-c", code, "place-prior", str(tmp_path / "nope")], capture_output=True, text=True
    )
    assert missing.returncode == 2 and len(missing.stderr.strip().splitlines()) == 1
    assert "nope" in missing.stderr


def _state(pid: int) -> str:
    try:
        return open(f"/proc/{pid}/status").read().lower()
    except OSError:
        return "zombie"


def test_sigkill_leaves_no_process_behind(drive, tmp_path):
    """`kill -9` during the tile stage: no handler of build-map runs, yet its tile workers and
    multiprocessing's resource tracker are gone within 2 s (the workers die with their parent)."""
    import os
    import signal
    import time

    _, seq, _ = drive
    code = "import sys; from rangemcl.cli import main; sys.argv[0] = 'rangemcl'; main()"
    proc = subprocess.Popen(
        [sys.executable, "-c", code, "build-map", str(seq), "--out", str(tmp_path / "m")],
        env={**os.environ, "TMPDIR": str(tmp_path)},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )

    def children() -> set[int]:
        try:
            text = Path(f"/proc/{proc.pid}/task/{proc.pid}/children").read_text()
        except OSError:
            return set()
        return {int(p) for p in text.split()}

    deadline = time.monotonic() + 120
    while len(children()) < 3 and proc.poll() is None and time.monotonic() < deadline:
        time.sleep(0.05)  # two tile workers and the resource tracker
    left = children()
    assert proc.poll() is None and len(left) >= 3
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    time.sleep(2.0)
    alive = [p for p in left if os.path.exists(f"/proc/{p}") and "zombie" not in _state(p)]
    assert not alive, [Path(f"/proc/{p}/cmdline").read_text().replace("\0", " ") for p in alive]
    # nothing of it ran after the kill, yet its work is resumable
    resumed = subprocess.run(
        [sys.executable, "-c", code, "build-map", str(seq), "--out", str(tmp_path / "m"), "--resume"],
        capture_output=True,
        text=True,
    )
    assert resumed.returncode == 0, resumed.stderr
    assert MeshMap.load(tmp_path / "m").n_triangles > 10_000


@pytest.fixture(scope="module")
def uninterrupted(drive):
    """The drive's map built once, uninterrupted, by the CLI with its default settings."""
    root, seq, _ = drive
    out = root / "uninterrupted"
    r = subprocess.run([sys.executable, "-m", "rangemcl.cli", "build-map", str(seq), "--out", str(out)])
    assert r.returncode == 0
    return out


def _same_map(out: Path, reference: Path) -> None:
    """The two map folders hold the same files, byte for byte (the build reports aside)."""
    names = sorted(str(p.relative_to(reference)) for p in reference.rglob("*") if p.is_file())
    names.remove("report.json")
    assert (
        sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file() and p.name != "report.json")
        == names
    )
    assert any(name.startswith("tiles/") for name in names)
    for name in names:
        _same_file(out / name, reference / name)


def _same_file(a: Path, b: Path) -> None:
    """Byte for byte (the place prior too: its file holds no timing)."""
    assert a.read_bytes() == b.read_bytes(), a.name


@pytest.mark.parametrize(
    "moment,backend",
    [("scans", "process"), ("tiles", "process"), ("assemble", "process"), ("tiles", "ray")],
)
def test_sigkill_at_three_moments_resumes_to_the_same_map_and_leaves_no_process(
    drive, uninterrupted, tmp_path, moment, backend
):
    """`kill -9` in the middle of the scan stage, with some tiles built and some not, and with the map
    folder half written (``$RANGEMCL_KILL_AT``: the run kills itself there, no handler runs): no process
    of the killed run (tile workers, multiprocessing's resource tracker; with ``--backend ray`` the local
    Ray instance: GCS, raylet, agents, workers) is alive 2 s later, a plain rerun is refused naming
    --resume, and --resume finishes a map identical, byte for byte, to the uninterrupted build (made by
    the process pool)."""
    if backend == "ray":
        pytest.importorskip("ray")
    import os
    import signal
    import time
    import uuid

    _, seq, _ = drive
    token = uuid.uuid4().hex
    out = tmp_path / "m"
    cmd = [
        sys.executable,
        "-m",
        "rangemcl.cli",
        "build-map",
        str(seq),
        "--out",
        str(out),
        "--backend",
        backend,
    ]
    env = {**os.environ, "RANGEMCL_KILL_AT": moment, "RANGEMCL_TEST_TOKEN": token, "TMPDIR": str(tmp_path)}
    if backend == "ray":
        del env["TMPDIR"]  # Ray's sockets live under it, and a socket's path is at most 107 bytes
    killed = subprocess.run(cmd, env=env, capture_output=True, text=True)
    assert killed.returncode == -signal.SIGKILL, killed.stderr
    assert (out / ".build").is_dir()
    time.sleep(2.0)
    alive = []
    for proc in Path("/proc").iterdir():
        try:
            ours = proc.name.isdigit() and token.encode() in (proc / "environ").read_bytes()
            if ours and "zombie" not in _state(int(proc.name)):
                alive.append((proc / "cmdline").read_text().replace("\0", " "))
        except OSError:
            pass
    assert not alive, alive
    refused = subprocess.run(cmd, capture_output=True, text=True)
    assert refused.returncode == 2 and "--resume" in refused.stderr
    resumed = subprocess.run([*cmd, "--resume"], capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    assert not (out / ".build").exists()
    if moment != "scans":
        assert "taken from the interrupted build" in resumed.stdout
    _same_map(out, uninterrupted)


def test_ray_tasks_on_another_node_read_the_chunks_through_the_driver(
    drive, uninterrupted, tmp_path, monkeypatch
):
    """`build-map --backend ray` with every task fetching its spooled chunks from the reader actor on the
    driver's node, as a task on another node of a cluster does: the same map, byte for byte, as the
    process pool's; each tile job reports its own peak memory."""
    pytest.importorskip("ray")
    import functools

    from rangemcl.mapping import raybuild

    _, seq, _ = drive
    monkeypatch.setattr(raybuild, "run_tiles", functools.partial(raybuild.run_tiles, via_reader=True))
    out = tmp_path / "m"
    report = build_map(seq, out, MapSettings(), backend="ray")  # all cores, as `uninterrupted`
    from rangemcl.localization import map_place_prior

    map_place_prior(out, map_memory_mb=500.0)  # the CLI's last step, as for `uninterrupted`
    _same_map(out, uninterrupted)
    peaks = [s["peak_rss_mb"] for s in report.tile_stats]  # every tile job (a margin's may end empty)
    assert len(peaks) >= report.tiles and min(peaks) > 50
    assert report.peak_rss_tile_jobs_mb >= max(peaks)
    with pytest.raises(InputError, match="backend 'dask'"):
        build_map(seq, tmp_path / "n", MapSettings(), backend="dask")
