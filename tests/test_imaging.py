"""Camera image formation (sim/world/imaging.py): noise, saturation, auto exposure,
vignetting, motion blur, stereo response error, determinism."""

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest

from sim.world.imaging import GUPPY_PRO_F125B, IDEAL_IMAGING, CameraImaging, ImagingParams

W, H = 320, 240
F = (W / 2) / math.tan(math.radians(50.6) / 2)  # the LRU rig's hfov at 320 px

#: Everything off but a physical sensor behind it: single effects are switched on per test.
QUIET = replace(
    GUPPY_PRO_F125B, noise=False, auto_exposure=False, vignetting=0.0, right_gain_error=0.0, motion_blur=False
)


def _camera(params: ImagingParams, seed: int = 0, width: int = W, height: int = H) -> CameraImaging:
    return CameraImaging(params, width, height, F * width / W, np.random.default_rng(seed), flat_field=False)


def _flat(level: int, width: int = W, height: int = H) -> np.ndarray:
    return np.full((height, width), level, np.uint8)


def _texture(seed: int = 7) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (H, W), dtype=np.uint8)


def test_ideal_imaging_returns_the_inputs_bit_identically():
    left, right = _texture(1), _texture(2)
    cam = _camera(IDEAL_IMAGING)
    out_l, out_r = cam.expose(left, right, np.array([0.5, 2.0, 0.1]))
    assert out_l.dtype == np.uint8 and out_r.dtype == np.uint8
    assert np.array_equal(out_l, left) and np.array_equal(out_r, right)
    rgb = np.stack([left, right, left], axis=-1)
    out_rgb, _ = cam.expose(rgb, rgb)
    assert out_rgb.shape == rgb.shape and np.array_equal(out_rgb, rgb)
    # The full float pipeline with no effect active (blur enabled, no rate) is exact too.
    out_l, out_r = _camera(replace(IDEAL_IMAGING, motion_blur=True)).expose(left, right, None)
    assert np.array_equal(out_l, left) and np.array_equal(out_r, right)


@pytest.mark.parametrize("level", [30, 128])
def test_noise_variance_matches_shot_read_and_quantisation_noise(level):
    p = replace(QUIET, noise=True)
    width, height = 800, 600
    cam = _camera(p, width=width, height=height)
    out, _ = cam.expose(_flat(level, width, height), _flat(level, width, height))
    electrons = level / 255 * p.full_well_e
    dn_per_e = 255 / p.full_well_e
    expected_var = dn_per_e**2 * (electrons + p.read_noise_e**2) + 1 / 12
    values = out.astype(float)
    assert values.var() == pytest.approx(expected_var, rel=0.03)
    assert abs(values.mean() - level) < 0.05
    assert cam.saturated_share == 0.0


def test_saturation_after_a_dark_scene_and_dark_images_stay_dark():
    p = replace(QUIET, noise=True, auto_exposure=True, exposure_range_s=(1e-4, 4 * QUIET.nominal_exposure_s))
    cam = _camera(replace(p, right_gain_error=-0.04, max_gain=1.0))
    for _ in range(10):
        cam.expose(_flat(20), _flat(20))
    assert cam.exposure_s == p.exposure_range_s[1] > p.nominal_exposure_s and cam.gain == 1.0
    # A white scene right after: everything clips (thesis 9.3, tags "plain white"). The
    # well clips before gain, so the 4 % less responsive right camera tops out at 0.96 x 255.
    out_l, out_r = cam.expose(_flat(255), _flat(255))
    assert np.all(out_l == 255) and np.all(out_r == 245)
    assert cam.saturated_share > 0.999
    # A bright tag on a dark background: the AE brightens the background, the tag clips.
    scene = _flat(40)
    scene[100:140, 140:180] = 200
    cam = _camera(replace(p, target_mean=0.6))
    for _ in range(15):
        out, _ = cam.expose(scene, scene)
    assert np.all(out[100:140, 140:180] == 255)
    assert 0.015 < cam.saturated_share < 0.03  # the tag's 1600 of 76800 pixels
    # A dark image at the nominal exposure stays dark.
    cam = _camera(replace(QUIET, noise=True))
    out, _ = cam.expose(_flat(3), _flat(3))
    assert abs(out.mean() - 3) < 0.2 and out.max() < 15 and cam.saturated_share == 0.0


