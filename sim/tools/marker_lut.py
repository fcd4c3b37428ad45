"""Precomputation of the marker error lookup tables (thesis 6.2.3): a tag rendered in
MuJoCo over a grid of distance and view angle for one camera and marker size, blurred
to approximate defocus, detected with the on-board detector, and its corners plus their
256 perturbations (eq. 6.9) pushed through PnP; the largest error against the true pose
per grid cell goes into the table (``slam.marker_uncertainty.MarkerErrorTable``),
post-processed as the thesis says and saved under ``assets/marker_lut/``.

    marsyard marker-lut SCENARIO.yaml [--force]

builds every table a scenario's robots need (each camera rig x each marker size of the
team, the lander's tag included). Deterministic: rendering has no randomness and the
perturbations are a fixed product, so the same command gives the same table.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from pathlib import Path

import cv2
import mujoco
import numpy as np
from dm_control import mjcf

from sim.robots import make_robot
from sim.scenario import Scenario
from sim.world.camera_rig import MUJOCO_TO_OPENCV
from sim.world.markers import MarkerSpec, add_marker
from slam.lie import se3, se3_inv
from slam.marker_uncertainty import DEFAULT_DP_PX, MarkerErrorTable, corner_perturbations, pose_error, postprocess, table_name
from slam.markers import MarkerDetector

LUT_DIR = Path(__file__).resolve().parents[2] / "assets" / "marker_lut"
TAG_ID = 3
CAMERA_HEIGHT_M = 1.0
MIN_DISTANCE_M = 0.3
MIN_SIDE_PX = 6.0  # the grid reaches the distance where a frontal tag is this small
MAX_ANGLE_DEG = 88.0
DEFAULT_BLUR_SIGMA_PX = 0.6  # chosen by eye, as the thesis's "manually tuned" blur


class MarkerLutError(FileNotFoundError):
    """A scenario asks for a lookup table that has not been built."""


def lut_path(width: int, height: int, focal_px: float, size_m: float) -> Path:
    return LUT_DIR / table_name(width, height, round(focal_px, 1), size_m)


def load_tables(rigs, sizes: set[float]) -> dict[tuple[str, float], MarkerErrorTable]:
    """(rig name, marker size) -> table for a robot's stereo rigs, from ``assets/marker_lut``."""
    tables = {}
    for rig in rigs:
        for size in sorted(sizes):
            path = lut_path(rig.width, rig.height, rig.focal_px, size)
            if not path.exists():
                raise MarkerLutError(
                    f"no marker lookup table {path.name} for rig {rig.name!r} and {size:g} m tags under {LUT_DIR}; "
                    "build it with `marsyard marker-lut SCENARIO.yaml`"
                )
            tables[(rig.name, size)] = MarkerErrorTable.load(path)
    return tables


