"""The sparse soft rasterizer's CPU path: pair selection and log-transparency terms as compiled loops.

:func:`usl.render.soft.rasterize_soft` spends most of a CPU training step in two places when it
runs as torch ops: the no-grad selection of (face, pixel) pairs (a dozen elementwise ops on every
candidate pair, then one big sort for the nearest K per pixel) and autograd through the signed
distance of the kept pairs (dozens of small ops forward and backward). Here both are loops compiled
by numba (:mod:`usl.utils.compiled`):

* :func:`select_pairs` walks each face's pixel box once, with the torch path's arithmetic in the
  faces' dtype, so it keeps exactly the same pairs in the same order (face after face, row-major in
  the box). For each it also keeps the signed distance ``d`` and which edges the gradient of the
  distance's minimum goes to. The nearest K of a pixel with more candidates are picked from a
  bucket of that pixel's depths, ties going to the earlier pair, as the torch path's stable sort does.
* :class:`LogTransparency` sums ``log sigmoid(d / sigma)`` per pixel and has an analytic backward
  into the (16, F) face table that follows the torch path's autograd formulas, ties included.
  Per pair it stores a few bytes, not autograd's dozens of tensors, so no checkpointing is needed.

The torch path stays for CUDA (and is the oracle of the tests); these loops run on CPU tensors of
float32 or float64 when numba imports.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from usl.render.face_tables import NUMPY_DTYPES, box_table, centres, face_row, face_table
from usl.render.screen import ScreenFaces, blur_margin_pixels, face_pixel_boxes, ndc_scale
from usl.utils.compiled import compiled

Tensor = torch.Tensor


@dataclass
class Pairs:
    """The kept (face, pixel) pairs: face and flat pixel ``window * H * W + row * W + col`` (int32),
    the signed squared pixel distance ``d`` (the faces' dtype), and ``share`` (uint8): 2 bits per
    edge k at bit 2k, the share of the gradient of ``d`` that edge k's distance takes (0: none,
    1: all, 2: half, 3: a quarter, as nested ``torch.minimum`` splits exact ties), and bit 6 set
    when the pixel is inside (``d = -min``). ``faces``: the (F, 22) face table the pairs were
    selected from (the 16 :class:`~usl.render.screen.Plane` fields, then the 6
    :class:`~usl.render.screen.Depths` fields, as columns); ``centres``: pixel-centre coordinates
    0.5, 1.5, ... in the faces' dtype."""

    face: np.ndarray
    pixel: np.ndarray
    dist: np.ndarray
    share: np.ndarray
    faces: np.ndarray
    centres: np.ndarray
    height: int
    width: int


def select_pairs(
    screen: ScreenFaces, face_window: Tensor, num_windows: int, height: int, width: int, settings
) -> Pairs:
    """The torch path's ``_select_pairs``, the same pairs in the same order (``settings``: the
    :class:`~usl.render.soft.SoftRasterSettings`)."""
    np_dtype = NUMPY_DTYPES[screen.plane.dtype]
    boxes = face_pixel_boxes(screen, blur_margin_pixels(settings.blur_radius, height, width), height, width)
    faces, ints = face_table(screen), box_table(face_window, boxes)
    capacity = int(np.dot(ints[:, 3], ints[:, 4]))
    face, pixel = np.empty(capacity, dtype=np.int32), np.empty(capacity, dtype=np.int32)
    depth, dist = np.empty(capacity, dtype=np.float32), np.empty(capacity, dtype=np_dtype)
    share = np.empty(capacity, dtype=np.uint8)
    counts = np.zeros(num_windows * height * width, dtype=np.int32)
    constants = np.array([ndc_scale(height, width) ** 2, settings.blur_radius, 0.0, 1.0], dtype=np_dtype)
    pixel_centres = centres(max(height, width), np_dtype)
    row, codes = np.empty((2, width), dtype=np_dtype), np.empty(width, dtype=np.int32)
    count = _select_loop(
        faces, ints, pixel_centres, constants, height, width, face, pixel, depth, dist, share, counts, row, codes
    )
    k = settings.faces_per_pixel
    if k is not None and count:
        count = _nearest_loop(
            face[:count],
            pixel[:count],
            depth[:count].view(np.int32),  # positive floats order like their bit patterns (the torch sort key)
            dist[:count],
            share[:count],
            counts,
            k,
            np.empty(count, dtype=np.int32),
            np.empty(count, dtype=np.int32),
            np.empty(len(counts), dtype=np.int32),
            np.empty(len(counts), dtype=np.int32),
            np.empty(k, dtype=np.int32),
            np.empty(k, dtype=np.int32),
        )
    return Pairs(face[:count], pixel[:count], dist[:count], share[:count], faces, pixel_centres, height, width)


