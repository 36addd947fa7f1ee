"""Surface normals from range images (paper Eq. 2) and per-point normals of one scan.

Paper Eq. 2 (Chen et al., ICRA 2021) takes the normal of pixel ``(u, v)`` (``u`` the column, ``v`` the
row) of a vertex map ``V`` from forward differences::

    n(u, v) = (V(u+1, v) − V(u, v)) × (V(u, v+1) − V(u, v)),   normalised.

What :func:`vertex_map_normals` does, exactly:

* **Neighbours.** Columns wrap around at ``W`` when ``wrap_columns`` (a 360° sweep); rows never wrap.
  A neighbour is *usable* when it is inside the grid, has a return, and is not across a depth
  discontinuity (below). In each direction the forward neighbour (``u+1``, ``v+1``) is used as in Eq. 2;
  where it is not usable the backward one (``u−1``, ``v−1``) takes its place, so the last row and pixels
  just before a gap or a discontinuity still get normals. A pixel with no usable neighbour in one of the
  two directions gets no normal (a one-pixel-wide sliver, a lone return, a "mixed" pixel floating between
  two surfaces).
* **Depth discontinuities** (``max_edge_m``): neighbours ``a``, ``b`` (angle ``α`` between their rays)
  are on one surface when ``|V_b − V_a| ≤ max_edge_m + min(r_a, r_b)·sin α / sin(min_grazing_deg)``.
  The second term is the gap that a surface seen at the grazing angle ``min_grazing_deg`` leaves between
  the two rays (law of sines), so the test scales with range and with the angular spacing of the pair:
  it adapts to each sensor's resolution, and to the wider spacing of staggered beams. With the defaults
  (1 m, 3°) and 1024 columns, a depth step between neighbouring columns (0.35° apart) is a discontinuity
  above 2.2 m at 10 m range; flat ground 1.73 m below the sensor keeps its normals (measured through
  :func:`scan_normals`) to 41 m with an OS1-64 and 48 m with an HDL-64E, where it is seen at about 2–3°;
  a VLP-16 loses only its farthest ground ring (99 m). ``max_edge_m=None`` turns the test off;
  ``min_grazing_deg=None`` keeps the fixed ``max_edge_m`` only. Ranges are measured from the sensor
  origin (beam origin offsets of a few centimetres are ignored here).
* **Creases** (``crease_tol_deg``, an addition to the paper): at a fold such as a wall meeting the
  ground, the forward stencil can straddle the fold and give a normal of neither surface (a wall's bottom
  row would then look like ground). Each of the four stencils (forward/backward × forward/backward)
  whose neighbours are usable is scored by how far the next pixels out along its two directions
  (``u±2``, ``v±2``, where usable) leave its plane: the sine of the larger angle between those second
  differences and the plane. On a plane every score is 0 and Eq. 2's forward stencil is kept; at a
  crease the stencil that stays on one face wins. The stencil used is the first of (forward, forward),
  (backward, forward), (forward, backward), (backward, backward) — columns first — whose score is within
  ``sin(crease_tol_deg)`` of the best one, where stencils whose second differences could both be checked
  go before those with a missing one (off the grid, no return, or across a discontinuity: it cannot
  count as evidence of a plane). ``crease_tol_deg=None`` disables scoring (first usable stencil in that
  order: plain Eq. 2 with the backward fallback). On noisy scans the scoring also picks the locally
  smoothest stencil, which makes the normals markedly less noisy than plain Eq. 2.
* **Degenerate** stencils (the two differences parallel: sine of their angle ≤ 1e-6) are skipped like
  unusable ones.
* **Orientation**: every normal is flipped if needed so that ``n · V(u, v) < 0`` (toward the sensor).

Computation is in float64, vectorised over the whole image.
"""

from __future__ import annotations

import numpy as np

from rangemcl.errors import InputError

_DEGENERATE_SIN = 1e-6

# the four stencils, in order of preference: (column step, row step)
_STENCILS = ((1, 1), (-1, 1), (1, -1), (-1, -1))


def _shift(a: np.ndarray, k: int, axis: int, wrap: bool) -> tuple[np.ndarray, np.ndarray]:
    """``out[v, u] = a[v + k, u]`` (axis 0) or ``a[v, u + k]`` (axis 1), and where that neighbour exists."""
    out = np.roll(a, -k, axis=axis)
    n = a.shape[axis]
    inside = np.ones(a.shape[:2], bool)
    if not wrap:
        idx = np.arange(n) + k
        ok = (idx >= 0) & (idx < n)
        inside &= ok[:, None] if axis == 0 else ok[None, :]
    return out, inside


def _norm(a: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("...i,...i->...", a, a))


