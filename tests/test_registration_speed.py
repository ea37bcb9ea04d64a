"""Registration's shortcuts (issue #46): each does the work it replaces, on the fixtures."""

import math
from dataclasses import replace

import torch

from meshseal.reading import registration
from meshseal.reading.registration import _hull_points, _moved, _refine_silhouettes, _targets, frame_picture
from meshseal.render import (MeshRenderer, clip_to_screen, pixels_at, relight_fragments, sample_any_view_cameras)

from test_informed import _bunny, _view


def test_the_hull_frames_the_object_as_all_its_vertices_do():
    """The convex hull's vertices are a small part of the mesh's, and their projected box is the whole
    mesh's from any side, close up or far (what `_center_objects` places candidates by)."""
    mesh = _bunny()
    hull = _hull_points(mesh)
    used = mesh.positions[0].index_select(0, mesh.faces.unique())
    assert len(hull) < len(used) / 4
    assert _hull_points(mesh) is hull  # kept for the next picture of the mesh
    cameras = sample_any_view_cameras(16, torch.Generator().manual_seed(0))
    for points in (hull, used):
        xy = clip_to_screen(cameras.world_to_clip(points[None].expand(16, -1, -1), 1.0), 64, 64)
        box = torch.cat([xy.amin(1), xy.amax(1)], -1)
        if points is hull:
            hull_box = box
    assert torch.allclose(hull_box, box, atol=1e-4)


def test_silhouette_refinement_stops_each_camera_on_its_own():
    """Three cameras refined in one batch, one already at the picture's pose and two a few pixels off:
    each ends on the pose (the one that starts there is not moved off it while the others still move)."""
    mesh, (camera, lights) = _bunny(), _view(index=0)
    out = MeshRenderer()(mesh, camera, lights, 128, 128, (0.5, 0.5, 0.5))
    target, target_mask, box, inside = frame_picture(out.image[0], out.rgba[0, ..., 3] > 0.5, 64,
                                                     torch.tensor([0.5, 0.5, 0.5]))
    from meshseal.reading.registration import crop_intrinsics

    fov, principal = crop_intrinsics(128, 128, box[0], camera.fov_y)
    framed = replace(camera, fov_y=fov, principal=principal)
    level = _targets(target, target_mask, inside)[64]
    offsets = torch.tensor([[0.0] * 6, [0.0, 0.0, 0.5, 3.0, -2.0, 1.0], [-1.0, 0.5, 0.3, -1.5, 2.0, -0.5]])
    starts = _moved(replace(framed, eye=framed.eye.expand(3, 3), at=framed.at.expand(3, 3), up=framed.up.expand(3, 3)),
                    offsets, 64)
    refined = _refine_silhouettes(mesh, starts, level, 1.0, iterations=20)
    from meshseal.reading.registration import pose_error

    errors = [pose_error(mesh, framed, refined[[k]], 64, 64) for k in range(3)]
    before = [pose_error(mesh, framed, starts[[k]], 64, 64) for k in range(3)]
    assert min(before[1:]) > 1.0 and max(errors) < 0.3, (before, errors)


def test_the_flat_light_run_is_skipped_only_where_the_first_run_fits(monkeypatch):
    """`refine_on_texture_twice` runs the flat-half light's refinement where the all-pixel light's run
    leaves a texture misfit of FLAT_ENOUGH or more (and FLAT_RETRY of the start's), not under it;
    FLAT_ENOUGH = 0 restores running it wherever FLAT_RETRY says."""
    runs = []
    misfit_after = {}

    def fake_refine(mesh, camera, picture, mask, light_from="all", **_):
        runs.append(light_from)
        return replace(camera, eye=camera.eye + (1.0 if light_from == "all" else 2.0))

    def fake_misfits(mesh, cameras, picture, mask, *args, **kwargs):  # which run: the eye's offset from 60
        return [{60: 0.05, 61: misfit_after["all"], 62: 0.001}[round(float(eye[0]))] for eye in cameras.eye]

    monkeypatch.setattr(registration, "refine_on_texture", fake_refine)
    monkeypatch.setattr(registration, "texture_misfits", fake_misfits)
    monkeypatch.setattr(registration, "texture_misfit", lambda *a, **k: fake_misfits(*a, **k)[0])
    camera = replace(_view()[0], eye=torch.tensor([[60.0, 0.0, 0.0]]))  # never rendered: the fakes read its eye
    picture, mask = torch.zeros(1, 3, 32, 32), torch.ones(1, 32, 32)
    enough_now = registration.FLAT_ENOUGH
    for after, expected, enough in ((0.5 * enough_now, ["all"], enough_now), (1.5 * enough_now, ["all", "flat"], enough_now),
                                    (0.01, ["all", "flat"], 0.0), (0.001, ["all"], 0.0)):
        runs.clear()
        misfit_after["all"] = after
        monkeypatch.setattr(registration, "FLAT_ENOUGH", enough)
        found = registration.refine_on_texture_twice(None, camera, picture, mask)
        assert runs == expected, (after, enough, runs)
        assert round(float(found.eye[0, 0])) == (62 if "flat" in expected else 61)


