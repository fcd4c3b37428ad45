"""Affine refinement of KLT tracks (our addition to the visual odometry of thesis 4.1.1).

Pyramidal KLT (Bouguet's, OpenCV) moves a window by a translation only. Between a
keyframe and an image 0.4-0.5 m further on, the patches of the ground ahead are
magnified and sheared by the perspective, and the translation that best aligns them is
not where the corner went: on the rendered rover sequence of tests/vo_sequences.py these
tracks err from the true projections by 0.3-0.5 px (std; more vertically, along which
the ground is foreshortened), in a pattern that follows the image position. That is noise the
VO's 0.5 px (thesis 5.1.1) absorbs, but it is structured, so it biases what is read from
fine geometry: the rig's disparity offsets (slam/stereo_offset.py) measured from such
tracks were 0.7-1 px (yaw) and 1.4-3 px (roll coefficient) on an exact rig.

:func:`refine_tracks_affine` aligns each keyframe patch with an affine warp by the
enhanced correlation coefficient (Evangelidis and Psarakis 2008, ``cv2.findTransformECC``),
started at the KLT track: the magnification and shear are then part of the model. ECC's
correlation is blind to a patch's gain and offset (auto exposure); both images are also
high-pass filtered first (less a Gaussian blur of 4 px), so that a smooth brightness
gradient across a patch (vignetting, shading) does not pull it. On the same sequence the
refined tracks err by 0.03-0.05 px (tests/test_track_refinement.py; without the
high-pass 0.033 / 0.027 px, with it 0.043 / 0.033 px: the filter costs a little on the
clean rendered images, and made no difference to the offset's estimates with vignetting
on them, nor on quickstart; kept for real images). Each patch is an iterative alignment
of its own (about 0.2 ms, ECC given only the patch's surroundings), so it is used where
few tracks matter, once per keyframe (slam.vo.StereoVO's offset measurement), not on
every frame's tracks.
"""

from __future__ import annotations

import math

import cv2
import numpy as np

_CRITERIA = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 20, 1e-3)
MIN_CORRELATION = 0.8  # ECC's normalised correlation below this: the patch did not align
MAX_SHIFT_PX = 2.0  # further than this from the KLT track: converged elsewhere
MAX_SCALE_CHANGE = 2.0  # the warp's singular values within [1 / this, this]
CROP_MARGIN_PX = 8  # the part of image1 ECC sees: the patch at the KLT track, widened by this on each side
HIGH_PASS_SIGMA_PX = 4.0  # both images less their Gaussian blur of this sigma: smooth brightness gradients removed


def _high_pass(image: np.ndarray) -> np.ndarray:
    return image - cv2.GaussianBlur(image, (0, 0), HIGH_PASS_SIGMA_PX)


def refine_tracks_affine(
    image0: np.ndarray, image1: np.ndarray, uv0: np.ndarray, uv1: np.ndarray, window_px: int = 21
) -> tuple[np.ndarray, np.ndarray]:
    """Refined positions (N, 2) in ``image1`` of the corners ``uv0`` of ``image0`` that
    KLT tracked to ``uv1``, and which were refined (N,) bool (the others keep ``uv1``):
    a ``window_px`` square patch around each corner (odd; wholly inside ``image0``),
    aligned to ``image1`` by an affine warp (ECC, module docstring), accepted when its
    correlation reaches :data:`MIN_CORRELATION`, it moved the track by at most
    :data:`MAX_SHIFT_PX` and its scale change is within :data:`MAX_SCALE_CHANGE`.
    ``image0``, ``image1``: grey, the same size."""
    if window_px < 5 or window_px % 2 == 0:
        raise ValueError(f"window_px must be odd and at least 5, got {window_px}")
    half = window_px // 2
    target, source = (_high_pass(np.asarray(im, dtype=np.float32)) for im in (image1, image0))
    h, w = source.shape
    th, tw = target.shape
    crop = window_px + 2 * CROP_MARGIN_PX
    if th < crop or tw < crop:
        raise ValueError(f"image1 ({tw}x{th}) is smaller than a patch with its margin ({crop} px)")
    out = np.array(uv1, dtype=float, copy=True)
    refined = np.zeros(len(out), dtype=bool)
    centre = np.array([half, half, 1.0])
    for i, ((x0, y0), (x1, y1)) in enumerate(zip(np.asarray(uv0, dtype=float), out)):
        if not (half <= x0 <= w - 1 - half and half <= y0 <= h - 1 - half and np.isfinite(x1) and np.isfinite(y1)):
            continue
        template = cv2.getRectSubPix(source, (window_px, window_px), (float(x0), float(y0)))
        # ECC works on the whole input image (its gradients each call): give it the patch's surroundings only
        ox = int(min(max(math.floor(x1) - half - CROP_MARGIN_PX, 0), tw - crop))
        oy = int(min(max(math.floor(y1) - half - CROP_MARGIN_PX, 0), th - crop))
        warp = np.array([[1.0, 0.0, x1 - half - ox], [0.0, 1.0, y1 - half - oy]], dtype=np.float32)
        try:
            correlation, warp = cv2.findTransformECC(template, target[oy : oy + crop, ox : ox + crop], warp, cv2.MOTION_AFFINE,
                                                     _CRITERIA, None, 1)
        except cv2.error:  # no convergence, or a flat patch
            continue
        moved = warp.astype(float) @ centre + (ox, oy)
        scale = np.linalg.svd(warp[:, :2].astype(float), compute_uv=False)
        if (correlation >= MIN_CORRELATION and np.hypot(*(moved - (x1, y1))) <= MAX_SHIFT_PX
                and 1.0 / MAX_SCALE_CHANGE <= scale[1] and scale[0] <= MAX_SCALE_CHANGE
                and 0.0 <= moved[0] <= w - 1 and 0.0 <= moved[1] <= h - 1):
            out[i], refined[i] = moved, True
    return out, refined
