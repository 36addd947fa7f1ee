"""Tests of ``simbed.sim.geometry`` against independent references: MuJoCo's own ``mj_ray`` and analytic
shapes.

Every geom type is placed in a tiny MJCF scene at a random rotated and translated pose, on a static body
and on a free-joint body, and a few hundred rays aimed at it from outside go through the Warp caster (with
the triangles under test) and through ``mujoco.mj_ray`` (which intersects MuJoCo's analytic shapes and its
own mesh and height-field triangles). Hit or miss must agree, and ranges must agree to ``FLAT_TOL`` on
flat-faced geoms, and on curved ones within the tessellation's sagitta bound.
"""

from __future__ import annotations

import math
import os
import zlib

import mujoco
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from rangemcl.errors import InputError
from rangemcl.raycast import RayCaster
from simbed.sim import geometry as G

SEGMENTS = 64  # sagitta 0.12 % of the radius: tight enough that a wrong radius or pose shows
N_RAYS = 300
FLAT_TOL = 1e-4  # metres: float32 Warp ranges of a few metres against MuJoCo's float64
MIN_COS = 0.25  # rays meeting the surface within ~15° of tangent are not compared (see below)
NORMAL_TURN_RAD = 0.5  # a normal turning this much between neighbouring rays marks an edge or rim
_T = mujoco.mjtGeom
CURVED = [int(t) for t in (_T.mjGEOM_SPHERE, _T.mjGEOM_CAPSULE, _T.mjGEOM_CYLINDER, _T.mjGEOM_ELLIPSOID)]


# ---------------------------------------------------------------------- helpers
def unit(v):
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def random_pose(rng) -> tuple[np.ndarray, np.ndarray]:
    """A position and a MuJoCo (w, x, y, z) quaternion of a random rotation."""
    x, y, z, w = Rotation.random(random_state=rng).as_quat()
    return rng.uniform(-2.0, 2.0, 3), np.array([w, x, y, z])


def fmt(a) -> str:
    return " ".join(f"{float(x):.9g}" for x in np.ravel(a))


def mj_cast(model, data, origins, directions, geomgroup=None):
    """``mj_ray`` per ray: ranges (inf on a miss), world normals, geom ids (-1 on a miss)."""
    n = len(directions)
    ranges, normals, geoms = np.full(n, np.inf), np.zeros((n, 3)), np.full(n, -1)
    gid, normal = np.zeros(1, np.int32), np.zeros(3)
    group = None if geomgroup is None else np.asarray(geomgroup, np.uint8)
    for i in range(n):
        r = mujoco.mj_ray(model, data, origins[i], directions[i], group, 1, -1, gid, normal)
        if r >= 0:
            ranges[i], normals[i], geoms[i] = r, normal, gid[0]
    return ranges, normals, geoms


def ambiguous(model, data, origins, directions, delta, check_normals, geomgroup=None):
    """Rays whose hit or miss is not defined to the precision of a tessellation: (N,) bool.

    Each ray is compared with four parallel rays shifted sideways by ``delta`` metres. It is ambiguous if
    a neighbour's hit/miss differs (the ray passes within ``delta`` of a silhouette or an outer edge, where
    a polyhedron inscribed in the analytic surface, or float32 against float64, may decide otherwise), if a
    neighbour's range jumps (an occluding edge in front of a farther surface), with ``check_normals`` if a
    neighbour's normal turns sharply (a cylinder's rim, where the inscribed polygon of a cap is smaller
    than the disc), or if the ray meets the surface within acos(MIN_COS) of tangent, where the range of
    an inscribed polyhedron grows as sagitta / cos and hit/miss flips across the last facet.
    """
    r0, n0, geoms = mj_cast(model, data, origins, directions, geomgroup)
    side_u = unit(np.cross(directions, unit(np.random.default_rng(0).normal(size=3))))
    side_v = np.cross(directions, side_u)
    amb = np.zeros(len(directions), dtype=bool)
    hit0 = np.isfinite(r0)
    for shift in (side_u, -side_u, side_v, -side_v):
        rk, nk, _ = mj_cast(model, data, origins + delta * shift, directions, geomgroup)
        hitk = np.isfinite(rk)
        amb |= hitk != hit0
        both = hit0 & hitk
        amb[both] |= np.abs(rk[both] - r0[both]) > 2.0 * delta / MIN_COS
        if check_normals:
            amb[both] |= np.einsum("ij,ij->i", nk[both], n0[both]) < math.cos(NORMAL_TURN_RAD)
    cos = np.abs(np.einsum("ij,ij->i", directions, n0))
    amb |= hit0 & (cos < MIN_COS)
    return amb, r0, cos, geoms