def test_misfits_in_one_batch_are_those_one_at_a_time():
    """`texture_misfits` of several cameras (their light fits and renders in one batch) gives each
    camera's `texture_misfit`, and tells the true view from views a few degrees off."""
    mesh, (camera, lights) = _bunny(), _view(index=0)
    out = MeshRenderer()(mesh, camera, lights, 96, 96, (0.5, 0.5, 0.5))
    picture, mask = out.image, (out.rgba[..., 3] > 0.5).float()
    cameras = _moved(replace(camera, eye=camera.eye.expand(3, 3), at=camera.at.expand(3, 3), up=camera.up.expand(3, 3)),
                     torch.tensor([[0.0] * 6, [2.0, 0, 0, 0, 0, 0], [0, 0, 0, 0, 1.5, 0]]), 96)
    together = registration.texture_misfits(mesh, cameras, picture, mask, (1.0, 2.0))
    alone = [registration.texture_misfit(mesh, cameras[[k]], picture, mask, (1.0, 2.0)) for k in range(3)]
    assert all(abs(a - b) <= 1e-4 * max(1.0, b) for a, b in zip(together, alone)), (together, alone)
    assert together[0] < 0.5 * min(together[1:])


def test_the_candidates_coarser_light_fit_still_explains_our_renders():
    """The shading score's cheaper light fit (SCORE_LIGHT_DIRECTIONS, SCORE_LIGHT_PIXELS) explains a
    render of our own nearly as the texture stage's finer one does, and far better than no light."""
    mesh, (camera, lights) = _bunny(), _view()
    out = MeshRenderer(blend="hard")(mesh, camera, lights, 64, 64)
    seen = pixels_at(out.image, out.fragments)
    fine, _, _ = relight_fragments(mesh, out.fragments, camera, seen)
    coarse, _, _ = relight_fragments(mesh, out.fragments, camera, seen, directions=registration.SCORE_LIGHT_DIRECTIONS,
                                     max_pixels=registration.SCORE_LIGHT_PIXELS)
    rms = lambda predicted: float((seen - predicted).pow(2).mean().sqrt())  # noqa: E731
    assert rms(coarse) < 0.015 and rms(coarse) < 1.5 * rms(fine) + 0.002
    assert rms(coarse) < 0.2 * float((seen - seen.mean(0)).pow(2).mean().sqrt())


def test_a_first_candidate_that_fits_the_texture_is_taken_without_refining_the_others(monkeypatch):
    """`_refine_candidates` with `accept` refines the best-scored candidate alone first and takes it
    where its texture misfit is under `accept`, leaving the others unrefined (misfits None); where it
    fits worse, every candidate is refined and the pick is the usual one."""
    refined_batches = []

    def fake_coarse(mesh, cameras, levels):
        refined_batches.append(len(cameras))
        return replace(cameras, eye=cameras.eye + 0.5)

    def fake_misfits(mesh, cameras, *args, **kwargs):  # the misfit is the eye's x before refinement
        return [float(eye[0]) - 0.5 for eye in cameras.eye]

    monkeypatch.setattr(registration, "_coarse_silhouettes", fake_coarse)
    monkeypatch.setattr(registration, "texture_misfits", fake_misfits)
    monkeypatch.setattr(registration, "_overlaps", lambda mesh, cameras, level: torch.ones(len(cameras)))
    levels = {registration.SEARCH_SIZE: (None, torch.zeros(1, 1, 8, 8), None)}
    base = _view()[0]

    def candidates(*misfits):
        eye = torch.tensor([[m, 0.0, 3.0] for m in misfits])
        return replace(base, eye=eye, at=torch.zeros_like(eye), up=base.up.expand(len(misfits), 3))

    refined, misfits, chosen = registration._refine_candidates(None, None, candidates(0.05, 0.01, 2.0), levels, accept=0.2)
    assert refined_batches == [1] and chosen == 0 and misfits[1:] == [None, None] and len(refined) == 1
    refined_batches.clear()
    refined, misfits, chosen = registration._refine_candidates(None, None, candidates(0.5, 0.1, 2.0), levels, accept=0.2)
    assert refined_batches == [1, 3] and chosen == 1 and torch.allclose(torch.tensor(misfits), torch.tensor([0.5, 0.1, 2.0]))
    refined_batches.clear()
    registration._refine_candidates(None, None, candidates(0.05, 0.01, 2.0), levels)  # no `accept`: all at once
    assert refined_batches == [3]