class LogTransparency(torch.autograd.Function):
    """Per flat pixel, the sum of ``log sigmoid(d * scale)`` over its kept pairs (``scale`` =
    squared normalised units per squared pixel / sigma), differentiable w.r.t. the (16, F) plane
    table ``plane`` that ``pairs`` (from :func:`select_pairs`) were selected from.

    The backward is the derivative of the torch path's ops: an exact tie between edge distances
    splits the gradient as ``torch.minimum`` does, and the clamp of the projection onto an edge
    passes gradient at its bounds as ``torch.clamp`` does.
    """

    @staticmethod
    def forward(ctx, plane: Tensor, pairs: Pairs, num_pixels: int, scale: float) -> Tensor:  # noqa: D102
        np_dtype = pairs.faces.dtype
        out = np.zeros(num_pixels, dtype=np_dtype)
        slope = np.empty(len(pairs.face), dtype=np_dtype)
        constants = np.array([scale, 0.0, 1.0], dtype=np_dtype)
        _terms_loop(pairs.pixel, pairs.dist, pairs.share, constants, out, slope)
        ctx.save_for_backward(plane)  # for autograd's check that plane was not modified in place
        ctx.pairs, ctx.slope, ctx.constants = pairs, slope, constants
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad: Tensor) -> tuple[Tensor | None, ...]:  # noqa: D102
        _ = ctx.saved_tensors
        pairs = ctx.pairs
        grad_plane = np.zeros((pairs.faces.shape[0], 16), dtype=pairs.faces.dtype)
        _terms_backward_loop(
            pairs.faces,
            pairs.face,
            pairs.pixel,
            pairs.share,
            ctx.slope,
            pairs.centres,
            ctx.constants,
            pairs.width,
            pairs.height,
            grad.contiguous().numpy(),
            grad_plane,
        )
        return torch.from_numpy(grad_plane).t(), None, None, None


# ----------------------------------------------------------------------------- compiled loops
# Constants come in arrays of the faces' dtype, so float32 arithmetic stays float32 (a Python float
# literal would promote it) and scalars are rounded to that dtype as torch rounds a Python operand.
# Face table columns: corners x0 y0 x1 y1 x2 y2 (0-5), edge vectors ex0 ey0 ex1 ey1 ex2 ey2 (6-11),
# inverse squared edge lengths (12-14), 1 / twice the signed area (15), then w0 w1 w2 z0 z1 z2
# (16-21). Edge k runs from corner k + 1 (its columns: see _edge_backward).
@compiled
def _edge_sq_distance(px, py, ax, ay, ex, ey, il, zero, one):  # pragma: no cover
    """``usl.render.screen.signed_sq_distance`` for one edge, op for op: the squared distance, the
    barycentric numerator, and the projection before and after its clamp to [0, 1]."""
    rx, ry = px - ax, py - ay
    u = (rx * ex + ry * ey) * il
    t = zero if u < zero else (one if u > one else u)
    ox, oy = rx - t * ex, ry - t * ey
    return ox * ox + oy * oy, ex * ry - ey * rx, u, t, rx, ry, ox, oy


@compiled
def _tie_share(a, b, zero_if_above):  # pragma: no cover
    """Share code of ``a`` in ``torch.minimum(a, b)``'s gradient: 1 all, 2 half, 0 none; combined
    with the share of the minimum itself (``zero_if_above``: that share, 0 for none)."""
    own = 1 if a < b else (2 if a == b else 0)
    return 0 if own == 0 or zero_if_above == 0 else own + zero_if_above - 1


