"""The spread-spectrum mark: invisible by the numbers, read back by the matched filter with the camera
known, and no mark found where there is none."""

import json
import math
import sys
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from meshseal.cli import main
from meshseal.mesh import load, normalize, to_z_up
from meshseal.models import ModelConfig, WatermarkModel
from meshseal.models.spread import texels_used
from meshseal.methods import read_bits
from meshseal.render.views import sample_views
from meshseal.render import MeshBatch, MeshRenderer

FIXTURES = Path(__file__).parent / "fixtures"

SPREAD = ModelConfig(n_bits=64, texture_encoder="spread", decoder="matched")


def _marked_and_original(strength: float = 1.0, config: ModelConfig = SPREAD):
    model = WatermarkModel(config)
    mesh = normalize(to_z_up(load(FIXTURES / "bunny.glb")))
    message = torch.randint(0, 2, (1, 64), generator=torch.Generator().manual_seed(3)).float()
    texture = mesh.materials[0].texture.permute(2, 0, 1)[None]
    marked_texture = model.texture_encoder(texture, message, strength)
    return model, mesh, message, texture, marked_texture


def _quantise(pictures: torch.Tensor) -> torch.Tensor:
    """8-bit values, as saved pictures have."""
    return torch.round(pictures.clamp(0, 1) * 255) / 255


def _original_and_marked_batches(config: ModelConfig = SPREAD):
    """The bunny, original and marked (strength 1): model, message, original batch, marked batch."""
    model, mesh, message, _, marked_texture = _marked_and_original(config=config)
    marked = MeshBatch.from_mesh(mesh)
    marked.textures = [marked_texture[0]]
    return model, message, MeshBatch.from_mesh(mesh), marked


def test_mark_strength_sets_the_texture_psnr():
    for strength, target in ((1.0, 40.0), (2.0, 40.0 - 20 * 0.30103)):
        _, _, _, texture, marked = _marked_and_original(strength)
        psnr = 10 * torch.log10(1 / ((marked - texture) ** 2).mean())
        assert abs(float(psnr) - target) < 0.3, (strength, float(psnr))


def test_matched_filter_reads_the_mark_and_finds_none_in_the_original():
    model, message, original, marked = _original_and_marked_batches()
    cameras, lights = sample_views(3, "seed", torch.Generator().manual_seed(0))
    with torch.no_grad():
        seen_marked = _quantise(MeshRenderer()(marked, cameras, lights, 256, 256).image)
        seen_clean = _quantise(MeshRenderer()(original, cameras, lights, 256, 256).image)
    z_marked = torch.cat([read_bits(model, original, seen_marked[[i]], cameras[[i]]) for i in range(3)])
    z_clean = torch.cat([read_bits(model, original, seen_clean[[i]], cameras[[i]]) for i in range(3)])
    assert ((z_marked > 0).float() == message).float().mean() >= 0.97
    signed = z_marked * (2 * message - 1)
    assert signed.mean() > 1.5  # every bit well clear of the noise
    # No mark: the soft bits look like N(0, 1), far from the marked ones.
    assert abs(float(z_clean.mean())) < 0.35 and 0.7 < float(z_clean.std()) < 1.3


def test_the_preview_has_a_labelled_row_per_material_texture(tmp_path):
    """A multi-material mesh: one row per textured material and one render, labels above them."""
    import numpy as np
    from PIL import Image

    from meshseal.evaluation.reports import write_preview
    from meshseal.mesh import load

    original = load(FIXTURES / "multi_material.glb")
    marked = original.copy()
    textured = [m for m in marked.materials if m.texture is not None]
    assert len(textured) >= 2
    for material in textured:
        material.texture = (material.texture + 0.1).clamp(0, 1)
    render = torch.full((3, 64, 64), 0.5)
    write_preview(tmp_path / "sheet.png", original, marked, (render, render))
    with Image.open(tmp_path / "sheet.png") as image:
        sheet = np.asarray(image.convert("L")).astype(int)
    rows = len(textured) + 1
    assert sheet.shape == (18 + rows * (18 + 256), 3 * 256 + 2 * 6)
    for top in [0] + [18 + row * (18 + 256) for row in range(rows)]:  # column labels, each row's label
        band = sheet[top:top + 18]  # dark text on white
        assert band.min() < 100 and np.median(band) == 255, top
    first = sheet[36:36 + 256]
    assert first[:, 256 + 6:2 * 256 + 6].mean() > first[:, :256].mean()  # marked (brighter here) | original


def test_embed_reports_object_pixel_visibility_and_writes_a_preview(tmp_path, capsys, monkeypatch):
    bits = "01" * 32
    monkeypatch.setattr(sys.stderr, "isatty", lambda: True)  # on a terminal: stage lines on stderr
    assert main(["embed", str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "b.glb"), "--bits", bits,
                 "--views", "1", "--max-flip", "0.05", "--json", "--preview", str(tmp_path / "sheet.png")]) == 0
    captured = capsys.readouterr()
    report = json.loads(captured.out)  # stdout: the one JSON object
    stages = [line for line in captured.err.splitlines() if line.startswith("meshseal: [")]
    assert [line.split("] ")[1].split()[0] for line in stages] == ["loading", "marking", "writing", "measuring",
                                                                  "writing"], captured.err
    monkeypatch.undo()
    assert report["strength"] == 1.0  # within this budget
    assert 39.8 < report["psnr_texture_shown"] < 40.2 and report["cells"] == 64  # the default's own grid on the bunny
    assert report["psnr_texture"] > report["psnr_texture_shown"]  # texels no face shows stay as they were
    assert report["psnr_object"] < report["psnr_frame"]  # the background inflates the whole-frame figure
    assert 0.0 < report["flip_object"] < 0.05 and report["ssim_object"] > 0.98
    from PIL import Image

    with Image.open(tmp_path / "sheet.png") as sheet:
        assert sheet.size == (3 * 256 + 2 * 6, 18 + 2 * (18 + 256))  # labels; the texture row, the render row
    assert main(["embed", str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "c.glb"), "--bits", bits,
                 "--views", "1", "--strength", "0"]) == 2
    assert main(["embed", str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "c.glb"), "--bits", bits,
                 "--views", "0", "--preview", str(tmp_path / "s.png")]) == 2  # a preview needs a render
    capsys.readouterr()
    assert main(["embed", str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "c.glb"), "--bits", bits,
                 "--views", "0", "--json"]) == 0  # file figures only, no renders
    report = json.loads(capsys.readouterr().out)
    assert 39.8 < report["psnr_texture_shown"] < 40.2 and "psnr_object" not in report


def test_embed_lowers_the_strength_to_keep_the_marks_flip_within_the_budget(tmp_path, capsys):
    bits = "01" * 32
    common = [str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "b.glb"), "--bits", bits, "--views", "1", "--json"]
    assert main(["embed", *common, "--max-flip", "0"]) == 0  # no budget: strength 1 as given
    loud = json.loads(capsys.readouterr().out)
    budget = round(loud["flip_object"] * 0.7, 4)  # below what strength 1 shows
    assert main(["embed", *common, "--max-flip", str(budget)]) == 0
    quiet = json.loads(capsys.readouterr().out)
    assert quiet["flip_object"] <= budget < loud["flip_object"] and quiet["max_flip"] == budget
    assert 0.5 <= quiet["strength"] < 1.0 and quiet["strength_asked"] == 1.0
    assert quiet["psnr_texture_shown"] > loud["psnr_texture_shown"] + 1.0  # quieter by the figures too
    assert main(["embed", *common, "--strength", "2"]) == 0  # a strength given is used as is
    louder = json.loads(capsys.readouterr().out)
    assert louder["strength"] == 2.0 and louder["max_flip"] is None and louder["flip_object"] > loud["flip_object"]
    assert main(["embed", *common, "--max-flip", "0.001"]) == 0  # out of reach: the floor, with a warning
    floored = capsys.readouterr()
    assert json.loads(floored.out)["strength"] == 0.5 and "above the budget" in floored.err
    assert main(["embed", *common[:-3], "--views", "0", "--max-flip", "0.03"]) == 2  # nothing to measure it in
    assert main(["embed", *common, "--max-flip", "2"]) == 2


def test_a_flip_budget_lowers_the_strength_by_the_power_law_and_keeps_it_where_nothing_is_seen():
    from meshseal.evaluation.metrics import MIN_STRENGTH, strength_within

    tried = []
    flip_at = lambda s: (tried.append(s), 0.0311 * s ** 0.7)[1]  # noqa: E731 (the teapot's curve)
    marked, strength, flip = strength_within(lambda s: s, flip_at, 1.0, 0.03)  # "marked" is its strength here
    assert 0.9 < strength < 1.0 and 0.029 < flip <= 0.03 and marked == strength and len(tried) == 2
    _, strength, flip = strength_within(lambda s: s, flip_at, 1.0, 0.001)  # out of reach: the floor
    assert strength == MIN_STRENGTH and flip > 0.001
    _, strength, _ = strength_within(lambda s: s, lambda _: float("nan"), 1.0, 0.03)  # no object pixel in any view
    assert strength == 1.0


def test_texels_used_are_the_ones_faces_cover_wrapped_with_their_neighbours():
    quad = torch.tensor([[0.0, 0.0], [0.5, 0.0], [0.5, 1.0], [0.0, 1.0]])  # the left half of the UV square
    used = texels_used(quad, torch.tensor([[0, 1, 2], [0, 2, 3]]), 16, 16)
    assert used[:, :10].all() and not used[:, 10:15].any()  # 8 columns, the one its edge touches, a neighbour
    assert used[:, 15].all()  # ... on both sides: a repeating texture wraps
    shifted = texels_used(quad + torch.tensor([2.0, -3.0]), torch.tensor([[0, 1, 2], [0, 2, 3]]), 16, 16)
    assert torch.equal(shifted, used)
    line = torch.tensor([[0.1, 0.5], [0.9, 0.5], [0.5, 0.5]])  # a face whose UVs lie on a line
    on_line = texels_used(line, torch.tensor([[0, 1, 2]]), 16, 16)
    assert on_line[7:10, 2:14].all() and int(on_line.sum()) < 16 * 5
    huge = texels_used(quad * 5, torch.tensor([[0, 1, 2]]), 16, 16)
    assert huge.all()


def test_the_mark_lies_on_the_texels_shown_at_the_target_psnr_there():
    model = WatermarkModel(SPREAD)
    texture = torch.rand(1, 3, 128, 128, generator=torch.Generator().manual_seed(1)) * 0.5 + 0.25
    message = torch.randint(0, 2, (1, 64), generator=torch.Generator().manual_seed(2)).float()
    used = torch.zeros(128, 128, dtype=torch.bool)
    used[:, :32] = True
    residual = model.texture_encoder(texture, message, 1.0, used=used) - texture
    assert residual[..., 32:].abs().max() == 0
    shown = 10 * torch.log10(1 / residual[..., :32].pow(2).mean())
    assert abs(float(shown) - 40.0) < 0.1  # a quarter of the texture: 6 dB quieter over all of it
    assert abs(float(10 * torch.log10(1 / residual.pow(2).mean())) - 46.02) < 0.1
    upsampled = model.texture_encoder(texture[..., :64, :64], message, 1.0, chips=128, used=used[::2, ::2]) - \
        model.texture_encoder(texture[..., :64, :64], message, 1.0, chips=128, used=None)
    assert upsampled.shape[-1] == 128  # the mask follows the texture resampled to carry the grid


