"""Hypersim inputs with every kind of trouble the converter must survive, and converting them.

A uniquely named module (not conftest) so tests can import it whatever else is on sys.path.
"""

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipelines.hypersim.cli import main
from tests.pipelines.hypersim.hypersim_fixture import (
    SyntheticScene,
    edit_hdf5,
    make_scene,
    split_rows,
    truncate,
    write_camera_csv,
    write_scene,
    write_split_csv,
)

NAN_PATCH = (slice(10, 16), slice(20, 30))  # rows, cols of NaN depth in ai_001_001/cam_00 frame 4
MIN_PIXELS = 6


@dataclass
class Inputs:
    scenes_root: Path
    split_csv: Path
    camera_csv: Path
    scenes: dict[str, SyntheticScene]

    def argv(self, out: Path, *extra: str) -> list[str]:
        return [
            str(self.scenes_root),
            "--split-csv",
            str(self.split_csv),
            "--camera-csv",
            str(self.camera_csv),
            "--out",
            str(out),
            "--quiet",
            "--min-instance-pixels",
            str(MIN_PIXELS),
            *extra,
        ]


def write_inputs(root: Path, exr: bool = False) -> Inputs:
    """Two scenes with every kind of trouble the converter must survive.

    ai_001_001 (tilt-shift, inches, train): cam_00 frames 0-5 on disk; frame 2 flagged for removal
    (files present anyway), frame 3 lacks its geometry files, frame 4 has a NaN depth patch.
    cam_01 is an excluded trajectory whose frames 0-1 are on disk anyway.
    ai_002_001 (canonical camera, centimetres, val): frames 0-5; 0 has a scaled orientation, 1 a
    truncated semantic file, 2 no geometry at all, 3 a semantic image of the wrong size; its cam_01
    is in the split but was not downloaded at all.
    """
    a = make_scene("ai_001_001", cameras=("cam_00", "cam_01"))
    b = make_scene("ai_002_001", tilt_shift=False, meters_per_asset_unit=0.01)
    scenes_root = root / "downloads"
    a_dir = write_scene(scenes_root, a, {"cam_00": [0, 1, 2, 3, 4, 5], "cam_01": [0, 1]}, exr=exr)
    b_dir = write_scene(scenes_root, b, {"cam_00": [0, 1, 2, 3, 4, 5]}, exr=exr)
    rows = split_rows("ai_001_001", "cam_00", range(8), "train", {2: "CONTENT FLAGGED FOR REMOVAL"})
    outside = {f: "OUTSIDE VIEWING AREA (BAD TRAJECTORY)" for f in range(8)}
    rows += split_rows("ai_001_001", "cam_01", range(8), "", outside)
    rows += split_rows("ai_002_001", "cam_00", range(6), "val")
    rows += split_rows("ai_002_001", "cam_01", range(4), "val")  # listed, never downloaded
    split_csv = write_split_csv(root / "metadata_images_split_scene_v1.csv", rows)
    camera_csv = write_camera_csv(root / "metadata_camera_parameters.csv", [a, b])
    # ai_001_001 frames 6, 7 are listed but were never downloaded; frame 3 loses its geometry.
    geometry = a_dir / "images" / "scene_cam_00_geometry_hdf5"
    for kind in ("semantic", "semantic_instance"):
        (geometry / f"frame.0003.{kind}.hdf5").unlink()
    if exr:
        (a_dir / "images" / "scene_cam_00_geometry" / "frame.0003.exr").unlink()
    else:
        for kind in ("depth_meters", "render_entity_id"):
            (geometry / f"frame.0003.{kind}.hdf5").unlink()

        def nan_patch(depth):
            depth[NAN_PATCH] = np.nan
            return depth

        edit_hdf5(geometry / "frame.0004.depth_meters.hdf5", nan_patch)
        b_geometry = b_dir / "images" / "scene_cam_00_geometry_hdf5"
        edit_hdf5(b_geometry / "frame.0002.render_entity_id.hdf5", lambda e: np.full_like(e, -1))
        edit_hdf5(b_geometry / "frame.0002.depth_meters.hdf5", lambda d: np.full_like(d, np.nan))
    b_geometry = b_dir / "images" / "scene_cam_00_geometry_hdf5"
    truncate(b_geometry / "frame.0001.semantic.hdf5")
    edit_hdf5(b_geometry / "frame.0003.semantic.hdf5", lambda s: s[::2, ::2].copy())
    edit_hdf5(
        b_dir / "_detail" / "cam_00" / "camera_keyframe_orientations.hdf5",
        lambda r: np.concatenate([r[:1] * 1.2, r[1:]]),
    )
    return Inputs(scenes_root, split_csv, camera_csv, {"ai_001_001": a, "ai_002_001": b})


def convert(inputs: Inputs, out: Path, *extra: str) -> Path:
    assert main(inputs.argv(out, *extra)) == 0
    return out
