"""The paper's experiments as reproducible suites of localization trials (``simbed trials SUITE``).

A **trial** is one localization run: a recorded test drive (scene, sensor, route, parked-car variant,
moving actors, seed), a start frame on it, a particle count, an observation model and a seed; global
localization, or a kidnapped car (tracking, then teleported halfway). Suites:

* ``particles``: success rate against the particle count, per observation model (the paper's Fig. 6);
* ``sensors``: location and yaw RMSE for the 8- to 128-beam presets with one parameter set (Table III);
* ``models``: location and yaw error per observation model on two test drives (Table II);
* ``kidnap``: relocalization rate and time after a teleport;
* ``runtime``: frame rates before and after convergence;
* ``robustness``: the ``sensors`` suite's presets at each sensor realism level (:data:`REALISM_LEVELS`:
  the ideal sensor, the realistic one, in rain, in fog, and with heavy dropout), the same starts for all.

``quick`` sizes run in CI time; the full sizes are for a long run or a GPU. Drives are recorded once into
``OUT/drives`` and shared by the trials; every trial writes its ``rangemcl localize`` folder under
``OUT/trials`` and, when done, one row of ``OUT/results.csv``: a crashed or interrupted suite continues
where it stopped (finished trials are skipped). Trials run in parallel on all cores (a process pool), or
on a Ray cluster (``backend="ray"``). Each suite writes ``OUT/SUITE.md`` (a markdown table) and
``OUT/SUITE.png``.
"""

from __future__ import annotations

import csv
import hashlib
import json
import os
import time
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

from rangemcl import method_version
from rangemcl.common.pool import process_pool
from rangemcl.errors import InputError
from rangemcl.localization.models import MODEL_NAMES
from simbed.sim import DEFAULT_SENSOR_MODEL

SUITES = ("particles", "sensors", "models", "kidnap", "runtime", "robustness")
# The robustness suite's sensor realism levels: how its test drives are recorded (simbed.record.record's
# sensor_model, weather and dropout). Rain of 10 mm/h is heavy rain; fog of 200 m visibility is moderate
# fog (it halves a 10 % target's range: tools/weather_ranges.py); half the returns dropped at random is
# a stress level no sensor reaches in clear air.
REALISM_LEVELS: dict[str, dict] = {
    "ideal": {"sensor_model": "ideal"},
    "realistic": {"sensor_model": "realistic"},
    "rain": {"sensor_model": "realistic", "weather": "rain:10"},
    "fog": {"sensor_model": "realistic", "weather": "fog:200"},
    "dropout": {"sensor_model": "realistic", "dropout": 0.5},
}
# The paper's figures per sensor in Carla (location RMSE m, yaw RMSE deg), beside ours in
# docs/results/town_large/README.md
PAPER_SENSORS = {
    "mq-8": (0.48, 3.87),
    "vlp-16": (0.43, 3.87),
    "hdl-32e": (0.42, 3.40),
    "hdl-64e": (0.36, 3.46),
    "os1-128": (0.33, 3.31),
}


@dataclass(frozen=True)
class Trial:
    suite: str
    scene: str
    sensor: str
    route: str
    variant: int
    actors: int
    drive_seed: int
    drive_frames: int
    start_frame: int
    frames: int
    particles: int
    model: str
    seed: int
    kidnap: bool = False
    settings: str = ""  # localizer settings the suite was given (canonical JSON; "" = the defaults)
    method: str = "default"  # a name for those settings in the tables (the config file's stem); not keyed
    realism: str = "ideal"  # how the test drive's sensor was simulated (REALISM_LEVELS)
    realtime: bool = False  # localized at the sensor's pace (rangemcl localize --realtime)

    @property
    def key(self) -> str:
        return (
            f"{self.suite}-{self.drive_key}-s{self.start_frame}-f{self.frames}-p{self.particles}-{self.model}"
            f"-r{self.seed}{'-kidnap' if self.kidnap else ''}{settings_tag(self.settings)}"
            f"{'-rt' if self.realtime else ''}-v{METHOD_VERSION}"
        )

    @property
    def drive_key(self) -> str:
        return drive_key(*(getattr(self, k) for k in DRIVE_FIELDS))


# Every trial key ends with the localizer's method version: the package version's major.minor (semantic
# versioning: a minor release changes what the localizer computes, a patch release does not), so trials run
# by another version of the method are never taken for today's when a suite folder is continued. What each
# version changed: CHANGELOG.md.
METHOD_VERSION = method_version()

DRIVE_FIELDS = ("scene", "sensor", "route", "variant", "actors", "drive_seed", "drive_frames", "realism")