class _TagScene:
    """A tag on a mocap body in front of a fixed pinhole camera looking along world +x."""

    def __init__(self, width: int, height: int, focal_px: float, size_m: float):
        root = mjcf.RootElement(model="marker_lut")
        glob = getattr(root.visual, "global")
        glob.offwidth, glob.offheight = width, height
        root.visual.quality.offsamples = 0
        root.asset.add("texture", name="sky", type="skybox", builtin="gradient", rgb1=[0.55, 0.5, 0.45], rgb2=[0.25, 0.22, 0.2], width=32, height=32)
        root.worldbody.add("light", directional=True, castshadow=False, dir=[0.6, -0.3, -0.7], diffuse=[0.8, 0.8, 0.8], ambient=[0.35, 0.35, 0.35])
        fovy = math.degrees(2 * math.atan((height / 2) / focal_px))
        root.worldbody.add("camera", name="cam", pos=[0, 0, CAMERA_HEIGHT_M], xyaxes=[0, -1, 0, 0, 0, 1], fovy=fovy)
        add_marker(root.worldbody.add("body", name="tag", mocap=True), MarkerSpec("tag", TAG_ID, size_m, (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)))
        self.model = mujoco.MjModel.from_xml_string(root.to_xml_string(), root.get_assets())
        self.data = mujoco.MjData(self.model)
        self.renderer = mujoco.Renderer(self.model, height, width)
        self.cam = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, "cam")
        self.K = np.array([[focal_px, 0, (width - 1) / 2], [0, focal_px, (height - 1) / 2], [0, 0, 1.0]])

    def render(self, distance_m: float, angle_rad: float, blur_sigma_px: float, roll_rad: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Grey image and the true T_cam_marker: the tag ``distance_m`` ahead, its face
        turned ``angle_rad`` away from the camera about its vertical axis, then turned
        ``roll_rad`` in its own plane (about its normal; the tables use none)."""
        c, s = math.cos(angle_rad), math.sin(angle_rad)
        z = np.array([-c, -s, 0.0])  # face normal: towards the camera, turned about world z
        y = np.array([0.0, 0.0, 1.0])
        cr, sr = math.cos(roll_rad), math.sin(roll_rad)
        R = np.column_stack([np.cross(y, z), y, z]) @ np.array([[cr, -sr, 0.0], [sr, cr, 0.0], [0.0, 0.0, 1.0]])
        q = np.zeros(4)
        mujoco.mju_mat2Quat(q, R.ravel())
        self.data.mocap_pos[0], self.data.mocap_quat[0] = [distance_m, 0.0, CAMERA_HEIGHT_M], q
        mujoco.mj_forward(self.model, self.data)
        self.renderer.update_scene(self.data, camera="cam")
        grey = cv2.cvtColor(self.renderer.render(), cv2.COLOR_RGB2GRAY)
        if blur_sigma_px > 0:
            grey = cv2.GaussianBlur(grey, (0, 0), blur_sigma_px)
        T_world_cam = se3(self.data.cam_xmat[self.cam].reshape(3, 3) @ MUJOCO_TO_OPENCV, self.data.cam_xpos[self.cam])
        return grey, se3_inv(T_world_cam) @ se3(R, [distance_m, 0.0, CAMERA_HEIGHT_M])

    def close(self) -> None:
        self.renderer.close()


def _closer(detector: MarkerDetector, T_true: np.ndarray, corners: np.ndarray) -> np.ndarray | None:
    """PnP on ``corners``; of the two planar solutions the one nearer the truth (6.2.2:
    mirrored solutions are compensated with the known ground truth)."""
    d = detector.pose_from_corners(TAG_ID, corners)
    if d is None:
        return None
    if d.T_cam_marker_alt is not None and pose_error(d.T_cam_marker_alt, T_true)[:3].max() < pose_error(d.T_cam_marker, T_true)[:3].max():
        return d.T_cam_marker_alt
    return d.T_cam_marker


def cell_errors(scene: _TagScene, detector: MarkerDetector, distance_m: float, angle_rad: float, dp_px: float, blur_sigma_px: float) -> np.ndarray:
    """Maximum errors (6,) of the detection and its 256 perturbations at one grid point;
    NaN when the tag is not detected."""
    grey, T_true = scene.render(distance_m, angle_rad, blur_sigma_px)
    found = [d for d in detector.detect(grey) if d.tag_id == TAG_ID]
    if not found:
        return np.full(6, np.nan)
    errors = []
    for corners in [found[0].corners, *corner_perturbations(found[0].corners, dp_px)]:
        T = _closer(detector, T_true, corners)
        if T is not None:
            errors.append(pose_error(T, T_true))
    return np.max(errors, axis=0)


def build_table(
    width: int,
    height: int,
    focal_px: float,
    size_m: float,
    n_distances: int = 30,
    n_angles: int = 23,
    dp_px: float = DEFAULT_DP_PX,
    blur_sigma_px: float = DEFAULT_BLUR_SIGMA_PX,
    progress: Callable[[int, int], None] | None = None,
) -> MarkerErrorTable:
    """The table for one camera and marker size over ``n_distances`` distances from
    0.3 m to where a frontal tag's side is 6 px, and ``n_angles`` view angles 0-88 deg."""
    distances = np.linspace(MIN_DISTANCE_M, size_m * focal_px / MIN_SIDE_PX, n_distances)
    angles = np.radians(np.linspace(0.0, MAX_ANGLE_DEG, n_angles))
    scene = _TagScene(width, height, focal_px, size_m)
    detector = MarkerDetector(scene.K, {TAG_ID: size_m})
    raw = np.full((n_distances, n_angles, 6), np.nan)
    try:
        for i, d in enumerate(distances):
            for j, a in enumerate(angles):
                raw[i, j] = cell_errors(scene, detector, float(d), float(a), dp_px, blur_sigma_px)
            if progress is not None:
                progress(i + 1, n_distances)
    finally:
        scene.close()
    return MarkerErrorTable(distances, angles, raw, postprocess(raw), width, height, float(focal_px), float(size_m), dp_px, blur_sigma_px)


def tables_for_scenario(scenario: Scenario) -> list[tuple[int, int, float, float]]:
    """(width, height, focal_px, size_m) of every camera rig of the team against every
    marker size the team carries (the lander's tag included), sorted, without repeats."""
    robots = [make_robot(cfg, list(range(cfg.marker_count))) for cfg in scenario.robots]
    sizes = {spec.size_m for r in robots for spec in r.markers}
    if scenario.terrain.lander is not None:
        sizes.add(scenario.terrain.lander.tag_size_m)
    cameras = {(rig.width, rig.height, round(rig.focal_px, 1)) for r in robots for rig in r.stereo_rigs}
    return sorted((w, h, f, s) for w, h, f in cameras for s in sizes)


def plot_table(table: MarkerErrorTable, path: Path) -> None:
    """The six error maps over distance and view angle (fig. 6.16)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = ["roll [deg]", "pitch [deg]", "yaw [deg]", "x [m]", "y [m]", "z [m]"]
    fig, axes = plt.subplots(2, 3, figsize=(13, 7), constrained_layout=True)
    extent = [0, math.degrees(table.angles_rad[-1]), table.distances_m[0], table.distances_m[-1]]
    for k, ax in enumerate(axes.ravel()):
        values = np.degrees(table.errors[..., k]) if k < 3 else table.errors[..., k]
        im = ax.imshow(values, origin="lower", aspect="auto", extent=extent, cmap="viridis")
        ax.set(title=f"max error {names[k]}", xlabel="view angle [deg]", ylabel="distance [m]")
        fig.colorbar(im, ax=ax)
    fig.suptitle(f"{table.width}x{table.height}, f = {table.focal_px:.1f} px, tag {table.size_m:.3f} m (thesis fig. 6.16)")
    fig.savefig(path, dpi=80)
    plt.close(fig)


def build_for_scenario(
    scenario: Scenario, force: bool = False, n_distances: int = 30, n_angles: int = 23, log: Callable[[str], None] = print
) -> list[Path]:
    """Build (or with ``force`` rebuild) every table ``scenario`` needs; returns the paths written."""
    written = []
    for w, h, f, s in tables_for_scenario(scenario):
        path = lut_path(w, h, f, s)
        if path.exists() and not force:
            log(f"{path.name}: exists")
            continue
        t0 = time.perf_counter()

        def progress(i: int, n: int, name: str = path.name) -> None:
            if i % 10 == 0 or i == n:
                log(f"{name}: {i}/{n} distances")

        table = build_table(w, h, f, s, n_distances, n_angles, progress=progress)
        table.save(path)
        plot_table(table, path.with_suffix(".png"))
        detected = int(np.isfinite(table.raw[..., 0]).sum())
        log(f"{path.name}: built in {time.perf_counter() - t0:.0f} s, {detected}/{table.raw[..., 0].size} cells detected")
        written.append(path)
    return written