def geom_radius(model, gid) -> float:
    """The r of the sagitta bound: the radius, or the largest semi-axis of an ellipsoid."""
    size = model.geom_size[gid]
    return float(size.max() if model.geom_type[gid] == mujoco.mjtGeom.mjGEOM_ELLIPSOID else size[0])


def compare(model, data, caster, origins, directions, *, delta, check_normals, geomgroup=None, mask=None):
    """Cast through both, drop ambiguous rays, check hit/miss and ranges.

    Returns ``(keep (N,) bool: the rays compared, our RayHits, mj_ray's geom ids)``.
    """
    amb, r_mj, cos, geoms = ambiguous(model, data, origins, directions, delta, check_normals, geomgroup)
    if mask is not None:
        hit = np.isfinite(r_mj)
        amb[hit] |= ~mask(origins[hit] + r_mj[hit, None] * directions[hit])
    ours = caster.cast(origins, directions, max_range=100.0)
    keep = ~amb
    hit_mj = np.isfinite(r_mj)
    disagree = np.flatnonzero(keep & (ours.hit != hit_mj))
    assert len(disagree) == 0, (
        f"{len(disagree)} rays disagree on hit/miss, first: origin {origins[disagree[0]]}, "
        f"direction {directions[disagree[0]]}, mj_ray {r_mj[disagree[0]]}, ours {ours.ranges[disagree[0]]}"
    )
    both = np.flatnonzero(keep & hit_mj)
    err = ours.ranges[both].astype(np.float64) - r_mj[both]
    curved = np.isin(model.geom_type[geoms[both]], CURVED)
    radius = np.array([geom_radius(model, g) for g in geoms[both]])
    # An inscribed polyhedron is hit no earlier than the analytic surface, and, as it contains that
    # surface moved inward by the sagitta s, no later than where the ray meets the inner surface: for a
    # sphere of radius r that is 2·s / (cos + sqrt(cos² − 2·s/r)) farther, within 2 % of s / cos for
    # cos >= MIN_COS at this s/r. The same holds locally on any smooth convex surface; 10 % margin.
    upper = np.where(curved, 1.1 * G.sagitta(1.0, SEGMENTS) * radius / cos[both], 0.0) + FLAT_TOL
    lower = np.full(len(both), -FLAT_TOL)
    bad = np.flatnonzero((err < lower) | (err > upper))
    assert len(bad) == 0, (
        f"{len(bad)} ranges off, worst error {err[bad].max():+.6f} m vs bound {upper[bad].max():.6f} "
        f"(geom {geoms[both][bad[0]]}, cos {cos[both][bad[0]]:.3f})"
    )
    return keep, ours, geoms


# ---------------------------------------------------------------------- scenes
OCTAHEDRON = (
    '<mesh name="m" vertex="0.5 0 0  -0.5 0 0  0 0.4 0  0 -0.4 0  0 0 0.3  0 0 -0.3" '
    'face="0 2 4  2 1 4  1 3 4  3 0 4  2 0 5  1 2 5  3 1 5  0 3 5"/>'
)


