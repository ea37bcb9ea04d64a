"""The keyed spread-spectrum method (the default): a keyed pattern of cells in the texture
(`models.spread`), read by a matched filter after un-rendering a picture onto the original mesh
relit to match it. Its soft bits are z-scores with an exact null (`payload`)."""

from __future__ import annotations

from dataclasses import replace

import torch

from ..imaging import gaussian_blur
from ..models import WatermarkModel
from ..reading import footprint as footprints
from ..reading.footprint import AREA_TEMPLATE_SCALE, picture_footprint, take_off_linear_light
from ..reading.relight import NEAR_WHITE, relit_residual
from ..render import (
    Cameras,
    MeshBatch,
    interpolate,
)
from .base import Method, informed_original, source_prefix, textured_faces, textured_geometry

PALETTE_WARNING = 0.5  # embed warns when this share of the textured surface has faces without UV area


# The local affine fit of the picture on the prediction (`read_affine`) is used for a picture where it
# leaves under this share of the plain residual's detail (RMS after the whitening's high-pass): a
# picture from another engine (0.35-0.6 measured on Blender's three), not our renderer's own pictures
# nor their JPEG or WebP copies (0.65-0.9), which the fit would only weaken.
AFFINE_BELOW = 0.7
LINEAR_LIGHT = True  # a picture the sRGB prediction misses is also predicted in linear light (`reading.linear_light`)


def _luma_along(colour: torch.Tensor) -> float:
    """What one unit of a mark along `colour` (unit, (1, 3, 1)-shaped or (3,)) is in luminance, so that
    the mark read in luminance through JPEG's quantiser (`dequantized`) is put back along its colour;
    inf for a chroma colour (under half a grey mark's luminance): its luminance says next to nothing of
    it, and it reads 0 there."""
    from ..reading.compression import LUMA

    along = float((colour.reshape(-1).cpu() * torch.tensor(LUMA, dtype=colour.dtype)).sum())
    return along if along > 0.5 / 3 ** 0.5 else float("inf")


def _read_along(model: WatermarkModel) -> torch.Tensor:
    """The unit colour (3,) the residual is read along: the config's `read_colour`, else the mark's."""
    if model.config.read_colour:
        from ..models.spread import colour_direction

        return colour_direction(model.config.read_colour)
    return model.texture_encoder.colour


def _affine_where_it_fits(seen: torch.Tensor, expected: torch.Tensor, colour: torch.Tensor, pixel: torch.Tensor,
                          shape: tuple[int, int, int], sigma: float, highpass: float) -> torch.Tensor:
    """The prediction (P, 3) to read the picture against: in each picture where the local affine fit of
    the picture on the prediction (`models.spread.local_affine`) explains the misfit (`AFFINE_BELOW`:
    judged along the mark's colour, on the fit of that projection alone, which costs a third of the
    per-channel one), the per-channel fit; elsewhere `expected` as it is. Picture and prediction only:
    no key."""
    from ..models.spread import local_affine, local_mean

    along_seen, along_expected = (seen * colour).sum(1, keepdim=True), (expected * colour).sum(1, keepdim=True)
    residuals = torch.cat([along_seen - local_affine(along_seen, along_expected, pixel, shape, sigma),
                           along_seen - along_expected], 1)
    detail = (residuals - local_mean(residuals, pixel, shape, highpass)) ** 2
    image = pixel // (shape[1] * shape[2])
    energy = torch.zeros(shape[0], 2, dtype=seen.dtype, device=seen.device).index_add_(0, image, detail)
    use = energy[:, 0] < AFFINE_BELOW ** 2 * energy[:, 1]
    if not bool(use.any()):
        return expected
    fitted = local_affine(seen, expected, pixel, shape, sigma)
    return torch.where(use.index_select(0, image)[:, None], fitted, expected)


