"""Routes from waypoint files, for any scene: the file is the lane itself.

A waypoint file holds one waypoint per line, ``x y`` or ``x,y`` in metres, optionally a third number,
the speed in m/s from that waypoint on (``#`` starts a comment). :func:`lane_from_waypoints` turns it into
the lane the car follows: straight legs between the waypoints, each corner rounded by a circular arc
(as a driver would take it) no tighter than the car can steer, resampled every half metre; ``loop``
closes it back to the first waypoint. :func:`check_lane` then checks it against the scene before
anything is written: ground under every point, no step a car cannot climb, no static geometry in the
car's box anywhere along the way. Every problem names the first waypoint concerned (its line in the
file) in one error line.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from rangemcl.errors import InputError

# The car of scenes/car.xml, in its base frame (x forward from the rear axle, z up from the ground).
CAR_BOX_X = (-0.85, 3.65)  # the chassis from 0.85 m behind the rear axle to 0.95 m ahead of the front one
CAR_HALF_WIDTH_M = 0.9
CAR_BOX_Z = (0.30, 1.50)  # the chassis's bottom and top above the ground
CAR_MIN_RADIUS_M = 2.70 / math.tan(0.6)  # wheelbase / tan(full steering lock): 3.9 m

MAX_SPEED_MPS = 30.0


@dataclass(frozen=True)
class Waypoints:
    """Waypoints as read from a file: positions ``(P, 2)``, speeds ``(P,)`` (NaN: not given) and the line
    of the file each came from."""

    path: Path
    xy: np.ndarray
    speed: np.ndarray
    lines: np.ndarray

    def name(self, k: int) -> str:
        """Waypoint ``k`` as the error messages name it."""
        return (
            f"{self.path}:{int(self.lines[k])}: waypoint {k + 1} ({self.xy[k, 0]:.1f}, {self.xy[k, 1]:.1f})"
        )


def read_waypoints(path: str | Path) -> Waypoints:
    """Read a waypoint file; a malformed line is an :class:`InputError` naming the file and line."""
    path = Path(path)
    try:
        text = path.read_text()
    except (OSError, UnicodeDecodeError) as err:
        why = err.strerror if isinstance(err, OSError) else "not a text file"
        raise InputError(f"{path}: cannot read waypoints ({why or err})") from None
    rows, lines = [], []
    for n, raw in enumerate(text.splitlines(), 1):
        line = raw.split("#")[0].replace(",", " ").strip()
        if not line:
            continue
        parts = line.split()
        try:
            values = [float(v) for v in parts]
        except ValueError:
            raise InputError(f"{path}:{n}: expected 'x y' or 'x y speed', got {raw.strip()!r}") from None
        if len(values) not in (2, 3) or not np.isfinite(values).all():
            raise InputError(
                f"{path}:{n}: expected two or three finite numbers 'x y [speed]', got {raw.strip()!r}"
            )
        if len(values) == 3 and not 0.0 < values[2] <= MAX_SPEED_MPS:
            raise InputError(
                f"{path}:{n}: speed {values[2]:g} m/s: expected more than 0 and at most {MAX_SPEED_MPS:g}"
            )
        rows.append(values if len(values) == 3 else [*values, math.nan])
        lines.append(n)
    if len(rows) < 2:
        raise InputError(f"{path}: a route needs at least 2 waypoints, found {len(rows)}")
    arr = np.asarray(rows, np.float64)
    wp = Waypoints(path, arr[:, :2], arr[:, 2], np.asarray(lines))
    step = np.linalg.norm(np.diff(wp.xy, axis=0), axis=1)
    same = np.flatnonzero(step < 0.1)
    if len(same):
        raise InputError(f"{wp.name(int(same[0]) + 1)} repeats the waypoint before it")
    return wp


@dataclass(frozen=True)
class Lane:
    """The lane the car follows: points ``(Q, 2)`` every ``step_m`` or closer, the speed at each
    (``NaN``: the driver's own choice), and the waypoint whose leg each point belongs to."""

    points: np.ndarray
    speed: np.ndarray
    leg: np.ndarray
    waypoints: Waypoints
    loop: bool


def lane_from_waypoints(
    wp: Waypoints,
    *,
    loop: bool = False,
    corner_radius_m: float = 8.0,
    min_radius_m: float = 1.2 * CAR_MIN_RADIUS_M,
    step_m: float = 0.5,
) -> Lane:
    """Straight legs between the waypoints with every corner rounded by an arc of ``corner_radius_m``
    (less where the legs are short, each leg giving at most half its length to each of its corners); a
    corner that would need an arc tighter than ``min_radius_m`` is an :class:`InputError` naming it."""
    xy = wp.xy
    n = len(xy)
    if loop:
        if n < 3:
            raise InputError(f"{wp.path}: a loop needs at least 3 waypoints, found {n}")
        if np.linalg.norm(xy[0] - xy[-1]) < 0.1:
            raise InputError(
                f"{wp.name(n - 1)} repeats the first: give a loop's waypoints once (--loop closes it)"
            )
    legs = n if loop else n - 1
    a = xy[np.arange(legs)]
    b = xy[(np.arange(legs) + 1) % n]
    length = np.linalg.norm(b - a, axis=1)
    u = (b - a) / length[:, None]
    corners = range(n) if loop else range(1, n - 1)
    cut = np.zeros(n)  # distance cut back from each waypoint on both sides
    arcs: dict[int, tuple[float, float]] = {}  # waypoint -> (turn angle, radius)
    for k in corners:
        u_in, u_out = u[(k - 1) % legs], u[k % legs]
        turn = math.atan2(u_in[0] * u_out[1] - u_in[1] * u_out[0], float(np.clip(u_in @ u_out, -1, 1)))
        if abs(turn) < math.radians(1.0):
            continue
        half = math.tan(abs(turn) / 2)
        room = 0.5 * min(length[(k - 1) % legs], length[k % legs])
        r = min(corner_radius_m, room / half) if half > 1e-9 else corner_radius_m
        if r < min_radius_m:
            raise InputError(
                f"{wp.name(k)}: a turn of {math.degrees(abs(turn)):.0f} deg between legs of "
                f"{length[(k - 1) % legs]:.1f} m and {length[k % legs]:.1f} m leaves an arc of radius "
                f"{r:.1f} m; the car needs at least {min_radius_m:.1f} m (space the waypoints further "
                "apart or soften the turn)"
            )
        cut[k] = r * half
        arcs[k] = (turn, r)
    pts: list[np.ndarray] = []
    legs_of: list[int] = []

    def add(points: np.ndarray, leg: int) -> None:
        if pts and len(points) and np.linalg.norm(points[0] - pts[-1]) < 1e-9:
            points = points[1:]
        pts.extend(points)
        legs_of.extend([leg] * len(points))

    for k in range(legs):
        j = (k + 1) % n
        p0 = a[k] + u[k] * cut[k]
        p1 = b[k] - u[k] * cut[j]
        m = max(1, math.ceil(np.linalg.norm(p1 - p0) / step_m))
        add(p0 + (p1 - p0) * np.linspace(0, 1, m + 1)[:, None], k)
        if j in arcs and (loop or j < n - 1):
            turn, r = arcs[j]
            normal = np.array([-u[k][1], u[k][0]]) * math.copysign(1.0, turn)
            centre = p1 + normal * r
            a0 = math.atan2(p1[1] - centre[1], p1[0] - centre[0])
            m = max(2, math.ceil(abs(turn) * r / step_m))
            ang = a0 + np.linspace(0.0, turn, m + 1)
            add(centre + r * np.stack([np.cos(ang), np.sin(ang)], axis=1), j % legs)
    points = np.asarray(pts)
    leg = np.asarray(legs_of)
    if loop and len(points) > 2 and np.linalg.norm(points[-1] - points[0]) < 1e-6:
        points, leg = points[:-1], leg[:-1]  # the loop closes onto its first point
    speed = wp.speed[leg]
    return Lane(points, speed, leg, wp, loop)


def box_rays(
    x: tuple[float, float] = CAR_BOX_X,
    half_width_m: float = CAR_HALF_WIDTH_M,
    z: tuple[float, float] = CAR_BOX_Z,
    step_m: float = 0.3,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Rays that cross a box (by default the car's, in its base frame): ``(origins (R, 3), directions
    (R, 3), lengths (R,))`` along its length, across its width and down through it, ``step_m`` apart."""
    x0, x1 = x
    w = half_width_m
    z0, z1 = z
    xs = np.linspace(x0, x1, max(2, math.ceil((x1 - x0) / step_m) + 1))
    ys = np.linspace(-w, w, max(2, math.ceil(2 * w / step_m) + 1))
    zs = np.linspace(z0, z1, max(2, math.ceil((z1 - z0) / step_m) + 1))
    o, d, n = [], [], []
    for y in ys:  # along the box
        for zz in zs:
            o.append((x0, y, zz)), d.append((1.0, 0.0, 0.0)), n.append(x1 - x0)
    for xx in xs:  # across it
        for zz in zs:
            o.append((xx, -w, zz)), d.append((0.0, 1.0, 0.0)), n.append(2 * w)
    for xx in xs:  # down through it
        for y in ys:
            o.append((xx, y, z1)), d.append((0.0, 0.0, -1.0)), n.append(z1 - z0)
    return np.asarray(o), np.asarray(d), np.asarray(n)


def blocked(points, heading, z, caster, static_handle: int, rays=None) -> tuple[np.ndarray, np.ndarray]:
    """Whether a box (``rays``: :func:`box_rays`, default the car's) posed at each of ``points`` (Q, 2)
    with ``heading`` (Q,) on ground ``z`` (Q,) holds static geometry: ``(blocked (Q,) bool, the first hit
    of each blocked pose (Q, 3), NaN elsewhere)``."""
    o, d, length = rays if rays is not None else box_rays()
    pts = np.asarray(points, np.float64)
    c, s = np.cos(heading), np.sin(heading)
    ox = pts[:, 0, None] + c[:, None] * o[None, :, 0] - s[:, None] * o[None, :, 1]
    oy = pts[:, 1, None] + s[:, None] * o[None, :, 0] + c[:, None] * o[None, :, 1]
    oz = np.asarray(z, np.float64)[:, None] + o[None, :, 2]
    dx = c[:, None] * d[None, :, 0] - s[:, None] * d[None, :, 1]
    dy = s[:, None] * d[None, :, 0] + c[:, None] * d[None, :, 1]
    dz = np.broadcast_to(d[None, :, 2], dx.shape)
    origins = np.stack([ox, oy, oz], axis=-1).reshape(-1, 3)
    dirs = np.stack([dx, dy, dz], axis=-1).reshape(-1, 3)
    reach = np.broadcast_to(length[None, :], dx.shape).ravel()
    hits = caster.cast(origins, dirs, float(length.max()), only=static_handle)
    hit = (hits.hit & (hits.ranges <= reach)).reshape(len(pts), -1)
    where = np.full((len(pts), 3), np.nan)
    for i in np.flatnonzero(hit.any(axis=1)):
        k = i * len(o) + int(np.argmax(hit[i]))
        where[i] = origins[k] + dirs[k] * float(hits.ranges[k])
    return hit.any(axis=1), where


def headings(points: np.ndarray, loop: bool) -> np.ndarray:
    """The direction of travel at each point of a polyline (towards the next point)."""
    nxt = np.roll(points, -1, axis=0) if loop else np.vstack([points[1:], 2 * points[-1:] - points[-2:-1]])
    return np.arctan2(nxt[:, 1] - points[:, 1], nxt[:, 0] - points[:, 0])


def check_lane(lane: Lane, ground, caster, static_handle: int, *, max_step_m: float = 0.25) -> np.ndarray:
    """Check ``lane`` against a scene before driving it; return the ground height under each point.

    ``ground(x, y)`` gives heights (NaN: none); ``caster`` casts rays through the scene whose static
    world is the mesh ``static_handle``. Problems (an :class:`InputError` naming the first waypoint
    concerned): no ground under a point, a step in the ground between neighbouring points higher than
    ``max_step_m`` (a kerb, a wall's top, a roof edge), static geometry inside the car's box at any point
    along the lane."""
    wp, pts = lane.waypoints, lane.points
    z = np.asarray(ground(pts[:, 0], pts[:, 1]), np.float64)
    bad = np.flatnonzero(~np.isfinite(z))
    if len(bad):
        i = int(bad[0])
        raise InputError(
            f"{wp.name(int(lane.leg[i]))}: no ground under the route at ({pts[i, 0]:.1f}, {pts[i, 1]:.1f}) "
            f"({len(bad)} of {len(pts)} route points have none: outside the scene or over a hole)"
        )
    dz = np.abs(np.diff(np.concatenate([z, z[:1]]) if lane.loop else z))
    steep = np.flatnonzero(dz > max_step_m)
    if len(steep):
        i = int(steep[0])
        j = (i + 1) % len(pts)
        raise InputError(
            f"{wp.name(int(lane.leg[i]))}: the ground steps from {z[i]:.2f} m to {z[j]:.2f} m at "
            f"({pts[j, 0]:.1f}, {pts[j, 1]:.1f}) (a kerb, a wall or a building in the way; a car climbs at "
            f"most {max_step_m:.2f} m between route points {np.linalg.norm(pts[j] - pts[i]):.1f} m apart)"
        )
    stuck, where = blocked(pts, headings(pts, lane.loop), z, caster, static_handle)
    if stuck.any():
        i = int(np.flatnonzero(stuck)[0])
        raise InputError(
            f"{wp.name(int(lane.leg[i]))}: the car would hit the scene's static geometry at "
            f"({where[i, 0]:.1f}, {where[i, 1]:.1f}, {where[i, 2]:.1f}) on the way to the next waypoint "
            f"({int(stuck.sum())} of {len(pts)} route points blocked)"
        )
    return z