def test_each_pixels_surface_point_is_the_interpolated_fragment():
    """The silhouette stage's world point at a pixel, its ray at the z-buffer's depth, is the visible
    surface point the fragments interpolate (and the coverage is the rasterizer's); off the object it
    is the ray at the object's mean depth."""
    from meshseal.render import surface_points

    mesh = _bunny()
    cameras = sample_any_view_cameras(3, torch.Generator().manual_seed(5))
    cover, points = registration._pixel_points(mesh, cameras, 48)
    fragments, covered = registration._rasterized(mesh, cameras, 48, 48)
    assert torch.equal(cover[:, 0], covered)
    expected, _ = surface_points(mesh, fragments, cameras)
    assert torch.allclose(points.reshape(-1, 3)[fragments.pixel], expected, atol=1e-4)
    view = cameras.view_matrix()
    depth = -(points @ view[:, 2, :3, None] + view[:, 2, None, 3:])[..., 0]  # (B, S*S) along the view axis
    on = covered.reshape(3, -1) > 0.5
    for k in range(3):
        assert torch.allclose(depth[k][~on[k]], depth[k][on[k]].mean().expand(int((~on[k]).sum())), atol=1e-4)


def test_one_zoomed_step_tells_another_lens_from_the_assumed_one():
    """The zoom probe: from a pose refined on the texture with the assumed field of view, one
    Gauss-Newton step with the zoom turns the field of view by ZOOM_PROBE_DEGREES or more on a picture
    made through a narrower lens (as a central crop is), and by less on a picture of the assumed lens."""
    mesh, (camera, lights) = _bunny(), _view(index=0)
    turned = {}
    for fov in (camera.fov_y, camera.fov_y * 0.8):
        lens = replace(camera, fov_y=fov)
        distance = (camera.at - camera.eye).norm() * math.tan(math.radians(camera.fov_y) / 2) / math.tan(math.radians(fov) / 2)
        lens = replace(lens, eye=camera.at + (camera.eye - camera.at) / (camera.at - camera.eye).norm() * distance)
        out = MeshRenderer()(mesh, lens, lights, 128, 128, (0.5, 0.5, 0.5))
        picture, mask = out.image, (out.rgba[..., 3] > 0.5).float()
        start = replace(lens, fov_y=camera.fov_y, eye=camera.eye)  # the assumed lens, placed to match the size
        found = registration.refine_on_texture(mesh, start, picture, mask)
        probe = registration._texture_level(mesh, found, picture, mask, registration.ZOOM_PROBE_SIGMA, 1, 3, "all", True)
        turned[fov] = abs(probe.fov_y - found.fov_y)
    assert turned[camera.fov_y] < registration.ZOOM_PROBE_DEGREES <= turned[camera.fov_y * 0.8], turned


