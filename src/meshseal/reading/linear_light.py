"""The prediction made in linear light, for pictures another engine shaded.

Blender's engines (and game engines, web viewers) decode an 8-bit texture from sRGB to linear light,
shade it there, average each pixel's samples there (antialiasing, a film filter, mipmaps) and encode
the result back to sRGB. Our renderer shades the sRGB texture as it is. Where the shading changes from
face to face or a texture's detail is averaged within a pixel, the two differ by more than the mark,
and no local gain and offset of our prediction (`models.spread.local_affine`) takes that up. So a
picture our prediction misses by more than our own pictures mostly are (`TRY_ABOVE`) is predicted a
second time as such an engine would: the original's textures decoded to linear light, the picture
decoded likewise for the light fit, the relit render and its footprint (`picture_footprint`) made in
linear light and encoded to sRGB at the end; the prediction whose fine detail, once saved through the
picture's codec, misses the picture clearly less (`PICK_BELOW`) is read (`methods.spread`). Both look
at the picture and the original only, never at a key, so the matched filter's p-values stay exact.
"""

from __future__ import annotations

from dataclasses import replace

import torch

from ..imaging import linear_to_srgb, srgb_to_linear

TRY_ABOVE = 1.5 / 255  # the sRGB prediction's fine-detail misfit (RMS) above which the linear one is tried
PICK_BELOW = 0.9  # the linear prediction is read where its fine-detail misfit energy is under this share of the sRGB one's
DETAIL_SIGMA = 1.5  # px: the local mean taken off both predictions' residuals before comparing them
MIPMAPS = True  # the candidate whose texture a GPU sampled through mipmaps (`mipmapped`)
MIP_ANISOTROPY = 1.0
DISTANT_ORDER = 3  # spherical-harmonic order of the distant-light candidate (`distant_light`; 0: none)


def linear_mesh(mesh):
    """`mesh` (MeshBatch) with its textures decoded to linear light."""
    textures = mesh.textures
    if torch.is_tensor(textures):
        return replace(mesh, textures=srgb_to_linear(textures))
    return replace(mesh, textures=[None if t is None else srgb_to_linear(t) for t in textures])


def detail_misfit(seen: torch.Tensor, expected: torch.Tensor, pixel: torch.Tensor, shape: tuple[int, int, int]) -> float:
    """Mean square (per pixel and channel) of the picture's fine detail (P, 3) a prediction (P, 3)
    leaves unexplained: the residual less its local mean (Gaussian, DETAIL_SIGMA px, over the object)."""
    from ..models.spread import local_mean

    residual = seen - expected
    detail = residual - local_mean(residual, pixel, shape, DETAIL_SIGMA)
    return float((detail * detail).mean()) if len(detail) else 0.0


def linear_prediction(mesh, image: torch.Tensor, cameras, footprint: bool, found) -> list:
    """The relit original (`reading.relight.relit_residual`) and its footprint (`picture_footprint`,
    where `footprint`) made in linear light, as (found, sampled) with the predictions encoded to sRGB
    and `found`'s picture and albedo (the sRGB ones) kept: one picture `image` (1, 3, H, W) of `mesh`
    seen by `cameras`. `found`: the sRGB reading's `RelitResidual` of the same picture. A list of
    candidates: the point light's, then (with DISTANT_ORDER) the same albedo under distant light
    (`distant_light`); empty where the linear render does not cover the same pixels."""
    from .footprint import picture_footprint
    from .relight import relit_residual

    lit = linear_mesh(mesh)
    height, width = image.shape[-2], image.shape[-1]
    linear = relit_residual(lit, srgb_to_linear(image), cameras)
    if not torch.equal(linear.keep, found.keep):
        return []
    sampled = picture_footprint(lit, linear, cameras, height, width, shortcut=False) if footprint else None
    candidates = [(linear.expected, None if sampled is None else sampled.expected)]
    if DISTANT_ORDER:
        distant = distant_light(lit, linear, None if sampled is None else sampled.expected, DISTANT_ORDER)
        if distant is not None:
            candidates.append(distant)
    if MIPMAPS:
        candidates.append((mipmapped(lit, linear, MIP_ANISOTROPY), None))
    encode = lambda values: linear_to_srgb(values).to(found.expected)  # noqa: E731
    return [(replace(linear, seen=found.seen, albedo=found.albedo, expected=encode(point)),
             None if sampled is None or area is None else replace(sampled, expected=encode(area)))
            for point, area in candidates]