def drive_key(scene, sensor, route, variant, actors, drive_seed, drive_frames, realism="ideal") -> str:
    """A test drive's folder name under ``OUT/drives`` (from a Trial, or a results.csv row's fields). A
    scene, route or sensor given as a file path is named by its file's stem and a hash of its absolute
    path, so that the folder stays under ``OUT`` (``/home/me/s.xml`` would otherwise make it absolute).
    A realism level other than the ideal sensor ends it (``-lrain``)."""
    scene, sensor, route = (_name_part(str(v)) for v in (scene, sensor, route))
    level = "" if realism in ("ideal", "", None) else f"-l{realism}"
    return f"{scene}-{sensor}-{route}-v{variant}-a{actors}-d{drive_seed}-n{drive_frames}{level}"


def _name_part(value: str) -> str:
    """``value`` itself when it is a plain name, else ``STEM-HASH8`` of the path it names."""
    if "/" not in value and os.sep not in value and not value.startswith("."):
        return value
    digest = hashlib.sha1(str(Path(value).expanduser().resolve()).encode()).hexdigest()[:8]
    return f"{Path(value).stem or 'path'}-{digest}"


@dataclass
class SuiteConfig:
    scene: str = "town_small"
    route: str = "test"
    variant: int = 1
    actors: int = 10
    drive_frames: int = 1000
    frames: int = 250  # per trial (kidnap: half before and half after the jump)
    starts: int = 10
    sensor: str = "os1-64"
    particles: int = 10000  # global localization (suite 'particles' varies it); quick suites use 2,000
    particle_counts: tuple[int, ...] | None = None  # suite 'particles' (default 1k, 5k, 10k, 50k, 100k)
    models: tuple[str, ...] | None = None  # suites 'particles' and 'models' (default: all four)
    sensors: tuple[str, ...] | None = None  # suites 'sensors', 'robustness' (default: the paper's five)
    levels: tuple[str, ...] | None = None  # suite 'robustness' (default: all of REALISM_LEVELS)
    realism: str = DEFAULT_SENSOR_MODEL  # every other suite: its test drives' sensor (REALISM_LEVELS)
    settings: str = ""  # localizer settings for every trial (canonical JSON, see suite_settings)
    method: str = "default"  # their name in the tables
    realtime: bool = False  # every trial at the sensor's pace (scans that arrive while busy dropped)


def suite_settings(path) -> str:
    """Localizer settings from a YAML file (as ``rangemcl localize --config`` takes) for ``SuiteConfig``:
    checked now (an InputError names the file and the key), kept as canonical JSON. The suite still sets
    each trial's observation model and particle count."""
    from rangemcl.common.yamlio import parse_yaml, read_text
    from rangemcl.config import from_dict
    from rangemcl.localization import LocalizerSettings

    data = parse_yaml(read_text(path, "localizer settings"), str(path)) or {}
    from_dict(LocalizerSettings, data, str(path)).check(str(path))
    return json.dumps(data, sort_keys=True, separators=(",", ":"))


def settings_tag(settings: str) -> str:
    """The suffix that trial keys get for non-default settings: ``-c`` and 8 hex digits of their hash."""
    if not settings or settings == "{}":
        return ""
    return "-c" + hashlib.sha1(settings.encode()).hexdigest()[:8]


