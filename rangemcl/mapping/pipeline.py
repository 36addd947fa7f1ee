"""``rangemcl build-map``: a recorded drive (KITTI layout, with poses) to a tiled mesh map.

Reads like the method: per scan, range-image normals and ground labels; all scans into the world frame,
cut into tiles (each with a margin) on disk so memory does not grow with the drive; per tile, Poisson
reconstruction, trimming, cropping to the tile and ground simplification, as independent jobs on all
cores; the tiles streamed into the map folder one at a time (:mod:`rangemcl.mapping.assemble`), with the
effective config and a report.
"""

from __future__ import annotations

import json
import math
import os
import resource
import shutil
import time
from collections import defaultdict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from rangemcl.common.atomic import atomic_write
from rangemcl.common.pool import kill_point, process_pool
from rangemcl.config import to_dict, write_config
from rangemcl.datasets.kitti import Sequence
from rangemcl.datasets.sources import open_source
from rangemcl.errors import InputError
from rangemcl.mapping.assemble import assemble_map
from rangemcl.mapping.ground import label_ground
from rangemcl.mapping.normals import scan_normals
from rangemcl.mapping.poisson import poisson_mesh, transfer_labels
from rangemcl.mapping.simplify import simplify_ground
from rangemcl.maps.coarse import COARSE_RATIO
from rangemcl.maps.meshmap import thin_path
from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.se2 import interpolate_poses
from rangemcl.sensors import spec_from_dict

# ---------------------------------------------------------------------------------------------- settings


MAX_PROJECTION_PIXELS = 1 << 24  # a range image of more pixels would not fit in memory (and no LiDAR has one)


@dataclass
class ScanSettings:
    """Which scans, and which of their points, go into the map, and how each point is placed."""

    min_range_m: float = 1.5
    """Returns closer than this, in m, are dropped (the car's own surroundings, spray)."""
    max_range_m: float = 40.0
    """Returns farther than this, in m, are dropped: sparse far returns mesh badly (the paper's reference
    code crops scans to ±30 m). The localizer's `observation.max_range_m` should match it."""
    every_nth: int = 1
    """Use every n-th scan of the drive (1: all of them)."""
    max_edge_m: float = 1.0
    """Constant part, in m, of the depth-discontinuity limit between neighbouring range-image pixels: a
    neighbour farther off (beyond this plus an allowance that grows with range) lies across an edge and
    gives no normal. A point left without a normal is not meshed."""
    drop_dynamic_labels: bool = False
    """Drop the points labelled as moving actors (a non-zero `label` in the points' metadata, which only
    simulator recordings have)."""
    deskew: bool = True
    """With per-point firing times: place each point from the pose interpolated at its own firing time,
    not the scan's stamp."""


@dataclass
class GroundSettings:
    """Which points of each scan are ground (the paper's rule); the ground part of the mesh is simplified
    later (`simplify`)."""

    max_angle_deg: float = 30.0
    """A point is ground only when its normal lies within this angle, in degrees, of the scan's
    ground-plane normal e3 (|n · e3| > cos of it); below 90."""
    z_margin_m: float = 1.0
    """A ground point's height along e3 in the sensor frame must lie below −(sensor height) + this margin,
    in m."""
    sensor_height_m: float | None = None
    """The sensor's height in m above the ground, for the ground test; it is also stored in the map's
    metadata, where the localizer finds it. `None`: the sequence's sensor mount, else 1.73 (KITTI)."""


@dataclass
class ProjectionSettings:
    """The range-image grid (the paper's Eq. 1 projection) in which the normals of sequences without a
    sensor description of their own (e.g. KITTI) are computed."""

    height: int = 64
    """Rows of the range image, spread evenly over the vertical field of view."""
    width: int = 2048
    """Columns of the range image, spread evenly over 360 degrees of azimuth."""
    fov_up_deg: float = 3.0
    """Upper edge of the vertical field of view, in degrees of elevation (positive up)."""
    fov_down_deg: float = -25.0
    """Lower edge of the vertical field of view, in degrees of elevation; below `fov_up_deg`."""


