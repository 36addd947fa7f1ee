"""The mesh map (``rangemcl.maps.meshmap``): tiling, ground grid, ground labels, disk round trips,
import, and every error path.

Expected values come from this file: tiles from ``floor((centroid - floor(min / s)·s) / s)`` computed
here, heights from the analytic plane, PLY files written by trimesh (not by the code under test) and read
back by trimesh and Open3D.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest
import trimesh
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from rangemcl.errors import InputError
from rangemcl.maps.meshmap import (
    GroundGrid,
    MeshMap,
    import_mesh,
    label_ground_vertices,
    map_summary,
    read_ply_binary,
)
from rangemcl.maps.store import TileStore

GROUND = (128, 128, 128)
OTHER = (200, 120, 60)

# --- independent helpers ---------------------------------------------------------------------------------


def random_mesh(rng: np.random.Generator, n_faces: int, span: float, offset: np.ndarray):
    """Random triangles (shared vertices) over ``span`` metres from ``offset``; some long ones straddle."""
    nv = max(3, n_faces)
    v = offset + rng.uniform(0, span, (nv, 3)) * [1, 1, 0.02]
    # small triangles near a random vertex, plus some long ones (vertices anywhere)
    f = np.array([rng.choice(nv, 3, replace=False) for _ in range(n_faces)])  # (F, 3), distinct corners
    near = rng.random(n_faces) < 0.7
    anchors = rng.integers(0, nv, near.sum())
    extra = v[anchors] + rng.normal(0, 3.0, (near.sum(), 3))
    v = np.vstack([v, extra])
    f[near, 1] = nv + np.arange(near.sum())
    return v, f


def grid_plane(nx: int, ny: int, z_of_xy, step: float = 1.0, x0: float = 0.0, y0: float = 0.0):
    """Vertices at cell centres ``(x0 + (i + .5) step, y0 + (j + .5) step)``, two triangles per quad."""
    xs = x0 + (np.arange(nx) + 0.5) * step
    ys = y0 + (np.arange(ny) + 0.5) * step
    X, Y = np.meshgrid(xs, ys)  # (ny, nx)
    v = np.stack([X.ravel(), Y.ravel(), z_of_xy(X.ravel(), Y.ravel())], axis=1)
    idx = np.arange(nx * ny).reshape(ny, nx)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, 1:].ravel(), idx[1:, :-1].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return v, f


def box(lo, hi):
    """Closed axis-aligned box, outward-facing triangles."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    v = np.array([[x, y, z] for z in (lo[2], hi[2]) for y in (lo[1], hi[1]) for x in (lo[0], hi[0])])
    f = np.array(
        [
            [0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6],  # bottom, top
            [0, 1, 4], [1, 5, 4], [2, 6, 3], [3, 6, 7],  # y-, y+
            [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5],  # x-, x+
        ]
    )  # fmt: skip
    return v, f


def write_trimesh_ply(path: Path, v, f, rgb=None, encoding="binary"):
    mesh = trimesh.Trimesh(v, f, vertex_colors=rgb, process=False)
    path.write_bytes(trimesh.exchange.ply.export_ply(mesh, encoding=encoding))


# --- tiles -----------------------------------------------------------------------------------------------


