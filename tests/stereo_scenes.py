"""Small rendered scenes for the stereo and sensor tests (and scripts/bench_sensors.py):
a stereo head 1.2 m above textured ground, looking along +x and 20 deg down, like the
LRU's mast camera (thesis 7.1: b = 9 cm, 50.6 deg)."""

from __future__ import annotations  # noqa: I001  (sim before mujoco: it sets MUJOCO_GL)

import math

import sim  # noqa: F401  (sets MUJOCO_GL before mujoco is imported)
import cv2
import mujoco
import numpy as np

from sim.world.camera_rig import StereoRig
from sim.scenario import CameraConfig

HEAD_HEIGHT_M = 1.2
HEAD_PITCH_DEG = 20.0
BASELINE_M = 0.09
HFOV_DEG = 50.6


def head_xyaxes(pitch_deg: float = HEAD_PITCH_DEG) -> tuple[np.ndarray, np.ndarray]:
    """MuJoCo camera x (image right) and y (image up) axes, looking along +x, pitched down."""
    p = math.radians(pitch_deg)
    look = np.array([math.cos(p), 0.0, -math.sin(p)])
    x = np.array([0.0, -1.0, 0.0])
    y = np.cross(-look, x)
    return x, y


def camera_xml(rig: StereoRig, pos, pitch_deg: float = HEAD_PITCH_DEG) -> str:
    x, y = head_xyaxes(pitch_deg)
    axes = " ".join(f"{v:.12g}" for v in (*x, *y))
    half = rig.baseline_m / 2
    return (
        f'<body name="head" pos="{pos[0]} {pos[1]} {pos[2]}">'
        f'<camera name="{rig.left_camera}" pos="{-half * x[0]} {-half * x[1]} {-half * x[2]}" xyaxes="{axes}" fovy="{rig.vfov_deg!r}"/>'
        f'<camera name="{rig.right_camera}" pos="{half * x[0]} {half * x[1]} {half * x[2]}" xyaxes="{axes}" fovy="{rig.vfov_deg!r}"/>'
        "</body>"
    )


def noise_texture(size: int, rng: np.random.Generator, contrast: float = 0.35) -> np.ndarray:
    """Multi-octave value noise, equal weights from 4 cells per tile down to single texels."""
    img = np.zeros((size, size), np.float32)
    cells = 4
    while cells <= size:
        layer = rng.standard_normal((cells, cells)).astype(np.float32)
        img += cv2.resize(layer, (size, size), interpolation=cv2.INTER_CUBIC if cells < size else cv2.INTER_NEAREST)
        cells *= 2
    img = (img - img.mean()) / img.std()
    return np.clip(128 + 128 * contrast * img, 0, 255).astype(np.uint8)


def textured_heightfield_scene(width: int, height: int, seed: int = 0, size_m: float = 16.0, n: int = 161):
    """Gentle hills (0.3 m) with a 1024 px noise albedo (1.6 cm texels); the head at
    x = -6 m. Returns (model, data, rig, camera config)."""
    rng = np.random.default_rng(seed)
    tex = noise_texture(1024, rng)
    ok, png = cv2.imencode(".png", tex)
    assert ok
    g = np.linspace(-size_m / 2, size_m / 2, n)
    X, Y = np.meshgrid(g, g)
    h = 0.15 * np.sin(0.9 * X + 0.3) * np.cos(0.7 * Y) + 0.1 * np.sin(2.3 * Y + 1.1 * X)
    h_min, h_max = float(h.min()), float(h.max())
    rig = StereoRig("head", "left", "right", BASELINE_M, HFOV_DEG, width, height)
    ground_z = float(h[n // 2, np.argmin(np.abs(g + 6.0))])
    xml = f"""
    <mujoco>
      <statistic extent="{size_m}"/>
      <visual><global offwidth="640" offheight="480"/><quality offsamples="0"/></visual>
      <asset>
        <hfield name="ground" nrow="{n}" ncol="{n}" size="{size_m / 2} {size_m / 2} {h_max - h_min} 0.5"/>
        <texture name="albedo" type="2d" file="albedo.png"/>
        <material name="albedo" texture="albedo" texrepeat="1 1" specular="0" shininess="0"/>
        <texture name="sky" type="skybox" builtin="gradient" rgb1="0.1 0.1 0.15" rgb2="0 0 0" width="32" height="32"/>
      </asset>
      <worldbody>
        <light directional="true" castshadow="false" dir="-0.4 -0.3 -0.87" pos="0 0 20" diffuse="0.8 0.8 0.8" ambient="0.2 0.2 0.2"/>
        <geom type="hfield" hfield="ground" pos="0 0 {h_min}" material="albedo"/>
        {camera_xml(rig, (-6.0, 0.0, ground_z + HEAD_HEIGHT_M))}
      </worldbody>
    </mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml, {"albedo.png": png.tobytes()})
    model.hfield_data[:] = ((h - h_min) / (h_max - h_min)).astype(np.float32).ravel()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data, rig, CameraConfig(width=width, height=height)


def procedural_terrain_scene(
    width: int,
    height: int,
    seed: int = 3,
    size_m: float = 20.0,
    texture_px: int = 1024,
    light=None,
    pitch_deg: float = HEAD_PITCH_DEG,
    preset: str = "moon",
):
    """The same head over sim.world.terrain's heightfield, rocks and regolith albedo
    (``texture_px`` texels of 2 cm, repeated as often as the terrain needs), lit by ``light``
    (a ``sim.scenario.LightRealism``; default: add_terrain's), looking ``pitch_deg`` down,
    on a ``preset`` site (sim.world.terrain: ground and sky colours)."""
    from dm_control import mjcf

    from sim.scenario import TerrainConfig
    from sim.world.terrain import add_terrain, generate_terrain

    cfg = TerrainConfig.model_validate(
        {"preset": preset, "size_m": size_m, "craters": {"count": 2}, "rocks": {"count": 8}, "texture": {"size_px": texture_px}}
    )
    head_xy = (-size_m / 4, 0.0)
    terrain = generate_terrain(cfg, np.random.default_rng(seed), [(head_xy, 1.0)])
    root = mjcf.RootElement(model="scene")
    add_terrain(root, terrain, light)
    root.statistic.extent = size_m
    glob = getattr(root.visual, "global")
    glob.offwidth, glob.offheight = 640, 480
    rig = StereoRig("head", "left", "right", BASELINE_M, HFOV_DEG, width, height)
    x, y = head_xyaxes(pitch_deg)
    z = float(terrain.height_at(*head_xy)) + HEAD_HEIGHT_M
    body = root.worldbody.add("body", name="head", pos=[head_xy[0], head_xy[1], z])
    for name, sign in ((rig.left_camera, -0.5), (rig.right_camera, 0.5)):
        body.add("camera", name=name, pos=(sign * BASELINE_M * x).tolist(), xyaxes=[*x, *y], fovy=rig.vfov_deg)
    model = mujoco.MjModel.from_xml_string(root.to_xml_string(), root.get_assets())
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data, rig, CameraConfig(width=width, height=height)