def spherical_harmonics(normals: torch.Tensor, order: int) -> torch.Tensor:
    """The real spherical harmonics up to `order` (at most 3; unnormalised) of unit vectors (P, 3):
    (P, (order + 1)^2)."""
    x, y, z = normals.unbind(1)
    terms = [torch.ones_like(x)]
    if order >= 1:
        terms += [x, y, z]
    if order >= 2:
        terms += [x * y, y * z, 3 * z * z - 1, x * z, x * x - y * y]
    if order >= 3:
        terms += [y * (3 * x * x - y * y), x * y * z, y * (5 * z * z - 1), z * (5 * z * z - 3), x * (5 * z * z - 1),
                  z * (x * x - y * y), x * (x * x - 3 * y * y)]
    return torch.stack(terms, 1)


def distant_light(lit, linear, area, order: int):
    """The original's albedo (linear light) under distant light, a smooth function of the surface normal
    fitted to the picture: (point prediction (P, 3), its footprint's (P, 3) or None), both linear, or
    None where too few pixels fit. A studio light (Workbench's, a matcap, an environment map) shades by
    the normal alone, as no point light does; its low orders in spherical harmonics (`order`) are least
    squares per channel over the pixels the picture does not clip, weighted by the albedo. The
    footprint's prediction (`area`, the point light's) takes the new shading as a smooth gain."""
    from ..render import interpolate

    fragments = linear.fragments
    normals = lit.normals.expand(len(fragments.pix_to_face), -1, -1) if lit.normals.shape[0] == 1 else lit.normals
    normals = torch.nn.functional.normalize(interpolate(normals, fragments).index_select(0, linear.keep).double(), dim=1)
    basis = spherical_harmonics(normals, order)
    albedo, seen = linear.albedo.double(), linear.seen.double()
    fit = (seen < 0.98).all(1) & (albedo.amin(1) > 0.01)
    if int(fit.sum()) < 8 * basis.shape[1]:
        return None
    shading = torch.empty_like(albedo)
    for channel in range(3):
        design = albedo[fit, channel:channel + 1] * basis[fit]
        normal = design.T @ design
        ridge = 1e-6 * float(normal.diagonal().mean()) * torch.eye(len(normal), dtype=normal.dtype)
        coefficients = torch.linalg.solve(normal + ridge, design.T @ seen[fit, channel])
        shading[:, channel] = (basis @ coefficients).clamp_min(0.0)
    point = (albedo * shading).clamp(0.0, 1.0).to(linear.expected)
    if area is None:
        return point, None
    gain = (point / linear.expected.clamp_min(1e-4)).clamp(0.0, 4.0)
    return point, (area * gain).clamp(0.0, 1.0)


def mipmapped(lit, linear, anisotropy: float = 1.0) -> torch.Tensor:
    """The point-light prediction (linear light, P x 3) with the albedo a GPU engine samples: trilinear
    through mipmaps (`render.texture.sample_mipmapped`), the level from each pixel's texel footprint."""
    from ..render import interpolate
    from ..render.renderer import per_fragment
    from ..render.texture import sample_mipmapped, sample_texture, texel_footprint

    fragments = linear.fragments
    uvs = lit.uvs
    material = per_fragment(lit.face_material, fragments).index_select(0, linear.keep)
    uv = interpolate(uvs.expand(len(fragments.pix_to_face), -1, -1) if uvs.shape[0] == 1 else uvs, fragments)
    uv = uv.index_select(0, linear.keep)
    textures = lit.textures
    sizes = torch.tensor([[t.shape[-1], t.shape[-2]] if t is not None else [1, 1] for t in textures], dtype=uv.dtype)
    keep_fragments = replace(fragments, batch=fragments.batch.index_select(0, linear.keep),
                             vertex=fragments.vertex.index_select(0, linear.keep),
                             corners_xy=fragments.corners_xy.index_select(0, linear.keep))
    rho = texel_footprint(uvs, keep_fragments, sizes.index_select(0, material.long()), anisotropy)
    albedo = torch.ones(len(uv), 3, dtype=linear.expected.dtype)
    plain = torch.ones_like(albedo)  # the renderer's own lookup (bilinear, no mipmaps): what the shading divides
    for index, texture in enumerate(textures):
        if texture is None:
            continue
        chosen = torch.nonzero(material == index).squeeze(1)
        albedo[chosen] = sample_mipmapped(texture[:3].to(albedo.dtype), uv[chosen], rho[chosen])
        plain[chosen] = sample_texture(texture[:3].to(albedo.dtype), uv[chosen])
    shading = linear.expected / plain.clamp_min(1e-4)
    return (albedo * shading).clamp(0.0, 1.0)
