"""Reading a picture that went through JPEG or WebP: the prediction saved through the picture's codec
(`reading.compression`) takes the codec's own error on the host off the residual, and a grey mark read
that way survives the lossy formats the blue-yellow one does not."""

import numpy as np
import torch
from PIL import Image

from meshseal.evaluation.attacks import apply
from meshseal.mesh import load, normalize, to_z_up
from meshseal.methods.spread import spread_evidence
from meshseal.models import ModelConfig, WatermarkModel
from meshseal.models.spread import soft_bits
from meshseal.reading.compression import recompressed
from meshseal.render import MeshBatch, MeshRenderer
from meshseal.render.views import sample_views

from test_spread import FIXTURES, _quantise

GREY = ModelConfig(n_bits=64, texture_encoder="spread", decoder="matched", mark_colour="grey", texture_psnr=34.0,
                   read_highpass=3.0, read_window=3.0, read_brightness=-1.0)


def _scene(seed: int = 0):
    """A smooth random picture (1, 3, H, W), its object's pixel indices and an 8-bit copy as uint8."""
    generator = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 3, 8, 8, generator=generator)
    picture = torch.nn.functional.interpolate(coarse, size=(64, 64), mode="bicubic", align_corners=False)
    picture = (picture + 0.05 * torch.rand(1, 3, 64, 64, generator=generator)).clamp(0, 1)
    pixel = torch.arange(16 * 64 + 16, 48 * 64, 1)[(torch.arange(16 * 64 + 16, 48 * 64) % 64 >= 16)
                                                  & (torch.arange(16 * 64 + 16, 48 * 64) % 64 < 48)]
    uint8 = (picture[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    return picture, pixel, uint8


def test_the_codec_that_saved_a_picture_is_found_and_a_lossless_one_left_alone():
    _, pixel, uint8 = _scene()
    exact = torch.from_numpy(uint8.reshape(-1, 3)[pixel.numpy()].astype(np.float32) / 255.0)
    rng = np.random.default_rng(0)
    # JPEG's blocks are coded alone: its error is reproduced almost exactly; WebP predicts each block from
    # its neighbours, so only part of its error is
    for attack, codec, left in (("jpeg90", ("JPEG", 90, 2), 0.05), ("jpeg75", ("JPEG", 75, 2), 0.05),
                                ("webp80", ("WEBP", 80, None), 0.6), ("none", None, 1.0)):
        saved = apply(attack, uint8, rng)
        picture = torch.from_numpy(saved).permute(2, 0, 1)[None].float() / 255.0
        seen = picture[0].permute(1, 2, 0).reshape(-1, 3)[pixel]
        predicted, chosen = recompressed(picture, exact, pixel)
        assert chosen == [codec], attack
        before, after = float(((seen - exact) ** 2).mean()), float(((seen - predicted) ** 2).mean())
        assert after <= left * before, (attack, before, after)


def _renders(config: ModelConfig):
    model = WatermarkModel(config)
    mesh = normalize(to_z_up(load(FIXTURES / "bunny.glb")))
    message = torch.randint(0, 2, (1, 64), generator=torch.Generator().manual_seed(3)).float()
    texture = mesh.materials[0].texture.permute(2, 0, 1)[None]
    original, marked = MeshBatch.from_mesh(mesh), MeshBatch.from_mesh(mesh)
    marked.textures = [model.texture_encoder(texture, message, 1.0)[0]]
    cameras, lights = sample_views(2, "seed", torch.Generator().manual_seed(1))
    with torch.no_grad():
        pictures = {name: _quantise(MeshRenderer()(batch, cameras, lights, 256, 256, (0.5, 0.5, 0.5)).image)
                    for name, batch in (("marked", marked), ("clean", original))}
    return model, message, original, cameras, pictures


def _jpeg(pictures: torch.Tensor, attack: str) -> torch.Tensor:
    rng = np.random.default_rng(0)
    out = [torch.from_numpy(apply(attack, (p.permute(1, 2, 0).numpy() * 255).round().astype(np.uint8), rng))
           for p in pictures]
    return torch.stack(out).permute(0, 3, 1, 2).float() / 255.0


def test_a_grey_mark_read_through_the_codec_survives_jpeg_and_the_null_holds():
    model, message, original, cameras, pictures = _renders(GREY)
    signs = 2 * message - 1
    for attack in ("jpeg90", "jpeg75"):
        saved = _jpeg(pictures["marked"], attack)
        with torch.no_grad():
            read = soft_bits(model.texture_encoder, spread_evidence(model, original, saved, cameras))
            plain = soft_bits(model.texture_encoder, spread_evidence(model, original, saved, cameras, compression=False))
        agree = ((read > 0).float() == message).float().mean(1)
        assert float(agree.min()) >= 0.9, (attack, agree)
        assert float((read * signs).mean()) > float((plain * signs).mean()), attack  # the codec's error taken off
    # no mark: the codec is chosen without the key, so z under many keys stays N(0, 1)
    clean = _jpeg(pictures["clean"], "jpeg75")
    with torch.no_grad():
        sums = spread_evidence(model, original, clean, cameras)
    z = torch.cat([soft_bits(model.texture_encoder, sums, key) for key in range(40)])
    assert abs(float(z.mean())) < 0.08 and 0.9 < float(z.std()) < 1.1


def test_a_picture_file_saved_as_jpeg_reads_its_mark(tmp_path, capsys):
    """The shipped default (a luminance mark at texture PSNR 40 dB; `robust` is the same mark and
    reading at 34 dB) reads its own mark from a JPEG without metadata (registered), from the command line."""
    from meshseal.cli import main

    model = "default"

    marked = tmp_path / "m.glb"
    assert main(["embed", str(FIXTURES / "bunny.glb"), "-o", str(marked), "--message", "ab42", "--model",
                 model, "--views", "1"]) == 0
    assert main(["render", str(marked), "-o", str(tmp_path / "v.png"), "--width", "256", "--height", "256",
                 "--seed", "2"]) == 0
    Image.open(tmp_path / "v.png").convert("RGB").save(tmp_path / "v.jpg", quality=85)  # no metadata: registered
    capsys.readouterr()
    assert main(["detect", str(tmp_path / "v.jpg"), "--mesh", str(FIXTURES / "bunny.glb"), "--model", model]) == 0
    assert 'detected "ab42"' in capsys.readouterr().out


def test_a_picture_file_says_which_codecs_to_try(tmp_path):
    from meshseal.reading.compression import CODECS
    from meshseal.reading.pictures import CAMERA_KEY, load_picture_and_codecs

    _, _, uint8 = _scene()
    picture = Image.fromarray(uint8)
    for options, codecs in (({"quality": 75}, [("JPEG", 75, 2)]), ({"quality": 95, "subsampling": 0}, [("JPEG", 95, 0)]),
                            ({"quality": 92, "subsampling": 0}, None)):  # tables of an unlisted quality: search
        picture.save(tmp_path / "p.jpg", **options)
        assert load_picture_and_codecs(tmp_path / "p.jpg")[3] == codecs, options
        assert codecs is None or codecs[0] in CODECS
    from PIL.PngImagePlugin import PngInfo

    picture.save(tmp_path / "plain.png")
    assert load_picture_and_codecs(tmp_path / "plain.png")[3] is None  # a PNG may hold a decoded JPEG: search
    info = PngInfo()
    info.add_text(CAMERA_KEY, "{}")
    picture.save(tmp_path / "rendered.png", pnginfo=info)
    assert load_picture_and_codecs(tmp_path / "rendered.png")[3] == []  # meshseal render's: lossless
    picture.save(tmp_path / "p.webp", quality=80)
    assert load_picture_and_codecs(tmp_path / "p.webp")[3] is None
    assert load_picture_and_codecs(uint8)[3] is None


def test_codecs_a_file_gives_are_the_only_ones_tried(monkeypatch):
    import meshseal.reading.compression as compression

    _, pixel, uint8 = _scene()
    exact = torch.from_numpy(uint8.reshape(-1, 3)[pixel.numpy()].astype(np.float32) / 255.0)
    saved = apply("jpeg75", uint8, np.random.default_rng(0))
    tried = []
    real = compression._codec_round_trip
    monkeypatch.setattr(compression, "_codec_round_trip", lambda p, codec: tried.append(codec) or real(p, codec))
    searched, chosen = recompressed(torch.from_numpy(saved).permute(2, 0, 1)[None].float() / 255.0, exact, pixel)
    assert chosen == [("JPEG", 75, 2)] and len(tried) == len(compression.CODECS)
    tried.clear()
    picture = torch.from_numpy(saved).permute(2, 0, 1)[None].float() / 255.0
    compression.expect(picture, [[("JPEG", 75, 2)]])
    told, chosen = recompressed(picture, exact, pixel)
    assert chosen == [("JPEG", 75, 2)] and tried == [("JPEG", 75, 2)] and torch.equal(told, searched)
    tried.clear()
    lossless = torch.from_numpy(uint8).permute(2, 0, 1)[None].float() / 255.0
    compression.expect(lossless, [[]])
    kept, chosen = recompressed(lossless, exact, pixel)
    assert chosen == [None] and tried == [] and torch.equal(kept, exact)


def test_a_jpeg_read_first_under_a_poor_prediction_is_searched_again_and_a_lossless_picture_is_not(monkeypatch):
    """A registered picture is read first under its registered camera, then (a second look) under
    others on the same tensor. Where the first prediction was too far off for a codec to beat the
    margin, yet one came closer to the picture than none, the next reading searches again (and finds
    the JPEG under a good prediction); a lossless picture read under a good prediction, whose
    candidates only add error there, stays decided: the next reading tries nothing."""
    import meshseal.reading.compression as compression

    _, pixel, uint8 = _scene()
    exact = torch.from_numpy(uint8.reshape(-1, 3)[pixel.numpy()].astype(np.float32) / 255.0)
    shifted = np.roll(uint8, 1, axis=1).reshape(-1, 3)[pixel.numpy()]  # the scene a pixel off, as an off camera's
    poor = torch.from_numpy(shifted.astype(np.float32) / 255.0)
    tried = []
    real = compression._codec_round_trip
    monkeypatch.setattr(compression, "_codec_round_trip", lambda p, codec: tried.append(codec) or real(p, codec))
    picture = torch.from_numpy(apply("jpeg75", uint8, np.random.default_rng(0))).permute(2, 0, 1)[None].float() / 255.0
    _, chosen = recompressed(picture, poor, pixel)
    assert chosen == [None] and len(tried) == len(compression.CODECS)  # the first prediction: no codec taken
    tried.clear()
    _, chosen = recompressed(picture, exact, pixel)
    assert chosen == [("JPEG", 75, 2)] and len(tried) == len(compression.CODECS)  # searched again: found
    tried.clear()
    _, chosen = recompressed(picture, poor, pixel)
    assert chosen == [None] and tried == [("JPEG", 75, 2)]  # found once: only that one tried since
    tried.clear()
    lossless = torch.from_numpy(uint8).permute(2, 0, 1)[None].float() / 255.0
    kept, chosen = recompressed(lossless, exact, pixel)
    assert chosen == [None] and len(tried) == len(compression.CODECS) and torch.equal(kept, exact)
    tried.clear()
    kept, chosen = recompressed(lossless, poor, pixel)
    assert chosen == [None] and tried == [] and torch.equal(kept, poor)  # decided: nothing tried again


def test_a_rendered_png_reads_as_the_full_codec_search_reads_it_without_any_codec(tmp_path, monkeypatch):
    import meshseal
    import meshseal.reading.compression as compression
    from meshseal.cli import main
    from meshseal.reading.pictures import camera_from_metadata, load_picture

    marked = tmp_path / "m.glb"
    assert main(["embed", str(FIXTURES / "bunny.glb"), "-o", str(marked), "--message", "ab42", "--views", "0"]) == 0
    assert main(["render", str(marked), "-o", str(tmp_path / "v.png"), "--width", "128", "--height", "128"]) == 0
    watermarker = meshseal.load()
    original = watermarker.original(FIXTURES / "bunny.glb")
    pixels, _, text = load_picture(tmp_path / "v.png")
    searched = watermarker.decide([watermarker.read(pixels, original, camera=camera_from_metadata(text, "cpu"))])
    tried = []
    real = compression._codec_round_trip
    monkeypatch.setattr(compression, "_codec_round_trip", lambda p, codec: tried.append(codec) or real(p, codec))
    found = watermarker.detect(tmp_path / "v.png", original)
    assert tried == [] and found.message == "ab42"
    assert (found.bits, found.p_value, found.soft) == (searched.bits, searched.p_value, searched.soft)


def test_a_jpegs_quantiser_says_more_of_a_grey_mark_than_its_residual_and_nothing_of_a_resized_jpeg():
    from scipy.ndimage import gaussian_filter

    from meshseal.reading.compression import _codec_round_trip, dequantized_luma, jpeg_luma_table

    rng = np.random.default_rng(0)
    host = gaussian_filter(np.clip(0.5 + 0.2 * rng.standard_normal((96, 96, 3)), 0, 1), (1.0, 1.0, 0))
    mark = rng.choice([-1.0, 1.0], (48, 48)).repeat(2, 0).repeat(2, 1) * 1.5 / 255  # 2-px cells, +-1.5 levels
    marked = (np.clip(host + mark[..., None], 0, 1) * 255).round().astype(np.uint8)
    for quality in (90, 75, 50):
        codec = ("JPEG", quality, 2)
        saved = _codec_round_trip(marked, codec).astype(np.float64) / 255
        residual = (saved - _codec_round_trip((host * 255).round().astype(np.uint8), codec) / 255).mean(2)
        estimate = dequantized_luma(saved, host, jpeg_luma_table(codec), 2.0)
        cosine = lambda r: float((r * mark).sum() / np.linalg.norm(r) / np.linalg.norm(mark))  # noqa: E731
        assert cosine(estimate) > 1.15 * cosine(residual) > 0.2
        # No key in it: the estimate of a picture without the mark carries none of it.
        clean = _codec_round_trip((host * 255).round().astype(np.uint8), codec).astype(np.float64) / 255
        assert abs(cosine(dequantized_luma(clean, host, jpeg_luma_table(codec), 2.0))) < 0.05
    resized = Image.fromarray((saved * 255).round().astype(np.uint8)).resize((80, 80)).resize((96, 96))
    assert dequantized_luma(np.asarray(resized) / 255.0, host, jpeg_luma_table(codec), 2.0) is None
    assert jpeg_luma_table(("WEBP", 80, None)) is None


def test_a_jpeg_file_of_an_unlisted_quality_is_read_through_its_own_steps(tmp_path, monkeypatch):
    """JPEG 92 4:4:4 is none of the searched codecs: the quantiser read uses the file's own luminance
    steps (`pictures.file_luma_table`), which the picture's coefficients sit on."""
    from meshseal.reading import compression
    from meshseal.reading.pictures import load_picture_and_codecs

    rng = np.random.default_rng(1)
    pixels = (np.clip(0.5 + 0.2 * rng.standard_normal((64, 64, 3)), 0, 1) * 255).astype(np.uint8)
    Image.fromarray(pixels).save(tmp_path / "p.jpg", quality=92, subsampling=0)
    with Image.open(tmp_path / "p.jpg") as saved:
        steps = np.asarray(saved.quantization[0], dtype=np.float64).reshape(8, 8)
    loaded = load_picture_and_codecs(tmp_path / "p.jpg")
    assert loaded[3] is None and np.array_equal(loaded[4], steps)  # searched, but its steps known
    assert load_picture_and_codecs(pixels)[4] is None
    image = torch.from_numpy(loaded[0]).permute(2, 0, 1)[None].clone()
    pixel = torch.arange(16 * 64, 48 * 64)
    expected = image[0].permute(1, 2, 0).reshape(-1, 3)[pixel]
    seen = []
    monkeypatch.setattr(compression, "dequantized_luma", lambda *a: seen.append(a[2]) or np.zeros((64, 64)))
    compression.expect_luma(image, [steps])
    assert compression.dequantized(image, expected, pixel, [("JPEG", 90, 0)]) is not None
    assert np.array_equal(seen[0], steps)
    assert compression.dequantized(image.clone(), expected, pixel, [None]) is None  # no file steps, no JPEG found


def test_a_jpeg_pasted_at_another_place_is_found_where_its_blocks_start_and_read_there():
    """A JPEG shown on a page and captured in a screenshot: its 8 x 8 grid starts at the paste's offset
    (mod 8). `jpeg_phase` finds it (and (0, 0) for the JPEG itself and for a lossless picture);
    `recompressed` then finds the codec that saved it, and the quantiser read sees its steps."""
    from scipy.ndimage import gaussian_filter

    from meshseal.reading.compression import _codec_round_trip, dequantized_luma, jpeg_luma_table, jpeg_phase

    rng = np.random.default_rng(1)
    host = gaussian_filter(np.clip(0.5 + 0.25 * rng.standard_normal((96, 128, 3)), 0, 1), (1.0, 1.0, 0))
    lossless = (host * 255).round().astype(np.uint8)
    codec = ("JPEG", 75, 2)
    saved = _codec_round_trip(lossless, codec)
    assert jpeg_phase(lossless) == (0, 0) and jpeg_phase(saved) == (0, 0)
    canvas = np.full((160, 200, 3), 236, dtype=np.uint8)
    canvas[29:29 + 96, 43:43 + 128] = saved  # a screenshot: the picture pasted at (29, 43)
    assert jpeg_phase(canvas) == (5, 3)
    shot = np.full((160, 200, 3), 236, dtype=np.uint8)
    shot[29:29 + 96, 43:43 + 128] = lossless  # the prediction, pasted where the picture is
    ys, xs = np.mgrid[29 + 8:29 + 88, 43 + 8:43 + 120]
    pixel = torch.from_numpy((ys * 200 + xs).reshape(-1))
    picture = torch.from_numpy(canvas).permute(2, 0, 1)[None].float() / 255.0
    exact = torch.from_numpy(shot.reshape(-1, 3)[pixel.numpy()].astype(np.float32) / 255.0)
    _, chosen = recompressed(picture, exact, pixel)
    assert chosen == [codec]
    table = jpeg_luma_table(codec)
    assert dequantized_luma(canvas / 255.0, shot / 255.0, table, 2.0) is None  # read on the picture's own grid: off
    assert dequantized_luma(canvas / 255.0, shot / 255.0, table, 2.0, phase=(5, 3)) is not None
