"""``simbed import-scene``: a static triangle mesh (a city model, a photogrammetry, a map from ``rangemcl
build-map``) becomes a drivable MJCF scene.

The LiDAR sees the whole mesh, exactly: it goes into the scene as mesh geoms (binary STL files, cut into
pieces of at most ``max_piece_faces`` triangles by a quadtree over x/y, so that no single mesh gets
unwieldy for MuJoCo's compiler), collision-free. MuJoCo collides meshes through their convex hulls,
which would fill every street of a city, so the car drives on a **height field** sampled from the mesh's
ground instead (:class:`simbed.scenes.scene_ground.SceneGround`: the lowest surface a car can stand on under
each cell), a geom in the collision-only group :data:`COLLISION_ONLY_GROUP` that the LiDAR, ``export-mesh``
and renders leave out. Files written next to ``OUT.xml``: ``OUT_meshes/piece_NNN.stl`` and
``OUT_ground.bin`` (the town terrain's format: int32 rows, int32 columns, float32 heights in [0, 1]).

What the surfaces are made of, for the realistic sensor (:mod:`simbed.sim.materials`): ``material`` for
the whole mesh, and ``face_materials`` (a text file, one material name per face, in the mesh's face order)
to override it face by face. Each piece then holds faces of one material only, and ``OUT.materials.yaml``
names each piece's material.
"""

from __future__ import annotations

import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rangemcl.common.atomic import atomic_write
from rangemcl.common.outdir import check_output_files, output_files
from rangemcl.errors import InputError
from simbed.sim.world import COLLISION_ONLY_GROUP

MESH_SUFFIXES = (".obj", ".ply", ".stl", ".glb", ".gltf", ".off")
MAX_GROUND_CELLS = 16_000_000


@dataclass
class ImportReport:
    out: Path
    triangles: int
    vertices: int
    pieces: int
    ground_shape: tuple[int, int]
    ground_cell_m: float
    ground_cells_without_ground: int
    extent: tuple[float, float, float, float, float, float]
    seconds: float


def load_world_mesh(
    path: str | Path, *, scale: float = 1.0, up: str = "auto"
) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(V, 3)`` (z up, metres) and faces ``(F, 3)`` of a mesh file, every problem one
    :class:`InputError` naming the file: not a mesh, no triangle, non-finite vertices, bad indices."""
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such file" if not path.exists() else f"{path}: not a file")
    if path.suffix.lower() not in MESH_SUFFIXES:
        raise InputError(f"{path}: not a mesh file (expected one of {', '.join(MESH_SUFFIXES)})")
    if not (isinstance(scale, int | float) and math.isfinite(scale) and scale > 0):
        raise InputError(f"--scale {scale!r}: expected a number above 0")
    if up not in ("auto", "z", "y"):
        raise InputError(f"--up {up!r}: expected auto, z or y")
    try:
        mesh = trimesh.load(str(path), force="mesh", process=False)
    except Exception as err:  # trimesh raises many kinds for a bad file
        detail = " ".join(str(err).split()) or type(err).__name__
        raise InputError(f"{path}: not a mesh trimesh can read ({detail[:200]})") from None
    v = np.asarray(getattr(mesh, "vertices", np.zeros((0, 3))), np.float64)
    f = np.asarray(getattr(mesh, "faces", np.zeros((0, 3))), np.int64)
    if f.ndim != 2 or len(f) == 0 or f.shape[1] != 3:
        raise InputError(f"{path}: holds no triangles")
    if f.min() < 0 or f.max() >= len(v):
        raise InputError(f"{path}: face indices out of range (the file has {len(v)} vertices)")
    bad = ~np.isfinite(v).all(axis=1)
    if bad.any():
        raise InputError(f"{path}: {int(bad.sum())} of {len(v)} vertices are not finite (NaN or inf)")
    if up == "y" or (up == "auto" and path.suffix.lower() in (".glb", ".gltf")):
        v = np.stack([v[:, 0], -v[:, 2], v[:, 1]], axis=1)  # glTF's y up -> z up
    v = v * float(scale)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    keep = np.linalg.norm(np.cross(b - a, c - a), axis=1) > 1e-12  # degenerate triangles carry nothing
    if not keep.any():
        raise InputError(f"{path}: every triangle is degenerate (zero area)")
    return v, f[keep]


def split_pieces(v: np.ndarray, f: np.ndarray, max_faces: int) -> list[np.ndarray]:
    """Face indices of each piece: a quadtree over the faces' centroids in x/y, split until every piece
    holds at most ``max_faces`` faces."""
    centre = v[f].mean(axis=1)[:, :2]
    out: list[np.ndarray] = []
    stack = [np.arange(len(f))]
    while stack:
        idx = stack.pop()
        if len(idx) <= max_faces:
            out.append(idx)
            continue
        c = centre[idx]
        mid = np.median(c, axis=0)
        quad = (c[:, 0] > mid[0]).astype(int) + 2 * (c[:, 1] > mid[1]).astype(int)
        parts = [idx[quad == q] for q in range(4) if (quad == q).any()]
        if len(parts) == 1:  # all centroids coincide: cut by count
            parts = np.array_split(idx, math.ceil(len(idx) / max_faces))
        stack.extend(parts)
    return sorted(out, key=lambda p: int(p.min()))


def _binary_stl(v: np.ndarray, f: np.ndarray) -> bytes:
    tri = v[f].astype("<f4")  # (F, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)
    rec = np.zeros(len(f), dtype=[("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    rec["n"], rec["v"] = n, tri
    return b"simbed import-scene".ljust(80, b" ") + np.uint32(len(f)).tobytes() + rec.tobytes()


def ground_grid(
    v: np.ndarray, f: np.ndarray, cell_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Heights ``(rows, cols)`` of the mesh's ground at cell centres (x along columns, y along rows from
    the lowest y), their x and y, and how many cells had none (filled with the lowest ground)."""
    from rangemcl.raycast import RayCaster
    from simbed.scenes.scene_ground import SceneGround

    lo, hi = v.min(axis=0), v.max(axis=0)
    cells = math.ceil((hi[0] - lo[0]) / cell_m + 1) * math.ceil((hi[1] - lo[1]) / cell_m + 1)
    if cells > MAX_GROUND_CELLS:
        cell_m *= math.sqrt(cells / MAX_GROUND_CELLS)
    xs = np.arange(lo[0], hi[0] + cell_m, cell_m)
    ys = np.arange(lo[1], hi[1] + cell_m, cell_m)
    caster = RayCaster(threads=None)
    handle = caster.add_mesh(v, f, name="world")
    ground = SceneGround(caster, handle, float(hi[2]), float(lo[2]))
    z = np.empty((len(ys), len(xs)))
    for r in range(0, len(ys), 64):  # rows in batches: bounded memory for large worlds
        gx, gy = np.meshgrid(xs, ys[r : r + 64])
        z[r : r + 64] = ground.height(gx, gy)
    caster.close()
    missing = ~np.isfinite(z)
    if missing.all():
        raise InputError("the mesh has no surface a car can stand on (no upward face with 2 m free above)")
    z[missing] = np.nanmin(z)
    return z, xs, ys, int(missing.sum())


