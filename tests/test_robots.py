"""Robot models, controllers and world composition, checked against simulator truth.

Tolerances stated here are the ones the controllers are tuned for:
- rover: every waypoint reached within ``route.tolerance_m`` (0.35 m default) on flat
  and on rough (etna, craters) terrain; wheel speed x radius matches the true ground
  speed within 5 % when driving straight on flat ground;
- hexacopter: altitude above the terrain held within +-0.15 m in steady flight
  (2 s after a leg starts), waypoints within tolerance, lands and cuts its motors;
- a rover pushing against a steep ridge marks its waypoint "failed"/"stuck" and goes
  on to the next one; a tipped-over robot fails its remaining waypoints; timeouts and
  stuck bookkeeping of the route tracker;
- a hexacopter whose skid catches on a parked rover climbs, moves aside and lands;
- an AprilTag on a rover (and on ARDEA) is detected by ``cv2.aruco`` with the right id
  in an image rendered by another rover's camera from about 2 m;
- cameras: fovy and intrinsics as the rig says (a rendered world point lands on the
  pixel the pinhole model predicts) and the right camera sits +baseline along x.
"""

import sim  # noqa: F401, I001  (first: sim sets MUJOCO_GL before mujoco is imported)

import math

import cv2
import mujoco
import numpy as np
import pytest

from sim.world.markers import tag_dictionary
from sim.robots import RobotError, make_robot
from sim.robots.lru import DEFAULT_TILT_DEG
from sim.robots.base import WheelState
from sim.robots.route import RouteTracker
from sim.scenario import RouteConfig, load_scenario
from sim.world.sensors import IMU_PRESETS
from sim.world.terrain import generate_terrain
from sim.world.compose import build_world

FLAT = {"preset": "moon", "size_m": 20, "roughness_m": 0.0, "craters": {"count": 0}, "rocks": {"count": 0},
        "texture": {"size_px": 512}}
ROUGH = {"preset": "etna", "size_m": 20, "roughness_m": 0.1, "craters": {"count": 3, "radius_m": [1.5, 3.0]},
         "rocks": {"count": 0}, "texture": {"size_px": 512}}


def make_world(robots: list[dict], terrain: dict, seed: int = 3, **scenario):
    sc = load_scenario({"name": "t", "duration_s": 60, "seed": seed, "terrain": terrain, "robots": robots,
                        **scenario})
    clear = [(tuple(r.start.xy), 2.0) for r in sc.robots]
    clear += [(tuple(w.xy), 2.0) for r in sc.robots for w in r.route.waypoints]
    ter = generate_terrain(sc.terrain, np.random.default_rng(seed), clear)
    tags = sc.assigned_tag_ids()
    return build_world(sc, ter, [make_robot(c, tags[c.name]) for c in sc.robots])


def run_until_finished(world, max_s: float, every=None):
    """Advance in 0.1 s chunks until every robot is finished; ``every(world)`` after each."""
    while world.data.time < max_s and not all(r.finished for r in world.robots):
        world.advance(0.1)
        if every is not None:
            every(world)


def assert_reached(robot):
    tol = robot.cfg.route.tolerance_m
    for wp in robot.waypoints:
        assert wp.status == "reached", (robot.name, wp)
        assert wp.reached_t is not None and wp.reason is None
        assert math.dist(wp.final_xy, wp.xy) < tol, (robot.name, wp)


# ------------------------------------------------------------------ building


def test_make_robot_presets_names_and_errors():
    sc = load_scenario({"name": "t", "duration_s": 1, "robots": [
        {"name": "r1", "preset": "lru"}, {"name": "r2", "preset": "lru_wide", "start": {"xy": [3, 0]}},
        {"name": "a1", "preset": "ardea", "start": {"xy": [0, 3]}}]})
    tags = sc.assigned_tag_ids()
    robots = [make_robot(c, tags[c.name]) for c in sc.robots]
    assert [type(r).__name__ for r in robots] == ["LRU", "LRUWide", "Ardea"]
    for robot in robots:
        assert robot.imu_site == f"{robot.name}/imu" and robot.accel_sensor.startswith(f"{robot.name}/")
        assert [m.tag_id for m in robot.markers] == tags[robot.name]
        assert all(m.name.startswith(f"{robot.name}/") for m in robot.markers)
        assert all(w.status == "pending" for w in robot.waypoints) and not robot.finished
        # the robot-type traits the run and the on-board stack ask for fit the built robot
        assert len(robot.markers) == robot.marker_count
        assert robot.default_vo_rig in [rig.name for rig in robot.stereo_rigs]
        assert robot.default_imu_preset in IMU_PRESETS and robot.default_cores >= 1 and robot.antenna_height_m > 0
    assert [r.has_wheel_odometry for r in robots] == [True, True, False]
    assert [r.min_mapping_height_m is None for r in robots] == [True, True, False]
    with pytest.raises(RobotError, match="carries 3 markers"):
        make_robot(sc.robots[0], [1, 2])


