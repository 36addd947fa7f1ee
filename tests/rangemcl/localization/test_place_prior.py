"""The place prior: the yaw search recovers a known rotation to one bin, the FFT matching equals a direct
search over every shift, the true cell ranks first in a synthetic town of distinct places, and the prior
is stored in the map folder and rebuilt when the map changes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from rangemcl import meshgen
from rangemcl.errors import InputError
from rangemcl.localization.place_prior import (
    BEAM_MAX_RANGE_M,
    PRIOR_FILE,
    PlacePrior,
    PriorParams,
    beam_params,
    circular_distance_deg,
    elevations_deg,
    grid_cells,
    load_or_build,
    scan_profile,
    sequence_costs,
    top_beam_deg,
)
from rangemcl.maps.meshmap import MeshMap
from rangemcl.rangeimage import RangeImageGeometry
from rangemcl.raycast import RayCaster
from rangemcl.sensors import load_spec

HEIGHT = 1.73


@pytest.fixture(scope="module")
def town():
    t = meshgen.town(seed=11, size_m=100.0, n_buildings=18, n_poles=25, facade_cell_m=2.0, ground_cell_m=2.0)
    v, f = t.merged()
    caster = RayCaster(threads=2)
    caster.add_mesh(v, f, name="town")
    m = MeshMap.from_mesh(v, f, tile_size_m=50.0, meta={"sensor_height_m": HEIGHT})
    # the cells along the roads (where a car drives), every 2 m
    along = np.arange(-47.0, 47.0, 2.0) + 1.0
    cells = np.unique(
        np.vstack(
            [
                np.column_stack([along, np.full_like(along, r + o)])
                for r in t.road_xy
                for o in (-3.0, -1.0, 1.0, 3.0)
            ]
            + [
                np.column_stack([np.full_like(along, r + o), along])
                for r in t.road_xy
                for o in (-3.0, -1.0, 1.0, 3.0)
            ]
        ),
        axis=0,
    )
    prior = PlacePrior.build(caster, cells, m.ground.height_at(cells[:, 0], cells[:, 1]))
    return t, caster, m, prior


def scan(t, caster, x, y, yaw, sensor="os1-64", columns=720):
    geo = RangeImageGeometry.for_spec(load_spec(sensor).with_columns(columns))
    z = float(t.ground_height(x, y)) + HEIGHT
    c, s = math.cos(yaw), math.sin(yaw)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    d = geo.directions.reshape(-1, 3)
    hits = caster.cast(np.array([x, y, z]), d @ R.T, 80.0)
    return d[hits.hit] * hits.ranges[hits.hit, None]


def test_fft_matching_equals_a_direct_search_over_every_shift():
    rng = np.random.default_rng(0)
    params = PriorParams(bins=72)
    profiles = rng.integers(10, 240, (30, 2, 72)).astype(np.uint8)
    prior = PlacePrior(rng.uniform(0, 50, (30, 2)), profiles, params)
    q = rng.uniform(2.0, 30.0, (2, 72))
    for band, known_high in ((1, 0.6), (0, 0.05)):  # the high band when the scan knows enough of it
        known = np.stack([rng.uniform(size=72) < 0.6, rng.uniform(size=72) < known_high])
        m = prior.match(q, known)
        assert m.band == band
        enc_q = np.log1p(q[band])
        enc_c = np.log1p(profiles[:, band] * params.quant_m)
        mask = known[band]
        for k in range(30):
            costs = [np.mean((enc_q - np.roll(enc_c[k], -s))[mask] ** 2) for s in range(72)]
            assert m.cost[k] == pytest.approx(min(costs), abs=1e-9)
            s_best = int(np.argmin(costs))
            assert circular_distance_deg(m.yaw[k], s_best * 2 * math.pi / 72) <= 0.5 * 360 / 72 + 1e-9


def test_kept_cell_spectra_give_the_same_match_to_the_bit_and_are_counted():
    """The cell spectra kept from the first match give every later match (all cells, or some) the costs
    and yaws computed without them, to the bit; a prior whose spectra would pass spectra_max_mb keeps
    none; nbytes counts what is kept."""
    rng = np.random.default_rng(3)
    params = PriorParams(bins=72)
    K = 1300  # more than two of the match's chunks
    profiles = rng.integers(10, 240, (K, 2, 72)).astype(np.uint8)
    xy = rng.uniform(0, 50, (K, 2))
    kept, fresh = PlacePrior(xy, profiles, params), PlacePrior(xy, profiles, params)
    fresh.spectra_max_mb = 0
    before = kept.nbytes
    for _ in range(4):
        q = rng.uniform(2.0, 30.0, (2, 72))
        known = rng.uniform(size=(2, 72)) < 0.6
        for cells in (None, rng.choice(K, 700, replace=False)):
            a, b = kept.match(q, known, cells=cells), fresh.match(q, known, cells=cells)
            np.testing.assert_array_equal(a.cost, b.cost)
            np.testing.assert_array_equal(a.yaw, b.yaw)
    assert kept._spectra[1] is not None and fresh._spectra[1] is None
    assert kept.nbytes == before + 2 * K * (72 // 2 + 1) * 16 and fresh.nbytes == before


def test_yaw_search_recovers_a_known_rotation_to_one_bin(town):
    t, caster, _m, prior = town
    rng = np.random.default_rng(1)
    step = 360.0 / prior.params.bins
    for k in rng.choice(len(prior.xy), 8, replace=False):
        x, y = prior.xy[k]
        yaw = rng.uniform(-math.pi, math.pi)
        prof, known = scan_profile(scan(t, caster, x, y, yaw), HEIGHT, prior.params)
        got = prior.match(prof, known).yaw[k]
        assert circular_distance_deg(got, yaw) <= step  # to one column of the 360-bin profile


def test_true_cell_ranks_first_in_a_town_of_distinct_places(town):
    t, caster, _m, prior = town
    rng = np.random.default_rng(2)
    ranks = []
    for sensor in ("vlp-16", "hdl-64e", "mq-8"):
        for k in rng.choice(len(prior.xy), 6, replace=False):
            x, y = prior.xy[k]
            pts = scan(t, caster, x, y, rng.uniform(-math.pi, math.pi), sensor)
            prof, known = scan_profile(pts, HEIGHT, prior.params)
            cost = prior.match(prof, known).cost
            ranks.append(int((cost < cost[k]).sum()))
    # the true cell first for (nearly) every scan, and never outside the best 1 % of the cells
    assert np.mean(np.array(ranks) == 0) >= 0.85, ranks
    assert max(ranks) <= 0.01 * len(prior.xy), ranks


def test_the_two_stage_match_keeps_the_true_cell_and_the_exact_costs_of_its_shortlist(town, monkeypatch):
    """A city's prior is matched in two stages (6-degree bins for every cell, then the shortlist on the
    full bins): forced here with a shortlist of 5 % of the synthetic town's cells, the shortlisted cells
    carry exactly the one-stage costs and yaws, the others an infinite cost, and the true cell is still
    first for (nearly) every scan."""
    from rangemcl.localization import place_prior as pp

    t, caster, _m, prior = town
    monkeypatch.setattr(pp, "SHORTLIST", max(10, len(prior.xy) // 20))
    rng = np.random.default_rng(3)
    first = 0
    for sensor in ("vlp-16", "hdl-64e", "mq-8"):
        for k in rng.choice(len(prior.xy), 6, replace=False):
            x, y = prior.xy[k]
            pts = scan(t, caster, x, y, rng.uniform(-math.pi, math.pi), sensor)
            prof, known = scan_profile(pts, HEIGHT, prior.params)
            one = prior.match(prof, known, two_stage=False)
            two = prior.match(prof, known, two_stage=True)
            short = np.isfinite(two.cost)
            assert short.sum() == pp.SHORTLIST
            np.testing.assert_array_equal(two.cost[short], one.cost[short])
            np.testing.assert_array_equal(two.yaw[short], one.yaw[short])
            first += int(np.argmin(two.cost) == k)
    assert first >= 0.85 * 18, first
    assert prior._coarse.shape == (len(prior.xy), 2, prior.params.bins // pp.COARSE_FACTOR)
    # each coarse bin is the nearest of its fine bins
    fine = prior.profiles.reshape(len(prior.xy), 2, -1, pp.COARSE_FACTOR)
    np.testing.assert_array_equal(prior._coarse, fine.min(axis=3))


def test_a_match_of_some_cells_gives_them_their_whole_match_costs(town):
    """``cells``: the subset's costs and yaws are those of the match of every cell, the rest infinite, and
    candidates() ranks only among them."""
    t, caster, _m, prior = town
    rng = np.random.default_rng(5)
    k = int(rng.integers(len(prior.xy)))
    pts = scan(t, caster, *prior.xy[k], 0.7, "hdl-32e")
    prof, known = scan_profile(pts, HEIGHT, prior.params)
    whole = prior.match(prof, known, two_stage=False)
    some = np.sort(rng.choice(len(prior.xy), len(prior.xy) // 3, replace=False))
    part = prior.match(prof, known, cells=some)
    np.testing.assert_array_equal(part.cost[some], whole.cost[some])
    np.testing.assert_array_equal(part.yaw[some], whole.yaw[some])
    assert np.isinf(np.delete(part.cost, some)).all()
    xy, _yaw, _cost, _known = prior.candidates(pts, HEIGHT, 5, cells=some)
    best = some[np.argsort(whole.cost[some], kind="stable")[:5]]
    np.testing.assert_array_equal(xy, prior.xy[best])


def test_profile_of_a_scan_keeps_only_the_height_bands_and_marks_empty_bins():
    p = PriorParams(bins=4)
    pts = np.array(
        [
            [5.0, 0.0, -1.73 + 1.0],  # 1 m above the ground, straight ahead: low band (bin 2 of 4: 0..90 deg)
            [3.0, 0.0, -1.73 + 0.1],  # road: dropped
            [-8.0, 0.1, -1.73 + 1.5],  # behind (bin 3, just below 180 deg): low band
            [0.0, -6.0, -1.73 + 3.0],  # 3 m up on the right (bin 1): high band
            [0.0, -9.0, -1.73 + 5.0],  # too high for either
        ]
    )
    prof, known = scan_profile(pts, 1.73, p)
    assert known.tolist() == [[False, False, True, True], [False, True, False, False]]
    assert prof[0, 2] == pytest.approx(5.0) and prof[0, 3] == pytest.approx(math.hypot(8.0, 0.1))
    assert prof[1, 1] == pytest.approx(6.0)
    assert prof[0, 0] == p.max_range_m


def _group_distance(ri: np.ndarray, k: int) -> float | None:
    """The brute-force reference: the nearest of a bin's distances with k of them (itself included)
    within one surface's spread at or beyond it."""
    for x in np.sort(ri):
        if ((ri >= x) & (ri <= x + max(0.2, 0.1 * x))).sum() >= k:
            return float(x)
    return None


