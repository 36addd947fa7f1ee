"""``simbed trials generalization``: the ``sensors`` suite on towns drawn fresh for every run.

The other suites measure the localizer in the shipped towns, the ones its settings were tuned in. This suite
draws new towns for each run, maps each as a user would and runs the ``sensors`` suite in it:

1. **Draw**: one *run seed* (from the operating system's entropy unless given) draws every town's
   generator seed (unless given), side and style (:func:`draw_towns`); ``--run-seed S`` repeats a run
   town for town. The draw is printed first and recorded in ``OUT/towns.yaml``.
2. **Per town**, into ``OUT/towns/NAME/``: the scene (``simbed make-town``, two parked-car variants), the
   mapping drive (route ``mapping``, no moving actors, parked-car variant 0, until the route's end), the map
   (``rangemcl build-map`` from every 3rd scan), then the ``sensors`` suite in ``suite/``
   (:func:`simbed.trials.suites.run_suite`: test drives with parked-car variant 1 and moving actors).
3. **Report**: ``OUT/generalization.md`` (per sensor over all towns and per sensor per town, the
   :class:`Targets` as a pass/fail line, the seeds) and ``OUT/generalization.csv`` (every trial's row with
   its town).

Every step is skipped when its output is complete (a town's files and sidecar, a drive whose
``meta.yaml`` says complete, a map folder that opens), and the suites skip their finished trials, so the
same command continues an interrupted run: without ``--run-seed`` it takes the run seed that
``OUT/towns.yaml`` recorded. Trial keys name each town's scene by its path, so a run continues where it
was written. A town whose trials all have their rows is not prepared again: a run continues from its
``towns.yaml`` and the towns' ``results.csv`` alone, making only the towns with trials left.
"""

from __future__ import annotations

import csv
import io
import secrets
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from rangemcl.errors import InputError
from simbed.trials.suites import (
    ROW_FIELDS,
    SuiteConfig,
    aggregate,
    as_number,
    format_value,
    is_true,
    read_results,
    run_suite,
    suite_trials,
)

SUITE = "sensors"  # the suite each town runs
MAP_VARIANT = 0  # the parked-car variant of the mapping drive (the test drives take SuiteConfig.variant)
TOWN_SIZE_LIMITS_M = (120, 5000)  # the sides that generate_town accepts
TOWN_SEED_BOUND = 2**31  # drawn town seeds lie in [0, this)
RUN_SEED_BITS = 32  # fresh run seeds lie in [0, 2**this)
TOWNS_YAML = "towns.yaml"
MARKERS = (TOWNS_YAML, "towns", "generalization.md")  # what marks an output folder as this suite's
# generalization.csv's columns before each row's own
TOWN_COLUMNS = ["town", "town_seed", "town_size_m", "town_style"]


@dataclass(frozen=True)
class TownDraw:
    """One town of a run: its folder's name, generator seed, side (m) and named style."""

    name: str
    seed: int
    size_m: int
    style: str


@dataclass
class GeneralizationSettings:
    """What a run draws, how each town is mapped, and the ``sensors`` suite each town runs."""

    towns: int = 5  # towns per run (the number of town_seeds when those are given)
    town_seeds: tuple[int, ...] | None = None  # the towns' generator seeds; None: drawn from the run seed
    sizes_m: tuple[int, int] = (200, 500)  # each town's side is drawn uniformly from this range, m
    styles: tuple[str, ...] | None = None  # cycled in an order drawn from the run seed; None: every named one
    parked_variants: int = 2  # parked-car sets per town (the map sees MAP_VARIANT, the trials suite.variant)
    mapping_sensor: str = "os1-64"
    mapping_frames: int = 100_000  # a cap only: the recorder stops at the mapping route's end first
    map_every_nth: int = 3  # scans the map builder uses (rangemcl build-map's scans.every_nth)
    map_poisson_depth: int | None = None  # the map builder's poisson.depth; None: its default
    suite: SuiteConfig = field(default_factory=lambda: SuiteConfig(drive_frames=800, frames=100, starts=5))

    @classmethod
    def quick(cls) -> GeneralizationSettings:
        """CI size: one 160 m grid town, mapped along the first 200 frames of its mapping route (coarser
        Poisson), one trial of OS1-64 with 1,000 particles on the start of that route (parked-car variant 1,
        two moving actors): the same steps as a full run in about two minutes on two cores."""
        return cls(
            towns=1,
            sizes_m=(160, 160),
            styles=("grid",),
            mapping_frames=200,
            map_poisson_depth=8,
            suite=SuiteConfig(
                route="mapping",
                actors=2,
                drive_frames=40,
                frames=30,
                starts=1,
                sensors=("os1-64",),
                particles=1000,
            ),
        )


