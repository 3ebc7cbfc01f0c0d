import cv2
import numpy as np
import pytest


@pytest.fixture(scope="module")
def image_path(tmp_path_factory):
    """A 120x80 noise image, ``room.png``."""
    path = tmp_path_factory.mktemp("images") / "room.png"
    rng = np.random.default_rng(0)
    cv2.imwrite(str(path), rng.integers(0, 255, (80, 120, 3), dtype=np.uint8))
    return path