def test_a_profile_bin_of_k_returns_ignores_scattered_spurious_returns():
    """returns=k: each bin the nearest distance at which k returns lie within one surface's spread
    (max(0.2 m, 10 % of the distance)), a bin without such a group unknown; so droplets scattered near the
    sensor do not set a bin that a wall fills with its pulses, even several in one bin; k=1 is the
    nearest, as before. Checked against a brute-force search of each bin on random walls and droplets."""
    rng = np.random.default_rng(4)
    p = PriorParams(bins=36)
    walls = rng.uniform(6.0, 25.0, 36)  # one wall per 10-degree bin, several pulses on it (within 30 m)
    az = rng.uniform(-np.pi, np.pi, 600)
    b = np.clip(((az + np.pi) / (2 * np.pi) * 36).astype(int), 0, 35)
    r = walls[b] + rng.normal(0.0, 0.02, len(az))
    drops = rng.choice(len(az), 40, replace=False)  # droplets: some pulses return at 1.5-5 m
    r[drops] = rng.uniform(p.min_range_m, 5.0, len(drops))
    pts = np.column_stack([r * np.cos(az), r * np.sin(az), np.full(len(az), -1.73 + 1.0)])
    horizontal = np.hypot(pts[:, 0], pts[:, 1])
    for k in (1, 2, 3, 4):
        prof, known = scan_profile(pts, 1.73, p, returns=k)
        for i in range(36):
            ri = horizontal[(b == i) & (horizontal >= p.min_range_m)]
            want = _group_distance(ri, k)
            assert known[0, i] == (want is not None)
            assert prof[0, i] == (p.max_range_m if want is None else want)
    one = scan_profile(pts, 1.73, p, returns=1)[0][0]
    three = scan_profile(pts, 1.73, p, returns=3)[0][0]
    hit, times = np.unique(b[drops], return_counts=True)
    assert (times >= 2).sum() >= 5  # bins with several droplets: a k-th nearest return would take one
    assert (one[hit] < 5.0 + 1e-9).all()
    assert (np.abs(three[hit] - walls[hit]) < 0.1).mean() >= 0.9  # droplets this dense rarely group
    assert np.array_equal(one, scan_profile(pts, 1.73, p)[0][0])  # the default is k = 1
    assert np.array_equal(one, np.array([horizontal[b == i].min() for i in range(36)]))  # all >= 1.5 m


