"""Informed detection: crop cameras, lighting fits, un-rendering, registration, camera metadata, and the
CLI round trip embed -> render -> detect --mesh with a tiny informed model."""

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from meshseal.cli import main
from meshseal.errors import MeshsealError
from meshseal.reading.framing import boxes_from_mask, crop_boxes, object_mask
from meshseal.mesh import load, normalize, to_z_up
from meshseal.reading.pictures import camera_from_dict, camera_to_dict
from meshseal.reading.relight import flattest_half, uv_maps
from meshseal.reading.registration import crop_intrinsics, pose_error, refine_on_texture, register
from meshseal.render import (MeshBatch, MeshRenderer, pixels_at, relight_fragments, sample_any_lights,
                             sample_any_view_cameras, surface_at_pixels, unrender)
from meshseal.render.views import sample_views
from meshseal.training.train import TrainConfig, Trainer

FIXTURES = Path(__file__).parent / "fixtures"


def _bunny():
    return MeshBatch.from_mesh(normalize(to_z_up(load(FIXTURES / "bunny.glb"))))


def _view(seed=3, index=1):
    generator = torch.Generator().manual_seed(seed)
    cameras, lights = sample_any_view_cameras(3, generator), sample_any_lights(3, generator)
    return cameras[[index]], lights[[index]]


def _iou(a, b):
    return float((a & b).sum()) / float((a | b).sum())


def test_crop_camera_sees_exactly_the_crop():
    mesh, (camera, lights) = _bunny(), _view()
    full = MeshRenderer(blend="hard")(mesh, camera, lights, 240, 320)
    box = boxes_from_mask(full.rgba[..., 3] > 0.5)
    cropped = crop_boxes(full.rgba[..., 3:].permute(0, 3, 1, 2), box, 128)[0, 0] > 0.5
    fov, principal = crop_intrinsics(240, 320, box[0], camera.fov_y)
    direct = MeshRenderer(blend="hard")(mesh, replace(camera, fov_y=fov, principal=principal), lights, 128, 128)
    assert _iou(direct.rgba[0, ..., 3] > 0.5, cropped) > 0.97


def test_point_light_fit_explains_our_renders():
    mesh, (camera, lights) = _bunny(), _view()
    out = MeshRenderer(blend="hard")(mesh, camera, lights, 128, 128)
    fragments = out.fragments
    predicted, _, fitted = relight_fragments(mesh, fragments, camera, pixels_at(out.image, fragments))
    seen = pixels_at(out.image, fragments)
    assert float((seen - predicted).pow(2).mean().sqrt()) < 0.01
    # The colours do vary a lot, so a small misfit is the fit's doing.
    flat = (seen - seen.mean(0)).pow(2).mean().sqrt()
    assert float(flat) > 0.05


@pytest.mark.parametrize("blend", ["splat", "hard"])
@pytest.mark.parametrize("name", ["bunny.glb", "sh3d_crate/crate.obj", "teapot/teapot.obj"])
def test_the_polished_light_is_the_light_that_rendered_the_picture(monkeypatch, name, blend):
    """The light fit of every reading (`relight.relit_residual`) finds the light our renderer used,
    splatted or point-sampled: the first fit alone (registration's) is tenths of a unit off and trades
    diffuse for ambient light; the polish under the picture's own sampling recovers the position within
    two hundredths and the strengths within a percent (the teapot's red bricks clip at white under its
    light: the pixels beside a clipped one are left out), and the relit original then predicts the
    picture to its 8-bit rounding."""
    import meshseal.reading.relight as relight

    mesh = MeshBatch.from_mesh(normalize(to_z_up(load(FIXTURES / name))))
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(5))
    picture = torch.round(MeshRenderer(blend=blend)(mesh, cameras, lights, 128, 128).image.clamp(0, 1) * 255) / 255
    off = lambda found: float((found.position - lights.position).norm())  # noqa: E731
    found = relight.relit_residual(mesh, picture, cameras)
    _, point, _ = relight.fitted_light(mesh, picture, cameras)  # registration's: the first fit alone
    assert off(point) > 0.1 and off(found.lights) < 0.02
    assert float((found.lights.intensity - 1.0).abs().max()) < 0.01
    monkeypatch.setattr(relight, "POLISH_ITERATIONS", -1)  # the polish switched off: the first fit's light,
    monkeypatch.setattr(relight, "REGISTRATION_WHITE", 0.0)  # registration's under the reading's rule for white
    _, first, _ = relight.fitted_light(mesh, picture, cameras)
    assert off(relight.relit_residual(mesh, picture, cameras).lights) == pytest.approx(off(first))
    if blend == "splat":  # the relit original is our splatted render: it predicts the picture itself
        assert float((found.seen - found.expected).pow(2).mean().sqrt()) < 0.6 / 255