def vertex_map_normals(
    vertex_map,
    valid,
    *,
    max_edge_m: float | None = 1.0,
    wrap_columns: bool = True,
    min_grazing_deg: float | None = 3.0,
    crease_tol_deg: float | None = 1.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-pixel unit normals of a vertex map, oriented toward the sensor (module docstring: the rules).

    Args:
        vertex_map: ``(H, W, 3)`` points in the sensor frame.
        valid: ``(H, W)`` bool, pixels with a return (non-finite or zero vertices count as invalid).
        max_edge_m: constant part of the depth-discontinuity limit, metres; ``None``: no limit.
        wrap_columns: column ``W−1`` neighbours column 0 (a full sweep).
        min_grazing_deg: range-scaled part of the limit (see the module docstring); ``None``: none.
        crease_tol_deg: stencil choice at creases; ``None``: plain Eq. 2 with backward fallback.

    Returns:
        ``normals`` ``(H, W, 3)`` float32 (zeros where invalid) and ``normal_valid`` ``(H, W)`` bool.
    """
    V = np.asarray(vertex_map, dtype=np.float64)
    ok = np.asarray(valid, dtype=bool)
    if V.ndim != 3 or V.shape[2] != 3:
        raise InputError(f"vertex map: expected shape (H, W, 3), got {V.shape}")
    if ok.shape != V.shape[:2]:
        raise InputError(f"valid: expected shape {V.shape[:2]}, got {ok.shape}")
    for name, value in (("max_edge_m", max_edge_m), ("min_grazing_deg", min_grazing_deg)):
        if value is not None and not (np.isfinite(value) and value >= 0):
            raise InputError(f"{name} must be a non-negative number or None, got {value!r}")
    if crease_tol_deg is not None and not (np.isfinite(crease_tol_deg) and crease_tol_deg >= 0):
        raise InputError(f"crease_tol_deg must be a non-negative number or None, got {crease_tol_deg!r}")
    if min_grazing_deg is not None and not 0 < min_grazing_deg <= 90:
        raise InputError(f"min_grazing_deg must be in (0, 90], got {min_grazing_deg!r}")
    h, w = ok.shape
    if h == 0 or w == 0:
        return np.zeros((h, w, 3), np.float32), np.zeros((h, w), bool)

    r = _norm(V)
    with np.errstate(invalid="ignore"):
        ok = ok & np.isfinite(V).all(axis=2) & (r > 0)
    V = np.where(ok[..., None], V, 0.0)
    r = np.where(ok, r, 0.0)
    wrap = (False, bool(wrap_columns))  # per axis: rows never wrap

    # link[axis][v, u]: pixel and its +1 neighbour along axis are usable together
    link = []
    for axis in (0, 1):
        Vn, inside = _shift(V, 1, axis, wrap[axis])
        rn, _ = _shift(r, 1, axis, wrap[axis])
        okn, _ = _shift(ok, 1, axis, wrap[axis])
        good = ok & okn & inside
        if max_edge_m is not None:
            limit = np.full(good.shape, float(max_edge_m))
            if min_grazing_deg is not None:
                with np.errstate(invalid="ignore", divide="ignore"):
                    sin_alpha = _norm(np.cross(V, Vn)) / (r * rn)
                sin_alpha = np.where(good, sin_alpha, 0.0)
                limit += np.minimum(r, rn) * sin_alpha / np.sin(np.deg2rad(min_grazing_deg))
            good &= _norm(Vn - V) <= limit
        link.append(good)

    # per axis and step s = ±1: first difference V(+s) − V, its usability, second difference and usability
    first, first_ok, second, second_ok = {}, {}, {}, {}
    for axis in (0, 1):
        for s in (1, -1):
            V1, in1 = _shift(V, s, axis, wrap[axis])
            V2, in2 = _shift(V, 2 * s, axis, wrap[axis])
            # the link between the pixel and its neighbour at s, and between neighbours s and 2s
            l1, li1 = _shift(link[axis], 0 if s == 1 else -1, axis, wrap[axis])
            l2, li2 = _shift(link[axis], 1 if s == 1 else -2, axis, wrap[axis])
            first[axis, s] = V1 - V
            first_ok[axis, s] = l1 & li1 & in1
            second[axis, s] = V2 - V1
            second_ok[axis, s] = l2 & li2 & in2 & first_ok[axis, s]

    n_st = len(_STENCILS)
    normals = np.zeros((n_st, h, w, 3))
    usable = np.zeros((n_st, h, w), bool)
    score = np.full((n_st, h, w), np.inf)
    unchecked = np.zeros((n_st, h, w), np.int8)
    for i, (su, sv) in enumerate(_STENCILS):
        du, dv = first[1, su], first[0, sv]
        n = np.cross(du, dv)
        nn = _norm(n)
        with np.errstate(invalid="ignore", divide="ignore"):
            sin_angle = nn / (_norm(du) * _norm(dv))
            unit = n / nn[..., None]
        good = first_ok[1, su] & first_ok[0, sv] & (sin_angle > _DEGENERATE_SIN)
        unit = np.where(good[..., None], unit, 0.0)
        normals[i] = unit
        usable[i] = good
        if crease_tol_deg is not None:
            worst = np.zeros((h, w))
            for axis, s in ((1, su), (0, sv)):
                d2 = second[axis, s]
                length = _norm(d2)
                with np.errstate(invalid="ignore", divide="ignore"):
                    off = np.abs(np.einsum("...i,...i->...", unit, d2)) / length
                checked = second_ok[axis, s] & (length > 0)
                worst = np.maximum(worst, np.where(checked, off, 0.0))
                unchecked[i] += ~checked
            score[i] = np.where(good, worst, np.inf)

    if crease_tol_deg is None:
        pick = usable
    else:
        best = score.min(axis=0)
        pick = usable & (score <= best + np.sin(np.deg2rad(crease_tol_deg)))
        # among those, prefer stencils whose second differences could all be checked
        unchecked = np.where(pick, unchecked, 3)
        pick &= unchecked == unchecked.min(axis=0)
    normal_valid = pick.any(axis=0)
    choice = np.argmax(pick, axis=0)  # first stencil in order of preference
    out = np.take_along_axis(normals, choice[None, ..., None], axis=0)[0]
    out[~normal_valid] = 0.0
    flip = np.einsum("...i,...i->...", out, V) > 0
    out[flip] *= -1.0
    return out.astype(np.float32), normal_valid


def destagger_shifts(geometry) -> np.ndarray:
    """``(H,)`` int: columns by which each row's beam looks ahead of its column (0 for Eq. 1 grids).

    Pixel ``(r, c)`` of a spec grid looks along column ``c`` turned by the row's azimuth offset, i.e. at
    column position ``c − offset_r/Δ`` (Δ = 2π/W, columns turn clockwise); the shift is that rounded.
    """
    w = geometry.shape[1]
    offsets = np.asarray(geometry.row_azimuth_offset_rad, dtype=np.float64)
    return np.rint(offsets / (2.0 * np.pi / w)).astype(np.int64)


def scan_normals(
    points, geometry, rows=None, cols=None, *, destagger: bool = True, **kw
) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals ``(N, 3)`` float32 and their validity ``(N,)`` for the points of one scan.

    The scan (sensor frame) is projected with ``geometry`` (``rows``/``cols`` as in
    :meth:`RangeImageGeometry.project`; the closest point wins each pixel). The vertex map holds the
    winning points themselves (not their pixel's ray at the measured range), so normals follow the
    measured geometry. With ``destagger`` (and ``wrap_columns``, the default) each row is first rolled by
    :func:`destagger_shifts`, so that a pixel's row neighbours look in nearly the same azimuth (staggered
    beams such as the OS1's are up to 6° apart in one raw column); normals are mapped back afterwards.
    ``kw`` go to :func:`vertex_map_normals`. A point that lost its pixel to a closer one, or was dropped by
    the projection, gets a zero normal and ``valid`` False.
    """
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"points: expected shape (N, 3), got {p.shape}")
    normals = np.zeros((len(p), 3), np.float32)
    valid = np.zeros(len(p), bool)
    if len(p) == 0:
        return normals, valid
    image = geometry.project(p, rows=rows, cols=cols)
    h, w = geometry.shape
    won = image.index >= 0
    V = np.zeros((h, w, 3))
    V[won] = p[image.index[won]]
    shifts = destagger_shifts(geometry)
    roll = destagger and kw.get("wrap_columns", True) and bool(np.any(shifts))
    if roll:
        row_idx = np.arange(h)[:, None]
        src = (np.arange(w)[None, :] + shifts[:, None]) % w  # destaggered[r, j] = raw[r, j + k_r]
        n_d, ok_d = vertex_map_normals(V[row_idx, src], won[row_idx, src], **kw)
        back = (np.arange(w)[None, :] - shifts[:, None]) % w  # raw[r, c] = destaggered[r, c − k_r]
        n_img, ok_img = n_d[row_idx, back], ok_d[row_idx, back]
    else:
        n_img, ok_img = vertex_map_normals(V, won, **kw)
    got = won & ok_img
    idx = image.index[got]
    normals[idx] = n_img[got]
    valid[idx] = True
    return normals, valid
