"""Cached G-buffers (meshseal.training.gbuffer): a baked view composited with a texture is the render."""

import math

import pytest
import torch
import trimesh

from meshseal.reading.framing import BOX_MARGIN
from meshseal.render.views import sample_views
from meshseal.render import MeshBatch, MeshRenderer
from meshseal.training.gbuffer import GBuffers, bake_views, composite


def _spheres(n: int) -> dict:
    sphere = trimesh.creation.icosphere(3)
    p = torch.tensor(sphere.vertices, dtype=torch.float32)
    normals = torch.tensor(sphere.vertex_normals, dtype=torch.float32)
    uv = torch.stack([torch.atan2(p[:, 1], p[:, 0]) / (2 * math.pi) + 0.5, torch.acos(p[:, 2].clamp(-1, 1)) / math.pi], -1)
    faces = torch.tensor(sphere.faces, dtype=torch.long)
    scale = torch.linspace(0.6, 1.0, n)[:, None, None]
    return {"positions": p[None] * scale, "normals": normals[None].repeat(n, 1, 1), "uvs": 3 * uv[None].repeat(n, 1, 1),
            "faces": faces[None].repeat(n, 1, 1), "n_verts": torch.full((n,), len(p))}


@pytest.mark.parametrize("sampler", ["seed", "any"])
def test_composite_of_a_baked_view_is_the_hard_render(sampler):
    generator = torch.Generator().manual_seed(1)
    batch = _spheres(3)
    cameras, lights = sample_views(3, sampler, generator)
    texture = torch.rand(3, 3, 24, 40, generator=generator)  # not square, uvs beyond [0, 1]: REPEAT wrapping
    background = torch.rand(3, 3, generator=generator)
    buffers = bake_views(batch, cameras, lights, 96, framed=False)
    picture = composite(texture, buffers, background)
    render = MeshRenderer(blend="hard")(MeshBatch.from_tensors(batch["positions"], batch["normals"], batch["uvs"],
                                                               batch["faces"], texture), cameras, lights, 96, 96,
                                        background).image
    assert buffers.mask.any() and not buffers.mask.all()
    assert (picture - render).abs().max() < 1e-4
    # and it is differentiable in the texture
    texture.requires_grad_(True)
    composite(texture, buffers, background).sum().backward()
    assert texture.grad.abs().sum() > 0


def test_framed_views_fill_the_frame_as_detect_frames_a_picture():
    generator = torch.Generator().manual_seed(2)
    batch = _spheres(2)
    cameras, lights = sample_views(2, "seed", generator)
    loose = bake_views(batch, cameras, lights, 128, framed=False)
    framed = bake_views(batch, cameras, lights, 128, framed=True)
    assert framed.mask.float().mean() > 3 * loose.mask.float().mean()
    for mask in framed.mask:
        rows = torch.nonzero(mask.any(1)).squeeze(1)
        cols = torch.nonzero(mask.any(0)).squeeze(1)
        extent = max(rows[-1] - rows[0], cols[-1] - cols[0]) + 1
        margin = 128 * BOX_MARGIN / (1 + 2 * BOX_MARGIN)  # the box's margin, in frame pixels
        assert abs(128 - extent - 2 * margin) <= 3
        assert abs(int(rows[0]) - margin) <= 2 or abs(int(cols[0]) - margin) <= 2


def test_gbuffers_save_and_load_round_trip(tmp_path):
    generator = torch.Generator().manual_seed(3)
    batch = _spheres(2)
    cameras, lights = sample_views(2, "seed", generator)
    buffers = bake_views(batch, cameras, lights, 40, framed=True)
    buffers = GBuffers(buffers.uv.half(), buffers.shade.half(), buffers.mask, torch.tensor([4, 7]))
    buffers.save(tmp_path / "bank.npz", {"views": 1})
    loaded, meta = GBuffers.load(tmp_path / "bank.npz")
    assert meta == {"views": 1}
    assert torch.equal(loaded.mask, buffers.mask) and torch.equal(loaded.item, buffers.item)
    assert torch.equal(loaded.uv, buffers.uv) and torch.equal(loaded.shade, buffers.shade)


