"""MuJoCo geoms as triangle meshes for the Warp ray caster: the static world in one mesh, each moving body
in its own.

MuJoCo conventions this module relies on (each checked against ``mujoco.mj_ray`` in
``tests/simbed/sim/test_geometry.py``):

* Geom sizes: plane ``(half x, half y, grid spacing)`` where a half-size ``<= 0`` means infinite along that
  axis; box half-sizes; sphere ``(r,)``; capsule and cylinder ``(r, half length)`` along the geom's z axis;
  ellipsoid semi-axes.
* Mesh vertices (``mesh_vert``) are stored already moved into the geom frame (MuJoCo re-centres each mesh
  on its centroid and turns it to its principal axes, and folds that into ``geom_pos``/``geom_quat``);
  ``mesh_face`` indices are relative to the mesh's ``mesh_vertadr``.
* Height fields: ``hfield_data`` is ``(nrow, ncol)`` row-major, already normalised to [0, 1] by the
  compiler; row ``r`` lies at ``y = -size[1] + 2·size[1]·r/(nrow-1)`` (row 0 at -y), column ``c`` at
  ``x = -size[0] + 2·size[0]·c/(ncol-1)``, elevation ``data·size[2]``; each cell is split along the
  diagonal from its (-x, -y) corner to its (+x, +y) corner. (The MJCF ``elevation`` attribute lists
  its rows from +y down to -y: the compiler flips them, and rescales the values to [0, 1].)
  MuJoCo also closes the field with side walls and a base ``size[3]`` below z = 0; only the surface is
  meshed here.
* ``mj_ray`` hits planes from their front (+z) side only and skips invisible geoms (alpha 0: the
  material's alpha when the geom has a material, else the geom's); the triangles here are hit from both
  sides, and invisible geoms are kept unless ``skip_invisible=True``.

Curved shapes are inscribed polyhedra (every vertex lies on MuJoCo's analytic surface) whose facets stay
within the sagitta ``r·(1 - cos(π/segments))`` of it, ``r`` being the radius (the largest semi-axis for an
ellipsoid).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path

import mujoco
import numpy as np

from rangemcl import meshgen
from rangemcl.common.atomic import file_mode
from rangemcl.errors import InputError

Mesh = tuple[np.ndarray, np.ndarray]

INFINITE_PLANE_HALF_M = 1000.0  # half-extent used for a plane whose MuJoCo size is 0 (infinite)
# Planes are cut into cells no larger than this: Warp intersects in float32, and one 2 km triangle gave
# range errors of 0.2 mm where 100 m cells give 0.02 mm (the float32 rounding of the ray origin itself).
PLANE_CELL_M = 100.0

_GEOM_TYPE_NAMES = {int(v): k.removeprefix("mjGEOM_").lower() for k, v in mujoco.mjtGeom.__members__.items()}


# ---------------------------------------------------------------------- one geom
def sagitta(radius: float, segments: int) -> float:
    """Largest distance (metres) between an analytic curved surface of ``radius`` and its facets."""
    return float(radius) * (1.0 - math.cos(math.pi / segments))


def sphere_bands(segments: int) -> tuple[int, int]:
    """``(n_lat, n_lon)`` of a UV sphere whose facets stay within ``sagitta(r, segments)`` of the sphere.

    A facet's deviation is set by its circumradius; the equatorial cells are the largest, and with
    ``n_lon >= 1.5·segments`` and ``n_lat >= 0.75·segments`` their half-diagonal stays below
    ``r·sin(π/segments)``, the half-chord that gives exactly the sagitta. ``n_lat`` is odd so no ring
    lies on the equator (the capsule cuts the sphere there).
    """
    n_lon = max(3, math.ceil(1.5 * segments))
    n_lat = max(3, math.ceil(0.75 * segments))
    return n_lat + (1 - n_lat % 2), n_lon


def geom_name(model: mujoco.MjModel, geom_id: int) -> str:
    """``geom 'name' (id N)``, or ``geom N`` for an unnamed geom: how errors name a geom."""
    name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, int(geom_id))
    return f"geom {name!r} (id {geom_id})" if name else f"geom {geom_id}"


def _check_segments(segments: int) -> int:
    if isinstance(segments, bool) or not isinstance(segments, int | np.integer) or segments < 3:
        raise InputError(f"segments must be an integer >= 3, got {segments!r}")
    return int(segments)


def _mesh_of_geom(model: mujoco.MjModel, geom_id: int) -> Mesh:
    mesh_id = int(model.geom_dataid[geom_id])
    v0, nv = int(model.mesh_vertadr[mesh_id]), int(model.mesh_vertnum[mesh_id])
    f0, nf = int(model.mesh_faceadr[mesh_id]), int(model.mesh_facenum[mesh_id])
    vertices = np.asarray(model.mesh_vert[v0 : v0 + nv], dtype=np.float64)  # (V, 3), geom frame
    faces = np.asarray(model.mesh_face[f0 : f0 + nf], dtype=np.int32)  # (F, 3), indices from v0
    return vertices.copy(), faces.copy()


def _hfield_of_geom(model: mujoco.MjModel, geom_id: int) -> Mesh:
    hf = int(model.geom_dataid[geom_id])
    nrow, ncol = int(model.hfield_nrow[hf]), int(model.hfield_ncol[hf])
    size_x, size_y, size_z, _base = (float(s) for s in model.hfield_size[hf])
    adr = int(model.hfield_adr[hf])
    elevation = np.asarray(model.hfield_data[adr : adr + nrow * ncol], dtype=np.float64).reshape(nrow, ncol)
    x = np.linspace(-size_x, size_x, ncol)
    y = np.linspace(-size_y, size_y, nrow)
    xx, yy = np.meshgrid(x, y)  # (nrow, ncol): rows along y, columns along x
    vertices = np.stack([xx, yy, elevation * size_z], axis=-1).reshape(-1, 3)
    idx = np.arange(nrow * ncol).reshape(nrow, ncol)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()  # (r, c), (r, c+1)
    c, d = idx[1:, 1:].ravel(), idx[1:, :-1].ravel()  # (r+1, c+1), (r+1, c)
    # both triangles share MuJoCo's diagonal (r, c)-(r+1, c+1); counter-clockwise seen from +z
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return vertices, faces.astype(np.int32)


def geom_triangles(
    model: mujoco.MjModel,
    geom_id: int,
    *,
    segments: int = 32,
    infinite_plane_half_m: float = INFINITE_PLANE_HALF_M,
) -> Mesh:
    """Triangles of one geom in the geom's own frame: ``(vertices (V, 3) float64, faces (F, 3) int32)``.

    Faces wind counter-clockwise seen from outside (normals out of solids, +z for planes and height
    fields). Curved surfaces use ``segments`` facets around a full circle. SDF and other non-collision
    geom types raise ``InputError`` naming the geom.
    """
    segments = _check_segments(segments)
    gid = int(geom_id)
    if not 0 <= gid < model.ngeom:
        raise InputError(f"no geom with id {geom_id!r} (the model has {model.ngeom})")
    gtype = int(model.geom_type[gid])
    size = np.asarray(model.geom_size[gid], dtype=np.float64)
    G = mujoco.mjtGeom
    if gtype == G.mjGEOM_PLANE:
        hx = size[0] if size[0] > 0 else infinite_plane_half_m
        hy = size[1] if size[1] > 0 else infinite_plane_half_m
        nu, nv = (max(1, math.ceil(2 * h / PLANE_CELL_M)) for h in (hx, hy))
        return meshgen.grid_patch((-hx, -hy, 0.0), (2 * hx, 0.0, 0.0), (0.0, 2 * hy, 0.0), nu, nv)
    if gtype == G.mjGEOM_BOX:
        return meshgen.box(2.0 * size)
    if gtype in (G.mjGEOM_SPHERE, G.mjGEOM_ELLIPSOID, G.mjGEOM_CAPSULE):
        n_lat, n_lon = sphere_bands(segments)
        if gtype == G.mjGEOM_ELLIPSOID:  # affine image of the unit sphere: radial gap <= sagitta(max axis)
            v, f = meshgen.uv_sphere(1.0, n_lat=n_lat, n_lon=n_lon)
            return v * size, f
        v, f = meshgen.uv_sphere(size[0], n_lat=n_lat, n_lon=n_lon)
        if gtype == G.mjGEOM_CAPSULE:  # pull the hemispheres apart: the equator band becomes the side
            v[:, 2] += np.sign(v[:, 2]) * size[1]
        return v, f
    if gtype == G.mjGEOM_CYLINDER:
        return meshgen.cylinder(size[0], 2.0 * size[1], segments=segments)
    if gtype == G.mjGEOM_MESH:
        return _mesh_of_geom(model, gid)
    if gtype == G.mjGEOM_HFIELD:
        return _hfield_of_geom(model, gid)
    kind = _GEOM_TYPE_NAMES.get(gtype, str(gtype))
    raise InputError(f"{geom_name(model, gid)} has type {kind!r}, which cannot be turned into triangles")


# ---------------------------------------------------------------------- poses
def _pose(pos, mat) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.asarray(mat, dtype=np.float64).reshape(3, 3)
    T[:3, 3] = pos
    return T


def geom_pose(model: mujoco.MjModel, data: mujoco.MjData, geom_id: int) -> np.ndarray:
    """``T_world_geom`` (4, 4) from ``data.geom_xpos``/``geom_xmat`` (valid after ``mj_kinematics``)."""
    del model  # the pose lives in data; model is taken for symmetry with the other helpers
    return _pose(data.geom_xpos[geom_id], data.geom_xmat[geom_id])


def body_pose(data: mujoco.MjData, body_id: int) -> np.ndarray:
    """``T_world_body`` (4, 4) of a body's frame (``data.xpos``/``xmat``, not its inertial frame)."""
    return _pose(data.xpos[body_id], data.xmat[body_id])


