"""The run's sensor data as EuRoC MAV datasets (``output.dataset: euroc``), one per robot.

So that visual-inertial SLAM systems that read the EuRoC layout (OpenVINS, ORB-SLAM3,
VINS-Fusion, Kimera) run on a simulated team, each robot's sensors (thesis 7.1) go into
``dataset/<robot>/mav0/`` of the results folder, written while the run goes (images as
they come, CSV rows streamed to open files):

- ``cam0/``, ``cam1/``: the left and right camera of the robot's VO rig (``slam.vo_rig``,
  by default its preset's); a robot with more rigs (ARDEA: ``down`` and ``up``) has the
  others' left and right cameras as ``cam2/``, ``cam3/`` and so on, in the order its preset
  builds them. Each holds ``data.csv`` (``#timestamp [ns],filename``) and
  ``data/<timestamp>.png``, every frame at the camera rate: the 8-bit grey images the
  SLAM stack gets (after image formation, :mod:`sim.world.imaging`, and condition faults;
  RGB cameras converted to grey as the stereo matcher does), and ``sensor.yaml``:
  ``rate_hz``, ``resolution``, pinhole ``intrinsics`` ``[fu, fv, cu, cv]`` with zero
  radial-tangential distortion (the rectified rig), and ``T_BS``, the camera's pose in the
  body (IMU) frame, OpenCV camera axes. Both are the NOMINAL calibration the stack
  believes (:func:`sim.world.calibration_errors.believed_body_camera`), not the true
  cameras the images come from. On a robot whose cameras move on the body (a pan-tilt
  head, the LRU's) ``sensor.yaml`` holds ``T_BS`` at t = 0 and each camera folder has
  ``T_BS.csv`` (marsyard extension: ``#timestamp [ns]`` and the 16 entries of ``T_BS``
  row-major, per frame, as the head's encoders give it).
- ``imu0/``: ``data.csv`` (``#timestamp [ns]``, angular rate in rad/s, then specific force
  in m/s^2, body frame), the measured samples the stack gets (noise, biases, scale and
  misalignment, injected faults), and ``sensor.yaml`` with ``T_BS`` identity (the body
  frame is the IMU's) and the IMU preset's white-noise densities and bias random walks
  (:class:`sim.world.sensors.ImuSpec`: the simulator adds per-sample noise of std
  ``density * sqrt(rate_hz)`` and bias steps of std ``random_walk * sqrt(1 / rate_hz)``,
  the continuous-time convention EuRoC's files and Kalibr use, so the values carry over
  unchanged). The turn-on bias spread and the scale, misalignment and g-sensitivity errors
  have no place in EuRoC's model and are left out.
- ``state_groundtruth_estimate0/data.csv``: the truth at the ground-truth rate: body
  position in the world frame (R = the simulator's world, z up), orientation as a
  quaternion w, x, y, z, world-frame velocity, and the IMU's true gyro and accelerometer
  biases.
- ``odom0/data.csv`` (marsyard extension, robots with wheel odometry: the LRU):
  ``#timestamp [ns], v_x [m s^-1], v_y [m s^-1], yaw_rate [rad s^-1]``, the measured body
  velocity from the wheel encoders (:class:`sim.world.sensors.WheelOdometryModel`).

Timestamps are simulated seconds as integer nanoseconds (rounded), starting at 0 and
strictly increasing per sensor. A dead robot's sensors write nothing after it dies; its
ground truth goes on. :class:`EurocDataset` holds the team's writers; the run closes it
when it ends, failed or not (:meth:`sim.run.runner.Run.close`).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import TextIO

import cv2
import numpy as np

from sim.robots.base import Robot
from sim.world.camera_rig import StereoRig
from sim.world.sensors import ImuSpec

__all__ = ["DATASET_FOLDER", "DatasetError", "DatasetWriter", "EurocDataset", "nanoseconds"]

#: The datasets' folder in a run's results folder.
DATASET_FOLDER = "dataset"

CAMERA_HEADER = "#timestamp [ns],filename"
POSE_HEADER = "#timestamp [ns]," + ",".join(f"T_BS_{r}{c}" for r in range(4) for c in range(4))
IMU_HEADER = "#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]"
TRUTH_HEADER = (
    "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z [], "
    "v_RS_R_x [m s^-1], v_RS_R_y [m s^-1], v_RS_R_z [m s^-1], b_w_RS_S_x [rad s^-1], b_w_RS_S_y [rad s^-1], b_w_RS_S_z [rad s^-1], "
    "b_a_RS_S_x [m s^-2], b_a_RS_S_y [m s^-2], b_a_RS_S_z [m s^-2]"
)
ODOM_HEADER = "#timestamp [ns], v_x [m s^-1], v_y [m s^-1], yaw_rate [rad s^-1]"


class DatasetError(RuntimeError):
    """A dataset file could not be written as the layout requires; the message names the file."""


def nanoseconds(t: float) -> int:
    """Simulated seconds as the integer nanoseconds of the dataset's timestamps."""
    return round(t * 1e9)


