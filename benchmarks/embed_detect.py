"""Embed and detect speed with the shipped default model (or --model PATH), medians on this machine.

Embed: a 5k-face mesh with a 512x512 texture (Watermarker.embed). Detect: a 256x256 picture (object
finding, framing, decoder; informed models: with the picture's camera known, i.e. un-rendering,
relighting and reading, the original mesh prepared once), then registration (pictures without
metadata): 256^2 pictures of the five textured fixtures from two seeded views each, one timed read a
picture (`detect_registered_256_ms`: their median, what a user's picture costs), and the sphere's
picture (`detect_registered_sphere_256_ms`: the worst case, a shape with the same silhouette from every
side under a texture too fine to turn it by, so every retry and second look runs), then a batch of
pictures read as `meshseal detect` reads a folder (pictures per second, one process), then the command
line itself: the wall time of `meshseal detect PICTURE --mesh MESH` and of `meshseal embed MESH --views
0` in a fresh process (start-up included: what a user waits for the first result), and `meshseal detect
FOLDER --mesh MESH --jsonl` on a folder of 64 saved 256^2 pictures of the marked bunny with one worker
process per core (`--workers`): the rate at which its lines arrive between the first and the last
(`folder_pictures_per_s`), and the same command with `--register` on 16 of them, one worker per core
(`folder_registered_ms`: the time between lines, i.e. a registered picture's cost when a folder is
checked). References in the same run: a plain 512x512 bilinear resize + 3x3 blur in torch (what any
image tool does to the texture), so the ratio says how far from free we are on this machine, and the
wall time of a fresh `python -c "import torch, trimesh, numba"` (`import_floor_s`: the libraries' own
start-up, which no command can undercut).

LAST line: embed_5k_512_ms=<float> detect_256_ms=<float> detect_registered_256_ms=<float>
detect_registered_sphere_256_ms=<float> pictures_per_s=<float> cli_detect_s=<float> cli_embed_s=<float>
folder_pictures_per_s=<float> import_floor_s=<float> folder_registered_ms=<float>
"""

from __future__ import annotations

import argparse
import io
import os
import statistics
import time

import numpy as np
import torch

import meshseal
from meshseal.commands._common import available_cores
from meshseal.mesh import Material, Mesh, simplify, spherical_uv, vertex_normals
from meshseal.render import MeshRenderer, cameras_from_eyes, lights_at


def timed(function, repeats: int = 15, warmup: int = 3) -> float:
    for _ in range(warmup):
        function()
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        function()
        samples.append(time.perf_counter() - start)
    return statistics.median(samples) * 1e3


def five_k_mesh(texture_size: int = 512) -> Mesh:
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=5)  # 20480 faces
    mesh = Mesh(torch.tensor(sphere.vertices, dtype=torch.float32), torch.zeros(len(sphere.vertices), 3),
                torch.tensor(sphere.faces))
    mesh = simplify(mesh, 5000)
    mesh.normals = vertex_normals(mesh.positions, mesh.faces)
    mesh.uvs = spherical_uv(mesh.positions)
    generator = torch.Generator().manual_seed(0)
    mesh.materials = [Material(texture=torch.rand(texture_size, texture_size, 3, generator=generator))]
    return mesh


FIXTURES = ("bunny.glb", "suzanne.glb", "teapot/teapot.obj", "sh3d_crate/crate.obj", "sh3d_deckChair/deckChair.obj")


def fixture_registrations(watermarker, bits: str, views: int = 2) -> tuple[list[float], float]:
    """Seconds of `Watermarker.detect` without metadata (registration) on 256^2 pictures of the textured
    fixtures, marked with `bits`, from `views` seeded views of the paper's camera range each (one
    warm-up, then one timed read a picture), and the share read with every bit right: the pictures a
    user has, where the sphere's picture is registration's worst case."""
    from pathlib import Path

    from meshseal.mesh import load, normalize, to_z_up
    from meshseal.render import sample_seed_cameras

    folder = Path(__file__).resolve().parents[1] / "tests" / "fixtures"
    seconds, right = [], 0
    for name in FIXTURES:
        mesh = load(folder / name)
        original = watermarker.original(mesh)
        marked = normalize(to_z_up(watermarker.embed(mesh, bits=bits)))
        cameras = sample_seed_cameras(views, torch.Generator().manual_seed(0))
        lights = lights_at(torch.tensor([[2.0, 1.0, 2.0]]).expand(views, 3))
        rgba = MeshRenderer().render(marked, cameras, lights, 256, 256)
        for view in range(views):
            picture = (rgba[view, ..., :3].numpy() * 255 + 0.5).astype(np.uint8)
            if not seconds:
                watermarker.detect(picture, original)
            start = time.perf_counter()
            found = watermarker.detect(picture, original)
            seconds.append(time.perf_counter() - start)
            right += found.bits == bits
    return seconds, right / len(seconds)


