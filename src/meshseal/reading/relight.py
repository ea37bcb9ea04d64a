"""The original relit to match a picture: the prediction informed reading subtracts, and the
picture un-rendered onto the original's UV grid (what the learned informed decoder reads)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import torch
import torch.nn.functional as F

from ..render import (
    Cameras,
    MeshBatch,
    MeshRenderer,
    interpolate,
    lights_at,
    pixels_at,
    relight_fragments,
    unrender,
)
from ..render.lighting import K_AMBIENT, K_DIFFUSE


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
    surface: tuple | None = None  # `MeshRenderer.surface` of the original at `fragments` (relighting keeps it)


_SURFACE = ("positions", "normals", "uvs", "faces", "face_material", "textures", "diffuse")  # `MeshRenderer.surface` reads


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


def fitted_light(mesh: MeshBatch, image: torch.Tensor, cameras: Cameras, light_from: str = "all"):
    """`relit_residual`'s first fit alone (not polished: see `_fit`): the original with the fitted
    ambient factors, the point lights (the same numbers) and the rasterization they were fitted on (a
    render of the relit original from `cameras` can reuse it), without rendering the relit original
    (registration renders it itself)."""
    with torch.no_grad():
        fragments, relit, lights, _, _ = _fit(mesh, image, cameras, light_from, polish=False)
        return relit, lights, fragments


def _fit(mesh: MeshBatch, image: torch.Tensor, cameras: Cameras, light_from: str, polish: bool = True):
    """The light fit of `relit_residual`: (fragments, relit mesh, lights, antialiased albedo (P, 3),
    and the surface the renders look up, `MeshRenderer.surface`, which relighting does not change).
    `polish` (the reading's, not registration's): `splat_polished_light` after the first fit.
    Registration keeps the first fit: its texture stage compares band-passed pictures, which a light a
    few tenths of a unit off barely moves, and on a picture lit as no point light lights it (Blender's
    Workbench studio light) a polished light can pull its camera off."""
    from ..render import rasterize
    from ..render.unrender import facing_camera

    n_images, height, width = len(cameras), image.shape[-2], image.shape[-1]
    unlit = replace(mesh, ambient=torch.full_like(mesh.ambient, 1.0 / K_AMBIENT))
    renderer = MeshRenderer()
    # the rasterization and surface lookups the render would make itself, kept for the relit render
    on = cameras.to(mesh.positions.device, mesh.positions.dtype)
    positions = mesh.positions.expand(n_images, -1, -1) if mesh.positions.shape[0] == 1 else mesh.positions
    fragments = rasterize(on.world_to_clip(positions, width / height), mesh.faces, height, width)
    surface = renderer.surface(unlit, on, fragments)
    flat = renderer(unlit, cameras, lights_at(cameras.eye, 0.0), height, width, fragments=fragments,
                    surface=surface)  # antialiased albedo
    albedo = pixels_at(flat.image, fragments)
    fit_on = flattest_half(flat.image, fragments) if light_from == "flat" else None
    seen = pixels_at(image, fragments)
    fit_on = _below_white(seen, fragments, n_images, fit_on, 0.0 if polish else REGISTRATION_WHITE)
    # the surface points and camera-facing unit normals (`unrender.surface_points`), from the surface's
    points = (surface[0], facing_camera(surface[0], surface[1], on, fragments))
    _, ambient, lights = relight_fragments(mesh, fragments, cameras, seen, albedo, fit_on, predict=False, points=points)
    if polish:
        inside = pixels_at(flat.rgba[..., 3:].permute(0, 3, 1, 2), fragments)[:, 0] > 0.999
        ambient, lights = splat_polished_light(fragments, surface, cameras, seen, albedo, inside, ambient, lights,
                                               (n_images, height, width), renderer.sigma, fit_on, points[1])
    return fragments, _with_ambient_per_image(mesh, ambient), lights, albedo, surface


NEAR_WHITE = 250.0 / 255  # a pixel this bright in any channel (a clipped highlight) is left out of the light fit ...
MIN_FIT_PIXELS = 64  # ... where the picture keeps this many others; a pixel with such a neighbour, out of the polish
REGISTRATION_WHITE = 0.05  # registration's fits leave them out only where they are this share of the picture's pixels


def _below_white(seen: torch.Tensor, fragments, n_images: int, fit_on: torch.Tensor | None,
                 share: float = 0.0) -> torch.Tensor | None:
    """The pixels (P,) the first light fit uses: `fit_on` (None: all) less those the picture shows at
    NEAR_WHITE or above in any channel, in each picture that keeps MIN_FIT_PIXELS others. A highlight
    that clipped says only that the light there is at least that strong: fitted as a colour, it pulls a
    linear fit's light away from the rest of the object, whose relit prediction then misses the picture
    by more than the mark. A picture without such pixels is fitted as before (the same numbers).
    Registration's fits (`share` REGISTRATION_WHITE) leave them out only where they are that share of a
    view's pixels or more: left out wherever a few texels are near white, they moved four of
    benchmarks/registration.py's 110 registered poses and one of them (test mesh 63) lost its message."""
    clipped = seen.amax(1) >= NEAR_WHITE
    if not bool(clipped.any()):
        return fit_on
    count = torch.bincount(fragments.batch[clipped], minlength=n_images)
    left = torch.bincount(fragments.batch[~clipped], minlength=n_images)
    taken = (left >= MIN_FIT_PIXELS) & (count > share * (count + left))  # a picture almost all white keeps every pixel
    clipped = clipped & taken.index_select(0, fragments.batch)
    if not bool(clipped.any()):
        return fit_on
    return ~clipped if fit_on is None else fit_on & ~clipped


