"""SLAM messages as bytes (thesis 3.3), the pose buffer (thesis 4.2.2) and the gravity
check on PnP's planar ambiguity (thesis 6.2.1)."""

import numpy as np
import pytest

from slam.lie import se3, so3_exp
from slam.messages import (
    DetectionMessage,
    FrameSwitchMessage,
    GoalMessage,
    LoopClosureMessage,
    MessageException,
    PoseEstimate,
    SubmapMessage,
    decode,
    encode,
)
from slam.pose_buffer import PoseBuffer


def _pose(rng):
    return se3(so3_exp(rng.normal(size=3)), rng.normal(size=3))


def _cov(rng):
    A = rng.normal(size=(6, 6))
    return A @ A.T + np.eye(6)


def _same(a, b):
    assert type(a) is type(b)
    for name, va in vars(a).items():
        vb = getattr(b, name)
        if isinstance(va, np.ndarray):
            np.testing.assert_array_equal(va, vb)
        elif isinstance(va, PoseEstimate):
            _same(va, vb)
        else:
            assert va == vb or (va != va and vb != vb), name


def test_every_message_type_round_trips_exactly():
    rng = np.random.default_rng(0)
    pose = PoseEstimate("lru1", 12.25, 3, _pose(rng), _cov(rng), answer=True)
    bodies = [
        pose,
        FrameSwitchMessage("ärdea", 4, 30.5, _pose(rng), _cov(rng)),
        DetectionMessage(pose, _pose(rng), _cov(rng), target_robot="lru2", tag_id=5, distance_m=3.2),
        DetectionMessage(pose, _pose(rng), _cov(rng), landmark=0, tag_id=0),
        SubmapMessage("lru2", 7, bytes(range(256)) * 3),
        LoopClosureMessage("lru1", 3, 4, "lru2", 11, 12, _pose(rng), _cov(rng)),
        GoalMessage("lru2", 31.5, (4.25, -7.5)),
        GoalMessage("lru1", 300.0, (0.5, 1.0), finished=True),
    ]
    for seq, body in enumerate(bodies, start=1):
        env = decode(encode("lru1", seq, body))
        assert env.key == ("lru1", seq)
        _same(env.body, body)


def test_sizes_are_small_and_measured():
    rng = np.random.default_rng(1)
    pose = PoseEstimate("lru1", 1.0, 0, _pose(rng), _cov(rng))
    # header 6 + name 5 + seq 4, then name 5, t 8, frame 4, flag 1, pose 96, covariance 168
    assert len(encode("lru1", 1, pose)) == 15 + 5 + 8 + 4 + 1 + 96 + 168


def test_bad_bytes_are_rejected_with_reasons():
    rng = np.random.default_rng(2)
    good = encode("lru1", 1, PoseEstimate("lru1", 1.0, 0, _pose(rng), _cov(rng)))
    with pytest.raises(MessageException, match="magic"):
        decode(b"XXXX" + good[4:])
    with pytest.raises(MessageException, match="version"):
        decode(good[:4] + bytes([9]) + good[5:])
    with pytest.raises(MessageException, match="truncated"):
        decode(good[:-1])
    with pytest.raises(MessageException, match="trailing"):
        decode(good + b"\0")
    with pytest.raises(MessageException, match="exactly one target"):
        DetectionMessage(PoseEstimate("a", 0.0, 0, np.eye(4), np.eye(6)), np.eye(4), np.eye(6))
    with pytest.raises(MessageException, match="4x4"):
        encode("a", 1, FrameSwitchMessage("a", 0, 0.0, np.eye(3), np.eye(6)))