def test_light_fitted_on_some_pixels_explains_all_of_them():
    """The flattest half of the albedo (`flattest_half`) is half the covered pixels, all on the flat
    side of an albedo plain on the left and striped (one-pixel stripes) on the right, and the rest on
    the striped side or within reach of it; a light fitted on those pixels alone still explains the
    whole render."""
    mesh, (camera, lights) = _bunny(), _view()
    out = MeshRenderer(blend="hard")(mesh, camera, lights, 128, 128)
    fragments = out.fragments
    albedo = torch.full((1, 3, 128, 128), 0.6)
    albedo[..., 64:][..., ::2] = 0.2  # the right half striped
    flat = flattest_half(albedo, fragments)
    columns = fragments.pixel % 128
    flat_side = columns < 61  # the step into the stripes (at column 63) reaches 2 px further
    assert bool(flat_side.any() and (~flat_side).sum() > flat_side.sum())  # more busy pixels than flat ones
    assert abs(int(flat.sum()) - len(flat) / 2) <= 1 and bool(flat[flat_side].all())
    seen = pixels_at(out.image, fragments)
    predicted, _, _ = relight_fragments(mesh, fragments, camera, seen, fit_on=flat)
    assert float((seen - predicted).pow(2).mean().sqrt()) < 0.01


def test_unrender_averages_pixels_per_uv_cell():
    mesh, (camera, _) = _bunny(), _view()
    fragments, uv, _ = surface_at_pixels(mesh, camera, 96, 96)
    values = torch.full((len(uv), 2), 0.25)
    values[:, 1] = 0.75
    maps = unrender(values, uv, fragments.batch, 1, 16)
    covered = maps[0, 2] > 0
    assert covered.any() and not covered.all()
    assert torch.allclose(maps[0, 0][covered], torch.tensor(0.25)) and torch.allclose(maps[0, 1][covered], torch.tensor(0.75))
    assert float(maps[0, :2][:, ~covered].abs().max()) == 0.0


def test_uv_maps_isolate_a_texture_change():
    """What the informed decoder reads: near zero for the original, the change for a marked texture."""
    mesh, (camera, lights) = _bunny(), _view()
    picture = MeshRenderer()(mesh, camera, lights, 128, 128).image
    clean = uv_maps(mesh, picture, camera, 32)
    marked_textures = [t + 0.05 * torch.sign(torch.randn(1, *t.shape[1:], generator=torch.Generator().manual_seed(0)))
                       for t in mesh.textures]
    marked = MeshRenderer()(replace(mesh, textures=[t.clamp(0, 1) for t in marked_textures]), camera, lights, 128, 128).image
    changed = uv_maps(mesh, marked, camera, 32)
    covered = clean[:, 9] > 0
    residual_clean = clean[:, :3].abs().mean(1)[covered].mean() / 10
    residual_marked = changed[:, :3].abs().mean(1)[covered].mean() / 10
    assert residual_clean < 0.01 and residual_marked > 2 * residual_clean


def test_registration_recovers_the_view():
    """Registration of a picture from an unknown camera (non-square, grey background): the camera it
    returns is the whole picture's, and puts the visible surface within a pixel of where the true
    camera does; the texture stage brings it closer than the silhouette alone."""
    torch.manual_seed(0)
    mesh, (camera, lights) = _bunny(), _view(index=0)
    out = MeshRenderer()(mesh, camera, lights, 240, 320, (0.5, 0.5, 0.5))
    picture, mask = out.image[0], out.rgba[0, ..., 3] > 0.5
    silhouette = register(mesh, picture, mask, torch.tensor([0.5, 0.5, 0.5]), texture_refine=False)
    assert silhouette.iou > 0.9 and silhouette.camera.principal == (0.0, 0.0)
    before = pose_error(mesh, camera, silhouette.camera, 240, 320)
    after = pose_error(mesh, camera, refine_on_texture(mesh, silhouette.camera, picture[None], mask[None].float()),
                       240, 320)
    assert after < 1.0 and after < before, (before, after)