def generalization_settings(
    quick: bool = False,
    *,
    towns: int | None = None,
    town_seeds: tuple[int, ...] | None = None,
    sizes: str | None = None,
    styles: str | None = None,
    mapping_sensor: str | None = None,
    suite: dict | None = None,
) -> GeneralizationSettings:
    """The settings of ``simbed trials generalization``: the full or ``quick`` ones, with the options that
    were given (None: not given) in their place; ``suite``: :class:`SuiteConfig` fields. Given seeds set
    the number of towns unless ``towns`` is given too."""
    base = GeneralizationSettings.quick() if quick else GeneralizationSettings()
    if towns is None and town_seeds is not None:
        towns = len(town_seeds)
    given = {
        "towns": towns,
        "town_seeds": town_seeds,
        "sizes_m": None if sizes is None else parse_sizes(sizes),
        "styles": None if styles is None else parse_styles(styles),
        "mapping_sensor": mapping_sensor,
    }
    return replace(
        base,
        suite=replace(base.suite, **(suite or {})),
        **{k: v for k, v in given.items() if v is not None},
    )


@dataclass(frozen=True)
class Targets:
    """The issue's targets for a run of one method: what :func:`check_targets` judges."""

    min_success_rate: float = 0.9  # per sensor, over all towns
    max_held_frames: int = 10  # a wrong convergence held longer (or never undone) fails
    max_false_alarms: int = 0
    rmse_sensor: str = "mq-8"  # the sensor whose every successful trial ...
    max_rmse_m: float = 0.10  # ... has at most this location RMSE
    max_median_frames_to_converge: float = 40.0  # per sensor


# ------------------------------------------------------------------------------------------------- draw


def named_styles() -> dict:
    """The town generator's named styles (``TownStyle`` by name): its ``TOWN_STYLES`` where the generator
    has them, else ``grid`` alone (the default style)."""
    try:
        from simbed.scenes.towngen.style import TOWN_STYLES
    except ImportError:
        from simbed.scenes.towngen import DEFAULT_STYLE

        return {"grid": DEFAULT_STYLE}
    return dict(TOWN_STYLES)


def town_style(name: str):
    """The ``TownStyle`` named ``name``, or one :class:`InputError` line naming the choices."""
    styles = named_styles()
    if name not in styles:
        raise InputError(f"town style {name!r}: expected one of {', '.join(styles)}")
    return styles[name]


def parse_sizes(text: str) -> tuple[int, int]:
    """``--sizes``: ``LOW-HIGH`` or ``SIDE`` in whole metres, within what the town generator accepts."""
    parts = [p.strip() for p in str(text).split("-")]
    try:
        low, high = (int(parts[0]), int(parts[-1])) if 1 <= len(parts) <= 2 else (None, None)
    except ValueError:
        low = high = None
    lo_limit, hi_limit = TOWN_SIZE_LIMITS_M
    if low is None or not lo_limit <= low <= high <= hi_limit:
        raise InputError(
            f"--sizes {text!r}: expected LOW-HIGH (or one side) in whole metres, "
            f"{lo_limit} <= LOW <= HIGH <= {hi_limit}"
        )
    return low, high


def parse_styles(text: str) -> tuple[str, ...]:
    """``--styles``: named styles separated by commas, each checked (:func:`town_style`)."""
    names = tuple(s.strip() for s in str(text).split(",") if s.strip())
    if not names:
        raise InputError(f"--styles {text!r}: expected style names separated by commas")
    for name in names:
        town_style(name)
    return names


def fresh_run_seed() -> int:
    """A run seed from the operating system's entropy."""
    return secrets.randbits(RUN_SEED_BITS)


