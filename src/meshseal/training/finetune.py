"""Fine-tuning a learned decoder on another engine's pictures (the paper's section 4.8, Table 9e).

1. Cache: training meshes are watermarked with the model's own encoder (a random message each) and
   rendered by the engine from K views of the seed's camera and light ranges; each picture is kept with
   its camera and message in OUT/cache/ENGINE/, one .npz per mesh (resumable: done meshes are skipped).
2. Fine-tune: the decoder (only) learns to read the cached pictures, un-rendered with their known
   camera as detection does (`reading.relight.uv_maps` for informed models; the framed picture for blind ones),
   by Adam on the bit cross-entropy. Checkpoints every `save_every` steps (resumable).
3. Keep or not: bit accuracy of the original and the fine-tuned decoder on held-out test meshes rendered
   by every engine in `engines`; the fine-tuned one is written to OUT/model.safetensors only if it does
   not lose more than `tolerance` on any engine, and OUT/finetune.json records all figures either way.

A model whose decoder has no learned parameters (the spread-spectrum default: a matched filter) has
nothing to fine-tune; `finetune` says so rather than pretend.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from ..errors import MeshsealError
from ..mesh import Material, Mesh
from ..methods import method_for
from ..models import WatermarkModel
from ..models.io import save_model, save_tensors
from ..reading.framing import frame
from ..reading.relight import uv_maps
from ..render import Cameras, MeshBatch, make_renderer
from ..render.views import sample_views

BACKGROUND = (0.0, 0.0, 0.0)  # as training renders


@dataclass
class FinetuneConfig:
    engine: str = "eevee"
    meshes: int = 200
    views: int = 2
    size: int = 128
    steps: int = 500
    batch: int = 8
    lr: float = 1e-4
    seed: int = 0
    val_meshes: int = 30
    engines: list[str] = field(default_factory=lambda: ["ours", "gl", "cycles", "eevee", "workbench"])
    tolerance: float = 0.005
    save_every: int = 100


def mesh_from_item(item: dict, texture: torch.Tensor | None = None) -> Mesh:
    """A dataset item (padded tensors, canonical frame) as a one-material Mesh; `texture` (3, H, W)
    replaces the item's."""
    n_verts, n_faces = int(item["n_verts"]), int(item["n_faces"])
    image = (item["texture"] if texture is None else texture).permute(1, 2, 0).contiguous()
    return Mesh(item["positions"][:n_verts], item["normals"][:n_verts], item["faces"][:n_faces],
                item["uvs"][:n_verts], torch.zeros(n_faces, dtype=torch.long), [Material(texture=image)], up_axis="z")


def _cameras_to_array(cameras: Cameras) -> np.ndarray:
    return torch.cat([cameras.eye, cameras.at, cameras.up], dim=1).numpy()


def _cameras_from_array(values: np.ndarray) -> Cameras:
    tensor = torch.from_numpy(values).float()
    return Cameras(tensor[:, 0:3], tensor[:, 3:6], tensor[:, 6:9])


def render_marked(model: WatermarkModel, item: dict, engine_renderer, views: int, size: int,
                  generator: torch.Generator) -> dict:
    """Watermark one dataset item with a random message and render it: {'pictures' (K, H, W, 3)
    uint8, 'cameras' (K, 9), 'message' (N,)}."""
    message = torch.randint(0, 2, (1, model.n_bits), generator=generator).float()
    with torch.no_grad():
        _, _, marked_texture = model.embed(item["positions"][None], item["normals"][None], item["uvs"][None],
                                           item["texture"][None], message)
    cameras, lights = sample_views(views, "seed", generator)
    rgba = engine_renderer.render(mesh_from_item(item, marked_texture[0]), cameras, lights, size, size,
                                  background=BACKGROUND)
    pixels = (rgba[..., :3].clamp(0, 1).numpy() * 255 + 0.5).astype(np.uint8)
    return {"pictures": pixels, "cameras": _cameras_to_array(cameras), "message": message[0].numpy()}


def build_cache(model: WatermarkModel, dataset, cfg: FinetuneConfig, folder: Path, log=print) -> list[Path]:
    """Render (or find already rendered) the first `cfg.meshes` items of `dataset` with the engine."""
    folder.mkdir(parents=True, exist_ok=True)
    renderer = None
    paths = []
    for index in range(min(cfg.meshes, len(dataset))):
        path = folder / f"{index:05d}.npz"
        paths.append(path)
        if path.is_file():
            continue
        renderer = renderer or make_renderer(cfg.engine)
        generator = torch.Generator().manual_seed(cfg.seed * 1_000_003 + index)
        started = time.perf_counter()
        record = render_marked(model, dataset[index], renderer, cfg.views, cfg.size, generator)
        tmp = path.with_suffix(".tmp.npz")
        np.savez(tmp, index=index, **record)
        tmp.replace(path)
        log(f"cache {index + 1}/{cfg.meshes}: {time.perf_counter() - started:.1f} s")
    return paths


