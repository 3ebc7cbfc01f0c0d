"""Inputs shared by the detectron2 oracle script and the tests that replay its outputs.

* ``CHECKPOINT_KEYS``: every key and shape of detectron2's ``pointrend_rcnn_R_50_FPN_3x_coco`` and
  ``mask_rcnn_R_50_FPN_3x`` models, dumped from ``build_model(cfg).state_dict()`` of detectron2's own
  source (fixtures/detectron2_checkpoint_keys.json).
* ``write_random_checkpoint``: seeded random weights in the model zoo's pickle layout. Plain
  initialisations give near-uniform class scores (nothing passes the 0.05 threshold, and what does
  is nearly tied); these scales spread objectness, scores and mask logits so detections are many and
  distinct, while keeping the deep ResNet's activations bounded.
* ``write_test_images``: seeded pictures of coloured shapes on gradients.

Only numpy, pickle and OpenCV: the oracle runs this in a separate environment with detectron2.
"""

from __future__ import annotations

import json
import pickle
from pathlib import Path

import cv2
import numpy as np

FIXTURES = Path(__file__).parent / "fixtures"
CHECKPOINT_KEYS = json.loads((FIXTURES / "detectron2_checkpoint_keys.json").read_text())
ORACLE_SEED = 0  # the seed of the weights the recorded oracle ran
POINTREND = "pointrend_rcnn_R_50_FPN_3x_coco"
MASK_RCNN = "mask_rcnn_R_50_FPN_3x"

# (key suffix, standard deviation x sqrt(fan_in)) for the layers whose outputs we want spread out.
_OUTPUT_GAINS = (
    ("stem.conv1.weight", np.sqrt(2.0) / 60.0),  # the inputs are BGR 0-255 minus the mean (std ~60)
    ("fpn_lateral2.weight", 0.25),
    ("fpn_lateral3.weight", 0.25),
    ("fpn_lateral4.weight", 0.25),
    ("fpn_lateral5.weight", 0.25),
    ("fpn_output2.weight", 1.0),
    ("fpn_output3.weight", 1.0),
    ("fpn_output4.weight", 1.0),
    ("fpn_output5.weight", 1.0),
    ("rpn_head.objectness_logits.weight", 6.0),
    ("rpn_head.anchor_deltas.weight", 0.3),
    ("box_predictor.cls_score.weight", 2.0),
    ("box_predictor.bbox_pred.weight", 0.3),
    ("coarse_head.prediction.weight", 6.0),
    ("point_head.predictor.weight", 6.0),
    ("mask_head.predictor.weight", 6.0),
)


BACKGROUND_BIAS = 15.0


def _values(key: str, shape: tuple[int, ...], rng: np.random.Generator) -> np.ndarray:
    if key.endswith("running_var"):
        return rng.uniform(0.5, 1.5, shape).astype(np.float32)
    if key.endswith("running_mean") or key.endswith("bias"):
        return (0.1 * rng.standard_normal(shape)).astype(np.float32)
    if key.endswith("norm.weight"):
        # the last norm of each residual branch damps it, so 16 blocks do not blow the activations up
        low, high = (0.2, 0.4) if ".conv3." in key else (0.8, 1.2)
        return rng.uniform(low, high, shape).astype(np.float32)
    fan_in = int(np.prod(shape[1:]))
    gain = next((g for suffix, g in _OUTPUT_GAINS if key.endswith(suffix)), np.sqrt(2.0))
    return (gain / np.sqrt(fan_in) * rng.standard_normal(shape, dtype=np.float32)).astype(np.float32)


def random_weights(model: str, seed: int, background_bias: float = BACKGROUND_BIAS) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    weights = {key: _values(key, tuple(shape), rng) for key, shape in CHECKPOINT_KEYS[model].items()}
    # The box head's ReLU features share a large positive mean: zero-mean rows stop one class from
    # winning everywhere, and a background bias leaves only some proposals above the threshold.
    for layer in ("box_head.fc1", "box_head.fc2", "box_predictor.cls_score"):
        weights[f"roi_heads.{layer}.weight"] -= weights[f"roi_heads.{layer}.weight"].mean(axis=1, keepdims=True)
    weights["roi_heads.box_predictor.cls_score.bias"][-1] = background_bias
    return weights


def write_random_checkpoint(
    path: Path, model: str, seed: int, background_bias: float = BACKGROUND_BIAS
) -> dict[str, np.ndarray]:
    """A ``model_final_*.pkl`` look-alike: ``{"model": {key: array}, "__author__": ...}``.

    ``background_bias``: lower it for more detections (the default suits the colourful test images).
    """
    weights = random_weights(model, seed, background_bias)
    with open(path, "wb") as stream:
        pickle.dump({"model": weights, "__author__": "random weights for tests"}, stream)
    return weights


def checksum(weights: dict[str, np.ndarray]) -> float:
    """A fingerprint the oracle records, so a test notices if numpy ever draws other numbers."""
    return float(sum(float(np.abs(v).astype(np.float64).sum()) for v in weights.values()))


def synthetic_picture(seed: int, width: int, height: int) -> np.ndarray:
    """An RGB uint8 picture: a colour gradient with a dozen filled rectangles and ellipses."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    corners = rng.uniform(0, 255, (4, 3)).astype(np.float32)
    u, v = (x / max(width - 1, 1))[..., None], (y / max(height - 1, 1))[..., None]
    image = (1 - u) * (1 - v) * corners[0] + u * (1 - v) * corners[1] + (1 - u) * v * corners[2] + u * v * corners[3]
    image = np.ascontiguousarray(image.astype(np.uint8))
    for _ in range(12):
        colour = tuple(int(c) for c in rng.integers(0, 256, 3))
        cx, cy = int(rng.integers(0, width)), int(rng.integers(0, height))
        sx, sy = int(rng.integers(width // 20, width // 4)), int(rng.integers(height // 20, height // 4))
        if rng.random() < 0.5:
            cv2.rectangle(image, (cx - sx, cy - sy), (cx + sx, cy + sy), colour, thickness=-1)
        else:
            cv2.ellipse(image, (cx, cy), (sx, sy), float(rng.uniform(0, 180)), 0, 360, colour, thickness=-1)
    return image


# name -> (seed, width, height): ScanNet's frame size, a portrait one, and one wide enough to hit the 1333 cap.
TEST_IMAGES = {"scannet.png": (1, 640, 480), "portrait.png": (2, 360, 500), "panorama.png": (3, 900, 240)}


def write_test_images(folder: Path) -> list[Path]:
    paths = []
    for name, (seed, width, height) in TEST_IMAGES.items():
        path = folder / name
        cv2.imwrite(str(path), cv2.cvtColor(synthetic_picture(seed, width, height), cv2.COLOR_RGB2BGR))
        paths.append(path)
    return paths
