"""The scan's points on objects that may be parked vehicles (:func:`vehicle_points`), on scans cast in a
scene whose every object is known, and their removal from the rays the localizer draws."""

from __future__ import annotations

import numpy as np
import pytest

from rangemcl import meshgen
from rangemcl.localization.scan_prep import select_rays, top_elevation, vehicle_points
from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.raycast import RayCaster
from rangemcl.sensors import load_spec

HEIGHT = 1.73
# name: (size, centre) of boxes standing on the ground (z = 0)
OBJECTS = {
    "car": ((4.5, 1.8, 1.5), (9.0, 4.5)),
    "van": ((5.5, 2.0, 2.4), (-9.0, -4.5)),
    "building": ((20.0, 8.0, 9.0), (12.0, -12.0)),
    "pole": ((0.3, 0.3, 5.0), (4.0, -4.0)),
    "wall": ((16.0, 0.3, 1.2), (-12.0, 7.0)),  # a long low wall: structure, however low
    "row": ((4.5, 1.8, 1.5), (-18.0, -4.5)),  # two cars bumper to bumper: one 9 m object, kept
    "row2": ((4.5, 1.8, 1.5), (-22.5, -4.5)),
    "kiosk": ((6.5, 2.5, 4.5), (-5.0, 20.0)),  # vehicle-sized but taller than the movable height
}
VEHICLES = {"car", "van"}


def scene_scan(sensor: str):
    ground = meshgen.grid_patch((-40.0, -40.0, 0.0), (80.0, 0, 0), (0, 80.0, 0), 40, 40)
    parts = [ground]
    for (sx, sy, sz), (x, y) in OBJECTS.values():
        parts.append(meshgen.box((sx, sy, sz), (x, y, sz / 2), cell_m=0.5))
    caster = RayCaster(threads=2)
    caster.add_mesh(*meshgen.merge(parts), name="scene")
    geo = RangeImageGeometry.for_spec(load_spec(sensor).with_columns(1024))
    d = geo.directions.reshape(-1, 3)
    hits = caster.cast(np.array([0.0, 0.0, HEIGHT]), d, 40.0)
    pts = d[hits.hit] * hits.ranges[hits.hit, None]
    world = pts + np.array([0.0, 0.0, HEIGHT])
    which = np.full(len(pts), "ground", dtype=object)
    for name, ((sx, sy, _), (x, y)) in OBJECTS.items():
        inside = (np.abs(world[:, 0] - x) <= sx / 2 + 0.05) & (np.abs(world[:, 1] - y) <= sy / 2 + 0.05)
        which[inside & (world[:, 2] > 0.05)] = name
    return pts, which


@pytest.mark.parametrize("sensor", ["os1-64", "mq-8"])
def test_points_on_car_sized_objects_are_found_and_nothing_else(sensor):
    """A car and a van are found; the ground, a building (cut in two by a pole in front of it, as the
    MQ-8 sees it), the pole, a long low wall, two cars bumper to bumper (one of them half hidden by the
    van) are not."""
    pts, which = scene_scan(sensor)
    flagged = vehicle_points(pts, HEIGHT, max_length_m=7.0, max_height_m=4.0)
    for name in ("car", "van"):
        on = which == name
        assert on.sum() > 10, name  # the sensor sees it
        assert flagged[on & (pts[:, 2] + HEIGHT > 0.5)].all(), name
    for name in ("ground", "building", "pole", "wall", "row", "row2"):
        assert not flagged[which == name].any(), name
    # the kiosk is kept by a sensor that sees it rise above the movable height; without the height limit
    # it is a vehicle. The MQ-8 sees only its lowest 1.7 m, and cannot tell it from one.
    kiosk = (which == "kiosk") & (pts[:, 2] + HEIGHT > 0.5)
    anyheight = vehicle_points(pts, HEIGHT, max_length_m=7.0, max_height_m=None)
    assert kiosk.sum() > 10 and anyheight[kiosk].mean() > 0.9
    assert flagged[kiosk].mean() == (0.0 if sensor == "os1-64" else pytest.approx(anyheight[kiosk].mean()))


def test_the_rays_leave_out_the_vehicles_points():
    pts, _ = scene_scan("os1-64")
    rng = np.random.default_rng(0)
    common = dict(
        rays=100000,
        sampling="points",
        ground_share=0.2,
        tall_share=0.6,
        tall_m=2.0,
        min_range_m=2.0,
        max_range_m=40.0,
        deskew=False,
        level_with_imu=False,
        sensor_height_m=HEIGHT,
    )
    every = select_rays(pts, rng, vehicle_length_m=None, movable_height_m=None, **common)
    kept = select_rays(pts, rng, vehicle_length_m=7.0, movable_height_m=4.0, **common)
    on_vehicle = vehicle_points(pts, HEIGHT, 7.0, 4.0)
    r = np.linalg.norm(pts, axis=1)
    in_range = (r >= 2.0) & (r <= 40.0)
    assert len(every.ranges) == in_range.sum()
    assert len(kept.ranges) == (in_range & ~on_vehicle).sum() < len(every.ranges)
    assert kept.valid_points == every.valid_points  # the scan's valid points, before any is left out


def test_top_elevation_is_the_brute_force_maximum_on_random_scans():
    """The top beam's elevation from the steepest few points only is exactly the arctangent's maximum
    over every point: random scans of 1-60 points at scales from millimetres to 100 m, all below the
    horizon, points straight above or below the sensor (r = 0) and at the sensor itself (0 / 0)."""
    rng = np.random.default_rng(7)
    for t in range(3000):
        n = int(rng.integers(1, 60))
        p = rng.normal(size=(n, 3)) * rng.choice([1e-3, 1.0, 100.0])
        if t % 3 == 0:
            p[:, 2] = -np.abs(p[:, 2])
        if t % 5 == 0:
            p[rng.integers(n), :2] = 0.0
        if t % 11 == 0:
            p[rng.integers(n)] = 0.0
        expected = float(np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])).max())
        assert top_elevation(p) == expected, (t, p)


def test_lit_returns_leave_out_zero_intensity_only_where_some_return_is_lit():
    """The returns above zero intensity, where any is; all of them when none is (the ideal sensor, a
    source without intensity); an intensity array of another length is one error."""
    from rangemcl.errors import InputError
    from rangemcl.localization.scan_prep import lit_returns

    rng = np.random.default_rng(3)
    it = np.where(rng.random(1000) < 0.7, 0.0, rng.uniform(0.01, 1.0, 1000))
    assert np.array_equal(lit_returns(it, 1000), it > 0)
    assert lit_returns(np.zeros(50), 50).all() and len(lit_returns(np.zeros(50), 50)) == 50
    with pytest.raises(InputError, match="intensity of 49 returns for a scan of 50 points"):
        lit_returns(np.ones(49), 50)