def decoder_input(model: WatermarkModel, item: dict, pictures: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """What the decoder reads from pictures (K, 3, H, W) of an item taken with `cameras`."""
    if method_for(model).informed:
        original = MeshBatch.from_tensors(item["positions"][None], item["normals"][None], item["uvs"][None],
                                          item["faces"][None], item["texture"][None])
        with torch.no_grad():
            return uv_maps(original, pictures, cameras, model.config.uv_grid)
    alpha = (pictures.amax(dim=1) > 1.0 / 255).float()
    return frame(pictures, alpha, model.config.frame_size, torch.tensor(BACKGROUND).expand(len(pictures), 3))


def _examples(model: WatermarkModel, dataset, paths: list[Path]) -> tuple[torch.Tensor, torch.Tensor]:
    """Every cached picture as decoder input, with its message: (P, C, G, G), (P, N)."""
    inputs, messages = [], []
    for path in paths:
        with np.load(path) as record:
            item = dataset[int(record["index"])]
            pictures = torch.from_numpy(record["pictures"]).permute(0, 3, 1, 2).float() / 255
            cameras = _cameras_from_array(record["cameras"])
            inputs.append(decoder_input(model, item, pictures, cameras))
            messages.append(torch.from_numpy(record["message"]).float().expand(len(pictures), -1))
    return torch.cat(inputs), torch.cat(messages)


def accuracy(model: WatermarkModel, inputs: torch.Tensor, messages: torch.Tensor) -> float:
    with torch.no_grad():
        logits = torch.cat([model.decode(inputs[i:i + 32]) for i in range(0, len(inputs), 32)])
    return float(((logits > 0).float() == messages).float().mean())


def finetune(model: WatermarkModel, train_set, test_set, cfg: FinetuneConfig, out: Path, log=print) -> dict:
    """Steps 1-3 of the module docstring; returns the figures written to OUT/finetune.json."""
    if model.decoder is None or not any(p.requires_grad for p in model.decoder.parameters()):
        reader = f"the {method_for(model).name} method's reader"
        raise MeshsealError(f"this model's decoder has no learned parameters ({reader}): there is nothing "
                            "to fine-tune; it reads every engine as it is (docs/renderers.md)")
    out.mkdir(parents=True, exist_ok=True)
    torch.manual_seed(cfg.seed)
    train_paths = build_cache(model, train_set, cfg, out / "cache" / cfg.engine, log)
    inputs, messages = _examples(model, train_set, train_paths)
    before = {engine: _engine_accuracy(model, test_set, cfg, engine, out, log) for engine in cfg.engines}

    tuned = WatermarkModel(model.config)
    tuned.load_state_dict(model.state_dict())
    optimizer = torch.optim.Adam(tuned.decoder.parameters(), lr=cfg.lr)
    checkpoint = out / "finetune_state.safetensors"
    step = 0
    if checkpoint.is_file():
        from safetensors.torch import load_file

        state = load_file(str(checkpoint))
        step = int(state.pop("__step__"))
        tuned.decoder.load_state_dict(state)
        log(f"resuming at step {step}")
    generator = torch.Generator().manual_seed(cfg.seed + 17)
    tuned.train()
    while step < cfg.steps:
        pick = torch.randint(0, len(inputs), (cfg.batch,), generator=generator)
        loss = F.binary_cross_entropy_with_logits(tuned.decode(inputs[pick]), messages[pick])
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        step += 1
        if step % cfg.save_every == 0 or step == cfg.steps:
            state = {k: v.detach().clone() for k, v in tuned.decoder.state_dict().items()}
            save_tensors(state | {"__step__": torch.tensor(step)}, checkpoint, {"format": "meshseal-finetune-state"})
            log(f"step {step}/{cfg.steps}: loss {loss.item():.4f}, train bit acc {accuracy(tuned, inputs, messages):.4f}")
    tuned.eval()
    after = {engine: _engine_accuracy(tuned, test_set, cfg, engine, out, log) for engine in cfg.engines}
    keep = all(after[e] >= before[e] - cfg.tolerance for e in cfg.engines)
    if keep:
        save_model(tuned, out / "model.safetensors", {"finetuned_on": cfg.engine})
    report = {"engine": cfg.engine, "kept": keep, "before": before, "after": after,
              "train_pictures": len(inputs), "config": cfg.__dict__}
    (out / "finetune.json").write_text(json.dumps(report, indent=2))
    return report


def _engine_accuracy(model: WatermarkModel, test_set, cfg: FinetuneConfig, engine: str, out: Path, log) -> float:
    """Bit accuracy on `cfg.val_meshes` test meshes rendered by `engine` (cached like the training set)."""
    held_out = FinetuneConfig(**{**cfg.__dict__, "engine": engine, "meshes": cfg.val_meshes, "seed": cfg.seed + 1})
    paths = build_cache(model, test_set, held_out, out / "cache" / f"test_{engine}", log)
    return accuracy(model, *_examples(model, test_set, paths))
