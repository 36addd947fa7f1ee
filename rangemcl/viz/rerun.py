"""Seeing a run: stream it to the rerun viewer as it goes, or save it as an ``.rrd`` file headless.

:class:`RunViewer` shows a localization run (``rangemcl localize --viz`` / ``--viz-out run.rrd``): the map
mesh once, and per frame the scan under the estimated pose, the particle cloud colored by weight, the
estimated and true paths and the location error. :class:`DriveViewer` shows a simulated drive (``simbed
record --viz``): the scene mesh, the car's true pose and path, the sweep colored by label and the moving
actors' boxes. Both take plain arrays (a simbed frame is read by attribute), so ``rangemcl`` does not
import ``simbed``.

rerun-sdk is an optional extra, imported only when a viewer is opened; without it the error is one line
naming the install. ``RunViewer.disabled()`` (also what :meth:`RunViewer.open` gives when asked for neither
a viewer nor a file) does nothing, cheaply, so callers log every frame unconditionally.

Entities, all in the world frame (x east, y north, z up, metres)::

    world/map                  static mesh (vertex colors by height; ground grey)
    world/estimate             transform of the estimated sensor pose; world/estimate/scan: the scan
    world/truth                transform of the true sensor pose
    world/particles            points colored by weight; world/particles/yaw: arrows of the heaviest
    world/path/estimate, world/path/truth   line strips of the poses so far
    metrics/error_m, metrics/particles      scalars
    world/car, world/car/sweep, world/path/car, world/actors   (DriveViewer)

Timelines: ``frame`` (sequence) and ``time`` (duration, seconds of the sequence). A point costs 16 bytes
in the file, so a frame logs at most ``max_scan_points`` scan points and ``max_particles`` particles, fewer
when a file is written (:data:`FILE_LIMITS`: a 100-frame global run in the campus map writes 3.8 MB of
frames) than when only a viewer is shown (:data:`LIVE_LIMITS`); the map is logged once (campus, 380k
triangles: 4.6 MB).
"""

from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np

from rangemcl.errors import InputError

INSTALL = "pip install 'simbed-rangemcl[viz]'"

# Per-frame budgets: live (a viewer only) and with a file (which should stay a few MB per 100 frames).
LIVE_LIMITS = {"scan": 20_000, "particles": 20_000, "arrows": 2_000}
FILE_LIMITS = {"scan": 1_500, "particles": 1_500, "arrows": 300}
MAX_TRIANGLES = 2_000_000
MAX_PATH_VERTICES = 2_000  # a path is re-logged every frame: thinned to this many vertices

ESTIMATE_RGB = (255, 140, 0)
TRUTH_RGB = (40, 200, 60)
CAR_RGB = (40, 120, 255)
ACTOR_POINT_RGB = (230, 30, 30)

# Colormap anchors for values in [0, 1]: turbo-like (scans), plasma-like (particle weights), greys (maps).
TURBO = np.array(
    [
        [48, 18, 59],
        [40, 120, 240],
        [30, 200, 200],
        [120, 250, 80],
        [240, 220, 40],
        [250, 110, 20],
        [170, 20, 2],
    ],
    np.float64,
)
PLASMA = np.array([[13, 8, 135], [126, 3, 168], [204, 71, 120], [248, 149, 64], [240, 249, 33]], np.float64)
SLATE = np.array([[95, 105, 125], [225, 228, 235]], np.float64)
GROUND_RGB = (165, 165, 160)
# Sizes in UI points (rerun: a negative radius), so scans, clouds and paths stay visible when zoomed out.
SCAN_RADIUS, PARTICLE_RADIUS, PATH_RADIUS, MARKER_RADIUS, ARROW_RADIUS = -1.5, -2.5, -2.0, -6.0, -1.0
ARROW_M = 1.0  # length of a particle's yaw arrow


