"""The streamed map assembly equals building the whole map in memory (MeshMap.from_mesh + save), file for
file (format 2: a mesh file per tile and the index)."""

from __future__ import annotations

import numpy as np
import pytest

from rangemcl.errors import InputError
from rangemcl.mapping.assemble import assemble_map
from rangemcl.maps.meshmap import MeshMap


def random_tiles(rng, tmp_path, tiles, size=20.0, margin=3.0):
    """Per tile (i, j): random triangles with vertices in the tile's box widened by ``margin`` (so some
    centroids and ground cells fall in a neighbour), random ground labels; plus one empty tile."""
    paths, parts = [], []
    for n, (i, j) in enumerate(tiles):
        nv = int(rng.integers(30, 80))
        v = np.column_stack(
            [
                rng.uniform(i * size - margin, (i + 1) * size + margin, nv),
                rng.uniform(j * size - margin, (j + 1) * size + margin, nv),
                rng.normal(0.0, 0.5, nv),
            ]
        )
        f = rng.integers(0, nv, (2 * nv, 3))
        f = f[(f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 0] != f[:, 2])]
        # one triangle past the tile's upper y border: its face belongs to tile (i, j + 1)
        top = (j + 1) * size
        v = np.vstack(
            [v, [[i * size + 5, top + 1, 0], [i * size + 7, top + 1, 0], [i * size + 6, top + 2, 0]]]
        )
        f = np.vstack([f, [nv, nv + 1, nv + 2]])
        nv += 3
        g = rng.uniform(size=nv) < 0.6
        p = tmp_path / f"tile_{n}.npz"
        np.savez(p, vertices=v, faces=f.astype(np.int32), is_ground=g)
        paths.append(p)
        parts.append((v, f, g))
    empty = tmp_path / "empty.npz"
    np.savez(empty, vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), np.int32), is_ground=np.zeros(0, bool))
    paths.insert(1, empty)
    return paths, parts


def concatenated(parts):
    vs, fs, gs, offset = [], [], [], 0
    for v, f, g in parts:
        vs.append(v)
        fs.append(f + offset)
        gs.append(g)
        offset += len(v)
    return np.concatenate(vs), np.concatenate(fs), np.concatenate(gs)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_assembled_map_equals_the_in_memory_map(tmp_path, seed):
    rng = np.random.default_rng(seed)
    tiles = [(-1, -1), (-1, 0), (0, 0), (1, 0), (1, 1), (3, -2)]
    paths, parts = random_tiles(rng, tmp_path, tiles)
    drive = rng.uniform(-20, 40, (50, 2))
    meta = {"created_by": "test", "sensor_height_m": 1.73}
    counts = assemble_map(
        paths, tmp_path / "streamed", tile_size_m=20.0, work_dir=tmp_path / "work", meta=meta, drive_xy=drive
    )
    v, f, g = concatenated(parts)
    ref = MeshMap.from_mesh(v, f, g, tile_size_m=20.0, meta=meta)
    ref.drive_xy = drive
    ref.save(tmp_path / "ref")

    a, b = MeshMap.load(tmp_path / "streamed"), MeshMap.load(tmp_path / "ref")
    assert counts == {
        "vertices": b.n_vertices,  # per tile: a vertex of faces in two tiles is in both tile files
        "triangles": len(f),
        "ground_vertices": int(b.is_ground.sum()),
        "tiles": len(b.tiles),
    }
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.is_ground, b.is_ground)
    np.testing.assert_array_equal(a.tiles, b.tiles)
    np.testing.assert_array_equal(a.face_tile, b.face_tile)
    np.testing.assert_array_equal(a.tile_origin_xy, b.tile_origin_xy)
    np.testing.assert_array_equal(a.ground.origin_xy, b.ground.origin_xy)
    assert a.ground.cell_m == b.ground.cell_m
    np.testing.assert_array_equal(a.ground.heights, b.ground.heights)  # NaN where unmeasured, in both
    np.testing.assert_array_equal(a.drive_xy, b.drive_xy)
    assert a.meta == b.meta and a.extent == b.extent
    # the same triangles as the whole mesh, each in the tile of its centroid
    tri = lambda m: np.sort(m.vertices[m.faces].reshape(len(m.faces), -1), axis=0)  # noqa: E731
    np.testing.assert_array_equal(tri(a), np.sort(v[f].reshape(len(f), -1), axis=0))
    # each tile mesh's last triangle went to the tile above, the one that holds its centroid
    for (i, j), (pv, pf, _g) in zip(tiles, parts, strict=True):
        corners = pv[pf[-1]]
        k = np.flatnonzero((a.vertices[a.faces] == corners).all(axis=(1, 2)))
        assert len(k) == 1
        corner = a.tile_origin_xy + 20.0 * a.tiles[a.face_tile[k[0]]]  # the tile's lower-left corner
        np.testing.assert_allclose(corner, [20.0 * i, 20.0 * (j + 1)])
    # every file the same bytes (the tiles are written with fixed zip timestamps)
    names = sorted(p.relative_to(tmp_path / "ref") for p in (tmp_path / "ref").rglob("*") if p.is_file())
    assert names == sorted(
        p.relative_to(tmp_path / "streamed") for p in (tmp_path / "streamed").rglob("*") if p.is_file()
    )
    assert "tiles.json" in map(str, names) and not (tmp_path / "ref" / "mesh.ply").exists()
    for name in names:
        assert (tmp_path / "streamed" / name).read_bytes() == (tmp_path / "ref" / name).read_bytes(), name


def test_assembly_of_no_triangles_is_an_error(tmp_path):
    p = tmp_path / "t.npz"
    np.savez(p, vertices=np.zeros((0, 3)), faces=np.zeros((0, 3), np.int32), is_ground=np.zeros(0, bool))
    with pytest.raises(InputError, match="empty"):
        assemble_map([p], tmp_path / "map", tile_size_m=100.0, work_dir=tmp_path / "w")
    assert not (tmp_path / "map" / "map.yaml").exists()


def test_a_broken_tile_mesh_is_named(tmp_path):
    p = tmp_path / "t.npz"
    np.savez(p, vertices=np.zeros((3, 3)), faces=np.array([[0, 1, 5]]), is_ground=np.zeros(3, bool))
    with pytest.raises(InputError, match=r"t\.npz: face indices out of range"):
        assemble_map([p], tmp_path / "map", tile_size_m=100.0, work_dir=tmp_path / "w")