def spread_evidence(model: WatermarkModel, mesh: MeshBatch, image: torch.Tensor, cameras: Cameras,
                    whitening: dict | None = None, footprint: bool = True, brightness: bool = True,
                    grids: tuple[int, ...] | None = None, compression: bool = True,
                    imports=None) -> torch.Tensor:
    """A spread-spectrum model's matched-filter cell sums (B, C*C) for pictures (B, 3, H, W) of the
    original `mesh` taken with `cameras` (see `models.spread.cell_sums`; pictures pool by adding them).
    `grids` (default the model's own grid alone): the cell grids to read, their sums side by side
    (B, sum of C*C), the residual computed once.

    With `footprint` (the default) each picture's sampling is estimated first (`picture_footprint`):
    the prediction subtracted and the template the residual is matched against are both the
    original's texture as that picture sampled it, so pictures from engines that average over the
    pixel (and resized or blurred ones) are read with a filter matched to them. With `brightness` (the
    default) each pixel's brightness relative to the prediction is fitted and taken off first (see
    below). `imports` (`reading.imports.Imports` of the original; one picture at a time): the
    original's normals and textures as an asset's import may have changed them, the prediction made
    from the ones that explain the picture best (`reading.imports.pick_normals`, `pick`), the mark's
    template still from the original's own textures. One picture read again (the same tensor: a second look) keeps the footprint its
    first reading found (`reading.footprint.chosen_before`). `whitening`: options of
    `models.spread.whiten` other than its defaults (experiments). Every step looks at the picture and
    the original only, never at a key: z stays N(0, 1) without a mark."""
    from ..models.spread import cell_sums, whiten
    from ..render import sample_textures
    from ..render.renderer import per_fragment

    encoder = model.texture_encoder
    found = relit_residual(mesh, image, cameras)
    n_images, height, width = len(cameras), image.shape[-2], image.shape[-1]
    with torch.no_grad():
        # An untextured material carries no mark: weight 0 (a None texture would sample as white).
        masks = [encoder.amplitude(t[None])[0] if t is not None else image.new_zeros(3, 1, 1) for t in mesh.textures]
        given_footprint = None  # the textures' footprint, where an import was weighed against it and not taken
        if imports is not None and n_images == 1:  # the asset as its import made it, where that explains the picture
            from ..reading.imports import beats_footprint, pick, pick_normals

            if imports.normals is not None and pick_normals(found, imports.normals, cameras, (n_images, height, width)):
                mesh = replace(mesh, normals=imports.normals)
                found = relit_residual(mesh, image, cameras)
            chosen = pick(found, mesh.textures, imports.textures, (n_images, height, width))
            if chosen is not None:
                imported = replace(mesh, textures=imports.textures[chosen])
                candidate = relit_residual(imported, image, cameras)
                given_footprint = picture_footprint(mesh, found, cameras, height, width) if footprint else None
                if given_footprint is None or beats_footprint(candidate, found, given_footprint, (n_images, height, width)):
                    mesh, found, given_footprint = imported, candidate, None
        gain = (found.expected / found.albedo.clamp_min(0.02)).mean(1).clamp(0.0, 3.0)  # shading at the pixel
        pixel = found.fragments.pixel.index_select(0, found.keep)
        sampled = None
        if footprint:  # a picture read before (a second look) keeps the footprint found then
            from ..reading.footprint import chosen_before, remember_choice

            known = chosen_before(image) if n_images == 1 else None
            if known is None and given_footprint is not None:  # worked out above for the textures as given
                sampled = given_footprint
            else:
                sampled = picture_footprint(mesh, found, cameras, height, width, known=known)
            if n_images == 1 and known is None:
                remember_choice(image, sampled)
        expected = found.expected if sampled is None else sampled.expected
        fit = model.config.read_brightness if brightness else -1.0
        dequantized = None
        before, saved = expected, (lambda prediction: prediction)  # the prediction before and after the codec
        if compression:  # the prediction as the picture's codec saved it (`reading.compression`)
            from ..reading import compression as codecs

            expected, chosen = codecs.recompressed(image, expected, pixel)
            saved = lambda prediction: codecs.recompressed(image, prediction, pixel)[0]  # noqa: E731 (the codec found)
        if model.config.read_affine > 0.0 and n_images == 1 and LINEAR_LIGHT:  # another engine's shading?
            found, sampled, before, expected = _linear_if_better(mesh, image, cameras, footprint, found, sampled,
                                                                 before, expected, saved, pixel)
        if compression:
            if fit < 0.0 and codecs.reads_quantiser(image, chosen):  # no brightness fit: a JPEG read through its quantiser
                if model.config.read_affine > 0.0:  # the unrounded prediction as another engine showed it
                    before = _affine_where_it_fits(found.seen, before, _read_along(model).to(image), pixel,
                                                   (n_images, height, width), model.config.read_affine,
                                                   model.config.read_highpass)
                dequantized = codecs.dequantized(image, before, pixel, chosen)
        usable = torch.ones_like(gain, dtype=torch.bool) if sampled is None else sampled.usable
        textured = torch.tensor([t is not None for t in mesh.textures], device=usable.device)
        usable = usable & textured.index_select(0, found.material)  # nor in the whitening's statistics
        # nor where the picture or the prediction is near white: a highlight that clipped kept no mark, and
        # the clipped picture, or the prediction rounded there by the codec, is no evidence of one
        usable = usable & (found.seen.amax(1) < NEAR_WHITE) & (expected.amax(1) < NEAR_WHITE)
        colour = _read_along(model).to(image)
        config = model.config
        if fit == 0.0:
            # Each pixel's own brightness against the prediction (a shadow, one of two coincident sheets
            # lit from behind, a tone curve): taken off along the predicted colour, so the residual
            # keeps the part of the mark orthogonal to it, and the template scales by what is left.
            ratio = (found.seen * expected).sum(1) / (expected * expected).sum(1).clamp_min(1e-6)
            residual = found.seen - ratio[:, None] * expected
            direction = expected / expected.norm(dim=1, keepdim=True).clamp_min(1e-6)
            gain = gain * ratio.clamp(0.0, 3.0) * (1.0 - (direction * colour).sum(1) ** 2)
            residual, taken = take_off_linear_light(residual, expected, pixel, (n_images, height, width))
            along = (residual * colour).sum(1)
            kept = 1.0 - (direction * colour).sum(1) ** 2  # the mark keeps this much of its colour ...
            gain = gain * (kept - (taken * colour).sum(1) ** 2) / kept.clamp_min(1e-6)  # ... and loses this
        elif fit > 0.0:
            # The brightness as a smooth field (Gaussian sigma `fit` px): a mark along the predicted
            # colour (grey) that changes from cell to cell is not taken for a change of brightness.
            from ..models.spread import local_mean

            ratio = (found.seen * expected).sum(1) / (expected * expected).sum(1).clamp_min(1e-6)
            ratio = local_mean(ratio.clamp(0.0, 3.0), pixel, (n_images, height, width), fit)
            along = ((found.seen - ratio[:, None] * expected) * colour).sum(1)
            gain = gain * ratio
        else:
            if config.read_affine > 0.0:  # another engine's shading, tone and colour, fitted locally
                expected = _affine_where_it_fits(found.seen, expected, colour, pixel, (n_images, height, width),
                                                 config.read_affine, config.read_highpass)
            along = ((found.seen - expected) * colour).sum(1)
            if dequantized is not None:  # a mark a x colour shows as a x (luma . colour) in luminance
                along = torch.where(dequantized.isnan(), along, dequantized / _luma_along(colour))
        whitened = torch.zeros_like(along)
        if bool(usable.any()):
            options = {"highpass": config.read_highpass, "window": config.read_window} | (whitening or {})
            whitened[usable] = whiten(along[usable], pixel[usable], (n_images, height, width), **options)
        whitened = whitened * gain
        grids = grids or (encoder.chips,)
        point = torch.ones(n_images, dtype=torch.bool) if sampled is None else sampled.sigma.isnan()
        at_point = point.to(found.image_index.device).index_select(0, found.image_index)
        sums = whitened.new_zeros(n_images, sum(chips ** 2 for chips in grids))
        if bool(point.any()):
            amplitude = sample_textures(masks, found.uv, found.material).norm(dim=1)  # the JND mask, unsigned
            sums = cell_sums(encoder, whitened * amplitude * at_point, found.uv, found.image_index, n_images, grids)
        if bool(point.all()):
            return sums
        # The template under an area footprint: the adjoint of (blur, then average each pixel's
        # sub-pixel samples), i.e. the whitened residual blurred and spread over the sub-pixels.
        canvas = whitened.new_zeros(n_images * height * width).index_copy(0, pixel, whitened * ~at_point)
        canvas = canvas.reshape(n_images, 1, height, width)
        for index in torch.nonzero(~point).squeeze(1).tolist():
            resized = sampled.resized is not None and not bool(sampled.resized[index].isnan())
            if resized and footprints.RESAMPLED_ADJOINT:  # the resize's own adjoint, on the source render's pixels
                sums[index] += _resized_sums(encoder, masks, mesh, index, cameras[[index]], canvas[index: index + 1],
                                             float(sampled.resized[index]), grids)[0]
                canvas[index] = 0.0
                continue
            # a resized picture's template blur is its own; an area footprint's blur is narrowed for the template
            width = float(sampled.sigma[index]) * (1.0 if resized else AREA_TEMPLATE_SCALE)
            canvas[index] = gaussian_blur(canvas[index: index + 1], width)[0]
        fragments = sampled.fragments
        spread = canvas.reshape(-1).index_select(0, sampled.parent) / sampled.scale ** 2  # the adjoint of the mean
        uv = interpolate(mesh.uvs.expand(n_images, -1, -1) if mesh.uvs.shape[0] == 1 else mesh.uvs, fragments)
        amplitude = sample_textures(masks, uv, per_fragment(mesh.face_material, fragments)).norm(dim=1)
        return sums + cell_sums(encoder, spread * amplitude, uv, fragments.batch, n_images, grids)