def suite_trials(suite: str, quick: bool = False, config: SuiteConfig | None = None) -> list[Trial]:
    """The trials of a suite (``quick``: a handful that run in CI time)."""
    c = config or SuiteConfig()
    if suite not in SUITES:
        raise InputError(f"suite {suite!r}: expected one of {', '.join(SUITES)}")
    bad = [m for m in c.models or () if m not in MODEL_NAMES]
    if bad:
        raise InputError(f"observation model {bad[0]!r}: expected one of {', '.join(MODEL_NAMES)}")
    bad = [lv for lv in (*(c.levels or ()), c.realism) if lv not in REALISM_LEVELS]
    if bad:
        raise InputError(f"realism level {bad[0]!r}: expected one of {', '.join(REALISM_LEVELS)}")
    if any(not isinstance(n, int) or n < 1 for n in c.particle_counts or ()):
        raise InputError(f"particle counts must be positive integers, got {c.particle_counts}")
    starts = 2 if quick else c.starts
    default_particles = min(c.particles, 2000) if quick else c.particles

    def trials(
        sensor=c.sensor,
        route=c.route,
        particles=default_particles,
        model="range",
        n=starts,
        kidnap=False,
        seed0=0,
        realism=c.realism,
    ):
        span = max(0, c.drive_frames - c.frames)
        out = []
        for k in range(n):
            start = int(round(k * span / max(1, n - 1))) if n > 1 else 0
            out.append(
                Trial(
                    suite,
                    c.scene,
                    sensor,
                    route,
                    c.variant,
                    c.actors,
                    7,
                    c.drive_frames,
                    start,
                    c.frames,
                    particles,
                    model,
                    seed0 + k,
                    kidnap,
                    c.settings,
                    c.method,
                    realism,
                    c.realtime,
                )
            )
        return out

    if suite == "particles":
        counts = [300, 1000] if quick else list(c.particle_counts or (1000, 5000, 10000, 50000, 100000))
        models = ["range", "overlap"] if quick else list(c.models or MODEL_NAMES)
        return [t for m in models for p in counts for t in trials(particles=p, model=m)]
    if suite == "sensors":
        sensors = ["vlp-16", "os1-64"] if quick else list(c.sensors or PAPER_SENSORS)
        return [t for s in sensors for t in trials(sensor=s, n=1 if quick else starts)]
    if suite == "models":
        models = list(c.models or MODEL_NAMES)
        routes = [c.route] if quick else ["test-1", "test-2"]
        n = 1 if quick else max(1, starts // 2)
        return [t for m in models for r in routes for t in trials(route=r, model=m, n=n)]
    if suite == "kidnap":
        return trials(kidnap=True, n=2 if quick else starts)
    if suite == "robustness":
        sensors = ["vlp-16"] if quick else list(c.sensors or PAPER_SENSORS)
        levels = ["ideal", "realistic"] if quick else list(c.levels or REALISM_LEVELS)
        n = 1 if quick else starts
        return [t for s in sensors for lv in levels for t in trials(sensor=s, n=n, realism=lv)]
    return trials(n=1 if quick else 3)  # runtime


# ---------------------------------------------------------------------------------------------- running


def ensure_drive(trial: Trial, drives_dir: Path, device: str = "cpu") -> Path:
    """The trial's test drive, recorded once (a complete recording is reused)."""
    from rangemcl.datasets.kitti import load_sequence
    from simbed.record import record

    path = drives_dir / trial.drive_key
    try:
        if load_sequence(path).meta.get("complete"):
            return path
    except InputError:
        pass
    record(
        trial.scene,
        trial.route,
        trial.sensor,
        path,
        frames=trial.drive_frames,
        actors=trial.actors,
        variant=trial.variant,
        seed=trial.drive_seed,
        device=device,
        overwrite=True,
        progress=False,
        **REALISM_LEVELS[trial.realism or "ideal"],
    )
    return path


def run_trial(
    trial: Trial, drive: Path, map_dir: Path, trials_dir: Path, threads: int = 1, device: str = "cpu"
) -> dict:
    """Localize one trial; its results row (the trial's fields plus metrics and timings)."""
    from rangemcl.datasets.kitti import load_sequence, splice_kidnapped
    from rangemcl.localization.pipeline import RunOptions, localize_sequence

    out = trials_dir / trial.key
    settings = _trial_settings(trial)
    settings.observation.model = trial.model
    settings.particles.global_count = trial.particles
    n = len(load_sequence(drive))
    t0 = time.perf_counter()
    if trial.kidnap:
        half = max(1, trial.frames // 2)
        a = min(trial.start_frame, max(0, n - half))
        b = (a + n // 2) % max(1, n - half)
        seq = trials_dir / f"{trial.key}-seq"
        splice_kidnapped(drive, seq, a, b, half)
        try:
            s = localize_sequence(
                seq,
                map_dir,
                out,
                settings,
                RunOptions(mode="tracking", seed=trial.seed, threads=threads, device=device, plots=False),
            )
        finally:
            import shutil

            shutil.rmtree(seq, ignore_errors=True)
    else:
        first = min(trial.start_frame, max(0, n - 1))
        s = localize_sequence(
            drive,
            map_dir,
            out,
            settings,
            RunOptions(
                mode="global",
                seed=trial.seed,
                threads=threads,
                device=device,
                first_frame=first,
                frames=trial.frames,
                plots=False,
                realtime=trial.realtime,
            ),
        )
    m = json.loads((out / "metrics.json").read_text())
    success = bool(m["success"]) and (not trial.kidnap or s["recoveries"] >= 1)
    odo = load_sequence(drive).meta.get("odometry") or {}  # the drive's drawn odometry errors
    cal = s.get("odometry_calibration") or {}
    conv = s["converged_frame"]
    row = {
        **asdict(trial),
        "key": trial.key,
        "success": success,
        "frames_to_converge": None if conv is None else conv - s["first_frame"],
        # the first correct convergence: compute from the trial's first frame through it, metres driven
        "fix_seconds": s.get("first_fix_seconds"),
        "fix_driven_m": m.get("first_fix_driven_m"),
        "recoveries": s["recoveries"],
        "relocalized_after_frames": (conv - s["first_frame"] - trial.frames // 2)
        if trial.kidnap and conv is not None and s["recoveries"]
        else None,
        "location_rmse_m": m.get("location_rmse_m"),
        "yaw_rmse_deg": m.get("yaw_rmse_deg"),
        "location_median_m": m.get("location_median_m"),
        "wrong_convergences": m.get("wrong_convergences_count", 0),
        "wrong_convergences_uncaught": m.get("wrong_convergences_uncaught", 0),
        "wrong_held_max_frames": wrong_held_max_frames(m),
        "false_alarms": m.get("false_alarms_count", 0),
        "vetoed_alarms": s.get("vetoed_alarms", 0),
        "frames_after_convergence": None if conv is None else m["frames"] - (conv - s["first_frame"]),
        "seconds_per_frame_before": s["seconds_per_frame_before_convergence_median"],
        "hz_after": s["hz_after_convergence"],
        "startup_seconds": s.get("startup_seconds"),  # map, filter and priors before the first frame
        "late_scans": s.get("late_scans", 0),  # realtime: scans dropped while the localizer was busy
        "seconds": time.perf_counter() - t0,
        # the drive's odometry: its distance is wheel_scale x the true one, its gyro starts this biased
        "odometry_wheel_scale": odo.get("wheel_scale"),
        "odometry_gyro_bias_deg_s": odo.get("gyro_bias_initial_deg_s"),
        # ... and the filter's calibration at the trial's end (the scale it multiplies the odometry by)
        "calibrated_scale": cal.get("scale"),
        "calibrated_gyro_bias_deg_s": cal.get("gyro_bias_deg_s"),
    }
    return row


def wrong_held_max_frames(metrics: dict) -> int:
    """The longest that a trial held a wrong convergence, in frames (0 without one): from the frame it was
    declared (more than 5 m off) to the re-spread that undid it, or to the trial's end when none did (then
    a lower bound of how long it would have been held). From ``metrics.json``'s events
    (:func:`rangemcl.evaluation.metrics.convergence_events`)."""
    end = metrics.get("first_frame", 0) + metrics["frames"]
    return max(
        (
            w["caught_frame"] - w["frame"] if w["caught_frame"] is not None else end - w["frame"]
            for w in metrics.get("wrong_convergences", ())
        ),
        default=0,
    )


def _trial_job(args) -> dict:
    trial, drive, map_dir, trials_dir, threads, device = args
    return run_trial(trial, drive, map_dir, trials_dir, threads, device)


# results.csv columns: the settings themselves stay out (the key's tag names them; each trial's folder
# has its config.yaml)
ROW_FIELDS = [f.name for f in fields(Trial) if f.name != "settings"] + [
    "key",
    "success",
    "frames_to_converge",
    "fix_seconds",
    "fix_driven_m",
    "recoveries",
    "relocalized_after_frames",
    "location_rmse_m",
    "yaw_rmse_deg",
    "location_median_m",
    "wrong_convergences",
    "wrong_convergences_uncaught",
    "wrong_held_max_frames",
    "false_alarms",
    "vetoed_alarms",
    "frames_after_convergence",
    "seconds_per_frame_before",
    "hz_after",
    "startup_seconds",
    "late_scans",
    "seconds",
    "odometry_wheel_scale",
    "odometry_gyro_bias_deg_s",
    "calibrated_scale",
    "calibrated_gyro_bias_deg_s",
]


def read_results(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    with path.open() as fh:
        return list(csv.DictReader(fh))


def results_columns(path: Path) -> list[str]:
    """The columns to append rows of ``path`` (a results.csv) under: :data:`ROW_FIELDS` for a new file;
    a file written before some of them were added is rewritten once (atomically) with them, its rows
    empty there, and keeps any columns of its own after them."""
    if not path.is_file() or path.stat().st_size == 0:
        return list(ROW_FIELDS)
    with path.open(newline="") as fh:
        header = next(csv.reader(fh), [])
    columns = [*ROW_FIELDS, *(c for c in header if c not in ROW_FIELDS)]
    if all(c in header for c in ROW_FIELDS):
        return header  # every column there (in today's order, or another): append under the file's own
    import io

    from rangemcl.common.atomic import atomic_write

    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=columns, restval="", extrasaction="ignore")
    writer.writeheader()
    writer.writerows(read_results(path))
    atomic_write(path, text.getvalue())
    return columns


def run_suite(
    suite: str,
    out_dir,
    map_dir,
    *,
    quick: bool = False,
    config: SuiteConfig | None = None,
    workers: int | None = None,
    backend: str = "process",
    address: str | None = None,
    device: str = "cpu",
    say=print,
    report_only: bool = False,
    compare: tuple[SuiteConfig, ...] = (),
) -> list[dict]:
    """Run (or continue) a suite; write results.csv, SUITE.md and SUITE.png; return the suite's rows.

    ``report_only``: run nothing; write SUITE.md and SUITE.png from the trials already in results.csv
    (e.g. of a suite stopped part-way; the table counts the trials it holds); ``compare``: other suite
    configs (other localizer settings) whose trials join the report, side by side."""
    out = Path(out_dir)
    if report_only:
        keys = {t.key for cfg in (config, *compare) for t in suite_trials(suite, quick, cfg)}
        rows = [r for r in read_results(out / "results.csv") if r["key"] in keys]
        if not rows:
            raise InputError(
                f"{out / 'results.csv'}: no finished trial of suite {suite!r} with these settings"
            )
        say(f"suite {suite}: {len(rows)} of {len(keys)} trials finished; report only")
        write_report(suite, rows, out)
        return rows
    # a clear error now rather than in every worker minutes later (and before any folder)
    trials = check_suite(
        suite, map_dir, quick=quick, config=config, workers=workers, backend=backend, device=device
    )
    (out / "drives").mkdir(parents=True, exist_ok=True)
    (out / "trials").mkdir(parents=True, exist_ok=True)
    results_path = out / "results.csv"
    columns = results_columns(results_path)
    done = {r["key"] for r in read_results(results_path)}
    todo = [t for t in trials if t.key not in done]
    say(f"suite {suite}: {len(trials)} trials, {len(trials) - len(todo)} already done")
    workers = workers or os.cpu_count() or 1
    drives = _ensure_drives(todo, out / "drives", device, workers, say)
    _ensure_place_priors(todo, Path(map_dir), device, say)
    threads = max(1, (os.cpu_count() or 1) // workers)
    jobs = [(t, drives[t.drive_key], Path(map_dir), out / "trials", threads, device) for t in todo]
    new_file = not results_path.is_file() or results_path.stat().st_size == 0
    with results_path.open("a", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        if new_file:
            writer.writeheader()
            fh.flush()
        for row in _execute(jobs, workers, backend, address):
            writer.writerow({k: row.get(k) for k in columns})
            fh.flush()
            os.fsync(fh.fileno())
            verdict = "success" if row["success"] else "failure"
            say(f"  {row['key']}: {verdict}, RMSE {format_value(row['location_rmse_m'])} m")
    keys = {t.key for t in trials}
    rows = [r for r in read_results(results_path) if r["key"] in keys]
    write_report(suite, rows, out)
    return rows


def check_suite(
    suite: str,
    map_dir,
    *,
    quick: bool = False,
    config: SuiteConfig | None = None,
    workers: int | None = None,
    backend: str = "process",
    device: str = "cpu",
) -> list[Trial]:
    """The suite's trials, once everything they depend on is checked: a bad count, map, sensor, scene,
    parked-car variant, route, backend or device is an :class:`InputError` now, before a folder is made or
    a drive recorded (not minutes later in a worker)."""
    from rangemcl.maps.meshmap import MeshMap
    from rangemcl.raycast import resolve_device
    from rangemcl.sensors import load_spec
    from simbed.record import scene_route
    from simbed.sim.world import World

    c = config or SuiteConfig()
    trials = suite_trials(suite, quick, c)  # the suite's name, observation models, particle counts
    for option, value, least in (
        ("--frames", c.frames, 1),
        ("--starts", c.starts, 1),
        ("--drive-frames", c.drive_frames, 1),
        ("--actors", c.actors, 0),
        ("--variant", c.variant, 0),
        ("--workers", 0 if workers is None else workers, 0),
    ):
        if value < least:
            raise InputError(f"{option} must be >= {least}, got {value}")
    if backend not in ("process", "ray"):
        raise InputError(f"backend {backend!r}: expected 'process' or 'ray'")
    resolve_device(device)
    MeshMap.load(map_dir)
    for sensor in dict.fromkeys([c.sensor, *(c.sensors or ()), *(t.sensor for t in trials)]):
        load_spec(sensor)
    world = World(c.scene, variant=c.variant)  # the scene and its parked-car variant
    for route in dict.fromkeys(t.route for t in trials):
        scene_route(world, route)
    return trials


def _ensure_drives(trials: list[Trial], drives_dir: Path, device: str, workers: int, say) -> dict[str, Path]:
    """Each distinct test drive of the trials, recorded once (in parallel on the local pool)."""
    first = {}
    for t in trials:
        first.setdefault(t.drive_key, t)
    for key in first:
        say(f"  drive {key}")
    if workers <= 1 or len(first) <= 1:
        return {k: ensure_drive(t, drives_dir, device) for k, t in first.items()}
    with process_pool(min(workers, len(first))) as pool:
        futures = {k: pool.submit(ensure_drive, t, drives_dir, device) for k, t in first.items()}
        return {k: f.result() for k, f in futures.items()}


def _trial_settings(trial: Trial):
    from rangemcl.localization import LocalizerSettings

    if not trial.settings:
        return LocalizerSettings()
    from rangemcl.config import from_dict

    return from_dict(LocalizerSettings, json.loads(trial.settings), "suite settings")


def _ensure_place_priors(trials: list[Trial], map_dir: Path, device: str, say) -> None:
    """The map's place prior for each localizer setting of the trials, rendered once on all cores before
    the trials start (else every worker would render the same prior at its first global spread)."""
    from rangemcl.localization import map_place_prior

    for trial in {t.settings: t for t in trials}.values():
        s = _trial_settings(trial)
        if not s.init.place_prior:
            continue
        t0 = time.perf_counter()
        prior, how = map_place_prior(map_dir, s, device=device)
        say(f"place prior {how}: {len(prior.xy):,} cells, {time.perf_counter() - t0:.1f} s")


def _execute(jobs, workers: int, backend: str, address: str | None):
    """Results of the jobs as they finish, from a process pool or a Ray cluster."""
    if not jobs:
        return
    if backend == "ray":
        try:
            import ray
        except ImportError:
            raise InputError("backend 'ray' needs Ray: pip install 'simbed-rangemcl[ray]'") from None
        started = not ray.is_initialized()
        if started:
            ray.init(
                address=address,
                include_dashboard=False,
                log_to_driver=False,
                num_cpus=None if address else workers,
            )
        try:
            remote = ray.remote(num_cpus=1)(_trial_job)
            pending = [remote.remote(j) for j in jobs]
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                yield ray.get(ready[0])
        finally:
            if started:
                ray.shutdown()
        return
    if backend != "process":
        raise InputError(f"backend {backend!r}: expected 'process' or 'ray'")
    if workers <= 1 or len(jobs) == 1:
        for j in jobs:
            yield _trial_job(j)
        return
    from concurrent.futures import as_completed

    with process_pool(workers) as pool:
        futures = [pool.submit(_trial_job, j) for j in jobs]
        for f in as_completed(futures):
            yield f.result()


# ---------------------------------------------------------------------------------------------- reports


def as_number(x) -> float:
    """A results.csv cell as a float (NaN when empty or not a number)."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return float("nan")
    return v


def is_true(x) -> bool:
    """Whether a results.csv cell says true (``True``, ``true`` or ``1``)."""
    return str(x).lower() in ("true", "1")


def _total(rows: list[dict], col: str) -> int | None:
    """Sum of a count column (None when no row has it: rows of earlier versions lack the event counts)."""
    vals = [as_number(r.get(col)) for r in rows if r.get(col) not in ("", None)]
    return int(np.sum(vals)) if vals else None


def _median_of(rows: list[dict], value) -> float | None:
    """Median of ``value(row)`` over the rows where it is a number (None when none)."""
    vals = [v for v in (value(r) for r in rows) if v == v]
    return float(np.median(vals)) if vals else None


def aggregate(rows: list[dict], by: list[str]) -> list[dict]:
    """Per group: trials, successes, RMSE over the successful trials' frames after convergence, medians."""
    groups: dict[tuple, list[dict]] = {}
    for r in rows:
        groups.setdefault(tuple(r[k] for k in by), []).append(r)
    out = []
    for key, rs in sorted(
        groups.items(), key=lambda kv: [(as_number(v) if as_number(v) == as_number(v) else v) for v in kv[0]]
    ):
        good = [r for r in rs if is_true(r["success"])]
        converged = [r for r in rs if r["frames_to_converge"] not in ("", None)]
        w = np.array([as_number(r["frames_after_convergence"]) for r in good])
        loc = np.array([as_number(r["location_rmse_m"]) for r in good])
        yaw = np.array([as_number(r["yaw_rmse_deg"]) for r in good])
        med = [
            as_number(r["location_median_m"]) for r in good if r.get("location_median_m") not in ("", None)
        ]
        conv = [as_number(r["frames_to_converge"]) for r in converged]
        hz = [as_number(r["hz_after"]) for r in rs if r["hz_after"] not in ("", None)]
        before = [
            as_number(r["seconds_per_frame_before"])
            for r in rs
            if r["seconds_per_frame_before"] not in ("", None)
        ]

        reloc = [
            as_number(r["relocalized_after_frames"])
            for r in rs
            if r.get("relocalized_after_frames") not in ("", None)
        ]
        out.append(
            {
                **dict(zip(by, key, strict=True)),
                "trials": len(rs),
                "successes": len(good),
                # the two ways a trial fails: not converged at its end (never, or re-spread after a "lost"
                # alarm and not converged again), or its last convergence > 5 m off then or at a later check
                "not_converged": len(rs) - len(converged),
                "converged_failed": len(converged) - len(good),  # a success has always converged
                "wrong_convergences": _total(rs, "wrong_convergences"),  # declared > 5 m off (even if caught)
                "wrong_uncaught": _total(
                    rs, "wrong_convergences_uncaught"
                ),  # ... and not undone in 10 frames
                "false_alarms": _total(rs, "false_alarms"),  # declared lost while within 2 m
                "location_rmse_m": float(np.sqrt(np.sum(w * loc**2) / w.sum()))
                if len(good) and w.sum() > 0
                else None,
                "yaw_rmse_deg": float(np.sqrt(np.sum(w * yaw**2) / w.sum()))
                if len(good) and w.sum() > 0
                else None,
                "location_median_m": float(np.median(med)) if med else None,
                "location_rmse_mean_m": float(np.mean(loc)) if len(good) else None,
                "location_rmse_std_m": float(np.std(loc)) if len(good) else None,
                "yaw_rmse_mean_deg": float(np.mean(yaw)) if len(good) else None,
                "yaw_rmse_std_deg": float(np.std(yaw)) if len(good) else None,
                "frames_to_converge_median": float(np.median(conv)) if conv else None,
                "hz_after_median": float(np.median(hz)) if hz else None,
                "seconds_before_median": float(np.median(before)) if before else None,
                # the first correct fix (rows of earlier revisions lack it): compute seconds, metres driven
                "fix_seconds_median": _median_of(rs, lambda r: as_number(r.get("fix_seconds"))),
                "fix_driven_m_median": _median_of(rs, lambda r: as_number(r.get("fix_driven_m"))),
                "startup_seconds_median": _median_of(rs, lambda r: as_number(r.get("startup_seconds"))),
                # realtime trials: scans dropped while the localizer was busy, over all of them
                "late_scans": _total(rs, "late_scans"),
                "relocalized_after_frames_median": float(np.median(reloc)) if reloc else None,
                # the odometry the trials ran with: distance error in per cent (median over the trials),
                # and what is left of it after the filter's calibration (median of its absolute value)
                "odometry_error_pct": _median_of(
                    rs, lambda r: 100.0 * (as_number(r.get("odometry_wheel_scale")) - 1)
                ),
                "calibrated_error_pct": _median_of(
                    rs,
                    lambda r: (
                        100.0
                        * abs(
                            as_number(r.get("odometry_wheel_scale")) * as_number(r.get("calibrated_scale"))
                            - 1
                        )
                    ),
                ),
            }
        )
    return out


def format_value(x, digits=3) -> str:
    """A table cell: ``–`` for a missing value (None, NaN), floats with ``digits`` decimals."""
    return (
        "–"
        if x is None or (isinstance(x, float) and x != x)
        else (f"{x:.{digits}f}" if isinstance(x, float) else str(x))
    )


def write_report(suite: str, rows: list[dict], out: Path) -> tuple[Path, Path]:
    """``OUT/SUITE.md`` and ``OUT/SUITE.png`` from the suite's rows."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by = {
        "particles": ["model", "particles"],
        "sensors": ["sensor"],
        "models": ["model", "route"],
        "kidnap": ["model"],
        "runtime": ["particles"],
        "robustness": ["sensor", "realism"],
    }[suite]
    for r in rows:
        r.setdefault("method", "default")
        r["method"] = r["method"] or "default"
    if len({r["method"] for r in rows}) > 1:  # e.g. the paper's pipeline beside ours on the same trials
        by = ["method", *by]
    agg = aggregate(rows, by)
    lines = [
        f"# simbed trials: {suite}",
        "",
        f"{len(rows)} trials; RMSE over the frames after convergence of "
        "the successful trials; success = location error < 5 m at every 100th frame after convergence; "
        "location_median_m = median over the successful trials of each one's median error after convergence; "
        "the failures split into not_converged (not converged at the trial's end: never, or re-spread "
        "after a 'lost' alarm and not converged again) and converged_failed (its last convergence more than "
        "5 m off then or at a later check). wrong_convergences: convergence declared while more than 5 m off "
        "(counted even when caught), wrong_uncaught: of those, not undone by a re-spread within 10 frames; "
        "false_alarms: 'lost' declared while the estimate was within 2 m. odometry_error_pct: the test "
        "drive's odometry distance error (its drawn wheel scale - 1, per cent, median over the trials); "
        "calibrated_error_pct: what is left of it after the filter's online calibration at the trial's end "
        "(median of the absolute values; the odometry's own error where the calibration is off; – for rows "
        "of earlier revisions). fix_seconds_median, fix_driven_m_median: the first correct convergence's "
        "compute in seconds from the trial's first frame through it, and the metres the car drove meanwhile "
        "(medians over the trials that had one; – for rows of earlier revisions); startup_seconds_median: "
        "the map opened, the filter built and its place priors loaded, before the first frame. late_scans "
        "(methods named -realtime, run at the sensor's pace): the scans dropped because they arrived while "
        "the localizer was busy, over all the trials.",
        "",
    ]
    cols = [*by, "trials", "successes", "location_rmse_m", "yaw_rmse_deg", "frames_to_converge_median"]
    if suite in ("sensors", "particles", "robustness"):
        cols.insert(cols.index("yaw_rmse_deg"), "location_median_m")
        at = cols.index("successes") + 1
        cols[at:at] = [
            "not_converged",
            "converged_failed",
            "wrong_convergences",
            "wrong_uncaught",
            "false_alarms",
        ]
    if suite in ("sensors", "particles", "robustness", "runtime") and any(
        a["fix_seconds_median"] is not None for a in agg
    ):
        at = cols.index("frames_to_converge_median") + 1
        cols[at:at] = ["fix_seconds_median", "fix_driven_m_median"]
    if suite == "models":
        cols += ["location_rmse_mean_m", "location_rmse_std_m", "yaw_rmse_mean_deg", "yaw_rmse_std_deg"]
    if suite in ("sensors", "particles", "models", "kidnap") and any(
        a["odometry_error_pct"] is not None for a in agg
    ):
        cols += ["odometry_error_pct", "calibrated_error_pct"]
    if suite == "sensors":
        cols += ["paper_location_rmse_m", "paper_yaw_rmse_deg"]
        for a in agg:
            a["paper_location_rmse_m"], a["paper_yaw_rmse_deg"] = PAPER_SENSORS.get(a["sensor"], (None, None))
    if any(str(r.get("realtime")).lower() == "true" for r in rows):
        cols += ["late_scans"]
    if suite == "kidnap":
        cols += ["relocalized_after_frames_median"]
    if suite == "runtime":
        cols += ["seconds_before_median", "hz_after_median", "startup_seconds_median"]
    lines.append("| " + " | ".join(cols) + " |")
    lines.append("|" + "---|" * len(cols))
    for a in agg:
        lines.append("| " + " | ".join(format_value(a.get(c)) for c in cols) + " |")
    md = out / f"{suite}.md"
    md.write_text("\n".join(lines) + "\n")

    fig, ax = plt.subplots(figsize=(7, 4.5))
    if suite == "particles":
        names = sorted({a["model"] for a in agg})
        for i, model in enumerate(names):
            pts = sorted(
                (int(as_number(a["particles"])), a["successes"], a["trials"])
                for a in agg
                if a["model"] == model
            )
            shift = 1.0 + 0.04 * (i - (len(names) - 1) / 2)  # side by side where the rates coincide
            ax.plot(
                [p * shift for p, _, _ in pts],
                [k / n for _, k, n in pts],
                marker="osD^v<>"[i % 7],
                linestyle=("-", "--", ":", "-.")[i % 4],
                label=f"{model} (trials per point: {'/'.join(str(n) for _, _, n in pts)})",
            )
        ax.set_xscale("log")
        ax.set_xlabel("particles")
        ax.set_ylabel("success rate")
        ax.set_ylim(-0.05, 1.05)
        ax.legend()
    elif suite == "robustness":  # a grid: a row per preset (and method), a column per realism level
        levels = [lv for lv in REALISM_LEVELS if any((a["realism"] or "ideal") == lv for a in agg)]
        keys = [k for k in by if k != "realism"]
        names = sorted({tuple(str(a[k]) for k in keys) for a in agg})
        rate = np.full((len(names), len(levels)), np.nan)
        for a in agg:
            i, j = names.index(tuple(str(a[k]) for k in keys)), levels.index(a["realism"] or "ideal")
            rate[i, j] = a["successes"] / a["trials"]
            ax.text(j, i, f"{a['successes']}/{a['trials']}", ha="center", va="center", fontsize=9)
        fig.set_size_inches(1.6 * len(levels) + 3.0, 0.45 * len(names) + 1.8)
        im = ax.imshow(rate, vmin=0.0, vmax=1.0, cmap="RdYlGn", aspect="auto")
        ax.set_xticks(range(len(levels)), levels)
        ax.set_yticks(range(len(names)), [" / ".join(n) for n in names])
        fig.colorbar(im, ax=ax, label="success rate")
    else:
        labels = [" / ".join(str(a[k]) for k in by) for a in agg]
        x = np.arange(len(agg))
        if suite == "runtime":
            vals = [a["hz_after_median"] or 0 for a in agg]
            ax.bar(x, vals)
            ax.set_ylabel("Hz after convergence (median)")
        elif suite == "kidnap":
            ax.bar(x, [a["successes"] / a["trials"] for a in agg])
            ax.set_ylabel("relocalization rate")
        else:
            ours = [a["location_rmse_m"] or np.nan for a in agg]
            ax.bar(x - 0.2, ours, 0.4, label="ours")
            if suite == "sensors":
                ax.bar(
                    x + 0.2, [a["paper_location_rmse_m"] or np.nan for a in agg], 0.4, label="paper (Carla)"
                )
                ax.legend()
            ax.set_ylabel("location RMSE (m)")
        ax.set_xticks(x, labels, rotation=20, ha="right")
    ax.set_title(f"simbed trials {suite}")
    fig.tight_layout()
    png = out / f"{suite}.png"
    fig.savefig(png, dpi=120)
    plt.close(fig)
    return md, png