@settings(max_examples=25, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_faces=st.integers(1, 300),
    tile=st.sampled_from([7.0, 25.0, 100.0, 33.3]),
    offset=st.tuples(st.floats(-1e4, 1e4), st.floats(-1e4, 1e4)),
)
def test_tiles_partition_the_mesh(seed, n_faces, tile, offset):
    rng = np.random.default_rng(seed)
    v, f = random_mesh(rng, n_faces, span=3.5 * tile, offset=np.array([*offset, 0.0]))
    m = MeshMap.from_mesh(v, f, np.zeros(len(v), bool), tile_size_m=tile)

    origin = np.floor(v[:, :2].min(axis=0) / tile) * tile
    np.testing.assert_array_equal(m.tile_origin_xy, origin)
    centroid = v[f].mean(axis=1)[:, :2]
    ij = np.floor((centroid - origin) / tile).astype(int)
    expected_tiles = sorted({tuple(t) for t in ij})
    assert [tuple(t) for t in m.tiles] == expected_tiles
    np.testing.assert_array_equal(m.tiles[m.face_tile], ij)

    # union of tile_faces is all faces, each once; each tile's faces are exactly those with its (i, j)
    parts = [m.tile_faces([k]) for k in range(len(m.tiles))]
    allf = np.concatenate(parts)
    assert len(allf) == len(f)
    np.testing.assert_array_equal(np.sort(allf), np.arange(len(f)))
    for k, p in enumerate(parts):
        np.testing.assert_array_equal(p, np.flatnonzero((ij == m.tiles[k]).all(axis=1)))
    np.testing.assert_array_equal(m.tile_faces(np.arange(len(m.tiles))), np.arange(len(f)))

    # tile_at: direct floor computation and a lookup table
    lookup = {tuple(t): k for k, t in enumerate(m.tiles)}
    q = origin + rng.uniform(-tile, 4.5 * tile, (200, 2))
    qij = np.floor((q - origin) / tile).astype(int)
    want = [lookup.get(tuple(t), -1) for t in qij]
    np.testing.assert_array_equal(m.tile_at(q[:, 0], q[:, 1]), want)
    np.testing.assert_array_equal(m.tile_at(centroid[:, 0], centroid[:, 1]), m.face_tile)

    # bounds hold the centroids; submesh holds the same triangles
    k = int(m.face_tile[0])
    xmin, ymin, xmax, ymax = m.tile_bounds(k)
    inside = m.tile_faces(k)
    assert np.all((centroid[inside] >= [xmin, ymin]) & (centroid[inside] < [xmax, ymax]))
    sv, sf = m.submesh([k])
    np.testing.assert_array_equal(sv[sf], v[f[inside]])
    assert len(np.unique(sf)) == len(sv)


def test_straddling_faces_go_by_centroid_and_bounds():
    # tile 10 m, origin 0: a triangle from x=1 to x=19 with centroid x = 13 belongs to tile (1, 0)
    v = np.array([[1.0, 1, 0], [19, 1, 0], [19, 2, 0], [0, 0, 0], [2, 0, 0], [2, 2, 0], [25, 0, 0]])
    f = np.array([[0, 1, 2], [3, 4, 5]])
    m = MeshMap.from_mesh(v, f, tile_size_m=10.0)
    np.testing.assert_array_equal(m.tiles, [[0, 0], [1, 0]])
    np.testing.assert_array_equal(m.face_tile, [1, 0])
    assert m.tile_bounds(1) == (10.0, 0.0, 20.0, 10.0)
    # vertex 6 (unused) lies in tile (2, 0), which holds no face: no tile there
    assert m.tile_at(25.0, 5.0) == -1
    assert list(m.tile_at([5.0, 15.0, -1.0, np.nan], [5.0, 5.0, 5.0, 5.0])) == [0, 1, -1, -1]
    assert m.extent == (0.0, 0.0, 0.0, 25.0, 2.0, 0.0)
    assert (m.n_triangles, m.n_vertices) == (2, 7)
    with pytest.raises(IndexError):
        m.tile_faces([2])
    assert len(m.tile_faces([])) == 0


# --- ground grid -----------------------------------------------------------------------------------------


def test_ground_grid_is_exact_on_a_sloped_plane():
    v, f = grid_plane(30, 20, lambda x, y: 0.1 * x, x0=-10.0, y0=5.0)
    m = MeshMap.from_mesh(v, f, ground_cell_m=1.0)  # labels by the rule: a 5.7° slope is ground
    assert m.is_ground.all()
    g = m.ground
    assert g.shape == (20, 30) and g.measured.all()
    np.testing.assert_array_equal(g.origin_xy, [-10.0, 5.0])
    rng = np.random.default_rng(1)
    x = rng.uniform(-9.5, 19.5, 500)  # inside the hull of cell centres
    y = rng.uniform(5.5, 24.5, 500)
    np.testing.assert_allclose(g.height_at(x, y), 0.1 * x, atol=1e-5)
    # outside: the nearest edge value (clamped to the outermost cell centres)
    np.testing.assert_allclose(g.height_at([-50.0, 100.0], [0.0, 100.0]), [0.1 * -9.5, 0.1 * 19.5], atol=1e-5)
    assert g.height_at(np.zeros((3, 4)), np.zeros((3, 4))).shape == (3, 4)
    assert np.isnan(g.height_at(np.nan, 0.0))


