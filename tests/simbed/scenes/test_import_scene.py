"""``simbed import-scene``: a mesh world becomes a drivable scene whose LiDAR world is the mesh
itself (``export-mesh`` gives it back within 1 mm) and whose car drives on its ground."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree

from rangemcl.datasets.kitti import load_sequence
from rangemcl.errors import InputError
from simbed.record import record
from simbed.scenes.import_scene import import_scene, load_world_mesh
from simbed.sim.world import World


def small_world() -> trimesh.Trimesh:
    """A 60 m square of ground with a hump, three buildings and a pole, z up."""
    ground = trimesh.creation.box(extents=(60, 60, 1.0))
    ground.apply_translation((0, 0, -0.5))
    parts = [ground]
    for (x, y), (sx, sy, sz) in [((-15, 12), (10, 8, 9)), ((14, 14), (8, 8, 6)), ((16, -15), (12, 6, 4))]:
        b = trimesh.creation.box(extents=(sx, sy, sz))
        b.apply_translation((x, y, sz / 2))
        parts.append(b)
    pole = trimesh.creation.cylinder(radius=0.15, height=5, sections=16)
    pole.apply_translation((-5, -8, 2.5))
    parts.append(pole)
    return trimesh.util.concatenate(parts)


def same_surface(a_v, a_f, b_v, b_f, tol=1e-3) -> None:
    assert len(a_f) == len(b_f)
    assert cKDTree(a_v).query(b_v)[0].max() < tol and cKDTree(b_v).query(a_v)[0].max() < tol


@pytest.mark.parametrize("suffix", [".ply", ".obj", ".stl", ".glb"])
def test_export_mesh_gives_the_imported_mesh_back(tmp_path, suffix):
    mesh = small_world()
    src = mesh.copy()
    if suffix == ".glb":  # glTF is y up
        src.vertices = np.stack([mesh.vertices[:, 0], mesh.vertices[:, 2], -mesh.vertices[:, 1]], axis=1)
    path = tmp_path / f"world{suffix}"
    src.export(path)
    r = import_scene(path, tmp_path / "scene.xml", max_piece_faces=1000 if suffix == ".ply" else 200_000)
    world = World(tmp_path / "scene.xml")
    v, f = world.static_triangles
    same_surface(mesh.vertices, mesh.faces, v, f)
    assert r.pieces == 1 or suffix == ".ply"


def test_the_car_drives_on_the_imported_ground(tmp_path):
    mesh = small_world()
    mesh.export(tmp_path / "world.ply")
    import_scene(tmp_path / "world.ply", tmp_path / "scene.xml")
    route = tmp_path / "route.txt"
    route.write_text("-25 -2\n24 -2\n")  # between the buildings, over open ground
    record(
        str(tmp_path / "scene.xml"), str(route), "vlp-16", tmp_path / "run", frames=50, seed=1, progress=False
    )
    seq = load_sequence(tmp_path / "run")
    mount = float(seq.meta["sensor"]["mount"]["xyz_m"][2])
    z = seq.poses[:, 2, 3]
    assert np.ptp(seq.poses[:, 0, 3]) > 20  # it drove
    assert np.abs(z - mount).max() < 0.1  # on the ground at z = 0, not in it, not above
    # and the LiDAR sees the buildings: points up to their roofs
    pts = seq.scan(40) @ seq.poses[40][:3, :3].T + seq.poses[40][:3, 3]
    assert pts[:, 2].max() > 3.0


def test_bad_worlds_are_one_line(tmp_path):
    cases = {
        "text.ply": b"hello, not a mesh\n",
        "empty.obj": b"",
        "nan.obj": b"v 0 0 0\nv 1 0 nan\nv 0 1 0\nf 1 2 3\n",
        "points.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\n",
    }
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputError) as err:
            import_scene(tmp_path / name, tmp_path / "s.xml")
        assert name in str(err.value) and "\n" not in str(err.value), str(err.value)
        assert not (tmp_path / "s.xml").exists()
    (tmp_path / "w.txt").write_text("1 2 3\n")
    with pytest.raises(InputError, match="not a mesh file"):
        import_scene(tmp_path / "w.txt", tmp_path / "s.xml")
    small_world().export(tmp_path / "world.ply")
    import_scene(tmp_path / "world.ply", tmp_path / "s.xml")
    with pytest.raises(InputError, match="--overwrite"):
        import_scene(tmp_path / "world.ply", tmp_path / "s.xml")
    import_scene(tmp_path / "world.ply", tmp_path / "s.xml", overwrite=True)


def test_imported_meshes_carry_their_materials_face_by_face(tmp_path):
    """--material for the mesh, --face-materials face by face: every piece holds one material, the
    sidecar names it, and a ray that hits a face gets that face's material (checked on every face's
    centre, cast straight down or sideways onto it)."""
    mesh = small_world()
    mesh.export(tmp_path / "world.ply")
    loaded_v, loaded_f = load_world_mesh(tmp_path / "world.ply")
    centre = loaded_v[loaded_f].mean(axis=1)
    names = np.where(centre[:, 2] > 3.0, "glass", np.where(centre[:, 2] < -0.01, "asphalt", "brick"))
    names[np.hypot(centre[:, 0] + 5, centre[:, 1] + 8) < 0.5] = "steel"  # the pole
    (tmp_path / "faces.txt").write_text("\n".join(names) + "\n")
    import_scene(
        tmp_path / "world.ply",
        tmp_path / "scene.xml",
        material="concrete",
        face_materials=tmp_path / "faces.txt",
        max_piece_faces=1000,
    )
    side = (tmp_path / "scene.materials.yaml").read_text()
    assert "default: concrete" in side
    world = World(tmp_path / "scene.xml")
    mats = world.materials
    # each face centre, hit from outside along the face's normal
    v, f = world.static_triangles
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c = tri.mean(axis=1)
    hits = world.caster.cast(c + 0.05 * n, -n, 0.1, normals=True)
    ok = hits.hit & (n[:, 2] > -0.5)  # not the bottoms, which lie on the ground's top (either may be hit)
    got = mats.lookup(hits.mesh_ids[ok], hits.face_ids[ok], c[ok], hits.normals[ok])
    want = {tuple(np.round(cc, 3)): nm for cc, nm in zip(centre, names, strict=True)}
    expect = [want.get(tuple(np.round(cc, 3))) for cc in c[ok]]
    known = np.array([e is not None for e in expect])
    assert known.mean() > 0.95 and ok.sum() > 0.75 * len(f)
    got_names = np.array([mats.table.materials[g].name for g in got])
    np.testing.assert_array_equal(got_names[known], np.array(expect, dtype=object)[known])
    with pytest.raises(InputError, match=r"faces\.txt: 2 material names for a mesh of"):
        (tmp_path / "faces.txt").write_text("glass\nbrick\n")
        import_scene(tmp_path / "world.ply", tmp_path / "s2.xml", face_materials=tmp_path / "faces.txt")
    with pytest.raises(InputError, match="--material: no material 'marble'"):
        import_scene(tmp_path / "world.ply", tmp_path / "s3.xml", material="marble")
