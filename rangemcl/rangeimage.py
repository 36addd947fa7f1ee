"""Range images: projection of scans into an (H, W) grid, back-projection, and per-pixel ray geometry.

Paper Eq. 1 fixes the columns for every grid: ``u = 0.5·(1 − atan2(y, x)/π)·W``, so column ``W/2`` looks
forward and columns run clockwise seen from above. Rows come from one of two sources:

* a **spec grid** (:meth:`RangeImageGeometry.for_spec`): one row per beam of a :class:`LidarSpec`, sorted
  by elevation (row 0 the highest beam); each pixel's ray is that beam at that column, with the beam's
  azimuth offset and origin offset. Our own sensors fill this grid exactly.
* an **Eq. 1 grid** (:meth:`RangeImageGeometry.for_fov`): ``v = (1 − (asin(z/r) + |fov_down|)/fov)·H``,
  for arbitrary clouds such as KITTI scans.

A range image is ``(H, W)`` float32 with 0 where there is no return; when several points fall in one
pixel the closest wins (ties: the lowest point index).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rangemcl.errors import InputError


def column_azimuth_rad(width: int) -> np.ndarray:
    """Azimuth of each column centre by Eq. 1, ``(W,)``: pi·(1 − 2(c + 0.5)/W), from +pi down to −pi."""
    return np.pi * (1.0 - 2.0 * (np.arange(width) + 0.5) / width)


def azimuth_to_column(azimuth_rad: np.ndarray, width: int) -> np.ndarray:
    """Column index of each azimuth by Eq. 1 (wrapping, so every finite azimuth has a column)."""
    u = 0.5 * (1.0 - np.asarray(azimuth_rad) / np.pi) * width
    return np.floor(u).astype(np.int64) % width


def _unit(elevation: np.ndarray, azimuth: np.ndarray) -> np.ndarray:
    elevation, azimuth = np.broadcast_arrays(elevation, azimuth)
    ce = np.cos(elevation)
    return np.stack([ce * np.cos(azimuth), ce * np.sin(azimuth), np.sin(elevation)], axis=-1)


@dataclass(frozen=True)
class RangeImage:
    """A projected scan."""

    ranges: np.ndarray  # (H, W) float32 metres, 0 = no return
    index: np.ndarray  # (H, W) int32 index of the point that won each pixel, -1 = none
    rows: np.ndarray  # (N,) int32 row of each input point, -1 when it was dropped
    cols: np.ndarray  # (N,) int32 column of each input point, -1 when it was dropped

    @property
    def valid(self) -> np.ndarray:
        """(H, W) bool: pixels with a return."""
        return self.ranges > 0


@dataclass(frozen=True, eq=False)
class RangeImageGeometry:
    """The pixel grid of a range image and each pixel's ray in the sensor frame."""

    directions: np.ndarray  # (H, W, 3) float64 unit ray directions
    origins: np.ndarray  # (H, W, 3) float64 ray origins (beam origin offsets; zeros for Eq. 1 grids)
    row_elevation_rad: np.ndarray  # (H,) elevation of each row (pixel centre for Eq. 1 grids)
    row_azimuth_offset_rad: (
        np.ndarray
    )  # (H,) counter-clockwise azimuth of each row's beam from its column (0 for Eq. 1)
    fov_up_rad: float | None = None  # set for Eq. 1 grids
    fov_down_rad: float | None = None
    row_beam: np.ndarray | None = None  # (H,) beam index of each row, for spec grids

    @property
    def shape(self) -> tuple[int, int]:
        return self.directions.shape[:2]

    @property
    def is_spec_grid(self) -> bool:
        return self.row_beam is not None

    # ---------------------------------------------------------------- construction
    @classmethod
    def for_spec(cls, spec) -> RangeImageGeometry:
        """One row per beam of ``spec`` (sorted by elevation, highest first), ``spec.columns`` columns."""
        rows = np.asarray(spec.rows_by_elevation)
        elevation = np.deg2rad(np.asarray(spec.elevation_deg, dtype=np.float64)[rows])  # (H,)
        # spec offsets are measured clockwise (the way columns grow): a beam looks at atan2 = column − offset
        offset = -np.deg2rad(np.asarray(spec.azimuth_offset_deg, dtype=np.float64)[rows])  # (H,)
        encoder = column_azimuth_rad(spec.columns)  # (W,)
        directions = _unit(elevation[:, None], encoder[None, :] + offset[:, None])  # (H, W, 3)
        # beam origins sit on a circle of beam_origin_radius_m around the axis, turning with the encoder,
        # and each beam may have its own height offset
        radial = float(spec.beam_origin_radius_m)
        vertical = np.asarray(spec.beam_vertical_offset_m, dtype=np.float64)[rows]
        origins = np.zeros_like(directions)
        origins[..., 0] = radial * np.cos(encoder)[None, :]
        origins[..., 1] = radial * np.sin(encoder)[None, :]
        origins[..., 2] = vertical[:, None]
        return cls(directions, origins, elevation, offset, row_beam=rows.astype(np.int32))

    @classmethod
    def for_fov(cls, height: int, width: int, fov_up_deg: float, fov_down_deg: float) -> RangeImageGeometry:
        """An Eq. 1 grid of ``height × width`` pixels spanning elevations ``fov_down_deg .. fov_up_deg``."""
        if height < 1 or width < 1:
            raise InputError(f"range image size must be positive, got {height} x {width}")
        if not fov_up_deg > fov_down_deg:
            raise InputError(f"fov_up_deg ({fov_up_deg}) must be above fov_down_deg ({fov_down_deg})")
        up, down = np.deg2rad(fov_up_deg), np.deg2rad(fov_down_deg)
        elevation = up - (np.arange(height) + 0.5) / height * (up - down)  # pixel centres, (H,)
        directions = _unit(elevation[:, None], column_azimuth_rad(width)[None, :])
        return cls(directions, np.zeros_like(directions), elevation, np.zeros(height), float(up), float(down))

    # ---------------------------------------------------------------- projection
    def pixel_of(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Row, column (both ``(N,)`` int64, -1 when outside the grid) and range of each point.

        Spec grids pick the beam of nearest elevation; with beam origin offsets the pixel is found
        once from the raw angles, then refined once from the point's angles seen from that pixel's origin.
        """
        p = np.asarray(points, dtype=np.float64)
        rows, cols = self._angles_to_pixel(p)
        if self.is_spec_grid and np.any(self.origins):
            ok = rows >= 0
            q = p.copy()
            q[ok] -= self.origins[rows[ok], cols[ok]]
            rows, cols = self._angles_to_pixel(q, valid=ok)
        ok = rows >= 0
        r = np.full(len(p), np.nan)
        r[ok] = np.linalg.norm(p[ok] - self.origins[rows[ok], cols[ok]], axis=1)
        return rows, cols, r

    def _angles_to_pixel(self, p: np.ndarray, valid: np.ndarray | None = None):
        h, w = self.shape
        r = np.linalg.norm(p, axis=1)
        ok = np.isfinite(r) & (r > 0)
        if valid is not None:
            ok &= valid
        safe_r = np.where(ok, r, 1.0)
        elevation = np.arcsin(np.clip(p[:, 2] / safe_r, -1.0, 1.0))
        azimuth = np.arctan2(p[:, 1], p[:, 0])
        if self.is_spec_grid:
            # nearest beam by elevation; row_elevation_rad is sorted descending
            asc = self.row_elevation_rad[::-1]
            k = np.clip(np.searchsorted(asc, elevation), 1, h - 1) if h > 1 else np.zeros(len(p), np.int64)
            if h > 1:
                k = np.where(np.abs(asc[k - 1] - elevation) <= np.abs(asc[k] - elevation), k - 1, k)
            rows = (h - 1 - k).astype(np.int64)
            azimuth = azimuth - self.row_azimuth_offset_rad[rows]
        else:
            v = (1.0 - (elevation - self.fov_down_rad) / (self.fov_up_rad - self.fov_down_rad)) * h
            ok &= (v >= 0.0) & (v <= h)
            rows = np.minimum(np.floor(np.where(ok, v, 0.0)), h - 1).astype(np.int64)
        cols = azimuth_to_column(np.where(ok, azimuth, 0.0), w)
        rows[~ok] = -1
        cols[~ok] = -1
        return rows, cols

    def project(self, points, rows=None, cols=None) -> RangeImage:
        """Project an ``(N, 3)`` scan (sensor frame) into a range image; the closest point wins each pixel.

        Points that are NaN, at the origin, or outside the grid's field of view are dropped (their row and
        column are -1). ``rows``/``cols`` give each point's pixel directly (for example beam ring and firing
        column of our own sensors: ``rows = spec.row_of_beam[ring]``); then only the ranges are computed.
        The range is measured from the pixel's ray origin.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise InputError(f"points: expected shape (N, 3), got {p.shape}")
        h, w = self.shape
        if rows is None or cols is None:
            rows, cols, r = self.pixel_of(p)
        else:
            rows = np.asarray(rows, dtype=np.int64)
            cols = np.asarray(cols, dtype=np.int64)
            if rows.shape != (len(p),) or cols.shape != (len(p),):
                raise InputError(f"rows/cols: expected shape ({len(p)},), got {rows.shape} and {cols.shape}")
            inside = (rows >= 0) & (rows < h) & (cols >= 0) & (cols < w)
            rows, cols = np.where(inside, rows, -1), np.where(inside, cols, -1)
            r = np.linalg.norm(p - self.origins[np.maximum(rows, 0), np.maximum(cols, 0)], axis=1)
        keep = (rows >= 0) & np.isfinite(r) & (r > 0)
        rows = np.where(keep, rows, -1).astype(np.int32)
        cols = np.where(keep, cols, -1).astype(np.int32)
        ranges = np.zeros((h, w), np.float32)
        index = np.full((h, w), -1, np.int32)
        idx = np.flatnonzero(keep)
        if len(idx):
            pixel = rows[idx].astype(np.int64) * w + cols[idx]
            order = np.lexsort((idx, r[idx], pixel))  # by pixel, then range, then point index
            first = np.ones(len(order), bool)
            first[1:] = pixel[order][1:] != pixel[order][:-1]
            win = order[first]
            ranges.flat[pixel[win]] = r[idx[win]]
            index.flat[pixel[win]] = idx[win]
        return RangeImage(ranges, index, rows, cols)

    def back_project(self, ranges) -> np.ndarray:
        """Vertex map ``(H, W, 3)`` float32, sensor frame: each pixel's ray at its range; 0 where empty."""
        r = np.asarray(ranges, dtype=np.float64)
        if r.shape != self.shape:
            raise InputError(f"range image: expected shape {self.shape}, got {r.shape}")
        vertices = self.origins + r[..., None] * self.directions
        vertices[r <= 0] = 0.0
        return vertices.astype(np.float32)


def point_directions(points, origins=None) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray direction ``(N, 3)`` and range ``(N,)`` of each measured point, seen from ``origins``
    (``(3,)`` or ``(N, 3)``, default the sensor origin). Points at the origin get direction 0 and range 0."""
    p = np.asarray(points, dtype=np.float64)
    if origins is not None:
        p = p - np.asarray(origins, dtype=np.float64)
    r = np.linalg.norm(p, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        d = np.where(r[..., None] > 0, p / r[..., None], 0.0)
    return d, r
