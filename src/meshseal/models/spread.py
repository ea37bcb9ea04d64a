"""A keyed spread-spectrum mark in texture space, read by a matched filter after un-rendering.

The texture's UV square is cut into `chips` x `chips` cells (`grid_for`: `coarse_chips` x
`coarse_chips` on a mesh whose texture is so minified in a standard view that a finer cell would be
under `coarse_below` pixels, and `fine_chips` x `fine_chips` on one whose texture is so magnified that a
`chips` cell would be over `fine_above` pixels, where the picture would show too few cells for the
bits; a texture with fewer texels than the grid has cells is resampled up to carry it; on such meshes
detection reads both grids and pays for the two tries in its p-value). A fixed pseudo-random permutation (the
model's pattern seed) gives every cell to one of the n bits and a random sign, so each bit is spread
over cells all over the surface and any view shows some of every bit. The mark adds, at each texel,
`sign x (+-1 for the bit) x amplitude` along one colour direction, bilinearly interpolated between
cell centres:

- the colour direction is blue-yellow (1, 1, -2): fine chroma is what the eye sees least, and the
  relighting misfit of detection (a shading error, mostly luminance) leaves it nearly untouched;
- the amplitude follows a just-noticeable-difference mask: proportional to local texture activity
  (luminance standard deviation in a small window) plus a floor, so busy areas carry more than flat
  ones; the whole residual is then scaled to a target texture PSNR (the strength knob).

Detection has the original mesh and the picture's camera. The original is relit to match the picture
(`reading.relight.relit_residual`) and sampled as the picture sampled it (`reading.footprint.picture_footprint`: point
samples, or each pixel's area, blurred), each pixel's own brightness against that prediction is fitted
and taken off along the predicted colour (shadows, sheets lit from behind, tone curves), the residual at
every covered pixel is projected onto the mark's colour, whitened in the picture (`whiten`: slow
relighting misfit removed, texture edges damped), weighted by the mark's expected amplitude there
(recomputed from the original texture, times what the brightness fit left of it), and accumulated into
the cells by the same bilinear weights (at the sub-pixel samples of an area
footprint). Per bit, z = sum(sign x cell) / sqrt(sum(cell^2)): with no mark the cell signs are
independent of the picture, so z is a normalised Rademacher sum (mean 0, variance 1, whatever the
picture shows; `bit_weights` gives its weights, from which `payload` computes exact p-values); with a
mark it grows with the square root of the cells seen.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from ..versions import version as version_of

USED_RESOLUTION = 1024  # `texels_used` works at most this many texels a side
READ_BOTH_BELOW = 1.1  # detection reads both grids up to this many times the embedding's threshold
PIXEL_AT_OBJECT = 2 * 3.5 * math.tan(math.radians(30)) / 256  # a 256^2 picture's pixel at a radius-1 object 3.5 away, 60-degree view
COLOURS = {"blue-yellow": (1.0, 1.0, -2.0), "grey": (1.0, 1.0, 1.0), "red-green": (1.0, -1.0, 0.0),
           "luma": (0.299, 0.587, 0.114)}


def colour_direction(name: str) -> torch.Tensor:
    """The unit colour direction (3,) a mark colour names: one of COLOURS, or "r,g,b" (any three numbers,
    not all 0)."""
    if name in COLOURS:
        values = COLOURS[name]
    else:
        try:
            values = tuple(float(v) for v in name.split(","))
        except ValueError:
            values = ()
        if len(values) != 3 or not any(values):
            raise ValueError(f"mark colour must be one of {', '.join(COLOURS)} or three numbers r,g,b")
    return F.normalize(torch.tensor(values, dtype=torch.float32), dim=0)


def _widened(values: torch.Tensor, side: int, factor: int) -> torch.Tensor:
    """A side x side grid's values (side^2,) on the grid `factor` times finer, each value on its factor x
    factor block of cells, flattened ((side * factor)^2,)."""
    return values.reshape(side, side).repeat_interleave(factor, 0).repeat_interleave(factor, 1).reshape(-1)


def activity_mask(texture: torch.Tensor, window: int = 5, floor: float = 0.3) -> torch.Tensor:
    """Just-noticeable-difference weights (B, 1, H, W) of textures (B, 3, H, W): local luminance
    standard deviation over `window` texels, relative to its image mean, plus `floor`."""
    luminance = texture.mean(1, keepdim=True)
    pad = (window // 2,) * 4
    mean = F.avg_pool2d(F.pad(luminance, pad, mode="replicate"), window, 1)
    square = F.avg_pool2d(F.pad(luminance * luminance, pad, mode="replicate"), window, 1)
    activity = (square - mean * mean).clamp_min(0.0).sqrt()
    return floor + activity / activity.mean(dim=(2, 3), keepdim=True).clamp_min(1e-4)


class SpreadSpectrumEncoder(nn.Module):
    """Texture + message -> texture carrying the spread-spectrum mark (no learned parameters: the
    cell-to-bit assignment and the cell signs are buffers drawn from `seed`)."""

    def __init__(self, n_bits: int, chips: int = 128, colour: str = "blue-yellow", texture_psnr: float = 40.0,
                 window: int = 5, floor: float = 0.3, seed: int = 0, coarse_chips: int = 0, coarse_below: float = 0.6,
                 fine_chips: int = 0, fine_above: float = 2.0, block: int = 1, pilot_share: float = 0.0,
                 pilot_block: int = 1, pilot_gain: float = 1.0, pilot_chips: int = 0):
        super().__init__()
        if not 0.0 <= pilot_share < 1.0:
            raise ValueError("the pilot's share of the cells must be in [0, 1)")
        # The pilot: cells carrying the key's signs alone (bit index n_bits), `pilot_share` of them, drawn
        # as `pilot_slots` more bits would be, so that without a pilot the pattern is the one drawn before.
        self.pilot_slots = round(n_bits * pilot_share / (1.0 - pilot_share))
        self.n_bits, self.chips, self.texture_psnr, self.window, self.floor = n_bits, chips, texture_psnr, window, floor
        self.seed, self.coarse_chips, self.coarse_below = seed, coarse_chips, coarse_below
        self.fine_chips, self.fine_above, self.block, self.pilot_block = fine_chips, fine_above, block, pilot_block
        self.pilot_gain, self.pilot_chips = pilot_gain, pilot_chips
        assign, sign = self._draw(seed, chips)
        self.register_buffer("assign", assign)
        self.register_buffer("sign", sign)
        self.register_buffer("colour", colour_direction(colour))
        self._keyed: dict[tuple[int | None, int], tuple[torch.Tensor, torch.Tensor]] = {}
        self._amplitudes: list[tuple[torch.Tensor, int, torch.Tensor]] = []

    def grid_for(self, positions: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor) -> int:
        """The cell grid of a mesh's mark: `coarse_chips` where `chips` cells would be under
        `coarse_below` px in a standard view (`cell_pixels`), where a pose error of hundredths of a
        pixel already hides them; `fine_chips` where they would be over `fine_above` px, where a
        picture of the object shows a few dozen cells for all the bits; else `chips`."""
        return self._grids(cell_pixels(positions, faces, uvs, self.chips), 1.0)[-1]

    def grids_to_read(self, positions: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor) -> tuple[int, ...]:
        """The grids detection reads on a mesh, the model's own first: `grid_for`'s and, where that is
        another grid or nearly (cells within READ_BOTH_BELOW of either threshold, so that a mesh at a
        threshold is read either way), the model's own too (marks made before the other grids)."""
        return self._grids(cell_pixels(positions, faces, uvs, self.chips), READ_BOTH_BELOW)

    def _grids(self, width: float, slack: float) -> tuple[int, ...]:
        """The model's grid, then the other one for cells `width` px wide, the thresholds widened by
        `slack`."""
        if self.coarse_chips and width < slack * self.coarse_below:
            return (self.chips, self.coarse_chips)
        if self.fine_chips and width > self.fine_above / slack:
            return (self.chips, self.fine_chips)
        return (self.chips,)

    def _draw(self, seed: int, chips: int) -> tuple[torch.Tensor, torch.Tensor]:
        generator = torch.Generator().manual_seed(seed)
        cells = chips * chips
        block = self.block if self.block > 1 and chips % self.block == 0 else 1
        slots = self.n_bits + self.pilot_slots  # a slot past the bits is the pilot's
        wide = self.pilot_width(chips)
        if wide > 1:  # the pilot on blocks of wide x wide cells of one sign, the message on single cells
            side = chips // wide
            coarse = (torch.randperm(side * side, generator=generator) % slots) >= self.n_bits
            pilot = _widened(coarse, side, wide)
            free = torch.nonzero(~pilot).squeeze(1)  # the message's cells, dealt to the bits in equal shares
            free = free[torch.randperm(len(free), generator=generator)]
            assign = torch.full((cells,), self.n_bits, dtype=torch.long)
            assign[free] = torch.arange(len(free)) % self.n_bits
            coarse_sign = torch.randint(0, 2, (side * side,), generator=generator).float() * 2 - 1
            fine_sign = torch.randint(0, 2, (cells,), generator=generator).float() * 2 - 1
            return assign, torch.where(pilot, _widened(coarse_sign, side, wide), fine_sign)
        if block == 1:
            assign = (torch.randperm(cells, generator=generator) % slots).clamp_max(self.n_bits)
        else:  # a bit takes block x block neighbouring cells, so that a JPEG block holds few bits
            side = chips // block
            assign = _widened((torch.randperm(side * side, generator=generator) % slots).clamp_max(self.n_bits), side, block)
        return assign, torch.randint(0, 2, (cells,), generator=generator).float() * 2 - 1

    def pilot_width(self, chips: int) -> int:
        """Cells per side of the pilot's blocks of one sign on a chips x chips grid (1: single cells):
        `pilot_block`, or more on a grid finer than `pilot_chips`, whose pilot takes that grid's signs."""
        wide = max(self.pilot_block, chips // self.pilot_chips if self.pilot_chips else 1)
        return wide if wide > 1 and self.pilot_slots and chips % wide == 0 else 1

    def pattern(self, key_seed: int | None = None, chips: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """The cell-to-bit assignment (C*C,) and cell signs (C*C,) of a chips x chips grid (the model's
        own by default): the model's pattern (`key_seed` None, as training uses) or the one a secret key
        draws (`payload.key_seed`), so that a mark made under one key is noise to the matched filter
        under any other. Each grid draws its own."""
        chips = chips or self.chips
        if key_seed is None and chips == self.chips:
            return self.assign, self.sign
        if (key_seed, chips) not in self._keyed:
            seed = self.seed if key_seed is None else (self.seed * 1_000_003 + key_seed) % 2 ** 63
            if chips != self.chips:
                seed = (seed * 1_000_033 + chips) % 2 ** 63
            kept = {k: v for k, v in self._keyed.items() if k[0] == key_seed}  # this key's other grids stay
            self._keyed = kept | {(key_seed, chips): self._draw(seed, chips)}
        assign, sign = self._keyed[(key_seed, chips)]
        return assign.to(self.assign.device), sign.to(self.sign.device)

    def amplitude(self, texture: torch.Tensor) -> torch.Tensor:
        """Unsigned mark field (B, 3, H, W) for textures (B, 3, H, W): the mask times the colour.
        Without gradients the last few are kept (the same tensor, unmodified): detection asks for
        the original's mask once per picture."""
        if torch.is_grad_enabled():
            return activity_mask(texture, self.window, self.floor) * self.colour.to(texture)[None, :, None, None]
        for kept, version, field in self._amplitudes:  # kept alive here, so its memory is not reused
            if (kept.data_ptr(), kept.shape, kept.stride(), kept.dtype, version) == (
                    texture.data_ptr(), texture.shape, texture.stride(), texture.dtype, version_of(texture)):
                return field
        field = activity_mask(texture, self.window, self.floor) * self.colour.to(texture)[None, :, None, None]
        self._amplitudes = [(texture, version_of(texture), field)] + self._amplitudes[:3]
        return field

    def cells(self, message: torch.Tensor, key_seed: int | None = None, chips: int | None = None) -> torch.Tensor:
        """Bits (B, N) in {0, 1} -> signed cell values (B, 1, C, C) of the chips x chips grid."""
        chips = chips or self.chips
        assign, sign = self.pattern(key_seed, chips)
        signs = 2.0 * message - 1.0
        if self.pilot_slots:  # the pilot's cells keep the key's sign
            signs = torch.cat([signs, signs.new_ones(len(signs), 1)], 1)
        values = sign * signs.index_select(1, assign)
        if self.pilot_slots and self.pilot_gain != 1.0:  # the pilot's share of the energy, against the message's
            values = torch.where(assign == self.n_bits, values * self.pilot_gain, values)
        return values.reshape(-1, 1, chips, chips)

    def forward(self, texture: torch.Tensor, message: torch.Tensor, strength: float = 1.0,
                key_seed: int | None = None, chips: int | None = None, used: torch.Tensor | None = None) -> torch.Tensor:
        """texture (B, 3, H, W) in [0, 1], message (B, N) -> marked texture on the chips x chips grid
        (default the model's own; `grid_for` picks a mesh's). `used` (B, 1, h, w) or (h, w), any
        size: the texels the mesh shows (`texels_used`); the mark lies on them alone and its RMS there
        is `strength` times that of the model's target texture PSNR (strength 2: 6 dB louder), so no
        energy goes where no view can see it and the PSNR over the shown texels is the target
        whatever share of the texture the mesh uses (None: the whole texture). A texture with fewer
        texels a side than the grid has cells is first resampled up (`carrier`): the marked texture
        is then larger than the one given."""
        texture = carrier(texture, chips or self.chips)
        pattern = F.interpolate(self.cells(message, key_seed, chips).to(texture), size=texture.shape[-2:],
                                mode="bilinear", align_corners=False)
        residual = self.amplitude(texture) * pattern
        share = 1.0
        if used is not None:
            used = F.interpolate(used.reshape(-1, 1, *used.shape[-2:]).to(texture), size=texture.shape[-2:], mode="nearest")
            residual, share = residual * used, used.mean(dim=(1, 2, 3), keepdim=True).clamp_min(1e-8)
        rms = strength * 10.0 ** (-self.texture_psnr / 20.0)
        energy = residual.pow(2).mean(dim=(1, 2, 3), keepdim=True) / share
        residual = residual * rms / energy.sqrt().clamp_min(1e-8)
        return (texture + residual).clamp(0.0, 1.0)


def texels_used(uvs: torch.Tensor, faces: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """The texels (height, width) bool of a texture that faces (F, 3) with uvs (V, 2) can show: those
    whose centre a face covers in the UV square (wrapped, as repeating textures are), those under its
    edges (slivers, faces smaller than a texel, faces whose UVs lie on a line), and their neighbours
    (a bilinear lookup reads them). A face spanning over two UV squares shows every texel. Worked out
    at most USED_RESOLUTION texels a side and scaled up (a few texels more on large textures)."""
    from ..render.rasterizer import texel_coverage

    corners = uvs.detach().double().cpu()[faces.cpu().long()]  # (F, 3, 2)
    if len(corners) == 0:
        return torch.zeros(height, width, dtype=torch.bool)
    corners = corners - torch.floor(corners.amin(1, keepdim=True))  # each face near the first UV square
    if bool((corners.amax(dim=(1, 2)) > 2.0).any()):
        return torch.ones(height, width, dtype=torch.bool)
    used = texel_coverage(corners, min(height, USED_RESOLUTION), min(width, USED_RESOLUTION))
    grown = F.max_pool2d(F.pad(used[None, None].float(), (1, 1, 1, 1), mode="circular"), 3, 1)
    return F.interpolate(grown, size=(height, width), mode="nearest")[0, 0] > 0


def carrier(texture: torch.Tensor, chips: int) -> torch.Tensor:
    """`texture` (B, 3, H, W) with at least `chips` texels a side: as it is, or resampled up
    (bilinear, by the smallest whole factor) so that each cell of a chips x chips grid has a texel of
    its own. Bilinear resampling keeps the texture as a renderer's bilinear lookup shows it, up to a
    slight smoothing within each original texel."""
    factor = math.ceil(chips / min(texture.shape[-2:]))
    return _resized(texture, (texture.shape[-2] * factor, texture.shape[-1] * factor))


def resampled_like(texture: torch.Tensor, marked: torch.Tensor) -> torch.Tensor:
    """An original `texture` (..., C, H, W) at the size of its `marked` copy, resampled as `carrier`
    resampled it, so that comparing the two measures the mark alone."""
    return _resized(texture, marked.shape[-2:])


def _resized(texture: torch.Tensor, size) -> torch.Tensor:
    """`texture` (..., C, H, W) resampled bilinearly to `size` (the same tensor if it is that size)."""
    if tuple(texture.shape[-2:]) == tuple(size):
        return texture
    flat = texture.reshape(-1, *texture.shape[-3:]).float()
    resized = F.interpolate(flat, size=tuple(size), mode="bilinear", align_corners=False).clamp(0.0, 1.0)
    return resized.reshape(*texture.shape[:-2], *size).to(texture.dtype)


def local_mean(values: torch.Tensor, pixel: torch.Tensor, shape: tuple[int, int, int], sigma: float) -> torch.Tensor:
    """Gaussian mean (sigma px) of values (P,) or (P, C) at covered pixels, over the covered pixels
    only (the background does not bleed in). pixel (P,): flat indices into the (B, H, W) `shape`."""
    from ..imaging import blur_radius
    from ..render.blur import gaussian_blur  # compiled on the CPU, the same bits

    flat = values[:, None] if values.dim() == 1 else values
    channels = flat.shape[1]
    pixel, shape, _ = within_reach(pixel, shape, blur_radius(sigma))
    planes = values.new_zeros(channels + 1, shape[0] * shape[1] * shape[2])
    planes[:channels].index_copy_(1, pixel, flat.T)  # (index_copy_ and index_select: cheaper than [:, pixel])
    planes[channels].index_fill_(0, pixel, 1.0)
    blurred = gaussian_blur(planes.reshape(channels + 1, shape[0], shape[1], shape[2]).transpose(0, 1), sigma)
    blurred = blurred.transpose(0, 1).reshape(channels + 1, -1).index_select(1, pixel)
    return (blurred[:channels] / blurred[channels:].clamp_min(1e-6)).T.reshape(values.shape)


def local_affine(seen: torch.Tensor, expected: torch.Tensor, pixel: torch.Tensor, shape: tuple[int, int, int],
                 sigma: float, eps: float = 1e-6) -> torch.Tensor:
    """The picture (P, C) at covered pixels fitted as a local affine map of the prediction (P, C), each
    channel on its own: a * expected + b, with a and b least squares over a Gaussian window (sigma px)
    and then averaged over it (a guided filter with the prediction as the guide; `eps` regularises a
    where the prediction is flat, which then tends to the local mean). What another engine changes
    smoothly (its shading, its tone curve, its colour transform, the texture's contrast) is taken up;
    a mark, which does not follow the prediction, mostly stays in `seen - fitted`."""
    channels = seen.shape[1]
    means = local_mean(torch.cat([expected, seen, expected * seen, expected * expected], 1), pixel, shape, sigma)
    m_p, m_s, m_ps, m_pp = means.split(channels, 1)
    a = (m_ps - m_p * m_s) / ((m_pp - m_p * m_p).clamp_min(0.0) + eps)
    b = m_s - a * m_p
    a, b = local_mean(torch.cat([a, b], 1), pixel, shape, sigma).split(channels, 1)
    return a * expected + b


def within_reach(pixel: torch.Tensor, shape: tuple[int, int, int], reach: int):
    """The window of the (B, H, W) pictures that holds every pixel (P,) plus `reach` pixels around them
    (clipped to the picture): (the pixels' flat indices into it, its (B, h, w) shape, its (top, left)
    corner). A blur that reaches no further gives the same values at the pixels over the window as
    over the whole picture, for less."""
    if len(pixel) == 0:
        return pixel, shape, (0, 0)
    n_images, height, width = shape
    if n_images == 1:  # one picture (every reading): one integer division, not three
        row = torch.div(pixel, width, rounding_mode="floor")
        column = pixel - row * width
    else:
        within = pixel % (height * width)
        row, column = torch.div(within, width, rounding_mode="floor"), within % width
    (row_low, row_high), (column_low, column_high) = torch.aminmax(row), torch.aminmax(column)
    top, left = max(int(row_low) - reach, 0), max(int(column_low) - reach, 0)
    bottom, right = min(int(row_high) + reach + 1, height), min(int(column_high) + reach + 1, width)
    rows, columns = bottom - top, right - left
    if n_images == 1:
        return (row - top) * columns + (column - left), (n_images, rows, columns), (top, left)
    image = torch.div(pixel, height * width, rounding_mode="floor")
    return (image * rows + row - top) * columns + column - left, (n_images, rows, columns), (top, left)


def whiten(projected: torch.Tensor, pixel: torch.Tensor, shape: tuple[int, int, int], highpass: float | None = 1.5,
           window: float | None = 2.0, floor: float = 0.05) -> torch.Tensor:
    """The residual along the mark's colour at covered pixels (P,) -> whitened for the matched filter.

    Two kinds of host residual are not white: slow chroma misfit of the relighting (subtracted: the
    local mean over the object's pixels, Gaussian sigma `highpass` px) and texture edges that a camera
    a fraction of a pixel off leaves behind (damped: divided by the local variance, sigma `window` px,
    floored at `floor` x the picture's median). Both depend on the picture only, never on the key's signs, so z
    stays N(0, 1) without a mark. pixel (P,): flat indices into the (B, H, W) `shape` of the pictures.
    `highpass` or `window` None skips that step (docs/mark.md, "Alternatives measured", has what each is worth).
    """
    detail = projected if highpass is None else projected - local_mean(projected, pixel, shape, highpass)
    if window is None:
        return detail
    variance = local_mean(detail * detail, pixel, shape, window)
    if shape[0] == 1:  # one picture: its median
        least = floor * variance.median().clamp_min(1e-12)
        return detail / torch.maximum(variance, least)
    image = pixel // (shape[1] * shape[2])
    least = torch.zeros_like(variance)
    for index in torch.unique(image).tolist():  # each picture's own median
        chosen = image == index
        least[chosen] = floor * variance[chosen].median().clamp_min(1e-12)
    return detail / torch.maximum(variance, least)


def cell_sums(encoder: SpreadSpectrumEncoder, projected: torch.Tensor, uv: torch.Tensor, image_index: torch.Tensor,
              n_images: int, grids: tuple[int, ...] | None = None) -> torch.Tensor:
    """The matched filter's evidence per cell (n_images, C*C): the residual at covered pixels,
    projected on the mark's colour, whitened and weighted by the mark's expected amplitude (P,),
    accumulated into the cells by the embedding's bilinear weights. Cell sums of several pictures of
    one asset add up (pooling). uv (P, 2): the pixels' texture coordinates; image_index (P,): which
    picture each pixel belongs to; grids: the cell grids (default the model's own), their sums side by
    side (`split_grids` parts them).
    """
    grids = grids or (encoder.chips,)
    if len(grids) > 1:
        return torch.cat([cell_sums(encoder, projected, uv, image_index, n_images, (chips,)) for chips in grids], dim=1)
    cells = grids[0]
    wrapped = uv - torch.floor(uv)
    x, y = wrapped[:, 0] * cells - 0.5, (1.0 - wrapped[:, 1]) * cells - 0.5
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = x - x0, y - y0
    sums = projected.new_zeros(n_images * cells * cells)
    for dx, dy, weight in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        cell = ((y0 + dy).long() % cells) * cells + (x0 + dx).long() % cells
        sums.index_add_(0, image_index * cells * cells + cell, weight * projected)
    return sums.reshape(n_images, -1)


def texture_cell_sums(encoder: SpreadSpectrumEncoder, texture: torch.Tensor, used: torch.Tensor,
                      grids: tuple[int, ...], scales: tuple[float, ...] = (1.0,)) -> torch.Tensor:
    """The matched filter's evidence per cell (1, sum C*C) read from a texture (1, 3, H, W) itself, with
    no original to subtract: the texels `used` (H, W), projected on the mark's colour, with the
    texture's slow content taken off and its local variance divided out over a Gaussian window of
    `scale` cells (`whiten` in texture space), weighted by the mark's amplitude and accumulated into each grid's
    cells as `cell_sums` does. The host texture stays in the sums as noise, but every step depends on
    the texture alone, never on a key's signs: `soft_bits` / `bit_weights` of these sums keep the exact
    null of an unmarked texture (`payload.detection_pvalue`), so a texture that reads as marked under
    a key carries that key's mark. Used to tell a user that the mesh given as the original is itself
    marked. `scales`: the whitening's windows (sigma), in cells of each grid; with several, each
    window's sums scaled to unit RMS and added (one fixed function of the texture)."""
    from ..imaging import gaussian_blur

    height, width = texture.shape[-2:]
    projected = (texture.float() * encoder.colour.to(texture.device).view(1, 3, 1, 1)).sum(1, keepdim=True)
    amplitude = activity_mask(texture.float(), encoder.window, encoder.floor)
    rows, columns = torch.nonzero(used.to(texture.device), as_tuple=True)
    uv = torch.stack([(columns + 0.5) / width, 1.0 - (rows + 0.5) / height], dim=-1).float()
    image_index = torch.zeros(len(rows), dtype=torch.long, device=texture.device)
    total = 0.0
    for scale in scales:
        sums = []
        for chips in grids:
            # The mark varies between cell centres: a window much narrower than a cell takes much of it off
            # with the host's content, a much wider one leaves more of the host (`OWN_MARK_SCALES`).
            sigma = max(scale * width / chips, 1.0)
            detail = projected - gaussian_blur(projected, sigma)
            variance = gaussian_blur(detail * detail, sigma)
            variance = torch.maximum(variance, 0.05 * variance.median().clamp_min(1e-12))
            values = (detail / variance * amplitude)[0, 0, rows, columns]
            sums.append(cell_sums(encoder, values, uv, image_index, 1, (chips,)))
        sums = torch.cat(sums, dim=1)
        total = total + (sums / sums.pow(2).mean().sqrt().clamp_min(1e-30) if len(scales) > 1 else sums)
    return total


def split_grids(encoder: SpreadSpectrumEncoder, sums: torch.Tensor) -> list[torch.Tensor]:
    """Cell sums of one grid or two side by side (`grids_to_read`: the model's own, then the coarse or
    the fine one) -> each grid's sums (B, C*C)."""
    for other in (encoder.coarse_chips, encoder.fine_chips):
        sizes = [encoder.chips ** 2, other ** 2]
        if other and sums.shape[1] == sum(sizes):
            return list(torch.split(sums, sizes, dim=1))
    return [sums]  # the model's grid alone


def soft_bits(encoder: SpreadSpectrumEncoder, sums: torch.Tensor, key_seed: int | None = None) -> torch.Tensor:
    """Cell sums (B, C*C) -> soft bits z (B, N), about N(0, 1) per bit without a mark under this key:
    z = sum(sign x cell) / sqrt(sum(cell^2)) over the bit's cells. The grid is the one whose C*C the
    sums have."""
    assign, sign = encoder.pattern(key_seed, math.isqrt(sums.shape[1]))
    signed = sums * sign.to(sums)
    assign = assign.to(sums.device)
    slots = encoder.n_bits + (1 if encoder.pilot_slots else 0)  # the pilot's cells summed apart, then left out
    total = signed.new_zeros(len(sums), slots).index_add(1, assign, signed)
    energy = signed.new_zeros(len(sums), slots).index_add(1, assign, signed * signed)
    return (total / energy.sqrt().clamp_min(1e-12))[:, :encoder.n_bits]


def pilot_z(encoder: SpreadSpectrumEncoder, sums: torch.Tensor, key_seed: int | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """The matched filter over the pilot, whose signs the key alone sets: one picture's cell sums
    (C*C,) -> z (a 0-d tensor; 0 for a model without a pilot) and the weights of its units for
    `payload`'s exact null (|unit| / sqrt(sum(unit^2)) over the pilot's units, 0 elsewhere). A unit is
    what one of the key's signs covers: a pilot cell, or on a pilot of blocks (`pilot_block`) the sum
    of a block's cells, so that the null draws one fair coin per sign the key drew (cells of one block
    share theirs: counted apart, the host's residual, alike in neighbouring cells, would read as a mark).
    z = sum(sign x unit) / sqrt(sum(unit^2)), about N(0, 1) without a mark under this key."""
    chips = math.isqrt(sums.shape[-1])
    assign, sign = encoder.pattern(key_seed, chips)
    pilot = assign.to(sums.device) == encoder.n_bits
    units, sign = sums * pilot, sign.to(sums)
    wide = encoder.pilot_width(chips)
    if wide > 1:  # each block's cells summed; a block is all pilot or none, its sign on every cell
        side = chips // wide
        units = units.reshape(side, wide, side, wide).sum((1, 3)).reshape(-1)
        sign = sign.reshape(side, wide, side, wide)[:, 0, :, 0].reshape(-1)
    weights = units.abs()
    energy = weights.pow(2).sum().sqrt().clamp_min(1e-30)
    return (units * sign).sum() / energy, weights / energy


def bit_weights(encoder: SpreadSpectrumEncoder, sums: torch.Tensor, key_seed: int | None = None) -> torch.Tensor:
    """Each bit's cell weights (B, N, M) for `payload`'s exact null: |cell| / sqrt(sum(cell^2)) over
    the bit's cells, zero-padded to M, the most cells any bit has. Given the picture, z_b =
    sum_i w_bi s_i with the key's cell signs s_i, independent fair coins without a mark."""
    assign, _ = encoder.pattern(key_seed, math.isqrt(sums.shape[1]))
    assign = assign.to(sums.device)
    if encoder.pilot_slots:  # the bits' cells alone
        bit_cells = torch.nonzero(assign < encoder.n_bits).squeeze(1)
        assign, sums = assign.index_select(0, bit_cells), sums.index_select(1, bit_cells)
    order, counts = _grouping(assign, encoder.n_bits)
    grouped = sums.index_select(1, order).abs()
    if bool((counts == counts[0]).all()):  # every bit the same number of cells: a reshape
        weights = grouped.reshape(len(sums), encoder.n_bits, int(counts[0]))
    else:
        slot = torch.arange(len(assign), device=sums.device) - (torch.cumsum(counts, 0) - counts)[assign[order]]
        weights = sums.new_zeros(len(sums), encoder.n_bits, int(counts.max()))
        weights[:, assign[order], slot] = grouped
    return weights / weights.pow(2).sum(-1, keepdim=True).sqrt().clamp_min(1e-30)


_GROUPINGS: list = []  # (assignment, its version, bits, (order, counts)): the last few patterns read


def _grouping(assign: torch.Tensor, n_bits: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The cells of `assign` ordered by bit (stable) and each bit's count, worked out once per pattern
    (every picture read under one key uses the same)."""
    for kept, version, bits, grouping in _GROUPINGS:
        if kept is assign and version == version_of(assign) and bits == n_bits:
            return grouping
    grouping = torch.argsort(assign, stable=True), torch.bincount(assign, minlength=n_bits)
    _GROUPINGS[:] = [(assign, version_of(assign), n_bits, grouping)] + _GROUPINGS[:3]
    return grouping


def cell_pixels(positions: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor, chips: int) -> float:
    """How wide one of a chips x chips grid's cells is, in pixels, on a mesh (positions (V, 3), faces
    (F, 3) of its textured triangles, uvs (V, 2)) in a standard view: a 256^2 picture of the object
    scaled to radius 1 (about its box's centre) from 3.5 away with a 60-degree field. The
    area-weighted median over faces of sqrt(surface area / UV area): independent of the mesh's units."""
    if len(faces) == 0:
        return float("inf")
    positions, (surface, uv_area) = positions.detach().double().cpu(), _areas(positions, faces, uvs)
    radius = float((positions - (positions.amax(0) + positions.amin(0)) / 2).norm(dim=1).max())
    usable = (uv_area > 1e-12) & (surface > 0)
    if not bool(usable.any()) or radius <= 0:
        return float("inf")
    stretch, weight = (surface[usable] / uv_area[usable]).sqrt(), surface[usable]
    order = torch.argsort(stretch)
    cumulative = torch.cumsum(weight[order], 0)
    median = stretch[order][min(int(torch.searchsorted(cumulative, cumulative[-1] / 2)), len(order) - 1)]
    return float(median) / radius / chips / PIXEL_AT_OBJECT


def palette_share(positions: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor) -> float:
    """The share of a mesh's textured surface (faces (F, 3)) whose faces have no UV area: a texture
    used as a colour palette, each such face showing one texel or a line of them. A texture mark
    has next to no room there: all of a face's pixels show the same few cells."""
    surface, uv_area = _areas(positions, faces, uvs)
    total = float(surface.sum())
    return float(surface[uv_area <= 1e-12].sum()) / total if total > 0 else 0.0


def _areas(positions: torch.Tensor, faces: torch.Tensor, uvs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each face's surface area and UV area (F,), in double precision."""
    positions, uvs, faces = positions.detach().double().cpu(), uvs.detach().double().cpu(), faces.cpu().long()
    corners = positions[faces]
    surface = 0.5 * torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]).norm(dim=1)
    first, second = uvs[faces[:, 1]] - uvs[faces[:, 0]], uvs[faces[:, 2]] - uvs[faces[:, 0]]
    return surface, 0.5 * (first[:, 0] * second[:, 1] - first[:, 1] * second[:, 0]).abs()