def test_a_vertex_mark_reshades_baked_views_as_the_renderer_does():
    """Normals and uvs changed after baking (what a vertex encoder does): the stored faces, barycentrics
    and surface points give the hard render of the changed mesh, and gradients reach them."""
    from meshseal.training.gbuffer import composite_surface

    generator = torch.Generator().manual_seed(4)
    batch = _spheres(3)
    cameras, lights = sample_views(3, "seed", generator)
    buffers = bake_views(batch, cameras, lights, 80, framed=True, surface=True)
    texture = torch.rand(3, 3, 32, 32, generator=generator)
    normals = batch["normals"] + 0.3 * torch.randn(batch["normals"].shape, generator=generator)
    uvs = batch["uvs"] + 0.05 * torch.randn(batch["uvs"].shape, generator=generator)
    background = torch.rand(3, 3, generator=generator)
    normals.requires_grad_(True)
    uvs.requires_grad_(True)
    picture = composite_surface(texture, normals, uvs, batch["faces"], buffers, background)
    # the same framed view through the renderer: the framed clip coordinates, rasterized afresh
    from meshseal.render import rasterize, scatter_to_image
    from meshseal.render.renderer import MeshBatch as Batch
    from meshseal.training.gbuffer import frame_clip

    clip = frame_clip(cameras.world_to_clip(batch["positions"], 1.0), torch.ones(3, batch["positions"].shape[1], dtype=torch.bool))
    fragments = rasterize(clip, batch["faces"], 80, 80)
    mesh = Batch.from_tensors(batch["positions"], normals.detach(), uvs.detach(), batch["faces"], texture)
    lit = MeshRenderer(blend="hard").shade(mesh, cameras, lights, fragments)
    alpha = (fragments.pix_to_face >= 0).unsqueeze(-1)
    expected = (scatter_to_image(lit, fragments, 0.0) + ~alpha * background[:, None, None, :]).permute(0, 3, 1, 2)
    assert (picture.detach() - expected).abs().max() < 1e-4
    picture.sum().backward()
    assert normals.grad.abs().sum() > 0 and uvs.grad.abs().sum() > 0


@pytest.fixture(scope="module")
def two_meshes():
    """Two dataset items (spheres of two sizes), as a list: what `bake` reads of a dataset."""
    spheres = _spheres(2)
    return [{key: value[i] for key, value in spheres.items()} for i in range(2)]


def test_each_chunk_of_a_bank_draws_its_views_alone(two_meshes):
    """A chunk's cameras, lights and distortions come from its own generator: baked in any order, or alone,
    the chunks make the same bank (what lets a pool of processes bake it)."""
    from meshseal.training.gbuffer import _bake_chunk, bake

    bank = bake(two_meshes, 2, 24, "seed", 5, batch_size=1)
    chunks = [(view, index) for view in range(2) for index in range(len(two_meshes))]
    parts = {chunk: _bake_chunk(two_meshes, chunk[0], [chunk[1]], 24, "seed", 5, None, False) for chunk in reversed(chunks)}
    assert torch.equal(bank.uv, torch.cat([parts[chunk].uv for chunk in chunks]))
    assert torch.equal(bank.shade, torch.cat([parts[chunk].shade for chunk in chunks]))
    assert torch.equal(bank.item, torch.tensor([index for _, index in chunks]))
    assert not torch.equal(parts[(0, 0)].uv, parts[(1, 0)].uv)  # the two views of a mesh differ
    assert bool(bank.mask.any())


def test_a_bank_baked_in_processes_is_the_bank_baked_in_one(two_meshes):
    """A worker process baking the chunks bakes the views this process bakes (a pool of one: each spawned
    worker imports torch, seconds of the test tier)."""
    from meshseal.training.gbuffer import bake

    alone = bake(two_meshes, 2, 24, "seed", 5, batch_size=1)
    pooled = bake(two_meshes, 2, 24, "seed", 5, batch_size=1, workers=1)
    assert torch.equal(alone.item, pooled.item) and torch.equal(alone.mask, pooled.mask)
    assert torch.equal(alone.uv, pooled.uv) and torch.equal(alone.shade, pooled.shade)
