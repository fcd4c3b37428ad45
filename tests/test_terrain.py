"""Terrain against ground truth: MuJoCo's own ray casts and renders, cv2.aruco, statistics."""

from __future__ import annotations  # noqa: I001  (sim before mujoco: it sets MUJOCO_GL)

import math

import sim  # noqa: F401  (MUJOCO_GL)
import cv2
import mujoco
import numpy as np
import pytest
from dm_control import mjcf
from scipy import stats

from sim.scenario import LanderConfig, TerrainConfig
from sim.world.terrain import LANDER_PAD_RADIUS, TerrainError, add_terrain, generate_terrain

HFOV_DEG = 50.6  # LRU narrow stereo (thesis 7.1)
W, H = 320, 240
KEEP_CLEAR = [((-12.0, 0.0), 2.0), ((10.0, 10.0), 3.0)]
LANDER = LanderConfig(xy=(6.0, -5.0), yaw_deg=40.0, tag_id=17, tag_size_m=0.4)


def _compile(root: mjcf.RootElement) -> tuple[mujoco.MjModel, mujoco.MjData]:
    model = mujoco.MjModel.from_xml_string(root.to_xml_string(), root.get_assets())
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def _add_camera(root, name, pos, heading_deg, pitch_down_deg, hfov_deg=HFOV_DEG):
    """A pinhole camera heading ``heading_deg`` from +x, tilted down by ``pitch_down_deg``."""
    psi, theta = math.radians(heading_deg), math.radians(pitch_down_deg)
    forward = np.array([math.cos(psi) * math.cos(theta), math.sin(psi) * math.cos(theta), -math.sin(theta)])
    right = np.array([math.sin(psi), -math.cos(psi), 0.0])
    up = np.cross(right, forward)
    focal = (W / 2) / math.tan(math.radians(hfov_deg) / 2)
    fovy = math.degrees(2 * math.atan((H / 2) / focal))
    root.worldbody.add("camera", name=name, pos=list(pos), xyaxes=[*right, *up], fovy=fovy)


def _render_grey(model, data, cameras, width=W, height=H) -> list[np.ndarray]:
    renderer = mujoco.Renderer(model, height, width)
    try:
        out = []
        for camera in cameras:
            renderer.update_scene(data, camera)
            out.append(cv2.cvtColor(renderer.render(), cv2.COLOR_RGB2GRAY))
        return out
    finally:
        renderer.close()


@pytest.fixture(scope="module")
def terrain():
    return generate_terrain(TerrainConfig(lander=LANDER), np.random.default_rng(7), keep_clear=KEEP_CLEAR)


@pytest.fixture(scope="module")
def world(terrain):
    root = mjcf.RootElement()
    add_terrain(root, terrain)
    return root


# --------------------------------------------------------------------------- determinism


def test_same_seed_same_terrain_and_different_seed_differs():
    cfg = TerrainConfig(size_m=15, texture={"size_px": 256}, rocks={"count": 10}, craters={"count": 3})
    a, b, c = (generate_terrain(cfg, np.random.default_rng(s), keep_clear=[((0, 0), 2)]) for s in (3, 3, 4))
    assert np.array_equal(a.heights, b.heights)
    assert np.array_equal(a.albedo, b.albedo)
    assert len(a.rocks) == len(b.rocks) == 10
    for ra, rb in zip(a.rocks, b.rocks):
        assert np.array_equal(ra.center, rb.center) and np.array_equal(ra.vertices, rb.vertices)
        assert ra.yaw == rb.yaw
    assert not np.allclose(a.heights, c.heights)
    assert not np.array_equal(a.albedo, c.albedo)
    assert not np.allclose([r.center for r in a.rocks], [r.center for r in c.rocks])


def test_keep_clear_changes_rocks_not_heights_or_texture():
    cfg = TerrainConfig(size_m=15, texture={"size_px": 256}, craters={"count": 0})
    a = generate_terrain(cfg, np.random.default_rng(5))
    b = generate_terrain(cfg, np.random.default_rng(5), keep_clear=[((1.0, 2.0), 3.0)])
    assert np.array_equal(a.heights, b.heights) and np.array_equal(a.albedo, b.albedo)


# --------------------------------------------------------------------------- geometry


def test_grid_layout(terrain):
    n = terrain.heights.shape[0]
    assert terrain.heights.shape == (n, n) and terrain.heights.dtype == np.float64
    assert terrain.resolution_m == pytest.approx(terrain.size_m / (n - 1))
    i, j = 123, 321
    x, y = -terrain.size_m / 2 + j * terrain.resolution_m, -terrain.size_m / 2 + i * terrain.resolution_m
    assert terrain.height_at(x, y) == pytest.approx(terrain.heights[i, j])