@dataclass
class PoissonSettings:
    """Each tile's screened Poisson reconstruction, and the trimming of the surface it invents away from
    the data (`rangemcl.mapping.poisson`)."""

    depth: int = 9
    """Octree depth, 1 to 16: the finest cell is about the points' extent / 2^depth (about 0.2 m for a
    100 m tile at depth 9); one more level halves it and costs markedly more time and memory."""
    density_quantile: float = 0.1
    """Share in [0, 1) of the mesh's vertices, those of the lowest Poisson density, that are removed: it
    always removes that share, invented surface or not. 0 keeps all."""
    max_support_m: float = 0.5
    """Triangles with a vertex farther than this, in m, from every input point are removed (surface that
    Poisson invented away from the data)."""
    voxel_m: float = 0.1
    """Each tile's points are thinned to one per voxel of this size, in m, before reconstruction (the
    earliest scan's point wins), so that memory follows the surface, not how often the drive passed."""


@dataclass
class SimplifySettings:
    """Simplification of the ground part of each tile's mesh (vertex clustering and smoothing): flat road
    needs few triangles."""

    enabled: bool = True
    """Simplify the ground triangles; false: keep Poisson's resolution everywhere."""
    voxel_m: float = 1.0
    """Side in m of the cells in which ground vertices are merged (vertex clustering)."""
    smooth_iterations: int = 1
    """Rounds of the ground smoothing (paper Eq. 3) after merging; 0 skips it."""


@dataclass
class TileSettings:
    """How the map is cut into square tiles, each reconstructed as a job of its own."""

    size_m: float = 100.0
    """Edge length in m of the square map tiles; the map is built, stored and (within a memory budget)
    loaded by the localizer tile by tile."""
    margin_m: float = 10.0
    """Points within this distance, in m, beyond a tile's border take part in its reconstruction, which is
    then cropped to the tile, so that neighbouring tiles meet where the surface continues."""
    coarse_ratio: float = COARSE_RATIO
    """Share in [0, 1] of each tile's triangles kept in its coarse level, which a localizer within a memory
    budget holds for the farther tiles; 0: no coarse level."""


@dataclass
class MapSettings:
    """The map builder's settings, the YAML of `rangemcl build-map --config`: one section per stage, and
    the number of parallel tile jobs."""

    scans: ScanSettings = field(default_factory=ScanSettings)
    """Which scans and points go into the map."""
    ground: GroundSettings = field(default_factory=GroundSettings)
    """How ground points are labelled."""
    projection: ProjectionSettings = field(default_factory=ProjectionSettings)
    """The range-image grid of sequences without a sensor description."""
    poisson: PoissonSettings = field(default_factory=PoissonSettings)
    """Each tile's Poisson reconstruction and trimming."""
    simplify: SimplifySettings = field(default_factory=SimplifySettings)
    """Simplification of the ground mesh."""
    tiles: TileSettings = field(default_factory=TileSettings)
    """The tiles' size, margin and coarse level."""
    workers: int = 0
    """Tile jobs run in parallel (processes, or the CPUs of a local Ray instance); 0: all cores."""

    def check(self, where: str = "settings") -> None:
        """Range checks that the types alone do not give, before any work; an InputError names the key."""
        sc, g, pr, po, si, t = (
            self.scans,
            self.ground,
            self.projection,
            self.poisson,
            self.simplify,
            self.tiles,
        )
        positive = {
            "scans.max_range_m": sc.max_range_m,
            "scans.every_nth": sc.every_nth,
            "scans.max_edge_m": sc.max_edge_m,
            "ground.max_angle_deg": g.max_angle_deg,
            "projection.height": pr.height,
            "projection.width": pr.width,
            "poisson.depth": po.depth,
            "poisson.max_support_m": po.max_support_m,
            "poisson.voxel_m": po.voxel_m,
            "simplify.voxel_m": si.voxel_m,
            "tiles.size_m": t.size_m,
        }
        if g.sensor_height_m is not None:
            positive["ground.sensor_height_m"] = g.sensor_height_m
        for key, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise InputError(f"{where}: {key} must be > 0, got {value}")
        non_negative = {
            "scans.min_range_m": sc.min_range_m,
            "tiles.margin_m": t.margin_m,
            "simplify.smooth_iterations": si.smooth_iterations,
            "workers": self.workers,
        }
        for key, value in non_negative.items():
            if not (math.isfinite(value) and value >= 0):
                raise InputError(f"{where}: {key} must be >= 0, got {value}")
        if not (math.isfinite(t.coarse_ratio) and 0.0 <= t.coarse_ratio <= 1.0):
            raise InputError(f"{where}: tiles.coarse_ratio must lie in [0, 1], got {t.coarse_ratio}")
        if not math.isfinite(g.z_margin_m):
            raise InputError(f"{where}: ground.z_margin_m must be finite, got {g.z_margin_m}")
        if sc.min_range_m >= sc.max_range_m:
            raise InputError(f"{where}: scans.min_range_m must be below scans.max_range_m")
        if g.max_angle_deg >= 90:
            raise InputError(f"{where}: ground.max_angle_deg must be below 90, got {g.max_angle_deg}")
        if po.depth > 16:
            raise InputError(f"{where}: poisson.depth must be at most 16, got {po.depth}")
        if not 0 <= po.density_quantile < 1:
            raise InputError(
                f"{where}: poisson.density_quantile must be in [0, 1), got {po.density_quantile}"
            )
        if not pr.fov_down_deg < pr.fov_up_deg:
            raise InputError(f"{where}: projection.fov_down_deg must be below projection.fov_up_deg")
        if pr.height * pr.width > MAX_PROJECTION_PIXELS:
            raise InputError(
                f"{where}: projection.height x projection.width must be at most {MAX_PROJECTION_PIXELS} "
                f"pixels, got {pr.height} x {pr.width}"
            )


