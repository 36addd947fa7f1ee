"""The ``rangemcl`` console script. Heavy imports live inside the commands so ``--help`` stays fast."""

from __future__ import annotations

from pathlib import Path

import typer

from rangemcl import __version__
from rangemcl.common.cliutil import run_app, version_option
from rangemcl.maps.coarse import COARSE_RATIO  # light: Open3D is imported where a tile is decimated

app = typer.Typer(
    name="rangemcl",
    help="Range-image Monte Carlo LiDAR localization in triangle-mesh maps.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)


@app.callback()
def _root(version: bool = version_option(__version__)) -> None:
    """Range-image Monte Carlo LiDAR localization in triangle-mesh maps."""


def _at_least(option: str, value: int | None, least: int) -> None:
    """An integer option below ``least`` is an InputError naming it (None: not given)."""
    from rangemcl.errors import InputError

    if value is not None and value < least:
        raise InputError(f"{option} must be >= {least}, got {value}")


def _positive(option: str, value: float) -> None:
    """A number option that must be finite and > 0."""
    import math

    from rangemcl.errors import InputError

    if not (math.isfinite(value) and value > 0):
        raise InputError(f"{option} must be a number > 0, got {value}")


def _output_file(option: str, path: Path | None) -> None:
    """A file to write at the end of a command: refused now if it cannot be written (its folder missing,
    or the path a folder), not after the work."""
    from rangemcl.errors import InputError

    if path is None:
        return
    if path.is_dir():
        raise InputError(f"{option} {path}: is a folder (give a file name)")
    if not path.parent.is_dir():
        raise InputError(f"{option} {path}: no such folder {path.parent}")


def _output_dir(option: str, path: Path) -> None:
    """A folder a command writes files into (creating it and its parents): refused now if a file is in
    the way."""
    from rangemcl.errors import InputError

    probe = path
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        what = "exists and is not a folder" if probe == path else f"cannot be made ({probe} is not a folder)"
        raise InputError(f"{path}: {what} (choose another {option})")


def _bag_options(
    lidar_topic: str | None = None,
    imu_topic: str | None = None,
    odom_topic: str | None = None,
    sensor_to_base: str | None = None,
    poses: Path | None = None,
    point_time_field: str | None = None,
    scan_stamp: str | None = None,
    truth_topic: str | None = None,
):
    """The bag-reading options of a command, or None when none is given."""
    from rangemcl.datasets.rosbag import BagOptions
    from rangemcl.errors import InputError

    mount = None
    if sensor_to_base is not None:
        try:
            mount = tuple(float(v) for v in sensor_to_base.replace(",", " ").split())
        except ValueError:
            mount = ()
        if len(mount) != 6:
            raise InputError(f"--sensor-to-base {sensor_to_base!r}: expected 'x,y,z,roll,pitch,yaw' (m, deg)")
    if scan_stamp not in (None, "start", "end"):
        raise InputError(f"--scan-stamp {scan_stamp!r}: expected start or end")
    if poses is not None and not poses.is_file():
        raise InputError(f"{poses}: no such poses file")
    opt = BagOptions(
        lidar_topic=lidar_topic,
        imu_topic=imu_topic,
        odom_topic=odom_topic,
        truth_topic=truth_topic,
        sensor_to_base=mount,
        poses_file=None if poses is None else str(poses),
        point_time_field=point_time_field,
        scan_stamp=scan_stamp,
    )
    given = any(v is not None for v in vars(opt).values())
    return opt if given else None


_PRIOR_STEP_MB = 500.0  # the map held while build-map and import-mesh render the prior (tile by tile)
_PRIOR = typer.Option(
    True, help="Render the place prior of global localization into the map (--no-prior: on first use)."
)
_LIDAR_TOPIC = typer.Option(None, help="Bags: the PointCloud2 topic (default: the only one, or /points).")
_IMU_TOPIC = typer.Option(None, help="Bags: the sensor_msgs/Imu topic (default: /imu if present).")
_ODOM_TOPIC = typer.Option(None, help="Bags: the nav_msgs/Odometry topic (default: /odom if present).")
_TRUTH_TOPIC = typer.Option(
    None, help="Bags: the nav_msgs/Odometry topic of ground-truth poses (default: /ground_truth if present)."
)
_SENSOR_TO_BASE = typer.Option(
    None, help="Bags: the LiDAR's mounting 'x,y,z,roll,pitch,yaw' (m, deg) when TF does not give it."
)
_POINT_TIME_FIELD = typer.Option(
    None, help="Bags: the per-point time field (default: t, time, timestamp, time_stamp or offset_time)."
)
_SCAN_STAMP = typer.Option(
    None, help="Bags: a scan's stamp marks its sweep's start or end (default: detected)."
)


@app.command()
def sensors(
    name: str = typer.Argument(None, help="A preset name or a sensor YAML file; omit to list the presets."),
) -> None:
    """List the LiDAR presets as a table, or print one sensor spec in full (as YAML)."""
    import sys

    import yaml
    from rich.console import Console
    from rich.table import Table

    from rangemcl.sensors import load_spec, preset_names

    console = Console(width=None if sys.stdout.isatty() else 160)  # pipes and logs get whole lines
    if name:
        spec = load_spec(name)
        console.print(f"# {spec.description}", markup=False)
        console.print(yaml.safe_dump(spec.to_dict(), sort_keys=False, width=100), markup=False)
        return
    table = Table(title="LiDAR presets (rangemcl sensors NAME for the full spec)")
    for col, justify in [
        ("name", "left"),
        ("beams", "right"),
        ("vertical FOV (deg)", "right"),
        ("columns", "right"),
        ("Hz", "right"),
        ("range (m)", "right"),
        ("noise (m)", "right"),
        ("description", "left"),
    ]:
        table.add_column(col, justify=justify, no_wrap=col != "description")
    for preset in preset_names():
        s = load_spec(preset)
        table.add_row(
            s.name,
            str(s.beams),
            f"{s.fov_down_deg:+.2f} .. {s.fov_up_deg:+.2f}",
            str(s.columns),
            f"{s.rotation_hz:g}",
            f"{s.min_range_m:g} .. {s.max_range_m:g}",
            f"{s.range_noise_m:g}",
            s.description,
        )
    console.print(table)


@app.command()
def sweep(
    sensor: str = typer.Option("os1-64", help="Preset name or sensor YAML file."),
    out: Path = typer.Option(Path("out/sweep"), help="Folder for the range image PNG and the scan .bin."),
    seed: int = typer.Option(0, help="Seed of the town layout and of the range noise."),
    device: str = typer.Option("cpu", help="Warp device: cpu or cuda."),
    threads: int = typer.Option(0, help="CPU threads (0 = all cores)."),
    overwrite: bool = typer.Option(False, help="Replace this sensor's range image and scan in OUT."),
) -> None:
    """Cast one LiDAR sweep in a synthetic town through the Warp core and write what it saw (OUT keeps
    one range image and one scan per sensor)."""
    import time

    import numpy as np

    from rangemcl import meshgen
    from rangemcl.datasets.scanio import write_scan_bin
    from rangemcl.rangeimage import RangeImageGeometry
    from rangemcl.raycast import RayCaster, resolve_device
    from rangemcl.sensors import load_spec
    from rangemcl.viz.plots import save_range_image_png

    _at_least("--seed", seed, 0)
    _at_least("--threads", threads, 0)
    from rangemcl.common.outdir import check_output_files, output_files

    _output_dir("--out", out)
    spec = load_spec(sensor)
    files = [out / f"range_{spec.name}.png", out / f"scan_{spec.name}.bin"]
    check_output_files(files, overwrite=overwrite, what=f"the {spec.name} sweep")
    resolve_device(device)
    rng = np.random.default_rng(seed)
    town = meshgen.town(seed=seed)
    vertices, faces = town.merged()
    caster = RayCaster(device=device, threads=threads or None)
    caster.add_mesh(vertices, faces, name="town")
    geometry = RangeImageGeometry.for_spec(spec)

    x, y = float(town.road_xy[1]), float(town.road_xy[1]) + 12.0  # on a road, near a junction
    T_world_base = np.eye(4)
    T_world_base[:3, 3] = (x, y, float(meshgen.town_ground_height(x, y)))
    T_world_sensor = T_world_base @ spec.T_base_sensor

    t0 = time.perf_counter()
    ranges = caster.render(geometry, T_world_sensor, spec.max_range_m)
    first_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    caster.render(geometry, T_world_sensor, spec.max_range_m)  # again, warm
    seconds = time.perf_counter() - t0
    valid = ranges >= spec.min_range_m
    noisy = ranges + rng.normal(0.0, spec.range_noise_m, ranges.shape).astype(np.float32)
    noisy = np.where(valid, noisy, 0.0).astype(np.float32)
    points = geometry.back_project(noisy)[valid]  # (N, 3) sensor frame

    with output_files(files, overwrite=overwrite, what=f"the {spec.name} sweep"):
        png = save_range_image_png(files[0], noisy, spec.max_range_m)
        scan = write_scan_bin(files[1], points)
    n_rays = ranges.size
    typer.echo(
        f"{spec.name}: {spec.beams} x {spec.columns} rays in a town of {len(faces):,} triangles "
        f"({len(town.parts)} parts) on {device} with {caster.threads} thread(s)"
    )
    typer.echo(
        f"  {valid.sum():,} returns ({valid.mean():.1%}), median range {np.median(ranges[valid]):.1f} m, "
        f"cast in {seconds * 1e3:.0f} ms warm ({n_rays / seconds / 1e6:.2f} M rays/s; "
        f"first call {first_s * 1e3:.0f} ms)"
    )
    typer.echo(f"  wrote {png} and {scan}")


@app.command("build-map")
def build_map(
    seq_dir: Path = typer.Argument(
        ...,
        help="A sequence folder (KITTI layout) with poses, a bag (.bag, .mcap, ROS 2 folder) or a "
        "folder of .pcd/.ply scans.",
    ),
    out: Path = typer.Option(..., help="Map folder to write."),
    config: Path = typer.Option(None, help="YAML settings (defaults: see the map's config.yaml)."),
    workers: int = typer.Option(None, help="Tile jobs in parallel (default: the config's, 0 = all cores)."),
    overwrite: bool = typer.Option(
        False, help="Replace the map that OUT holds (it is kept until this one is built)."
    ),
    resume: bool = typer.Option(
        False, help="Finish the interrupted build in OUT (same sequence and settings): only missing tiles."
    ),
    backend: str = typer.Option(
        "process", help="Where the tile jobs run: process (a local pool) or ray (Ray tasks, one per tile)."
    ),
    address: str = typer.Option(
        None,
        help="Backend ray: the cluster's address ('auto': the one this machine is in; default: a "
        "local instance of --workers CPUs).",
    ),
    poses: Path = typer.Option(
        None, help="Bags: the LiDAR's poses, TUM (by time) or KITTI (a line per scan), if not in the bag."
    ),
    lidar_topic: str = _LIDAR_TOPIC,
    truth_topic: str = _TRUTH_TOPIC,
    sensor_to_base: str = _SENSOR_TO_BASE,
    point_time_field: str = _POINT_TIME_FIELD,
    scan_stamp: str = _SCAN_STAMP,
    prior: bool = _PRIOR,
) -> None:
    """Build a tiled mesh map: range-image normals, ground labels, Poisson per tile, ground simplification,
    then the place prior of global localization."""
    import sys

    from rangemcl.common.outdir import MAP_MARKERS, output_folder
    from rangemcl.config import load_config
    from rangemcl.errors import InputError
    from rangemcl.mapping.pipeline import BACKENDS, WORK_DIR, MapSettings
    from rangemcl.mapping.pipeline import build_map as run

    settings = load_config(MapSettings, config)
    bag = _bag_options(
        lidar_topic,
        sensor_to_base=sensor_to_base,
        poses=poses,
        point_time_field=point_time_field,
        scan_stamp=scan_stamp,
        truth_topic=truth_topic,
    )
    if workers is not None:
        settings.workers = workers
    if resume and overwrite:
        raise InputError("--resume and --overwrite exclude each other")
    if backend not in BACKENDS:
        raise InputError(f"--backend {backend!r}: expected one of {', '.join(BACKENDS)}")
    if address is not None and backend != "ray":
        raise InputError("--address needs --backend ray")
    where = {"backend": backend, "address": address}
    interrupted = (out / WORK_DIR).is_dir()  # a finished build removes its work area
    progress = sys.stderr.isatty()
    try:
        if resume:
            if not interrupted:
                raise InputError(f"{out}: nothing to resume (no interrupted build in it)")
            r = run(seq_dir, out, settings, progress=progress, resume=True, bag_options=bag, **where)
        else:
            if interrupted and not overwrite:
                raise InputError(
                    f"{out}: holds an interrupted build "
                    "(give --resume to finish it, or --overwrite to start over)"
                )
            with output_folder(
                out,
                overwrite=overwrite,
                kind="map",
                markers=(*MAP_MARKERS, WORK_DIR),
                keep_if=lambda p: (p / WORK_DIR / "state.json").is_file(),
            ):
                r = run(seq_dir, out, settings, progress=progress, bag_options=bag, **where)
    except KeyboardInterrupt:
        if (out / WORK_DIR / "state.json").is_file():
            typer.echo(
                f"interrupted: the finished work is kept in {out / WORK_DIR}; "
                f"`rangemcl build-map {seq_dir} --out {out} --resume` finishes the map",
                err=True,
            )
        else:
            typer.echo("interrupted before any stage finished: nothing kept", err=True)
        raise typer.Exit(130) from None
    typer.echo(
        f"wrote {out}: {r.triangles:,} triangles in {r.tiles} tiles from {r.scans_used}/{r.scans_total} "
        f"scans ({r.points_used:,} points; ground simplification {r.triangles_before_simplify:,} -> "
        f"{r.triangles:,} triangles) in {r.seconds.get('total', 0):.1f} s; peak memory "
        f"{r.peak_rss_main_mb:.0f} MB (this process), {r.peak_rss_tile_jobs_mb:.0f} MB (largest tile job)"
        + (f"; {r.tiles_resumed} tiles taken from the interrupted build" if r.tiles_resumed else "")
    )
    if r.scans_skipped_empty or r.points_nonfinite:
        typer.echo(
            f"  skipped {r.scans_skipped_empty} scans with no valid point, "
            f"{r.points_nonfinite} NaN/inf points"
        )
    if prior:
        _place_prior_step(out, map_memory=_PRIOR_STEP_MB)


@app.command()
def convert(
    source: Path = typer.Argument(
        ..., help="A KITTI-layout folder, a bag (.bag, .mcap, ROS 2 folder) or a folder of .pcd/.ply scans."
    ),
    out: Path = typer.Option(..., help="The folder (kitti, mcap, rosbag2) or .bag file (rosbag1) to write."),
    fmt: str = typer.Option("mcap", "--format", help="kitti, mcap, rosbag2 or rosbag1."),
    overwrite: bool = typer.Option(False, help="Replace the sequence or bag at OUT."),
    poses: Path = typer.Option(None, help="The LiDAR's poses (TUM or KITTI) when the source has none."),
    lidar_topic: str = _LIDAR_TOPIC,
    imu_topic: str = _IMU_TOPIC,
    odom_topic: str = _ODOM_TOPIC,
    truth_topic: str = _TRUTH_TOPIC,
    sensor_to_base: str = _SENSOR_TO_BASE,
    point_time_field: str = _POINT_TIME_FIELD,
    scan_stamp: str = _SCAN_STAMP,
) -> None:
    """Write a recording as a KITTI folder or a bag: scans with their per-point fields, times, poses,
    odometry, IMU roll and pitch, and its meta (a simbed drive opens in Foxglove or RViz this way)."""
    import sys

    from rangemcl.datasets.convert import convert as run

    bag = _bag_options(
        lidar_topic, imu_topic, odom_topic, sensor_to_base, poses, point_time_field, scan_stamp, truth_topic
    )
    try:
        n = run(source, out, fmt, bag_options=bag, overwrite=overwrite, progress=sys.stderr.isatty())
    except KeyboardInterrupt:
        typer.echo(f"interrupted: {out} holds the frames written so far (marked complete: false)", err=True)
        raise typer.Exit(130) from None
    typer.echo(f"wrote {out}: {n} frames ({fmt})")


@app.command("import-mesh")
def import_mesh_cmd(
    mesh: Path = typer.Argument(..., help="A triangle mesh file (PLY, OBJ)."),
    out: Path = typer.Option(..., help="Map folder to write."),
    tile_size: float = typer.Option(100.0, help="Tile side, metres."),
    coarse_ratio: float = typer.Option(
        COARSE_RATIO, help="The coarse level keeps this share of each tile's triangles (0: no coarse level)."
    ),
    overwrite: bool = typer.Option(False, help="Replace the map that OUT holds."),
    stream: bool = typer.Option(
        True, help="Read a binary triangle PLY in place, a block at a time (--no-stream: load it whole)."
    ),
    drive: Path = typer.Option(
        None,
        help="Where the car drives ('x y' per line, or KITTI or TUM poses; e.g. simbed export-mesh "
        "--route-out): global localization searches near it. Default: all of the mesh's ground.",
    ),
    prior: bool = _PRIOR,
) -> None:
    """Turn any triangle mesh (e.g. a published range-mcl map) into a map folder (tiles, their coarse
    level, the place prior)."""
    import math

    from rangemcl.common.outdir import MAP_MARKERS, check_output, output_folder
    from rangemcl.errors import InputError
    from rangemcl.mapping.stream_import import import_mesh_streaming, ply_layout
    from rangemcl.maps.meshmap import import_mesh

    if not (math.isfinite(coarse_ratio) and 0.0 <= coarse_ratio <= 1.0):
        raise InputError(f"--coarse-ratio must lie in [0, 1], got {coarse_ratio}")
    check_output(out, overwrite=overwrite, kind="map", markers=MAP_MARKERS)  # before reading the mesh
    meta = {"source_mesh": str(mesh.resolve())}
    drive_xy = None
    if drive is not None:
        from rangemcl.maps.meshmap import read_drive_xy

        drive_xy = read_drive_xy(drive)
        meta["source_drive"] = str(drive.resolve())
    if stream and mesh.is_file() and ply_layout(mesh) is not None:
        # a binary triangle PLY: read in place, a block at a time (a mesh larger than memory imports too)
        if not (math.isfinite(tile_size) and tile_size > 0):
            raise InputError(f"{mesh}: tile_size_m must be a positive number, got {tile_size!r}")
        work = out.absolute().parent / f".{out.name}.import"
        with output_folder(out, overwrite=overwrite, kind="map", markers=MAP_MARKERS):
            counts = import_mesh_streaming(
                mesh,
                out,
                work_dir=work,
                tile_size_m=tile_size,
                coarse_ratio=coarse_ratio,
                meta=meta,
                drive_xy=drive_xy,
            )
        typer.echo(f"wrote {out}: {counts['triangles']:,} triangles in {counts['tiles']} tiles")
    else:
        m = import_mesh(mesh, tile_size_m=tile_size, meta=meta)
        m.drive_xy = drive_xy
        with output_folder(out, overwrite=overwrite, kind="map", markers=MAP_MARKERS):
            m.save(out, coarse_ratio=coarse_ratio)
        typer.echo(f"wrote {out}: {m.n_triangles:,} triangles in {len(m.tiles)} tiles")
        del m
    if prior:
        _place_prior_step(out, map_memory=_PRIOR_STEP_MB)


def _place_prior_step(
    map_dir: Path,
    config: Path | None = None,
    map_memory: float | None = None,
    threads: int | None = None,
    *,
    required: bool = False,
) -> None:
    """Render (or find) the map's place prior for the localizer's settings and say so in one line. As the
    last step of a build or import (``required`` False), a map without the prior's inputs (no measured
    ground) is kept and the line says why there is no prior."""
    import time

    from rangemcl.config import load_config
    from rangemcl.errors import InputError
    from rangemcl.localization import LocalizerSettings, map_place_prior

    settings = load_config(LocalizerSettings, config)
    t0 = time.perf_counter()
    try:
        prior, how = map_place_prior(map_dir, settings, map_memory_mb=map_memory, threads=threads)
    except InputError as err:
        if required:
            raise
        typer.echo(f"{map_dir}: no place prior ({err}); global localization needs one", err=True)
        return
    typer.echo(
        f"{map_dir}: place prior {how}: {len(prior.xy):,} cells of {prior.params.cell_m:g} m, "
        f"{prior.nbytes / 1e6:.1f} MB, {time.perf_counter() - t0:.1f} s"
    )


@app.command("place-prior")
def place_prior_cmd(
    map_dir: Path = typer.Argument(..., help="A map folder."),
    config: Path = typer.Option(None, help="YAML localizer settings (the prior's grid, the drivable area)."),
    map_memory: float = typer.Option(
        None, metavar="MB", help="Hold only the tiles near the cells being rendered, within this many MB."
    ),
    threads: int = typer.Option(None, help="CPU threads for ray casting (default: all cores)."),
) -> None:
    """Render the map's place prior (global localization's descriptors of the drivable area) and store it in
    the map folder. build-map and import-mesh do this as their last step; run it again after changing the
    localizer's prior settings, or for a map built with --no-prior."""
    _place_prior_step(map_dir, config, map_memory, threads, required=True)


@app.command("settings")
def settings_cmd(
    config: Path = typer.Option(None, help="A localizer settings YAML: print its effective settings."),
) -> None:
    """Print the localizer's settings as YAML: the defaults, or a config's effective settings (what
    `rangemcl localize --config` runs with; every run also writes them to its results' config.yaml). The
    keys, their units and effects: the documentation's settings reference."""
    import yaml

    from rangemcl.config import load_config, to_dict
    from rangemcl.localization import LocalizerSettings

    settings = load_config(LocalizerSettings, config)
    settings.check(str(config) if config is not None else "settings")
    typer.echo(yaml.safe_dump(to_dict(settings), sort_keys=False), nl=False)


@app.command("map-info")
def map_info(map_dir: Path = typer.Argument(..., help="A map folder.")) -> None:
    """Print a map's size, triangles, tiles, extent, coarse level and place prior; every tile is read and
    checked, one at a time (a map of format 2 is never held whole)."""
    from rangemcl.localization.place_prior import describe_prior_file
    from rangemcl.mapping.info import map_info as summarize

    summary = summarize(map_dir, describe_prior=describe_prior_file)
    width = max(len(k) for k in summary)
    for key, value in summary.items():
        typer.echo(f"{key:<{width}}  {value}")


@app.command("map-upgrade")
def map_upgrade(map_dir: Path = typer.Argument(..., help="A map folder.")) -> None:
    """Rewrite a map folder of the older format 1 (one mesh file: mesh.ply + tiles.npz) as format 2 (a mesh
    file per tile, its coarse level and an index), in place. The tiles and the index are written first and
    map.yaml last: a run stopped part-way leaves the format-1 map as it was, and running it again
    finishes."""
    from rangemcl.maps.meshmap import MeshMap
    from rangemcl.maps.store import TileStore

    m = MeshMap.load(map_dir)
    if m.format_version >= 2:
        for name in ("mesh.ply", "tiles.npz"):  # left by a run stopped after map.yaml
            (map_dir / name).unlink(missing_ok=True)
        typer.echo(f"{map_dir}: already format {m.format_version}")
        return
    m.save(map_dir, coarse_ratio=COARSE_RATIO)
    store = TileStore.open(map_dir)
    typer.echo(
        f"{map_dir}: format 2, {store.n_triangles:,} triangles in {len(store.entries)} tile files, "
        f"{store.bytes_on_disk / 1e6:.1f} MB"
    )


@app.command("map-coarse")
def map_coarse(
    map_dir: Path = typer.Argument(..., help="A map folder (format 2)."),
    ratio: float = typer.Option(COARSE_RATIO, help="Share of each tile's triangles the coarse level keeps."),
) -> None:
    """Add a coarse level to a map: each tile decimated to RATIO of its triangles (coarse/I_J.npz). A
    localizer within a memory budget (--map-memory) holds the farther tiles at this level where the tiles
    in range do not all fit at full resolution. The index is rewritten last: a run stopped part-way leaves
    the map as it was."""
    from rangemcl.errors import InputError
    from rangemcl.maps.coarse import add_coarse_level
    from rangemcl.maps.meshmap import read_map_yaml

    version, _doc = read_map_yaml(map_dir)
    if version < 2:
        raise InputError(
            f"{map_dir}: a map of format {version} has no tiles; first: rangemcl map-upgrade {map_dir}"
        )
    r = add_coarse_level(map_dir, ratio)
    typer.echo(
        f"{map_dir}: coarse level of {r['tiles']} tiles, {r['coarse_triangles']:,} of {r['triangles']:,} "
        f"triangles ({100 * r['coarse_share']:.1f} %), {r['coarse_bytes_on_disk'] / 1e6:.1f} MB, "
        f"{r['seconds']:.1f} s"
    )


@app.command("map-quality")
def map_quality_cmd(
    map_dir: Path = typer.Argument(..., help="A map folder."),
    truth: Path = typer.Option(..., help="The true surface as a mesh file (e.g. from simbed export-mesh)."),
    reference: Path = typer.Option(
        None,
        help="A sequence whose scans give the visible true surface for completeness (default: the truth).",
    ),
    tolerance: float = typer.Option(0.2, help="Completeness tolerance, metres."),
    json_out: Path = typer.Option(None, "--json", help="Also write the figures here."),
) -> None:
    """Measure a map against a true surface: accuracy (distances) and completeness."""
    import json

    import numpy as np

    from rangemcl.mapping.quality import map_quality
    from rangemcl.maps.meshmap import MeshMap, import_mesh

    _positive("--tolerance", tolerance)
    _output_file("--json", json_out)
    m = MeshMap.load(map_dir)
    t = import_mesh(truth)
    ref = None
    if reference is not None:
        from rangemcl.datasets.kitti import load_sequence

        seq = load_sequence(reference, require_poses=True)
        every = max(1, len(seq) // 50)  # about 50 scans spread over the drive
        poses = seq.poses
        clouds = [seq.scan(i) @ poses[i][:3, :3].T + poses[i][:3, 3] for i in range(0, len(seq), every)]
        ref = np.concatenate(clouds)
        if len(ref) > 1_000_000:
            ref = ref[np.random.default_rng(0).choice(len(ref), 1_000_000, replace=False)]
    q = map_quality(m.vertices, m.faces, t.vertices, t.faces, reference_points=ref, tolerance_m=tolerance)
    for key, value in q.items():
        typer.echo(f"{key:<32}  {value:.4f}" if isinstance(value, float) else f"{key:<32}  {value}")
    if json_out:
        json_out.write_text(json.dumps(q, indent=2))


@app.command()
def localize(
    seq_dir: Path = typer.Argument(
        ..., help="A sequence folder (KITTI layout), a bag (.bag, .mcap, ROS 2 folder) or .pcd/.ply scans."
    ),
    map_dir: Path = typer.Option(..., "--map", help="A map folder (rangemcl build-map or import-mesh)."),
    out: Path = typer.Option(..., help="Results folder to write."),
    particles: int = typer.Option(None, help="Particles (global: the spread, default 10000; tracking: 100)."),
    mode: str = typer.Option(
        "global", help="global (no prior) or tracking (from --init-pose or the first true pose)."
    ),
    device: str = typer.Option("cpu", help="Warp device: cpu or cuda."),
    seed: int = typer.Option(0, help="Seed of everything random in the run."),
    config: Path = typer.Option(
        None, help="YAML localizer settings (defaults: see the results' config.yaml)."
    ),
    first_frame: int = typer.Option(0, help="Start at this frame."),
    frames: int = typer.Option(None, help="Localize at most this many frames."),
    init_pose: str = typer.Option(None, help="Tracking start 'x,y,yaw' (metres, radians)."),
    odometry_from_poses: bool = typer.Option(
        False, help="Without odometry.txt, derive the odometry from poses.txt (it is then noise-free)."
    ),
    odometry: str = typer.Option(
        None,
        help="kiss-icp (LiDAR odometry from the scans; the [kiss] extra) or poses:FILE (the LiDAR's poses, "
        "TUM or KITTI) instead of the sequence's own odometry.",
    ),
    poses: Path = typer.Option(None, help="Bags: ground-truth LiDAR poses (TUM or KITTI) for the metrics."),
    viz: bool = typer.Option(
        False,
        help="Stream the run to the rerun viewer: map, scan, particles, estimate, truth (the [viz] extra).",
    ),
    viz_out: Path = typer.Option(
        None, help="Save the run as a rerun .rrd file (headless; `rerun FILE` shows it)."
    ),
    lidar_topic: str = _LIDAR_TOPIC,
    imu_topic: str = _IMU_TOPIC,
    odom_topic: str = _ODOM_TOPIC,
    truth_topic: str = _TRUTH_TOPIC,
    sensor_to_base: str = _SENSOR_TO_BASE,
    point_time_field: str = _POINT_TIME_FIELD,
    scan_stamp: str = _SCAN_STAMP,
    plots: bool = typer.Option(True, help="Write trajectory, error and particle plots."),
    threads: int = typer.Option(None, help="CPU threads for ray casting (default: all cores)."),
    map_memory: float = typer.Option(
        None,
        metavar="MB",
        help="Hold only the map's tiles near the particles, within this many MB (a map of format 2; "
        "default: the config's map_memory_mb, else the whole map when it takes under a quarter of the "
        "memory available, else that quarter).",
    ),
    overwrite: bool = typer.Option(
        False, help="Replace the results that OUT holds (they are kept until this run has results)."
    ),
    resume: bool = typer.Option(
        False,
        help="Continue the interrupted run in OUT from its last checkpoint (same command and options; "
        "the results equal an uninterrupted run's).",
    ),
    realtime: bool = typer.Option(
        False,
        help="Replay at the sensor's pace: a scan that arrives (by its stamp) while the localizer still "
        "works on an earlier one is dropped, its odometry carried on, as on a car (frames.csv: late). "
        "The results then depend on this machine's speed.",
    ),
) -> None:
    """Localize a sequence in a mesh map (Monte Carlo localization, range-image observation model)."""
    import math
    import sys

    from rangemcl.config import load_config
    from rangemcl.errors import InputError
    from rangemcl.localization import LocalizerSettings
    from rangemcl.localization.pipeline import RunOptions, localize_sequence

    _at_least("--seed", seed, 0)
    settings = load_config(LocalizerSettings, config)
    start = None
    if init_pose is not None:
        try:
            start = tuple(float(t) for t in init_pose.split(","))
        except ValueError:
            start = ()
        if len(start) != 3:
            raise InputError(f"--init-pose {init_pose!r}: expected three numbers 'x,y,yaw'")
        if not all(math.isfinite(t) for t in start):
            raise InputError(f"--init-pose {init_pose!r}: expected three finite numbers 'x,y,yaw'")
    opts = RunOptions(
        mode=mode,
        particles=particles,
        device=device,
        seed=seed,
        threads=threads,
        first_frame=first_frame,
        frames=frames,
        init_pose=start,
        odometry_from_poses=odometry_from_poses,
        odometry=odometry,
        viz=viz,
        viz_out=None if viz_out is None else str(viz_out),
        bag=_bag_options(
            lidar_topic,
            imu_topic,
            odom_topic,
            sensor_to_base,
            poses,
            point_time_field,
            scan_stamp,
            truth_topic,
        ),
        plots=plots,
        progress=sys.stderr.isatty(),
        resume=resume,
        map_memory_mb=map_memory,
        realtime=realtime,
    )
    from rangemcl.common.outdir import RESULT_MARKERS, has_frames, output_folder

    if resume and overwrite:
        raise InputError("--resume continues the run in OUT, --overwrite replaces it: give one of them")
    if resume and not has_frames(out):
        raise InputError(f"{out}: holds no interrupted localization to resume (frames.csv missing or empty)")
    if not resume and not overwrite and (Path(out) / ".resume").is_dir():
        raise InputError(
            f"{out}: holds an interrupted localization (give --resume to continue it, or --overwrite to "
            "replace it)"
        )
    try:
        if resume:  # the folder is the interrupted run's: nothing is set aside or removed
            s = localize_sequence(seq_dir, map_dir, out, settings, opts)
        else:
            with output_folder(
                out,
                overwrite=overwrite,
                kind="localization results",
                markers=RESULT_MARKERS,
                keep_if=has_frames,
            ):
                s = localize_sequence(seq_dir, map_dir, out, settings, opts)
    except KeyboardInterrupt:
        typer.echo(f"interrupted: the frames localized so far are in {out}", err=True)
        raise typer.Exit(130) from None
    conv = s["converged_frame"]
    scanned = s.get("frames_localized_from_scans")
    typer.echo(
        f"wrote {out}: {s['frames']} frames"
        + (f" ({scanned} localized from scans), " if scanned is not None else ", ")
        + (f"converged at frame {conv}" if conv is not None else "never converged")
        + f", {s['recoveries']} recoveries, {s['skipped_scans']} scans without a valid point and "
        f"{s['unreadable_scans']} unreadable scans skipped, "
        + (f"{s['nan_points_dropped']} NaN points dropped, " if s.get("nan_points_dropped") else "")
        + (f"{s['late_scans']} scans dropped while busy (--realtime), " if realtime else "")
        + f"{s['seconds_total']:.1f} s"
    )
    if s["odometry_source"] != "odometry.txt":
        typer.echo(f"  odometry from {s['odometry_source']}")
    if s.get("calib_source", "calib.txt").startswith("identity (no calib.txt"):  # said, never assumed
        typer.echo(f"  sensor-to-pose calibration: {s['calib_source']}")
    m = s.get("metrics")
    if m:
        typer.echo(metrics_line(m))


def metrics_line(m: dict) -> str:
    events = ""
    if "wrong_convergences_count" in m:
        events = (
            f"; wrong convergences {m['wrong_convergences_count']} "
            f"(not caught within {m.get('caught_within_frames', 10)} frames: "
            f"{m.get('wrong_convergences_uncaught', 0)}), false alarms {m.get('false_alarms_count', 0)}"
        )
    scans = ""
    if m.get("frames_localized_from_scans") is not None:
        n = m["frames_localized_from_scans"] + m.get("frames_without_scan", 0)
        scans = f", {m['frames_localized_from_scans']} of {n} frames localized from scans"
    reason = m.get("failure_reason")
    if m.get("location_rmse_m") is None:
        why = f": {reason}" if reason and reason != "never converged" else ""
        return f"  metrics: not converged (failure{why})" + scans + events
    verdict = "success" if m["success"] else "FAILURE" + (f" ({reason})" if reason else "")
    return (
        f"  metrics: {verdict}, location RMSE {m['location_rmse_m']:.3f} m, "
        f"yaw RMSE {m['yaw_rmse_deg']:.2f} deg, converged at frame {m['converged_frame']}" + scans + events
    )


@app.command()
def evaluate(
    results: Path = typer.Argument(..., help="A results folder written by rangemcl localize."),
    gt: Path = typer.Option(..., help="Ground-truth poses.txt (the sequence's convention)."),
    check_every: int = typer.Option(100, help="Success is checked at every n-th frame after convergence."),
    success_m: float = typer.Option(5.0, help="Success threshold on the location error, metres."),
) -> None:
    """The paper's metrics: success, location and yaw RMSE after convergence, frames to converge."""
    import json

    from rangemcl.common.atomic import atomic_write
    from rangemcl.evaluation.metrics import evaluate_results

    _at_least("--check-every", check_every, 1)
    _positive("--success-m", success_m)
    m = evaluate_results(results, gt, check_every=check_every, success_m=success_m)
    atomic_write(results / "metrics.json", json.dumps(m, indent=2) + "\n")
    if m.get("partial"):
        typer.echo(f"partial: {results} is an interrupted run ({m['partial_reason']}, {m['frames']} frames)")
    typer.echo(
        json.dumps(
            {
                k: m[k]
                for k in (
                    "success",
                    "location_rmse_m",
                    "yaw_rmse_deg",
                    "converged_frame",
                    "frames",
                    "wrong_convergences_count",
                    "false_alarms_count",
                )
            }
        )
    )
    typer.echo(metrics_line(m))


def main() -> None:
    run_app(app, "rangemcl")


if __name__ == "__main__":
    main()
