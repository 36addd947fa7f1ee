#!/usr/bin/env python3
"""What the scan's rays meet, at the true pose and at the spread pose that explains the scan best: the
rays as the localizer draws them, each classed by the surface it ends on (the road; a parked car of the
test drive's parked-car set only, of the map's set only, or of both; anything else, i.e. the static
structure) and by how it compares with the map (``agree``: within ``--tol``; ``short``: measured in front
of the map's surface; ``long``: beyond it), with the mean capped cost of each class under the localizer's
settings (``--config``). For a generated town (``simbed make-town``), whose parked cars are the scene's
``parked_v{k}_{i}`` bodies:

    python tools/ray_breakdown.py --seq DRIVE --map MAP --scene TOWN.xml --frames 178,182,186

At the true pose the classes come from the measured points (where the scan's rays end in the test
drive's scene); at the best spread pose from the map's surface where its rays meet it. It shows what a
place that beats the truth is preferred for: when the truth's cost is carried by rays on cars that the
map lacks while its static structure agrees, and the other place's static structure does not, the
observation model weighs the added objects over the static world.

With ``--along`` it also says where along the street the likelihood of the scan peaks near the true pose
(offsets within ``--along`` m, summed over ``--draws`` draws of the rays), for all rays, for the rays that
end on a parked car of either set, and for the rest: a peak off the truth that only the rays on parked
cars put there is the pull of cars parked near, but not at, where the mapping drive's cars stood.
"""

from __future__ import annotations

import argparse
import math
import re
import sys

import numpy as np

CAR_RADIUS_M = 2.7  # a point this near a parked car's centre (in x, y) and ...
CAR_TOP_M = 2.2  # ... at most this high above the ground lies on that car


def parked_cars(scene: str) -> dict[int, np.ndarray]:
    """The (x, y) of each parked-car body of the scene, by parked-car set."""
    from rangemcl.errors import InputError

    try:
        with open(scene, encoding="utf-8") as fh:
            text = fh.read()
    except OSError as err:
        raise InputError(f"{scene}: cannot read the scene ({err.strerror})") from None
    cars: dict[int, list] = {}
    for m in re.finditer(r'<body name="parked_v(\d+)_\d+" pos="([-+\deE. ]+)"', text):
        cars.setdefault(int(m.group(1)), []).append([float(v) for v in m.group(2).split()[:2]])
    if not cars:
        raise InputError(f"{scene}: no parked-car bodies (parked_v<set>_<car>): not a generated town?")
    return {k: np.array(v) for k, v in cars.items()}