# ---------------------------------------------------------------------------------------------- report


@dataclass
class BuildReport:
    scans_total: int = 0
    scans_used: int = 0
    scans_skipped_empty: int = 0  # no valid point after filtering
    points_nonfinite: int = 0  # NaN / inf points removed
    points_dynamic_dropped: int = 0
    points_used: int = 0
    tiles: int = 0
    triangles_before_simplify: int = 0
    triangles: int = 0
    ground_triangles_before: int = 0
    ground_triangles_after: int = 0
    seconds: dict = field(default_factory=dict)
    peak_rss_mb: float = 0.0  # the larger of the two below
    peak_rss_main_mb: float = 0.0  # this process (scans, assembling the map folder)
    peak_rss_tile_jobs_mb: float = 0.0  # the largest tile job (0 when the tiles ran in this process)
    tile_stats: list = field(default_factory=list)
    tiles_resumed: int = 0  # tiles whose mesh an interrupted build had made (--resume)


def _rss_mb(who) -> float:
    return resource.getrusage(who).ru_maxrss / 1024.0


# ---------------------------------------------------------------------------------------------- stages


def scan_geometry(seq: Sequence, settings: MapSettings):
    """The range-image grid of the sequence's sensor (our recordings) or an Eq. 1 grid (others)."""
    sensor = seq.meta.get("sensor") if isinstance(seq.meta, dict) else None
    if sensor:
        spec = spec_from_dict(sensor, where=f"{seq.root / 'meta.yaml'}: sensor")
        return spec, RangeImageGeometry.for_spec(spec)
    p = settings.projection
    return None, RangeImageGeometry.for_fov(p.height, p.width, p.fov_up_deg, p.fov_down_deg)


def oriented_points(seq: Sequence, i: int, spec, geometry, settings: MapSettings, sensor_height_m, report):
    """One scan's valid points with normals and ground labels, in the world frame (or None)."""
    s = settings.scans
    points = seq.scan(i).astype(np.float64)
    meta = seq.point_meta(i)
    finite = np.isfinite(points).all(axis=1)
    report.points_nonfinite += int((~finite).sum())
    keep = finite.copy()
    if s.drop_dynamic_labels and "label" in meta:
        dynamic = meta["label"] != 0
        report.points_dynamic_dropped += int((dynamic & keep).sum())
        keep &= ~dynamic
    rows = cols = None
    if spec is not None and "ring" in meta and "column" in meta:
        rows = np.asarray(spec.row_of_beam)[meta["ring"].astype(np.int64)][keep]
        cols = meta["column"].astype(np.int64)[keep]
    fire_s = meta["time_s"][keep].astype(np.float64) if "time_s" in meta else None
    points = points[keep]
    if len(points) == 0:
        return None
    normals, valid = scan_normals(points, geometry, rows=rows, cols=cols, max_edge_m=s.max_edge_m)
    r = np.linalg.norm(points, axis=1)
    valid &= (r >= s.min_range_m) & (r <= s.max_range_m)
    if not valid.any():
        return None
    g = settings.ground
    ground = label_ground(
        points,
        normals,
        valid,
        sensor_height_m=sensor_height_m,
        max_angle_deg=g.max_angle_deg,
        z_margin_m=g.z_margin_m,
    )
    p, n = points[valid], normals[valid].astype(np.float64)
    if s.deskew and fire_s is not None and seq.times is not None and len(seq) > 1:
        # each point from the sensor pose at its firing time (relative to the scan's stamp, <= 0)
        times, unique_inv = np.unique(fire_s[valid], return_inverse=True)
        lo, hi = max(i - 1, 0), min(i + 1, len(seq) - 1)
        window = slice(lo, hi + 1)
        T = interpolate_poses(seq.times[window], seq.poses[window], seq.times[i] + times)[unique_inv]
        p_world = np.einsum("nij,nj->ni", T[:, :3, :3], p) + T[:, :3, 3]
        n_world = np.einsum("nij,nj->ni", T[:, :3, :3], n)
    else:
        T = seq.poses[i]
        p_world = p @ T[:3, :3].T + T[:3, 3]
        n_world = n @ T[:3, :3].T
    return p_world, n_world, ground[valid]


