"""One pass of the whole pipeline on a batch: embed -> distort (3D) -> render -> distort (2D) -> frame
(blind decoders) or un-render onto the original's UV space (informed ones) -> decode. Shared by
training, validation and `meshseal eval` so they measure the same thing."""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from .data.dataset import vertex_mask
from .distortions import Distortions2D, Distortions3D, gaussian_blur
from .framing import boxes_from_mask, crop_boxes
from .models import WatermarkModel
from .models.spread import SpreadSpectrumEncoder, texels_used
from .models.surface import SurfaceCodeEncoder, read_picture, texel_columns
from .render import (Cameras, MeshBatch, MeshRenderer, interpolate, lights_at, pixels_at, relight_fragments,
                     sample_any_lights, sample_any_view_cameras, sample_seed_cameras, sample_seed_lights, unrender)
from .render.lighting import K_AMBIENT


@dataclass
class PassOutput:
    logits: torch.Tensor
    message: torch.Tensor
    texture: torch.Tensor
    texture_marked: torch.Tensor
    normals: torch.Tensor
    normals_marked: torch.Tensor
    uvs: torch.Tensor
    uvs_marked: torch.Tensor
    render: torch.Tensor  # (B, 3, H, W) original
    render_marked: torch.Tensor  # (B, 3, H, W) watermarked, before 2D distortions
    decoded_input: torch.Tensor  # (B, 3, S, S) what the decoder saw (informed: UV maps (B, 10, G, G))
    vertex_mask: torch.Tensor | None  # (B, V) real vertices (None: no padding information)
    coverage: torch.Tensor  # (B, H, W) the marked object's interior pixels in the renders
    shown: torch.Tensor | None = None  # (B, 1, H, W) the texels a spread mark lay on (`batch_texels_used`)


def sample_views(n: int, sampler: str, generator: torch.Generator):
    """Cameras and lights from the seed's ranges ('seed') or from anywhere ('any')."""
    if sampler == "seed":
        return sample_seed_cameras(n, generator), sample_seed_lights(n, generator)
    if sampler == "any":
        return sample_any_view_cameras(n, generator), sample_any_lights(n, generator)
    raise ValueError(f"unknown view sampler '{sampler}' (seed | any)")


def random_backgrounds(n: int, generator: torch.Generator) -> torch.Tensor:
    """Plain backgrounds: a random grey level, sometimes tinted, per picture."""
    grey = torch.rand(n, 1, generator=generator).expand(n, 3)
    tint = 0.15 * (torch.rand(n, 3, generator=generator) - 0.5)
    return (grey + tint).clamp(0.0, 1.0)


def frame(image: torch.Tensor, alpha: torch.Tensor, size: int, background: torch.Tensor) -> torch.Tensor:
    """Crop the object's bounding box (from the coverage) into a square size x size picture."""
    boxes = boxes_from_mask(alpha.detach().cpu() > 0.5)
    return crop_boxes(image, boxes, size, background.to(image))


def jitter_cameras(cameras: Cameras, pixels: float, size: int, generator: torch.Generator) -> Cameras:
    """Move eye and look-at point by Gaussian noise worth about `pixels` pixels of a size x size
    picture at the look-at distance: the pose error a registration leaves."""
    if pixels <= 0:
        return cameras
    distance = (cameras.eye - cameras.at).norm(dim=-1, keepdim=True)
    sigma = pixels * 2.0 * distance * math.tan(math.radians(cameras.fov_y) / 2) / size
    shift = lambda: sigma * torch.randn(cameras.eye.shape, generator=generator).to(cameras.eye)  # noqa: E731
    return replace(cameras, eye=cameras.eye + shift(), at=cameras.at + shift())


@dataclass
class RelitResidual:
    """A picture's covered interior pixels next to the original mesh relit to match it: what the
    picture shows (P, 3), what the original predicts there (P, 3), its unlit albedo (P, 3), the
    texture coordinates (P, 2), material (P,) and picture index (P,) of each pixel, the `fragments`
    they were taken from (`keep` (P,) indexes them), and the fitted lighting: the original with the
    fitted ambient factors (`relit`) and the point `lights`."""

    seen: torch.Tensor
    expected: torch.Tensor
    albedo: torch.Tensor
    uv: torch.Tensor
    material: torch.Tensor
    image_index: torch.Tensor
    keep: torch.Tensor
    fragments: object
    relit: MeshBatch
    lights: object