def _ray_errors(terrain, root, n=300) -> list[float]:
    """|height_at - MuJoCo's ray hit| at random xy where a vertical ray hits the terrain geom."""
    model, data = _compile(root)
    terrain_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "terrain")
    half = terrain.size_m / 2 - 0.01
    xy = np.random.default_rng(0).uniform(-half, half, (n, 2))
    geom = np.zeros(1, np.int32)
    errors = []
    for x, y in xy:
        dist = mujoco.mj_ray(model, data, np.array([x, y, 20.0]), np.array([0, 0, -1.0]), None, 1, -1, geom)
        if geom[0] == terrain_id:
            errors.append(abs((20.0 - dist) - terrain.height_at(x, y)))
    assert np.allclose(terrain.height_at(xy[:, 0], xy[:, 1]), [terrain.height_at(x, y) for x, y in xy])
    return errors


def test_height_at_matches_mujoco_ray_casts(terrain, world):
    errors = _ray_errors(terrain, world)
    assert len(errors) > 250 and max(errors) < 1e-3


def test_height_at_follows_mujocos_triangulation_on_rough_ground():
    """Cell-scale roughness: picking the other cell diagonal would miss by centimetres."""
    cfg = TerrainConfig(size_m=8, roughness_m=0.2, roughness_wavelength_m=0.3, texture={"size_px": 256},
                        craters={"count": 0}, rocks={"count": 0})
    t = generate_terrain(cfg, np.random.default_rng(4))
    root = mjcf.RootElement()
    add_terrain(root, t)
    errors = _ray_errors(t, root)
    assert len(errors) == 300 and max(errors) < 1e-3


def test_normals_are_the_gradient_of_the_surface(terrain):
    rng = np.random.default_rng(1)
    x, y = rng.uniform(-19, 19, (2, 200))
    n = terrain.normal_at(x, y)
    assert n.shape == (200, 3) and np.allclose(np.linalg.norm(n, axis=1), 1) and (n[:, 2] > 0).all()
    e = 1e-6  # stays within one triangle except on a measure-zero set
    dzdx = (terrain.height_at(x + e, y) - terrain.height_at(x - e, y)) / (2 * e)
    dzdy = (terrain.height_at(x, y + e) - terrain.height_at(x, y - e)) / (2 * e)
    assert np.allclose(-n[:, 0] / n[:, 2], dzdx, atol=1e-4)
    assert np.allclose(-n[:, 1] / n[:, 2], dzdy, atol=1e-4)


def test_crater_centres_lie_below_their_rims_and_outside_keep_clear(terrain):
    assert len(terrain.craters) == 6
    angles = np.linspace(0, 2 * np.pi, 36, endpoint=False)
    for crater in terrain.craters:
        cx, cy = crater.xy
        rim = terrain.height_at(cx + crater.radius * np.cos(angles), cy + crater.radius * np.sin(angles))
        outside = terrain.height_at(cx + 2.5 * crater.radius * np.cos(angles), cy + 2.5 * crater.radius * np.sin(angles))
        inside = (np.abs(cx + 2.5 * crater.radius * np.cos(angles)) < 20) & (np.abs(cy + 2.5 * crater.radius * np.sin(angles)) < 20)
        assert terrain.height_at(cx, cy) < np.median(rim) - 0.5 * crater.depth
        assert np.median(rim[inside]) > np.median(outside[inside])  # a raised rim, not just a hole
        for (kx, ky), radius in KEEP_CLEAR:
            assert math.hypot(cx - kx, cy - ky) > radius


def _world_vertices(rock) -> np.ndarray:
    c, s = math.cos(rock.yaw), math.sin(rock.yaw)
    rot = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    return rock.vertices @ rot.T + rock.center


def test_rocks_respect_keep_clear_and_rest_half_buried_on_the_ground(terrain):
    assert len(terrain.rocks) == 25
    lander_disc = (LANDER.xy, 1.8 + TerrainConfig().rocks.clearance_m)
    for rock in terrain.rocks:
        v = _world_vertices(rock)
        for (kx, ky), radius in [*KEEP_CLEAR, lander_disc]:
            assert np.hypot(v[:, 0] - kx, v[:, 1] - ky).min() > radius
        ground = terrain.height_at(v[:, 0], v[:, 1])
        assert v[:, 2].min() < ground.min()  # no gap under the rock
        assert v[:, 2].max() > terrain.height_at(*rock.center[:2]) + 0.4 * rock.radii[2]  # it sticks out
        assert rock.center[2] <= terrain.height_at(*rock.center[:2]) + 1e-9  # at least half buried
        assert 0.15 - 1e-9 <= 2 * rock.radii[0] <= 0.8 + 1e-9