def test_registration_of_an_object_the_frame_cuts_off():
    """A close camera aimed off the bunny, so that the picture's edge cuts a third of it away: the
    silhouette past the edge is unknown, not background, and the candidates are placed so that the
    rest lies past the edge. Registered within a pixel (26 px off when the crop was taken for the
    whole object)."""
    mesh, (camera, lights) = _bunny(), _view(index=1)
    eye = camera.at + 0.4 * (camera.eye - camera.at)
    forward = torch.nn.functional.normalize(camera.at - eye, dim=-1)
    right = torch.nn.functional.normalize(torch.cross(forward, camera.up, dim=-1), dim=-1)
    shift = 0.45 * (camera.at - eye).norm() * right
    cut = replace(camera, eye=eye + shift, at=camera.at + shift)
    out = MeshRenderer()(mesh, cut, lights, 160, 160, (0.5, 0.5, 0.5))
    picture, mask = out.image[0], out.rgba[0, ..., 3] > 0.5
    assert bool(mask[:, 0].any() or mask[:, -1].any())  # the frame does cut it
    found = register(mesh, picture, mask, torch.tensor([0.5, 0.5, 0.5]))
    assert pose_error(mesh, cut, found.camera, 160, 160) < 1.0


@pytest.mark.heavy  # many seconds: CI's heavy tier keeps the default tier inside its five minutes
def test_registration_finds_another_lens(monkeypatch):
    """A picture through a longer lens than registration assumes (40 degrees, the camera moved back
    to keep the framing), as a crop of a picture or another renderer's camera makes: the texture
    stage's zoom finds the field of view and the pose within a fifth of a pixel; without it (a rigid
    move alone) the pose is half a pixel or more off."""
    import math

    from meshseal.reading import registration as registration

    mesh, (camera, lights) = _bunny(), _view(index=0)
    scale = np.tan(np.radians(30.0)) / np.tan(np.radians(20.0))
    lens = replace(camera, fov_y=40.0, eye=camera.at + (camera.eye - camera.at) * scale)
    out = MeshRenderer()(mesh, lens, lights, 192, 192, (0.5, 0.5, 0.5))
    picture, mask = out.image[0], out.rgba[0, ..., 3] > 0.5
    found = register(mesh, picture, mask, torch.tensor([0.5, 0.5, 0.5]))
    assert abs(found.camera.fov_y - 40.0) < 3.0, found.camera.fov_y
    assert pose_error(mesh, lens, found.camera, 192, 192) < 0.2
    monkeypatch.setattr(registration, "ZOOM_TRY", math.inf)
    rigid = register(mesh, picture, mask, torch.tensor([0.5, 0.5, 0.5]))
    assert rigid.camera.fov_y == 60.0 and pose_error(mesh, lens, rigid.camera, 192, 192) > 0.5


def test_a_dolly_keeps_the_object_size_under_another_lens():
    """`_dollied`: the camera moved along its view axis for another field of view shows the object at
    the size it had (the same silhouette, up to perspective), and the plain camera under that lens
    does not."""
    from meshseal.reading.registration import _dollied

    mesh, (camera, lights) = _bunny(), _view(index=0)
    hard = MeshRenderer(blend="hard")
    seen = lambda c: hard(mesh, c, lights, 96, 96).rgba[0, ..., 3] > 0.5  # noqa: E731
    for fov in (49.6, 71.6):
        moved = _dollied(mesh, camera, fov)
        assert moved.fov_y == fov and torch.allclose(moved.at - moved.eye, camera.at - camera.eye)
        assert _iou(seen(moved), seen(camera)) > 0.9 > _iou(seen(replace(camera, fov_y=fov)), seen(camera))


