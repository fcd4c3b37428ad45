"""The cameras' terrain tiles (sim/world/terrain_tiles.py) against MuJoCo's own hfield:
the finest level draws the same image, culling drops nothing in view, the levels of detail
keep their error bound, and skirts leave no hole where levels meet."""

from __future__ import annotations  # noqa: I001  (sim before mujoco: it sets MUJOCO_GL)

import math

import sim  # noqa: F401
import mujoco
import numpy as np
import pytest

import sim.world.terrain as terrain
import sim.world.terrain_tiles as terrain_tiles
from sim.scenario import LightRealism
from sim.world.sensors import StereoRenderer
from sim.world.terrain import Terrain
from sim.world.terrain_tiles import LOD_STRIDES, TerrainTiles, _coarse_error
from tests.stereo_scenes import procedural_terrain_scene

HEADINGS_DEG = (0.0, 70.0, 160.0)


@pytest.fixture(scope="module")
def scene():
    model, data, rig, camera = procedural_terrain_scene(320, 240, texture_px=512)
    assert model.mat_texrepeat[model.material("regolith").id][0] == 2  # the albedo repeats: its phase is checked
    return model, data, rig, camera


def _frames(scene, monkeypatch, tiles: bool = True, select=None):
    """Left image and depth of the scene's head turned to each of HEADINGS_DEG."""
    model, data, rig, camera = scene
    with monkeypatch.context() as patch:
        if not tiles:
            patch.setattr(TerrainTiles, "from_model", classmethod(lambda cls, m: None))
        if select is not None:
            patch.setattr(TerrainTiles, "select", select)
        renderer = StereoRenderer(model, rig, camera)
        head = model.body("head").id
        quat = model.body_quat[head].copy()
        out = []
        try:
            for heading in HEADINGS_DEG:
                half = math.radians(heading) / 2
                model.body_quat[head] = [math.cos(half), 0.0, 0.0, math.sin(half)]
                mujoco.mj_forward(model, data)
                frame = renderer.render(data, with_depth=True)
                out.append((frame.left.astype(int), frame.depth))
        finally:
            model.body_quat[head] = quat
            mujoco.mj_forward(model, data)
            renderer.close()
    return out


@pytest.fixture(scope="module")
def hfield_frames(scene):
    with pytest.MonkeyPatch.context() as patch:
        return _frames(scene, patch, tiles=False)


def _assert_same(frames, reference):
    for (grey, depth), (grey_ref, depth_ref) in zip(frames, reference):
        diff = np.abs(grey - grey_ref)
        assert np.mean(diff > 1) < 1e-3  # rounding at triangle edges (float32 vertices)
        assert np.sum(diff > 3) <= 2
        assert np.array_equal(np.isinf(depth), np.isinf(depth_ref))
        finite = np.isfinite(depth_ref)
        assert np.abs(depth[finite] - depth_ref[finite]).max() < 1e-3


def test_the_finest_level_draws_the_hfield(scene, hfield_frames, monkeypatch):
    monkeypatch.setattr(terrain_tiles, "SCREEN_ERROR_PX", 0.0)
    _assert_same(_frames(scene, monkeypatch), hfield_frames)


def test_culling_drops_no_tile_in_view(scene, hfield_frames, monkeypatch):
    """The culled tiles at the finest level draw what the whole hfield draws."""
    monkeypatch.setattr(terrain_tiles, "SCREEN_ERROR_PX", 0.0)
    select = TerrainTiles.select
    culled = []

    def counting(self, *args, **kwargs):
        chosen = select(self, *args, **kwargs)
        culled.append(len(self.radius) - len(chosen))
        return chosen

    _assert_same(_frames(scene, monkeypatch, select=counting), hfield_frames)
    assert min(culled) > 0  # culling did drop tiles out of view


