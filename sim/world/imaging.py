"""Image formation of a machine-vision stereo camera: from the renderer's ideal grey
images to what the camera delivers.

The renderer (:class:`~sim.world.sensors.StereoRenderer`) produces noise-free 8-bit
images with no notion of exposure. The thesis's cameras do not (6.2.1: "the conversion
of the photons reaching the camera sensor into digital images is subject to noise,
discretization effects, and possible over- or underexposures"; 9.3: in direct sunlight
on Mt. Etna the AprilTags were overexposed until whole tags appeared plain white).
:class:`CameraImaging` models that for one hardware-synchronised stereo pair of the
LRU rovers' Allied Vision Guppy PRO F-125B (thesis 7.1: Sony ICX445 interline CCD,
global shutter, greyscale, 8-bit output), in this order:

1. radiance = image / 255, linear (MuJoCo renders without gamma); 255 fills the well at
   the nominal exposure.
2. vignetting: a fixed map, cos^4-law shaped, 1 at the principal point and
   ``1 - vignetting`` at the image corners.
3. motion blur from the camera's rotation during the exposure (a line kernel).
4. signal in electrons, scaled by exposure / nominal exposure, with photon shot noise
   and read noise as in the EMVA 1288 linear camera model (EMVA Standard 1288,
   Release 3.1, sec. 2: signal in electrons, shot-noise variance = mean number of
   electrons, signal-independent temporal dark noise), clipped at the full well.
5. digital level = electrons / full well x gain x 255 (right camera x its response
   error), clipped and rounded to 8 bit.
6. auto exposure: from the left output's mean, the exposure and gain of the next frame.

With ``flat_field`` the camera pipeline divides the signal by the vignetting map before
step 5, as a calibrated pipeline's flat-field (shading) correction does with the lens's
relative illumination measured in the lab (at the camera's internal precision, before
the 8-bit output): the corners come out as bright as the centre, with their lower
signal-to-noise ratio, and saturate where the sensor did. The map is the true one (a
flat field measured against an integrating sphere is good to about a per cent; no
residual is modelled). Without it, brightness falls towards the corners, which a
tracker assuming brightness constancy (KLT, :mod:`slam.vo`) reads as motion: on Etna it
was the largest single cause of the graph's overconfidence (docs/slam.md, "Which
errors").

The lens distortion left after rectification is a calibration error
(:mod:`sim.world.calibration_errors`), applied by the renderer before this. Not
modelled: dark current and hot pixels (negligible at
exposures of milliseconds), fixed-pattern noise (DSNU/PRNU) apart from the right
camera's overall response error, blooming and vertical smear of the CCD (a saturated
pixel does not spill into its neighbours or its column), rolling shutter (the Guppy is
a global-shutter CCD), defocus, and the camera's internal resolution (it processes
12 bit, "the most significant 12-bit value from the digitizer" in the Guppy PRO
Technical Manual's LUT section, and delivers 8; a 12-bit step is 1/16 of an output
level, so quantisation is modelled at the 8-bit output only, and ``ImagingParams`` has
no ADC field).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.special import ndtri

from sim.scenario import CameraRealism

__all__ = ["GUPPY_PRO_F125B", "IDEAL_IMAGING", "CameraImaging", "ImagingParams", "imaging_params"]


@dataclass(frozen=True)
class ImagingParams:
    """Parameters of the image formation (see the module docstring for the model)."""

    noise: bool  # photon shot noise and read noise
    full_well_e: float  # electrons at saturation (EMVA 1288 saturation capacity)
    read_noise_e: float  # read noise, electrons rms (EMVA 1288 temporal dark noise)
    auto_exposure: bool  # False: exposure stays at nominal_exposure_s, gain 1
    nominal_exposure_s: float  # exposure at which rendered value 255 == full well
    exposure_range_s: tuple[float, float]  # (min, max) exposure the AE may set
    max_gain: float  # analog gain (>= 1) the AE may add once exposure is at its maximum
    target_mean: float  # AE aims the mean 8-bit level of the left image at this fraction of 255
    ae_rate: float  # 0..1: fraction of the log-brightness error the AE corrects per frame
    vignetting: float  # relative illumination lost at the image corner, 0 = none
    right_gain_error: float  # right camera's fixed relative response error, 0 = none
    motion_blur: bool  # blur from camera rotation during the exposure
    source: str = ""  # where the defaults come from


#: Everything off: :meth:`CameraImaging.expose` returns its inputs unchanged.
IDEAL_IMAGING = ImagingParams(
    noise=False,
    full_well_e=1.0,
    read_noise_e=0.0,
    auto_exposure=False,
    nominal_exposure_s=1.0,
    exposure_range_s=(1.0, 1.0),
    max_gain=1.0,
    target_mean=0.5,
    ae_rate=0.0,
    vignetting=0.0,
    right_gain_error=0.0,
    motion_blur=False,
    source="ideal camera: the rendered images as they are",
)

#: Allied Vision Guppy PRO F-125B, the LRU rovers' stereo cameras (thesis 7.1).
GUPPY_PRO_F125B = ImagingParams(
    noise=True,
    # Saturation capacity of the ICX445. EMVA 1288 sheets of cameras built on it
    # (Allied Vision Mako G-125B, Point Grey/FLIR Blackfly 13S2M) give roughly 8-10 ke-:
    # quoted from memory, not re-checked. Cross-check that was read: the sister
    # interline CCD ICX625 (3.45 um pixels, 0.85 x the ICX445's pixel area) has 5.9 ke-
    # (Point Grey GS3-PGE-50S5M) and 7.0 ke- (Basler piA2400-17gm) in those cameras'
    # EMVA 1288 sheets, as tabulated in mengineer.hatenablog.com/entry/2016/05/02/212822.
    # A round 8 ke-, uncertain by some 20 %.
    full_well_e=8000.0,
    # Temporal dark noise: the same ICX625 sheets give 8.3 e- and 13 e- (read, as
    # above); ICX445 sheets about 9-10 e- (quoted from memory, not re-checked). A round 10 e-.
    read_noise_e=10.0,
    auto_exposure=True,
    # The renderer's lighting is not radiometric, so the nominal exposure only fixes the
    # time scale (the auto exposure brings any scene to the same level and noise): a
    # rendered 255 fills the well at 1 ms, the order of a machine-vision camera's
    # exposure in direct sunlight. A modelling choice, not a data-sheet value; it sets the
    # motion blur: at 5 ms the lunar scenes exposed for 25-40 ms, and the head scans
    # (18 deg/s) smeared the 16-px mast tags 3 m away past decoding (one robot of
    # tests/test_slam_run.py's encounter detected none).
    nominal_exposure_s=1e-3,
    # Lower end: the Guppy PRO's shortest shutter is some tens of us (quoted from
    # memory, not re-checked); the AE never goes near it on rendered scenes. Upper end:
    # the camera's default shutter time, 40 ms (Guppy PRO Technical Manual V4.1.2,
    # "Video formats, modes and bandwidth": "default shutter time of 40 ms"); the LRU's
    # own auto-shutter limit is not known.
    exposure_range_s=(50e-6, 40e-3),
    # Analog gain 0 ... 24.4 dB on the Guppy PRO CCD models (Guppy PRO Technical Manual
    # V4.1.2, "Manual gain", gain range table): 10**(24.4/20) = 16.6.
    max_gain=10.0 ** (24.4 / 20.0),
    # The Guppy PRO's AE target grey level is settable within 50 ... 205 of 255 (same
    # manual, note to the gain table); mid-grey is a choice within that range.
    target_mean=0.5,
    # AE speed: a modelling choice that settles within a few frames (0.5 halves the
    # log-brightness error per frame); the camera's AE loop speed is not documented there.
    ae_rate=0.5,
    # Relative illumination at the corner of a 50.6 deg hfov lens on the 1/3" sensor: a
    # bare cos^4 law at the 31 deg corner field angle gives 54 %; lens designs recover
    # part of it. 70 % is an assumed value: the LRU's lenses are not characterised.
    vignetting=0.3,
    # Unit-to-unit sensitivity spread of two cameras of one model: an assumed 2 %
    # (magnitude of a per-robot draw; no data sheet states it).
    right_gain_error=0.02,
    motion_blur=True,
    source=(
        "Allied Vision Guppy PRO F-125B / Sony ICX445 (thesis 7.1); Guppy PRO Technical Manual V4.1.2 "
        "(gain range, AE target range, default shutter); sensor noise and full well from EMVA 1288 "
        "data of ICX445/ICX625 cameras, partly quoted from memory (see comments)"
    ),
)


def _unit_normal_quantiles(bits: int) -> np.ndarray:
    """The 2^bits equiprobable quantiles of the standard normal distribution, float32,
    rescaled to unit variance (with 16 bits the tails end at 4.3 sigma)."""
    q = ndtri((np.arange(2**bits) + 0.5) / 2**bits)
    return (q / q.std()).astype(np.float32)


#: A lookup of 16 random bits in this table draws a Gaussian deviate about 3x faster
#: than numpy's ziggurat sampler (which takes ~1 ms per 320x240 image on a 2-core VM).
_NORMAL_QUANTILES = _unit_normal_quantiles(16)


def _standard_normal(rng: np.random.Generator, out: np.ndarray) -> np.ndarray:
    """Fill ``out`` (float32) with standard normal deviates by quantile lookup
    (:data:`_NORMAL_QUANTILES`)."""
    return np.take(_NORMAL_QUANTILES, rng.integers(0, 2**16, out.shape, dtype=np.uint16), out=out)


def _vignetting_map(width: int, height: int, focal_px: float, vignetting: float) -> np.ndarray:
    """Relative illumination per pixel, float32 (H, W): the cos^4 law's shape in terms of
    the field angle θ (cos^4 θ = 1 / (1 + r^2)^2, r the distance from the principal
    point in focal lengths; principal point at the image centre, as
    :attr:`~sim.world.camera_rig.StereoRig.intrinsics`), rescaled linearly so the
    centre gets 1 and the corner pixels exactly ``1 - vignetting``."""
    x = (np.arange(width) - (width - 1) / 2) / focal_px
    y = (np.arange(height) - (height - 1) / 2) / focal_px
    r2 = y[:, None] ** 2 + x[None, :] ** 2
    cos4 = 1.0 / (1.0 + r2) ** 2
    cos4_corner = cos4[0, 0]
    return (1.0 - vignetting * (1.0 - cos4) / (1.0 - cos4_corner)).astype(np.float32)


def _blur_kernel(dx: float, dy: float) -> np.ndarray:
    """Normalised line kernel, float32, odd square size, centred: the path of an image
    point that moves by (dx, dy) px during the exposure, sampled densely along the
    segment and spread bilinearly onto the pixel grid (so sub-pixel lengths and
    oblique directions come out smooth). Symmetric about its centre, so the sign of
    the motion does not matter and correlation (cv2.filter2D) equals convolution."""
    length = math.hypot(dx, dy)
    half = math.ceil(length / 2) + 1
    size = 2 * half + 1
    s = np.linspace(-0.5, 0.5, max(2, math.ceil(4 * length) + 1))
    xs = half + s * dx
    ys = half + s * dy
    x0 = np.floor(xs).astype(np.intp)
    y0 = np.floor(ys).astype(np.intp)
    fx = xs - x0
    fy = ys - y0
    corner = y0 * size + x0
    cells = np.concatenate([corner, corner + 1, corner + size, corner + size + 1])
    weights = np.concatenate([(1 - fx) * (1 - fy), fx * (1 - fy), (1 - fx) * fy, fx * fy])
    kernel = np.bincount(cells, weights, minlength=size * size).reshape(size, size)
    # Drop empty outer rows and columns, as many on each side so the kernel stays
    # centred: a horizontal or vertical line becomes a 1- or 2-pixel-wide strip, which
    # cv2.filter2D applies some 30x faster than the full square.
    used = kernel > 1e-9 * kernel.max()
    rows = np.flatnonzero(used.any(axis=1))
    cols = np.flatnonzero(used.any(axis=0))
    r = min(rows[0], size - 1 - rows[-1])
    c = min(cols[0], size - 1 - cols[-1])
    kernel = kernel[r : size - r, c : size - c]
    return (kernel / kernel.sum()).astype(np.float32)


def _motion_blur(radiance: np.ndarray, angular_rate_cam: np.ndarray, focal_px: float, exposure_s: float, out: np.ndarray) -> np.ndarray:
    """Blur from the camera's rotation during the exposure (global shutter: the whole
    frame integrates over the same interval), written into ``out``. A rotation at ω_y
    about the camera's y (down) axis moves the image by about f ω_y t_exp px
    horizontally, one at ω_x about x by about f ω_x t_exp px vertically; the kernel is
    the same over the whole image (the motion grows by (1 + (x/f)^2) towards the edges,
    ignored). Roll about the optical axis (ω_z) is ignored: it blurs by at most
    ω_z t_exp times the distance from the centre, and the rovers' and ARDEA's roll
    rates are small. Translation blur is negligible: at rover speeds (0.3 m/s) over a
    few ms the camera moves ~1 mm, well below a pixel at the depths that are matched.
    Below half a pixel of motion ``radiance`` is returned as it is."""
    w = np.asarray(angular_rate_cam, dtype=float)
    dx = focal_px * w[1] * exposure_s
    dy = focal_px * w[0] * exposure_s
    if math.hypot(dx, dy) < 0.5:
        return radiance
    return cv2.filter2D(radiance, -1, _blur_kernel(dx, dy), dst=out, borderType=cv2.BORDER_REPLICATE)


def _electrons(
    radiance: np.ndarray, params: ImagingParams, exposure_s: float, rng: np.random.Generator, scratch: list[np.ndarray]
) -> np.ndarray:
    """Signal in electrons, float32, computed in place of ``radiance`` and clipped to
    [0, full well] (saturation; thesis 6.2.1 "over- or underexposures", 9.3). The mean
    is radiance x full well x exposure / nominal exposure. With ``noise``: photon shot
    noise (Poisson, variance = mean electrons) and read noise (EMVA 1288 temporal dark
    noise, ``read_noise_e`` rms), drawn together as one Gaussian of variance
    mean + read_noise^2 (:func:`_standard_normal`; two ``scratch`` buffers of the
    image's shape): the Poisson distribution at the tens to thousands of electrons that
    matter here is Gaussian to well within the accuracy of the parameters."""
    electrons = np.multiply(radiance, np.float32(params.full_well_e * exposure_s / params.nominal_exposure_s), out=radiance)
    if params.noise:
        sigma, deviate = scratch
        np.sqrt(np.add(electrons, np.float32(params.read_noise_e**2), out=sigma), out=sigma)
        electrons += np.multiply(sigma, _standard_normal(rng, deviate), out=deviate)
    return np.clip(electrons, 0.0, params.full_well_e, out=electrons)


def _digitise(electrons: np.ndarray, full_well_e: float, gain: float) -> np.ndarray:
    """8-bit output (thesis 6.2.1 "discretization"): electrons / full well x gain x 255,
    clipped to 0 ... 255 and rounded to the nearest level (cv2.convertScaleAbs: scale,
    round, saturate; the input is non-negative, so its absolute value is a no-op)."""
    return cv2.convertScaleAbs(electrons, alpha=255.0 * gain / full_well_e)


def _auto_exposure(mean_level: float, exposure_s: float, gain: float, params: ImagingParams) -> tuple[float, float]:
    """Exposure and gain for the next frame from the mean 8-bit level of this frame's
    left image: the brightness factor k = target / mean is applied in the log domain at
    ``ae_rate`` per frame (exposure x gain times k**ae_rate), exposure first (within
    ``exposure_range_s``, the less noisy way to brighten), the remainder as gain
    (1 ... ``max_gain``). A mean raised by clipped pixels still lowers the exposure,
    only by less than the true overexposure would call for; scenes whose mean is fine
    but whose bright parts clip stay clipped, as on Etna (thesis 9.3)."""
    k = params.target_mean * 255.0 / max(mean_level, 1.0)
    product = exposure_s * gain * k**params.ae_rate
    lo, hi = params.exposure_range_s
    new_exposure = min(max(product, lo), hi)
    new_gain = min(max(product / new_exposure, 1.0), params.max_gain)
    return new_exposure, new_gain


class CameraImaging:
    """Image formation of one stereo rig (both cameras share exposure and gain, as a
    hardware-synchronised pair does). See the module docstring for the model; thesis
    6.2.1 (noise, discretisation, exposure), 7.1 (cameras), 9.3 (overexposure).
    ``flat_field``: the pipeline corrects the vignetting (module docstring)."""

    def __init__(self, params: ImagingParams, width: int, height: int, focal_px: float, rng: np.random.Generator, *, flat_field: bool):
        lo, hi = params.exposure_range_s
        if not 0 < lo <= hi:
            raise ValueError(f"exposure_range_s must be 0 < min <= max, got {params.exposure_range_s}")
        if params.max_gain < 1.0 or not 0.0 <= params.ae_rate <= 1.0 or not 0.0 <= params.vignetting < 1.0:
            raise ValueError("need max_gain >= 1, 0 <= ae_rate <= 1 and 0 <= vignetting < 1")
        self.params = params
        self.width = width
        self.height = height
        self.focal_px = focal_px
        self._rng = rng
        self._exposure_s = params.nominal_exposure_s
        self._gain = 1.0
        self._saturated_share = 0.0
        # Radiance scale per pixel: 1/255 x relative illumination.
        relative_illumination = _vignetting_map(width, height, focal_px, params.vignetting)
        self._scale = relative_illumination / np.float32(255.0)
        # flat-field correction: the inverse of the relative illumination (None: none, or nothing to correct)
        self._flat_field = np.float32(1.0) / relative_illumination if flat_field and params.vignetting else None
        self._identity = not (
            params.noise or params.auto_exposure or params.motion_blur or params.vignetting or params.right_gain_error
        )
        # float32 work buffers per image shape (grey or RGB): radiance, blurred radiance
        # and two noise scratch buffers. Reusing them avoids allocating ~1 MB per image,
        # which costs more than the arithmetic.
        self._work: dict[tuple[int, ...], tuple[np.ndarray, ...]] = {}

    @property
    def exposure_s(self) -> float:
        """Exposure of the next frame."""
        return self._exposure_s

    @property
    def gain(self) -> float:
        """Analog gain (linear, >= 1) of the next frame."""
        return self._gain

    @property
    def saturated_share(self) -> float:
        """Share of the last left image's pixels at full well (before gain); 0 before the first frame."""
        return self._saturated_share

    def expose(self, left: np.ndarray, right: np.ndarray, angular_rate_cam: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Turn a rendered pair into the camera's pair.

        ``left``/``right``: uint8 (H, W) grey, or (H, W, 3) RGB (each channel alike).
        ``angular_rate_cam``: (3,) rad/s of the camera in OpenCV camera axes (x right,
        y down, z forward), or None (no blur). Returns uint8 images of the same shape;
        with :data:`IDEAL_IMAGING` the inputs themselves. Afterwards, with auto
        exposure, :attr:`exposure_s` and :attr:`gain` are those of the next frame.
        """
        if left.shape != right.shape or left.shape[:2] != (self.height, self.width) or left.ndim not in (2, 3):
            raise ValueError(f"expected two images of shape ({self.height}, {self.width}[, 3]), got {left.shape} and {right.shape}")
        if left.dtype != np.uint8 or right.dtype != np.uint8:
            raise ValueError(f"expected uint8 images, got {left.dtype} and {right.dtype}")
        p = self.params
        if self._identity:  # 255 is the full well at the nominal exposure
            self._saturated_share = float(np.count_nonzero(left == 255)) / left.size
            return left, right
        scale = self._scale if left.ndim == 2 else self._scale[:, :, None]
        flat = self._flat_field if self._flat_field is None or left.ndim == 2 else self._flat_field[:, :, None]
        if left.shape not in self._work:
            self._work[left.shape] = tuple(np.empty(left.shape, np.float32) for _ in range(4))
        radiance_buf, blurred_buf, *scratch = self._work[left.shape]
        out = []
        for i, image in enumerate((left, right)):
            radiance = np.multiply(image, scale, out=radiance_buf)
            if p.motion_blur and angular_rate_cam is not None:
                radiance = _motion_blur(radiance, angular_rate_cam, self.focal_px, self._exposure_s, blurred_buf)
            electrons = _electrons(radiance, p, self._exposure_s, self._rng, scratch)
            if i == 0:
                self._saturated_share = float(np.count_nonzero(electrons >= p.full_well_e)) / electrons.size
            if flat is not None:
                electrons *= flat
            response = 1.0 if i == 0 else 1.0 + p.right_gain_error
            out.append(_digitise(electrons, p.full_well_e, self._gain * response))
        if p.auto_exposure:
            self._exposure_s, self._gain = _auto_exposure(float(out[0].mean()), self._exposure_s, self._gain, p)
        return out[0], out[1]


def imaging_params(cfg: CameraRealism, rng: np.random.Generator) -> ImagingParams | None:
    """The scenario's ``realism.camera`` applied to :data:`GUPPY_PRO_F125B`, the right
    camera's response error drawn from ``rng``; None when every imperfection is off
    (the rendered images are used as they are)."""
    if not (cfg.noise or cfg.auto_exposure or cfg.vignetting or cfg.motion_blur or cfg.right_gain_error_std):
        return None
    return replace(
        GUPPY_PRO_F125B,
        noise=cfg.noise,
        auto_exposure=cfg.auto_exposure,
        vignetting=cfg.vignetting,
        motion_blur=cfg.motion_blur,
        right_gain_error=float(rng.standard_normal()) * cfg.right_gain_error_std,
    )