def _numbers(values) -> str:
    """Shortest round-trip decimals: a CSV value reads back as the float the run had."""
    return ",".join(repr(float(v)) for v in np.ravel(values))


def _yaml_float(value: float) -> str:
    """A float YAML 1.1 readers (PyYAML) also take as one: a mantissa with a point (``1.0e-05``, not ``1e-05``)."""
    text = repr(float(value))
    if "e" in text and "." not in text:
        mantissa, exponent = text.split("e")
        text = f"{mantissa}.0e{exponent}"
    return text


def _matrix_yaml(name: str, T: np.ndarray) -> str:
    rows = [", ".join(_yaml_float(v) for v in row) for row in T]
    data = ",\n         ".join(rows)
    return f"{name}:\n  cols: 4\n  rows: 4\n  data: [{data}]\n"


class _Csv:
    """One CSV file of a sensor, rows streamed to the open file, timestamps strictly increasing."""

    def __init__(self, path: Path, header: str):
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self._file: TextIO = path.open("w")
        self._file.write(header + "\n")
        self._last: int | None = None

    def row(self, ns: int, text: str) -> None:
        if self._last is not None and ns <= self._last:
            raise DatasetError(f"{self.path}: timestamp {ns} ns after {self._last} ns; they must increase strictly")
        self._last = ns
        self._file.write(f"{ns},{text}\n")

    def close(self) -> None:
        self._file.close()


class _Camera:
    """One camera folder ``camN/``: images, their list, ``sensor.yaml`` and, on a moving head, ``T_BS.csv``."""

    def __init__(self, folder: Path, rig: StereoRig, rate_hz: float, T_left_cam: np.ndarray, T_BS0: np.ndarray, moving: bool, comment: str):
        self.images = folder / "data"
        self.images.mkdir(parents=True, exist_ok=True)
        self.T_left_cam = T_left_cam
        K = rig.intrinsics
        (folder / "sensor.yaml").write_text(
            "# General sensor definitions.\n"
            "sensor_type: camera\n"
            f"comment: {json.dumps(comment)}\n\n"
            "# Sensor extrinsics wrt. the body-frame (nominal calibration"
            + (", at t = 0; per frame: T_BS.csv" if moving else "")
            + ").\n"
            + _matrix_yaml("T_BS", T_BS0 @ T_left_cam)
            + "\n# Camera specific definitions.\n"
            f"rate_hz: {rate_hz:g}\n"
            f"resolution: [{rig.width}, {rig.height}]\n"
            "camera_model: pinhole\n"
            f"intrinsics: [{', '.join(_yaml_float(v) for v in (K[0, 0], K[1, 1], K[0, 2], K[1, 2]))}] # fu, fv, cu, cv\n"
            "distortion_model: radial-tangential\n"
            "distortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n"
        )
        self.list = _Csv(folder / "data.csv", CAMERA_HEADER)
        self.poses = _Csv(folder / "T_BS.csv", POSE_HEADER) if moving else None

    def write(self, ns: int, image: np.ndarray, T_body_left: np.ndarray) -> None:
        if image.ndim == 3:
            image = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        name = f"{ns}.png"
        if not cv2.imwrite(str(self.images / name), image):
            raise DatasetError(f"could not write {self.images / name}")
        self.list.row(ns, name)
        if self.poses is not None:
            self.poses.row(ns, _numbers(T_body_left @ self.T_left_cam))

    def close(self) -> None:
        self.list.close()
        if self.poses is not None:
            self.poses.close()