POLISH_ITERATIONS = 6  # Levenberg-Marquardt steps of the polish at most
POLISH_PIXELS = 1024  # the polish fits on an even subsample of at most about this many interior pixels
POLISH_TOLERANCE = 1e-4  # it stops once a step moves the light less than this times its distance


def splat_polished_light(fragments, surface: tuple, cameras: Cameras, seen: torch.Tensor, albedo: torch.Tensor,
                         inside: torch.Tensor, ambient: torch.Tensor, lights, shape: tuple[int, int, int],
                         sigma: float, fit_on: torch.Tensor | None = None, unit: torch.Tensor | None = None):
    """The point light of `fit_point_light` polished for a picture our splatting renderer made.

    `fit_point_light` models each pixel as the albedo at it (antialiased: the splatted albedo render)
    times one Lambert term at the pixel's own surface point. A splatted interior pixel is the 3x3
    Gaussian (`sigma`) mean of its neighbours' lit colours instead, and where the normal changes from
    pixel to pixel (leaves, fine relief) the product of means is not the mean of products: the fit then
    moves the light and trades diffuse for ambient light, and the relit original misses the picture by
    more than the mark (the albedo, antialiased where the picture is point-sampled, misleads it the same
    way). Here, on an even subsample of the interior pixels (`inside` (P,), coverage 1, none near white
    around; within `fit_on` where given), the sampling that explains them best at the first fit's light
    is chosen (the splat's 3x3 Gaussian, or point samples), and under its exact model (ambient x the
    sampled albedo + diffuse x the sampled product of albedo and Lambert term, the two strengths per
    channel in closed form) the light's position is refined by Levenberg-Marquardt; the result is kept
    only where it explains those pixels better than the point model did (a picture sampled otherwise,
    by another engine, can keep its first fit).
    `fragments`/`surface` (`MeshRenderer.surface`: world position, normal, point-sampled albedo), `seen`
    and `albedo` (P, 3) at the fragments; `shape` (B, H, W) of the pictures; `unit` (P, 3): the surface's
    unit normals facing the camera, where the caller has them. Looks at the picture and the
    original only. Returns ambient (B, 3) and PointLights, as `fit_point_light` does."""
    from ..models.spread import within_reach
    from ..render.lighting import attenuation
    from ..render.splatter import _kernels

    world, normal, lookup, _ = surface
    usable = inside
    if fit_on is not None:
        usable = usable & fit_on
    local, (_, rows, columns), _ = within_reach(fragments.pixel, shape, 1)
    gaussian = _kernels(sigma, seen.dtype, seen.device)[0].reshape(9)  # the splat's 3x3 Gaussian
    samplings = (gaussian, torch.zeros_like(gaussian).index_fill_(0, torch.tensor([4], device=gaussian.device), 1.0))
    offsets = torch.tensor([dy * columns + dx for dy in (-1, 0, 1) for dx in (-1, 0, 1)], device=local.device)
    if unit is None:
        from ..render.unrender import facing_camera

        unit = facing_camera(world, normal, cameras, fragments)
    ambient, position, intensity = ambient.clone(), lights.position.clone(), lights.intensity.clone()
    for index in range(shape[0]):
        chosen = torch.nonzero(fragments.batch == index).squeeze(1)
        used = torch.nonzero(usable.index_select(0, chosen)).squeeze(1)
        if len(used) < 16:
            continue
        used = used[:: max(1, len(used) // POLISH_PIXELS)].contiguous()  # an even subsample
        # each used pixel's 3x3 neighbours (all covered: the pixel's coverage is whole), as fragments
        at = local.index_select(0, chosen) - index * rows * columns  # within this picture's window
        slot = torch.full((rows * columns,), -1, dtype=torch.long, device=at.device)
        slot.index_copy_(0, at, torch.arange(len(at), device=at.device))
        around = slot[(at.index_select(0, used)[:, None] + offsets).clamp(0, rows * columns - 1)]  # (U, 9)
        keep = (around >= 0).all(1)  # not whole after all (at the window's edge): left out
        used, around = used[keep], around[keep]
        if len(used) < 16:
            continue
        needed, around = torch.unique(around, return_inverse=True)
        picked = chosen.index_select(0, needed)
        p, n, u = world.index_select(0, picked), unit.index_select(0, picked), lookup.index_select(0, picked)
        p_squared, n_dot_p = (p * p).sum(1, keepdim=True), (n * p).sum(1, keepdim=True)

        def lambert(candidates: torch.Tensor) -> torch.Tensor:  # (K, 3) -> (N, K) at the needed fragments
            # |c - p| and n.(c - p) as matrix products, as `fit_point_light` scores its candidates
            distance = (p_squared - 2.0 * p @ candidates.T + (candidates * candidates).sum(1)).clamp_min(1e-24).sqrt()
            return ((n @ candidates.T - n_dot_p) / distance).clamp_min(0.0) / attenuation(distance)

        # left out too: a pixel with a neighbour near white in the picture or under the first fit's light
        # (the renderer clamps each lit colour before splatting, which the model does not)
        start = position[index, 0]
        lit = u * (K_AMBIENT * ambient[index] + K_DIFFUSE * intensity[index, 0] * lambert(start[None]))
        bright = (seen.index_select(0, picked).amax(1) >= NEAR_WHITE) | (lit.amax(1) >= NEAR_WHITE)
        keep = ~bright[around].any(1)
        used, around = used[keep], around[keep]
        if len(used) < 16:
            continue
        y = seen.index_select(0, chosen[used])  # (U, 3)
        centre = torch.searchsorted(needed, used)  # each used pixel's own fragment among the needed
        a_term = albedo.index_select(0, chosen[used])  # the point model's: the antialiased albedo

        def fit(diffuse_term: torch.Tensor):  # (U, 3, K) -> residuals (U, 3, K), a (3, K), d (3, K)
            a_ = a_term[:, :, None]
            suu, suy = (a_ * a_).sum(0), (a_ * y[:, :, None]).sum(0)
            suv, svv, svy = (a_ * diffuse_term).sum(0), (diffuse_term ** 2).sum(0), (diffuse_term * y[:, :, None]).sum(0)
            det = (suu * svv - suv * suv).clamp_min(1e-9)
            a = ((svv * suy - suv * svy) / det).clamp_min(0.0)
            d = ((suu * svy - suv * suy) / det).clamp_min(0.0)
            return y[:, :, None] - a * a_ - d * diffuse_term, a, d

        around_albedo = u[around]  # (U, 9, 3): each used pixel's neighbours' albedo

        def sampled(candidates: torch.Tensor):  # the exact model's diffuse term at the used pixels (U, 3, K)
            # sum over the neighbours o of weight(o) x albedo(o) x Lambert(o), as one batched product
            return torch.bmm(weighted, lambert(candidates)[around])

        point = float((fit(a_term[:, :, None] * lambert(start[None])[centre][:, None, :])[0] ** 2).sum())
        # the sampling that explains these pixels best at the first fit's light: splatted, or point samples
        costs = []
        for weights in samplings:
            weighted = (around_albedo * weights[None, :, None]).transpose(1, 2).contiguous()  # (U, 3, 9)
            a_term = weighted.sum(2)
            costs.append(float((fit(sampled(start[None]))[0] ** 2).sum()))
        weights = samplings[min(range(len(samplings)), key=costs.__getitem__)]
        weighted = (around_albedo * weights[None, :, None]).transpose(1, 2).contiguous()
        a_term = weighted.sum(2)
        # Levenberg-Marquardt on the light's position, the strengths projected out (closed form at
        # each position), the Jacobian by forward differences: one batch of four positions a step.
        light, damping, best = start, 1e-3, None
        for _ in range(POLISH_ITERATIONS + 1):
            h = 1e-3 * float(light.norm())
            residuals, a, d = fit(sampled(torch.cat([light[None], light[None] + h * torch.eye(3).to(light)])))
            cost = float((residuals[..., 0] ** 2).sum())
            if best is not None and cost >= best[0]:  # the step did not help: back, and damp more
                damping *= 10.0
                light = best[3] - best[4] / (1.0 + damping)  # a shorter step along the same direction
                if float(best[4].norm()) / (1.0 + damping) < POLISH_TOLERANCE * float(light.norm()):
                    break
                continue
            best_jacobian = ((residuals[..., 1:] - residuals[..., :1]) / h).reshape(-1, 3)
            best = (cost, a[:, 0], d[:, 0], light, None)
            normal_matrix = best_jacobian.T @ best_jacobian
            gradient = best_jacobian.T @ residuals[..., 0].reshape(-1)
            diagonal = normal_matrix.diagonal()
            if float(diagonal.max()) <= 0.0:  # the light's position changes nothing here (no lit pixel)
                break
            scale = torch.diag(diagonal.clamp_min(1e-9 * float(diagonal.max())))
            step = torch.linalg.solve(normal_matrix + damping * scale, gradient)
            best = best[:4] + (step,)
            damping = max(damping / 10.0, 1e-6)
            light = best[3] - step
            if float(step.norm()) < POLISH_TOLERANCE * float(best[3].norm()):
                break
        if best is not None and best[0] < point:
            ambient[index] = best[1] / K_AMBIENT
            position[index, 0], intensity[index, 0] = best[3], best[2] / K_DIFFUSE
    return ambient, type(lights)(position, intensity)


def relit_residual(mesh: MeshBatch, image: torch.Tensor, cameras: Cameras, light_from: str = "all") -> RelitResidual:
    """Rasterize the original `mesh` from `cameras` over the picture (B, 3, H, W), fit a point light
    that explains the picture from the original texture (`relight_fragments`) and render the original
    under it. Silhouette pixels (partly background) are left out. `light_from` "flat" fits the light on
    the half of the object's pixels where the albedo is flattest (`flattest_half`): a camera a pixel or
    two off then barely changes what the fit sees (registration refines such cameras)."""
    from ..render.renderer import per_fragment

    n_images, height, width = len(cameras), image.shape[-2], image.shape[-1]
    with torch.no_grad():
        fragments, relit, lights, albedo, surface = _fit(mesh, image, cameras, light_from)
        uv = interpolate(mesh.uvs.expand(n_images, -1, -1) if mesh.uvs.shape[0] == 1 else mesh.uvs, fragments)
        same = all(getattr(relit, name) is getattr(mesh, name) for name in _SURFACE)  # only the ambient refitted
        relit_render = MeshRenderer()(relit, cameras, lights, height, width, fragments=fragments,
                                      surface=surface if same else None)
        inside = pixels_at(relit_render.rgba[..., 3:].permute(0, 3, 1, 2), fragments)[:, 0] > 0.999
        keep = torch.nonzero(inside).squeeze(1)
        pick = lambda values: values.index_select(0, keep)  # noqa: E731
        return RelitResidual(pick(pixels_at(image, fragments)).to(image), pick(pixels_at(relit_render.image, fragments)).to(image),
                             pick(albedo).to(image), pick(uv).to(image), pick(per_fragment(mesh.face_material, fragments)),
                             pick(fragments.batch), keep, fragments, relit, lights,
                             surface if same else None)


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