# ------------------------------------------------------------------ rovers


def test_rover_flat_route_scan_wheels_and_imu():
    world = make_world(
        [{"name": "r1", "preset": "lru", "start": {"xy": [-3, -1], "yaw_deg": 0},
          "route": {"speed_mps": 0.4, "scan_duration_s": 4,
                    "waypoints": [[1, -1], {"xy": [1, 1.5], "scan": True}]}}],
        FLAT,
    )
    rover = world.robots[0]
    assert 38 < world.model.body_subtreemass[rover._body_id] < 42
    world.advance(1.0)
    # at rest: the accelerometer reads +g along body z, the gyro nothing
    assert np.allclose(world.data.sensor(rover.accel_sensor).data, [0, 0, 9.81], atol=0.15)
    assert np.allclose(world.data.sensor(rover.gyro_sensor).data, 0, atol=0.02)

    speeds, pans = [], []

    def sample(w):
        vel, _ = rover.velocity()
        if rover.status == "wp 1/2" and 3 < w.data.time < 8:  # straight, at cruise speed
            wheels = rover.wheel_states()
            speeds.append((np.linalg.norm(vel[:2]), np.mean([ws.angular_speed * ws.radius for ws in wheels])))
        if rover.phase == "scan":
            pans.append(rover.head_angles()[0])

    run_until_finished(world, 50, sample)
    assert rover.status == "done"
    assert_reached(rover)
    speeds = np.array(speeds)
    assert len(speeds) > 10 and np.allclose(speeds[:, 1], speeds[:, 0], rtol=0.05)
    assert abs(speeds[:, 0].mean() - 0.4) < 0.03
    # the scan pans the head through a full turn
    assert min(pans) < -math.pi + 0.1 and max(pans) > math.pi - 0.1
    wheels = rover.wheel_states()
    assert len(wheels) == 4 and all(isinstance(w, WheelState) for w in wheels)
    assert {tuple(np.sign(w.position_body[:2])) for w in wheels} == {(1, 1), (1, -1), (-1, 1), (-1, -1)}


def test_rover_head_sweeps_while_driving_and_still_reaches_its_goal():
    """With ``route.head_sweep_deg`` the head pans +-30 deg at the commanded period while the
    wheels drive straight; without it, it looks ahead."""
    route = {"speed_mps": 0.4, "head_sweep_deg": 30, "head_sweep_period_s": 4, "waypoints": [[3, -1]]}
    world = make_world([{"name": "r1", "preset": "lru", "start": {"xy": [-3, -1], "yaw_deg": 0}, "route": route}], FLAT)
    rover = world.robots[0]
    pans, times = [], []

    def sample(w):
        if rover.phase == "drive":
            pans.append(rover.head_angles()[0])
            times.append(w.data.time)

    run_until_finished(world, 40, sample)
    assert rover.status == "done"
    assert_reached(rover)
    pans, times = np.array(pans), np.array(times)
    assert math.radians(27) < pans.max() < math.radians(33) and -math.radians(33) < pans.min() < -math.radians(27)
    crossings = times[1:][np.diff(np.sign(pans)) > 0]  # upward zero crossings, one per period
    assert np.allclose(np.diff(crossings), 4.0, atol=0.2)