def test_a_profile_bin_of_k_returns_keeps_a_far_sparse_surface():
    """A wall far away that one ring crosses with a handful of pulses per bin, at grazing incidence (its
    distances spread over the bin), still sets the bin with k = 3: the spread allowed grows with the
    distance."""
    p = PriorParams(bins=360)
    az = np.radians(np.arange(0.1, 1.0, 0.2))  # 5 pulses in bin 180 (0-1 degree)
    r = 5.0 / np.cos(az + np.radians(75.0))  # a wall 5 m away, hit at 75-76 degrees' incidence: 19-21 m
    pts = np.column_stack([r * np.cos(az), r * np.sin(az), np.full(len(az), -1.73 + 1.0)])
    prof, known = scan_profile(pts, 1.73, p, returns=3)
    assert known[0, 180] and known[0].sum() == 1
    assert prof[0, 180] == pytest.approx(np.hypot(pts[:, 0], pts[:, 1]).min())


CORNERS = np.array([[0.0, -27.0], [10.0, -27.0], [20.0, 23.0]])  # a few drivable cells of the town


def _saved_map(m, tmp_path) -> MeshMap:
    """The town's map saved to a folder and loaded from it (a prior is stored beside it)."""
    m.save(tmp_path / "map")
    return MeshMap.load(tmp_path / "map")


