"""The particle renderer: each particle's view of the map for one scan's rays, reduced to the residuals
of the range-image observation model (paper Eq. 5) in one Warp kernel (:class:`ParticleRenderer`).

For each particle ``(x, y, yaw)`` the kernel casts, through the map's BVH, exactly the rays of a subset of
the measured pixels (each along its measured point's own direction, turned by the particle's yaw, from
the sensor at the particle's pose), and reduces ``d = mean |measured − rendered|`` inside the kernel: one
number per particle, nothing per pixel leaves it. A ray is cast no farther than its measured range plus a
margin; a ray that meets nothing by then counts as a residual of that margin (never as a range of 0, the
reference code's fault). Residuals are capped (``cap_m``) for robustness to moving objects.

Changes in the world are treated by their direction: a ray measured *shorter* than the map's surface met
something the map lacks (an actor, a newly parked car) or the pose is wrong; a ray measured *longer* than
the map's surface passed where the map holds something that is gone (a parked car of the mapping drive).
A ray measured more than ``cap_m`` beyond the map's surface costs ``cap_beyond_m`` (≤ ``cap_m``) instead
of ``cap_m``, so removed objects weigh less; a ray measured more than ``cap_m`` *short* of it (or meeting
nothing of the map) costs ``cap_short_m`` (≤ ``cap_m``; default ``cap_m``): at the true pose it met an
object the map lacks, which every pose explains alike, while a ray that passes through a mapped surface
is evidence against the pose. Within ``cap_m`` both directions cost alike (an asymmetric cost there pulls
the estimate towards the walls: measured, 0.3-0.8 m of bias). Only what moves changes between drives:
with a scan's ``change_top_z`` (the height of the tallest vehicle, in the sensor frame), a ray far short of
the map at a point above it, or far beyond a map surface above it, costs ``cap_m`` (no change explains
it: a facade does not appear or vanish). With ``explain_beyond``, a ray measured beyond the map's surface
counts as seen past a removed object only where the map has a surface within ``cap_m`` of its measured
point (what the scan saw behind the object is in the map); at a wrong pose such rays mostly end where the
map has nothing, and cost ``cap_m``. Rays beyond the surface are also counted (``beyond``).

What the residuals become as a likelihood is the observation models' business
(:mod:`rangemcl.localization.models`: Eq. 5 there, ``p(z | x) ∝ exp(−½ d² / σ_d²)``).
"""

from __future__ import annotations

import numpy as np
import warp as wp

from rangemcl.errors import InputError
from rangemcl.raycast import RayCaster, closest_hit
from rangemcl.se2 import row_norms

# the planar rendering casts each reference ray this far past the ray's own reach (m): a particle behind
# the reference, or turned from it where the ray grazes the surface, still meets the plane the reference
# met (a reference ray that ends short of it would render every particle's ray a miss)
PLANAR_REACH_M = 5.0
# ... and looks for a surface behind the one it met from this far past it (m), for explain_beyond
PLANAR_BEHIND_M = 0.05
PLANAR_CHUNK = 50  # particles per chunk of the planar kernel on the CPU threads (no ray is cast: cheap)
# the filter renders a converged cloud planar only while every particle lies this close to its estimate
# (m, degrees): the rankings of exact and planar rendering agree closely there (correlation 0.97-0.99 of
# the mean residuals for clouds of 0.05-0.4 m and 0.1-0.8 degrees on the demo drive)
PLANAR_WITHIN_M = 1.0
PLANAR_WITHIN_DEG = 3.0