def batch_rate(watermarker, original, image, count: int = 20) -> float:
    """Pictures per second over `count` reads and decisions of one picture, as the command reads a folder."""
    start = time.perf_counter()
    for _ in range(count):
        watermarker.decide([watermarker.read(image, original)])
    return count / (time.perf_counter() - start)


def command_line_times(image) -> tuple[float, float, float, float, float, float]:
    """Wall seconds of `meshseal detect` on one saved picture of the bunny fixture and of `meshseal embed
    --views 0` on it, each in a fresh process (median of 3); the folder rate (pictures per second
    between the first and the last line of `meshseal detect FOLDER --jsonl`); the import floor; the
    milliseconds between lines of `meshseal detect FOLDER --register` (16 pictures, one worker per
    core) and the share of those read right."""
    import json
    import shutil
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    bunny = Path(__file__).resolve().parents[1] / "tests" / "fixtures" / "bunny.glb"
    with tempfile.TemporaryDirectory() as folder:
        marked = Path(folder) / "marked.glb"
        command = [sys.executable, "-m", "meshseal.cli"]
        subprocess.run(command + ["embed", str(bunny), "-o", str(marked), "--message", "ab42", "--views", "0"],
                       check=True, capture_output=True)
        subprocess.run(command + ["render", str(marked), "-o", str(Path(folder) / "view.png")], check=True,
                       capture_output=True)

        def wall(arguments: list[str]) -> float:
            samples = []
            for _ in range(3):
                start = time.perf_counter()
                subprocess.run(command + arguments, check=True, capture_output=True)
                samples.append(time.perf_counter() - start)
            return statistics.median(samples)

        detect_s = wall(["detect", str(Path(folder) / "view.png"), "--mesh", str(bunny)])
        embed_s = wall(["embed", str(bunny), "-o", str(Path(folder) / "again.glb"), "--message", "ab42", "--views", "0"])
        pictures = Path(folder) / "pictures"
        pictures.mkdir()
        subprocess.run(command + ["render", str(marked), "-o", str(pictures / "v.png"), "--views", "4", "--width",
                                  "256", "--height", "256"], check=True, capture_output=True)
        for index in range(64):  # 64 pictures: 4 views, each saved 16 times
            shutil.copy(pictures / f"v_{index % 4}.png", pictures / f"copy_{index:02d}.png")
        for index in range(4):
            (pictures / f"v_{index}.png").unlink()

        def rate(arguments: list[str], count: int) -> tuple[float, float]:
            """Lines per second between the first and the last of `meshseal detect ARGUMENTS --jsonl`, and
            the share of its `count` pictures detected with the right message."""
            start = time.perf_counter()
            run = subprocess.Popen(command + ["detect", *arguments, "--mesh", str(bunny), "--jsonl"],
                                   stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
            lines, arrivals = [], []
            for line in run.stdout:
                arrivals.append(time.perf_counter() - start)
                lines.append(json.loads(line))
            if run.wait() != 0 or len(lines) != count:
                raise SystemExit(f"meshseal detect {' '.join(arguments)} failed (exit {run.returncode}, {len(lines)} lines)")
            right = sum(bool(r["detected"]) and r["message"] == "ab42" for r in lines) / count
            return (count - 1) / (arrivals[-1] - arrivals[0]), right

        folder_rate, right = rate([str(pictures), "--workers", str(available_cores())], 64)
        if right < 1.0:
            raise SystemExit(f"meshseal detect FOLDER read only {right:.2f} of its pictures right")
        registered = Path(folder) / "registered"
        registered.mkdir()
        for index in range(16):
            shutil.copy(pictures / f"copy_{index:02d}.png", registered / f"copy_{index:02d}.png")
        registered_rate, registered_right = rate([str(registered), "--register", "--workers", str(available_cores())], 16)
    floor = []
    for _ in range(3):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", "import torch, trimesh, numba"], check=True)
        floor.append(time.perf_counter() - start)
    return detect_s, embed_s, folder_rate, statistics.median(floor), 1000.0 / registered_rate, registered_right


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", default=None, help="shipped model name or .safetensors path (default: default)")
    args = parser.parse_args()
    print(f"load average at start: {os.getloadavg()}, torch threads: {torch.get_num_threads()}")
    watermarker = meshseal.load(args.model)
    mesh = five_k_mesh()
    bits = "".join(str(int(b)) for b in torch.randint(0, 2, (watermarker.n_bits,), generator=torch.Generator().manual_seed(1)))
    embed_ms = timed(lambda: watermarker.embed(mesh, bits=bits))
    marked = watermarker.embed(mesh, bits=bits)
    camera = cameras_from_eyes(torch.tensor([[0.0, -2.5, 3.0]]))
    light = lights_at(torch.tensor([[2.0, 1.0, 2.0]]))
    rgba = MeshRenderer().render(marked, camera, light, 256, 256)
    picture = (rgba[0, ..., :3].numpy() * 255 + 0.5).astype(np.uint8)
    from PIL import Image

    if watermarker.informed:
        from meshseal.reading.pictures import image_bytes

        original = watermarker.original(mesh)
        image = Image.open(io.BytesIO(image_bytes(Image.fromarray(picture), camera=camera)))
        image.load()
        detect = lambda: watermarker.detect(image, original)  # noqa: E731
        register_ms = timed(lambda: watermarker.detect(picture, original), repeats=3, warmup=1)
        found = watermarker.detect(picture, original)
        registered_accuracy = sum(a == b for a, b in zip(found.bits, bits)) / len(bits)
        fixture_seconds, fixture_right = fixture_registrations(watermarker, bits)
    else:
        detect, register_ms, fixture_seconds = (lambda: watermarker.detect(picture)), None, []
    detect_ms = timed(detect)
    texture = mesh.materials[0].texture.permute(2, 0, 1)[None]
    blur = torch.ones(3, 1, 3, 3) / 9

    def reference():
        small = torch.nn.functional.interpolate(texture, size=(128, 128), mode="bilinear", antialias=True)
        big = torch.nn.functional.interpolate(small, size=(512, 512), mode="bilinear")
        return torch.nn.functional.conv2d(big, blur, padding=1, groups=3)

    reference_ms = timed(reference)
    result = detect()
    accuracy = sum(a == b for a, b in zip(result.bits, bits)) / len(bits)
    per_second = batch_rate(watermarker, original if watermarker.informed else None, image if watermarker.informed
                            else picture)
    cli_detect_s, cli_embed_s, folder_rate, import_floor_s, folder_registered_ms, registered_right = command_line_times(
        image if watermarker.informed else Image.fromarray(picture))
    print(f"model: {watermarker.name} ({watermarker.n_bits} bits)")
    print(f"embed 5k faces + 512^2 texture: {embed_ms:.1f} ms  (goal < 300)")
    print(f"detect 256^2 picture:            {detect_ms:.1f} ms  (goal < 30); bit accuracy on it {accuracy:.3f}")
    if register_ms is not None:
        print(f"detect with registration (camera unknown), {len(fixture_seconds)} pictures of the textured fixtures: "
              f"median {1e3 * statistics.median(fixture_seconds):.0f} ms  (goal < 2000), max "
              f"{1e3 * max(fixture_seconds):.0f} ms; {fixture_right:.2f} read with every bit right")
        print(f"detect with registration, the sphere under a noise texture (the worst case: every side has its "
              f"silhouette, and the texture is too fine to turn it by, so every retry and second look runs): "
              f"{register_ms:.0f} ms; bit accuracy on it {registered_accuracy:.3f}")
    print(f"batch of pictures as `meshseal detect FOLDER` reads them: {per_second:.1f} pictures/s  (goal >= 10)")
    print(f"command line, fresh process: detect one picture {cli_detect_s:.2f} s, embed --views 0 {cli_embed_s:.2f} s "
          f"(goal <= 1.5 s to the first result); import torch, trimesh, numba alone: {import_floor_s:.2f} s")
    print(f"meshseal detect FOLDER (64 pictures, default workers): {folder_rate:.1f} pictures/s  (goal >= 10)")
    print(f"meshseal detect FOLDER --register (16 pictures, {available_cores()} workers): one picture every "
          f"{folder_registered_ms:.0f} ms, {registered_right:.2f} read right")
    print(f"reference resize+blur of the 512^2 texture: {reference_ms:.1f} ms; embed/reference = {embed_ms / reference_ms:.1f}x")
    print(f"load average at end: {os.getloadavg()}")
    registered_ms = 1e3 * statistics.median(fixture_seconds) if fixture_seconds else float("nan")
    print(f"embed_5k_512_ms={embed_ms:.2f} detect_256_ms={detect_ms:.2f} detect_registered_256_ms="
          f"{registered_ms:.0f} detect_registered_sphere_256_ms="
          f"{register_ms if register_ms is not None else float('nan'):.0f} pictures_per_s={per_second:.2f} "
          f"cli_detect_s={cli_detect_s:.2f} cli_embed_s={cli_embed_s:.2f} folder_pictures_per_s={folder_rate:.2f} "
          f"import_floor_s={import_floor_s:.2f} folder_registered_ms={folder_registered_ms:.0f}")


if __name__ == "__main__":
    main()
