"""Networks, distortions, framing and weights I/O: shapes, bounds, gradients, any-size inputs."""

import io

import numpy as np
import pytest
import torch
from PIL import Image

from meshseal.training.distortions import Distortions2D, Distortions3D, jpeg, random_crop_faces, random_rotation
from meshseal.errors import MeshsealError
from meshseal.reading.framing import boxes_from_mask, crop_boxes, object_mask
from meshseal.models import ModelConfig, WatermarkModel
from meshseal.models.io import load_model, save_model

SMALL = dict(texture_channels=8, decoder_channels=8, vertex_width=8, texture_size=32, frame_size=32)


@pytest.mark.parametrize("strategy", ["texture", "vertex", "vertex+texture"])
@pytest.mark.parametrize("texture_encoder", ["hidden", "unet"])
def test_embed_shapes_bounds_and_masking(strategy, texture_encoder):
    torch.manual_seed(0)
    model = WatermarkModel(ModelConfig(n_bits=8, strategy=strategy, texture_encoder=texture_encoder,
                                       texture_tile=4 if texture_encoder == "hidden" else 0, **SMALL)).eval()
    positions, normals = torch.rand(2, 50, 3), torch.nn.functional.normalize(torch.randn(2, 50, 3), dim=-1)
    uvs, texture = torch.rand(2, 50, 2), torch.rand(2, 3, 32, 32)
    mask = torch.ones(2, 50)
    mask[1, 40:] = 0
    message = torch.randint(0, 2, (2, 8)).float()
    with torch.no_grad():
        new_normals, new_uvs, new_texture = model.embed(positions, normals, uvs, texture, message, mask)
    assert new_texture.shape == texture.shape and 0 <= float(new_texture.min()) and float(new_texture.max()) <= 1
    assert torch.allclose(new_normals.norm(dim=-1), torch.ones(2, 50), atol=1e-5)
    if "vertex" in strategy:
        assert (new_uvs - uvs).abs().max() <= model.config.uv_strength + 1e-6
        assert torch.equal(new_normals[1, 40:], normals[1, 40:])  # padded vertices untouched
    else:
        assert torch.equal(new_normals, normals) and torch.equal(new_uvs, uvs)
    if "texture" in strategy:
        assert (new_texture - texture).abs().max() <= model.config.texture_strength + 1e-6
        assert not torch.equal(new_texture, texture)


def test_texture_encoder_any_size_and_aspect():
    model = WatermarkModel(ModelConfig(n_bits=8, texture_tile=4, texture_downsample=2, **SMALL)).eval()
    for shape in ((1, 3, 32, 32), (1, 3, 77, 200), (1, 3, 512, 256)):
        texture = torch.rand(*shape)
        marked = model.texture_encoder(texture, torch.ones(1, 8))
        assert marked.shape == texture.shape


@pytest.mark.parametrize("decoder,head_grid", [("hidden", 0), ("hidden", 4), ("simple", 0), ("residual", 0)])
@pytest.mark.parametrize("stem", [1, 2, 4])
def test_decoders_take_any_image_size(decoder, stem, head_grid):
    model = WatermarkModel(ModelConfig(n_bits=12, decoder=decoder, decoder_stem_stride=stem,
                                       decoder_head_grid=head_grid, **SMALL)).eval()
    for size in ((32, 32), (57, 91), (128, 64)):
        assert model.decode(torch.rand(2, 3, *size)).shape == (2, 12)


def test_vertex_encoder_any_vertex_count_and_pooling_variants():
    for encoder in ("pointnet", "pointnet2"):
        model = WatermarkModel(ModelConfig(n_bits=4, strategy="vertex", vertex_encoder=encoder, **SMALL)).eval()
        for n in (3, 1000):
            normals, uvs = model.vertex_encoder(torch.rand(1, n, 3), torch.rand(1, n, 3), torch.rand(1, n, 2),
                                                torch.ones(1, 4))
            assert normals.shape == (1, n, 3) and uvs.shape == (1, n, 2)


def test_bad_config_is_refused():
    with pytest.raises(ValueError):
        ModelConfig.from_dict({"n_bits": 8, "strategy": "everything"})
    with pytest.raises(ValueError):
        ModelConfig.from_dict({"no_such_setting": 1})