def draw_towns(settings: GeneralizationSettings, run_seed: int) -> list[TownDraw]:
    """The towns of a run, all drawn from ``run_seed`` (the same seed and settings, the same towns): the
    generator seeds (unless given), the sides (uniform whole metres in ``sizes_m``) and the styles (cycled
    in a drawn order, so that each appears about as often)."""
    s = settings
    check_draw(s)
    if isinstance(run_seed, bool) or not isinstance(run_seed, int) or run_seed < 0:
        raise InputError(f"--run-seed must be a non-negative integer, got {run_seed!r}")
    rng = np.random.default_rng(run_seed)
    n = s.towns
    drawn = [int(x) for x in rng.integers(0, TOWN_SEED_BOUND, size=n)]
    seeds = drawn if s.town_seeds is None else [int(x) for x in s.town_seeds]
    sizes = [int(x) for x in rng.integers(s.sizes_m[0], s.sizes_m[1] + 1, size=n)]
    names = list(s.styles or named_styles())
    order = [names[int(k)] for k in rng.permutation(len(names))]
    out = []
    for i, (seed, size) in enumerate(zip(seeds, sizes, strict=True)):
        style = order[i % len(order)]
        out.append(TownDraw(f"t{i + 1:02d}-{style}-{size}m-s{seed}", seed, size, style))
    return out


def check_draw(s: GeneralizationSettings) -> None:
    """The draw's settings: the number of towns, the given seeds, the sizes and the styles."""
    if s.towns < 1:
        raise InputError(f"--towns must be >= 1, got {s.towns}")
    if s.town_seeds is not None:
        if len(s.town_seeds) != s.towns:
            raise InputError(f"--town-seeds: {len(s.town_seeds)} seeds for {s.towns} towns")
        bad = [x for x in s.town_seeds if isinstance(x, bool) or not isinstance(x, int) or x < 0]
        if bad:
            raise InputError(f"--town-seeds: seeds must be non-negative integers, got {bad[0]!r}")
    parse_sizes(f"{s.sizes_m[0]}-{s.sizes_m[1]}")
    for name in s.styles or ():
        town_style(name)


def check_generalization(
    s: GeneralizationSettings, *, workers: int | None = None, backend: str = "process", device: str = "cpu"
) -> None:
    """Everything a run can check before it writes or records anything: the draw, the counts, the
    sensors, the parked-car variants, the backend and the device (an :class:`InputError` names the
    option)."""
    from rangemcl.raycast import resolve_device
    from rangemcl.sensors import load_spec

    check_draw(s)
    c = s.suite
    for option, value, least in (
        ("--frames", c.frames, 1),
        ("--starts", c.starts, 1),
        ("--drive-frames", c.drive_frames, 1),
        ("--actors", c.actors, 0),
        ("--workers", 0 if workers is None else workers, 0),
        ("mapping_frames", s.mapping_frames, 1),
        ("map_every_nth", s.map_every_nth, 1),
    ):
        if value < least:
            raise InputError(f"{option} must be >= {least}, got {value}")
    if not 0 <= c.variant < s.parked_variants:
        raise InputError(
            f"--variant must be one of the towns' {s.parked_variants} parked-car variants "
            f"(0 to {s.parked_variants - 1}; the map's is {MAP_VARIANT}), got {c.variant}"
        )
    if backend not in ("process", "ray"):
        raise InputError(f"backend {backend!r}: expected 'process' or 'ray'")
    resolve_device(device)
    for sensor in dict.fromkeys([s.mapping_sensor, *(t.sensor for t in suite_trials(SUITE, False, c))]):
        load_spec(sensor)


# -------------------------------------------------------------------------------------------- the run