def _with_ambient_per_image(mesh: MeshBatch, ambient: torch.Tensor) -> MeshBatch:
    """`mesh` with the fitted ambient factors (B, 3), one per picture: B meshes with a material each
    take theirs; one mesh of M materials seen B times gets its material table repeated per picture."""
    n_images, n_materials = len(ambient), mesh.ambient.shape[0]
    if n_materials == n_images and (mesh.face_material.dim() == 2 or n_images == 1):
        return replace(mesh, ambient=ambient)
    material = mesh.face_material if mesh.face_material.dim() == 2 else mesh.face_material.expand(n_images, -1)
    offsets = n_materials * torch.arange(n_images, device=material.device).unsqueeze(1)
    return replace(mesh, face_material=material + offsets, textures=list(mesh.textures) * n_images,
                   ambient=ambient.repeat_interleave(n_materials, dim=0), diffuse=mesh.diffuse.repeat(n_images, 1),
                   specular=mesh.specular.repeat(n_images, 1), shininess=mesh.shininess.repeat(n_images))


def relit_residual(mesh: MeshBatch, image: torch.Tensor, cameras: Cameras, light_from: str = "all") -> RelitResidual:
    """Rasterize the original `mesh` from `cameras` over the picture (B, 3, H, W), fit a point light
    that explains the picture from the original texture (`relight_fragments`) and render the original
    under it. Silhouette pixels (partly background) are left out. `light_from` "flat" fits the light on
    the half of the object's pixels where the albedo is flattest (`flattest_half`): a camera a pixel or
    two off then barely changes what the fit sees (registration refines such cameras)."""
    from .render.renderer import per_fragment

    n_images, height, width = len(cameras), image.shape[-2], image.shape[-1]
    with torch.no_grad():
        unlit = replace(mesh, ambient=torch.full_like(mesh.ambient, 1.0 / K_AMBIENT))
        flat = MeshRenderer()(unlit, cameras, lights_at(cameras.eye, 0.0), height, width)  # antialiased albedo
        fragments = flat.fragments
        uv = interpolate(mesh.uvs.expand(n_images, -1, -1) if mesh.uvs.shape[0] == 1 else mesh.uvs, fragments)
        albedo = pixels_at(flat.image, fragments)
        fit_on = flattest_half(flat.image, fragments) if light_from == "flat" else None
        _, ambient, lights = relight_fragments(mesh, fragments, cameras, pixels_at(image, fragments), albedo, fit_on)
        relit = _with_ambient_per_image(mesh, ambient)
        relit_render = MeshRenderer()(relit, cameras, lights, height, width, fragments=fragments)
        inside = pixels_at(relit_render.rgba[..., 3:].permute(0, 3, 1, 2), fragments)[:, 0] > 0.999
        keep = torch.nonzero(inside).squeeze(1)
        pick = lambda values: values.index_select(0, keep)  # noqa: E731
        return RelitResidual(pick(pixels_at(image, fragments)).to(image), pick(pixels_at(relit_render.image, fragments)).to(image),
                             pick(albedo).to(image), pick(uv).to(image), pick(per_fragment(mesh.face_material, fragments)),
                             pick(fragments.batch), keep, fragments, relit, lights)