def rerun_module(what: str = "the rerun viewer (--viz, --viz-out)"):
    """``import rerun``, or an :class:`InputError` naming the install."""
    try:
        import rerun as rr
    except ImportError:
        raise InputError(f"{what} needs rerun-sdk, which is not installed: {INSTALL}") from None
    return rr


def check_rrd_path(out) -> Path:
    """The ``.rrd`` path to write, or an :class:`InputError` naming it (a folder, no parent folder)."""
    out = Path(out)
    if out.is_dir():
        raise InputError(f"{out}: is a folder; give a file to write the recording to (e.g. run.rrd)")
    parent = out.parent
    if not parent.is_dir():
        why = "is not a folder" if parent.exists() else "does not exist"
        raise InputError(f"cannot write {out}: the folder {parent} {why}")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"cannot write {out}: the folder {parent} is not writable")
    if out.exists() and not os.access(out, os.W_OK):
        raise InputError(f"cannot write {out}: the file is not writable")
    return out


def colormap(
    values, lo: float | None = None, hi: float | None = None, anchors: np.ndarray = TURBO
) -> np.ndarray:
    """``(N, 3)`` uint8 colors of ``values`` scaled from ``lo`` (first anchor; default the minimum) to
    ``hi`` (last anchor; default the maximum)."""
    v = np.asarray(values, np.float64).ravel()
    if len(v) == 0:
        return np.zeros((0, 3), np.uint8)
    finite = v[np.isfinite(v)]
    lo = float(finite.min()) if lo is None and len(finite) else (0.0 if lo is None else lo)
    hi = float(finite.max()) if hi is None and len(finite) else (1.0 if hi is None else hi)
    s = np.clip((v - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    s = np.where(np.isfinite(s), s, 0.0)
    x = np.linspace(0.0, 1.0, len(anchors))
    return np.stack([np.interp(s, x, anchors[:, c]) for c in range(3)], axis=1).astype(np.uint8)


def pose_matrix(pose, z_m: float = 0.0) -> np.ndarray:
    """``(4, 4)`` of a ``(4, 4)`` pose or of ``(x, y, yaw)`` (level, at height ``z_m``)."""
    p = np.asarray(pose, np.float64)
    if p.shape == (4, 4):
        return p
    if p.shape != (3,):
        raise ValueError(f"a pose is (4, 4) or (x, y, yaw), got shape {p.shape}")
    c, s = math.cos(p[2]), math.sin(p[2])
    T = np.eye(4)
    T[:2, :2] = [[c, -s], [s, c]]
    T[:3, 3] = (p[0], p[1], z_m)
    return T


def overview_eye(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A camera (position, target) that sees the whole of ``vertices`` obliquely from the south."""
    lo, hi = np.percentile(vertices, 1, axis=0), np.percentile(vertices, 99, axis=0)
    target = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    size = max(float(np.max(hi[:2] - lo[:2])), 10.0)
    return target + np.array([0.0, -0.75, 0.6]) * size, target


def thin_indices(n: int, k: int) -> np.ndarray:
    """At most ``k`` indices spread evenly over ``range(n)`` (all of them when ``n <= k``)."""
    if n <= k:
        return np.arange(n)
    return np.unique(np.linspace(0, n - 1, k).round().astype(np.int64))


def _thin_path(points: list[np.ndarray]) -> np.ndarray:
    xyz = np.asarray(points, np.float32).reshape(-1, 3)
    return xyz[thin_indices(len(xyz), MAX_PATH_VERTICES)]  # keeps the first and the last vertex


class _Viewer:
    """An explicit rerun recording stream (never the global one) and its sinks; without one (``rec=None``,
    :meth:`disabled`) every method returns at once."""

    application = "rangemcl"
    plots: tuple[tuple[str, str], ...] = ()  # (entity under metrics/, title) of the time series shown

    def __init__(self, rec=None, rr=None, limits: dict | None = None):
        self._rec, self._rr = rec, rr
        self.limits = dict(limits or FILE_LIMITS)
        self.out_rrd: Path | None = None

    @classmethod
    def disabled(cls):
        """A viewer that logs nothing (every method returns at once)."""
        return cls()

    @classmethod
    def open(
        cls,
        name: str,
        *,
        out_rrd: str | os.PathLike | None = None,
        spawn: bool = False,
        max_scan_points: int | None = None,
        max_particles: int | None = None,
        max_arrows: int | None = None,
    ):
        """Open a recording named ``name``: ``spawn`` starts the rerun viewer and streams to it,
        ``out_rrd`` writes an ``.rrd`` file (both may be given; neither gives :meth:`disabled`).

        Per-frame limits default to :data:`FILE_LIMITS` when a file is written, else :data:`LIVE_LIMITS`.
        Missing rerun-sdk, or an ``out_rrd`` that cannot be written, is an :class:`InputError`.
        """
        if out_rrd is None and not spawn:
            return cls.disabled()
        rr = rerun_module()
        out = check_rrd_path(out_rrd) if out_rrd is not None else None
        limits = dict(LIVE_LIMITS if out is None else FILE_LIMITS)
        for key, value in (("scan", max_scan_points), ("particles", max_particles), ("arrows", max_arrows)):
            if value is not None:
                if value < 0:
                    raise InputError(f"max {key} per frame must be >= 0, got {value}")
                limits[key] = int(value)
        rec = rr.RecordingStream(cls.application)
        blueprint = cls._blueprint()
        try:
            if spawn:
                rec.spawn(connect=False, hide_welcome_screen=True)  # the viewer process; sinks below
            sinks = ([rr.GrpcSink()] if spawn else []) + ([rr.FileSink(str(out))] if out is not None else [])
            rec.set_sinks(*sinks, default_blueprint=blueprint)
        except (OSError, RuntimeError, ValueError) as err:
            where = f"{out}" if out is not None else "the rerun viewer"
            raise InputError(f"{where}: cannot open the recording ({err})") from None
        rec.send_recording_name(name)
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        viewer = cls(rec, rr, limits)
        viewer.out_rrd = out
        viewer._start()
        return viewer

    @classmethod
    def _blueprint(cls, eye: tuple | None = None):
        """The 3D world (seen from ``eye``: position, target) beside one plot per metric (their scales
        differ), following the newest frame."""
        import rerun.blueprint as rrb

        controls = None
        if eye is not None:
            controls = rrb.EyeControls3D(
                kind="Orbital", position=eye[0], look_target=eye[1], eye_up=(0, 0, 1)
            )
        world = rrb.Spatial3DView(origin="world", name="world", eye_controls=controls)
        plots = [rrb.TimeSeriesView(origin=f"metrics/{k}", name=name) for k, name in cls.plots]
        return rrb.Blueprint(
            rrb.Horizontal(world, rrb.Vertical(*plots), column_shares=[3, 1]) if plots else world,
            rrb.TimePanel(timeline="frame", play_state="following", state="collapsed"),
            collapse_panels=True,
        )

    def _start(self) -> None:
        """Static entities a subclass logs once, after the sinks are set."""

    @property
    def enabled(self) -> bool:
        return self._rec is not None

    def log_map(
        self, vertices, faces, normals=None, *, colors=None, max_triangles: int = MAX_TRIANGLES
    ) -> None:
        """The map (or scene) mesh, static under ``world/map``: ``vertices (V, 3)``, ``faces (F, 3)``,
        optional ``normals (V, 3)`` and ``colors (V, 3)`` uint8 (default: by height). Above
        ``max_triangles`` an even subset of the faces is shown, and a note under ``notes`` says so
        (``max_triangles=0`` leaves the mesh out)."""
        if self._rec is None:
            return
        rr = self._rr
        v = np.asarray(vertices, np.float64).reshape(-1, 3)
        f = np.asarray(faces, np.int64).reshape(-1, 3)
        n = None if normals is None else np.asarray(normals, np.float32).reshape(-1, 3)
        if colors is None:  # greys lighter with height: shapes read without normals (no lighting)
            c = colormap(v[:, 2], anchors=SLATE)
        else:
            c = np.asarray(colors, np.uint8).reshape(-1, 3)
        if len(f) > max_triangles:
            note = f"map: {len(f):,} triangles, over max_triangles {max_triangles:,}"
            if max_triangles <= 0:
                self._rec.log("notes", rr.TextLog(note + ": not shown", level="WARN"), static=True)
                return
            f = f[thin_indices(len(f), max_triangles)]
            self._rec.log("notes", rr.TextLog(note + f": showing {len(f):,}", level="WARN"), static=True)
        used, f = np.unique(f, return_inverse=True)  # drop the vertices no shown face uses
        f = f.reshape(-1, 3).astype(np.uint32)
        self._rec.log(
            "world/map",
            rr.Mesh3D(
                vertex_positions=v[used].astype(np.float32),
                triangle_indices=f,
                vertex_normals=None if n is None else n[used],
                vertex_colors=c[used],
            ),
            static=True,
        )
        if len(used):
            self._rec.send_blueprint(self._blueprint(overview_eye(v[used])))

    def log_mesh_map(self, mesh_map, *, max_triangles: int = MAX_TRIANGLES) -> None:
        """A :class:`rangemcl.maps.meshmap.MeshMap`: ground light grey, the rest colored by height above
        the ground's median."""
        if self._rec is None:
            return
        v, ground = mesh_map.vertices, np.asarray(mesh_map.is_ground, bool)
        base = float(np.median(v[ground, 2])) if ground.any() else float(v[:, 2].min(initial=0.0))
        colors = colormap(v[:, 2] - base, 0.0, 15.0, anchors=SLATE)
        colors[ground] = GROUND_RGB
        self.log_map(v, mesh_map.faces, colors=colors, max_triangles=max_triangles)

    def _set_time(self, i: int, t_s: float | None) -> None:
        self._rec.set_time("frame", sequence=int(i))
        if t_s is not None and math.isfinite(t_s):
            self._rec.set_time("time", duration=float(t_s))

    def _transform(self, path: str, T: np.ndarray) -> None:
        self._rec.log(path, self._rr.Transform3D(translation=T[:3, 3], mat3x3=T[:3, :3]))

    def close(self) -> None:
        """Flush and close the sinks (the ``.rrd`` is complete, with its footer, afterwards)."""
        if self._rec is None:
            return
        rec, self._rec = self._rec, None
        rec.flush()
        rec.disconnect()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class RunViewer(_Viewer):
    """A localization run in rerun (see the module docstring): :meth:`open`, :meth:`log_mesh_map` once,
    :meth:`frame` after every filter step, :meth:`close`."""

    plots = (("error_m", "location error (m)"), ("particles", "particles"))

    def __init__(self, rec=None, rr=None, limits: dict | None = None):
        super().__init__(rec, rr, limits)
        # Each path is a list of strips (lists of positions); a new strip starts after a gap.
        self._paths: dict[str, list[list[np.ndarray]]] = {"estimate": [[]], "truth": [[]]}

    def _start(self) -> None:
        rr = self._rr
        for name, rgb in (("estimate", ESTIMATE_RGB), ("truth", TRUTH_RGB)):
            self._rec.log(f"world/{name}", rr.TransformAxes3D(2.0), static=True)
            self._rec.log(
                f"world/{name}/marker",
                rr.Points3D([[0.0, 0.0, 0.0]], colors=[rgb], radii=MARKER_RADIUS),
                static=True,
            )

    def frame(
        self,
        i: int,
        t_s: float | None,
        *,
        scan_sensor=None,
        estimate=None,
        truth=None,
        particles=None,
        weights=None,
        particle_z=None,
        sensor_height_m: float = 0.0,
        error_m: float | None = None,
        converged: bool | None = None,
    ) -> None:
        """Log frame ``i`` at ``t_s`` seconds.

        ``scan_sensor``: ``(M, 3+)`` points in the sensor frame, shown under the estimated pose (an even
        subset of at most ``limits['scan']``, colored by height). ``estimate`` and ``truth``: ``(4, 4)``
        sensor poses or ``(x, y, yaw)`` (then at ``sensor_height_m``). ``particles``: ``(P, 3)`` x, y, yaw
        at height ``particle_z`` (a number or ``(P,)``; default ``sensor_height_m``), colored by
        ``weights`` (``(P,)``, log scale over three decades), arrows for the heaviest. ``error_m``: the
        location error (default: the horizontal distance of estimate and truth when both are given).
        ``converged=False`` leaves the estimate out of the estimated path (before convergence it is the
        mean of a spread cloud); the path goes on in a new strip once converged again.
        """
        if self._rec is None:
            return
        rec, rr = self._rec, self._rr
        self._set_time(i, t_s)
        T_est = T_true = None
        if estimate is not None:
            T_est = pose_matrix(estimate, sensor_height_m)
            self._transform("world/estimate", T_est)
            self._log_path("estimate", T_est[:3, 3] if converged is not False else None, ESTIMATE_RGB)
        if truth is not None:
            T_true = pose_matrix(truth, sensor_height_m)
            self._transform("world/truth", T_true)
            self._log_path("truth", T_true[:3, 3], TRUTH_RGB)
        if scan_sensor is not None:
            pts = np.asarray(scan_sensor)[:, :3]
            pts = pts[np.isfinite(pts).all(axis=1)]
            pts = pts[thin_indices(len(pts), self.limits["scan"])].astype(np.float32)
            rec.log(
                "world/estimate/scan",
                rr.Points3D(pts, colors=colormap(pts[:, 2], -2.0, 6.0), radii=SCAN_RADIUS),
            )
        if particles is not None:
            self._log_particles(i, particles, weights, sensor_height_m if particle_z is None else particle_z)
        if error_m is None and T_est is not None and T_true is not None:
            error_m = float(np.hypot(*(T_est[:2, 3] - T_true[:2, 3])))
        if error_m is not None:
            rec.log("metrics/error_m", rr.Scalars(float(error_m)))

    def _log_path(self, name: str, xyz: np.ndarray | None, rgb) -> None:
        """Extend the path by ``xyz``, or (``None``) end its current strip."""
        strips = self._paths[name]
        if xyz is None:
            if strips[-1]:
                strips.append([])
            return
        strips[-1].append(np.asarray(xyz, np.float64).copy())
        shown = [_thin_path(s) for s in strips if len(s) > 1]
        if shown:
            self._rec.log(f"world/path/{name}", self._rr.LineStrips3D(shown, colors=[rgb], radii=PATH_RADIUS))

    def _log_particles(self, i: int, particles, weights, z) -> None:
        rec, rr = self._rec, self._rr
        p = np.asarray(particles, np.float64).reshape(-1, 3)
        n = len(p)
        w = np.full(n, 1.0 / max(n, 1)) if weights is None else np.asarray(weights, np.float64).ravel()
        if len(w) != n:
            raise ValueError(f"weights: {len(w)} for {n} particles")
        zs = np.broadcast_to(np.asarray(z, np.float64), (n,))
        rec.log("metrics/particles", rr.Scalars(float(n)))
        keep = np.arange(n)
        if n > self.limits["particles"]:  # an unbiased subset: the cloud's shape, not only its peak
            keep = np.sort(np.random.default_rng(i).choice(n, self.limits["particles"], replace=False))
        top = float(w.max()) if n else 1.0
        shade = np.log10(np.maximum(w / top, 1e-12)) / 3.0 + 1.0 if top > 0 else np.zeros(n)
        colors = colormap(shade, 0.0, 1.0, anchors=PLASMA)
        xyz = np.column_stack([p[:, :2], zs]).astype(np.float32)
        rec.log("world/particles", rr.Points3D(xyz[keep], colors=colors[keep], radii=PARTICLE_RADIUS))
        k = min(n, self.limits["arrows"])
        heavy = np.argpartition(-w, k - 1)[:k] if 0 < k < n else np.arange(k)
        vectors = np.column_stack([np.cos(p[heavy, 2]), np.sin(p[heavy, 2]), np.zeros(len(heavy))]) * ARROW_M
        rec.log(
            "world/particles/yaw",
            rr.Arrows3D(
                origins=xyz[heavy],
                vectors=vectors.astype(np.float32),
                colors=colors[heavy],
                radii=ARROW_RADIUS,
            ),
        )


class DriveViewer(_Viewer):
    """A simulated drive in rerun: :meth:`open`, :meth:`log_map` of the scene's static triangles once,
    :meth:`record_frame` per frame, :meth:`close`."""

    application = "simbed"

    def __init__(self, rec=None, rr=None, limits: dict | None = None):
        super().__init__(rec, rr, limits)
        self._path: list[np.ndarray] = []

    def _start(self) -> None:
        rr = self._rr
        self._rec.log("world/car", rr.TransformAxes3D(2.0), static=True)
        self._rec.log(
            "world/car/marker",
            rr.Points3D([[0.0, 0.0, 0.0]], colors=[CAR_RGB], radii=MARKER_RADIUS),
            static=True,
        )

    def record_frame(self, frame, actors: list[dict] | None = None) -> None:
        """Log a simbed ``Frame`` (read by attribute: ``index``, ``time_s``, ``T_world_sensor``,
        ``sweep.points`` in the sensor frame, ``sweep.label`` 0 static / 1 moving actor) and the actors'
        boxes (dicts with ``xyz``, ``quat_wxyz``, ``half``, optional ``rgba`` and ``name``, as
        ``simbed.record._actor_boxes`` gives them)."""
        if self._rec is None:
            return
        rec, rr = self._rec, self._rr
        self._set_time(frame.index, frame.time_s)
        T = np.asarray(frame.T_world_sensor, np.float64)
        self._transform("world/car", T)
        self._path.append(T[:3, 3].copy())
        if len(self._path) > 1:
            rec.log(
                "world/path/car",
                rr.LineStrips3D([_thin_path(self._path)], colors=[CAR_RGB], radii=PATH_RADIUS),
            )
        pts = np.asarray(frame.sweep.points)[:, :3]
        label = np.asarray(frame.sweep.label)
        keep = thin_indices(len(pts), self.limits["scan"])
        pts, label = pts[keep].astype(np.float32), label[keep]
        colors = colormap(pts[:, 2], -2.0, 6.0)
        colors[label == 1] = ACTOR_POINT_RGB
        rec.log("world/car/sweep", rr.Points3D(pts, colors=colors, radii=SCAN_RADIUS))
        if actors is not None:
            self.log_actors(actors)

    def log_actors(self, actors: list[dict]) -> None:
        """The moving actors' boxes at the current time (an empty list clears them)."""
        if self._rec is None:
            return
        rr = self._rr
        if not actors:
            self._rec.log("world/actors", rr.Clear(recursive=False))
            return
        q = np.array([a["quat_wxyz"] for a in actors], np.float64)  # MuJoCo order (w, x, y, z)
        rgba = np.array([a.get("rgba", (0.9, 0.1, 0.1, 1.0)) for a in actors], np.float64)
        self._rec.log(
            "world/actors",
            rr.Boxes3D(
                centers=np.array([a["xyz"] for a in actors], np.float32),
                half_sizes=np.array([a["half"] for a in actors], np.float32),
                quaternions=[rr.Quaternion(xyzw=row[[1, 2, 3, 0]]) for row in q],
                colors=(np.clip(rgba[:, :3], 0, 1) * 255).astype(np.uint8),
                labels=[str(a.get("name", "")) for a in actors],
            ),
        )
