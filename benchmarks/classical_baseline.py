"""Our spread-spectrum mark against a classical image watermark in the texture (issue #10), same PSNR, same reading.

For each textured fixture (and optionally the first N test meshes of a dataset) the same 64 random bits are
embedded twice: by the shipped default model (`Watermarker.embed`, public key, strength 1) and by a classical
image watermark from a kept library (`blind-watermark`: DWT-DCT-SVD quantisation, or `invisible-watermark`'s
dwtDctSvd) in the first textured material as an 8-bit RGB image, its strength bisected per texture so that the
texture PSNR matches ours within 0.5 dB. Both marked textures are stored as 8 bits. Each marked mesh is rendered
from K seeded views at 256x256 (8-bit) and read with the true camera: ours as `meshseal detect` reads it (`Watermarker.read`, every grid its mark may lie on);
the baseline by un-rendering the picture onto a full-resolution texture (each covered pixel's texel gets
albedo * seen / expected, the relit original's shading divided out, splatted with bilinear weights and averaged;
texels not seen keep the original texture) and running the library's extractor on it. The baseline read straight
from its marked texture checks that it decodes at that strength at all.

    pip install -e '.[baseline]' && pip install --no-deps blind-watermark   # (its opencv-python would shadow opencv-python-headless)
    pip install --no-deps invisible-watermark   # only for --library invisible-watermark (it lists torch)
    python benchmarks/classical_baseline.py [--views 4] [--seed 0] [--library NAME] [--data DIR --meshes N]
        [--models default,robust] [--attacks none,jpeg90,jpeg75,jpeg50,webp80,brightness,noise2]

With several `--models` each is set against the baseline at its own texture PSNR; `--attacks` (names of
`meshseal.evaluation.attacks`; those that keep the frame, since both readings take the true camera)
puts every picture through each attack first, and a second table gives the mean bit accuracy per attack.

LAST line: ours_bit_acc=<f> baseline_bit_acc=<f> psnr_texture=<f> (means over the first model's clean
pictures; psnr_texture is ours)
"""

from __future__ import annotations

import argparse
import contextlib
import io
import math
import os
import time
from pathlib import Path

import numpy as np
import torch

import meshseal
from meshseal.evaluation.attacks import apply, parse
from meshseal.mesh import Material, Mesh, normalize, to_z_up
from meshseal.reading.relight import relit_residual
from meshseal.render.views import sample_views
from meshseal.render import MeshBatch, MeshRenderer

FIXTURES = Path(__file__).resolve().parents[1] / "tests" / "fixtures"
MESHES = ["bunny.glb", "teapot/teapot.obj", "sh3d_crate/crate.obj", "suzanne.glb", "multi_material.glb",
          "sh3d_deckChair/deckChair.obj"]
SIZE = 256


def quantise(image: torch.Tensor) -> torch.Tensor:
    """Float image in [0, 1] -> the nearest 8-bit level (what a PNG holds)."""
    return torch.round(image.clamp(0.0, 1.0) * 255.0) / 255.0


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    """PSNR in dB of two 8-bit images."""
    mse = np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)
    return math.inf if mse == 0 else 10.0 * math.log10(255.0 ** 2 / mse)


class BlindWatermark:
    """`blind-watermark` (github.com/guofei9987/blind_watermark): one bit per 4x4 DCT block of the Haar DWT
    approximation of each YUV channel, quantised into the block's first two singular values with steps d1, d2
    (36, 20 by default); the bits repeat over the blocks and the extractor averages them. `strength` scales
    both steps. Images are RGB uint8 (H, W, 3); the library works in OpenCV's BGR order."""

    range = (0.02, 8.0)

    def __init__(self, seed: int):
        self.seed = seed

    def _watermark(self, strength: float):
        from blind_watermark import WaterMark

        with contextlib.redirect_stdout(io.StringIO()):  # it prints a banner on construction
            mark = WaterMark(password_wm=self.seed, password_img=self.seed)
        mark.bwm_core.d1, mark.bwm_core.d2 = 36.0 * strength, 20.0 * strength
        return mark

    def embed(self, image: np.ndarray, bits: np.ndarray, strength: float) -> np.ndarray:
        mark = self._watermark(strength)
        mark.read_img(img=np.ascontiguousarray(image[..., ::-1]))
        mark.read_wm(bits.astype(bool).copy(), mode="bit")
        return np.round(mark.embed())[..., ::-1].clip(0, 255).astype(np.uint8)

    def extract(self, image: np.ndarray, n_bits: int, strength: float) -> np.ndarray:
        mark = self._watermark(strength)
        return np.asarray(mark.extract(embed_img=np.ascontiguousarray(image[..., ::-1]), wm_shape=n_bits,
                                       mode="bit"), dtype=np.uint8)


