"""The terrain as the cameras draw it: tiles with levels of detail, chosen per camera.

MuJoCo draws an hfield as one display list, so every camera processed every triangle of
the whole terrain, and that set the cost of an image (a 30 m terrain at 0.1 m has 180,000
triangles; on llvmpipe about 55 of the 75 ms of a 320x240 stereo pair). The physics keeps
the one hfield (contacts, ``mj_ray``, :meth:`sim.world.terrain.Terrain.height_at`), and so
does any plain ``mujoco.Renderer``; the robots' cameras
(:class:`sim.world.sensors.StereoRenderer`) draw instead square tiles of the same surface,
mesh assets at several levels of detail (every ``stride``-th grid point): in each render's
scene :class:`TerrainTiles` replaces the hfield with

- the tiles in the camera's view frustum, widened by the stereo baseline;
- each at the coarsest level whose largest height deviation from the full grid projects to
  at most :data:`SCREEN_ERROR_PX` at the tile's nearest distance (screen-space error, as in
  chunked level of detail: T. Ulrich, "Rendering massive terrains using chunked level of
  detail control", SIGGRAPH 2002 course notes).

The finest level is MuJoCo's hfield surface exactly: the same triangles (each cell split
along its diagonal from ``(i, j)`` to ``(i+1, j+1)``), flat face normals, and the texture
coordinates of MuJoCo's hfield texture mapping (``s = x / period - 1/2``,
``t = -y / period - 1/2``, the albedo's period ``size_m / albedo_repeat``): an image drawn at
the finest level everywhere equals the hfield's to one grey level. Tiles at different levels
meet with gaps up to their height deviation; skirts (Ulrich 2002: strips hanging down from
every tile edge, facing out) close them.

When the sun casts shadows the cameras draw the hfield itself: MuJoCo's shadow map then
holds the hfield's closed box, while open sheets of tiles shade differently where the sun
grazes a slope (up to 80 grey levels on 3 % of a view into a crater wall, sun 10 deg high)
and skirts cast dots of shadow along the seams.

Written here because MuJoCo has no level of detail or culling of its own and no maintained
Python library adds them to it.
"""

from __future__ import annotations

import dataclasses
import math

import mujoco
import numpy as np
from dm_control import mjcf

#: Largest projected height error of a tile's level of detail (pixels).
SCREEN_ERROR_PX = 0.5
#: Levels of detail: every ``stride``-th grid point of the terrain.
LOD_STRIDES = (1, 2, 4, 8)
#: Tile side in metres (rounded to a multiple of the coarsest stride in grid cells).
TILE_M = 4.0
#: Largest terrain grid (cells per side) drawn as tiles: a tiled cell costs about 256 bytes
#: of mesh (three vertices per triangle for flat shading, all levels), so 640 x 640 cells
#: (64 m at 0.1 m) take about 105 MB; larger grids are drawn as the one hfield.
MAX_TILED_CELLS = 640
#: Skirts reach this much below the deepest gap any two levels can leave (m).
SKIRT_MARGIN_M = 0.02
#: Prefix of the tiles' mesh assets, ``terrain_tile_<tile>_<stride>``; a custom numeric of
#: the same name holds the tile's bounding sphere (centre x, y, z, radius) and the level's
#: height error.
PREFIX = "terrain_tile_"


def tile_mesh_name(tile: int, stride: int) -> str:
    return f"{PREFIX}{tile}_{stride}"