class TileSpool:
    """Points cut into tiles (with a margin) and spooled to disk, so memory stays bounded."""

    def __init__(self, root: Path, tile_m: float, margin_m: float):
        self.root = root
        self.tile_m = tile_m
        self.margin_m = margin_m
        self.chunks: dict[tuple[int, int], list[Path]] = defaultdict(list)

    def add(self, points: np.ndarray, normals: np.ndarray, ground: np.ndarray) -> None:
        lo = np.floor((points[:, :2] - self.margin_m) / self.tile_m).astype(np.int64)
        hi = np.floor((points[:, :2] + self.margin_m) / self.tile_m).astype(np.int64)
        for ti in range(int(lo[:, 0].min()), int(hi[:, 0].max()) + 1):
            for tj in range(int(lo[:, 1].min()), int(hi[:, 1].max()) + 1):
                inside = (lo[:, 0] <= ti) & (ti <= hi[:, 0]) & (lo[:, 1] <= tj) & (tj <= hi[:, 1])
                if not inside.any():
                    continue
                path = self.root / f"tile_{ti}_{tj}_{len(self.chunks[(ti, tj)]):06d}.npz"
                np.savez(
                    path,
                    points=points[inside].astype(np.float64),
                    normals=normals[inside].astype(np.float32),
                    ground=ground[inside],
                )
                self.chunks[(ti, tj)].append(path)


@dataclass
class TileJob:
    tile: tuple[int, int]
    chunks: list[Path]
    tile_m: float
    poisson: PoissonSettings
    simplify: SimplifySettings
    out: Path


def voxel_thin(points: np.ndarray, voxel_m: float) -> np.ndarray:
    """Indices of one point per occupied voxel (the first in input order)."""
    keys = np.floor(points / voxel_m).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    return np.sort(first)


def accumulate_thinned(chunks, voxel_m: float, flush_points: int = 4_000_000):
    """A tile's spooled points, one per voxel (the earliest scan's wins), read chunk by chunk so that
    memory follows the tile's surface area, not how often the drive passed by."""
    kept: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    pending = 0
    for source in chunks:
        with np.load(source) as d:
            kept.append((d["points"], d["normals"], d["ground"]))
        pending += len(kept[-1][0])
        if pending >= flush_points:
            kept = [_thin_parts(kept, voxel_m)]
            pending = 0
    return _thin_parts(kept, voxel_m)


def _thin_parts(parts, voxel_m: float):
    points = np.concatenate([p for p, _, _ in parts])
    normals = np.concatenate([n for _, n, _ in parts])
    ground = np.concatenate([g for _, _, g in parts])
    keep = voxel_thin(points, voxel_m)
    return points[keep], normals[keep], ground[keep]