def planar_references(poses, centres, of) -> tuple[np.ndarray, np.ndarray]:
    """References for rendering ``poses`` ``(N, 3)`` planar (:meth:`ParticleRenderer.planar_scores`), each
    pose about a reference near its centre ``centres[of]`` (``centres`` ``(K, 3)``, ``of`` ``(N,)``: a
    local grid's seed, a place): the pose's offset from its centre, in the centre's frame, is binned
    (forward and left in bins of :data:`PLANAR_WITHIN_M` x sqrt(2), yaw in bins of 2 x
    :data:`PLANAR_WITHIN_DEG`, the middle bin centred on the centre), and each occupied bin's middle is a
    reference, so that every pose lies within ``PLANAR_WITHIN_M`` and ``PLANAR_WITHIN_DEG`` of its own.
    A grid of +-2 m and +-8 degrees around a seed needs 27 references. Returns the references ``(M, 3)``
    and each pose's reference index ``(N,)`` (int32)."""
    p = np.asarray(poses, np.float64).reshape(-1, 3)
    c = np.asarray(centres, np.float64).reshape(-1, 3)
    of = np.asarray(of, np.int64).reshape(-1)
    if len(of) != len(p):
        raise InputError(f"planar references: {len(of)} centre indices for {len(p)} poses")
    step_xy, step_yaw = PLANAR_WITHIN_M * np.sqrt(2.0), np.radians(2.0 * PLANAR_WITHIN_DEG)
    cc = c[of]
    cos, sin = np.cos(cc[:, 2]), np.sin(cc[:, 2])
    dx, dy = p[:, 0] - cc[:, 0], p[:, 1] - cc[:, 1]
    dyaw = np.mod(p[:, 2] - cc[:, 2] + np.pi, 2.0 * np.pi) - np.pi
    bins = np.column_stack(
        [
            np.round((cos * dx + sin * dy) / step_xy),
            np.round((-sin * dx + cos * dy) / step_xy),
            np.round(dyaw / step_yaw),
        ]
    ).astype(np.int64)
    # one integer key per (centre, bin): a 1-D unique is several times faster than a row-wise one
    lo = bins.min(axis=0) if len(bins) else np.zeros(3, np.int64)
    span = (bins.max(axis=0) - lo + 1) if len(bins) else np.ones(3, np.int64)
    b = bins - lo
    key = ((of * span[0] + b[:, 0]) * span[1] + b[:, 1]) * span[2] + b[:, 2]
    _keys, first, ref_of = np.unique(key, return_index=True, return_inverse=True)
    base = c[of[first]]
    fwd, left = bins[first, 0] * step_xy, bins[first, 1] * step_xy
    bc, bs = np.cos(base[:, 2]), np.sin(base[:, 2])
    refs = np.column_stack(
        [
            base[:, 0] + bc * fwd - bs * left,
            base[:, 1] + bs * fwd + bc * left,
            np.mod(base[:, 2] + bins[first, 2] * step_yaw + np.pi, 2.0 * np.pi) - np.pi,
        ]
    )
    return refs, ref_of.reshape(-1).astype(np.int32)


@wp.func
def ray_cost(
    measured: float,
    t: float,
    hit: int,
    measured_z: float,  # sensor-frame height of the measured point ...
    rendered_z: float,  # ... and of the map's surface the ray met
    structure: float,
    margin: float,
    cap: float,
    cap_beyond: float,
    cap_short: float,
    change_top: float,
    explain_beyond: int,
    behind: int,  # the map has a surface within cap of the measured point (read with explain_beyond)
    tau: float,
):
    """One ray's cost and counts: (cost, agrees, measured beyond the surface, a structure ray far short of
    the map or meeting nothing of it, a structure ray far beyond it)."""
    r = float(margin)
    # what the scan met may be an object added since the mapping drive only where such objects stand
    low = measured_z < change_top
    lim = cap
    if low:
        lim = cap_short  # a miss: the scan met something where the map has nothing, an added object
    far = structure  # a miss: the scan met something where the map has nothing (or wrong pose)
    beyond = float(0.0)
    gone = float(0.0)
    if hit != 0:
        e = measured - t
        r = wp.abs(e)
        lim = cap
        if e < -cap and low:  # far in front of the map's surface: an object the map lacks
            lim = cap_short
        if e > tau:
            beyond = 1.0
        if e > cap:  # far beyond the map's surface: a removed object, not a small pose error
            if rendered_z < change_top:  # (the surface it passed may be such an object)
                lim = cap_beyond
                # ...only if what the scan saw behind it is in the map: a surface within cap of the
                # measured point (at a wrong pose the ray mostly ends where the map has none)
                if explain_beyond != 0 and behind == 0:
                    lim = cap
            gone = structure
        if e >= -cap:
            far = 0.0
    agree = float(0.0)
    if r < tau:
        agree = 1.0
    return wp.min(r, lim), agree, beyond, far, gone


