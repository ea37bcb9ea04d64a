"""The watermarking model: vertex encoder + texture encoder + decoder, built from a config."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

import torch
from torch import nn

from .spread import SpreadSpectrumEncoder
from .surface import SurfaceCodeEncoder
from .decoders import HiddenDecoder, ResidualCNNDecoder, SimpleCNNDecoder, UVDecoder
from .texture_encoders import HiddenTextureEncoder, UNetTextureEncoder
from .vertex_encoders import PointNetVertexEncoder

STRATEGIES = ("vertex", "texture", "vertex+texture")


@dataclass
class ModelConfig:
    """Every architecture of the seed, selectable by name (see configs/*.yaml)."""

    n_bits: int = 32
    strategy: str = "texture"  # vertex | texture | vertex+texture
    texture_encoder: str = "hidden"  # hidden | unet | spread (keyed spread spectrum, see models/spread.py) | surface (models/surface.py)
    texture_channels: int = 64
    texture_blocks: int = 4
    texture_downsample: int = 1
    texture_strength: float = 0.1
    texture_rms: float = 0.0  # > 0: fixed-power mark of this RMS at the working size (texture PSNR ~ -20 log10 rms)
    texture_rms_after_clip: bool = False  # the RMS held is that of the mark left after clipping to [0, 1]
    texture_size: int = 128
    texture_tile: int = 0  # > 0: a learned periodic carrier of this period (in working-size texels)
    texture_tile_channels: int = 8
    texture_tile_keying: str = "antipodal"  # antipodal: a bit flips its carrier's sign | fsk: each value of a bit has its own carrier
    texture_coords: bool = False  # hidden encoder: the texel's (u, v) as inputs, so a bit can take a place on the surface
    chips: int = 128  # spread: cells per side of the UV square, each carrying one bit with a random sign; surface: cells along x
    coarse_chips: int = 64  # spread: the grid of meshes whose `chips` cells would be under coarse_below px (0: never)
    coarse_below: float = 0.6  # spread: ... in a standard 256^2 view (models.spread.cell_pixels)
    fine_chips: int = 512  # spread: the grid of meshes whose `chips` cells would be over fine_above px (0: never)
    fine_above: float = 2.0  # spread: ... in the same view (a texture with fewer texels is resampled up)
    mark_colour: str = "blue-yellow"  # spread: colour direction of the mark
    texture_psnr: float = 40.0  # spread: texture PSNR of the mark at strength 1
    activity_window: int = 5  # spread: window of the just-noticeable-difference mask, in texels
    activity_floor: float = 0.3  # spread: the mask's floor (flat areas still carry this much)
    pattern_seed: int = 0  # spread: seed of the cell-to-bit assignment and the cell signs
    bit_block: int = 1  # spread: cells given to a bit together, bit_block x bit_block (each its own sign)
    pilot_block: int = 1  # spread: the pilot's cells in pilot_block x pilot_block blocks of one sign (a wider pilot)
    pilot_chips: int = 0  # spread: the finest grid the pilot's signs take (a finer grid puts them on blocks of its cells; 0: every grid's own cells)
    pilot_gain: float = 1.0  # spread: the pilot's cells' amplitude against the message's (before the mark is scaled to its PSNR)
    pilot_share: float = 0.0  # spread: the share of the cells that carry the key's own signs, not the message (a presence test)
    read_highpass: float = 1.5  # spread reading: the residual's slow part taken off (Gaussian sigma, px; `models.spread.whiten`)
    read_window: float = 2.0  # spread reading: the window of the residual's local variance (sigma, px)
    read_brightness: float = 0.0  # spread reading: the brightness fit's window (sigma, px; 0: each pixel's own; < 0: none)
    read_affine: float = 0.0  # spread reading without a brightness fit: > 0, the picture fitted as a local affine map of the prediction, per channel (window sigma, px)
    read_colour: str = ""  # spread reading: the colour the residual is read along ('': the mark's own; models.spread.colour_direction)
    read_imports: bool = False  # spread reading: predict from the original's textures as an asset's import may have changed them (`reading.imports`)
    vertex_encoder: str = "pointnet2"  # pointnet (max pooling) | pointnet2 (average pooling)
    vertex_width: int = 64
    normal_strength: float = 0.05
    uv_strength: float = 0.002
    decoder: str = "hidden"  # hidden | simple | residual (blind) | uv (informed, UVDecoder) | matched (spread) | surface (blind)
    decoder_channels: int = 64
    decoder_blocks: int = 7
    decoder_stem_stride: int = 1
    decoder_growth: int = 1
    decoder_head_grid: int = 0  # hidden decoder: > 0 keeps a g x g grid of positions before its linear layer
    frame_size: int = 128
    uv_grid: int = 64  # informed decoder: cells per side of the un-rendered UV map

    @property
    def method(self) -> str:
        """The watermarking scheme this config builds (`methods.method_for`): 'spread' (matched
        decoder), 'surface' (surface decoder) or 'learned' (the paper's networks)."""
        return {"matched": "spread", "surface": "surface"}.get(self.decoder, "learned")

    @classmethod
    def from_dict(cls, values: dict) -> "ModelConfig":
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"unknown model setting(s): {', '.join(sorted(unknown))}")
        config = cls(**values)
        if config.strategy not in STRATEGIES:
            raise ValueError(f"strategy must be one of {STRATEGIES}")
        return config

    def to_dict(self) -> dict:
        return asdict(self)


class WatermarkModel(nn.Module):
    def __init__(self, config: ModelConfig):
        super().__init__()
        self.config = config
        n = config.n_bits
        self.texture_encoder = None
        if "texture" in config.strategy:
            if config.texture_encoder == "hidden":
                self.texture_encoder = HiddenTextureEncoder(n, config.texture_channels, config.texture_blocks,
                                                            config.texture_size, config.texture_strength,
                                                            config.texture_downsample, config.texture_tile,
                                                            config.texture_tile_channels, config.texture_tile_keying,
                                                            config.texture_coords)
                self.texture_encoder.rms = config.texture_rms
                self.texture_encoder.rms_after_clip = config.texture_rms_after_clip
            elif config.texture_encoder == "spread":
                self.texture_encoder = SpreadSpectrumEncoder(n, config.chips, config.mark_colour, config.texture_psnr,
                                                             config.activity_window, config.activity_floor,
                                                             config.pattern_seed, config.coarse_chips, config.coarse_below,
                                                             config.fine_chips, config.fine_above, config.bit_block,
                                                             config.pilot_share, config.pilot_block, config.pilot_gain,
                                                             config.pilot_chips)
            elif config.texture_encoder == "surface":
                self.texture_encoder = SurfaceCodeEncoder(n, config.chips, config.mark_colour, config.texture_psnr,
                                                          config.activity_window, config.activity_floor,
                                                          config.pattern_seed)
            elif config.texture_encoder == "unet":
                self.texture_encoder = UNetTextureEncoder(n, size=config.texture_size, strength=config.texture_strength)
                self.texture_encoder.rms = config.texture_rms
                self.texture_encoder.rms_after_clip = config.texture_rms_after_clip
            else:
                raise ValueError(f"unknown texture encoder '{config.texture_encoder}'")
        self.vertex_encoder = None
        if "vertex" in config.strategy:
            if config.vertex_encoder not in ("pointnet", "pointnet2"):
                raise ValueError(f"unknown vertex encoder '{config.vertex_encoder}'")
            self.vertex_encoder = PointNetVertexEncoder(n, "max" if config.vertex_encoder == "pointnet" else "avg",
                                                        config.vertex_width, config.normal_strength, config.uv_strength)
        if config.decoder == "hidden":
            self.decoder = HiddenDecoder(n, config.decoder_channels, config.decoder_blocks,
                                         config.decoder_stem_stride, config.decoder_growth,
                                         config.decoder_head_grid)
        elif config.decoder == "simple":
            self.decoder = SimpleCNNDecoder(n, config.decoder_channels)
        elif config.decoder == "residual":
            self.decoder = ResidualCNNDecoder(n, config.decoder_channels)
        elif config.decoder == "uv":
            self.decoder = UVDecoder(n, config.decoder_channels, config.uv_grid)
        elif config.decoder == "matched":
            if config.texture_encoder != "spread" or config.strategy != "texture":
                raise ValueError("the matched-filter decoder reads the spread texture encoder's mark alone")
            self.decoder = None
        elif config.decoder == "surface":
            if config.texture_encoder != "surface" or config.strategy != "texture":
                raise ValueError("the surface decoder reads the surface texture encoder's mark alone")
            self.decoder = None
        else:
            raise ValueError(f"unknown decoder '{config.decoder}'")

    @property
    def n_bits(self) -> int:
        return self.config.n_bits

    @property
    def device(self) -> torch.device:
        """Where the model lives (a spread-spectrum model has buffers but no parameters)."""
        return next(iter([*self.parameters(), *self.buffers()])).device

    def embed(self, positions, normals, uvs, texture, message, vertex_mask=None):
        """The learned encoders on a batch: (normals, uvs, texture), each unchanged where its encoder is
        off. Keyed marks (spread, surface) mark through their `methods.Method` instead."""
        if self.vertex_encoder is not None:
            normals, uvs = self.vertex_encoder(positions, normals, uvs, message, vertex_mask)
        if self.texture_encoder is not None:
            texture = self.texture_encoder(texture, message)
        return normals, uvs, texture

    def decode(self, image: torch.Tensor) -> torch.Tensor:
        """Framed pictures (B, 3, S, S) in [0, 1] (or, informed, UV maps (B, 10, G, G)) -> logits (B, N)."""
        return self.decoder(image if isinstance(self.decoder, UVDecoder) else image * 2.0 - 1.0)