def test_prior_is_stored_in_the_map_folder_and_rebuilt_when_the_map_changes(town, tmp_path):
    _t, caster, m, _ = town
    loaded = _saved_map(m, tmp_path)
    corners = CORNERS
    p1, how1 = load_or_build(loaded, caster, corners, 1.0)
    assert how1 == "built" and (tmp_path / "map" / PRIOR_FILE).is_file()
    p2, how2 = load_or_build(loaded, caster, corners, 1.0)
    assert how2 == "loaded" and np.array_equal(p1.profiles, p2.profiles)
    assert np.allclose(p1.xy, grid_cells(corners, 1.0, 2.0))
    # other cells (another drivable area, another map) do not match the stored key
    _, how3 = load_or_build(loaded, caster, corners[:2], 1.0)
    assert how3 == "built"
    (tmp_path / "map" / PRIOR_FILE).write_bytes(b"not a zip")
    with pytest.raises(InputError, match="place prior"):
        load_or_build(loaded, caster, corners, 1.0)


def test_a_prior_rendered_with_tiles_held_coarse_is_not_taken_for_the_whole_maps(town, tmp_path):
    """Within a budget too small for the tiles in range at full resolution, the prior is rendered partly
    from the coarse level: stored under its own key, which later runs within a budget load and a run with
    the whole map does not; within a budget that holds them all, the prior is the whole map's."""
    from rangemcl.localization.place_prior import PARTIAL, prior_key
    from rangemcl.maps.view import MapView

    _t, caster, m, _ = town
    m.save(tmp_path / "map", coarse_ratio=0.05)
    corners = CORNERS

    # the ground grid and the drive count against a budget too: the budgets below are the tiles' share
    probe = MapView(tmp_path / "map", 100.0, RayCaster(threads=2))
    derived_mb = sum(probe.derived.values()) / 1e6
    probe.close()

    def in_view(tiles_mb: float):
        view = MapView(tmp_path / "map", tiles_mb + derived_mb, RayCaster(threads=2))
        try:
            return load_or_build(view, view.caster, corners, 1.0), prior_key(
                view, grid_cells(corners, 1.0, 2.0), PriorParams()
            )
        finally:
            view.close()

    (small, how), key = in_view(0.12)  # every tile coarse, a few small ones at full resolution
    assert how == "built"
    assert PlacePrior.load(tmp_path / "map" / PRIOR_FILE, key + PARTIAL) is not None
    assert PlacePrior.load(tmp_path / "map" / PRIOR_FILE, key) is None
    assert in_view(0.12)[0][1] == "loaded"
    whole, how = load_or_build(MeshMap.load(tmp_path / "map"), caster, corners, 1.0)
    assert how == "built" and not np.array_equal(whole.profiles, small.profiles)
    (tmp_path / "map" / PRIOR_FILE).unlink()
    (full, how), _ = in_view(100.0)
    assert how == "built" and np.array_equal(full.profiles, whole.profiles)
    assert PlacePrior.load(tmp_path / "map" / PRIOR_FILE, key) is not None


