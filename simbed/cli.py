"""The ``simbed`` console script. Heavy imports live inside the commands so ``--help`` stays fast."""

from __future__ import annotations

from pathlib import Path

import typer

from rangemcl.common.cliutil import run_app, version_option
from simbed import __version__
from simbed.sim import DEFAULT_SENSOR_MODEL

app = typer.Typer(
    name="simbed",
    help="Simulation test bed: MuJoCo towns, a driven car, simulated LiDAR, recorded drives.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root(version: bool = version_option(__version__)) -> None:
    """Simulation test bed: MuJoCo towns, a driven car, simulated LiDAR, recorded drives."""


@app.command("make-town")
def make_town(
    out: Path = typer.Option(..., help="MJCF file to write (its .yaml sidecar is written beside it)."),
    seed: int = typer.Option(0, help="Seed of the layout."),
    size: float = typer.Option(400.0, help="Side of the square town, metres."),
    variants: int = typer.Option(2, help="Parked-car variants (one per mapping/test run)."),
    style: str = typer.Option(
        "grid",
        help="grid (straight roads on a jittered grid, the shipped towns), suburb (winding roads between "
        "scattered junctions, low houses, many trees) or mixed (a grid with some roads bent, tall centre, "
        "low outskirts).",
    ),
    overwrite: bool = typer.Option(False, help="Replace a town that OUT (and its files beside it) holds."),
) -> None:
    """Generate a town: roads with loops and junctions, terrain, buildings, poles, trees, parked cars."""
    from simbed.scenes.towngen import generate_town, town_style

    info = generate_town(
        seed, size, out, n_parked_variants=variants, style=town_style(style), overwrite=overwrite
    )
    typer.echo(
        f"wrote {out} and {out.with_suffix('.yaml')} ({info.style} style): {len(info.nodes)} junctions and "
        f"bends, {len(info.edges)} roads, {info.total_length_m:.0f} m of road, {info.parked_variants} "
        "parked-car variants"
    )


@app.command()
def record(
    out: Path = typer.Option(
        ..., help="Sequence folder to write (KITTI layout), a ROS 2 bag folder, or a ROS 1 .bag file."
    ),
    scene: str = typer.Option("town_small", help="Scene name in scenes/ or an MJCF file."),
    route: str = typer.Option(
        "mapping",
        help="mapping, test, test-N (towns' road networks), or a waypoint file ('x y' or 'x y speed' per "
        "line; any scene).",
    ),
    sensor: str = typer.Option("os1-64", help="LiDAR preset or sensor YAML."),
    frames: int = typer.Option(100, help="LiDAR frames to record (fewer if the route ends first)."),
    actors: int = typer.Option(
        0, help="Moving actors (cars, cyclists, pedestrians): on a town's roads, else beside the route."
    ),
    variant: int = typer.Option(0, help="Parked-car variant present in the scene."),
    seed: int = typer.Option(0, help="Seed of everything random in the run."),
    skew: bool = typer.Option(True, help="Per-column sensor poses, so motion skews the scan."),
    device: str = typer.Option("cpu", help="Warp device: cpu or cuda."),
    overwrite: bool = typer.Option(False, help="Replace an existing sequence in OUT."),
    loop: bool = typer.Option(False, help="Close the waypoint route and drive it lap after lap."),
    actor_paths: Path = typer.Option(
        None, help="YAML file of actors with their own paths (kind, speed, loop, start_m, waypoints)."
    ),
    fmt: str = typer.Option(
        "kitti",
        "--format",
        help="kitti (folder), mcap (ROS 2 bag folder holding one .mcap), rosbag2 (ROS 2 bag folder, "
        "SQLite) or rosbag1 (.bag file); bags need the [ros] extra.",
    ),
    viz: bool = typer.Option(False, help="Stream the scene, car, sweeps and actors to the rerun viewer."),
    viz_out: Path = typer.Option(None, help="Save the drive as a rerun .rrd file (headless)."),
    sensor_model: str = typer.Option(
        DEFAULT_SENSOR_MODEL,
        help="ideal (every surface returns every ray; intensity 0) or realistic (materials decide "
        "returns, range noise and intensity).",
    ),
    weather: str = typer.Option(
        "clear",
        help="realistic sensor: clear, fog:VISIBILITY_M (e.g. fog:100) or rain:MM_PER_H (e.g. rain:10).",
    ),
    returns: str = typer.Option(
        "strongest",
        help="realistic sensor: strongest, last or dual echoes (last, dual: sensors that have them).",
    ),
    dropout: float = typer.Option(0.0, help="Share of the returns dropped at random on top (a stress test)."),
    resume: bool = typer.Option(
        False,
        help="Continue an interrupted KITTI recording in OUT from its last checkpoint (one every "
        "200 frames), with the same options; the result has the bytes of an uninterrupted one.",
    ),
) -> None:
    """Drive a route and record LiDAR, ground-truth poses, odometry and IMU in the KITTI layout or as a
    ROS bag / MCAP (PointCloud2 with per-point time and ring, IMU, odometry, TF, truth, actors).

    Any MJCF scene can be driven: without a `car` body simbed adds its car at the route's start, and
    without a town's sidecar the ground is found in the scene's own geometry."""
    import sys

    from simbed.record import record as run_record

    try:
        s = run_record(
            scene,
            route,
            sensor,
            out,
            frames=frames,
            actors=actors,
            variant=variant,
            seed=seed,
            skew=skew,
            device=device,
            overwrite=overwrite,
            progress=sys.stderr.isatty(),
            loop=loop,
            actor_paths=actor_paths,
            fmt=fmt,
            viz=viz,
            viz_out=viz_out,
            sensor_model=sensor_model,
            weather=weather,
            return_mode=returns,
            dropout=dropout,
            resume=resume,
        )
    except KeyboardInterrupt:
        from rangemcl.datasets.sources import open_source
        from rangemcl.errors import InputError

        try:
            done = len(open_source(out))
        except InputError:
            done = 0
        where = "meta.yaml" if fmt == "kitti" else "its /simbed/meta message"
        again = ""
        if fmt == "kitti":
            from simbed.record import checkpoint_path

            if checkpoint_path(out).is_file():
                again = "; the same command with --resume continues it from its last checkpoint"
        typer.echo(
            f"interrupted: {done} complete frames in {out} (readable; {where} says complete: false){again}",
            err=True,
        )
        raise typer.Exit(130) from None
    if s.stuck_at is not None:
        typer.echo(
            f"warning: the car got stuck at ({s.stuck_at[0]:.1f}, {s.stuck_at[1]:.1f}); recording stopped",
            err=True,
        )
    typer.echo(
        f"wrote {s.frames} frames to {s.out} ({s.seconds_simulated:.1f} s simulated, "
        f"{s.distance_driven_m:.0f} m "
        f"of a {s.route_length_m:.0f} m route{', route finished' if s.route_done else ''})"
    )


@app.command("import-scene")
def import_scene(
    world: Path = typer.Argument(..., help="A triangle mesh: .obj, .ply, .stl, .glb/.gltf or .off."),
    out: Path = typer.Option(..., help="The MJCF scene to write (.xml; its meshes and ground go beside it)."),
    scale: float = typer.Option(1.0, help="Metres per unit of the file (0.01 for centimetres)."),
    up: str = typer.Option("auto", help="The file's up axis: z, y, or auto (y for glTF, z otherwise)."),
    ground_cell: float = typer.Option(0.5, help="Cell of the height field the car drives on (metres)."),
    max_piece_faces: int = typer.Option(200_000, help="Triangles per mesh piece at most."),
    overwrite: bool = typer.Option(False, help="Replace a scene imported before into OUT."),
    material: str = typer.Option(
        None, help="What the mesh is made of, for the realistic sensor (a name of simbed/sim/materials.yaml)."
    ),
    face_materials: Path = typer.Option(
        None, help="A text file of one material name per face (the mesh's face order), overriding --material."
    ),
) -> None:
    """Turn a static triangle mesh (a city model, a photogrammetry, a rangemcl map) into a drivable scene:
    the LiDAR sees the whole mesh, the car drives on a height field sampled from its ground."""
    from simbed.scenes.import_scene import import_scene as run

    r = run(
        world,
        out,
        scale=scale,
        up=up,
        ground_cell_m=ground_cell,
        max_piece_faces=max_piece_faces,
        overwrite=overwrite,
        material=material,
        face_materials=face_materials,
    )
    rows, cols = r.ground_shape
    typer.echo(
        f"wrote {r.out}: {r.triangles:,} triangles in {r.pieces} mesh pieces, ground {rows} x {cols} cells "
        f"of {r.ground_cell_m:.2f} m ({r.ground_cells_without_ground:,} without ground), {r.seconds:.1f} s"
    )


@app.command("export-mesh")
def export_mesh(
    out: Path = typer.Option(..., help="PLY file to write."),
    scene: str = typer.Option("town_small", help="Scene name in scenes/ or an MJCF file."),
    variant: int = typer.Option(0, help="Parked-car variant to include."),
    route_out: Path = typer.Option(
        None,
        help="Also write a route of the town's roads as waypoints ('x y' per line): where the car drives, "
        "for `rangemcl import-mesh --drive`.",
    ),
    route: str = typer.Option("mapping", help="With --route-out: the route (mapping: every road)."),
    overwrite: bool = typer.Option(False, help="Replace the PLY file (and the route file) that exist."),
) -> None:
    """Write the scene's true static geometry (the ground truth of map quality) as PLY."""
    from rangemcl.common.outdir import check_output_files, output_files
    from simbed.sim.geometry import write_ply
    from simbed.sim.world import World

    files = [out] if route_out is None else [out, route_out]
    check_output_files(files, overwrite=overwrite, what="the exported mesh")  # before the scene is read
    world = World(scene, variant=variant)
    if route_out is not None:
        from simbed.record import scene_route

        r = scene_route(world, route)  # checked before anything is written
    v, f = world.static_triangles
    with output_files(files, overwrite=overwrite, what="the exported mesh"):
        write_ply(out, v, f)
        if route_out is not None:
            from rangemcl.common.atomic import atomic_write

            atomic_write(route_out, "".join(f"{x:.3f} {y:.3f}\n" for x, y in r.points))
    typer.echo(f"wrote {out}: {len(f):,} triangles, {len(v):,} vertices")
    if route_out is not None:
        typer.echo(f"wrote {route_out}: route {route}, {len(r.points):,} points, {r.length_m / 1000:.1f} km")


@app.command()
def demo(
    out: Path = typer.Option(Path("out/demo"), help="Folder for the drives, the map and the results."),
    seed: int = typer.Option(0, help="Seed of the drives and of the localizer."),
    device: str = typer.Option("cpu", help="Warp device: cpu or cuda."),
    test_frames: int = typer.Option(400, help="Frames of the test drive."),
    particles: int = typer.Option(10000, help="Particles for global localization."),
    overwrite: bool = typer.Option(False, help="Replace the demo that OUT holds (finished or not)."),
    sensor_model: str = typer.Option(
        DEFAULT_SENSOR_MODEL,
        help="Both drives' LiDAR: ideal, or realistic (materials decide returns, noise, intensity).",
    ),
) -> None:
    """Map town_small, record a test drive with other parked cars and moving actors, localize globally in
    the map, and print the metrics (plots in OUT/results). Run again with the same options, an
    interrupted demo continues where it stopped."""
    from rangemcl.cli import metrics_line
    from simbed.demo import DemoSettings, run_demo

    s = run_demo(
        out,
        DemoSettings(seed=seed, test_frames=test_frames, particles=particles, sensor_model=sensor_model),
        device=device,
        say=typer.echo,
        overwrite=overwrite,
    )
    m = s.get("metrics") or {}
    typer.echo(
        f"demo done in {s['demo_seconds']['total']:.0f} s: converged at frame {s['converged_frame']}, "
        f"{s['hz_after_convergence'] or 0:.1f} Hz after convergence"
    )
    typer.echo(metrics_line(m))
    typer.echo(f"plots: {out / 'results'}/trajectory.png, error.png, particles.png")


def _int_list(text: str, option: str) -> tuple[int, ...]:
    from rangemcl.errors import InputError

    try:
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise InputError(f"{option}: expected integers separated by commas, got {text!r}") from None


@app.command()
def trials(
    suite: str = typer.Argument(
        ..., help="particles, sensors, models, kidnap, runtime, robustness or generalization."
    ),
    out: Path = typer.Option(
        ...,
        help="Suite folder (drives, trials, results.csv, SUITE.md, SUITE.png; generalization: towns.yaml, "
        "towns/, generalization.md and .csv).",
    ),
    map_dir: Path = typer.Option(
        None,
        "--map",
        help="The scene's map folder (rangemcl build-map); every suite but generalization, which maps the "
        "towns it draws.",
    ),
    quick: bool = typer.Option(False, help="A handful of trials (CI size; generalization: one tiny town)."),
    scene: str = typer.Option(
        None, help="Scene of the test drives (default town_small; not generalization)."
    ),
    route: str = typer.Option(None, help="Route of the test drives (default test)."),
    sensor: str = typer.Option(
        None, help="Sensor (all suites but 'sensors'; default os1-64); generalization: of the mapping drives."
    ),
    actors: int = typer.Option(None, help="Moving actors in the test drives (default 10)."),
    variant: int = typer.Option(None, help="Parked-car variant of the test drives (default 1)."),
    drive_frames: int = typer.Option(
        None, help="Frames of each test drive (default 1000; generalization 800)."
    ),
    frames: int = typer.Option(None, help="Frames of each trial (default 250; generalization 100)."),
    starts: int = typer.Option(None, help="Start points per setting (default 10; generalization 5)."),
    counts: str = typer.Option(
        None,
        help="Suite 'particles': particle counts, comma-separated (default 1000,5000,10000,50000,100000).",
    ),
    models: str = typer.Option(
        None, help="Suites 'particles' and 'models': observation models, comma-separated (default: all four)."
    ),
    sensors: str = typer.Option(
        None,
        help="Suites 'sensors', 'robustness' and 'generalization': sensor presets, comma-separated "
        "(default: the paper's five).",
    ),
    levels: str = typer.Option(
        None,
        help="Robustness: sensor realism levels, comma-separated (default ideal,realistic,rain,fog,dropout).",
    ),
    realism: str = typer.Option(
        None,
        help="Every suite but robustness: the test drives' sensor, one of ideal, realistic, rain, fog, "
        "dropout (the robustness suite's levels; trial keys and drive folders name it; default "
        f"{DEFAULT_SENSOR_MODEL}).",
    ),
    towns: int = typer.Option(None, help="Generalization: towns to draw (default 5)."),
    town_seeds: str = typer.Option(
        None, help="Generalization: the towns' generator seeds, comma-separated (default: drawn)."
    ),
    run_seed: int = typer.Option(
        None,
        help="Generalization: the seed of every draw, printed and recorded in OUT/towns.yaml; it repeats a "
        "run (default: fresh from the OS, or the one OUT/towns.yaml recorded, to continue that run).",
    ),
    sizes: str = typer.Option(
        None, help="Generalization: the towns' sides are drawn from LOW-HIGH metres (default 200-500)."
    ),
    styles: str = typer.Option(
        None, help="Generalization: town styles, comma-separated, cycled (default: every named style)."
    ),
    workers: int = typer.Option(None, help="Trials in parallel (default: all cores)."),
    backend: str = typer.Option("process", help="process (local pool) or ray."),
    address: str = typer.Option(None, help="Ray cluster address (backend ray; default: a local instance)."),
    device: str = typer.Option("cpu", help="Warp device: cpu or cuda."),
    config: Path = typer.Option(
        None,
        help="Localizer settings YAML for every trial (as rangemcl localize --config; the suite still sets "
        "the observation model and particle count). Trial keys get a tag of these settings.",
    ),
    report_only: bool = typer.Option(
        False, help="Run nothing: write the table and figure from the trials already in results.csv."
    ),
    compare: list[str] = typer.Option(
        None,
        help="Also report the same trials run with this localizer settings YAML ('default': no --config), "
        "side by side (a method column); may be given more than once. With --report-only, or with suite "
        "generalization, which runs them too (in each town, after --config's).",
    ),
    overwrite: bool = typer.Option(
        False, help="Start the suite folder over (its drives, trials and results are replaced)."
    ),
    realtime: bool = typer.Option(
        False,
        help="Every trial at the sensor's pace (rangemcl localize --realtime: a scan that arrives while the "
        "localizer is busy is dropped); the method's name gets '-realtime'. Its results depend on the "
        "machine's speed and load: run such trials alone.",
    ),
) -> None:
    """Run (or continue) one of the paper's experiments as a suite of localization trials, or
    (generalization) the sensors suite in towns drawn fresh for the run, each mapped first.

    A suite folder is continued by design: trials already in its results.csv are kept and not run again
    (trial keys name every setting), so rerunning the same command after an interruption finishes it."""
    from dataclasses import replace

    from rangemcl.errors import InputError
    from simbed.trials.suites import SUITES, run_suite

    general = suite == "generalization"
    if suite not in (*SUITES, "generalization"):
        raise InputError(f"suite {suite!r}: expected one of {', '.join(SUITES)}, generalization")
    if compare and not (report_only or general):
        raise InputError(
            "--compare: only with --report-only, or with suite generalization (run each method of a "
            "one-scene suite with its own --config)"
        )
    given = {
        "scene": scene,
        "route": route,
        "sensor": None if general else sensor,  # generalization: the mapping drives' sensor
        "variant": variant,
        "actors": actors,
        "drive_frames": drive_frames,
        "frames": frames,
        "starts": starts,
        "particle_counts": None if counts is None else _int_list(counts, "--counts"),
        "models": None if models is None else tuple(m.strip() for m in models.split(",") if m.strip()),
        "sensors": None if sensors is None else tuple(m.strip() for m in sensors.split(",") if m.strip()),
        "levels": None if levels is None else tuple(m.strip() for m in levels.split(",") if m.strip()),
        "realism": realism,
        "realtime": realtime or None,
    }
    if realism is not None and suite == "robustness":
        raise InputError("--realism: the robustness suite takes its realism levels from --levels")
    given = {k: v for k, v in given.items() if v is not None}
    draw = {
        "--towns": towns,
        "--town-seeds": town_seeds,
        "--run-seed": run_seed,
        "--sizes": sizes,
        "--styles": styles,
    }
    if general:
        others_given = {"--map": map_dir, "--scene": scene, "--counts": counts, "--models": models}
        gen = _generalization_settings(quick, sensor, given, others_given, draw)
        base = gen.suite
    else:
        _check_suite_options(suite, draw, map_dir, report_only)
        from simbed.trials.suites import SuiteConfig

        base = SuiteConfig(**given)
    suite_config, others = _methods(base, config, compare)

    def run():
        if general:
            from simbed.trials.generalization import run_generalization

            return run_generalization(
                out,
                replace(gen, suite=suite_config),
                run_seed=run_seed,
                workers=workers,
                backend=backend,
                address=address,
                device=device,
                say=typer.echo,
                report_only=report_only,
                compare=others,
            )
        return run_suite(
            suite,
            out,
            map_dir,
            quick=quick,
            config=suite_config,
            workers=workers,
            backend=backend,
            address=address,
            device=device,
            say=typer.echo,
            report_only=report_only,
            compare=others,
        )

    rows = _in_suite_folder(out, general, report_only, overwrite, run)
    ok = sum(str(r["success"]).lower() == "true" for r in rows)
    if general:
        typer.echo(
            f"{suite}: {ok}/{len(rows)} trials successful; report {out}/generalization.md, every trial's row "
            f"with its town {out}/generalization.csv"
        )
    else:
        typer.echo(
            f"{suite}: {ok}/{len(rows)} trials successful; table {out}/{suite}.md, figure {out}/{suite}.png"
        )


def _generalization_settings(quick: bool, sensor, given: dict, refused: dict, draw: dict):
    """The generalization suite's settings from the ``trials`` options (``refused``: options it does not
    take, by name; ``draw``: the town draw's options)."""
    from rangemcl.errors import InputError
    from simbed.trials.generalization import generalization_settings

    for option, value in refused.items():
        if value is not None:
            raise InputError(f"{option}: not for suite 'generalization' (it draws its towns and maps them)")
    seeds = draw["--town-seeds"]
    return generalization_settings(
        quick,
        towns=draw["--towns"],
        town_seeds=None if seeds is None else _int_list(seeds, "--town-seeds"),
        sizes=draw["--sizes"],
        styles=draw["--styles"],
        mapping_sensor=sensor,
        suite=given,
    )


def _check_suite_options(suite: str, draw: dict, map_dir, report_only: bool) -> None:
    """A suite in one scene: no town draw's options, and a map unless it only reports."""
    from rangemcl.errors import InputError

    option = next((o for o, v in draw.items() if v is not None), None)
    if option is not None:
        raise InputError(f"{option}: only for suite 'generalization'")
    if map_dir is None and not report_only:
        raise InputError(f"--map: suite {suite!r} needs the scene's map folder (rangemcl build-map)")


def _methods(base, config: Path | None, compare: list[str] | None):
    """The suite's configuration with ``--config``'s localizer settings, and one per ``--compare``."""
    from dataclasses import replace

    from simbed.trials.suites import suite_settings

    pace = "-realtime" if base.realtime else ""  # trials at the sensor's pace are another method
    suite_config = replace(
        base,
        settings=base.settings if config is None else suite_settings(config),
        method=(base.method if config is None else config.stem) + pace,
    )
    others = tuple(
        replace(suite_config, settings="", method="default" + pace)
        if c == "default"
        else replace(suite_config, settings=suite_settings(Path(c)), method=Path(c).stem + pace)
        for c in compare or ()
    )
    return suite_config, others


def _in_suite_folder(out: Path, general: bool, report_only: bool, overwrite: bool, run) -> list[dict]:
    """``run()`` in the suite folder ``out`` under rangemcl.common.outdir's policy: a folder of an earlier
    run is continued (or started over with ``overwrite``), a new one removed again if the run fails before
    it has anything worth keeping."""
    from rangemcl.common.outdir import check_output, output_folder
    from rangemcl.errors import InputError

    if general:
        from simbed.trials.generalization import MARKERS as markers
    else:
        markers = ("results.csv", "drives", "trials")
    if report_only and overwrite:
        raise InputError("--report-only reads the suite folder, --overwrite replaces it: give one of them")
    if report_only:
        return run()
    if not overwrite and any((Path(out) / m).exists() for m in markers):
        check_output(out, overwrite=True, kind="suite results", markers=markers)  # writable, ours
        typer.echo(f"continuing the suite folder {out} (--overwrite starts it over)")
        return run()
    if general:  # a run that recorded its towns is kept, to continue
        keep = lambda p: (p / markers[0]).is_file()  # noqa: E731
    else:
        keep = lambda p: (p / "results.csv").is_file() or any((p / "drives").glob("*/meta.yaml"))  # noqa: E731
    with output_folder(out, overwrite=overwrite, kind="suite results", markers=markers, keep_if=keep):
        return run()


@app.command()
def render(
    out: Path = typer.Option(..., help="PNG file to write."),
    scene: str = typer.Option("town_small", help="Scene name in scenes/ or an MJCF file."),
    actors: int = typer.Option(0, help="Moving actors to show."),
    variant: int = typer.Option(0, help="Parked-car variant to show."),
    seed: int = typer.Option(0, help="Seed of the actors' paths."),
    camera: str = typer.Option(None, help="A camera of the model (default: behind the car)."),
    scan: Path = typer.Option(None, help="Instead: a sequence folder whose frame to draw as a range image."),
    frame: int = typer.Option(0, help="With --scan: the frame."),
    overwrite: bool = typer.Option(False, help="Replace the PNG file that exists."),
) -> None:
    """Write a PNG of the scene with the car and actors, or (--scan) of a recorded scan's range image."""
    import numpy as np

    from rangemcl.common.outdir import check_output_files, output_files
    from rangemcl.errors import InputError

    for option, value in (("--actors", actors), ("--variant", variant), ("--seed", seed)):
        if value < 0:
            raise InputError(f"{option} must be >= 0, got {value}")
    check_output_files([out], overwrite=overwrite, what="the picture")
    if scan is not None:
        from rangemcl.datasets.kitti import load_sequence
        from rangemcl.rangeimage import RangeImageGeometry
        from rangemcl.sensors import spec_from_dict
        from rangemcl.viz.plots import save_range_image_png

        seq = load_sequence(scan)
        if not 0 <= frame < len(seq):
            raise InputError(f"{scan}: frame {frame} out of range (the sequence has {len(seq)})")
        points = seq.scan(frame)
        sensor = seq.meta.get("sensor")
        if sensor:
            spec = spec_from_dict(sensor, where=f"{scan}/meta.yaml")
            geometry = RangeImageGeometry.for_spec(spec)
            pm = seq.point_meta(frame)
            rows = spec.row_of_beam[pm["ring"]] if "ring" in pm else None
            image = geometry.project(points, rows=rows, cols=pm.get("column"))
            top = spec.max_range_m
        else:  # a foreign sequence: paper Eq. 1 with KITTI's HDL-64 field of view
            image = RangeImageGeometry.for_fov(64, 900, 3.0, -25.0).project(points)
            top = None
        with output_files([out], overwrite=overwrite, what="the picture"):
            save_range_image_png(out, image.ranges, top)
        typer.echo(f"wrote {out}: frame {frame} of {scan}, {int(np.count_nonzero(image.ranges))} returns")
        return
    from simbed.sim.render import render_png
    from simbed.sim.world import World

    world = World(scene, variant=variant, n_actors=actors, rng=np.random.default_rng(seed))
    if world.car is not None and world.town is not None:
        x, y, yaw = world.town.spawn
        world.car.place(world.model, world.data, x, y, float(world.ground_height(x, y)) + 0.02, yaw)
    world.step(int(0.5 / world.model.opt.timestep))  # let it settle, actors move off
    with output_files([out], overwrite=overwrite, what="the picture"):
        render_png(world, out, camera=camera)
    typer.echo(f"wrote {out}")


def main() -> None:
    run_app(app, "simbed")


if __name__ == "__main__":
    main()
