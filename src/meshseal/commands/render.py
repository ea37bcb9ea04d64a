"""`meshseal render`: render a mesh file to PNG with the differentiable renderer (no gradients)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ..errors import MeshsealError
from ._common import colour, positive_int, vector3

DEFAULT_EYE = (0.0, -2.5, 3.0)  # inside the seed's camera range (x=0, y in [-3,-2], z in [2,4])
DEFAULT_LIGHT = (2.0, 1.0, 2.0)  # the mean of the seed's light distribution
MAX_SIZE = 8192
MAX_VIEWS = 1000
CHUNK = 8  # views rendered per batch


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "render", help="render a mesh to PNG image(s)",
        description="Render a mesh with meshseal's differentiable renderer. The mesh is rotated into the "
                    "canonical Z-up frame and scaled into [-1, 1]^3 so the seed's cameras frame it.")
    parser.add_argument("mesh", type=Path, help="mesh file (.obj, .glb, .gltf, .ply, .off, .stl)")
    parser.add_argument("-o", "--output", type=Path, required=True,
                        help="output PNG; with several views OUT_0.png, OUT_1.png, ... are written")
    parser.add_argument("--width", type=positive_int(MAX_SIZE), default=512, help="image width (default 512)")
    parser.add_argument("--height", type=positive_int(MAX_SIZE), default=512, help="image height (default 512)")
    parser.add_argument("--camera", type=vector3, action="append", metavar="X,Y,Z",
                        help="camera position looking at the origin, Z up (repeat for several views; "
                             f"default {','.join(map(str, DEFAULT_EYE))} for one view)")
    parser.add_argument("--light", type=vector3, metavar="X,Y,Z", default=DEFAULT_LIGHT,
                        help=f"point light position (default {','.join(map(str, DEFAULT_LIGHT))})")
    parser.add_argument("--views", type=positive_int(MAX_VIEWS), default=1, metavar="K",
                        help="number of sampled views (default 1: the fixed default camera)")
    parser.add_argument("--seed", type=int, default=0, help="random seed of the view sampler (default 0)")
    parser.add_argument("--sampler", choices=("seed", "any"), default="seed",
                        help="views for --views K>1: 'seed' = the seed's training range, 'any' = any azimuth")
    parser.add_argument("--background", type=colour, default=(0.0, 0.0, 0.0), metavar="R,G,B",
                        help="background colour in [0, 1] (default 0,0,0)")
    parser.add_argument("--up", choices=("y", "z"), default=None,
                        help="the file's up axis (default: y for OBJ/glTF/GLB, z for PLY/OFF/STL)")
    parser.add_argument("--blend", choices=("splat", "hard"), default="splat",
                        help="'splat' (antialiased, default) or 'hard' (plain rasterization)")
    parser.set_defaults(func=run)


def output_paths(output: Path, n_views: int) -> list[Path]:
    if n_views == 1:
        return [output]
    return [output.with_name(f"{output.stem}_{k}{output.suffix}") for k in range(n_views)]


def _cameras(args, torch):
    from ..render.cameras import Cameras, sample_any_view_cameras, sample_seed_cameras

    if args.camera:
        if args.views not in (1, len(args.camera)):
            raise MeshsealError("give either --camera (once per view) or --views K, not both")
        eye = torch.tensor(args.camera, dtype=torch.float32)
    elif args.views == 1:
        eye = torch.tensor([DEFAULT_EYE], dtype=torch.float32)
    else:
        generator = torch.Generator().manual_seed(args.seed)
        sampler = sample_seed_cameras if args.sampler == "seed" else sample_any_view_cameras
        return sampler(args.views, generator)
    if bool((eye.norm(dim=-1) < 1e-6).any()):
        raise MeshsealError("--camera must not be at the origin (the camera looks at the origin)")
    # Z is up on screen; a camera straight above or below the object uses +Y as its up vector instead.
    direction = torch.nn.functional.normalize(eye, dim=-1)
    z_up = torch.tensor([0.0, 0.0, 1.0]).expand_as(eye)
    up = torch.where((direction[:, 2].abs() > 0.999).unsqueeze(1), torch.tensor([0.0, 1.0, 0.0]), z_up)
    return Cameras(eye, torch.zeros_like(eye), up.clone())


def run(args: argparse.Namespace) -> int:
    import numpy as np
    import torch
    from PIL import Image

    from ..mesh import load, normalize, to_z_up
    from ..mesh.io import atomic_write, check_output, image_bytes
    from ..render import MeshRenderer, lights_at

    output: Path = args.output
    if output.suffix.lower() != ".png":
        raise MeshsealError(f"{output}: the output must be a .png file")
    mesh = load(args.mesh, up_axis=args.up)
    paths = output_paths(output, len(args.camera) if args.camera else args.views)
    protected = set(mesh.source.input_files) if mesh.source is not None else set()
    protected.add(Path(args.mesh).resolve())
    for path in paths:
        check_output(path, protected)
    mesh = normalize(to_z_up(mesh))
    cameras = _cameras(args, torch)
    lights = lights_at(torch.tensor([args.light], dtype=torch.float32).expand(len(cameras), 3))
    renderer = MeshRenderer(blend=args.blend)
    with torch.no_grad():
        for start in range(0, len(cameras), CHUNK):
            index = list(range(start, min(start + CHUNK, len(cameras))))
            rgba = renderer.render(mesh, cameras[index], lights[index], args.width, args.height,
                                   background=args.background)
            pixels = (rgba[..., :3].clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
            for k, image in zip(index, pixels):
                atomic_write(paths[k], image_bytes(Image.fromarray(image, "RGB"), camera=cameras[k]))
                print(paths[k])
    return 0
