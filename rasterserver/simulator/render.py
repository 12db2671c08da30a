"""Render a scene as the station's camera sees it under the projector's line raster.

Physics, per camera sub-sample (``supersampling`` x ``supersampling`` per pixel):

1. the camera ray hits the nearest surface (open3d ``RaycastingScene``);
2. the hit point's diapositive coordinate ``v`` gives the blurred raster transmission
   (:class:`~rasterserver.simulator.illumination.RasterLight`);
3. a shadow ray towards the projector centre decides whether the raster light arrives
   (cast for every pixel centre first; a sub-sample gets its own only where the 3 x 3
   neighbouring pixel centres disagree, i.e. near a shadow edge, so a shadow narrower than
   about one pixel may be missed in the image — never in the ground truth's pixel maps);
4. Lambertian shading: projector irradiance ``x max(0, n.l)`` ``x (d_ref/d)**2`` (optional),
   plus uniform ambient light, times the object's albedo at the point, gives expected
   photo-electrons;
5. the sub-sampled electron image is blurred by the camera PSF (Gaussian; the scene is
   rendered a few pixels beyond the sensor's edge so that the PSF sees real scene there) and
   box-averaged to pixels (the pixel's area integral), then digitised with shot noise, read
   noise, saturation and quantisation (:mod:`rasterserver.simulator.noise`).

Accuracy (tests/simulator/test_render.py): on planes, noise-free, the first-moment centre of
every line peak lies within 0.002 px of the analytic prediction; 3 x 3 supersampling is
within ~1 % in intensity of a 7 x 7 reference.

Ground truth is traced separately at the exact pixel centres (points, normals, object,
raster line, shadows) and, per column, the exact rows of all visible line centres
(:func:`rasterserver.simulator.ground_truth.find_line_rows`).

All randomness comes from ``numpy.random.default_rng(seed)``: one seed, one image.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from rasterserver.optics import Camera, Station, undistort_normalized
from rasterserver.simulator.ground_truth import LineRows, find_line_rows
from rasterserver.simulator.illumination import RasterLight
from rasterserver.simulator.noise import expose
from rasterserver.simulator.scene import Scene
from rasterserver.simulator.tracing import Hits, Tracer

__all__ = ["RenderSettings", "Rendering", "render"]

_MAX_BAND_RAYS = 1 << 22  # rays per ray-casting batch: bounds memory for large sensors


@dataclass(frozen=True)
class RenderSettings:
    """How to render: optics, light levels and the sensor.

    Attributes
    ----------
    supersampling : int
        Sub-samples per pixel along each axis (3: 3 x 3, on a regular grid).
    projector_defocus : float
        Gaussian sigma of the projector blur in diapositive units (~mm on the back).
    camera_blur : float
        Gaussian sigma of the camera PSF in pixels (0: none).
    projector_electrons : float
        Photo-electrons per pixel from a fully transparent diapositive on a surface of albedo
        1 facing the projector at the reference distance (projector centre to world origin).
    ambient_electrons : float
        Photo-electrons per pixel from ambient light on albedo 1 (not shadowed).
    background_electrons : float
        Photo-electrons where no surface is hit (far wall).
    inverse_square : bool
        Projector irradiance falls with the squared distance from the projector.
    smooth_normals : bool
        Interpolate vertex normals where meshes have them.
    shadow_epsilon : float
        Shadow-ray start offset along the normal (mm).
    shadow_threshold : float
        Shadow rays are cast only where the raster transmission exceeds this (elsewhere the
        projector's contribution is below ``threshold x projector_electrons`` anyway).
    full_well : float
        Electrons at saturation.
    gain : float
        DN per electron.
    offset : float
        Black level (DN).
    read_noise : float
        Read noise (electrons rms).
    shot_noise : bool
        Poisson photo-electron noise.
    noise : bool
        False renders noise-free (deterministic rounding only).
    bit_depth : int
        8 (uint8) or 10-16 (uint16).
    line_rows : bool
        Compute the exact per-column line rows (ground truth); costs ~0.1 s.
        With ``projector_electrons = 0`` (projector off) the ground truth has no lines:
        ``line_number`` is -1, ``line_rows`` empty and every visible pixel is in "shadow".
    threads : int
        Worker threads shading bands of sub-samples (0: one per CPU). Albedo functions are
        then called from several threads at once (pure numpy functions are safe).
    """

    supersampling: int = 3
    projector_defocus: float = 0.6
    camera_blur: float = 0.5
    projector_electrons: float = 30000.0
    ambient_electrons: float = 800.0
    background_electrons: float = 0.0
    inverse_square: bool = True
    smooth_normals: bool = True
    shadow_epsilon: float = 0.05
    shadow_threshold: float = 1e-4
    full_well: float = 20000.0
    gain: float = 0.0125
    offset: float = 6.0
    read_noise: float = 12.0
    shot_noise: bool = True
    noise: bool = True
    bit_depth: int = 8
    line_rows: bool = True
    threads: int = 0

    def __post_init__(self) -> None:
        if self.supersampling < 1:
            raise ValueError("supersampling must be >= 1")
        if self.camera_blur < 0 or self.projector_defocus < 0:
            raise ValueError("blur sigmas must be >= 0")

    def replace(self, **changes: Any) -> RenderSettings:
        """A copy with some fields changed."""
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True, eq=False)
class Rendering:
    """A simulated camera frame with its exact ground truth.

    Attributes
    ----------
    image : numpy.ndarray
        ``(H, W)`` uint8 or uint16 digitised frame.
    electrons : numpy.ndarray
        ``(H, W)`` float32 expected photo-electrons (noise-free, after camera blur, before
        saturation): the "float image".
    points : numpy.ndarray
        ``(H, W, 3)`` float64 surface point (world mm) seen at each pixel centre; NaN where
        nothing is hit.
    normals : numpy.ndarray
        ``(H, W, 3)`` float32 unit normals facing the camera (0 where nothing is hit).
    object_index : numpy.ndarray
        ``(H, W)`` int16 index into ``object_names`` (-1: nothing).
    object_names : list of str
        Scene object names.
    line_number : numpy.ndarray
        ``(H, W)`` int32 absolute number of the raster line whose centre is nearest (in
        ``v``) to the pixel-centre point; -1 where not lit by the raster (nothing hit, shadow,
        outside the raster's extent).
    diapositive : numpy.ndarray
        ``(H, W, 2)`` float64 diapositive coordinates ``(u, v)`` of the pixel-centre point.
    visible : numpy.ndarray
        ``(H, W)`` bool: a surface is hit at the pixel centre.
    shadow : numpy.ndarray
        ``(H, W)`` bool: visible but not reached by projector light (cast shadow, surface
        turned away from the projector, or outside the diapositive).
    line_rows : LineRows
        Exact rows of visible line centres per column.
    settings : RenderSettings
    seed : int
    timings : dict
        Seconds per phase: ``subsamples`` is the wall time of the sub-sample pass; the
        phases inside it (``rays``, ``ray_casting``, ``shadow_rays``, ``shading``) are summed
        over its worker threads.
    """

    image: np.ndarray
    electrons: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    object_index: np.ndarray
    object_names: list[str]
    line_number: np.ndarray
    diapositive: np.ndarray
    visible: np.ndarray
    shadow: np.ndarray
    line_rows: LineRows
    settings: RenderSettings
    seed: int
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def expected_dn(self) -> np.ndarray:
        """Noise-free float image in DN: ``gain * electrons + offset`` (no clipping)."""
        return self.settings.gain * self.electrons.astype(np.float64) + self.settings.offset

    def settings_dict(self) -> dict[str, Any]:
        """Settings as a JSON-ready dict."""
        return dataclasses.asdict(self.settings)


# ---------------------------------------------------------------------- camera rays
_IDEAL_GRID_CACHE: dict[tuple[str, int], np.ndarray] = {}


def _ideal_grid(camera: Camera, pad: int = 1) -> np.ndarray:
    """Ideal normalised coordinates at pixel centres ``-pad .. W-1+pad`` (and rows alike).

    Shape ``(H + 2 pad, W + 2 pad, 2)``, exact (Newton) undistortion.
    """
    key = (camera.key(), pad)
    grid = _IDEAL_GRID_CACHE.get(key)
    if grid is None:
        h, w = camera.shape  # ints (width and height are typed float on the base class)
        u, v = np.meshgrid(
            np.arange(-pad, w + pad, dtype=np.float64), np.arange(-pad, h + pad, dtype=np.float64)
        )
        xd, yd = camera.image_to_normalized(np.column_stack([u.ravel(), v.ravel()]))
        x, y = undistort_normalized(xd, yd, camera.dist)
        grid = np.stack([x, y], axis=-1).reshape(h + 2 * pad, w + 2 * pad, 2)
        if len(_IDEAL_GRID_CACHE) >= 2:
            _IDEAL_GRID_CACHE.pop(next(iter(_IDEAL_GRID_CACHE)))
        _IDEAL_GRID_CACHE[key] = grid
    return grid


_RAY_CACHE: dict[tuple[str, int, int, int, int], np.ndarray] = {}
_RAY_CACHE_MAX_BYTES = 160 * 2**20
_RAY_CACHE_LOCK = threading.Lock()


def _band_rays(camera: Camera, s: int, row0: int, row1: int, margin: int) -> np.ndarray:
    """Float32 ``(N, 6)`` camera rays of the sub-samples of extended pixel rows ``row0:row1``.

    The extended image has ``margin`` extra pixels on every side (extended row ``i`` is
    image row ``i - margin``).

    Cached per camera for small sensors: the rays of a camera never change, and building
    them costs as much as casting them.
    """
    key = (camera.key(), s, row0, row1, margin)
    with _RAY_CACHE_LOCK:
        rays = _RAY_CACHE.get(key)
    if rays is None:
        dirs = _band_directions(camera, s, row0, row1, margin)
        rays = np.empty((dirs.shape[0], 6), dtype=np.float32)
        rays[:, :3] = camera.centre.astype(np.float32)[None, :]
        rays[:, 3:] = dirs
        if rays.nbytes <= _RAY_CACHE_MAX_BYTES:
            with _RAY_CACHE_LOCK:  # bands are built from worker threads
                while _RAY_CACHE and (
                    sum(r.nbytes for r in _RAY_CACHE.values()) + rays.nbytes > _RAY_CACHE_MAX_BYTES
                ):
                    _RAY_CACHE.pop(next(iter(_RAY_CACHE)))
                _RAY_CACHE[key] = rays
    return rays


def _subsample_offsets(s: int) -> np.ndarray:
    return (np.arange(s) + 0.5) / s - 0.5


def _band_directions(camera: Camera, s: int, row0: int, row1: int, margin: int) -> np.ndarray:
    """World unit directions of the sub-samples of extended pixel rows ``row0:row1``.

    The undistortion is exact at pixel centres and bilinearly interpolated in between:
    the interpolation error is ~1e-5 px for the distortions of real lenses (it scales with
    the second derivative of the distortion, ~6 k1 x / f**2 per px**2).
    """
    grid = _ideal_grid(camera, margin + 1)
    w = camera.shape[1] + 2 * margin
    n = row1 - row0
    out = np.empty((n * s, w * s, 2), dtype=np.float64)
    offs = _subsample_offsets(s)
    for a, oy in enumerate(offs):
        by = row0 + (0 if oy < 0 else 1)  # padded index of the upper neighbour
        fy = oy + 1.0 if oy < 0 else oy
        for b, ox in enumerate(offs):
            bx = 0 if ox < 0 else 1
            fx = ox + 1.0 if ox < 0 else ox
            g00 = grid[by : by + n, bx : bx + w]
            g01 = grid[by : by + n, bx + 1 : bx + 1 + w]
            g10 = grid[by + 1 : by + 1 + n, bx : bx + w]
            g11 = grid[by + 1 : by + 1 + n, bx + 1 : bx + 1 + w]
            out[a::s, b::s] = (1 - fy) * ((1 - fx) * g00 + fx * g01) + fy * (
                (1 - fx) * g10 + fx * g11
            )
    d = np.empty((n * s, w * s, 3), dtype=np.float32)
    d[..., :2] = out
    d[..., 2] = 1.0
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    if not np.allclose(camera.R, np.eye(3)):
        d = d @ camera.R.astype(np.float32)
    return d.reshape(-1, 3)


# ---------------------------------------------------------------------- shading
_TEST, _KNOWN_LIT, _KNOWN_BLOCKED = 0, 1, 2


@dataclass
class _Shaded:
    electrons: np.ndarray  # (N,) float32 expected electrons
    v: np.ndarray  # (N,) float32 diapositive v (NaN: facing away or outside the diapositive)
    lit: np.ndarray  # (N,) bool lit by the projector
    candidate: np.ndarray  # (N,) bool facing the projector inside the diapositive


def _albedo(scene: Scene, obj: np.ndarray, points: np.ndarray) -> np.ndarray:
    out = np.zeros(obj.shape, dtype=np.float32)
    for index, so in enumerate(scene.objects):
        sel = obj == index
        if not np.any(sel):
            continue
        if callable(so.albedo):
            out[sel] = np.asarray(so.albedo(points[sel].astype(np.float64)), dtype=np.float32)
        else:
            out[sel] = float(so.albedo)
    return out


def _shade(
    scene: Scene,
    tracer: Tracer,
    station: Station,
    light: RasterLight,
    settings: RenderSettings,
    origins: np.ndarray,
    directions: np.ndarray,
    hits: Hits,
    *,
    shadow_hint: np.ndarray | None,
) -> tuple[_Shaded, dict[str, float]]:
    """Expected electrons of every ray.

    ``shadow_hint`` (per ray, optional): ``_KNOWN_LIT`` / ``_KNOWN_BLOCKED`` skip the shadow
    ray; ``_TEST`` casts one where raster light could arrive. Without hints every such ray
    is tested, whatever the transmission (the ground truth's shadow mask needs that).
    """
    t0 = time.perf_counter()
    n = hits.t.size
    electrons = np.full(n, settings.background_electrons, dtype=np.float32)
    v_all = np.full(n, np.nan, dtype=np.float32)
    lit_all = np.zeros(n, dtype=bool)
    cand_all = np.zeros(n, dtype=bool)
    sel = np.flatnonzero(hits.hit)
    if sel.size == 0:
        return _Shaded(electrons, v_all, lit_all, cand_all), {"shading": time.perf_counter() - t0}
    everything = sel.size == n  # common (a back filling the frame): skip the gathers

    def pick(a: np.ndarray) -> np.ndarray:
        return a if everything else a[sel]

    o = origins if origins.shape[0] == 1 else pick(origins)
    p = pick(hits.t)[:, None] * pick(directions)
    p += o
    nrm = pick(hits.normals)
    projector = station.projector
    uv = projector.project(p)
    centre = projector.centre.astype(np.float32)
    to_proj = centre[None, :] - p
    d2 = np.einsum("ij,ij->i", to_proj, to_proj)
    cos = np.einsum("ij,ij->i", nrm, to_proj) / np.sqrt(d2)
    trans = light.transmission_fast(uv[:, 1])
    candidate = (cos > 0) & projector.in_bounds(uv)
    blocked = np.zeros(sel.size, dtype=bool)
    if shadow_hint is None:
        test = candidate
    else:
        hint = pick(shadow_hint)
        test = candidate & (hint == _TEST) & (trans > settings.shadow_threshold)
        blocked |= hint == _KNOWN_BLOCKED
    t1 = time.perf_counter()
    idx = np.flatnonzero(test)
    blocked[idx] = tracer.occluded(p[idx], nrm[idx], centre, epsilon=settings.shadow_epsilon)
    t2 = time.perf_counter()
    lit = candidate & ~blocked
    irr = trans * np.maximum(cos, 0.0)
    if settings.inverse_square:
        d_ref2 = float(np.dot(projector.centre, projector.centre))
        irr *= np.float32(d_ref2) / d2
    irr = np.where(lit, irr, np.float32(0.0))
    albedo = _albedo(scene, pick(hits.object_index), p)
    irr *= np.float32(settings.projector_electrons)
    irr += np.float32(settings.ambient_electrons)
    irr *= albedo
    # v wherever the raster can reach (cast shadows are decided per crossing later)
    v = np.where(candidate, uv[:, 1], np.float32(np.nan))
    if everything:
        electrons, v_all, lit_all, cand_all = irr, v, lit, candidate
    else:
        electrons[sel], v_all[sel], lit_all[sel], cand_all[sel] = irr, v, lit, candidate
    t3 = time.perf_counter()
    return _Shaded(electrons, v_all, lit_all, cand_all), {
        "shading": (t1 - t0) + (t3 - t2),
        "shadow_rays": t2 - t1,
    }


def _shadow_hints(hit: np.ndarray, shaded: _Shaded) -> np.ndarray:
    """Per extended pixel: is the whole pixel surely lit, surely shadowed, or to be tested?

    A pixel whose 3 x 3 neighbourhood of pixel centres is all lit (or all in cast shadow)
    is taken to be so over its whole area; sub-samples elsewhere get their own shadow ray.
    Only a shadow (or a gap in one) narrower than about a pixel can slip through; it spares
    most of the sub-sample shadow rays.
    """
    lit = (hit & shaded.lit).astype(np.uint8)
    dark = (hit & shaded.candidate & ~shaded.lit).astype(np.uint8)
    kernel = np.ones((3, 3), np.uint8)
    sure_lit = cv2.erode(lit, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    sure_dark = cv2.erode(dark, kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    hints = np.full(lit.shape, _TEST, dtype=np.uint8)
    hints[sure_lit.astype(bool)] = _KNOWN_LIT
    hints[sure_dark.astype(bool)] = _KNOWN_BLOCKED
    return hints


# ---------------------------------------------------------------------- truth at pixels
_PIXEL_DIRECTIONS_CACHE: dict[tuple[str, int], np.ndarray] = {}


def _pixel_directions(camera: Camera, margin: int = 0) -> np.ndarray:
    """Exact float64 world unit directions through the (extended) pixel centres.

    ``(H + 2 margin) * (W + 2 margin)`` rows, row-major.
    """
    key = (camera.key(), margin)
    d = _PIXEL_DIRECTIONS_CACHE.get(key)
    if d is None:
        # the sub-sample pass caches the grid padded by margin + 1: share it
        grid = _ideal_grid(camera, margin + 1)[1:-1, 1:-1].reshape(-1, 2)
        d = np.column_stack([grid, np.ones(grid.shape[0])])
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        if not np.array_equal(camera.R, np.eye(3)):
            d = d @ camera.R
        _PIXEL_DIRECTIONS_CACHE.clear()
        _PIXEL_DIRECTIONS_CACHE[key] = d
    return d


def _pixel_truth(
    tracer: Tracer,
    station: Station,
    light: RasterLight,
    directions: np.ndarray,
    hits: Hits,
    lit: np.ndarray,
) -> dict[str, np.ndarray]:
    """Ground-truth maps from the pixel-centre rays' hits and lighting."""
    camera = station.camera
    h, w = camera.shape
    o = np.broadcast_to(camera.centre, directions.shape)
    points = tracer.exact_points(o, directions, hits.triangle)
    uv = station.projector.project(points)
    raster = light.raster
    j = light.nearest(uv[:, 1])
    half = light.min_spacing / 2.0
    with np.errstate(invalid="ignore"):
        in_raster = (uv[:, 1] >= raster.positions[0] - half) & (
            uv[:, 1] <= raster.positions[-1] + half
        )
    number = np.where(lit & in_raster, raster.numbers[j], -1)
    visible = hits.hit
    return {
        "points": points.reshape(h, w, 3),
        "normals": hits.normals.reshape(h, w, 3),
        "object_index": hits.object_index.reshape(h, w),
        "line_number": number.astype(np.int32).reshape(h, w),
        "diapositive": uv.reshape(h, w, 2),
        "visible": visible.reshape(h, w),
        "shadow": (visible & ~lit).reshape(h, w),
    }


def _take_hits(hits: Hits, index: np.ndarray) -> Hits:
    return Hits(
        t=hits.t[index],
        hit=hits.hit[index],
        object_index=hits.object_index[index],
        triangle=hits.triangle[index],
        normals=hits.normals[index],
    )


# ---------------------------------------------------------------------- render
def render(
    scene: Scene,
    station: Station,
    *,
    settings: RenderSettings | None = None,
    seed: int = 0,
) -> Rendering:
    """Render one camera frame of ``scene`` with its ground truth.

    Parameters
    ----------
    scene : Scene
        Surfaces in world mm.
    station : Station
        Camera, projector and raster.
    settings : RenderSettings, optional
        Defaults to ``RenderSettings()``.
    seed : int
        Seed of the noise; the same seed gives the same image bit for bit.

    Returns
    -------
    Rendering
    """
    settings = settings or RenderSettings()
    t_start = time.perf_counter()
    timings = dict.fromkeys(("rays", "ray_casting", "shadow_rays", "shading"), 0.0)
    camera = station.camera
    h, w = camera.shape
    s = settings.supersampling
    light = RasterLight(station.raster_definition, defocus=settings.projector_defocus)
    t0 = time.perf_counter()
    tracer = Tracer(scene, smooth_normals=settings.smooth_normals)
    timings["scene_setup"] = time.perf_counter() - t0
    # the camera PSF reaches beyond the sensor's edge: render a margin of real scene around
    # the image instead of mirroring it (a mirrored slanted line biases edge centroids)
    m = int(np.ceil(4.0 * settings.camera_blur)) + 1 if settings.camera_blur > 0 else 0
    he, we = h + 2 * m, w + 2 * m
    origin = camera.centre.astype(np.float32)[None, :]

    # pass 1, pixel centres (of the extended image): exact shadows for the ground truth and
    # shadow hints that spare most sub-sample shadow rays
    t0 = time.perf_counter()
    centre_dirs = _pixel_directions(camera, m)
    t1 = time.perf_counter()
    centre_hits = tracer.cast(np.broadcast_to(origin, centre_dirs.shape), centre_dirs)
    t2 = time.perf_counter()
    centre_shaded, tt = _shade(
        scene,
        tracer,
        station,
        light,
        settings,
        origin,
        centre_dirs.astype(np.float32),
        centre_hits,
        shadow_hint=None,
    )
    hints = _shadow_hints(centre_hits.hit.reshape(he, we), _reshape(centre_shaded, he, we))
    timings["rays"] += t1 - t0
    timings["ray_casting"] += t2 - t1
    timings["shading"] += tt["shading"]
    timings["shadow_rays"] += tt.get("shadow_rays", 0.0)

    # pass 2, all sub-samples, in bands of rows
    fine: np.ndarray = np.empty((he * s, we * s), dtype=np.float32)
    # with odd s the middle sub-sample column of every pixel lies on x = c exactly: the
    # exact line rows are bracketed on those samples
    c = s // 2 if s % 2 == 1 else None
    col_v = np.full((he * s, w), np.nan, dtype=np.float32)
    col_obj = np.full((he * s, w), -1, dtype=np.int16)
    col_tri = np.full((he * s, w), -1, dtype=np.int64)

    def band(row0: int, row1: int) -> dict[str, float]:
        n = row1 - row0
        t0 = time.perf_counter()
        rays = _band_rays(camera, s, row0, row1, m)
        band_hint = np.repeat(np.repeat(hints[row0:row1], s, axis=0), s, axis=1).ravel()
        t1 = time.perf_counter()
        hits = tracer.cast_rays(rays)
        t2 = time.perf_counter()
        shaded, tt = _shade(
            scene,
            tracer,
            station,
            light,
            settings,
            rays[:1, :3],
            rays[:, 3:],
            hits,
            shadow_hint=band_hint,
        )
        # bands write disjoint rows: safe from worker threads
        fine[row0 * s : row1 * s] = shaded.electrons.reshape(n * s, we * s)
        if c is not None:
            cols = slice(m * s + c, (m + w) * s, s)
            col_v[row0 * s : row1 * s] = shaded.v.reshape(n * s, we * s)[:, cols]
            col_obj[row0 * s : row1 * s] = hits.object_index.reshape(n * s, we * s)[:, cols]
            col_tri[row0 * s : row1 * s] = hits.triangle.reshape(n * s, we * s)[:, cols]
        return {"rays": t1 - t0, "ray_casting": t2 - t1, **tt}

    workers = settings.threads or os.cpu_count() or 1
    # at most _MAX_BAND_RAYS per band (memory); two bands per worker balance the load
    n_bands = max(-(-he * we * s * s // _MAX_BAND_RAYS), 2 * workers if workers > 1 else 1)
    bounds = np.linspace(0, he, n_bands + 1).round().astype(int)
    jobs = [(int(a), int(b)) for a, b in itertools.pairwise(bounds) if b > a]
    t0 = time.perf_counter()
    if workers > 1 and len(jobs) > 1:
        # numpy and Embree release the GIL: bands shade in parallel
        with ThreadPoolExecutor(max_workers=workers) as pool:
            parts = list(pool.map(lambda job: band(*job), jobs))
    else:
        parts = [band(*job) for job in jobs]
    timings["subsamples"] = time.perf_counter() - t0
    for part in parts:
        for key, value in part.items():
            timings[key] = timings.get(key, 0.0) + value

    t0 = time.perf_counter()
    if settings.camera_blur > 0:
        sigma = settings.camera_blur * s
        radius = int(np.ceil(4.0 * sigma))
        fine = cv2.GaussianBlur(
            fine,
            (2 * radius + 1, 2 * radius + 1),
            sigmaX=sigma,
            sigmaY=sigma,
            borderType=cv2.BORDER_REFLECT,
        )
    fine = fine[m * s : (m + h) * s, m * s : (m + w) * s]
    electrons = fine.reshape(h, s, w, s).mean(axis=(1, 3), dtype=np.float32)
    image = expose(
        electrons,
        rng=np.random.default_rng(seed),
        gain=settings.gain,
        offset=settings.offset,
        read_noise=settings.read_noise,
        full_well=settings.full_well,
        bit_depth=settings.bit_depth,
        shot_noise=settings.shot_noise,
        noise=settings.noise,
    )
    timings["blur_noise"] = time.perf_counter() - t0

    t0 = time.perf_counter()
    inner = (np.arange(he)[:, None] >= m) & (np.arange(he)[:, None] < m + h)
    inner = (inner & (np.arange(we)[None, :] >= m) & (np.arange(we)[None, :] < m + w)).ravel()
    idx = np.flatnonzero(inner)
    truth = _pixel_truth(
        tracer,
        station,
        light,
        centre_dirs[idx],
        _take_hits(centre_hits, idx),
        centre_shaded.lit[idx],
    )
    timings["pixel_truth"] = time.perf_counter() - t0

    projector_on = settings.projector_electrons > 0
    if not projector_on:
        # no raster light at all (a control-point frame): nothing is lit, no line is seen
        truth["line_number"] = np.full_like(truth["line_number"], -1)
        truth["shadow"] = truth["visible"].copy()

    t0 = time.perf_counter()
    if settings.line_rows and projector_on:
        if c is not None:
            sample_rows = np.arange(he * s) / s + (0.5 / s - 0.5) - m
            v_cols, obj_cols, tri_cols = col_v, col_obj, col_tri
        else:
            sample_rows = np.arange(he, dtype=np.float64) - m
            v_cols = centre_shaded.v.reshape(he, we)[:, m : m + w]
            obj_cols = centre_hits.object_index.reshape(he, we)[:, m : m + w]
            tri_cols = centre_hits.triangle.reshape(he, we)[:, m : m + w]
        line_rows = find_line_rows(
            tracer,
            station,
            sample_rows=sample_rows,
            v=v_cols,
            object_index=obj_cols,
            triangle=tri_cols,
            light=light,
            shadow_epsilon=settings.shadow_epsilon,
        )
    else:
        line_rows = LineRows.empty()
    timings["line_rows"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_start
    return Rendering(
        image=image,
        electrons=electrons,
        points=truth["points"],
        normals=truth["normals"],
        object_index=truth["object_index"],
        object_names=list(tracer.object_names),
        line_number=truth["line_number"],
        diapositive=truth["diapositive"],
        visible=truth["visible"],
        shadow=truth["shadow"],
        line_rows=line_rows,
        settings=settings,
        seed=seed,
        timings=timings,
    )


def _reshape(shaded: _Shaded, he: int, we: int) -> _Shaded:
    return _Shaded(
        electrons=shaded.electrons.reshape(he, we),
        v=shaded.v.reshape(he, we),
        lit=shaded.lit.reshape(he, we),
        candidate=shaded.candidate.reshape(he, we),
    )
