"""Rasterization: a compiled z-buffer for visibility, then differentiable barycentrics in torch.

Visibility (which triangle is front-most at each pixel centre) has no useful gradient, so it runs in a
numba kernel on the CPU. The perspective-correct barycentrics of the foreground pixels are then
recomputed in torch from the clip-space vertices, so gradients reach vertex positions and everything
interpolated with them. On CUDA tensors the z-buffer still runs on the CPU copy of the projected
vertices (a few hundred KB); everything else stays on the device.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from . import compiled
from .compiled import njit, prange


SPAN_REACH = 1e6  # px: screen coordinates under this solve a row's span to well under a pixel
SPAN_SLOPE = 1e-3  # an edge whose function changes less than this a pixel along a row bounds no span
SPAN_WIDEST = 4  # boxes fewer columns wide than this are scanned whole: solving costs more than it skips


@njit(cache=True)
def _edge_span(offset, slope, first, last):  # pragma: no cover - compiled
    """Columns first..last narrowed to those within a pixel of where offset + slope * (col + 0.5) >= 0."""
    if slope > SPAN_SLOPE:
        first = max(first, int(math.ceil(-offset / slope - 0.5)) - 1)
    elif slope < -SPAN_SLOPE:
        last = min(last, int(math.floor(-offset / slope - 0.5)) + 1)
    return first, last


@njit(cache=True)
def _zbuffer_one(xy, z, w, faces, near, face_out, depth, top, left, height, width):  # pragma: no cover - compiled
    """Rows top.. and columns left.. of a height x width raster: face_out[row - top, col - left]."""
    bottom, right = top + face_out.shape[0] - 1, left + face_out.shape[1] - 1
    for f in range(faces.shape[0]):
        i0, i1, i2 = faces[f, 0], faces[f, 1], faces[f, 2]
        if w[i0] <= near or w[i1] <= near or w[i2] <= near:
            continue
        x0, y0 = xy[i0, 0], xy[i0, 1]
        x1, y1 = xy[i1, 0], xy[i1, 1]
        x2, y2 = xy[i2, 0], xy[i2, 1]
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-12:
            continue
        col_lo = max(int(math.ceil(min(x0, x1, x2) - 0.5)), 0, left)
        col_hi = min(int(math.floor(max(x0, x1, x2) - 0.5)), width - 1, right)
        row_lo = max(int(math.ceil(min(y0, y1, y2) - 0.5)), 0, top)
        row_hi = min(int(math.floor(max(y0, y1, y2) - 0.5)), height - 1, bottom)
        z0, z1, z2 = z[i0], z[i1], z[i2]
        inv_area = 1.0 / area
        # Each row's columns are those of the box within a pixel of the triangle's edges (solved for
        # along the row): the exact test below decides them all, as over the whole box, and the box's
        # other pixels would fail it. Narrow, far off screen (or not finite): the box is scanned whole.
        spans = (col_hi - col_lo >= SPAN_WIDEST
                 and max(abs(x0), abs(x1), abs(x2), abs(y0), abs(y1), abs(y2)) < SPAN_REACH)
        sign = 1.0 if area > 0.0 else -1.0
        for row in range(row_lo, row_hi + 1):
            py = row + 0.5
            first, last = col_lo, col_hi
            if spans:
                first, last = _edge_span(sign * (x1 * (y2 - py) - x2 * (y1 - py)), sign * (y1 - y2), first, last)
                first, last = _edge_span(sign * (x2 * (y0 - py) - x0 * (y2 - py)), sign * (y2 - y0), first, last)
                first, last = _edge_span(sign * (x0 * (y1 - py) - x1 * (y0 - py)), sign * (y0 - y1), first, last)
            for col in range(first, last + 1):
                px = col + 0.5
                l0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) * inv_area
                l1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) * inv_area
                l2 = 1.0 - l0 - l1
                if l0 < 0.0 or l1 < 0.0 or l2 < 0.0:
                    continue
                depth_here = l0 * z0 + l1 * z1 + l2 * z2
                if depth_here < -1.0 or depth_here > 1.0:
                    continue
                if depth_here < depth[row - top, col - left]:
                    depth[row - top, col - left] = depth_here
                    face_out[row - top, col - left] = f


@njit(parallel=True, cache=True)
def _zbuffer(xy, z, w, faces, near, face_out, depth, top, left, height, width):  # pragma: no cover - compiled
    n_faces_sets = faces.shape[0]
    for b in prange(xy.shape[0]):
        _zbuffer_one(xy[b], z[b], w[b], faces[min(np.int64(b), n_faces_sets - 1)], near, face_out[b], depth[b],
                     top, left, height, width)


PAIRS_AT_ONCE = 1 << 20  # `_zbuffer_torch` tests at most about this many (face, pixel) pairs at a time


def _zbuffer_torch(xy, z, w, faces, near, face_out, depth, top, left, height, width):
    """`_zbuffer` in torch, for a process that has not loaded the compiled kernels (`compiled.spare`):
    every (face, pixel) pair of each face's box tested at once (faces in runs of about PAIRS_AT_ONCE
    pairs), the same arithmetic in the same order (float64, no fused operations), so the same faces
    and depths: the nearest depth per pixel, and of the faces at it the first, as the kernel's strict
    test keeps. A face with a vertex at or behind `near` or a coordinate not finite draws nothing, as
    in the kernel."""
    n_batch, rows, columns = face_out.shape
    bottom, right = top + rows - 1, left + columns - 1
    all_faces = torch.from_numpy(faces)
    for b in range(n_batch):
        corners = all_faces[min(b, len(all_faces) - 1)]
        cx, cy = torch.from_numpy(xy[b, :, 0])[corners], torch.from_numpy(xy[b, :, 1])[corners]  # (F, 3)
        cz, cw = torch.from_numpy(z[b])[corners], torch.from_numpy(w[b])[corners]
        area = (cx[:, 1] - cx[:, 0]) * (cy[:, 2] - cy[:, 0]) - (cx[:, 2] - cx[:, 0]) * (cy[:, 1] - cy[:, 0])
        drawn = (cw > near).all(1) & (area.abs() >= 1e-12) & cx.isfinite().all(1) & cy.isfinite().all(1)
        col_lo = torch.ceil(cx.amin(1) - 0.5).clamp(-1e9, 1e9).long().clamp_min(max(0, left))
        col_hi = torch.floor(cx.amax(1) - 0.5).clamp(-1e9, 1e9).long().clamp_max(min(width - 1, right))
        row_lo = torch.ceil(cy.amin(1) - 0.5).clamp(-1e9, 1e9).long().clamp_min(max(0, top))
        row_hi = torch.floor(cy.amax(1) - 0.5).clamp(-1e9, 1e9).long().clamp_max(min(height - 1, bottom))
        box_w = (col_hi - col_lo + 1).clamp_min(0)
        count = torch.where(drawn, box_w * (row_hi - row_lo + 1).clamp_min(0), 0)
        listed = count.nonzero().squeeze(1)
        nearest = torch.from_numpy(depth[b]).view(-1)  # inf, then each run's nearest where nearer
        first = torch.from_numpy(face_out[b]).view(-1)
        ends = count[listed].cumsum(0)
        marks = torch.tensor(range(PAIRS_AT_ONCE, int(ends[-1]) if len(ends) else 0, PAIRS_AT_ONCE), dtype=ends.dtype)
        bounds = torch.searchsorted(ends, marks, right=True).tolist()
        for run in torch.tensor_split(listed, bounds):
            if len(run) == 0:
                continue
            run_count = count[run]
            f = run.repeat_interleave(run_count)  # a face per pair, its box's pixels in row-major order
            offset = torch.arange(len(f)) - (run_count.cumsum(0) - run_count).repeat_interleave(run_count)
            row = row_lo[f] + torch.div(offset, box_w[f], rounding_mode="floor")
            col = col_lo[f] + offset % box_w[f]
            px, py = col.double() + 0.5, row.double() + 0.5
            (x0, x1, x2), (y0, y1, y2) = cx[f].unbind(1), cy[f].unbind(1)
            inv_area = 1.0 / area[f]
            l0 = ((x1 - px) * (y2 - py) - (x2 - px) * (y1 - py)) * inv_area
            l1 = ((x2 - px) * (y0 - py) - (x0 - px) * (y2 - py)) * inv_area
            l2 = 1.0 - l0 - l1
            fz = cz[f]
            here = l0 * fz[:, 0] + l1 * fz[:, 1] + l2 * fz[:, 2]
            inside = (l0 >= 0.0) & (l1 >= 0.0) & (l2 >= 0.0) & (here >= -1.0) & (here <= 1.0)
            here, f = here[inside], f[inside]
            pixel = (row[inside] - top) * columns + (col[inside] - left)
            run_nearest = torch.full_like(nearest, math.inf).scatter_reduce_(0, pixel, here, "amin")
            at_nearest = here == run_nearest[pixel]
            run_first = torch.full_like(first, torch.iinfo(torch.int64).max)
            run_first.scatter_reduce_(0, pixel[at_nearest], f[at_nearest], "amin")
            nearer = run_nearest < nearest  # a tie keeps the earlier run's face, the lower index
            nearest[nearer] = run_nearest[nearer]
            first[nearer] = run_first[nearer]


@njit(cache=True)
def _texel_coverage(corners, used):  # pragma: no cover - compiled
    height, width = used.shape
    for f in range(corners.shape[0]):
        xs = np.empty(3)
        ys = np.empty(3)
        for k in range(3):  # texel coordinates: texel (r, c) spans [c, c + 1) x [r, r + 1), row 0 at v = 1
            xs[k] = corners[f, k, 0] * width
            ys[k] = (1.0 - corners[f, k, 1]) * height
        area = (xs[1] - xs[0]) * (ys[2] - ys[0]) - (xs[2] - xs[0]) * (ys[1] - ys[0])
        if abs(area) > 1e-12:  # texel centres inside the face
            inv_area = 1.0 / area
            for row in range(int(math.ceil(min(ys[0], ys[1], ys[2]) - 0.5)), int(math.floor(max(ys[0], ys[1], ys[2]) - 0.5)) + 1):
                py = row + 0.5
                for col in range(int(math.ceil(min(xs[0], xs[1], xs[2]) - 0.5)), int(math.floor(max(xs[0], xs[1], xs[2]) - 0.5)) + 1):
                    px = col + 0.5
                    l0 = ((xs[1] - px) * (ys[2] - py) - (xs[2] - px) * (ys[1] - py)) * inv_area
                    l1 = ((xs[2] - px) * (ys[0] - py) - (xs[0] - px) * (ys[2] - py)) * inv_area
                    if l0 >= 0.0 and l1 >= 0.0 and l0 + l1 <= 1.0:
                        used[row % height, col % width] = True
        for k in range(3):  # the texels under its edges, a point every half texel or closer
            x0, y0, x1, y1 = xs[k], ys[k], xs[(k + 1) % 3], ys[(k + 1) % 3]
            steps = int(math.ceil(2.0 * math.hypot(x1 - x0, y1 - y0))) + 1
            for step in range(steps + 1):
                t = step / steps
                used[int(math.floor(y0 + t * (y1 - y0))) % height, int(math.floor(x0 + t * (x1 - x0))) % width] = True


def texel_coverage(corners: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """The texels (height, width) bool of a height x width texture that triangles with UV corners
    `corners` (F, 3, 2) cover, wrapped (a repeating texture): those whose centre a triangle covers and
    those its edges cross (a sliver, or a triangle whose UVs lie on a line, covers no centre)."""
    used = np.zeros((height, width), dtype=np.bool_)
    _texel_coverage(np.ascontiguousarray(corners.detach().to("cpu", torch.float64).numpy()), used)
    return torch.from_numpy(used)


@dataclass
class Fragments:
    """The visible surface at each foreground pixel.

    pix_to_face: (B, H, W) long, the front-most face index (within its batch element) or -1.
    pixel: (P,) flat index into B*H*W of each foreground pixel; batch, face: (P,) long;
    bary: (P, 3) perspective-correct barycentrics (differentiable w.r.t. the clip-space vertices);
    vertex: (P, 3) the face's vertex indices; screen_bary: (P, 3) screen-space barycentrics;
    corners_xy: (P, 3, 2) the face's corners in pixels (differentiable; the splatter reuses them).
    """

    pix_to_face: torch.Tensor
    pixel: torch.Tensor
    batch: torch.Tensor
    face: torch.Tensor
    vertex: torch.Tensor
    bary: torch.Tensor
    screen_bary: torch.Tensor
    corners_xy: torch.Tensor

    @property
    def shape(self) -> tuple[int, int, int]:
        return tuple(self.pix_to_face.shape)


def clip_to_screen(clip: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """(..., 4) clip coordinates -> (..., 2) pixel coordinates (x right, y down, row 0 on top)."""
    ndc = clip[..., :2] / clip[..., 3:4]
    half = clip.new_tensor([0.5 * width, 0.5 * height])
    return torch.addcmul(half, ndc, half * clip.new_tensor([1.0, -1.0]))  # one op: it runs thousands of times


def gather_corners(values: torch.Tensor, batch: torch.Tensor, vertex: torch.Tensor) -> torch.Tensor:
    """values (B, V, C) (or (1, V, C), shared) at the corners vertex (P, 3) of elements batch (P,) -> (P, 3, C).

    One index_select on the flattened table: its backward is an index_add, cheaper on the CPU than the
    accumulating index_put of advanced indexing (benchmarks/render.py times the renderer).
    """
    n_vertices, channels = values.shape[1], values.shape[2]
    index = vertex if values.shape[0] == 1 else batch.unsqueeze(1) * n_vertices + vertex
    return values.reshape(-1, channels).index_select(0, index.reshape(-1)).reshape(*vertex.shape, channels)


def _batched_faces(faces: torch.Tensor) -> torch.Tensor:
    return faces.unsqueeze(0) if faces.dim() == 2 else faces


def visible_faces(clip: torch.Tensor, faces: torch.Tensor, height: int, width: int,
                  near: float = 1e-5) -> torch.Tensor:
    """(B, H, W) index of the front-most face at each pixel centre, -1 for background (no gradient)."""
    return _visible(clip, faces, height, width, near, None)[0]


def visible_faces_and_depth(clip: torch.Tensor, faces: torch.Tensor, height: int, width: int,
                            near: float = 1e-5) -> tuple[torch.Tensor, torch.Tensor]:
    """`visible_faces` (B, H, W) and the normalised device depth z / w (B, H, W, float64; inf on the
    background) the z-buffer kept at each pixel centre: exact there, since z / w is affine on the
    screen, so a pixel's surface point is its ray at that depth, without interpolating fragments."""
    faces_out, _, depth = _visible(clip, faces, height, width, near, None, True)
    return faces_out, depth