def run_generalization(
    out_dir,
    settings: GeneralizationSettings | None = None,
    *,
    run_seed: int | None = None,
    workers: int | None = None,
    backend: str = "process",
    address: str | None = None,
    device: str = "cpu",
    say=print,
    report_only: bool = False,
    compare: tuple[SuiteConfig, ...] = (),
) -> list[dict]:
    """Run (or continue) a generalization run into ``out_dir``; write its report; return its rows (the
    results.csv rows of every town's trials, each with the town's columns).

    ``run_seed``: None draws a fresh one, or takes the one ``OUT/towns.yaml`` recorded (a run continues).
    ``report_only``: run nothing, report the trials finished so far of the towns ``OUT/towns.yaml``
    records; ``compare``: other suite configs (other localizer settings: ``settings`` and ``method`` of
    ``settings.suite``) whose trials run in every town after the suite's own, on the same trials, and
    join the report, side by side."""
    s = settings or GeneralizationSettings()
    out = Path(out_dir)
    if report_only:
        record = read_towns_yaml(out)
        towns = [TownDraw(t["name"], t["seed"], t["size_m"], t["style"]) for t in record["towns"]]
        configs = (s.suite, *compare)
        rows, expected = town_rows(out, towns, configs), expected_trials(out, towns, configs)
        if not rows:
            raise InputError(f"{out}: no finished trial of its towns with these settings")
        say(f"generalization: {len(rows)} of {expected} trials finished; report only")
        for line in write_generalization_report(out, record, rows, expected):
            say(line)
        return rows
    check_generalization(s, workers=workers, backend=backend, device=device)
    configs = (s.suite, *compare)
    record, towns = start_run(out, s, run_seed, say)
    for town in towns:
        town_dir = out / "towns" / town.name
        if town_finished(out, town, configs):  # its scene, drives and map are not needed again
            say(f"[{town.name}] every trial of this run is finished; the town is not prepared again")
            continue
        stats = prepare_town(town, town_dir, s, workers=workers, device=device, say=say)
        entry = next(t for t in record["towns"] if t["name"] == town.name)
        entry.update(stats)
        write_towns_yaml(out, record)
        scene = str(scene_path(out, town))
        for config in configs:  # each method on the same trials (the same drives, starts and seeds)
            say(f"[{town.name}] {SUITE} suite ({config.method}) -> {town_dir / 'suite'}")
            run_suite(
                SUITE,
                town_dir / "suite",
                town_dir / "map",
                config=replace(config, scene=scene),
                workers=workers,
                backend=backend,
                address=address,
                device=device,
                say=lambda line, name=town.name: say(f"[{name}] {line}"),
            )
        if compare:  # the town's own table with every method side by side
            run_suite(
                SUITE,
                town_dir / "suite",
                town_dir / "map",
                config=replace(s.suite, scene=scene),
                report_only=True,
                compare=tuple(replace(c, scene=scene) for c in compare),
                say=lambda line: None,
            )
    rows = town_rows(out, towns, configs)
    for line in write_generalization_report(out, record, rows, expected_trials(out, towns, configs)):
        say(line)
    return rows


def scene_path(out: Path, town: TownDraw) -> Path:
    """A town's MJCF file in the run's folder."""
    return out / "towns" / town.name / f"{town.name}.xml"


def start_run(out: Path, s: GeneralizationSettings, run_seed: int | None, say) -> tuple[dict, list[TownDraw]]:
    """The run's record (``towns.yaml``'s document) and towns: those ``OUT/towns.yaml`` recorded when the
    same run continues, else a new draw, recorded before any town is made. A folder holding another draw
    is refused in one line."""
    recorded = read_towns_yaml(out) if (out / TOWNS_YAML).is_file() else None
    if run_seed is None:
        run_seed = recorded["run_seed"] if recorded else fresh_run_seed()
    towns = draw_towns(s, run_seed)
    drawn = [_draw_entry(t) for t in towns]
    if recorded is not None:
        before = [{k: t.get(k) for k in ("name", "seed", "size_m", "style")} for t in recorded["towns"]]
        if before != drawn or recorded["run_seed"] != run_seed:
            raise InputError(
                f"{out / TOWNS_YAML}: holds another draw of towns (run seed {recorded['run_seed']}, "
                f"{len(before)} towns); give that run's options to continue it, --overwrite to start over, "
                "or another --out"
            )
        record = recorded
        say(f"continuing the run of run seed {run_seed}")
    else:
        record = {
            "run_seed": run_seed,
            "draw": {
                "towns": s.towns,
                "town_seeds": None if s.town_seeds is None else list(s.town_seeds),
                "sizes_m": list(s.sizes_m),
                "styles": None if s.styles is None else list(s.styles),
            },
            "towns": drawn,
        }
        out.mkdir(parents=True, exist_ok=True)
        write_towns_yaml(out, record)
    say(f"run seed {run_seed} (--run-seed {run_seed} repeats this run); towns:")
    for t in towns:
        say(f"  {t.name}: seed {t.seed}, {t.size_m} m, style {t.style}")
    return record, towns


