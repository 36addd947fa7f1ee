"""Observation models for the Monte Carlo localizer: the paper's range-image model and three baselines.
Only the observation model changes between them, as in the paper's comparison; each scores all particles
against one scan's rays and returns log-likelihoods and a *badness* (lower is better: what the recovery
watches).

* ``range`` (paper Eq. 5): ``d = mean |measured − rendered|`` (capped per ray in the robust variant),
  ``log p = −½ d² / σ²``; badness ``d`` (m).
* ``overlap``: an analytic overlap model, no network: the share ``a`` of rays whose rendered range agrees
  with the measured one within ``overlap_tau_m``; ``log p = −½ ((1 − a) / σ_o)²``; badness ``1 − a``.
* ``likelihood_field``: the beam-end model (Thrun et al.) on a 10 cm voxel map of the mesh's surface (the
  mesh sampled densely, one point per occupied voxel): each ray's end point at the particle's pose is
  scored by its distance ``e`` to the nearest occupied voxel, ``log p = w · mean log(z_hit · exp(−½
  e²/σ²) + z_rand)``; badness ``mean min(e, 1 m)``. Rays are not cast through the map at all. Over a
  map held within a memory budget (``--map-memory``) the voxels are made and held tile by tile with the
  tiles the budget holds (:class:`TiledLikelihoodFieldModel`).
* ``histogram`` (after Röhling et al., IROS 2015): range histograms of the measured rays and of the rays
  rendered at the particle's pose, compared by the Wasserstein distance of their normalised histograms
  (as a share of the histogram range); ``log p = −½ (W / σ_h)²``; badness ``W``. Histograms do not see
  yaw, so this model cannot tell headings apart on its own.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from rangemcl.errors import InputError
from rangemcl.localization.renderer import ParticleRenderer

MODEL_NAMES = ("range", "overlap", "likelihood_field", "histogram")


class ScoringModel:
    """Base: ``score(rays, particles, sensor_z) -> (log-likelihood (N,), badness (N,))``.

    Models that cast rays also leave ``last_inliers`` ``(N,)``: per particle, the share of the scan's
    structure rays (those that met something above the ground: the ground agrees almost anywhere) that
    agree with the map within ``inlier_m``, leaving out those more than ``cap_m`` off the map's surface
    either way (objects added since the map was made, or removed from it) but never more than half of
    them (at a wrong pose most are far off); lost detection watches it.
    ``None`` for models without it."""

    name = ""
    lost_floor = 0.3  # the recovery's floor on the best badness, in the model's units
    last_inliers: np.ndarray | None = None
    inlier_m = 0.3

    def score(
        self, rays, particles: np.ndarray, sensor_z: np.ndarray, about=None, about_of=None
    ) -> tuple[np.ndarray, np.ndarray]:
        """``about`` ``(x, y, yaw, sensor_z)`` (or ``(K, 4)`` with ``about_of``, each particle's): particles
        close around this pose may be rendered about it (:meth:`ParticleRenderer.planar_scores`); models
        that cast no rays ignore it."""
        raise NotImplementedError


def inlier_share(scores: dict) -> np.ndarray:
    """The share of the structure rays that agree with the map within the inlier distance."""
    return scores["structure"].astype(np.float64)


class RangeModel(ScoringModel):
    name = "range"
    lost_floor = 0.3

    def __init__(self, kernel: ParticleRenderer, sigma_m: float, movable_height_m: float | None = None):
        if not sigma_m > 0:
            raise InputError(f"range model: sigma_m must be > 0, got {sigma_m}")
        if movable_height_m is not None and not movable_height_m > 0:
            raise InputError(f"range model: movable_height_m must be > 0, got {movable_height_m}")
        self.kernel = kernel
        self.sigma = float(sigma_m)
        self.movable_height_m = movable_height_m

    def change_top_z(self, rays) -> float | None:
        """The sensor-frame height below which the world may have changed, for these rays."""
        h = getattr(rays, "sensor_height_m", None)
        if self.movable_height_m is None or h is None:
            return None
        return self.movable_height_m - h

    def log_likelihood(self, mean_residuals: np.ndarray) -> np.ndarray:
        """Eq. 5 in log form: ``−½ d² / σ_d²``."""
        d = np.asarray(mean_residuals, np.float64)
        return -0.5 * d * d / self.sigma**2

    def score(self, rays, particles, sensor_z, about=None, about_of=None):
        self.kernel.set_scan(
            rays.directions, rays.ranges, structure=rays.structure, change_top_z=self.change_top_z(rays)
        )
        out = self.kernel.scores(particles, sensor_z, agree_m=self.inlier_m, about=about, about_of=about_of)
        self.last_inliers = inlier_share(out)
        d = out["mean"].astype(np.float64)
        return self.log_likelihood(d), d


class OverlapModel(ScoringModel):
    name = "overlap"
    lost_floor = 0.5

    def __init__(self, kernel: ParticleRenderer, tau_m: float, sigma: float):
        self.kernel = kernel
        self.tau = float(tau_m)
        self.sigma = float(sigma)

    def score(self, rays, particles, sensor_z, about=None, about_of=None):
        self.kernel.set_scan(rays.directions, rays.ranges, structure=rays.structure)
        out = self.kernel.scores(particles, sensor_z, agree_m=self.tau, about=about, about_of=about_of)
        self.last_inliers = inlier_share(out)
        a = out["agree"].astype(np.float64)
        bad = 1.0 - a
        return -0.5 * (bad / self.sigma) ** 2, bad


class HistogramModel(ScoringModel):
    name = "histogram"
    lost_floor = 0.05

    def __init__(self, kernel: ParticleRenderer, bins: int, top_m: float, sigma: float):
        self.kernel = kernel  # cast to the full range: histograms need the rendered ranges themselves
        self.bins = int(bins)
        self.top = float(top_m)
        self.sigma = float(sigma)

    def score(self, rays, particles, sensor_z, about=None, about_of=None):
        self.kernel.set_scan(rays.directions, rays.ranges)
        rendered = self.kernel.scores(
            particles, sensor_z, hist_bins=self.bins, hist_top_m=self.top, about=about, about_of=about_of
        )["hist"]
        measured, _ = np.histogram(rays.ranges, bins=self.bins, range=(0.0, self.top))
        w = wasserstein_1d(rendered.astype(np.float64), measured.astype(np.float64)[None, :])
        return -0.5 * (w / self.sigma) ** 2, w


def wasserstein_1d(h1: np.ndarray, h2: np.ndarray) -> np.ndarray:
    """Earth mover's distance between normalised histograms on the same equal bins, as a share of their
    span (0 … 1); an empty histogram is at distance 1 from anything."""
    h1 = np.atleast_2d(np.asarray(h1, np.float64))
    h2 = np.atleast_2d(np.asarray(h2, np.float64))
    s1, s2 = h1.sum(axis=1, keepdims=True), h2.sum(axis=1, keepdims=True)
    c1 = np.cumsum(h1 / np.where(s1 > 0, s1, 1.0), axis=1)
    c2 = np.cumsum(h2 / np.where(s2 > 0, s2, 1.0), axis=1)
    w = np.abs(c1 - c2).sum(axis=1) / h1.shape[1]
    return np.where((s1[:, 0] > 0) & (s2[:, 0] > 0), w, 1.0)


class LikelihoodFieldModel(ScoringModel):
    name = "likelihood_field"
    lost_floor = 0.3

    def __init__(
        self,
        centres: np.ndarray | None,
        *,
        voxel_m: float = 0.1,
        sigma_m: float = 0.2,
        weight: float = 20.0,
        z_hit: float = 0.9,
    ):
        """``centres``: the surface voxels' centres (:func:`surface_voxels` or :func:`cached_surface_voxels`
        of the map); None for a subclass that holds its own (:class:`TiledLikelihoodFieldModel`)."""
        from scipy.spatial import cKDTree

        self.voxel = float(voxel_m)
        self.sigma = float(sigma_m)
        self.weight = float(weight)
        self.z_hit, self.z_rand = float(z_hit), 1.0 - float(z_hit)
        self.voxels = 0 if centres is None else len(centres)
        self.tree = None if centres is None else cKDTree(centres)

    def score(self, rays, particles, sensor_z, about=None, about_of=None, chunk: int = 1000):
        ends_local = rays.directions * rays.ranges[:, None]  # (R, 3) levelled sensor frame
        n = len(particles)
        loglik = np.empty(n)
        bad = np.empty(n)
        for lo in range(0, n, chunk):
            p = particles[lo : lo + chunk]
            c, s = np.cos(p[:, 2])[:, None], np.sin(p[:, 2])[:, None]
            x = p[:, 0:1] + c * ends_local[None, :, 0] - s * ends_local[None, :, 1]
            y = p[:, 1:2] + s * ends_local[None, :, 0] + c * ends_local[None, :, 1]
            z = np.asarray(sensor_z)[lo : lo + chunk, None] + ends_local[None, :, 2]
            pts = np.stack([x, y, z], axis=-1).reshape(-1, 3)
            e = self.distances(pts).reshape(len(p), -1)
            like = self.z_hit * np.exp(-0.5 * (e / self.sigma) ** 2) + self.z_rand
            loglik[lo : lo + chunk] = self.weight * np.log(like).mean(axis=1)
            bad[lo : lo + chunk] = e.mean(axis=1)
        return loglik, bad

    def distances(self, pts: np.ndarray) -> np.ndarray:
        """``(P,)`` distance of each point ``(P, 3)`` to the nearest surface voxel's centre, 1 m where none
        lies within 1 m."""
        e, _ = self.tree.query(pts, distance_upper_bound=1.0, workers=-1)
        return np.minimum(e, 1.0)  # beyond 1 m (inf from the query): 1 m


# bytes a surface voxel takes in a k-d tree: its centre (3 float64), which the tree shares, and 24 for the
# tree's index and nodes (scipy's cKDTree: the resident memory grew by 24 B a voxel beyond the centres
# when a tree of 3 M random points was built)
FIELD_BYTES_PER_VOXEL = 48


class TiledLikelihoodFieldModel(LikelihoodFieldModel):
    """The likelihood field over a map held within a memory budget (:class:`rangemcl.maps.view.
    MapView`): the surface voxels of each tile the view holds within the rays' reach of the particles
    (not the tiles loaded ahead), at the level it holds it (full or coarse),
    in one k-d tree a tile, made when the tile comes in (the voxels kept on disk per tile file, as
    :func:`cached_surface_voxels` keeps a whole map's) and dropped when it leaves. Their bytes count
    against the view's budget (``likelihood field`` among its derived items), so the tiles get what is
    left at the next update. A beam end is looked up in the trees whose tile box, 1 m wider, holds it:
    the nearest voxel within 1 m is found as in one tree over the whole map (a face belongs to one tile,
    so each voxel of the surface is in the tree of a tile whose box holds it).

    The trees are made in a worker thread, as the view loads its tiles: an update that the view made
    without waiting (tracking) scores with the trees that are ready and leaves the tiles whose tree is
    still being made out of it (their beam ends count as far from any surface; ``building`` says how
    many, ``updates_without_trees`` how often); a search, and the first update, wait for them."""

    def __init__(
        self,
        view,
        *,
        voxel_m: float = 0.1,
        sigma_m: float = 0.2,
        weight: float = 20.0,
        z_hit: float = 0.9,
        seed: int = 0,
    ):
        super().__init__(None, voxel_m=voxel_m, sigma_m=sigma_m, weight=weight, z_hit=z_hit)
        self.seed = int(seed)
        self.view = view
        self._trees: dict[int, tuple] = {}  # tile -> (level, tree or None when empty, box lo, box hi, bytes)
        self._pending: dict[int, tuple] = {}  # tile -> (level, future of the tree)
        self._pool = None
        self.nbytes = 0
        self.building = 0  # tiles in reach whose tree is not ready at the last update
        self.updates_without_trees = 0

    def _build(self, k: int, level: int):
        from scipy.spatial import cKDTree

        centres = tile_surface_voxels(self.view.store, k, bool(level), self.voxel, self.seed)
        if len(centres) == 0:
            return (level, None, None, None, 0)
        lo, hi = centres.min(axis=0) - 1.0, centres.max(axis=0) + 1.0
        return (level, cKDTree(centres), lo, hi, FIELD_BYTES_PER_VOXEL * len(centres))

    def sync(self) -> None:
        """Follow the tiles the view holds within reach: drop the trees of tiles that left (or changed
        level), start making those of tiles that came in (waiting for them when the view's last update
        waited), take the finished ones, and count their bytes in the budget."""
        from concurrent.futures import ThreadPoolExecutor
        from concurrent.futures import wait as wait_futures

        if self._pool is None:
            self._pool = ThreadPoolExecutor(1, thread_name_prefix="field")
        held = self.view.cache.levels
        levels = {k: held[k] for k in self.view.in_range if k in held}
        for k in [k for k, t in self._trees.items() if levels.get(k) != t[0]]:
            del self._trees[k]
        for k in [k for k, (lvl, _fu) in self._pending.items() if levels.get(k) != lvl]:
            self._pending.pop(k)[1].cancel()
        for k, level in levels.items():
            if k not in self._trees and k not in self._pending:
                self._pending[k] = (level, self._pool.submit(self._build, k, level))
        if self._pending and (self.view.last_wait or not self._trees):
            wait_futures([fu for _lvl, fu in self._pending.values()])
        for k in [k for k, (_lvl, fu) in self._pending.items() if fu.done()]:
            self._trees[k] = self._pending.pop(k)[1].result()
        self.building = len(self._pending)
        self.updates_without_trees += self.building > 0
        trees = [t for t in self._trees.values() if t[1] is not None]
        self.voxels = sum(t[1].n for t in trees)
        self.nbytes = sum(t[4] for t in trees)
        view = self.view
        view.reserve("likelihood field", self.nbytes)
        cache = view.cache
        need = sum(min(s for s in cache.sizes[k] if s is not None) for k in levels)
        if cache.budget_bytes < need:  # the tiles in range would be evicted for their own voxels
            others = sum(v for k, v in view.derived.items() if k != "likelihood field")
            raise InputError(
                f"{view.source_dir}: --map-memory {view.budget_bytes / 1e6:g} MB is too small for the "
                f"likelihood field here: the voxels of the tiles in range take {self.nbytes / 1e6:.0f} MB, "
                f"the tiles {need / 1e6:.0f} MB, the rest of the map {others / 1e6:.0f} MB; give at least "
                f"{(self.nbytes + need + others) / 1e6 * 1.2:.0f} MB"
            )

    def score(self, rays, particles, sensor_z, about=None, about_of=None, chunk: int = 1000):
        self.sync()
        return super().score(rays, particles, sensor_z, chunk)

    def close(self) -> None:
        """Stop the worker thread."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def distances(self, pts: np.ndarray) -> np.ndarray:
        e = np.ones(len(pts))
        for _level, tree, lo, hi, _n in (t for t in self._trees.values() if t[1] is not None):
            inside = np.flatnonzero(((pts >= lo) & (pts <= hi)).all(axis=1))
            if len(inside):
                d, _ = tree.query(pts[inside], distance_upper_bound=1.0, workers=-1)
                e[inside] = np.minimum(e[inside], d)
        return np.minimum(e, 1.0)


def surface_voxels(
    vertices, faces, voxel_m: float, *, max_points: int = 400_000_000, seed: int = 0, chunk: int = 8_000_000
) -> np.ndarray:
    """Centres of the ``voxel_m`` voxels a triangle mesh's surface passes through: each triangle sampled
    at random points, about three per voxel face of its area (at least one; fewer for all when the total
    would pass ``max_points``), then one centre per occupied voxel. Sampled ``chunk`` points at a time, so
    memory follows the number of voxels, not of samples."""
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if len(f) == 0:
        raise InputError("likelihood field: the map has no triangles")
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    per = 3.0 * area / voxel_m**2
    scale = min(1.0, max_points / max(per.sum(), 1.0))
    counts = np.maximum(1, np.ceil(per * scale)).astype(np.int64)
    rng = np.random.default_rng(seed)
    lo = np.floor(v.min(axis=0) / voxel_m).astype(np.int64) - 1
    span = np.floor(v.max(axis=0) / voxel_m).astype(np.int64) + 2 - lo
    ends = np.cumsum(counts)
    keys, start = [], 0
    while start < len(f):
        stop = max(start + 1, int(np.searchsorted(ends, ends[start] - counts[start] + chunk, side="right")))
        tri = np.repeat(np.arange(start, stop), counts[start:stop])
        r1, r2 = np.sqrt(rng.uniform(size=len(tri))), rng.uniform(size=len(tri))
        pts = (1 - r1)[:, None] * a[tri] + (r1 * (1 - r2))[:, None] * b[tri] + (r1 * r2)[:, None] * c[tri]
        ijk = np.floor(pts / voxel_m).astype(np.int64) - lo
        keys.append(np.unique((ijk[:, 0] * span[1] + ijk[:, 1]) * span[2] + ijk[:, 2]))  # one int per voxel
        start = stop
    k = np.unique(np.concatenate(keys))
    ijk = np.column_stack([k // (span[1] * span[2]), (k // span[2]) % span[1], k % span[2]])
    return (ijk + lo + 0.5) * voxel_m


def _voxel_cache(key: str, compute) -> np.ndarray:
    """``compute()``'s voxel centres, kept in the cache directory under ``key`` (module functions)."""
    import hashlib
    import os

    from rangemcl.common.atomic import atomic_write

    root = os.environ.get("RANGEMCL_CACHE_DIR") or (
        Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "rangemcl"
    )
    path = Path(root) / f"surface-voxels-{hashlib.sha1(key.encode()).hexdigest()[:16]}.npy"
    try:
        centres = np.load(path)
        if centres.ndim == 2 and centres.shape[1] == 3:
            return centres
    except (OSError, ValueError):
        pass
    centres = compute()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, lambda fh: np.save(fh, centres))
    except (OSError, InputError):
        pass  # no cache: only slower next time
    return centres


def tile_surface_voxels(store, k: int, coarse: bool, voxel_m: float, seed: int = 0) -> np.ndarray:
    """:func:`surface_voxels` of tile ``k`` of a :class:`~rangemcl.maps.store.TileStore` (its coarse
    level with ``coarse``), kept in the cache directory keyed by the tile file and its checksum."""
    e = store.entries[k].coarse if coarse else store.entries[k]
    key = f"{(Path(store.map_dir) / e.file).resolve()}|{e.sha256}|{voxel_m!r}|{seed}|tile-v1"

    def compute() -> np.ndarray:
        v, f, _g = store.read(k, coarse=coarse)
        return surface_voxels(v, f, voxel_m, seed=seed) if len(f) else np.zeros((0, 3))

    return _voxel_cache(key, compute)


def cached_surface_voxels(mesh_map, voxel_m: float, seed: int = 0) -> np.ndarray:
    """:func:`surface_voxels` of a map, kept in a cache file when the map was loaded from a folder (a
    town-sized map takes minutes): ``$RANGEMCL_CACHE_DIR``, else ``$XDG_CACHE_HOME/rangemcl``, else
    ``~/.cache/rangemcl``; keyed by the map's tile index or mesh file (path, size, modification time) and
    the settings."""
    src = getattr(mesh_map, "source_dir", None)
    mesh = None  # the file that changes whenever the mesh does: the tile index (format 2) or mesh.ply (1)
    if src is not None:
        mesh = next((Path(src) / n for n in ("tiles.json", "mesh.ply") if (Path(src) / n).is_file()), None)
    if mesh is None:
        return surface_voxels(mesh_map.vertices, mesh_map.faces, voxel_m, seed=seed)
    st = mesh.stat()
    key = f"{mesh.resolve()}|{st.st_size}|{st.st_mtime_ns}|{voxel_m!r}|{seed}|v2"
    return _voxel_cache(key, lambda: surface_voxels(mesh_map.vertices, mesh_map.faces, voxel_m, seed=seed))


def make_model(name: str, caster, settings, mesh_map) -> ScoringModel:
    """The observation model ``name`` (one of :data:`MODEL_NAMES`) with the given ObservationSettings."""
    o = settings
    cap = np.inf if o.cap_m is None else o.cap_m
    beyond = cap if o.cap_beyond_m is None else o.cap_beyond_m
    short = cap if o.cap_short_m is None else o.cap_short_m
    if name == "range":
        return RangeModel(
            ParticleRenderer(
                caster,
                margin_m=o.margin_m,
                cap_m=cap,
                cap_beyond_m=beyond,
                cap_short_m=short,
                explain_beyond=o.explain_beyond,
            ),
            o.sigma_m,
            o.movable_height_m,
        )
    if name == "overlap":
        return OverlapModel(ParticleRenderer(caster, margin_m=o.margin_m), o.overlap_tau_m, o.overlap_sigma)
    if name == "histogram":
        kernel = ParticleRenderer(caster, margin_m=max(o.max_range_m, 1.0))
        return HistogramModel(kernel, o.histogram_bins, o.max_range_m, o.histogram_sigma)
    if name == "likelihood_field" and mesh_map.budgeted:  # a map within a memory budget
        return TiledLikelihoodFieldModel(
            mesh_map, voxel_m=o.field_voxel_m, sigma_m=o.field_sigma_m, weight=o.field_weight
        )
    if name == "likelihood_field":
        return LikelihoodFieldModel(
            cached_surface_voxels(mesh_map, o.field_voxel_m),
            voxel_m=o.field_voxel_m,
            sigma_m=o.field_sigma_m,
            weight=o.field_weight,
        )
    raise InputError(f"observation model {name!r}: expected one of {', '.join(MODEL_NAMES)}")
