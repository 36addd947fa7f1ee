"""Ground height from a scene's own static geometry, for scenes without a terrain sidecar.

A generated town describes its terrain in its sidecar (a height field). Any other MJCF scene or mesh
world has its ground among its static triangles: a plane, boxes, a ramp, a height field, an imported
mesh. :class:`SceneGround` finds it by casting vertical rays down through the static geometry (every
surface on the way, not only the first) and taking, under each point, the **lowest surface a car can
stand on**: a face whose normal points up (slope at most ``max_slope_deg``) with at least
``clearance_m`` of free space above it up to the next surface. So

* under a tree's crown or a bridge the ground is the road beneath (the crown's top is higher, the gap
  under the crown is the free space), a multi-level scene gives its lowest level;
* under a ramp or a box lying on the ground it is the ramp's or the box's top (the plane beneath is
  covered, no free space above it); under a building it is the roof: a route through a building is
  caught by the route checks (:mod:`simbed.scenes.lanes`), not here;
* where no surface qualifies (outside the scene, a hole) the height is NaN.

Heights are cast at query time (exact, no grid to keep), against the static mesh alone: the moving
bodies (actors, doors) and the ego car are not ground.
"""

from __future__ import annotations

import math

import numpy as np

from rangemcl.raycast import RayCaster


class SceneGround:
    """Ground height under (x, y) points from the static mesh ``static_handle`` of ``caster``.

    Args:
        caster: the scene's ray caster (the static world is one of its meshes).
        static_handle: the handle of that static mesh.
        top_z: a height above every static surface (rays start there).
        bottom_z: a height below every static surface (rays end there).
        clearance_m: free space a surface needs above it to count as ground (about a car's height).
        max_slope_deg: steeper faces are walls, not ground.
        max_layers: surfaces followed per vertical line (deeper ones are not looked at).
    """

    def __init__(
        self,
        caster: RayCaster,
        static_handle: int,
        top_z: float,
        bottom_z: float,
        *,
        clearance_m: float = 2.0,
        max_slope_deg: float = 35.0,
        max_layers: int = 16,
    ):
        self.caster = caster
        self.static_handle = int(static_handle)
        self.top_z = float(top_z) + 1.0
        self.bottom_z = float(bottom_z) - 1.0
        self.clearance_m = float(clearance_m)
        self.min_normal_z = math.cos(math.radians(max_slope_deg))
        self.max_layers = int(max_layers)

    @classmethod
    def from_triangles(cls, caster: RayCaster, static_handle: int, vertices: np.ndarray, **kw) -> SceneGround:
        v = np.asarray(vertices, np.float64)
        if len(v) == 0:
            return cls(caster, static_handle, 0.0, 0.0, **kw)
        return cls(caster, static_handle, float(v[:, 2].max()), float(v[:, 2].min()), **kw)

    def surfaces(self, x, y) -> tuple[np.ndarray, np.ndarray]:
        """Every static surface under each point, from the top down: heights ``(N, L)`` (NaN past the
        last) and the up-component of their normals ``(N, L)``."""
        x = np.atleast_1d(np.asarray(x, np.float64)).ravel()
        y = np.atleast_1d(np.asarray(y, np.float64)).ravel()
        n = len(x)
        z = np.full((n, self.max_layers), np.nan)
        nz = np.full((n, self.max_layers), np.nan)
        start = np.full(n, self.top_z)
        active = np.arange(n)
        layer = np.zeros(n, np.int64)
        down = np.array([0.0, 0.0, -1.0])
        eps = 1e-4
        for _ in range(self.max_layers):
            if len(active) == 0:
                break
            origins = np.stack([x[active], y[active], start[active]], axis=1)
            reach = start[active] - self.bottom_z
            dirs = np.tile(down, (len(active), 1))
            hits = self.caster.cast(origins, dirs, float(reach.max()), normals=True, only=self.static_handle)
            got = hits.hit & (hits.ranges <= reach)
            hz = start[active] - hits.ranges.astype(np.float64)
            for k in np.flatnonzero(got):
                i = active[k]
                if layer[i] < self.max_layers:
                    z[i, layer[i]] = hz[k]
                    nz[i, layer[i]] = float(hits.normals[k, 2])
                    layer[i] += 1
            start[active[got]] = hz[got] - eps
            keep = got & (layer[active] < self.max_layers)
            active = active[keep]
        return z, nz

    def height(self, x, y) -> np.ndarray:
        """Ground height under each point (NaN where there is none), the shape of ``x``."""
        shape = np.shape(x)
        z, nz = self.surfaces(x, y)
        above = np.concatenate([np.full((len(z), 1), np.inf), z[:, :-1]], axis=1)  # the surface above each
        ok = (nz >= self.min_normal_z) & ((above - z) >= self.clearance_m)
        ok &= np.isfinite(z)
        # the lowest qualifying surface: the last True along each row
        idx = np.where(ok.any(axis=1), self.max_layers - 1 - np.argmax(ok[:, ::-1], axis=1), -1)
        out = np.where(idx >= 0, z[np.arange(len(z)), np.maximum(idx, 0)], np.nan)
        return out.reshape(shape) if shape else out[0]