def _draw_entry(t: TownDraw) -> dict:
    return {"name": t.name, "seed": t.seed, "size_m": t.size_m, "style": t.style}


def read_towns_yaml(out: Path) -> dict:
    """``OUT/towns.yaml``, checked: a run seed and the towns with their names, seeds, sides and styles."""
    from rangemcl.common.yamlio import parse_yaml, read_text

    path = out / TOWNS_YAML
    doc = parse_yaml(read_text(path, "generalization run record"), str(path))
    towns = doc.get("towns") if isinstance(doc, dict) else None
    ok = isinstance(towns, list) and bool(towns) and isinstance(doc.get("run_seed"), int)
    for t in towns if ok else ():
        ok = ok and isinstance(t, dict) and isinstance(t.get("name"), str) and isinstance(t.get("style"), str)
        ok = ok and isinstance(t.get("seed"), int) and isinstance(t.get("size_m"), int)
    if not ok:
        raise InputError(
            f"{path}: not a generalization run record (run_seed, towns with name, seed, size_m, style)"
        )
    return doc


def write_towns_yaml(out: Path, record: dict) -> Path:
    """``OUT/towns.yaml``, atomically (rewritten as each town's steps finish)."""
    import yaml

    from rangemcl.common.atomic import atomic_write

    return atomic_write(out / TOWNS_YAML, yaml.safe_dump(record, sort_keys=False))


# ------------------------------------------------------------------------------------------ one town


def prepare_town(
    town: TownDraw, town_dir: Path, s: GeneralizationSettings, *, workers: int | None, device: str, say
) -> dict:
    """The town's scene, mapping drive and map, each made unless complete; their figures for towns.yaml."""
    xml = town_dir / f"{town.name}.xml"
    info = ensure_scene(town, xml, s.parked_variants, say)
    drive = ensure_mapping_drive(xml, town_dir / "mapping_drive", town, s, device, say)
    doc = ensure_map(drive, town_dir / "map", s, workers, say)
    meta = _sequence_meta(drive)
    return {
        "road_length_m": float(info.total_length_m),
        "junctions": len(info.nodes),
        "roads": len(info.edges),
        "mapping_drive": {
            "frames": int(meta.get("frames") or 0),
            "route_length_m": meta.get("route_length_m"),
            "route_done": bool(meta.get("route_done")),
        },
        "map": {
            **{k: int(doc["counts"][k]) for k in ("triangles", "vertices", "tiles")},
            "scans_used": (doc.get("meta") or {}).get("scans_used"),
            "every_nth": s.map_every_nth,
        },
    }


def ensure_scene(town: TownDraw, xml: Path, parked_variants: int, say):
    """The town's files (``simbed make-town``), generated unless complete; its ``TownInfo``."""
    from simbed.scenes.towngen import generate_town

    info = _complete_scene(town, xml, parked_variants)
    if info is not None:
        say(f"[{town.name}] scene: reusing {xml}")
        return info
    say(f"[{town.name}] scene: seed {town.seed}, {town.size_m} m, style {town.style} -> {xml}")
    return generate_town(
        town.seed, town.size_m, xml, n_parked_variants=parked_variants, style=town_style(town.style)
    )


def _complete_scene(town: TownDraw, xml: Path, parked_variants: int):
    """The ``TownInfo`` of a town written whole with this seed, side, style and parked-car variants, else
    None (the sidecar is written after the XML, the terrain and the texture; ``car.xml`` is copied last)."""
    from simbed.scenes.towngen import CAR_XML, load_town_info, town_files

    car = xml.parent / "car.xml"
    if not all(p.is_file() for p in town_files(xml)) or not car.is_file():
        return None
    if car.read_bytes() != CAR_XML.read_bytes():
        return None
    try:
        info = load_town_info(xml.with_suffix(".yaml"))
    except InputError:
        return None
    made = (info.seed, info.size_m, info.style, info.parked_variants)
    same = made == (town.seed, town.size_m, town.style, parked_variants)
    return info if same else None