def near_cars(xy: np.ndarray, cars: np.ndarray | None) -> np.ndarray:
    if cars is None or not len(cars):
        return np.zeros(len(xy), bool)
    d = np.linalg.norm(xy[:, None, :] - cars[None, :, :], axis=2).min(axis=1)
    return d < CAR_RADIUS_M


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seq", required=True, help="a recorded test drive with poses.txt (ground truth)")
    ap.add_argument("--map", required=True, help="its map folder")
    ap.add_argument("--scene", required=True, help="the town's MJCF scene (its parked-car bodies)")
    ap.add_argument("--frames", required=True, help="comma-separated frame numbers")
    ap.add_argument("--map-variant", type=int, default=0, help="the mapping drive's parked-car set")
    ap.add_argument("--particles", type=int, default=20000, help="poses spread over the map")
    ap.add_argument("--config", help="localizer settings YAML (default: the localizer's defaults)")
    ap.add_argument("--tol", type=float, default=0.3, help="metres: a ray agrees within this")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--along",
        type=float,
        default=0.0,
        help="metres: also the likelihood's peak along the street, within this",
    )
    ap.add_argument("--draws", type=int, default=8, help="with --along: draws of the rays summed")
    a = ap.parse_args()

    from rangemcl.config import load_config
    from rangemcl.datasets.kitti import load_sequence
    from rangemcl.errors import InputError
    from rangemcl.localization import LocalizerSettings, build_localizer
    from rangemcl.localization.pipeline import frame_rays, odometry_xyyaw, resolve_sensor_height
    from rangemcl.maps.meshmap import MeshMap
    from rangemcl.se2 import xyyaw_of

    cars = parked_cars(a.scene)
    seq = load_sequence(a.seq, require_poses=True)
    test_variant = seq.meta.get("parked_variant")
    if test_variant is None:
        raise InputError(f"{a.seq}: meta.yaml names no parked_variant (not a simbed recording?)")
    settings = load_config(LocalizerSettings, a.config)
    settings.observation.model = "range"
    o = settings.observation
    mesh_map = MeshMap.load(a.map)
    height, _ = resolve_sensor_height(seq, mesh_map, settings)
    loc = build_localizer(mesh_map, settings, seed=a.seed, sensor_height_m=height)
    truths = xyyaw_of(seq.poses)
    odo, _ = odometry_xyyaw(seq, False)

    def per_ray(rays, pose):
        c, s = math.cos(pose[2]), math.sin(pose[2])
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        origin = np.array([pose[0], pose[1], float(loc.sensor_z(pose[None, :2])[0])])
        dirs = rays.directions @ R.T
        hits = loc.caster.cast(origin, dirs, float(o.max_range_m + o.margin_m))
        rendered = np.where(hits.hit, hits.ranges, np.inf)
        e = rays.ranges - rendered  # > 0: measured beyond the map's surface; -inf: the map has nothing
        measured_at = origin + dirs * rays.ranges[:, None]
        rendered_at = origin + dirs * np.where(hits.hit, hits.ranges, rays.ranges)[:, None]
        behind = None
        if loc.model.explain_beyond:  # is there a map surface within cap_m of each measured point?
            cap = loc.model.cap_m
            near = loc.caster.cast(measured_at - dirs * cap, dirs, 2.0 * cap)
            behind = near.hit
        # sensor-frame heights of the measured points and of the map's surfaces met
        heights = (dirs[:, 2] * rays.ranges, dirs[:, 2] * np.where(hits.hit, hits.ranges, 0.0))
        cost = loc.model.ray_costs(e, *heights, behind)  # the kernel's per-ray costs
        return e, cost, measured_at, rendered_at, origin[2] - height

    every_car = np.vstack(list(cars.values()))

    def along_peaks(f: int, truth: np.ndarray) -> str:
        """Where along the street the summed log-likelihood peaks: all rays, those on cars, the rest."""
        offsets = np.round(np.arange(-a.along, a.along + 1e-9, 0.05), 2) + 0.0  # (+0.0: no -0.00)
        c, s = math.cos(truth[2]), math.sin(truth[2])
        poses = truth + offsets[:, None] * np.array([c, s, 0.0])
        z = loc.sensor_z(poses[:, :2])
        ll = {k: np.zeros(len(offsets)) for k in ("all", "cars", "rest")}
        share = []
        for k in range(a.draws):
            rays = frame_rays(seq, f, o, np.random.default_rng(a.seed + f + 7919 * k), odo)
            _, _, measured_at, _, ground = per_ray(rays, truth)
            low = measured_at[:, 2] - ground < CAR_TOP_M
            on_car = near_cars(measured_at[:, :2], every_car) & low & rays.structure
            share.append(on_car.mean())
            for key, m in (("all", np.ones_like(on_car)), ("cars", on_car), ("rest", ~on_car)):
                if m.sum() >= 10:
                    ll[key] += loc.scorer.score(rays.subset(m), poses, z)[0]
        at = {k: f"{offsets[int(np.argmax(v))]:+.2f} m" if v.any() else "-" for k, v in ll.items()}
        return (
            f"  along the street ({a.draws} draws): the likelihood peaks at {at['all']} (all rays), "
            f"{at['cars']} (the {np.mean(share):.0%} on parked cars), {at['rest']} (the rest)"
        )

    for f in (int(x) for x in a.frames.split(",") if x.strip()):
        if not 0 <= f < len(seq):
            raise InputError(f"{a.seq}: frame {f} is outside the sequence (0..{len(seq) - 1})")
        rays = frame_rays(seq, f, o, np.random.default_rng(a.seed + f), odo)
        loc.spread(a.particles)
        d = loc.residuals(rays)
        best = loc.particles[int(np.argmin(d))].copy()
        truth = truths[f]
        d_truth = float(loc.residuals(rays, truth[None])[0])
        away = math.hypot(*(best[:2] - truth[:2]))
        print(
            f"frame {f}: {len(rays.ranges)} rays; d at the truth {d_truth:.3f} m, best of "
            f"{a.particles} spread poses {float(d.min()):.3f} m, {away:.0f} m from the truth"
        )
        for name, pose in (("truth", truth), ("best", best)):
            e, cost, measured_at, rendered_at, ground = per_ray(rays, pose)
            at = measured_at if name == "truth" else rendered_at
            low = at[:, 2] - ground < CAR_TOP_M
            road = ~rays.structure
            test = near_cars(at[:, :2], cars.get(int(test_variant))) & low & ~road
            mapped = near_cars(at[:, :2], cars.get(a.map_variant)) & low & ~road
            agree, short, long_ = np.abs(e) < a.tol, e < -a.tol, e > a.tol
            print(
                f"  {name:5s} agree {agree.mean():.2f}  short {short.mean():.2f}  long {long_.mean():.2f}  "
                f"mean cost {cost.mean():.3f} m"
            )
            classes = (
                ("road", road),
                ("test-drive car", test & ~mapped),
                ("map's car", mapped & ~test),
                ("car of both", test & mapped),
                ("static", ~road & ~test & ~mapped),
            )
            for cname, m in classes:
                if m.any():
                    print(
                        f"    {cname:15s} {m.mean():5.0%} of the rays: agree {agree[m].mean():.2f} short "
                        f"{short[m].mean():.2f} long {long_[m].mean():.2f}, cost {cost[m].mean():.3f} m"
                    )
        if a.along > 0:
            print(along_peaks(f, truth))


if __name__ == "__main__":
    from rangemcl.errors import InputError

    try:
        main()
    except InputError as err:
        print(f"ray_breakdown: error: {err}", file=sys.stderr)
        raise SystemExit(2) from None
