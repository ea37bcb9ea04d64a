"""The paper's learned networks: a texture encoder (and optionally a vertex encoder) marks the mesh;
a decoder reads framed pictures (blind) or pictures un-rendered onto the original's UV grid
(informed, `reading.relight.uv_maps`). Soft bits are logits: no p-values without an expected message."""

from __future__ import annotations

import sys
from dataclasses import replace

import torch

from ..reading.relight import uv_maps
from .base import Method, informed_original, source_prefix

_Z_UP = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


class LearnedMethod(Method):
    """The paper's encoder and decoder networks (`models.texture_encoders`, `models.vertex_encoders`,
    `models.decoders`)."""

    name = "learned"
    params_named = ("n_bits", "strategy", "texture_encoder", "texture_channels", "texture_blocks", "texture_downsample",
                    "texture_strength", "texture_rms", "texture_size", "texture_tile", "vertex_encoder", "vertex_width",
                    "normal_strength", "uv_strength", "decoder", "decoder_channels", "decoder_blocks", "frame_size",
                    "uv_grid")

    def __init__(self, model):
        super().__init__(model)
        self.informed = model.config.decoder == "uv"
        self.paper_pictures = not self.informed  # a blind decoder learned the paper's protocol: read its pictures

    def describe(self) -> str:
        """The model card's sentence on the embedder(s) and the extractor."""
        config = self.model.config.to_dict()
        if self.informed:
            text = (f"informed decoder `uv` ({config['decoder_channels']} channels) reading the picture un-rendered "
                            f"onto a {config['uv_grid']}^2 UV grid of the original mesh (detection needs the original mesh "
                            "and the picture's camera: from the PNG's metadata, or registered)")
        else:
            text = (f"decoder `{config['decoder']}` ({config['decoder_channels']} channels, {config['decoder_blocks']} "
                            f"blocks, stem stride {config['decoder_stem_stride']}), decoding on a {config['frame_size']}^2 "
                            "object-centred frame")
        mark = (f"fixed RMS {config['texture_rms']}" if config.get("texture_rms", 0) > 0
                else f"residual bound {config['texture_strength']}")
        text = (f"texture encoder `{config['texture_encoder']}` ({config['texture_channels']} channels, "
                        f"blocks at 1/{config['texture_downsample']} resolution, periodic carrier {config['texture_tile']}, "
                        f"{mark}); {text}")
        return text

    def embed(self, mesh, message, key_seed, strength, warn):
        """Textures marked at the model's working resolution (the residual upsampled to each
        texture's size); with a vertex encoder, normals (and uvs) too, in the canonical frame."""
        from ..errors import MeshsealError
        from ..mesh import normalize, to_z_up

        if strength != 1.0:
            raise MeshsealError("only spread-spectrum and surface models take a strength (learned marks have "
                                "a trained power)")
        model = self.model
        marked = mesh.copy()
        textured = marked.uvs is not None and any(m.texture is not None for m in marked.materials)
        if model.texture_encoder is not None and textured:
            for material in marked.materials:
                if material.texture is None:
                    continue
                texture = material.texture.to(self.device).permute(2, 0, 1).unsqueeze(0)
                material.texture = model.texture_encoder(texture, message)[0].permute(1, 2, 0).cpu()
        elif model.vertex_encoder is None:
            raise MeshsealError(f"{source_prefix(mesh)}the mesh has no texture with UVs to carry the watermark, "
                                f"and this model only marks textures")
        elif model.texture_encoder is not None and warn:
            print("meshseal: warning: no texture with UVs: only the vertex normals carry the mark", file=sys.stderr)
        if model.vertex_encoder is not None:
            rotation = _Z_UP if mesh.up_axis == "y" else torch.eye(3)
            canonical = normalize(to_z_up(replace(mesh, source=None)))
            uvs = marked.uvs if marked.uvs is not None else torch.zeros(mesh.n_vertices, 2)
            normals, new_uvs = model.vertex_encoder(canonical.positions.to(self.device)[None],
                                                    canonical.normals.to(self.device)[None],
                                                    uvs.to(self.device)[None], message)
            marked.normals = (normals[0].cpu() @ rotation).contiguous()  # back to the file's frame
            if marked.uvs is not None:
                marked.uvs = new_uvs[0].cpu()
        return marked

    def prepare(self, mesh):
        if not self.informed:
            return super().prepare(mesh)
        return informed_original(self, mesh)

    def evidence(self, original, picture, camera):
        if not self.informed:
            return super().evidence(original, picture, camera)
        return self.read_pictures(original, picture, camera)[0].cpu()

    def read_pictures(self, original, pictures, cameras, key_seed=None) -> torch.Tensor:
        """Logits (B, N) of pictures (B, 3, H, W) of the prepared `original` seen from `cameras`."""
        return self.model.decode(uv_maps(original, pictures, cameras, self.model.config.uv_grid))

    def blind_evidence(self, pixels, mask, background):
        """The object's square box framed at the decoder's size, decoded."""
        from ..reading.framing import boxes_from_mask, crop_boxes

        if self.informed:
            return super().blind_evidence(pixels, mask, background)
        tensor = torch.from_numpy(pixels).permute(2, 0, 1)[None].to(self.device)
        box = boxes_from_mask(torch.from_numpy(mask)[None])
        framed = crop_boxes(tensor, box, self.model.config.frame_size, background.to(tensor)[None])
        return self.model.decode(framed.clamp(0, 1))[0].cpu()

    def mark_batch(self, batch, message, vertex_mask):
        model, texture = self.model, batch["texture"]
        normals, uvs = batch["normals"], batch["uvs"]
        if model.vertex_encoder is not None:
            normals, uvs = model.vertex_encoder(batch["positions"], normals, uvs, message, vertex_mask)
        if model.texture_encoder is not None:
            texture = model.texture_encoder(texture, message)
        return normals, uvs, texture, None

    def read_batch(self, pictures, alpha, original_mesh, cameras, original_image, background, frame_size,
                   distortions_2d, generator, reference_mix):
        from ..reading.framing import frame

        if self.informed:
            if distortions_2d is not None:
                pictures = distortions_2d(pictures, generator)
            framed = uv_maps(original_mesh, pictures, cameras, self.model.config.uv_grid, original_image, reference_mix)
        else:
            framed = frame(pictures, alpha, frame_size, background)
            if distortions_2d is not None:
                framed = distortions_2d(framed, generator)
        return framed, self.model.decode(framed)
