"""The camera of a photo whose intrinsics nobody measured: ``--fov auto``.

Phones and most cameras write EXIF ``FocalLengthIn35mmFilm``: the focal length a full-frame (36 x
24 mm) camera would need for the same angle of view. CIPA DC-008 matches the diagonals, so the
photo's diagonal spans 43.27 mm at that focal length, whatever its aspect ratio or orientation, and
its width spans ``43.27 * W / hypot(W, H)`` mm. Without the tag (arrays, scans, stripped files)
``DEFAULT_FOV_DEG`` is used, with a warning: a wrong field of view scales every depth.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

from usl.errors import UslWarning

DEFAULT_FOV_DEG = 60.0  # horizontal; a phone's main camera is 60-70 degrees wide in landscape
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
EXIF_IFD = 0x8769
FOCAL_LENGTH_35MM = 0xA405  # FocalLengthIn35mmFilm


class FieldOfViewWarning(UslWarning):
    """A field of view was assumed, not read: depths scale with how wrong it is."""


def exif_fov_deg(path: str | Path, width: int, height: int) -> float | None:
    """Horizontal field of view (degrees) of a ``width`` x ``height`` photo from its EXIF, or None."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as image:
            focal = image.getexif().get_ifd(EXIF_IFD).get(FOCAL_LENGTH_35MM)
    except (OSError, UnidentifiedImageError):
        return None
    if not focal or float(focal) <= 0:  # 0 means unknown in EXIF
        return None
    half_width_mm = 0.5 * FULL_FRAME_DIAGONAL_MM * width / math.hypot(width, height)
    return math.degrees(2.0 * math.atan(half_width_mm / float(focal)))


def auto_fov_deg(path: str | Path | None, width: int, height: int) -> float:
    """EXIF's field of view of the photo at ``path``, else ``DEFAULT_FOV_DEG`` with a warning."""
    fov = exif_fov_deg(path, width, height) if path is not None else None
    if fov is None:
        where = f"{path} has no EXIF FocalLengthIn35mmFilm" if path is not None else "an array carries no EXIF"
        warnings.warn(
            f"{where}: assuming a {DEFAULT_FOV_DEG:g} degree horizontal field of view (pass K or fov if known)",
            FieldOfViewWarning,
            stacklevel=2,
        )
        return DEFAULT_FOV_DEG
    return fov
