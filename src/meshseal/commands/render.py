"""`meshseal render`: render a mesh file to PNG or JPEG with our renderer, OpenGL or Blender (Cycles, Eevee,
Workbench), all with the same cameras, lights and conventions (docs/conventions.md)."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from ..errors import MeshsealError
from ..render import ENGINES, LIGHT_KINDS, VIEW_TRANSFORMS
from ._common import Stages, colour, positive_int, require_mesh, sampler, vector3

FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}

DEFAULT_EYE = (0.0, -2.5, 3.0)  # the default view's direction: inside the seed's camera range (x=0, y in [-3,-2], z in [2,4])
FILL = 0.7  # the default view is moved along that direction until the object spans this share of the frame
KEY_LIGHT = (-0.4, 0.2, 0.0)  # without --light: a key light beside each camera (right, up, back, times its distance)
MAX_SIZE = 8192
MAX_VIEWS = 1000
CHUNK = 8  # views rendered per batch


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "render", help="render a mesh to PNG/JPEG image(s) with any engine",
        description="Render a mesh with meshseal's differentiable renderer, OpenGL or Blender. The mesh is "
                    "rotated into the canonical Z-up frame and scaled into [-1, 1]^3 so the seed's cameras "
                    "frame it; every engine uses the same cameras and light.")
    parser.add_argument("mesh", type=Path, help="mesh file (.obj, .glb, .gltf, .ply, .off, .stl)")
    parser.add_argument("-o", "--output", type=Path, required=True,
                        help="output .png or .jpg; with several views OUT_0.png, OUT_1.png, ... are written")
    parser.add_argument("--engine", choices=ENGINES, default="ours",
                        help="ours (default), gl (OpenGL reference), or Blender's cycles | eevee | workbench "
                             "(needs pip install 'meshseal[blender]')")
    parser.add_argument("--width", type=positive_int(MAX_SIZE), default=512, help="image width (default 512)")
    parser.add_argument("--height", type=positive_int(MAX_SIZE), default=512, help="image height (default 512)")
    parser.add_argument("--camera", type=vector3, action="append", metavar="X,Y,Z",
                        help="camera position looking at the origin, Z up (repeat for several views; default "
                             f"for one view: from the direction {','.join(map(str, DEFAULT_EYE))}, as close as "
                             f"makes the object span {round(FILL * 100)}%% of the frame)")
    parser.add_argument("--light", type=vector3, metavar="X,Y,Z", default=None,
                        help="point light position (default: a key light beside each camera, up and to its "
                             "left, so that the side the camera sees is lit)")
    parser.add_argument("--views", type=positive_int(MAX_VIEWS), default=1, metavar="K",
                        help="number of sampled views (default 1: the fixed default camera)")
    parser.add_argument("--seed", type=int, default=0,
                        help="random seed (an integer) of the views drawn for --views K>1 (default 0)")
    parser.add_argument("--sampler", type=sampler, default="seed", metavar="{paper,any}",
                        help="where the --views K>1 cameras are drawn from: 'paper' (default) the camera range "
                             "of the seed paper (Yoo et al. 2022: in front of the object, from above), 'any' all "
                             "around ('seed' is accepted for 'paper')")
    parser.add_argument("--background", type=colour, default=(0.0, 0.0, 0.0), metavar="R,G,B",
                        help="background colour in [0, 1] (default 0,0,0)")
    parser.add_argument("--up", choices=("y", "z"), default=None,
                        help="the file's up axis (default: y for OBJ/glTF/GLB, z for PLY/OFF/STL)")
    parser.add_argument("--blend", choices=("splat", "hard"), default="splat",
                        help="engine 'ours': 'splat' (antialiased, default) or 'hard' (plain rasterization)")
    parser.add_argument("--light-type", choices=LIGHT_KINDS, default="point",
                        help="Blender engines: a point, sun or area lamp where --light is, or 'world': only "
                             "a bundled studio HDRI (--hdri); default point")
    parser.add_argument("--hdri", default="studio", help="Blender's bundled world HDRI for --light-type world "
                                                         "(studio, city, courtyard, forest, interior, night, sunrise, sunset)")
    parser.add_argument("--view-transform", choices=VIEW_TRANSFORMS, default="Standard",
                        help="Blender engines: Standard (default) or AgX (Blender's own default)")
    parser.add_argument("--samples", type=positive_int(100000), default=None,
                        help="Blender engines: samples per pixel (default: cycles 64, eevee 16, workbench 8)")
    parser.add_argument("--quality", type=positive_int(100), default=90, help="JPEG quality for .jpg output (default 90)")
    parser.set_defaults(func=run)


def output_paths(output: Path, n_views: int) -> list[Path]:
    if n_views == 1:
        return [output]
    return [output.with_name(f"{output.stem}_{k}{output.suffix}") for k in range(n_views)]


def _cameras(args, torch, mesh=None):
    from ..render.cameras import Cameras, sample_any_view_cameras, sample_seed_cameras

    if args.camera:
        if args.views not in (1, len(args.camera)):
            raise MeshsealError("give either --camera (once per view) or --views K, not both")
        eye = torch.tensor(args.camera, dtype=torch.float32)
    elif args.views == 1:
        return framed_camera(mesh.positions, args.width / args.height)
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


def framed_camera(positions, aspect: float, direction=DEFAULT_EYE, fill: float = FILL):
    """The camera looking along -`direction` that frames `positions` (N, 3): centred on their projected
    box, as close as makes the box's larger side `fill` of the frame's (fov_y 60)."""
    import torch

    from ..render.cameras import Cameras

    unit = torch.nn.functional.normalize(torch.tensor([direction], dtype=torch.float32), dim=-1)
    at, distance = torch.zeros(1, 3), float(torch.tensor(direction).norm())
    up = torch.tensor([[0.0, 0.0, 1.0]])
    right = torch.nn.functional.normalize(torch.cross(-unit, up, dim=-1), dim=-1)
    true_up = torch.cross(right, -unit, dim=-1)
    points = positions.detach().float().cpu()[None]
    half_height = math.tan(math.radians(60.0) / 2)
    for _ in range(6):  # the box shrinks about as 1/distance; a few rounds settle it
        camera = Cameras(at + unit * distance, at.clone(), up.clone())
        clip = camera.world_to_clip(points, aspect)[0]
        ndc = clip[:, :2] / clip[:, 3:].clamp_min(1e-6)
        low, high = ndc.min(0).values, ndc.max(0).values
        centre, span = (low + high) / 2, float(((high - low) / 2).max())
        at = at + (right * float(centre[0]) * aspect + true_up * float(centre[1])) * distance * half_height
        distance *= span / fill
    return Cameras(at + unit * distance, at, up)


def key_lights(cameras):
    """One point light per camera beside it (KEY_LIGHT: right, up and back in the camera's frame, times
    its distance to what it looks at), so that what the camera sees is lit from the front."""
    import torch

    from ..render import lights_at

    forward = torch.nn.functional.normalize(cameras.at - cameras.eye, dim=-1)
    right = torch.nn.functional.normalize(torch.cross(forward, cameras.up, dim=-1), dim=-1)
    true_up = torch.cross(right, forward, dim=-1)
    distance = (cameras.at - cameras.eye).norm(dim=-1, keepdim=True)
    x, y, z = KEY_LIGHT
    return lights_at(cameras.eye + distance * (x * right + y * true_up - z * forward))


def _engine_options(args) -> dict:
    if args.engine == "ours":
        return {"blend": args.blend}
    if args.engine == "gl":
        return {}
    return {"light": args.light_type, "hdri": args.hdri, "view_transform": args.view_transform,
            "samples": args.samples, "seed": args.seed}


def run(args: argparse.Namespace) -> int:
    require_mesh(args.mesh)
    output: Path = args.output
    fmt = FORMATS.get(output.suffix.lower())
    if fmt is None:  # before the heavy imports: answered at once
        raise MeshsealError(f"{output}: the output must be a .png or .jpg file")
    stage = Stages()
    stage(f"loading {args.mesh.name}")
    import numpy as np
    import torch
    from PIL import Image

    from ..mesh import load, normalize, to_z_up
    from ..mesh.files import atomic_write
    from ..mesh.io import check_output
    from ..reading.pictures import image_bytes
    from ..render import lights_at, make_renderer

    mesh = load(args.mesh, up_axis=args.up, cache=True)
    paths = output_paths(output, len(args.camera) if args.camera else args.views)
    protected = set(mesh.source.input_files) if mesh.source is not None else set()
    protected.add(Path(args.mesh).resolve())
    for path in paths:
        check_output(path, protected)
    mesh = normalize(to_z_up(mesh))
    cameras = _cameras(args, torch, mesh)
    lights = (key_lights(cameras) if args.light is None else
              lights_at(torch.tensor([args.light], dtype=torch.float32).expand(len(cameras), 3)))
    renderer = make_renderer(args.engine, **_engine_options(args))
    chunk = CHUNK if args.engine in ("ours", "gl") else len(cameras)  # Blender: one process for all views
    stage(f"rendering {len(cameras)} view{'s' if len(cameras) > 1 else ''} with {args.engine}")
    with torch.no_grad():
        for start in range(0, len(cameras), chunk):
            index = list(range(start, min(start + chunk, len(cameras))))
            rgba = renderer.render(mesh, cameras[index], lights[index], args.width, args.height,
                                   background=args.background)
            pixels = (rgba[..., :3].clamp(0, 1).cpu().numpy() * 255.0 + 0.5).astype(np.uint8)
            for k, image in zip(index, pixels):
                encoded = (image_bytes(Image.fromarray(image, "RGB"), camera=cameras[k]) if fmt == "PNG" else
                           image_bytes(Image.fromarray(image, "RGB"), "JPEG", quality=args.quality))
                atomic_write(paths[k], encoded)
                print(paths[k])
    return 0
