"""The one ray-casting core: triangle meshes in Warp BVHs, queried by batches of rays.

The simulated LiDAR (simbed) and the localizer's particle renderer both cast through this module.

Conventions and defined results:

* Ranges are float32 metres along the *normalised* direction; a ray that hits nothing within its max
  range returns ``inf``, mesh id ``-1`` and face id ``-1``.
* A ray whose max range is ``<= 0`` returns a miss. Max ranges may be ``inf``.
* Origins and directions must be finite and directions must have non-zero length, else ``InputError``
  names the first bad ray (checked in numpy before any kernel runs, so the interpreter never sees them).
* Degenerate triangles (zero area) never produce hits; they are dropped when a mesh is added (counted in
  :attr:`MeshInfo.dropped_degenerate`). A mesh with no usable triangle is an ``InputError``.
* Backface hits count: a ray hits a triangle from either side.

Warp's CPU launches run on one core, and release the GIL, so on the CPU a batch is cut into contiguous
chunks that are launched from a pool of threads, one chunk per core at a time. Contiguous chunks keep each
origin's rays together, which the BVH traversal needs to stay fast.
"""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace

import numpy as np
import warp as wp

from rangemcl.common.heap import trim_freed_memory
from rangemcl.errors import InputError
from rangemcl.se2 import invert_rigid, quat_from_matrix

wp.config.log_level = wp.LOG_ERROR  # no banner, no missing-driver notice on CPU machines
wp.set_module_options({"enable_backward": False})


@wp.func
def segment_meets_box(o: wp.vec3, d: wp.vec3, t_max: float, lo: wp.vec3, hi: wp.vec3):
    """Whether the ray ``o + t d``, 0 <= t <= t_max, meets the box [lo, hi] (slab test)."""
    t0 = float(0.0)
    t1 = t_max
    ok = int(1)
    for a in range(3):
        if d[a] == 0.0:
            if o[a] < lo[a] or o[a] > hi[a]:
                ok = 0
        else:
            inv = 1.0 / d[a]
            ta = (lo[a] - o[a]) * inv
            tb = (hi[a] - o[a]) * inv
            t0 = wp.max(t0, wp.min(ta, tb))
            t1 = wp.min(t1, wp.max(ta, tb))
    if t0 > t1:
        ok = 0
    return ok


@wp.func
def closest_hit(
    meshes: wp.array[wp.uint64],
    inv_poses: wp.array[wp.transform],
    moved: wp.array[wp.int32],
    boxes: wp.array[wp.vec3],
    origin: wp.vec3,
    direction: wp.vec3,
    max_t: float,
):
    """Closest hit over all meshes: (t, mesh index, face, normal in the hit mesh's frame).

    On a miss t = max_t and the mesh index is -1. Meshes with ``moved[m] == 0`` sit at the identity
    pose and skip the ray transform (the common case: the static world). ``boxes[2m], boxes[2m + 1]``:
    mesh ``m``'s bounds in its own frame, padded; a mesh whose box the ray does not meet before the
    closest hit so far is not queried (a map held as tiles: most tiles of a launch lie off each ray).
    """
    best_t = max_t
    best_mesh = int(-1)  # int(...) makes Warp declare a mutable loop variable
    best_face = int(-1)
    best_normal = wp.vec3(0.0, 0.0, 0.0)
    for m in range(meshes.shape[0]):
        o = origin
        d = direction
        if moved[m] != 0:
            o = wp.transform_point(inv_poses[m], origin)
            d = wp.transform_vector(inv_poses[m], direction)
        if segment_meets_box(o, d, best_t, boxes[2 * m], boxes[2 * m + 1]) != 0:
            q = wp.mesh_query_ray(meshes[m], o, d, best_t)
            if q.result:
                best_t = q.t
                best_mesh = m
                best_face = q.face
                best_normal = q.normal
    return best_t, best_mesh, best_face, best_normal