def star_prism() -> str:
    """A concave mesh: a five-pointed star extruded 0.5 m (fan caps from the centre, quad sides)."""
    n, outer, inner, h = 5, 0.8, 0.3, 0.25
    angles = np.pi * np.arange(2 * n) / n
    radii = np.where(np.arange(2 * n) % 2 == 0, outer, inner)
    rim = np.stack([radii * np.cos(angles), radii * np.sin(angles)], 1)
    verts = [(0, 0, h), (0, 0, -h)] + [(x, y, h) for x, y in rim] + [(x, y, -h) for x, y in rim]
    m, faces = 2 * n, []
    for k in range(m):
        j = (k + 1) % m
        faces += [(0, 2 + k, 2 + j), (1, 2 + m + j, 2 + m + k), (2 + k, 2 + m + k, 2 + m + j)]
        faces += [(2 + k, 2 + m + j, 2 + j)]
    return f'<mesh name="m" vertex="{fmt(verts)}" face="{fmt(faces)}"/>'


def hfield_asset(nrow=9, ncol=12) -> str:
    """A non-square height field with a seeded random elevation grid (rows listed as MJCF wants them)."""
    elevation = np.random.default_rng(7).uniform(0.0, 1.0, (nrow, ncol))
    return (
        f'<hfield name="h" nrow="{nrow}" ncol="{ncol}" size="0.6 0.4 0.2 0.1" elevation="{fmt(elevation)}"/>'
    )


# name: (asset, geom attributes, where rays aim): a bounding radius for a solid, rays from all around;
# the half-extents (x, y) of a plane or a height field, rays from its +z side (the side mj_ray sees)
CASES = {
    "plane": ("", 'type="plane" size="0.8 0.5 0.1"', (0.8, 0.5)),
    "plane_infinite": ("", 'type="plane" size="0 0 1"', (3.0, 3.0)),
    "box": ("", 'type="box" size="0.4 0.25 0.15"', 0.5),
    "sphere": ("", 'type="sphere" size="0.35"', 0.35),
    "capsule": ("", 'type="capsule" size="0.2 0.3"', 0.5),
    "cylinder": ("", 'type="cylinder" size="0.3 0.25"', 0.4),
    "ellipsoid": ("", 'type="ellipsoid" size="0.45 0.25 0.15"', 0.45),
    "mesh_octahedron": (OCTAHEDRON, 'type="mesh" mesh="m"', 0.5),
    "mesh_star_concave": (star_prism(), 'type="mesh" mesh="m"', 0.85),
    "hfield": (hfield_asset(), 'type="hfield" hfield="h"', (0.6, 0.4)),
}


