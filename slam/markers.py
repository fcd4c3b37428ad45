"""AprilTag 36h11 detection, marker pose by PnP, the simple detection uncertainty models
(thesis 6.2.1, eq. 8.1-8.2; the learned ones of 6.2.3 are in ``slam.marker_uncertainty``)
and the robot-detection composition of eq. 4.7.

Detection runs on a rectified, distortion-free pinhole image. ``cv2.aruco``
(``DICT_APRILTAG_36h11``) finds and decodes the tags; the corners are then refined with
the AprilTag detector's edge fitting (:func:`refine_corners`, :class:`CornerRefinement`
says why not OpenCV's ``CORNER_REFINE_APRILTAG``). The pose comes from the 4 corners by
``cv2.solvePnPGeneric`` with ``SOLVEPNP_IPPE_SQUARE``, which returns both solutions of
the planar ambiguity (Schweighofer and Pinz, 2006); the one with the lower reprojection
error is kept and the other as ``T_cam_marker_alt``, their error ratio as
``ambiguity``. A Levenberg-Marquardt polish (``cv2.solvePnPRefineLM``, ``refine_lm``) is
off by default: on 400 noisy synthetic tags and on the rendered ones it changed the
pose errors by less than 3 %, and with 4 corners it can trade the tilt for a perfect fit
of biased corners (1.4 deg became 10 deg on one warped tag).

Measured on MuJoCo-rendered 15 cm tags (``sim.world.markers``), 320x240, 50 deg hfov, 40
views up to 50 deg off the tag normal: detected 40/40 at 2 m, 39/40 at 3 m, 31/40 at
4 m (sides 8-13 px); translation error median 0.07 / 0.17 / 0.95 cm, rotation error
median 0.06 / 0.28 / 0.81 deg, no mirrored pose chosen.

Conventions (as everywhere in ``slam``):

- camera frame as OpenCV: x right, y down, z forward; pixel centres at integer
  coordinates (the convention of ``K``);
- marker frame: origin at the tag centre, x to the right of the printed tag, y up,
  z out of the printed face (the frame of ``sim.world.markers``); corners in ``cv2.aruco``
  order (top-left, top-right, bottom-right, bottom-left of the printed tag), i.e.
  marker coordinates ``(-s/2, s/2), (s/2, s/2), (s/2, -s/2), (-s/2, -s/2)``, with
  ``s`` the edge of the black square;
- covariances are 6x6 in the GTSAM ``Pose3`` tangent order [rotation, translation]
  with the right perturbation ``T_true = T Exp(xi)``.

Only ``numpy``, ``cv2`` and the standard library (and ``slam``'s own helpers).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import cv2
import numpy as np

from slam.lie import adjoint, se3, se3_inv

__all__ = [
    "SIGMA_CONSTANT",
    "CornerRefinement",
    "MarkerDetection",
    "MarkerDetector",
    "MarkerException",
    "UncertaintyModel",
    "detection_covariance",
    "refine_corners",
    "relative_pose",
]

TAG_FAMILY = cv2.aruco.DICT_APRILTAG_36h11
DEFAULT_MIN_SIDE_PX = 8.0  # the black square's 8 cells at one pixel each at least
# CORNER_REFINE_APRILTAG returns corners in AprilTag's pixel convention (pixel centres at
# +0.5, AprilRobotics/apriltag#121); OpenCV's (and K's) has them at integers. Measured on
# warped and MuJoCo-rendered tags: raw corners are off by +0.43..+0.6 px in x and y, by
# -0.15..+0.0 px after this shift.
APRILTAG_CORNER_OFFSET_PX = 0.5
IPPE_FAILURE_PX = 1.0  # an IPPE solution this far off its own 4 corners is a solver failure


class MarkerException(Exception):
    """Bad input to the marker detector or the uncertainty models."""


class CornerRefinement(StrEnum):
    """How the 4 tag corners are located to sub-pixel accuracy.

    ``EDGES`` (default): ``cv2.aruco``'s contour candidates and decoding
    (``CORNER_REFINE_NONE``), then :func:`refine_corners`, the edge refinement of the
    AprilTag detector (Olson 2011; Wang and Olson 2016): each side of the black square
    fitted as a line to gradient-weighted edge points, corners at the intersections.

    ``APRILTAG``: OpenCV's port of the AprilTag quad detector (``CORNER_REFINE_APRILTAG``),
    its corners shifted by -0.5 px into OpenCV's pixel convention. On the rendered 15 cm
    tags of the module docstring it decoded 38/40, 27/40 and 5/40 at 2, 3 and 4 m, with
    5-10x the translation error of ``EDGES`` and the mirrored pose chosen in 6 of the 27
    at 3 m. It was faster on a checkered floor (many square candidates for ``cv2.aruco``)
    and similar on terrain.
    """

    EDGES = "edges"
    APRILTAG = "apriltag"


class UncertaintyModel(StrEnum):
    """How a detection's 6x6 covariance is modelled (thesis 8, eq. 8.1-8.2)."""

    CONSTANT = "constant"  # eq. 8.1
    QUADRATIC = "quadratic"  # eq. 8.2: eq. 8.1 times (1 + d)^2
    LUT = "lut"  # 6.2.3: precomputed table over distance and view angle (slam.marker_uncertainty)
    ONLINE = "online"  # 6.2.3: 256 corner perturbations through PnP (eq. 6.9)
    LUT_ONLINE = "lut_online"  # 6.2.3: the larger of both (the thesis's method)