def padded_boxes(bounds: np.ndarray) -> np.ndarray:
    """``(M, 6)`` mesh bounds (NaN rows: unknown) as the ``(2M, 3)`` float32 boxes :func:`closest_hit`
    tests, padded for float32 rounding (a hit exactly on a flat tile's face still counts); unknown
    bounds give a box that every ray meets."""
    b = np.asarray(bounds, np.float64).reshape(-1, 6)
    known = np.isfinite(b).all(axis=1)
    pad = 1e-3 + 1e-5 * np.abs(np.where(np.isfinite(b), b, 0.0)).max(axis=1, initial=0.0)
    lo = np.where(known[:, None], b[:, :3] - pad[:, None], -1e30)
    hi = np.where(known[:, None], b[:, 3:] + pad[:, None], 1e30)
    return np.stack([lo, hi], axis=1).reshape(-1, 3).astype(np.float32)


@wp.kernel
def cast_kernel(
    meshes: wp.array[wp.uint64],
    inv_poses: wp.array[wp.transform],
    moved: wp.array[wp.int32],
    boxes: wp.array[wp.vec3],
    origins: wp.array[wp.vec3],
    directions: wp.array[wp.vec3],
    max_ranges: wp.array[float],
    origin_stride: int,
    max_range_stride: int,
    offset: int,
    want_normals: int,
    out_range: wp.array[float],
    out_mesh: wp.array[wp.int32],
    out_face: wp.array[wp.int32],
    out_normal: wp.array[wp.vec3],
):
    i = wp.tid() + offset
    # one origin (or max range) may serve the whole batch: stride 0; one per ray: stride 1
    max_t = max_ranges[i * max_range_stride]
    t = float(wp.inf)
    m = int(-1)
    face = int(-1)
    normal = wp.vec3(0.0, 0.0, 0.0)
    if max_t > 0.0:
        t, m, face, normal = closest_hit(
            meshes, inv_poses, moved, boxes, origins[i * origin_stride], wp.normalize(directions[i]), max_t
        )
        if m < 0:
            t = float(wp.inf)
        elif want_normals != 0 and moved[m] != 0:
            normal = wp.transform_vector(wp.transform_inverse(inv_poses[m]), normal)
    out_range[i] = t
    out_mesh[i] = wp.int32(m)
    out_face[i] = wp.int32(face)
    if want_normals != 0:
        out_normal[i] = normal


@dataclass
class RayHits:
    """Result of :meth:`RayCaster.cast` for N rays."""

    ranges: np.ndarray  # (N,) float32 metres, inf on a miss
    mesh_ids: np.ndarray  # (N,) int32 handle of the hit mesh, -1 on a miss
    face_ids: (
        np.ndarray
    )  # (N,) int32 triangle index within that mesh (after degenerate removal), -1 on a miss
    normals: np.ndarray | None  # (N, 3) float32 unit world-frame face normals (winding order), if asked

    @property
    def hit(self) -> np.ndarray:
        """(N,) bool: the ray hit something within its max range."""
        return self.mesh_ids >= 0


@dataclass
class MeshInfo:
    """What the scene knows of one added mesh."""

    name: str
    movable: bool
    n_vertices: int
    n_faces: int
    dropped_degenerate: int
    kept_faces: np.ndarray | None  # (n_faces,) int32 indices of the faces kept; None: all were kept
    removed: bool = False  # taken out of the scene by RayCaster.remove_mesh (its handle stays unused)
    bounds: np.ndarray | None = None  # (6,) xmin, ymin, zmin, xmax, ymax, zmax of its vertices (own frame)

    @property
    def face_map(self) -> np.ndarray:
        """``(n_faces,)`` int32: index of each kept face in the faces given to add_mesh (made on demand: a
        map's tiles rarely drop a face, and the identity would take 4 bytes a triangle)."""
        if self.kept_faces is None:
            return np.arange(self.n_faces, dtype=np.int32)
        return self.kept_faces


@dataclass
class BuiltMesh:
    """A mesh with its BVH, built by :meth:`RayCaster.build_mesh` and not yet in a scene."""

    mesh: wp.Mesh
    info: MeshInfo