def test_ground_grid_median_and_nan_filling():
    v = np.array(
        [
            *([0.5, 0.5, 1.0], [0.6, 0.4, 2.0], [0.4, 0.6, 10.0]),  # cell (0, 0): median 2
            *([3.5, 0.5, 1.0], [3.5, 0.5, 2.0], [3.5, 0.5, 3.0], [3.5, 0.5, 10.0]),  # cell (3, 0): 2.5
            [3.5, 2.5, 99.0],  # not ground
        ]
    )
    g = GroundGrid.from_vertices(v, np.arange(len(v)) < 7, cell_m=1.0)
    assert g.shape == (3, 4)
    np.testing.assert_array_equal(g.measured, [[1, 0, 0, 1], [0, 0, 0, 0], [0, 0, 0, 0]])
    np.testing.assert_array_equal(g.heights[0, [0, 3]], [2.0, 2.5])
    assert np.isnan(g.heights[1:, :]).all()
    # unmeasured cell centres take the nearest measured cell's value; between centres, bilinear
    assert g.height_at(1.5, 0.5) == 2.0 and g.height_at(2.5, 0.5) == 2.5
    assert g.height_at(0.5, 2.5) == 2.0 and g.height_at(3.5, 2.5) == 2.5
    np.testing.assert_allclose(g.height_at(2.0, 0.5), 2.25)
    # a hand-made grid: NaN cells filled from the nearest known cell, outside = edge
    h = np.array([[np.nan, 1.0, np.nan], [np.nan, np.nan, np.nan], [3.0, np.nan, np.nan]], np.float32)
    g2 = GroundGrid(np.array([10.0, 20.0]), 2.0, h)
    np.testing.assert_array_equal(g2.filled, [[1, 1, 1], [3, 1, 1], [3, 3, 3]])  # by distance
    assert g2.height_at(11.0, 21.0) == 1.0 and g2.height_at(0.0, 100.0) == 3.0
    # nothing measured: NaN everywhere
    assert np.isnan(GroundGrid.from_vertices(v, np.zeros(len(v), bool)).height_at(0.5, 0.5))


def test_ground_rule_keeps_roofs_and_walls_out():
    pv, pf = grid_plane(10, 10, lambda x, y: 0.02 * y)
    bv, bf = box([3.2, 3.2, 0.0], [6.8, 6.8, 2.0])  # sits on the plane; its cells hold plane vertices
    v = np.vstack([pv, bv])
    f = np.vstack([pf, bf + len(pv)])
    g = label_ground_vertices(v, f)
    assert g[: len(pv)].all()
    assert not g[len(pv) + 4 :].any()  # the box's top corners
    # the winding does not matter
    np.testing.assert_array_equal(label_ground_vertices(v, f[:, ::-1]), g)


# --- disk ------------------------------------------------------------------------------------------------


def make_map(seed=0, tile=40.0):
    rng = np.random.default_rng(seed)
    v, f = random_mesh(rng, 400, span=150.0, offset=np.array([-60.0, 30.0, 5.0]))
    is_ground = rng.random(len(v)) < 0.4
    meta = {
        "frame": "world",
        "sensor_height_m": 1.73,
        "build": {"poisson": {"depth": 9, "voxel_m": 0.1}, "tiles": [1, 2]},
        "scene": None,
        "source": Path("/x/y"),
        "n": np.int64(3),
    }
    return MeshMap.from_mesh(v, f, is_ground, tile_size_m=tile, ground_cell_m=2.0, meta=meta)


def _triangles(m: MeshMap) -> np.ndarray:
    """The map's triangles as sorted rows of 9 coordinates (independent of vertex and face order)."""
    return np.sort(m.vertices[m.faces].reshape(len(m.faces), -1), axis=0)