@pytest.mark.heavy  # many seconds: CI's heavy tier keeps the default tier inside its five minutes
def test_a_crop_has_its_own_lens_among_the_alternatives(monkeypatch):
    """A central crop to 80 % of a picture (`attacks.cropped_camera` its true camera: 0.8 times the
    tangent of the field of view assumed) registered as `meshseal detect` does: the registration
    carries the other lenses as its last alternatives (`lens_alternatives`), and the crop's, finished,
    has its field of view and a pose less than half as far off as the camera registered under the
    assumed lens (the texture stage's zoom, which gets near on the bunny's smooth texture, held off)."""
    from meshseal.evaluation.attacks import cropped_camera
    from meshseal.reading import registration as registration
    from meshseal.reading.registration import LENSES, register_with_masks

    mesh, (camera, lights) = _bunny(), _view(index=0)
    out = MeshRenderer()(mesh, camera, lights, 240, 240, (0.5, 0.5, 0.5))
    picture, mask = out.image[0, :, 24:216, 24:216], out.rgba[0, 24:216, 24:216, 3] > 0.5
    truth = cropped_camera("crop0.8", camera, 240, 240)
    assert not bool(mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())  # the crop keeps it whole
    monkeypatch.setattr(registration, "ZOOM_TRY", math.inf)
    found = register_with_masks(mesh, picture, [mask], torch.tensor([0.5, 0.5, 0.5]))
    assert found.camera.fov_y == 60.0 and len(found.alternatives) >= len(LENSES)
    lens = found.alternatives[-len(LENSES) + LENSES.index(0.8)]
    rough = lens.rough()
    assert abs(rough.fov_y - truth.fov_y) < 0.01, (rough.fov_y, truth.fov_y)
    error = pose_error(mesh, truth, lens.finish(), 192, 192)
    assert error < 0.5 * pose_error(mesh, truth, found.camera, 192, 192), error


@pytest.mark.heavy  # many seconds: CI's heavy tier keeps the default tier inside its five minutes
def test_a_small_object_is_registered_on_an_enlarged_copy():
    """A bunny about 70 px wide (a halved picture, a thumbnail) is registered on a copy enlarged a
    whole number of times (`registration_factor`; its guesses and recut enlarged alike), and the
    camera found there is the small picture's own: closer to the truth than registering the small
    picture as it is, and within a tenth of a pixel."""
    from meshseal.reading.read import enlarged, registration_factor

    mesh, (camera, lights) = _bunny(), _view(index=0)
    out = MeshRenderer()(mesh, camera, lights, 96, 96, (0.5, 0.5, 0.5))
    picture, mask = out.image[0], out.rgba[0, ..., 3] > 0.5
    factor = registration_factor(mask.numpy())
    assert factor >= 2 and registration_factor(np.ones((400, 400), bool)) == 1
    calls = []
    big, masks, recut = enlarged(picture, [mask], lambda m: calls.append(m.shape) or m, factor)
    assert big.shape[-2:] == (96 * factor, 96 * factor) and masks[0].shape == big.shape[-2:]
    assert recut(np.zeros(big.shape[-2:], bool)).shape == big.shape[-2:] and calls == [(96, 96)]
    background = torch.tensor([0.5, 0.5, 0.5])
    small = pose_error(mesh, camera, register(mesh, picture, mask, background).camera, 96, 96)
    large = pose_error(mesh, camera, register(mesh, big, masks[0], background).camera, 96, 96)
    assert large < 0.1 and large < small, (small, large)


