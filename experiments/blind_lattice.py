"""Blind detection with a self-synchronising lattice mark in the seed paper's protocol: test meshes
with spherical UVs and a noise or real 128^2 texture, the seed's camera and light ranges, 600 x 400
renders (the paper's size) by our renderer, read from the picture alone. Not shipped: see
docs/training.md for what it reached.

The texture carries one keyed tile (`period` x `period` texels, `cells` x `cells` chips: a pilot plus
one scrambled Walsh-Hadamard code per bit) repeated over the UV square, so on the surface the mark is
a lattice, locally an affine image of the texture's. Per window of the picture: whiten the blue-yellow
chroma, find the local lattice from the two strongest independent autocorrelation peaks, fold every
pixel onto the tile by its lattice coordinates, synchronise with the pilot over every cyclic shift and
small unimodular basis change, and add the aligned tiles of all windows before correlating with the
codes (classical image watermarking's answer to geometric attacks).

python experiments/blind_lattice.py --data data --meshes 12 --stride 23 --bits 8 --psnr 28
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from meshseal.data.dataset import MeshDataset
from meshseal.framing import object_mask
from meshseal.mesh import spherical_uv
from meshseal.metrics import visibility
from meshseal.models.spread import COLOURS, activity_mask
from meshseal.models.surface import _hadamard
from meshseal.render import MeshBatch, MeshRenderer, sample_seed_cameras, sample_seed_lights


def _unimodular(limit: int = 1) -> list[np.ndarray]:
    """2x2 integer matrices with entries in [-limit, limit] and determinant +-1: every way a reduced
    lattice basis found in the picture can relate to the texture's."""
    values = range(-limit, limit + 1)
    return [np.array(m).reshape(2, 2) for m in itertools.product(values, repeat=4)
            if abs(m[0] * m[3] - m[1] * m[2]) == 1]


