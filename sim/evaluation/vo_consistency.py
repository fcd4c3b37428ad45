"""How well the visual odometry knows its own errors: each delta ``T_kf_cur`` it reports
(slam/vo.py, thesis 4.1.1) against the true motion of the VO rig's left camera between the
keyframe's and the current frame's capture, scored by the NEES with the delta's own
covariance (``VoResult.cov``: pixel noise and stereo uncertainty, eq. 5.2, propagated
through the pose refinement). The true camera is the rendered one, so a calibration error
of the rig (sim/world/calibration_errors.py) shows here as it acts on the images; the
filter holds the calibration's share as consider parameters (slam/filter.py), which this
covariance leaves out on purpose. A delta covariance that fits gives a mean near 6 (3
for the rotation part, 3 for the translation part). The signed scale error of the deltas'
translations (their length against the true one) shows a bias common to all of them,
which no covariance per delta describes; so does the heading of the keyframe chain (each
delta that made a new keyframe, chained): its error about the world's vertical and the
scale of its turns against the true ones, what a focal length error of the rig does
(slam.vo.focal_scale_sensitivity)."""

from __future__ import annotations

from typing import Any

import numpy as np

from sim.evaluation.trajectory import nees_report
from slam.lie import se3_inv, so3_log
from slam.vo import VoResult


class VoDeltaScores:
    """True camera poses by frame id (:meth:`capture`) and the errors of the deltas that refer
    to them (:meth:`score`); frames older than every keyframe the VO still holds are dropped."""

    def __init__(self) -> None:
        self._true: dict[int, np.ndarray] = {}
        self._errors: list[np.ndarray] = []
        self._covs: list[np.ndarray] = []
        self._lengths: list[tuple[float, float]] = []  # (estimated, true) translation length
        self._links: list[tuple[float, float]] = []  # keyframe-to-keyframe deltas: (estimated minus true, true turn) about the world's z, rad
        self.unscored = 0  # ok deltas whose keyframe or frame had no true pose

    def capture(self, frame_id: int, T_world_cam: np.ndarray) -> None:
        self._true[frame_id] = np.asarray(T_world_cam, dtype=float)

    def score(self, result: VoResult) -> None:
        """The error ``xi`` of an ok delta, ``T_true = T_kf_cur Exp(xi)`` (its right perturbation,
        ``[rotation, translation]`` in the current camera frame, as its covariance)."""
        if result.ok and result.T_kf_cur is not None and result.cov is not None:
            kf, cur = self._true.get(result.keyframe_id), self._true.get(result.frame_id)
            if kf is None or cur is None:
                self.unscored += 1
            else:
                true, est = se3_inv(kf) @ cur, result.T_kf_cur
                R = est[:3, :3]
                self._errors.append(np.concatenate([so3_log(R.T @ true[:3, :3]), R.T @ (true[:3, 3] - est[:3, 3])]))
                self._covs.append(np.asarray(result.cov, dtype=float))
                self._lengths.append((float(np.linalg.norm(est[:3, 3])), float(np.linalg.norm(true[:3, 3]))))
                if result.new_keyframe:
                    up_error = cur[:3, :3] @ self._errors[-1][:3]  # true minus estimated, as a rotation in the world frame
                    up_turn = kf[:3, :3] @ so3_log(true[:3, :3])
                    self._links.append((-float(up_error[2]), float(up_turn[2])))
        if result.keyframe_history:
            oldest = min(min(result.keyframe_history), result.frame_id)
            for frame in [f for f in self._true if f < oldest]:
                del self._true[frame]

    def report(self, min_length_m: float = 0.05, gross_rad: float = np.radians(1.0)) -> dict[str, Any]:
        """NEES of the whole delta (6 dof), its rotation and its translation (3 each), the
        median sizes of the errors (deg, mm), over the deltas that moved at least
        ``min_length_m`` the median and mean of ``|t_est| / |t_true| - 1``, and the keyframe
        chain's heading (:meth:`_heading_report`)."""
        if not self._errors:
            return {"status": "no deltas scored", "unscored": self.unscored}
        err, cov = np.array(self._errors), np.array(self._covs)
        zero = np.zeros_like(err)
        out: dict[str, Any] = {"status": "ok", "deltas": len(err), "unscored": self.unscored}
        for key, dims, angles in (("nees", slice(0, 6), 3), ("nees_rotation", slice(0, 3), 3), ("nees_translation", slice(3, 6), 0)):
            out[key] = nees_report(err[:, dims], zero[:, dims], cov[:, dims, dims], angles)[0]
        out["median_rotation_error_deg"] = float(np.degrees(np.median(np.linalg.norm(err[:, :3], axis=1))))
        out["median_translation_error_mm"] = float(1e3 * np.median(np.linalg.norm(err[:, 3:], axis=1)))
        lengths = np.array(self._lengths)
        moved = lengths[lengths[:, 1] >= min_length_m]
        scale = moved[:, 0] / moved[:, 1] - 1.0 if len(moved) else np.zeros(0)
        out["scale_error"] = {"deltas": len(scale), "median": float(np.median(scale)) if len(scale) else None,
                              "mean": float(np.mean(scale)) if len(scale) else None}
        out["heading"] = self._heading_report(gross_rad)
        return out

    def _heading_report(self, gross_rad: float) -> dict[str, Any]:
        """The keyframe chain's heading: links (deltas that made a new keyframe), its chained
        error about the world's vertical (estimated minus true, deg, as the filter's
        ``yaw_error_deg``) and the true net and total turn, over the links off by less than
        ``gross_rad`` (the others, which the filter's gate meets, counted apart), and the
        rotation scale error ``ε`` of a least-squares fit ``error = a + ε turn`` with its
        standard error: the turns read ``1 + ε`` times the true ones."""
        links = np.array(self._links).reshape(-1, 2)
        gross = np.abs(links[:, 0]) >= gross_rad
        err, turn = links[~gross, 0], links[~gross, 1]
        out: dict[str, Any] = {"links": len(links), "gross_links": int(gross.sum()), "error_deg": float(np.degrees(err.sum())),
                               "net_turn_deg": float(np.degrees(turn.sum())), "turned_deg": float(np.degrees(np.abs(turn).sum())),
                               "rotation_scale_error": None, "rotation_scale_error_std": None}
        if len(err) > 2 and np.ptp(turn) > 0.0:
            A = np.stack([np.ones_like(turn), turn], axis=1)
            coef, *_ = np.linalg.lstsq(A, err, rcond=None)
            resid = err - A @ coef
            cov = np.linalg.inv(A.T @ A) * (resid @ resid) / (len(err) - 2)
            out["rotation_scale_error"], out["rotation_scale_error_std"] = float(coef[1]), float(np.sqrt(cov[1, 1]))
        return out