@wp.func
def ray_in_world(p: wp.vec3, z: float, d: wp.vec3, o: wp.vec3):
    """A particle's ray in the world: ``p`` (x, y, yaw) at sensor height ``z``, the ray's sensor-frame
    direction ``d`` and origin offset ``o``. Returns its origin and direction."""
    c = wp.cos(p[2])
    s = wp.sin(p[2])
    dw = wp.vec3(c * d[0] - s * d[1], s * d[0] + c * d[1], d[2])
    ow = wp.vec3(p[0], p[1], z) + wp.vec3(c * o[0] - s * o[1], s * o[0] + c * o[1], o[2])
    return ow, dw


@wp.func
def add_ray(
    k: int,
    measured: float,
    t: float,
    hit: int,
    d_z: float,  # the ray's sensor-frame direction's z ...
    o_z: float,  # ... and origin's
    structure: float,
    behind: int,
    margin: float,
    cap: float,
    cap_beyond: float,
    cap_short: float,
    change_top: float,
    explain_beyond: int,
    tau: float,
    hist_top: float,
    out_hist: wp.array2d[float],
    sums: wp.vec3,  # (total cost, agree, beyond)
    s_sums: wp.vec4,  # the structure rays' (agree, count, far, gone)
):
    """One ray rendered at ``t`` (``hit``: it met the map) costed (:func:`ray_cost`) and added to the
    particle's sums (and to its histogram, when ``out_hist`` has columns). Returns the sums."""
    cost, a, b, far, gone = ray_cost(
        measured,
        t,
        hit,
        o_z + d_z * measured,
        o_z + d_z * t,
        structure,
        margin,
        cap,
        cap_beyond,
        cap_short,
        change_top,
        explain_beyond,
        behind,
        tau,
    )
    bins = out_hist.shape[1]
    if hit != 0 and bins > 0 and t < hist_top:
        bb = wp.min(int(t / hist_top * float(bins)), bins - 1)
        out_hist[k, bb] = out_hist[k, bb] + 1.0
    return (
        wp.vec3(sums[0] + cost, sums[1] + a, sums[2] + b),
        wp.vec4(s_sums[0] + a * structure, s_sums[1] + structure, s_sums[2] + far, s_sums[3] + gone),
    )


@wp.func
def write_scores(
    k: int,
    n_rays: int,
    sums: wp.vec3,
    s_sums: wp.vec4,
    out_mean: wp.array[float],
    out_agree: wp.array[float],
    out_beyond: wp.array[float],
    out_structure: wp.array[float],
):
    out_mean[k] = sums[0] / float(n_rays)
    out_agree[k] = sums[1] / float(n_rays)
    out_beyond[k] = sums[2] / float(n_rays)
    # structure rays that agree, among those within cap of the map's surface: the ones far beyond it
    # (objects removed since the map was made) left out, and those far short of it (objects added, or a
    # wrong pose) left out too but at most half of the rest (at a wrong pose most of them are far short)
    rest = s_sums[1] - s_sums[3]
    out_structure[k] = s_sums[0] / wp.max(wp.max(rest - s_sums[2], 0.5 * rest), 1.0)