@pytest.mark.heavy  # many seconds: CI's heavy tier keeps the default tier inside its five minutes
def test_registration_tries_more_views_where_the_texture_disagrees(monkeypatch):
    """Where the view refined first is wrong (here forced: the first pass keeps only the candidate
    facing most away from the true camera), the texture explains the picture poorly and registration
    tries more candidate views (RETRY_KEEP), which find the view; without them it stays wrong."""
    from meshseal.reading import registration as registration

    mesh, (camera, lights) = _bunny(), _view(index=0)
    out = MeshRenderer()(mesh, camera, lights, 160, 160, (0.5, 0.5, 0.5))
    picture, mask = out.image[0], out.rgba[0, ..., 3] > 0.5
    truth = torch.nn.functional.normalize(camera.eye - camera.at, dim=-1)[0]
    distinct = registration._distinct

    def wrong_first(scores, directions, keep, min_angle=30.0, away_from=()):
        if away_from:
            return distinct(scores, directions, keep, min_angle, away_from)
        return [int((directions @ truth).argmin())]

    monkeypatch.setattr(registration, "_distinct", wrong_first)
    found = register(mesh, picture, mask, torch.tensor([0.5, 0.5, 0.5]))
    assert pose_error(mesh, camera, found.camera, 160, 160) < 1.0
    monkeypatch.setattr(registration, "RETRY_KEEP", 0)
    stuck = register(mesh, picture, mask, torch.tensor([0.5, 0.5, 0.5]))
    assert pose_error(mesh, camera, stuck.camera, 160, 160) > 5.0


def test_texture_refinement_survives_a_flat_picture():
    """A picture of one colour gives the texture stage nothing to align on: it still returns a finite
    camera (a singular Gauss-Newton system, from a band with no gradient, is a stop, not a crash)."""
    mesh, (camera, lights) = _bunny(), _view(index=0)
    flat = replace(mesh, textures=[torch.full_like(t, 0.6) for t in mesh.textures])
    mask = (MeshRenderer()(flat, camera, lights, 96, 96).rgba[..., 3] > 0.5).float()
    picture = torch.full((1, 3, 96, 96), 0.3)
    found = refine_on_texture(flat, camera, picture, mask)
    assert torch.isfinite(found.eye).all() and torch.isfinite(found.at).all()


def test_camera_metadata_round_trip_and_errors(tmp_path, capsys):
    assert main(["render", str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "b.png"), "--width", "64",
                 "--height", "48", "--camera", "1,-3,2"]) == 0
    with Image.open(tmp_path / "b.png") as image:
        values = json.loads(image.info["meshseal:camera"])
    camera = camera_from_dict(values)
    assert torch.allclose(camera.eye, torch.tensor([[1.0, -3.0, 2.0]])) and camera.fov_y == 60.0
    assert camera_to_dict(camera) == values
    for bad in ({}, {"eye": [1, 2], "at": [0, 0, 0], "up": [0, 0, 1], "fov_y": 60},
                {"eye": [1, 2, 3], "at": [0, 0, 0], "up": [0, 0, 1], "fov_y": 0}):
        with pytest.raises(MeshsealError):
            camera_from_dict(bad)


INFORMED = {
    "name": "tiny_informed", "seed": 1,
    "model": {"n_bits": 8, "strategy": "texture", "texture_channels": 8, "texture_blocks": 2, "texture_downsample": 2,
              "texture_tile": 4, "texture_size": 32, "decoder": "uv", "decoder_channels": 8, "uv_grid": 16},
    "train": {"steps": 4, "batch_size": 2, "lr": 0.001, "render_size": 48, "background": "random",
              "unrender_jitter": 0.5, "reference_steps": 4, "warmup_steps": 2, "distortion_start": 2,
              "distortion_2d": 0.5, "val_every": 2, "val_meshes": 2, "checkpoint_every": 2},
}


