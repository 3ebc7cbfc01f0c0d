"""A synthetic ScanNet-like scan with exact ground truth, and writers for every input format.

Tests and the benchmark need ``.sens`` files, exported folders, detections files and ScanNet label
images whose content is known exactly. The scene is a room with boxes on the floor, ray-cast
analytically (no renderer needed): colour (textured, so JPEG is realistic), planar depth at the
depth camera's resolution, and an instance map at colour resolution. The camera slides and turns
along a path; chosen frames get ScanNet's ``-inf`` pose for lost tracking.
"""

from __future__ import annotations

import json
import struct
import zlib
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from pycocotools import mask as mask_utils

from usl.geometry.cameras import look_at

ROOM = (np.array([-4.0, -4.0, 0.0]), np.array([4.0, 4.0, 3.0]))  # world frame: z up, metres


@dataclass(frozen=True)
class Box:
    instance: int  # 1.. (0 = room)
    coco_id: int
    label_id: int  # a ScanNet label id (label-filt value)
    centre: tuple[float, float, float]
    half: tuple[float, float, float]
    colour: tuple[int, int, int]


DEFAULT_BOXES = (
    Box(1, 62, 2, (-0.7, 0.2, 0.45), (0.25, 0.25, 0.45), (200, 60, 50)),  # chair
    Box(2, 63, 6, (0.6, 0.6, 0.4), (0.45, 0.3, 0.4), (60, 170, 70)),  # couch
    Box(3, 72, 25, (0.0, 1.4, 0.9), (0.35, 0.1, 0.25), (50, 80, 200)),  # tv
    Box(4, 62, 2, (3.25, 0.3, 0.45), (0.25, 0.25, 0.45), (210, 180, 40)),  # chair seen only late in the path
)


@dataclass(frozen=True)
class SyntheticFrame:
    index: int
    pose: np.ndarray  # 4x4 float32 as stored (all -inf when "lost")
    color: bytes  # encoded JPEG, exactly the bytes a file stores
    depth_mm: np.ndarray  # (Hd, Wd) uint16
    instances: np.ndarray  # (Hc, Wc) uint8 instance ids, 0 = none


def scaled_half_pixel(K: np.ndarray, sx: float, sy: float) -> np.ndarray:
    return np.diag([sx, sy, 1.0]) @ K


def integer_centres(K_half: np.ndarray) -> np.ndarray:
    """K with pixel centres at +0.5 -> ScanNet's stored convention (integer centres), 4x4."""
    K4 = np.eye(4)
    K4[:3, :3] = np.array([[1.0, 0, -0.5], [0, 1.0, -0.5], [0, 0, 1.0]]) @ K_half
    return K4


