"""``output.dataset: euroc``: a short two-robot run read back from its EuRoC MAV datasets."""

import copy

import cv2
import numpy as np
import pytest
import yaml

from sim.run import run_folder
from sim.run.onboard import body_camera_transform
from sim.run.recording import Recorder
from sim.run.runner import Run
from sim.scenario import load_scenario
from sim.world.calibration_errors import believed_body_camera

SCENARIO = {
    "name": "dataset",
    "seed": 7,
    "duration_s": 6,
    "terrain": {"size_m": 20, "rocks": {"count": 6}, "craters": {"count": 2}},
    "robots": [
        {"name": "rover", "preset": "lru", "start": {"xy": [-3, 0]}, "route": {"waypoints": [[2, 0]], "start_delay_s": 0.5}},
        {"name": "copter", "preset": "ardea", "start": {"xy": [-3, -3]}, "route": {"waypoints": [[2, -3]], "start_delay_s": 0.5}},
    ],
    # the recording's frame hook sees every pair the stereo matcher gets (recording_image_every: 1)
    "output": {"recording": True, "recording_image_every": 1, "topdown_png": False, "dataset": "euroc"},
    "slam": {"enabled": False},
}
CAMERAS = {"rover": {"head": ("cam0", "cam1")}, "copter": {"down": ("cam0", "cam1"), "up": ("cam2", "cam3")}}


def ns(t) -> np.ndarray:
    return np.round(np.asarray(t) * 1e9).astype(np.int64)


def timestamps(path) -> np.ndarray:
    return np.loadtxt(path, delimiter=",", skiprows=1, usecols=0, dtype=np.int64, ndmin=1)


def numbers(path) -> tuple[np.ndarray, np.ndarray]:
    """A numeric CSV: its timestamps and the other columns."""
    return timestamps(path), np.loadtxt(path, delimiter=",", skiprows=1, dtype=np.float64, ndmin=2)[:, 1:]


@pytest.fixture(scope="module")
def dataset_run(tmp_path_factory):
    """Runs the scenario through ``run_to_folder``; keeps the run and every stereo pair its matcher got."""
    out = tmp_path_factory.mktemp("dataset_run")
    frames: dict[tuple[str, str], list[tuple[float, np.ndarray, np.ndarray]]] = {}
    runs: list[Run] = []

    class KeptRun(Run):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            runs.append(self)

    def keep_frame(self, robot, rig, t, stereo):
        frames.setdefault((robot, rig.name), []).append((t, stereo.left.copy(), stereo.right.copy()))

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(run_folder, "Run", KeptRun)
        patch.setattr(Recorder, "log_frame", keep_frame)
        metrics = run_folder.run_to_folder(load_scenario(copy.deepcopy(SCENARIO)), out)
    assert metrics["status"] == "completed", metrics["error"]
    return runs[0], frames, out / "dataset"


def test_images_are_every_frame_the_stereo_matcher_got(dataset_run):
    run, frames, root = dataset_run
    for robot, rigs in CAMERAS.items():
        runtime = run.robots[robot]
        assert runtime.log.frames >= 25  # 5 Hz for 6 s
        assert sorted(p.name for p in (root / robot / "mav0").iterdir() if p.name.startswith("cam")) == sorted(
            c for pair in rigs.values() for c in pair
        )
        for rig, pair in rigs.items():
            seen = frames[(robot, rig)]
            assert len(seen) == runtime.log.frames
            for side, cam in enumerate(pair):
                lines = (root / robot / "mav0" / cam / "data.csv").read_text().splitlines()
                assert lines[0] == "#timestamp [ns],filename"
                rows = [line.split(",") for line in lines[1:]]
                stamps = np.array([int(r[0]) for r in rows])
                assert np.array_equal(stamps, ns([t for t, _, _ in seen]))
                assert np.all(np.diff(stamps) > 0)
                assert [r[1] for r in rows] == [f"{s}.png" for s in stamps]
                images = sorted((root / robot / "mav0" / cam / "data").iterdir())
                assert len(images) == len(rows)
                previous = None
                for (_, left, right), (_, name) in zip(seen, rows):
                    image = cv2.imread(str(root / robot / "mav0" / cam / "data" / name), cv2.IMREAD_UNCHANGED)
                    assert image.dtype == np.uint8 and image.ndim == 2
                    assert np.array_equal(image, (left, right)[side]), (robot, cam, name)
                    assert previous is None or not np.array_equal(image, previous)
                    previous = image