@pytest.mark.heavy
def test_informed_model_trains_and_round_trips_on_the_cli(tmp_path, capsys):
    import shutil

    from meshseal.data.build import build

    src = tmp_path / "src"
    src.mkdir()
    for name in ("bunny.glb", "suzanne.glb"):
        shutil.copy(FIXTURES / name, src / name)
    shutil.copytree(FIXTURES / "teapot", src / "teapot")
    build(tmp_path / "data", sources=[], texture_sources=[], from_folder=src, textures_dir=FIXTURES / "textures",
          seed=0, n_faces=400, texture_size=32, workers=1, license_="CC0-1.0", test_fraction=0.4)
    values = json.loads(json.dumps(INFORMED))
    values["data"] = str(tmp_path / "data")
    summary = Trainer(TrainConfig.from_dict(values), tmp_path / "run", log=lambda *_: None).fit()
    assert summary["steps"] == 4
    model = str(tmp_path / "run" / "model.safetensors")
    bits = "10110010"
    assert main(["embed", str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "m.glb"), "--bits", bits,
                 "--model", model, "--views", "1"]) == 0
    assert main(["render", str(tmp_path / "m.glb"), "-o", str(tmp_path / "v.png"), "--width", "160", "--height", "120"]) == 0
    capsys.readouterr()
    assert main(["detect", str(tmp_path / "v.png"), "--model", model, "--mesh", str(FIXTURES / "bunny.glb"), "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert len(result["bits"]) == 8 and result["camera"] == "metadata"
    # Without the original mesh, or with one that has no texture: one clear line, exit 2.
    for argv in (["detect", str(tmp_path / "v.png"), "--model", model],
                 ["detect", str(tmp_path / "v.png"), "--model", model, "--mesh", str(FIXTURES / "cube.off")],
                 ["detect", str(tmp_path / "v.png"), "--model", model, "--mesh", str(FIXTURES / "bunny.glb"), "--fov", "0"]):
        capsys.readouterr()
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and err[0].startswith("meshseal: error:"), argv


def test_shipped_default_model_round_trips_on_the_bunny(tmp_path, capsys):
    """The README's first command, with the shipped weights: embed -> render (2 views) -> detect."""
    assert main(["models", "--json"]) == 0
    models = {m["name"]: m for m in json.loads(capsys.readouterr().out)}
    assert models["default"]["n_bits"] == 64
    bits = "1011001110001111000010101100101001110110010010111100000111010010"
    assert main(["embed", str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "b.glb"), "--bits", bits, "--views", "1"]) == 0
    assert main(["render", str(tmp_path / "b.glb"), "-o", str(tmp_path / "v.png"), "--views", "2", "--seed", "0"]) == 0
    capsys.readouterr()
    assert main(["detect", str(tmp_path / "v_0.png"), str(tmp_path / "v_1.png"), "--mesh", str(FIXTURES / "bunny.glb"),
                 "--json"]) == 0
    results = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    accuracy = sum(sum(a == b for a, b in zip(r["bits"], bits)) for r in results) / (64 * len(results))
    assert accuracy >= 0.95, accuracy
    # The camera from the metadata places the object's box without searching the picture for it.
    for index, result in enumerate(results):
        pixels = np.asarray(Image.open(tmp_path / f"v_{index}.png").convert("RGB"), dtype=np.float32) / 255
        found = boxes_from_mask(torch.from_numpy(object_mask(pixels)[0])[None])[0]
        assert result["camera"] == "metadata" and torch.allclose(torch.tensor(result["box"]), found, atol=2.0)


def test_object_mask_on_a_graded_background():
    """A background ramping between two colours (a studio backdrop) is not the object: the mask is the
    object alone, also when the object touches the frame."""
    ramp = np.linspace(0.0, 1.0, 120, dtype=np.float32)[None, :, None]
    picture = (0.2 + 0.5 * ramp * np.array([1.0, 0.6, 0.2], dtype=np.float32)).repeat(100, axis=0)
    truth = np.zeros((100, 120), dtype=bool)
    truth[30:70, 40:90] = True
    truth[0:20, 0:15] = True  # a second part of the object, cut off by the frame's corner
    picture[truth] = (0.9, 0.1, 0.5)
    mask, _ = object_mask(picture)
    assert (mask & truth).sum() / (mask | truth).sum() > 0.95


def test_object_mask_keeps_the_half_covered_pixels_of_an_antialiased_edge():
    """An antialiased object (a textured disc and a thin slanted bar, 16x supersampled) on a plain
    background: the mask is the pixels it covers at least half, as a hard raster marks them, not every
    pixel its rim touches (which made registered silhouettes half a pixel too wide)."""
    fine = 16
    ys, xs = (np.mgrid[0:96 * fine, 0:96 * fine] + 0.5) / fine
    shape = ((ys - 40.3) ** 2 + (xs - 44.7) ** 2 < 21.2 ** 2) | ((np.abs(ys - 0.35 * xs - 60.2) < 1.3) & (xs > 20) & (xs < 85))
    coverage = shape.reshape(96, fine, 96, fine).mean(axis=(1, 3)).astype(np.float32)
    generator = np.random.default_rng(0)
    colour = (np.array([0.8, 0.3, 0.2], dtype=np.float32) + 0.1 * generator.random((96, 96, 1), dtype=np.float32))
    background = np.array([0.2, 0.4, 0.6], dtype=np.float32)
    picture = coverage[..., None] * colour + (1 - coverage[..., None]) * background
    truth, touched = coverage >= 0.5, coverage > 0.05
    mask, _ = object_mask(picture)
    iou = lambda a, b: (a & b).sum() / (a | b).sum()  # noqa: E731
    assert iou(mask, truth) > 0.97 > iou(touched, truth)
    columns = np.arange(96)[None]
    on_bar = (np.abs(np.arange(96)[:, None] - 0.35 * columns - 60.2) < 0.5) & (columns > 22) & (columns < 83)
    assert mask[on_bar].mean() > 0.9  # the bar stays


def test_reading_runs_under_inference_mode_and_leaves_later_renders_differentiable():
    """A reading runs under torch.inference_mode (no version counters, no view tracking: a reading is
    thousands of small operations); what it caches on the way (the splat's kernels) must not stop a
    later render in the same process from taking gradients, and a reading's caches keyed on a
    picture still serve a second reading of the same tensor (`reading.kept`)."""
    import meshseal

    watermarker = meshseal.load()
    mesh = _bunny()
    cameras, lights = _view()
    with torch.no_grad():
        picture = MeshRenderer()(mesh, cameras, lights, 96, 96).image[0]
    original = watermarker.original(FIXTURES / "bunny.glb")
    first = watermarker.read(picture, original, camera=cameras)
    again = watermarker.read(picture, original, camera=cameras)
    assert first.evidence.is_inference() and torch.equal(first.evidence, again.evidence)
    texture = mesh.textures[0].clone().requires_grad_(True)
    image = MeshRenderer()(replace(mesh, textures=[texture]), cameras, lights, 96, 96).image
    image.sum().backward()
    assert texture.grad is not None and float(texture.grad.abs().sum()) > 0


def test_a_light_fit_of_many_images_at_once_is_each_images_own_fit():
    """`fit_point_light` searches around each image's best light for all images at once (a registration
    scores a hundred views): each image ends at the light it would reach fitted alone."""
    from meshseal.render import fit_point_light

    generator = torch.Generator().manual_seed(0)
    counts = torch.tensor([700, 20, 9, 2500])  # a small image, one too small to fit (ambient only), a large one
    image = torch.repeat_interleave(torch.arange(4), counts)[torch.randperm(int(counts.sum()), generator=generator)]
    position = torch.randn(len(image), 3, generator=generator) * 0.3
    normal = torch.nn.functional.normalize(torch.randn(len(image), 3, generator=generator), dim=1)
    albedo = torch.rand(len(image), 3, generator=generator)
    lights = torch.tensor([[2.0, 1.0, 3.0], [-1.0, 2.0, 2.0], [0.0, 0.0, 4.0], [3.0, -2.0, 1.0]])[image]
    distance = (lights - position).norm(dim=1)
    lambert = ((normal * (lights - position)).sum(1) / distance).clamp_min(0) / (1 + 0.1 * distance)
    seen = (albedo * (0.3 + 0.7 * lambert[:, None])).clamp(0, 1)
    ambient, fitted = fit_point_light(seen, albedo, position, normal, image, 4, 48, 256)
    for index in range(4):
        alone = image == index
        own_ambient, own = fit_point_light(seen[alone], albedo[alone], position[alone], normal[alone],
                                           torch.zeros(int(alone.sum()), dtype=torch.long), 1, 48, 256)
        assert torch.allclose(ambient[index], own_ambient[0], atol=1e-5)
        assert torch.allclose(fitted.position[index], own.position[0], atol=1e-5)
        assert torch.allclose(fitted.intensity[index], own.intensity[0], atol=1e-5)
    assert torch.equal(fitted.intensity[2], torch.zeros(1, 3))  # too few pixels: no point light


def _lit_plane(strength: float):
    """A textured plane (1, 3, 128, 128 8-bit picture) under a point light `strength` strong, its camera and
    the mesh: from about 1.4 up the middle of the plane clips at white."""
    from meshseal.render import cameras_from_eyes, lights_at

    n = 33
    u = torch.linspace(0, 1, n)
    v, w = torch.meshgrid(u, u, indexing="ij")
    positions = torch.stack([w * 2 - 1, v * 2 - 1, torch.zeros_like(w)], -1).reshape(1, -1, 3)
    normals = torch.tensor([0.0, 0.0, 1.0]).expand(1, n * n, 3).clone()
    corner = (torch.arange(n - 1)[:, None] * n + torch.arange(n - 1)[None, :]).reshape(-1)
    faces = torch.cat([torch.stack([corner, corner + 1, corner + n + 1], -1),
                       torch.stack([corner, corner + n + 1, corner + n], -1)])
    texture = 0.45 + 0.25 * torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(0))
    mesh = MeshBatch.from_tensors(positions, normals, torch.stack([w, v], -1).reshape(1, -1, 2), faces, texture)
    cameras = cameras_from_eyes(torch.tensor([[0.0, -1.6, 2.2]]))
    with torch.no_grad():
        image = MeshRenderer()(mesh, cameras, lights_at(torch.tensor([[0.3, 0.2, 1.4]]), strength), 128, 128).image
    return torch.round(image.clamp(0, 1) * 255) / 255, cameras, mesh