class InvisibleWatermark:
    """`invisible-watermark`'s dwtDctSvd (github.com/ShieldMnt/invisible-watermark): one bit per 4x4 DCT block
    of the Haar DWT approximation of the U channel, quantised into the block's first singular value with step
    `scales[1]` (36 by default); the bits repeat over the blocks and the decoder averages them. `strength`
    scales that step. Its `EmbedDwtDctSvd` is used directly: the package's `WatermarkEncoder` refuses images
    under 256x256 pixels. It has no key. Images are RGB uint8 (H, W, 3), the library's BGR order inside."""

    range = (0.02, 8.0)

    def __init__(self, seed: int):
        del seed  # no key to seed

    def _method(self, bits: list[int], strength: float):
        from imwatermark.dwtDctSvd import EmbedDwtDctSvd

        return EmbedDwtDctSvd(bits, wmLen=len(bits), scales=[0, 36.0 * strength, 0])

    def embed(self, image: np.ndarray, bits: np.ndarray, strength: float) -> np.ndarray:
        marked = self._method([int(b) for b in bits], strength).encode(np.ascontiguousarray(image[..., ::-1]))
        return np.round(marked)[..., ::-1].clip(0, 255).astype(np.uint8)

    def extract(self, image: np.ndarray, n_bits: int, strength: float) -> np.ndarray:
        bits = self._method([0] * n_bits, strength).decode(np.ascontiguousarray(image[..., ::-1]))
        return np.asarray(bits, dtype=np.uint8)


LIBRARIES = {"blind-watermark": BlindWatermark, "invisible-watermark": InvisibleWatermark}


def match_psnr(library, image: np.ndarray, bits: np.ndarray, target: float, steps: int = 14):
    """Bisect the library's strength (log scale) so the marked image's PSNR is within 0.5 dB of `target`,
    the closest found (preferring not louder than the target). Returns (marked, strength, psnr)."""
    low, high = (math.log(v) for v in library.range)
    best = None
    for _ in range(steps):
        middle = (low + high) / 2
        marked = library.embed(image, bits, math.exp(middle))
        value = psnr(marked, image)
        key = (abs(value - target) > 0.5, value < target - 0.5, abs(value - target))
        if best is None or key < best[0]:
            best = (key, marked, math.exp(middle), value)
        if value > target:
            low = middle  # too quiet: louder
        else:
            high = middle
    return best[1], best[2], best[3]


def unrender_texture(batch: MeshBatch, material: int, pictures: torch.Tensor, cameras,
                     texture: torch.Tensor) -> tuple[torch.Tensor, float]:
    """Pictures (B, 3, H, W) of the mesh -> the marked texture (3, T, T') of `material` as they show it: per
    covered pixel albedo * seen / expected (the relit original's shading divided out), splatted onto the
    texel grid with bilinear weights and averaged over all pictures; texels not seen keep `texture`.
    Also returns the fraction of texels seen."""
    found = relit_residual(batch, pictures, cameras)
    pick = found.material == material
    diffuse = batch.diffuse[material].clamp_min(1e-3)
    ratio = found.seen[pick] / found.expected[pick].clamp_min(1e-3)
    values = (found.albedo[pick] / diffuse * ratio).clamp(0.0, 1.0)
    _, height, width = texture.shape
    uv = found.uv[pick] - torch.floor(found.uv[pick])
    x, y = uv[:, 0] * width - 0.5, (1.0 - uv[:, 1]) * height - 0.5
    x0, y0 = torch.floor(x), torch.floor(y)
    fx, fy = x - x0, y - y0
    sums, weights = texture.new_zeros(3, height * width), texture.new_zeros(height * width)
    for dx, dy, weight in ((0, 0, (1 - fx) * (1 - fy)), (1, 0, fx * (1 - fy)), (0, 1, (1 - fx) * fy), (1, 1, fx * fy)):
        texel = ((y0 + dy).long() % height) * width + (x0 + dx).long() % width
        sums.index_add_(1, texel, (weight[:, None] * values).T)
        weights.index_add_(0, texel, weight)
    seen = weights > 1e-3
    estimate = texture.reshape(3, -1).clone()
    estimate[:, seen] = sums[:, seen] / weights[seen]
    return estimate.reshape(3, height, width), float(seen.float().mean())