def one_geom_scene(name: str, moving: bool):
    """(model, data) with the case's geom at a random pose in a body at a random pose, forwarded."""
    asset, attrs, _ = CASES[name]
    rng = np.random.default_rng(zlib.crc32(f"{name}{moving}".encode()))
    body_pos, body_quat = random_pose(rng)
    geom_pos, geom_quat = random_pose(rng)
    geom_pos *= 0.2
    xml = f"""<mujoco><asset>{asset}</asset><worldbody>
      <body name="holder" pos="{fmt(body_pos)}" quat="{fmt(body_quat)}">{"<freejoint/>" if moving else ""}
        <geom name="g" {attrs} pos="{fmt(geom_pos)}" quat="{fmt(geom_quat)}"/>
      </body></worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    if moving:  # away from where the model placed it, so a pose read from the model would be wrong
        pos, quat = random_pose(rng)
        data.qpos[:7] = [*pos, *quat]
    mujoco.mj_forward(model, data)
    return model, data, rng


def aimed_rays(model, data, rng, extent, n=N_RAYS):
    """Rays from outside at random points near the geom (see ``CASES`` for ``extent``)."""
    center, R = data.geom_xpos[0].copy(), data.geom_xmat[0].reshape(3, 3)
    if isinstance(extent, tuple):
        d = unit(rng.normal(size=(n, 3)))
        d[:, 2] = np.abs(d[:, 2]) + 0.3  # at least ~17° above the plane
        origins_local = unit(d) * rng.uniform(2.0, 3.0, (n, 1)) * max(extent)
        origins_local[:, 2] += 0.25  # above the highest point of the height field
        targets_local = np.c_[rng.uniform(-1.2, 1.2, (n, 2)) * extent, rng.uniform(0.0, 0.2, n)]
    else:
        origins_local = unit(rng.normal(size=(n, 3))) * rng.uniform(2.0, 3.0, (n, 1)) * extent
        targets_local = unit(rng.normal(size=(n, 3))) * rng.uniform(0, 1.4, (n, 1)) * extent
    origins = center + origins_local @ R.T
    return origins, unit(center + targets_local @ R.T - origins)


# ---------------------------------------------------------------------- every geom type against mj_ray
# MuJoCo allows planes only in static bodies
@pytest.mark.parametrize(
    ("name", "moving"),
    [(n, m) for n in CASES for m in (False, True) if not (m and n.startswith("plane"))],
    ids=lambda x: x if isinstance(x, str) else ("moving" if x else "static"),
)
def test_geom_triangles_match_mj_ray(name, moving):
    model, data, rng = one_geom_scene(name, moving)
    split = G.split_static_dynamic(model, data, segments=SEGMENTS)
    caster = RayCaster(threads=1)
    if moving:
        assert len(split.static[1]) == 0 and [b.body_id for b in split.dynamic] == [1]
        body = split.dynamic[0]
        caster.add_mesh(body.vertices, body.faces, movable=True, pose=G.body_pose(data, body.body_id))
    else:
        assert split.dynamic == []
        caster.add_mesh(split.static[0], split.static[1])
    origins, directions = aimed_rays(model, data, rng, CASES[name][2])
    gtype = int(model.geom_type[0])
    mask = None
    if gtype == mujoco.mjtGeom.mjGEOM_HFIELD:
        # MuJoCo closes a height field with side walls and a base; we mesh only its surface
        size = model.hfield_size[0]

        def mask(points):
            local = (points - data.geom_xpos[0]) @ data.geom_xmat[0].reshape(3, 3)
            inside = (np.abs(local[:, 0]) < size[0] - 1e-6) & (np.abs(local[:, 1]) < size[1] - 1e-6)
            return inside & (local[:, 2] > -size[3] + 1e-6)

    curved = gtype in CURVED
    delta = 0.01 if curved else 0.002  # metres; the curved shapes' rims and silhouettes need the wider
    keep, ours, _ = compare(
        model, data, caster, origins, directions, delta=delta, check_normals=curved, mask=mask
    )
    assert keep.sum() >= 0.6 * N_RAYS  # the exclusions leave most rays to compare
    assert (keep & ours.hit).sum() >= 0.25 * N_RAYS
    if name != "plane_infinite":
        assert (keep & ~ours.hit).sum() >= 0.05 * N_RAYS  # and misses too


def test_mesh_geoms_keep_mujoco_faces_including_concave():
    """MuJoCo's mesh faces as given, not a convex hull: the star keeps its volume and its notches."""
    model = mujoco.MjModel.from_xml_string(
        f'<mujoco><asset>{star_prism()}</asset><worldbody><geom type="mesh" mesh="m"/></worldbody></mujoco>'
    )
    v, f = G.geom_triangles(model, 0)
    assert (len(v), len(f)) == (22, 40)
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_watertight and not mesh.is_convex
    assert mesh.volume == pytest.approx(5 * 0.8 * 0.3 * math.sin(math.pi / 5) * 0.5)  # outward winding


