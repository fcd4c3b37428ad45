"""Rendering and SGBM speed and depth accuracy on procedural terrain.

    .venv/bin/python scripts/bench_sensors.py [--size 40] [--poses 8] [--frames 20]

Builds sim.world.terrain's default terrain (40 m, 0.1 m grid, craters, rocks, 2048 px albedo),
puts an LRU-like stereo head (1.2 m, 20 deg down, b = 9 cm, 50.6 deg) at several
poses and reports, per resolution: stereo pairs rendered per second with and without
ground-truth depth (median time per pair, interleaved), SGBM milliseconds per pair (median), and SGBM depth error against the
rendered depth between 2 and 6 m.
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import sim  # noqa: F401, I001  (sets MUJOCO_GL before mujoco is imported)
import mujoco
import numpy as np
from dm_control import mjcf

from sim.world.camera_rig import StereoRig
from sim.scenario import CameraConfig, TerrainConfig
from sim.world.sensors import StereoRenderer
from sim.world.terrain import add_terrain, generate_terrain
from slam.stereo import StereoCalibration, StereoMatcher
from stereo_scenes import BASELINE_M, HEAD_HEIGHT_M, HEAD_PITCH_DEG


def build(size_m: float, hfov: float, resolutions):
    cfg = TerrainConfig(size_m=size_m)
    poses = []
    rng = np.random.default_rng(11)
    for _ in range(64):
        xy = rng.uniform(-size_m / 3, size_m / 3, 2)
        poses.append((tuple(xy), float(rng.uniform(0, 2 * math.pi))))
    terrain = generate_terrain(cfg, np.random.default_rng(5), [(p[0], 2.0) for p in poses[:16]])
    root = mjcf.RootElement(model="bench")
    add_terrain(root, terrain)
    root.statistic.extent = size_m
    glob = getattr(root.visual, "global")
    glob.offwidth, glob.offheight = 640, 480
    head = root.worldbody.add("body", name="head", mocap="true")
    rigs = {}
    for w, h in resolutions:
        rig = StereoRig(f"r{w}", f"l{w}", f"rr{w}", BASELINE_M, hfov, w, h)
        for name, sign in ((rig.left_camera, -0.5), (rig.right_camera, 0.5)):
            # head frame: x forward, y left, z up; camera looks along +x, pitched down
            p = math.radians(HEAD_PITCH_DEG)
            look = np.array([math.cos(p), 0.0, -math.sin(p)])
            x = np.array([0.0, -1.0, 0.0])
            y = np.cross(-look, x)
            head.add("camera", name=name, pos=(sign * BASELINE_M * x).tolist(), xyaxes=[*x, *y], fovy=rig.vfov_deg)
        rigs[(w, h)] = rig
    model = mujoco.MjModel.from_xml_string(root.to_xml_string(), root.get_assets())
    data = mujoco.MjData(model)
    placed = []
    for xy, yaw in poses[:16]:
        z = float(terrain.height_at(*xy)) + HEAD_HEIGHT_M
        placed.append((np.array([xy[0], xy[1], z]), np.array([math.cos(yaw / 2), 0, 0, math.sin(yaw / 2)])))
    return model, data, rigs, placed


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", type=float, default=40.0)
    ap.add_argument("--poses", type=int, default=8)
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--hfov", type=float, default=50.6)
    args = ap.parse_args()
    resolutions = [(320, 240), (640, 480)]
    t0 = time.perf_counter()
    model, data, rigs, poses = build(args.size, args.hfov, resolutions)
    print(f"terrain + compile: {time.perf_counter() - t0:.2f} s, hfield {model.hfield_nrow[0]}^2, {model.ngeom} geoms")
    poses = poses[: args.poses]
    for (w, h), rig in rigs.items():
        renderer = StereoRenderer(model, rig, CameraConfig(width=w, height=h))
        matcher = StereoMatcher(StereoCalibration.from_intrinsics(rig.intrinsics, rig.baseline_m, w, h))
        # interleaved, median per-pair time: robust to other processes on the shared cores
        times = {False: [], True: []}
        for i in range(args.frames):
            data.mocap_pos[0], data.mocap_quat[0] = poses[i % len(poses)]
            mujoco.mj_kinematics(model, data)
            mujoco.mj_camlight(model, data)
            for with_depth in (False, True):
                t = time.perf_counter()
                renderer.render(data, with_depth=with_depth)
                times[with_depth].append(time.perf_counter() - t)
        rates = {k: 1.0 / float(np.median(v)) for k, v in times.items()}
        rel, ab, valid, total, sgbm_s = [], [], 0, 0, []
        for pos, quat in poses:
            data.mocap_pos[0], data.mocap_quat[0] = pos, quat
            mujoco.mj_kinematics(model, data)
            mujoco.mj_camlight(model, data)
            frame = renderer.render(data, with_depth=True)
            t = time.perf_counter()
            est = matcher.depth(frame.left, frame.right)
            sgbm_s.append(time.perf_counter() - t)
            gt = frame.depth
            sel = (gt >= 2) & (gt <= 6)
            ok = sel & np.isfinite(est)
            rel.append(np.abs(est[ok] - gt[ok]) / gt[ok])
            ab.append(np.abs(est[ok] - gt[ok]))
            valid += ok.sum()
            total += sel.sum()
        renderer.close()
        rel, ab = np.concatenate(rel), np.concatenate(ab)
        print(
            f"{w}x{h}: render {rates[False]:.1f} pairs/s without depth, {rates[True]:.1f} with depth; "
            f"SGBM ({matcher.num_disparities} disparities) {1000 * float(np.median(sgbm_s)):.1f} ms/pair; "
            f"2-6 m: median rel error {100 * np.median(rel):.2f} %, p95 {100 * np.percentile(rel, 95):.1f} %, "
            f"median abs {100 * np.median(ab):.1f} cm, valid {100 * valid / max(total, 1):.0f} % of {total} px"
        )


if __name__ == "__main__":
    main()