def ensure_mapping_drive(xml: Path, path: Path, town: TownDraw, s: GeneralizationSettings, device: str, say):
    """The town's mapping drive (route ``mapping``, no moving actors, parked-car variant 0, to the route's
    end), recorded unless complete."""
    from simbed.record import record, resumable

    if _sequence_meta(path).get("complete"):
        say(f"[{town.name}] mapping drive: reusing {path}")
        return path
    say(f"[{town.name}] mapping drive: route 'mapping', {s.mapping_sensor}, no moving actors -> {path}")
    r = record(
        str(xml),
        "mapping",
        s.mapping_sensor,
        path,
        frames=s.mapping_frames,
        variant=MAP_VARIANT,
        seed=town.seed,
        device=device,
        overwrite=True,
        progress=False,
        resume=resumable(path),
    )
    say(f"[{town.name}]   {r.frames} frames, {r.distance_driven_m:.0f} m of {r.route_length_m:.0f} m")
    if r.stuck_at is not None:
        say(
            f"[{town.name}]   warning: the car got stuck at ({r.stuck_at[0]:.1f}, {r.stuck_at[1]:.1f}): "
            "the map covers the route up to there"
        )
    return path


def _sequence_meta(path: Path) -> dict:
    """A recorded drive's ``meta.yaml`` (empty when there is no readable drive)."""
    from rangemcl.datasets.kitti import load_sequence

    try:
        return dict(load_sequence(path).meta)
    except InputError:
        return {}


def ensure_map(drive: Path, map_dir: Path, s: GeneralizationSettings, workers: int | None, say) -> dict:
    """The town's map (``rangemcl build-map`` from every ``map_every_nth``-th scan), built unless the
    folder opens whole (an interrupted build is resumed); its ``map.yaml`` document."""
    import shutil

    from rangemcl.mapping.pipeline import WORK_DIR, MapSettings, build_map
    from rangemcl.maps.meshmap import open_map_folder

    if map_dir.is_dir() and not (map_dir / WORK_DIR).exists():
        try:
            doc = open_map_folder(map_dir)[1]
        except InputError:
            pass
        else:
            say(f"[{map_dir.parent.name}] map: reusing {map_dir}")
            return doc
    ms = MapSettings()
    ms.scans.every_nth = s.map_every_nth
    if s.map_poisson_depth is not None:
        ms.poisson.depth = s.map_poisson_depth
    ms.workers = workers or 0
    resume = (map_dir / WORK_DIR / "state.json").is_file()
    if map_dir.exists() and not resume:
        shutil.rmtree(map_dir)
    how = "resuming the interrupted build" if resume else f"every {s.map_every_nth}. scan"
    say(f"[{map_dir.parent.name}] map: {how} -> {map_dir}")
    r = build_map(drive, map_dir, ms, resume=resume)
    say(f"[{map_dir.parent.name}]   {r.triangles:,} triangles in {r.tiles} tiles from {r.scans_used} scans")
    return open_map_folder(map_dir)[1]


# --------------------------------------------------------------------------------------------- report


def town_rows(out: Path, towns: list[TownDraw], configs: tuple[SuiteConfig, ...]) -> list[dict]:
    """The results.csv rows of the towns' trials of these configs, each with the town's columns first."""
    rows = []
    for town in towns:
        keys = _trial_keys(out, town, configs)
        for r in read_results(out / "towns" / town.name / "suite" / "results.csv"):
            if r.get("key") in keys:
                rows.append(
                    {
                        "town": town.name,
                        "town_seed": town.seed,
                        "town_size_m": town.size_m,
                        "town_style": town.style,
                        **r,
                    }
                )
    return rows


def town_finished(out: Path, town: TownDraw, configs: tuple[SuiteConfig, ...]) -> bool:
    """Whether every trial of these configs in the town has its row in the town's results.csv (a run
    continued from the rows alone, its towns' files gone, makes only the towns with trials left)."""
    done = {r.get("key") for r in read_results(out / "towns" / town.name / "suite" / "results.csv")}
    return _trial_keys(out, town, configs) <= done


def expected_trials(out: Path, towns: list[TownDraw], configs: tuple[SuiteConfig, ...]) -> int:
    """How many trials the towns hold with these configs, finished or not."""
    return sum(len(_trial_keys(out, town, configs)) for town in towns)


def _trial_keys(out: Path, town: TownDraw, configs: tuple[SuiteConfig, ...]) -> set[str]:
    scene = str(scene_path(out, town))
    return {t.key for c in configs for t in suite_trials(SUITE, False, replace(c, scene=scene))}


