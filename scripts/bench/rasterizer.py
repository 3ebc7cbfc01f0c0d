"""Benchmark the rasterizers, side by side in one run.

1. Sparse vs dense soft rasterizer, forward + backward, one 72x72 window, ico-sphere level 3
   (642 verts, 1280 faces), on the CPU (and on --device when that is CUDA): times, their
   ratio, and the max abs difference of outputs and vertex gradients.
2. A Hypersim-like batch on --device: 50 objects x 5 views = 250 (object, view) windows at
   72x72 through ``render_dynamic`` (window choice, exact-area targets from 768x1024 true
   masks, sparse soft rasterizer, BCE backward), reported as object-views per second; the
   rasterizer alone; and the z-buffer rasterizer producing the 5 views' true masks (on the CPU
   also its torch path, which CUDA runs, against the compiled loop: CPU-time ratio, same maps).

Usage: python scripts/bench/rasterizer.py [--device cuda] [--repeats 5] [--threads N]
(--threads 1 gives steadier CPU numbers on a shared machine.)
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import time

import torch
import torch.nn.functional as F

from usl.geometry.cameras import transform_points
from usl.geometry.icosphere import ico_sphere
from usl.render import (
    PaddedMasks,
    SoftRasterSettings,
    rasterize_hard,
    rasterize_soft,
    rasterize_soft_dense,
    render_dynamic,
)
from usl.utils.compiled import torch_paths_only

RESOLUTION = 72
HEIGHT, WIDTH = 768, 1024  # Hypersim frames


def timed(fn, device: torch.device, repeats: int) -> tuple[float, float]:
    """Median (wall, process CPU) seconds of ``fn()``, after one warm-up call.

    CPU time counts only this process's work, so it stays meaningful when other processes
    share the cores; wall time is what a user waits.
    """
    fn()
    walls, cpus = [], []
    for _ in range(repeats):
        _sync(device)
        wall, cpu = time.perf_counter(), time.process_time()
        fn()
        _sync(device)
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    return statistics.median(walls), statistics.median(cpus)


def fmt(seconds: tuple[float, float]) -> str:
    return f"{seconds[0] * 1e3:9.1f} ms (cpu {seconds[1] * 1e3:9.1f} ms)"


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def bumpy_spheres(count: int, generator: torch.Generator, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    """(count, 642, 3) ellipsoidal ico-spheres with radial noise, unit-ish size, and faces (1280, 3)."""
    verts, faces = ico_sphere(3, dtype=torch.float32)
    scale = 0.6 + 0.8 * torch.rand(count, 1, 3, generator=generator)
    bumps = 1.0 + 0.08 * torch.randn(count, verts.shape[0], 1, generator=generator)
    return (verts[None] * scale * bumps).to(device), faces.to(device)


def random_rotation(generator: torch.Generator, max_angle: float) -> torch.Tensor:
    axis = F.normalize(torch.randn(3, generator=generator), dim=0)
    angle = max_angle * (2 * torch.rand((), generator=generator) - 1)
    cross = torch.tensor([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return torch.eye(3) + torch.sin(angle) * cross + (1 - torch.cos(angle)) * cross @ cross


def single_window(device: torch.device, repeats: int) -> None:
    generator = torch.Generator().manual_seed(0)
    verts, faces = bumpy_spheres(1, generator, device)
    verts = (verts[0] * 0.5 + torch.tensor([0.05, -0.03, 2.0], device=device)).contiguous()
    K = torch.tensor([[[80.0, 0.0, 36.0], [0.0, 80.0, 36.0], [0.0, 0.0, 1.0]]], device=device)
    face_window = torch.zeros(faces.shape[0], dtype=torch.long, device=device)
    settings = SoftRasterSettings()
    weights = torch.rand(1, RESOLUTION, RESOLUTION, generator=generator).to(device)

    def run(fn):
        v = verts.clone().requires_grad_(True)
        image = fn(v, faces, face_window, K, RESOLUTION, RESOLUTION, settings)
        (image * weights).sum().backward()
        return image.detach(), v.grad

    sparse_t = timed(lambda: run(rasterize_soft), device, repeats)
    dense_t = timed(lambda: run(rasterize_soft_dense), device, max(1, repeats // 2))
    (sparse, sparse_grad), (dense, dense_grad) = run(rasterize_soft), run(rasterize_soft_dense)
    print(
        f"[{device.type}] single 72x72 window, ico-sphere level 3 ({verts.shape[0]} verts, {faces.shape[0]} faces), fwd+bwd:"
    )
    print(f"  sparse {fmt(sparse_t)} | dense {fmt(dense_t)}")
    print(f"  dense/sparse = {dense_t[0] / sparse_t[0]:.1f}x wall, {dense_t[1] / sparse_t[1]:.1f}x cpu")
    print(
        f"  max |sparse - dense|: output {(sparse - dense).abs().max().item():.2e}, "
        f"vertex grad {(sparse_grad - dense_grad).abs().max().item():.2e} (max |grad| {dense_grad.abs().max().item():.2e})"
    )


def hypersim_like_batch(device: torch.device, repeats: int, num_objects: int = 50, num_views: int = 5) -> None:
    generator = torch.Generator().manual_seed(1)
    f = 0.5 * WIDTH / math.tan(math.radians(60) / 2)
    K = torch.tensor([[f, 0.0, WIDTH / 2], [0.0, f, HEIGHT / 2], [0.0, 0.0, 1.0]])
    # Objects in view 1's frame: blobs 0.1-0.9 m across, 2-9 m away, inside the frustum.
    depth = 2.0 + 7.0 * torch.rand(num_objects, generator=generator)
    u = WIDTH * (0.1 + 0.8 * torch.rand(num_objects, generator=generator))
    v = HEIGHT * (0.1 + 0.8 * torch.rand(num_objects, generator=generator))
    centres = torch.stack([(u - WIDTH / 2) / f * depth, (v - HEIGHT / 2) / f * depth, depth], dim=1)
    shapes, faces = bumpy_spheres(num_objects, generator, torch.device("cpu"))
    sizes = 0.08 + 0.25 * torch.rand(num_objects, 1, 1, generator=generator)
    predicted = shapes * sizes + centres[:, None]
    truth = shapes * sizes * 1.1 + centres[:, None] + 0.1 * torch.randn(num_objects, 1, 3, generator=generator)
    # Views 2..M: small camera motions; R_{1->j} applied to every object.
    transforms = [torch.eye(4)]
    for _ in range(num_views - 1):
        T = torch.eye(4)
        T[:3, :3] = random_rotation(generator, math.radians(8))
        T[:3, 3] = 0.4 * torch.randn(3, generator=generator)
        transforms.append(T)
    pred_cam = torch.cat([transform_points(predicted, T) for T in transforms]).to(device)  # (P, V, 3), view-major
    true_cam = torch.cat([transform_points(truth, T) for T in transforms]).to(device)
    num_pairs, num_verts = pred_cam.shape[:2]
    faces = faces.to(device)
    packed_faces = (faces[None] + num_verts * torch.arange(num_pairs, device=device)[:, None, None]).reshape(-1, 3)
    face_pair = torch.arange(num_pairs, device=device).repeat_interleave(faces.shape[0])
    mesh_view = torch.arange(num_views, device=device).repeat_interleave(num_objects)
    Ks = K.to(device).expand(num_pairs, 3, 3)

    def hard_views():
        return rasterize_hard(
            true_cam.reshape(-1, 3),
            packed_faces,
            face_pair,
            K.to(device).expand(num_views, 3, 3),
            HEIGHT,
            WIDTH,
            mesh_view=mesh_view,
        )

    hard_t = timed(hard_views, device, max(1, repeats // 2))
    hard = hard_views()
    if device.type == "cpu":  # the compiled loop against the torch path it replaces (what CUDA runs)
        with torch_paths_only():
            hard_torch_t = timed(hard_views, device, max(1, repeats // 2))
            hard_torch = hard_views()
        same = torch.equal(hard.instance_map, hard_torch.instance_map) and torch.equal(
            hard.depth_map, hard_torch.depth_map
        )
    true_masks = PaddedMasks.of(hard.masks)
    visible = int((hard.masks.flatten(1).any(1)).sum())

    def dynamic():
        verts = pred_cam.reshape(-1, 3).clone().requires_grad_(True)
        out = render_dynamic(verts, packed_faces, face_pair, Ks, true_masks, resolution=RESOLUTION)
        F.binary_cross_entropy(out.soft.clamp(1e-6, 1 - 1e-6), out.target).backward()
        return out

    out = dynamic()
    K_window = out.K_window

    def raster_only():
        verts = pred_cam.reshape(-1, 3).clone().requires_grad_(True)
        rasterize_soft(verts, packed_faces, face_pair, K_window, RESOLUTION, RESOLUTION).sum().backward()

    dynamic_t = timed(dynamic, device, repeats)
    raster_t = timed(raster_only, device, repeats)
    side = (out.windows[:, 2] - out.windows[:, 0]).median().item()
    print(
        f"[{device.type}] Hypersim-like batch: {num_objects} objects x {num_views} views = {num_pairs} windows at {RESOLUTION}x{RESOLUTION} "
        f"({num_pairs * faces.shape[0]} faces; {visible} pairs visible; median window {side:.0f} px):"
    )
    print(
        f"  render_dynamic fwd+bwd (windows, targets, raster) {fmt(dynamic_t)} -> {num_pairs / dynamic_t[0]:7.1f} object-views/s "
        f"({num_pairs / dynamic_t[1]:.1f} per cpu-second)"
    )
    print(
        f"  rasterize_soft fwd+bwd only                       {fmt(raster_t)} -> {num_pairs / raster_t[0]:7.1f} object-views/s "
        f"({num_pairs / raster_t[1]:.1f} per cpu-second)"
    )
    print(f"  rasterize_hard, {num_views} full {HEIGHT}x{WIDTH} views, {num_pairs} meshes  {fmt(hard_t)}")
    if device.type == "cpu":
        print(
            f"  rasterize_hard's torch path (CUDA's)                {fmt(hard_torch_t)} -> compiled loop "
            f"{hard_torch_t[1] / hard_t[1]:.1f}x less CPU, same maps: {same}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cpu", help="cpu or cuda (part 1 always also runs on the CPU)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    # Timings of many small ops suffer badly when other processes compete for the cores
    # (each OpenMP region waits for descheduled threads): print the load so runs can be judged.
    print(
        f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads, device {device}, "
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"
    )
    single_window(torch.device("cpu"), args.repeats)
    if device.type != "cpu":
        single_window(device, args.repeats)
    hypersim_like_batch(device, args.repeats)


if __name__ == "__main__":
    main()