_DRIVER_NOTICE = "Could not find or load the NVIDIA CUDA driver"


def init_warp() -> None:
    """Initialise Warp once, without its missing-driver notice on machines that have no GPU.

    Warp prints that notice from native code, so stderr is captured at the file-descriptor level while
    Warp starts; every other line it printed is passed on.
    """
    if wp._src.context.runtime is not None:  # already initialised
        return
    import sys
    import tempfile

    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile(mode="w+b") as captured:
        os.dup2(captured.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        captured.seek(0)
        for line in captured.read().decode(errors="replace").splitlines():
            if _DRIVER_NOTICE not in line:
                print(line, file=sys.stderr)


def default_threads() -> int:
    """Worker threads for CPU launches: every core this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


def resolve_device(device: str | None) -> str:
    """``"cpu"`` (default), ``"cuda"``/``"cuda:N"``; an unavailable CUDA device is an ``InputError``."""
    init_warp()
    name = "cpu" if device in (None, "", "cpu") else str(device)
    if name.startswith("cuda"):
        if not wp.is_cuda_available():
            raise InputError(
                f"device {name!r}: no CUDA device is available on this machine (use --device cpu)"
            )
        try:
            wp.get_device(name)
        except (RuntimeError, ValueError) as err:
            raise InputError(f"device {name!r}: {err}") from None
        return name
    if name != "cpu":
        raise InputError(f"device {name!r}: expected 'cpu' or 'cuda[:N]'")
    return name


def _unit_directions(d: np.ndarray) -> np.ndarray:
    """Unit float32 directions; zero-length rows are an ``InputError``.

    The common case stays in float32 (this runs single-threaded before the parallel launch); only rows
    whose squared length under- or overflows float32 are normalised in float64.
    """
    n2 = np.einsum("ij,ij->i", d, d)
    awkward = ~((n2 > 1e-30) & (n2 < 1e30))
    if not awkward.any() and np.abs(n2 - 1.0).max(initial=0.0) < 1e-6:
        return d  # already unit
    out = d / np.sqrt(np.where(awkward, 1.0, n2))[:, None]
    if awkward.any():
        rows = np.flatnonzero(awkward)
        d64 = d[rows].astype(np.float64)
        length = np.sqrt(np.einsum("ij,ij->i", d64, d64))
        if (length == 0.0).any():
            first = int(rows[np.flatnonzero(length == 0.0)[0]])
            raise InputError(f"directions[{first}] has zero length ({int((length == 0.0).sum())} rays)")
        out[rows] = (d64 / length[:, None]).astype(np.float32)
    return np.ascontiguousarray(out, dtype=np.float32)


def _as_points(name: str, array, *, allow_single: bool = False) -> np.ndarray:
    a = np.asarray(array, dtype=np.float32)
    if allow_single and a.shape == (3,):
        a = a[None, :]
    if a.ndim != 2 or a.shape[1] != 3:
        raise InputError(f"{name}: expected shape (N, 3), got {a.shape}")
    if np.isfinite(a).all():  # the common case, without a per-row pass
        return np.ascontiguousarray(a)
    bad = ~np.isfinite(a).all(axis=1)
    if bad.any():
        raise InputError(f"{name}[{int(np.flatnonzero(bad)[0])}] is not finite ({bad.sum()} bad rows)")
    return np.ascontiguousarray(a)


def clean_mesh(name: str, vertices, faces) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate a triangle mesh and drop zero-area triangles.

    Returns ``(vertices (V, 3) float32, faces (F, 3) int32, kept (F,) int32 original face indices)``.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise InputError(f"mesh {name!r}: vertices must have shape (V, 3), got {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3:
        raise InputError(f"mesh {name!r}: faces must have shape (F, 3), got {f.shape}")
    if len(f) == 0 or len(v) == 0:
        raise InputError(f"mesh {name!r} is empty ({len(v)} vertices, {len(f)} faces)")
    if not np.issubdtype(f.dtype, np.integer):
        raise InputError(f"mesh {name!r}: faces must be integer vertex indices, got {f.dtype}")
    if f.min() < 0 or f.max() >= len(v):
        raise InputError(
            f"mesh {name!r}: face indices must lie in [0, {len(v) - 1}], got [{f.min()}, {f.max()}]"
        )
    if not np.isfinite(v).all():
        raise InputError(f"mesh {name!r}: {int((~np.isfinite(v)).any(axis=1).sum())} vertices are not finite")
    scale = max(float(np.ptp(v, axis=0).max()), 1e-9)
    keep = np.empty(len(f), bool)
    chunk = 1 << 16  # faces per pass: 5 MB of temporaries (the corners of a whole city would be gigabytes)
    for lo in range(0, len(f), chunk):
        g = f[lo : lo + chunk]
        a, b, c = v[g[:, 0]], v[g[:, 1]], v[g[:, 2]]
        keep[lo : lo + len(g)] = np.linalg.norm(np.cross(b - a, c - a), axis=1) > 1e-12 * scale * scale
    kept = np.flatnonzero(keep).astype(np.int32)
    if len(kept) == 0:
        raise InputError(f"mesh {name!r}: all {len(f)} triangles are degenerate (zero area)")
    return v.astype(np.float32), np.ascontiguousarray(f[kept], dtype=np.int32), kept


class RayCaster:
    """A scene of triangle meshes that casts batches of rays through Warp BVHs.

    Static geometry goes in one (or a few) large meshes; movable meshes are either moved rigidly with
    :meth:`set_pose` (no rebuild: rays are transformed into the mesh frame) or deformed with
    :meth:`update_vertices` (the BVH is refit, not rebuilt).

    Args:
        device: ``"cpu"`` (default) or ``"cuda[:N]"``.
        threads: CPU worker threads (None or 0: all cores); ignored on CUDA.
    """

    def __init__(self, device: str | None = "cpu", threads: int | None = None):
        self.device = resolve_device(device)
        if threads is not None and threads < 0:
            raise InputError(f"threads must be >= 0 (0 = all cores), got {threads}")
        self.threads = 1 if self.device != "cpu" else int(threads or default_threads())
        self._meshes: list[wp.Mesh | None] = []  # by handle; None once removed
        self._info: list[MeshInfo] = []
        self._poses: list[np.ndarray] = []  # T_world_mesh per mesh, (4, 4)
        self._inv_xforms: list[
            np.ndarray
        ] = []  # inverse pose per mesh as Warp's (px, py, pz, qx, qy, qz, qw)
        self._ids: wp.array | None = None
        self._inv: tuple[wp.array, wp.array] | None = None  # inverse poses, moved flags
        self._region_cache: tuple | None = None  # scene_within's boxes and arrays of the live meshes
        self._boxes: wp.array | None = None  # the live meshes' padded bounds (closest_hit)
        self.meshes_cast = 0  # meshes the last launch within a region visited (diagnostics)
        self._live = np.zeros(0, np.int32)  # handle of each mesh in the arrays the kernels see
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(self.threads) if self.threads > 1 else None
        wp.load_module(device=self.device)

    # ------------------------------------------------------------------ scene
    def add_mesh(self, vertices, faces, *, name: str | None = None, movable: bool = False, pose=None) -> int:
        """Add a triangle mesh (vertices ``(V, 3)`` in its own frame, faces ``(F, 3)``); returns its handle.

        ``pose`` is ``T_world_mesh`` (4×4, default identity).
        """
        built = self.build_mesh(vertices, faces, name=name or f"mesh{len(self._meshes)}")
        return self.insert_mesh(built, movable=movable, pose=pose)

    def build_mesh(
        self, vertices, faces, *, name: str | None = None, trim: bool = False, leaf_size: int | None = None
    ) -> BuiltMesh:
        """The expensive half of :meth:`add_mesh`: check the mesh and build its BVH on this caster's device,
        without touching the scene (safe from another thread while this caster casts: a map's tile loader
        builds tiles in the background); :meth:`insert_mesh` puts it in the scene. ``trim``: give the
        check's temporaries back to the system before the BVH is built, so that the BVH's arrays, which Warp
        allocates larger than it writes, do not land on pages already touched
        (:func:`rangemcl.common.heap.trim_freed_memory`; a map's tiles: 7 % less resident memory).
        ``leaf_size``: triangles per BVH leaf (Warp's default, 4, when None; 8 takes about 13 % less memory
        for the same hits, ``docs/architecture.md``, "Design decisions and why")."""
        name = name or "mesh"
        v, f, kept = clean_mesh(name, vertices, faces)
        if trim:
            trim_freed_memory()
        with wp.ScopedDevice(self.device):
            mesh = wp.Mesh(
                points=wp.array(v, dtype=wp.vec3),
                indices=wp.array(f.ravel(), dtype=wp.int32),
                bvh_leaf_size=leaf_size,
            )
        bounds = np.concatenate([v.min(axis=0), v.max(axis=0)]).astype(np.float64)
        dropped = int(len(faces) - len(kept))
        info = MeshInfo(name, False, len(v), len(f), dropped, kept if dropped else None, bounds=bounds)
        return BuiltMesh(mesh, info)

    def insert_mesh(self, built: BuiltMesh, *, movable: bool = False, pose=None) -> int:
        """Put a mesh from :meth:`build_mesh` in the scene (the thread that casts); returns its handle."""
        if built.mesh.device != self.device:
            raise InputError(f"mesh {built.info.name!r} was built on {built.mesh.device}, not {self.device}")
        with self._lock:
            self._meshes.append(built.mesh)
            self._info.append(replace(built.info, movable=movable))
            self._poses.append(np.eye(4))
            self._inv_xforms.append(np.array([0, 0, 0, 0, 0, 0, 1.0]))
            self._ids = None
            self._inv = None
            self._region_cache = None
            self._boxes = None
            handle = len(self._meshes) - 1
        if pose is not None:
            self.set_pose(handle, pose)
        return handle

    @property
    def meshes(self) -> list[MeshInfo]:
        return list(self._info)

    def _check_handle(self, handle: int) -> MeshInfo:
        if not isinstance(handle, int | np.integer) or not 0 <= handle < len(self._info):
            raise InputError(f"no mesh with handle {handle!r} (the scene has {len(self._info)})")
        if self._info[handle].removed:
            raise InputError(f"mesh {self._info[handle].name!r} (handle {handle}) was removed from the scene")
        return self._info[handle]

    def remove_mesh(self, handle: int) -> None:
        """Take a mesh out of the scene and free its BVH (a map tile leaving the memory budget); the other
        handles stay valid and the handle is never reused."""
        info = self._check_handle(handle)
        with self._lock:
            self._meshes[handle] = None
            info.removed = True
            self._ids = None
            self._inv = None
            self._region_cache = None
            self._boxes = None

    def set_pose(self, handle: int, T_world_mesh) -> None:
        """Place a mesh rigidly in the world (4×4 homogeneous, rotation part orthonormal)."""
        self.set_poses([handle], np.asarray(T_world_mesh, dtype=np.float64)[None])

    def set_poses(self, handles, T_world_meshes) -> None:
        """Place several meshes at once: ``handles`` (K,) and poses ``(K, 4, 4)`` (checked together)."""
        handles = list(handles)
        T = np.asarray(T_world_meshes, dtype=np.float64)
        if T.shape != (len(handles), 4, 4) or not np.isfinite(T).all():
            names = ", ".join(repr(self._check_handle(h).name) for h in handles)
            raise InputError(f"pose of mesh {names} must be a finite 4x4 matrix, got shape {T.shape[1:]}")
        for h in handles:
            self._check_handle(h)
        R = T[:, :3, :3]
        error = np.abs(R @ R.transpose(0, 2, 1) - np.eye(3)).max(axis=(1, 2))
        bad = (error > 1e-5) | (np.linalg.det(R) < 0)
        if bad.any():
            name = self._info[handles[int(np.flatnonzero(bad)[0])]].name
            raise InputError(f"pose of mesh {name!r}: rotation is not orthonormal")
        Ti = invert_rigid(T)
        xforms = np.concatenate([Ti[:, :3, 3], quat_from_matrix(Ti[:, :3, :3])], axis=1)  # (K, 7)
        for h, Tk, xf in zip(handles, T, xforms, strict=True):
            self._poses[h] = Tk
            self._inv_xforms[h] = xf
        self._inv = None
        self._region_cache = None  # (the boxes are in each mesh's own frame: a pose leaves them as they are)

    def update_vertices(self, handle: int, vertices) -> None:
        """Replace a mesh's vertex positions (same count and faces) and refit its BVH."""
        info = self._check_handle(handle)
        v = np.asarray(vertices, dtype=np.float32)
        if v.shape != (info.n_vertices, 3):
            raise InputError(f"mesh {info.name!r}: expected {info.n_vertices} vertices, got shape {v.shape}")
        if not np.isfinite(v).all():
            raise InputError(f"mesh {info.name!r}: new vertices are not finite")
        mesh = self._meshes[handle]
        mesh.points.assign(wp.array(v, dtype=wp.vec3, device=self.device))
        mesh.refit()
        info.bounds = np.concatenate([v.min(axis=0), v.max(axis=0)]).astype(np.float64)
        self._region_cache = None
        self._boxes = None

    def _bounds(self, live) -> np.ndarray:
        """``(M, 6)`` own-frame bounds of the meshes ``live`` (handles); NaN where unknown."""
        return np.array(
            [self._info[h].bounds if self._info[h].bounds is not None else [np.nan] * 6 for h in live],
            np.float64,
        ).reshape(-1, 6)

    def scene_arrays(self) -> tuple[wp.array, wp.array, wp.array, wp.array]:
        """The scene's meshes as the kernels see them: BVH ids, inverse poses, moved flags, padded boxes
        (two rows a mesh, :func:`closest_hit`); mesh ``k`` of these arrays has handle
        ``live_handles[k]``."""
        live = [h for h, m in enumerate(self._meshes) if m is not None]
        if not live:
            raise InputError("the ray-casting scene has no mesh: add one before casting")
        if self._ids is None:
            self._live = np.asarray(live, np.int32)
            self._ids = wp.array([self._meshes[h].id for h in live], dtype=wp.uint64, device=self.device)
        if self._inv is None:
            moved = [0 if np.array_equal(self._poses[h], np.eye(4)) else 1 for h in live]
            self._inv = (
                wp.array(
                    np.asarray([self._inv_xforms[h] for h in live], dtype=np.float32),
                    dtype=wp.transform,
                    device=self.device,
                ),
                wp.array(moved, dtype=wp.int32, device=self.device),
            )
        if self._boxes is None:
            self._boxes = wp.array(padded_boxes(self._bounds(self._live)), dtype=wp.vec3, device=self.device)
        return self._ids, *self._inv, self._boxes

    def scene_within(self, region) -> tuple[wp.array, wp.array, wp.array, wp.array, np.ndarray]:
        """:meth:`scene_arrays` of the meshes that a ray within ``region`` can hit, and their handles:
        ``region`` is a world box ``(6,)`` (xmin, ymin, zmin, xmax, ymax, zmax) that holds every ray of the
        launch from its origin to its end. A mesh whose box lies outside it cannot be hit, so the kernels
        need not visit it (a map held as many tiles: the tiles far from the particles); meshes placed away
        from the identity pose are always kept. Exact: the hits are those of the whole scene."""
        with self._lock:
            ids, inv, moved, boxes = self.scene_arrays()
            live = self._live
            if region is None or not np.isfinite(region).all():
                return ids, inv, moved, boxes, live
            if self._region_cache is None:
                b = self._bounds(live)
                b[np.isnan(b).any(axis=1)] = [-np.inf] * 3 + [np.inf] * 3
                arrays = (ids.numpy(), inv.numpy(), boxes.numpy().reshape(-1, 2, 3))
                self._region_cache = (b, moved.numpy().astype(bool), *arrays)
            b, is_moved, ids_np, inv_np, boxes_np = self._region_cache
        r = np.asarray(region, np.float64)
        pad = 1e-3 + 1e-6 * np.abs(r).max()  # float32 rays: a hit exactly on the region's face still counts
        r = np.concatenate([r[:3] - pad, r[3:] + pad])
        keep = is_moved | ((b[:, :3] <= r[3:]) & (b[:, 3:] >= r[:3])).all(axis=1)
        self.meshes_cast = int(keep.sum())
        if keep.all():
            return ids, inv, moved, boxes, live
        if not keep.any():  # nothing within reach: one mesh all the same (the kernels need one); no hit
            keep[0] = True
        sel = np.flatnonzero(keep)
        dev = self.device
        return (
            wp.array(ids_np[sel], dtype=wp.uint64, device=dev),
            wp.array(inv_np[sel], dtype=wp.transform, device=dev),
            wp.array(is_moved[sel].astype(np.int32), dtype=wp.int32, device=dev),
            wp.array(boxes_np[sel].reshape(-1, 3), dtype=wp.vec3, device=dev),
            live[sel],
        )

    @property
    def live_handles(self) -> np.ndarray:
        """Handle of each mesh in :meth:`scene_arrays`' order."""
        with self._lock:
            self.scene_arrays()
            return self._live.copy()

    # ------------------------------------------------------------------ casting
    def cast(
        self, origins, directions, max_range=np.inf, *, normals: bool = False, only: int | None = None
    ) -> RayHits:
        """Cast N rays and return the closest hit of each.

        Args:
            origins: ``(N, 3)`` ray origins, or one ``(3,)`` origin shared by all rays.
            directions: ``(N, 3)`` directions (normalised inside; must be non-zero).
            max_range: scalar or ``(N,)`` max range in metres (``inf`` allowed, ``<= 0`` gives a miss).
            normals: also return world-frame face normals.
            only: cast against this mesh (a handle) alone, as if the others were not there.
        """
        d = _as_points("directions", directions)
        n = len(d)
        o = _as_points("origins", origins, allow_single=True)
        if len(o) not in (1, n):
            raise InputError(f"origins: expected 1 or {n} rows to match directions, got {len(o)}")
        d = _unit_directions(d)
        r = np.asarray(max_range, dtype=np.float32).reshape(-1)
        if len(r) not in (1, n):
            raise InputError(f"max_range: expected a scalar or {n} values, got {len(r)}")
        if np.isnan(r).any():
            raise InputError(f"max_range[{int(np.flatnonzero(np.isnan(r))[0])}] is NaN")
        ranges = np.empty(n, np.float32)
        mesh_ids = np.empty(n, np.int32)
        face_ids = np.empty(n, np.int32)
        normal_out = np.zeros((n, 3), np.float32) if normals else np.zeros((1, 3), np.float32)
        if n == 0:
            return RayHits(ranges, mesh_ids, face_ids, normal_out if normals else None)
        if only is None:
            ends = o + d * np.where(np.isfinite(r), r, 0.0)[:, None] if len(o) == n else o + d * r.max()
            region = np.concatenate(
                [np.minimum(o.min(axis=0), ends.min(axis=0)), np.maximum(o.max(axis=0), ends.max(axis=0))]
            )
            if not np.isfinite(r).all():
                region = None  # an endless ray: every mesh
            ids, inv, moved, boxes, live = self.scene_within(region)
        else:
            with self._lock:
                ids, inv, moved, boxes = self.scene_arrays()
                live = self._live
        if only is not None:
            self._check_handle(only)
            k = int(np.searchsorted(live, only))
            ids, inv, moved, boxes = (
                ids[k : k + 1],
                inv[k : k + 1],
                moved[k : k + 1],
                boxes[2 * k : 2 * k + 2],
            )
        dev = self.device
        inputs = [
            ids,
            inv,
            moved,
            boxes,
            # on the CPU the kernel reads the numpy buffers in place (they are contiguous float32 here)
            wp.array(o, dtype=wp.vec3, device=dev, copy=dev != "cpu"),
            wp.array(d, dtype=wp.vec3, device=dev, copy=dev != "cpu"),
            wp.array(np.ascontiguousarray(r), dtype=float, device=dev, copy=dev != "cpu"),
            0 if len(o) == 1 else 1,
            0 if len(r) == 1 else 1,
        ]
        if dev == "cpu":
            outs = [
                wp.array(ranges, dtype=float, device=dev, copy=False),
                wp.array(mesh_ids, dtype=wp.int32, device=dev, copy=False),
                wp.array(face_ids, dtype=wp.int32, device=dev, copy=False),
                wp.array(normal_out, dtype=wp.vec3, device=dev, copy=False),
            ]
            self.launch(cast_kernel, n, inputs, outs, [int(normals)])
        else:
            outs = [
                wp.empty(n, dtype=float, device=dev),
                wp.empty(n, dtype=wp.int32, device=dev),
                wp.empty(n, dtype=wp.int32, device=dev),
                wp.zeros(len(normal_out), dtype=wp.vec3, device=dev),
            ]
            self.launch(cast_kernel, n, inputs, outs, [int(normals)])
            ranges, mesh_ids, face_ids, normal_out = (a.numpy() for a in outs)
        if only is not None:
            mesh_ids[mesh_ids >= 0] = only
        else:  # kernel indices to handles (some meshes removed, or left out of the launch)
            hit = mesh_ids >= 0
            mesh_ids[hit] = live[mesh_ids[hit]]
        return RayHits(ranges, mesh_ids, face_ids, normal_out if normals else None)

    def render(self, geometry, T_world_sensor, max_range_m: float = np.inf) -> np.ndarray:
        """Range image ``(H, W)`` float32 seen by a sensor with pixel grid ``geometry``
        (:class:`~rangemcl.rangeimage.RangeImageGeometry`) at pose ``T_world_sensor``; 0 = no return."""
        T = np.asarray(T_world_sensor, dtype=np.float64)
        if T.shape != (4, 4) or not np.isfinite(T).all():
            raise InputError(f"T_world_sensor must be a finite 4x4 matrix, got shape {T.shape}")
        R, t = T[:3, :3], T[:3, 3]
        origins = geometry.origins.reshape(-1, 3) @ R.T + t  # (H*W, 3)
        directions = geometry.directions.reshape(-1, 3) @ R.T
        ranges = self.cast(origins, directions, max_range_m).ranges
        ranges[~np.isfinite(ranges)] = 0.0
        return ranges.reshape(geometry.shape)

    def launch(
        self, kernel, n: int, inputs: list, outputs: list, tail_inputs=(), *, min_chunk: int = 1024
    ) -> None:
        """Launch ``kernel`` over ``n`` items on the caster's device; its inputs are ``inputs``, the first
        item's index (an ``offset``), then ``tail_inputs``. On a GPU one launch; on the CPU contiguous
        chunks of at least ``min_chunk`` items (when there are four chunks' worth), up to four per thread,
        run on the thread pool: Warp's CPU launches are single-threaded."""
        if self.device != "cpu":
            wp.launch(kernel, dim=n, inputs=[*inputs, 0, *tail_inputs], outputs=outputs, device=self.device)
            return
        small = self._pool is None or n < 4 * min_chunk
        n_chunks = 1 if small else min(4 * self.threads, n // min_chunk)
        bounds = np.linspace(0, n, n_chunks + 1).astype(int)

        def run(k: int) -> None:
            lo, hi = int(bounds[k]), int(bounds[k + 1])
            if hi > lo:
                wp.launch(
                    kernel, dim=hi - lo, inputs=[*inputs, lo, *tail_inputs], outputs=outputs, device="cpu"
                )

        if n_chunks == 1:
            run(0)
        else:
            list(self._pool.map(run, range(n_chunks)))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown()
            self._pool = None

    def __del__(self):  # pragma: no cover - best effort, also at interpreter exit when globals are gone
        try:  # noqa: SIM105 - contextlib may already be torn down at exit
            self.close()
        except Exception:
            pass
