"""``--poses sfm``: camera poses and intrinsics from the images alone, with COLMAP through pycolmap.

The steps ``ns-process-data`` runs for a video, on the CPU: SIFT features (one shared camera,
``SIMPLE_RADIAL`` by default, as COLMAP's own default), sequential matching (each frame against the
next ``overlap`` ones: frames of a video or a walk-around are in time order), incremental mapping;
the largest model wins. The model is written to the build's state folder once per capture
(``<out>/.build/captures/<scene>/sfm``), so a resumed build reads it instead of solving again.
Poses come out in COLMAP's arbitrary unit: ``scale`` makes them metric.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from usl.errors import UslError
from usl.records.tempfiles import process_token

from .colmap import import_pycolmap

MODEL = "model"


@dataclass(frozen=True)
class SfmOptions:
    camera_model: str = "SIMPLE_RADIAL"  # one camera for all frames (a phone video)
    max_features: int = 4096  # SIFT features per image (COLMAP's default 8192 doubles the matching time)
    max_image_size: int = 1600  # longest side SIFT sees (COLMAP's default 3200)
    overlap: int = 10  # frames each frame is matched against
    threads: int = -1  # -1: all cores

    def __post_init__(self) -> None:
        if self.max_features < 100 or self.overlap < 1 or self.max_image_size < 100:
            raise ValueError("SfM needs >= 100 features, an image size >= 100 and an overlap >= 1")


def run_sfm(images: Path, names: list[str], work: Path, options: SfmOptions) -> Path:
    """The COLMAP model of ``images`` (the ``names`` in frame order), solved once into ``work/model``."""
    model = work / MODEL
    if model.is_dir():
        return model
    pycolmap = import_pycolmap()
    pycolmap.logging.minloglevel = 1  # warnings and errors only: COLMAP's INFO lines would bury the build's output
    scratch = work / f"tmp-{process_token()}"
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir(parents=True)
    database = scratch / "database.db"
    cpu = pycolmap.Device.cpu
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = options.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.use_gpu = False
    extraction.num_threads = options.threads
    extraction.max_image_size = options.max_image_size
    extraction.sift.max_num_features = options.max_features
    pycolmap.extract_features(database, images, names, pycolmap.CameraMode.SINGLE, reader, extraction, device=cpu)
    matching = pycolmap.FeatureMatchingOptions()
    matching.use_gpu = False
    matching.num_threads = options.threads
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = options.overlap
    pycolmap.match_sequential(database, matching, pairing, device=cpu)
    mapping = pycolmap.IncrementalPipelineOptions()
    mapping.num_threads = options.threads
    mapping.random_seed = 0
    models = pycolmap.incremental_mapping(database, images, scratch / "sparse", mapping)
    if not models:
        shutil.rmtree(scratch, ignore_errors=True)
        raise UslError(f"{images}: SfM registered no images (too little texture or overlap between frames?)")
    best = max(models.values(), key=lambda m: m.num_reg_images())
    (scratch / MODEL).mkdir()
    best.write_binary(str(scratch / MODEL))
    (scratch / MODEL).rename(model)  # the commit point: a resumed build trusts a model folder
    shutil.rmtree(scratch, ignore_errors=True)
    return model