def test_surface_height_is_rock_top_where_mujoco_sees_a_rock(terrain, world):
    model, data = _compile(world)
    geom = np.zeros(1, np.int32)
    for i, rock in enumerate(terrain.rocks[:8]):
        rock_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, f"rock_{i}")
        x, y = rock.center[:2] + 0.2 * rock.radii[:2]
        dist = mujoco.mj_ray(model, data, np.array([x, y, 20.0]), np.array([0, 0, -1.0]), None, 1, -1, geom)
        assert geom[0] == rock_id
        assert terrain.surface_height_at(x, y) == pytest.approx(20.0 - dist, abs=1e-3)
    far = np.array([-12.0, 0.3])  # inside a keep-clear disc: no rock there
    assert terrain.surface_height_at(*far) == terrain.height_at(*far)


def test_rock_diameters_follow_the_truncated_power_law():
    cfg = TerrainConfig(size_m=80, resolution_m=0.5, texture={"size_px": 256}, craters={"count": 0},
                        rocks={"count": 400, "diameter_m": (0.1, 1.0), "power_law_exponent": 2.0})
    d = np.array([2 * r.radii[0] for r in generate_terrain(cfg, np.random.default_rng(2)).rocks])
    k, a, b = 2.0, 0.1, 1.0

    def cdf(x):
        return (a**-k - np.asarray(x) ** -k) / (a**-k - b**-k)

    assert stats.kstest(d, cdf).pvalue > 0.01


def test_slope_and_ridge_shape_the_heights():
    cfg = TerrainConfig(size_m=20, roughness_m=0, texture={"size_px": 256}, craters={"count": 0},
                        rocks={"count": 0}, slope={"gradient_deg": 10, "direction_deg": 90},
                        ridges=[{"start_xy": (-5, -6), "end_xy": (5, -6), "height_m": -0.5, "width_m": 2}])
    t = generate_terrain(cfg, np.random.default_rng(0))
    rise = math.tan(math.radians(10))
    assert t.height_at(3, 4) - t.height_at(3, 2) == pytest.approx(2 * rise)  # uphill along +y
    assert t.height_at(-7, 4) == pytest.approx(t.height_at(7, 4))
    assert t.height_at(0, -6) == pytest.approx(-6 * rise - 0.5)  # trench floor
    assert t.height_at(0, -8) == pytest.approx(-8 * rise)  # outside its width


def test_lander_pad_is_flat_and_rocks_fail_loudly():
    t_cfg = TerrainConfig(size_m=20, texture={"size_px": 256}, lander=LanderConfig(xy=(2, 3)))
    t = generate_terrain(t_cfg, np.random.default_rng(1))
    angles = np.linspace(0, 2 * np.pi, 24)
    ring = t.height_at(2 + (LANDER_PAD_RADIUS - 0.2) * np.cos(angles), 3 + (LANDER_PAD_RADIUS - 0.2) * np.sin(angles))
    assert np.allclose(ring, t.lander.base_z)
    with pytest.raises(TerrainError, match="rocks"):
        generate_terrain(TerrainConfig(size_m=10, texture={"size_px": 256}, craters={"count": 0}),
                         np.random.default_rng(1), keep_clear=[((0, 0), 6.5)])


# --------------------------------------------------------------------------- MJCF and looks


def test_mjcf_contents(terrain, world):
    model, _ = _compile(world)
    names = {model.geom(i).name for i in range(model.ngeom)}
    assert {"terrain", "lander_tag", *(f"rock_{i}" for i in range(len(terrain.rocks)))} <= names
    assert model.body("lander").id > 0
    assert model.light("sun").type[0] == mujoco.mjtLightType.mjLIGHT_DIRECTIONAL and not model.light("sun").castshadow
    assert model.vis.quality.shadowsize == 0 and model.vis.quality.offsamples == 0
    rock = model.geom("rock_0")
    assert rock.contype[0] and rock.conaffinity[0] and model.body_weldid[rock.bodyid[0]] == 0  # static, collides
    assert model.hfield_nrow[0] == terrain.heights.shape[0]


def test_texture_repeats_when_the_tile_is_smaller_than_the_terrain():
    cfg = TerrainConfig(size_m=30, texture={"size_px": 512, "texel_m": 0.02}, rocks={"count": 0})
    t = generate_terrain(cfg, np.random.default_rng(0))
    assert t.albedo.shape == (512, 512) and t.albedo_repeat == 3  # 30 m / 10.24 m
    root = mjcf.RootElement()
    add_terrain(root, t)
    model, _ = _compile(root)
    assert tuple(model.mat_texrepeat[model.material("regolith").id]) == (3.0, 3.0)