def geom_in_body(model: mujoco.MjModel, geom_id: int) -> np.ndarray:
    """``T_body_geom`` (4, 4): the geom's fixed pose in its body's frame (``geom_pos``, ``geom_quat``)."""
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(model.geom_quat[geom_id], dtype=np.float64))
    return _pose(model.geom_pos[geom_id], mat)


# ---------------------------------------------------------------------- whole model
@dataclass
class BodyMesh:
    """All kept geoms of one moving body, merged, in that body's frame (pose: :func:`body_pose`)."""

    body_id: int
    name: str
    vertices: np.ndarray  # (V, 3) float64, body frame
    faces: np.ndarray  # (F, 3) int32
    geom_ids_per_face: np.ndarray  # (F,) int32 geom each face came from


@dataclass
class ModelTriangles:
    """A MuJoCo model as triangles: the static world in one mesh, each moving body in its own.

    ``static`` is ``(vertices (V, 3) world frame, faces (F, 3) int32, geom_ids_per_face (F,) int32)``,
    empty arrays when nothing is static. Build it with :func:`split_static_dynamic`.
    """

    static: tuple[np.ndarray, np.ndarray, np.ndarray]
    dynamic: list[BodyMesh] = field(default_factory=list)

    def add_to(self, caster, data: mujoco.MjData | None = None) -> tuple[int | None, dict[int, int]]:
        """Add every mesh to a ``rangemcl.raycast.RayCaster``: the static one fixed, the bodies movable.

        Returns ``(static handle or None when empty, {body_id: handle})``; bodies are placed at their
        pose in ``data`` when given (then call :meth:`update_poses` after each step).
        """
        static_handle = None
        if len(self.static[1]):
            static_handle = caster.add_mesh(self.static[0], self.static[1], name="static")
        handles = {}
        for body in self.dynamic:
            pose = None if data is None else body_pose(data, body.body_id)
            handles[body.body_id] = caster.add_mesh(
                body.vertices, body.faces, name=body.name, movable=True, pose=pose
            )
        return static_handle, handles

    @staticmethod
    def update_poses(caster, handles: dict[int, int], data: mujoco.MjData) -> None:
        """Move each body's mesh to its pose in ``data`` (after ``mj_forward`` or ``mj_step``)."""
        for body_id, handle in handles.items():
            caster.set_pose(handle, body_pose(data, body_id))