def test_embed_charts_a_texture_used_as_a_palette_and_warns_where_it_cannot(tmp_path, capsys):
    from meshseal.mesh import save

    mesh = load(FIXTURES / "bunny.glb")
    mesh.uvs = torch.full_like(mesh.uvs, 0.3)  # every face shows one texel
    save(mesh, tmp_path / "palette.glb")
    assert main(["embed", str(tmp_path / "palette.glb"), "-o", str(tmp_path / "m.glb"), "--bits", "01" * 32,
                 "--views", "0"]) == 0
    err = capsys.readouterr().err
    assert "got charts of their own" in err and "warning" not in err
    tiled = mesh.uvs.clone()
    tiled[mesh.faces[0]] = torch.tensor([[1.2, 0.2], [1.6, 0.2], [1.2, 0.6]])  # past the texture's edge: a tiled map
    mesh.uvs = tiled
    save(mesh, tmp_path / "tiled.glb")
    assert main(["embed", str(tmp_path / "tiled.glb"), "-o", str(tmp_path / "t.glb"), "--bits", "01" * 32,
                 "--views", "0"]) == 0
    err = capsys.readouterr().err
    assert "of the textured surface has faces without UV area" in err and "got charts" not in err
    assert main(["embed", str(FIXTURES / "bunny.glb"), "-o", str(tmp_path / "b.glb"), "--bits", "01" * 32,
                 "--views", "0"]) == 0
    assert "palette" not in capsys.readouterr().err


def test_many_views_of_one_mesh_read_as_one_by_one():
    """Pictures of one multi-material mesh from several cameras, read in one batch (a light fitted per
    picture), give exactly the evidence of reading them one at a time."""
    from meshseal.methods.spread import spread_evidence

    model = WatermarkModel(SPREAD)
    original = MeshBatch.from_mesh(normalize(to_z_up(load(FIXTURES / "multi_material.glb"))))
    cameras, lights = sample_views(3, "seed", torch.Generator().manual_seed(0))
    with torch.no_grad():
        pictures = MeshRenderer()(original, cameras, lights, 96, 96).image
        together = spread_evidence(model, original, pictures, cameras)
        alone = torch.cat([spread_evidence(model, original, pictures[[i]], cameras[[i]]) for i in range(3)])
    assert together.abs().max() > 0 and torch.allclose(together, alone, atol=1e-6)



def test_whitening_removes_slow_misfit_and_trusts_quiet_areas_more():
    """`whiten` takes a slow ramp (relighting misfit) out of the residual, and weighs each area by its
    inverse noise variance: a mark of one amplitude under noise ten times louder in half the object
    (texture edges under a slightly wrong camera) correlates better after whitening than before."""
    from meshseal.models.spread import whiten

    generator = torch.Generator().manual_seed(0)
    size = 64
    rows, cols = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    pixel = torch.nonzero((((rows - 32).abs() < 24) & ((cols - 32).abs() < 24)).flatten()).squeeze(1)
    y, x = (pixel // size).float(), (pixel % size).float()
    centre = ((x - 32).abs() < 16) & ((y - 32).abs() < 16)
    noise = 0.01 * torch.randn(len(pixel), generator=generator)
    ramp = 0.05 + 0.01 * x + 0.005 * y
    correlation = lambda a, b: float(torch.corrcoef(torch.stack([a[centre], b[centre]]))[0, 1])  # noqa: E731
    assert correlation(noise + ramp, noise) < 0.2
    assert correlation(whiten(noise + ramp, pixel, (1, size, size)), whiten(noise, pixel, (1, size, size))) > 0.999

    mark = 0.01 * (torch.randint(0, 2, (len(pixel),), generator=generator) * 2.0 - 1.0)
    noise = torch.randn(len(pixel), generator=generator) * torch.where(x < 32, 0.01, 0.1)
    score = lambda values: float((values * mark).sum() / values.norm())  # noqa: E731 (matched filter, normalised)
    assert score(whiten(mark + noise, pixel, (1, size, size))) > 2.0 * score(mark + noise)


def test_footprint_matches_how_the_picture_sampled_the_texture():
    """A picture whose pixels average the surface over their area (Blender, game engines, a resize)
    is read with a prediction and template sampled the same way: its soft bits grow clearly, and the
    footprint found is the one that made it. A point-sampled picture (ours) is read as before."""
    import torch.nn.functional as F

    from meshseal.imaging import gaussian_blur
    from meshseal.reading.footprint import picture_footprint
    from meshseal.reading.relight import relit_residual
    from meshseal.methods.spread import spread_evidence
    from meshseal.models.spread import soft_bits

    model, message, original, marked = _original_and_marked_batches()
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(1))
    signs = 2 * message - 1
    with torch.no_grad():
        point = _quantise(MeshRenderer()(marked, cameras, lights, 128, 128).image)
        fine = MeshRenderer()(marked, cameras, lights, 512, 512).image
        area = _quantise(F.avg_pool2d(gaussian_blur(fine, 2.0), 4))  # pixel area, then a 0.5 px blur
        for picture, sigma in ((point, None), (area, 0.5)):
            found = picture_footprint(original, relit_residual(original, picture, cameras), cameras, 128, 128)
            assert (sigma is None and bool(found.sigma.isnan().all())) or float(found.sigma[0]) == sigma
        assert torch.equal(spread_evidence(model, original, point, cameras),
                           spread_evidence(model, original, point, cameras, footprint=False))
        # The footprint alone (the brightness fit absorbs part of a point prediction's misfit too).
        matched, centre = (soft_bits(model.texture_encoder, spread_evidence(model, original, area, cameras, footprint=f,
                                                                            brightness=False))
                           for f in (True, False))
    assert float((matched * signs).mean()) > 1.3 * float((centre * signs).mean())


def test_each_pixels_brightness_is_taken_off():
    """Pixels darker or brighter than the prediction on their own (a shadow; two coincident sheets, one
    lit from behind, that Blender z-fights between) leave the mark's colour where it was: the matched
    filter fits each pixel's brightness first and reads such a picture about as well as a clean one."""
    from meshseal.models.spread import soft_bits
    from meshseal.methods.spread import spread_evidence

    model, message, original, marked = _original_and_marked_batches()
    signs = 2 * message - 1
    cameras, lights = sample_views(2, "seed", torch.Generator().manual_seed(4))
    with torch.no_grad():
        clean = MeshRenderer()(marked, cameras, lights, 128, 128).image
        dark = torch.rand(2, 1, 128, 128, generator=torch.Generator().manual_seed(5)) < 0.4
        speckled = _quantise(clean * torch.where(dark, 0.35, 1.0))
        fitted, ignored = (soft_bits(model.texture_encoder, spread_evidence(model, original, speckled, cameras,
                                                                           brightness=b)) for b in (True, False))
        reference = soft_bits(model.texture_encoder, spread_evidence(model, original, _quantise(clean), cameras))
    assert float((fitted * signs).mean()) > 0.85 * float((reference * signs).mean())
    assert float((fitted * signs).mean()) > 2.0 * float((ignored * signs).mean())


def test_light_added_in_linear_light_is_taken_off_where_it_is():
    """An engine shades in linear light: noise or a highlight added there lifts a saturated colour's
    dark channel in sRGB, partly along the mark's colour. The matched filter takes that direction off
    where the residual varies along it, and reads such a picture of a saturated asset far better than
    without; on a clean picture it changes almost nothing."""
    import meshseal.reading.footprint as footprint
    from meshseal.methods.spread import spread_evidence
    from meshseal.models.spread import soft_bits

    model, mesh, message, _, _ = _marked_and_original()
    tint = torch.tensor([0.05, 0.55, 1.0])  # a saturated blue, red near black (a deck chair's stripes)
    texture = (mesh.materials[0].texture * tint).permute(2, 0, 1)[None]
    original, marked = MeshBatch.from_mesh(mesh), MeshBatch.from_mesh(mesh)
    original.textures, marked.textures = [texture[0]], [model.texture_encoder(texture, message, 1.0)[0]]
    signs = 2 * message - 1
    cameras, lights = sample_views(2, "seed", torch.Generator().manual_seed(4))
    to_linear = lambda x: torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)  # noqa: E731
    to_srgb = lambda x: torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(0) ** (1 / 2.4) - 0.055)  # noqa: E731
    with torch.no_grad():
        clean = MeshRenderer()(marked, cameras, lights, 128, 128).image
        noise = 0.06 * torch.rand(2, 1, 128, 128, generator=torch.Generator().manual_seed(5))
        noisy = _quantise(to_srgb(to_linear(clean) + noise))

        def read(picture, ratio):
            saved, footprint.LINEAR_LIGHT_RATIO = footprint.LINEAR_LIGHT_RATIO, ratio
            try:
                evidence = spread_evidence(model, original, picture, cameras)
            finally:
                footprint.LINEAR_LIGHT_RATIO = saved
            return float((soft_bits(model.texture_encoder, evidence) * signs).mean())

        taken_off, kept = read(noisy, footprint.LINEAR_LIGHT_RATIO), read(noisy, 1e9)  # 1e9: never taken off
        clean_now, clean_before = read(_quantise(clean), footprint.LINEAR_LIGHT_RATIO), read(_quantise(clean), 1e9)
    assert taken_off > 1.3 * kept
    assert clean_now > 0.95 * clean_before


def test_local_mean_averages_over_covered_pixels_only():
    from meshseal.models.spread import local_mean

    pixel = torch.tensor([0, 1, 2, 10])  # three neighbours in a row, one far away, of a 1 x 4 x 4 picture
    values = torch.tensor([[1.0, 2.0], [1.0, 2.0], [1.0, 2.0], [5.0, 0.0]])
    mean = local_mean(values, pixel, (1, 4, 4), 0.7)
    assert torch.allclose(mean[:3], torch.tensor([1.0, 2.0]).expand(3, 2), atol=0.05)
    assert torch.allclose(local_mean(values[:, 0], pixel, (1, 4, 4), 0.7), mean[:, 0])
    assert local_mean(values[:0], pixel[:0], (1, 4, 4), 0.7).shape == (0, 2)  # nothing covered: nothing to average


