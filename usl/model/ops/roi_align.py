"""RoIAlign in pure torch, with torchvision's exact sampling semantics.

Why it is built this way: bilinear interpolation with torchvision's boundary rules is
*separable*: the value sampled at ``(y, x)`` is ``sum_ij wy_i(y) wx_j(x) f[i, j]`` where
each axis weight is zero when that coordinate falls outside ``[-1, size]``, and a zero
in either factor zeroes the sample exactly as torchvision's "empty" test does. Averaging
over a bin's sampling grid keeps the product form, so each RoI reduces to

    out[c] = Wy @ f[c, window] @ Wx^T

with ``Wy`` (out_h, window_h) and ``Wx`` (out_w, window_w) small dense weight matrices
and ``window`` the feature rows/columns the RoI touches. This costs ~RoI area per
channel (not ``out_h * out_w * 4 * grid^2`` gathers) and handles the adaptive
sampling grid (a different grid per RoI) without padding samples.

RoIs are processed in chunks of similar window size so memory stays bounded; there is
no Python loop over RoIs. The RoIs are laid out in chunk order once, so a chunk's matrices
and output are strided views and its work is two ``bmm`` calls (a few ops per chunk, which
is what a CUDA step pays for). The backward pass is written out (the transposed matmuls and
one ``index_add_`` into a single gradient buffer): autograd through the gathers would
allocate a full-size input gradient per chunk.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from usl.utils.transfer import constant, to_device

from .autocast import autocast_off

Tensor = torch.Tensor
BoxesArg = Tensor | Sequence[Tensor]

# Upper bound on the gathered feature elements held at once (64 MiB in float32).
DEFAULT_CHUNK_ELEMENTS = 1 << 24
# RoIs whose window sides agree within this factor are pooled together (padded to the largest)...
_BUCKET_GROWTH = 1.5
# ...and such groups merged while padding them to a common window gathers fewer elements than this:
# a chunk costs a few dozen ops (forward and backward) whatever its size.
_CHUNK_COST = 1 << 20


def convert_boxes_to_rois(boxes: BoxesArg, like: Tensor) -> Tensor:
    """Turn ``list[Tensor[Ki, 4]]`` (one per image) into ``Tensor[K, 5]`` (batch_idx, x0, y0, x1, y1)."""
    if isinstance(boxes, Tensor):
        if boxes.dim() != 2 or boxes.shape[1] != 5:
            raise ValueError(f"RoIs given as one tensor must be (K, 5), got {tuple(boxes.shape)}")
        return boxes
    per_image = []
    for image_index, image_boxes in enumerate(boxes):
        if image_boxes.dim() != 2 or image_boxes.shape[1] != 4:
            raise ValueError(f"boxes[{image_index}] must be (Ki, 4), got {tuple(image_boxes.shape)}")
        batch_column = image_boxes.new_full((image_boxes.shape[0], 1), image_index)
        per_image.append(torch.cat([batch_column, image_boxes], dim=1))
    if not per_image:
        return like.new_zeros((0, 5))
    return torch.cat(per_image, dim=0)


def roi_align(
    input: Tensor,
    boxes: BoxesArg,
    output_size: int | tuple[int, int],
    spatial_scale: float = 1.0,
    sampling_ratio: int = -1,
    aligned: bool = False,
    max_chunk_elements: int = DEFAULT_CHUNK_ELEMENTS,
) -> Tensor:
    """Pool each RoI of ``input`` (N, C, H, W) to ``(K, C, out_h, out_w)``.

    Args:
        boxes: ``Tensor[K, 5]`` rows ``(batch_idx, x0, y0, x1, y1)`` or ``list[Tensor[Ki, 4]]``,
            in input-image coordinates; ``spatial_scale`` maps them onto ``input``.
        sampling_ratio: samples per bin along each axis; ``<= 0`` means adaptive,
            ``ceil(roi_size / output_size)`` per RoI.
        aligned: shift boxes by -0.5 feature pixel so that pixel centres line up
            (detectron2's ROIAlignV2); when False, RoIs are at least 1x1 (legacy).
    Boxes receive no gradient (as in torchvision); ``input`` does. Integer or bool
    inputs (e.g. instance masks) are pooled in float32 without a float copy of the input.
    """
    rois = convert_boxes_to_rois(boxes, input)
    level = torch.zeros(rois.shape[0], dtype=torch.long, device=input.device)
    return roi_align_levels(
        [input], [spatial_scale], rois, level, output_size, sampling_ratio, aligned, max_chunk_elements
    )


def roi_align_levels(
    inputs: Sequence[Tensor],
    scales: Sequence[float],
    rois: Tensor,
    level: Tensor,
    output_size: int | tuple[int, int],
    sampling_ratio: int = -1,
    aligned: bool = False,
    max_chunk_elements: int = DEFAULT_CHUNK_ELEMENTS,
) -> Tensor:
    """:func:`roi_align` of each RoI (K, 5) from its own map: ``inputs[level[k]]`` (N, C, H_l, W_l),
    whose ``scales[level[k]]`` maps the box onto it. All levels are pooled in one pass (one host
    read of the RoI sizes the chunk shapes depend on), e.g. an FPN's levels."""
    out_h, out_w = (output_size, output_size) if isinstance(output_size, int) else tuple(output_size)
    first = inputs[0]
    num_images, channels = first.shape[:2]
    compute_dtype = torch.promote_types(first.dtype, torch.float32)
    out_dtype = first.dtype if first.is_floating_point() else compute_dtype
    rois = rois.detach().to(device=first.device, dtype=compute_dtype)
    num_rois = rois.shape[0]
    if num_rois == 0:
        return first.new_zeros((0, channels, out_h, out_w), dtype=out_dtype)
    device = first.device
    level = level.to(device)
    batch_index = rois[:, 0].long()
    # Both axes at once: row 0 the y axis, row 1 the x axis, (2, K) each.
    heights, widths = tuple(m.shape[2] for m in inputs), tuple(m.shape[3] for m in inputs)
    map_size = constant((heights, widths), torch.int64, device)[:, level]
    spatial_scale = constant(tuple(float(s) for s in scales), compute_dtype, device)[level]
    offset = 0.5 if aligned else 0.0
    corners = (rois[:, 1:] * spatial_scale[:, None] - offset).T  # (4, K): x0, y0, x1, y1
    start, end = corners.unflatten(0, (2, 2)).flip(1)  # (y0, x0), (y1, x1); a list index would upload
    roi_size = end - start
    if not aligned:
        roi_size = roi_size.clamp(min=1.0)
    bins = constant(((out_h,), (out_w,)), torch.int64, device)
    grid = _grid(roi_size, bins, sampling_ratio)
    # The only device-to-host transfer: the sizes every tensor shape below depends on.
    sizes = torch.cat([roi_size, grid.to(roi_size.dtype), map_size.to(roi_size.dtype)])  # (6, K)
    bounds = torch.stack([batch_index.min(), batch_index.max()]).to(sizes.dtype)
    host = torch.cat([bounds, sizes.T.flatten()]).cpu().numpy().astype(np.float64)
    if host[0] < 0 or host[1] >= num_images:
        raise ValueError(f"RoI batch indices must lie in [0, {num_images}), got [{int(host[0])}, {int(host[1])}]")
    host_roi_h, host_roi_w, host_grid_h, host_grid_w, host_h, host_w = np.nan_to_num(host[2:].reshape(-1, 6)).T
    max_grid = max(int(host_grid_h.max()), int(host_grid_w.max()), 1)
    samples = _axis_samples(start, roi_size, bins, map_size, grid, max(out_h, out_w), max_grid)
    window_h, window_w = _window_bound(host_roi_h, host_h), _window_bound(host_roi_w, host_w)
    plan = _plan_chunks(window_h, window_w, channels, max_chunk_elements)
    # Every RoI's axis matrices and window rows/columns, built once up to the largest chunk window;
    # each chunk then takes its RoIs' leading window_h x window_w part.
    window = int(max(max(h, w) for _, h, w in plan))
    matrices = _axis_matrices(samples, window)  # (2, K, max bins, window)
    # Rows/columns past the map's edge only occur where the matrices are zero; clamp them in.
    ids = torch.minimum(samples.start[..., None] + torch.arange(window, device=device), map_size[..., None] - 1)
    # where each (level, image) map starts in the channels-last concatenation of all levels
    pixels = constant(tuple(h * w for h, w in zip(heights, widths, strict=True)), torch.int64, device)
    level_start = torch.cumsum(pixels * num_images, 0) - pixels * num_images
    map_start = level_start[level] + batch_index * pixels[level]
    window_rows = map_start[:, None] + ids[0] * map_size[1, :, None]  # (K, window) first pixel of each row
    # Everything per RoI in plan order, so that each chunk is a block of consecutive rows: its
    # matrices and output are then strided views of one tensor, one op each.
    shapes = [(len(index), int(h), int(w)) for index, h, w in plan]
    rows_at, cols_at = _window_entries(plan, window)
    # one upload: the plan's RoI order and where each chunk's window pixels are in window_rows/col_ids
    uploaded = to_device(np.concatenate([*(index for index, _, _ in plan), rows_at, cols_at]), device)
    order, rows_at, cols_at = uploaded.split([num_rois, len(rows_at), len(cols_at)])
    pixels = window_rows.view(-1).index_select(0, rows_at) + ids[1].reshape(-1).index_select(0, cols_at)
    layout = _ChunkLayout(
        shapes=shapes,
        order=order,
        row_matrices=matrices[0, :, :out_h].index_select(0, order),
        # the column matrix once per output row: a chunk's column pass is then one plain bmm
        col_matrices=matrices[1, :, None, :out_w]
        .index_select(0, order)
        .expand(-1, out_h, -1, -1)
        .reshape(-1, out_w, window),
        pixels=pixels.split([k * h * w for k, h, w in shapes]),
    )
    # In compute_dtype under autocast too (as torchvision's autocast rule does): autocast would run
    # the pooling matmuls in bf16/fp16 and write them into the float32 output.
    with autocast_off(device.type):
        pooled = _RoIAlignFunction.apply(layout, compute_dtype, *inputs)
    return pooled.to(out_dtype)


class RoIAlign(nn.Module):
    """Module form of :func:`roi_align` with fixed pooling parameters."""

    def __init__(self, output_size, spatial_scale: float, sampling_ratio: int = -1, aligned: bool = True):
        super().__init__()
        self.output_size = output_size
        self.spatial_scale = spatial_scale
        self.sampling_ratio = sampling_ratio
        self.aligned = aligned

    def forward(self, input: Tensor, boxes: BoxesArg) -> Tensor:
        return roi_align(input, boxes, self.output_size, self.spatial_scale, self.sampling_ratio, self.aligned)

    def extra_repr(self) -> str:
        return (
            f"output_size={self.output_size}, spatial_scale={self.spatial_scale}, "
            f"sampling_ratio={self.sampling_ratio}, aligned={self.aligned}"
        )


@dataclass
class _AxisSamples:
    """Bilinear taps of A axes for every RoI: ``index``/``weight`` are (A, K, bins, taps)."""

    index: Tensor  # absolute feature row (or column) of each tap
    weight: Tensor  # bilinear weight / grid count; zero for invalid or padding taps
    start: Tensor  # (A, K) first row of the window the RoI touches


def _grid(roi_size: Tensor, bins: Tensor, sampling_ratio: int) -> Tensor:
    """Samples per bin along each axis: fixed, or adaptive ``ceil(roi_size / bins)``."""
    if sampling_ratio > 0:
        return torch.full_like(roi_size, sampling_ratio, dtype=torch.long)
    return torch.ceil(roi_size / bins).long().clamp(min=0)


def _window_bound(roi_size: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Upper bound of the feature rows an RoI's taps touch, from its size alone (host side).

    Samples lie strictly inside ``[start, start + roi_size]`` and each takes its floor and the
    next row, so at most ``ceil(roi_size) + 2`` rows, and never more than the map has.
    """
    return np.clip(np.ceil(np.maximum(roi_size, 0.0)) + 2, 1, np.maximum(size, 1))


def _axis_samples(
    start: Tensor, roi_size: Tensor, bins: Tensor, sizes: Tensor, grid: Tensor, max_bins: int, max_grid: int
) -> _AxisSamples:
    """Sampling positions along the axes of every RoI and their two bilinear taps (torchvision's
    rules): ``start``, ``roi_size``, ``sizes`` (the axis length of each RoI's map) and ``grid`` are
    (A, K) for A axes, ``bins`` (A, 1) their bins, ``max_bins`` and ``max_grid`` host bounds of
    ``bins`` and ``grid``; the result is (A, K, max_bins, 2 max_grid), padding with zero weight."""
    size = sizes[..., None, None]
    bin_size = (roi_size / bins)[..., None, None]
    grid_f = grid.clamp(min=1).to(start.dtype)[..., None, None]
    bin_index = torch.arange(max_bins, device=start.device)[:, None]
    sample_index = torch.arange(max_grid, device=start.device)
    coord = (
        start[..., None, None]
        + bin_index.to(start.dtype) * bin_size
        + (sample_index.to(start.dtype) + 0.5) * bin_size / grid_f
    )
    valid = (
        (bin_index < bins[..., None, None]) & (sample_index < grid[..., None, None]) & (coord >= -1.0) & (coord <= size)
    )
    coord = coord.clamp(min=0.0)
    low = coord.floor().long()  # coord >= 0, so floor equals C's int() truncation
    at_edge = low >= size - 1
    low = torch.minimum(low, size - 1)
    high = torch.where(at_edge, low, low + 1)
    frac = torch.where(at_edge, torch.zeros_like(coord), coord - low.to(coord.dtype))
    scale = valid.to(coord.dtype) / grid_f

    big = torch.iinfo(torch.long).max
    window_start = torch.where(valid, low, big).flatten(-2).amin(dim=-1)
    window_start = torch.where(valid.flatten(-2).any(dim=-1), window_start, torch.zeros_like(window_start))
    # Padding/invalid taps point at the window start with zero weight, so they cost nothing.
    low = torch.where(valid, low, window_start[..., None, None])
    high = torch.where(valid, high, window_start[..., None, None])
    return _AxisSamples(
        index=torch.cat([low, high], dim=-1),
        weight=torch.cat([(1.0 - frac) * scale, frac * scale], dim=-1),
        start=window_start,
    )


def _plan_chunks(
    heights: np.ndarray, widths: np.ndarray, channels: int, max_elements: int
) -> list[tuple[np.ndarray, int, int]]:
    """Chunks of RoIs, each padded to its largest window (rows of ``(rois, height, width)``).

    RoIs whose windows have similar height and width form groups (geometric buckets per axis, so
    tall and wide windows are not padded to each other's size); consecutive groups, by window
    area, are then merged where the padding gathers fewer elements than another chunk costs
    (``_CHUNK_COST``), the cheapest such merge found by a dynamic programme over the groups; a
    chunk whose padded gather passes ``max_elements`` is split.
    """
    step = np.log(_BUCKET_GROWTH)
    buckets = np.ceil(np.log(heights) / step) * 4096 + np.ceil(np.log(widths) / step)
    _, group_of = np.unique(buckets, return_inverse=True)
    group_h, group_w = np.zeros(group_of.max() + 1), np.zeros(group_of.max() + 1)
    np.maximum.at(group_h, group_of, heights)
    np.maximum.at(group_w, group_of, widths)
    by_area = np.argsort(group_h * group_w, kind="stable")
    sizes = np.bincount(group_of)[by_area]
    group_h, group_w = group_h[by_area], group_w[by_area]
    # best[j]: the cheapest plan of the first j groups; a plan's last chunk holds groups cut[j]..j-1
    best, cut = np.zeros(len(sizes) + 1), np.zeros(len(sizes) + 1, dtype=int)
    for end in range(1, len(sizes) + 1):
        first = np.arange(end)  # the last chunk's first group
        high = np.maximum.accumulate(group_h[end - 1 :: -1])[::-1]
        wide = np.maximum.accumulate(group_w[end - 1 :: -1])[::-1]
        count = np.cumsum(sizes[end - 1 :: -1])[::-1]
        cost = best[first] + _chunk_cost(count, channels * high * wide, max_elements)
        cut[end] = int(np.argmin(cost))
        best[end] = cost[cut[end]]
    rank = np.empty_like(by_area)
    rank[by_area] = np.arange(len(by_area))
    order = np.argsort(rank[group_of], kind="stable")  # RoIs group by group, in area order
    bounds = np.concatenate([[0], np.cumsum(sizes)])
    segments, end = [], len(sizes)
    while end:
        segments.append((cut[end], end))
        end = cut[end]
    chunks = []
    for first, end in reversed(segments):
        rois = order[bounds[first] : bounds[end]]
        per_roi = channels * int(heights[rois].max()) * int(widths[rois].max())
        size = max(1, max_elements // max(per_roi, 1))
        chunks += [
            (part, heights[part].max(), widths[part].max()) for part in np.split(rois, range(size, len(rois), size))
        ]
    return chunks


def _chunk_cost(count: np.ndarray, per_roi: np.ndarray, max_elements: int) -> np.ndarray:
    """Gathered elements plus ``_CHUNK_COST`` a chunk of ``count`` RoIs of ``per_roi`` padded
    elements each, split to fit ``max_elements``."""
    per_chunk = np.maximum(1, max_elements // np.maximum(per_roi, 1))
    return count * per_roi + np.ceil(count / per_chunk) * _CHUNK_COST


def _axis_matrices(axes: _AxisSamples, window: int) -> Tensor:
    """Dense (A, K, bins, window) interpolation matrices relative to each RoI's window start."""
    local = axes.index - axes.start[..., None, None]
    matrix = axes.weight.new_zeros(*axes.index.shape[:-1], window)
    return matrix.scatter_add_(-1, local, axes.weight)


@dataclass
class _ChunkLayout:
    """RoIs in plan order (``order``: their output rows), chunk after chunk.

    Chunk ``c`` holds ``shapes[c] = (k, window_h, window_w)``: the next ``k`` RoIs, their windows
    padded to that size. ``row_matrices`` (K, out_h, window) and ``col_matrices`` (K out_h, out_w,
    window) are every RoI's axis matrices up to the largest window, the column one repeated per
    output row (so a chunk's column pass is one plain ``bmm``); ``pixels[c]`` (k window_h window_w,)
    the row of each window pixel of chunk ``c`` in the channels-last table of all levels.
    """

    shapes: list[tuple[int, int, int]]
    order: Tensor
    row_matrices: Tensor
    col_matrices: Tensor
    pixels: Sequence[Tensor]

    def chunks(self) -> Iterator[tuple[int, int, int, int, Tensor]]:
        """``(first RoI, k, window_h, window_w, pixels)`` of each chunk, first RoI in plan order."""
        for first, (k, h, w), pixels in zip(_first_rois(self.shapes), self.shapes, self.pixels, strict=True):
            yield int(first), k, h, w, pixels


def _leading(stack: Tensor, first: int, count: int, rows: int, cols: int) -> Tensor:
    """``stack[first : first + count, :rows, :cols]`` of an (N, R, C) stack as one strided view: one
    op where slicing takes three."""
    batch, row, col = stack.stride()
    return stack.as_strided((count, rows, cols), (batch, row, col), stack.storage_offset() + first * batch)


def _first_rois(shapes: Sequence[tuple[int, int, int]]) -> np.ndarray:
    """The first RoI (in plan order) of each chunk of ``shapes`` ``(k, h, w)``: chunks hold consecutive RoIs."""
    counts = np.array([k for k, _, _ in shapes])
    return np.cumsum(counts) - counts


def _window_entries(plan: Sequence[tuple[np.ndarray, int, int]], window: int) -> tuple[np.ndarray, np.ndarray]:
    """Where each chunk's window pixels are, chunk after chunk (RoI, row, column order), as flat
    positions in the (K, window) tables of window rows and of columns: computed on the host from
    the plan alone (a few hundred thousand entries), so the device builds every chunk's pixel
    rows with one gather per table instead of a few ops per chunk."""
    rows, cols = [], []
    for index, h, w in plan:
        start = index[:, None, None] * window
        shape = (len(index), int(h), int(w))
        rows.append(np.broadcast_to(start + np.arange(int(h))[:, None], shape).ravel())
        cols.append(np.broadcast_to(start + np.arange(int(w)), shape).ravel())
    return np.concatenate(rows), np.concatenate(cols)


def _channels_last(inputs: Sequence[Tensor]) -> Tensor:
    """All maps (N, C, H_l, W_l) as one (sum_l N H_l W_l, C) table of pixel rows."""
    rows = [m.permute(0, 2, 3, 1).reshape(-1, m.shape[1]) for m in inputs]
    return rows[0] if len(rows) == 1 else torch.cat(rows)


class _RoIAlignFunction(torch.autograd.Function):
    """Pooling chunk by chunk: forward two ``bmm`` per chunk (rows, then columns, written straight
    into the output), backward their transposes and one ``index_add_``; the matrices are views."""

    @staticmethod
    def forward(ctx, layout: _ChunkLayout, dtype: torch.dtype, *inputs: Tensor):
        channels = inputs[0].shape[1]
        out_h, out_w = layout.row_matrices.shape[1], layout.col_matrices.shape[1]
        table = _channels_last(inputs)
        num_rois = layout.order.shape[0]
        pooled = torch.empty((num_rois, out_h, out_w, channels), dtype=dtype, device=table.device)  # plan order
        by_row = pooled.view(num_rois * out_h, out_w, channels)
        for first, k, h, w, pixels in layout.chunks():
            window = table.index_select(0, pixels).to(dtype).view(k, h, w * channels)
            row_pooled = torch.bmm(_leading(layout.row_matrices, first, k, out_h, h), window)  # (k, out_h, w C)
            torch.bmm(
                _leading(layout.col_matrices, first * out_h, k * out_h, out_w, w),
                row_pooled.view(k * out_h, w, channels),
                out=_leading(by_row, first * out_h, k * out_h, out_w, channels),
            )
        ctx.layout = layout
        ctx.input_shapes = [m.shape for m in inputs]
        ctx.input_dtype = inputs[0].dtype
        result = pooled.new_empty((num_rois, channels, out_h, out_w))
        result.permute(0, 2, 3, 1).index_copy_(0, layout.order, pooled)  # back to the RoIs' order
        return result

    @staticmethod
    def backward(ctx, grad_output: Tensor):
        with autocast_off(grad_output.device.type):  # backward can run under the caller's autocast
            return _RoIAlignFunction._backward(ctx, grad_output)

    @staticmethod
    def _backward(ctx, grad_output: Tensor):
        layout = ctx.layout
        channels = ctx.input_shapes[0][1]
        num_rois, out_h, _ = layout.row_matrices.shape
        out_w = layout.col_matrices.shape[1]
        # (K out_h, out_w, C) in plan order; the column matrices transposed once, contiguous
        grad = grad_output.permute(0, 2, 3, 1).index_select(0, layout.order).view(num_rois * out_h, out_w, channels)
        row_matrices = layout.row_matrices.transpose(1, 2)  # (K, window, out_h)
        col_matrices = layout.col_matrices.transpose(1, 2).contiguous()  # (K out_h, window, out_w)
        total = sum(n * h * w for n, _, h, w in ctx.input_shapes)
        grad_table = grad.new_zeros((total, channels))  # channels-last rows of all levels
        for first, k, h, w, pixels in layout.chunks():
            by_column = torch.bmm(  # (k out_h, w, C)
                _leading(col_matrices, first * out_h, k * out_h, w, out_w),
                _leading(grad, first * out_h, k * out_h, out_w, channels),
            )
            window = torch.bmm(_leading(row_matrices, first, k, h, out_h), by_column.view(k, out_h, w * channels))
            grad_table.index_add_(0, pixels, window.view(k * h * w, channels))
        grads, start = [], 0
        for n, _, h, w in ctx.input_shapes:
            part = grad_table[start : start + n * h * w].view(n, h, w, channels).permute(0, 3, 1, 2)
            grads.append(part.to(ctx.input_dtype).contiguous())
            start += n * h * w
        return None, None, *grads