def dataset_meshes(root: str, count: int) -> list[tuple[str, Mesh]]:
    """The first `count` test meshes of a built dataset, as textured Meshes."""
    from meshseal.data.dataset import MeshDataset

    dataset = MeshDataset(root, "test")
    meshes = []
    for index in range(min(count, len(dataset))):
        item = dataset[index]
        n_verts, n_faces = int(item["n_verts"]), int(item["n_faces"])
        texture = Material(texture=item["texture"].permute(1, 2, 0))
        meshes.append((item["id"], Mesh(item["positions"][:n_verts], item["normals"][:n_verts], item["faces"][:n_faces],
                                        item["uvs"][:n_verts], materials=[texture])))
    return meshes


def to_uint8(texture: torch.Tensor) -> np.ndarray:
    """(3, H, W) float in [0, 1] -> (H, W, 3) uint8."""
    return (quantise(texture) * 255).round().byte().permute(1, 2, 0).numpy()


def ours_bit_accuracy(watermarker, original: MeshBatch, picture: torch.Tensor, camera, bits: torch.Tensor) -> float:
    """Our bits read as `meshseal detect` reads a picture with its camera known (every grid the mesh's
    mark may lie on; a picture it refuses counts as read at chance)."""
    try:
        reading = watermarker.read(picture[0].permute(1, 2, 0).numpy(), original, camera=camera)
    except meshseal.MeshsealError:
        return 0.5
    found = torch.tensor([int(b) for b in watermarker.decide([reading]).bits])
    return float((found == bits).float().mean())