def test_a_picture_without_wholly_covered_pixels_reads_as_point_samples():
    """A tiny or thin object may leave no pixel that every footprint covers: nothing to compare, so
    the picture keeps point samples (this crashed on an empty reshape)."""
    from meshseal.reading.footprint import picture_footprint
    from meshseal.reading.relight import relit_residual
    from meshseal.methods.spread import spread_evidence

    model, _, original, marked = _original_and_marked_batches()
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(1))
    with torch.no_grad():
        picture = _quantise(MeshRenderer()(marked, cameras, lights, 8, 8).image)
        found = relit_residual(original, picture, cameras)
        sampled = picture_footprint(original, found, cameras, 8, 8)
        assert bool(sampled.sigma.isnan().all()) and len(sampled.expected) == len(found.keep)
        assert spread_evidence(model, original, picture, cameras).shape == (1, model.texture_encoder.chips ** 2)


def test_untextured_materials_weigh_nothing():
    """A material without a texture carries no mark: the matched filter reads nothing there (a missing
    texture samples as white, which used to give those pixels the weight of a busy texture)."""
    from dataclasses import replace

    import meshseal
    from meshseal.methods.spread import spread_evidence

    model = WatermarkModel(SPREAD)
    bunny = normalize(to_z_up(load(FIXTURES / "bunny.glb")))
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(2))
    for materials in ([bunny.materials[0]], [meshseal.Material(texture=None)]):
        original = MeshBatch.from_mesh(replace(bunny, materials=materials))
        with torch.no_grad():
            picture = MeshRenderer()(original, cameras, lights, 128, 128).image.clamp(0, 1)
            picture = (picture + 0.02 * torch.randn(picture.shape, generator=torch.Generator().manual_seed(0))).clamp(0, 1)
            evidence = spread_evidence(model, original, picture, cameras)
        assert (float(evidence.abs().max()) > 0) == (materials[0].texture is not None)


@pytest.mark.parametrize("keys", [40, pytest.param(300, marks=[pytest.mark.slow, pytest.mark.stats])])
def test_bit_weights_give_each_picture_its_own_exact_null_over_keys(keys):
    """One picture's cell evidence read under many keys: z_b is the bit's cells' sum with the key's signs
    over their norm (what `bit_weights` holds), and the exact-null p-values over keys are uniform (a KS
    test: 40 keys in the default run, 300 in the `stats` tier)."""
    from scipy import stats

    from meshseal import payload
    from meshseal.models.spread import bit_weights, soft_bits

    encoder = WatermarkModel(SPREAD).texture_encoder
    generator = torch.Generator().manual_seed(0)
    sums = torch.zeros(1, encoder.chips ** 2, dtype=torch.float64)
    seen = torch.randperm(encoder.chips ** 2, generator=generator)[:3000]  # a small object: ~47 cells a bit
    sums[0, seen] = torch.randn(3000, generator=generator, dtype=torch.float64) ** 3  # heavy-tailed evidence
    exact = []
    for key in range(keys):
        weights = bit_weights(encoder, sums, key)
        assign, _ = encoder.pattern(key)
        assert weights.shape == (1, 64, encoder.chips ** 2 // 64)
        for bit in (0, 63):
            cells = sums[0, assign == bit].abs()
            assert torch.allclose(weights[0, bit].sort().values[-len(cells):], cells.sort().values / cells.norm())
        z = soft_bits(encoder, sums, key)[0]
        exact.append(payload.detection_pvalue(z, weights[0]))
    assert stats.kstest(exact, "uniform").pvalue > 0.01


def test_the_mark_mask_is_kept_only_while_the_texture_is_unchanged():
    from meshseal.models.spread import activity_mask

    encoder = WatermarkModel(SPREAD).texture_encoder
    texture = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        first = encoder.amplitude(texture)
        assert encoder.amplitude(texture) is first  # detection asks once per picture
        texture[:, :, :32] = 0.5  # changed in place: recomputed
        second = encoder.amplitude(texture)
        expected = activity_mask(texture, encoder.window, encoder.floor) * encoder.colour[None, :, None, None]
        assert not torch.equal(first, second) and torch.equal(second, expected)
    assert encoder.amplitude(texture) is not second  # with gradients (training): never kept


def _assert_read_on_either_grid(wm, mesh, marked):
    """Pictures (seeded view, true camera) of `marked` (`embed`'s "ab42" on the mesh's own grid) and of
    the same message on the model's 128^2 grid (a mark made before other grids) are read as "ab42"; a
    picture of the clean `mesh` is not detected."""
    from meshseal import payload

    original = wm.original(mesh)
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(5))
    bits = payload.encode("ab42", None, 64)[None]
    texture = mesh.materials[0].texture.permute(2, 0, 1)[None]
    old_style = mesh.copy()
    old_style.materials[0].texture = wm.model.texture_encoder(texture, bits, 1.0, payload.key_seed(None), 128)[0].permute(1, 2, 0)

    def detection(shown):
        with torch.no_grad():
            image = MeshRenderer()(MeshBatch.from_mesh(normalize(to_z_up(shown))), cameras, lights, 256, 256).image
        return wm.decide([wm.read(_quantise(image)[0].permute(1, 2, 0).numpy(), original, camera=cameras)])

    for shown in (marked, old_style):
        found = detection(shown)
        assert found.detected and found.message == "ab42"
    assert not detection(mesh).detected


def test_a_mark_too_faint_to_decode_is_found_by_its_expected_message():
    """The owner who names the message (`--expect`) tests the mark's correlation with it, which needs
    far less of the mark than the any-message test or the code: a faint mark no other test finds is
    detected at the FPR, its message left unread; another message is not. (`dense`: every cell carries
    the message; the default's pilot finds a mark whatever its message as surely as the named test.)"""
    from meshseal.api import load as load_model

    wm = load_model("dense")
    bunny = load(FIXTURES / "bunny.glb")
    original = wm.original(bunny)
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(5))
    faint = wm.embed(bunny, "ab42", strength=0.035)
    with torch.no_grad():
        image = MeshRenderer()(MeshBatch.from_mesh(normalize(to_z_up(faint))), cameras, lights, 128, 128).image
    reading = wm.read(_quantise(image)[0].permute(1, 2, 0).numpy(), original, camera=cameras)
    anything, named, other = (wm.decide([reading], expect=e) for e in (None, "ab42", "zz99"))
    assert not anything.detected and anything.p_value > 1e-4
    assert named.detected and named.p_value < 1e-7 and named.message is None
    assert not other.detected and other.p_value > 1e-3


def test_a_minified_texture_is_marked_on_coarser_cells_and_either_grid_is_read():
    """Where 128^2 cells would be a fraction of a pixel, `embed` marks on 64^2 cells; detection reads both
    grids there, so a mark on the model's own grid (made before) is still found, and a clean picture is not."""
    from dataclasses import replace

    from meshseal.api import Watermarker
    from meshseal.models.spread import cell_pixels

    bunny = load(FIXTURES / "bunny.glb")
    small = replace(bunny, uvs=bunny.uvs * 8)  # the texture repeated 8 x 8 times as often over the surface
    model = WatermarkModel(SPREAD)
    assert model.texture_encoder.grid_for(bunny.positions, bunny.faces, bunny.uvs) == 128
    assert model.texture_encoder.grid_for(small.positions, small.faces, small.uvs) == 64
    encoder = model.texture_encoder
    assert encoder.grids_to_read(bunny.positions, bunny.faces, bunny.uvs) == (128,)  # no second try to pay for
    assert encoder.grids_to_read(small.positions, small.faces, small.uvs) == (128, 64)
    base = cell_pixels(small.positions, small.faces, small.uvs, 128)
    assert abs(cell_pixels(small.positions * 37 + 5, small.faces, small.uvs, 128) - base) < 1e-5 * base  # any units

    wm = Watermarker(model)
    _assert_read_on_either_grid(wm, small, wm.embed(small, "ab42"))


def test_a_magnified_texture_is_marked_on_finer_cells_of_a_resampled_texture_and_either_grid_is_read():
    """Where 128^2 cells would be several pixels wide (a small part of the texture stretched over the
    surface), `embed` marks on 512^2 cells, resampling a smaller texture up to carry them; the figures
    measure the mark alone, a picture of it is read, and so is a mark on the model's own grid."""
    from dataclasses import replace

    from meshseal.api import Watermarker
    from meshseal.evaluation.reports import embed_report
    from meshseal.models.spread import carrier, resampled_like

    bunny = load(FIXTURES / "bunny.glb")
    large = replace(bunny, uvs=bunny.uvs * 0.25 + 0.3)  # a quarter of the texture, 4x magnified
    model = WatermarkModel(SPREAD)
    encoder = model.texture_encoder
    assert model.texture_encoder.grid_for(large.positions, large.faces, large.uvs) == 512
    assert encoder.grids_to_read(large.positions, large.faces, large.uvs) == (128, 512)
    texture = large.materials[0].texture.permute(2, 0, 1)[None]  # 256^2
    assert carrier(texture, 128) is texture and carrier(texture, 512).shape[-2:] == (512, 512)
    assert torch.equal(resampled_like(texture, texture), texture)

    wm = Watermarker(model)
    marked = wm.embed(large, "ab42")
    assert marked.materials[0].texture.shape[:2] == (512, 512) and large.materials[0].texture.shape[:2] == (256, 256)
    report, _ = embed_report(large, marked, views=0)
    assert abs(report["psnr_texture_shown"] - encoder.texture_psnr) < 0.2  # the mark's power, not the resampling's

    _assert_read_on_either_grid(wm, large, marked)


def test_a_second_look_reads_the_twin_view_and_pays_for_it(monkeypatch):
    """A registered reading whose camera is a wrong (twin) view: `look_again` reads it under the
    registration's alternatives and keeps the one whose mark is found; the p-value pays x4 at the
    registered camera (four stages: it, the matched and sharpened cameras, the nudges, the
    alternatives) and x4K at an alternative; unmarked pictures stay undetected; pooling skips it."""
    import meshseal.reading.second_look as api
    from meshseal import payload
    from meshseal.api import Watermarker
    from meshseal.reading.registration import Alternative, pose_error

    model, message, original, marked = _original_and_marked_batches()
    marked.textures = [model.texture_encoder(original.textures[0][None], message, 1.0, payload.key_seed(None))[0]]
    watermarker = Watermarker(model)  # reads under the public key's pattern
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(0))
    turned = replace(cameras, eye=cameras.eye * torch.tensor([-1.0, -1.0, 1.0]))  # half a turn about the vertical
    with torch.no_grad():
        seen = {name: _quantise(MeshRenderer()(mesh, cameras, lights, 256, 256).image)
                for name, mesh in (("marked", marked), ("clean", original))}
    mask = seen["marked"][0].sum(0) > 0

    def registered_at(picture, camera, alternatives):
        reading = watermarker.read(picture[0].permute(1, 2, 0).numpy(), original, camera=camera)
        return replace(reading, camera="registered", second_look=(picture, mask, alternatives))

    first = registered_at(seen["marked"], turned, (Alternative(turned), Alternative(cameras)))
    plain = watermarker.decide([replace(first, second_look=())])
    monkeypatch.setattr(api, "LOOK_AGAIN_BELOW", 1.0)  # finish every alternative whatever the first reading says
    again = watermarker.look_again(first, original)
    decision = watermarker.decide([again])
    assert not plain.detected and decision.detected and again.tries == 8 and not again.second_look
    assert ((torch.tensor([int(b) for b in decision.bits]) == message[0]).float().mean()) >= 0.95
    # the alternative finished is polished (`registration.polish`): the true view stays within hundredths of a pixel
    assert pose_error(original, cameras, again.found, 256, 256) < 0.02
    single = watermarker.decide([replace(again, tries=1)])
    assert decision.p_value == pytest.approx(min(1.0, 8 * single.p_value), rel=1e-9)
    # Found at the registered camera: x4 (four stages paid for), nothing else read.
    direct = watermarker.look_again(registered_at(seen["marked"], cameras, (Alternative(turned),)), original)
    assert direct.tries == 4 and torch.allclose(direct.found.eye, cameras.eye)
    # An unmarked picture: no camera finds a mark; pooling keeps the first camera and no factor.
    clean = watermarker.look_again(registered_at(seen["clean"], turned, (Alternative(cameras),)), original)
    assert not watermarker.decide([clean]).detected and clean.tries == 4
    pooled = watermarker.look_again(first, original, search=False)
    assert pooled.tries == 1 and not pooled.second_look and torch.equal(pooled.evidence, first.evidence)


