"""The retina front end (hippomap.retina): light adaptation, centre-surround, contrast gain
control — and what they buy the visual memory: recognition under lighting change."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hippomap.config import VisualConfig
from hippomap.errors import InputError
from hippomap.retina import Retina, imadjust
from hippomap.sim.scenes import shapes_scene
from hippomap.visual_memory import VisualMemory, prepare_image


def relight(img: np.ndarray, gain: float, gradient: float = 0.0, gamma: float = 1.0) -> np.ndarray:
    """Change the light: a gamma (camera response / exposure curve), a gain, and a
    left-to-right ramp of relative size ``gradient`` (light falling across the view)."""
    h, w = img.shape
    ramp = 1.0 + gradient * (np.arange(w) / (w - 1) - 0.5)
    x = 255.0 * (img.astype(np.float64) / 255.0) ** gamma
    return np.clip(x * gain * ramp[None, :], 0, 255).round().astype(np.uint8)


def test_uniform_light_gives_no_response():
    """Centre and surround cancel on a uniform field: every ganglion cell sits at rest (128)."""
    for level in (10, 128, 250):
        out = Retina(VisualConfig())(np.full((120, 160), level, np.uint8))
        assert np.all(np.abs(out.astype(int) - 128) <= 1)


def test_on_and_off_responses_have_opposite_signs():
    """A bright spot excites ON-centre responses (above rest), a dark spot the OFF side (below)."""
    img = np.full((101, 101), 100, np.uint8)
    bright, dark = img.copy(), img.copy()
    bright[45:56, 45:56] = 200
    dark[45:56, 45:56] = 20
    r = Retina(VisualConfig())
    assert r(bright)[50, 50] > 160
    assert r(dark)[50, 50] < 96


@settings(max_examples=25, deadline=None)
@given(gain=st.floats(0.4, 0.95), seed=st.integers(0, 10_000))
def test_response_is_invariant_to_the_light_level(gain, seed):
    """A global change of illumination (I -> g I, unsaturated) barely moves the ganglion image,
    while the raw grey levels move by up to (1 - g) * 255."""
    img = (shapes_scene(seed).astype(np.float64) * 0.8 + 20).astype(np.uint8)  # keep dark levels above 0
    dim = relight(img, gain)
    cfg = VisualConfig()
    r = Retina(cfg)
    a, b = r(img).astype(float), r(dim).astype(float)
    change = np.abs(a - b).mean()
    raw_change = np.abs(img.astype(float) - dim.astype(float)).mean()
    assert change < 6.0
    assert change < 0.5 * raw_change or raw_change < 6.0


def test_retina_output_is_uint8_of_the_same_shape_and_none_mode_is_imadjust():
    img = shapes_scene(3)
    out = Retina(VisualConfig())(img)
    assert out.dtype == np.uint8 and out.shape == img.shape
    cfg = VisualConfig(retina_mode="none")
    assert np.array_equal(Retina(cfg)(img), imadjust(img, cfg.contrast_clip))
    work, _ = prepare_image(img, cfg)
    assert np.array_equal(work, imadjust(img, cfg.contrast_clip))


def test_bad_inputs_raise():
    r = Retina(VisualConfig())
    with pytest.raises(InputError):
        r.ganglion_response(np.zeros((10, 10), np.float32))
    with pytest.raises(InputError):
        r.ganglion_response(np.zeros((0, 10), np.uint8))
    with pytest.raises(InputError):
        Retina(VisualConfig(retina_center_sigma=5.0, retina_surround_sigma=4.0))


@pytest.mark.parametrize("gain,gradient,gamma", [(0.6, 0.8, 1.0), (1.0, 0.0, 0.5), (0.7, 1.0, 1.6)])
def test_recognition_survives_a_lighting_change_that_defeats_grey_level_cells(gain, gradient, gamma):
    """Frames learned in one light, queried under another (darker with light falling off
    across the view, another exposure curve, both): the retina front end recognises them;
    sensory cells tuned to stretched grey levels (the paper's input, retina_mode='none')
    mostly do not — imadjust undoes a global gain only."""
    scenes = [shapes_scene(100 + s) for s in range(10)]
    hits = {}
    for mode in ("dog", "none"):
        mem = VisualMemory(VisualConfig(retina_mode=mode, repeat_accept=None))  # the front ends alone
        ids = [mem.learn(s) for s in scenes]
        ok = wrong = 0
        for fid, s in zip(ids, scenes):
            rec = mem.recognise(relight(s, gain, gradient, gamma))
            ok += int(rec.frame_id == fid)
            wrong += int(rec.accepted and rec.frame_id != fid)
        hits[mode] = ok
        assert wrong == 0
    assert hits["dog"] >= 9
    assert hits["dog"] >= hits["none"] + 4


# ---------------------------------------------------------------------------------------
# V1 orientation channels
# ---------------------------------------------------------------------------------------
def _edge(angle_deg: float, size: int = 81, lo: int = 60, hi: int = 180) -> np.ndarray:
    """A straight luminance edge through the image centre, oriented at ``angle_deg`` (0 = horizontal)."""
    yy, xx = np.mgrid[:size, :size].astype(np.float64) - size // 2
    th = np.deg2rad(angle_deg)
    side = -np.sin(th) * xx + np.cos(th) * yy  # signed distance across the edge
    return np.where(side > 1e-9, hi, lo).astype(np.uint8)


@pytest.mark.parametrize("n", [4, 8])
def test_orientation_channel_prefers_its_edge_and_ignores_the_orthogonal_one(n):
    """Channel i responds at the centre of an edge oriented at i * 180 / n degrees, and that channel
    stays near rest for the orthogonal edge; on a uniform field every channel is silent."""
    r = Retina(VisualConfig(v1_orientations=n))
    for i in range(n):
        angle = 180.0 * i / n
        on = r.orientation_channels(_edge(angle))[40, 40].astype(int)
        ortho = r.orientation_channels(_edge(angle + 90.0))[40, 40].astype(int)
        assert int(np.argmax(on)) == i, (angle, on)
        assert on[i] > 150
        assert ortho[i] < 0.15 * on[i], (angle, on[i], ortho[i])
    flat = r.orientation_channels(np.full((60, 60), 120, np.uint8))
    assert flat.max() <= 1


@settings(max_examples=20, deadline=None)
@given(gain=st.floats(0.4, 0.95), gamma=st.floats(0.6, 1.6), seed=st.integers(0, 10_000))
def test_orientation_channels_are_invariant_to_brightness_and_contrast(gain, gamma, seed):
    """A global gain and an exposure curve (gamma, i.e. a contrast change of the light-adapted image)
    barely move the normalised orientation responses, while the grey levels move a lot."""
    img = (shapes_scene(seed).astype(np.float64) * 0.8 + 20).astype(np.uint8)
    other = relight(img, gain, 0.0, gamma)
    r = Retina(VisualConfig(v1_orientations=4))
    a = r.orientation_channels(img).astype(float)
    b = r.orientation_channels(other).astype(float)
    change = np.abs(a - b).mean()
    raw_change = np.abs(img.astype(float) - other.astype(float)).mean()
    assert change < 8.0, change
    assert change < 0.5 * raw_change or raw_change < 8.0


def test_sensory_image_stacks_the_channels_and_bad_inputs_raise():
    img = shapes_scene(5)
    off = Retina(VisualConfig(v1_orientations=0)).sensory_image(img)
    assert off.shape == img.shape
    cfg = VisualConfig(v1_orientations=4)
    on = Retina(cfg).sensory_image(img)
    assert on.shape == img.shape + (5,) and on.dtype == np.uint8
    assert np.array_equal(on[..., 0], Retina(cfg)(img))
    assert Retina(VisualConfig(v1_orientations=4, retina_mode="none")).sensory_image(img).ndim == 2
    with pytest.raises(InputError, match="v1_orientations"):
        Retina(VisualConfig(v1_orientations=0)).orientation_channels(img)
    with pytest.raises(InputError, match="gray image"):
        Retina(cfg).orientation_channels(img.astype(np.float32))


def _reference_ganglion(cfg: VisualConfig, gray: np.ndarray) -> np.ndarray:
    """Retina.ganglion_response as first written: every step into a fresh array."""
    from hippomap.retina import _LOG_LUT, _gauss

    L = _LOG_LUT[gray]
    c = _gauss(L, cfg.retina_center_sigma) - _gauss(L, cfg.retina_surround_sigma)
    energy = _gauss(c * c, cfg.retina_norm_sigma)
    C = float(np.sqrt(np.median(energy[::4, ::4])))
    k = cfg.retina_semisaturation * C + 1e-3
    return c / cv2.sqrt(energy + k * k)


def _reference_imadjust(gray: np.ndarray, clip: float) -> np.ndarray:
    hist = np.bincount(gray.ravel(), minlength=256).astype(np.float64)
    cdf = np.cumsum(hist) / hist.sum()
    lo = int(np.searchsorted(cdf, clip, side="left"))
    hi = int(np.searchsorted(cdf, 1.0 - clip, side="left"))
    if hi <= lo:
        return gray.copy()
    lut = np.clip((np.arange(256) - lo) * (255.0 / (hi - lo)), 0, 255).round().astype(np.uint8)
    return lut[gray]


@pytest.mark.parametrize(
    "override",
    [{}, {"retina_center_sigma": 4.5, "retina_surround_sigma": 9.0, "retina_norm_sigma": 3.0}],
    ids=["default", "wide-fields"],
)
def test_fast_retina_equals_the_reference_bit_for_bit(override):
    """In-place ganglion response, OpenCV histogram of imadjust and the retina kept per config give the
    same numbers as the plain computations."""
    cfg = VisualConfig(**override)
    rng = np.random.default_rng(4)
    imgs = [shapes_scene(s) for s in range(6)] + [
        rng.integers(0, 256, (int(rng.integers(120, 300)), int(rng.integers(100, 400))), dtype=np.uint8)
        for _ in range(6)
    ]
    imgs.append(np.full((90, 120), 7, np.uint8))  # one grey level: imadjust keeps the image
    for img in imgs:
        r = Retina(cfg).ganglion_response(img)
        assert r.dtype == np.float32 and np.array_equal(r, _reference_ganglion(cfg, img))
        for clip in (0.0, 0.01, 0.2):
            assert np.array_equal(imadjust(img, clip), _reference_imadjust(img, clip))
        first, again = prepare_image(img, cfg), prepare_image(img, cfg)  # the second reuses the retina
        assert np.array_equal(first[0], again[0]) and first[1] == again[1]
        other = prepare_image(img, VisualConfig(**override))  # an equal config, another object
        assert np.array_equal(first[0], other[0])