def test_rover_rough_terrain_route():
    world = make_world(
        [{"name": "r1", "preset": "lru", "start": {"xy": [-4, -3], "yaw_deg": 0},
          "route": {"waypoints": [[1, -3], [1, 2], [-3, 1]]}}],
        ROUGH,
    )
    terrain, rover = world.terrain, world.robots[0]
    assert np.ptp(terrain.heights) > 1.0  # really rough
    tilts = []
    run_until_finished(world, 70, lambda w: tilts.append(max(map(abs, rover.roll_pitch_yaw()[:2]))))
    assert_reached(rover)
    assert max(tilts) > math.radians(8)  # it did drive over uneven ground
    pos, _ = rover.pose()
    assert abs(pos[2] - 0.29 - terrain.height_at(pos[0], pos[1])) < 0.15  # still on its wheels


def test_rover_against_steep_ridge_is_stuck_then_goes_on():
    ridge = {**FLAT, "ridges": [{"start_xy": [0, -5], "end_xy": [0, 5], "height_m": 1.2, "width_m": 0.8}]}
    world = make_world(
        [{"name": "r1", "preset": "lru", "start": {"xy": [-2.5, 0], "yaw_deg": 0},
          "route": {"stuck_timeout_s": 3, "waypoints": [[3, 0], [-3, 1]]}}],
        ridge,
    )
    rover = world.robots[0]
    statuses = set()
    run_until_finished(world, 40, lambda w: statuses.add(rover.status))
    first, second = rover.waypoints
    assert first.status == "failed" and first.reason == "stuck", first
    assert first.final_xy[0] < -0.3  # it never crossed the ridge
    assert second.status == "reached", second
    assert rover.status == "done (1 failed)"
    assert not rover.tipped_over


def test_tipped_over_fails_the_rest_of_the_route():
    world = make_world(
        [{"name": "r1", "preset": "lru", "route": {"waypoints": [[3, 0], [3, 3]]}}], FLAT
    )
    rover, data = world.robots[0], world.data
    # test set-up only: lay the rover on its side
    data.qpos[rover._qadr + 2] += 0.4
    data.qpos[rover._qadr + 3 : rover._qadr + 7] = [math.cos(math.pi / 4), math.sin(math.pi / 4), 0, 0]
    mujoco.mj_forward(world.model, data)
    world.advance(0.5)
    assert rover.tipped_over and rover.finished and rover.status == "tipped over"
    assert [(w.status, w.reason) for w in rover.waypoints] == [("failed", "tipped_over")] * 2


def test_route_tracker_timeout_and_stuck_bookkeeping():
    route = RouteConfig(speed_mps=1.0, stuck_timeout_s=5.0, waypoints=[[2, 0], [2, 2], [0, 0]])
    tracker = RouteTracker(route)
    tracker.begin_leg(0.0, (0, 0))
    assert tracker.deadline == pytest.approx(3 * 2 / 1.0 + 30)
    # slow but steady progress never counts as stuck, only the deadline ends it
    for k in range(37):
        assert tracker.check(float(k), (0.051 * k, 0)) is None
    assert tracker.check(36.5, (0.051 * 36.5, 0)) == "timeout"
    tracker.fail(36.5, (1.0, 0), "timeout")
    tracker.begin_leg(40.0, (1.0, 0))
    assert tracker.check(40.0, (1.0, 0)) is None
    # turning towards the waypoint is progress too, for a while
    assert tracker.check(44.0, (1.0, 0), heading_error=1.0) is None
    assert tracker.check(48.0, (1.0, 0), heading_error=0.5) is None
    assert tracker.check(52.9, (1.0, 0), heading_error=0.5) is None
    assert tracker.check(53.1, (1.0, 0), heading_error=0.5) == "stuck"
    tracker.fail(53.1, (1.0, 0), "stuck")
    tracker.fail_remaining(54.0, "tipped_over")
    assert tracker.done
    assert [(r.status, r.reason) for r in tracker.records] == [
        ("failed", "timeout"), ("failed", "stuck"), ("failed", "tipped_over")]


# ------------------------------------------------------------------ hexacopter