@pytest.mark.parametrize("segments", [3, 4, 5, 7, 8, 16, 33, 64])
@pytest.mark.parametrize("kind", ["sphere", "capsule", "cylinder", "ellipsoid"])
def test_curved_facets_are_inscribed_within_the_sagitta(kind, segments):
    """Every vertex on the analytic surface, every facet outward and at most the sagitta deep (checked
    with the support function h(n): a facet with unit normal n through vertex a cuts a cap h(n) - n·a deep).
    """
    size = {"sphere": (0.7, 0, 0), "capsule": (0.4, 0.9, 0), "cylinder": (0.5, 0.3, 0)}
    size["ellipsoid"] = (0.9, 0.5, 0.3)
    s = np.array(size[kind])
    attrs = f'type="{kind}" size="{fmt(s[s > 0])}"'
    model = mujoco.MjModel.from_xml_string(f"<mujoco><worldbody><geom {attrs}/></worldbody></mujoco>")
    v, f = G.geom_triangles(model, 0, segments=segments)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    n = unit(np.cross(b - a, c - a))
    r, h = s[0], s[1]
    if kind == "sphere":
        on_surface, support = np.linalg.norm(v, axis=1) - r, np.full(len(n), r)
    elif kind == "ellipsoid":
        on_surface = np.linalg.norm(v / s, axis=1) - 1.0
        support = np.linalg.norm(n * s, axis=1)
    elif kind == "capsule":
        axis_point = np.clip(v[:, 2], -h, h)
        on_surface = np.linalg.norm(v - np.c_[0 * v[:, :2], axis_point], axis=1) - r
        support = r + h * np.abs(n[:, 2])
    else:
        radial, top = np.linalg.norm(v[:, :2], axis=1), np.abs(v[:, 2])
        on_surface = np.where(radial < r - 1e-9, top - h, np.maximum(radial - r, top - h))
        support = r * np.linalg.norm(n[:, :2], axis=1) + h * np.abs(n[:, 2])
    assert np.abs(on_surface).max() < 1e-9
    assert (np.einsum("ij,ij->i", n, (a + b + c) / 3) > 0).all()  # outward: the shapes contain 0
    depth = support - np.einsum("ij,ij->i", n, a)
    assert depth.max() <= G.sagitta(float(s.max()), segments) + 1e-12


def test_flat_geoms_have_outward_or_up_normals_and_closed_volumes():
    xml = f"""<mujoco><asset>{OCTAHEDRON}{hfield_asset()}</asset><worldbody>
      <geom type="plane" size="2 3 1"/><geom type="box" size="0.1 0.2 0.3"/>
      <geom type="mesh" mesh="m"/><geom type="hfield" hfield="h"/></worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    volumes = {}
    for gid in range(model.ngeom):
        v, f = G.geom_triangles(model, gid)
        assert v.dtype == np.float64 and f.dtype == np.int32
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        volumes[gid] = np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0
        if model.geom_type[gid] in (mujoco.mjtGeom.mjGEOM_PLANE, mujoco.mjtGeom.mjGEOM_HFIELD):
            assert (np.cross(b - a, c - a)[:, 2] > 0).all()
    assert volumes[1] == pytest.approx(0.2 * 0.4 * 0.6)
    assert volumes[2] == pytest.approx(4 / 3 * 0.5 * 0.4 * 0.3)  # octahedron: (4/3)·a·b·c
    v, _ = G.geom_triangles(model, 0)
    assert np.allclose(v.min(0), [-2, -3, 0]) and np.allclose(v.max(0), [2, 3, 0])


def test_infinite_plane_is_a_large_square():
    xml = '<mujoco><worldbody><geom type="plane" size="0 4 1"/><geom type="plane" size="0 0 1"/>'
    model = mujoco.MjModel.from_xml_string(xml + "</worldbody></mujoco>")
    v, _ = G.geom_triangles(model, 0)
    assert np.allclose(v.max(0), [1000, 4, 0])  # one infinite axis
    v, _ = G.geom_triangles(model, 1, infinite_plane_half_m=50.0)
    assert np.allclose(v.min(0), [-50, -50, 0])


def test_mujoco_hfield_conventions_pinned():
    """What MuJoCo does with an MJCF ``elevation`` grid (our triangles read the compiled hfield_data)."""
    xml = """<mujoco><asset><hfield name="h" nrow="2" ncol="3" size="1 1 0.5 0.1"
      elevation="0 2 4  6 8 10"/></asset><worldbody><geom type="hfield" hfield="h"/></worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    # rescaled to [0, 1], and the MJCF rows reversed: its first row becomes the +y edge
    assert np.allclose(model.hfield_data, [0.6, 0.8, 1.0, 0.0, 0.2, 0.4])
    v, f = G.geom_triangles(model, 0)
    assert np.allclose(v[[0, 2, 3, 5]], [[-1, -1, 0.3], [1, -1, 0.5], [-1, 1, 0.0], [1, 1, 0.2]])
    assert len(f) == 2 * 1 * 2