def test_auto_exposure_raises_exposure_first_then_gain_on_a_dark_scene():
    p = replace(QUIET, noise=True, auto_exposure=True, exposure_range_s=(1e-4, 2 * QUIET.nominal_exposure_s), ae_rate=0.5)
    cam = _camera(p)
    target = p.target_mean * 255
    cam.expose(_flat(40), _flat(40))
    # One step corrects half the log-brightness error: exposure x (target / 40)^0.5.
    assert cam.exposure_s == pytest.approx(p.nominal_exposure_s * (target / 40) ** 0.5, rel=0.01)
    assert cam.gain == 1.0
    exposures, gains = [cam.exposure_s], [cam.gain]
    for _ in range(25):
        out, _ = cam.expose(_flat(40), _flat(40))
        exposures.append(cam.exposure_s)
        gains.append(cam.gain)
    assert all(b >= a for a, b in itertools.pairwise(exposures))
    assert all(g == 1.0 for e, g in zip(exposures, gains) if e < p.exposure_range_s[1])
    assert exposures[-1] == p.exposure_range_s[1]
    assert gains[-1] == pytest.approx(target / 40 / 2, rel=0.02)
    assert abs(out.mean() - target) < 2


def test_auto_exposure_lowers_exposure_on_a_bright_scene():
    p = replace(QUIET, noise=True, auto_exposure=True)
    cam = _camera(p)
    for _ in range(20):
        out, _ = cam.expose(_flat(200), _flat(200))
    assert cam.exposure_s == pytest.approx(p.nominal_exposure_s * p.target_mean * 255 / 200, rel=0.02)
    assert cam.gain == 1.0
    assert abs(out.mean() - p.target_mean * 255) < 2


def test_auto_exposure_off_keeps_nominal_exposure_and_unit_gain():
    cam = _camera(replace(QUIET, noise=True))
    for _ in range(3):
        cam.expose(_flat(40), _flat(40))
    assert cam.exposure_s == QUIET.nominal_exposure_s and cam.gain == 1.0