@compiled
def _select_loop(
    faces,
    ints,
    centres,
    constants,
    height,
    width,
    face_out,
    pixel_out,
    depth_out,
    dist_out,
    share_out,
    counts,
    row,
    codes,
):  # pragma: no cover
    """Every pair in the faces' boxes with ``d * ndc_scale**2 <= blur_radius``, face after face,
    row-major in the box: writes face, flat pixel, float32 clipped perspective depth, d and the
    gradient shares, counts the pairs of each pixel, and returns how many pairs.

    Each box row is first evaluated without branches into the scratch ``row`` (2, W) (d, depth)
    and ``codes`` (W,) (shares, bit 7: within the blur radius), a loop the compiler vectorizes;
    then every pair of the row is written at the output's end, which advances only past the pairs
    kept (no branch to mispredict)."""
    scale2, blur, zero, one = constants[0], constants[1], constants[2], constants[3]
    dists, depths = row[0], row[1]
    count = 0
    for f in range(faces.shape[0]):
        nx, ny = ints[f, 3], ints[f, 4]
        if nx == 0 or ny == 0:
            continue
        x0, y0, x1, y1, x2, y2, ex0, ey0, ex1, ey1, ex2, ey2, il0, il1, il2, inv_area, w0, w1, w2, z0, z1, z2 = (
            face_row(faces[f])
        )
        base, col0, row0 = ints[f, 0] * height, ints[f, 1], ints[f, 2]
        for r in range(row0, row0 + ny):
            py = centres[r]
            for j in range(nx):
                px = centres[col0 + j]
                d0, n0, _, _, _, _, _, _ = _edge_sq_distance(px, py, x1, y1, ex0, ey0, il0, zero, one)
                d1, n1, _, _, _, _, _, _ = _edge_sq_distance(px, py, x2, y2, ex1, ey1, il1, zero, one)
                d2, n2, _, _, _, _, _, _ = _edge_sq_distance(px, py, x0, y0, ex2, ey2, il2, zero, one)
                b0, b1, b2 = n0 * inv_area, n1 * inv_area, n2 * inv_area
                m01 = d0 if d0 <= d1 else d1  # torch.minimum (equal values are equal either way)
                m = m01 if m01 <= d2 else d2
                inside = (b0 >= zero) & (b1 >= zero) & (b2 >= zero)
                dist = -m if inside else m
                dists[j] = dist
                # usl.render.screen.perspective_depth(clip=True), op for op
                q0 = (b0 if b0 >= zero else zero) / w0
                q1 = (b1 if b1 >= zero else zero) / w1
                q2 = (b2 if b2 >= zero else zero) / w2
                depths[j] = (q0 * z0 + q1 * z1 + q2 * z2) / (q0 + q1 + q2)
                s01 = 1 if m01 < d2 else (2 if m01 == d2 else 0)
                codes[j] = (
                    _tie_share(d0, d1, s01)
                    | (_tie_share(d1, d0, s01) << 2)
                    | (_tie_share(d2, m01, 1) << 4)
                    | (64 if inside else 0)
                    | (128 if dist * scale2 <= blur else 0)
                )
            p = (base + r) * width + col0
            for j in range(nx):
                code = codes[j]
                face_out[count] = f
                pixel_out[count] = p + j
                depth_out[count] = np.float32(depths[j])
                dist_out[count] = dists[j]
                share_out[count] = code & 127
                kept = code >> 7
                counts[p + j] += kept
                count += kept
    return count