class SyntheticScan:
    """``num_frames`` frames along a path: the camera slides along x from ``x_range`` looking across the room."""

    def __init__(
        self,
        num_frames: int = 120,
        color_size: tuple[int, int] = (96, 72),
        depth_size: tuple[int, int] = (48, 36),
        boxes: tuple[Box, ...] = DEFAULT_BOXES,
        lost_frames: Iterable[int] = (),
        x_range: tuple[float, float] = (-1.2, 1.6),
        jpeg_quality: int = 90,
        period: int | None = None,
        render_scale: int = 1,
        depth_noise_mm: float = 0.0,
    ):
        self.num_frames = num_frames
        self.color_size, self.depth_size = color_size, depth_size
        self.boxes = boxes
        self.lost = set(lost_frames)
        self.x_range = x_range
        self.jpeg_quality = jpeg_quality
        self.period = period  # the path goes back and forth with this period (frames); None: once
        # ray-cast at 1/render_scale of the sizes and repeat pixels: fast large frames for benchmarks
        self.render_scale = render_scale
        self.depth_noise_mm = depth_noise_mm  # sensor-like noise, so depth compresses like real depth
        cw, ch = color_size
        self.K_color = np.array([[0.62 * cw, 0.0, 0.5 * cw + 0.3], [0.0, 0.62 * cw, 0.5 * ch - 0.2], [0, 0, 1.0]])
        self.K_depth = scaled_half_pixel(self.K_color, depth_size[0] / cw, depth_size[1] / ch)

    def true_pose(self, index: int) -> np.ndarray:
        s = index / max(self.num_frames - 1, 1)
        if self.period:
            phase = (index % self.period) / self.period
            s = 2 * phase if phase < 0.5 else 2 - 2 * phase
        x = self.x_range[0] + s * (self.x_range[1] - self.x_range[0])
        eye = np.array([x, -2.6, 1.25 + 0.1 * np.sin(6 * s)])
        return look_at(eye, np.array([0.55 * x, 0.6, 0.5]), up=(0.0, 0.0, 1.0))

    def _cast(
        self, pose: np.ndarray, K: np.ndarray, size: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Planar depth, instance id and world hit point of every pixel centre."""
        w, h = size
        v, u = np.mgrid[0:h, 0:w]
        pix = np.stack([u.ravel() + 0.5, v.ravel() + 0.5, np.ones(u.size)])
        dirs = pose[:3, :3] @ (np.linalg.inv(K) @ pix)  # (3, N); camera z = 1, so the ray parameter is planar depth
        eye = pose[:3, 3:]
        safe = np.where(np.abs(dirs) < 1e-12, 1e-12, dirs)
        t1, t2 = (ROOM[0][:, None] - eye) / safe, (ROOM[1][:, None] - eye) / safe
        far = np.maximum(t1, t2)
        depth = np.minimum(np.minimum(far[0], far[1]), far[2])  # exit through the room's walls, floor or ceiling
        label = np.zeros(u.size, np.uint8)
        for box in self.boxes:
            lo = np.array(box.centre)[:, None] - np.array(box.half)[:, None]
            hi = np.array(box.centre)[:, None] + np.array(box.half)[:, None]
            a, b = (lo - eye) / safe, (hi - eye) / safe
            lower, upper = np.minimum(a, b), np.maximum(a, b)
            near = np.maximum(np.maximum(lower[0], lower[1]), lower[2])
            exit_ = np.minimum(np.minimum(upper[0], upper[1]), upper[2])
            hit = (exit_ >= near) & (near > 1e-6) & (near < depth)
            depth = np.where(hit, near, depth)
            label[hit] = box.instance
        points = (eye + dirs * depth).T
        return depth.reshape(h, w), label.reshape(h, w), points.reshape(h, w, 3)

    def _cast_scaled(self, pose: np.ndarray, K: np.ndarray, size: tuple[int, int]):
        s = self.render_scale
        if s == 1:
            return self._cast(pose, K, size)
        if size[0] % s or size[1] % s:
            raise ValueError(f"render_scale {s} does not divide {size}")
        out = self._cast(pose, scaled_half_pixel(K, 1 / s, 1 / s), (size[0] // s, size[1] // s))
        return tuple(np.repeat(np.repeat(a, s, axis=0), s, axis=1) for a in out)

    def render(self, index: int) -> SyntheticFrame:
        pose = self.true_pose(index)
        _, label, points = self._cast_scaled(pose, self.K_color, self.color_size)
        checker = (np.floor(points * 5).astype(np.int64).sum(axis=2) % 2).astype(np.float32)
        base = np.full(label.shape + (3,), 150.0, np.float32)
        for box in self.boxes:
            base[label == box.instance] = box.colour
        shade = 0.75 + 0.25 * checker[..., None] + 0.05 * np.sin(points[..., :1] * 7)
        rgb = np.clip(base * shade, 0, 255).astype(np.uint8)
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        ok, jpeg = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality])
        assert ok
        depth, _, _ = self._cast_scaled(pose, self.K_depth, self.depth_size)
        depth_mm = np.rint(depth * 1000.0)
        if self.depth_noise_mm > 0:
            depth_mm += np.random.default_rng(index).normal(0.0, self.depth_noise_mm, depth_mm.shape).round()
        depth_mm = np.clip(depth_mm, 0, 65535).astype(np.uint16)
        stored = np.full((4, 4), -np.inf, np.float32) if index in self.lost else pose.astype(np.float32)
        return SyntheticFrame(index, stored, jpeg.tobytes(), depth_mm, label)

    def frames(self) -> Iterator[SyntheticFrame]:
        for index in range(self.num_frames):
            yield self.render(index)


def write_sens(
    path: Path,
    scan: SyntheticScan,
    frames: Iterable[SyntheticFrame],
    *,
    depth_codec: int = 1,
    color_codec: int = 2,
    depth_shift: float = 1000.0,
    imu_records: int = 3,
) -> None:
    """A ``.sens`` file (version 4) byte for byte as sensorData.h lays it out; frames are streamed."""
    cw, ch = scan.color_size
    dw, dh = scan.depth_size
    with open(path, "wb") as f:
        name = b"StructureSensor"
        f.write(struct.pack("<IQ", 4, len(name)) + name)
        for matrix in (integer_centres(scan.K_color), np.eye(4), integer_centres(scan.K_depth), np.eye(4)):
            f.write(np.asarray(matrix, "<f4").tobytes())
        f.write(struct.pack("<ii4IfQ", color_codec, depth_codec, cw, ch, dw, dh, depth_shift, 0))
        count_at = f.tell() - 8
        count = 0
        for frame in frames:
            raw = frame.depth_mm.astype("<u2").tobytes()
            depth = zlib.compress(raw) if depth_codec == 1 and raw else raw  # no pixels: an empty payload
            f.write(np.asarray(frame.pose, "<f4").tobytes())
            f.write(struct.pack("<4Q", 1000 * frame.index, 1000 * frame.index + 7, len(frame.color), len(depth)))
            f.write(frame.color + depth)
            count += 1
        f.write(struct.pack("<Q", imu_records) + bytes(128 * imu_records))
        f.seek(count_at)
        f.write(struct.pack("<Q", count))


def _write_matrix(path: Path, matrix: np.ndarray) -> None:
    np.savetxt(path, np.asarray(matrix, dtype=np.float64), fmt="%f")


def write_exported(root: Path, scan: SyntheticScan, frames: Iterable[SyntheticFrame]) -> None:
    """SensReader's export layout: color/{i}.jpg, depth/{i}.png, pose/{i}.txt, intrinsic/*.txt."""
    for sub in ("color", "depth", "pose", "intrinsic"):
        (root / sub).mkdir(parents=True, exist_ok=True)
    _write_matrix(root / "intrinsic" / "intrinsic_color.txt", integer_centres(scan.K_color))
    _write_matrix(root / "intrinsic" / "intrinsic_depth.txt", integer_centres(scan.K_depth))
    _write_matrix(root / "intrinsic" / "extrinsic_color.txt", np.eye(4))
    _write_matrix(root / "intrinsic" / "extrinsic_depth.txt", np.eye(4))
    for frame in frames:
        (root / "color" / f"{frame.index}.jpg").write_bytes(frame.color)
        cv2.imwrite(str(root / "depth" / f"{frame.index}.png"), frame.depth_mm)
        np.savetxt(root / "pose" / f"{frame.index}.txt", frame.pose.astype(np.float64), fmt="%.9g")


def write_labels(root: Path, scan: SyntheticScan, frames: Iterable[SyntheticFrame]) -> None:
    """ScanNet's instance-filt/ and label-filt/ images (colour resolution) for the frames."""
    (root / "instance-filt").mkdir(parents=True, exist_ok=True)
    (root / "label-filt").mkdir(parents=True, exist_ok=True)
    labels = np.zeros(256, np.uint16)
    for box in scan.boxes:
        labels[box.instance] = box.label_id
    for frame in frames:
        cv2.imwrite(str(root / "instance-filt" / f"{frame.index}.png"), frame.instances)
        cv2.imwrite(str(root / "label-filt" / f"{frame.index}.png"), labels[frame.instances])


def write_label_map(path: Path) -> None:
    """A small scannetv2-labels.combined.tsv with the columns the converter reads."""
    rows = [
        (1, "wall", "wall", "wall"),
        (2, "chair", "chair", "chair"),
        (6, "sofa", "couch", "sofa"),
        (25, "tv", "tv", "television"),
        (40, "box", "box", "otherprop"),
    ]
    lines = ["id\traw_category\tcategory\tcount\tnyu40id\tnyu40class"]
    lines += [f"{i}\t{raw}\t{cat}\t1\t0\t{nyu}" for i, raw, cat, nyu in rows]
    path.write_text("\n".join(lines) + "\n")


def detections_from_instances(frame: SyntheticFrame, scan: SyntheticScan, rng: np.random.Generator) -> list[dict]:
    """COCO-results detections (without image_id) from a frame's instance map, scores in [0.6, 1)."""
    out = []
    coco = {box.instance: box.coco_id for box in scan.boxes}
    for value in np.unique(frame.instances):
        if value == 0:
            continue
        mask = np.asfortranarray((frame.instances == value).astype(np.uint8))
        rle = mask_utils.encode(mask)
        x, y, w, h = mask_utils.toBbox(rle).tolist()
        out.append(
            {
                "category_id": coco[int(value)],
                "score": float(rng.uniform(0.6, 1.0)),
                "segmentation": {"size": rle["size"], "counts": rle["counts"].decode("ascii")},
                "bbox": [x, y, w, h],
                "true_instance": int(value),
            }
        )
    return out


def write_detections(
    results_path: Path,
    images_path: Path,
    scene_id: str,
    scan: SyntheticScan,
    frames: Iterable[SyntheticFrame],
    seed: int = 0,
    first_image_id: int = 1,
) -> None:
    """A detectron2-style results file and its COCO images file for the frames of one scan."""
    rng = np.random.default_rng(seed)
    images, results = [], []
    cw, ch = scan.color_size
    for k, frame in enumerate(frames):
        image_id = first_image_id + k
        images.append({"id": image_id, "file_name": f"{scene_id}/color/{frame.index}.jpg", "width": cw, "height": ch})
        for det in detections_from_instances(frame, scan, rng):
            det.pop("true_instance")
            results.append({"image_id": image_id, **det})
    images_path.write_text(json.dumps({"images": images, "categories": []}))
    results_path.write_text(json.dumps(results))