def test_vignetting_corner_to_centre_ratio_and_cos4_shape():
    v = 0.3
    cam = _camera(replace(QUIET, vignetting=v))
    out, _ = cam.expose(_flat(200), _flat(200))
    centre = float(out[H // 2, W // 2])
    corners = [out[0, 0], out[0, -1], out[-1, 0], out[-1, -1]]
    assert len(set(corners)) == 1
    assert corners[0] / centre == pytest.approx(1 - v, abs=1 / 200)
    # Middle of the right edge: the cos^4 law's shape between centre and corner.
    xe, ye = (W - 1) / 2, (H - 1) / 2
    cos4_edge, cos4_corner = (1 / (1 + (xe**2 + y**2) / F**2) ** 2 for y in (0.5, ye))
    expected = 1 - v * (1 - cos4_edge) / (1 - cos4_corner)
    assert out[H // 2, -1] == round(200 * expected)
    # RGB: each channel alike.
    rgb, _ = cam.expose(np.stack([_flat(200)] * 3, axis=-1), np.stack([_flat(200)] * 3, axis=-1))
    assert all(np.array_equal(rgb[..., c], out) for c in range(3))


def test_flat_field_correction_evens_out_the_vignetting_at_the_corners_lower_snr():
    """A flat scene through a vignetted lens: corrected, corner and centre come out alike
    (the pipeline divides by the relative illumination); the corners keep their fewer
    electrons, so their noise is larger by about 1 / sqrt(1 - v)."""
    v = 0.3
    flat = CameraImaging(replace(QUIET, vignetting=v), W, H, F, np.random.default_rng(0), flat_field=True)
    out, _ = flat.expose(_flat(200), _flat(200))
    assert int(out.min()) >= 199 and int(out.max()) <= 201
    raw, _ = _camera(replace(QUIET, vignetting=v)).expose(_flat(200), _flat(200))
    assert raw[0, 0] / raw[H // 2, W // 2] == pytest.approx(1 - v, abs=1 / 200)
    # With the sensor's noise: the same means, the corners noisier than the centre.
    noisy = CameraImaging(replace(QUIET, vignetting=v, noise=True), W, H, F, np.random.default_rng(1), flat_field=True)
    frames = np.stack([noisy.expose(_flat(120), _flat(120))[0].astype(float) for _ in range(40)])
    centre, corner = frames[:, 100:140, 140:180], frames[:, :20, :20]
    assert corner.mean() == pytest.approx(centre.mean(), abs=1.0)
    ratio = corner.std(axis=0).mean() / centre.std(axis=0).mean()
    assert 1.05 < ratio < 1.35  # shot noise dominates: sqrt(1 / 0.7) = 1.20 at the very corner
    # Nothing to correct without vignetting: identical to the uncorrected camera.
    a = CameraImaging(QUIET, W, H, F, np.random.default_rng(2), flat_field=True).expose(_texture(3), _texture(4))
    b = CameraImaging(QUIET, W, H, F, np.random.default_rng(2), flat_field=False).expose(_texture(3), _texture(4))
    assert all(np.array_equal(x, y) for x, y in zip(a, b))


def _rise_width(profile: np.ndarray) -> float:
    """10-90 % rise distance (px) of a monotone step profile, linearly interpolated."""
    lo, hi = profile[0], profile[-1]
    frac = (profile - lo) / (hi - lo)
    x = np.arange(len(profile))
    return float(np.interp(0.9, frac, x) - np.interp(0.1, frac, x))


def test_motion_blur_turns_a_vertical_edge_into_a_ramp_of_the_rotation_length():
    p = replace(QUIET, motion_blur=True, nominal_exposure_s=0.02)
    edge = _flat(50)
    edge[:, W // 2 :] = 200
    length_px = 12.0
    omega = length_px / (F * p.nominal_exposure_s)
    cam = _camera(p)
    out, out_r = cam.expose(edge, edge, np.array([0.0, omega, 0.0]))
    assert np.array_equal(out, out_r)
    # A box of length L rises from 10 % to 90 % over 0.8 L.
    assert _rise_width(out[H // 2].astype(float)) == pytest.approx(0.8 * length_px, abs=1.0)
    assert np.ptp(out[:, W // 2 - 20 : W // 2 + 20], axis=0).max() == 0  # same ramp on every row
    # Half the rate, half the ramp.
    out, _ = cam.expose(edge, edge, np.array([0.0, omega / 2, 0.0]))
    assert _rise_width(out[H // 2].astype(float)) == pytest.approx(0.4 * length_px, abs=1.0)
    # Rotation about x smears vertically: along the edge, no change; roll is ignored.
    out, _ = cam.expose(edge, edge, np.array([omega, 0.0, omega]))
    assert np.array_equal(out, edge)
    out, _ = cam.expose(edge, edge, None)
    assert np.array_equal(out, edge)
    # Below half a pixel of motion, nothing.
    out, _ = cam.expose(edge, edge, np.array([0.0, 0.4 / (F * p.nominal_exposure_s), 0.0]))
    assert np.array_equal(out, edge)


def test_right_gain_error_scales_the_right_image():
    cam = _camera(replace(QUIET, right_gain_error=0.05))
    out_l, out_r = cam.expose(_flat(100), _flat(100))
    assert out_r.mean() / out_l.mean() == pytest.approx(1.05, abs=0.006)


def test_same_seed_same_images_different_seed_different_images():
    left, right = _texture(3), _texture(4)
    rate = np.array([0.1, 0.8, 0.0])

    def run(seed):
        cam = _camera(GUPPY_PRO_F125B, seed=seed)
        return [cam.expose(left, right, rate) for _ in range(3)]

    a, b, c = run(5), run(5), run(6)
    assert all(np.array_equal(x, y) for fa, fb in zip(a, b) for x, y in zip(fa, fb))
    assert not np.array_equal(a[0][0], c[0][0])


def test_rejects_images_of_the_wrong_shape_or_dtype():
    cam = _camera(GUPPY_PRO_F125B)
    with pytest.raises(ValueError):
        cam.expose(_flat(10, W, H + 2), _flat(10, W, H + 2))
    with pytest.raises(ValueError):
        cam.expose(_flat(10), _flat(10).astype(np.float32))
