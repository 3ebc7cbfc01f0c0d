"""The sparse soft rasterizer's CPU path: pair selection and log-transparency terms as compiled loops.

:func:`usl.render.soft.rasterize_soft` spends most of a CPU training step in two places when it
runs as torch ops: the no-grad selection of (face, pixel) pairs (a dozen elementwise ops on every
candidate pair, then one big sort for the nearest K per pixel) and autograd through the signed
distance of the kept pairs (dozens of small ops forward and backward). Here both are loops compiled
by numba (as the NMS's CPU loop in ``usl.model.ops.nms``; cached on disk, compiled once per machine
and dtype):

* :func:`select_pairs` walks each face's pixel box once, with the torch path's arithmetic in the
  faces' dtype, so it keeps exactly the same pairs in the same order (face after face, row-major in
  the box); the nearest K per pixel are then picked from per-pixel buckets with ties going to the
  earlier pair, as the torch path's stable sort does.
* :class:`LogTransparency` sums ``log sigmoid(d / sigma)`` per pixel and has an analytic backward
  into the (16, F) face table: ``d`` is recomputed pair by pair, so nothing per pair is stored
  beyond the (face, pixel) indices, and no checkpointing is needed.

The torch path stays for CUDA (and is the oracle of the tests); these loops run on CPU tensors of
float32 or float64 when numba imports. The loops allocate nothing: outputs are preallocated here.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from usl.render.screen import FaceBoxes, ScreenFaces

Tensor = torch.Tensor
_NUMPY_DTYPES = {torch.float32: np.float32, torch.float64: np.float64}


def available(table: Tensor) -> bool:
    """Whether the compiled loops serve faces held in ``table`` (a CPU float32/float64 tensor)."""
    return numba is not None and table.device.type == "cpu" and table.dtype in (torch.float32, torch.float64)


def select_pairs(
    screen: ScreenFaces, face_window: Tensor, boxes: FaceBoxes, height: int, width: int, scale2: float, settings
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The torch path's ``_select_pairs`` (the same pairs in the same order) as int64 (face, flat
    pixel) arrays, and the faces' (16, F) plane table as a numpy array, read once here for
    :class:`LogTransparency`. ``scale2``: squared normalised units per squared pixel; ``settings``:
    the :class:`~usl.render.soft.SoftRasterSettings`."""
    table = torch.cat([screen.plane.detach(), screen.depths.detach()]).numpy()  # (22, F)
    ints = torch.stack([face_window, boxes.x0, boxes.y0, boxes.nx, boxes.ny]).numpy()  # (5, F)
    capacity = int(np.dot(ints[3], ints[4]))
    face = np.empty(capacity, dtype=np.int64)
    pixel = np.empty(capacity, dtype=np.int64)
    depth = np.empty(capacity, dtype=np.float32)
    constants = _constants(screen.plane.dtype, scale2, settings.blur_radius)
    centres = _centres(height, width, screen.plane.dtype)
    count = _select_loop(table, ints, centres, constants, height, width, face, pixel, depth)
    face, pixel, depth = face[:count], pixel[:count], depth[:count]
    k = settings.faces_per_pixel
    if k is not None and count:
        keep = np.empty(count, dtype=np.bool_)
        _nearest_loop(
            pixel,
            depth.view(np.int32),  # positive floats order like their bit patterns (the torch path's sort key)
            k,
            np.zeros(int(pixel.max()) + 2, dtype=np.int64),
            np.empty(count, dtype=np.int64),
            np.empty(k, dtype=np.int32),
            np.empty(k, dtype=np.int64),
            keep,
        )
        face, pixel = face[keep], pixel[keep]
    return face, pixel, table[:16]