def test_unsupported_geom_types_name_the_geom():
    model = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><geom name="blob" size="1"/></worldbody></mujoco>'
    )
    model.geom_type[0] = mujoco.mjtGeom.mjGEOM_SDF
    with pytest.raises(InputError, match=r"geom 'blob'.*'sdf'"):
        G.geom_triangles(model, 0)
    with pytest.raises(InputError, match="segments"):
        G.geom_triangles(model, 0, segments=2)
    with pytest.raises(InputError, match="no geom"):
        G.geom_triangles(model, 5)


def test_poses_compose():
    model, data, _ = one_geom_scene("box", True)
    T = G.body_pose(data, 1) @ G.geom_in_body(model, 0)
    assert np.allclose(T, G.geom_pose(model, data, 0), atol=1e-12)
    assert np.allclose(T[:3, :3] @ T[:3, :3].T, np.eye(3)) and np.allclose(T[3], [0, 0, 0, 1])


# ---------------------------------------------------------------------- static / dynamic split
SPLIT_XML = """<mujoco><worldbody>
  <geom name="floor" type="plane" size="6 6 0.1"/>
  <body name="wall" pos="3 0 1" euler="0 0 20"><geom name="wall_g" type="box" size=".1 2 1"/>
    <body name="wall_lamp" pos="0 0 1.3"><geom name="lamp_g" type="sphere" size=".3"/></body></body>
  <body name="parked" pos="-3 1 .5"><geom name="parked_g" type="box" size="1 .5 .4"/></body>
  <geom name="ghost" type="box" size=".5 .5 .5" pos="0 -3 .5" rgba="1 1 1 0"/>
  <body name="car" pos="0 0 .6"><freejoint/>
    <geom name="car_g" type="box" size="1 .5 .3" group="3"/>
    <geom name="roof_g" type="box" size=".5 .4 .15" pos="-.2 0 .45" euler="0 10 0" group="3"/>
    <body name="wheel" pos=".7 .6 -.3"><joint name="axle" type="hinge" axis="0 1 0"/>
      <geom name="wheel_g" type="cylinder" size=".3 .1" euler="90 0 0" group="3"/></body></body>
  <body name="actor" mocap="true" pos="0 2.5 .9"><geom name="actor_g" type="box" size=".3 .3 .9"/></body>
</worldbody></mujoco>"""


def ids(model, obj, *names):
    return [mujoco.mj_name2id(model, obj, n) for n in names]