def _aliasing_bunny():
    """The bunny with a 512^2 noise texture (finer than a 256^2 picture's pixels: it aliases), marked:
    model, message, original and marked batches, a Watermarker, the seed's first view and its 256^2
    8-bit picture (1, 3, H, W) of the marked bunny."""
    from meshseal import payload
    from meshseal.api import Watermarker

    model, message, original, marked = _original_and_marked_batches()
    noise = torch.rand(3, 512, 512, generator=torch.Generator().manual_seed(0))
    original.textures = [noise]
    marked.textures = [model.texture_encoder(noise[None], message, 1.0, payload.key_seed(None))[0]]
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(0))
    with torch.no_grad():
        picture = _quantise(MeshRenderer()(marked, cameras, lights, 256, 256).image)
    return model, message, original, marked, Watermarker(model), cameras, picture


def test_a_camera_a_fraction_of_a_pixel_off_is_sharpened_on_the_reading_residual():
    """A texture finer than the picture's pixels aliases (a 512^2 noise texture on the bunny, seen at
    256^2): a camera 0.19 px off misses the mark. `register.sharpen` brings it within a few hundredths
    of a pixel of the true camera, and `look_again` reads the mark there, paying x3(R + 1) (no
    alternatives: three stages, R sharpening rounds)."""
    import meshseal.reading.second_look as api
    from meshseal.reading.registration import _moved, pose_error, sharpen

    model, message, original, marked, watermarker, cameras, picture = _aliasing_bunny()
    mask = picture[0].sum(0) > 0
    off = _moved(cameras, torch.tensor([0.15, 0.0, 0.0, 0.0, 0.1, 0.0]), 256)
    reading = watermarker.read(picture[0].permute(1, 2, 0).numpy(), original, camera=off)
    assert pose_error(original, cameras, off, 256, 256) > 0.15 and not watermarker.decide([reading]).detected
    assert pose_error(original, cameras, sharpen(original, off, picture, mask[None].float()), 256, 256) < 0.05

    again = watermarker.look_again(replace(reading, camera="registered", second_look=(picture, mask, ())), original)
    decision = watermarker.decide([again])
    assert decision.detected and again.tries == 3 * (api.SHARPEN_ROUNDS + 1)
    assert pose_error(original, cameras, again.found, 256, 256) < 0.05
    assert ((torch.tensor([int(b) for b in decision.bits]) == message[0]).float().mean()) >= 0.95


def test_a_second_look_nudges_the_registered_camera_and_pays_for_every_nudge(monkeypatch):
    """Where the stages before it find nothing (here the block matching and the sharpening are taken
    out), a second look reads the registered camera nudged each way along six screen moves
    (`registration.nudges`: 12 cameras, each moving the seen surface by the step, RMS) and keeps the
    nudge whose reading finds the mark, paying x3 x 12 (three stages without alternatives)."""
    import meshseal.reading.registration as registration
    import meshseal.reading.second_look as api
    from meshseal.render import surface_at_pixels

    model, message, original, marked, watermarker, cameras, picture = _aliasing_bunny()
    with torch.no_grad():
        fragments, _, _ = surface_at_pixels(original, cameras, 256, 256)
    mask = picture[0].sum(0) > 0
    inside = registration._interior(fragments.pix_to_face >= 0, mask[None].float(), 2)
    basis = registration._screen_basis(original, cameras, fragments, inside)
    off = registration._moved(cameras, -0.4 * basis[:, 0], 256)  # one nudge of 0.4 px from the truth
    nudged = registration.nudges(original, off, mask[None].float(), 0.4)
    shifts = [registration.pose_error(original, off, nudged[[k]], 256, 256) for k in range(12)]
    assert len(nudged) == 12 and all(0.2 < shift <= 0.4 for shift in shifts)  # mean distance, 0.4 px RMS
    # the nearest nudge: back near the truth (the basis at `off` is turned a little from the truth's)
    assert min(registration.pose_error(original, cameras, nudged[[k]], 256, 256) for k in range(12)) < 0.1

    reading = watermarker.read(picture[0].permute(1, 2, 0).numpy(), original, camera=off)
    assert not watermarker.decide([reading]).detected
    monkeypatch.setattr(registration, "polish_blocks", lambda mesh, camera, *args: None)
    monkeypatch.setattr(registration, "sharpen", lambda mesh, camera, *args: camera)
    monkeypatch.setattr(api, "NUDGE_STEP", 0.4)
    monkeypatch.setattr(api, "NUDGE_BELOW", 1.0)  # whatever the first reading hints
    again = watermarker.look_again(replace(reading, camera="registered", second_look=(picture, mask, ())), original)
    decision = watermarker.decide([again])
    assert decision.detected and again.tries == 3 * 12
    assert registration.pose_error(original, cameras, again.found, 256, 256) < 0.1
    single = watermarker.decide([replace(again, tries=1)])
    assert decision.p_value == pytest.approx(min(1.0, 36 * single.p_value), rel=1e-9)


def _bunny_picture_and_jpeg(marked, cameras, lights):
    """The marked bunny's 256^2 picture (1, 3, H, W, 8-bit values), the same saved as JPEG 75 and read
    back, and its object mask (1, H, W)."""
    import io

    import numpy as np
    from PIL import Image

    with torch.no_grad():
        clean = _quantise(MeshRenderer()(marked, cameras, lights, 256, 256).image)
    buffer = io.BytesIO()
    Image.fromarray((clean[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)).save(buffer, "JPEG", quality=75)
    jpeg = torch.from_numpy(np.asarray(Image.open(io.BytesIO(buffer.getvalue())).convert("RGB")).astype(np.float32) / 255)
    return clean, jpeg.permute(2, 0, 1)[None], (clean[0].sum(0) > 0).float()[None]


def test_a_registered_camera_is_polished_onto_the_picture_and_a_long_move_is_refused(monkeypatch):
    """After JPEG the texture stage leaves a camera a tenth of a pixel or so off, and a luminance mark's
    reading loses much of its evidence to that. `polish` (Gauss-Newton on central differences of
    full renders, high-passed) brings a camera 0.1 px off the bunny's JPEG 75 picture to within a few
    hundredths of a pixel and leaves the true camera within two; on a texture that aliases (a 512^2
    noise texture at 256^2, PNG) the reading's p-value at the polished camera is that of the true
    one's order, far under the camera's it started from. A move longer than POLISH_MAX is not taken."""
    import meshseal.reading.registration as registration
    from meshseal import payload
    from meshseal.api import Watermarker
    from meshseal.reading.registration import _moved, polish, pose_error

    model, message, original, marked = _original_and_marked_batches()
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(0))
    off = _moved(cameras, torch.tensor([0.15, -0.1, 0.0, 0.05, 0.1, 0.0]), 256)
    assert pose_error(original, cameras, off, 256, 256) > 0.09
    clean, jpeg, mask = _bunny_picture_and_jpeg(marked, cameras, lights)
    assert pose_error(original, cameras, polish(original, off, jpeg, mask), 256, 256) < 0.04
    assert pose_error(original, cameras, polish(original, cameras, jpeg, mask), 256, 256) < 0.02

    noise = torch.rand(3, 512, 512, generator=torch.Generator().manual_seed(0))
    original.textures = [noise]
    marked.textures = [model.texture_encoder(noise[None], message, 1.0, payload.key_seed(None))[0]]
    with torch.no_grad():
        picture = _quantise(MeshRenderer()(marked, cameras, lights, 256, 256).image)
    watermarker = Watermarker(model)
    pixels = picture[0].permute(1, 2, 0).numpy()

    def log_p(camera) -> float:
        return math.log10(watermarker.decide([watermarker.read(pixels, original, camera=camera)]).p_value)

    polished = polish(original, off, picture, mask)
    assert pose_error(original, cameras, polished, 256, 256) < 0.01
    assert log_p(polished) < 0.9 * log_p(cameras) and log_p(polished) < 10 * log_p(off)
    monkeypatch.setattr(registration, "POLISH_MAX", 0.01)
    assert polish(original, off, picture, mask) is off



def test_the_polish_moves_along_an_orbit_that_only_parallax_shows(monkeypatch):
    """A camera turned by 3 px and shifted back by 2.7 px (an orbit about the bunny: the picture moves
    0.17 px on average, by parallax) is polished to within 0.03 px of its camera as PNG and as JPEG 75:
    the polish measures its Jacobian along moves that each shift the picture alike
    (`registration._screen_basis`). Along `_moved`'s own coordinates (the polish before), that orbit
    is the small difference of two large moves, and the polish stops 0.04 px or more off."""
    import meshseal.reading.registration as registration
    from meshseal.reading.registration import _moved, polish, pose_error

    _, _, original, marked = _original_and_marked_batches()
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(0))
    clean, jpeg, mask = _bunny_picture_and_jpeg(marked, cameras, lights)
    pictures = (clean, jpeg)
    off = _moved(cameras, torch.tensor([3.0, 0.0, 0.0, 2.7, 0.0, 0.0]), 256)
    assert 0.15 < pose_error(original, cameras, off, 256, 256) < 0.2
    for picture in pictures:
        assert pose_error(original, cameras, polish(original, off, picture, mask), 256, 256) < 0.03
    monkeypatch.setattr(registration, "_screen_basis", lambda *args: torch.eye(6))
    for picture in pictures:
        assert pose_error(original, cameras, polish(original, off, picture, mask), 256, 256) > 0.04