def test_pose_buffer_interpolates_within_a_frame_and_never_across_a_switch():
    buf = PoseBuffer("lru1", period_s=0.05, horizon_s=10.0)
    for k in range(41):  # 2 s at 20 Hz: yaw 0.5 rad/s, 0.3 m/s along x; frame switch at 1 s
        t = 0.05 * k
        frame = 0 if t < 1.0 - 1e-9 else 1
        tf = t if frame == 0 else t - 1.0
        assert buf.due(t)
        buf.add(t, frame, se3(so3_exp([0, 0, 0.5 * tf]), [0.3 * tf, 0, 0]), np.eye(6) * (1 + t))
        assert not buf.due(t + 0.01)
    p = buf.at(0.52)
    assert p.frame_index == 0
    np.testing.assert_allclose(p.T_frame_body[:3, 3], [0.3 * 0.52, 0, 0], atol=1e-12)
    np.testing.assert_allclose(p.T_frame_body[:3, :3], so3_exp([0, 0, 0.26]), atol=1e-12)
    assert p.cov[0, 0] == pytest.approx(1.55)  # the later entry's
    near = buf.at(0.97)  # between 0.95 (frame 0) and 1.0 (frame 1): the nearer one, no blending
    assert near.frame_index == 0 and near.T_frame_body[0, 3] == pytest.approx(0.3 * 0.95)
    assert buf.at(-0.1) is None and buf.at(2.1) is None
    # an image captured after the last entry (2.0 s): between it and the filter's current estimate
    current = PoseEstimate("lru1", 2.04, 1, se3(so3_exp([0, 0, 0.52]), [0.312, 0, 0]), np.eye(6) * 3.04)
    late = buf.at(2.02, latest=current)
    np.testing.assert_allclose(late.T_frame_body[:3, 3], [0.306, 0, 0], atol=1e-12)
    np.testing.assert_allclose(late.T_frame_body[:3, :3], so3_exp([0, 0, 0.51]), atol=1e-12)
    assert late.t == 2.02 and late.frame_index == 1
    assert buf.at(2.05, latest=current) is None  # after the current estimate: not known yet
    assert buf.at(0.52, latest=current).T_frame_body[0, 3] == pytest.approx(0.3 * 0.52)
    for k in range(41, 400):
        buf.add(0.05 * k, 1, np.eye(4), np.eye(6))
    assert buf.at(1.0) is None  # beyond the horizon
    with pytest.raises(ValueError, match="not after"):
        buf.add(1.0, 1, np.eye(4), np.eye(6))


def test_the_mirrored_pnp_solution_is_recognised_by_gravity():
    from slam.agent import TeamMarker, upright_solution
    from slam.lie import rot_zyx

    # a rover's mast marker tilted back 35 deg, seen by a robot standing 10 deg rolled
    T_body_marker = se3(rot_zyx(0, np.radians(-55), 0) @ rot_zyx(0, 0, np.pi), [0.1, 0, 0.5])
    marker = TeamMarker(3, 0.15, robot="lru2", T_body_marker=T_body_marker)
    T_frame_body = se3(rot_zyx(np.radians(10), 0, 0.3), [1, 2, 0])
    T_body_cam = se3(rot_zyx(-np.pi / 2, 0, -np.pi / 2), [0.2, 0, 1.0])  # looking forward
    # truth: the target stands level 3 m ahead, turned towards the detector
    T_frame_target = se3(rot_zyx(0, 0, 0.3 + np.pi), T_frame_body[:3, 3] + [3 * np.cos(0.3), 3 * np.sin(0.3), 0])
    T_cam_marker = np.linalg.solve(T_frame_body @ T_body_cam, T_frame_target @ T_body_marker)
    mirrored = T_cam_marker @ se3(so3_exp([0, 0.7, 0]), [0, 0, 0])  # flipped by 40 deg about its (horizontal) y axis
    max_tilt = np.radians(30)
    assert upright_solution((mirrored, T_cam_marker), marker, T_body_cam, T_frame_body, max_tilt) is T_cam_marker
    assert upright_solution((T_cam_marker, None), marker, T_body_cam, T_frame_body, max_tilt) is T_cam_marker
    assert upright_solution((mirrored, None), marker, T_body_cam, T_frame_body, max_tilt) is None
