"""Busy backgrounds: telling them from plain ones, the object found by the original's colours, and a
marked picture on a photograph-like backdrop read end to end from the command line."""

import json
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

import meshseal
from meshseal.cli import main
from meshseal.reading.framing import object_mask
from meshseal.mesh import load, normalize, to_z_up
from meshseal.render import MeshBatch, MeshRenderer, sample_any_lights, sample_any_view_cameras
from meshseal.reading.segmentation import (PLAIN_FIRST, busy_background, guided_object_mask, mask_iou,
                                          plain_share, recut)

FIXTURES = Path(__file__).parent / "fixtures"


def _backdrop(name: str, size: int) -> np.ndarray:
    """A fixture texture tiled to size x size (H, W, 3) float: a busy background."""
    with Image.open(FIXTURES / "textures" / name) as image:
        tile = np.asarray(image.convert("RGB"), dtype=np.float32) / 255
    reps = -(-size // tile.shape[0])
    return np.tile(tile, (reps, reps, 1))[:size, :size]


def _picture(mesh: MeshBatch, backdrop: np.ndarray, seed: int = 3):
    """The mesh rendered from a seeded view over `backdrop`: the picture (H, W, 3), its true mask and
    camera."""
    generator = torch.Generator().manual_seed(seed)
    cameras, lights = sample_any_view_cameras(1, generator), sample_any_lights(1, generator)
    size = backdrop.shape[0]
    with torch.no_grad():
        rgba = MeshRenderer()(mesh, cameras, lights, size, size, (0.0, 0.0, 0.0)).rgba[0].numpy()
    alpha = rgba[..., 3:]
    return rgba[..., :3] + (1 - alpha) * backdrop, alpha[..., 0] > 0.5, cameras


def test_busy_and_plain_backgrounds_are_told_apart():
    bunny = MeshBatch.from_mesh(normalize(to_z_up(load(FIXTURES / "bunny.glb"))))
    plain, _, _ = _picture(bunny, np.full((128, 128, 3), (0.4, 0.45, 0.5), dtype=np.float32))
    busy, _, _ = _picture(bunny, _backdrop("brick.png", 128))
    assert not busy_background(plain) and busy_background(busy)


def test_the_original_s_colours_find_the_object_on_a_busy_background():
    """On bricks, "differs from the border" marks nearly the whole picture; the cut guided by the bunny's
    colours finds the bunny."""
    bunny = MeshBatch.from_mesh(normalize(to_z_up(load(FIXTURES / "bunny.glb"))))
    picture, truth, _ = _picture(bunny, _backdrop("brick.png", 160))
    plain_mask, _ = object_mask(picture)
    assert mask_iou(plain_mask, truth) < 0.7
    assert mask_iou(guided_object_mask(picture, bunny), truth) > 0.9


def test_an_object_the_frame_cuts_off_on_a_plain_background_is_found_and_its_mask_tried_first():
    """A dark crate cut off by the frame on both sides, on a plain light background (a tenth of the
    border is crate): the background fit starts from the border's own colour, so the plain mask is
    the crate (a fit of every border pixel was pulled off the background everywhere and took the whole
    picture for the object), and since most of the border is plain that mask is registered first."""
    crate = MeshBatch.from_mesh(normalize(to_z_up(load(FIXTURES / "sh3d_crate" / "crate.obj"))))
    picture, truth, _ = _picture(crate, np.full((192, 192, 3), (0.80, 0.85, 0.85), dtype=np.float32), seed=11)
    columns = np.nonzero(truth.any(0))[0]
    middle = (columns[0] + columns[-1]) // 2
    half = (columns[-1] - columns[0]) * 9 // 20  # the frame cuts a twentieth off each side
    picture, truth = picture[:, middle - half:middle + half], truth[:, middle - half:middle + half]
    border = np.concatenate([truth[0], truth[-1], truth[:, 0], truth[:, -1]])
    assert 0.03 < border.mean() < 0.2  # the crate touches the frame, the border is mostly background
    assert mask_iou(object_mask(picture)[0], truth) > 0.9
    assert plain_share(picture) >= PLAIN_FIRST


@pytest.mark.heavy  # many seconds: CI's heavy tier keeps the default tier inside its five minutes
def test_a_marked_picture_on_a_busy_background_is_read_without_metadata(tmp_path, capsys):
    """The marked bunny rendered over gravel and saved as a plain PNG (no camera in it): `meshseal
    detect --mesh` finds the object, registers the camera and reads the message; the unmarked bunny on
    the same backdrop is not detected."""
    wm = meshseal.load()
    original = meshseal.load_mesh(FIXTURES / "bunny.glb")
    marked = wm.embed(original, "b42")
    for name, mesh in (("marked", marked), ("clean", original)):
        batch = MeshBatch.from_mesh(normalize(to_z_up(mesh)))
        picture, _, _ = _picture(batch, _backdrop("gravel.png", 256), seed=5)
        Image.fromarray((np.clip(picture, 0, 1) * 255 + 0.5).astype(np.uint8)).save(tmp_path / f"{name}.png")
    capsys.readouterr()
    assert main(["detect", str(tmp_path / "marked.png"), str(tmp_path / "clean.png"),
                 "--mesh", str(FIXTURES / "bunny.glb"), "--json"]) == 0
    marked_result, clean_result = (json.loads(line) for line in capsys.readouterr().out.splitlines())
    assert marked_result["camera"] == "registered" and marked_result["registration_iou"] > 0.9
    assert marked_result["detected"] and marked_result["message"] == "b42", marked_result["p_value"]
    assert not clean_result["detected"]


def test_a_registered_silhouette_a_few_pixels_off_cuts_the_object_out_again():
    """`recut` seeded by a silhouette 6 px off the bunny on bricks cuts along the bunny's own edges."""
    bunny = MeshBatch.from_mesh(normalize(to_z_up(load(FIXTURES / "bunny.glb"))))
    picture, truth, _ = _picture(bunny, _backdrop("brick.png", 160))
    off = np.roll(truth, (4, -5), axis=(0, 1))
    assert mask_iou(off, truth) < 0.8
    assert mask_iou(recut(picture, off), truth) > 0.9


@pytest.mark.heavy
def test_a_cut_that_took_in_a_patch_of_the_background_is_mended_from_its_registration():
    """A first guess of the object's pixels that also holds a square of the background: registered on
    it, the camera is off and the texture does not confirm it; `register_with_masks` with `recut` cuts
    again from that camera's silhouette and registers within half a pixel."""
    from meshseal.reading.registration import ACCEPT_MISFIT, PICK_SIGMAS, pose_error, register_with_masks, texture_misfit

    bunny = MeshBatch.from_mesh(normalize(to_z_up(load(FIXTURES / "bunny.glb"))))
    picture, truth, camera = _picture(bunny, _backdrop("gravel.png", 256), seed=5)
    guess = truth.copy()
    guess[8:72, 8:72] = True
    tensor, background = torch.from_numpy(picture).permute(2, 0, 1).float(), torch.zeros(3)
    masks = [torch.from_numpy(guess)]
    everywhere = torch.ones(1, 256, 256)
    with torch.enable_grad():
        alone = register_with_masks(bunny, tensor, masks, background)
        again = register_with_masks(bunny, tensor, masks, background, recut=lambda silhouette: recut(picture, silhouette))
    assert texture_misfit(bunny, alone.camera, tensor[None], everywhere, PICK_SIGMAS) > ACCEPT_MISFIT
    assert texture_misfit(bunny, again.camera, tensor[None], everywhere, PICK_SIGMAS) < ACCEPT_MISFIT
    assert pose_error(bunny, camera, again.camera, 256, 256) < 0.5


@pytest.mark.heavy
def test_a_later_guess_is_made_only_when_the_search_reaches_it():
    """`register_with_masks` takes a later guess as a function and calls it only when the guesses
    before it are not confirmed: never after a right registration; after a wrong first guess (a
    square of the background), it is called, a None from it is passed over, and the guess it makes
    is registered."""
    from meshseal.reading.registration import pose_error, register_with_masks

    bunny = MeshBatch.from_mesh(normalize(to_z_up(load(FIXTURES / "bunny.glb"))))
    picture, truth, camera = _picture(bunny, np.full((128, 128, 3), (0.2, 0.3, 0.35), dtype=np.float32), seed=5)
    tensor, background = torch.from_numpy(picture).permute(2, 0, 1).float(), torch.tensor([0.2, 0.3, 0.35])
    square = np.zeros_like(truth)
    square[4:36, 4:36] = True
    calls = []

    def later(mask):
        return lambda: calls.append(mask is not None) or (None if mask is None else torch.from_numpy(mask))

    with torch.enable_grad():
        right = register_with_masks(bunny, tensor, [torch.from_numpy(truth), later(square)], background)
        assert calls == [] and pose_error(bunny, camera, right.camera, 128, 128) < 0.5
        found = register_with_masks(bunny, tensor, [torch.from_numpy(square), later(None), later(truth)], background)
    assert calls == [False, True] and pose_error(bunny, camera, found.camera, 128, 128) < 0.5


def test_a_picture_pasted_into_a_screenshot_is_found_and_a_plain_picture_is_left_alone():
    """`framing.inner_picture`: a render pasted into a light window with a dark title bar is found as
    the rectangle it fills; a picture of an object on a plain background, and a plain rectangle object,
    are not pictures within pictures."""
    from meshseal.evaluation.attacks import apply
    from meshseal.reading.framing import inner_picture

    ys, xs = np.mgrid[0:120, 0:160]
    render = np.zeros((120, 160, 3), dtype=np.float32) + np.float32([0.35, 0.3, 0.25])
    disk = (ys - 60) ** 2 + (xs - 85) ** 2 < 40 ** 2
    render[disk] = np.stack([0.8 + 0.1 * np.sin(xs[disk] / 3), 0.4 + 0.0 * xs[disk], 0.2 + 0.1 * np.cos(ys[disk] / 4)], -1)
    shot = apply("screenshot", np.round(render * 255).astype(np.uint8), np.random.default_rng(0)).astype(np.float32) / 255
    top, bottom, left, right = inner_picture(shot)
    assert (bottom - top, right - left) == (120, 160)
    assert np.abs(shot[top:bottom, left:right] - render).max() < 1 / 255 + 1e-6
    assert inner_picture(render) is None
    box = np.full((120, 160, 3), 0.9, dtype=np.float32)
    box[20:100, 30:130] = 0.3  # a plain rectangle on a plain background: nothing inside it
    assert inner_picture(box) is None


def test_a_camera_known_readings_object_mask_is_made_when_asked_and_pickles_as_the_mask():
    """A picture whose camera is known keeps its pixels for `why_not` instead of a mask it rarely needs
    (`reading.read.ObjectMask`): asked, it is `framing.object_mask` untrimmed; pickled (a worker's
    reading sent back), it travels as that mask, not as a closure or the pixels. `clearly_not_empty`
    passes a picture with a few hundred pixels off its border's colour and not a plain one."""
    import pickle

    from meshseal.reading.read import CLEARLY_NOT_EMPTY, ObjectMask, clearly_not_empty

    picture = np.full((64, 64, 3), 0.5, dtype=np.float32)
    assert not clearly_not_empty(picture)
    picture[10:40, 12:44] = (0.9, 0.2, 0.1)
    assert clearly_not_empty(picture) and 30 * 32 >= CLEARLY_NOT_EMPTY
    expected = torch.from_numpy(object_mask(picture, trim=False)[0] > 0.5)
    lazy = ObjectMask(picture)
    sent = pickle.loads(pickle.dumps(lazy))
    assert sent._pixels is None and torch.equal(sent(), expected)
    assert torch.equal(lazy(), expected) and int(expected.sum()) == 30 * 32 - 4  # the opening takes the corners