def test_the_light_is_fitted_on_the_pixels_below_white(monkeypatch):
    """A highlight that clipped says only that the light there is at least that strong: the first light fit
    leaves such pixels out, and the relit original then fits the rest of the picture as closely as when
    nothing clipped; fitted as colours, they pull the light off and the prediction misses by over twice
    as much (2.3-2.6 times: how far the light is pulled depends on the order of the fit's sums, which
    moves with the thread count and the CPU's vector kernels). Where nothing clips, the fit is the one
    it always was."""
    import meshseal.reading.relight as relight
    from meshseal.reading.relight import NEAR_WHITE, relit_residual

    def misfit(picture, cameras, mesh):
        found = relit_residual(mesh, picture, cameras)
        below = found.seen.amax(1) < NEAR_WHITE
        return float(((found.seen - found.expected)[below] ** 2).mean()), float((~below).float().mean())

    clean, clean_share = misfit(*_lit_plane(1.0))
    clipped, share = misfit(*_lit_plane(1.4))
    monkeypatch.setattr(relight, "_below_white", lambda seen, fragments, n_images, fit_on, share=0.0: fit_on)
    same_clean, _ = misfit(*_lit_plane(1.0))
    taken_as_colours, _ = misfit(*_lit_plane(1.4))
    assert clean_share == 0.0 and same_clean == clean
    assert 0.3 < share < 0.7
    assert clipped < 1.2 * clean and taken_as_colours > 2.0 * clipped


