"""`rangemcl import-mesh` of a binary PLY read in place, a block at a time: the same map folder, file for
file, as the in-memory import; other files fall back to it; bad meshes are one line."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from rangemcl.errors import InputError
from rangemcl.mapping.stream_import import import_mesh_streaming, ply_layout
from rangemcl.maps.meshmap import GROUND_RGB, NON_GROUND_RGB, import_mesh


def write_binary_ply(path: Path, v, f, *, rgb=None, endian="<", vertex_type="f8", extra_face=False) -> Path:
    """A binary PLY written field by field (independent of the reader under test)."""
    names = {"f8": "double", "f4": "float"}
    vfields = [(c, endian + vertex_type) for c in "xyz"]
    header = ["ply", f"format binary_{'little' if endian == '<' else 'big'}_endian 1.0", "comment test"]
    header += [f"element vertex {len(v)}"] + [f"property {names[vertex_type]} {c}" for c in "xyz"]
    if rgb is not None:
        vfields += [(c, "u1") for c in ("red", "green", "blue")]
        header += [f"property uchar {c}" for c in ("red", "green", "blue")]
    ffields = [("n", "u1"), ("i", endian + "i4", (3,))]
    header += [f"element face {len(f)}", "property list uchar int vertex_indices"]
    if extra_face:
        ffields.append(("quality", endian + "f4"))
        header.append("property float quality")
    header.append("end_header")
    vrec = np.zeros(len(v), vfields)
    for k, c in enumerate("xyz"):
        vrec[c] = v[:, k]
    if rgb is not None:
        for k, c in enumerate(("red", "green", "blue")):
            vrec[c] = rgb[:, k]
    frec = np.zeros(len(f), ffields)
    frec["n"], frec["i"] = 3, f
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode())
        fh.write(vrec.tobytes())
        fh.write(frec.tobytes())
    return path


def town_mesh(seed: int = 0):
    """A wavy ground grid of 2 m cells over 90 m x 70 m (several 25 m tiles) with boxes standing on it,
    an unused vertex and long sliver triangles crossing tile borders."""
    rng = np.random.default_rng(seed)
    xs, ys = np.arange(-40.0, 50.0, 2.0), np.arange(-30.0, 40.0, 2.0)
    gx, gy = np.meshgrid(xs, ys)
    gz = 0.3 * np.sin(gx / 9.0) + 0.2 * np.cos(gy / 7.0) + rng.normal(0, 0.01, gx.shape)
    v = [np.stack([gx, gy, gz], -1).reshape(-1, 3)]
    nx = len(xs)
    i, j = np.meshgrid(np.arange(len(ys) - 1), np.arange(nx - 1), indexing="ij")
    a = (i * nx + j).reshape(-1)
    f = [np.stack([a, a + 1, a + nx + 1], 1), np.stack([a, a + nx + 1, a + nx], 1)]
    n = len(v[0])
    for _ in range(12):
        c = rng.uniform([-35, -25, 0], [45, 35, 0])
        h = rng.uniform([1, 1, 2], [4, 4, 9])
        corners = np.array([[sx, sy, sz] for sz in (0, 1) for sy in (-1, 1) for sx in (-1, 1)], float)
        v.append(c + corners * [h[0], h[1], h[2]] - [0, 0, 0.5])
        quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
        f.append(
            np.array(
                [[n + q[0], n + q[1], n + q[2]] for q in quads]
                + [[n + q[0], n + q[2], n + q[3]] for q in quads]
            )
        )
        n += 8
    v.append(np.array([[0.0, 0.0, 100.0], [-39.0, 0.0, 3.0], [48.0, 0.5, 3.0], [48.0, 1.0, 6.0]]))
    f.append(np.array([[n + 1, n + 2, n + 3]]))  # a sliver over every tile of its row; vertex n unused
    return np.concatenate(v), np.concatenate(f).astype(np.int64)


def same_folders(a: Path, b: Path) -> None:
    names = sorted(str(p.relative_to(a)) for p in a.rglob("*") if p.is_file())
    assert names == sorted(str(p.relative_to(b)) for p in b.rglob("*") if p.is_file())
    assert any(n.startswith("coarse/") for n in names) and sum(n.startswith("tiles/") for n in names) >= 6
    for n in names:
        assert (a / n).read_bytes() == (b / n).read_bytes(), n


@pytest.mark.parametrize(
    "variant",
    [
        dict(),
        dict(endian=">", vertex_type="f4", extra_face=True),
        dict(colours=True),
    ],
    ids=["doubles", "big-endian-floats-face-property", "colour-labels"],
)
def test_the_same_map_files_as_the_in_memory_import(tmp_path, variant):
    v, f = town_mesh()
    rgb = None
    if variant.pop("colours", False):
        rng = np.random.default_rng(1)
        rgb = np.where(rng.random(len(v))[:, None] < 0.5, GROUND_RGB, NON_GROUND_RGB).astype(np.uint8)
    ply = write_binary_ply(tmp_path / "m.ply", v, f, rgb=rgb, **variant)
    assert ply_layout(ply) is not None
    meta = {"source_mesh": str(ply)}
    m = import_mesh(ply, tile_size_m=25.0, meta=meta)
    assert m.meta["ground_labels"] == ("vertex colours" if rgb is not None else m.meta["ground_labels"])
    m.save(tmp_path / "memory", coarse_ratio=0.2)
    counts = import_mesh_streaming(
        ply,
        tmp_path / "stream",
        work_dir=tmp_path / "work",
        tile_size_m=25.0,
        coarse_ratio=0.2,
        meta=meta,
        block=997,  # many blocks, none aligned with anything
    )
    assert counts["triangles"] == m.n_triangles and not (tmp_path / "work").exists()
    same_folders(tmp_path / "memory", tmp_path / "stream")


def test_other_files_fall_back_and_bad_meshes_are_one_line(tmp_path):
    v, f = town_mesh()
    ply = write_binary_ply(tmp_path / "m.ply", v, f)
    # not streamable: truncated, trailing bytes, ASCII, quads -> the in-memory import reads them
    data = ply.read_bytes()
    for name, content in (("short.ply", data[:-5]), ("long.ply", data + b"\0\0")):
        (tmp_path / name).write_bytes(content)
        assert ply_layout(tmp_path / name) is None
    import trimesh

    trimesh.Trimesh(v, f, process=False).export(tmp_path / "ascii.ply", encoding="ascii")
    assert ply_layout(tmp_path / "ascii.ply") is None
    assert ply_layout(tmp_path / "nothing.ply") is None
    # a NaN vertex, an index out of range: one line naming the file
    bad = v.copy()
    bad[7] = np.nan
    with pytest.raises(InputError, match=r"nan\.ply: vertex 7 is NaN"):
        import_mesh_streaming(
            write_binary_ply(tmp_path / "nan.ply", bad, f),
            tmp_path / "o1",
            work_dir=tmp_path / "w",
            block=100,
        )
    bad_f = f.copy()
    bad_f[-1, 0] = len(v) + 3
    with pytest.raises(InputError, match=r"range\.ply: face indices out of range"):
        import_mesh_streaming(
            write_binary_ply(tmp_path / "range.ply", v, bad_f), tmp_path / "o2", work_dir=tmp_path / "w"
        )
    assert not (tmp_path / "w").exists()
