"""Mask, image and depth encoding against independent oracles (pycocotools, OpenCV)."""

import numpy as np
import pytest
from pycocotools import mask as coco

from usl.records import decode_depth, decode_image, decode_mask, encode_depth, encode_image, encode_mask, make_instance


def random_mask(rng, h=37, w=53):
    return rng.random((h, w)) < rng.uniform(0.05, 0.6)


def test_rle_round_trip_through_pycocotools():
    rng = np.random.default_rng(0)
    for _ in range(20):
        mask = random_mask(rng)
        rle = encode_mask(mask)
        assert isinstance(rle["counts"], str) and rle["size"] == [37, 53]
        decoded = coco.decode({"size": rle["size"], "counts": rle["counts"].encode()})
        np.testing.assert_array_equal(decoded.astype(bool), mask)
        theirs = coco.encode(np.asfortranarray(mask.astype(np.uint8)))
        assert theirs["counts"].decode() == rle["counts"]
        np.testing.assert_array_equal(decode_mask(rle), mask)


def test_instance_box_area_and_depth_match_pycocotools():
    rng = np.random.default_rng(1)
    mask = np.zeros((40, 60), bool)
    mask[5:17, 8:31] = True
    mask[20, 40] = True
    depth = rng.uniform(1, 3, (40, 60))
    depth[5, 8] = np.nan
    inst = make_instance(3, 7, mask, depth)
    rle = {"size": [40, 60], "counts": inst["mask"]["counts"].encode()}
    x, y, w, h = coco.toBbox(rle)
    assert inst["box_xyxy"] == [x, y, x + w, y + h] == [8.0, 5.0, 41.0, 21.0]
    assert inst["area"] == coco.area(rle) == mask.sum()
    assert inst["depth_min"] == pytest.approx(np.nanmin(np.where(mask, depth, np.nan)))
    with pytest.raises(ValueError):
        make_instance(1, 1, np.zeros((4, 4), bool))


def test_image_and_depth_codecs():
    rng = np.random.default_rng(2)
    image = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    np.testing.assert_array_equal(decode_image(encode_image(image, "png")), image)
    smooth = np.stack([*np.meshgrid(np.linspace(0, 255, 30), np.linspace(0, 255, 20)), np.full((20, 30), 90.0)], -1)
    smooth = smooth.astype(np.uint8)
    assert np.abs(decode_image(encode_image(smooth, "jpeg", 95)).astype(int) - smooth).mean() < 3
    depth = rng.uniform(0.2, 30.0, (20, 30))
    depth[0, :3] = [np.nan, -1.0, np.inf]
    back = decode_depth(encode_depth(depth))
    assert np.isnan(back[0, :3]).all()
    np.testing.assert_allclose(back[1:], depth[1:], atol=5e-4)