def _line_prior(rng, cells=11, bins=72):
    """Cells every 2 m along x with random profiles (both bands alike)."""
    xy = np.column_stack([np.arange(cells) * 2.0, np.zeros(cells)])
    prof = rng.integers(8, 240, (cells, 1, bins)).astype(np.uint8).repeat(2, axis=1)
    return PlacePrior(xy, prof, PriorParams(bins=bins))


def test_sequence_costs_separate_look_alikes_by_the_scans_before():
    """Cells 5 and 8 look alike to today's scan; 2 m behind cell 5 lies what the scan 2 m back saw, behind
    cell 8 not: over the sequence cell 5 wins, and today's match alone ties them."""
    rng = np.random.default_rng(5)
    prior = _line_prior(rng)
    prior.profiles[8] = prior.profiles[5]
    q = prior.params.quant_m
    today = prior.profiles[5].astype(np.float64) * q
    before = prior.profiles[4].astype(np.float64) * q
    known = np.ones_like(today, bool)
    now = prior.match(today, known)
    assert now.cost[5] == pytest.approx(now.cost[8]) and now.cost[5] == pytest.approx(0.0, abs=1e-9)
    past = [(prior.match(before, known), np.array([-2.0, 0.0, 0.0]))]  # 2 m behind, same heading
    c = sequence_costs(prior, now, past)
    assert np.argmin(c) == 5 and c[8] > c[5] + 0.1


def test_top_beam_is_the_highest_ring_of_returns_despite_stray_points():
    rng = np.random.default_rng(5)
    rings = np.radians([-14.0, -8.1, -3.17, -2.37, -1.57])
    az = rng.uniform(-math.pi, math.pi, (len(rings), 2000))
    el = np.broadcast_to(rings[:, None], az.shape)
    r = rng.uniform(3.0, 60.0, az.shape)
    pts = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], -1).reshape(
        -1, 3
    )
    stray = np.column_stack([rng.uniform(5, 20, 20), rng.uniform(-5, 5, 20), rng.uniform(1, 5, 20)])
    assert top_beam_deg(np.vstack([pts, stray])) == pytest.approx(-1.57, abs=1e-6)
    assert top_beam_deg(pts[:100]) is None  # too few points to tell