def test_camera_calibration_is_the_nominal_one_at_t0(dataset_run):
    _, _, root = dataset_run
    fresh = Run(load_scenario(copy.deepcopy({**SCENARIO, "output": {"recording": False, "topdown_png": False}})))  # its state is t = 0
    try:
        for robot, rigs in CAMERAS.items():
            body = fresh.robots[robot].robot
            for rig in body.stereo_rigs:
                T_true = body_camera_transform(fresh.world.model, fresh.world.data, body, rig.left_camera)
                T_believed = believed_body_camera(T_true, rig, fresh.calibration_errors[robot])
                assert not np.allclose(T_believed, T_true, atol=1e-6)  # the realistic default: calibration errors
                right = T_believed.copy()
                right[:3, 3] += T_believed[:3, 0] * rig.baseline_m
                for cam, T in zip(rigs[rig.name], (T_believed, right)):
                    sensor = yaml.safe_load((root / robot / "mav0" / cam / "sensor.yaml").read_text())
                    assert sensor["sensor_type"] == "camera" and sensor["camera_model"] == "pinhole"
                    assert sensor["rate_hz"] == body.cfg.camera.rate_hz
                    assert sensor["resolution"] == [rig.width, rig.height]
                    assert sensor["intrinsics"] == [rig.focal_px, rig.focal_px, (rig.width - 1) / 2, (rig.height - 1) / 2]
                    assert sensor["distortion_model"] == "radial-tangential" and sensor["distortion_coefficients"] == [0, 0, 0, 0]
                    assert sensor["T_BS"]["rows"] == sensor["T_BS"]["cols"] == 4
                    np.testing.assert_allclose(np.reshape(sensor["T_BS"]["data"], (4, 4)), T, atol=1e-12)
                    moving = root / robot / "mav0" / cam / "T_BS.csv"
                    assert moving.is_file() == body.pan_tilt_head
                    if body.pan_tilt_head:  # per frame, the first at t = 0
                        stamps, poses = numbers(moving)
                        assert np.array_equal(stamps, timestamps(root / robot / "mav0" / cam / "data.csv"))
                        np.testing.assert_allclose(poses[0].reshape(4, 4), T, atol=1e-12)
                        assert np.all(np.abs(poses[:, 12:] - [0, 0, 0, 1]) < 1e-12)
    finally:
        fresh.close()


def test_imu_odometry_and_truth_are_the_logged_samples(dataset_run):
    run, _, root = dataset_run
    for robot in CAMERAS:
        runtime, mav0 = run.robots[robot], root / robot / "mav0"
        log = runtime.log
        assert (mav0 / "imu0" / "data.csv").read_text().splitlines()[0].startswith("#timestamp [ns],w_RS_S_x [rad s^-1]")
        stamps, imu = numbers(mav0 / "imu0" / "data.csv")
        assert np.array_equal(stamps, ns(log.imu_t)) and np.all(np.diff(stamps) > 0)
        measured = np.asarray(log.imu)  # accel, gyro
        assert np.array_equal(imu, np.hstack([measured[:, 3:], measured[:, :3]]))  # gyro first
        sensor = yaml.safe_load((mav0 / "imu0" / "sensor.yaml").read_text())
        spec = runtime.imu.spec
        assert sensor["sensor_type"] == "imu" and sensor["rate_hz"] == runtime.robot.cfg.imu.rate_hz
        assert np.array_equal(np.reshape(sensor["T_BS"]["data"], (4, 4)), np.eye(4))
        assert sensor["gyroscope_noise_density"] == spec.gyro_noise_density
        assert sensor["gyroscope_random_walk"] == spec.gyro_random_walk
        assert sensor["accelerometer_noise_density"] == spec.accel_noise_density
        assert sensor["accelerometer_random_walk"] == spec.accel_random_walk

        stamps, truth = numbers(mav0 / "state_groundtruth_estimate0" / "data.csv")
        assert np.array_equal(stamps, ns(log.gt_t))
        assert np.array_equal(truth[:, :7], np.asarray(log.gt_pose))
        speed = np.linalg.norm(truth[:, 7:10], axis=1)
        assert speed.max() > 0.1 and speed[0] < 0.05  # rests, then drives or flies
        bias = np.asarray(log.imu_bias)  # accel, gyro; the truth's are those of the latest sample before it
        latest = np.searchsorted(np.asarray(log.imu_t), np.asarray(log.gt_t)[1:]) - 1
        assert np.array_equal(truth[1:, 10:], np.hstack([bias[:, 3:], bias[:, :3]])[latest])

        odometry = mav0 / "odom0" / "data.csv"
        assert odometry.is_file() == runtime.robot.has_wheel_odometry
        if runtime.robot.has_wheel_odometry:
            stamps, odom = numbers(odometry)
            assert np.array_equal(stamps, ns(log.odom_t)) and np.array_equal(odom, np.asarray(log.odom))


def test_a_failing_run_leaves_its_dataset_complete_up_to_the_failure(tmp_path, monkeypatch):
    scenario = {**copy.deepcopy(SCENARIO), "duration_s": 3, "robots": SCENARIO["robots"][:1], "output": {**SCENARIO["output"], "recording": False}}
    runs: list[Run] = []

    class FailingRun(Run):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            runs.append(self)

        def _sample(self, tick, gt_every):
            if self.env.now >= 1.5:
                raise RuntimeError("sensor bus lost")
            super()._sample(tick, gt_every)

    monkeypatch.setattr(run_folder, "Run", FailingRun)
    metrics = run_folder.run_to_folder(load_scenario(scenario), tmp_path)
    assert metrics["status"] == "failed" and "sensor bus lost" in metrics["error"]
    log, mav0 = runs[0].robots["rover"].log, tmp_path / "dataset" / "rover" / "mav0"
    for path, times in ((mav0 / "imu0" / "data.csv", log.imu_t), (mav0 / "state_groundtruth_estimate0" / "data.csv", log.gt_t)):
        text = path.read_text()
        assert text.endswith("\n")  # written to the end and closed, not left in a buffer
        assert np.array_equal(timestamps(path), ns(times)) and timestamps(path)[-1] <= 1.5e9
    assert len(timestamps(mav0 / "cam0" / "data.csv")) == log.frames == len(list((mav0 / "cam0" / "data").iterdir()))