def test_a_picture_almost_all_white_keeps_every_pixel_for_its_light_fit():
    from types import SimpleNamespace

    from meshseal.reading.relight import MIN_FIT_PIXELS, _below_white

    size = 2 * MIN_FIT_PIXELS  # pixels a picture
    seen = torch.full((2 * size, 3), 0.5)
    seen[:10] = 1.0  # picture 0: ten white pixels among many others
    seen[size + 10:] = 1.0  # picture 1: fewer than MIN_FIT_PIXELS below white
    fragments = SimpleNamespace(batch=torch.arange(2).repeat_interleave(size))
    fit_on = _below_white(seen, fragments, 2, None)
    assert not bool(fit_on[:10].any()) and bool(fit_on[10:].all())
    flat = torch.zeros(2 * size, dtype=torch.bool)
    assert _below_white(torch.full((2 * size, 3), 0.5), fragments, 2, flat) is flat
    # registration's rule: only a picture whose near-white pixels are at least `share` of its own
    few = _below_white(seen, fragments, 2, None, share=0.05)  # picture 0: 10 of 128 (7.8 %): left out
    assert not bool(few[:10].any()) and bool(few[10:].all())
    assert _below_white(seen, fragments, 2, flat, share=0.1) is flat  # 7.8 % is under a tenth: all kept