def _tilted_scan(t, caster, x, y, yaw, pitch, sensor="mq-8", columns=720):
    """A scan from a sensor pitched by ``pitch`` (radians): the raw points (sensor frame) and the points
    levelled by that pitch."""
    geo = RangeImageGeometry.for_spec(load_spec(sensor).with_columns(columns))
    z = float(t.ground_height(x, y)) + HEIGHT
    c, s = math.cos(yaw), math.sin(yaw)
    Rz = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    cp, sp = math.cos(pitch), math.sin(pitch)
    Ry = np.array([[cp, 0, sp], [0, 1.0, 0], [-sp, 0, cp]])
    d = geo.directions.reshape(-1, 3)
    hits = caster.cast(np.array([x, y, z]), d @ (Rz @ Ry).T, 120.0)
    raw = d[hits.hit] * hits.ranges[hits.hit, None]
    return raw, raw @ Ry.T


def test_a_beam_prior_ranks_the_true_cell_first_for_a_sensor_below_the_horizon(town):
    t, caster, m, band_prior = town
    rng = np.random.default_rng(6)
    raw0, _ = _tilted_scan(t, caster, *band_prior.xy[0], 0.0, 0.0)
    params = beam_params(PriorParams(), top_beam_deg(raw0), HEIGHT)
    assert params.beam_deg == pytest.approx(-1.57) and params.rows == 1 and params.dtype == np.uint16
    prior = PlacePrior.build(caster, band_prior.xy, m.ground.height_at(*band_prior.xy.T), params)
    ranks, yaw_err = [], []
    for k in rng.choice(len(prior.xy), 8, replace=False):
        x, y = prior.xy[k]
        yaw = rng.uniform(-math.pi, math.pi)
        raw, levelled = _tilted_scan(t, caster, x, y, yaw, math.radians(0.6))
        _, known_bands = scan_profile(levelled, HEIGHT, band_prior.params)
        assert known_bands[1].sum() == 0  # nothing 2 m up: the band prior would use its low band
        # the ring is picked by its elevation before levelling (0.6 degrees of pitch would mix it with the
        # next ring's, 0.8 degrees below)
        prof, known = scan_profile(levelled, HEIGHT, params, elevations_deg(raw))
        assert known.shape == (1, params.bins) and known.mean() > 0.5  # off the town: no return
        mt = prior.match(prof, known)
        ranks.append(int((mt.cost < mt.cost[k]).sum()))
        yaw_err.append(float(circular_distance_deg(mt.yaw[k], yaw)))
    assert np.mean(np.array(ranks) == 0) >= 0.85 and max(ranks) <= 0.01 * len(prior.xy), ranks
    assert max(yaw_err) <= 2 * 360.0 / params.bins, yaw_err


def test_a_beam_prior_is_stored_beside_the_band_prior_which_keeps_its_key(town, tmp_path):
    _t, caster, m, _ = town
    loaded = _saved_map(m, tmp_path)
    corners = CORNERS
    band, _ = load_or_build(loaded, caster, corners, 1.0)
    params = beam_params(PriorParams(), -1.571, HEIGHT)
    beam, how = load_or_build(loaded, caster, corners, 1.0, params)
    assert how == "built" and (tmp_path / "map" / params.file_name).is_file()
    assert params.file_name != PRIOR_FILE and beam.profiles.shape == (len(band.xy), 1, params.bins)
    again, how = load_or_build(loaded, caster, corners, 1.0, params)
    assert how == "loaded" and again.params == params and np.array_equal(again.profiles, beam.profiles)
    assert load_or_build(loaded, caster, corners, 1.0)[1] == "loaded"  # the band prior untouched
    # a band prior's key is what it was before beam priors existed (stored priors stay valid)
    assert "beam_deg" not in PriorParams().key_dict() and "beam_deg" in params.key_dict()
    # the beam's hits are stored as horizontal distances, up to BEAM_MAX_RANGE_M
    assert beam.profiles.max() * params.quant_m <= BEAM_MAX_RANGE_M + 1e-9
    with pytest.raises(InputError, match="bad beam"):
        beam_params(PriorParams(), -75.0, HEIGHT).check()
