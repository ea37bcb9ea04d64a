"""The blind surface code: a keyed code running along the surface's x in the canonical frame
(`models.surface`), read from a picture alone (no original mesh, no camera)."""

from __future__ import annotations

import torch

from ..models import WatermarkModel
from ..models.surface import read_picture
from .base import Method, source_prefix


def surface_evidence(model: WatermarkModel, pictures: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """A surface model's soft bits (B, N) of pictures (B, 3, H, W) as 8-bit files hold them, the
    object found from the plain background as `meshseal detect` finds it (`alpha` is ignored but for
    pictures whose background is not plain)."""
    from ..reading.framing import object_mask

    softs = []
    for picture, coverage in zip(pictures, alpha):
        image = (torch.round(picture.clamp(0, 1) * 255) / 255).permute(1, 2, 0).cpu().numpy()
        mask, _ = object_mask(image)
        if mask.sum() == 0:
            mask = coverage.cpu().numpy() > 0.5
        softs.append(read_picture(model.texture_encoder, image, mask))
    return torch.stack(softs).to(pictures.device)


class SurfaceMethod(Method):
    """The blind surface code (`models.surface`)."""

    name = "surface"
    params_named = ("n_bits", "chips", "mark_colour", "texture_psnr", "activity_window", "activity_floor", "pattern_seed")
    takes_strength = True
    paper_pictures = True  # evaluated on the paper's 600 x 400 pictures

    def describe(self) -> str:
        """The model card's sentence on the embedder and the extractor."""
        config = self.model.config.to_dict()
        text = (f"keyed code along the object's x (`models/surface.py`): {config['chips']} cells across the object "
                        "as the seed's cameras see it, each bit a scrambled Walsh-Hadamard code over them, laid in the "
                        "texture through the surface point each texel paints, colour "
                        f"`{config['mark_colour']}`, amplitude shaped by local texture activity (window "
                        f"{config['activity_window']}, floor {config['activity_floor']}), texture PSNR "
                        f"{config['texture_psnr']} dB over the texels the mesh paints at strength 1; read **blind**, from "
                        "the picture alone: the object's column range, the chroma high-passed along rows, averaged per "
                        "cell and correlated with the codes. It needs the seed paper's views (cameras at x = 0, z up): "
                        "a view from the side shows the code edge-on")
        return text

    def embed(self, mesh, message, key_seed, strength, warn):
        """Each texture carrying the code: its texels traced to the surface points they paint in the
        canonical frame, where the paper's cameras look from."""
        from dataclasses import replace

        from ..errors import MeshsealError
        from ..mesh import normalize, to_z_up
        from ..models.surface import texel_columns

        if mesh.uvs is None or all(m.texture is None for m in mesh.materials):
            raise MeshsealError(f"{source_prefix(mesh)}the mesh has no texture with UVs to carry the watermark, "
                                f"and this model only marks textures")
        marked = mesh.copy()
        canonical = normalize(to_z_up(replace(mesh, source=None)))
        for index, material in enumerate(marked.materials):
            if material.texture is None:
                continue
            faces = marked.faces[marked.face_material == index]
            if len(faces) == 0:  # a texture no face uses shows nowhere
                continue
            texture = material.texture.to(self.device).permute(2, 0, 1).unsqueeze(0)
            columns, painted = texel_columns(canonical.positions, canonical.normals, faces, marked.uvs,
                                             *texture.shape[-2:])
            marked_texture = self.model.texture_encoder(texture, message, columns[None].to(self.device),
                                                        painted[None].to(self.device), strength=strength)
            material.texture = marked_texture[0].permute(1, 2, 0).cpu()
        return marked

    def blind_evidence(self, pixels, mask, background):
        return read_picture(self.model.texture_encoder, pixels.clip(0, 1), mask > 0.5)

    def mark_batch(self, batch, message, vertex_mask):
        from .batches import batch_texel_columns

        columns, painted = batch_texel_columns(batch)
        texture = self.model.texture_encoder(batch["texture"], message, columns, painted)
        return batch["normals"], batch["uvs"], texture, painted[:, None]

    def read_batch(self, pictures, alpha, original_mesh, cameras, original_image, background, frame_size,
                   distortions_2d, generator, reference_mix):
        """The whole picture, read as a file holds it."""
        if distortions_2d is not None:
            pictures = distortions_2d(pictures, generator)
        return pictures, surface_evidence(self.model, pictures, alpha)