@pytest.mark.parametrize("terrain", [FLAT, ROUGH], ids=["flat", "rough"])
def test_hexacopter_altitude_waypoints_landing(terrain):
    world = make_world(
        [{"name": "a1", "preset": "ardea", "start": {"xy": [-3, -2], "yaw_deg": 30},
          "route": {"speed_mps": 1.0, "cruise_altitude_m": 2.0, "land": True, "scan_duration_s": 3,
                    "waypoints": [[2, -2], {"xy": [2, 2], "altitude_m": 3.0, "scan": True}]}}],
        terrain,
    )
    copter, ter = world.robots[0], world.terrain
    assert 2.7 < copter.mass < 3.3
    phases = set()
    errors = []
    scan_yaw = []

    def sample(w):
        phases.add(copter.phase)
        if copter.phase == "scan":
            scan_yaw.append(copter.roll_pitch_yaw()[2])
        if copter.phase == "fly" and w.data.time - copter.route.leg_start_t > 2.0:
            target = copter.route.target.altitude_m or copter.cfg.route.cruise_altitude_m
            errors.append(copter.altitude(ter) - target)

    run_until_finished(world, 60, sample)
    assert {"takeoff", "fly", "scan", "landing", "done"} <= phases
    turned = np.sum(np.diff(np.unwrap(scan_yaw)))
    assert abs(turned - 2 * math.pi) < math.radians(20), math.degrees(turned)  # the scan yaws a full turn
    assert_reached(copter)
    errors = np.abs(errors)
    assert len(errors) > 10 and errors.max() < 0.15, errors.max()
    assert copter.landed and copter.status == "done"
    pos, _ = copter.pose()
    assert math.dist(pos[:2], (2, 2)) < 0.35
    foot_clearance = pos[2] - 0.29 - float(ter.height_at(pos[0], pos[1]))
    assert abs(foot_clearance) < 0.08  # standing on its gear (rough ground under the feet)
    assert np.all(world.data.ctrl == 0)


def test_hexacopter_landing_on_a_parked_rover_moves_aside():
    world = make_world(
        [
            # under one skid, turned so that its mast stands clear of the rotors (they collide)
            {"name": "rover", "preset": "lru", "start": {"xy": [2.0, 0.35], "yaw_deg": 90}},
            {"name": "copter", "preset": "ardea", "start": {"xy": [-2, 0]},
             "route": {"speed_mps": 1.0, "cruise_altitude_m": 1.5, "land": True, "waypoints": [[2, 0]]}},
        ],
        FLAT,
    )
    rover, copter = world.robots
    run_until_finished(world, 45)
    assert copter.landed and not copter.tipped_over and copter.status == "done"
    assert copter._relandings >= 1  # it touched the rover first, then moved aside
    pos, _ = copter.pose()
    assert pos[2] - 0.29 == pytest.approx(float(world.terrain.height_at(pos[0], pos[1])), abs=0.03)
    assert not rover.tipped_over


def test_a_rover_cannot_drive_under_the_lander_deck():
    """The LRU's chassis passes between the lander's legs, below its deck (0.7 m), but its mast and head
    (1.3 m) collide with the deck's edge: the rover stops there and the waypoint behind the lander fails."""
    world = make_world(
        [{"name": "rover", "preset": "lru", "start": {"xy": [-5.0, 0.0]}, "route": {"waypoints": [[5.0, 0.0]], "stuck_timeout_s": 8.0}}],
        {**FLAT, "lander": {"xy": [0.0, 0.0]}},
    )
    (rover,) = world.robots
    furthest = []
    run_until_finished(world, 40, every=lambda w: furthest.append(rover.pose()[0][0]))
    assert max(furthest) < -0.8  # mast at 0.18 m ahead of the body centre, deck edge at -0.8 m
    assert max(furthest) > -1.5  # it got there
    (wp,) = rover.waypoints
    assert wp.status == "failed" and wp.reason in ("stuck", "timeout"), wp


# ------------------------------------------------------------------ markers and cameras


def _render(model, data, camera: str, width: int, height: int) -> np.ndarray:
    renderer = mujoco.Renderer(model, height=height, width=width)
    try:
        renderer.update_scene(data, camera=camera)
        return renderer.render().copy()
    finally:
        renderer.close()


def _detect(image: np.ndarray) -> set[int]:
    detector = cv2.aruco.ArucoDetector(tag_dictionary(), cv2.aruco.DetectorParameters())
    _, ids, _ = detector.detectMarkers(cv2.cvtColor(image, cv2.COLOR_RGB2GRAY))
    return set() if ids is None else {int(i) for i in ids.ravel()}