def _resized_sums(encoder, masks: list, mesh: MeshBatch, index: int, camera: Cameras, canvas: torch.Tensor,
                  factor: float, grids: tuple[int, ...]) -> torch.Tensor:
    """The matched filter's cell sums (1, sum C*C) of one picture found resized by `factor`: its
    whitened residual on the picture's pixels (1, 1, H, W) carried back through the resize
    (`footprint.resized_adjoint`) onto the pixels of the source render, and summed per cell at those
    pixels' texture coordinates, as a picture read at its own size is (the splat's blur there left
    out, as it is there: docs/reading.md). `index`: the picture's mesh where `mesh` holds one per
    picture. Picture and original only: no key."""
    from ..models.spread import cell_sums
    from ..render import rasterize, sample_textures
    from ..render.renderer import per_fragment

    source = footprints.resized_adjoint(canvas, factor)
    height, width = source.shape[-2:]
    own = lambda table: table if table.shape[0] == 1 else table[index: index + 1]  # noqa: E731 (this picture's mesh)
    positions = own(mesh.positions)
    fragments = rasterize(camera.to(positions.device, positions.dtype).world_to_clip(positions, width / height),
                          own(mesh.faces) if mesh.faces.dim() == 3 else mesh.faces, height, width)
    values = source.reshape(-1).index_select(0, fragments.pixel)
    uv = interpolate(own(mesh.uvs), fragments)
    material = own(mesh.face_material) if mesh.face_material.dim() == 2 else mesh.face_material
    amplitude = sample_textures(masks, uv, per_fragment(material, fragments)).norm(dim=1)
    return cell_sums(encoder, values * amplitude, uv, fragments.batch, 1, grids)


