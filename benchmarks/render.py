"""Render benchmark: our differentiable MeshRenderer (blend='splat') against the OpenGL reference.

A batch of 4 different textured meshes of about 5000 faces each (bunny, suzanne, teapot, crate from
tests/fixtures, subdivided then quadric-simplified, textures resized to 128x128, padded with
degenerate faces to one V/F so they batch), seen from 4 seeded cameras of the seed's training range
with seeded lights, rendered at 128x128, 256x256 and 400x600 (H x W). For each size it reports the
median over RUNS runs (after WARMUP warm-ups) of:

- fwd:      MeshRenderer forward with requires_grad on positions, normals, uvs and textures
            (i.e. building the autograd graph, as in training);
- fwd+bwd:  that forward plus backward of rgba.sum();
- gl:       OpenGLRenderer.render_batch of the same frames (upload, draw, read back).

Run: python benchmarks/render.py [--runs N] [--threads N] [--profile]. The last line is machine-readable:
    render_256_b4_fwdbwd_ms=<float> gl_256_b4_ms=<float>
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

ROOT = Path(__file__).resolve().parents[1]
FIXTURES = ROOT / "tests" / "fixtures"
MESHES = ["bunny.glb", "suzanne.glb", "teapot/teapot.obj", "sh3d_crate/crate.obj"]
TARGET_FACES = 5000
TEXTURE_SIZE = 128
BATCH = 4
SIZES = [(128, 128), (256, 256), (400, 600)]  # (height, width)
WARMUP = 3


def load_to_faces(path: Path, target: int):
    """A Z-up, normalised, single-texture mesh of about `target` faces: subdivide until above, then simplify."""
    import trimesh.remesh

    from meshseal.mesh import load, normalize, simplify, to_z_up, vertex_normals
    from dataclasses import replace

    mesh = normalize(to_z_up(load(path)))
    if len(mesh.materials) != 1 or mesh.materials[0].texture is None or mesh.uvs is None:
        raise SystemExit(f"benchmark mesh {path.name} must have exactly one textured material")
    while mesh.n_faces < target * 1.2:
        positions, faces, attributes = trimesh.remesh.subdivide(
            mesh.positions.double().numpy(), mesh.faces.numpy(), vertex_attributes={"uv": mesh.uvs.double().numpy()})
        positions = torch.from_numpy(positions).float()
        faces = torch.from_numpy(np.asarray(faces, dtype=np.int64))
        mesh = replace(mesh, positions=positions, faces=faces, uvs=torch.from_numpy(attributes["uv"]).float(),
                       normals=vertex_normals(positions, faces),
                       face_material=torch.zeros(len(faces), dtype=torch.long), source=None)
    mesh = simplify(mesh, target)
    texture = mesh.materials[0].texture.permute(2, 0, 1).unsqueeze(0).float()
    texture = F.interpolate(texture, size=(TEXTURE_SIZE, TEXTURE_SIZE), mode="area")[0].clamp(0, 1)
    return mesh, texture


def build_batch():
    """(positions, normals, uvs) (B, V, 3/3/2), faces (B, F, 3), textures (B, 3, T, T), padded."""
    meshes = [load_to_faces(FIXTURES / name, TARGET_FACES) for name in MESHES]
    n_vertices = max(m.n_vertices for m, _ in meshes)
    n_faces = max(m.n_faces for m, _ in meshes)
    positions = torch.zeros(BATCH, n_vertices, 3)
    normals = torch.zeros(BATCH, n_vertices, 3)
    normals[..., 2] = 1.0
    uvs = torch.zeros(BATCH, n_vertices, 2)
    faces = torch.zeros(BATCH, n_faces, 3, dtype=torch.long)  # padding: degenerate (0, 0, 0), never drawn
    textures = torch.zeros(BATCH, 3, TEXTURE_SIZE, TEXTURE_SIZE)
    for b, (mesh, texture) in enumerate(meshes):
        positions[b, :mesh.n_vertices] = mesh.positions
        normals[b, :mesh.n_vertices] = mesh.normals
        uvs[b, :mesh.n_vertices] = mesh.uvs
        faces[b, :mesh.n_faces] = mesh.faces
        textures[b] = texture
    counts = [(m.n_vertices, m.n_faces) for m, _ in meshes]
    return positions, normals, uvs, faces, textures, counts


def median_ms(fn, runs: int) -> tuple[float, float]:
    """(median, min) wall time in ms over `runs` calls after WARMUP untimed ones."""
    for _ in range(WARMUP):
        fn()
    times = []
    for _ in range(runs):
        start = time.perf_counter()
        fn()
        times.append((time.perf_counter() - start) * 1e3)
    return statistics.median(times), min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--runs", type=int, default=10, help="timed runs per measurement (>= 10)")
    parser.add_argument("--profile", action="store_true", help="also print a torch.profiler table at 256x256")
    parser.add_argument("--threads", type=int, default=0,
                        help="torch and numba threads (default: as configured); 1 is far less sensitive to a loaded CPU")
    args = parser.parse_args()

    import numba

    if args.threads > 0:
        torch.set_num_threads(args.threads)
        numba.set_num_threads(args.threads)  # numba's OpenMP layer shares torch's runtime: set both

    from meshseal.render import MeshBatch, MeshRenderer, sample_seed_cameras, sample_seed_lights

    load_start = os.getloadavg()
    print(f"start: loadavg {load_start[0]:.2f} {load_start[1]:.2f} {load_start[2]:.2f} (1/5/15 min), "
          f"{os.cpu_count()} CPUs, torch {torch.__version__} with {torch.get_num_threads()} threads, "
          f"numba {numba.__version__} with {numba.get_num_threads()} threads")

    prep = time.perf_counter()
    positions, normals, uvs, faces, textures, counts = build_batch()
    print(f"meshes {', '.join(f'{n}: V={v} F={f}' for n, (v, f) in zip(MESHES, counts))}; "
          f"padded to V={positions.shape[1]} F={faces.shape[1]}; textures {TEXTURE_SIZE}^2; "
          f"built in {time.perf_counter() - prep:.1f} s")

    generator = torch.Generator().manual_seed(0)
    cameras = sample_seed_cameras(BATCH, generator)
    lights = sample_seed_lights(BATCH, generator)
    renderer = MeshRenderer(blend="splat")
    leaves = [t.clone().requires_grad_() for t in (positions, normals, uvs, textures)]

    def forward(height, width):
        p, n, u, t = leaves
        return renderer(MeshBatch.from_tensors(p, n, u, faces, t), cameras, lights, height, width).rgba

    def forward_backward(height, width):
        for leaf in leaves:
            leaf.grad = None
        forward(height, width).sum().backward()

    gl = None
    try:
        from meshseal.render.opengl import OpenGLRenderer

        gl = OpenGLRenderer()
        gl.ctx
        print(f"OpenGL: {gl.info.get('GL_RENDERER')} / {gl.info.get('GL_VERSION')}")
    except Exception as error:  # no moderngl or no EGL: still time our renderer
        print(f"OpenGL reference unavailable: {error}", file=sys.stderr)
        gl = None

    def gl_render(height, width):
        return gl.render_batch(positions, normals, uvs, faces, textures, cameras, lights, width, height)

    rows = []
    for height, width in SIZES:
        fwd = median_ms(lambda: forward(height, width), args.runs)
        fwdbwd = median_ms(lambda: forward_backward(height, width), args.runs)
        gl_ms = median_ms(lambda: gl_render(height, width), args.runs) if gl is not None else (math.nan, math.nan)
        rows.append((height, width, fwd, fwdbwd, gl_ms))
        if height == 256 and width == 256 and gl is not None:
            with torch.no_grad():
                ours = forward(height, width)
            alpha_agree = float(((ours[..., 3] > 0.5) == (gl_render(height, width)[..., 3] > 0.5)).float().mean())
            print(f"sanity 256x256: coverage of ours (alpha > 0.5) vs GL agree on {100 * alpha_agree:.2f}% of pixels")

    try:
        layer = numba.threading_layer()
    except ValueError:
        layer = "not initialised"
    print(f"numba threading layer: {layer}; torch threads: {torch.get_num_threads()}")
    print()
    print(f"{'size (HxW)':>11} | {'fwd ms':>15} | {'fwd+bwd ms':>15} | {'GL ms':>13} | {'fwd/GL':>6} | {'fwd+bwd/GL':>10}")
    print(f"{'':>11} | {'median (min)':>15} | {'median (min)':>15} | {'median (min)':>13} | {'':>6} | {'':>10}")
    print("-" * 88)
    for height, width, fwd, fwdbwd, gl_ms in rows:
        print(f"{f'{height}x{width}':>11} | {fwd[0]:7.1f} ({fwd[1]:5.1f}) | {fwdbwd[0]:7.1f} ({fwdbwd[1]:5.1f}) | "
              f"{gl_ms[0]:6.1f} ({gl_ms[1]:4.1f}) | {fwd[0] / gl_ms[0]:6.1f} | {fwdbwd[0] / gl_ms[0]:10.1f}")
    print(f"(batch {BATCH}, blend 'splat', float32; median and min of {args.runs} runs after {WARMUP} warm-ups; "
          f"ratios of medians)")

    if args.profile:
        from torch.profiler import ProfilerActivity, profile

        forward_backward(256, 256)
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            for _ in range(5):
                forward_backward(256, 256)
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))

    load_end = os.getloadavg()
    print(f"end: loadavg {load_end[0]:.2f} {load_end[1]:.2f} {load_end[2]:.2f} (1/5/15 min)")
    at_256 = next(r for r in rows if r[0] == 256 and r[1] == 256)
    print(f"render_256_b4_fwdbwd_ms={at_256[3][0]:.2f} gl_256_b4_ms={at_256[4][0]:.2f}")


if __name__ == "__main__":
    main()