@wp.kernel
def particle_residual_kernel(
    meshes: wp.array[wp.uint64],
    inv_poses: wp.array[wp.transform],
    moved: wp.array[wp.int32],
    boxes: wp.array[wp.vec3],
    particles: wp.array[wp.vec3],  # (x, y, yaw)
    sensor_z: wp.array[float],  # sensor height in the world at each particle
    directions: wp.array[wp.vec3],  # measured rays, levelled sensor frame, unit
    origins: wp.array[wp.vec3],  # per-ray origin offsets in the sensor frame
    measured: wp.array[float],
    structure: wp.array[float],  # 1 for rays that met structure (not the ground), else 0
    margin: float,
    cap: float,
    cap_beyond: float,  # cost of a ray measured more than cap beyond the map's surface (a removed object)
    cap_short: float,  # cost of a ray measured more than cap short of the map's surface (an added object)
    change_top: float,  # sensor-frame z below which the world may have changed (cap_short, cap_beyond apply)
    explain_beyond: int,  # 1: cap_beyond only where the map has a surface near the measured point
    tau: float,  # a ray agrees when its residual is below tau
    hist_top: float,  # rendered ranges binned into out_hist's columns over [0, hist_top)
    offset: int,
    out_mean: wp.array[float],
    out_agree: wp.array[float],
    out_beyond: wp.array[float],  # share of rays measured more than tau beyond the map's surface
    out_structure: wp.array[float],  # share of the structure rays that agree (see write_scores)
    out_hist: wp.array2d[float],  # (N, bins); (1, 0) when no histogram is wanted
):
    k = wp.tid() + offset
    sums = wp.vec3(0.0)
    s_sums = wp.vec4(0.0)  # structure rays: agree, count, far short of the map (or missing it), far beyond
    for i in range(directions.shape[0]):
        d = directions[i]
        o = origins[i]
        ow, dw = ray_in_world(particles[k], sensor_z[k], d, o)
        t, m, _face, _normal = closest_hit(meshes, inv_poses, moved, boxes, ow, dw, measured[i] + margin)
        hit = int(0)
        if m >= 0:
            hit = 1
        behind = int(1)
        if explain_beyond != 0 and hit != 0 and measured[i] - t > cap and o[2] + d[2] * t < change_top:
            _t2, m2, _f2, _n2 = closest_hit(
                meshes, inv_poses, moved, boxes, ow + dw * (measured[i] - cap), dw, 2.0 * cap
            )
            if m2 < 0:
                behind = 0
        sums, s_sums = add_ray(
            k, measured[i], t, hit, d[2], o[2], structure[i], behind, margin, cap, cap_beyond, cap_short,
            change_top, explain_beyond, tau, hist_top, out_hist, sums, s_sums,
        )  # fmt: skip
    write_scores(k, directions.shape[0], sums, s_sums, out_mean, out_agree, out_beyond, out_structure)


@wp.kernel
def planar_residual_kernel(
    particles: wp.array[wp.vec3],  # (x, y, yaw)
    sensor_z: wp.array[float],
    directions: wp.array[wp.vec3],
    origins: wp.array[wp.vec3],
    measured: wp.array[float],
    structure: wp.array[float],
    ref_of: wp.array[wp.int32],  # each particle's reference pose
    ref_points: wp.array[wp.vec3],  # (references x rays): where each ray cast from the reference met the map
    ref_normals: wp.array[wp.vec3],  # ... the normal of the surface there (world)
    ref_hit: wp.array[wp.int32],  # ... 1 where it met something
    ref_behind: wp.array[wp.int32],  # ... 1 where the map has a surface within cap of the measured point
    margin: float,
    cap: float,
    cap_beyond: float,
    cap_short: float,
    change_top: float,
    explain_beyond: int,
    tau: float,
    hist_top: float,
    offset: int,
    out_mean: wp.array[float],
    out_agree: wp.array[float],
    out_beyond: wp.array[float],
    out_structure: wp.array[float],
    out_hist: wp.array2d[float],
):
    """The residual kernel's scores with each particle's rendered range taken where its ray meets the
    plane of the surface that the reference pose's ray met (no ray cast)."""
    k = wp.tid() + offset
    sums = wp.vec3(0.0)
    s_sums = wp.vec4(0.0)
    n_rays = directions.shape[0]
    first = ref_of[k] * n_rays
    for i in range(n_rays):
        d = directions[i]
        o = origins[i]
        ow, dw = ray_in_world(particles[k], sensor_z[k], d, o)
        limit = measured[i] + margin
        t = limit
        hit = int(0)
        j = first + i
        if ref_hit[j] != 0:
            nrm = ref_normals[j]
            den = wp.dot(nrm, dw)
            if wp.abs(den) > 1.0e-6:
                tt = wp.dot(nrm, ref_points[j] - ow) / den
                if tt > 0.0 and tt < limit:
                    t = tt
                    hit = 1
        sums, s_sums = add_ray(
            k, measured[i], t, hit, d[2], o[2], structure[i], ref_behind[j], margin, cap, cap_beyond,
            cap_short, change_top, explain_beyond, tau, hist_top, out_hist, sums, s_sums,
        )  # fmt: skip
    write_scores(k, n_rays, sums, s_sums, out_mean, out_agree, out_beyond, out_structure)


