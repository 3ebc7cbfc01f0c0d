"""``--fov auto``: the field of view from a photo's EXIF, checked against a file Pillow writes."""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image

from usl.inference.field_of_view import DEFAULT_FOV_DEG, EXIF_IFD, FOCAL_LENGTH_35MM, auto_fov_deg, exif_fov_deg
from usl.inference.predict import camera_for


def photo(path, width, height, focal_35mm=None):
    exif = Image.Exif()
    if focal_35mm is not None:
        exif.get_ifd(EXIF_IFD)[FOCAL_LENGTH_35MM] = focal_35mm
    Image.fromarray(np.zeros((height, width, 3), np.uint8)).save(path, exif=exif)
    return path


@pytest.mark.parametrize("width, height", [(360, 240), (240, 360), (400, 300)])
def test_exif_focal_length_matches_a_full_frame_diagonal(tmp_path, width, height):
    path = photo(tmp_path / "p.jpg", width, height, focal_35mm=24)
    with Image.open(path) as reread:  # the tag really is in the file
        assert reread.getexif().get_ifd(EXIF_IFD)[FOCAL_LENGTH_35MM] == 24
    fov = exif_fov_deg(path, width, height)
    # the photo's diagonal field of view is a full-frame camera's at 24 mm (84.1 degrees)
    focal_px = 0.5 * width / math.tan(math.radians(fov) / 2)
    diagonal = math.degrees(2 * math.atan(0.5 * math.hypot(width, height) / focal_px))
    assert diagonal == pytest.approx(math.degrees(2 * math.atan(0.5 * math.hypot(36, 24) / 24)))
    if width / height == 1.5:  # 3:2 landscape is full frame's own shape: 36 mm across
        assert fov == pytest.approx(math.degrees(2 * math.atan(18 / 24)))


def test_without_exif_the_default_with_a_warning(tmp_path):
    path = photo(tmp_path / "p.png", 64, 48)
    assert exif_fov_deg(path, 64, 48) is None
    with pytest.warns(UserWarning, match="p.png has no EXIF FocalLengthIn35mmFilm: assuming a 60 degree"):
        assert auto_fov_deg(path, 64, 48) == DEFAULT_FOV_DEG
    with pytest.warns(UserWarning, match="an array carries no EXIF"):
        assert auto_fov_deg(None, 64, 48) == DEFAULT_FOV_DEG


def test_camera_for_auto_uses_the_files_exif(tmp_path):
    path = photo(tmp_path / "p.jpg", 360, 240, focal_35mm=36)
    K = camera_for(np.zeros((240, 360, 3), np.uint8), None, "auto", path=path).double().numpy()
    assert K[0, 0] == pytest.approx(360.0, rel=1e-5)  # 36 mm across at 36 mm: the width in pixels
