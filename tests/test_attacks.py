"""The picture attacks of `meshseal eval --attacks` (meshseal.attacks): what each does to a picture."""

import numpy as np
import pytest

from meshseal.evaluation import attacks as attacks


@pytest.fixture
def picture():
    rng = np.random.default_rng(0)
    smooth = np.cumsum(np.cumsum(rng.normal(size=(96, 128, 3)), 0), 1)
    smooth = (smooth - smooth.min()) / (smooth.max() - smooth.min())
    return np.round(smooth * 255).astype(np.uint8)


@pytest.mark.parametrize("name", list(attacks.ATTACKS))
def test_every_attack_returns_an_8_bit_picture_and_repeats_with_its_seed(name, picture):
    first = attacks.apply(name, picture, np.random.default_rng(1))
    again = attacks.apply(name, picture, np.random.default_rng(1))
    assert first.dtype == np.uint8 and first.ndim == 3 and first.shape[2] == 3
    assert np.array_equal(first, again)
    assert picture.sum() == attacks.apply("none", picture, np.random.default_rng(0)).sum()  # input untouched


def test_geometry_of_the_geometric_attacks(picture):
    rng = np.random.default_rng(2)
    assert attacks.apply("resize0.5", picture, rng).shape == (48, 64, 3)
    assert attacks.apply("resize1.5", picture, rng).shape == (144, 192, 3)
    crop = attacks.apply("crop0.8", picture, rng)
    assert crop.shape == (77, 102, 3) and np.array_equal(crop, picture[9:86, 13:115])
    shot = attacks.apply("screenshot", picture, rng)
    assert shot.shape == (320, 400, 3) and (shot[:24] == 60).all()
    found = [(top, left) for top in range(24, 320 - 96 + 1) for left in range(0, 400 - 128 + 1)
             if np.array_equal(shot[top:top + 96, left:left + 128], picture)]
    assert len(found) == 1  # the picture, unscaled, somewhere below the bar


def test_lossy_formats_change_the_picture_a_little_and_brightness_a_lot(picture):
    rng = np.random.default_rng(3)
    for name, most in (("jpeg95", 6.0), ("jpeg50", 10.0), ("webp80", 10.0)):
        out = attacks.apply(name, picture, rng).astype(float)
        error = np.abs(out - picture).mean()
        assert 0 < error < most, (name, error)
    assert np.abs(attacks.apply("brightness", picture, rng).astype(float).mean() - picture.mean()) > 5


def test_names_parse_and_unknown_ones_are_refused():
    assert attacks.parse("jpeg90, webp80") == ["jpeg90", "webp80"]
    assert attacks.parse("all") == [*attacks.ATTACKS, *attacks.ASSET_NAMES]
    assert attacks.parse("jpeg75,texture_bc1") == ["jpeg75", "texture_bc1"]
    with pytest.raises(ValueError, match="unknown attack"):
        attacks.parse("jpeg90,bogus")
    with pytest.raises(ValueError):
        attacks.parse(" , ")


def test_pictures_are_sorted_into_the_kinds_the_report_splits_out():
    """`picture_kinds`: a texture on its fine / coarse grid is magnified / minified (on its own grid,
    minified where its cells are narrow), an object mostly at
    white clips, one under SMALL_OBJECT pixels is small, and a picture of none of these is plain."""
    import torch

    from meshseal.evaluation.evaluate import MINIFIED_BELOW, SMALL_OBJECT, picture_kinds
    from meshseal.models.spread import SpreadSpectrumEncoder

    encoder = SpreadSpectrumEncoder(64, chips=128, coarse_chips=64, fine_chips=512)
    pictures = torch.full((3, 3, 64, 64), 0.4)
    pictures[1, :, :40] = 1.0  # most of the object at white
    masks = torch.zeros(3, 64, 64, dtype=torch.bool)
    masks[:2] = True
    masks[2, :10, :10] = True  # 100 pixels
    assert SMALL_OBJECT > 100 and 64 * 64 >= SMALL_OBJECT
    assert picture_kinds(encoder, 128, pictures, masks) == [["plain"], ["clipped"], ["small"]]
    assert picture_kinds(encoder, 512, pictures, masks)[0] == ["magnified"]
    assert picture_kinds(encoder, 64, pictures, masks)[1] == ["minified", "clipped"]
    # On the model's own grid, cells under MINIFIED_BELOW px in a standard view are minified too
    # (a mark without a coarser grid for them), and cells just over it are not.
    assert picture_kinds(encoder, 128, pictures, masks, MINIFIED_BELOW * 0.9)[0] == ["minified"]
    assert picture_kinds(encoder, 128, pictures, masks, MINIFIED_BELOW * 1.1)[0] == ["plain"]


def test_a_central_crop_has_the_camera_that_renders_it():
    """`cropped_camera`: the original rendered with the crop's camera at the crop's size is the crop."""
    import torch

    from pathlib import Path

    from meshseal.mesh import load, normalize, to_z_up
    from meshseal.render import Cameras, MeshBatch, MeshRenderer, lights_at

    bunny = Path(__file__).parent / "fixtures" / "bunny.glb"
    mesh = MeshBatch.from_mesh(normalize(to_z_up(load(bunny))))
    cameras = Cameras(torch.tensor([[0.4, -1.6, 0.8]]), torch.tensor([[0.05, 0.0, 0.1]]), torch.tensor([[0.0, 0.0, 1.0]]))
    lights = lights_at(torch.tensor([[2.0, -1.0, 2.0]]))
    renderer = MeshRenderer()
    whole = renderer(mesh, cameras, lights, 96, 96).image.clamp(0, 1)[0].permute(1, 2, 0).numpy()
    crop = attacks.apply("crop0.8", np.round(whole * 255).astype(np.uint8), np.random.default_rng(0))
    camera = attacks.cropped_camera("crop0.8", cameras, 96, 96)
    again = renderer(mesh, camera, lights, crop.shape[0], crop.shape[1]).image.clamp(0, 1)[0].permute(1, 2, 0).numpy()
    inner = (slice(2, -2), slice(2, -2))  # at the frame the splats of pixels outside the crop are missing
    assert crop.shape == (77, 77, 3) and np.abs(np.round(again * 255) - crop)[inner].max() <= 1
    assert not np.array_equal(crop, np.round(whole[10:87, 10:87] * 255))  # the object fills the frame: a crop shows less of it
    assert attacks.cropped_camera("screenshot", cameras, 96, 96) is None  # placed at random: no camera
    assert attacks.cropped_camera("crop0.8", cameras, 96, 128) is None  # not square: not worked out