def held_too_long(row: dict, max_held_frames: int) -> bool:
    """Whether a trial held a wrong convergence more than ``max_held_frames`` frames: one not undone
    within 10 frames (``wrong_convergences_uncaught``), or held longer (``wrong_held_max_frames``; rows
    of earlier revisions lack it)."""
    return (
        as_number(row.get("wrong_convergences_uncaught")) > 0
        or as_number(row.get("wrong_held_max_frames")) > max_held_frames
    )


def summarize(rows: list[dict], by: list[str], targets: Targets | None = None) -> list[dict]:
    """Per group (:func:`simbed.trials.suites.aggregate`'s figures, with the same grouping and order):
    besides, the wrong convergences caught within 10 frames, the trials that held one longer, the longest
    held, and the largest location RMSE of a successful trial."""
    t = targets or Targets()
    out = []
    for a in aggregate(rows, by):
        rs = [r for r in rows if all(r[k] == a[k] for k in by)]
        good = [v for v in (as_number(r["location_rmse_m"]) for r in rs if is_true(r["success"])) if v == v]
        held = [v for v in (as_number(r.get("wrong_held_max_frames")) for r in rs) if v == v]
        wrong, uncaught = a["wrong_convergences"], a["wrong_uncaught"]
        out.append(
            {
                **a,
                "success": f"{a['successes']}/{a['trials']}",
                "wrong_caught": None if wrong is None or uncaught is None else wrong - uncaught,
                "trials_held_too_long": sum(held_too_long(r, t.max_held_frames) for r in rs),
                "wrong_held_max_frames": int(max(held)) if held else None,
                "location_rmse_max_m": max(good) if good else None,
            }
        )
    return out


def check_targets(rows: list[dict], targets: Targets | None = None) -> list[tuple[str, bool | None, str]]:
    """The targets judged on one method's rows: ``(target, passed, what was found)``; passed is None
    where nothing could be judged (no trial of the RMSE target's sensor)."""
    t = targets or Targets()
    per_sensor = summarize(rows, ["sensor"], t)
    low = [a for a in per_sensor if a["successes"] < round(t.min_success_rate * a["trials"], 9)]
    held = sum(held_too_long(r, t.max_held_frames) for r in rows)
    alarms = sum(a["false_alarms"] or 0 for a in per_sensor)
    judged = [r for r in rows if r["sensor"] == t.rmse_sensor and is_true(r["success"])]
    rmse = [as_number(r["location_rmse_m"]) for r in judged]
    worst = max(rmse, key=lambda v: np.inf if v != v else v) if rmse else None  # a missing RMSE fails
    most = t.max_median_frames_to_converge
    slow = [
        a
        for a in per_sensor
        if a["frames_to_converge_median"] is None or a["frames_to_converge_median"] > most
    ]
    return [
        (
            f"success >= {t.min_success_rate:.0%} per sensor",
            not low,
            ", ".join(f"{a['sensor']} {a['success']}" for a in per_sensor),
        ),
        (
            f"no wrong convergence held > {t.max_held_frames} frames",
            held == 0,
            f"{held} trials held one longer",
        ),
        (f"at most {t.max_false_alarms} false alarms", alarms <= t.max_false_alarms, f"{alarms}"),
        (
            f"every successful {t.rmse_sensor} trial's RMSE <= {t.max_rmse_m:g} m",
            None if worst is None else bool(worst <= t.max_rmse_m),  # NaN fails
            f"no successful {t.rmse_sensor} trial"
            if worst is None
            else f"largest {worst:.3f} m of {len(rmse)}",
        ),
        (
            f"median frames to converge <= {t.max_median_frames_to_converge:g} per sensor",
            not slow,
            ", ".join(f"{a['sensor']} {format_value(a['frames_to_converge_median'], 0)}" for a in per_sensor),
        ),
    ]


def verdict_line(method: str, checks: list[tuple[str, bool | None, str]]) -> str:
    """One line: PASS when every target that could be judged passed, each target with what was found."""
    failed = any(ok is False for _, ok, _ in checks)
    parts = [
        f"{name}: {'n/a' if ok is None else 'pass' if ok else 'FAIL'} ({found})" for name, ok, found in checks
    ]
    return f"targets ({method}): {'FAIL' if failed else 'PASS'}; " + "; ".join(parts)