def test_apriltags_detected_from_2m():
    cam = {"width": 640, "height": 480}
    world = make_world(
        [
            {"name": "seen", "preset": "lru", "start": {"xy": [0, 0], "yaw_deg": 0}, "tag_ids": [11, 12, 13]},
            # its camera sits ~2 m from the forward-facing tag of "seen"
            {"name": "viewer", "preset": "lru", "start": {"xy": [2.49, 0], "yaw_deg": 180}, "camera": cam},
            {"name": "copter", "preset": "ardea", "start": {"xy": [0, -4.5], "yaw_deg": 0}, "tag_ids": [21, 22]},
            {"name": "viewer2", "preset": "lru", "start": {"xy": [0, -2.3], "yaw_deg": -90}, "camera": cam},
        ],
        FLAT,
    )
    world.advance(1.5)  # settle, heads tilted to their default
    seen, viewer, copter, viewer2 = world.robots
    cam_pos = world.data.cam_xpos[world.model.camera(viewer.stereo_rigs[0].left_camera).id]
    tag_pos = world.data.geom_xpos[world.model.geom(seen.markers[0].name).id]
    assert 1.9 < np.linalg.norm(cam_pos - tag_pos) < 2.2
    ids = _detect(_render(world.model, world.data, viewer.stereo_rigs[0].left_camera, 640, 480))
    assert 11 in ids, ids
    # ARDEA on the ground, its left (+y) tag facing the second viewer ~2 m away
    cam_pos = world.data.cam_xpos[world.model.camera(viewer2.stereo_rigs[0].left_camera).id]
    tag_pos = world.data.geom_xpos[world.model.geom(copter.markers[0].name).id]
    assert 1.9 < np.linalg.norm(cam_pos - tag_pos) < 2.4
    ids = _detect(_render(world.model, world.data, viewer2.stereo_rigs[0].left_camera, 640, 480))
    assert 21 in ids, ids


def _camera_frame(model, data, name):
    """OpenCV camera frame (x right, y down, z forward) of a MuJoCo camera: position, R_world_cam."""
    cid = model.camera(name).id
    r_mj = data.cam_xmat[cid].reshape(3, 3)  # columns: x right, y up, z backwards
    return data.cam_xpos[cid].copy(), r_mj @ np.diag([1.0, -1.0, -1.0])


def _red_centroid(image: np.ndarray) -> np.ndarray:
    img = image.astype(float)
    mask = (img[..., 0] > 100) & (img[..., 0] > 2.5 * img[..., 1]) & (img[..., 0] > 2.5 * img[..., 2])
    assert mask.sum() > 3, "the red probe is not in the image"
    v, u = np.nonzero(mask)
    return np.array([u.mean(), v.mean()])


def _render_with_probe(model, data, camera, point, width, height):
    renderer = mujoco.Renderer(model, height=height, width=width)
    try:
        renderer.update_scene(data, camera=camera)
        scene = renderer.scene
        mujoco.mjv_initGeom(scene.geoms[scene.ngeom], mujoco.mjtGeom.mjGEOM_SPHERE, np.array([0.02, 0, 0]),
                            np.asarray(point, float), np.eye(3).ravel(), np.array([1, 0, 0, 1], np.float32))
        scene.geoms[scene.ngeom].emission = 1.0
        scene.ngeom += 1
        return renderer.render().copy()
    finally:
        renderer.close()