def _coarse_error(sub: np.ndarray, stride: int) -> float:
    """Largest |height| difference between a tile's full grid and its surface at ``stride``
    (the coarse grid triangulated as MuJoCo's hfield, evaluated at every fine grid point)."""
    if stride == 1:
        return 0.0
    n_i, n_j = sub.shape
    i, j = np.meshgrid(np.arange(n_i), np.arange(n_j), indexing="ij")
    ci = np.minimum(i // stride, (n_i - 1) // stride - 1)
    cj = np.minimum(j // stride, (n_j - 1) // stride - 1)
    v = (i - ci * stride) / stride
    u = (j - cj * stride) / stride
    hs = sub[::stride, ::stride]
    h00, h01, h10, h11 = hs[ci, cj], hs[ci, cj + 1], hs[ci + 1, cj], hs[ci + 1, cj + 1]
    lower = u >= v
    z = np.where(lower, h00 + u * (h01 - h00) + v * (h11 - h01), h00 + v * (h10 - h00) + u * (h11 - h10))
    return float(np.max(np.abs(z - sub)))


def _surface(hs: np.ndarray, x0: float, y0: float, step: float) -> np.ndarray:
    """Triangles (n, 3, 3) of a grid with MuJoCo's hfield diagonal, counter-clockwise from above."""
    n_i, n_j = hs.shape
    xs, ys = x0 + step * np.arange(n_j), y0 + step * np.arange(n_i)
    i, j = (a.ravel() for a in np.meshgrid(np.arange(n_i - 1), np.arange(n_j - 1), indexing="ij"))

    def p(ii, jj):
        return np.stack([xs[jj], ys[ii], hs[ii, jj]], axis=-1)

    lower = np.stack([p(i, j), p(i, j + 1), p(i + 1, j + 1)], axis=1)
    upper = np.stack([p(i, j), p(i + 1, j + 1), p(i + 1, j)], axis=1)
    return np.concatenate([lower, upper])


def _skirts(hs: np.ndarray, x0: float, y0: float, step: float, depth: float) -> np.ndarray:
    """Triangles (n, 3, 3) hanging ``depth`` below the grid's four edges, facing outwards."""
    n_i, n_j = hs.shape
    xs, ys = x0 + step * np.arange(n_j), y0 + step * np.arange(n_i)
    centre = np.array([xs.mean(), ys.mean()])
    edges = [
        np.stack([xs, np.full(n_j, ys[0]), hs[0]], axis=1),
        np.stack([xs, np.full(n_j, ys[-1]), hs[-1]], axis=1),
        np.stack([np.full(n_i, xs[0]), ys, hs[:, 0]], axis=1),
        np.stack([np.full(n_i, xs[-1]), ys, hs[:, -1]], axis=1),
    ]
    tris = []
    for top in edges:
        bottom = top - [0.0, 0.0, depth]
        a, b, a_low, b_low = top[:-1], top[1:], bottom[:-1], bottom[1:]
        quad = np.concatenate([np.stack([a, a_low, b_low], axis=1), np.stack([a, b_low, b], axis=1)])
        normal = np.cross(quad[:, 1] - quad[:, 0], quad[:, 2] - quad[:, 0])
        outward = quad[:, :, :2].mean(axis=1) - centre
        flip = np.einsum("ij,ij->i", normal[:, :2], outward) < 0
        quad[flip] = quad[flip][:, ::-1]
        tris.append(quad)
    return np.concatenate(tris)


def _msh(triangles: np.ndarray, normals: np.ndarray, period: float) -> bytes:
    """MuJoCo's binary mesh format: one normal per triangle (flat shading) and the texture
    coordinates of the hfield's mapping."""
    vert = triangles.reshape(-1, 3)
    norm = np.repeat(normals, 3, axis=0)
    uv = np.stack([vert[:, 0] / period - 0.5, -vert[:, 1] / period - 0.5], axis=1)
    face = np.arange(len(vert), dtype=np.int32)
    header = np.array([len(vert), len(vert), len(vert), len(face) // 3], np.int32)
    parts = [header, vert.astype(np.float32), norm.astype(np.float32), uv.astype(np.float32), face]
    return b"".join(p.tobytes() for p in parts)


def _face_normals(triangles: np.ndarray) -> np.ndarray:
    normal = np.cross(triangles[:, 1] - triangles[:, 0], triangles[:, 2] - triangles[:, 0])
    return normal / np.linalg.norm(normal, axis=1, keepdims=True)


def add_terrain_tiles(root: mjcf.RootElement, heights: np.ndarray, size_m: float, albedo_repeat: int) -> None:
    """Mesh assets of every tile at every level of detail that divides it, each with a
    custom numeric of its name that :class:`TerrainTiles` reads."""
    n = heights.shape[0]
    res = size_m / (n - 1)
    half = size_m / 2
    period = size_m / albedo_repeat
    coarsest = LOD_STRIDES[-1]
    cells = max(coarsest, round(TILE_M / res / coarsest) * coarsest)
    starts = range(0, n - 1, cells)
    tiles = [(i0, j0, min(cells, n - 1 - i0), min(cells, n - 1 - j0)) for i0 in starts for j0 in starts]
    subs = [heights[i0 : i0 + ci + 1, j0 : j0 + cj + 1] for i0, j0, ci, cj in tiles]
    errors = [{s: _coarse_error(sub, s) for s in LOD_STRIDES if ci % s == 0 and cj % s == 0} for sub, (_, _, ci, cj) in zip(subs, tiles)]
    depth = 2 * max(max(e.values()) for e in errors) + SKIRT_MARGIN_M  # every level's skirts cover every gap
    for k, ((i0, j0, ci, cj), sub, level_errors) in enumerate(zip(tiles, subs, errors)):
        x0, y0 = -half + j0 * res, -half + i0 * res
        lo, hi = float(sub.min()) - depth, float(sub.max())
        centre = np.array([x0 + cj * res / 2, y0 + ci * res / 2, (lo + hi) / 2])
        radius = math.sqrt((cj * res / 2) ** 2 + (ci * res / 2) ** 2 + ((hi - lo) / 2) ** 2)
        for stride, error in level_errors.items():
            hs = sub[::stride, ::stride]
            surface = _surface(hs, x0, y0, res * stride)
            skirts = _skirts(hs, x0, y0, res * stride, depth)
            up = np.tile([0.0, 0.0, 1.0], (len(skirts), 1))  # skirts shaded as the ground they stand in for
            blob = _msh(np.concatenate([surface, skirts]), np.concatenate([_face_normals(surface), up]), period)
            name = tile_mesh_name(k, stride)
            root.asset.add("mesh", name=name, file=mjcf.Asset(blob, ".msh"), inertia="shell")
            root.custom.add("numeric", name=name, data=[*centre, radius, error])


@dataclasses.dataclass
class _Mesh:
    mesh_id: int
    pos: np.ndarray
    mat: np.ndarray

    @classmethod
    def of(cls, model: mujoco.MjModel, name: str) -> _Mesh:
        """A mesh asset and the frame MuJoCo moved its vertices into (``mesh_pos``, ``mesh_quat``)."""
        mesh_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MESH, name)
        mat = np.zeros(9)
        mujoco.mju_quat2Mat(mat, model.mesh_quat[mesh_id])
        return cls(mesh_id, model.mesh_pos[mesh_id].copy(), mat)


class TerrainTiles:
    """The tiles of a compiled model (:func:`add_terrain_tiles`): :meth:`select` chooses them
    for a camera, :meth:`replace_hfield` puts them in its scene. :meth:`from_model` gives
    ``None`` for a model without tiles."""

    def __init__(self, model: mujoco.MjModel, rows: list[tuple[int, int, np.ndarray]], material: int):
        n_tiles = 1 + max(k for k, _, _ in rows)
        self.centre = np.zeros((n_tiles, 3))
        self.radius = np.zeros(n_tiles)
        self.error = np.full((n_tiles, len(LOD_STRIDES)), np.inf)  # inf: level does not divide the tile
        self.meshes: dict[tuple[int, int], _Mesh] = {}
        for k, stride, (cx, cy, cz, radius, error) in rows:
            level = LOD_STRIDES.index(stride)
            self.centre[k] = cx, cy, cz
            self.radius[k] = radius
            self.error[k, level] = error
            name = tile_mesh_name(k, stride)
            self.meshes[k, level] = _Mesh.of(model, name)
        self.material = material
        self.hfield = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "terrain")
        self.texture = int(model.mat_texid[material, mujoco.mjtTextureRole.mjTEXROLE_RGB])
        self.rgba = model.mat_rgba[material].astype(np.float32)
        self.specular = float(model.mat_specular[material])
        self.shininess = float(model.mat_shininess[material])
        self.emission = float(model.mat_emission[material])

    @classmethod
    def from_model(cls, model: mujoco.MjModel) -> TerrainTiles | None:
        rows = []
        for i in range(model.nnumeric):
            numeric = model.numeric(i)
            if numeric.name.startswith(PREFIX):
                tile, stride = numeric.name.removeprefix(PREFIX).split("_")
                rows.append((int(tile), int(stride), numeric.data))
        if not rows:
            return None
        material = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_MATERIAL, "regolith")
        return cls(model, rows, material)

    def select(self, pos: np.ndarray, cam_mat: np.ndarray, fovy_deg: float, aspect: float, height_px: int,
               near: float, far: float, margin: float) -> list[tuple[int, int]]:
        """(tile, level) pairs to draw for a camera at ``pos`` with MuJoCo orientation
        ``cam_mat`` (x right, y up, looking along -z). ``margin`` widens each tile's bounding
        sphere (the stereo baseline: the right camera shares the scene)."""
        R = cam_mat.reshape(3, 3)
        p = (self.centre - pos) @ R  # tile centres in camera axes
        r = self.radius + margin
        forward = -p[:, 2]
        half_y = math.radians(fovy_deg) / 2
        half_x = math.atan(math.tan(half_y) * aspect)
        keep = (forward + r >= near) & (forward - r <= far)
        for axis, half in ((0, half_x), (1, half_y)):
            keep &= np.abs(p[:, axis]) * math.cos(half) - forward * math.sin(half) <= r
        distance = np.maximum(np.linalg.norm(p, axis=1) - r, near)
        focal_px = height_px / 2 / math.tan(math.radians(fovy_deg) / 2)
        fine_enough = focal_px * self.error / distance[:, None] <= SCREEN_ERROR_PX
        level = len(LOD_STRIDES) - 1 - np.argmax(fine_enough[:, ::-1], axis=1)
        return [(int(k), int(level[k])) for k in np.flatnonzero(keep)]

    def replace_hfield(self, scene: mujoco.MjvScene, chosen: list[tuple[int, int]]) -> None:
        """Put the chosen tiles in ``scene`` in place of the terrain hfield, as static geoms
        with the terrain's material."""
        geom_obj = mujoco.mjtObj.mjOBJ_GEOM
        slots = [i for i in range(scene.ngeom) if scene.geoms[i].objtype == geom_obj and scene.geoms[i].objid == self.hfield]
        added = max(0, len(chosen) - len(slots))
        if scene.ngeom + added > scene.maxgeom:
            raise RuntimeError(f"scene holds {scene.maxgeom} geoms; {scene.ngeom} + {len(chosen)} terrain tiles do not fit")
        targets = slots[: len(chosen)] + list(range(scene.ngeom, scene.ngeom + added))
        scene.ngeom += added
        size = np.ones(3)
        for slot, key in zip(targets, chosen):
            mesh = self.meshes[key]
            geom = scene.geoms[slot]
            mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_MESH, size, mesh.pos, mesh.mat, self.rgba)
            geom.dataid = 2 * mesh.mesh_id  # the mesh's own display list, not its convex hull
            geom.matid, geom.texid = self.material, self.texture
            geom.texcoord = 1  # the mesh's own coordinates, already at the albedo's period
            geom.texrepeat = (1.0, 1.0)
            geom.category = mujoco.mjtCatBit.mjCAT_STATIC
            geom.specular, geom.shininess, geom.emission = self.specular, self.shininess, self.emission
        for slot in reversed(slots[len(chosen) :]):  # no tile in view: the hfield's slot takes the last geom
            scene.ngeom -= 1
            if slot != scene.ngeom:
                _copy_geom(scene.geoms[scene.ngeom], scene.geoms[slot])


_GEOM_FIELDS = [name for name in dir(mujoco.MjvGeom) if not name.startswith("_")]


def _copy_geom(src, dst) -> None:
    for name in _GEOM_FIELDS:
        setattr(dst, name, getattr(src, name))
