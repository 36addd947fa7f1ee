"""From rays to echoes: what a pulse of the realistic sensor meets, and which echoes the sensor reports.

A pulse is not a line. Its footprint grows with the beam divergence, so at a depth edge part of it lands on
the foreground and part on the background; glass passes most of it on; fog and rain scatter some of it
back. Each pulse is traced as samples, each sample as a chain of surfaces, and what comes back is grouped
into echoes:

* **Samples.** Every pulse is traced along its axis. Where the axis' range differs from a horizontal
  neighbour's by more than :data:`EDGE_M` (or one of them meets nothing), a depth edge may cross the
  footprint, and four more samples are traced at half the divergence to each side (left, right, up,
  down). The axis carries :data:`AXIS_WEIGHT` of the energy and the four the rest (a Gaussian beam's
  energy within and beyond its half width, roughly); elsewhere the axis carries all of it.
* **Chains.** A sample that meets glass records the glass's own return and goes on, dimmed by its two-way
  transmission, up to :data:`GLASS_SURFACES` surfaces; the next surface ends it.
* **Echoes.** All returns of a pulse (every sample's chain, and the weather's, see
  :class:`simbed.sim.weather.Weather`) sorted by range merge into one echo where they lie within
  :data:`ECHO_SEPARATION_M` of each other: the echo's range is their signal-weighted mean (a **mixed
  pixel** between a foreground edge and a nearby background), its signal and apparent reflectivity the
  sums. Returns further apart are separate echoes.
* **Reported**: the strongest echo, the last, or both (``dual``) where the sensor has that mode.

Constants marked "assumption" are not from a datasheet; docs/testbed.md lists them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

GLASS_SURFACES = 4  # glass surfaces a ray may cross (a car's cabin: four); the next surface ends it
GLASS_STEP_M = 1e-3  # a continued ray starts this far beyond the glass
EDGE_M = 0.5  # a depth difference between horizontal neighbours that may hide an edge in the footprint
AXIS_WEIGHT = 0.4  # energy share of the axis sample at an edge; the four others share the rest (assumption)
ECHO_SEPARATION_M = 1.0  # returns closer than this merge into one echo (VLS-128 manual's dual-return limit)
RETURN_MODES = ("strongest", "last", "dual")


@dataclass
class Returns:
    """Surface returns of ``N`` rays, up to ``P`` each along the glass chain (unused slots: range 0)."""

    range_m: np.ndarray  # (N, P) float64 from the sensor
    signal: np.ndarray  # (N, P) float64
    rho: np.ndarray  # (N, P) float32 apparent reflectivity (dimmed by the glass passed)
    label: np.ndarray  # (N, P) uint8 1 on a moving actor


def trace(caster, materials, model, actor_ids, origins, dirs, max_range_m: float) -> Returns:
    """Every surface return along each ray (``dirs`` unit), glass passed on."""
    n = len(dirs)
    p = GLASS_SURFACES + 1
    out = Returns(
        np.zeros((n, p)), np.zeros((n, p)), np.zeros((n, p), np.float32), np.zeros((n, p), np.uint8)
    )
    table = materials.table
    travelled = np.zeros(n)
    passing = np.ones(n)
    live = np.arange(n)
    o = np.asarray(origins, np.float64).copy()
    for step in range(p):
        hits = caster.cast(o[live], dirs[live], max_range_m - travelled[live], normals=True)
        hit = hits.hit
        idx, rr = live[hit], hits.ranges[hit].astype(np.float64)
        points = o[idx] + rr[:, None] * dirs[idx]
        normals = hits.normals[hit]
        mat = materials.lookup(hits.mesh_ids[hit], hits.face_ids[hit], points, normals)
        cos = np.abs(np.einsum("ij,ij->i", normals, dirs[idx]))
        rho = model.effective_reflectivity(table.reflectivity[mat], table.mirror[mat], table.retro[mat], cos)
        total = travelled[idx] + rr
        out.range_m[idx, step] = total
        out.signal[idx, step] = model.signal(rho, total, passing[idx])
        out.rho[idx, step] = rho * passing[idx] * model.weather_dimming(total)
        out.label[idx, step] = np.isin(hits.mesh_ids[hit], actor_ids)
        go = table.transmission[mat] > 0
        live = idx[go]
        if len(live) == 0 or step == p - 1:
            break
        passing[live] *= table.transmission[mat[go]].astype(np.float64) ** 2
        o[live] = points[go] + GLASS_STEP_M * dirs[live]
        travelled[live] = total[go] + GLASS_STEP_M
    return out


@dataclass
class Echo:
    """One echo per pulse (``range_m`` 0: none)."""

    range_m: np.ndarray  # (N,) float64
    signal: np.ndarray  # (N,) float64
    rho: np.ndarray  # (N,) float32
    label: np.ndarray  # (N,) uint8


def echoes(range_m, signal, rho, label) -> tuple[Echo, Echo]:
    """``(strongest, last)`` echo of each pulse from its candidate returns ``(N, M)`` (range 0: none),
    merging returns within :data:`ECHO_SEPARATION_M` (see the module docstring)."""
    n, m = range_m.shape
    valid = range_m > 0
    count = valid.sum(axis=1)
    strong = Echo(np.zeros(n), np.zeros(n), np.zeros(n, np.float32), np.zeros(n, np.uint8))
    last = Echo(np.zeros(n), np.zeros(n), np.zeros(n, np.float32), np.zeros(n, np.uint8))
    one = np.flatnonzero(count == 1)  # most pulses: one return, which is both echoes
    k = np.argmax(valid[one], axis=1)
    for e in (strong, last):
        e.range_m[one] = range_m[one, k]
        e.signal[one] = signal[one, k]
        e.rho[one] = rho[one, k]
        e.label[one] = label[one, k]
    many = np.flatnonzero(count > 1)
    if len(many) == 0:
        return strong, last
    nm = len(many)
    r = np.where(valid[many], range_m[many], np.inf)
    order = np.argsort(r, axis=1, kind="stable")
    r = np.take_along_axis(r, order, 1)
    s = np.take_along_axis(signal[many], order, 1)
    q = np.take_along_axis(rho[many].astype(np.float64), order, 1)
    lab = np.take_along_axis(label[many], order, 1).astype(np.float64)
    ok = np.isfinite(r)
    r = np.where(ok, r, 0.0)
    gap = np.diff(r, axis=1, prepend=-np.inf) > ECHO_SEPARATION_M
    gap &= ok
    gap[:, 0] = True
    cluster = np.cumsum(gap, axis=1) - 1  # 0.. per pulse
    key = (np.arange(nm)[:, None] * m + cluster)[ok]

    def total(values) -> np.ndarray:
        return np.bincount(key, weights=values[ok], minlength=nm * m).reshape(nm, m)

    sums, wr, rq, actor = total(s), total(s * r), total(q), total(s * lab)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_r = np.where(sums > 0, wr / sums, 0.0)
    rows = np.arange(nm)
    for e, c in ((strong, np.argmax(sums, axis=1)), (last, np.where(ok, cluster, 0).max(axis=1))):
        e.range_m[many] = mean_r[rows, c]
        e.signal[many] = sums[rows, c]
        e.rho[many] = rq[rows, c]
        e.label[many] = actor[rows, c] > 0.5 * sums[rows, c]
    return strong, last


def footprint_offsets(geometry, divergence_rad: float) -> np.ndarray:
    """``(H, W, 4, 3)`` unit directions in the sensor frame of each pixel's four edge samples: half the
    divergence to the left, right, up and down of its axis."""
    d = geometry.directions  # (H, W, 3)
    up = np.array([0.0, 0.0, 1.0])
    side = np.cross(up, d)
    side /= np.maximum(np.linalg.norm(side, axis=-1, keepdims=True), 1e-12)
    tilt = np.cross(d, side)
    a = 0.5 * divergence_rad
    out = np.stack([d + a * side, d - a * side, d + a * tilt, d - a * tilt], axis=2)
    return out / np.linalg.norm(out, axis=-1, keepdims=True)


def edge_pixels(axis_range: np.ndarray, previous: np.ndarray | None) -> np.ndarray:
    """``(C, H)`` bool: pixels whose horizontal neighbour (within these columns, or the column cast just
    before them, ``previous`` ``(H,)``) differs in range by more than :data:`EDGE_M` or in having a return."""
    r = axis_range
    left = np.vstack([previous[None] if previous is not None else r[:1], r[:-1]])
    right = np.vstack([r[1:], r[-1:]])
    out = np.zeros(r.shape, bool)
    for nb in (left, right):
        out |= ((r > 0) != (nb > 0)) | ((r > 0) & (nb > 0) & (np.abs(r - nb) > EDGE_M))
    return out
