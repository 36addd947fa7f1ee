#!/usr/bin/env python3
"""Localizer benchmark: frame rate after convergence (few particles) and seconds per frame before it
(many particles), on a recorded drive in its map, with the same particle weighting done through Open3D's
Embree ``RaycastingScene`` in the same run as the peer.

    python tools/bench_localize.py --seq out/demo/test_drive --map out/demo/map
    python tools/bench_localize.py --seq SEQ --map MAP --device cuda

* after convergence: pose tracking from the first true pose with ``--few`` particles (default 100) over
  ``--frames`` frames; per frame the whole step (scan read, de-skew, motion, weighting, resampling, the
  scan-to-mesh refinement and the odometry calibration) is timed; the median gives the frame rate; the
  weighting and the refinement alone are timed on every 10th frame. Once per rendering (``--rendering``,
  ``observation.rendering``, default ``exact,planar``: every particle's rays cast, or the cloud rendered
  about its estimate), from the same start and seed, so their ratio and their tracking errors compare.
* before convergence: ``--many`` particles (default 10,000) spread over the map, weighted on ``--global-
  frames`` frames; median seconds per update (the first update of a search: the place prior's match of
  the scan, the prior's particles, the weighting and the hypothesis bookkeeping).
* a whole global search: from frame 0 with ``--many`` particles until convergence (at most
  ``--search-frames``); median and largest seconds per frame before convergence (the cloud shrinks as the
  hypotheses thin out), the frame it converged at and its error then, and the first correct fix (a
  convergence within 5 m): the seconds of compute through its frame and the metres driven; the search's
  filter is built anew, and its start-up (the filter, the place priors loaded, before frame 0) is timed.
  Then ``--probation-frames`` more frames (default: the recovery's probation and 5 more), in which each
  update after a convergence asks the place prior for a second opinion: their median and largest seconds,
  and the worst frame of the whole global localization (search and probation). Once per search method
  (``--search``, default ``hypotheses,prior``: the particle search and the prior search) and rendering
  (``--rendering``: the local grids of the search, the challenge and the second opinion rendered exactly
  or planar), in the same run.
* the place prior: rendered anew for the map (seconds), its size in memory and on disk, per km² of the
  drivable area it covers; the same for a beam prior (the prior of a sensor that sees nothing above the
  parked cars: one beam, ``--beam-deg``, default the MQ-8's top beam, from the sensor's height).
* peer: the same rays of the same particles cast by Embree (all cores) and reduced in numpy, on the same
  frames; ratio = Embree time / Warp time of the weighting (above 1: Warp is faster).

Figures are medians; the machine is shared, so compare ratios within one run.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import numpy as np


def embree_residuals(scene, o3d, particles, z, rays, margin, costs):
    """Eq. 5's mean residual per particle through Embree: all particles' rays in one batch, each ray's
    residual costed as the Warp kernel costs it (``costs``: :meth:`ParticleRenderer.ray_costs`)."""
    n, r = len(particles), len(rays.ranges)
    c, s = np.cos(particles[:, 2]), np.sin(particles[:, 2])
    d = rays.directions
    dx = c[:, None] * d[None, :, 0] - s[:, None] * d[None, :, 1]
    dy = s[:, None] * d[None, :, 0] + c[:, None] * d[None, :, 1]
    dz = np.broadcast_to(d[None, :, 2], (n, r))
    origin = np.broadcast_to(np.column_stack([particles[:, :2], z])[:, None, :], (n, r, 3))
    batch = (
        np.concatenate([origin, np.stack([dx, dy, dz], axis=-1)], axis=-1).reshape(-1, 6).astype(np.float32)
    )
    t = scene.cast_rays(o3d.core.Tensor(batch))["t_hit"].numpy().reshape(n, r)
    hit = t <= rays.ranges[None, :] + margin
    return costs(np.where(hit, rays.ranges[None, :] - t, -np.inf)).mean(axis=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", required=True, help="a recorded test drive (KITTI layout, with poses)")
    ap.add_argument("--map", required=True, help="its map folder")
    ap.add_argument("--frames", type=int, default=200, help="frames tracked with few particles")
    ap.add_argument("--few", type=int, default=100)
    ap.add_argument("--many", type=int, default=10000)
    ap.add_argument("--global-frames", type=int, default=8)
    ap.add_argument("--search-frames", type=int, default=80)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--search",
        default="hypotheses,prior",
        help="convergence.method values whose global search is measured from frame 0, comma-separated",
    )
    ap.add_argument(
        "--rendering",
        default="exact,planar",
        help="observation.rendering values whose tracking and searches are measured, comma-separated",
    )
    ap.add_argument(
        "--probation-frames",
        type=int,
        default=None,
        help="frames measured after a search's convergence (default: recovery.probation_updates + 5)",
    )
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument(
        "--beam-deg", type=float, default=-1.57, help="the beam prior's beam (default: the MQ-8's top)"
    )
    args = ap.parse_args()

    import open3d as o3d

    from rangemcl.datasets.kitti import load_sequence
    from rangemcl.localization import LocalizerSettings, build_localizer, prepare_rays
    from rangemcl.localization.pipeline import frame_period
    from rangemcl.maps.meshmap import MeshMap
    from rangemcl.se2 import se2_between, xyyaw_of

    seq = load_sequence(args.seq)
    mesh_map = MeshMap.load(args.map)
    odo, truth = xyyaw_of(seq.odometry), xyyaw_of(seq.poses)
    period = frame_period(seq)
    settings = LocalizerSettings()
    o = settings.observation
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(mesh_map.vertices.astype(np.float32)),
        o3d.core.Tensor(mesh_map.faces.astype(np.uint32)),
    )
    rng = np.random.default_rng(args.seed)
    loc = build_localizer(mesh_map, settings, rng=rng, device=args.device, sensor_height_m=1.73)
    n_frames = min(args.frames, len(seq))

    # --- after convergence: whole steps with few particles, each converged rendering ---------------------
    def tracking(rendering: str) -> dict:
        s = LocalizerSettings()
        s.observation.rendering = rendering
        loc = build_localizer(
            mesh_map, s, rng=np.random.default_rng(args.seed), device=args.device, sensor_height_m=1.73
        )
        return after_convergence(loc, rendering)

    def after_convergence(loc, rendering: str) -> dict:
        loc.start_at(truth[0], args.few)
        rays_rng = np.random.default_rng(args.seed + 1)  # the same rays for every rendering
        step_s, weigh_warp, weigh_embree, errors, refine_s = [], [], [], [], []
        for i in range(n_frames):
            t0 = time.perf_counter()
            delta = se2_between(odo[i - 1], odo[i]) if i else np.zeros(3)
            pts = seq.scan(i)
            fire = seq.point_meta(i).get("time_s")
            rp = tuple(seq.imu_roll_pitch[i]) if seq.imu_roll_pitch is not None else None
            info = loc.step(delta, pts, fire_time_s=fire, frame_period_s=period, roll_pitch=rp)
            step_s.append(time.perf_counter() - t0)
            errors.append(float(np.hypot(*(info.estimate[:2] - truth[i, :2]))))
            if i % 10 == 5:  # the weighting alone, Warp and Embree on the same rays and particles
                rays = prepare_rays(
                    pts,
                    o,
                    rays_rng,
                    fire_time_s=fire,
                    frame_period_s=period,
                    frame_motion=delta,
                    roll_pitch=rp,
                )
                rays.sensor_height_m = loc.sensor_height_m
                z = loc.sensor_z(loc.particles[:, :2])
                about = loc._planar_about()  # the filter's own weighting: planar about the estimate, or exact
                t1 = time.perf_counter()
                if about is None:
                    loc.scorer.score(rays, loc.particles, z)
                else:  # and the best particle rendered exactly for the lost watch
                    loc.scorer.score(rays, loc.particles, z, about=about)
                    loc.scorer.score(rays, loc.particles[:1], z[:1])
                t2 = time.perf_counter()
                de = embree_residuals(scene, o3d, loc.particles, z, rays, o.margin_m, loc.model.ray_costs)
                t3 = time.perf_counter()
                weigh_warp.append(t2 - t1)
                weigh_embree.append(t3 - t2)
                dw = loc.residuals(rays)  # exact: Warp and Embree cast the same rays to the same ranges
                if loc.refiner is not None:  # the scan-to-mesh refinement alone (its result not applied)
                    est = loc.last_estimate
                    t4 = time.perf_counter()
                    loc.refiner.refine(
                        rays.directions, rays.ranges, est, float(loc.sensor_z(est[None, :2])[0])
                    )
                    refine_s.append(time.perf_counter() - t4)
                assert np.allclose(dw, de, atol=2e-3), float(np.abs(dw - de).max())
        return {
            "rendering": rendering,
            "particles": args.few,
            "frames": n_frames,
            "step_median_s": statistics.median(step_s[5:]),
            "hz": 1.0 / statistics.median(step_s[5:]),
            "weighting_median_s_warp": statistics.median(weigh_warp),
            "weighting_median_s_embree": statistics.median(weigh_embree),
            "embree_over_warp": statistics.median(weigh_embree) / statistics.median(weigh_warp),
            "tracking_error_median_m": statistics.median(errors),
            "tracking_error_p95_m": float(np.quantile(errors, 0.95)),
            "refine_median_s": statistics.median(refine_s) if refine_s else None,
            "refinements": loc.refinements,
            "refused_refinements": loc.refused_refinements,
        }

    renderings = [m.strip() for m in args.rendering.split(",") if m.strip()]
    tracked = {m: tracking(m) for m in renderings}
    after = tracked[renderings[0]]

    # --- before convergence: updates with many particles ------------------------------------------------
    gw, ge = [], []
    loc.spread(args.many)
    for i in np.linspace(0, len(seq) - 1, args.global_frames).astype(int):
        pts = seq.scan(i)
        rays = prepare_rays(
            pts,
            o,
            rng,
            fire_time_s=seq.point_meta(i).get("time_s"),
            frame_period_s=period,
            frame_motion=se2_between(odo[max(i - 1, 0)], odo[i]),
            roll_pitch=tuple(seq.imu_roll_pitch[i]) if seq.imu_roll_pitch is not None else None,
        )
        loc.spread(args.many)
        info = loc.step(
            np.array([0.5, 0.0, 0.0]), pts, fire_time_s=seq.point_meta(i).get("time_s"), frame_period_s=period
        )
        gw.append(info.seconds)
        z = loc.sensor_z(loc.particles[:, :2])
        t1 = time.perf_counter()
        embree_residuals(scene, o3d, loc.particles, z, rays, o.margin_m, loc.model.ray_costs)
        ge.append(time.perf_counter() - t1)
    before = {
        "particles": args.many,
        "updates": len(gw),
        "update_median_s_warp": statistics.median(gw),
        "weighting_median_s_embree": statistics.median(ge),
        "embree_over_warp": statistics.median(ge) / statistics.median(gw),
    }

    # --- a whole global search from frame 0, each search method (a new filter: its start-up timed) ---------
    probation_frames = (
        settings.recovery.probation_updates + 5 if args.probation_frames is None else args.probation_frames
    )

    def global_search(method: str, rendering: str) -> dict:
        s = LocalizerSettings()
        s.convergence.method = method
        s.observation.rendering = rendering
        t0 = time.perf_counter()
        loc = build_localizer(
            mesh_map, s, rng=np.random.default_rng(args.seed), device=args.device, sensor_height_m=1.73
        )
        loc.spread(args.many)
        loc.warm_up(seq.scan(0), tuple(seq.imu_roll_pitch[0]) if seq.imu_roll_pitch is not None else None)
        startup_s = time.perf_counter() - t0
        frame_s, after_s, conv_at, conv_err, fix_s, fix_m = [], [], None, None, None, None
        for i in range(min(args.search_frames, len(seq))):
            delta = se2_between(odo[i - 1], odo[i]) if i else np.zeros(3)
            rp = tuple(seq.imu_roll_pitch[i]) if seq.imu_roll_pitch is not None else None
            converged_before = loc.converged
            info = loc.step(
                delta,
                seq.scan(i),
                fire_time_s=seq.point_meta(i).get("time_s"),
                frame_period_s=period,
                roll_pitch=rp,
            )
            if converged_before:  # after the convergence: the probation's frames
                after_s.append(info.seconds)
                if len(after_s) >= probation_frames:
                    break
                continue
            frame_s.append(info.seconds)  # the converging frame is the search's last
            if info.converged:
                conv_at, conv_err = i, float(np.hypot(*(info.estimate[:2] - truth[i, :2])))
                if conv_err <= 5.0:  # the first correct fix: the compute through this frame, metres driven
                    fix_s = sum(frame_s)
                    fix_m = float(np.hypot(*np.diff(truth[: i + 1, :2], axis=0).T).sum())
                if probation_frames <= 0:
                    break
        every = frame_s + after_s
        return {
            "method": method,
            "rendering": rendering,
            "particles": args.many if method != "prior" else None,
            "seconds_per_frame_median": statistics.median(frame_s) if frame_s else None,
            "seconds_per_frame_max": max(frame_s) if frame_s else None,
            "search_frame_count": len(frame_s),
            "frames_over_100ms": sum(t > 0.1 for t in frame_s),
            "converged_frame": conv_at,
            "error_at_convergence_m": conv_err,
            "first_fix_seconds": fix_s,
            "first_fix_driven_m": fix_m,
            "startup_seconds": startup_s,
            "probation_frames": len(after_s),
            "probation_seconds_median": statistics.median(after_s) if after_s else None,
            "probation_seconds_max": max(after_s) if after_s else None,
            "worst_frame_seconds": max(every) if every else None,
            "all_frames_over_100ms": sum(t > 0.1 for t in every),
            "recoveries": loc.recoveries,
        }

    searches = {
        f"{m}/{r}": global_search(m, r)
        for m in (x.strip() for x in args.search.split(","))
        if m
        for r in renderings
    }
    search = next(iter(searches.values()))

    # --- the place prior: rendered anew ---------------------------------------------------------------------
    import tempfile
    from pathlib import Path

    from rangemcl.localization.place_prior import PlacePrior, PriorParams, beam_params, grid_cells

    params = PriorParams(cell_m=settings.init.prior_cell_m)
    cells = grid_cells(loc.init_cells.corners, loc.init_cells.cell_m, params.cell_m)
    ground_z = mesh_map.ground.height_at(cells[:, 0], cells[:, 1])
    area_km2 = len(cells) * params.cell_m**2 / 1e6

    def render(p: PriorParams) -> dict:
        """A prior rendered anew on the cells: seconds, memory and disk, also per km2."""
        t0 = time.perf_counter()
        prior = PlacePrior.build(loc.caster, cells, ground_z, p)
        build_s = time.perf_counter() - t0
        with tempfile.TemporaryDirectory() as tmp:
            prior.save(Path(tmp) / "p.npz", "bench")
            disk = (Path(tmp) / "p.npz").stat().st_size
        return {
            "build_s": build_s,
            "memory_mb": prior.nbytes / 1e6,
            "disk_mb": disk / 1e6,
            "memory_mb_per_km2": prior.nbytes / 1e6 / area_km2,
            "build_s_per_km2": build_s / area_km2,
        }

    prior_fig = {"cells": len(cells), "cell_m": params.cell_m, "drivable_km2": area_km2, **render(params)}
    bparams = beam_params(params, args.beam_deg, loc.sensor_height_m)
    prior_fig["beam"] = {"beam_deg": bparams.beam_deg, **render(bparams)}
    out = {
        "device": loc.caster.device,
        "cores": os.cpu_count(),
        "rays_per_particle": o.rays,
        "map_triangles": mesh_map.n_triangles,
        "after_convergence": after,
        "after_convergence_by_rendering": tracked,
        "before_convergence": before,
        "global_search": search,
        "global_search_by_method": searches,
        "place_prior": prior_fig,
    }
    print(
        f"device {out['device']}, {out['cores']} cores, {o.rays} rays per particle, "
        f"map {mesh_map.n_triangles:,} triangles"
    )
    for a in tracked.values():
        print(
            f"after convergence ({args.few} particles, whole step, {a['rendering']} rendering): "
            f"{a['hz']:.1f} Hz (median {1000 * a['step_median_s']:.1f} ms; target >= 100 Hz); "
            f"weighting Warp {1000 * a['weighting_median_s_warp']:.1f} ms vs Embree's exact "
            f"{1000 * a['weighting_median_s_embree']:.1f} ms (Embree/Warp {a['embree_over_warp']:.2f}); "
            f"tracking error median {a['tracking_error_median_m']:.4f} m, 95th percentile "
            f"{a['tracking_error_p95_m']:.4f} m"
        )
        if a["refine_median_s"] is not None:
            print(
                f"  of which the scan-to-mesh refinement {1000 * a['refine_median_s']:.1f} ms per update "
                f"({a['refinements']} taken, {a['refused_refinements']} refused)"
            )
    if len(tracked) > 1:
        first, *others = tracked.values()
        for a in others:
            print(
                f"  {a['rendering']} against {first['rendering']}, same run: step "
                f"{first['step_median_s'] / a['step_median_s']:.2f}x faster, weighting "
                f"{first['weighting_median_s_warp'] / a['weighting_median_s_warp']:.2f}x"
            )
    print(
        f"before convergence ({args.many:,} particles): {before['update_median_s_warp']:.2f} s per frame "
        f"(target <= 3 s; paper <= 56.7 s on a GTX 1080 Ti); Embree weighting "
        f"{before['weighting_median_s_embree']:.2f} s (Embree/Warp {before['embree_over_warp']:.2f})"
    )
    for g in searches.values():
        who = f"{args.many:,} particles" if g["particles"] else "the place prior's hypotheses"
        print(
            f"global search, {g['method']}, {g['rendering']} rendering ({who}, from frame 0): "
            + (
                f"{g['seconds_per_frame_median']:.3f} s per frame median, {g['seconds_per_frame_max']:.3f} s "
                f"at most ({g['frames_over_100ms']} frames over 100 ms); "
                if g["seconds_per_frame_median"] is not None
                else ""
            )
            + (
                f"converged at frame {g['converged_frame']}, {g['error_at_convergence_m']:.2f} m off"
                if g["converged_frame"] is not None
                else f"not converged in {args.search_frames} frames"
            )
            + (
                f"; first correct fix after {g['first_fix_seconds']:.2f} s of compute and "
                f"{g['first_fix_driven_m']:.1f} m driven"
                if g["first_fix_seconds"] is not None
                else "; no correct fix"
            )
            + f"; start-up (filter, place priors) {g['startup_seconds']:.2f} s"
        )
        if g["probation_frames"]:
            n_all = g["search_frame_count"] + g["probation_frames"]
            print(
                f"  then {g['probation_frames']} frames of the probation: "
                f"{g['probation_seconds_median']:.3f} s per frame median, {g['probation_seconds_max']:.3f} s "
                f"at most; the whole global localization's worst frame {g['worst_frame_seconds']:.3f} s "
                f"({g['all_frames_over_100ms']} of {n_all} frames over 100 ms), {g['recoveries']} recoveries"
            )
    print(
        f"place prior: {prior_fig['cells']:,} cells of {params.cell_m:g} m ({area_km2:.3f} km2 drivable), "
        f"rendered in {prior_fig['build_s']:.1f} s ({prior_fig['build_s_per_km2']:.0f} s per km2), "
        f"{prior_fig['memory_mb']:.1f} MB in memory ({prior_fig['memory_mb_per_km2']:.0f} MB per km2), "
        f"{prior_fig['disk_mb']:.1f} MB on disk"
    )
    b = prior_fig["beam"]
    print(
        f"beam prior ({b['beam_deg']:g} deg beam, {args.beam_deg:g} asked): rendered in {b['build_s']:.1f} s "
        f"({b['build_s_per_km2']:.0f} s per km2), {b['memory_mb']:.1f} MB in memory "
        f"({b['memory_mb_per_km2']:.0f} MB per km2), {b['disk_mb']:.1f} MB on disk"
    )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=2)


if __name__ == "__main__":
    main()