@pytest.mark.parametrize("n_tiles", [0, 1, 5])
def test_the_tiles_take_the_hfields_place_in_the_scene(scene, n_tiles):
    """Whatever the number of tiles in view (none when looking at the sky), the scene
    holds every other geom unchanged, no hfield, and the tiles."""
    model, data, _, _ = scene
    tiles = TerrainTiles.from_model(model)
    scn = mujoco.MjvScene(model, maxgeom=1000)
    camera = mujoco.MjvCamera()
    mujoco.mjv_updateScene(model, data, mujoco.MjvOption(), None, camera, mujoco.mjtCatBit.mjCAT_ALL, scn)

    def content(s):
        geoms = (s.geoms[i] for i in range(s.ngeom))
        return sorted((int(g.type), int(g.objtype), int(g.objid), tuple(np.round(g.pos, 6)), int(g.dataid)) for g in geoms)

    before = content(scn)
    hfield = [c for c in before if c[0] == mujoco.mjtGeom.mjGEOM_HFIELD]
    assert len(hfield) == 1
    chosen = [(k, 0) for k in range(n_tiles)]
    tiles.replace_hfield(scn, chosen)
    after = content(scn)
    ids = {2 * tiles.meshes[key].mesh_id for key in chosen}
    meshes = [c for c in after if c[0] == mujoco.mjtGeom.mjGEOM_MESH and c[4] in ids]
    assert len(meshes) == n_tiles
    assert sorted(set(after) - set(meshes)) == sorted(set(before) - set(hfield))
    assert scn.ngeom == len(before) - 1 + n_tiles


def test_levels_of_detail_keep_depth_within_their_error_bound(scene, hfield_frames, monkeypatch):
    frames = _frames(scene, monkeypatch)
    for (_, depth), (_, depth_ref) in zip(frames, hfield_frames):
        near = np.isfinite(depth_ref) & (depth_ref < 6.0)
        error = np.abs(depth[near] - depth_ref[near])
        assert np.median(error) < 1e-3
        assert np.mean(error > 0.02) < 0.01  # larger only at silhouettes that moved by < 0.5 px


def test_skirts_close_the_gaps_between_levels(scene, monkeypatch):
    """Neighbouring tiles alternately at the finest and the coarsest level: no sky shows
    through where they meet."""

    def checkerboard(self, *args, **kwargs):
        side = round(math.sqrt(len(self.radius)))
        coarsest = [int(np.flatnonzero(np.isfinite(row))[-1]) for row in self.error]
        return [(k, 0 if (k // side + k % side) % 2 else coarsest[k]) for k in range(len(self.radius))]

    frames = _frames(scene, monkeypatch, select=checkerboard)
    for _, depth in frames:
        ground_above = np.maximum.accumulate(np.isfinite(depth), axis=0)  # a heightfield seen from above:
        holes = np.isinf(depth) & ground_above  # no sky below ground in an image column but through holes
        assert holes.sum() == 0


@pytest.mark.parametrize("stride", LOD_STRIDES[1:])
def test_coarse_error_is_the_largest_deviation_from_the_grid(stride):
    rng = np.random.default_rng(stride)
    cells, res = 24, 0.1
    fine = rng.normal(0.0, 0.05, (cells + 1, cells + 1))
    coarse_grid = fine[::stride, ::stride]
    size = cells * res
    coarse = Terrain(heights=coarse_grid, size_m=size, resolution_m=res * stride, rocks=[], lander=None,
                     albedo=np.zeros((4, 4), np.uint8), preset="moon")
    xy = -size / 2 + res * np.arange(cells + 1)
    X, Y = np.meshgrid(xy, xy)
    expected = np.abs(coarse.height_at(X, Y) - fine).max()
    assert _coarse_error(fine, stride) == pytest.approx(expected, abs=1e-12)
    assert expected > 0.01


def test_with_shadows_the_cameras_draw_the_hfield(monkeypatch):
    scene = procedural_terrain_scene(160, 120, light=LightRealism(shadows=True, sun_elevation_deg=10.0))
    model, data, rig, camera = scene

    def refuse(self, *args, **kwargs):
        raise AssertionError("tiles chosen for a render with shadows")

    monkeypatch.setattr(TerrainTiles, "select", refuse)
    renderer = StereoRenderer(model, rig, camera)
    try:
        frame = renderer.render(data, with_depth=True)
    finally:
        renderer.close()
    assert np.isfinite(frame.depth).mean() > 0.5  # the ground is there


def test_a_grid_too_large_for_tiles_keeps_the_hfield(monkeypatch):
    """Above MAX_TILED_CELLS cells per side the model has no tiles and the renderer draws
    the hfield (large terrains would need gigabytes of tile meshes)."""
    monkeypatch.setattr(terrain, "MAX_TILED_CELLS", 150)
    small = procedural_terrain_scene(160, 120, size_m=14.0)  # 140 cells
    large = procedural_terrain_scene(160, 120, size_m=16.0)  # 160 cells
    assert TerrainTiles.from_model(small[0]) is not None
    assert TerrainTiles.from_model(large[0]) is None
    model, data, rig, camera = large
    renderer = StereoRenderer(model, rig, camera)
    try:
        assert np.isfinite(renderer.render(data, with_depth=True).depth).mean() > 0.5
    finally:
        renderer.close()