def test_round_trip_is_exact(tmp_path):
    m = make_map()
    out = tmp_path / "deep" / "map"
    m.save(out)
    assert sorted(p.name for p in out.iterdir()) == ["ground.npz", "map.yaml", "tiles", "tiles.json"]
    assert sorted(p.name for p in (out / "tiles").iterdir()) == sorted(f"{i}_{j}.npz" for i, j in m.tiles)
    r = MeshMap.load(out)
    # every tile's mesh is the whole map's faces of that tile with the vertices they use, bit for bit
    np.testing.assert_array_equal(r.tiles, m.tiles)
    np.testing.assert_array_equal(r.tile_origin_xy, m.tile_origin_xy)
    for k in range(len(m.tiles)):
        for a, b in zip(r.submesh([k]), m.submesh([k]), strict=True):
            np.testing.assert_array_equal(a, b)
        used = np.unique(m.faces[m.tile_faces([k])])
        np.testing.assert_array_equal(r.is_ground[np.unique(r.faces[r.tile_faces([k])])], m.is_ground[used])
        # a tile file is a plain numpy archive
        with np.load(out / "tiles" / "{}_{}.npz".format(*m.tiles[k])) as z:
            np.testing.assert_array_equal(z["vertices"], m.submesh([k])[0])
    np.testing.assert_array_equal(_triangles(r), _triangles(m))
    assert r.tile_size_m == m.tile_size_m == 40.0
    np.testing.assert_array_equal(r.ground.heights, m.ground.heights)
    np.testing.assert_array_equal(r.ground.origin_xy, m.ground.origin_xy)
    assert r.ground.cell_m == 2.0
    assert r.meta == {**m.meta, "source": "/x/y", "n": 3}
    assert r.faces.dtype == np.int32 and r.vertices.dtype == np.float64

    store = TileStore.open(out)
    doc = yaml.safe_load((out / "map.yaml").read_text())
    assert doc["format_version"] == 2 and r.format_version == 2
    assert doc["counts"] == {
        "vertices": store.n_vertices,
        "triangles": m.n_triangles,
        "ground_vertices": int(r.is_ground.sum()),
        "tiles": len(m.tiles),
    }
    assert store.n_vertices == r.n_vertices >= len(np.unique(m.faces))  # border vertices once per tile

    s = map_summary(r)
    assert s["triangles"] == m.n_triangles and s["tiles"] == len(m.tiles) and s["tile_size_m"] == 40.0
    assert s["bytes_on_disk"] == sum(p.stat().st_size for p in out.rglob("*") if p.is_file())
    assert s["frame"] == "world" and s["sensor_height_m"] == 1.73 and s["format_version"] == 2
    assert "bytes_on_disk" not in map_summary(m)

    # saving again over it gives the same bytes and leaves no temporary files
    before = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    r.save(out)
    assert {p: p.read_bytes() for p in out.rglob("*") if p.is_file()} == before


def test_a_map_of_format_1_still_loads(tmp_path, save_v1):
    """Maps of the older format 1 (the whole mesh in mesh.ply, the tiling in tiles.npz) load as they did;
    their PLY is ordinary (trimesh and Open3D read the same vertices and colours)."""
    m = make_map()
    out = tmp_path / "old"
    save_v1(m, out)
    r = MeshMap.load(out)
    assert r.format_version == 1 and map_summary(r)["format_version"] == 1
    for name in ("vertices", "faces", "is_ground", "tiles", "face_tile", "tile_origin_xy"):
        np.testing.assert_array_equal(getattr(r, name), getattr(m, name))
    np.testing.assert_array_equal(r.ground.heights, m.ground.heights)
    t = trimesh.load(out / "mesh.ply", process=False)
    np.testing.assert_array_equal(t.vertices, m.vertices)
    np.testing.assert_array_equal(t.faces, m.faces)
    rgb = np.asarray(t.visual.vertex_colors)[:, :3]
    np.testing.assert_array_equal(rgb, np.where(m.is_ground[:, None], GROUND, OTHER))
    import open3d as o3d

    o = o3d.io.read_triangle_mesh(str(out / "mesh.ply"))
    np.testing.assert_array_equal(np.asarray(o.vertices), m.vertices)
    # saved again it becomes format 2, and the old files go
    r.save(out)
    assert not (out / "mesh.ply").exists() and not (out / "tiles.npz").exists()
    np.testing.assert_array_equal(_triangles(MeshMap.load(out)), _triangles(m))