class LatticeEncoder(nn.Module):
    """Texture + message -> texture carrying the periodic keyed tile (no learned parameters)."""

    def __init__(self, n_bits: int, period: int = 8, cells: int = 8, pilot_share: float = 0.5,
                 colour: str = "blue-yellow", texture_psnr: float = 40.0, window: int = 5, floor: float = 0.3,
                 seed: int = 0, grating: float = 0.0):
        super().__init__()
        chips = cells * cells
        if chips & (chips - 1) or n_bits + 1 >= chips:
            raise ValueError(f"{cells}x{cells} chips (a power of two) must exceed n_bits + 1")
        self.n_bits, self.period, self.cells, self.pilot_share = n_bits, period, cells, pilot_share
        self.texture_psnr, self.window, self.floor, self.seed = texture_psnr, window, floor, seed
        self.grating = grating  # share of the power in two sync gratings, one period along u and along v
        self.register_buffer("colour", F.normalize(torch.tensor(COLOURS[colour]), dim=0))
        pilot, codes = self._draw(seed)
        self.register_buffer("pilot", pilot)
        self.register_buffer("codes", codes)

    def _draw(self, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Keyed pilot (n, n) and codes (N, n, n): Hadamard rows (skipping the constant one) picked and
        chip-scrambled by the seed."""
        rng = np.random.default_rng(seed)
        chips = self.cells * self.cells
        rows = _hadamard(chips)[1 + rng.permutation(chips - 1)[: self.n_bits + 1]]
        scramble = rng.choice([-1.0, 1.0], chips)
        place = rng.permutation(chips)
        rows = (rows * scramble)[:, place].reshape(-1, self.cells, self.cells)
        return torch.tensor(rows[0], dtype=torch.float32), torch.tensor(rows[1:], dtype=torch.float32)

    def tile(self, message: torch.Tensor) -> torch.Tensor:
        """Bits (B, N) -> chip values (B, n, n), unit mean square."""
        data = torch.einsum("bk,kij->bij", 2.0 * message - 1.0, self.codes) / math.sqrt(self.n_bits)
        keyed = math.sqrt(self.pilot_share) * self.pilot + math.sqrt(1.0 - self.pilot_share) * data
        phase = 2 * math.pi * (torch.arange(self.cells) + 0.5) / self.cells
        grating = torch.cos(phase)[:, None] + torch.cos(phase)[None, :]  # unit mean square
        return math.sqrt(1.0 - self.grating) * keyed + math.sqrt(self.grating) * grating.to(keyed)

    def forward(self, texture: torch.Tensor, message: torch.Tensor, strength: float = 1.0) -> torch.Tensor:
        """texture (B, 3, H, W) in [0, 1] (H, W multiples of the period), message (B, N) -> marked."""
        height, width = texture.shape[-2:]
        if height % self.period or width % self.period:
            raise ValueError(f"texture {height}x{width} is not a whole number of {self.period}-texel periods")
        tile = self.tile(message).to(texture)[:, None]
        tile = F.interpolate(tile, scale_factor=self.period / self.cells, mode="nearest")
        pattern = tile.repeat(1, 1, height // self.period, width // self.period)
        residual = activity_mask(texture, self.window, self.floor) * self.colour.to(texture)[None, :, None, None] * pattern
        rms = strength * 10.0 ** (-self.texture_psnr / 20.0)
        residual = residual * rms / residual.pow(2).mean(dim=(1, 2, 3), keepdim=True).sqrt().clamp_min(1e-8)
        return (texture + residual).clamp(0.0, 1.0)


def whiten(image: np.ndarray, mask: np.ndarray, colour: np.ndarray, sigma: float = 2.0) -> np.ndarray:
    """The picture's chroma along the mark's colour, minus its local mean, over its local RMS: shading
    and smooth host texture drop out, busy and dark regions count alike. (H, W, 3) -> (H, W), 0 off
    the object."""
    from scipy import ndimage

    signal = image @ colour
    weight = ndimage.gaussian_filter(mask.astype(float), sigma) + 1e-6
    mean = ndimage.gaussian_filter(signal * mask, sigma) / weight
    detail = (signal - mean) * mask
    energy = ndimage.gaussian_filter(detail * detail, 3 * sigma) / ndimage.gaussian_filter(mask.astype(float), 3 * sigma).clip(1e-6)
    return np.where(mask, detail / np.sqrt(energy + 1e-8), 0.0)


def lattice_peaks(patch: np.ndarray, weight: np.ndarray, min_period: float, max_period: float,
                  count: int = 6) -> list[tuple[np.ndarray, float]]:
    """The strongest local maxima of a window's normalised autocorrelation, as (offset (dy, dx),
    height), offsets between min_period and max_period pixels, one of each +-pair."""
    from scipy import ndimage

    size = patch.shape[0]
    full = 2 * size
    spectrum = np.fft.rfft2(patch * weight, (full, full))
    overlap = np.fft.irfft2(np.abs(np.fft.rfft2(weight, (full, full))) ** 2, (full, full))
    auto = np.fft.irfft2(np.abs(spectrum) ** 2, (full, full))
    auto = np.fft.fftshift(auto / np.maximum(overlap, 0.25 * overlap.max()))
    auto = auto / max(auto[full // 2, full // 2], 1e-12)
    offsets = np.stack(np.meshgrid(np.arange(full) - full // 2, np.arange(full) - full // 2, indexing="ij"), -1)
    radius = np.linalg.norm(offsets, axis=-1)
    allowed = (radius >= min_period) & (radius <= max_period) & ((offsets[..., 0] > 0) | ((offsets[..., 0] == 0) & (offsets[..., 1] > 0)))
    peaks = (auto == ndimage.maximum_filter(auto, size=3)) & allowed
    found = np.argwhere(peaks)
    heights = auto[found[:, 0], found[:, 1]]
    order = np.argsort(heights)[::-1][:count]
    result = []
    for index in order:
        y, x = found[index]
        # parabolic sub-pixel refinement
        dy = _vertex(auto[y - 1, x], auto[y, x], auto[y + 1, x]) if 0 < y < full - 1 else 0.0
        dx = _vertex(auto[y, x - 1], auto[y, x], auto[y, x + 1]) if 0 < x < full - 1 else 0.0
        result.append((offsets[y, x] + np.array([dy, dx]), float(heights[index])))
    return result


def _vertex(left: float, centre: float, right: float) -> float:
    denominator = left - 2 * centre + right
    return 0.0 if denominator >= 0 else float(np.clip(0.5 * (left - right) / denominator, -0.5, 0.5))


def lattice_basis(peaks: list[tuple[np.ndarray, float]]) -> np.ndarray | None:
    """Two independent lattice vectors (columns of a 2x2 matrix, pixels) from autocorrelation peaks:
    the strongest peak and the strongest one not parallel to it, Gauss-reduced."""
    if len(peaks) < 2:
        return None
    first = peaks[0][0]
    for vector, _ in peaks[1:]:
        cross = first[0] * vector[1] - first[1] * vector[0]
        if abs(cross) > 0.5 * np.linalg.norm(first) * np.linalg.norm(vector):
            return _reduce(first, vector)
    return None


def spectral_basis(patch: np.ndarray, weight: np.ndarray, min_period: float, max_period: float) -> np.ndarray | None:
    """The lattice of two sync gratings from a window's power spectrum: the strongest frequency in the
    allowed band and the strongest one at least 30 degrees from it are the dual basis F; the spatial
    basis is F^-T (pixels, columns), Gauss-reduced. A grating's spectral line grows with its amplitude
    times the window's size, where an autocorrelation peak grows with the amplitude squared."""
    from scipy import ndimage

    full = 2 * patch.shape[0]
    power = np.fft.fftshift(np.abs(np.fft.fft2(patch * weight, (full, full))) ** 2)
    frequency = np.stack(np.meshgrid(np.arange(full) - full // 2, np.arange(full) - full // 2, indexing="ij"), -1) / full
    radius = np.linalg.norm(frequency, axis=-1)
    allowed = (radius >= 1.0 / max_period) & (radius <= 1.0 / min_period)
    peaks = np.argwhere((power == ndimage.maximum_filter(power, size=3)) & allowed)
    order = np.argsort(power[peaks[:, 0], peaks[:, 1]])[::-1]
    chosen: list[np.ndarray] = []
    for index in order[:12]:
        y, x = peaks[index]
        vector = frequency[y, x] + np.array([
            _vertex(power[y - 1, x], power[y, x], power[y + 1, x]) if 0 < y < full - 1 else 0.0,
            _vertex(power[y, x - 1], power[y, x], power[y, x + 1]) if 0 < x < full - 1 else 0.0]) / full
        if not chosen:
            chosen.append(vector)
            continue
        cross = chosen[0][0] * vector[1] - chosen[0][1] * vector[0]
        if abs(cross) > 0.5 * np.linalg.norm(chosen[0]) * np.linalg.norm(vector):
            dual = np.stack([chosen[0], vector], axis=1)
            return _reduce(*np.linalg.inv(dual)) if abs(np.linalg.det(dual)) > 1e-9 else None
    return None


def _reduce(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Lagrange-Gauss reduction: the shortest basis of the lattice a, b span."""
    a, b = a.astype(float), b.astype(float)
    for _ in range(20):
        if a @ a > b @ b:
            a, b = b, a
        shift = round(float(a @ b) / float(a @ a))
        if shift == 0:
            break
        b = b - shift * a
    return np.stack([a, b], axis=1)


def fold(patch: np.ndarray, weight: np.ndarray, basis: np.ndarray, bins: int) -> np.ndarray:
    """Average the window's pixels into a bins x bins torus by their lattice coordinates."""
    size = patch.shape[0]
    grid = np.stack(np.meshgrid(np.arange(size), np.arange(size), indexing="ij"), -1).reshape(-1, 2) - size / 2
    coordinates = grid @ np.linalg.inv(basis).T
    index = np.floor((coordinates - np.floor(coordinates)) * bins).astype(int) % bins
    flat = index[:, 0] * bins + index[:, 1]
    w = weight.reshape(-1)
    sums = np.bincount(flat, weights=patch.reshape(-1) * w, minlength=bins * bins)
    counts = np.bincount(flat, weights=w, minlength=bins * bins)
    return (sums / np.maximum(counts, 1e-6)).reshape(bins, bins)


class LatticeDetector:
    """Picture -> soft bits for a `LatticeEncoder`'s mark, with nothing but the picture."""

    def __init__(self, encoder: LatticeEncoder, window: int = 96, stride: int = 48, oversample: int = 2,
                 min_period: float = 6.0, max_period: float = 45.0, basis_limit: int = 1, sync: str = "autocorrelation"):
        self.encoder, self.sync = encoder, sync
        self.window, self.stride, self.oversample = window, stride, oversample
        self.min_period, self.max_period = min_period, max_period
        n = encoder.cells * oversample
        self.maps = []
        for matrix in _unimodular(basis_limit):
            grid = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2)
            self.maps.append((grid @ matrix.T) % n)
        pilot = encoder.pilot.numpy()
        self.pilot = np.kron(pilot, np.ones((oversample, oversample)))
        self.codes = encoder.codes.numpy()
        self.colour = encoder.colour.numpy()

    def windows(self, mask: np.ndarray) -> list[tuple[int, int]]:
        height, width = mask.shape
        size, stride = self.window, self.stride
        corners = []
        for y in range(0, max(height - size, 0) + 1, stride):
            for x in range(0, max(width - size, 0) + 1, stride):
                if mask[y:y + size, x:x + size].mean() > 0.3:
                    corners.append((y, x))
        return corners

    def align(self, folded: np.ndarray) -> tuple[np.ndarray, float]:
        """Best basis change and cyclic shift of a folded tile against the pilot: (chips (n, n) in the
        texture's frame, normalised pilot correlation)."""
        n = folded.shape[0]
        pilot_spectrum = np.conj(np.fft.fft2(self.pilot))
        best, best_score = None, -np.inf
        flat = folded.reshape(-1)
        for mapping in self.maps:
            remapped = flat[mapping[:, 0] * n + mapping[:, 1]].reshape(n, n)
            correlation = np.real(np.fft.ifft2(np.fft.fft2(remapped) * pilot_spectrum))
            shift = np.unravel_index(np.argmax(correlation), correlation.shape)
            if correlation[shift] > best_score:
                best_score, best = correlation[shift], np.roll(remapped, (-shift[0], -shift[1]), axis=(0, 1))
        o = self.oversample
        chips = best.reshape(n // o, o, n // o, o).mean(axis=(1, 3))
        norm = np.linalg.norm(best) * np.linalg.norm(self.pilot) + 1e-12
        return chips, float(best_score / norm)

    def read(self, image: np.ndarray, mask: np.ndarray) -> dict:
        """image (H, W, 3) in [0, 1], mask (H, W) the object -> soft bits and what synchronisation saw."""
        signal = whiten(image, mask, self.colour)
        # the gratings sit at the period's fundamental, which the fine whitening would mostly remove
        sync_signal = signal if self.sync == "autocorrelation" else whiten(image, mask, self.colour, sigma=8.0)
        taper = np.outer(np.hanning(self.window), np.hanning(self.window))
        total = np.zeros((self.encoder.cells, self.encoder.cells))
        scores, used = [], 0
        for y, x in self.windows(mask):
            patch = signal[y:y + self.window, x:x + self.window]
            weight = mask[y:y + self.window, x:x + self.window] * taper
            basis = lattice_basis(lattice_peaks(patch, weight, self.min_period, self.max_period)) \
                if self.sync == "autocorrelation" else \
                spectral_basis(sync_signal[y:y + self.window, x:x + self.window], weight, self.min_period, self.max_period)
            if basis is None:
                continue
            chips, score = self.align(fold(patch, weight, basis, self.encoder.cells * self.oversample))
            scores.append(score)
            total += chips * max(score, 0.0)
            used += 1
        soft = np.einsum("kij,ij->k", self.codes, total) / (np.linalg.norm(total) / self.encoder.cells + 1e-12)
        return {"soft": soft, "windows": used, "scores": scores}


def sphere_items(count: int):
    """A UV sphere (icosphere, spherical UVs) with a different seed-style noise texture each time: the
    shape spherical UVs suit best, to tell the code's limits from the mapping's."""
    import trimesh

    from meshseal.data.process import noise_texture

    sphere = trimesh.creation.icosphere(5)
    positions = torch.tensor(sphere.vertices, dtype=torch.float32)
    for index in range(count):
        texture = torch.tensor(noise_texture(np.random.default_rng(index), 128)).permute(2, 0, 1).float() / 255
        yield {"id": f"sphere-{index}", "positions": positions, "uvs": spherical_uv(positions), "texture": texture,
               "normals": torch.tensor(sphere.vertex_normals, dtype=torch.float32), "faces": torch.tensor(sphere.faces)}


def seed_protocol_items(data: Path, count: int, seed: int, stride: int = 1):
    """Test meshes re-mapped with spherical UVs and a fresh noise or real texture (the seed's ModelNet)."""
    dataset = MeshDataset(data, "test", retexture=1.0, seed=seed)
    for index in range(0, min(count * stride, len(dataset)), stride):
        item = dataset[index]
        n_verts = int(item["n_verts"])
        item["uvs"][:n_verts] = spherical_uv(item["positions"][:n_verts])
        yield item


def render_pair(item: dict, texture: torch.Tensor, marked: torch.Tensor, generator: torch.Generator,
                height: int, width: int):
    """The original and the marked `item` rendered from one seed-range camera and light drawn from
    `generator`, as 8-bit pictures (H, W, 3), and the mark's visibility over the object's pixels."""
    cameras, lights = sample_seed_cameras(1, generator), sample_seed_lights(1, generator)
    renderer, pictures = MeshRenderer(), []
    for tex in (texture, marked):
        batch = MeshBatch.from_tensors(item["positions"][None], item["normals"][None], item["uvs"][None],
                                       item["faces"], tex)
        with torch.no_grad():
            pictures.append(renderer(batch, cameras, lights, height, width).rgba[0])
    original, picture = (torch.round(p[..., :3].clamp(0, 1) * 255) / 255 for p in pictures)
    coverage = pictures[0][..., 3] > 0.5
    return original, picture, visibility(original.permute(2, 0, 1)[None], picture.permute(2, 0, 1)[None],
                                          coverage[None])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data"))
    parser.add_argument("--meshes", type=int, default=20)
    parser.add_argument("--bits", type=int, default=8)
    parser.add_argument("--psnr", type=float, default=40.0, help="texture PSNR of the mark")
    parser.add_argument("--period", type=int, default=8)
    parser.add_argument("--cells", type=int, default=8)
    parser.add_argument("--pilot", type=float, default=0.5)
    parser.add_argument("--floor", type=float, default=0.3, help="activity mask floor (higher: flatter mark)")
    parser.add_argument("--grating", type=float, default=0.0, help="share of the mark's power in two sync gratings")
    parser.add_argument("--sync", choices=("autocorrelation", "spectrum"), default="autocorrelation")
    parser.add_argument("--sphere", action="store_true", help="a UV sphere with noise textures instead of the test meshes")
    parser.add_argument("--window", type=int, default=96)
    parser.add_argument("--width", type=int, default=600)
    parser.add_argument("--height", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--stride", type=int, default=1, help="every stride-th test mesh")
    parser.add_argument("--save", type=Path, default=None, help="folder for original | marked | whitened pictures")
    parser.add_argument("--jsonl", type=Path, default=None)
    args = parser.parse_args()

    encoder = LatticeEncoder(args.bits, period=args.period, cells=args.cells, pilot_share=args.pilot, floor=args.floor, grating=args.grating,
                             texture_psnr=args.psnr)
    detector = LatticeDetector(encoder, window=args.window, stride=args.window // 2, sync=args.sync)
    generator = torch.Generator().manual_seed(args.seed)
    accuracies, rows = [], []
    items = sphere_items(args.meshes) if args.sphere else seed_protocol_items(args.data, args.meshes, args.seed, args.stride)
    for item in items:
        message = torch.randint(0, 2, (1, args.bits), generator=generator).float()
        texture = item["texture"][None]
        marked = encoder(texture, message)
        original, picture, seen = render_pair(item, texture, marked, generator, args.height, args.width)
        started = time.perf_counter()
        image = picture.numpy().astype(np.float64)
        mask, _ = object_mask(image)
        reading = detector.read(image, mask)
        clean = detector.read(original.numpy().astype(np.float64), mask)
        seconds = time.perf_counter() - started
        accuracy = float(((reading["soft"] > 0) == message[0].bool().numpy()).mean())
        accuracies.append(accuracy)
        row = {"mesh": item["id"], "bit_acc": accuracy, "windows": reading["windows"],
               "score": float(np.median(reading["scores"])) if reading["scores"] else None,
               "clean_score": float(np.median(clean["scores"])) if clean["scores"] else None,
               "texture_psnr": float(-10 * torch.log10((marked - texture).pow(2).mean())),
               "seconds": seconds, **seen}
        rows.append(row)
        print(f"{item['id'][:36]:36s} bits {accuracy:.3f} windows {row['windows']:2d} score {row['score']} "
              f"(clean {row['clean_score']}) object PSNR {seen['psnr_object']:.2f} FLIP {seen['flip_object']:.4f} "
              f"{seconds:.1f} s", flush=True)
    if args.jsonl:
        args.jsonl.write_text("".join(json.dumps(r) + "\n" for r in rows))
    mean = lambda key: float(np.mean([r[key] for r in rows]))  # noqa: E731
    print(json.dumps({"bits": args.bits, "bit_acc": float(np.mean(accuracies)), "psnr_object": mean("psnr_object"),
                      "flip_object": mean("flip_object"), "texture_psnr": mean("texture_psnr"),
                      "seconds": mean("seconds")}))


if __name__ == "__main__":
    main()