def test_blocks_find_the_pose_where_an_aliasing_texture_traps_the_polish():
    """On a texture finer than the pixels (a 512^2 noise texture on the bunny at 256^2) a pose's misfit
    is rugged: from cameras 0.5 and 0.65 px off, the polish stops 0.3 px or more off. Matched block by
    block against every sub-pixel shift of a supersampled render (`registration.match_blocks`), the
    camera comes within 0.1 px, and the polish from there (`polish_blocks`) within 0.01 px; from the
    true camera the blocks find nothing better or stay there."""
    from meshseal import payload
    from meshseal.reading.registration import _moved, match_blocks, polish, polish_blocks, pose_error

    model, message, original, marked = _original_and_marked_batches()
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(0))
    noise = torch.rand(3, 512, 512, generator=torch.Generator().manual_seed(0))
    original.textures = [noise]
    marked.textures = [model.texture_encoder(noise[None], message, 1.0, payload.key_seed(None))[0]]
    with torch.no_grad():
        picture = _quantise(MeshRenderer()(marked, cameras, lights, 256, 256).image)
    mask = (picture[0].sum(0) > 0).float()[None]
    error = lambda camera: pose_error(original, cameras, camera, 256, 256)  # noqa: E731
    for move in ([0.0, 0.5, 0.3, 0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.6, 0.0, 0.0]):
        off = _moved(cameras, torch.tensor(move), 256)
        assert error(off) > 0.5 and error(polish(original, off, picture, mask)) > 0.3
        assert error(match_blocks(original, off, picture, mask)) < 0.1
        assert error(polish_blocks(original, off, picture, mask)) < 0.01
    kept = polish_blocks(original, cameras, picture, mask)
    assert kept is None or error(kept) < 0.01


def test_a_small_objects_rim_finds_the_pose_the_interior_polish_misses():
    """The bunny 18 units away (under 400 pixels at 256^2) on a plain background: the interior pixels the
    polish compares are few and their texture finer than the pixels, so from cameras a quarter of a
    pixel off it stops 0.2 px or more off; compared over its whole window, the antialiased rim composited
    over the background included (`registration.polish_composited`), the camera comes within 0.05 px,
    and the true camera stays where it is."""
    from meshseal.reading.registration import _moved, polish, polish_composited, pose_error

    _, _, original, marked = _original_and_marked_batches()
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(0))
    far = replace(cameras, eye=cameras.eye * (18.0 / cameras.eye.norm()))
    grey = torch.tensor([[0.45, 0.5, 0.55]])
    with torch.no_grad():
        rendered = MeshRenderer()(marked, far, lights, 256, 256, grey)
    picture, mask = _quantise(rendered.image), (rendered.rgba[..., 3] >= 0.5).float()
    assert int(mask.sum()) < 400
    behind = grey.reshape(1, 3, 1, 1).expand(1, 3, 256, 256)
    error = lambda camera: pose_error(original, far, camera, 256, 256)  # noqa: E731
    for move in ([0.0, 0.15, 0.0, 0.2, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.25, 0.2]):
        off = _moved(far, torch.tensor(move), 256)
        assert error(off) > 0.2 and error(polish(original, off, picture, mask)) > 0.2
        assert error(polish_composited(original, off, picture, mask, behind)) < 0.05
    assert error(polish_composited(original, far, picture, mask, behind)) < 0.01


def test_a_registered_object_of_few_pixels_is_polished_on_its_rim_first(monkeypatch):
    """The bunny 8 units away on a plain background: a box over RIM_BELOW px wide, but under
    RIM_PIXELS_BELOW pixels, few of them interior. Registration handing over cameras a quarter of a
    pixel off, the polish alone (`RIM_PIXELS_BELOW` 0) stops a tenth of a pixel or more off; the reading
    first compares the whole window, its rim included (`registration.polish_composited`, one quick
    round), and the polish then ends within 0.02 px. A picture of a larger object is not polished on its
    rim (its interior pixels suffice)."""
    import numpy as np

    import meshseal
    import meshseal.reading.read as read
    import meshseal.reading.registration as registration
    from meshseal.reading.registration import Registration, _moved, pose_error

    watermarker = meshseal.load()
    original = watermarker.original(FIXTURES / "bunny.glb")
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(0))
    far = replace(cameras, eye=cameras.eye * (8.0 / cameras.eye.norm()))
    grey = torch.tensor([[0.45, 0.5, 0.55]])
    with torch.no_grad():
        rendered = MeshRenderer()(original, far, lights, 256, 256, grey)
    picture = (_quantise(rendered.image)[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    pixels = int((rendered.rgba[..., 3] >= 0.5).sum())
    assert pixels < read.RIM_PIXELS_BELOW and read.object_side(rendered.rgba[0, ..., 3].numpy()) >= read.RIM_BELOW
    handed = []
    monkeypatch.setattr(registration, "register_with_masks", lambda *args, **kwargs: Registration(
        handed[-1], torch.tensor([128.0, 128.0, 40.0]), 1.0))
    rims = []
    composited = registration.polish_composited
    monkeypatch.setattr(registration, "polish_composited", lambda *args, **kwargs: rims.append(kwargs) or composited(*args, **kwargs))
    error = lambda camera: pose_error(original, far, camera.to("cpu"), 256, 256)  # noqa: E731

    def registered(move, rim_pixels=read.RIM_PIXELS_BELOW):
        handed.append(_moved(far, torch.tensor(move), 256))
        monkeypatch.setattr(read, "RIM_PIXELS_BELOW", rim_pixels)
        return error(watermarker.read(picture, original, register=True).found)

    for move in ([0.0, 0.15, 0.0, 0.2, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.25, 0.2]):
        rims.clear()
        assert error(_moved(far, torch.tensor(move), 256)) > 0.2
        assert registered(move, rim_pixels=0) > 0.1 and not rims
        assert registered(move) < 0.02 and rims[-1] == {"sigmas": (0.0,), "rounds": 1}
    rims.clear()
    registered([0.0] * 6, rim_pixels=pixels)  # as if the object were larger: the polish alone
    assert not rims


def test_the_polish_renders_a_halved_picture_as_it_was_made(monkeypatch):
    """A picture halved after it was rendered (bicubic, as image tools resize) averaged four rendered
    pixels into each of its own. The polish finds that (a render at twice the window's size resized to
    it explains the picture better than point samples) and brings a camera 0.07 px off to within 0.025
    px, and the true camera stays there; with point samples alone (the polish before) it stops 0.03 px
    or more off."""
    import numpy as np

    import meshseal.reading.registration as registration
    from meshseal.evaluation.attacks import apply
    from meshseal.reading.registration import _moved, polish, pose_error

    _, _, original, marked = _original_and_marked_batches()
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(0))
    with torch.no_grad():
        clean = _quantise(MeshRenderer()(marked, cameras, lights, 256, 256).image)
    eight = (clean[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
    half = torch.from_numpy(apply("resize0.5", eight, np.random.default_rng(0)).astype(np.float32) / 255)
    half = half.permute(2, 0, 1)[None]
    mask = (half[0].sum(0) > 0.02).float()[None]
    off = _moved(cameras, torch.tensor([0.1, -0.05, 0.0, 0.03, 0.05, 0.0]), 128)
    assert pose_error(original, cameras, off, 128, 128) > 0.06
    assert pose_error(original, cameras, polish(original, off, half, mask), 128, 128) < 0.025
    assert pose_error(original, cameras, polish(original, cameras, half, mask), 128, 128) < 0.025
    monkeypatch.setattr(registration, "POLISH_FOOTPRINTS", (1.0,))
    assert pose_error(original, cameras, polish(original, off, half, mask), 128, 128) > 0.03


def test_a_second_look_sharpens_only_a_reading_that_hints_at_a_mark(monkeypatch):
    """Sharpening costs a second look its renders: the unmarked bunny's registered reading (no hint, p
    above SHARPEN_BELOW) is not sharpened; with the bar at 1 it is, and the p-value pays the same
    either way (every stage is paid for, tried or not: x3 at the registered camera)."""
    import meshseal.reading.registration as registration
    import meshseal.reading.second_look as api
    from meshseal.api import Watermarker

    model, message, original, marked = _original_and_marked_batches()
    watermarker = Watermarker(model)
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(0))
    with torch.no_grad():
        picture = _quantise(MeshRenderer()(original, cameras, lights, 256, 256).image)
    mask = picture[0].sum(0) > 0
    reading = watermarker.read(picture[0].permute(1, 2, 0).numpy(), original, camera=cameras)
    first = replace(reading, camera="registered", second_look=(picture, mask, ()))
    assert watermarker.decide([replace(first, second_look=())]).p_value > api.SHARPEN_BELOW
    calls = []
    real = registration.sharpen
    monkeypatch.setattr(registration, "sharpen", lambda *args, **kwargs: calls.append(1) or real(*args, **kwargs))
    again = watermarker.look_again(first, original)
    assert calls == [] and not watermarker.decide([again]).detected and again.tries == 3
    monkeypatch.setattr(api, "SHARPEN_BELOW", 1.0)
    watermarker.look_again(first, original)
    assert len(calls) == 1  # one round: its reading hints at nothing either


def test_a_second_look_finishes_only_the_views_whose_rough_reading_hints_at_the_mark():
    """Where the registered reading shows no hint of a mark, each alternative is read rough (refined on
    its silhouettes alone) and finished on the texture only if that reading hints at one: the twin
    view is finished and found, the view that shows nothing is never finished, and the p-value still
    pays x4K for every alternative."""
    import meshseal.reading.second_look as api
    from meshseal import payload
    from meshseal.api import Watermarker
    from meshseal.reading.registration import Alternative, pose_error

    model, message, original, marked = _original_and_marked_batches()
    marked.textures = [model.texture_encoder(original.textures[0][None], message, 1.0, payload.key_seed(None))[0]]
    watermarker = Watermarker(model)
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(0))
    turned = replace(cameras, eye=cameras.eye * torch.tensor([-1.0, -1.0, 1.0]))
    aside = replace(cameras, eye=cameras.eye[:, [1, 0, 2]] * torch.tensor([-1.0, 1.0, 1.0]))  # a quarter turn: another wrong view
    with torch.no_grad():
        picture = _quantise(MeshRenderer()(marked, cameras, lights, 256, 256).image)
    mask = picture[0].sum(0) > 0
    finished = []

    def stages(rough):
        """An alternative whose silhouettes give `rough` and whose texture stage lands on the truth."""
        return Alternative(turned, lambda camera: rough, lambda camera: finished.append(rough) or cameras)

    reading = watermarker.read(picture[0].permute(1, 2, 0).numpy(), original, camera=turned)
    first = replace(reading, camera="registered", second_look=(picture, mask, (stages(aside), stages(cameras))))
    assert watermarker.decide([replace(first, second_look=())]).p_value > api.LOOK_AGAIN_BELOW  # no hint
    again = watermarker.look_again(first, original)
    decision = watermarker.decide([again])
    assert decision.detected and again.tries == 8 and pose_error(original, cameras, again.found, 256, 256) < 0.02  # polished
    assert len(finished) == 1 and finished[0] is cameras  # the view showing nothing was not finished


def test_a_registered_reading_leaves_a_worker_without_what_a_second_look_needs(tmp_path, monkeypatch):
    """`meshseal detect --workers N` sends results between processes: a Detection, or with --pool a
    registered reading settled (no picture, mask or refinement closures), so both pickle. (The small
    object is registered at its own size here: the enlarged copy is not what this is about.)"""
    import pickle

    from PIL import Image

    from meshseal.api import Watermarker
    from meshseal.commands.model import _read_one
    from meshseal.reading import read

    monkeypatch.setattr(read, "REGISTER_MIN_SIDE", 0)

    model, _, original, marked = _original_and_marked_batches()
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(1))
    with torch.no_grad():
        picture = _quantise(MeshRenderer()(marked, cameras, lights, 128, 128, (0.5, 0.5, 0.5)).image)[0]
    Image.fromarray((picture.permute(1, 2, 0).numpy() * 255).round().astype("uint8")).save(tmp_path / "p.png")
    watermarker = Watermarker(model)
    path, reading, error = _read_one(watermarker, original, tmp_path / "p.png", True, 60.0, None, None, True)  # --pool
    assert error is None and reading.camera == "registered" and reading.second_look == ()
    assert torch.equal(pickle.loads(pickle.dumps(reading)).evidence, reading.evidence)
    path, result, error = _read_one(watermarker, original, tmp_path / "p.png", True, 60.0, None, None, False)
    assert error is None and result.camera == "registered"  # a Detection, its second look taken in the worker
    assert pickle.loads(pickle.dumps(result)).to_dict() == result.to_dict()