def measure(name: str, mesh: Mesh, watermarker, library, views: int, seed: int, renderer: MeshRenderer,
            attacks=("none",)) -> dict:
    """One mesh: both marks embedded at the same texture PSNR, rendered from the same views, each picture
    put through each attack (8-bit), read back with the true camera."""
    generator = torch.Generator().manual_seed(seed)
    bits = torch.randint(0, 2, (watermarker.n_bits,), generator=generator)
    material = next(i for i, m in enumerate(mesh.materials) if m.texture is not None)
    original = to_uint8(mesh.materials[material].texture.permute(2, 0, 1))

    ours = watermarker.embed(mesh, bits="".join(str(int(b)) for b in bits))
    for m in ours.materials:
        if m.texture is not None:
            m.texture = quantise(m.texture)
    psnr_ours = psnr(to_uint8(ours.materials[material].texture.permute(2, 0, 1)), original)

    baseline_texture, strength, psnr_baseline = match_psnr(library, original, bits.numpy(), psnr_ours)
    baseline = mesh.copy()
    baseline.materials[material].texture = torch.from_numpy(baseline_texture).float() / 255.0
    direct = float((library.extract(baseline_texture, len(bits), strength) == bits.numpy()).mean())

    canonical = lambda m: MeshBatch.from_mesh(normalize(to_z_up(m)))  # noqa: E731
    original_batch = canonical(mesh)
    cameras, lights = sample_views(views, "seed", torch.Generator().manual_seed(seed))
    with torch.no_grad():
        pictures = {k: quantise(renderer(canonical(m), cameras, lights, SIZE, SIZE).image) for k, m in
                    (("ours", ours), ("baseline", baseline))}
        texture = original_batch.textures[material]
        ours_acc, baseline_acc = {a: 0.0 for a in attacks}, {a: 0.0 for a in attacks}
        coverage = 0.0
        for view in range(views):  # one picture at a time, as `Watermarker.detect` reads them
            for number, attack in enumerate(attacks):
                hit = {}
                for kind in ("ours", "baseline"):
                    picture = (pictures[kind][view].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
                    attacked = apply(attack, picture, np.random.default_rng([seed, view, number]))
                    hit[kind] = torch.from_numpy(attacked.astype(np.float32) / 255.0).permute(2, 0, 1)[None]
                ours_acc[attack] += ours_bit_accuracy(watermarker, original_batch, hit["ours"], cameras[[view]], bits) / views
                seen, fraction = unrender_texture(original_batch, material, hit["baseline"], cameras[[view]], texture)
                if number == 0:
                    coverage += fraction / views
                baseline_acc[attack] += float((library.extract(to_uint8(seen), len(bits), strength)
                                               == bits.numpy()).mean()) / views
    first = attacks[0]
    return {"name": name, "texture": "x".join(map(str, original.shape[:2])), "psnr_ours": psnr_ours,
            "psnr_baseline": psnr_baseline, "strength": strength, "ours": ours_acc[first],
            "baseline": baseline_acc[first], "direct": direct, "coverage": coverage,
            "attacks": {a: (ours_acc[a], baseline_acc[a]) for a in attacks}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--views", type=int, default=4, help="rendered views per mesh (K)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--library", choices=sorted(LIBRARIES), default="blind-watermark")
    parser.add_argument("--data", default=None, help="a built dataset: add its first --meshes test meshes")
    parser.add_argument("--meshes", type=int, default=0)
    parser.add_argument("--models", default="default", help="comma-separated shipped models, each against the baseline")
    parser.add_argument("--attacks", default="none", help="comma-separated attacks that keep the frame")
    args = parser.parse_args()
    attacks = parse(args.attacks)
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    print(f"load average at start: {os.getloadavg()}, torch threads: {torch.get_num_threads()}")
    start = time.perf_counter()
    library = LIBRARIES[args.library](args.seed)
    meshes = [(name, meshseal.load_mesh(FIXTURES / name)) for name in MESHES]
    if args.data and args.meshes > 0:
        meshes += dataset_meshes(args.data, args.meshes)
    renderer = MeshRenderer()
    by_model = {}
    for model_name in args.models.split(","):
        watermarker = meshseal.load(model_name)
        by_model[model_name] = [measure(name, mesh, watermarker, library, args.views, args.seed + index, renderer,
                                        attacks) for index, (name, mesh) in enumerate(meshes)]
    watermarker = meshseal.load(args.models.split(",")[0])
    rows = by_model[watermarker.name if watermarker.name in by_model else args.models.split(",")[0]]
    keys = ("psnr_ours", "psnr_baseline", "ours", "baseline", "direct", "coverage")
    mean = {key: sum(row[key] for row in rows) / len(rows) for key in keys}
    print(f"\n{args.library} vs meshseal ({watermarker.name}), {watermarker.n_bits} bits, {args.views} views at "
          f"{SIZE}x{SIZE}, seed {args.seed}; bit accuracy with the true camera\n")
    print("| mesh | texture | PSNR ours / baseline (dB) | baseline strength | bit acc ours | bit acc baseline "
          "| baseline direct | texels seen |")
    print("|---|---|---|---|---|---|---|---|")
    for row in rows:
        print(f"| {row['name']} | {row['texture']} | {row['psnr_ours']:.2f} / {row['psnr_baseline']:.2f} | "
              f"{row['strength']:.3f} | {row['ours']:.3f} | {row['baseline']:.3f} | {row['direct']:.3f} | "
              f"{row['coverage']:.2f} |")
    print(f"| **mean** | | {mean['psnr_ours']:.2f} / {mean['psnr_baseline']:.2f} | | {mean['ours']:.3f} | "
          f"{mean['baseline']:.3f} | {mean['direct']:.3f} | {mean['coverage']:.2f} |")
    if len(by_model) > 1 or attacks != ["none"]:
        print(f"\nMean bit accuracy per attack, {len(meshes)} meshes x {args.views} views, true camera; the "
              "baseline at each model's texture PSNR (ours / baseline, and the ratio of their gains over chance)\n")
        print("| attack | " + " | ".join(f"{m} (PSNR {np.mean([r['psnr_ours'] for r in part]):.1f} dB): ours / baseline / gain ratio"
                                       for m, part in by_model.items()) + " |")
        print("|---|" + "---|" * len(by_model))
        for attack in attacks:
            cells = []
            for part in by_model.values():
                ours = float(np.mean([r["attacks"][attack][0] for r in part]))
                base = float(np.mean([r["attacks"][attack][1] for r in part]))
                ratio = (ours - 0.5) / (base - 0.5) if base > 0.5 else None  # no gain of the baseline's to compare
                cells.append(f"{ours:.3f} / {base:.3f} / " + ("-" if ratio is None else f"{ratio:.1f}x"))
            print(f"| {attack} | " + " | ".join(cells) + " |")
    print(f"\n{time.perf_counter() - start:.1f} s; load average at end: {os.getloadavg()}")
    print(f"ours_bit_acc={mean['ours']:.4f} baseline_bit_acc={mean['baseline']:.4f} "
          f"psnr_texture={mean['psnr_ours']:.2f} psnr_texture_baseline={mean['psnr_baseline']:.2f} "
          f"baseline_direct_bit_acc={mean['direct']:.4f}")


if __name__ == "__main__":
    main()
