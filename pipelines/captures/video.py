"""Frames of a video file at ``--fps``, decoded with OpenCV and kept as JPEG files for SfM and the records.

Written once per capture into the build's state folder (``<out>/.build/captures/<scene>/frames``,
renamed into place when complete), so a resumed build and its SfM model see the same frames.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2

from usl.errors import UslError
from usl.records.tempfiles import process_token

VIDEO_SUFFIXES = {".mp4", ".mov", ".m4v", ".avi", ".mkv", ".webm"}
FRAMES = "frames"


def frame_name(k: int) -> str:
    return f"frame_{k:05d}.jpg"


def sample_video(video: Path, fps: float, work: Path, jpeg_quality: int = 95) -> Path:
    """The folder of ``video``'s frames at ``fps`` (all frames if the video has fewer per second)."""
    frames = work / FRAMES
    if frames.is_dir():
        return frames
    capture = cv2.VideoCapture(str(video))
    if not capture.isOpened():
        raise UslError(f"{video}: OpenCV cannot open this video")
    native = capture.get(cv2.CAP_PROP_FPS)
    if not native or native <= 0:
        raise UslError(f"{video}: the video states no frame rate")
    step = max(1.0, native / fps)
    scratch = work / f"tmp-frames-{process_token()}"
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir(parents=True)
    kept, position, next_time = 0, 0, 0.0
    try:
        while True:
            ok, bgr = capture.read()
            if not ok:
                break
            if position >= next_time - 1e-6:
                cv2.imwrite(str(scratch / frame_name(kept)), bgr, [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality])
                kept += 1
                next_time += step
            position += 1
    finally:
        capture.release()
    if kept == 0:
        shutil.rmtree(scratch, ignore_errors=True)
        raise UslError(f"{video}: no frame decodes")
    scratch.rename(frames)
    return frames