def _halved_picture(marked, cameras, lights, factor: float = 0.5) -> torch.Tensor:
    """A 256^2 8-bit render of `marked` halved (or resized by `factor`) as image tools resize (Pillow's
    bicubic) -> (1, 3, 128, 128) (at 0.5)."""
    import numpy as np
    from PIL import Image

    large = (MeshRenderer()(marked, cameras, lights, 256, 256).image[0].clamp(0, 1).permute(1, 2, 0) * 255).round()
    side = round(256 * factor)
    halved = Image.fromarray(large.byte().numpy()).resize((side, side), Image.Resampling.BICUBIC)
    return torch.from_numpy(np.asarray(halved).astype(np.float32) / 255).permute(2, 0, 1)[None]


def test_a_resized_picture_is_predicted_as_resized(monkeypatch):
    """A picture rendered at twice its size and resized (bicubic, as image tools resize) is predicted by
    the original rendered at that size and resized the same way, not by a Gaussian footprint; a
    luminance mark (whose reading the texture's resampled edges disturb most) reads better for it. A picture blurred as an engine samples keeps its Gaussian footprint."""
    import functools

    import torch.nn.functional as F

    import meshseal.methods.spread as spread_module
    from meshseal.imaging import gaussian_blur
    from meshseal.methods.spread import spread_evidence
    from meshseal.models.spread import soft_bits
    from meshseal.reading.footprint import picture_footprint
    from meshseal.reading.relight import relit_residual

    grey = replace(SPREAD, mark_colour="grey", texture_psnr=34.0, read_highpass=3.0, read_window=3.0,
                   read_brightness=-1.0)  # configs/robust.yaml's mark and reading
    model, message, original, marked = _original_and_marked_batches(grey)
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(1))
    signs = 2 * message - 1
    with torch.no_grad():
        picture = _halved_picture(marked, cameras, lights)
        found = picture_footprint(original, relit_residual(original, picture, cameras), cameras, 128, 128)
        assert float(found.resized[0]) == 0.5
        fine = MeshRenderer()(marked, cameras, lights, 512, 512).image
        area = _quantise(F.avg_pool2d(gaussian_blur(fine, 2.0), 4))
        blurred = picture_footprint(original, relit_residual(original, area, cameras), cameras, 128, 128)
        assert bool(blurred.resized.isnan().all()) and float(blurred.sigma[0]) == 0.5
        resizing = soft_bits(model.texture_encoder, spread_evidence(model, original, picture, cameras))
        monkeypatch.setattr(spread_module, "picture_footprint", functools.partial(picture_footprint, resampled=()))
        # another tensor: the same one read again would keep the footprint its first reading found
        gaussian = soft_bits(model.texture_encoder, spread_evidence(model, original, picture.clone(), cameras))
    assert float((resizing * signs).mean()) > 1.1 * float((gaussian * signs).mean()) > 0


def test_a_resized_footprint_kept_from_before_reads_a_view_with_no_whole_pixel():
    """A second look may read a resized picture under a camera where none of the kept pixels is wholly
    covered (the object at the frame's edge): the footprint kept from the first reading (a resize) has
    nothing to be compared on there, and the picture reads under point samples, without an error."""
    from meshseal.reading import footprint
    from meshseal.reading.relight import relit_residual

    model, message, original, marked = _original_and_marked_batches(SPREAD)
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(1))
    with torch.no_grad():
        picture = _halved_picture(marked, cameras, lights)
        found = relit_residual(original, picture, cameras)
        none = found.keep[:0]
        bare = replace(found, seen=found.seen[:0], expected=found.expected[:0], albedo=found.albedo[:0],
                       uv=found.uv[:0], material=found.material[:0], image_index=found.image_index[:0], keep=none)
        chosen = footprint.picture_footprint(original, bare, cameras, *picture.shape[-2:],
                                             known=(footprint.RESAMPLED_TEMPLATE_SIGMA, 0.5))
    assert len(chosen.expected) == 0 and bool(torch.isnan(chosen.sigma).all())


def test_a_picture_read_again_keeps_the_footprint_its_first_reading_found():
    """A second look reads the same picture tensor under other cameras: the footprint found the first
    time is kept (`footprint.chosen_before`), so the reading under the same camera is the same and no
    search runs again; another tensor holding the same pixels searches anew."""
    from meshseal.methods.spread import spread_evidence
    from meshseal.reading import footprint

    grey = replace(SPREAD, mark_colour="grey", texture_psnr=34.0, read_highpass=3.0, read_window=3.0,
                   read_brightness=-1.0)
    model, message, original, marked = _original_and_marked_batches(grey)
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(1))
    with torch.no_grad():
        picture = _halved_picture(marked, cameras, lights)
        first = spread_evidence(model, original, picture, cameras)
        assert footprint.chosen_before(picture) == (footprint.RESAMPLED_TEMPLATE_SIGMA, 0.5)  # a resized picture's footprint
        searched = []
        real = footprint.resampled_prediction

        def counting(*args, **kwargs):
            searched.append(args[-1])
            return real(*args, **kwargs)

        footprint.resampled_prediction = counting
        try:
            again = spread_evidence(model, original, picture, cameras)
            assert searched == [0.5]  # only the factor found before
            anew = spread_evidence(model, original, picture.clone(), cameras)
            assert sorted(searched[1:]) == [0.5, 0.75, 1.5]
        finally:
            footprint.resampled_prediction = real
    assert torch.allclose(again, first) and torch.allclose(anew, first)


def test_a_bit_block_gives_each_bit_whole_blocks_of_cells_and_leaves_the_shipped_draws_alone():
    from meshseal.models.spread import SpreadSpectrumEncoder

    plain = SpreadSpectrumEncoder(64, chips=64, colour="grey", seed=0)
    again = SpreadSpectrumEncoder(64, chips=64, colour="grey", seed=0, block=1)
    assert torch.equal(plain.assign, again.assign) and torch.equal(plain.sign, again.sign)
    assert torch.equal(plain.assign, torch.randperm(64 * 64, generator=torch.Generator().manual_seed(0)) % 64)
    blocked = SpreadSpectrumEncoder(64, chips=64, colour="grey", seed=0, block=2)
    for key_seed in (None, 12345):
        assign, sign = blocked.pattern(key_seed, 64)
        grid = assign.reshape(32, 2, 32, 2)
        assert (grid == grid[:, :1, :, :1]).all()  # one bit a 2x2 block
        assert torch.equal(torch.bincount(assign, minlength=64), torch.full((64,), 64))  # every bit as many cells
        assert not (grid == torch.roll(grid, 1, 2)).all()  # neighbouring blocks differ somewhere
        assert 0.4 < float((sign > 0).float().mean()) < 0.6
    config = ModelConfig.from_dict({"n_bits": 64, "texture_encoder": "spread", "chips": 64, "bit_block": 2})
    assert WatermarkModel(config).texture_encoder.block == 2


def test_local_affine_takes_up_another_engines_tone_and_leaves_the_mark():
    """`local_affine`: a picture that is a smooth affine map of the prediction in each channel (another
    engine's shading and colour transform) is fitted to within a small residual, while a mark that does
    not follow the prediction stays in `seen - fitted` almost whole."""
    from meshseal.models.spread import local_affine

    generator = torch.Generator().manual_seed(0)
    height = width = 48
    texture = torch.nn.functional.avg_pool2d(torch.rand(1, 3, height, width, generator=generator), 3, 1, 1)[0]
    ys, xs = torch.meshgrid(torch.linspace(0, 1, height), torch.linspace(0, 1, width), indexing="ij")
    shading = (0.6 + 0.4 * xs)[None]  # slow light across the object
    engine = shading * texture * torch.tensor([0.8, 0.9, 1.1])[:, None, None] + torch.tensor([0.05, 0.0, 0.08])[:, None, None]
    mark = 0.01 * torch.sign(torch.randn(1, height, width, generator=generator)).expand(3, -1, -1)
    pixel = torch.arange(height * width)
    as_rows = lambda image: image.reshape(3, -1).T  # noqa: E731
    fitted = local_affine(as_rows(engine + mark), as_rows(texture), pixel, (1, height, width), sigma=1.0)
    left = as_rows(engine + mark) - fitted
    plain = as_rows(engine + mark) - as_rows(texture)
    assert float(left.pow(2).mean()) < 0.05 * float(plain.pow(2).mean())  # the engine's change is taken up
    kept = float((left * as_rows(mark)).sum() / as_rows(mark).pow(2).sum())
    assert kept > 0.6  # most of the mark stays


def test_the_affine_fit_is_used_only_where_it_explains_the_misfit():
    """`_affine_where_it_fits`: a picture that is the prediction plus white noise keeps the plain residual;
    one that another engine's tone curve bent takes the fitted one."""
    from meshseal.methods.spread import _affine_where_it_fits

    generator = torch.Generator().manual_seed(1)
    height = width = 40
    texture = torch.nn.functional.avg_pool2d(torch.rand(1, 3, height, width, generator=generator), 3, 1, 1)[0]
    rows = lambda image: image.reshape(3, -1).T  # noqa: E731
    pixel = torch.arange(height * width)
    colour = torch.ones(3) / 3 ** 0.5
    for seen, expect_fit in ((texture + 0.01 * torch.randn(3, height, width, generator=generator), False),
                             (0.3 + 0.5 * texture ** 0.6, True)):
        used = _affine_where_it_fits(rows(seen), rows(texture), colour, pixel, (1, height, width), 1.0, 3.0)
        assert torch.equal(used, rows(texture)) is (not expect_fit)


