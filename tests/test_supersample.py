"""The compiled box-mean render (`render.supersample`) against the torch path it replaces in informed
reading's footprint: rasterize `scale` times finer, shade every fragment, average each pixel's."""

import torch
import torch.nn.functional as F

from meshseal.mesh import load, normalize, to_z_up
from meshseal.reading.relight import relit_residual
from meshseal.render import MeshBatch, MeshRenderer, rasterize
from meshseal.render.supersample import box_mean_render, fused
from meshseal.render.views import sample_views

from test_spread import FIXTURES


def _torch_box_mean(mesh, cameras, lights, height, width, scale):
    n_images = len(cameras)
    positions = mesh.positions.expand(n_images, -1, -1) if mesh.positions.shape[0] == 1 else mesh.positions
    fine = rasterize(cameras.world_to_clip(positions, width / height), mesh.faces, height * scale, width * scale)
    lit = MeshRenderer().shade(mesh, cameras, lights, fine)
    within = fine.pixel % (height * scale * width * scale)
    row, column = within // (width * scale), within % (width * scale)
    parent = fine.batch * height * width + (row // scale) * width + column // scale
    return lit.new_zeros(n_images * height * width, 4).index_add_(0, parent, F.pad(lit, (0, 1), value=1.0)) / scale ** 2


def test_the_compiled_box_mean_agrees_with_shading_every_fine_fragment():
    cameras, lights = sample_views(2, "seed", torch.Generator().manual_seed(4))
    for name in ("bunny.glb", "multi_material.glb"):
        mesh = MeshBatch.from_mesh(normalize(to_z_up(load(FIXTURES / name))))
        picture = MeshRenderer()(mesh, cameras, lights, 48, 40).image
        relit = relit_residual(mesh, picture, cameras).relit  # per-picture ambient, the material table repeated
        for batch, light in ((mesh, lights), (relit, lights)):
            assert fused(batch, MeshRenderer().shader)
            sums, pix_to_face = box_mean_render(batch, cameras, light, 48, 40, 3)
            expected = _torch_box_mean(batch, cameras, light, 48, 40, 3)
            assert pix_to_face.shape == (2, 144, 120)
            assert float(expected[:, 3].sum()) > 200  # the object covers pixels of both pictures
            torch.testing.assert_close(sums, expected, atol=2e-5, rtol=0)