# Eq. 8.1: standard deviations of 1 cm (translation) and 1.3 deg (rotation), here in the
# [rotation, translation] tangent order. The thesis states the rotation part as variances
# of roll, pitch and yaw; to first order an isotropic diagonal is the same in any small
# rotation parameterization. Under the right perturbation T Exp([w, v]) the marker
# centre moves by R v, so 1 cm is the isotropic noise of the marker centre in the camera.
SIGMA_CONSTANT = np.diag([0.0005, 0.0005, 0.0005, 0.0001, 0.0001, 0.0001])
SIGMA_CONSTANT.setflags(write=False)


@dataclass(frozen=True)
class MarkerDetection:
    """One decoded tag and its pose in the camera frame.

    ``ambiguity`` is the ratio of the RMS reprojection errors of the two IPPE solutions,
    best / second best, in [0, 1]: near 0 the planar ambiguity is resolved clearly (a
    close or strongly tilted tag), near 1 both poses explain the corners equally well
    (a small, far, nearly frontal tag) and the chosen pose may be the mirrored one (its
    tilt flipped about the line of sight). Both errors zero, or no usable second solution
    (``T_cam_marker_alt`` None; IPPE degenerates on exactly fronto-parallel squares), count
    as 1.
    ``reprojection_error_px`` is the RMS over the 4 corners of the pixel distance to the
    projection of ``T_cam_marker`` (after the LM polish, if on; the ratio uses the IPPE
    errors, so both sides are alike).
    """

    tag_id: int
    corners: np.ndarray  # (4, 2) pixels, cv2.aruco order
    T_cam_marker: np.ndarray  # 4x4
    reprojection_error_px: float
    ambiguity: float
    T_cam_marker_alt: np.ndarray | None  # the other IPPE solution
    distance_m: float  # camera centre to marker centre
    view_angle_rad: float  # between the marker normal (z) and the line of sight to the camera; 0 = frontal

    @property
    def side_px(self) -> float:
        """Shortest edge of the detected quadrilateral, in pixels."""
        return _min_side(self.corners)


def _min_side(corners: np.ndarray) -> float:
    d = corners - np.roll(corners, -1, axis=0)
    return float(np.sqrt(np.min(np.einsum("ij,ij->i", d, d))))


def _square_points(size_m: float) -> np.ndarray:
    h = size_m / 2
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])