class LogTransparency(torch.autograd.Function):
    """Per flat pixel, the sum of ``log sigmoid(d * scale)`` over its kept pairs (``scale`` =
    squared NDC units per squared pixel / sigma), differentiable w.r.t. the (16, F) plane table.

    ``plane_np`` is ``plane``'s data as read by :func:`select_pairs`; ``face`` and ``pixel`` its
    kept pairs. The backward is the derivative of the torch path's ops, ties included: an exact tie
    between two edge distances splits the gradient in halves as ``torch.minimum`` does, and the
    clamp of the projection onto an edge passes gradient at its bounds as ``torch.clamp`` does.
    """

    @staticmethod
    def forward(ctx, plane, plane_np, face, pixel, num_pixels, height, width, scale):  # noqa: D102
        out = np.zeros(num_pixels, dtype=plane_np.dtype)
        centres = _centres(height, width, plane.dtype)
        constants = _constants(plane.dtype, scale, 0.0)
        _terms_loop(plane_np, face, pixel, centres, constants, height, width, out)
        ctx.save_for_backward(plane)  # only for autograd's check that plane was not modified in place
        ctx.pairs = (plane_np, face, pixel, centres, constants, height, width)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad):  # noqa: D102
        (plane,) = ctx.saved_tensors
        plane_np, face, pixel, centres, constants, height, width = ctx.pairs
        grad_plane = np.zeros(plane_np.shape, dtype=plane_np.dtype)
        _terms_backward_loop(
            plane_np, face, pixel, centres, constants, height, width, grad.contiguous().numpy(), grad_plane
        )
        return torch.from_numpy(grad_plane), None, None, None, None, None, None, None


def _centres(height: int, width: int, dtype: torch.dtype) -> np.ndarray:
    """Pixel-centre coordinates 0.5, 1.5, ... in the faces' dtype (``pixel_centres``' arithmetic)."""
    return np.arange(max(height, width)).astype(_NUMPY_DTYPES[dtype]) + _NUMPY_DTYPES[dtype](0.5)


def _constants(dtype: torch.dtype, scale: float, threshold: float) -> np.ndarray:
    """[scale, threshold, 0, 1] rounded to the faces' dtype, as torch rounds a Python scalar
    operand; typed constants keep the compiled arithmetic in float32 for float32 faces."""
    return np.array([scale, threshold, 0.0, 1.0], dtype=_NUMPY_DTYPES[dtype])


# ----------------------------------------------------------------------------- compiled loops
try:  # numba is a dependency; without it the torch path serves the CPU too
    import numba
except ImportError:
    numba = None


def _compiled(loop):
    """numba's error model: x / 0 gives inf or nan as in torch; cache: compiled once per machine, on disk."""
    return numba.njit(cache=True, nogil=True, error_model="numpy")(loop) if numba else loop


# Plane rows: corners x0 y0 x1 y1 x2 y2 (0-5), edge vectors ex0 ey0 ex1 ey1 ex2 ey2 (6-11), inverse
# squared edge lengths (12-14), 1 / twice the signed area (15); edge k runs from corner k + 1.
# Depth rows (16-21 of the selection's table): w0 w1 w2 z0 z1 z2.


@_compiled
def _edge_sq_distance(px, py, ax, ay, ex, ey, il, zero, one):  # pragma: no cover
    """Squared distance to one edge, its barycentric numerator term and the clamped projection."""
    rx, ry = px - ax, py - ay
    u = (rx * ex + ry * ey) * il
    t = zero if u < zero else (one if u > one else u)
    ox, oy = rx - t * ex, ry - t * ey
    return ox * ox + oy * oy, ex * ry - ey * rx, u, t, rx, ry, ox, oy