def test_import_obj_and_ply_with_our_colours(tmp_path, save_v1):
    v, f = grid_plane(6, 5, lambda x, y: 0.0 * x, x0=100.0)
    bv, bf = box([101.2, 1.2, 0.0], [103.8, 3.8, 3.0])
    v, f = np.vstack([v, bv]), np.vstack([f, bf + len(v)])
    obj = tmp_path / "m.obj"
    obj.write_text(trimesh.exchange.obj.export_obj(trimesh.Trimesh(v, f, process=False), digits=10))
    m = import_mesh(obj, tile_size_m=50.0, meta={"frame": "utm"})
    np.testing.assert_allclose(m.vertices, v, atol=1e-9)
    np.testing.assert_array_equal(m.faces, f)
    assert m.is_ground[:30].all() and not m.is_ground[30 + 4 :].any()
    assert m.meta["frame"] == "utm" and m.meta["source_mesh"] == str(obj)
    assert m.tile_size_m == 50.0

    # a PLY with our colours: labels come from the colours (here deliberately unlike the rule)
    want = np.zeros(len(v), bool)
    want[::3] = True
    ply = tmp_path / "c.ply"
    write_trimesh_ply(ply, v, f, np.where(want[:, None], GROUND, OTHER).astype(np.uint8))
    c = import_mesh(ply)
    np.testing.assert_array_equal(c.is_ground, want)
    np.testing.assert_allclose(c.vertices, v, atol=1e-5)  # trimesh writes float32 here
    # other colours: the rule
    write_trimesh_ply(ply, v, f, np.full((len(v), 3), 7, np.uint8))
    np.testing.assert_array_equal(import_mesh(ply).is_ground, m.is_ground)
    # our own map's mesh.ply imports with its labels
    mm = make_map(3)
    save_v1(mm, tmp_path / "map")
    np.testing.assert_array_equal(import_mesh(tmp_path / "map" / "mesh.ply").is_ground, mm.is_ground)


# --- errors ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("vertices", "faces", "words"),
    [
        (np.zeros((0, 3)), np.zeros((0, 3), int), "empty"),
        (np.zeros((3, 3)), np.zeros((0, 3), int), "empty"),
        ([[0, 0, np.nan], [1, 0, 0], [0, 1, 0]], [[0, 1, 2]], "NaN"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 3]], "out of range"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, -1]], "out of range"),
        ([[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 2], [0, 0, 1]], "degenerate"),
        ([[0, 0, 0], [1, 0, 0], [0, 1, 0]], [[0, 1, 2, 0]], "triangles"),
        ([[0, 0], [1, 0], [0, 1]], [[0, 1, 2]], "(V, 3)"),
    ],
)
def test_from_mesh_rejects_bad_meshes(vertices, faces, words):
    with pytest.raises(InputError, match=None) as err:
        MeshMap.from_mesh(np.asarray(vertices, float), np.asarray(faces), np.zeros(len(vertices), bool))
    assert words in str(err.value) and "\n" not in str(err.value)


def test_from_mesh_rejects_bad_labels_and_sizes():
    v, f = box([0, 0, 0], [1, 1, 1])
    with pytest.raises(InputError, match="is_ground"):
        MeshMap.from_mesh(v, f, np.zeros(3, bool))
    with pytest.raises(InputError, match="tile_size_m"):
        MeshMap.from_mesh(v, f, tile_size_m=0)
    with pytest.raises(InputError, match="ground_cell_m"):
        MeshMap.from_mesh(v, f, ground_cell_m=float("nan"))


def _saved(tmp_path, save_v1) -> Path:
    d = tmp_path / "map"
    save_v1(MeshMap.from_mesh(*box([0, 0, 0], [150, 30, 5]), tile_size_m=100.0), d)
    return d


def _saved_v2(tmp_path) -> Path:
    d = tmp_path / "map"
    MeshMap.from_mesh(*box([0, 0, 0], [150, 30, 5]), tile_size_m=100.0).save(d)
    return d


def _edit_yaml(path: Path, edit):
    doc = yaml.safe_load(path.read_text())
    edit(doc)
    path.write_text(yaml.safe_dump(doc))


def _npz_without(path: Path, key: str, **replace):
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files if k != key}
    arrays.update(replace)
    np.savez(path, **arrays)


