"""``simbed demo``: the whole story on the built-in town in one command.

1. record a mapping drive (the covering route, no moving actors, parked-car variant 0);
2. build the mesh map from it (``rangemcl build-map``);
3. record a different test drive (another route, parked-car variant 1, moving actors);
4. localize globally in the map (``rangemcl localize``), print the metrics, write the plots.

Every step writes into one folder. The folder's ``demo.yaml`` (written first) holds the demo's settings:
run again with the same settings, the demo continues where it stopped (a step whose output is complete
is reused); a folder that holds a finished demo, or a demo with other settings, is refused in one line
naming ``--overwrite``, which replaces the folder whole (:mod:`rangemcl.common.outdir`).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

from rangemcl.common.atomic import atomic_write
from rangemcl.config import write_config
from rangemcl.datasets.kitti import load_sequence
from rangemcl.errors import InputError
from rangemcl.localization import LocalizerSettings
from rangemcl.localization.pipeline import RunOptions, localize_sequence
from rangemcl.mapping.pipeline import MapSettings, build_map
from simbed.record import record, resumable
from simbed.sim import DEFAULT_SENSOR_MODEL


@dataclass
class DemoSettings:
    scene: str = "town_small"
    sensor: str = "os1-64"
    mapping_frames: int = 3000  # the whole covering route (it ends first)
    map_every_nth: int = 3  # scans used by the map builder (every 3rd: about 1.8 m apart)
    test_route: str = "test"
    test_frames: int = 400
    test_variant: int = 1
    actors: int = 10
    particles: int = 10000
    seed: int = 0
    sensor_model: str = DEFAULT_SENSOR_MODEL  # both drives' simulated LiDAR: ideal or realistic

    def check(self, device: str = "cpu") -> None:
        """Every setting (and the device) checked before the demo writes or records anything: a bad one
        is an :class:`InputError` naming it (and its ``simbed demo`` option)."""
        from rangemcl.raycast import resolve_device
        from rangemcl.sensors import load_spec
        from simbed.sim.world import resolve_scene

        options = {"test_frames": "--test-frames", "particles": "--particles", "seed": "--seed"}
        for key, least in (
            ("mapping_frames", 1),
            ("map_every_nth", 1),
            ("test_frames", 1),
            ("test_variant", 0),
            ("actors", 0),
            ("particles", 1),
            ("seed", 0),
        ):
            value = getattr(self, key)
            if value < least:
                name = options.get(key, f"demo setting {key}")
                raise InputError(f"{name} must be >= {least}, got {value}")
        resolve_scene(self.scene)
        spec = load_spec(self.sensor)
        resolve_device(device)
        from simbed.sim.lidar import sensor_setup

        sensor_setup(spec, self.sensor_model)


def _complete(seq_dir: Path) -> bool:
    try:
        return bool(load_sequence(seq_dir).meta.get("complete"))
    except InputError:
        return False


DEMO_MARKERS = ("demo.yaml", "mapping_drive", "map", "test_drive", "results", "demo_summary.json")


def check_demo_folder(out: Path, s: DemoSettings, overwrite: bool) -> bool:
    """Whether ``out`` holds an unfinished demo with the same settings (to continue); refuses, in one
    line, a finished demo or one with other settings unless ``overwrite``, and a folder that holds
    something else. Changes nothing."""
    from rangemcl.common.outdir import check_output
    from rangemcl.common.yamlio import parse_yaml, read_text
    from rangemcl.config import to_dict

    if overwrite or not (out / "demo.yaml").is_file():
        check_output(out, overwrite=overwrite, kind="demo results", markers=DEMO_MARKERS)
        return False
    saved = parse_yaml(read_text(out / "demo.yaml", "demo settings"), str(out / "demo.yaml"))
    now = to_dict(s)
    if saved != now:
        diff = sorted(k for k in set(now) | set(saved or {}) if (saved or {}).get(k) != now.get(k))
        raise InputError(
            f"{out}: holds a demo with other settings ({', '.join(diff[:4])}); give --overwrite to replace "
            "it, or another --out"
        )
    if (out / "demo_summary.json").is_file():
        raise InputError(f"{out}: holds this demo, finished (give --overwrite to run it again)")
    return True


def run_demo(
    out_dir, settings: DemoSettings | None = None, *, device: str = "cpu", say=print, overwrite: bool = False
) -> dict:
    """Run the four steps into ``out_dir`` (continuing an unfinished demo with the same settings, or
    replacing the folder with ``overwrite``); return the localization summary (with metrics)."""
    from rangemcl.common.outdir import output_folder

    s = settings or DemoSettings()
    s.check(device)
    out = Path(out_dir)
    if check_demo_folder(out, s, overwrite):
        say(f"continuing the demo in {out}")
        return _run_demo(out, s, device, say)
    keep = lambda p: (p / "demo.yaml").is_file() and any((p / m).exists() for m in DEMO_MARKERS[1:])  # noqa: E731
    with output_folder(out, overwrite=overwrite, kind="demo results", markers=DEMO_MARKERS, keep_if=keep):
        return _run_demo(out, s, device, say)


def _run_demo(out: Path, s: DemoSettings, device: str, say) -> dict:
    write_config(s, out / "demo.yaml")
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def step(name: str, t0: float) -> None:
        timings[name] = time.perf_counter() - t0
        say(f"[{name}] {timings[name]:.0f} s")

    mapping, map_dir, test, results = out / "mapping_drive", out / "map", out / "test_drive", out / "results"
    t0 = time.perf_counter()
    if _complete(mapping):
        say(f"[mapping drive] reusing {mapping}")
    else:
        say(f"[mapping drive] {s.scene}, route 'mapping', {s.sensor}, no moving actors -> {mapping}")
        r = record(
            s.scene,
            "mapping",
            s.sensor,
            mapping,
            frames=s.mapping_frames,
            seed=s.seed,
            device=device,
            overwrite=True,
            progress=True,
            sensor_model=s.sensor_model,
            resume=resumable(mapping),
        )
        say(f"  {r.frames} frames, {r.distance_driven_m:.0f} m driven")
    step("mapping drive", t0)

    t0 = time.perf_counter()
    if (map_dir / "map.yaml").is_file():
        say(f"[map] reusing {map_dir}")
    else:
        say(f"[map] rangemcl build-map (every {s.map_every_nth}. scan) -> {map_dir}")
        ms = MapSettings()
        ms.scans.every_nth = s.map_every_nth
        rep = build_map(mapping, map_dir, ms, progress=True)
        say(f"  {rep.triangles:,} triangles in {rep.tiles} tiles from {rep.scans_used} scans")
    step("map", t0)

    t0 = time.perf_counter()
    if _complete(test):
        say(f"[test drive] reusing {test}")
    else:
        say(
            f"[test drive] route '{s.test_route}', parked-car variant {s.test_variant}, "
            f"{s.actors} moving actors -> {test}"
        )
        record(
            s.scene,
            s.test_route,
            s.sensor,
            test,
            frames=s.test_frames,
            actors=s.actors,
            variant=s.test_variant,
            seed=s.seed + 1,
            device=device,
            overwrite=True,
            progress=True,
            sensor_model=s.sensor_model,
            resume=resumable(test),
        )
    step("test drive", t0)

    t0 = time.perf_counter()
    say(f"[localize] global localization with {s.particles:,} particles -> {results}")
    resume = (results / ".resume").is_dir()  # an interrupted localization of this demo continues
    if results.exists() and not resume:
        import shutil

        shutil.rmtree(results)
    summary = localize_sequence(
        test,
        map_dir,
        results,
        LocalizerSettings(),
        RunOptions(
            mode="global", particles=s.particles, device=device, seed=s.seed, progress=True, resume=resume
        ),
    )
    step("localize", t0)
    timings["total"] = time.perf_counter() - clock
    summary["demo_seconds"] = timings
    atomic_write(out / "demo_summary.json", json.dumps(summary, indent=2) + "\n")
    return summary