@_compiled
def _signed_sq_distance(plane, f, px, py, zero, one):  # pragma: no cover
    """``usl.render.screen.signed_sq_distance`` of one pair, op for op; also the three edge
    distances (for the backward) and the screen barycentrics (for the depth)."""
    inv_area = plane[15, f]
    d0, n0, _, _, _, _, _, _ = _edge_sq_distance(
        px, py, plane[2, f], plane[3, f], plane[6, f], plane[7, f], plane[12, f], zero, one
    )
    d1, n1, _, _, _, _, _, _ = _edge_sq_distance(
        px, py, plane[4, f], plane[5, f], plane[8, f], plane[9, f], plane[13, f], zero, one
    )
    d2, n2, _, _, _, _, _, _ = _edge_sq_distance(
        px, py, plane[0, f], plane[1, f], plane[10, f], plane[11, f], plane[14, f], zero, one
    )
    b0, b1, b2 = n0 * inv_area, n1 * inv_area, n2 * inv_area
    m = d0 if d0 <= d1 else d1  # torch.minimum; equal values are equal either way
    m = m if m <= d2 else d2
    inside = b0 >= zero and b1 >= zero and b2 >= zero
    return (-m if inside else m), inside, d0, d1, d2, b0, b1, b2


@_compiled
def _select_loop(table, ints, centres, constants, height, width, face_out, pixel_out, depth_out):  # pragma: no cover
    """Every pair in the faces' boxes with ``d * ndc_scale**2 <= blur_radius``, face after face,
    row-major in the box; writes face, flat pixel and float32 clipped perspective depth, returns
    how many."""
    scale2, blur, zero, one = constants[0], constants[1], constants[2], constants[3]
    count = 0
    for f in range(table.shape[1]):
        nx, ny = ints[3, f], ints[4, f]
        if nx == 0 or ny == 0:
            continue
        base = ints[0, f] * height
        w0, w1, w2, z0, z1, z2 = table[16, f], table[17, f], table[18, f], table[19, f], table[20, f], table[21, f]
        for row in range(ints[2, f], ints[2, f] + ny):
            py = centres[row]
            for col in range(ints[1, f], ints[1, f] + nx):
                dist, _, _, _, _, b0, b1, b2 = _signed_sq_distance(table, f, centres[col], py, zero, one)
                if not dist * scale2 <= blur:
                    continue
                # usl.render.screen.perspective_depth(clip=True), op for op
                q0 = (b0 if b0 >= zero else zero) / w0
                q1 = (b1 if b1 >= zero else zero) / w1
                q2 = (b2 if b2 >= zero else zero) / w2
                face_out[count] = f
                pixel_out[count] = (base + row) * width + col
                depth_out[count] = np.float32((q0 * z0 + q1 * z1 + q2 * z2) / (q0 + q1 + q2))
                count += 1
    return count


@_compiled
def _nearest_loop(pixel, depth_bits, k, start, order, top_bits, top_index, keep):  # pragma: no cover
    """keep[i]: pair i ranks among the k smallest ``depth_bits`` of its pixel, ties going to the
    earlier pair. Pairs are bucketed by pixel in their order (a counting sort), and each bucket with
    more than k pairs keeps a sorted list of its k best."""
    for i in range(pixel.shape[0]):
        start[pixel[i] + 1] += 1
        keep[i] = True
    for p in range(1, start.shape[0]):
        start[p] += start[p - 1]
    for i in range(pixel.shape[0]):  # start[p] advances to the end of bucket p - 1, then is restored
        order[start[pixel[i]]] = i
        start[pixel[i]] += 1
    for p in range(start.shape[0] - 2, -1, -1):
        start[p + 1] = start[p]
    start[0] = 0
    for p in range(start.shape[0] - 1):
        lo, hi = start[p], start[p + 1]
        if hi - lo <= k:
            continue
        size = 0
        for j in range(lo, hi):
            i = order[j]
            bits = depth_bits[i]
            keep[i] = False
            if size == k:
                if bits >= top_bits[k - 1]:  # an equal depth loses to the earlier pair
                    continue
                size -= 1
            slot = size
            while slot > 0 and top_bits[slot - 1] > bits:
                top_bits[slot], top_index[slot] = top_bits[slot - 1], top_index[slot - 1]
                slot -= 1
            top_bits[slot], top_index[slot] = bits, i
            size += 1
        for slot in range(k):
            keep[top_index[slot]] = True