class MarkerDetector:
    """AprilTag 36h11 detector for one rectified pinhole camera.

    ``K`` is the 3x3 camera matrix (no distortion), ``sizes`` maps the tag ids to report to
    their black-square edge in metres (other ids are ignored), and quadrilaterals whose
    shortest side is below ``min_side_px`` are dropped (under a pixel per cell). One
    ``cv2.aruco.ArucoDetector`` is built here and reused; its minimum candidate perimeter
    follows ``min_side_px`` (set again when the image size changes), which saves most of
    the contour work on textured terrain. Not thread-safe: one detector per camera lane.
    """

    def __init__(
        self,
        K: np.ndarray,
        sizes: dict[int, float],
        min_side_px: float = DEFAULT_MIN_SIDE_PX,
        *,
        corner_refinement: CornerRefinement | str = CornerRefinement.EDGES,
        refine_lm: bool = False,
    ):
        K = np.asarray(K, dtype=float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)) or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise MarkerException(f"K must be a finite 3x3 camera matrix with positive focal lengths, got {K!r}")
        self.K = K
        self.min_side_px = float(min_side_px)
        if not self.min_side_px >= 0:
            raise MarkerException(f"min_side_px must be >= 0, got {min_side_px}")
        self.refine_lm = bool(refine_lm)
        try:
            self.corner_refinement = CornerRefinement(corner_refinement)
        except ValueError:
            raise MarkerException(f"unknown corner refinement {corner_refinement!r}; expected one of {[m.value for m in CornerRefinement]}") from None
        self.sizes: dict[int, float] = {}
        self._object_points: dict[int, np.ndarray] = {}
        for tag_id, size in sizes.items():
            if not (isinstance(tag_id, int | np.integer) and isinstance(size, int | float | np.number) and math.isfinite(size) and size > 0):
                raise MarkerException(f"sizes must map int tag ids to positive sizes in metres, got {tag_id!r}: {size!r}")
            self.sizes[int(tag_id)] = float(size)
            self._object_points[int(tag_id)] = _square_points(float(size))
        self._dist = np.zeros(0)
        self._criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 20, 1e-10)
        params = cv2.aruco.DetectorParameters()
        if self.corner_refinement is CornerRefinement.APRILTAG:
            params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_APRILTAG
        else:
            params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_NONE
        self._params = params
        self._shape: tuple[int, int] | None = None
        self._detector = cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(TAG_FAMILY), params)

    # ------------------------------------------------------------------ detection

    def detect(self, image: np.ndarray) -> list[MarkerDetection]:
        """Decoded tags with known ids in a grey ``uint8`` (h, w) or RGB (h, w, 3) image,
        sorted by id."""
        grey = self._grey(image)
        if grey.shape != self._shape:
            # candidates whose contour is shorter than a square of min_side_px are dropped
            # early (the perimeter limit is relative to the image's larger side)
            self._params.minMarkerPerimeterRate = max(0.02, 3.6 * self.min_side_px / max(grey.shape))
            self._detector.setDetectorParameters(self._params)
            self._shape = grey.shape
        corners, ids, _ = self._detector.detectMarkers(grey)
        if ids is None:
            return []
        out = []
        for quad, tag_id in zip(corners, ids.ravel()):
            tag_id = int(tag_id)
            if tag_id not in self.sizes:
                continue
            quad = quad.reshape(4, 2).astype(float)
            if self.corner_refinement is CornerRefinement.APRILTAG:
                quad -= APRILTAG_CORNER_OFFSET_PX
            if _min_side(quad) < self.min_side_px:
                continue
            if self.corner_refinement is CornerRefinement.EDGES:
                refined = refine_corners(grey, quad)
                if refined is None:
                    continue
                quad = refined
            detection = self.pose_from_corners(tag_id, quad)
            if detection is not None:
                out.append(detection)
        out.sort(key=lambda d: d.tag_id)
        return out

    @staticmethod
    def _grey(image: np.ndarray) -> np.ndarray:
        if not isinstance(image, np.ndarray):
            raise MarkerException(f"image must be a numpy array, got {type(image).__name__}")
        if image.dtype != np.uint8:
            raise MarkerException(f"image must be uint8, got {image.dtype}")
        if image.ndim == 2:
            return image
        if image.ndim == 3 and image.shape[2] == 3:
            return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
        if image.ndim == 3 and image.shape[2] == 1:
            return image[:, :, 0]
        raise MarkerException(f"image must be grey (h, w) or RGB (h, w, 3), got shape {image.shape}")

    # ------------------------------------------------------------------ pose

    def pose_from_corners(self, tag_id: int, corners: np.ndarray) -> MarkerDetection | None:
        """Marker pose from its 4 image corners (cv2.aruco order, OpenCV pixel coordinates);
        ``None`` when PnP fails. Public so that corner-perturbation models (thesis 6.2.3)
        can reuse it."""
        obj = self._object_points.get(tag_id)
        if obj is None:
            raise MarkerException(f"tag id {tag_id} has no known size (known: {sorted(self.sizes)})")
        corners = np.ascontiguousarray(corners, dtype=float)
        if corners.shape not in ((4, 2), (1, 4, 2), (4, 1, 2)):
            raise MarkerException(f"corners must be 4 image points (4, 2), got shape {corners.shape}")
        corners = corners.reshape(4, 2)
        n, rvecs, tvecs, _ = cv2.solvePnPGeneric(obj, corners, self.K, self._dist, flags=cv2.SOLVEPNP_IPPE_SQUARE)
        if n < 1:
            return None
        # (error, rvec, tvec), best first; OpenCV's own errors are per coordinate (RMS / sqrt 2),
        # here the per-corner distance is used throughout.
        solutions = sorted(((self._rms(obj, corners, r, t), r.reshape(3, 1), t.reshape(3, 1)) for r, t in zip(rvecs, tvecs)), key=lambda s: s[0])
        if not solutions[0][0] <= IPPE_FAILURE_PX:
            # OpenCV's IPPE returns a mirrored pose (or NaN) for an exactly fronto-parallel
            # square; fall back to SQPnP. Both IPPE solutions coincide there (a zero tilt
            # mirrored), so the alternative is the same pose, ambiguity 1.
            ok, r, t = cv2.solvePnP(obj, corners, self.K, self._dist, flags=cv2.SOLVEPNP_SQPNP)
            err = self._rms(obj, corners, r, t) if ok else math.inf
            if err < solutions[0][0]:
                solutions = [(err, r.reshape(3, 1), t.reshape(3, 1))] * 2
        err, rvec, tvec = solutions[0]
        if not math.isfinite(err):
            return None
        if self.refine_lm and err > 0:
            r, t = cv2.solvePnPRefineLM(obj, corners, self.K, self._dist, rvec.copy(), tvec.copy(), self._criteria)
            err_lm = self._rms(obj, corners, r, t)
            if err_lm < err:
                err, rvec, tvec = err_lm, r, t
        T = _pose(rvec, tvec)
        if len(solutions) >= 2 and math.isfinite(solutions[1][0]):
            (e1, _, _), (e2, r2, t2) = solutions[:2]
            T_alt = _pose(r2, t2)
            ambiguity = 1.0 if e2 <= 0 else e1 / e2
        else:  # no usable second solution (IPPE degenerates on exactly fronto-parallel squares)
            T_alt, ambiguity = None, 1.0
        t = T[:3, 3]
        distance = float(np.linalg.norm(t))
        cos_view = -float(T[:3, 2] @ t) / distance if distance > 0 else 1.0
        return MarkerDetection(
            tag_id=int(tag_id),
            corners=corners,
            T_cam_marker=T,
            reprojection_error_px=float(err),
            ambiguity=float(ambiguity),
            T_cam_marker_alt=T_alt,
            distance_m=distance,
            view_angle_rad=math.acos(min(1.0, max(-1.0, cos_view))),
        )

    def _rms(self, obj: np.ndarray, corners: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> float:
        """RMS over the corners of the pixel distance between ``corners`` and the projection."""
        R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=float).reshape(3, 1))
        p = obj @ R.T + np.asarray(tvec, dtype=float).ravel()
        uv = p @ self.K.T
        d = uv[:, :2] / uv[:, 2:3] - corners
        err = float(np.sqrt(np.mean(np.einsum("ij,ij->i", d, d))))
        return err if math.isfinite(err) and np.all(p[:, 2] > 0) else math.inf


