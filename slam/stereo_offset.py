"""Online estimate of a stereo rig's disparity offsets (our addition to thesis 4.1.1 and 5.1.1).

A rectified pair whose right camera is turned by a small rotation ``θ`` against the
calibration measures its disparities too large by ``s · c``, ``c = f θ`` in pixels and
``s`` the rotation's image motion along the rows (:func:`slam.stereo.disparity_offset_sensitivity`):
a yaw ``θy`` offsets every disparity by ``f θy (1 + x^2)`` (x the normalised column: 1.2
times the centre's at the sides of a 50 deg image, 3.3 times at those of a 113 deg one),
a roll ``θz`` by ``-f θz y``, a pitch ``θx`` by ``-f θx x y``. An offset biases depth by
``z^2 δ / (f b)``, growing with range (the shape of eq. 5.2c), which no per-point noise
model averages out. It stretches (yaw) and tilts (roll) every point the visual odometry
and the mapping triangulate, so each robot's submaps are distorted by its own rig
(docs/matching.md, "Calibration bias and the ICP's points"). The thesis calibrates the rig
once (5.1.1: a reprojection RMSE up to 0.46 px) and treats what is left as noise.

The offsets are observable while the robot moves: a keyframe's points are placed by their
disparities, and the pixels where a later image sees them depend on their true depths. An
offset changes near and far points differently (``dz/dδ = -z^2 / (f b)``), and different
parts of the image differently, which the pose cannot absorb, so a keyframe and a later
image of it measure ``c`` (:func:`slam.vo.two_view_disparity_offset`, on sparse subpixel
disparities of the keyframe's corners). The VO measures it once per keyframe, with the
widest baseline; all measurements against one keyframe would share that keyframe's
disparity noise. Two views see the yaw well but a roll or pitch of a narrow rig looking at
the ground hardly at all (they tilt the points much as the ground's own slope would); the
same turn also moves the right image across the rows (:func:`slam.stereo.row_offset_sensitivity`),
which every stereo match shows without a depth, so with the ``rotation`` model each new
keyframe's matches measure the pitch and roll (:func:`slam.vo.row_offset_measurement`) and
the two views the yaw alone. This class fuses the keyframes' measurements with a Gaussian
prior (the calibration's uncertainty), in information form: the weighted mean of
independent measurements of a constant, each with its 3x3 information (zero where it
sees nothing). A keyframe measured again in the same way, after a revisit, keeps its more
informative measurement (larger trace). A measurement whose Mahalanobis
distance from the current estimate, under both covariances, exceeds the ``gate_sigma``
quantile of a chi-square (as many degrees of freedom as the measurement informs) is not
fused (mismatched points, a moving object in view). Written by hand: no library holds
this estimator.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.stats import chi2


class StereoOffsetException(Exception):
    """Bad parameters of the offset estimate."""


class DisparityOffsetEstimate:
    """The fused coefficients ``c = f θ`` (px, (3,): the right camera's rotation error
    about x, y, z, slam.stereo.disparity_offset_sensitivity) of one rig. ``prior_std_px``:
    the calibration's uncertainty of each coefficient (the filter holds the same for the
    offset at the image centre as a consider parameter, slam.filter); ``gate_sigma``: the
    outlier gate, as the two-sided normal quantile it matches."""

    def __init__(self, prior_std_px: float, gate_sigma: float = 3.0):
        if not (prior_std_px > 0 and gate_sigma > 0):
            raise StereoOffsetException(f"prior_std_px and gate_sigma must be > 0, got {prior_std_px}, {gate_sigma}")
        self.gate_sigma = gate_sigma
        self._gate_p = math.erf(gate_sigma / math.sqrt(2.0))
        self._best: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}  # (kind, keyframe) -> its best measurement
        self._info = np.eye(3) / prior_std_px**2  # prior: zero offsets
        self._weighted = np.zeros(3)  # sum of information @ estimate
        self.rejected = 0

    @property
    def coefficients(self) -> np.ndarray:
        """``c`` (px, (3,)): the offset of a pixel is ``s · c``."""
        return np.linalg.solve(self._info, self._weighted)

    @property
    def covariance(self) -> np.ndarray:
        return np.linalg.inv(self._info)

    @property
    def value(self) -> float:
        """The offset at the image centre (px): ``f θy``."""
        return float(self.coefficients[1])

    @property
    def std(self) -> float:
        """The standard deviation of :attr:`value`."""
        return float(math.sqrt(self.covariance[1, 1]))

    @property
    def keyframes(self) -> int:
        """Keyframes whose measurements are fused."""
        return len({keyframe for _, keyframe in self._best})

    def add(self, keyframe: int, estimate, information, kind: str = "tracks") -> bool:
        """One VO measurement of ``keyframe``: its ``estimate`` of ``c`` (px, (3,)) with its
        ``information`` (3x3, 1 / px^2, positive semi-definite). Replaces the keyframe's
        earlier measurement of the same ``kind`` (its tracks into a later image, its stereo
        matches' rows) when it is more informative. Returns whether it was fused."""
        estimate, information = np.asarray(estimate, dtype=float), np.asarray(information, dtype=float)
        if estimate.shape != (3,) or information.shape != (3, 3):
            raise StereoOffsetException(f"expected a (3,) estimate and a (3, 3) information, got {estimate.shape}, {information.shape}")
        information = 0.5 * (information + information.T)
        if not (np.all(np.isfinite(estimate)) and np.all(np.isfinite(information)) and np.trace(information) > 0
                and np.linalg.eigvalsh(information)[0] >= -1e-9 * np.trace(information)):
            return False
        key = (kind, keyframe)
        old = self._best.get(key)
        if old is not None and np.trace(old[1]) >= np.trace(information):
            return False
        info, weighted = self._info, self._weighted
        if old is not None:
            info, weighted = info - old[1], weighted - old[1] @ old[0]
        e = estimate - np.linalg.solve(info, weighted)
        # (Λ_m^-1 + Λ^-1)^-1 = Λ_m (Λ_m + Λ)^-1 Λ: defined for a singular Λ_m
        dof = np.linalg.matrix_rank(information, tol=1e-9 * np.trace(information))
        if e @ information @ np.linalg.solve(information + info, info @ e) > chi2.ppf(self._gate_p, dof):
            self.rejected += 1
            return False
        self._best[key] = (estimate, information)
        self._info, self._weighted = info + information, weighted + information @ estimate
        return True

    def report(self) -> dict:
        """JSON-ready: the offset at the image centre and its std, the coefficients ``c`` and
        their stds (px), the keyframes fused and the measurements gated out."""
        return {
            "estimate_px": self.value, "std_px": self.std,
            "coefficients_px": self.coefficients.tolist(), "coefficients_std_px": np.sqrt(np.diag(self.covariance)).tolist(),
            "keyframes": self.keyframes, "rejected": self.rejected,
        }
