"""The whole-mesh checks and the place prior's matching run a chunk at a time (on whole arrays, loading
town_large's map peaked at 1.8 GB in their temporaries): the chunked results equal a direct whole-array
computation, whatever the chunk size."""

from __future__ import annotations

import numpy as np
import pytest

from rangemcl.errors import InputError
from rangemcl.localization import place_prior as pp
from rangemcl.maps import meshmap
from rangemcl.raycast import clean_mesh


def soup(rng, n=1000):
    v = rng.uniform(-50, 50, (3 * n, 3))
    f = np.arange(3 * n, dtype=np.int32).reshape(n, 3)
    return v, f


@pytest.mark.parametrize("chunk", [1, 7, 1 << 20])
def test_face_tiles_and_validation_in_chunks(monkeypatch, chunk):
    rng = np.random.default_rng(0)
    v, f = soup(rng)
    monkeypatch.setattr(meshmap, "_CHUNK_FACES", chunk)
    tri = v[f]
    want = np.floor(((tri[:, 0, :2] + tri[:, 1, :2] + tri[:, 2, :2]) / 3.0 - (-60.0, -60.0)) / 20.0)
    got = meshmap.face_tile_ij(v, f, (-60.0, -60.0), 20.0)
    assert got.dtype == np.int64 and np.array_equal(got, want.astype(np.int64))
    tiles, face_tile = np.unique(got, axis=0, return_inverse=True)
    assert meshmap._tiling_matches(tiles, face_tile.ravel(), v, f, (-60.0, -60.0), 20.0)
    face_tile[-1] = (face_tile[-1] + 1) % len(tiles)  # the last face in the last chunk
    assert not meshmap._tiling_matches(tiles, face_tile.ravel(), v, f, (-60.0, -60.0), 20.0)
    # degenerate triangles everywhere but in the last chunk: valid; everywhere: one line
    flat = v.copy()
    flat[: 3 * 999] = flat[0]
    vv, ff = meshmap._validate_mesh(flat, f)
    assert ff.dtype == np.int32 and np.shares_memory(vv, flat)
    flat[-3:] = flat[0]
    with pytest.raises(InputError, match="all 1000 triangles are degenerate"):
        meshmap._validate_mesh(flat, f)


def test_clean_mesh_keeps_the_same_faces_as_a_direct_computation():
    rng = np.random.default_rng(1)
    v, f = soup(rng, 3000)
    v[f[::5, 1]] = v[f[::5, 0]]  # every fifth triangle has no area
    _, faces, kept = clean_mesh("soup", v, f)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    scale = np.ptp(v, axis=0).max()
    want = np.flatnonzero(np.linalg.norm(np.cross(b - a, c - a), axis=1) > 1e-12 * scale * scale)
    assert np.array_equal(kept, want) and len(kept) == 2400 and np.array_equal(faces, f[want])


def test_prior_matching_in_chunks_equals_one_pass(monkeypatch):
    rng = np.random.default_rng(2)
    params = pp.PriorParams()
    prior = pp.PlacePrior(rng.uniform(0, 50, (50, 2)), rng.integers(0, 255, (50, 2, params.bins)), params)
    profile = rng.uniform(0, 30, (2, params.bins))
    known = rng.uniform(0, 1, (2, params.bins)) > 0.3
    whole = prior.match(profile, known)
    monkeypatch.setattr(pp, "_MATCH_CHUNK", 7)
    chunked = prior.match(profile, known)
    assert np.array_equal(whole.cost, chunked.cost) and np.array_equal(whole.yaw, chunked.yaw)
    # the cost at the best yaw is the direct masked squared difference there (up to the yaw refinement)
    band = whole.band
    m = known[band].astype(float)
    q = np.log1p(profile[band])
    enc = np.log1p(prior.profiles[:, band].astype(float) * params.quant_m)
    direct = np.array([[np.sum(m * (q - np.roll(c, -s)) ** 2) for s in range(params.bins)] for c in enc])
    assert np.allclose(whole.cost, direct.min(axis=1) / m.sum(), atol=1e-9)