def test_a_pilot_takes_its_share_of_the_cells_and_leaves_the_draws_without_it_alone():
    """`pilot_share` gives that share of the cells to the pilot (index n_bits, the key's own signs);
    without it the pattern is the one drawn before; the bits keep equal shares."""
    from meshseal.models.spread import SpreadSpectrumEncoder

    plain = SpreadSpectrumEncoder(64, chips=64, colour="grey", seed=0)
    assert plain.pilot_slots == 0
    assert torch.equal(plain.assign, torch.randperm(64 * 64, generator=torch.Generator().manual_seed(0)) % 64)
    piloted = SpreadSpectrumEncoder(64, chips=64, colour="grey", seed=0, pilot_share=0.5)
    assert piloted.pilot_slots == 64 and torch.equal(piloted.sign, plain.sign)
    for key_seed in (None, 12345):
        assign, sign = piloted.pattern(key_seed, 64)
        counts = torch.bincount(assign, minlength=65)
        assert int(counts[64]) == 64 * 64 // 2 and (counts[:64] == 32).all()
    message = torch.randint(0, 2, (1, 64), generator=torch.Generator().manual_seed(1)).float()
    cells = piloted.cells(message).reshape(-1)
    pilot = piloted.assign == 64
    assert torch.equal(cells[pilot], piloted.sign[pilot])  # the pilot's cells: the key's sign alone
    assert torch.equal(cells[~pilot], (piloted.sign * (2 * message[0] - 1)[piloted.assign.clamp_max(63)])[~pilot])
    config = ModelConfig.from_dict({"n_bits": 64, "texture_encoder": "spread", "chips": 64, "pilot_share": 0.5})
    assert WatermarkModel(config).texture_encoder.pilot_slots == 64


def test_the_pilot_reads_a_mark_and_has_an_exact_null_over_keys():
    """Cell sums of a mark under one key: the pilot's z is large under that key and weighs the pilot's
    cells alone; under other keys its exact p-values are uniform (KS), as are the bits' own."""
    from scipy import stats

    from meshseal import payload
    from meshseal.models.spread import SpreadSpectrumEncoder, bit_weights, pilot_z, soft_bits

    encoder = SpreadSpectrumEncoder(64, chips=64, colour="grey", seed=0, pilot_share=0.5)
    generator = torch.Generator().manual_seed(0)
    message = torch.randint(0, 2, (1, 64), generator=generator).float()
    noise = torch.randn(64 * 64, generator=generator, dtype=torch.float64) ** 3  # heavy-tailed misfit
    assign, sign = encoder.pattern(7, 64)
    signs = torch.cat([2 * message[0] - 1, torch.ones(1)]).double()
    z, weights = pilot_z(encoder, noise + sign.double() * signs[assign], 7)
    assert float(z) > 8
    assert float(weights[assign != 64].abs().sum()) == 0.0 and abs(float(weights.norm()) - 1) < 1e-9
    pilots, bits = [], []
    for key in range(60):
        z, w = pilot_z(encoder, noise, key)
        pilots.append(float(payload.match_pvalue(z[None], [1], w[None])))
        bits.append(payload.detection_pvalue(soft_bits(encoder, noise[None], key)[0], bit_weights(encoder, noise[None], key)[0]))
    for p_values in (pilots, bits):
        assert stats.kstest(p_values, "uniform").pvalue > 0.01


def test_a_pilot_mark_is_detected_by_its_pilot_and_read_as_before():
    """A model with a pilot marks and reads the bunny: detected, the message read and named; the
    original reads no mark."""
    from meshseal.api import Watermarker

    config = ModelConfig.from_dict(load_default_config() | {"pilot_share": 0.5})
    wm = Watermarker(WatermarkModel(config).eval())
    bunny = load(FIXTURES / "bunny.glb")
    original = wm.original(bunny)
    marked = wm.embed(bunny, "ab42")
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(5))
    with torch.no_grad():
        pictures = [MeshRenderer()(MeshBatch.from_mesh(normalize(to_z_up(m))), cameras, lights, 256, 256).image
                    for m in (marked, bunny)]
    found, clean = (wm.decide([wm.read(_quantise(p)[0].permute(1, 2, 0).numpy(), original, camera=cameras)])
                    for p in pictures)
    named = wm.decide([wm.read(_quantise(pictures[0])[0].permute(1, 2, 0).numpy(), original, camera=cameras)],
                      expect="ab42")
    assert found.detected and found.message == "ab42" and named.detected
    assert not clean.detected and clean.p_value > 1e-3


def load_default_config() -> dict:
    from meshseal.api import load as load_model

    return load_model("default").model.config.to_dict()


def test_the_default_reads_a_mark_of_dense_on_its_message_cells():
    """`dense` (the default before its pilot) marks the bunny; the default reads the message from the
    cells the two share (the message's half of its cells), and `dense` itself reads it more surely."""
    from meshseal.api import load as load_model

    default, dense = load_model("default"), load_model("dense")
    bunny = load(FIXTURES / "bunny.glb")
    marked = dense.embed(bunny, "ab42")
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(5))
    with torch.no_grad():
        image = MeshRenderer()(MeshBatch.from_mesh(normalize(to_z_up(marked))), cameras, lights, 256, 256).image
    picture = _quantise(image)[0].permute(1, 2, 0).numpy()
    by_default, by_dense = (wm.decide([wm.read(picture, wm.original(bunny), camera=cameras)]) for wm in (default, dense))
    assert by_default.detected and by_default.message == "ab42"
    assert by_dense.detected and by_dense.message == "ab42" and by_dense.p_value < by_default.p_value


def test_a_mark_colour_is_named_or_given_and_the_reading_may_take_another():
    """A colour is one of COLOURS or "r,g,b", made unit; the luminance direction carries the most
    luminance for a texture PSNR (a third more energy than grey); a grey mark read along luminance
    (`read_colour`) still reads."""
    from meshseal.methods.spread import _luma_along
    from meshseal.models.spread import colour_direction
    from meshseal.reading.compression import LUMA

    assert torch.allclose(colour_direction("grey"), torch.full((3,), 3 ** -0.5))
    assert torch.allclose(colour_direction("1,2,2"), torch.tensor([1.0, 2.0, 2.0]) / 3)
    for bad in ("purple", "0,0,0", "1,2"):
        with pytest.raises(ValueError, match="mark colour"):
            colour_direction(bad)
    luma = torch.tensor(LUMA)
    grey_y, luma_y = float(colour_direction("grey") @ luma), float(colour_direction("luma") @ luma)
    assert abs((luma_y / grey_y) ** 2 - 1.341) < 0.01
    assert abs(_luma_along(colour_direction("grey")) - grey_y) < 1e-6
    assert _luma_along(colour_direction("blue-yellow")) == float("inf")  # its luminance says nothing: read as 0

    config = replace(SPREAD, mark_colour="grey", read_colour="luma", read_highpass=3.0, read_window=3.0,
                     read_brightness=-1.0)  # the default's reading: no brightness fit
    model, message, original, marked = _original_and_marked_batches(config)
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(0))
    with torch.no_grad():
        seen = _quantise(MeshRenderer()(marked, cameras, lights, 256, 256).image)
    z = read_bits(model, original, seen, cameras)
    assert ((z > 0).float() == message).float().mean() >= 0.95
    across = WatermarkModel(replace(config, read_colour="1,-1,0"))  # orthogonal to grey: nothing of the mark
    across.load_state_dict(model.state_dict())
    z_across = read_bits(across, original, seen, cameras)
    assert float((z_across * (2 * message - 1)).mean()) < 0.3 * float((z * (2 * message - 1)).mean())


def test_a_wide_pilot_lies_on_blocks_of_one_sign_and_leaves_the_draws_without_it_alone():
    """`pilot_block` 2: the pilot takes half the cells in 2 x 2 blocks, each block one sign, under every
    key; the bits keep equal shares of the others; without it (1) the pattern is the one drawn before."""
    from meshseal.models.spread import SpreadSpectrumEncoder

    piloted = SpreadSpectrumEncoder(64, chips=64, colour="grey", seed=0, pilot_share=0.5)
    same = SpreadSpectrumEncoder(64, chips=64, colour="grey", seed=0, pilot_share=0.5, pilot_block=1)
    assert torch.equal(same.assign, piloted.assign) and torch.equal(same.sign, piloted.sign)
    wide = SpreadSpectrumEncoder(64, chips=64, colour="grey", seed=0, pilot_share=0.5, pilot_block=2)
    for key_seed in (None, 12345):
        assign, sign = wide.pattern(key_seed, 64)
        counts = torch.bincount(assign, minlength=65)
        assert int(counts[64]) == 64 * 64 // 2 and (counts[:64] == 32).all()
        blocks = (assign == 64).reshape(32, 2, 32, 2).permute(0, 2, 1, 3).reshape(32, 32, 4)
        assert torch.equal(blocks.all(2), blocks.any(2))  # a block is all pilot or none of it
        signs = sign.reshape(32, 2, 32, 2).permute(0, 2, 1, 3).reshape(32, 32, 4)[blocks.all(2)]
        assert (signs == signs[:, :1]).all() and 0.4 < float((signs[:, 0] > 0).float().mean()) < 0.6
    assert not torch.equal(wide.pattern(None, 64)[0], wide.pattern(12345, 64)[0])
    config = ModelConfig.from_dict({"n_bits": 64, "texture_encoder": "spread", "chips": 64, "pilot_share": 0.5,
                                    "pilot_block": 2, "pilot_gain": 0.6})
    encoder = WatermarkModel(config).texture_encoder
    assert encoder.pilot_block == 2 and encoder.pilot_gain == 0.6
    message = torch.randint(0, 2, (1, 64), generator=torch.Generator().manual_seed(1)).float()
    cells, pilot = encoder.cells(message).reshape(-1), encoder.assign == 64
    assert torch.equal(cells[pilot], 0.6 * encoder.sign[pilot])  # the pilot's share of the energy, scaled
    assert torch.equal(cells[~pilot], (encoder.sign * (2 * message[0] - 1)[encoder.assign.clamp_max(63)])[~pilot])


def test_a_wide_pilot_keeps_an_exact_null_where_neighbouring_cells_read_alike():
    """Without a mark, cell sums alike over each 2 x 2 block (a host residual slower than a cell): the
    pilot's p-values stay uniform, since its exact null draws one sign per block (a null drawing one
    per cell would call such residual a mark: its z spreads twice as wide); a block-wide mark is found."""
    from meshseal.methods import method_for
    from meshseal.models.spread import pilot_z

    config = ModelConfig.from_dict({"n_bits": 64, "texture_encoder": "spread", "chips": 64, "pilot_share": 0.5,
                                    "pilot_block": 2, "pilot_gain": 0.8, "decoder": "matched"})
    method = method_for(WatermarkModel(config))
    encoder = method.encoder
    generator = torch.Generator().manual_seed(3)
    p_values, z_values = [], []
    for _ in range(400):
        slow = torch.randn(32, 32, generator=generator).repeat_interleave(2, 0).repeat_interleave(2, 1)
        sums = (slow + 0.2 * torch.randn(64, 64, generator=generator)).reshape(1, -1).double()
        p_values.append(method.pilot_pvalue(sums, "k"))
        z_values.append(float(pilot_z(encoder, sums[0], method.key_seed("k"))[0]))
    p_values, z_values = torch.tensor(p_values), torch.tensor(z_values)
    assert float((p_values <= 0.05).float().mean()) <= 0.05 + 3 * (0.05 * 0.95 / 400) ** 0.5
    assert float((p_values <= 0.5).float().mean()) >= 0.4 and float(p_values.min()) > 1e-4
    assert 0.85 < float(z_values.std()) < 1.15
    _, sign = encoder.pattern(method.key_seed("k"), 64)
    marked = (0.3 * sign * (encoder.pattern(method.key_seed("k"), 64)[0] == 64) + torch.randn(4096, generator=generator))
    assert method.pilot_pvalue(marked[None].double(), "k") < 1e-6