def flattest_half(albedo: torch.Tensor, fragments, reach: int = 2) -> torch.Tensor:
    """Which covered pixels of `fragments` (P,) lie where the albedo render (B, 3, H, W) varies least
    within `reach` pixels: the flatter half of each image's pixels, by rank. Steps to the next pixel
    measure the variation (a central difference misses stripes one pixel wide)."""
    step_x = F.pad((albedo[..., :, 1:] - albedo[..., :, :-1]).abs(), (0, 1))
    step_y = F.pad((albedo[..., 1:, :] - albedo[..., :-1, :]).abs(), (0, 0, 0, 1))
    activity = (step_x + step_y).amax(1, keepdim=True)
    activity = pixels_at(F.max_pool2d(activity, 2 * reach + 1, 1, reach), fragments)[:, 0]
    flat = torch.zeros_like(activity, dtype=torch.bool)
    for index in torch.unique(fragments.batch).tolist():
        chosen = torch.nonzero(fragments.batch == index).squeeze(1)
        flat[chosen[activity[chosen].argsort(stable=True)[: (len(chosen) + 1) // 2]]] = True
    return flat


def uv_maps(mesh: MeshBatch, image: torch.Tensor, cameras: Cameras, grid: int, reference: torch.Tensor | None = None,
            reference_mix: float = 0.0) -> torch.Tensor:
    """What the learned informed decoder reads: the picture (B, 3, H, W) seen from `cameras`,
    un-rendered onto the original mesh's UV grid -> (B, 10, grid, grid).

    Channels: the residual left by the relit original (x10: mostly the watermark; `relit_residual`),
    the picture (3), the original albedo (3), coverage (1). Training may blend in the exact `reference`
    (the original rendered under the picture's own light) with weight `reference_mix`: a curriculum.
    """
    found = relit_residual(mesh, image, cameras)
    expected = found.expected
    if reference is not None and reference_mix > 0:
        exact = pixels_at(reference, found.fragments).index_select(0, found.keep).to(image)
        expected = reference_mix * exact + (1.0 - reference_mix) * expected
    seen = pixels_at(image, found.fragments).index_select(0, found.keep)  # differentiable in the picture
    values = torch.cat([10.0 * (seen - expected), seen, found.albedo], dim=1)
    return unrender(values, found.uv, found.image_index, len(cameras), grid)


def read_bits(model: WatermarkModel, mesh: MeshBatch, image: torch.Tensor, cameras: Cameras,
              key_seed: int | None = None) -> torch.Tensor:
    """Informed detection: soft bits (B, N) (logits, or matched-filter z for spread-spectrum models,
    with the pattern of `key_seed`) from pictures (B, 3, H, W) of the original `mesh` taken with `cameras`."""
    if model.config.decoder != "matched":
        return model.decode(uv_maps(mesh, image, cameras, model.config.uv_grid))
    from .models.spread import soft_bits

    return soft_bits(model.texture_encoder, spread_evidence(model, mesh, image, cameras), key_seed)


FOOTPRINT_SIGMAS = (0.35, 0.5, 0.75, 1.0)
LINEAR_LIGHT_SIGMA = 2.0  # px: window of the residual's variance along and across light added in linear light
LINEAR_LIGHT_RATIO = 1.0  # taken off fully where the variance along it is this many times that across
LINEAR_LIGHT_DISTINCT = 0.05  # and where its direction differs this much (sine) from the brightness's


@dataclass
class Footprint:
    """How a picture sampled the surface, as far as the original's texture shows: per picture, point
    samples at pixel centres (our renderer, OpenGL without multisampling) or the average over each
    pixel's area blurred by a Gaussian of `sigma` pixels (antialiasing and pixel filters of Blender and
    game engines, mipmaps, resizing, blur). `expected` (P, 3): the relit original under each picture's
    footprint at the kept pixels; `usable` (P,): the kept pixels that footprint covers wholly; `sigma`
    (B,): NaN for point samples. `fragments`: the rasterization `scale` times finer that sampled each
    pixel's area, and `parent` (F,): the picture pixel (flat index into B*H*W) of each of its
    fragments; the matched filter's template is built from them."""

    expected: torch.Tensor
    usable: torch.Tensor
    sigma: torch.Tensor
    fragments: object
    parent: torch.Tensor
    scale: int


def supersampling(height: int, width: int) -> int:
    """Sub-pixel samples per picture pixel along each axis for `picture_footprint`: 4 up to 256^2,
    fewer for larger pictures (whose pixels cover less texture) to bound the render to about 1024^2."""
    return max(1, min(4, 1024 // max(height, width)))


def picture_footprint(mesh: MeshBatch, found: RelitResidual, cameras: Cameras, height: int, width: int,
                      sigmas: tuple[float, ...] = FOOTPRINT_SIGMAS) -> Footprint:
    """Pick, per picture, the footprint (point samples, or the pixel area blurred by one of `sigmas`)
    under which the relit original best predicts the picture's fine detail: the largest normalised
    correlation between the picture and the prediction, both high-passed (their local mean over the
    object's pixels, sigma 1.5 px, taken off: a relighting misfit is slow and must not decide), over
    the pixels every candidate covers. The pixel's area is the mean of a rasterization `supersampling`
    times finer, shaded and summed per pixel without forming the finer image. The choice looks at
    the picture and the original only, never at a key, so the matched filter's null stays the same."""
    from .distortions import blur_radius
    from .models.spread import local_mean, within_reach
    from .render import rasterize

    scale = supersampling(height, width)
    n_images = len(cameras)
    relit = found.relit
    positions = relit.positions.expand(n_images, -1, -1) if relit.positions.shape[0] == 1 else relit.positions
    # Hard edges: the sub-pixel mean is the antialiasing, and only wholly covered pixels are used.
    fine = rasterize(cameras.world_to_clip(positions, width / height), relit.faces, height * scale, width * scale)
    lit = MeshRenderer().shade(relit, cameras, found.lights, fine)
    within = fine.pixel % (height * scale * width * scale)
    row = torch.div(within, width * scale, rounding_mode="floor")
    column = within - row * width * scale
    parent = fine.batch * height * width + torch.div(row, scale, rounding_mode="floor") * width + column // scale
    sums = lit.new_zeros(n_images * height * width, 4).index_add_(0, parent, F.pad(lit, (0, 1), value=1.0)) / scale ** 2
    kept = found.fragments.pixel.index_select(0, found.keep)
    usable = sums[:, 3].index_select(0, kept) > 0.999
    widths = ((0.0,) if scale > 1 else ()) + tuple(sigmas)
    # Blurred at the picture's resolution, over the window the kept pixels and the widest blur reach.
    local, (_, rows, columns), (top, left) = within_reach(kept, (n_images, height, width), blur_radius(max(widths)))
    averaged = sums[:, :3].reshape(n_images, height, width, 3)[:, top: top + rows, left: left + columns]
    averaged = averaged.permute(0, 3, 1, 2)
    pick = lambda image: image.permute(0, 2, 3, 1).reshape(-1, 3).index_select(0, local)  # noqa: E731
    candidates = [found.expected] + [pick(gaussian_blur(averaged, s)) for s in widths]
    pixel = kept[usable]
    image = found.image_index[usable]
    values = torch.cat([found.seen] + candidates, 1)[usable]  # (U, 3 + 3K): one masked blur for all
    detail = values - local_mean(values, pixel, (n_images, height, width), 1.5)
    seen, predicted = detail[:, :3].unsqueeze(1), detail[:, 3:].reshape(len(pixel), len(candidates), 3)
    agree = seen.new_zeros(n_images, len(candidates)).index_add_(0, image, (seen * predicted).sum(-1))
    power = seen.new_zeros(n_images, len(candidates)).index_add_(0, image, (predicted * predicted).sum(-1))
    scores = torch.nan_to_num(agree / power.sqrt(), nan=-float("inf"))
    choice = scores.argmax(1)  # (B,); a picture with nothing to compare keeps point samples
    sigma = torch.tensor((float("nan"),) + widths, device=choice.device)[choice]
    per_pixel = choice.index_select(0, found.image_index)
    expected = torch.stack(candidates).gather(0, per_pixel[None, :, None].expand(1, -1, 3))[0]
    usable = usable | (per_pixel == 0)  # point samples keep every interior pixel, as before
    return Footprint(expected, usable, sigma, fine, parent, scale)


def linear_light_direction(expected: torch.Tensor) -> torch.Tensor:
    """How each predicted sRGB colour (P, 3) moves when white light is added to it in linear light ->
    directions (P, 3), the part orthogonal to the colour itself (its brightness is fitted on its own)
    of a unit vector.

    Every physically based engine shades in linear light: a specular highlight, Workbench's studio
    light or light bounced off the rest of the scene adds to the linear value. In sRGB that moves each
    channel by the slope of the sRGB curve at its linear value: steep on dark channels, so it lifts a
    saturated colour's darkest channel most (a deck chair's blue stripes) and is no longer white; on a
    grey pixel it is the brightness, and the direction returned is short there."""
    linear = torch.where(expected <= 0.04045, expected / 12.92, ((expected.clamp_min(0.0) + 0.055) / 1.055) ** 2.4)
    slope = torch.where(linear <= 0.0031308, torch.full_like(linear, 12.92),
                        1.055 / 2.4 * linear.clamp_min(0.0031308) ** (1.0 / 2.4 - 1.0))
    slope = F.normalize(slope, dim=1)
    brightness = F.normalize(expected, dim=1, eps=1e-6)
    return slope - (slope * brightness).sum(1, keepdim=True) * brightness


def take_off_linear_light(residual: torch.Tensor, expected: torch.Tensor, pixel: torch.Tensor,
                          shape: tuple[int, int, int]) -> tuple[torch.Tensor, torch.Tensor]:
    """Residuals (P, 3) (brightness already taken off) with light added in linear light
    (`linear_light_direction`: a highlight, bounced light, a path tracer's noise) taken off where they
    vary along it more than across it, smoothly (fully at `LINEAR_LIGHT_RATIO`), over windows of
    `LINEAR_LIGHT_SIGMA` px; elsewhere the mark keeps all its colour. Returns the residuals and the
    direction taken off at each pixel, scaled by the square root of how much was (for the template's
    gain). Looks at the picture and the original only, never at a key."""
    from .models.spread import local_mean

    added = linear_light_direction(expected)
    unit = F.normalize(added, dim=1, eps=1e-6)
    across = torch.cross(F.normalize(expected, dim=1, eps=1e-6), unit, dim=1)
    along_added = local_mean((residual * unit).sum(1) ** 2, pixel, shape, LINEAR_LIGHT_SIGMA)
    along_across = local_mean((residual * across).sum(1) ** 2, pixel, shape, LINEAR_LIGHT_SIGMA)
    weight = (1.0 - LINEAR_LIGHT_RATIO * along_across / along_added.clamp_min(1e-12)).clamp(0.0, 1.0)
    weight = weight * ((added * added).sum(1) / LINEAR_LIGHT_DISTINCT ** 2).clamp(max=1.0)
    residual = residual - weight[:, None] * (residual * unit).sum(1, keepdim=True) * unit
    return residual, weight.sqrt()[:, None] * unit


def unpadded(batch: dict, index: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Item `index` of a dataset batch without its padding: positions, normals, uvs (V, .), faces (F, 3)."""
    n_verts, n_faces = int(batch["n_verts"][index]), int(batch["n_faces"][index])
    return (batch["positions"][index, :n_verts], batch["normals"][index, :n_verts], batch["uvs"][index, :n_verts],
            batch["faces"][index, :n_faces])


def charted_item(batch: dict, index: int = 0) -> dict:
    """Item `index` of a dataset batch as a one-item batch (no padding) with its palette faces
    charted as `Watermarker.layout` charts a mesh for a spread mark (`mesh.charts`); the item as it
    is (unpadded) where nothing is charted."""
    from .mesh import Material, Mesh
    from .mesh.charts import chart_palette_faces

    positions, normals, uvs, faces = unpadded(batch, index)
    texture = batch["texture"][index]
    mesh = Mesh(positions.cpu(), normals.cpu(), faces.cpu(), uvs.cpu(),
                materials=[Material(texture=texture.permute(1, 2, 0).cpu())])
    charted = chart_palette_faces(mesh)
    device = texture.device
    return {"positions": charted.positions[None].to(device), "normals": charted.normals[None].to(device),
            "uvs": charted.uvs[None].to(device), "faces": charted.faces[None].to(device),
            "texture": charted.materials[0].texture.permute(2, 0, 1)[None].contiguous().to(device),
            "n_verts": torch.tensor([charted.n_vertices], device=device),
            "n_faces": torch.tensor([charted.n_faces], device=device)}


def batch_mark_grid(model: WatermarkModel, batch: dict, index: int = 0) -> int | None:
    """The cell grid a spread mark uses on item `index` of a dataset batch (its padding left out), as
    `Watermarker.embed` picks it for that mesh."""
    positions, _, uvs, faces = unpadded(batch, index)
    return model.mark_grid(positions, faces, uvs)


def batch_texels_used(batch: dict) -> torch.Tensor:
    """The texels (B, 1, H, W) each mesh of a dataset batch shows (its padding left out), where a
    spread mark lies, as `Watermarker.embed` finds them (`models.spread.texels_used`)."""
    height, width = batch["texture"].shape[-2:]
    items = (unpadded(batch, index) for index in range(len(batch["texture"])))
    return torch.stack([texels_used(uvs, faces, height, width)
                        for _, _, uvs, faces in items])[:, None].to(batch["texture"].device)


def batch_texel_columns(batch: dict) -> tuple[torch.Tensor, torch.Tensor]:
    """Each texel's column and whether it paints any (B, H, W) each, for every mesh of a dataset batch
    (its padding left out), where a surface mark lies (`models.surface.texel_columns`)."""
    height, width = batch["texture"].shape[-2:]
    pairs = [texel_columns(positions, normals, faces, uvs, height, width)
             for positions, normals, uvs, faces in (unpadded(batch, i) for i in range(len(batch["texture"])))]
    device = batch["texture"].device
    return torch.stack([c for c, _ in pairs]).to(device), torch.stack([p for _, p in pairs]).to(device)


def surface_evidence(model: WatermarkModel, pictures: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """A surface model's soft bits (B, N) of pictures (B, 3, H, W) as 8-bit files hold them, the
    object found from the plain background as `meshseal detect` finds it (`alpha` is ignored but for
    pictures whose background is not plain)."""
    from .framing import object_mask

    softs = []
    for picture, coverage in zip(pictures, alpha):
        image = (torch.round(picture.clamp(0, 1) * 255) / 255).permute(1, 2, 0).cpu().numpy()
        mask, _ = object_mask(image)
        if mask.sum() == 0:
            mask = coverage.cpu().numpy() > 0.5
        softs.append(read_picture(model.texture_encoder, image, mask))
    return torch.stack(softs).to(pictures.device)


def spread_evidence(model: WatermarkModel, mesh: MeshBatch, image: torch.Tensor, cameras: Cameras,
                    whitening: dict | None = None, footprint: bool = True, brightness: bool = True,
                    grids: tuple[int, ...] | None = None) -> torch.Tensor:
    """A spread-spectrum model's matched-filter cell sums (B, C*C) for pictures (B, 3, H, W) of the
    original `mesh` taken with `cameras` (see `models.spread.cell_sums`; pictures pool by adding them).
    `grids` (default the model's own grid alone): the cell grids to read, their sums side by side
    (B, sum of C*C), the residual computed once.

    With `footprint` (the default) each picture's sampling is estimated first (`picture_footprint`):
    the prediction subtracted and the template the residual is matched against are both the
    original's texture as that picture sampled it, so pictures from engines that average over the
    pixel (and resized or blurred ones) are read with a filter matched to them. With `brightness` (the
    default) each pixel's brightness relative to the prediction is fitted and taken off first (see
    below). `whitening`: options of `models.spread.whiten` other than its defaults (experiments). Every
    step looks at the picture and the original only, never at a key: z stays N(0, 1) without a mark."""
    from .models.spread import cell_sums, whiten
    from .render import sample_textures
    from .render.renderer import per_fragment

    encoder = model.texture_encoder
    found = relit_residual(mesh, image, cameras)
    n_images, height, width = len(cameras), image.shape[-2], image.shape[-1]
    with torch.no_grad():
        # An untextured material carries no mark: weight 0 (a None texture would sample as white).
        masks = [encoder.amplitude(t[None])[0] if t is not None else image.new_zeros(3, 1, 1) for t in mesh.textures]
        gain = (found.expected / found.albedo.clamp_min(0.02)).mean(1).clamp(0.0, 3.0)  # shading at the pixel
        pixel = found.fragments.pixel.index_select(0, found.keep)
        sampled = picture_footprint(mesh, found, cameras, height, width) if footprint else None
        expected = found.expected if sampled is None else sampled.expected
        usable = torch.ones_like(gain, dtype=torch.bool) if sampled is None else sampled.usable
        textured = torch.tensor([t is not None for t in mesh.textures], device=usable.device)
        usable = usable & textured.index_select(0, found.material)  # nor in the whitening's statistics
        colour = encoder.colour.to(image)
        if brightness:
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
        else:
            along = ((found.seen - expected) * colour).sum(1)
        whitened = torch.zeros_like(along)
        if bool(usable.any()):
            whitened[usable] = whiten(along[usable], pixel[usable], (n_images, height, width), **(whitening or {}))
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
            canvas[index] = gaussian_blur(canvas[index: index + 1], float(sampled.sigma[index]))[0]
        fragments = sampled.fragments
        spread = canvas.reshape(-1).index_select(0, sampled.parent) / sampled.scale ** 2  # the adjoint of the mean
        uv = interpolate(mesh.uvs.expand(n_images, -1, -1) if mesh.uvs.shape[0] == 1 else mesh.uvs, fragments)
        amplitude = sample_textures(masks, uv, per_fragment(mesh.face_material, fragments)).norm(dim=1)
        return sums + cell_sums(encoder, spread * amplitude, uv, fragments.batch, n_images, grids)


def run_pass(model: WatermarkModel, batch: dict, message: torch.Tensor, renderer: MeshRenderer,
             generator: torch.Generator, render_size: int = 128, sampler: str = "seed",
             distortions_3d: Distortions3D | None = None, distortions_2d: Distortions2D | None = None,
             background: torch.Tensor | None = None, render_original: bool = True,
             unrender_jitter: float = 0.0, reference_mix: float = 0.0) -> PassOutput:
    """`unrender_jitter` (informed models): pose error in pixels of the camera used to un-render;
    `reference_mix`: weight of the exact original render in what the un-rendering subtracts (see
    `uv_maps`; 0 at evaluation and detection)."""
    positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
    n = positions.shape[0]
    mask = vertex_mask(batch) if "n_verts" in batch else None
    spread = isinstance(model.texture_encoder, SpreadSpectrumEncoder) and mask is not None
    surface = isinstance(model.texture_encoder, SurfaceCodeEncoder)
    shown = batch_texels_used(batch) if spread else None
    columns = batch_texel_columns(batch) if surface else None
    normals_marked, uvs_marked, texture_marked = model.embed(positions, normals, uvs, texture, message, mask, shown,
                                                             columns)
    if surface:
        shown = columns[1][:, None]
    height, width = (render_size, render_size) if isinstance(render_size, int) else render_size
    cameras, lights = sample_views(n, sampler, generator)
    if background is None:
        background = torch.zeros(n, 3)
    background = background.to(positions)
    distorted_positions, distorted_normals, distorted_faces = positions, normals_marked, faces
    state = generator.get_state()
    if distortions_3d is not None and model.informed:  # rigid moves are what registration recovers
        distortions_3d = replace(distortions_3d, p_rotation=0.0, p_scaling=0.0)
    if distortions_3d is not None:
        distorted_positions, distorted_normals, distorted_faces = distortions_3d(positions, normals_marked, faces, generator)
    marked = renderer(MeshBatch.from_tensors(distorted_positions, distorted_normals, uvs_marked, distorted_faces,
                                             texture_marked), cameras, lights, height, width, background)
    original_image = None
    if render_original:
        after = generator.get_state()
        generator.set_state(state)  # the same 3D distortion for the original
        with torch.no_grad():
            p, nr, f = positions, normals, faces
            if distortions_3d is not None:
                p, nr, f = distortions_3d(positions, normals, faces, generator)
            original_image = renderer(MeshBatch.from_tensors(p, nr, uvs, f, texture), cameras, lights,
                                      height, width, background).image
        generator.set_state(after)
    marked_image = marked.image
    if model.informed:
        picture = marked_image if distortions_2d is None else distortions_2d(marked_image, generator)
        original_mesh = MeshBatch.from_tensors(positions, normals, uvs, faces, texture)
        seen_from = jitter_cameras(cameras, unrender_jitter, height, generator)
        if model.config.decoder == "matched":
            framed, logits = picture, read_bits(model, original_mesh, picture, seen_from)
        else:
            framed = uv_maps(original_mesh, picture, seen_from, model.config.uv_grid, original_image, reference_mix)
            logits = model.decode(framed)
    elif surface:  # the whole picture, read as a file holds it
        framed = marked_image if distortions_2d is None else distortions_2d(marked_image, generator)
        logits = surface_evidence(model, framed, marked.rgba[..., 3])
    else:
        framed = frame(marked_image, marked.rgba[..., 3], model.config.frame_size, background)
        if distortions_2d is not None:
            framed = distortions_2d(framed, generator)
        logits = model.decode(framed)
    return PassOutput(logits, message, texture, texture_marked, normals, normals_marked, uvs, uvs_marked,
                      original_image, marked_image, framed, mask, marked.rgba[..., 3].detach() > 0.999, shown)