class ParticleRenderer:
    """Renders one scan's measured rays from many particles in a map loaded into a :class:`RayCaster` and
    reduces them per particle (:meth:`scores`).

    Args:
        caster: the map (static mesh; movable meshes are seen at their current poses).
        margin_m: how far past the measured range a ray is cast.
        cap_m: residual cap (robust variant); ``inf`` for the plain paper model.
        cap_beyond_m: cost of a ray measured more than ``cap_m`` longer than the map's surface (default:
            ``cap_m``, symmetric).
        cap_short_m: cost of a ray measured more than ``cap_m`` shorter than the map's surface, or meeting
            nothing of it (default: ``cap_m``).
        explain_beyond: ``cap_beyond_m`` only for a ray whose measured point lies within ``cap_m`` of a
            surface of the map (behind the one it passed); others ``cap_m``.
    """

    def __init__(
        self,
        caster: RayCaster,
        *,
        margin_m: float = 2.0,
        cap_m: float = np.inf,
        cap_beyond_m: float | None = None,
        cap_short_m: float | None = None,
        explain_beyond: bool = False,
    ):
        if cap_beyond_m is None:
            cap_beyond_m = cap_m
        if cap_short_m is None:
            cap_short_m = cap_m
        if not margin_m > 0 or not cap_m > 0 or not cap_beyond_m > 0 or not cap_short_m > 0:
            raise InputError(
                "margin_m, cap_m, cap_beyond_m and cap_short_m must be > 0, got "
                f"{margin_m}, {cap_m}, {cap_beyond_m}, {cap_short_m}"
            )
        self.caster = caster
        self.margin_m = float(margin_m)
        self.cap_m = float(min(cap_m, 3.0e38))
        self.cap_beyond_m = float(min(cap_beyond_m, self.cap_m))
        self.cap_short_m = float(min(cap_short_m, self.cap_m))
        self.explain_beyond = bool(explain_beyond)
        self._rays: tuple | None = None
        self._change_top = 3.0e38
        wp.load_module(device=caster.device)  # this module's kernels compiled now, not at the first update

    def ray_costs(self, errors, measured_z=None, rendered_z=None, behind=None) -> np.ndarray:
        """Each ray's cost as the kernel charges it, in numpy: ``errors`` = measured − rendered range
        (``-inf`` where the map has nothing within the margin); the kernel's ``d`` is their mean. With a
        scan's ``change_top_z`` (:meth:`set_scan`), ``measured_z`` and ``rendered_z`` are the sensor-frame
        heights of each ray's measured point and of the map's surface it met; with ``explain_beyond``,
        ``behind`` says whether the map has a surface within ``cap_m`` of each ray's measured point."""
        e = np.asarray(errors, np.float64)
        miss = ~np.isfinite(e)
        top = self._change_top
        low = np.ones(e.shape, bool) if measured_z is None else np.asarray(measured_z) < top
        gone = np.ones(e.shape, bool) if rendered_z is None else np.asarray(rendered_z) < top
        if self.explain_beyond:
            if behind is None:
                raise InputError("ray_costs: explain_beyond needs `behind`")
            gone &= np.asarray(behind, bool)
        cost = np.minimum(np.where(miss, self.margin_m, np.abs(e)), self.cap_m)
        cost = np.where(~miss & (e > self.cap_m) & gone, self.cap_beyond_m, cost)
        return np.where((miss | (e < -self.cap_m)) & low, np.minimum(cost, self.cap_short_m), cost)

    def set_scan(self, directions, ranges, origins=None, structure=None, change_top_z=None) -> None:
        """The measured rays of a scan: unit directions ``(R, 3)`` in the levelled sensor frame, ranges
        ``(R,)`` (> 0), optional per-ray origin offsets ``(R, 3)`` and ``structure`` flags ``(R,)`` (rays
        that met something above the ground; default: all). ``change_top_z``: the height in the levelled
        sensor frame (m; the ground lies at minus the sensor's height) below which the world may have
        changed since the mapping drive: a ray far short of the map at a measured point above it, or far
        beyond a map surface above it, costs ``cap_m``, not ``cap_short_m`` or ``cap_beyond_m``
        (default: no such height, every change possible)."""
        d = np.asarray(directions, np.float32)
        r = np.asarray(ranges, np.float32).reshape(-1)
        if d.ndim != 2 or d.shape[1] != 3 or len(d) != len(r) or len(d) == 0:
            raise InputError(
                f"scan rays: expected (R, 3) directions and (R,) ranges, got {d.shape}, {r.shape}"
            )
        if not (np.isfinite(d).all() and np.isfinite(r).all() and (r > 0).all()):
            raise InputError("scan rays: directions and ranges must be finite and ranges > 0")
        o = np.zeros_like(d) if origins is None else np.asarray(origins, np.float32).reshape(d.shape)
        st = (
            np.ones(len(r), np.float32)
            if structure is None
            else np.asarray(structure, np.float32).reshape(-1)
        )
        if len(st) != len(r):
            raise InputError(f"scan rays: {len(st)} structure flags for {len(r)} rays")
        top = 3.0e38 if change_top_z is None else float(change_top_z)
        if not np.isfinite(top):
            raise InputError(f"scan rays: change_top_z must be finite, got {change_top_z}")
        self._change_top = top
        dev = self.caster.device
        # the farthest any ray of this scan reaches from its particle's sensor position
        self._reach = float(row_norms(o).max() + r.max() + self.margin_m)
        unit = d / row_norms(d)[:, None]
        self._scan = (unit, o, r)  # for the planar rendering's reference rays
        self._rays = (
            wp.array(unit, dtype=wp.vec3, device=dev),
            wp.array(o, dtype=wp.vec3, device=dev),
            wp.array(r, dtype=float, device=dev),
            wp.array(st, dtype=float, device=dev),
        )

    def mean_residuals(self, particles, sensor_z) -> np.ndarray:
        """``d`` of Eq. 5 for each particle: ``particles`` ``(N, 3)`` (x, y, yaw), ``sensor_z`` ``(N,)``."""
        return self.scores(particles, sensor_z)["mean"]

    def scores(
        self,
        particles,
        sensor_z,
        *,
        agree_m: float = 0.3,
        hist_bins: int = 0,
        hist_top_m: float = 100.0,
        about=None,
        about_of=None,
    ):
        """Per particle, from one pass over its rays: ``mean`` (``d`` of Eq. 5), ``agree`` (the share of
        rays whose residual is below ``agree_m``), ``beyond`` (the share measured more than ``agree_m``
        longer than the map's surface), ``structure`` (the share of the structure rays that agree, among
        those within ``cap_m`` of the map's surface, at least half of them) and,
        with ``hist_bins``, ``hist`` ``(N, bins)``: counts of the rendered ranges (hits only) in equal bins
        over ``[0, hist_top_m)``.

        ``about``: the planar rendering (:meth:`planar_scores`) about this pose ``(x, y, yaw, sensor_z)``,
        for a cloud of particles close around it; or about each of ``K`` poses ``(K, 4)``, each particle
        about the one ``about_of`` ``(N,)`` names (hypotheses' local grids in one launch)."""
        if self._rays is None:
            raise InputError("no scan set: call set_scan first")
        p = np.ascontiguousarray(particles, np.float32)
        z = np.ascontiguousarray(np.broadcast_to(np.asarray(sensor_z, np.float32), (len(p),)))
        if p.ndim != 2 or p.shape[1] != 3 or not np.isfinite(p).all() or not np.isfinite(z).all():
            raise InputError(f"particles: expected finite (N, 3) x, y, yaw, got shape {p.shape}")
        n = len(p)
        bins = int(hist_bins)
        out = {
            "mean": np.empty(n, np.float32),
            "agree": np.empty(n, np.float32),
            "beyond": np.empty(n, np.float32),
            "structure": np.empty(n, np.float32),
            "hist": np.zeros((n if bins else 1, bins), np.float32),
        }
        if n == 0:
            return out
        if about is not None:
            return self.planar_scores(p, z, out, bins, float(agree_m), float(hist_top_m), about, about_of)
        groups = self._groups(p)
        if len(groups) == 1:
            return self._launch(p, z, out, bins, float(agree_m), float(hist_top_m))
        for idx in groups:  # particles far apart: each group casts only into the meshes near it
            part = {k: (v[idx] if k != "hist" or bins else v) for k, v in out.items()}
            got = self._launch(p[idx], z[idx], part, bins, float(agree_m), float(hist_top_m))
            for k, v in got.items():
                if k != "hist" or bins:
                    out[k][idx] = v
        return out

    def _groups(self, p: np.ndarray) -> list[np.ndarray]:
        """The particles in groups of nearby ones, where the scene holds many meshes (a map within a memory
        budget: its tiles) and the particles are spread wider than their rays reach: a launch casts into
        the meshes within reach of its particles, so a global search over a city-sized map casts each ray
        into the few tiles near its particle, not into all of them. One group otherwise."""
        reach = self._reach
        span = np.ptp(p[:, :2], axis=0).max() if len(p) else 0.0
        if len(self.caster.live_handles) <= 8 or span <= 4.0 * reach:
            return [np.arange(len(p))]
        cell = np.floor(p[:, :2] / (2.0 * reach)).astype(np.int64)
        _, inverse = np.unique(cell, axis=0, return_inverse=True)
        order = np.argsort(inverse.reshape(-1), kind="stable")
        bounds = np.flatnonzero(np.diff(inverse.reshape(-1)[order])) + 1
        return np.split(order, bounds)

    def _launch(self, p, z, out, bins: int, agree_m: float, hist_top_m: float) -> dict:
        n = len(p)
        p = np.ascontiguousarray(p)
        z = np.ascontiguousarray(z)
        out = {k: np.ascontiguousarray(v) for k, v in out.items()}
        c = self.caster
        # every ray of the launch lies within its particle's reach: the meshes beyond are not visited
        reach = self._reach
        region = np.concatenate(
            [
                [p[:, 0].min() - reach, p[:, 1].min() - reach, z.min() - reach],
                [p[:, 0].max() + reach, p[:, 1].max() + reach, z.max() + reach],
            ]
        )
        ids, inv, moved, boxes, _handles = c.scene_within(region)
        cpu = c.device == "cpu"
        dev = c.device
        inputs = [
            ids,
            inv,
            moved,
            boxes,
            wp.array(p, dtype=wp.vec3, device=dev, copy=not cpu),
            wp.array(z, dtype=float, device=dev, copy=not cpu),
            *self._rays,
            self.margin_m,
            self.cap_m,
            self.cap_beyond_m,
            self.cap_short_m,
            self._change_top,
            int(self.explain_beyond),
            agree_m,
            hist_top_m,
        ]
        # a particle casts hundreds of rays: every particle is worth a chunk of its own
        return self._run(particle_residual_kernel, n, inputs, out, min_chunk=1)

    def _run(self, kernel, n: int, inputs: list, out: dict, *, min_chunk: int) -> dict:
        """Launch a residual kernel over ``n`` particles into ``out``'s arrays (in place on the CPU)."""
        c = self.caster
        dev = c.device
        names = ("mean", "agree", "beyond", "structure", "hist")
        if dev == "cpu":  # the kernel writes into the numpy arrays in place
            outs = [wp.array(out[k], dtype=float, device=dev, copy=False) for k in names]
        else:
            outs = [wp.empty(n, dtype=float, device=dev) for _ in names[:-1]]
            outs.append(wp.zeros(out["hist"].shape, dtype=float, device=dev))
        c.launch(kernel, n, inputs, outs, min_chunk=min_chunk)
        return out if dev == "cpu" else {k: a.numpy() for k, a in zip(names, outs, strict=True)}

    def planar_scores(
        self, p, z, out, bins: int, agree_m: float, hist_top_m: float, about, about_of=None
    ) -> dict:
        """:meth:`scores` of particles close around a reference pose ``about`` ``(x, y, yaw, sensor_z)``
        (or around several: ``about`` ``(K, 4)``, each particle's reference named by ``about_of`` ``(N,)``),
        rendered without casting their rays: the scan's rays are cast once from each reference (with the
        surface normal where they meet the map), and each particle's rendered range is where its own ray
        meets the plane of the surface that its reference's ray met. A converged cloud lies within
        decimetres of its estimate, where almost every ray meets the same surface as the estimate's ray,
        so the particles are ranked as the exact rendering ranks them for the cost of one particle's rays
        (rays near a depth edge, which the particle's own ray would pass, are rendered on the plane
        anyway). With ``explain_beyond``, whether the map has a surface near each measured point is also
        looked up from the reference."""
        refs = np.asarray(about, np.float64).reshape(-1, 4)
        of = np.zeros(len(p), np.int32) if about_of is None else np.ascontiguousarray(about_of, np.int32)
        if of.shape != (len(p),) or (len(of) and (of.min() < 0 or of.max() >= len(refs))):
            raise InputError(f"planar rendering: {of.size} reference indices for {len(p)} particles")
        unit, o, r = self._scan
        K, R = len(refs), len(r)
        cy, sy = np.cos(refs[:, 2])[:, None], np.sin(refs[:, 2])[:, None]
        u64, o64 = unit.astype(np.float64), o.astype(np.float64)
        dw = np.stack(
            [
                cy * u64[None, :, 0] - sy * u64[None, :, 1],
                sy * u64[None, :, 0] + cy * u64[None, :, 1],
                np.broadcast_to(u64[None, :, 2], (K, R)),
            ],
            axis=-1,
        ).reshape(-1, 3)
        ow = np.stack(
            [
                refs[:, None, 0] + cy * o64[None, :, 0] - sy * o64[None, :, 1],
                refs[:, None, 1] + sy * o64[None, :, 0] + cy * o64[None, :, 1],
                refs[:, None, 3] + np.broadcast_to(o64[None, :, 2], (K, R)),
            ],
            axis=-1,
        ).reshape(-1, 3)
        m = np.tile(r.astype(np.float64), K)
        # cast a little past each ray's own reach: a particle behind the reference still meets the plane
        hits = self.caster.cast(ow, dw, m + self.margin_m + PLANAR_REACH_M, normals=True)
        hit = np.isfinite(hits.ranges)
        points = ow + np.where(hit, hits.ranges, 0.0)[:, None] * dw
        behind = np.ones(K * R, np.int32)
        if self.explain_beyond and self.cap_m < 1e30:
            # read only for a particle whose ray ends more than cap_m beyond the plane: the surface near its
            # measured point must lie behind the plane (past the reference's hit), within cap_m of that point
            start = np.maximum(m - self.cap_m, np.where(hit, hits.ranges, 0.0) + PLANAR_BEHIND_M)
            length = m + self.cap_m - start
            found = self.caster.cast(ow + dw * start[:, None], dw, np.maximum(length, 0.0)).ranges
            behind = (np.isfinite(found) & (length > 0)).astype(np.int32)
        dev = self.caster.device
        cpu = dev == "cpu"
        inputs = [
            wp.array(p, dtype=wp.vec3, device=dev, copy=not cpu),
            wp.array(z, dtype=float, device=dev, copy=not cpu),
            *self._rays,
            wp.array(of, dtype=wp.int32, device=dev),
            wp.array(points.astype(np.float32), dtype=wp.vec3, device=dev),
            wp.array(hits.normals.astype(np.float32), dtype=wp.vec3, device=dev),
            wp.array(hit.astype(np.int32), dtype=wp.int32, device=dev),
            wp.array(behind, dtype=wp.int32, device=dev),
            self.margin_m,
            self.cap_m,
            self.cap_beyond_m,
            self.cap_short_m,
            self._change_top,
            int(self.explain_beyond),
            agree_m,
            hist_top_m,
        ]
        return self._run(planar_residual_kernel, len(p), inputs, out, min_chunk=PLANAR_CHUNK)