@_compiled
def _terms_loop(plane, face, pixel, centres, constants, height, width, out):  # pragma: no cover
    """out[pixel] += log sigmoid(d * scale), pair by pair in order (index_add's order); torch's
    log_sigmoid arithmetic: min(x, 0) - log1p(exp(-|x|))."""
    scale, zero, one = constants[0], constants[2], constants[3]
    for i in range(face.shape[0]):
        p = pixel[i]
        dist, _, _, _, _, _, _, _ = _signed_sq_distance(
            plane, face[i], centres[p % width], centres[(p // width) % height], zero, one
        )
        x = dist * scale
        out[p] += (x if x < zero else zero) - math.log1p(math.exp(-abs(x)))


@_compiled
def _terms_backward_loop(plane, face, pixel, centres, constants, height, width, grad, grad_plane):  # pragma: no cover
    """Accumulates into grad_plane (16, F) the derivative of :func:`_terms_loop`'s sum w.r.t. the
    plane rows, following the torch path's autograd formulas."""
    scale, zero, one = constants[0], constants[2], constants[3]
    half = one / (one + one)
    for i in range(face.shape[0]):
        p, f = pixel[i], face[i]
        px, py = centres[p % width], centres[(p // width) % height]
        dist, inside, d0, d1, d2, _, _, _ = _signed_sq_distance(plane, f, px, py, zero, one)
        x = dist * scale
        z = math.exp(-abs(x))
        g = grad[p] * ((one - z / (one + z)) if x < zero else z / (one + z)) * scale  # d / d dist
        g = -g if inside else g
        # torch.minimum(torch.minimum(d0, d1), d2): exact ties share the gradient in halves
        m01 = d0 if d0 <= d1 else d1
        g01 = g if m01 < d2 else (g * half if m01 == d2 else zero)
        g2 = g if d2 < m01 else (g * half if d2 == m01 else zero)
        g0 = g01 if d0 < d1 else (g01 * half if d0 == d1 else zero)
        g1 = g01 if d1 < d0 else (g01 * half if d1 == d0 else zero)
        _edge_backward(plane, grad_plane, f, px, py, g0, 2, 3, 6, 7, 12, zero, one)
        _edge_backward(plane, grad_plane, f, px, py, g1, 4, 5, 8, 9, 13, zero, one)
        _edge_backward(plane, grad_plane, f, px, py, g2, 0, 1, 10, 11, 14, zero, one)


@_compiled
def _edge_backward(plane, grad_plane, f, px, py, g, ax, ay, ex, ey, il, zero, one):  # pragma: no cover
    """Gradient of one edge's squared distance (times g) into its plane rows."""
    if g == zero:
        return
    vx, vy, inv = plane[ex, f], plane[ey, f], plane[il, f]
    _, _, u, t, rx, ry, ox, oy = _edge_sq_distance(px, py, plane[ax, f], plane[ay, f], vx, vy, inv, zero, one)
    g_ox, g_oy = (g + g) * ox, (g + g) * oy
    g_rx, g_ry = g_ox, g_oy
    g_vx, g_vy = -g_ox * t, -g_oy * t
    if zero <= u <= one:  # torch.clamp passes gradient inside [0, 1], bounds included
        g_u = -(g_ox * vx + g_oy * vy)
        grad_plane[il, f] += g_u * (rx * vx + ry * vy)
        g_s = g_u * inv
        g_rx += g_s * vx
        g_ry += g_s * vy
        g_vx += g_s * rx
        g_vy += g_s * ry
    grad_plane[ax, f] -= g_rx
    grad_plane[ay, f] -= g_ry
    grad_plane[ex, f] += g_vx
    grad_plane[ey, f] += g_vy