def _linear_if_better(mesh, image, cameras, footprint, found, sampled, before, after, saved, pixel):
    """The reading's prediction of one picture, (found, sampled, before the codec, after it), made in
    linear light instead (`reading.linear_light`) where the sRGB one (`after`, through the picture's
    codec) misses the picture's fine detail by more than our own pictures are missed and the linear one,
    through the same codec (`saved`), misses it clearly less. A picture read before (the same tensor: a
    second look) makes its linear prediction under the footprint found for it then
    (`linear_light.chosen_before`: how the engine sampled the picture does not change with the camera),
    without searching the others again; the choice between the two predictions is made afresh under
    each camera (the first camera's can be the wrong one's: docs/reading.md, stage 6). Picture and
    original only: no key."""
    from ..reading import linear_light

    shape = (1, image.shape[-2], image.shape[-1])
    misfit = linear_light.detail_misfit(found.seen, after, pixel, shape)
    if misfit <= linear_light.TRY_ABOVE ** 2:
        return found, sampled, before, after
    known = linear_light.chosen_before(image)
    candidate = linear_light.linear_prediction(mesh, image, cameras, footprint, found, known=known)
    if candidate is None:
        return found, sampled, before, after
    if known is None:
        linear_light.remember_choice(image, candidate[1])
    linear = candidate[0].expected if candidate[1] is None else candidate[1].expected
    through = saved(linear)
    if linear_light.detail_misfit(found.seen, through, pixel, shape) >= linear_light.PICK_BELOW * misfit:
        return found, sampled, before, after
    return candidate[0], candidate[1], linear, through