_NEXT = np.array([1, 2, 3, 0])
_PREV = np.array([3, 0, 1, 2])


def refine_corners(grey: np.ndarray, corners: np.ndarray, max_iterations: int = 4, tol_px: float = 0.02) -> np.ndarray | None:
    """Sub-pixel corners of a tag's black square from approximate ones (cv2.aruco order,
    OpenCV pixel convention, within about a pixel), the edge refinement of the AprilTag
    detector: across each side, intensity profiles are sampled (bilinear, 0.25 px steps,
    reaching 2 px or 0.9 cell at most, so that neither the data cells inside nor the
    background beyond the one-cell white quiet zone are reached); the centroid of the
    dark-to-bright gradient along a profile is an edge point; a gradient-weighted
    total-least-squares line is fitted to each side's points and the corners are the
    intersections of adjacent lines. Repeated from the new corners (a small tag's reach is
    short) until no corner moves by ``tol_px``. ``None`` when a side shows no edge or a
    corner moved implausibly far."""
    c0 = np.asarray(corners, dtype=float).reshape(4, 2)
    h, w = grey.shape
    lo = np.maximum(np.floor(c0.min(axis=0)) - 4, 0).astype(int)
    hi = np.minimum(np.ceil(c0.max(axis=0)) + 5, [w, h]).astype(int)
    roi = grey[lo[1] : hi[1], lo[0] : hi[0]].astype(np.float32)
    c = c0 - lo
    for _ in range(max_iterations):
        e = c[_NEXT] - c  # side i runs from corner i to corner i+1
        L = np.hypot(e[:, 0], e[:, 1])
        if L.min() < 3:
            return None
        d = e / L[:, None]
        # outward normals: the square runs clockwise in the image (y down) seen from its face
        sign = 1.0 if np.sum(c[:, 0] * c[_NEXT, 1] - c[_NEXT, 0] * c[:, 1]) > 0 else -1.0
        normal = sign * np.column_stack([d[:, 1], -d[:, 0]])
        reach = min(2.0, 0.9 * L.min() / 8)
        s = np.arange(-reach, reach + 1e-9, 0.25)
        s_mid = 0.5 * (s[1:] + s[:-1])
        m = int(np.clip(0.8 * L.min(), 3, 48))  # edge points per side, corners' 10 % left out
        t = 0.1 + 0.8 * (np.arange(m) + 0.5) / m
        base = c[:, None, :] + t[None, :, None] * e[:, None, :]  # (4, m, 2)
        pts = base[:, :, None, :] + s[None, None, :, None] * normal[:, None, None, :]  # (4, m, n, 2)
        prof = cv2.remap(
            roi,
            pts[..., 0].reshape(4 * m, -1).astype(np.float32),
            pts[..., 1].reshape(4 * m, -1).astype(np.float32),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        ).reshape(4, m, -1)
        g = np.clip(np.diff(prof, axis=2), 0.0, None)  # dark inside -> bright outside
        weight = g.sum(axis=2)  # (4, m)
        if np.any(np.count_nonzero(weight > 1e-3, axis=1) < 2):
            return None
        offset = (g @ s_mid) / np.maximum(weight, 1e-9)
        p = base + offset[..., None] * normal[:, None, :]  # (4, m, 2) edge points
        wk = weight / weight.sum(axis=1, keepdims=True)
        mu = (wk[..., None] * p).sum(axis=1)
        qx, qy = p[..., 0] - mu[:, 0:1], p[..., 1] - mu[:, 1:2]
        wx = wk * qx
        theta = 0.5 * np.arctan2(2 * (wx * qy).sum(axis=1), (wx * qx).sum(axis=1) - (wk * qy * qy).sum(axis=1))
        u = np.column_stack([np.cos(theta), np.sin(theta)])  # fitted side directions
        # corner i = intersection of side i-1 and side i
        p1, d1, p2, d2 = mu[_PREV], u[_PREV], mu, u
        det = d1[:, 1] * d2[:, 0] - d1[:, 0] * d2[:, 1]
        if np.any(np.abs(det) < 1e-6):
            return None
        r = p2 - p1
        a = (r[:, 1] * d2[:, 0] - r[:, 0] * d2[:, 1]) / det
        c, moved = p1 + a[:, None] * d1, c
        if np.max(np.abs(c - moved)) < tol_px:
            break
    c = c + lo
    if not np.all(np.isfinite(c)) or np.max(np.abs(c - c0)) > max(3.0, 0.2 * _min_side(c0)):
        return None
    return c