def test_camera_intrinsics_and_baseline_match_the_rigs():
    world = make_world(
        [
            {"name": "narrow", "preset": "lru", "start": {"xy": [-4, 0]}, "camera": {"width": 320, "height": 240}},
            {"name": "wide", "preset": "lru_wide", "start": {"xy": [0, 4]}, "camera": {"width": 320, "height": 240}},
            {"name": "custom", "preset": "lru", "start": {"xy": [0, -4]}, "camera": {"hfov_deg": 70.0}},
            {"name": "copter", "preset": "ardea", "start": {"xy": [4, 0]}, "camera": {"width": 400, "height": 300}},
        ],
        FLAT,
    )
    model, data = world.model, world.data
    # near/far planes: MuJoCo's are fractions of stat.extent
    assert model.vis.map.znear * model.stat.extent == pytest.approx(0.05)
    assert model.vis.map.zfar * model.stat.extent == pytest.approx(60.0)
    expected = {"narrow": (50.6, ["head"], 0.09), "wide": (112.8, ["head"], 0.09), "custom": (70.0, ["head"], 0.09),
                "copter": (80.0, ["up", "down"], 0.12)}
    for robot in world.robots:
        hfov, rigs, baseline = expected[robot.name]
        assert [r.name for r in robot.stereo_rigs] == rigs
        for rig in robot.stereo_rigs:
            assert rig.hfov_deg == pytest.approx(hfov) and rig.baseline_m == pytest.approx(baseline)
            assert (rig.width, rig.height) == (robot.cfg.camera.width, robot.cfg.camera.height)
            for cam in (rig.left_camera, rig.right_camera):
                assert model.cam_fovy[model.camera(cam).id] == pytest.approx(rig.vfov_deg)
            p_left, r_left = _camera_frame(model, data, rig.left_camera)
            p_right, r_right = _camera_frame(model, data, rig.right_camera)
            assert np.allclose(r_left.T @ (p_right - p_left), [baseline, 0, 0], atol=1e-9)
            assert np.allclose(r_left, r_right)
    # ARDEA's pairs look 60 deg above and below the horizon (copter at rest on its gear)
    copter = world.robot("copter")
    for rig, sign in zip(copter.stereo_rigs, (1, -1), strict=True):
        _, r = _camera_frame(model, data, rig.left_camera)
        assert math.degrees(math.asin(-r[2, 2])) == pytest.approx(-60 * sign, abs=2.0)

    # a world point projects onto the pixel the pinhole model predicts, in both cameras
    for name in ("narrow", "wide", "copter"):
        rig = world.robot(name).stereo_rigs[0]
        K = rig.intrinsics
        p_left, r_left = _camera_frame(model, data, rig.left_camera)
        point_cam = np.array([0.35, -0.2, 3.0]) if name != "wide" else np.array([-1.2, 0.6, 2.0])
        world_point = p_left + r_left @ point_cam
        for cam, shift in ((rig.left_camera, 0.0), (rig.right_camera, rig.baseline_m)):
            pc = point_cam - np.array([shift, 0, 0])
            expected_px = (K @ pc)[:2] / pc[2]
            got = _red_centroid(_render_with_probe(model, data, cam, world_point, rig.width, rig.height))
            assert np.allclose(got, expected_px, atol=1.0), (name, cam, got, expected_px)


class _FixedGaze:
    def __init__(self, point):
        self.point = np.asarray(point, float)

    def look_at(self, t):
        return self.point


@pytest.mark.parametrize("point, row", [([-2.0, 3.0, 1.2], 0.25), ([1.6, 0.8, 0.0], None)])
def test_a_rover_points_its_head_at_its_gaze(point, row):
    """A standing rover turns its head to the gaze source's point: the point appears on the
    image's centre column, a quarter of the height below the top (a peer's markers, about
    head high), or, for a point on the ground nearby, below the centre with the usual tilt."""
    world = make_world([{"name": "r1", "preset": "lru", "start": {"xy": [0, 0], "yaw_deg": 30}}], FLAT)
    rover = world.robots[0]
    ground = float(np.ravel(world.terrain.surface_height_at(point[0], point[1]))[0])
    rover.gaze_source = _FixedGaze([point[0], point[1], point[2] + ground])
    world.advance(4.0)
    rig = rover.stereo_rigs[0]
    pos, R_world_cam = _camera_frame(world.model, world.data, rig.left_camera)
    p = R_world_cam.T @ (rover.gaze_source.point - pos)
    u, v = (rig.intrinsics @ p)[:2] / p[2]
    assert p[2] > 0 and abs(u - rig.intrinsics[0, 2]) < 0.03 * rig.width
    if row is not None:
        assert abs(v - row * rig.height) < 0.05 * rig.height
    else:
        assert v > rig.height / 2 and abs(rover.head_angles()[1] - math.radians(DEFAULT_TILT_DEG)) < math.radians(1)