LOAD_BREAKAGES = {
    "missing folder": (lambda d: os.rename(d, d.with_name("gone")), "map"),
    "missing mesh": (lambda d: (d / "mesh.ply").unlink(), "mesh.ply"),
    "missing map.yaml": (lambda d: (d / "map.yaml").unlink(), "map.yaml"),
    "missing tiles": (lambda d: (d / "tiles.npz").unlink(), "tiles.npz"),
    "truncated ply": (
        lambda d: (d / "mesh.ply").write_bytes((d / "mesh.ply").read_bytes()[:-20]),
        "mesh.ply",
    ),
    "ply header only": (
        lambda d: (d / "mesh.ply").write_bytes((d / "mesh.ply").read_bytes()[:150]),
        "mesh.ply",
    ),
    "not a ply": (lambda d: (d / "mesh.ply").write_text("hello"), "mesh.ply"),
    "ascii ply": (
        lambda d: write_trimesh_ply(d / "mesh.ply", *box([0, 0, 0], [1, 1, 1]), encoding="ascii"),
        "mesh.ply",
    ),
    "counts disagree": (
        lambda d: _edit_yaml(d / "map.yaml", lambda y: y["counts"].update(vertices=9)),
        "mesh.ply",
    ),
    "wrong version": (lambda d: _edit_yaml(d / "map.yaml", lambda y: y.update(format_version=3)), "map.yaml"),
    "malformed yaml": (lambda d: (d / "map.yaml").write_text("counts: [1, 2\n"), "map.yaml"),
    "duplicate key": (lambda d: (d / "map.yaml").write_text("a: 1\na: 2\n"), "map.yaml"),
    "broken npz": (lambda d: (d / "tiles.npz").write_bytes(b"PK\x03\x04junk"), "tiles.npz"),
    "npz lacks key": (lambda d: _npz_without(d / "ground.npz", "heights"), "ground.npz"),
    "bad tiling": (lambda d: _npz_without(d / "tiles.npz", "tile_size_m", tile_size_m=7.0), "tiles.npz"),
    "face_tile short": (
        lambda d: _npz_without(d / "tiles.npz", "face_tile", face_tile=np.zeros(3, np.int32)),
        "tiles.npz",
    ),
}


@pytest.mark.parametrize("case", sorted(LOAD_BREAKAGES))
def test_load_errors_name_the_file(tmp_path, case, save_v1):
    d = _saved(tmp_path, save_v1)
    breakage, name = LOAD_BREAKAGES[case]
    breakage(d)
    with pytest.raises(InputError) as err:
        MeshMap.load(d)
    msg = str(err.value)
    assert name in msg and "\n" not in msg, msg


def _tile(d: Path) -> Path:
    return sorted((d / "tiles").glob("*.npz"))[0]


def _flip_byte(path: Path, at: int) -> None:
    b = bytearray(path.read_bytes())
    b[at] ^= 0xFF
    path.write_bytes(bytes(b))


def _edit_index(d: Path, edit) -> None:
    doc = json.loads((d / "tiles.json").read_text())
    edit(doc)
    (d / "tiles.json").write_text(json.dumps(doc))


LOAD_BREAKAGES_V2 = {
    "missing index": (lambda d: (d / "tiles.json").unlink(), "tiles.json", "missing"),
    "malformed index": (lambda d: (d / "tiles.json").write_text("{"), "tiles.json", "cannot read"),
    "index of something else": (lambda d: (d / "tiles.json").write_text("[]"), "tiles.json", "not a tile"),
    "index entry lacks a field": (
        lambda d: _edit_index(d, lambda x: x["tiles"][0].pop("sha256")),
        "tiles.json",
        "malformed",
    ),
    "index escapes the folder": (
        lambda d: _edit_index(d, lambda x: x["tiles"][0].update(file="../x.npz")),
        "tiles.json",
        "file name",
    ),
    "counts disagree": (
        lambda d: _edit_yaml(d / "map.yaml", lambda y: y["counts"].update(triangles=9)),
        "tiles.json",
        "map.yaml says 9",
    ),
    "missing tile": (lambda d: _tile(d).unlink(), "tiles/", "missing"),
    "truncated tile": (lambda d: _tile(d).write_bytes(_tile(d).read_bytes()[:-40]), "tiles/", "truncated"),
    "damaged tile": (lambda d: _flip_byte(_tile(d), 100), "tiles/", "checksum"),
    "wrong version": (
        lambda d: _edit_yaml(d / "map.yaml", lambda y: y.update(format_version=7)),
        "map.yaml",
        "7",
    ),
    "missing ground": (lambda d: (d / "ground.npz").unlink(), "ground.npz", "missing"),
}


@pytest.mark.parametrize("case", sorted(LOAD_BREAKAGES_V2))
def test_load_errors_name_the_file_format_2(tmp_path, case):
    d = _saved_v2(tmp_path)
    breakage, name, words = LOAD_BREAKAGES_V2[case]
    breakage(d)
    with pytest.raises(InputError) as err:
        MeshMap.load(d)
    msg = str(err.value)
    assert name in msg and words in msg and "\n" not in msg, msg