def test_the_zoomed_run_is_made_only_where_the_probe_asks_for_it(monkeypatch):
    """`refine_on_texture_twice` runs the zoomed refinement from its best where the misfit is ZOOM_TRY or
    more and one zoomed step turns the field of view by ZOOM_PROBE_DEGREES or more, and not otherwise."""
    zoomed_runs, probe_turn = [], {}

    def fake_refine(mesh, camera, picture, mask, light_from="all", zoom=False, **_):
        if zoom:
            zoomed_runs.append(light_from)
            return replace(camera, fov_y=camera.fov_y - 5.0)
        return replace(camera, eye=camera.eye + 1.0)

    monkeypatch.setattr(registration, "refine_on_texture", fake_refine)
    monkeypatch.setattr(registration, "texture_misfits", lambda mesh, cameras, *a, **k: [0.5, 0.01 + probe_turn["misfit"]][:len(cameras)])
    monkeypatch.setattr(registration, "texture_misfit", lambda mesh, camera, *a, **k: 0.0 if camera.fov_y < 50 else 1.0)
    monkeypatch.setattr(registration, "_texture_level",
                        lambda mesh, camera, *a, **k: replace(camera, fov_y=camera.fov_y + probe_turn["turn"]))
    camera = replace(_view()[0], fov_y=50.0)
    picture, mask = torch.zeros(1, 3, 32, 32), torch.ones(1, 32, 32)
    for misfit, turn, runs in ((0.2, 0.5, 0), (0.2, 3.0, 1), (0.0, 3.0, 0)):
        zoomed_runs.clear()
        probe_turn.update(misfit=misfit, turn=turn)
        found = registration.refine_on_texture_twice(None, camera, picture, mask)
        assert len(zoomed_runs) == runs, (misfit, turn, zoomed_runs)
        assert found.fov_y == (45.0 if runs else 50.0)


def _cards(count: int = 24) -> "registration.MeshBatch":
    """`count` separate square cards (two faces each, four vertices of their own) at seeded places and
    angles: foliage as game assets draw it, open sheets that quadric decimation shrinks."""
    generator = torch.Generator().manual_seed(0)
    corners = torch.tensor([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]]) * 0.25
    positions, faces = [], []
    for k in range(count):
        turn = torch.linalg.matrix_exp(torch.tensor([[0.0, -1.0, 0.5], [1.0, 0.0, -0.7], [-0.5, 0.7, 0.0]])
                                       * torch.rand(1, generator=generator) * 3)
        positions.append(corners @ turn.T + (torch.rand(3, generator=generator) - 0.5))
        faces += [[4 * k, 4 * k + 1, 4 * k + 2], [4 * k, 4 * k + 2, 4 * k + 3]]
    positions = torch.cat(positions)[None]
    texture = torch.full((1, 3, 8, 8), 0.5)
    return registration.MeshBatch.from_tensors(positions, torch.zeros_like(positions), torch.zeros(1, len(positions[0]), 2),
                                               torch.tensor(faces)[None], texture)


def _subdivided(mesh, times: int):
    """`mesh` (one, shared faces (F, 3) or (1, F, 3)) with each face cut into four `times` times."""
    from meshseal.mesh.preprocess import subdivide

    uvs = mesh.uvs[0] if mesh.uvs is not None else torch.zeros(len(mesh.positions[0]), 2)
    positions, normals, uvs, faces = subdivide(mesh.positions[0], mesh.normals[0], uvs, mesh.faces.reshape(-1, 3), times)
    texture = mesh.textures[0][None] if isinstance(mesh.textures, list) else mesh.textures
    return registration.MeshBatch.from_tensors(positions[None], normals[None], uvs[None], faces[None], texture)


def test_a_high_poly_mesh_searches_its_silhouettes_on_a_decimated_outline(monkeypatch):
    """Above OUTLINE_ABOVE faces the search renders silhouettes from a copy of at most OUTLINE_FACES
    faces whose outline matches the whole mesh's from every side, kept for the next picture; separate
    open cards (foliage) keep their borders and so their outline; a mesh under the bar, one whose
    decimated outline would differ (OUTLINE_IOU) and one the decimation hardly reduces (OUTLINE_SHARE)
    keep their own faces."""
    registration._OUTLINE.clear()
    bunny = _bunny()
    assert registration.outline_mesh(bunny) is bunny  # 4,000 faces: under the bar
    dense = _subdivided(bunny, 1)  # 16,000 faces
    monkeypatch.setattr(registration, "OUTLINE_ABOVE", 10000)
    monkeypatch.setattr(registration, "OUTLINE_FACES", 3000)
    outline = registration.outline_mesh(dense)
    assert outline is not dense and len(outline.faces) <= 3000 and outline.uvs is None
    assert registration.outline_mesh(dense) is outline  # decimated once for a folder of pictures
    assert float(registration._outline_overlaps(dense, outline).min()) >= registration.OUTLINE_IOU
    cards = _subdivided(_cards(), 4)  # 12,288 faces
    kept = registration.outline_mesh(cards)
    assert kept is not cards and len(kept.faces) <= registration.OUTLINE_SHARE * len(cards.faces[0])
    assert float(registration._outline_overlaps(cards, kept).min()) >= registration.OUTLINE_IOU
    for name, value in (("OUTLINE_IOU", 1.01), ("OUTLINE_SHARE", 0.1)):
        monkeypatch.setattr(registration, name, value)
        registration._OUTLINE.clear()
        assert registration.outline_mesh(dense) is dense, name
        monkeypatch.undo()
        monkeypatch.setattr(registration, "OUTLINE_ABOVE", 10000)
        monkeypatch.setattr(registration, "OUTLINE_FACES", 3000)