def test_albedo_rows_run_along_y_like_the_heights():
    """A top-down render of flat, evenly lit ground reproduces the albedo array with row 0 at -y."""
    cfg = TerrainConfig(size_m=20, roughness_m=0, craters={"count": 0}, rocks={"count": 0},
                        texture={"size_px": 512, "texel_m": 0.04})
    t = generate_terrain(cfg, np.random.default_rng(0))
    root = mjcf.RootElement()
    add_terrain(root, t)
    root.worldbody.add("camera", name="top", pos=[0, 0, 30], fovy=math.degrees(2 * math.atan(10 / 30)))
    model, data = _compile(root)
    (image,) = _render_grey(model, data, ["top"], 256, 256)  # image row 0 is at +y
    albedo = cv2.resize(t.albedo.astype(float), (256, 256), interpolation=cv2.INTER_AREA)
    crop = slice(20, -20)
    r = np.corrcoef(np.flipud(image)[crop, crop].ravel(), albedo[crop, crop].ravel())[0, 1]
    assert r > 0.95


def _patch_contrast(image: np.ndarray, patch: int = 16) -> np.ndarray:
    """Std of the Laplacian in each patch x patch block: local texture stereo can match."""
    lap = cv2.Laplacian(image.astype(np.float32), cv2.CV_32F)
    h, w = (s // patch * patch for s in image.shape)
    return lap[:h, :w].reshape(h // patch, patch, w // patch, patch).std(axis=(1, 3))


CONTRAST_THRESHOLD = 3.0  # grey levels; flat untextured ground stays below 1


def _ground_views(terrain: object, strip_texture: bool) -> list[np.ndarray]:
    root = mjcf.RootElement()
    add_terrain(root, terrain)
    if strip_texture:
        root.asset.find("material", "regolith").texture = None
    views = [((-12.0, 0.0), 0.0, 20.0), ((-12.0, 0.0), 0.0, 30.0), ((10.0, 10.0), 225.0, 25.0)]
    for k, ((x, y), heading, pitch) in enumerate(views):
        _add_camera(root, f"view{k}", (x, y, float(terrain.height_at(x, y)) + 1.2), heading, pitch)
    model, data = _compile(root)
    return _render_grey(model, data, [f"view{k}" for k in range(len(views))])


@pytest.mark.parametrize("preset", ["moon", "mars", "etna"])
def test_texture_gives_local_contrast_everywhere_in_a_rover_view(preset):
    """320x240, 1.2 m above ground, 20-30 deg down: nearly every 16x16 patch is textured."""
    flat = {"roughness_m": 0, "craters": {"count": 0}, "rocks": {"count": 0}}
    textured = generate_terrain(TerrainConfig(preset=preset), np.random.default_rng(3), keep_clear=KEEP_CLEAR)
    plain = generate_terrain(TerrainConfig(preset=preset, **flat), np.random.default_rng(3))
    for image in _ground_views(textured, strip_texture=False) + _ground_views(plain, strip_texture=False):
        assert (_patch_contrast(image) > CONTRAST_THRESHOLD).mean() > 0.98
    for image in _ground_views(plain, strip_texture=True):  # the control: the test can fail
        assert (_patch_contrast(image) > CONTRAST_THRESHOLD).mean() < 0.2


def test_lander_tag_is_detected_upright_from_three_metres(terrain, world):
    lander = terrain.lander
    c, s = math.cos(lander.yaw), math.sin(lander.yaw)
    tag = np.array([lander.xy[0] + c * lander.marker.pos[0] - s * lander.marker.pos[1],
                    lander.xy[1] + s * lander.marker.pos[0] + c * lander.marker.pos[1],
                    lander.base_z + lander.marker.pos[2]])
    camera = tag + 3.0 * np.array([c, s, 0.0])
    assert camera[2] - terrain.height_at(*camera[:2]) == pytest.approx(1.0, abs=0.1)  # a rover's head height
    _add_camera(world, "tag_view", camera, math.degrees(lander.yaw) + 180.0, 0.0)
    model, data = _compile(world)
    (image,) = _render_grey(model, data, ["tag_view"])
    world.find("camera", "tag_view").remove()
    detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11),
                                       cv2.aruco.DetectorParameters())
    corners, ids, _ = detector.detectMarkers(image)
    assert ids is not None and ids.ravel().tolist() == [LANDER.tag_id]
    top_left = corners[0][0][0]  # the tag's first corner is its top-left when upright
    assert top_left[0] < corners[0][0][:, 0].mean() and top_left[1] < corners[0][0][:, 1].mean()
