"""Online estimate of a stereo rig's disparity offset (our addition to thesis 4.1.1 and 5.1.1).

A rectified pair whose right camera is turned by a small yaw ``θ`` against the
calibration measures every disparity ``f θ`` pixels too large: a depth bias
``z^2 f θ / (f b)`` that grows with range (the shape of eq. 5.2c), which no per-point noise
model averages out. It stretches every point the visual odometry and the mapping
triangulate, so each robot's submaps are distorted by its own offset (docs/matching.md,
"Calibration bias and the ICP's points"). The thesis calibrates the rig once (5.1.1: a
reprojection RMSE up to 0.46 px) and treats what is left as noise.

The offset is observable while the robot moves: a keyframe's points are placed by their
disparities, and the pixels where a later image sees them depend on their true depths. An
offset changes near and far points differently (``dz/dδ = -z^2 / (f b)``), which the
pose cannot absorb, so a keyframe and a later image of it measure the offset
(:func:`slam.vo.two_view_disparity_offset`, on sparse subpixel disparities of the
keyframe's corners). The VO measures it once per keyframe, with the widest baseline; all
measurements against one keyframe would share that keyframe's disparity noise. This
class fuses the keyframes' measurements with a Gaussian prior (the calibration's
uncertainty): the weighted mean of independent measurements of a constant (a keyframe
measured again, after a revisit, keeps its more informative measurement). A measurement
more than ``gate_sigma`` combined standard deviations from the current estimate is not
fused (mismatched points, a moving object in view). Written by hand: no library holds
this estimator.
"""

from __future__ import annotations

import math


class StereoOffsetException(Exception):
    """Bad parameters of the offset estimate."""


class DisparityOffsetEstimate:
    """The fused offset (px, the amount measured disparities exceed the true ones) of one
    rig. ``prior_std_px``: the calibration's uncertainty of the offset (the filter holds the
    same as a consider parameter, slam.filter); ``gate_sigma``: the outlier gate."""

    def __init__(self, prior_std_px: float, gate_sigma: float = 3.0):
        if not (prior_std_px > 0 and gate_sigma > 0):
            raise StereoOffsetException(f"prior_std_px and gate_sigma must be > 0, got {prior_std_px}, {gate_sigma}")
        self.gate_sigma = gate_sigma
        self._best: dict[int, tuple[float, float]] = {}  # keyframe -> (estimate, information) of its best measurement
        self._info = 1.0 / prior_std_px**2  # prior: zero offset
        self._weighted = 0.0  # sum of information x estimate
        self.rejected = 0

    @property
    def value(self) -> float:
        return self._weighted / self._info

    @property
    def std(self) -> float:
        return 1.0 / math.sqrt(self._info)

    @property
    def keyframes(self) -> int:
        """Keyframes whose measurements are fused."""
        return len(self._best)

    def add(self, keyframe: int, estimate: float, information: float) -> bool:
        """One VO measurement against ``keyframe``: its offset ``estimate`` (px) with
        ``information`` (1 / px^2). Replaces the keyframe's earlier measurement when it is
        more informative. Returns whether it was fused."""
        if not (math.isfinite(estimate) and math.isfinite(information) and information > 0):
            return False
        old = self._best.get(keyframe)
        if old is not None and old[1] >= information:
            return False
        info, weighted = self._info, self._weighted
        if old is not None:
            info, weighted = info - old[1], weighted - old[0] * old[1]
        if (estimate - weighted / info) ** 2 > self.gate_sigma**2 * (1.0 / information + 1.0 / info):
            self.rejected += 1
            return False
        self._best[keyframe] = (estimate, information)
        self._info, self._weighted = info + information, weighted + estimate * information
        return True

    def report(self) -> dict:
        """JSON-ready: the estimate, its standard deviation, the keyframes fused and the measurements gated out."""
        return {"estimate_px": self.value, "std_px": self.std, "keyframes": self.keyframes, "rejected": self.rejected}
