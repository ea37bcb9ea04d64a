"""Camera registration: find the view of a picture of a known mesh, by analysis by synthesis.

Informed detection un-renders a picture onto the original mesh, so it needs the picture's camera. The
picture is cropped to the object's square box (as `framing` does); candidate views from all around the
mesh are rendered, framed the same way and scored by silhouette overlap and by how well the picture's
colours fit the mesh's texture under the best-fitting simple lighting; the best few are refined on their
silhouettes, the one whose texture fits best is refined again, and the camera of the whole picture is
finished on the texture (its field of view too, where the assumed one leaves the texture fitting
poorly: a crop, another lens); where the texture then still fits poorly, more candidate views, nearer
each other, get the same treatment. Every refinement is Gauss-Newton on a rigid move whose Jacobian is an
image gradient times the move's analytic screen flow (Lucas-Kanade style: one render per iteration, no
backward pass), but the last: `polish` brings the camera its last hundredths of a pixel on the picture's
own pixels, with a Jacobian of rendered differences.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from ..render import (
    Cameras,
    MeshBatch,
    MeshRenderer,
    fibonacci_directions,
    pixels_at,
    relight_fragments,
)
from .framing import boxes_from_mask, crop_boxes

SEARCH_SIZE = 128  # render size of the candidate views and of the refinement
COMPARE_SIZE = 64  # framed size at which candidates are scored
LOWPASS = 4.0  # the texture stage compares band-passed pictures: shading (a light misfit) is left out
WORKING_SIZE = 512  # longest side at which the whole picture is refined on the texture
TEXTURE_SCALE_SIGMA = 2.0  # coarse texture levels run shrunk so that their blur is this many pixels
TEXTURE_SIGMAS = (4.0, 2.0, 1.0, 0.5)  # the texture stage's bands, widest first (pixels of blur)
ROBUST_SCALE = 2.0  # the texture stage's Cauchy scale, in median absolute residuals
ROBUST_MIN_SIGMA = 2.0  # ... on levels blurred this much or more (finer ones: least squares)
FREEZE_DAMPING = 1e-3  # silhouette refinement stops a camera whose step is under SILHOUETTE_DONE px at a damping of at most this
SILHOUETTE_DONE = 0.01  # px: ... on the picked candidate's fine levels (SEARCH_SIZE) ...
SILHOUETTE_COARSE_DONE = 0.05  # ... and on the candidates' coarse ones (COMPARE_SIZE), which finer levels follow
TEXTURE_DONE = 0.01  # a texture level ends once its step is under this many pixels (a step half as long as one that failed
TEXTURE_COARSE_DONE = 0.05  # ... would be, it ends there too); on the coarse (robust) levels, which finer ones follow, this
PICK_SIGMAS = (1.0, 2.0)  # the refined candidates are told apart by their texture misfit in these bands
COARSE_SILHOUETTE_SIGMAS = (3.0, 1.5)  # the candidates' silhouette refinement at COMPARE_SIZE (blur, pixels)
FINE_SILHOUETTE_SIGMAS = (1.0, 0.5)  # the picked candidate's silhouette refinement at SEARCH_SIZE
PICK_MARGIN = 0.7  # another candidate replaces the best-scored one only if its texture misfit is this much lower
PICK_IOU_SLACK = 0.1  # ... and only if its refined silhouette's IoU is at most this much below the best one's
TEXTURE_IOU_SLACK = 0.04  # the texture stage's camera is kept only if its silhouette's IoU is at most this much below the start's
FLAT_RETRY = 0.1  # the texture stage tries the flat-half light only if the all-pixel one left this share of the misfit or more
FLAT_ENOUGH = 0.05  # ... and a texture misfit (sigma 1) of this or more: under it the all-pixel light's run fits as a registered pose does (the flat-half run ends within a tenth of a pixel of it there)
RECUT_ROUNDS = 2  # `register_with_masks`: at most this many guesses in a row cut again from a registered silhouette
RECUT_BELOW_IOU = 0.9  # ... only where the registered silhouette's IoU with its own guess is under this (a mask it disagrees with)
MIN_RECUT_PIXELS = 64  # ... a cut smaller than this is not registered
ACCEPT_MISFIT = 0.2  # a registration whose texture misfit (PICK_SIGMAS) is under this is taken without trying other masks (a registered view fits far under it, an unrelated one near 2 a band)
SHADED_CANDIDATES = 100  # the candidate views with the best silhouette overlap that are also scored on shading
SCORE_LIGHT_DIRECTIONS = 48  # the candidates' shading score fits its light on this many directions (x 5 distances) ...
SCORE_LIGHT_PIXELS = 256  # ... and at most about this many pixels a view (the texture stage's fits: 96 and 512)
RETRY_ABOVE = 0.2  # a registration whose texture misfit (PICK_SIGMAS) is over this also tries RETRY_KEEP more candidate views
RETRY_KEEP = 12
RETRY_FINISH_BELOW = 1.0  # ... and finishes its best on the texture only where on its silhouettes it fits under this share of the finished camera's misfit
RETRY_ANGLE = 12.0  # ... at least this many degrees from each other and from the views refined first
TEXTURE_DAMPING = 1e-3  # the texture stage's Levenberg-Marquardt damping, times the normal matrix's mean diagonal ...
ZOOM_DAMPING = 1e-6  # ... and with the zoom, whose valley along the view axis that damping would hold back
ZOOM_TRY = 0.03  # the texture stage tries the zoom where the texture misfit (sigma 1) is still this or more (a registered pose of the assumed lens fits under it) ...
ZOOM_GAIN = 0.9  # ... and the texture stage keeps the zoomed camera only if its texture misfit is under this share of the other's
ZOOM_PROBE_SIGMA = 1.0  # ... and only where one step of the zoomed move on this band turns the field of view ...
ZOOM_PROBE_DEGREES = 1.0  # ... by this many degrees or more (a crop's picture turns it by several; a picture of the assumed lens hardly at all)
ZOOM_ROUNDS = 1  # the texture stage's coarse-to-fine passes at most (more read crops no better, for longer) ...
ZOOM_AGAIN = 0.5  # ... another one while the last changed the field of view by this many degrees or more
SHARPEN_STEPS = (0.2, 0.025)  # pixels: `sharpen`'s first and last step
SHARPEN_RENDERS = 150  # ... and at most this many renders
SHARPEN_WINDOW = 256  # ... of at most this many pixels a side around the object's centre
POLISH_STEP = 0.1  # pixels: `polish`'s central differences
POLISH_ROUNDS = 2  # ... its rounds, each with the light refitted and the Jacobian taken afresh ...
POLISH_AGAIN = 0.02  # ... the next round only where the last moved the camera by this many pixels or more ...
POLISH_ITERATIONS = 6  # ... its Gauss-Newton steps a round at most ...
POLISH_WINDOW = 256  # ... on at most this many pixels a side around the object's centre (a large picture: its central part) ...
POLISH_HIGHPASS = 4.0  # ... comparing pictures high-passed at this many pixels (0: as they are) ...
POLISH_MAX = 0.5  # ... and a move of more than this many pixels (mean screen distance) not taken
POLISH_FOOTPRINTS = (1.0, 0.5, 0.75, 1.5)  # how the picture may have sampled the object: a render at 1 / f its size resized to it ...
POLISH_FOOTPRINT_GAIN = 0.9  # ... a resized one used only where it fits under this share of the point samples' misfit (1.5: never)
COMPOSITE_SIGMAS = (1.0, 0.0)  # `polish_composited`: the window compared as it is, and blurred this much (pixels) first ...
COMPOSITE_ROUNDS = 8  # ... in at most this many rounds a level, the light refitted each ...
COMPOSITE_ITERATIONS = 20  # ... of at most this many Gauss-Newton steps ...
COMPOSITE_MAX = 1.0  # ... and a move of more than this many pixels (mean screen distance) not taken
BLOCK_SIDE = 12  # `match_blocks`: blocks of this many pixels a side ...
BLOCK_SUPERSAMPLE = 4  # ... matched at shifts of 1 / this many pixels ...
BLOCK_REACH = 1  # ... plus whole pixels up to this many each way ...
BLOCK_COVER = 0.1  # ... in the blocks where at least this share of the pixels is the object's ...
BLOCK_ROUNDS = 2  # ... in at most this many rounds (the light refitted each) ...
BLOCK_MAX = 1.5  # ... a move of more than this many pixels (RMS over the seen surface) not taken
OUTLINE_ABOVE = 20000  # a mesh of more faces than this searches its silhouettes on a decimated copy ...
OUTLINE_FACES = 8000  # ... of at most this many faces (`outline_mesh`) ...
OUTLINE_SHARE = 0.6  # ... where the decimation gets it to this share of the faces or fewer (open sheets' borders stay) ...
OUTLINE_IOU = 0.97  # ... where its silhouette overlaps the whole mesh's by at least this in each of OUTLINE_VIEWS views
OUTLINE_VIEWS = 12
LENSES = (0.8, 1.25)  # a second look also reads under these other lenses: the tangent of half the field of view times each (a central 80 % crop's; a screenshot's larger canvas)
ALTERNATIVES = 3  # the next-best candidate views a Registration offers for a second look (see `alternatives`)
DISTANCE = 3.5
FOV = 60.0


@dataclass
class Registration:
    """camera: the camera of the whole picture (its field of view as assumed, or as the texture stage
    refined it; principal point at the centre); box: the object's square box (cx, cy, half) in the picture's pixels; iou: overlap of the
    registered silhouette with the picture's. alternatives: the next-best distinct views (up to
    ALTERNATIVES, best first, each an `Alternative`): a near-symmetric shape's twin views fit
    silhouette and texture alike, and only the mark can tell them apart (`reading.second_look`)."""

    camera: Cameras
    box: torch.Tensor
    iou: float
    alternatives: tuple = ()


class Alternative:
    """A next-best view of a registration, refined only when asked: `rough()` on its silhouettes
    alone (a few renders: near enough to see whether the mark is there), `finish()` then on the
    texture as the registered camera was. One given without stages is already finished."""

    def __init__(self, camera: Cameras, silhouettes=None, texture=None):
        self._camera, self._silhouettes, self._texture = camera, silhouettes, texture
        self._rough: Cameras | None = None

    @property
    def finished(self) -> bool:
        return self._texture is None

    def rough(self) -> Cameras:
        if self._rough is None:
            self._rough = self._silhouettes(self._camera) if self._silhouettes else self._camera
        return self._rough

    def finish(self) -> Cameras:
        return self.rough() if self._texture is None else self._texture(self.rough())


def _up_for(direction: torch.Tensor) -> torch.Tensor:
    """+Z up, except looking straight down or up, where +Y is used."""
    up = torch.zeros_like(direction)
    vertical = direction[:, 2].abs() > 0.98
    up[:, 2] = (~vertical).float()
    up[:, 1] = vertical.float()
    return up


def _iou(a: torch.Tensor, b: torch.Tensor, inside: torch.Tensor | None = None) -> torch.Tensor:
    """Overlap of coverages a and b (..., H, W), over the pixels `inside` the picture if given."""
    a, b = a > 0.5, b > 0.5
    if inside is not None:
        a, b = a & (inside > 0.5), b & (inside > 0.5)
    return (a & b).sum(dim=(-2, -1)).float() / (a | b).sum(dim=(-2, -1)).clamp_min(1).float()


def crop_intrinsics(height: int, width: int, box, fov_y: float) -> tuple[float, tuple[float, float]]:
    """(fov_y, principal) of the camera that sees the square `box` (cx, cy, half) cropped out of a
    height x width picture taken with vertical field of view `fov_y` (centred principal point)."""
    cx, cy, half = (float(v) for v in box)
    tan = math.tan(math.radians(fov_y) / 2) * 2 * half / height
    return math.degrees(2 * math.atan(tan)), ((width / 2 - cx) / half, (cy - height / 2) / half)


def _center_objects(mesh: MeshBatch, cameras: Cameras, size: int, rounds: int = 3, seen=None) -> Cameras:
    """Move each camera (without turning it) so the object's framed box fills its size x size picture.
    The box is that of the projected vertices (the silhouette's, without rendering); a few rounds
    absorb the perspective. `seen` (low (2,), high (2,), cut (2, 2) bool: per axis x, y whether the
    picture's edge cuts the object off at the low / high side), in this picture's pixels: the object
    seen only in part. Its uncut sides are matched: the scale from an axis cut on neither side, the
    position from the uncut side of each axis, so that the rest of the object lies past the edge."""
    from ..render import clip_to_screen
    from .framing import BOX_MARGIN

    focal = size / 2 / math.tan(math.radians(cameras.fov_y) / 2)
    used = _hull_points(mesh)
    for _ in range(rounds):
        with torch.no_grad():
            xy = clip_to_screen(cameras.world_to_clip(used[None].expand(len(cameras), -1, -1), 1.0), size, size)
        low, high = xy.amin(1), xy.amax(1)
        centre = (low + high) / 2
        if seen is None:
            half = (high - low).amax(-1, keepdim=True) / 2 * (1 + 2 * BOX_MARGIN)
            target, grow = torch.full_like(centre, size / 2), (size / 2) / half
        else:
            target, grow = _seen_target(low, high, *seen)
        view = cameras.view_matrix()[:, :3, :3]  # rows: right, up, back
        distance = (cameras.at - cameras.eye).norm(dim=-1, keepdim=True)
        # Closer by `grow`, the object's offset from the middle grows by it; the rest is a sideways move
        # (moving the camera right moves the object left).
        moved = target - ((centre - size / 2) * grow + size / 2)
        dx, dy = moved[:, :1] * distance / grow / focal, moved[:, 1:] * distance / grow / focal
        shift = -dx * view[:, 0] + dy * view[:, 1]
        closer = (1.0 - 1.0 / grow) * distance * -view[:, 2]  # toward the object
        cameras = replace(cameras, eye=cameras.eye + shift + closer, at=cameras.at + shift)
    return cameras


_HULL: list = []  # (positions, faces, hull points) of the last mesh `_hull_points` saw


def _hull_points(mesh: MeshBatch) -> torch.Tensor:
    """The vertices (N, 3) of the convex hull of the mesh's used vertices: a perspective projection of
    points in front of the camera keeps convex hulls, so their projected box is the whole mesh's (and
    `_center_objects` projects a few hundred points instead of thousands). Kept for the last mesh: a
    folder of pictures of one mesh computes it once."""
    positions, faces = mesh.positions, mesh.faces
    if _HULL and _HULL[0][0] is positions and _HULL[0][1] is faces:
        return _HULL[0][2]
    used = positions[0].index_select(0, faces.unique())
    try:
        from scipy.spatial import ConvexHull

        hull = used.index_select(0, torch.as_tensor(ConvexHull(used.detach().cpu().double().numpy()).vertices,
                                                    device=used.device))
    except Exception:  # flat or degenerate (qhull refuses): every used vertex
        hull = used
    _HULL[:] = [(positions, faces, hull)]
    return hull


_OUTLINE: list = []  # (positions, faces, outline) of the last mesh `outline_mesh` saw


def outline_mesh(mesh: MeshBatch) -> MeshBatch:
    """The mesh whose silhouettes the search and the silhouette stages render: `mesh` itself, or where it
    has more than OUTLINE_ABOVE faces a copy decimated toward OUTLINE_FACES (quadric error, one pass,
    its vertices first welded where the file split them at UV or normal seams, so that no seam opens,
    and the open borders kept: a card of foliage keeps its shape). The
    candidate views' silhouettes are 64 px and the silhouette stages' 128 px wide, where a few
    thousand faces draw the same outline as a scan's hundreds of thousands; the cost of each render
    grows with the faces (clipping, the z-buffer), so a high-poly asset would otherwise pay it
    hundreds of times. The decimated copy is used only where its silhouette overlaps the whole mesh's
    by OUTLINE_IOU or more in each of OUTLINE_VIEWS views all around (at the silhouette stages' size)
    and has at most OUTLINE_SHARE of its faces: decimation can eat thin parts, and a search on a wrong
    outline finds a wrong view. Positions and faces only: the shading score and the texture stage keep the
    whole mesh. Kept for the last mesh: a folder of pictures of one mesh decimates it once."""
    import fast_simplification
    import numpy as np

    positions, faces = mesh.positions, mesh.faces
    shared = faces if faces.dim() == 2 else faces[0] if faces.shape[0] == 1 else None
    if shared is None or positions.shape[0] != 1 or len(shared) <= OUTLINE_ABOVE:
        return mesh
    if _OUTLINE and _OUTLINE[0][0] is positions and _OUTLINE[0][1] is faces:
        return _OUTLINE[0][2]
    points = positions[0].detach().cpu().double().numpy()
    welded, inverse = np.unique(points, axis=0, return_inverse=True)
    triangles = inverse.reshape(-1)[shared.cpu().numpy()]
    triangles = triangles[(triangles[:, 0] != triangles[:, 1]) & (triangles[:, 1] != triangles[:, 2])
                          & (triangles[:, 0] != triangles[:, 2])]
    new_points, new_faces = None, ()  # nothing to decimate, or the simplifier refused: the whole mesh
    if len(triangles) > OUTLINE_FACES:
        try:
            new_points, new_faces = fast_simplification.simplify(welded, triangles.astype(np.int32),
                                                                 target_count=OUTLINE_FACES, preserve_border=True)
        except (ValueError, RuntimeError):
            pass
    outline = mesh
    if 0 < len(new_faces) <= OUTLINE_SHARE * len(triangles):
        vertices = torch.from_numpy(np.asarray(new_points)).to(positions)[None]
        new_faces = torch.from_numpy(np.asarray(new_faces, dtype=np.int64)).to(faces)
        decimated = replace(mesh, positions=vertices, normals=torch.zeros_like(vertices), uvs=None, faces=new_faces,
                            face_material=torch.zeros(len(new_faces), dtype=torch.long, device=faces.device))
        if float(_outline_overlaps(mesh, decimated).min()) >= OUTLINE_IOU:
            outline = decimated
    _OUTLINE[:] = [(positions, faces, outline)]
    return outline


def _outline_overlaps(mesh: MeshBatch, outline: MeshBatch) -> torch.Tensor:
    """Silhouette IoU (OUTLINE_VIEWS,) of `outline` against `mesh` from views all around, each framing
    the object at SEARCH_SIZE."""
    from ..render.rasterizer import visible_faces

    directions = fibonacci_directions(OUTLINE_VIEWS).to(mesh.positions)
    cameras = Cameras(DISTANCE * directions, torch.zeros_like(directions), _up_for(directions), FOV)
    cameras = _center_objects(mesh, cameras, SEARCH_SIZE)
    with torch.no_grad():
        whole, simple = (visible_faces(_clip(m, cameras, SEARCH_SIZE, SEARCH_SIZE), m.faces, SEARCH_SIZE,
                                       SEARCH_SIZE) >= 0 for m in (mesh, outline))
    return _iou(whole.float(), simple.float())


def _seen_target(low: torch.Tensor, high: torch.Tensor, seen_low: torch.Tensor, seen_high: torch.Tensor,
                 cut: torch.Tensor):
    """For `_center_objects` with an object seen in part: where each projected box (B, 2) should be
    centred (B, 2) once magnified by the returned factor (B, 1)."""
    span, seen_span = (high - low).clamp_min(1e-6), seen_high - seen_low
    whole = ~cut.any(-1)  # axes cut on neither side give the scale
    ratios = seen_span / span  # (B, 2)
    grow = (ratios * whole if bool(whole.any()) else ratios).amax(-1, keepdim=True)
    half = span * grow / 2
    centre = torch.where(~cut[:, 0], seen_low + half, torch.where(~cut[:, 1], seen_high - half,
                                                                   (seen_low + seen_high) / 2))
    return centre, grow


def frame_picture(picture: torch.Tensor, mask: torch.Tensor, size: int, background: torch.Tensor):
    """picture (3, H, W), mask (H, W) bool -> framed picture (1, 3, S, S), mask (1, S, S), box (1, 3),
    inside (1, S, S): where the square crop lies within the picture. An object cut off by the frame
    edge goes on beyond it, where the picture says nothing: the silhouette stages leave that out."""
    box = boxes_from_mask(mask[None].cpu())
    framed = crop_boxes(picture[None], box, size, background.reshape(1, 3).to(picture))
    framed_mask = crop_boxes(mask[None, None].to(picture.dtype), box, size)[:, 0]
    inside = crop_boxes(torch.ones_like(picture[None, :1]), box, size)[:, 0]
    return framed, framed_mask, box, inside


def _seen_part(mask: torch.Tensor, box: torch.Tensor, size: int):
    """The object's box in the picture (H, W) mask, in the pixels of the size x size crop `box`, and
    which of its sides the picture's edge cuts (`_center_objects`'s `seen`); None if none is cut."""
    height, width = mask.shape
    rows = torch.nonzero(mask.any(1)).squeeze(1)
    columns = torch.nonzero(mask.any(0)).squeeze(1)
    if not len(rows):
        return None
    left, right, top, bottom = float(columns[0]), float(columns[-1]) + 1, float(rows[0]), float(rows[-1]) + 1
    cut = torch.tensor([[left <= 0, right >= width], [top <= 0, bottom >= height]])
    if not bool(cut.any()):
        return None
    cx, cy, half = (float(v) for v in box)
    to_crop = lambda x, c: (x - (c - half)) / (2 * half) * size  # noqa: E731
    low = torch.tensor([[to_crop(left, cx), to_crop(top, cy)]])
    high = torch.tensor([[to_crop(right, cx), to_crop(bottom, cy)]])
    return low, high, cut[None]


def _targets(target: torch.Tensor, target_mask: torch.Tensor, inside: torch.Tensor) -> dict[int, tuple]:
    """The framed picture (1, 3, S, S), its mask (1, 1, S, S) and where it lies within the picture
    (1, 1, S, S) at the two working sizes."""
    levels = {}
    for size in (COMPARE_SIZE, SEARCH_SIZE):
        levels[size] = (F.interpolate(target, size=size, mode="area"),
                        F.interpolate(target_mask[:, None], size=size, mode="area"),
                        F.interpolate(inside[:, None], size=size, mode="area"))
    return levels


def _clip(mesh: MeshBatch, cameras: Cameras, height: int, width: int) -> torch.Tensor:
    """The mesh's clip-space vertices (B, V, 4) for each camera of a height x width picture."""
    positions = mesh.positions.expand(len(cameras), -1, -1) if mesh.positions.shape[0] == 1 else mesh.positions
    return cameras.world_to_clip(positions, width / height)


def _rasterized(mesh: MeshBatch, cameras: Cameras, height: int, width: int, pix_to_face: torch.Tensor | None = None):
    """Fragments and hard coverage (B, H, W) of each camera's view: what the silhouette stages need,
    without shading. `pix_to_face`: the views' visible faces, already worked out (`_overlaps`)."""
    from ..render.rasterizer import rasterize

    fragments = rasterize(_clip(mesh, cameras, height, width), mesh.faces, height, width, pix_to_face)
    return fragments, (fragments.pix_to_face >= 0).to(mesh.positions.dtype)


def _overlaps(mesh: MeshBatch, cameras: Cameras, level, faces_out: list | None = None) -> torch.Tensor:
    """Silhouette IoU (B,) of cameras against the picture (coverage only); their visible faces (B, S, S)
    are appended to `faces_out` where given."""
    from ..render.rasterizer import visible_faces

    size = level[1].shape[-1]
    with torch.no_grad():
        faces = visible_faces(_clip(mesh, cameras, size, size), mesh.faces, size, size)
        if faces_out is not None:
            faces_out.append(faces)
        return _iou(faces >= 0, level[1][:, 0], level[2][:, 0])


def _scores(mesh: MeshBatch, cameras: Cameras, level, shading_weight: float,
            pix_to_face: torch.Tensor | None = None) -> torch.Tensor:
    """Silhouette IoU - weighted shading misfit (B,) of cameras against the picture (`pix_to_face`:
    their visible faces, where `_overlaps` already found them)."""
    target, target_mask, inside = level
    size = target_mask.shape[-1]
    with torch.no_grad():
        fragments, cover = _rasterized(mesh, cameras, size, size, pix_to_face)
        iou = _iou(cover, target_mask[:, 0], inside[:, 0])
        return iou - shading_weight * _shading_misfit(mesh, fragments, cameras, target, target_mask)


def _shading_misfit(mesh: MeshBatch, fragments, cameras: Cameras, target: torch.Tensor,
                    target_mask: torch.Tensor) -> torch.Tensor:
    """How badly the picture's colours fit the mesh's texture under the best-fitting point light
    (`relight_fragments`), relative to their variance, per image (B,)."""
    n_batch = fragments.shape[0]
    seen = pixels_at(target.expand(n_batch, -1, -1, -1), fragments)
    inside = (pixels_at(target_mask.expand(n_batch, -1, -1, -1), fragments)[:, 0] > 0.5).to(seen.dtype)
    predicted, _, _ = relight_fragments(mesh, fragments, cameras, seen, directions=SCORE_LIGHT_DIRECTIONS,
                                        max_pixels=SCORE_LIGHT_PIXELS)
    error = seen.new_zeros(n_batch).index_add(0, fragments.batch, ((seen - predicted) ** 2).mean(1) * inside)
    count = seen.new_zeros(n_batch).index_add(0, fragments.batch, inside)
    pixels = seen.new_zeros(n_batch).index_add(0, fragments.batch, torch.ones_like(inside)).clamp_min(1)
    mean = seen.new_zeros(n_batch, 3).index_add(0, fragments.batch, seen) / pixels[:, None]
    variance = seen.new_zeros(n_batch).index_add(0, fragments.batch,
                                                 ((seen - mean[fragments.batch]) ** 2).mean(1) * inside)
    return torch.where(count >= 16, error / variance.clamp_min(1e-4), torch.ones_like(error))


def _moved(start: Cameras, delta: torch.Tensor, size: int) -> Cameras:
    """`start` (one camera, or B) moved by `delta` ((6,) or (B, 6)), in pixel-sized units of a size x
    size picture: a rotation (x, y, z) whose x and y turn the view by that many pixels at the centre, a
    translation (x, y) shifting the object by that many pixels and a move along the view axis growing
    it by that many pixels at its edge. Well-conditioned coordinates for the optimizer. One camera per
    row of `delta`, so that many moves render in one batch."""
    delta = delta.reshape(-1, 6)
    focal = size / 2 / math.tan(math.radians(start.fov_y) / 2)
    distance = (start.at - start.eye).norm(dim=-1, keepdim=True)  # (B or 1, 1)
    w0, w1, w2 = -delta[:, 1] / focal, delta[:, 0] / focal, delta[:, 2] * 2 / size
    zero = torch.zeros_like(w0)
    skew = torch.stack([torch.stack([zero, -w2, w1], -1), torch.stack([w2, zero, -w0], -1),
                        torch.stack([-w1, w0, zero], -1)], 1)  # (B, 3, 3): cross product with omega
    rotation = torch.linalg.matrix_exp(skew)
    translation = torch.stack([delta[:, 3] * distance[:, 0] / focal, -delta[:, 4] * distance[:, 0] / focal,
                               delta[:, 5] * distance[:, 0] * 2 / size], -1)
    view = start.view_matrix()
    rotation_world = rotation @ view[:, :3, :3]
    translation_world = (rotation @ view[:, :3, 3:])[..., 0] + translation
    eye = -(rotation_world.transpose(1, 2) @ translation_world[..., None])[..., 0]
    forward = -rotation_world[:, 2]
    return replace(start, eye=eye, at=eye + distance * forward, up=rotation_world[:, 1])


def _zoomed(start: Cameras, delta: torch.Tensor, size: int) -> Cameras:
    """`_moved` by the first six coordinates of `delta` (6 or 7,), and the focal length changed by the
    seventh (if any), in the same units: the picture grows by that many pixels at `size / 2` from its centre.
    A crop of a picture, or a picture made with another lens, has another field of view than the one
    registration assumes; the rigid move alone can match its size but not its perspective."""
    if len(delta) == 6:
        return _moved(start, delta, size)
    focal_scale = 1.0 + 2.0 * float(delta[6]) / size
    fov = math.degrees(2 * math.atan(math.tan(math.radians(start.fov_y) / 2) / max(focal_scale, 1e-3)))
    return replace(_moved(start, delta[:6], size), fov_y=fov)


def _screen_flow(start: Cameras, delta: torch.Tensor, points: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """How far each camera's world points (B, N, 3) move on its height x width screen per unit of each
    of `_moved`'s six coordinates, at `delta` (B, 6) (or (1, 6) for all) from `start` (B cameras):
    (6, B, N, 2) pixels. Analytic: the points in the moved camera's frame, their derivatives (a turn
    by the exponential map, to first order in the rotation already made; a shift) through the
    perspective division. The flow of both Gauss-Newton stages: exact, and one pass instead of the
    twelve projections central differences would take."""
    n_batch = len(start)
    delta = delta.reshape(-1, 6).expand(n_batch, 6)
    focal = height / 2 / math.tan(math.radians(start.fov_y) / 2)
    distance = (start.at - start.eye).norm(dim=-1)[:, None]  # (B, 1)
    moved = _moved(start, delta, height)
    view = moved.view_matrix()
    seen = points @ view[:, :3, :3].transpose(1, 2) + view[:, None, :3, 3]  # (B, N, 3): camera frame
    shift = torch.cat([distance / focal, -distance / focal, distance * 2 / height], -1)  # (B, 3) per unit
    turned = seen - delta[:, None, 3:] * shift[:, None]  # the start camera's view of the points, turned
    omega = torch.stack([-delta[:, 1] / focal, delta[:, 0] / focal, delta[:, 2] * 2 / height], -1)[:, None]
    x, y, z = turned.unbind(-1)
    half_dot = 0.5 * (omega * turned).sum(-1)
    # d seen / d omega_j = (e_j + omega x e_j / 2) x turned = e_j x turned + (e_j (omega . turned) - omega turned_j) / 2
    turn = [torch.stack(e, -1) - 0.5 * omega * t[..., None]
            for e, t in (((half_dot, -z, y), x), ((z, half_dot, -x), y), ((-y, x, half_dot), z))]
    axes = torch.eye(3, dtype=points.dtype)
    moves = torch.stack([turn[1] / focal, -turn[0] / focal, turn[2] * 2 / height,
                         *(shift[:, None, k:k + 1] * axes[k].expand_as(turned) for k in range(3))])  # (6, B, N, 3)
    projection = moved.projection_matrix(width / height)
    depth = -seen[..., 2:]
    ndc = (seen @ projection[:2, :3].T + projection[:2, 3]) / depth
    d_ndc = (moves @ projection[:2, :3].T + ndc * moves[..., 2:]) / depth
    return d_ndc * torch.tensor([width / 2, -height / 2], dtype=points.dtype)


def _pixel_points(mesh: MeshBatch, cameras: Cameras, size: int):
    """Hard coverage (B, 1, S, S) of each camera's size x size picture and a world point (B, S*S, 3)
    at every pixel: the visible surface on the object, and on the background the pixel's ray at the
    object's mean depth (the silhouette stage's flow is needed just outside the silhouette too). The
    surface point is the pixel's ray at the depth the z-buffer kept (exact: z / w is affine on the
    screen), so no fragment is interpolated."""
    from ..render.rasterizer import visible_faces_and_depth

    n_batch = len(cameras)
    faces, ndc = visible_faces_and_depth(_clip(mesh, cameras, size, size), mesh.faces, size, size)
    covered = (faces >= 0).reshape(n_batch, -1)
    cover = covered.to(mesh.positions.dtype).reshape(n_batch, 1, size, size)
    # gluPerspective: ndc = -A + B / depth, with A, B the projection's third row (`perspective`).
    a = (cameras.far + cameras.near) / (cameras.near - cameras.far)
    b = 2.0 * cameras.far * cameras.near / (cameras.near - cameras.far)
    visible_depth = torch.where(covered, b / (ndc.reshape(n_batch, -1) + a), 0.0)
    count = covered.sum(1)
    mean_depth = visible_depth.sum(1) / count.clamp_min(1)
    depth = torch.where(covered, visible_depth, mean_depth[:, None]).to(mesh.positions.dtype)  # (B, S*S)
    view = cameras.view_matrix()
    rotation, translation = view[:, :3, :3], view[:, :3, 3]
    centres = (torch.arange(size, dtype=depth.dtype) + 0.5) / size * 2 - 1
    ndc_y, ndc_x = torch.meshgrid(-centres, centres, indexing="ij")
    focal = 1.0 / math.tan(math.radians(cameras.fov_y) / 2)
    x = (ndc_x.reshape(1, -1) - cameras.principal[0]) / focal * depth
    y = (ndc_y.reshape(1, -1) - cameras.principal[1]) / focal * depth
    in_camera = torch.stack([x, y, -depth], -1)  # (B, S*S, 3)
    world = ((in_camera - translation[:, None]) @ rotation)  # R^T (p - t), row vectors
    return cover, world


def _refine_silhouettes(mesh: MeshBatch, start: Cameras, level, sigma: float, iterations: int = 10,
                        done_step: float | None = None) -> Cameras:
    """Gauss-Newton on a rigid move of each camera of `start` (`_moved`; independent, one batch) that
    brings its silhouette onto the picture's, both blurred by `sigma` pixels. The Jacobian is the
    blurred silhouette's gradient times each pose coordinate's screen flow (as `_flow_jacobian`), so an
    iteration costs one hard render and no backward pass; a camera whose step does not lower its cost
    keeps its pose and damps harder (Levenberg-Marquardt). A camera stops once its step is under
    `done_step` pixels (SILHOUETTE_DONE by default) at a damping of at most FREEZE_DAMPING."""
    from ..render.blur import gaussian_blur  # compiled on the CPU where no gradient flows: the same bits

    _, target_mask, inside = level
    size = target_mask.shape[-1]
    done_step = SILHOUETTE_DONE if done_step is None else done_step
    n_batch = len(start)
    blurred_target = gaussian_blur(target_mask, sigma).reshape(1, -1)
    # Only pixels whose blur sees nothing beyond the picture's edge: past it the object may go on.
    known = (gaussian_blur(inside, sigma) > 0.999).to(target_mask.dtype).reshape(1, -1)
    delta = torch.zeros(n_batch, 6)
    damping = torch.full((n_batch,), 1e-3)

    def evaluate(cameras: Cameras, delta):
        cover, points = _pixel_points(mesh, _moved(cameras, delta, size), size)
        blurred = gaussian_blur(cover, sigma)
        return blurred, points, (known * (blurred.reshape(len(delta), -1) - blurred_target) ** 2).sum(1)

    with torch.no_grad():
        blurred, points, cost = evaluate(start, delta)
        running = list(range(n_batch))  # the cameras still moving
        # A rejected step leaves its camera where it was: its normal equations are kept and solved
        # again with more damping, not rebuilt.
        normal_all, rhs_all = torch.zeros(n_batch, 6, 6), torch.zeros(n_batch, 6)
        stale = [True] * n_batch
        for _ in range(iterations):
            renew = [camera for camera in running if stale[camera]]
            if renew:
                run = torch.tensor(renew)
                some = start if len(renew) == n_batch else start[renew]
                n_run = len(renew)
                gradient_y, gradient_x = torch.gradient(blurred[run, 0], dim=(1, 2))
                gradient_x, gradient_y = gradient_x.reshape(n_run, -1), gradient_y.reshape(n_run, -1)
                # Only pixels where the blurred silhouette varies have a Jacobian row (elsewhere the
                # image gradient is exactly zero): the screen flow is taken at those alone, per
                # camera, padded to the longest list with rows of zero weight.
                active = ((gradient_x != 0) | (gradient_y != 0)) & (known > 0.5)
                counts = active.sum(1)
                longest = max(1, int(counts.max()))
                rows, columns = active.nonzero(as_tuple=True)  # row-major: each row's pixels in order
                starts = torch.cumsum(counts, 0) - counts
                pick = torch.zeros(n_run, longest, dtype=torch.long)
                pick[rows, torch.arange(len(rows)) - starts[rows]] = columns
                valid = (torch.arange(longest)[None] < counts[:, None]).to(blurred.dtype)
                flow = _screen_flow(some, delta[run], points[run].gather(1, pick[..., None].expand(-1, -1, 3)), size,
                                    size)  # (6, B, N, 2)
                jacobian = -(gradient_x.gather(1, pick)[None] * flow[..., 0]
                             + gradient_y.gather(1, pick)[None] * flow[..., 1]).permute(1, 2, 0)  # (B, N, 6)
                jacobian = jacobian * valid[..., None]
                residual = ((blurred[run].reshape(n_run, -1) - blurred_target) * known).gather(1, pick)
                normal_all[run] = jacobian.transpose(1, 2) @ jacobian
                rhs_all[run] = (jacobian.transpose(1, 2) @ residual[..., None])[..., 0]
                for camera in renew:
                    stale[camera] = False
            run = torch.tensor(running)
            some = start if len(running) == n_batch else start[running]
            normal = normal_all[run]
            scale = normal.diagonal(dim1=1, dim2=2).mean(-1).clamp_min(1e-12)
            damped = damping[run]
            update = -torch.linalg.solve(normal + (damped * scale)[:, None, None] * torch.eye(6), rhs_all[run])
            trial_blurred, trial_points, trial_cost = evaluate(some, delta[run] + update)
            better = trial_cost < cost[run]
            delta[run] = torch.where(better[:, None], delta[run] + update, delta[run])
            blurred[run] = torch.where(better[:, None, None, None], trial_blurred, blurred[run])
            points[run] = torch.where(better[:, None, None], trial_points, points[run])
            cost[run] = torch.where(better, trial_cost, cost[run])
            damping[run] = torch.where(better, damping[run] * 0.3, damping[run] * 10).clamp(1e-6, 1e6)
            for camera, moved in zip(running, better.tolist()):
                stale[camera] = stale[camera] or moved
            # Done: a step under `done_step` that is short because the minimum is near, not because damping
            # (raised by rejected steps) shortened it: a damped camera may yet get going again.
            done = (update.abs().amax(1) < done_step) & (damped <= FREEZE_DAMPING)
            running = [camera for camera, stop in zip(running, done.tolist()) if not stop]
            if not running:
                break
        return _moved(start, delta, size)


def _working_size(picture: torch.Tensor, mask: torch.Tensor, longest: int = WORKING_SIZE):
    """The picture (1, 3, H, W) and mask (1, H, W) shrunk (area) so that the longer side is at most
    `longest` pixels: a camera is resolution-independent, so it can be refined on the smaller copy."""
    height, width = picture.shape[-2:]
    scale = min(1.0, longest / max(height, width))
    if scale == 1.0:
        return picture, mask
    size = (max(1, round(height * scale)), max(1, round(width * scale)))
    return F.interpolate(picture, size=size, mode="area"), F.interpolate(mask[:, None].float(), size=size, mode="area")[:, 0]


def silhouette_iou(mesh: MeshBatch, camera: Cameras, mask: torch.Tensor) -> float:
    """Overlap of the mesh's silhouette seen by `camera` with the picture's object `mask` (H, W)."""
    small, small_mask = _working_size(mask[None, None].float().expand(1, 3, -1, -1), mask[None].float(), 256)
    height, width = small_mask.shape[-2:]
    with torch.no_grad():
        _, cover = _rasterized(mesh, camera, height, width)
    return float(_iou(cover, small_mask)[0])


def pose_error(mesh: MeshBatch, truth: Cameras, found: Cameras, height: int, width: int) -> float:
    """Mean distance in pixels between where the `truth` camera and the `found` one put the surface
    points that a height x width picture from `truth` shows (the registration's error as the
    un-rendering feels it)."""
    from ..render import clip_to_screen, surface_at_pixels, surface_points

    with torch.no_grad():
        fragments, _, _ = surface_at_pixels(mesh, truth, height, width)
        points, _ = surface_points(mesh, fragments, truth)
        if len(points) == 0:
            return float("nan")
        where = [clip_to_screen(c.world_to_clip(points[None], width / height), height, width)[0] for c in (truth, found)]
        return float((where[0] - where[1]).norm(dim=-1).mean())


def refine_on_texture(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor,
                      sigmas: tuple[float, ...] | None = None, iterations: int = 10,
                      margin: int = 3, light_from: str = "all", zoom: bool = False) -> Cameras:
    """Sub-pixel refinement of `camera` (one camera of `picture` (1, 3, H, W), object pixels `mask`
    (1, H, W)) on the texture rather than the silhouette: Gauss-Newton on the rigid move of `_moved`
    (pixel units) minimising the squared difference between the picture and the original relit to
    match it, over interior pixels at least `margin` pixels from any silhouette (so that moves of a
    pixel or two never bring background in). Both are band-passed around each of `sigmas` in turn
    (coarse to fine: wider basins first; TEXTURE_SIGMAS unless given); the light is refitted before each level (on the pixels
    `light_from` says, see `reading.relight.relit_residual`), and a level blurred
    by sigma > TEXTURE_SCALE_SIGMA pixels runs on a copy shrunk so that its blur is that many pixels
    (fewer pixels to render, as accurate). The Jacobian is the band-passed picture's gradient times the
    analytic screen flow of each pose coordinate (`_flow_jacobian`, one render per iteration), not
    central differences of rendered pictures, which cost twelve renders an iteration and whose noise on
    fine texture stops refinements short of the pose (docs/reading.md, "Alternatives measured"). A
    step that does not lower the cost is halved twice before the level stops. With `zoom` the move has
    a seventh coordinate, the focal length (`_zoomed`): a crop or another lens gives a picture another
    field of view than the one assumed. Zoom and a move along the view axis differ only by
    perspective, so a large change of the field of view takes more than one pass: the levels run again
    from where the last pass ended while it changed the field of view by ZOOM_AGAIN degrees or more,
    ZOOM_ROUNDS passes at most. Works on a copy of at most WORKING_SIZE pixels a side."""
    picture, mask = _working_size(picture, mask)
    sigmas = TEXTURE_SIGMAS if sigmas is None else sigmas
    if not zoom:
        return _texture_levels(mesh, camera, picture, mask, sigmas, iterations, margin, light_from, False)
    for _ in range(ZOOM_ROUNDS):
        start_fov = camera.fov_y
        camera = _texture_levels(mesh, camera, picture, mask, sigmas, iterations, margin, light_from, True)
        if abs(camera.fov_y - start_fov) < ZOOM_AGAIN:
            break
    return camera


def _texture_levels(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor,
                    sigmas: tuple[float, ...], iterations: int, margin: int, light_from: str, zoom: bool) -> Cameras:
    """One coarse-to-fine pass of `refine_on_texture`."""
    for sigma in sigmas:
        scale = min(1.0, TEXTURE_SCALE_SIGMA / sigma)
        level_picture, level_mask = picture, mask
        if scale < 1.0:
            size = (max(8, round(picture.shape[-2] * scale)), max(8, round(picture.shape[-1] * scale)))
            level_picture = F.interpolate(picture, size=size, mode="area")
            level_mask = F.interpolate(mask[:, None], size=size, mode="area")[:, 0]
        camera = _texture_level(mesh, camera, level_picture, level_mask, sigma * scale, iterations, margin,
                                light_from, zoom)
    return camera


@dataclass
class _Fit:
    """The original relit to match a picture: the mesh with the fitted ambient factors, the lights, and
    the rasterization they were fitted on."""

    relit: MeshBatch
    lights: object
    fragments: object = None


def _relit_view(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor, margin: int,
                light_from: str = "all"):
    """The original relit to match `picture` (1, 3, H, W) from `camera` (`reading.relight.relit_residual`)
    and the interior pixels (1, H, W): on the object in both and at least `margin` pixels from any
    silhouette, so that moves of a pixel or two never bring background in. None when fewer than 64
    interior pixels are left."""
    from .relight import fitted_light

    relit, lights, fragments = fitted_light(mesh, picture, camera, light_from)
    inside = _interior(fragments.pix_to_face >= 0, mask, margin)
    if int(inside.sum()) < 64:
        return None
    return _Fit(relit, lights, fragments), inside


def _interior(covered: torch.Tensor, mask: torch.Tensor, margin: int) -> torch.Tensor:
    """The pixels (B, H, W) on the object both in a render (`covered`, B, H, W) and in the picture
    (`mask`, 1 or B, H, W) and at least `margin` pixels (in both axes) from any pixel off either: a
    square max pool of the outside, as two one-dimensional ones (the same pixels, several times
    faster)."""
    outside = (~covered | (mask < 0.5)).to(mask.dtype)[:, None]
    size = 2 * margin + 1
    grown = F.max_pool2d(F.max_pool2d(outside, (1, size), 1, (0, margin)), (size, 1), 1, (margin, 0))
    return grown[:, 0] < 0.5


def _band_pass(inside: torch.Tensor, sigma: float, wide: float | None = None):
    """A function band-passing pictures (B, 3, H, W) around `sigma` over the `inside` (1, H, W) pixels
    only (normalised blurs, so the silhouette's edge leaks nothing in). The blurs run on the box around
    the inside pixels that the wider one reaches (the rest of the frame, zero, is the same as the whole
    frame would give there), and the blurred weights once."""
    from ..imaging import blur_radius
    from ..render.blur import gaussian_blur  # compiled on the CPU where no gradient flows: the same bits

    wide = LOWPASS * max(sigma, 1.0) if wide is None else wide
    reach = blur_radius(wide)
    rows, columns = inside[0].any(dim=1).nonzero()[:, 0], inside[0].any(dim=0).nonzero()[:, 0]
    top, left = max(0, int(rows[0]) - reach), max(0, int(columns[0]) - reach)
    box = (slice(top, int(rows[-1]) + 1 + reach), slice(left, int(columns[-1]) + 1 + reach))
    weight = inside[:, None, box[0], box[1]].float()
    narrow = (lambda x: x) if sigma <= 0 else (lambda x: gaussian_blur(x, sigma))  # noqa: E731
    norms = [narrow(weight).clamp_min(1e-3), gaussian_blur(weight, wide).clamp_min(1e-3)]

    def band(x: torch.Tensor) -> torch.Tensor:
        part = x[..., box[0], box[1]] * weight
        out = x.new_zeros(x.shape)
        out[..., box[0], box[1]] = narrow(part) / norms[0] - gaussian_blur(part, wide) / norms[1]
        return out

    return band


def _band_problem(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor, sigma: float,
                  margin: int, light_from: str = "all"):
    """What the texture stage compares, from `camera`'s view of `picture` (1, 3, H, W): a function
    rendering the relit original from any camera and returning the band-passed difference to the
    picture over the interior pixels of `_relit_view`, the band-passed picture there, the interior and
    the relit mesh. None when `_relit_view` is."""
    view = _relit_view(mesh, camera, picture, mask, margin, light_from)
    if view is None:
        return None
    fit, inside = view
    height, width = picture.shape[-2:]
    band = _band_pass(inside, sigma)
    target = band(picture).permute(0, 2, 3, 1)[inside].reshape(-1)
    renderer = MeshRenderer(blend="hard")

    def residual(moved: Cameras, with_image: bool = False):
        """(B, M) for B cameras: every camera of `moved` renders in one batch; with `with_image`, also
        the band-passed renders (B, 3, H, W) and their rasterization."""
        rendered = renderer(fit.relit, moved, fit.lights[[0] * len(moved)], height, width)
        banded = band(rendered.image)
        values = banded.permute(0, 2, 3, 1)[:, inside[0]].reshape(len(moved), -1) - target
        return (values, banded, rendered.fragments) if with_image else values

    return residual, target, inside, fit.relit


def texture_misfit(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor,
                   sigmas: tuple[float, ...] = (1.0,), margin: int = 2) -> float:
    """How badly the original's texture, seen from `camera`, explains the picture (1, 3, H, W)
    band-passed around each of `sigmas`: residual energy over picture energy, summed over the bands
    (0: perfect, ~2 a band: unrelated). One light fit and one render serve every band. Shading is
    mostly outside the bands, so a wrong view cannot buy a good score with a wrongly fitted light, as
    it can with the silhouette-and-shading score. Used to pick among candidate views of symmetric
    shapes."""
    return texture_misfits(mesh, camera, picture, mask, sigmas, margin)[0]


def texture_misfits(mesh: MeshBatch, cameras: Cameras, picture: torch.Tensor, mask: torch.Tensor,
                    sigmas: tuple[float, ...] = (1.0,), margin: int = 2) -> list[float]:
    """`texture_misfit` of each of several cameras of the same picture, their light fits and renders
    in one batch (the same numbers as one camera at a time)."""
    from .relight import fitted_light

    n_cameras = len(cameras)
    if n_cameras == 0:
        return []
    height, width = picture.shape[-2:]
    with torch.no_grad():
        relit, lights, fragments = fitted_light(mesh, picture.expand(n_cameras, -1, -1, -1), cameras)
        rendered = MeshRenderer(blend="hard")(relit, cameras, lights, height, width, fragments=fragments).image
        inside = _interior(fragments.pix_to_face >= 0, mask.to(picture.dtype), margin)
        misfits = []
        for index in range(n_cameras):
            seen_inside = inside[index:index + 1]
            if int(seen_inside.sum()) < 64:
                misfits.append(float("inf"))
                continue
            total = 0.0
            for sigma in sigmas:
                band = _band_pass(seen_inside, sigma)
                target, seen = (band(x).permute(0, 2, 3, 1)[seen_inside] for x in (picture, rendered[index:index + 1]))
                total += float(((seen - target) ** 2).sum() / (target ** 2).sum().clamp_min(1e-12))
            misfits.append(total)
        return misfits


def _joined(cameras: list[Cameras]) -> Cameras:
    """Cameras (one each, same intrinsics) as one batch."""
    return replace(cameras[0], eye=torch.cat([c.eye for c in cameras]), at=torch.cat([c.at for c in cameras]),
                   up=torch.cat([c.up for c in cameras]))


def refine_on_texture_twice(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor) -> Cameras:
    """`refine_on_texture` from `camera` with the light fitted on all the object's pixels and, unless
    that already cut the texture misfit to under `FLAT_RETRY` of the start's, again with the light
    fitted on its flattest half, keeping whichever result (or `camera` itself) the texture fits best.
    A light fitted at a pose a pixel or two off can be far wrong (a far, strong light for a near one),
    and with it the cost is lower off the true pose than at it; on the flat half the fit barely sees
    the pose error, but it has fewer and less varied pixels, and it loses on some meshes that the
    all-pixel fit reads. Keeping the start guards against runs that drift off a good pose. The second
    run is skipped where the first plainly converged: there it would change nothing and only cost time.
    Where the best still fits the texture poorly (ZOOM_TRY) and one Gauss-Newton step that also moves
    the field of view moves it by ZOOM_PROBE_DEGREES or more, a run that also refines the field of view
    (`refine_on_texture`'s `zoom`) goes on from it: a crop, or a picture made through another lens,
    is registered a pixel or so off without it, and that costs a luminance mark its reading."""
    picture, mask = _working_size(picture, mask)
    results = [camera, refine_on_texture(mesh, camera, picture, mask, light_from="all")]
    misfits = texture_misfits(mesh, _joined(results), picture, mask)
    lights = [None, "all"]
    if misfits[1] >= FLAT_RETRY * misfits[0] and misfits[1] >= FLAT_ENOUGH:
        results.append(refine_on_texture(mesh, camera, picture, mask, light_from="flat"))
        misfits.append(texture_misfit(mesh, results[-1], picture, mask))
        lights.append("flat")
    best = min(range(len(results)), key=misfits.__getitem__)
    if misfits[best] < ZOOM_TRY:
        return results[best]
    # The field of view too, from the best, where the texture still fits poorly and one step with the
    # zoom asks for another field of view (a full zoomed run costs several plain ones): kept only where
    # it explains the texture clearly better (on a picture with the assumed field of view the weakly
    # determined zoom only adds noise).
    probe = _texture_level(mesh, results[best], picture, mask, ZOOM_PROBE_SIGMA, 1, 3, lights[best] or "all", True)
    if abs(probe.fov_y - results[best].fov_y) < ZOOM_PROBE_DEGREES:
        return results[best]
    zoomed = refine_on_texture(mesh, results[best], picture, mask, light_from=lights[best] or "all", zoom=True)
    return zoomed if texture_misfit(mesh, zoomed, picture, mask) < ZOOM_GAIN * misfits[best] else results[best]


@dataclass
class _Window:
    """The object's square window of a picture, its edges on pixel edges so that its pixels are the
    picture's: a camera rendering just it (`camera`, `side` pixels a side), the interior pixels in it
    (`seen`, side x side) and the picture's values there (`target`, (M, 3))."""

    camera: Cameras
    side: int
    seen: torch.Tensor
    target: torch.Tensor
    image: torch.Tensor  # the picture's window (3, side, side)
    box: tuple  # (cx, cy, half) in the picture's pixels, and the picture's (height, width)
    size: tuple

    def seen_from(self, camera: Cameras) -> Cameras:
        """Another camera of the same picture, rendering just this window (the window is the object's
        box, the same whatever the camera)."""
        fov, principal = crop_intrinsics(*self.size, self.box, camera.fov_y)
        return replace(camera, fov_y=fov, principal=principal)


def _object_window(camera: Cameras, picture: torch.Tensor, inside: torch.Tensor, largest: int) -> _Window:
    """`_Window` of the `inside` pixels (1, H, W) of `picture` (1, 3, H, W) seen from `camera`: their
    square box and two pixels, at most `largest` pixels a side (in a large picture, the part around the
    object's centre, so that the cost stays bounded)."""
    height, width = picture.shape[-2:]
    rows, columns = inside[0].any(1).nonzero()[:, 0], inside[0].any(0).nonzero()[:, 0]
    top, bottom = int(rows[0]) - 2, int(rows[-1]) + 3
    left, right = int(columns[0]) - 2, int(columns[-1]) + 3
    side = max(bottom - top, right - left)
    top, left = (top + bottom - side) // 2, (left + right - side) // 2
    if side > largest:
        centre_row, centre_column = inside[0].nonzero().float().mean(0).round().long().tolist()
        top = min(max(centre_row - largest // 2, top), top + side - largest)
        left = min(max(centre_column - largest // 2, left), left + side - largest)
        side = largest
    box = (left + side / 2, top + side / 2, side / 2)
    # The window may reach past the picture's edges: pad, then cut it out.
    pad_left, pad_top = max(0, -left), max(0, -top)
    cut = lambda x: F.pad(x, (pad_left, max(0, left + side - width), pad_top, max(0, top + side - height)))[  # noqa: E731
        0, :, top + pad_top:top + pad_top + side, left + pad_left:left + pad_left + side]
    seen, image = cut(inside[:, None].float())[0] > 0.5, cut(picture)
    window = _Window(camera, side, seen, image.permute(1, 2, 0)[seen], image, box, (height, width))
    return replace(window, camera=window.seen_from(camera))


def _from_window(window: _Window, delta: torch.Tensor, camera: Cameras) -> Cameras:
    """The picture's camera after the move `delta` of `_moved` made in `window`'s frame: `_moved`'s turn
    about the view axis and move along it are in pixels at the window's edge, the window's own camera
    carries them back, then the picture's intrinsics."""
    return replace(_moved(window.camera, delta, window.side), fov_y=camera.fov_y, principal=camera.principal)


def sharpen(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor) -> Cameras:
    """`camera` moved to where the relit original, rendered as the reading renders it (antialiased and
    unfiltered, the light fitted once at `camera`), best explains the picture (1, 3, H, W) over its
    interior pixels. A point-sampled texture a little finer than the pixels makes the picture alias:
    a tenth of a pixel moves each pixel to other texels, the texture leaks into the residual the
    reading subtracts and drowns the mark, even where the texture stage calls the camera registered
    (docs/reading.md, stage 7). The texture stage's band-passed
    alignment cannot see that, and neither can image gradients (their Jacobian points elsewhere):
    this is a pattern search, six moves by +-step px (those of `_screen_basis`, each shifting the seen
    surface alike) in one batch of renders, the step halved when none helps, from SHARPEN_STEPS[0] to
    SHARPEN_STEPS[1] pixels, at most SHARPEN_RENDERS renders of the object's own window (at most SHARPEN_WINDOW pixels a side: in
    a large picture, the part around the object's centre). Where it moves the camera to a worse
    view, only the reading can tell: `reading.second_look` reads both."""
    with torch.no_grad():
        view = _relit_view(mesh, camera, picture, mask, margin=2)
        if view is None:
            return camera
        fit, inside = view
        window = _object_window(camera, picture, inside, SHARPEN_WINDOW)
        renderer = MeshRenderer()

        def costs(deltas: torch.Tensor) -> torch.Tensor:
            lights = fit.lights[[0] * len(deltas)]  # the one fitted light for every trial camera
            rendered = renderer(fit.relit, _moved(window.camera, deltas, window.side), lights, window.side,
                                window.side).image
            return ((rendered.permute(0, 2, 3, 1)[:, window.seen] - window.target) ** 2).sum((1, 2))

        centre = torch.zeros(6, dtype=picture.dtype)
        best, step, renders = float(costs(centre[None])[0]), SHARPEN_STEPS[0], 1
        # Each move shifts the seen surface by `step` px (RMS), no two alike (`_screen_basis`), as the polish's.
        seen = window.seen[None]
        fragments, _ = _rasterized(fit.relit, window.camera, window.side, window.side)
        basis = _screen_basis(fit.relit, window.camera, fragments, seen & (fragments.pix_to_face >= 0))
        moves = torch.cat([basis.T, -basis.T]).to(picture.dtype)
        while step >= SHARPEN_STEPS[1] and renders + len(moves) <= SHARPEN_RENDERS:
            trials = centre + step * moves
            trial_costs = costs(trials)
            renders += len(moves)
            pick = int(trial_costs.argmin())
            if float(trial_costs[pick]) < best:
                best, centre = float(trial_costs[pick]), trials[pick]
            else:
                step /= 2
        return _from_window(window, centre, camera)


def nudges(mesh: MeshBatch, camera: Cameras, mask: torch.Tensor, step: float) -> Cameras:
    """The 12 cameras `step` pixels (RMS over the surface seen at the interior pixels) from `camera`
    (one, of a picture whose object pixels are `mask` (1, H, W)) along each way of the six orthogonal
    screen moves (`_screen_basis`). No cost decides among them: the second look reads each, with the
    key (`reading.second_look`), where its texture-led stages leave a picture a tenth of a pixel off."""
    height, width = mask.shape[-2:]
    with torch.no_grad():
        fragments, _ = _rasterized(mesh, camera, height, width)
        inside = _interior(fragments.pix_to_face >= 0, mask, 2)
        basis = _screen_basis(mesh, camera, fragments, inside)
        return _moved(camera, step * torch.cat([basis.T, -basis.T]).to(camera.eye.dtype), height)


def _splat_weights(dtype) -> torch.Tensor:
    """The renderer's splat (`render.splatter`, sigma 0.5) over an interior pixel's 3 x 3 neighbours:
    what turns point samples into the antialiased render there."""
    offsets = torch.tensor([-1.0, 0.0, 1.0], dtype=torch.float64)
    rows, columns = torch.meshgrid(offsets, offsets, indexing="ij")
    weights = torch.exp(-(rows ** 2 + columns ** 2) / (2 * 0.5 ** 2))
    return (weights / weights.sum()).to(dtype)


def match_blocks(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor) -> Cameras:
    """`camera` moved to where the picture's blocks (BLOCK_SIDE pixels a side) each best match the
    relit original, found by trying every shift of the render in steps of 1 / BLOCK_SUPERSAMPLE of a
    pixel up to BLOCK_REACH + 1/2 pixels each way at once, then the six-move pose whose screen flow
    (`_screen_basis`) best carries each block by its shift (robust least squares, each block weighted by
    how clearly its best shift stands out).

    A fine texture on a thin or small object (leaves, a fence, a tool's handle) makes the misfit of a
    pose a rugged function of it: a tenth of a pixel brings each pixel to other texels, and the
    Gauss-Newton stages stop in a hollow a third of a pixel from the picture's pose, which the reading
    needs to hundredths. Every shift of a point-sampled render is a sub-sampling of one render
    BLOCK_SUPERSAMPLE times larger (the splat then applied as the renderer applies it), so all of them
    cost one render, and a block's best shift is found however rugged the misfit between. The blocks
    cover the whole object, silhouette included (each shift compared where it and the picture are the
    object), so a thin object has blocks too. Nothing here looks at a key."""
    with torch.no_grad():
        supersample, weights = BLOCK_SUPERSAMPLE, _splat_weights(picture.dtype)
        for _ in range(BLOCK_ROUNDS):
            window = _object_window(camera, picture, mask > 0.5, POLISH_WINDOW)
            side, blocks = window.side, window.side // BLOCK_SIDE
            view = _relit_view(mesh, window.camera, window.image[None], window.seen[None].to(picture.dtype), margin=1)
            if view is None or blocks < 2:
                return camera
            fit, inside = view
            large = MeshRenderer(blend="hard")(fit.relit, window.camera, fit.lights, side * supersample,
                                               side * supersample).rgba
            # (K, 4, side, side): the render sub-sampled at each of the K = supersample^2 offsets, splatted
            samples = large[0].reshape(side, supersample, side, supersample, 4).permute(1, 3, 4, 0, 2)
            samples = samples.reshape(-1, 4, side, side)
            colours = F.conv2d(samples[:, :3].reshape(-1, 1, side, side), weights[None, None], padding=1)
            colours, covered = colours.reshape(-1, 3, side, side), samples[:, 3] > 0.5
            cut, reach = blocks * BLOCK_SIDE, BLOCK_REACH
            misfits = []  # per whole-pixel shift: (K, blocks, blocks)
            for whole_y in range(-reach, reach + 1):
                for whole_x in range(-reach, reach + 1):
                    moved = torch.roll(colours, (-whole_y, -whole_x), (2, 3))
                    valid = torch.roll(covered, (-whole_y, -whole_x), (1, 2)) & inside
                    error = ((moved - window.image[None]) ** 2).sum(1) * valid
                    count = F.avg_pool2d(valid[:, None, :cut, :cut].to(error.dtype), BLOCK_SIDE)[:, 0]
                    misfits.append(F.avg_pool2d(error[:, None, :cut, :cut], BLOCK_SIDE)[:, 0] / count.clamp_min(1e-3))
            # on one regular grid of shifts, 1 / supersample px apart: (y, x, block)
            width = (2 * reach + 1) * supersample
            grid = torch.stack(misfits).reshape(2 * reach + 1, 2 * reach + 1, supersample, supersample, -1)
            grid = grid.permute(0, 2, 1, 3, 4).reshape(width, width, -1).double()
            flat = grid.reshape(width * width, -1)
            best = flat.argmin(0)
            best_y, best_x = best // width, best % width
            lowest, typical = flat.gather(0, best[None])[0], flat.median(0).values
            weight = ((typical - lowest) / typical.clamp_min(1e-12)).clamp(0, 1) ** 2
            cover = F.avg_pool2d(inside[:, None, :cut, :cut].to(picture.dtype), BLOCK_SIDE).reshape(-1)
            inner = lambda k: (k > 0) & (k < width - 1)  # noqa: E731  (not at the edge of the search)
            usable = (cover >= BLOCK_COVER) & inner(best_y) & inner(best_x)
            found = torch.stack([best_x, best_y], 1).double()
            for axis, (dy, dx) in enumerate(((0, 1), (1, 0))):  # a parabola through each axis's three misfits
                ys, xs = best_y.clamp(1, width - 2), best_x.clamp(1, width - 2)
                at = lambda y, x: flat.gather(0, (y * width + x)[None])[0]  # noqa: E731
                left, right = at(ys - dy, xs - dx), at(ys + dy, xs + dx)
                curve = left - 2 * lowest + right
                found[:, axis] += torch.where(curve > 0, 0.5 * (left - right) / curve.clamp_min(1e-30), 0.0).clamp(-0.5, 0.5)
            found = (found + 0.5) / supersample - 0.5 - reach  # grid index -> pixels
            if int(usable.sum()) < 6:
                return camera
            # each block's mean screen flow under the six moves of the screen basis
            flow = _seen_flow(fit.relit, window.camera, fit.fragments, inside).double()  # (6, M, 2)
            basis = _screen_basis(fit.relit, window.camera, fit.fragments, inside).double()
            rows, columns = inside[0].nonzero(as_tuple=True)
            within = (rows < cut) & (columns < cut)
            block_of = (rows // BLOCK_SIDE * blocks + columns // BLOCK_SIDE)[within]
            total = flow.new_zeros(6, blocks * blocks, 2).index_add_(1, block_of, flow[:, within])
            count = flow.new_zeros(blocks * blocks).index_add_(0, block_of, flow.new_ones(len(block_of)))
            per_move = torch.einsum("ik,ijl->jlk", basis, (total / count.clamp_min(1)[None, :, None]))[usable]
            # a picture that is the render shifted by d shows each surface point d nearer the origin
            wanted, weight = -found[usable], weight[usable]
            design = per_move.reshape(-1, 6)
            move = torch.zeros(6, dtype=torch.float64)
            for _ in range(5):  # Huber weights at 0.1 px, iteratively reweighted
                miss = (wanted - per_move @ move).norm(dim=1)
                robust = (weight * (0.1 / miss.clamp_min(0.1))).repeat_interleave(2)
                normal = design.T @ (design * robust[:, None]) + 1e-6 * torch.eye(6, dtype=torch.float64)
                move = torch.linalg.solve(normal, design.T @ (robust * wanted.reshape(-1)))
            length = float(move.norm())  # px RMS over the seen surface: the basis is orthonormal there
            if not length <= BLOCK_MAX:
                return camera
            camera = _from_window(window, (basis @ move).to(picture.dtype), camera)
            if length < POLISH_AGAIN:
                break
        return camera


def polish_blocks(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor) -> Cameras | None:
    """`match_blocks`' camera, polished (`polish`), where the picture's misfit (`polish_misfit`) is lower
    there than at `camera`; else None (the blocks found nothing better)."""
    matched = match_blocks(mesh, camera, picture, mask)
    if matched is camera or not polish_misfit(mesh, matched, picture, mask) < polish_misfit(mesh, camera, picture, mask):
        return None
    return polish(mesh, matched, picture, mask)


def polish_misfit(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor) -> float:
    """What `polish` lowers, at `camera`: the mean squared difference between the picture (1, 3, H, W) and
    the original relit there, both high-passed at POLISH_HIGHPASS, over the interior of its object
    `mask` (1, H, W); inf where too little of it is left."""
    with torch.no_grad():
        window = _object_window(camera, picture, mask > 0.5, POLISH_WINDOW)
        view = _relit_view(mesh, window.camera, window.image[None], window.seen[None].to(picture.dtype), margin=2)
        if view is None:
            return math.inf
        fit, inside = view
        band = (lambda x: x) if not POLISH_HIGHPASS else _band_pass(inside, 0.0, POLISH_HIGHPASS)
        render = MeshRenderer()(fit.relit, window.camera, fit.lights, window.side, window.side).image
        difference = (band(window.image[None]) - band(render))[0].permute(1, 2, 0)[inside[0]]
        return float((difference.double() ** 2).mean())


def polish(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor) -> Cameras:
    """The registered `camera` of `picture` (1, 3, H, W), object pixels `mask` (1, H, W), brought the last
    hundredths of a pixel to where the relit original, rendered as the reading renders it (antialiased,
    unblurred, at the picture's own size), best explains the picture over its interior pixels, both
    high-passed at POLISH_HIGHPASS pixels (what the relit original's shading misfits there would
    otherwise pull the pose to mend).

    The texture stage aligns band-passed pictures on image gradients: after JPEG or WebP, whose error
    lies on the same edges, it ends a tenth of a pixel or so off, and a luminance mark's reading loses
    half its evidence to that (docs/reading.md, stage 4). Here the Jacobian is central differences of
    renders of the object's window (twelve renders in one batch) along six moves that each shift the
    seen surface by POLISH_STEP pixels (RMS) and are orthogonal in that measure (`_screen_basis`: an
    orbit about the object, which moves the picture only by parallax and which `_moved`'s turn and shift
    make as the small difference of two large moves, is measured on its own), taken once per round and
    kept for its Gauss-Newton steps (the pose moves by hundredths of a pixel, the Jacobian hardly
    changes), each step halved twice before the round ends; the light is refitted
    at the start of each of POLISH_ROUNDS rounds, a round made only where the last one moved the
    camera by POLISH_AGAIN pixels or more. A least-squares step only ever lowers the cost, and
    a move of more than POLISH_MAX pixels is not taken (a picture the original explains poorly, from
    another engine, can pull the pose where the texture stage and the silhouette did not put it).

    A picture made smaller after it was rendered (a page's thumbnail, a halved screenshot) averaged
    several rendered pixels into each of its own: compared with point samples it pulls the pose off by
    a tenth of a pixel or more. So the first round also renders the start camera's view at 1 / f the
    window's size for each factor f of POLISH_FOOTPRINTS and resizes it to the window as an image
    tool would; a resized render that explains the picture under POLISH_FOOTPRINT_GAIN of the point
    samples' misfit is the one every render of the polish is made with. An enlarged picture (f = 1.5) is
    smoother than point samples too, but its own pixel grid does not line up with the window's render
    at 1 / f, so it keeps point samples: its candidate is there so that its smoothness is not taken for
    a smaller picture's.
    Nothing here looks at a key: the reading's p-values stay as they are."""
    with torch.no_grad():
        start, renderer = camera, MeshRenderer()
        # Everything runs on the object's window (the picture's own pixels, at most POLISH_WINDOW a side),
        # whatever the picture's size: the window is the object's box, the same for every camera.
        first = _object_window(camera, picture, mask > 0.5, POLISH_WINDOW)
        crop, side = first.image[None], first.side
        crop_mask = first.seen[None].to(picture.dtype)
        footprint = None  # chosen in the first round
        for _ in range(POLISH_ROUNDS):
            window = replace(first, camera=first.seen_from(camera))
            view = _relit_view(mesh, window.camera, crop, crop_mask, margin=2)
            if view is None:
                return start
            fit, inside = view
            band = (lambda x: x) if not POLISH_HIGHPASS else _band_pass(inside, 0.0, POLISH_HIGHPASS)
            target = band(crop)[0].permute(1, 2, 0)[inside[0]].reshape(-1).double()

            def rendered(deltas: torch.Tensor, factor: float | None = None) -> torch.Tensor:
                factor = footprint if factor is None else factor
                lights = fit.lights[[0] * len(deltas)]
                size = max(8, round(side / factor))
                image = renderer(fit.relit, _moved(window.camera, deltas.to(picture.dtype), side), lights,
                                 size, size).image
                if size != side:  # as an image tool resizes (bicubic, antialiased when it shrinks)
                    image = F.interpolate(image, size=(side, side), mode="bicubic", antialias=size > side,
                                          align_corners=False)
                return band(image).permute(0, 2, 3, 1)[:, inside[0]].reshape(len(deltas), -1).double()

            at_start = None  # the start camera's render under the chosen footprint, where already made
            if footprint is None:  # the first round: how the picture sampled the object, at the start camera
                zero = torch.zeros(1, 6, dtype=torch.float64)
                starts = [rendered(zero, f)[0] for f in POLISH_FOOTPRINTS]
                fits = [float(((target - start_render) ** 2).sum()) for start_render in starts]
                best = min(range(len(fits)), key=fits.__getitem__)
                footprint = POLISH_FOOTPRINTS[best]
                point = fits[POLISH_FOOTPRINTS.index(1.0)] if 1.0 in POLISH_FOOTPRINTS else math.inf
                if footprint > 1.0 or fits[best] >= POLISH_FOOTPRINT_GAIN * point:
                    footprint = 1.0
                if footprint in POLISH_FOOTPRINTS:
                    at_start = starts[POLISH_FOOTPRINTS.index(footprint)]

            # The moves are taken along directions that each move the seen surface by POLISH_STEP px
            # (RMS) and no two alike (`_screen_basis`), not along `_moved`'s own coordinates: a turn and a
            # shift that nearly cancel (an orbit about the object, which only parallax shows) is then a
            # direction of its own, measured by its own renders, rather than the small difference of two
            # large ones, lost in their noise.
            basis = _screen_basis(fit.relit, window.camera, fit.fragments, inside).double()  # (6, 6): columns
            steps = _gauss_newton(rendered, basis, target, POLISH_ITERATIONS, TEXTURE_DONE, at_start)
            if steps is None:  # nothing to align on
                return start
            delta = steps[0]
            camera = _from_window(window, delta.to(picture.dtype), camera)
            if float(delta.abs().max()) < POLISH_AGAIN:  # the light refitted at a camera this near would change nothing
                break
        return camera if pose_error(mesh, first.camera, first.seen_from(camera), side, side) <= POLISH_MAX else start


def _gauss_newton(rendered, basis: torch.Tensor, target: torch.Tensor, iterations: int, done: float,
                  at_start: torch.Tensor | None = None):
    """The Gauss-Newton steps of `polish` and `polish_composited`: `rendered` (K, 6) moves -> (K, N) values
    to compare with `target` (N,); the Jacobian is central differences at +-POLISH_STEP along the
    columns of `basis` (6, 6), taken once; each step is halved twice before the steps end, and they end
    once one moves under `done` px or after `iterations`. `at_start`: the render at no move, where already
    made. Returns the move (6,) and its cost (the sum of squares left), or None where the renders do not
    change along any move (nothing to align on)."""
    both = rendered(POLISH_STEP * torch.cat([basis.T, -basis.T]))
    jacobian = ((both[:6] - both[6:]) / (2 * POLISH_STEP)).T
    normal = jacobian.T @ jacobian
    scale = float(normal.diagonal().mean())
    if not scale > 1e-12:
        return None
    solve = normal + TEXTURE_DAMPING * scale * torch.eye(6, dtype=torch.float64)
    delta = torch.zeros(6, dtype=torch.float64)
    residual = target - (rendered(delta[None])[0] if at_start is None else at_start)
    cost = float((residual ** 2).sum())
    for _ in range(iterations):
        update = basis @ torch.linalg.solve(solve, jacobian.T @ residual)
        length = float(update.abs().max())
        for fraction in (1.0, 0.5, 0.25):
            trial = target - rendered((delta + fraction * update)[None])[0]
            if float((trial ** 2).sum()) < cost:
                break
        else:
            break
        delta, residual = delta + fraction * update, trial
        cost = float((residual ** 2).sum())
        if fraction * length < done:
            break
    return delta, cost


def polish_composited(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor,
                      background: torch.Tensor, sigmas: tuple[float, ...] = COMPOSITE_SIGMAS,
                      rounds: int = COMPOSITE_ROUNDS) -> Cameras:
    """The registered `camera` of a small object's `picture` (1, 3, H, W) on a plain background
    (`background` (1, 3, H, W): the picture's own background, a colour or a ramp), brought to where the
    relit original, rendered as the reading renders it and composited over that background, best
    explains the whole of the object's window (`mask` (1, H, W): its pixels), its antialiased rim
    included.

    `polish` compares interior pixels only (two pixels from any edge, so that its moves never bring the
    background in): on an object of a few hundred pixels few or none are left, and the texture there is
    finer than the pixels, so its misfit is rugged and its steps stop a fifth of a pixel or more from the
    picture's pose, where a mark whose cells are smaller than a pixel is lost. The rim's pixels mix the
    object with the background in proportion to how much of each pixel the object covers: a sub-pixel
    move changes them smoothly, and on a small object they are a large share of its pixels. Gauss-Newton
    along `_screen_basis`'s moves (`_gauss_newton`; where no step helps, a pattern search along the same
    moves, SHARPEN_STEPS), the light refitted at the start of each of at most COMPOSITE_ROUNDS rounds;
    run from `camera` as it is and from where the window blurred (COMPOSITE_SIGMAS) first takes it, each
    with point samples and with the smaller render of `polish`'s footprints that fits `camera` best (a
    picture made smaller after it was rendered has another rim); the end the composite explains best is
    kept, a resized render's only where its misfit is under POLISH_FOOTPRINT_GAIN of the point samples',
    and a move of more than COMPOSITE_MAX px is not taken. `sigmas` and `rounds` replace
    COMPOSITE_SIGMAS and COMPOSITE_ROUNDS: with `(0.0,)` and 1 (what the reading runs on an object of a
    few thousand pixels, `reading.read.RIM_PIXELS_BELOW`) one round from `camera` on the sharp pixels
    alone, at each footprint. Nothing here looks at a key."""
    with torch.no_grad():
        start = camera
        # the window: the object's box with its antialiased rim and a pixel or two of background around
        around = F.max_pool2d((mask > 0.5).to(picture.dtype)[:, None], 5, 1, 2)[:, 0] > 0.5
        first = _object_window(camera, picture, around, POLISH_WINDOW)
        side, crop = first.side, first.image[None]
        behind = _object_window(camera, background, around, POLISH_WINDOW).image[None]  # the same window
        # How the picture sampled the object (`polish`'s footprints): a picture made smaller after it was
        # rendered has a rim its own renderer's antialiasing does not make. A smaller footprint's blur also
        # explains a misaligned start better, so it is judged where each one's alignment ends.
        shrunk = [factor for factor in POLISH_FOOTPRINTS if factor < 1.0]
        costs = [_composite_cost(mesh, start, first, crop, behind, factor) for factor in shrunk]
        factors = [1.0] + ([shrunk[min(range(len(costs)), key=costs.__getitem__)]] if shrunk else [])
        ends, costs = [], []
        for factor in factors:
            # From the start as it is, and from where the blurred levels take it (a wider basin, but the
            # sharp pixels can disagree).
            paths = [_composite_level(mesh, start, first, crop, behind, 0.0, factor, rounds)]
            if any(sigmas):
                coarse = start
                for sigma in sigmas:
                    coarse = _composite_level(mesh, coarse, first, crop, behind, sigma, factor, rounds)
                paths.append(coarse)
            for end in paths:
                if pose_error(mesh, first.camera, first.seen_from(end), side, side) <= COMPOSITE_MAX:
                    gain = 1.0 if factor == 1.0 else POLISH_FOOTPRINT_GAIN  # a resized render must explain clearly better
                    ends.append(end)
                    costs.append(_composite_cost(mesh, end, first, crop, behind, factor) / gain)
        return ends[min(range(len(ends)), key=costs.__getitem__)] if ends else start


def _composited(relit: MeshBatch, cameras: Cameras, lights, side: int, behind: torch.Tensor, factor: float) -> torch.Tensor:
    """Renders (B, 3, side, side) of `relit` from `cameras` (each rendering the window) composited over
    the background `behind` (1, 3, side, side), at 1 / `factor` the window's size and resized to it as an
    image tool resizes (bicubic, antialiased when it shrinks) where `factor` is not 1."""
    size = max(8, round(side / factor))
    rgba = MeshRenderer()(relit, cameras, lights, size, size).rgba.permute(0, 3, 1, 2)  # over black
    if size != side:
        behind = F.interpolate(behind, size=(size, size), mode="bilinear", align_corners=False)
    image = rgba[:, :3] + (1.0 - rgba[:, 3:]) * behind  # the background in proportion to what is uncovered
    if size != side:
        image = F.interpolate(image, size=(side, side), mode="bicubic", antialias=size > side, align_corners=False)
    return image


def _composite_cost(mesh: MeshBatch, camera: Cameras, first: _Window, crop: torch.Tensor, behind: torch.Tensor,
                    factor: float = 1.0) -> float:
    """What `polish_composited` lowers, at `camera`: the squared difference over its window between the
    picture and the relit original (the light fitted there) composited over the background (`_composited`)."""
    from .relight import fitted_light

    window = replace(first, camera=first.seen_from(camera))
    relit, lights, _ = fitted_light(mesh, crop, window.camera)
    image = _composited(relit, window.camera, lights, first.side, behind, factor)
    return float(((image - crop).double() ** 2).sum())


def _composite_level(mesh: MeshBatch, camera: Cameras, first: _Window, crop: torch.Tensor, behind: torch.Tensor,
                     sigma: float, factor: float = 1.0, rounds: int = COMPOSITE_ROUNDS) -> Cameras:
    """`polish_composited`'s rounds on its window (`first`: the picture's `crop` and the background
    `behind` it, (1, 3, S, S) each), both sides blurred by `sigma` px (0: as they are), rendered at the
    footprint `factor` (`_composited`)."""
    from ..render.blur import gaussian_blur
    from .relight import fitted_light

    side = first.side
    blur = (lambda x: x) if not sigma else (lambda x: gaussian_blur(x, sigma))  # noqa: E731
    target = blur(crop)[0].permute(1, 2, 0).reshape(-1).double()
    for _ in range(rounds):
        window = replace(first, camera=first.seen_from(camera))
        relit, lights, fragments = fitted_light(mesh, crop, window.camera)

        def rendered(deltas: torch.Tensor) -> torch.Tensor:
            image = _composited(relit, _moved(window.camera, deltas.to(crop.dtype), side), lights[[0] * len(deltas)],
                                side, behind, factor)
            return blur(image).permute(0, 2, 3, 1).reshape(len(deltas), -1).double()

        basis = _screen_basis(relit, window.camera, fragments, fragments.pix_to_face >= 0).double()
        steps = _gauss_newton(rendered, basis, target, COMPOSITE_ITERATIONS, TEXTURE_DONE / 2)
        if steps is None:  # nothing to align on
            break
        delta, cost = steps
        if not bool(delta.any()):  # not one step helped: a pattern search along the same moves instead
            moves, step = torch.cat([basis.T, -basis.T]), SHARPEN_STEPS[0]
            while step >= SHARPEN_STEPS[1]:
                trials = delta + step * moves
                trial_costs = ((target - rendered(trials)) ** 2).sum(1)
                pick = int(trial_costs.argmin())
                if float(trial_costs[pick]) < cost:
                    delta, cost = trials[pick], float(trial_costs[pick])
                else:
                    step /= 2
        camera = _from_window(window, delta.to(crop.dtype), camera)
        if float(delta.abs().max()) < TEXTURE_DONE:  # the light refitted this near would change nothing
            break
    return camera


def _texture_level(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor, sigma: float,
                   iterations: int, margin: int, light_from: str, zoom: bool) -> Cameras:
    """One level of `refine_on_texture`, at the picture's (1, 3, H, W) own size: six coordinates of a
    rigid move, seven with `zoom`."""
    n_coordinates = 7 if zoom else 6
    height = picture.shape[-2]
    with torch.no_grad():
        problem = _band_problem(mesh, camera, picture, mask, sigma, margin, light_from)
        if problem is None:
            return camera
        render_residual, _, inside, relit = problem
        residual = lambda delta, **options: render_residual(_zoomed(camera, delta, height), **options)  # noqa: E731

        delta = torch.zeros(n_coordinates, dtype=picture.dtype)
        base, banded, fragments = residual(delta, with_image=True)
        base = base[0]
        # Cauchy weights (IRLS) on the coarse levels: what the relit original cannot explain there (a
        # light misfit at creases) counts less than texture that lines up. Scale fixed per level.
        robust = ROBUST_SCALE * float(base.abs().median()) + 1e-6 if sigma >= ROBUST_MIN_SIGMA else None
        loss = (lambda r: float((r ** 2).sum())) if robust is None else \
            (lambda r: float(torch.log1p((r / robust) ** 2).sum()))  # noqa: E731
        cost = loss(base)
        # Converged: a hundredth of a pixel; a coarse level, which finer ones follow, a twentieth.
        done = TEXTURE_DONE if robust is None else TEXTURE_COARSE_DONE
        for _ in range(iterations):
            jacobian = _flow_jacobian(relit, _zoomed(camera, delta, height), banded, inside, fragments, zoom)
            weight = torch.ones_like(base) if robust is None else 1.0 / (1.0 + (base / robust) ** 2)
            normal = jacobian.T @ (weight[:, None] * jacobian)
            scale = float(normal.diagonal().mean())
            if not scale > 1e-12:  # a flat band: nothing to align on (or not a number)
                break
            damping = ZOOM_DAMPING if zoom else TEXTURE_DAMPING
            update = -torch.linalg.solve(normal + damping * scale * torch.eye(n_coordinates), jacobian.T @ (weight * base))
            length = float(update.abs().max())
            for fraction in (1.0, 0.5, 0.25):
                if fraction < 1.0 and fraction * length < done:  # a step this short would end the level anyway
                    fraction = None
                    break
                trial, trial_banded, trial_fragments = residual(delta + fraction * update, with_image=True)
                if loss(trial[0]) < cost:
                    break
            else:
                break
            if fraction is None:
                break
            delta, base, banded, fragments = delta + fraction * update, trial[0], trial_banded, trial_fragments
            cost = loss(base)
            if fraction * length < done:  # converged
                break
        return _zoomed(camera, delta, height)


def _flow_jacobian(mesh: MeshBatch, camera: Cameras, banded: torch.Tensor, inside: torch.Tensor,
                   fragments, zoom: bool = False) -> torch.Tensor:
    """The texture stage's Jacobian (M, 6), or (M, 7) with `zoom`, at `camera` from one render instead of twelve: a rigid move
    (`_moved`) carries each surface point seen at an `inside` pixel (1, H, W) along an analytic screen
    flow, and the band-passed picture `banded` (1, 3, H, W) moves with it (brightness constancy: dI =
    -grad I . flow), as in Lucas-Kanade image alignment. `fragments`: the rasterization of `banded`'s
    render."""
    height, width = banded.shape[-2:]
    flow = _seen_flow(mesh, camera, fragments, inside)  # (6, M, 2)
    if zoom:  # `_zoomed`'s seventh: each pixel moves away from the principal point, 1 px a unit at height / 2
        rows, columns = inside[0].nonzero(as_tuple=True)
        centre_x, centre_y = width / 2 * (1 + camera.principal[0]), height / 2 * (1 - camera.principal[1])
        outward = torch.stack([columns + 0.5 - centre_x, rows + 0.5 - centre_y], -1).to(flow.dtype) * (2.0 / height)
        flow = torch.cat([flow, outward[None]])  # (7, M, 2)
    gradient_y, gradient_x = torch.gradient(banded[0], dim=(1, 2))
    pick = lambda g: g.permute(1, 2, 0)[inside[0]]  # noqa: E731  (M, 3)
    jacobian = -(pick(gradient_x)[None] * flow[..., :1] + pick(gradient_y)[None] * flow[..., 1:])  # (6 or 7, M, 3)
    return jacobian.reshape(len(flow), -1).T


def _screen_basis(mesh: MeshBatch, camera: Cameras, fragments, inside: torch.Tensor) -> torch.Tensor:
    """Pose moves (6, 6), one a column in `_moved`'s coordinates, that each move the surface seen at the
    `inside` pixels (1, H, W) of `fragments` (a rasterization from `camera`) by 1 px RMS and are mutually
    orthogonal in that measure: the flow's Gram matrix to the power -1/2 (eigenvectors scaled). Small
    moves of the camera that barely move the picture (a turn and a shift that nearly cancel: an orbit
    about the object, seen only by its parallax) are then directions of their own, scaled up."""
    flow = _seen_flow(mesh, camera, fragments, inside).reshape(6, -1)
    values, vectors = torch.linalg.eigh(flow @ flow.T / max(1, flow.shape[1] // 2))
    return vectors * values.clamp_min(1e-12).rsqrt()[None]


def _seen_flow(mesh: MeshBatch, camera: Cameras, fragments, inside: torch.Tensor) -> torch.Tensor:
    """The screen flow (6, M, 2) of `_moved`'s six coordinates at the surface points seen at the `inside`
    pixels (1, H, W; M of them) of `fragments`, a rasterization of `mesh` from `camera` (one camera)."""
    from ..render import surface_points

    height, width = inside.shape[-2:]
    points, _ = surface_points(mesh, fragments, camera)
    at_pixel = points.new_zeros(height * width, 3).index_copy(0, fragments.pixel, points)
    seen = at_pixel[inside.reshape(-1)]  # (M, 3)
    return _screen_flow(camera, points.new_zeros(1, 6), seen[None], height, width)[:, 0]


def _distinct(scores: torch.Tensor, directions: torch.Tensor, keep: int, min_angle: float = 30.0,
              away_from: list[int] = ()) -> list[int]:
    """The `keep` best-scoring candidates whose view directions are at least `min_angle` degrees apart
    (the runner-up views of one mode would only repeat the best's refinement), and as far from those
    of `away_from`."""
    chosen: list[int] = []
    cosine = math.cos(math.radians(min_angle))
    for index in scores.argsort(descending=True).tolist():
        if not math.isfinite(float(scores[index])):  # the rest were never scored
            break
        if all(float(directions[index] @ directions[other]) < cosine for other in [*away_from, *chosen]):
            chosen.append(index)
            if len(chosen) == keep:
                break
    return chosen


def _coarse_silhouettes(mesh: MeshBatch, cameras: Cameras, levels) -> Cameras:
    """Cameras refined coarsely on their silhouettes (COARSE_SILHOUETTE_SIGMAS at COMPARE_SIZE, one batch)."""
    for sigma in COARSE_SILHOUETTE_SIGMAS:
        cameras = _refine_silhouettes(mesh, cameras, levels[COMPARE_SIZE], sigma, done_step=SILHOUETTE_COARSE_DONE)
    return cameras


def _refine_candidates(mesh: MeshBatch, outline: MeshBatch, cameras: Cameras, levels, margin: float = PICK_MARGIN,
                       accept: float | None = None):
    """Candidate `cameras` (best-scored first) refined coarsely on their silhouettes, their texture
    misfits (PICK_SIGMAS; inf for a candidate whose refined silhouette overlaps clearly worse than the
    best one's) and the index picked: the first, unless another fits the texture better than `margin`
    times its misfit. With `accept`, the first is refined alone first and picked at once where its
    misfit is under `accept` (a registered view's): no other could then be much nearer the picture's
    view than it, and the finer stages take it to the same pose. The others are then left as they
    were, their misfits None (`register` offers them for a second look, refined only if asked).
    `outline`: the mesh the silhouettes are rendered from (`outline_mesh`)."""
    target, target_mask, _ = levels[SEARCH_SIZE]
    if accept is not None and len(cameras) > 1:
        first = _coarse_silhouettes(outline, cameras[[0]], levels)
        misfit = texture_misfits(mesh, first, target, target_mask[:, 0], PICK_SIGMAS)[0]
        if misfit < accept:
            return first, [misfit] + [None] * (len(cameras) - 1), 0
    refined = _coarse_silhouettes(outline, cameras, levels)
    # Symmetric shapes leave several views with the same silhouette: the texture tells them apart. The
    # best-scored candidate stays unless another fits the texture clearly better: a candidate a few
    # degrees off fits the fine bands as badly as a wrong view, so a plain minimum of the misfit would
    # often throw the right one away.
    # Candidates whose refined silhouette overlaps clearly worse than the best one's are not scored.
    overlap = _overlaps(outline, refined, levels[SEARCH_SIZE])
    scored = [i for i in range(len(refined)) if i == 0 or overlap[i] >= overlap.max() - PICK_IOU_SLACK]
    misfits = [math.inf] * len(refined)
    for i, misfit in zip(scored, texture_misfits(mesh, refined[scored], target, target_mask[:, 0], PICK_SIGMAS)):
        misfits[i] = misfit
    pick = min(range(len(refined)), key=misfits.__getitem__)
    return refined, misfits, (pick if misfits[pick] < margin * misfits[0] else 0)


def register(mesh: MeshBatch, picture: torch.Tensor, mask: torch.Tensor, background: torch.Tensor,
             candidates: int = 400, keep: int = 8, shading_weight: float = 0.3, fov_y: float = FOV,
             texture_refine: bool = True, retry: bool = True, start: Cameras | None = None) -> Registration:
    """Find the camera of `picture` (3, H, W) in [0, 1] of `mesh` (one mesh in the canonical frame);
    `mask` (H, W) marks the object's pixels; `fov_y` is the picture's vertical field of view as first
    assumed (the texture stage refines it where the texture says otherwise; the principal point is
    assumed at the centre). `retry`: where the texture does not confirm the camera, try RETRY_KEEP more
    views (step 4); off for a quick scan (`register_with_masks`' `quick`). `start`: a camera of the
    whole picture found before under another field of view: no search (steps 1, 2 and 4), it is moved
    along its view axis so the object keeps its size under `fov_y` (`_dollied`) and refined from there
    on its silhouettes (and, with `texture_refine`, the texture; `lens_alternatives`). See the module
    docstring."""
    target, target_mask, box, inside = frame_picture(picture, mask, SEARCH_SIZE, background)
    levels = _targets(target, target_mask, inside)
    fov, principal = crop_intrinsics(picture.shape[-2], picture.shape[-1], box[0], fov_y)
    seen = _seen_part(mask, box[0], COMPARE_SIZE)
    outline = outline_mesh(mesh)

    def on_silhouettes(camera: Cameras) -> Cameras:
        """The picked candidate refined finely on silhouettes: the camera of the whole picture."""
        for sigma in FINE_SILHOUETTE_SIGMAS:
            camera = _refine_silhouettes(outline, camera, levels[SEARCH_SIZE], sigma)
        return replace(camera, fov_y=fov_y, principal=(0.0, 0.0))

    def on_texture(camera: Cameras) -> Cameras:
        """(3.) The whole picture's camera refined on the texture."""
        return _on_texture(mesh, camera, picture, mask) if texture_refine else camera

    def finish(camera: Cameras) -> Cameras:
        return on_texture(on_silhouettes(camera))

    if start is not None:
        framed = replace(_dollied(mesh, start, fov_y), fov_y=fov, principal=principal)
        camera = finish(_coarse_silhouettes(outline, framed, levels))
        return Registration(camera, box[0], silhouette_iou(mesh, camera, mask), ())

    # 1. Candidate views all around, moved so the object fills the crop as in the picture, and scored.
    directions = fibonacci_directions(candidates)
    search = Cameras(DISTANCE * directions, torch.zeros_like(directions), _up_for(directions), fov,
                     principal=principal)
    search = _center_objects(mesh, search, COMPARE_SIZE, seen=seen)
    # Silhouette overlap first (a render each); the light fits of the shading term only for the views
    # that overlap best.
    chunks = [list(range(first, min(candidates, first + 32))) for first in range(0, candidates, 32)]
    visible = []  # each candidate's visible faces, rasterized once for both scores (the outline's: its own)
    overlap = torch.cat([_overlaps(outline, search[chunk], levels[COMPARE_SIZE], visible) for chunk in chunks])
    visible = torch.cat(visible) if outline is mesh else None
    shortlist = overlap.topk(min(candidates, SHADED_CANDIDATES)).indices.tolist()
    scores = torch.full((candidates,), -math.inf)
    for first in range(0, len(shortlist), 32):
        chunk = shortlist[first:first + 32]
        scores[chunk] = _scores(mesh, search[chunk], levels[COMPARE_SIZE], shading_weight,
                                None if visible is None else visible[chunk])
    best = _distinct(scores, directions, keep)

    # 2. Refine the best few coarsely, then the best of them finely, on blurred silhouettes (a wider
    # blur first: its basin is wider).
    refined, misfits, chosen = _refine_candidates(mesh, outline, search[best], levels, accept=ACCEPT_MISFIT)
    taken_at_once = len(misfits) > 1 and misfits[1] is None  # the others left unrefined
    if taken_at_once:  # the others, best-scored first, as they are
        others = list(range(1, len(best)))
    else:
        others = sorted((i for i in range(len(refined)) if i != chosen and math.isfinite(misfits[i])),
                        key=misfits.__getitem__)

    camera = finish(refined[[chosen]])
    if taken_at_once:
        alternatives = tuple(Alternative(search[[best[i]]], lambda c: on_silhouettes(_coarse_silhouettes(outline, c, levels)),
                                         on_texture) for i in others[:ALTERNATIVES])
    else:
        alternatives = tuple(Alternative(refined[[i]], on_silhouettes, on_texture) for i in others[:ALTERNATIVES])
    if texture_refine and RETRY_KEEP and retry:
        # 4. A registration the texture does not confirm tries more views, nearer each other: a view
        # a few degrees from the truth can rank far down the first score and lose its place among
        # the first few to a higher-scored one further off.
        full, full_mask = picture[None].clamp(0, 1), mask[None].float()
        misfit = texture_misfit(mesh, camera, full, full_mask, PICK_SIGMAS)
        more = _distinct(scores, directions, RETRY_KEEP, RETRY_ANGLE, away_from=best) if misfit > RETRY_ABOVE else []
        if more:
            extra, extra_misfits, extra_chosen = _refine_candidates(mesh, outline, search[more], levels, margin=1.0)
            # The retry's best view is finished on the texture (the costliest stage) only where on its
            # silhouettes alone it already fits the texture better than the finished camera does: a view
            # the retry rescues fits far better from the start, and one that would lose costs no texture stage.
            if math.isfinite(extra_misfits[extra_chosen]):
                rough = on_silhouettes(extra[[extra_chosen]])
                if texture_misfit(mesh, rough, full, full_mask, PICK_SIGMAS) < RETRY_FINISH_BELOW * misfit:
                    other = on_texture(rough)
                    if texture_misfit(mesh, other, full, full_mask, PICK_SIGMAS) < misfit:
                        alternatives = (Alternative(camera), *alternatives[:ALTERNATIVES - 1])
                        camera = other
    return Registration(camera, box[0], silhouette_iou(mesh, camera, mask), alternatives)


def _on_texture(mesh: MeshBatch, camera: Cameras, picture: torch.Tensor, mask: torch.Tensor) -> Cameras:
    """(3.) The whole picture's `camera` refined on the texture (`refine_on_texture_twice`), kept only
    where its silhouette still overlaps the picture's (`mask` (H, W)) about as well."""
    refined = refine_on_texture_twice(mesh, camera, picture[None].clamp(0, 1), mask[None].float())
    # Where the original's texture explains the picture poorly (another engine's light and texture
    # filtering), the texture stage can drift off a pose the silhouette had right: the silhouette
    # is a second, independent witness, and a move it clearly disagrees with is not taken.
    if silhouette_iou(mesh, refined, mask) >= silhouette_iou(mesh, camera, mask) - TEXTURE_IOU_SLACK:
        camera = refined
    return camera


def _dollied(mesh: MeshBatch, camera: Cameras, fov_y: float) -> Cameras:
    """`camera` (one) moved along its view axis so that, under the field of view `fov_y`, the object's
    centre plane shows at the size it had under the camera's own: the eye's distance to that plane
    times the ratio of the tangents of half the fields of view (a zoom and a dolly agree there)."""
    centre = mesh.positions[0].mean(0).to(camera.eye)
    forward = F.normalize(camera.at - camera.eye, dim=-1)
    depth = ((centre - camera.eye) * forward).sum(-1, keepdim=True)
    ratio = math.tan(math.radians(camera.fov_y) / 2) / math.tan(math.radians(fov_y) / 2)
    eye = camera.eye + forward * depth * (1.0 - ratio)
    return replace(camera, eye=eye, at=eye + (camera.at - camera.eye), fov_y=fov_y)


def lens_alternatives(mesh: MeshBatch, picture: torch.Tensor, mask: torch.Tensor, background: torch.Tensor,
                      found: Registration, fov_y: float = FOV) -> Registration:
    """`found` with the other lenses of LENSES as its last alternatives for the second look: the
    registered camera under each lens (the tangent of half of `fov_y` times each), moved along its
    view axis so that the object keeps its size (`_dollied`), `rough()` refined on the picture's
    silhouettes under that lens (`register`'s `start`, no search), `finish()` on the texture and then
    sharpened (`sharpen`: a fine texture loses the mark to a tenth of a pixel, as the second look
    finds for the registered camera).

    A crop keeps the camera's focal length in pixels on fewer pixels: a central 80 % crop has 0.8
    times the tangent of the field of view assumed, and registered under the assumed lens its camera
    can end a pixel or more off, which a luminance mark does not survive; a screenshot's larger
    canvas is the other way round. The texture misfit does not tell the lenses apart reliably (taken
    where it was lower, it moved two of the registration benchmark's PNG pictures of the assumed
    lens off theirs, and left crops whose misfit is alike under both): the keyed reading does, on
    the second look, which pays for each alternative in the p-value (`second_look.look_again`)."""
    mask = mask if mask.dim() == 2 else mask[0]

    def finish(camera: Cameras) -> Cameras:  # the texture stage, then sharpened as a second look sharpens
        return sharpen(mesh, _on_texture(mesh, camera, picture, mask), picture[None].clamp(0, 1), mask[None].float())

    alternatives = []
    for lens in LENSES:
        other = math.degrees(2 * math.atan(lens * math.tan(math.radians(fov_y) / 2)))
        silhouettes = lambda camera, other=other: register(mesh, picture, mask, background, fov_y=other,  # noqa: E731
                                                            texture_refine=False, start=camera).camera
        alternatives.append(Alternative(found.camera, silhouettes, finish))
    return replace(found, alternatives=(*found.alternatives, *alternatives))


def register_with_masks(mesh: MeshBatch, picture: torch.Tensor, masks: list[torch.Tensor], background: torch.Tensor,
                        fov_y: float = FOV, recut=None, quick: bool = False) -> Registration:
    """`register` with each of several guesses of the object's pixels (H, W; after the first, also a
    function making one, or None, called only when the search reaches it) in turn (e.g. a busy
    background's colour-guided cut, then the plain-background threshold, when they disagree), keeping
    the camera under which the original's texture explains the picture best (`texture_misfit` over
    the registered silhouette's own interior, so no guess judges itself). A guess whose camera
    explains it well (misfit under ACCEPT_MISFIT) ends the search. `recut` (the best camera's
    silhouette (H, W) bool -> a new guess, e.g. `segmentation.recut`), where given, makes a new guess from
    each guess's registration that the texture does not confirm and whose silhouette disagrees with
    the guess (IoU under RECUT_BELOW_IOU: on a plain background whose frame cuts the object off, a
    registration can be right yet over ACCEPT_MISFIT), up to RECUT_ROUNDS in a row while they fit
    better. A new cut much like its guess is registered all the same: registration on a slightly
    different mask can land on a better view. The registration found carries the other lenses as its
    last alternatives (`lens_alternatives`). `quick` (a scan of many pictures, most of them of other
    meshes, where those take most of the time): no recut, no other lens and no retry of more views
    (`register`), at the cost of the pictures of the right mesh only they register."""
    first = register(mesh, picture, masks[0], background, fov_y=fov_y, retry=not quick)
    lenses = (lambda found, mask: found) if quick else (  # noqa: E731
        lambda found, mask: lens_alternatives(mesh, picture, mask, background, found, fov_y))
    if len(masks) == 1 and (recut is None or quick or first.iou >= RECUT_BELOW_IOU):
        return lenses(first, masks[0])  # nothing to compare it with: its misfit is not needed
    everywhere = torch.ones_like(masks[0][None], dtype=picture.dtype)
    best, best_misfit, best_mask, cut_from = None, math.inf, masks[0], None

    def attempt(mask: torch.Tensor, found: Registration | None = None) -> bool:
        """Register on `mask` (unless `found` already is), keep it if it fits best; whether it fit
        better than the best before."""
        nonlocal best, best_misfit, best_mask
        found = found if found is not None else register(mesh, picture, mask, background, fov_y=fov_y, retry=not quick)
        misfit = texture_misfit(mesh, found.camera, picture[None].clamp(0, 1), everywhere, PICK_SIGMAS)
        if best is None or misfit < best_misfit:
            best, best_misfit, best_mask = found, misfit, mask
            return True
        return False

    for index, mask in enumerate(masks):
        if callable(mask):  # a guess made only when it is reached
            mask = mask()
            if mask is None:
                continue
        attempt(mask, first if index == 0 else None)
        for _ in range(RECUT_ROUNDS if recut is not None and not quick else 0):
            # `best` changes only when a guess fits better, so the last camera cut from is the only repeat.
            if best_misfit < ACCEPT_MISFIT or best.iou >= RECUT_BELOW_IOU or best is cut_from:
                break
            cut_from = best
            with torch.no_grad():
                _, cover = _rasterized(mesh, best.camera, *picture.shape[-2:])
            guess = torch.as_tensor(recut(cover[0].cpu().numpy() > 0.5), device=picture.device)
            if int(guess.sum()) < MIN_RECUT_PIXELS or not attempt(guess):
                break
        if best_misfit < ACCEPT_MISFIT:
            break
    return lenses(best, best_mask)