def _pose(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    R, _ = cv2.Rodrigues(np.asarray(rvec, dtype=float).reshape(3, 1))
    return se3(R, np.asarray(tvec, dtype=float).ravel())


# ---------------------------------------------------------------------- uncertainty


def detection_covariance(model: UncertaintyModel | str, distance_m: float) -> np.ndarray:
    """6x6 covariance of ``T_cam_marker`` ([rotation, translation], right perturbation):
    eq. 8.1 (constant) or eq. 8.2 (eq. 8.1 times ``(1 + d)^2``, ``d`` camera-marker distance)."""
    try:
        model = UncertaintyModel(model)
    except ValueError:
        raise MarkerException(f"unknown uncertainty model {model!r}; expected one of {[m.value for m in UncertaintyModel]}") from None
    d = float(distance_m)
    if not (math.isfinite(d) and d >= 0):
        raise MarkerException(f"distance_m must be finite and >= 0, got {distance_m}")
    if model is UncertaintyModel.CONSTANT:
        return SIGMA_CONSTANT.copy()
    if model is UncertaintyModel.QUADRATIC:
        return SIGMA_CONSTANT * (1.0 + d) ** 2
    raise MarkerException(f"the {model.value} model needs the detection itself: slam.marker_uncertainty.detection_sigmas")


def relative_pose(T_a_cam: np.ndarray, T_cam_marker: np.ndarray, T_b_marker: np.ndarray, cov_marker: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 4.7: the pose of frame ``b`` (the detected robot, carrying the marker at
    ``T_b_marker``) in frame ``a`` (the detecting robot, carrying the camera at
    ``T_a_cam``): ``T_a_b = T_a_cam T_cam_marker T_b_marker^-1``.

    With ``T_cam_marker`` perturbed on the right, ``T_cam_marker Exp(xi)``,
    ``T_a_b' = T_a_b T_b_marker Exp(xi) T_b_marker^-1 = T_a_b Exp(Ad(T_b_marker) xi)``, so
    ``Σ_ab = Ad(T_b_marker) Σ Ad(T_b_marker)^T`` in the same right-perturbation convention
    (the extrinsics ``T_a_cam`` and ``T_b_marker`` are taken as exact)."""
    T_a_cam, T_cam_marker, T_b_marker = (np.asarray(T, dtype=float) for T in (T_a_cam, T_cam_marker, T_b_marker))
    cov_marker = np.asarray(cov_marker, dtype=float)
    for name, T in (("T_a_cam", T_a_cam), ("T_cam_marker", T_cam_marker), ("T_b_marker", T_b_marker)):
        if T.shape != (4, 4):
            raise MarkerException(f"{name} must be 4x4, got shape {T.shape}")
    if cov_marker.shape != (6, 6):
        raise MarkerException(f"cov_marker must be 6x6, got shape {cov_marker.shape}")
    T_a_b = T_a_cam @ T_cam_marker @ se3_inv(T_b_marker)
    Ad = adjoint(T_b_marker)
    return T_a_b, Ad @ cov_marker @ Ad.T