def _face_materials(n_faces: int, material: str | None, path) -> np.ndarray | None:
    """Each face's material name (None when neither is given); every problem one InputError line."""
    from simbed.sim.materials import MaterialTable

    if material is None and path is None:
        return None
    table = MaterialTable.load()
    if material is not None:
        table.id(material, "--material")
    names = np.full(n_faces, material or "unknown", dtype=object)
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise InputError(f"{path}: no such file (--face-materials: one material name per face)")
        lines = [ln.strip() for ln in path.read_text(encoding="utf-8", errors="replace").splitlines()]
        lines = [ln for ln in lines if ln and not ln.startswith("#")]
        if len(lines) != n_faces:
            raise InputError(
                f"{path}: {len(lines)} material names for a mesh of {n_faces} faces (one per face)"
            )
        for i, name in enumerate(lines):
            if name not in table.index:
                table.id(name, f"{path}: face {i}")
        names[:] = lines
    return names


def import_scene(
    world_file: str | Path,
    out: str | Path,
    *,
    scale: float = 1.0,
    up: str = "auto",
    ground_cell_m: float = 0.5,
    max_piece_faces: int = 200_000,
    overwrite: bool = False,
    material: str | None = None,
    face_materials: str | Path | None = None,
) -> ImportReport:
    """Write ``out`` (an MJCF file) and its mesh pieces and ground height field from ``world_file``, and
    with ``material`` or ``face_materials`` its materials sidecar ``OUT.materials.yaml``."""
    clock = time.perf_counter()
    out = Path(out)
    if out.suffix.lower() != ".xml":
        raise InputError(f"{out}: the scene to write must be an .xml file")
    if not (math.isfinite(ground_cell_m) and ground_cell_m > 0):
        raise InputError(f"--ground-cell {ground_cell_m}: expected metres above 0")
    if max_piece_faces < 1000:
        raise InputError(f"--max-piece-faces {max_piece_faces}: expected at least 1000")
    pieces_dir = out.with_name(out.stem + "_meshes")
    ground_file = out.with_name(out.stem + "_ground.bin")
    sidecar = out.with_suffix(".materials.yaml")
    existing = [p for p in (out, pieces_dir, ground_file, sidecar) if p.exists()]
    if existing and not overwrite:
        raise InputError(f"{existing[0]}: exists (give --overwrite to replace the imported scene)")
    check_output_files([out], overwrite=True, what="the scene")  # a folder, under a file, not writable
    v, f = load_world_mesh(world_file, scale=scale, up=up)
    face_mat = _face_materials(len(f), material, face_materials)
    z, xs, ys, missing = ground_grid(v, f, ground_cell_m)
    parts, part_mat = [], []
    for name in sorted(set(face_mat)) if face_mat is not None else [None]:
        mine = np.arange(len(f)) if name is None else np.flatnonzero(face_mat == name)
        for idx in split_pieces(v, f[mine], max_piece_faces):
            parts.append(mine[idx])
            part_mat.append(name)

    with output_files([out], overwrite=True, what="the scene"):  # folders missing above it are made
        tmp_dir = out.with_name(f".{out.stem}_meshes.tmp")
        shutil.rmtree(tmp_dir, ignore_errors=True)
        tmp_dir.mkdir()
        names = []
        try:
            for k, idx in enumerate(parts):
                used, local = np.unique(f[idx], return_inverse=True)
                name = f"piece_{k:03d}.stl"
                (tmp_dir / name).write_bytes(_binary_stl(v[used], local.reshape(-1, 3)))
                names.append(name)
            z_min, z_max = float(z.min()), float(z.max())
            z_range = max(z_max - z_min, 1e-3)
            data = ((z - z_min) / z_range).astype("<f4")
            ground_bytes = np.array(data.shape, "<i4").tobytes() + data.tobytes()
            if pieces_dir.exists():
                shutil.rmtree(pieces_dir)
            tmp_dir.rename(pieces_dir)
        except BaseException:
            shutil.rmtree(tmp_dir, ignore_errors=True)
            raise
        atomic_write(ground_file, ground_bytes)
        cx, cy = (xs[0] + xs[-1]) / 2, (ys[0] + ys[-1]) / 2
        hx, hy = max((xs[-1] - xs[0]) / 2, 1e-3), max((ys[-1] - ys[0]) / 2, 1e-3)
        lo, hi = v.min(axis=0), v.max(axis=0)
        extent = float(max(hi - lo)) / 2
        lines = [
            f'<mujoco model="{out.stem}">',
            f"  <!-- made by simbed import-scene from {Path(world_file).name} (scale {scale:g}, up {up});",
            f"       the meshes are what the LiDAR sees, the height field (group {COLLISION_ONLY_GROUP},",
            "       invisible) what the car drives on -->",
            '  <option timestep="0.002"/>',
            f'  <statistic center="{cx:.3f} {cy:.3f} {(lo[2] + hi[2]) / 2:.3f}" extent="{extent:.3f}"/>',
            "  <visual>",
            '    <global offwidth="1280" offheight="960"/>',
            '    <headlight ambient="0.35 0.35 0.35" diffuse="0.55 0.55 0.55" specular="0.1 0.1 0.1"/>',
            f'    <map znear="0.0005" zfar="{max(8.0, 4 * extent / 100):.1f}" haze="0.2"/>',
            "  </visual>",
            "  <asset>",
            f'    <hfield name="simbed_ground" file="{ground_file.name}"',
            f'            size="{hx:.4f} {hy:.4f} {z_range:.6f} 1"/>',
        ]
        lines += [
            f'    <mesh name="world_{k:03d}" file="{pieces_dir.name}/{n}" inertia="shell"/>'
            for k, n in enumerate(names)
        ]
        lines += [
            "  </asset>",
            "  <worldbody>",
            '    <light name="sun" directional="true" pos="0 0 200" dir="-0.3 -0.4 -1" '
            'diffuse="0.5 0.5 0.5"/>',
            '    <geom name="simbed_ground" type="hfield" hfield="simbed_ground"',
            f'          pos="{cx:.4f} {cy:.4f} {z_min:.6f}"',
            f'          group="{COLLISION_ONLY_GROUP}" rgba="0.5 0.5 0.5 0" contype="1" conaffinity="0"/>',
        ]
        lines += [
            f'    <geom name="world_{k:03d}" type="mesh" mesh="world_{k:03d}" contype="0" conaffinity="0" '
            'rgba="0.62 0.62 0.6 1"/>'
            for k in range(len(names))
        ]
        lines += ["  </worldbody>", "</mujoco>", ""]
        atomic_write(out, "\n".join(lines))
        if face_mat is not None:
            rows = [
                f"# materials of {out.name}'s mesh pieces (simbed import-scene); see simbed/sim/materials.py"
            ]
            rows.append(f"default: {material or 'unknown'}")
            rows.append("geoms:")
            rows += [f"  world_{k:03d}: {m}" for k, m in enumerate(part_mat)]
            atomic_write(sidecar, "\n".join(rows) + "\n")
        elif sidecar.exists():
            sidecar.unlink()  # an earlier import's, replaced with --overwrite
        return ImportReport(
            out=out,
            triangles=len(f),
            vertices=len(np.unique(f)),
            pieces=len(names),
            ground_shape=z.shape,
            ground_cell_m=float(xs[1] - xs[0]) if len(xs) > 1 else ground_cell_m,
            ground_cells_without_ground=missing,
            extent=(*map(float, lo), *map(float, hi)),
            seconds=time.perf_counter() - clock,
        )