def excluded_bodies(model: mujoco.MjModel, exclude_bodies: Iterable[int]) -> np.ndarray:
    """``(nbody,)`` bool: the bodies in ``exclude_bodies`` and every descendant of them."""
    roots = {int(b) for b in exclude_bodies}
    bad = [b for b in roots if not 0 <= b < model.nbody]
    if bad:
        raise InputError(f"exclude_bodies: no body with id {bad[0]} (the model has {model.nbody})")
    out = np.zeros(model.nbody, dtype=bool)
    for b in range(model.nbody):  # parents always have smaller ids than their children
        out[b] = b in roots or (b > 0 and out[int(model.body_parentid[b])])
    return out


def is_invisible(model: mujoco.MjModel, geom_id: int) -> bool:
    """Alpha 0 as ``mj_ray`` reads it: the material's alpha when the geom has a material, else the geom's."""
    mat = int(model.geom_matid[geom_id])
    alpha = model.mat_rgba[mat, 3] if mat >= 0 else model.geom_rgba[geom_id, 3]
    return bool(alpha == 0)


def _merge_geoms(parts: list[tuple[int, Mesh]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    vertices, faces = meshgen.merge([mesh for _, mesh in parts])
    gids = np.concatenate(
        [np.full(len(f), gid, np.int32) for gid, (_, f) in parts] or [np.zeros(0, np.int32)]
    )
    return vertices.astype(np.float64), faces.astype(np.int32), gids


def split_static_dynamic(
    model: mujoco.MjModel,
    data: mujoco.MjData | None = None,
    *,
    exclude_bodies: Iterable[int] = (),
    include_geom: Callable[[int], bool] = lambda gid: True,
    segments: int = 32,
    skip_invisible: bool = False,
    infinite_plane_half_m: float = INFINITE_PLANE_HALF_M,
) -> ModelTriangles:
    """Triangulate a model: geoms of bodies welded to the world (``body_weldid == 0``) merged in the
    world frame, and one mesh per other body (free, jointed or mocap) in that body's frame.

    Bodies in ``exclude_bodies`` and all their descendants are left out (the ego car), as are geoms with
    ``include_geom(gid)`` false and, with ``skip_invisible``, geoms ``mj_ray`` would not see (alpha 0).
    World poses of static geoms come from ``data`` when it has been forwarded, else from a private
    ``mj_kinematics`` (static poses do not depend on the state).
    """
    segments = _check_segments(segments)
    if data is None or not np.any(data.xmat[0]):  # never forwarded: xmat is all zeros
        data = mujoco.MjData(model)
        mujoco.mj_kinematics(model, data)
    excluded = excluded_bodies(model, exclude_bodies)
    static_parts: list[tuple[int, Mesh]] = []
    body_parts: dict[int, list[tuple[int, Mesh]]] = {}
    for gid in range(model.ngeom):
        body = int(model.geom_bodyid[gid])
        if excluded[body] or not include_geom(gid) or (skip_invisible and is_invisible(model, gid)):
            continue
        mesh = geom_triangles(model, gid, segments=segments, infinite_plane_half_m=infinite_plane_half_m)
        if int(model.body_weldid[body]) == 0:
            static_parts.append((gid, meshgen.transform(mesh, geom_pose(model, data, gid))))
        else:
            body_parts.setdefault(body, []).append((gid, meshgen.transform(mesh, geom_in_body(model, gid))))
    dynamic = []
    for body, parts in sorted(body_parts.items()):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, body) or f"body{body}"
        dynamic.append(BodyMesh(body, name, *_merge_geoms(parts)))
    return ModelTriangles(static=_merge_geoms(static_parts), dynamic=dynamic)


# ---------------------------------------------------------------------- files
def write_ply(path, vertices, faces) -> Path:
    """Write a triangle mesh as binary PLY (float64 positions, through Open3D's legacy writer, which keeps
    them exact), atomically; an unwritable path is an ``InputError`` naming it."""
    import os
    import tempfile

    import open3d as o3d

    path = Path(path)
    if not path.parent.is_dir():
        why = "is not a folder" if path.parent.exists() else "does not exist"
        raise InputError(f"cannot write {path}: {path.parent} {why}")
    mesh = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.ascontiguousarray(vertices, np.float64).reshape(-1, 3)),
        o3d.utility.Vector3iVector(np.ascontiguousarray(faces, np.int32).reshape(-1, 3)),
    )
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".ply")
    os.close(fd)
    try:
        ok = o3d.io.write_triangle_mesh(tmp, mesh, write_ascii=False, compressed=False)
        if not ok:
            raise InputError(f"cannot write {path}")
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, file_mode())
        os.replace(tmp, path)
        tmp = None
    except OSError as err:
        raise InputError(f"cannot write {path}: {err.strerror or err}") from None
    finally:
        if tmp is not None:
            Path(tmp).unlink(missing_ok=True)
    return path


def export_static_mesh(model: mujoco.MjModel, path, **kw) -> Path:
    """Write the static part of a model (the scene's ground-truth mesh, world frame) as binary PLY.

    ``kw`` are passed to :func:`split_static_dynamic` (``exclude_bodies``, ``include_geom``, ``segments``...).
    """
    vertices, faces, _ = split_static_dynamic(model, kw.pop("data", None), **kw).static
    if len(faces) == 0:
        raise InputError(f"cannot write {path}: the model has no static geometry")
    return write_ply(path, vertices, faces)