def mesh_tile(job: TileJob, sources=None) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """Poisson mesh of one tile (its points include the margin), cropped to the tile, ground simplified:
    ``(vertices, faces, is_ground, stats)``. ``sources`` are the tile's spooled chunks as paths or open
    binary files (default: ``job.chunks``), in spool order."""
    t0 = time.perf_counter()
    chunks = job.chunks if sources is None else sources
    points, normals, ground = accumulate_thinned(chunks, job.poisson.voxel_m)
    normals = normals.astype(np.float64)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    ti, tj = job.tile
    box = (ti * job.tile_m, tj * job.tile_m, (ti + 1) * job.tile_m, (tj + 1) * job.tile_m)
    p = job.poisson
    v, f, stats = poisson_mesh(
        points,
        normals,
        depth=p.depth,
        density_quantile=p.density_quantile,
        max_support_m=p.max_support_m,
        crop=box,
        n_threads=1,  # reproducible (Open3D threads change a few triangles); tiles run in parallel instead
    )
    stats = {"tile": [ti, tj], "points": len(points), **{k: v_ for k, v_ in stats.items() if _plain(v_)}}
    is_ground = transfer_labels(v, points, ground) if len(v) else np.zeros(0, bool)
    stats["triangles_before_simplify"] = len(f)
    stats["ground_triangles_before"] = int(is_ground[f].all(axis=1).sum()) if len(f) else 0
    if job.simplify.enabled and len(f):
        s = job.simplify
        v, f, is_ground, _ = simplify_ground(
            v, f, is_ground, voxel_m=s.voxel_m, smooth_iterations=s.smooth_iterations
        )
    stats["triangles"] = len(f)
    stats["ground_triangles_after"] = int(is_ground[f].all(axis=1).sum()) if len(f) else 0
    stats["seconds"] = time.perf_counter() - t0
    return v, f, is_ground, stats


def write_tile(job: TileJob, v: np.ndarray, f: np.ndarray, is_ground: np.ndarray, stats: dict) -> dict:
    """A tile's mesh into the work area: whole or absent (a resumed build trusts every tile output it
    finds), then its stats beside it."""
    tmp = job.out.with_name(f".{job.out.name}.tmp.npz")
    np.savez(tmp, vertices=v, faces=f, is_ground=is_ground)
    os.replace(tmp, job.out)
    job.out.with_suffix(".json").write_text(json.dumps(stats, default=_jsonable))
    return stats


def build_tile(job: TileJob) -> dict:
    """One tile job of the process pool: its mesh, written to ``job.out``."""
    return write_tile(job, *mesh_tile(job))


def _plain(x) -> bool:
    return isinstance(x, int | float | str | bool)


BACKENDS = ("process", "ray")  # where the tile jobs run: a local process pool, or Ray (local or a cluster)
WORK_DIR = ".build"  # an unfinished build's work area inside its map folder (kept for --resume)
STATE_VERSION = 1
_SCAN_COUNTS = (
    "scans_used",
    "scans_skipped_empty",
    "points_nonfinite",
    "points_dynamic_dropped",
    "points_used",
)


def _fingerprint(seq, settings: MapSettings) -> str:
    """What a resumed build must share with the interrupted one: the sequence and the settings that
    shape the map (not ``workers``: every tile's mesh is the same however many build at once, so a build
    may be resumed with another count)."""
    import hashlib

    scans = [str(p) for p in seq.scan_paths]
    shaping = {k: v for k, v in to_dict(settings).items() if k != "workers"}
    data = json.dumps(
        {"seq": str(Path(seq.root).resolve()), "scans": scans, "settings": shaping},
        sort_keys=True,
        default=str,
    )
    return hashlib.sha1(data.encode()).hexdigest()


def build_map(
    seq_dir: str | os.PathLike,
    out_dir: str | os.PathLike,
    settings: MapSettings | None = None,
    *,
    progress: bool = False,
    resume: bool = False,
    bag_options=None,
    backend: str = "process",
    address: str | None = None,
) -> BuildReport:
    """Build a mesh map from a sequence with poses and write it (mesh, tiles, metadata, config, report).

    The work (the spooled points per tile, each tile's mesh) lives in ``OUT/.build`` and is removed when
    the map is written. An interrupted build keeps it: ``resume=True`` then skips the scan stage if it
    had finished and builds only the tiles whose mesh is missing (the same sequence and settings are
    required; an :class:`InputError` says otherwise). Without ``resume`` a leftover work area is swept.
    A build that fails leaves nothing it created; one interrupted (Ctrl-C, SIGTERM) after its scan stage
    keeps the work area for ``resume``. ``backend`` "ray" runs the tile jobs as Ray tasks
    (:mod:`rangemcl.mapping.raybuild`) on a local instance of ``settings.workers`` CPUs, or on the cluster
    at ``address``; the map is the same as the process pool's."""
    out_dir = Path(out_dir)
    made = None  # the outermost folder this build creates
    probe = out_dir
    while not probe.exists():
        made = probe
        probe = probe.parent
    try:
        if backend not in BACKENDS:
            raise InputError(f"backend {backend!r}: expected one of {', '.join(BACKENDS)}")
        return _build(seq_dir, out_dir, settings, progress, resume, bag_options, backend, address)
    except BaseException as err:
        work = out_dir / WORK_DIR
        keep = isinstance(err, KeyboardInterrupt) and (work / "state.json").is_file()
        if not keep:
            if made is not None:
                shutil.rmtree(made, ignore_errors=True)
            elif not resume:
                shutil.rmtree(work, ignore_errors=True)
        raise