def test_weights_round_trip_without_pickle(tmp_path):
    model = WatermarkModel(ModelConfig(n_bits=8, **SMALL)).eval()
    path = tmp_path / "m.safetensors"
    save_model(model, path)
    loaded = load_model(path)
    image = torch.rand(1, 3, 32, 32)
    assert torch.allclose(model.decode(image), loaded.decode(image))
    (tmp_path / "bad.safetensors").write_bytes(b"not a model")
    with pytest.raises(MeshsealError):
        load_model(tmp_path / "bad.safetensors")
    with pytest.raises(MeshsealError):
        load_model(tmp_path / "missing.safetensors")


def test_jpeg_approximation_is_close_to_real_jpeg_and_differentiable():
    rng = np.random.default_rng(0)
    smooth = np.clip(np.cumsum(np.cumsum(rng.normal(0, 0.02, (64, 64, 3)), 0), 1) + 0.5, 0, 1)
    image = torch.tensor(smooth, dtype=torch.float32).permute(2, 0, 1)[None].requires_grad_()
    approx = jpeg(image, 75)
    buffer = io.BytesIO()
    Image.fromarray((smooth * 255 + 0.5).astype(np.uint8)).save(buffer, "JPEG", quality=75, subsampling=0)
    real = torch.tensor(np.asarray(Image.open(buffer)), dtype=torch.float32).permute(2, 0, 1)[None] / 255
    mse = float(((approx.detach() - real) ** 2).mean())
    assert 10 * np.log10(1 / mse) > 35
    approx.sum().backward()
    assert image.grad is not None and float(image.grad.abs().sum()) > 0


def test_distortions_keep_shapes_and_gradients():
    generator = torch.Generator().manual_seed(0)
    image = torch.rand(2, 3, 40, 40, requires_grad=True)
    attacks = Distortions2D(1.0)
    for name in attacks.attacks:
        out = attacks.apply(name, image, generator)
        assert out.shape == image.shape
        if name != "identity":
            assert not torch.equal(out, image)
    positions = torch.rand(2, 30, 3, requires_grad=True)
    normals = torch.nn.functional.normalize(torch.randn(2, 30, 3), dim=-1)
    faces = torch.randint(0, 30, (2, 40, 3))
    rotated, turned = random_rotation(positions, normals, 1.0, generator)
    assert torch.allclose(rotated.norm(dim=-1), positions.norm(dim=-1), atol=1e-5)
    cropped = random_crop_faces(positions, faces, 1.0, generator)
    removed = (cropped == 0).all(-1).float().mean()
    assert float(removed) <= 0.25
    p, n, f = Distortions3D(1.0, 1, 1, 1, 1)(positions, normals, faces, generator)
    p.sum().backward()
    assert positions.grad is not None


def test_boxes_of_a_batch_each_fit_their_own_mask():
    masks = torch.zeros(3, 40, 60, dtype=torch.bool)
    masks[0, 10:20, 5:45] = True  # wide: the side is the width plus margins
    masks[2, 30, 50] = True  # one pixel: the smallest box
    boxes = boxes_from_mask(masks, margin=0.1)
    assert torch.allclose(boxes[0], torch.tensor([25.0, 15.0, 24.0]))
    assert torch.allclose(boxes[1], torch.tensor([30.0, 20.0, 30.0]))  # empty: the whole picture
    assert torch.allclose(boxes[2], torch.tensor([50.5, 30.5, 4.0]))


def test_framing_finds_the_object_and_crops_square():
    picture = np.full((200, 300, 3), 0.9, dtype=np.float32)
    picture[50:110, 120:200] = 0.2
    mask, background = object_mask(picture)
    assert np.allclose(background, 0.9)
    box = boxes_from_mask(torch.from_numpy(mask)[None])[0]
    assert abs(float(box[0]) - 160) < 1.5 and abs(float(box[1]) - 80) < 1.5
    framed = crop_boxes(torch.from_numpy(picture).permute(2, 0, 1)[None], box[None], 64,
                        torch.tensor([[0.9, 0.9, 0.9]]))
    assert framed.shape == (1, 3, 64, 64)
    centre = framed[0, :, 28:36, 28:36]
    assert torch.allclose(centre, torch.full_like(centre, 0.2), atol=1e-4)
    assert torch.allclose(framed[0, :, 0, 0], torch.tensor([0.9, 0.9, 0.9]), atol=1e-4)