@pytest.fixture(scope="module")
def split_scene():
    model = mujoco.MjModel.from_xml_string(SPLIT_XML)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def test_split_classifies_bodies(split_scene):
    model, data = split_scene
    geom = lambda *n: set(ids(model, mujoco.mjtObj.mjOBJ_GEOM, *n))  # noqa: E731
    car, wheel, actor = ids(model, mujoco.mjtObj.mjOBJ_BODY, "car", "wheel", "actor")
    split = G.split_static_dynamic(model, data)
    assert set(split.static[2]) == geom("floor", "wall_g", "lamp_g", "parked_g", "ghost")
    assert [(b.body_id, b.name) for b in split.dynamic] == [(car, "car"), (wheel, "wheel"), (actor, "actor")]
    assert set(split.dynamic[0].geom_ids_per_face) == geom("car_g", "roof_g")
    for part in [split.static, *((b.vertices, b.faces, b.geom_ids_per_face) for b in split.dynamic)]:
        v, f, g = part
        assert f.dtype == np.int32 and g.shape == (len(f),) and f.max() < len(v)

    no_car = G.split_static_dynamic(model, data, exclude_bodies=[car])  # the whole subtree goes
    assert [b.body_id for b in no_car.dynamic] == [actor]
    assert np.array_equal(no_car.static[1], split.static[1])
    (wall,) = ids(model, mujoco.mjtObj.mjOBJ_BODY, "wall")
    assert set(G.split_static_dynamic(model, data, exclude_bodies=[wall]).static[2]) == geom(
        "floor", "parked_g", "ghost"
    )
    (parked_g,) = geom("parked_g")
    filtered = G.split_static_dynamic(model, data, include_geom=lambda gid: gid != parked_g)
    assert parked_g not in set(filtered.static[2]) and len(filtered.dynamic) == 3
    visible = G.split_static_dynamic(model, data, skip_invisible=True)
    assert set(visible.static[2]) == geom("floor", "wall_g", "lamp_g", "parked_g")
    # the static part does not depend on the state, nor on whether data was forwarded
    fresh = G.split_static_dynamic(model, mujoco.MjData(model)).static
    assert np.allclose(fresh[0], split.static[0]) and np.array_equal(fresh[1], split.static[1])
    with pytest.raises(InputError, match="exclude_bodies"):
        G.split_static_dynamic(model, data, exclude_bodies=[99])


def test_split_scene_after_moving_matches_mj_ray(split_scene):
    model, _ = split_scene
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    car, actor = ids(model, mujoco.mjtObj.mjOBJ_BODY, "car", "actor")
    split = G.split_static_dynamic(
        model, data, segments=SEGMENTS, skip_invisible=True
    )  # mj_ray skips alpha 0
    caster = RayCaster(threads=1)
    static_handle, handles = split.add_to(caster, data)
    rng = np.random.default_rng(3)
    # move everything: the free car, its wheel's hinge, the mocap actor
    data.qpos[:7] = [0.4, -0.3, 0.9, *random_pose(rng)[1]]
    data.qpos[7] = 1.1
    data.mocap_pos[0] = [0.5, 2.2, 1.0]
    data.mocap_quat[0] = random_pose(rng)[1]
    mujoco.mj_forward(model, data)
    G.ModelTriangles.update_poses(caster, handles, data)
    n = 400
    origins = unit(rng.normal(size=(n, 3))) * rng.uniform(5.0, 7.0, (n, 1))
    origins[:, 2] = np.abs(origins[:, 2]) + 0.5  # above the floor, which mj_ray sees from above only
    targets = rng.uniform([-3.5, -3.5, 0.0], [3.5, 3.5, 2.5], (n, 3))
    directions = unit(targets - origins)
    keep, ours, mj_geoms = compare(model, data, caster, origins, directions, delta=0.01, check_normals=True)
    assert keep.sum() >= 0.6 * n and (keep & ours.hit).sum() >= 0.5 * n
    # the faces we hit belong to the geom mj_ray hit
    per_face = {
        static_handle: split.static[2],
        **{handles[b.body_id]: b.geom_ids_per_face for b in split.dynamic},
    }
    ok = np.flatnonzero(keep & ours.hit)
    our_geoms = [
        per_face[ours.mesh_ids[i]][caster.meshes[ours.mesh_ids[i]].face_map[ours.face_ids[i]]] for i in ok
    ]
    assert np.array_equal(our_geoms, mj_geoms[ok])
    assert {actor, car} <= {int(model.geom_bodyid[g]) for g in mj_geoms[ok]}  # rays met the moved bodies

    # without the car (and so its wheel) we agree with mj_ray told to ignore the car's geom group 3
    no_car = G.split_static_dynamic(model, data, segments=SEGMENTS, skip_invisible=True, exclude_bodies=[car])
    caster = RayCaster(threads=1)
    _, handles = no_car.add_to(caster, data)
    assert set(handles) == {actor}
    keep, _, _ = compare(
        model, data, caster, origins, directions, delta=0.01, check_normals=True, geomgroup=[1, 1, 1, 0, 1, 1]
    )
    assert keep.sum() >= 0.6 * n