@compiled
def _nearest_loop(
    face, pixel, depth_bits, dist, share, counts, k, buckets, slot_of, limit_bits, limit_slot, top_bits, top_slot
):  # pragma: no cover
    """Keeps, in place and in order, the pairs that rank among the k smallest ``depth_bits`` of
    their pixel (ties going to the earlier pair); returns how many.

    The depths of pixels with more than k pairs are bucketed by pixel in pair order (a counting
    sort; ``slot_of`` records each pair's slot), so a slot orders equal depths as pair order does.
    A sorted list of each bucket's k best (``top_*``) gives the pixel's k-th (depth, slot), and a
    pair is kept when its own does not exceed it. ``counts`` (pairs per pixel) is overwritten."""
    total = 0
    for p in range(counts.shape[0]):  # counts[p] -> start of p's bucket, or -1 (k or fewer pairs)
        n = counts[p]
        counts[p] = total if n > k else -1
        if n > k:
            total += n
    for i in range(pixel.shape[0]):
        slot = counts[pixel[i]]
        slot_of[i] = slot
        if slot >= 0:  # the bucket's fill pointer advances to the bucket's end
            buckets[slot] = depth_bits[i]
            counts[pixel[i]] = slot + 1
    end = 0
    for p in range(counts.shape[0]):
        if counts[p] < 0:
            continue
        start, end = end, counts[p]
        size = 0
        for slot in range(start, end):
            bits = buckets[slot]
            if size == k:
                if bits >= top_bits[k - 1]:  # an equal depth loses to the earlier pair
                    continue
                size -= 1
            rank = size
            while rank > 0 and top_bits[rank - 1] > bits:
                top_bits[rank], top_slot[rank] = top_bits[rank - 1], top_slot[rank - 1]
                rank -= 1
            top_bits[rank], top_slot[rank] = bits, slot
            size += 1
        limit_bits[p], limit_slot[p] = top_bits[k - 1], top_slot[k - 1]
    kept = 0
    for i in range(pixel.shape[0]):  # written in place, the end advancing past kept pairs only
        p, slot, bits = pixel[i], slot_of[i], depth_bits[i]
        keep = slot < 0 or bits < limit_bits[p] or (bits == limit_bits[p] and slot <= limit_slot[p])
        face[kept], pixel[kept], dist[kept], share[kept] = face[i], p, dist[i], share[i]
        kept += keep
    return kept


@compiled
def _terms_loop(pixel, dist, share, constants, out, slope):  # pragma: no cover
    """out[pixel] += log sigmoid(d * scale), pair by pair in order (index_add's order), with torch's
    log_sigmoid arithmetic min(x, 0) - log1p(exp(-|x|)); slope: the derivative w.r.t. the minimum
    edge distance (log_sigmoid's backward formula, times scale, negated inside)."""
    scale, zero, one = constants[0], constants[1], constants[2]
    for i in range(pixel.shape[0]):
        x = dist[i] * scale
        z = math.exp(-abs(x))
        out[pixel[i]] += (x if x < zero else zero) - math.log1p(z)
        s = ((one - z / (one + z)) if x < zero else z / (one + z)) * scale
        slope[i] = -s if share[i] & 64 else s


@compiled
def _terms_backward_loop(
    faces, face, pixel, share, slope, centres, constants, width, height, grad, grad_plane
):  # pragma: no cover
    """Accumulates into grad_plane (F, 16) the derivative of :func:`_terms_loop`'s sums (times
    ``grad``) w.r.t. the plane columns, edge by edge as the pairs' shares say."""
    zero, one = constants[1], constants[2]
    half = one / (one + one)
    for i in range(face.shape[0]):
        p, f = pixel[i], face[i]
        g = grad[p] * slope[i]
        px, py = centres[p % width], centres[(p // width) % height]
        for edge in range(3):
            code = (share[i] >> (2 * edge)) & 3
            if code == 0:
                continue
            g_edge = g if code == 1 else (g * half if code == 2 else g * half * half)
            _edge_backward(faces[f], grad_plane[f], px, py, g_edge, edge, zero, one)


@compiled
def _edge_backward(c, grad, px, py, g, edge, zero, one):  # pragma: no cover
    """Adds g times the gradient of edge ``edge``'s squared distance to its face's columns."""
    ax, ex, il = (2, 6, 12) if edge == 0 else ((4, 8, 13) if edge == 1 else (0, 10, 14))
    vx, vy, inv = c[ex], c[ex + 1], c[il]
    _, _, u, t, rx, ry, ox, oy = _edge_sq_distance(px, py, c[ax], c[ax + 1], vx, vy, inv, zero, one)
    g_ox, g_oy = (g + g) * ox, (g + g) * oy
    g_rx, g_ry, g_vx, g_vy = g_ox, g_oy, -g_ox * t, -g_oy * t
    if zero <= u <= one:  # torch.clamp passes gradient inside [0, 1], bounds included
        g_u = -(g_ox * vx + g_oy * vy)
        grad[il] += g_u * (rx * vx + ry * vy)
        g_s = g_u * inv
        g_rx += g_s * vx
        g_ry += g_s * vy
        g_vx += g_s * rx
        g_vy += g_s * ry
    grad[ax] -= g_rx
    grad[ax + 1] -= g_ry
    grad[ex] += g_vx
    grad[ex + 1] += g_vy