class DatasetWriter:
    """One robot's EuRoC dataset in ``folder`` (its ``mav0/`` inside), fed by the run.

    ``vo_rig``: the rig written as ``cam0``/``cam1``; ``imu``: the robot's IMU preset;
    ``T_body_cam``: each rig's left camera in the body frame as the stack believes it at t = 0.
    """

    def __init__(self, folder: Path, robot: Robot, vo_rig: str, imu: ImuSpec, T_body_cam: dict[str, np.ndarray]):
        mav0 = folder / "mav0"
        rigs = sorted(robot.stereo_rigs, key=lambda rig: rig.name != vo_rig)  # stable: the VO rig first, the others in order
        self._cameras: dict[str, tuple[_Camera, _Camera]] = {}
        self._files: list[_Csv | _Camera] = []
        try:
            for i, rig in enumerate(rigs):
                T_right = np.eye(4)
                T_right[0, 3] = rig.baseline_m  # the nominal rectified pair: right camera at +baseline along x
                pair = []
                for k, (side, T_left_cam) in enumerate((("left", np.eye(4)), ("right", T_right))):
                    comment = f"{robot.name} rig {rig.name} {side}" + (" (VO rig)" if rig.name == vo_rig else "")
                    folder_k = mav0 / f"cam{2 * i + k}"
                    pair.append(_Camera(folder_k, rig, robot.cfg.camera.rate_hz, T_left_cam, T_body_cam[rig.name], robot.pan_tilt_head, comment))
                    self._files.append(pair[-1])
                self._cameras[rig.name] = (pair[0], pair[1])
            self._imu = self._open(mav0 / "imu0" / "data.csv", IMU_HEADER)
            comment = json.dumps(f"{robot.name} IMU, preset {imu.name} ({imu.source})")
            (mav0 / "imu0" / "sensor.yaml").write_text(
                "# General sensor definitions.\n"
                "sensor_type: imu\n"
                f"comment: {comment}\n\n"
                "# Sensor extrinsics wrt. the body-frame (the body frame is the IMU's).\n"
                + _matrix_yaml("T_BS", np.eye(4))
                + f"rate_hz: {robot.cfg.imu.rate_hz:g}\n\n"
                "# inertial sensor noise model parameters (static, continuous time)\n"
                f"gyroscope_noise_density: {_yaml_float(imu.gyro_noise_density)} # [ rad / s / sqrt(Hz) ] (gyro white noise)\n"
                f"gyroscope_random_walk: {_yaml_float(imu.gyro_random_walk)} # [ rad / s^2 / sqrt(Hz) ] (gyro bias diffusion)\n"
                f"accelerometer_noise_density: {_yaml_float(imu.accel_noise_density)} # [ m / s^2 / sqrt(Hz) ] (accel white noise)\n"
                f"accelerometer_random_walk: {_yaml_float(imu.accel_random_walk)} # [ m / s^3 / sqrt(Hz) ] (accel bias diffusion)\n"
            )
            self._truth = self._open(mav0 / "state_groundtruth_estimate0" / "data.csv", TRUTH_HEADER)
            self._odometry = self._open(mav0 / "odom0" / "data.csv", ODOM_HEADER) if robot.has_wheel_odometry else None
        except BaseException:
            self.close()
            raise

    def _open(self, path: Path, header: str) -> _Csv:
        csv = _Csv(path, header)
        self._files.append(csv)
        return csv

    def stereo(self, rig: str, t: float, left: np.ndarray, right: np.ndarray, T_body_cam: np.ndarray) -> None:
        """One stereo pair of rig ``rig`` as the stack gets it, with its believed left ``T_body_cam``."""
        ns = nanoseconds(t)
        for camera, image in zip(self._cameras[rig], (left, right)):
            camera.write(ns, image, T_body_cam)

    def imu(self, t: float, accel: np.ndarray, gyro: np.ndarray) -> None:
        """One measured IMU sample (m/s^2, rad/s, body frame)."""
        self._imu.row(nanoseconds(t), _numbers(np.concatenate([gyro, accel])))

    def odometry(self, t: float, odom: np.ndarray) -> None:
        """One wheel odometry measurement: v_x, v_y (m/s, body frame), yaw rate (rad/s); robots with wheel odometry only."""
        self._odometry.row(nanoseconds(t), _numbers(odom))

    def truth(self, t: float, pos: np.ndarray, quat_wxyz: np.ndarray, velocity: np.ndarray, gyro_bias: np.ndarray, accel_bias: np.ndarray) -> None:
        """One ground-truth state: world position, orientation, world velocity, true IMU biases."""
        self._truth.row(nanoseconds(t), _numbers(np.concatenate([pos, quat_wxyz, velocity, gyro_bias, accel_bias])))

    def close(self) -> None:
        for f in self._files:
            f.close()


class EurocDataset:
    """The team's datasets under ``folder`` (a run's ``dataset/``): one :class:`DatasetWriter` per robot,
    closed together (again closing does nothing)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        shutil.rmtree(self.folder, ignore_errors=True)  # an earlier run's images would stay beside this run's
        self.writers: dict[str, DatasetWriter] = {}

    def robot(self, robot: Robot, vo_rig: str, imu: ImuSpec, T_body_cam: dict[str, np.ndarray]) -> DatasetWriter:
        """The writer of ``robot``'s dataset, ``folder/<robot>/``."""
        writer = DatasetWriter(self.folder / robot.name, robot, vo_rig, imu, T_body_cam)
        self.writers[robot.name] = writer
        return writer

    def close(self) -> None:
        writers, self.writers = list(self.writers.values()), {}
        for writer in writers:
            writer.close()