def test_a_broken_tile_leaves_the_others_readable(tmp_path):
    d = _saved_v2(tmp_path)
    store = TileStore.open(d)
    assert len(store.entries) == 2
    (d / store.entries[0].file).write_bytes(b"PK\x03\x04 not a zip")
    with pytest.raises(InputError, match=store.entries[0].file):
        store.read(0)
    _v, f, g = store.read(1)
    assert len(f) == store.entries[1].triangles and g.dtype == bool
    # the index alone opens a map whose tile files are all gone
    for e in store.entries:
        (d / e.file).unlink()
    again = TileStore.open(d)
    assert again.n_triangles == store.n_triangles and again.extent() == store.extent()


def test_ascii_ply_is_for_import_only(tmp_path):
    p = tmp_path / "a.ply"
    write_trimesh_ply(p, *box([0, 0, 0], [1, 1, 1]), encoding="ascii")
    with pytest.raises(InputError, match="only binary PLY"):
        read_ply_binary(p)
    assert import_mesh(p).n_triangles == 12  # import reads any format trimesh reads


def test_save_to_unwritable_path_names_it(tmp_path):
    blocker = tmp_path / "file.txt"
    blocker.write_text("x")
    m = MeshMap.from_mesh(*box([0, 0, 0], [1, 1, 1]))
    with pytest.raises(InputError, match=r"file\.txt"):
        m.save(blocker / "map")
    with pytest.raises(InputError, match=r"file\.txt"):
        m.save(blocker)


def test_import_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match=r"nope\.ply"):
        import_mesh(tmp_path / "nope.ply")
    bad = tmp_path / "bad.ply"
    bad.write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 99\nproperty float x\nend_header\n"
    )
    with pytest.raises(InputError, match=r"bad\.ply"):
        import_mesh(bad)
    cloud = tmp_path / "cloud.ply"
    cloud.write_bytes(trimesh.PointCloud(np.random.default_rng(0).random((10, 3))).export(file_type="ply"))
    with pytest.raises(InputError, match=r"cloud\.ply"):
        import_mesh(cloud)
    flat = tmp_path / "flat.obj"
    flat.write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")
    with pytest.raises(InputError, match=r"flat\.obj.*degenerate"):
        import_mesh(flat)
    garbage = tmp_path / "g.obj"
    garbage.write_bytes(np.random.default_rng(5).integers(0, 256, 200, np.uint8).tobytes())
    with pytest.raises(InputError, match=r"g\.obj"):
        import_mesh(garbage)


def _upgrade(d: Path, kill_at: str | None = None):
    import subprocess
    import sys

    env = {**os.environ}
    env.pop("RANGEMCL_KILL_AT", None)
    if kill_at:
        env["RANGEMCL_KILL_AT"] = kill_at
    code = "import sys; from rangemcl.cli import main; sys.argv[0] = 'rangemcl'; main()"
    return subprocess.run(
        [sys.executable, "-c", code, "map-upgrade", str(d)],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )


def test_map_upgrade_gives_the_same_rays_and_survives_a_kill(tmp_path, save_v1):
    """``rangemcl map-upgrade`` rewrites a format-1 folder as format 2 in place: the same rays hit the same
    surfaces (cast through both with the Warp caster); killed outright before map.yaml, the folder still
    opens as the format-1 map, and a second run finishes."""
    from rangemcl.raycast import RayCaster

    m = make_map(5, tile=30.0)
    d = tmp_path / "map"
    save_v1(m, d)
    killed = _upgrade(d, kill_at="map-files")
    assert killed.returncode == -9
    assert MeshMap.load(d).format_version == 1 and (d / "tiles.json").is_file()
    done = _upgrade(d)
    assert done.returncode == 0, done.stderr
    assert "format 2" in done.stdout and "tile files" in done.stdout
    assert not (d / "mesh.ply").exists() and not (d / "tiles.npz").exists()
    r = MeshMap.load(d)
    assert r.format_version == 2 and r.n_triangles == m.n_triangles
    again = _upgrade(d)
    assert again.returncode == 0 and "already format 2" in again.stdout

    rng = np.random.default_rng(0)
    lo, hi = np.array(m.extent[:3]), np.array(m.extent[3:])
    origins = rng.uniform(lo, hi, (2000, 3))
    origins[:, 2] += 1.0
    dirs = rng.normal(size=(2000, 3)) * [1, 1, 3]
    dirs[:, 2] = -np.abs(dirs[:, 2])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    ranges = []
    for mm in (m, r):
        c = RayCaster(threads=1)
        c.add_mesh(mm.vertices, mm.faces, name="map")
        ranges.append(c.cast(origins, dirs, 500.0).ranges)
    assert np.isfinite(ranges[0]).sum() > 200
    np.testing.assert_array_equal(ranges[0], ranges[1])