def test_a_batch_frames_each_picture_as_it_would_be_framed_alone():
    """A large object beside a small one: the small one keeps its detail (no shrink by the batch's largest box)."""
    generator = torch.Generator().manual_seed(0)
    pictures = torch.rand(2, 3, 240, 320, generator=generator)
    boxes = torch.tensor([[160.0, 120.0, 110.0], [100.0, 90.0, 40.0]])  # sides 220 and 80 px, framed to 64
    together = crop_boxes(pictures, boxes, 64)
    alone = torch.cat([crop_boxes(pictures[i:i + 1], boxes[i:i + 1], 64) for i in range(2)])
    assert torch.allclose(together, alone, atol=1e-6)
    assert float(together[1].std()) > 0.15  # shrunk as the 220 px box would be, the noise averages out (std about 0.06)


def test_fixed_power_mark_has_the_configured_rms():
    config = ModelConfig.from_dict(dict(SMALL, n_bits=8, texture_rms=0.05, texture_tile=4))
    model = WatermarkModel(config).eval()
    texture = torch.full((2, 3, 64, 48), 0.5)  # mid grey: nothing is clipped
    message = torch.randint(0, 2, (2, 8), generator=torch.Generator().manual_seed(0)).float()
    with torch.no_grad():
        marked = model.texture_encoder(texture, message)
    rms = (marked - texture).pow(2).mean(dim=(1, 2, 3)).sqrt()
    assert torch.allclose(rms, torch.tensor([0.05, 0.05]), rtol=0.1)
    with torch.no_grad():
        other = model.texture_encoder(texture, 1 - message)
    assert float((other - marked).abs().mean()) > 0.01  # the pattern carries the message


def test_fixed_power_after_clip_holds_the_rms_on_saturated_textures():
    texture = torch.full((2, 3, 64, 64), 0.98)
    texture[:, :, :, 32:] = 0.0  # half near white, half black: most of a raw residual is clipped away
    message = torch.randint(0, 2, (2, 8), generator=torch.Generator().manual_seed(0)).float()
    kept = {}
    for after_clip in (False, True):
        torch.manual_seed(0)
        config = ModelConfig.from_dict(dict(SMALL, n_bits=8, texture_rms=0.05, texture_rms_after_clip=after_clip))
        model = WatermarkModel(config).eval()
        with torch.no_grad():
            marked = model.texture_encoder(texture, message)
        kept[after_clip] = (marked - texture).pow(2).mean(dim=(1, 2, 3)).sqrt()
    assert bool((kept[False] < 0.04).all())  # the raw rescale loses power to clipping
    assert torch.allclose(kept[True], torch.tensor([0.05, 0.05]), rtol=0.1)


def test_hidden_encoder_coords_and_fsk_keying():
    """texture_coords makes the mark depend on where a texel sits (the same texture content at two
    places gets two different residuals); fsk keys the carrier by each bit's value, so flipping one
    bit swaps in another pattern rather than negating it."""
    torch.manual_seed(0)
    flat = torch.full((1, 3, 32, 32), 0.5)
    message = torch.tensor([[1.0, 0, 1, 1, 0, 0, 1, 0]])
    plain = WatermarkModel(ModelConfig(n_bits=8, **SMALL)).eval().texture_encoder
    placed = WatermarkModel(ModelConfig(n_bits=8, texture_coords=True, **SMALL)).eval().texture_encoder
    with torch.no_grad():
        residual_plain = plain.residual(flat, message)
        residual_placed = placed.residual(flat, message)
    interior = (slice(None), slice(None), slice(6, -6), slice(6, -6))  # beyond the reach of zero padding
    assert residual_plain[interior].std(dim=(2, 3)).max() < 1e-5  # a flat texture: nothing says where a texel is
    assert residual_placed[interior].std(dim=(2, 3)).min() > 1e-3
    fsk = WatermarkModel(ModelConfig(n_bits=8, texture_tile=4, texture_tile_keying="fsk", **SMALL)).eval().texture_encoder
    assert fsk.carrier.in_features == 16
    with torch.no_grad():
        keys = torch.cat([message, 1 - message], dim=1)
        flipped = message.clone()
        flipped[0, 0] = 0
        keys_flipped = torch.cat([flipped, 1 - flipped], dim=1)
        change = fsk.carrier(keys_flipped) - fsk.carrier(keys)
        expected = fsk.carrier.weight[:, 8] - fsk.carrier.weight[:, 0]  # bit 0 leaves its 1-carrier for its 0-carrier
    assert torch.allclose(change[0], expected, atol=1e-5)
    with pytest.raises(ValueError, match="keying"):
        WatermarkModel(ModelConfig(n_bits=8, texture_tile=4, texture_tile_keying="qam", **SMALL))