def visible_faces_within(clip: torch.Tensor, faces: torch.Tensor, height: int, width: int, near: float = 1e-5,
                         align: int = 1) -> tuple[torch.Tensor, tuple[int, int]]:
    """`visible_faces` over the window of the (B, H, W) raster that the vertices in front of the camera
    span (every pixel outside it is background): (B, h, w) and the window's (top, left) corner, its
    edges on multiples of `align` pixels. The same faces at the same pixels, without filling and
    scanning the rest of a large raster."""
    return _visible(clip, faces, height, width, near, align)


def whole_raster(window: torch.Tensor, corner: tuple[int, int], height: int, width: int) -> torch.Tensor:
    """`visible_faces_within`'s window (B, h, w) at `corner` back in its whole (B, height, width) raster."""
    top, left = corner
    whole = window.new_full((window.shape[0], height, width), -1)
    whole[:, top: top + window.shape[1], left: left + window.shape[2]] = window
    return whole


def _visible(clip, faces, height, width, near, align, with_depth=False):
    with torch.no_grad():
        clip64 = clip.detach().to("cpu", torch.float64)
        xy = clip_to_screen(clip64, height, width).numpy()
        z = (clip64[..., 2] / clip64[..., 3]).numpy()
        w = clip64[..., 3].numpy()
        face_array = _batched_faces(faces).detach().to("cpu", torch.int64).numpy()
        n_batch = clip.shape[0]
        top, left, bottom, right = 0, 0, height, width
        if align is not None:  # the pixels any face drawn can reach: within its vertices' box
            front = xy[w > near]
            if len(front) == 0:
                top, left, bottom, right = 0, 0, 0, 0
            elif np.isfinite(front).all():
                low, high = front.min(0), front.max(0)
                left = min(max(math.ceil(low[0] - 0.5), 0), width) // align * align
                top = min(max(math.ceil(low[1] - 0.5), 0), height) // align * align
                right = max(min(math.floor(high[0] - 0.5) + 1, width), left)
                bottom = max(min(math.floor(high[1] - 0.5) + 1, height), top)
                right = min(-(-right // align) * align, width)
                bottom = min(-(-bottom // align) * align, height)
        face_out = np.full((n_batch, bottom - top, right - left), -1, dtype=np.int64)
        depth = np.full((n_batch, bottom - top, right - left), np.inf, dtype=np.float64)
        if face_out.size:
            arrays = [np.ascontiguousarray(a) for a in (xy, z, w, face_array)]
            if compiled.spare(face_out.size):  # a small job while the kernels are not loaded: the same in torch
                with compiled.in_torch():
                    _zbuffer_torch(*arrays, near, face_out, depth, top, left, height, width)
            else:
                _zbuffer(*arrays, near, face_out, depth, top, left, height, width)
    if with_depth:
        return torch.from_numpy(face_out).to(clip.device), (top, left), torch.from_numpy(depth).to(clip.device)
    return torch.from_numpy(face_out).to(clip.device), (top, left)


def rasterize(clip: torch.Tensor, faces: torch.Tensor, height: int, width: int,
              pix_to_face: torch.Tensor | None = None) -> Fragments:
    """Rasterize clip-space vertices (B, V, 4) with faces (F, 3) shared or (B, F, 3) per element.
    `pix_to_face`: `visible_faces` of the same, already worked out."""
    if pix_to_face is None:
        pix_to_face = visible_faces(clip, faces, height, width)
    flat = pix_to_face.reshape(-1)
    pixel = torch.nonzero(flat >= 0).squeeze(1)
    face = flat[pixel]
    batch = torch.div(pixel, height * width, rounding_mode="floor")
    within = pixel - batch * height * width
    row = torch.div(within, width, rounding_mode="floor")
    col = within - row * width
    batched_faces = _batched_faces(faces)
    n_face_sets, n_faces = batched_faces.shape[0], batched_faces.shape[1]
    face_index = face if n_face_sets == 1 else batch * n_faces + face
    vertex = batched_faces.reshape(-1, 3).index_select(0, face_index)
    corners = gather_corners(clip, batch, vertex)  # (P, 3, 4)
    xy = clip_to_screen(corners, height, width)  # (P, 3, 2)
    px = (col.to(clip.dtype) + 0.5).unsqueeze(1)
    py = (row.to(clip.dtype) + 0.5).unsqueeze(1)
    dx, dy = xy[..., 0] - px, xy[..., 1] - py  # (P, 3)
    # Signed areas of the sub-triangles opposite each corner, normalised: screen barycentrics.
    sub = torch.stack([dx[:, 1] * dy[:, 2] - dx[:, 2] * dy[:, 1],
                       dx[:, 2] * dy[:, 0] - dx[:, 0] * dy[:, 2],
                       dx[:, 0] * dy[:, 1] - dx[:, 1] * dy[:, 0]], dim=1)
    screen_bary = sub / sub.sum(dim=1, keepdim=True)
    perspective = screen_bary / corners[..., 3]
    bary = perspective / perspective.sum(dim=1, keepdim=True)
    return Fragments(pix_to_face, pixel, batch, face, vertex, bary, screen_bary, xy)