def test_map_info_reads_a_tiled_map_one_tile_at_a_time(tmp_path, save_v1):
    """``rangemcl map-info``: of a map of format 2, the same counts and ground shares as the whole map's
    summary (border vertices counted in each tile file), its coarse level and place prior, and the size of
    every file; of a map of format 1, the whole map's summary."""
    from rangemcl.localization.place_prior import describe_prior_file
    from rangemcl.mapping.info import map_info
    from rangemcl.maps.coarse import add_coarse_level
    from rangemcl.maps.meshmap import map_summary

    m = make_map()
    d = tmp_path / "v2"
    m.save(d)
    info = map_info(d, describe_prior=describe_prior_file)
    whole = map_summary(MeshMap.load(d))
    assert info["triangles"] == whole["triangles"] and info["tiles"] == whole["tiles"]
    assert info["size_m"] == whole["size_m"] and info["extent_m"] == whole["extent_m"]
    assert info["triangles_per_tile"] == whole["triangles_per_tile"]
    assert info["ground_grid"] == whole["ground_grid"]
    store = TileStore.open(d)
    assert info["vertices"].startswith(f"{store.n_vertices} ")
    g = sum(e.ground_vertices for e in store.entries) / store.n_vertices
    assert info["ground_vertex_share"] == round(g, 4)
    assert abs(info["ground_triangle_share"] - whole["ground_triangle_share"]) < 1e-9  # faces are not shared
    assert info["bytes_on_disk"] == sum(p.stat().st_size for p in d.rglob("*") if p.is_file())
    assert info["coarse_level"].startswith("none") and info["place_prior"].startswith("none")
    assert info["index_open_ms"] >= 0 and info["format_version"] == 2
    add_coarse_level(d, 0.2)
    info = map_info(d, describe_prior=describe_prior_file)
    assert info["coarse_level"].startswith(f"{len(store.entries)} tiles")
    assert info["bytes_on_disk"] == sum(p.stat().st_size for p in d.rglob("*") if p.is_file())
    v1 = tmp_path / "v1"
    save_v1(m, v1)
    assert map_info(v1) == map_summary(MeshMap.load(v1))


def test_a_drive_file_reads_as_waypoints_kitti_or_tum_poses(tmp_path):
    """``import-mesh --drive``: the same path from 'x y' lines, KITTI poses and TUM poses, thinned to a
    point a metre; a malformed line names the file and line."""
    from rangemcl.maps.meshmap import read_drive_xy

    t = np.linspace(0.0, 20.0, 81)
    xy = np.column_stack([3.0 * t, np.sin(t)])
    (tmp_path / "w.txt").write_text("# x y\n" + "".join(f"{x} {y}\n" for x, y in xy))
    (tmp_path / "k.txt").write_text("".join(f"1 0 0 {x} 0 1 0 {y} 0 0 1 0.5\n" for x, y in xy))
    (tmp_path / "t.txt").write_text(
        "".join(f"{k * 0.1} {x} {y} 0.5 0 0 0 1\n" for k, (x, y) in enumerate(xy))
    )
    ref = read_drive_xy(tmp_path / "w.txt")
    for name in ("k.txt", "t.txt"):
        np.testing.assert_allclose(read_drive_xy(tmp_path / name), ref)
    assert 30 < len(ref) < 81 and (np.linalg.norm(np.diff(ref[:-1], axis=0), axis=1) >= 1.0).all()
    np.testing.assert_allclose(ref[[0, -1]], xy[[0, -1]])
    (tmp_path / "bad.txt").write_text("1 2\n3 four\n")
    with pytest.raises(InputError, match=r"bad\.txt:2"):
        read_drive_xy(tmp_path / "bad.txt")
    (tmp_path / "five.txt").write_text("1 2\n1 2 3 4 5\n")
    with pytest.raises(InputError, match=r"five\.txt:2.*5 numbers"):
        read_drive_xy(tmp_path / "five.txt")
    (tmp_path / "one.txt").write_text("1 2\n")
    with pytest.raises(InputError, match="at least two points"):
        read_drive_xy(tmp_path / "one.txt")
    with pytest.raises(InputError, match=r"nope\.txt"):
        read_drive_xy(tmp_path / "nope.txt")
