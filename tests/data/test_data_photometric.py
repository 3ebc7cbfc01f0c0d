"""Colour jitter (``data.color_jitter``) changes the input image only, as its factors say: checked
against PIL's ImageEnhance and colorsys (Python's own HSV conversions), and on real samples."""
import colorsys

import numpy as np
import pytest
import torch
from PIL import Image, ImageEnhance

from usl.config import ColorJitterConfig, ConfigError, DataConfig
from usl.data import CategoryIndex, MultiViewDataset, SampleKey
from usl.data.photometric import jitter_colors
from usl.records import RecordsDataset


class _Fixed:
    """An rng whose uniform(-s, s) returns ``fraction * s``: the jitter at a chosen point of its range."""

    def __init__(self, fraction: float):
        self.fraction = fraction

    def uniform(self, low: float, high: float) -> float:
        return self.fraction * high


def _image(seed: int = 0, size: int = 6) -> torch.Tensor:
    return torch.from_numpy(np.random.default_rng(seed).uniform(0.05, 0.95, (3, size, size))).float()


def test_hue_follows_colorsys():
    image = _image()
    got = jitter_colors(image, ColorJitterConfig(hue=0.4), _Fixed(0.5))  # hue +0.2 turns
    for r, g, b, out in zip(*image.reshape(3, -1).tolist(), got.reshape(3, -1).T.tolist()):
        h, s, v = colorsys.rgb_to_hsv(r, g, b)
        assert out == pytest.approx(colorsys.hsv_to_rgb((h + 0.2) % 1.0, s, v), abs=1e-5)


def _pil_case(seed: int = 3) -> tuple[np.ndarray, torch.Tensor]:
    """An 8-bit image with unequal channel means (so the luma mean, the RGB mean and 0.5 differ by
    tens of levels), and the same as a float tensor."""
    rng = np.random.default_rng(seed)
    pixels = (rng.integers(0, 256, (16, 16, 3)) * np.array([1.0, 0.3, 0.1])).astype(np.uint8)
    return pixels, torch.from_numpy(pixels).permute(2, 0, 1).float() / 255


def _as_tensor(image: Image.Image) -> torch.Tensor:
    return torch.from_numpy(np.asarray(image).astype(np.float32) / 255)


@pytest.mark.parametrize("name, enhancer", [("brightness", ImageEnhance.Brightness), ("contrast", ImageEnhance.Contrast),
                                            ("saturation", ImageEnhance.Color)])
@pytest.mark.parametrize("fraction", [-1.0, 0.6])
def test_brightness_contrast_and_saturation_are_pils_image_enhance(name, enhancer, fraction):
    """PIL's enhancer at the same factor (PIL rounds its mean grey and every result to 8 bits)."""
    pixels, image = _pil_case()
    got = jitter_colors(image, ColorJitterConfig(**{name: 0.5}), _Fixed(fraction))
    want = _as_tensor(enhancer(Image.fromarray(pixels)).enhance(1.0 + 0.5 * fraction))
    torch.testing.assert_close(got.permute(1, 2, 0), want, atol=1.1 / 255, rtol=0)


def test_the_three_enhancements_chain_in_order():
    """Brightness, then contrast on the brightened image, then saturation on that: PIL's enhancers
    chained (each rounds to 8 bits, so the tolerance grows to four levels)."""
    pixels, image = _pil_case(4)
    got = jitter_colors(image, ColorJitterConfig(brightness=0.4, contrast=0.4, saturation=0.4), _Fixed(0.5))
    want = Image.fromarray(pixels)
    for enhancer in (ImageEnhance.Brightness, ImageEnhance.Contrast, ImageEnhance.Color):
        want = enhancer(want).enhance(1.2)
    torch.testing.assert_close(got.permute(1, 2, 0), _as_tensor(want), atol=4.0 / 255, rtol=0)


def test_no_jitter_is_the_identity_and_pure_red_turns_green():
    image = _image(2)
    torch.testing.assert_close(jitter_colors(image, ColorJitterConfig(), np.random.default_rng(0)), image, atol=1e-6, rtol=0)
    red = torch.zeros(3, 2, 2)
    red[0] = 1.0
    green = jitter_colors(red, ColorJitterConfig(hue=1 / 3), _Fixed(1.0))
    torch.testing.assert_close(green, red.roll(1, dims=0), atol=1e-6, rtol=0)


def _dataset(root, jitter: ColorJitterConfig) -> MultiViewDataset:
    records = RecordsDataset(root, "train")
    cfg = DataConfig(root=str(root), num_views=4, num_workers=0, color_jitter=jitter)
    return MultiViewDataset(records, cfg, CategoryIndex(records.categories), seed=3)


def test_jittered_sample_changes_only_its_input_image(synthetic_root):
    plain = _dataset(synthetic_root, ColorJitterConfig())
    jittered = _dataset(synthetic_root, ColorJitterConfig(brightness=0.3, contrast=0.3, saturation=0.3, hue=0.5))
    for index in (0, 5):
        a, b = plain[SampleKey(index, 1)], jittered[SampleKey(index, 1)]
        assert a.seed == b.seed and [v.view_id for v in a.views] == [v.view_id for v in b.views]
        assert not torch.allclose(a.frame.image, b.frame.image, atol=1e-3)
        assert b.frame.image.min() >= 0 and b.frame.image.max() <= 1
        for name in ("masks", "boxes", "K", "cam_to_world"):
            assert torch.equal(getattr(a.frame, name), getattr(b.frame, name))
        for view_a, view_b in zip(a.views, b.views):
            assert torch.equal(view_a.masks, view_b.masks) and torch.equal(view_a.K, view_b.K)
        torch.testing.assert_close(jittered[SampleKey(index, 1)].frame.image, b.frame.image, atol=0, rtol=0)  # reproducible


@pytest.mark.parametrize("key, value", [("brightness", 1.5), ("contrast", 1.01), ("saturation", -0.1), ("hue", 0.6)])
def test_jitter_outside_its_range_is_an_error(key, value):
    with pytest.raises(ConfigError, match=f"data.color_jitter.{key}"):
        ColorJitterConfig(**{key: value})