TABLE_COLUMNS = [
    "trials",
    "success",
    "wrong_convergences",
    "wrong_caught",
    "wrong_uncaught",
    "wrong_held_max_frames",
    "trials_held_too_long",
    "false_alarms",
    "frames_to_converge_median",
    "location_rmse_m",
    "location_rmse_max_m",
    "yaw_rmse_deg",
]


TOWN_TABLE_COLUMNS = [
    "town",
    "style",
    "size_m",
    "seed",
    "road_length_m",
    "junctions",
    "mapping_frames",
    "map_triangles",
    "map_tiles",
]


def write_generalization_report(out: Path, record: dict, rows: list[dict], expected: int) -> list[str]:
    """``OUT/generalization.md`` and ``OUT/generalization.csv`` from the run's rows; the targets' lines
    (one per method)."""
    from rangemcl.common.atomic import atomic_write

    for r in rows:
        r["method"] = r.get("method") or "default"
    methods = list(dict.fromkeys(r["method"] for r in rows))
    lead = ["method"] if len(methods) > 1 else []
    verdicts = [verdict_line(m, check_targets([r for r in rows if r["method"] == m])) for m in methods]
    seed = record["run_seed"]
    lines = [
        "# simbed trials: generalization",
        "",
        f"Run seed {seed} (`--run-seed {seed}` repeats this run); towns drawn: {len(record['towns'])}, "
        f"{len(rows)} of {expected} trials finished. Each town is mapped from its own mapping drive "
        f"(parked-car variant {MAP_VARIANT}), its trials run on test drives with other parked cars and "
        "moving actors (`towns/NAME/suite/`).",
        "",
        "success: successful trials / trials (location error < 5 m at every 100th frame after convergence); "
        "wrong_convergences: convergence declared while more than 5 m off (counted even when caught), "
        "wrong_caught: of those, undone by a re-spread within 10 frames, wrong_uncaught: not; "
        "wrong_held_max_frames: the longest a trial held a wrong convergence (to the re-spread that undid "
        "it, or to the trial's end), trials_held_too_long: trials that held one more than "
        f"{Targets().max_held_frames} frames or never undid it; false_alarms: 'lost' declared while within "
        "2 m of the truth; frames_to_converge_median over the trials that converged; location and yaw RMSE "
        "over the frames after convergence of the successful trials (location_rmse_max_m: the largest of "
        "one trial).",
        "",
        "## Per sensor, all towns",
        "",
        *_table(summarize(rows, [*lead, "sensor"]), [*lead, "sensor"]),
        "",
        *verdicts,
        "",
        "## Per sensor and town",
        "",
        *_table(summarize(rows, [*lead, "town", "sensor"]), [*lead, "town", "sensor"]),
        "",
        "## Towns",
        "",
        "| " + " | ".join(TOWN_TABLE_COLUMNS) + " |",
        "|" + "---|" * len(TOWN_TABLE_COLUMNS),
        *(_town_line(t) for t in record["towns"]),
        "",
    ]
    atomic_write(out / "generalization.md", "\n".join(lines))
    text = io.StringIO()
    writer = csv.DictWriter(text, fieldnames=[*TOWN_COLUMNS, *ROW_FIELDS], restval="", extrasaction="ignore")
    writer.writeheader()
    writer.writerows(rows)
    atomic_write(out / "generalization.csv", text.getvalue())
    return verdicts


def _table(groups: list[dict], by: list[str]) -> list[str]:
    cols = [*by, *TABLE_COLUMNS]
    return [
        "| " + " | ".join(cols) + " |",
        "|" + "---|" * len(cols),
        *("| " + " | ".join(format_value(g.get(c)) for c in cols) + " |" for g in groups),
    ]


def _town_line(t: dict) -> str:
    drive, m = t.get("mapping_drive") or {}, t.get("map") or {}
    cells = [
        t["name"],
        t["style"],
        t["size_m"],
        t["seed"],
        format_value(t.get("road_length_m"), 0),
        t.get("junctions"),
        drive.get("frames"),
        m.get("triangles"),
        m.get("tiles"),
    ]
    return "| " + " | ".join("–" if c is None else str(c) for c in cells) + " |"