def _build(
    seq_dir,
    out_dir: Path,
    settings: MapSettings | None,
    progress: bool,
    resume: bool,
    bag_options=None,
    backend: str = "process",
    address: str | None = None,
) -> BuildReport:
    settings = settings or MapSettings()
    settings.check()
    out_dir = Path(out_dir)
    report = BuildReport()
    clock = time.perf_counter()
    seq = open_source(seq_dir, require_poses=True, bag_options=bag_options)
    spec, geometry = scan_geometry(seq, settings)
    height = settings.ground.sensor_height_m
    if height is None:
        mount = seq.meta.get("sensor_to_base") if isinstance(seq.meta, dict) else None  # a bag's TF
        if spec is not None:
            height = float(spec.T_base_sensor[2, 3])
        elif isinstance(mount, dict):
            height = float(mount["xyz_m"][2])
        else:
            height = 1.73
    _check_out_dir(out_dir)
    work = out_dir / WORK_DIR
    state_file = work / "state.json"
    fingerprint = _fingerprint(seq, settings)
    state = None
    if resume:
        if not state_file.is_file():
            if not work.is_dir():
                raise InputError(f"{out_dir}: nothing to resume (no interrupted build in it)")
        else:
            try:
                state = json.loads(state_file.read_text())
            except (OSError, ValueError) as err:
                raise InputError(
                    f"{state_file}: unreadable ({err}); give --overwrite to start the build over"
                ) from None
            if not isinstance(state, dict):
                raise InputError(f"{state_file}: not a build state; give --overwrite to start the build over")
            if state.get("version") != STATE_VERSION or state.get("fingerprint") != fingerprint:
                raise InputError(
                    f"{out_dir}: the interrupted build used another sequence or other settings; "
                    "give --overwrite to start over"
                )
    if state is None and work.exists():
        shutil.rmtree(work)  # a leftover of a killed run: swept
    work.mkdir(parents=True, exist_ok=True)
    spool = TileSpool(work, settings.tiles.size_m, settings.tiles.margin_m)
    report.scans_total = len(seq)
    if state is not None:  # the scan stage had finished
        for k in (
            "scans_used",
            "scans_skipped_empty",
            "points_nonfinite",
            "points_dynamic_dropped",
            "points_used",
        ):
            setattr(report, k, state["report"][k])
        for key, names in state["chunks"].items():
            ti, tj = (int(x) for x in key.split(","))
            spool.chunks[(ti, tj)] = [work / n for n in names]
        report.seconds["scans"] = 0.0
    else:
        indices = range(0, len(seq), max(1, settings.scans.every_nth))
        for n, i in enumerate(_progress(indices, progress, "normals and ground")):
            if n == len(indices) // 2:
                kill_point("scans")  # tests: killed in the middle of the scan stage
            got = oriented_points(seq, i, spec, geometry, settings, height, report)
            if got is None:
                report.scans_skipped_empty += 1
                continue
            report.scans_used += 1
            report.points_used += len(got[0])
            spool.add(*got)
        if report.scans_used == 0:
            shutil.rmtree(work, ignore_errors=True)
            raise InputError(f"{seq.root}: no scan has a valid point: nothing to build a map from")
        report.seconds["scans"] = time.perf_counter() - clock
        done = {
            "version": STATE_VERSION,
            "fingerprint": fingerprint,
            "chunks": {f"{ti},{tj}": [p.name for p in paths] for (ti, tj), paths in spool.chunks.items()},
            "report": {
                k: getattr(report, k)
                for k in (
                    "scans_used",
                    "scans_skipped_empty",
                    "points_nonfinite",
                    "points_dynamic_dropped",
                    "points_used",
                )
            },
        }
        atomic_write(state_file, json.dumps(done))
    t1 = time.perf_counter()
    jobs = [
        TileJob(
            tile,
            chunks,
            settings.tiles.size_m,
            settings.poisson,
            settings.simplify,
            work / f"mesh_{tile[0]}_{tile[1]}.npz",
        )
        for tile, chunks in sorted(spool.chunks.items())
    ]
    todo = [j for j in jobs if not (j.out.is_file() and j.out.with_suffix(".json").is_file())]
    report.tiles_resumed = len(jobs) - len(todo)
    workers = settings.workers or os.cpu_count() or 1
    ray_peaks = []
    if backend == "ray":
        from rangemcl.mapping.raybuild import run_tiles

        ran = run_tiles(todo, mesh_tile, write_tile, work_dir=work, workers=workers, address=address)
        for s in _progress(ran, progress, "tiles", total=len(todo)):
            ray_peaks.append(s.get("peak_rss_mb", 0.0))
            kill_point("tiles")
    elif workers == 1 or len(todo) <= 1:
        for j in _progress(todo, progress, "tiles"):
            build_tile(j)
            kill_point("tiles")  # tests: killed with tiles done and tiles to do
    else:
        # spawned workers: each one's peak memory is its own (a forked one counts the parent's pages)
        with process_pool(min(workers, len(todo)), "spawn") as pool:
            for _ in _progress(pool.map(build_tile, todo), progress, "tiles", total=len(todo)):
                kill_point("tiles")
    stats = [json.loads(j.out.with_suffix(".json").read_text()) for j in jobs]
    report.seconds["tiles"] = time.perf_counter() - t1
    report.tile_stats = stats
    t2 = time.perf_counter()
    for key in ("triangles_before_simplify", "ground_triangles_before", "ground_triangles_after"):
        setattr(report, key, int(sum(s[key] for s in stats)))
    meta = {
        "frame": "world (the sequence's poses frame)",
        "source_sequence": str(Path(seq.root).resolve()),
        "scene": seq.meta.get("scene") if isinstance(seq.meta, dict) else None,
        "sensor": spec.name if spec is not None else "unknown (Eq. 1 projection)",
        "sensor_height_m": height,
        "scans_used": report.scans_used,
        "created_by": "rangemcl build-map",
    }
    if sum(s["triangles"] for s in stats) == 0:
        shutil.rmtree(work, ignore_errors=True)
        raise InputError(f"{seq.root}: the reconstruction is empty (too few points with normals)")
    assembly = work / "assemble"
    shutil.rmtree(assembly, ignore_errors=True)
    counts = assemble_map(
        [j.out for j in jobs],
        out_dir,
        tile_size_m=settings.tiles.size_m,
        work_dir=assembly,
        meta=meta,
        drive_xy=thin_path(seq.poses[:, :2, 3], 1.0),
        coarse_ratio=settings.tiles.coarse_ratio,
    )
    report.tiles = counts["tiles"]
    report.triangles = counts["triangles"]
    report.seconds["assemble"] = time.perf_counter() - t2
    write_config(settings, out_dir / "config.yaml")
    report.seconds["total"] = time.perf_counter() - clock
    report.peak_rss_main_mb = _rss_mb(resource.RUSAGE_SELF)
    report.peak_rss_tile_jobs_mb = max([_rss_mb(resource.RUSAGE_CHILDREN), *ray_peaks])
    report.peak_rss_mb = max(report.peak_rss_main_mb, report.peak_rss_tile_jobs_mb)
    (out_dir / "report.json").write_text(json.dumps(report.__dict__, indent=2, default=_jsonable))
    shutil.rmtree(work, ignore_errors=True)  # the map is whole: its work area goes
    return report


def _jsonable(x):
    if isinstance(x, np.integer | np.floating):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)


def _check_out_dir(out: Path) -> None:
    probe = out
    while not probe.exists():
        probe = probe.parent
    if not probe.is_dir() or not os.access(probe, os.W_OK | os.X_OK):
        raise InputError(f"{out}: cannot write the map folder here ({probe} is not a writable folder)")


def _progress(items, enabled: bool, label: str, total: int | None = None):
    if not enabled:
        yield from items
        return
    from rich.progress import track

    yield from track(items, description=label, total=total if total is not None else len(items))