def test_skip_invisible_follows_mj_ray():
    """Invisible as mj_ray sees it: the material's alpha when the geom has a material, else the geom's."""
    xml = """<mujoco><asset><material name="clear" rgba="1 1 1 0"/><material name="solid" rgba="1 1 1 1"/>
      </asset><worldbody>
      <geom type="box" size=".2 .2 .2" pos="0 0 0" rgba="1 0 0 0"/>
      <geom type="box" size=".2 .2 .2" pos="1 0 0" material="clear" rgba="1 0 0 1"/>
      <geom type="box" size=".2 .2 .2" pos="2 0 0" material="solid" rgba="1 0 0 0"/>
      <geom type="box" size=".2 .2 .2" pos="3 0 0"/></worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    origins = np.c_[np.arange(4.0), np.zeros(4), np.full(4, 5.0)]
    _, _, seen = mj_cast(model, data, origins, np.tile([0.0, 0.0, -1.0], (4, 1)))
    assert list(seen) == [-1, -1, 2, 3]
    kept = G.split_static_dynamic(model, data, skip_invisible=True).static[2]
    assert sorted(set(kept)) == [2, 3]
    assert sorted(set(G.split_static_dynamic(model, data).static[2])) == [0, 1, 2, 3]


# ---------------------------------------------------------------------- files
def test_export_static_mesh_round_trips(split_scene, tmp_path):
    model, _ = split_scene
    path = G.export_static_mesh(model, tmp_path / "gt.ply", segments=16)
    vertices, faces, _ = G.split_static_dynamic(model, segments=16).static
    loaded = trimesh.load(path, process=False)
    assert len(loaded.faces) == len(faces) and len(loaded.vertices) == len(vertices)
    assert np.allclose(loaded.bounds, [vertices.min(0), vertices.max(0)], atol=1e-6)
    assert os.listdir(tmp_path) == ["gt.ply"]  # no temporary file left behind
    with open(path, "rb") as f:
        assert f.read(64).startswith(b"ply\nformat binary_little_endian")


def test_write_ply_errors_name_the_path(tmp_path):
    v, f = np.eye(3), np.array([[0, 1, 2]], np.int32)
    missing = tmp_path / "nope" / "gt.ply"
    with pytest.raises(InputError, match=f"cannot write {missing}.*does not exist"):
        G.write_ply(missing, v, f)
    (tmp_path / "file").write_text("x")
    with pytest.raises(InputError, match="is not a folder"):
        G.write_ply(tmp_path / "file" / "gt.ply", v, f)
    (tmp_path / "taken.ply").mkdir()  # the path is a folder: the final rename fails
    with pytest.raises(InputError, match=f"cannot write {tmp_path / 'taken.ply'}"):
        G.write_ply(tmp_path / "taken.ply", v, f)
    assert sorted(os.listdir(tmp_path)) == ["file", "taken.ply"]  # the temporary file was removed
    empty = mujoco.MjModel.from_xml_string(
        "<mujoco><worldbody><body><freejoint/><geom size='1'/></body></worldbody></mujoco>"
    )
    with pytest.raises(InputError, match="no static geometry"):
        G.export_static_mesh(empty, tmp_path / "e.ply")