OWN_MARK_SCALES = (0.5, 1.0)  # `own_mark_pvalue`'s whitening windows, in cells (docs/payload.md: measured against (2.0,))


class SpreadMethod(Method):
    """The keyed spread-spectrum mark and its matched filter."""

    name = "spread"
    params_named = ("n_bits", "chips", "coarse_chips", "coarse_below", "fine_chips", "fine_above", "mark_colour",
                    "texture_psnr", "activity_window", "activity_floor", "pattern_seed", "bit_block", "pilot_share",
                    "pilot_block", "pilot_chips", "pilot_gain", "read_highpass",
                    "read_window", "read_brightness", "read_affine", "read_imports")
    informed = True
    calibrated = True
    takes_strength = True
    flip_budget = True
    second_look = True

    def __init__(self, model):
        super().__init__(model)
        self.encoder = model.texture_encoder
        self._grids_of: tuple | None = None  # (prepared original, its grids_to_read)
        self._imports_of: tuple | None = None  # (prepared original, its `reading.imports.Imports`)

    def describe(self) -> str:
        """The model card's sentence on the embedder and the extractor."""
        config = self.model.config.to_dict()
        coarse, fine = config.get("coarse_chips", 0), config.get("fine_chips", 0)
        others = ([f"{coarse}^2 on a mesh whose {config['chips']}^2 cells would be under {config['coarse_below']} px in a "
                   "256^2 view (a minified texture)"] if coarse else []) + \
                 ([f"{fine}^2 where they would be over {config['fine_above']} px (a magnified texture, resampled up when "
                   "it has fewer texels)"] if fine else [])
        coarse_text = f" ({'; '.join(others)}; detection reads both grids there)" if others else ""
        share = config.get("pilot_share", 0.0)
        wide = config.get("pilot_block", 1)
        blocks = f" on {wide} x {wide} blocks of cells of one sign" if wide > 1 else ""
        capped = config.get("pilot_chips", 0)
        blocks += (f" (on a finer grid than {capped}^2, on blocks of cells as wide as a {capped}^2 grid's, one sign "
                   "each)" if capped else "")
        gain = config.get("pilot_gain", 1.0)
        blocks += f" at {gain:g} of the message's amplitude" if gain != 1.0 else ""
        pilot_text = (f"{share:.0%} of them a pilot{blocks} carrying the key's own signs (a presence test whatever the message, "
                      "beside the bits' test, a weighted Bonferroni giving it nine tenths of the false-positive rate), the others " if share else "")
        text = (f"keyed spread-spectrum mark (`models/spread.py`): {config['chips']}^2 cells over the UV square"
                        f"{coarse_text}, {pilot_text}each carrying one of the bits with a random sign, colour `{config['mark_colour']}`, amplitude "
                        f"shaped by local texture activity (window {config['activity_window']}, floor "
                        f"{config['activity_floor']}), laid on the texels the mesh shows and scaled to texture PSNR {config['texture_psnr']} dB over those at strength 1; "
                        "read by a matched filter (the residual whitened in the picture) after un-rendering the picture onto the "
                        "original mesh relit to match it "
                        "(detection needs the original mesh and the picture's camera: from the PNG's metadata, or "
                        "registered). Its soft bits are z-scores (given the picture, a Rademacher sum per bit without a mark: exact p-values, `payload.detection_pvalue`)")
        return text

    def key_seed(self, key) -> int:
        from .. import payload

        return payload.key_seed(key)

    # ------------------------------------------------------------ embed
    def layout(self, mesh, note: bool = False):
        """Faces without UV area (a palette texture) get charts of their own (`methods.charts`), so that
        they carry the mark too. A charted mesh is its own layout. `note`: say on stderr what charting added."""
        import sys

        from .charts import chart_palette_faces

        charted = chart_palette_faces(mesh)
        if note and charted is not mesh:
            sizes = [f"{a.texture.shape[1]}x{a.texture.shape[0]} -> {b.texture.shape[1]}x{b.texture.shape[0]}"
                     for a, b in zip(mesh.materials, charted.materials)
                     if a.texture is not None and a.texture.shape != b.texture.shape]
            print(f"meshseal: note: faces without UV area (the texture used as a colour palette) got charts of "
                  f"their own so that they carry the mark too: {charted.n_vertices - mesh.n_vertices} vertices "
                  f"added, texture {', '.join(sizes)}", file=sys.stderr)
        return charted

    def mark_grid(self, mesh) -> int | None:
        """Cells per side of the UV square the mark uses on `mesh` (coarser where its texture is
        minified, finer where magnified: `SpreadSpectrumEncoder.grid_for`)."""
        if mesh.uvs is None or all(m.texture is None for m in mesh.materials):
            return None
        mesh = self.layout(mesh)
        return self.encoder.grid_for(mesh.positions, textured_faces(mesh), mesh.uvs)

    def embed(self, mesh, message, key_seed, strength, warn):
        import sys

        from ..errors import MeshsealError
        from ..models.spread import palette_share, texels_used

        if mesh.uvs is None or all(m.texture is None for m in mesh.materials):
            raise MeshsealError(f"{source_prefix(mesh)}the mesh has no texture with UVs to carry the watermark, "
                                f"and this model only marks textures")
        marked = self.layout(mesh.copy(), note=True)
        grid = self.mark_grid(marked)
        palette = palette_share(marked.positions, textured_faces(marked), marked.uvs)
        if palette >= PALETTE_WARNING and warn:
            print(f"meshseal: warning: {palette:.0%} of the textured surface has faces without UV area (the "
                  "texture used as a colour palette) and could not be given charts (a tiled texture, or vertices "
                  "shared with another material): the mark has little room there and may read poorly",
                  file=sys.stderr)
        for index, material in enumerate(marked.materials):
            if material.texture is None:
                continue
            texture = material.texture.to(self.device).permute(2, 0, 1).unsqueeze(0)
            used = texels_used(marked.uvs, marked.faces[marked.face_material == index], *texture.shape[-2:])
            try:
                marked_texture = self.encoder(texture, message, strength, key_seed, grid, used)
            except ValueError as error:
                raise MeshsealError(str(error)) from None
            material.texture = marked_texture[0].permute(1, 2, 0).cpu()
        return marked

    # ------------------------------------------------------------ read
    def prepare(self, mesh):
        return informed_original(self, mesh)

    def evidence(self, original, picture, camera):
        """Matched-filter cell sums of every grid a mark may use on this mesh, side by side
        (`soft_bits` splits them)."""
        return spread_evidence(self.model, original, picture, camera, grids=self.grids_to_read(original),
                               imports=self.imports_of(original))[0].cpu()

    def imports_of(self, original):
        """The prepared original as an asset's import may have changed it (`reading.imports.Imports`:
        its textures, its normals), made once for it; None where the model's `read_imports` is off."""
        if not self.model.config.read_imports:
            return None
        if self._imports_of is None or self._imports_of[0] is not original:
            from ..reading.imports import imported

            self._imports_of = (original, imported(original))
        return self._imports_of[1]

    def read_pictures(self, original, pictures, cameras, key_seed=None) -> torch.Tensor:
        """Soft bits (B, N) of pictures (B, 3, H, W) of the prepared `original` seen from `cameras`,
        on the model's own grid under the pattern of `key_seed` (None: the model's own)."""
        from ..models.spread import soft_bits

        return soft_bits(self.encoder, spread_evidence(self.model, original, pictures, cameras), key_seed)

    def grids_to_read(self, original) -> tuple[int, ...]:
        """`grids_to_read` of a prepared original, worked out once for it rather than per picture (it
        measures every face, and a folder holds many pictures of one asset)."""
        if self._grids_of is None or self._grids_of[0] is not original:
            self._grids_of = (original, self.encoder.grids_to_read(*textured_geometry(original)))
        return self._grids_of[1]

    def soft_bits(self, evidence, key, expected):
        """Soft bits and cell weights of the cell grid (of those `evidence` holds side by side) whose
        mark is likeliest, and the number of grids tried. The pick is by the statistic the p-value
        grows with (sum of z^2; with an `expected` message, its correlation with the message's signs; with
        several, the largest),
        so only the picked grid pays for an exact p-value; any rule of picking keeps the Bonferroni bound."""
        from ..models.spread import bit_weights, soft_bits, split_grids

        key_seed = self.key_seed(key)
        parts = split_grids(self.encoder, evidence)
        softs = [soft_bits(self.encoder, sums, key_seed)[0].double() for sums in parts]
        if expected is None:
            scores = [float((soft * soft).sum()) for soft in softs]
        else:  # one message (N,) or a list of them (M, N): the best agreement
            scores = [float(((2.0 * expected.to(soft) - 1.0) @ soft).max()) for soft in softs]
        best = max(range(len(parts)), key=scores.__getitem__)
        return softs[best], bit_weights(self.encoder, parts[best], key_seed)[0].double(), len(parts)

    def pilot_pvalue(self, evidence, key):
        """The pilot's test (`models.spread.pilot_z`) on each grid `evidence` holds: the smallest exact
        p-value times the grids. None without a pilot."""
        from .. import payload
        from ..models.spread import pilot_z, split_grids

        if not self.encoder.pilot_slots:
            return None
        key_seed = self.key_seed(key)
        parts = split_grids(self.encoder, evidence)
        p_values = []
        for sums in parts:
            z, weights = pilot_z(self.encoder, sums[0].double(), key_seed)
            p_values.append(float(payload.match_pvalue(z[None], [1], weights[None])))
        return min(1.0, len(parts) * min(p_values))

    def own_mark_pvalue(self, original, key=None) -> float | None:
        """The p-value that the textures of a prepared `original` carry a mark under `key`
        themselves, read from the textures alone (`models.spread.texture_cell_sums`, every grid
        detection reads, their sums over the materials, Bonferroni over the grids): under the FPR,
        the mesh given as the original is a marked copy, against which a picture of it reads no mark."""
        from .. import payload
        from ..models.spread import bit_weights, soft_bits, split_grids, texels_used, texture_cell_sums

        key_seed = self.key_seed(key)
        grids = self.grids_to_read(original)
        faces = original.faces[0] if original.faces.dim() == 3 else original.faces
        material = original.face_material[0] if original.face_material.dim() == 2 else original.face_material
        total = None
        for index, texture in enumerate(original.textures):
            if texture is None:
                continue
            texture = texture[None] if texture.dim() == 3 else texture[:1]  # (1, 3, H, W)
            used = texels_used(original.uvs[0], faces[material == index], *texture.shape[-2:])
            # Two whitening windows, half a cell and a cell: the host texture leaves less in the first, the mark
            # more in the second.
            sums = texture_cell_sums(self.encoder, texture, used, grids, OWN_MARK_SCALES)
            total = sums if total is None else total + sums
        if total is None:
            return None
        parts = split_grids(self.encoder, total.cpu())
        p_values = [float(payload.detection_pvalue(soft_bits(self.encoder, sums, key_seed)[0].double(),
                                                   bit_weights(self.encoder, sums, key_seed)[0].double()))
                    for sums in parts]
        p_value = min(1.0, len(parts) * min(p_values))
        pilot = self.pilot_pvalue(total.cpu(), key)
        return payload.any_mark_pvalue(p_value, pilot)

    # ------------------------------------------------------------ training pass
    def mark_batch(self, batch, message, vertex_mask):
        from .batches import batch_texels_used

        shown = batch_texels_used(batch) if vertex_mask is not None else None
        texture = self.encoder(batch["texture"], message, used=shown)
        return batch["normals"], batch["uvs"], texture, shown

    def read_batch(self, pictures, alpha, original_mesh, cameras, original_image, background, frame_size,
                   distortions_2d, generator, reference_mix):
        from ..models.spread import soft_bits

        return pictures, soft_bits(self.encoder, spread_evidence(self.model, original_mesh, pictures, cameras))
