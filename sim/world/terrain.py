"""Procedural planetary terrain: heightfield, craters, slope, ridges, rocks, lander, albedo.

Everything is drawn from one ``numpy.random.Generator`` (the scenario's ``terrain``
stream of :class:`sim.seeding.RandomStreams`), split into independent child streams per part,
so moving a robot start (``keep_clear``) never changes the heightfield or the texture.

Geometry (world frame, origin at the terrain centre, z up):

- ``Terrain.heights[i, j]`` is the height at ``x = -size/2 + j*res``,
  ``y = -size/2 + i*res``; MuJoCo's hfield stores its rows the same way (row 0 at -y).
- Between grid points the surface is MuJoCo's own triangulation: each cell is split along
  its diagonal from ``(i, j)`` to ``(i+1, j+1)`` (as in ``mj_ray`` and the hfield
  collider), so :meth:`Terrain.height_at` agrees with physics and ray casts.
- ``Terrain.albedo[i, j]`` uses the same row convention (row 0 at -y, column 0 at -x);
  the texture uploaded to MuJoCo is flipped to match.

Parts: fractal roughness (multi-octave periodic value noise with cubic B-spline
interpolation); simple craters (parabolic bowl inside the rim, exponentially decaying
rim outside it); a global planar slope; straight ridges/trenches with a cos^2 profile;
rocks as convex meshes with diameters from a truncated power law N(>D) ~ D^-k (sampled
by inverse CDF), half buried; a lander on a flattened pad with an AprilTag 36h11 on a
side face (thesis 6.2: landers as static landmarks). The regolith albedo is multi-octave
noise whose octave weights grow slightly with frequency, so that texture survives at
every scale a 320x240 camera sees between 2 and 6 m (SGBM and VO need texture to match).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import cv2
import numpy as np
import scipy.sparse
from dm_control import mjcf
from scipy.spatial import ConvexHull, cKDTree

from sim.scenario import ROCK_MAX_REACH_FACTOR, LightRealism, TerrainConfig
from sim.world.lander import (
    LANDER_DECK_HALF,
    LANDER_DECK_Z,
    LANDER_FOOT_RADIUS,
    LANDER_FOOT_XY,
    LANDER_LEG_RADIUS,
    LANDER_PAD_BLEND_M,
    LANDER_PAD_RADIUS,
)
from sim.world.markers import (
    MARKER_THICKNESS_M,
    QUIET_CELLS,
    TAG_CELLS,
    MarkerSpec,
    add_marker,
)
from sim.world.terrain_tiles import MAX_TILED_CELLS, add_terrain_tiles
from slam.lie import yaw_quat

HFIELD_BASE_M = 1.0  # depth of MuJoCo's hfield box below the lowest terrain point
TAG_PANEL_MARGIN_M = 0.05  # backing plate around the tag's quiet zone ...
TAG_PANEL_HALF_THICKNESS_M = 0.01  # ... on the deck's +x face

ROCK_PLACEMENT_TRIES = 512  # candidate positions per rock (and crater) before giving up
ROCK_CANDIDATES = 32  # rock candidates drawn at a time
CRATER_RIM_DECAY = 0.35  # e-folding width of the outer rim, in crater radii
CRATER_REACH = 3.0  # the outer rim ends (smoothly, at zero) at this many radii


class TerrainError(ValueError):
    """A terrain that cannot be built as configured (e.g. no room for the rocks)."""


@dataclasses.dataclass(frozen=True)
class _Preset:
    """Look and feel of a site: albedo, colours, sun and sky."""

    albedo_mean: float  # mean of the grey albedo texture, 0..1
    tint: tuple[float, float, float]  # material colour multiplying the grey texture
    rock_rgb: tuple[float, float, float]
    sky_zenith: tuple[float, float, float]
    sky_horizon: tuple[float, float, float]
    sun_elevation_deg: float
    sun_azimuth_deg: float  # direction the sun is in, counter-clockwise from +x
    sun_diffuse: float
    ambient: float
    roughness_scale: float  # multiplies TerrainConfig.roughness_m


PRESETS: dict[str, _Preset] = {
    "moon": _Preset(0.55, (1.0, 1.0, 1.0), (0.62, 0.62, 0.62), (0.0, 0.0, 0.0), (0.02, 0.02, 0.03),
                    sun_elevation_deg=20.0, sun_azimuth_deg=135.0, sun_diffuse=1.2, ambient=0.12,
                    roughness_scale=1.0),
    "mars": _Preset(0.55, (1.0, 0.68, 0.46), (0.55, 0.42, 0.34), (0.45, 0.36, 0.30), (0.85, 0.66, 0.48),
                    sun_elevation_deg=40.0, sun_azimuth_deg=200.0, sun_diffuse=0.9, ambient=0.15,
                    roughness_scale=1.0),
    "etna": _Preset(0.42, (0.62, 0.58, 0.56), (0.30, 0.28, 0.27), (0.35, 0.55, 0.85), (0.75, 0.82, 0.90),
                    sun_elevation_deg=50.0, sun_azimuth_deg=160.0, sun_diffuse=1.0, ambient=0.15,
                    roughness_scale=2.5),
}


@dataclasses.dataclass(frozen=True, eq=False)
class Rock:
    center: np.ndarray  # (3,) world position of the rock's centre
    radii: np.ndarray  # (3,) semi-axes (x, y, z) in the rock frame
    yaw: float  # rock frame rotation about world z
    vertices: np.ndarray  # (n, 3) convex hull vertices in the rock frame


@dataclasses.dataclass(frozen=True)
class Crater:
    xy: tuple[float, float]  # centre
    radius: float  # rim crest radius
    depth: float  # centre below the surrounding surface
    rim_height: float  # rim crest above it


@dataclasses.dataclass(frozen=True)
class LanderPlacement:
    xy: tuple[float, float]
    yaw: float
    base_z: float  # height of the flattened pad (the lander body origin)
    marker: MarkerSpec  # the AprilTag, pos/quat relative to the lander body


@dataclasses.dataclass(eq=False)
class Terrain:
    heights: np.ndarray  # (n, n) world z; row i <-> y = -size/2 + i*res, column j <-> x
    size_m: float
    resolution_m: float  # size_m / (n - 1)
    rocks: list[Rock]
    lander: LanderPlacement | None
    albedo: np.ndarray  # (H, W) uint8 albedo tile, rows along y (row 0 at -y), columns along x
    preset: str
    albedo_repeat: int = 1  # the tile repeats this often along x and y to span the terrain
    craters: list[Crater] = dataclasses.field(default_factory=list)
    _rock_planes: list[np.ndarray] = dataclasses.field(init=False, repr=False)

    def __post_init__(self) -> None:
        # Half-space form of each rock hull, n . p + d <= 0 inside (rock frame).
        self._rock_planes = [ConvexHull(r.vertices).equations for r in self.rocks]

    def _cell(self, x, y):
        half = self.size_m / 2
        n = self.heights.shape[0]
        fx = (np.clip(x, -half, half) + half) / self.resolution_m
        fy = (np.clip(y, -half, half) + half) / self.resolution_m
        j = np.clip(np.floor(fx).astype(int), 0, n - 2)
        i = np.clip(np.floor(fy).astype(int), 0, n - 2)
        h = self.heights
        return fx - j, fy - i, h[i, j], h[i, j + 1], h[i + 1, j], h[i + 1, j + 1]

    def height_at(self, x, y):
        """Surface height at world (x, y), vectorised; points off the terrain are clamped
        onto its edge. Exact on MuJoCo's triangulated hfield surface."""
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        u, v, h00, h01, h10, h11 = self._cell(x, y)
        lower = u >= v  # triangle (i,j), (i,j+1), (i+1,j+1)
        z = np.where(lower, h00 + u * (h01 - h00) + v * (h11 - h01), h00 + v * (h10 - h00) + u * (h11 - h10))
        return z[()]

    def normal_at(self, x, y) -> np.ndarray:
        """Unit upward normals (..., 3) of the triangulated surface at world (x, y)."""
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        u, v, h00, h01, h10, h11 = self._cell(x, y)
        lower = u >= v
        dzdx = np.where(lower, h01 - h00, h11 - h10) / self.resolution_m
        dzdy = np.where(lower, h11 - h01, h10 - h00) / self.resolution_m
        n = np.stack([-dzdx, -dzdy, np.ones_like(dzdx)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def surface_height_at(self, x, y):
        """Height of the terrain or of the top of a rock, whichever is higher."""
        x, y = np.broadcast_arrays(np.asarray(x, float), np.asarray(y, float))
        z = np.array(self.height_at(x, y), float, ndmin=1).ravel()
        if self.rocks:
            points = np.stack([x.ravel(), y.ravel()], axis=1)
            tree = cKDTree(points)
            reach = [float(np.linalg.norm(r.vertices[:, :2], axis=1).max()) for r in self.rocks]
            nearby = tree.query_ball_point([r.center[:2] for r in self.rocks], reach)
            for rock, planes, idx in zip(self.rocks, self._rock_planes, nearby):
                if not idx:
                    continue
                idx = np.asarray(idx)
                c, s = math.cos(rock.yaw), math.sin(rock.yaw)
                dx, dy = points[idx, 0] - rock.center[0], points[idx, 1] - rock.center[1]
                lx, ly = c * dx + s * dy, -s * dx + c * dy
                # For each upward facing plane the hull's top is z = -(nx x + ny y + d) / nz.
                offset = -(np.outer(lx, planes[:, 0]) + np.outer(ly, planes[:, 1]) + planes[:, 3])
                with np.errstate(divide="ignore"):
                    bounds = offset / planes[:, 2]
                up, down = planes[:, 2] > 1e-9, planes[:, 2] < -1e-9
                top = bounds[:, up].min(axis=1)
                bottom = bounds[:, down].max(axis=1) if down.any() else np.full_like(top, -np.inf)
                inside = bottom <= top
                z[idx[inside]] = np.maximum(z[idx[inside]], rock.center[2] + top[inside])
        return z.reshape(x.shape)[()]


# --------------------------------------------------------------------------- noise


def _bspline_matrix(n_out: int, cells: int, samples_per_period: float) -> scipy.sparse.csr_matrix:
    """Sparse (n_out, cells) weights of periodic cubic B-spline interpolation of a lattice
    with ``cells`` values per period, sampled ``samples_per_period`` times per period."""
    p = np.arange(n_out) * cells / samples_per_period
    i = np.floor(p).astype(int)
    t = p - i
    w = np.stack([(1 - t) ** 3, 3 * t**3 - 6 * t**2 + 4, -3 * t**3 + 3 * t**2 + 3 * t + 1, t**3], axis=1) / 6
    cols = (i[:, None] + np.arange(-1, 3)) % cells
    rows = np.repeat(np.arange(n_out), 4)
    return scipy.sparse.csr_matrix((w.ravel(), (rows, cols.ravel())), shape=(n_out, cells))


def _fractal_noise(rng: np.random.Generator, n_out: int, samples_per_period: float,
                   cells: Sequence[int], weights: Sequence[float]) -> np.ndarray:
    """Zero-mean, unit-std sum of periodic value-noise octaves on an (n_out, n_out) grid."""
    total = np.zeros((n_out, n_out))
    for c, w in zip(cells, weights):
        m = _bspline_matrix(n_out, c, samples_per_period)
        lattice = rng.standard_normal((c, c))
        total += w * (m @ (m @ lattice).T)  # = (M L M^T)^T, as random as M L M^T: skip the transpose
    total -= total.mean()
    std = total.std()
    return total / std if std > 0 else total


def _roughness(rng: np.random.Generator, cfg: TerrainConfig, n: int, amplitude: float) -> np.ndarray:
    """fBm heights with RMS ``amplitude``: octaves from ``roughness_wavelength_m`` down to
    two grid cells, amplitude proportional to wavelength^0.8 (a Hurst exponent of 0.8)."""
    wavelengths = []
    wl = cfg.roughness_wavelength_m
    while wl >= 2 * cfg.size_m / (n - 1) or not wavelengths:
        wavelengths.append(wl)
        wl /= 2
    cells = [max(2, round(cfg.size_m / wl)) for wl in wavelengths]
    weights = [(wl / wavelengths[0]) ** 0.8 for wl in wavelengths]
    return amplitude * _fractal_noise(rng, n, n - 1, cells, weights)


def _albedo(rng: np.random.Generator, size_px: int, mean: float, contrast: float) -> np.ndarray:
    """Tileable uint8 regolith albedo: octaves from 4 cells per tile down to one texel,
    weights growing with frequency (strong high frequencies), std = ``contrast`` x mean."""
    cells, c = [], size_px
    while c >= 4:
        cells.append(c)
        c //= 2
    weights = [(c / size_px) ** 0.3 for c in cells]
    z = _fractal_noise(rng, size_px, size_px, cells, weights)
    return np.clip(np.rint(255 * mean * (1 + contrast * z)), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------- features


def _outside_discs(xy: np.ndarray, discs: Sequence[tuple[tuple[float, float], float]], margin) -> np.ndarray:
    """Mask of points (k, 2) whose distance to every disc centre exceeds radius + margin."""
    ok = np.ones(len(xy), bool)
    for (cx, cy), radius in discs:
        ok &= np.hypot(xy[:, 0] - cx, xy[:, 1] - cy) > radius + margin
    return ok


def _add_craters(h: np.ndarray, grid: np.ndarray, cfg: TerrainConfig, rng: np.random.Generator,
                 discs: Sequence[tuple[tuple[float, float], float]]) -> list[Crater]:
    """Carve ``cfg.craters.count`` craters (no centre inside a keep-clear disc).

    Profile in r/R (a simple fresh-crater model): inside, a parabolic bowl from
    -depth at the centre to +rim at r = R; outside, a rim decaying exponentially with
    e-folding width CRATER_RIM_DECAY*R, shifted to end at zero at CRATER_REACH*R.
    """
    c = cfg.craters
    half = cfg.size_m / 2
    craters = []
    for _ in range(c.count):
        cand = rng.uniform(-half, half, (ROCK_PLACEMENT_TRIES, 2))
        ok = np.flatnonzero(_outside_discs(cand, discs, 0.0))
        if ok.size == 0:
            raise TerrainError(f"no room for crater {len(craters) + 1} of {c.count} outside the keep-clear discs")
        center, radius = cand[ok[0]], float(rng.uniform(*c.radius_m))
        depth, rim = c.depth_ratio * radius, c.rim_height_ratio * radius
        reach = CRATER_REACH * radius
        j0, j1 = np.searchsorted(grid, [center[0] - reach, center[0] + reach])
        i0, i1 = np.searchsorted(grid, [center[1] - reach, center[1] + reach])
        r = np.hypot(grid[None, j0:j1] - center[0], grid[i0:i1, None] - center[1]) / radius
        cut = math.exp(-(CRATER_REACH - 1) / CRATER_RIM_DECAY)
        outer = rim * (np.exp(-(np.minimum(r, CRATER_REACH) - 1) / CRATER_RIM_DECAY) - cut) / (1 - cut)
        h[i0:i1, j0:j1] += np.where(r <= 1, -depth + (depth + rim) * r**2, outer)
        craters.append(Crater(xy=(float(center[0]), float(center[1])), radius=radius, depth=depth, rim_height=rim))
    return craters


def _segment_distance(px: np.ndarray, py: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    ab = b - a
    t = ((px - a[0]) * ab[0] + (py - a[1]) * ab[1]) / max(float(ab @ ab), 1e-12)
    t = np.clip(t, 0, 1)
    return np.hypot(px - a[0] - t * ab[0], py - a[1] - t * ab[1])


def _flatten_pad(h: np.ndarray, X: np.ndarray, Y: np.ndarray, xy: tuple[float, float]) -> float:
    """Flatten the terrain under the lander to the mean height of its pad; returns it."""
    r = np.hypot(X - xy[0], Y - xy[1])
    pad = r <= LANDER_PAD_RADIUS
    base = float(h[pad].mean())
    s = np.clip((r - LANDER_PAD_RADIUS) / LANDER_PAD_BLEND_M, 0, 1)
    w = s * s * (3 - 2 * s)  # smoothstep
    h[:] = base * (1 - w) + h * w
    return base


def _icosphere() -> np.ndarray:
    """Unit vectors of an icosahedron subdivided once (42 directions)."""
    g = (1 + 5**0.5) / 2
    v = np.array([[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g],
                  [0, -1, -g], [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]], float)
    edges = {tuple(sorted(e)) for f in ConvexHull(v).simplices for e in ((f[0], f[1]), (f[1], f[2]), (f[0], f[2]))}
    v = np.vstack([v, [(v[a] + v[b]) / 2 for a, b in sorted(edges)]])
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _power_law_diameters(rng: np.random.Generator, n: int, d_min: float, d_max: float, k: float) -> np.ndarray:
    """Inverse-CDF samples of N(>D) ~ D^-k truncated to [d_min, d_max]."""
    u = rng.uniform(size=n)
    a, b = d_min**-k, d_max**-k
    return (a - u * (a - b)) ** (-1 / k)


def _place_rocks(height_at, cfg: TerrainConfig, rng: np.random.Generator,
                 discs: Sequence[tuple[tuple[float, float], float]]) -> list[Rock]:
    """The scenario's ``placed`` rocks where it puts them, then the random ones, largest
    first: whole rock outside every keep-clear disc and inside the terrain, no two
    overlapping (bounding circles). Each is a perturbed ellipsoid
    (icosphere directions, radial jitter +-15 %, then its convex hull), sunk to its
    centre at the local terrain height, and further where the ground falls away so
    that its underside is below the terrain everywhere under it."""
    rc = cfg.rocks
    diameters = np.sort(_power_law_diameters(rng, rc.count, *rc.diameter_m, rc.power_law_exponent))[::-1]
    dirs = _icosphere()
    half = cfg.size_m / 2
    k = len(rc.placed)
    placed_xy = np.zeros((k + rc.count, 2))
    placed_r = np.zeros(k + rc.count)

    def shape(d: float) -> tuple[np.ndarray, np.ndarray, float, float]:
        radii = d / 2 * np.array([1.0, rng.uniform(0.6, 1.0), rng.uniform(0.45, 0.8)])
        points = dirs * radii * rng.uniform(0.85, ROCK_MAX_REACH_FACTOR, (len(dirs), 1))
        vertices = points[ConvexHull(points).vertices]
        return radii, vertices, float(np.linalg.norm(vertices[:, :2], axis=1).max()), float(rng.uniform(0, 2 * math.pi))

    def rock(xy: np.ndarray, radii: np.ndarray, vertices: np.ndarray, yaw: float) -> Rock:
        c, s = math.cos(yaw), math.sin(yaw)
        foot_x = xy[0] + c * vertices[:, 0] - s * vertices[:, 1]
        foot_y = xy[1] + s * vertices[:, 0] + c * vertices[:, 1]
        ground_min = float(np.min(height_at(foot_x, foot_y)))
        z = min(float(height_at(*xy)), ground_min - 0.01 - float(vertices[:, 2].min()))
        return Rock(center=np.array([xy[0], xy[1], z]), radii=radii, yaw=yaw, vertices=vertices)

    rocks = []
    for n, spec in enumerate(rc.placed):  # where the scenario says; the scenario keeps them off starts and the lander
        radii, vertices, reach, yaw = shape(spec.diameter_m)
        xy = np.asarray(spec.xy, float)
        if np.any(np.abs(xy) > half - reach - 0.1):
            raise TerrainError(f"terrain.rocks.placed.{n}: a {spec.diameter_m:g} m rock at {list(spec.xy)} reaches off the {cfg.size_m:g} m terrain")
        rocks.append(rock(xy, radii, vertices, yaw))
        placed_xy[n], placed_r[n] = xy, reach
    for n, d in enumerate(diameters, start=k):
        radii, vertices, reach, yaw = shape(d)
        limit = half - reach - 0.1
        if limit <= 0:
            raise TerrainError(f"rock diameter {d:.2f} m does not fit on a {cfg.size_m:g} m terrain")
        for _ in range(ROCK_PLACEMENT_TRIES // ROCK_CANDIDATES):
            cand = rng.uniform(-limit, limit, (ROCK_CANDIDATES, 2))
            d2 = (cand[:, :1] - placed_xy[:n, 0]) ** 2 + (cand[:, 1:] - placed_xy[:n, 1]) ** 2
            free = (d2 > (placed_r[:n] + reach) ** 2).all(axis=1)
            good = np.flatnonzero(_outside_discs(cand, discs, reach) & free)
            if good.size:
                break
        else:
            raise TerrainError(
                f"placed only {n - k} of {rc.count} rocks: no room left outside the keep-clear discs "
                f"(clearance_m={rc.clearance_m:g}); lower terrain.rocks.count or the clearance"
            )
        xy = cand[good[0]]
        rocks.append(rock(xy, radii, vertices, yaw))
        placed_xy[n], placed_r[n] = xy, reach
    return rocks


def _tag_placement(cfg_lander) -> MarkerSpec:
    """The lander's tag on the deck's +x face, upright, facing outward, its centre at the
    deck height (higher for big tags, so that it clears the ground)."""
    tag_half = cfg_lander.tag_size_m * (TAG_CELLS + 2 * QUIET_CELLS) / TAG_CELLS / 2
    z = max(LANDER_DECK_Z, tag_half + TAG_PANEL_MARGIN_M + 0.1)
    x = LANDER_DECK_HALF[0] + 2 * TAG_PANEL_HALF_THICKNESS_M + MARKER_THICKNESS_M / 2
    # geom z -> body +x (outward), geom y -> body +z (the tag's up), geom x -> body +y
    quat = (0.5, 0.5, 0.5, 0.5)
    return MarkerSpec(name="lander_tag", tag_id=cfg_lander.tag_id, size_m=cfg_lander.tag_size_m,
                      pos=(x, 0.0, z), quat=quat)


# --------------------------------------------------------------------------- public


def generate_terrain(cfg: TerrainConfig, rng: np.random.Generator,
                     keep_clear: Sequence[tuple[tuple[float, float], float]] = (),
                     albedo_contrast_scale: float = 1.0) -> Terrain:
    """Build the terrain of ``cfg`` from ``rng`` (same generator state, same terrain).

    ``albedo_contrast_scale`` (a scenario's ``realism.light``) scales the albedo
    texture's contrast ``cfg.texture.contrast``; it changes no height, rock or crater.

    ``keep_clear`` lists ``(xy, radius)`` discs (robot starts, waypoints) where no rock
    and no crater centre may lie; the lander's footprint plus ``cfg.rocks.clearance_m``
    is added to them. Raises :class:`TerrainError` if the rocks or craters do not fit.
    """
    preset = PRESETS[cfg.preset]
    rng_rough, rng_craters, rng_rocks, rng_albedo = rng.spawn(4)
    n = cfg.grid_points()
    grid = np.linspace(-cfg.size_m / 2, cfg.size_m / 2, n)
    X, Y = np.meshgrid(grid, grid)

    h = _roughness(rng_rough, cfg, n, cfg.roughness_m * preset.roughness_scale)
    slope = math.tan(math.radians(cfg.slope.gradient_deg))
    direction = math.radians(cfg.slope.direction_deg)
    h += slope * (X * math.cos(direction) + Y * math.sin(direction))
    discs = [(tuple(map(float, xy)), float(r)) for xy, r in [*keep_clear, *cfg.lander_keep_clear()]]
    craters = _add_craters(h, grid, cfg, rng_craters, discs)
    for ridge in cfg.ridges:
        dist = _segment_distance(X, Y, np.array(ridge.start_xy, float), np.array(ridge.end_xy, float))
        h += ridge.height_m * np.where(dist < ridge.width_m / 2, np.cos(math.pi * dist / ridge.width_m) ** 2, 0.0)

    lander = None
    if cfg.lander is not None:
        base = _flatten_pad(h, X, Y, cfg.lander.xy)
        lander = LanderPlacement(xy=tuple(cfg.lander.xy), yaw=math.radians(cfg.lander.yaw_deg), base_z=base,
                                 marker=_tag_placement(cfg.lander))

    tile_m = cfg.texture.size_px * cfg.texture.texel_m
    ground = Terrain(heights=h, size_m=float(cfg.size_m), resolution_m=float(cfg.size_m) / (n - 1), rocks=[],
                     lander=lander, albedo=_albedo(rng_albedo, cfg.texture.size_px, preset.albedo_mean,
                                                   cfg.texture.contrast * albedo_contrast_scale),
                     preset=cfg.preset, albedo_repeat=max(1, math.ceil(cfg.size_m / tile_m - 1e-9)), craters=craters)
    return dataclasses.replace(ground, rocks=_place_rocks(ground.height_at, cfg, rng_rocks, discs))


def _rock_mesh(rock: Rock, albedo_tile_m: float, offset: np.ndarray) -> dict:
    """Mesh attributes: hull faces (outward) and texture coordinates projected along
    (-1, 1, 1), so the regolith texture covers every face at its ground scale."""
    hull = ConvexHull(rock.vertices)
    faces = hull.simplices.copy()
    v = rock.vertices
    normal = np.cross(v[faces[:, 1]] - v[faces[:, 0]], v[faces[:, 2]] - v[faces[:, 0]])
    flip = np.einsum("ij,ij->i", normal, hull.equations[:, :3]) < 0
    faces[flip] = faces[flip][:, ::-1]
    uv = np.stack([v[:, 0] + v[:, 2], v[:, 1] - v[:, 2]], axis=1) / albedo_tile_m + offset
    return {"vertex": v.ravel(), "face": faces.ravel(), "texcoord": uv.ravel()}


#: Shadow map size (texels) when the sun casts shadows: 2048 resolves a rock's shadow edge
#: to about 2 cm at 1 m distance over a 40 m terrain (MuJoCo's default is 4096).
SHADOW_MAP_SIZE = 2048


def add_terrain(root: mjcf.RootElement, terrain: Terrain, light: LightRealism | None = None) -> None:
    """Add terrain, rocks, lander, sun, sky and fast render settings to ``root``; without
    the sun's shadows, and up to ``MAX_TILED_CELLS`` grid cells per side, also the
    terrain's tiles for the cameras (:func:`sim.world.terrain_tiles.add_terrain_tiles`).

    ``light`` (a scenario's ``realism.light``): the sun's direction (default: the
    preset's), whether it casts shadows, and whether a camera-fixed headlight fills in;
    None: the preset's sun without shadows, with the headlight."""
    light = light or LightRealism(shadows=False, headlight=True)
    preset = PRESETS[terrain.preset]
    h = terrain.heights
    n = h.shape[0]
    h_min, h_max = float(h.min()), float(h.max())
    elevation = max(h_max - h_min, 1e-6)
    data = ((h - h_min) / elevation).astype(np.float32)
    blob = np.array([n, n], np.int32).tobytes() + data.tobytes()
    half = terrain.size_m / 2
    root.asset.add("hfield", name="terrain", size=[half, half, elevation, HFIELD_BASE_M],
                   file=mjcf.Asset(blob, ".bin"))

    ok, png = cv2.imencode(".png", np.flipud(terrain.albedo), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise RuntimeError("PNG encoding of the terrain albedo failed")
    root.asset.add("texture", name="regolith", type="2d", file=mjcf.Asset(png.tobytes(), ".png"))
    rep = terrain.albedo_repeat
    root.asset.add("material", name="regolith", texture="regolith", texrepeat=[rep, rep],
                   rgba=[*preset.tint, 1], specular=0, shininess=0, reflectance=0)
    root.worldbody.add("geom", name="terrain", type="hfield", hfield="terrain", pos=[0, 0, h_min],
                       material="regolith")
    if not light.shadows and n - 1 <= MAX_TILED_CELLS:  # else the cameras draw the hfield (sim/world/terrain_tiles.py)
        add_terrain_tiles(root, h, terrain.size_m, rep)

    tile_m = terrain.size_m / rep
    root.asset.add("material", name="rock", texture="regolith", rgba=[*preset.rock_rgb, 1],
                   specular=0, shininess=0, reflectance=0)
    for i, rock in enumerate(terrain.rocks):
        root.asset.add("mesh", name=f"rock_{i}", **_rock_mesh(rock, tile_m, rock.center[:2] / tile_m))
        root.worldbody.add("geom", name=f"rock_{i}", type="mesh", mesh=f"rock_{i}", material="rock",
                           pos=rock.center, quat=yaw_quat(rock.yaw).tolist())

    if terrain.lander is not None:
        _add_lander(root, terrain.lander)

    el = math.radians(light.sun_elevation_deg if light.sun_elevation_deg is not None else preset.sun_elevation_deg)
    az = math.radians(light.sun_azimuth_deg if light.sun_azimuth_deg is not None else preset.sun_azimuth_deg)
    to_sun = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    root.worldbody.add("light", name="sun", type="directional", castshadow=bool(light.shadows), pos=100 * to_sun,
                       dir=-to_sun, diffuse=[preset.sun_diffuse] * 3, specular=[0, 0, 0],
                       ambient=[preset.ambient] * 3)
    root.visual.headlight.ambient = [0.05 if light.headlight else 0.0] * 3
    root.visual.headlight.diffuse = [0.25 if light.headlight else 0.0] * 3
    root.visual.headlight.specular = [0, 0, 0]
    root.asset.add("texture", name="sky", type="skybox", builtin="gradient", rgb1=preset.sky_zenith,
                   rgb2=preset.sky_horizon, width=64, height=64)
    root.visual.quality.shadowsize = SHADOW_MAP_SIZE if light.shadows else 0
    root.visual.quality.offsamples = 0


def _add_lander(root: mjcf.RootElement, lander: LanderPlacement) -> None:
    """Static lander body: deck box on four splayed legs with footpads, the tag on a
    backing plate on the deck's +x face."""
    body = root.worldbody.add("body", name="lander", pos=[*lander.xy, lander.base_z], quat=yaw_quat(lander.yaw).tolist())
    gold, grey = [0.75, 0.6, 0.25, 1], [0.55, 0.55, 0.55, 1]
    dx, dy, dz = LANDER_DECK_HALF
    body.add("geom", name="lander_deck", type="box", size=LANDER_DECK_HALF, pos=[0, 0, LANDER_DECK_Z], rgba=gold)
    foot_h = 0.03
    for k, (sx, sy) in enumerate([(1, 1), (-1, 1), (-1, -1), (1, -1)]):
        top = [sx * (dx - 0.1), sy * (dy - 0.1), LANDER_DECK_Z - dz]
        foot = [sx * LANDER_FOOT_XY, sy * LANDER_FOOT_XY, 2 * foot_h]
        body.add("geom", name=f"lander_leg_{k}", type="capsule", fromto=[*top, *foot], size=[LANDER_LEG_RADIUS],
                 rgba=grey)
        body.add("geom", name=f"lander_foot_{k}", type="cylinder", size=[LANDER_FOOT_RADIUS, foot_h / 2],
                 pos=[foot[0], foot[1], foot_h / 2], rgba=grey)
    spec = lander.marker
    tag_half = spec.size_m * (TAG_CELLS + 2 * QUIET_CELLS) / TAG_CELLS / 2
    panel_half = tag_half + TAG_PANEL_MARGIN_M
    body.add("geom", name="lander_tag_panel", type="box", size=[TAG_PANEL_HALF_THICKNESS_M, panel_half, panel_half],
             pos=[dx + TAG_PANEL_HALF_THICKNESS_M, 0, spec.pos[2]], rgba=[0.9, 0.9, 0.9, 1])
    add_marker(body, spec)
