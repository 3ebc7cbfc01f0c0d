"""Photometric jitter of a training sample's input image (``data.color_jitter``).

Only the input image changes: every target of the loss (masks, boxes, poses, intrinsics) is
independent of colour, so a jittered sample is as exact as the original. Real captures vary in
exposure and white balance, which a network trained on few scenes has not seen; on Scene-Shapes,
which draws every object's, floor's and sky's colour at random already, it measured no gain
(README, "Learning shape on a CPU").

The four changes are PIL's ``ImageEnhance`` (and torchvision's ``ColorJitter``) definitions, in a
fixed order (torchvision permutes it per sample): brightness blends with black, contrast with the
image's mean grey, saturation with the image's grey version (ITU-R 601 luma), then the HSV hue
turns (scikit-image's conversions). Each result is clipped to [0, 1].
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch
from skimage.color import hsv2rgb, rgb2hsv

from usl.config import ColorJitterConfig

from .samples import MultiViewSample

LUMA = (0.299, 0.587, 0.114)  # ITU-R 601, as PIL's "L" conversion


def grey(image: torch.Tensor) -> torch.Tensor:
    """(3, H, W) -> (1, H, W) luma."""
    return (image * image.new_tensor(LUMA)[:, None, None]).sum(dim=0, keepdim=True)


def _blend(image: torch.Tensor, other: torch.Tensor, factor: float) -> torch.Tensor:
    """``other + factor (image - other)``: 0 gives ``other``, 1 the image, above 1 extrapolates."""
    return (other + factor * (image - other)).clamp(0.0, 1.0)


def jitter_colors(image: torch.Tensor, cfg: ColorJitterConfig, rng: np.random.Generator) -> torch.Tensor:
    """(3, H, W) float image in [0, 1] -> the same with random brightness, contrast, saturation
    and hue. Draws four numbers from ``rng`` whatever is enabled, so a sample's later draws do
    not depend on which changes are on."""
    brightness, contrast, saturation = (1.0 + rng.uniform(-s, s) for s in (cfg.brightness, cfg.contrast, cfg.saturation))
    hue = rng.uniform(-cfg.hue, cfg.hue)
    out = _blend(image, torch.zeros_like(image), brightness)
    out = _blend(out, grey(out).mean(), contrast)
    out = _blend(out, grey(out), saturation)
    if hue:
        hsv = rgb2hsv(out.permute(1, 2, 0).numpy())
        hsv[..., 0] = np.mod(hsv[..., 0] + hue, 1.0)
        out = torch.from_numpy(hsv2rgb(hsv)).permute(2, 0, 1).to(image.dtype).clamp_(0.0, 1.0).contiguous()
    return out


def jitter_sample(sample: MultiViewSample, cfg: ColorJitterConfig, rng: np.random.Generator) -> MultiViewSample:
    return replace(sample, frame=replace(sample.frame, image=jitter_colors(sample.frame.image, cfg, rng)))