def test_a_pilot_chips_grid_puts_a_finer_grids_pilot_on_blocks_and_leaves_coarser_grids_alone():
    """`pilot_chips` 128: on the 512^2 grid of a magnified texture the pilot's signs lie on 4 x 4 blocks
    of cells (a 128^2 grid of signs, which a codec keeps more of), each block all pilot or none; the 64^2
    grid keeps its single-cell pilot, drawn as without the setting, so marks on it read as before."""
    from meshseal.models.spread import SpreadSpectrumEncoder

    plain = SpreadSpectrumEncoder(64, chips=64, colour="grey", seed=0, pilot_share=0.5, fine_chips=512)
    capped = SpreadSpectrumEncoder(64, chips=64, colour="grey", seed=0, pilot_share=0.5, fine_chips=512, pilot_chips=128)
    assert capped.pilot_width(64) == 1 and capped.pilot_width(128) == 1 and capped.pilot_width(512) == 4
    for key_seed in (None, 777):
        assert all(torch.equal(a, b) for a, b in zip(plain.pattern(key_seed, 64), capped.pattern(key_seed, 64)))
        assign, sign = capped.pattern(key_seed, 512)
        counts = torch.bincount(assign, minlength=65)
        assert int(counts[64]) == 512 * 512 // 2 and (counts[:64] == 2048).all()
        blocks = (assign == 64).reshape(128, 4, 128, 4).permute(0, 2, 1, 3).reshape(128, 128, 16)
        assert torch.equal(blocks.all(2), blocks.any(2))
        signs = sign.reshape(128, 4, 128, 4).permute(0, 2, 1, 3).reshape(128, 128, 16)[blocks.all(2)]
        assert (signs == signs[:, :1]).all() and 0.45 < float((signs[:, 0] > 0).float().mean()) < 0.55
    config = ModelConfig.from_dict({"n_bits": 64, "texture_encoder": "spread", "chips": 64, "pilot_share": 0.5,
                                    "fine_chips": 512, "pilot_chips": 128})
    assert WatermarkModel(config).texture_encoder.pilot_width(512) == 4


def test_a_picture_shaded_in_linear_light_is_predicted_in_linear_light(monkeypatch):
    """A picture made as Blender's engines make theirs (the texture decoded to linear light, shaded and
    averaged over each pixel there, then encoded to sRGB) is predicted in linear light too, and that
    prediction, which misses it less, is read: the pilot's z grows clearly. Our own point-sampled picture
    reads exactly as without it."""
    import torch.nn.functional as F
    import yaml

    import meshseal.methods.spread as spread
    from meshseal.imaging import gaussian_blur
    from meshseal.methods.spread import spread_evidence
    from meshseal.models.spread import pilot_z
    from meshseal.reading.linear_light import linear_mesh, linear_to_srgb, srgb_to_linear

    levels = torch.linspace(0, 1, 256)
    assert torch.allclose(linear_to_srgb(srgb_to_linear(levels)), levels, atol=1e-6)
    config = ModelConfig.from_dict(yaml.safe_load((FIXTURES.parents[1] / "configs" / "default.yaml").read_text())["model"])
    model = WatermarkModel(config)
    mesh = normalize(to_z_up(load(FIXTURES / "sh3d_crate" / "crate.obj")))
    message = torch.randint(0, 2, (1, 64), generator=torch.Generator().manual_seed(3)).float()
    original, marked = MeshBatch.from_mesh(mesh), MeshBatch.from_mesh(mesh)
    marked.textures = [model.texture_encoder(mesh.materials[0].texture.permute(2, 0, 1)[None], message, 1.0)[0]]
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(0))
    with torch.no_grad():
        ours = _quantise(MeshRenderer()(marked, cameras, lights, 128, 128).image)
        fine = MeshRenderer()(linear_mesh(marked), cameras, lights, 512, 512).image
        engine = _quantise(linear_to_srgb(F.avg_pool2d(gaussian_blur(fine, 2.0), 4)))  # pixel area, 0.5 px filter
        readings = {}
        for linear in (True, False):
            monkeypatch.setattr(spread, "LINEAR_LIGHT", linear)
            readings[linear] = [spread_evidence(model, original, picture, cameras) for picture in (ours, engine)]
    z = {linear: [float(pilot_z(model.texture_encoder, sums[0].double())[0]) for sums in evidence]
         for linear, evidence in readings.items()}
    assert torch.equal(readings[True][0], readings[False][0])  # our own picture: as before
    assert z[True][1] > 1.3 * z[False][1] and z[True][1] > 10.0

    # Read again (a second look: the same tensor), the engine's picture makes its linear prediction under
    # the footprint found for it before, without searching the others (the same sums); ours, which the
    # sRGB prediction explains, never makes one.
    from meshseal.reading import footprint, linear_light

    monkeypatch.setattr(spread, "LINEAR_LIGHT", True)
    with torch.no_grad():
        first = [spread_evidence(model, original, picture, cameras) for picture in (ours, engine)]
        assert linear_light.chosen_before(ours) is None and isinstance(linear_light.chosen_before(engine), tuple)
        searched = []
        search = footprint.picture_footprint
        monkeypatch.setattr(footprint, "picture_footprint",
                            lambda *a, **k: searched.append(k.get("known")) or search(*a, **k))
        again_engine = spread_evidence(model, original, engine, cameras)
        assert searched and all(known is not None for known in searched)

        def refused(*args, **kwargs):
            raise AssertionError("a linear prediction made for a picture the sRGB one explains")

        monkeypatch.setattr(linear_light, "linear_prediction", refused)
        again_ours = spread_evidence(model, original, ours, cameras)
    assert torch.equal(again_engine, first[1]) and torch.equal(again_ours, first[0])


def test_the_resize_adjoint_carries_values_back_as_the_resize_weighed_them():
    """`resized_adjoint` is the transpose of the bicubic, antialiased resize `resampled_prediction`
    makes: <resize(x), y> = <x, adjoint(y)> for any x on the source pixels and y on the picture's, at
    each factor the reading tries; its output has the source render's size."""
    import torch.nn.functional as F

    from meshseal.reading.footprint import RESAMPLED, resized_adjoint, resized_source_size

    generator = torch.Generator().manual_seed(3)
    for factor in RESAMPLED:
        y = torch.randn(2, 1, 96, 80, generator=generator, dtype=torch.float64)
        size = resized_source_size(96, 80, factor)
        x = torch.randn(2, 1, *size, generator=generator, dtype=torch.float64)
        resized = F.interpolate(x, size=(96, 80), mode="bicubic", antialias=True, align_corners=False)
        back = resized_adjoint(y, factor)
        assert back.shape == x.shape
        assert torch.allclose((resized * y).sum(), (x * back).sum(), rtol=1e-10)
        assert float(back.abs().sum()) > 0


def test_a_resized_picture_is_read_through_its_resizes_adjoint(monkeypatch):
    """A picture enlarged 1.5 times (bicubic, as image tools resize) is read with the resize's own
    adjoint as its template (`RESAMPLED_ADJOINT`: the residual carried back onto the source render's
    pixels and summed per cell there): its soft bits agree with their signs more than under the
    pixel's area blurred by `RESAMPLED_TEMPLATE_SIGMA`, which stood in for the bicubic filter before,
    or by twice that. A halved picture reads at least as well as under the blur."""
    import meshseal.reading.footprint as footprint
    from meshseal.methods.spread import spread_evidence
    from meshseal.models.spread import soft_bits

    assert footprint.RESAMPLED_ADJOINT and footprint.RESAMPLED_TEMPLATE_SIGMA == 0.25
    model, message, original, marked = _original_and_marked_batches(SPREAD)
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(1))
    signs = 2 * message - 1
    for factor, margin in ((1.5, 1.03), (0.5, 1.0)):
        with torch.no_grad():
            picture = _halved_picture(marked, cameras, lights, factor)
            adjoint = soft_bits(model.texture_encoder, spread_evidence(model, original, picture, cameras))
            assert footprint.chosen_before(picture)[1] == factor  # read as resized by it
            monkeypatch.setattr(footprint, "RESAMPLED_ADJOINT", False)
            blurred = soft_bits(model.texture_encoder, spread_evidence(model, original, picture.clone(), cameras))
            monkeypatch.setattr(footprint, "RESAMPLED_TEMPLATE_SIGMA", 0.5)
            wider = soft_bits(model.texture_encoder, spread_evidence(model, original, picture.clone(), cameras))
            monkeypatch.undo()
        agreement = [float((bits * signs).mean()) for bits in (adjoint, blurred, wider)]
        assert agreement[0] > margin * agreement[1] and agreement[0] > margin * agreement[2] > 0, (factor, agreement)


def test_an_area_footprints_template_is_narrower_than_the_blur_it_predicts_with(monkeypatch):
    """A picture whose pixels average the surface over their area, blurred as an engine's pixel filter
    blurs it, is predicted under that area footprint, and read with a template blurred half as much
    (`AREA_TEMPLATE_SCALE`): its soft bits agree with their signs more than under the full blur."""
    import torch.nn.functional as F

    import meshseal.methods.spread as spread_module
    from meshseal.imaging import gaussian_blur
    from meshseal.methods.spread import spread_evidence
    from meshseal.models.spread import soft_bits

    assert spread_module.AREA_TEMPLATE_SCALE == 0.5
    model, message, original, marked = _original_and_marked_batches(SPREAD)
    cameras, lights = sample_views(1, "seed", torch.Generator().manual_seed(1))
    signs = 2 * message - 1
    with torch.no_grad():
        fine = MeshRenderer()(marked, cameras, lights, 512, 512).image
        picture = _quantise(F.avg_pool2d(gaussian_blur(fine, 2.0), 4))
        narrow = soft_bits(model.texture_encoder, spread_evidence(model, original, picture, cameras))
        monkeypatch.setattr(spread_module, "AREA_TEMPLATE_SCALE", 1.0)
        full = soft_bits(model.texture_encoder, spread_evidence(model, original, picture.clone(), cameras))
    assert float((narrow * signs).mean()) > 1.03 * float((full * signs).mean()) > 0