def test_registration_on_the_outline_finds_the_view(monkeypatch):
    """A picture of a 16,000-face bunny registered with its silhouettes searched on a 3,000-face
    outline: the camera is the picture's, within half a pixel."""
    from meshseal.reading.registration import pose_error, register

    monkeypatch.setattr(registration, "OUTLINE_ABOVE", 10000)
    monkeypatch.setattr(registration, "OUTLINE_FACES", 3000)
    registration._OUTLINE.clear()
    mesh, (camera, lights) = _subdivided(_bunny(), 1), _view(index=0)
    assert registration.outline_mesh(mesh) is not mesh
    out = MeshRenderer()(mesh, camera, lights, 128, 128, (0.5, 0.5, 0.5))
    found = register(mesh, out.image[0], out.rgba[0, ..., 3] > 0.5, torch.tensor([0.5, 0.5, 0.5]))
    assert pose_error(mesh, camera, found.camera, 128, 128) < 0.5


def test_a_quick_registration_neither_recuts_nor_retries_more_views(monkeypatch):
    """`register_with_masks(quick=True)` (`meshseal detect --quick`, a scan): each guess registered once,
    without `register`'s retry of more views, and no guess cut again from a registered silhouette; the
    full registration does both where the texture does not confirm the camera."""
    calls, cuts = [], []

    def fake_register(mesh, picture, mask, background, fov_y=60.0, retry=True):
        calls.append(retry)
        return registration.Registration(None, (0, 0, 8, 8), 0.5, ())

    monkeypatch.setattr(registration, "register", fake_register)
    monkeypatch.setattr(registration, "texture_misfit", lambda *a, **k: 1.0 - 0.1 * len(calls))  # each fits better
    monkeypatch.setattr(registration, "_rasterized", lambda mesh, camera, h, w: (None, torch.ones(1, h, w)))

    def recut(silhouette):
        cuts.append(silhouette.shape)
        return torch.ones(8, 8, dtype=torch.bool)

    picture, masks = torch.zeros(3, 8, 8), [torch.ones(8, 8, dtype=torch.bool), torch.ones(8, 8, dtype=torch.bool)]
    registration.register_with_masks(None, picture, masks, torch.zeros(3), recut=recut)
    assert calls[0] is True and len(cuts) >= 1 and len(calls) > len(masks)
    calls.clear(), cuts.clear()
    registration.register_with_masks(None, picture, masks, torch.zeros(3), recut=recut, quick=True)
    assert calls == [False] * len(masks) and cuts == []


def test_the_retry_finishes_its_view_on_the_texture_only_where_its_silhouettes_already_fit_better(monkeypatch):
    """Where the finished camera fits the texture poorly (over RETRY_ABOVE), `register` refines more
    candidate views; their best is taken on to the texture stage (the costliest) only where, refined on
    its silhouettes alone, it already fits the texture better than the finished camera."""
    mesh, (camera, lights) = _bunny(), _view(index=0)
    out = MeshRenderer()(mesh, camera, lights, 128, 128, (0.5, 0.5, 0.5))
    finished = []
    monkeypatch.setattr(registration, "_on_texture", lambda mesh, camera, picture, mask: finished.append(camera) or camera)

    def run(misfits):
        values = iter(misfits)  # the finished camera's texture misfit, then the retry's view's, ...
        monkeypatch.setattr(registration, "texture_misfit", lambda *args, **kwargs: next(values, 1.0))
        finished.clear()
        registration.register(mesh, out.image[0], out.rgba[0, ..., 3] > 0.5, torch.tensor([0.5, 0.5, 0.5]))
        return len(finished)

    assert run([0.5, 0.9]) == 1  # the retry's view fits worse on its silhouettes: not finished
    assert run([0.5, 0.1, 0.05]) == 2  # it fits better: finished, and kept
    assert run([0.1]) == 1  # the finished camera fits: no retry at all
