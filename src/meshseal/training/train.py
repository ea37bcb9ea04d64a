"""Training: `meshseal train --config configs/NAME.yaml [--out DIR] [--resume]`.

Curriculum (each stage is a config knob; see docs/training.md):
1. texture-space pretraining: the texture encoder and the decoder learn on random perspective views of
   the watermarked texture itself (no renderer: fast), so the decoder starts from a working code;
2. end to end through the differentiable renderer with random cameras, lights and backgrounds, the
   3D and 2D distortions switched on after `distortion_start` steps;
the texture- and rendered-image loss weights are adapted by dual ascent to hold the texture PSNR at
`target_psnr_texture` and the rendered PSNR at `target_psnr` (fixed weights, as in the seed, when the
targets are null), so the mark is always as strong as the invisibility budget allows; the vertex loss
ramps up over `warmup_steps`.
"""

from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import torch
import torch.nn.functional as F
import yaml

from ..data.dataset import collate
from ..errors import MeshsealError
from ..models import ModelConfig, WatermarkModel
from ..models.io import save_model, save_tensors
from ..render import MeshRenderer
from .distortions import Distortions2D, Distortions3D
from .distributed import average, average_gradients
from .losses import bit_accuracy, masked_l1, message_loss, psnr, ssim
from .step import run_pass
from .views import random_backgrounds

FREEZABLE = ("texture_encoder", "vertex_encoder", "decoder")


@dataclass
class LossWeights:
    """The seed's lambda, gamma, delta, theta, eta (Eq. 6) and per-component vertex weights w^i."""

    vertex: float = 2.0
    normal_weight: float = 1.0
    uv_weight: float = 1.0
    texture: float = 1.0
    image: float = 1.0
    message: float = 1.0
    reg: float = 0.01


@dataclass
class TrainSettings:
    steps: int = 3000
    pretrain_steps: int = 0
    batch_size: int = 8
    lr: float = 1e-4
    render_size: int = 128
    sampler: str = "seed"
    background: str = "black"  # black | random
    warmup_steps: int = 0
    distortion_start: int = 0
    distortion_3d: float = 1.0
    distortion_2d: float = 0.0
    target_psnr: float | None = None  # rendered PSNR to hold (dual ascent on the image-loss weight)
    target_psnr_texture: float | None = None  # texture PSNR to hold (dual ascent on the texture-loss weight)
    dual_rate: float = 0.05  # weight *= exp(rate * (target - measured)) each step
    target_slack: float = 0.0  # PSNR targets start this many dB lower and reach theirs after warmup_steps
    val_every: int = 250
    val_meshes: int = 32
    checkpoint_every: int = 250
    checkpoint_minutes: float | None = None  # also checkpoint this often (runs on short device leases)
    time_limit_minutes: float | None = None
    stop_at: int | None = None  # stop after this step, the schedules still running to `steps` (a run made in parts)
    retexture: float = 0.0
    texture_kinds: list | None = None  # only items whose texture is of these kinds (own | real | noise)
    unrender_jitter: float = 0.0  # informed models: pose error (pixels) of the un-rendering camera (ramps up over warmup_steps)
    reference_steps: int = 0  # informed models: subtract the exact original render at first, fading out by this step
    texture_rms_start: float | None = None  # fixed-power marks: start this loud, reach texture_rms after warmup_steps
    lr_decay_from: int | None = None  # cosine decay of the learning rate to 5 % from this step to the last
    init_from: str | None = None  # start from these weights (a model.safetensors of the same architecture)
    frozen: list | None = None  # parts kept as they start: texture_encoder | vertex_encoder | decoder
    gbuffer: str = "auto"  # auto: texture-only blind models train on cached G-buffers (training.gbuffer); off
    gbuffer_views: int = 8  # baked views per training mesh (each its own camera, light and 3D distortion)
    gbuffer_supersample: int = 1  # views baked at this many times the frame size, each picture box-filtered down to it
    log_every: int = 0  # steps between log rows (one host round trip each); 0: 1 on the CPU, 50 on a GPU
    amp: bool = True  # bfloat16 autocast on CUDA
    channels_last: bool = False  # the networks' weights (and so their activations) in NHWC memory order
    bn_renders: int = 0  # G-buffer runs: at the end, the decoder's batch-norm statistics from this many rendered pictures


# Banks of at least this many views are baked by a pool of processes (one per free core): a spawned
# worker's start-up (it imports torch, seconds) costs more than a small bank takes in this process.
BAKE_IN_PROCESSES_FROM = 2048


@dataclass
class TrainConfig:
    name: str = "default"
    seed: int = 0
    data: str = "data"
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossWeights = field(default_factory=LossWeights)
    train: TrainSettings = field(default_factory=TrainSettings)

    @classmethod
    def load(cls, path) -> "TrainConfig":
        path = Path(path)
        if not path.is_file():
            raise MeshsealError(f"{path}: no such config file")
        try:
            values = yaml.safe_load(path.read_text()) or {}
        except yaml.YAMLError as error:
            raise MeshsealError(f"{path}: invalid YAML: {str(error).splitlines()[0]}") from None
        return cls.from_dict(values, str(path))

    @classmethod
    def from_dict(cls, values: dict, origin: str = "config") -> "TrainConfig":
        def build(kind, part):
            known = {f.name for f in fields(kind)}
            unknown = set(part or {}) - known
            if unknown:
                raise MeshsealError(f"{origin}: unknown setting(s) {', '.join(sorted(unknown))}")
            return kind(**(part or {}))

        top = dict(values)
        try:
            model = ModelConfig.from_dict(top.pop("model", {}) or {})
        except (TypeError, ValueError) as error:
            raise MeshsealError(f"{origin}: model: {error}") from None
        loss = build(LossWeights, top.pop("loss", None))
        train = build(TrainSettings, top.pop("train", None))
        config = build(cls, top)
        config.model, config.loss, config.train = model, loss, train
        return config

    def to_dict(self) -> dict:
        return {"name": self.name, "seed": self.seed, "data": self.data, "model": self.model.to_dict(),
                "loss": asdict(self.loss), "train": asdict(self.train)}


# ---------------------------------------------------------------- texture-space views (stage 1)


def texture_views(texture: torch.Tensor, size: int, generator: torch.Generator) -> torch.Tensor:
    """Random perspective-like views of a (repeating) texture, shaded and on a plain background:
    what a render of a textured surface looks like, without rendering."""
    n = texture.shape[0]
    rand = lambda *shape: torch.rand(*shape, generator=generator)  # noqa: E731
    zoom = 0.4 + 1.1 * rand(n)  # fraction of the texture across the view (renders show 0.5-1.5)
    angle = 2 * math.pi * rand(n)
    squash = 0.45 + 0.55 * rand(n)  # foreshortening
    c, s = torch.cos(angle), torch.sin(angle)
    matrix = torch.stack([torch.stack([c * zoom, -s * zoom * squash], -1),
                          torch.stack([s * zoom, c * zoom * squash], -1)], 1)  # (n, 2, 2)
    axis = torch.linspace(-1, 1, size)
    ys, xs = torch.meshgrid(axis, axis, indexing="ij")
    points = torch.stack([xs, ys], -1).reshape(1, -1, 2)
    bend = 0.15 * (rand(n, 1, 2) - 0.5) * (points ** 2).sum(-1, keepdim=True)  # mild curvature
    grid = points @ matrix.transpose(1, 2) + (2 * rand(n, 1, 2) - 1) + bend
    grid = torch.remainder(grid + 1, 2) - 1  # REPEAT wrap
    view = F.grid_sample(texture, grid.reshape(n, size, size, 2).to(texture), mode="bilinear",
                         padding_mode="border", align_corners=False)
    gradient = (rand(n, 2) - 0.5).to(texture)
    shading = 0.35 + 0.8 * rand(n, 1, 1).to(texture) + (gradient[:, :1, None] * xs + gradient[:, 1:, None] * ys).to(texture)
    view = (view * shading.unsqueeze(1).clamp(0.1, 1.6)).clamp(0, 1)
    # A silhouette: an ellipse of random size and place, plain background outside.
    centre = 0.4 * (rand(n, 2) - 0.5)
    radii = 0.55 + 0.45 * rand(n, 2)
    inside = (((xs - centre[:, :1, None]) / radii[:, :1, None]) ** 2 +
              ((ys - centre[:, 1:, None]) / radii[:, 1:, None]) ** 2) <= 1
    background = random_backgrounds(n, generator).to(texture)[:, :, None, None]
    return torch.where(inside.unsqueeze(1).to(texture.device), view, background)


# ---------------------------------------------------------------- the loop


def _optimizer_tensors(optimizer: torch.optim.Optimizer, parameters: list) -> dict[str, torch.Tensor]:
    tensors = {}
    for index, parameter in enumerate(parameters):
        for key, value in optimizer.state.get(parameter, {}).items():
            tensors[f"{index}.{key}"] = value if torch.is_tensor(value) else torch.tensor(value)
    return tensors


def _load_optimizer_tensors(optimizer, parameters, tensors) -> None:
    for name, value in tensors.items():
        index, key = name.split(".", 1)
        parameter = parameters[int(index)]
        fused = any(group.get("fused") for group in optimizer.param_groups)  # fused Adam keeps its step beside the weights
        optimizer.state[parameter][key] = value if key == "step" and not fused else value.to(parameter.device)


class CachedItems:
    """Keeps each item's geometry in memory after the first read (the textures may change per epoch)."""

    def __init__(self, dataset):
        self.dataset = dataset
        self.geometry: dict[int, dict] = {}

    def __len__(self) -> int:
        return len(self.dataset)

    def set_epoch(self, epoch: int) -> None:
        self.dataset.set_epoch(epoch)

    def __getitem__(self, index: int) -> dict:
        if index not in self.geometry:
            item = self.dataset[index]
            self.geometry[index] = {k: v for k, v in item.items() if k != "texture"}
            return item
        texture = torch.from_numpy(self.dataset.texture_for(index).copy()).permute(2, 0, 1).float() / 255.0
        return self.geometry[index] | {"texture": texture}


class Trainer:
    def __init__(self, config: TrainConfig, out_dir, resume: bool = False, device: str = "cpu", log=print):
        from ..data.dataset import MeshDataset
        from .distributed import join

        self.world, device = join(device)
        self.config, self.out, self.device = config, Path(out_dir), torch.device(device)
        self.log = log if self.world.main else (lambda *_: None)
        self.out.mkdir(parents=True, exist_ok=True)
        torch.manual_seed(config.seed)
        self.generator = torch.Generator().manual_seed(config.seed)
        # Draws for the G-buffer step on a GPU come from the GPU's own generator: a copy from host memory
        # would wait for the queued work every step. On the CPU it is the one generator.
        self.device_generator = (torch.Generator(device=self.device).manual_seed(config.seed)
                                 if self.device.type == "cuda" else self.generator)
        kinds = config.train.texture_kinds
        self.train_set = CachedItems(MeshDataset(config.data, "train", retexture=config.train.retexture,
                                                 seed=config.seed, texture_kinds=kinds))
        self.val_set = MeshDataset(config.data, "test", seed=config.seed, texture_kinds=kinds)
        if len(self.train_set) == 0:
            raise MeshsealError(f"{config.data}: the train split is empty")
        self.model = WatermarkModel(config.model).to(self.device)
        if config.train.channels_last:  # cuDNN's tensor-core convolutions work in NHWC: no transpose around each
            self.model.to(memory_format=torch.channels_last)
        if self.device.type == "cuda":
            torch.backends.cudnn.benchmark = True  # fixed picture sizes: cuDNN may time its convolution algorithms once
        from ..methods import method_for

        self.method = method_for(self.model)
        if self.method.informed and config.train.pretrain_steps > 0:
            raise MeshsealError("pretrain_steps must be 0 for an informed (uv) decoder: its input is a UV map, "
                                "not a picture")
        if config.train.init_from:
            self._start_from(Path(config.train.init_from))
        for name in config.train.frozen or []:
            part = getattr(self.model, name, None)
            if name not in FREEZABLE or part is None:
                raise MeshsealError(f"frozen: this model has no {name} ({' | '.join(FREEZABLE)})")
            part.requires_grad_(False)
        self.parameters = [p for p in self.model.parameters() if p.requires_grad]
        # eta * sum(w^2) in the loss is exactly Adam's coupled weight decay 2 * eta.
        self.optimizer = torch.optim.Adam(self.parameters, lr=config.train.lr, weight_decay=2 * config.loss.reg,
                                          fused=self.device.type == "cuda") \
            if self.parameters else None  # a spread-spectrum model has nothing to learn
        self.renderer = MeshRenderer()
        self.step = 0
        self.image_weight = config.loss.image
        self.texture_weight = config.loss.texture
        self.position = (0, 0)  # (epoch, offset) of the next batch
        self.elapsed = 0.0
        self.views = self._view_banks() if self._uses_gbuffers() else None
        if self.world.distributed:
            self._check_distributed()
        self._pending_psnr, self._pending_count = None, 0  # G-buffer steps' PSNRs since the last dual update
        if resume and (self.out / "checkpoint.safetensors").is_file():
            self._restore()

    # -------------------------------------------------------- cached G-buffers
    def _uses_gbuffers(self) -> bool:
        """Blind models with learned encoders (texture, vertex or both: positions never move) train on
        cached G-buffers unless told not to."""
        mode, model = self.config.train.gbuffer, self.model
        if mode not in ("auto", "on", "off"):
            raise MeshsealError(f"gbuffer: '{mode}' is not one of auto | on | off")
        applies = (model.texture_encoder is not None or model.vertex_encoder is not None) and not self.method.informed \
            and model.decoder is not None
        if mode == "on" and not applies:
            raise MeshsealError("gbuffer: on needs learned encoders and a blind decoder")
        if self.config.train.gbuffer_supersample < 1:
            raise MeshsealError(f"gbuffer_supersample: {self.config.train.gbuffer_supersample} (1 or more: views baked at "
                                "that many times the frame size)")
        return mode != "off" and applies

    def _check_distributed(self) -> None:
        """Several processes: the G-buffer path (every process draws the same numbers for the whole
        batch), an even split of the batch, batch normalisation over the global batch."""
        from .distributed import global_batch_norm

        cfg, world = self.config.train, self.world
        if self.views is None or cfg.pretrain_steps > 0:
            raise MeshsealError("training in several processes needs the G-buffer path (learned encoders, a blind "
                                "decoder) and pretrain_steps 0")
        if cfg.batch_size % world.size:
            raise MeshsealError(f"batch_size {cfg.batch_size} does not split evenly over {world.size} processes")
        global_batch_norm(self.model)

    def _view_banks(self) -> dict:
        """The train and test views, baked once into `<data>/gbuffers/` and kept on the training device,
        with the items' textures (uint8) beside them and, for a vertex mark, their geometry. A vertex
        mark's views are baked without the 3D rotation (a rotation would turn the marked normals too)."""
        from .gbuffer import bake_key, cached_bake

        cfg = self.config.train
        folder = Path(self.config.data) / "gbuffers"
        size = self.model.config.frame_size * cfg.gbuffer_supersample
        surface = self.model.vertex_encoder is not None
        distort = Distortions3D(cfg.distortion_3d, p_rotation=0.0 if surface else 0.25) if cfg.distortion_3d > 0 else None
        if self.world.distributed and not self.world.main:
            torch.distributed.barrier()  # the main process bakes both banks; the others then read its files
        from ..threads import policy_threads

        cores = policy_threads()  # a large bank is baked by one-thread processes on the cores other jobs leave free
        workers = cores if cores > 1 and cfg.gbuffer_views * len(self.train_set) >= BAKE_IN_PROCESSES_FROM else 0
        train = cached_bake(self.train_set.dataset, folder / bake_key("train", cfg.texture_kinds, cfg.gbuffer_views, size,
                                                                     cfg.sampler, self.config.seed, cfg.distortion_3d,
                                                                     surface),
                            cfg.gbuffer_views, size, cfg.sampler, self.config.seed, distort, self.log, surface, workers)
        val_views = min(len(self.val_set), cfg.val_meshes)
        val_set = torch.utils.data.Subset(self.val_set, range(val_views))
        test = cached_bake(val_set, folder / bake_key("test", cfg.texture_kinds, 1, size, cfg.sampler,
                                                      self.config.seed + 1_000_003, 0.0, surface),
                           1, size, cfg.sampler, self.config.seed + 1_000_003, None, self.log, surface,
                           workers if val_views >= BAKE_IN_PROCESSES_FROM else 0)
        if self.world.distributed and self.world.main:
            torch.distributed.barrier()
        as_bytes = lambda dataset, count: torch.stack([self._texture_bytes(dataset, i) for i in range(count)])  # noqa: E731
        bank = {"train": train.to(self.device), "test": test.to(self.device),
                "train_textures": as_bytes(self.train_set, len(self.train_set)).to(self.device),
                "test_textures": as_bytes(self.val_set, val_views).to(self.device), "textures_epoch": 0}
        if surface:
            from .gbuffer import _geometry

            for split, dataset, count in (("train", self.train_set, len(self.train_set)), ("test", self.val_set, val_views)):
                bank[f"{split}_geometry"] = collate([_geometry(dataset, i) for i in range(count)], self.device)
        return bank

    @staticmethod
    def _texture_bytes(dataset, index: int) -> torch.Tensor:
        source = getattr(dataset, "dataset", dataset)
        return torch.from_numpy(source.texture_for(index).copy()).permute(2, 0, 1).contiguous()

    def _view_batches(self):
        """Batches of view indices (on the device) in an order drawn from (seed, epoch) alone, so a
        resumed run continues exactly; with `retexture` each epoch reads the items' textures afresh."""
        size, bank = self.config.train.batch_size, self.views
        while True:
            epoch, offset = self.position
            if self.config.train.retexture > 0 and bank["textures_epoch"] != epoch:
                self.train_set.set_epoch(epoch)
                bank["train_textures"] = torch.stack([self._texture_bytes(self.train_set, i)
                                                      for i in range(len(self.train_set))]).to(self.device)
                bank["textures_epoch"] = epoch
            order = torch.randperm(len(bank["train"]), generator=torch.Generator().manual_seed(
                self.config.seed * 100_003 + epoch)).to(self.device)
            for start in range(offset, len(order) - size + 1, size):
                self.position = (epoch, start + size)
                yield order[start:start + size]
            self.position = (epoch + 1, 0)

    def _autocast(self):
        enabled = self.config.train.amp and self.device.type == "cuda"
        return torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=enabled)

    def _gbuffer_pass(self, views, split: str, message, background, attack=None) -> dict:
        """Marked and original pictures of the baked `views` of `split`'s items, the decoder's logits,
        and what the encoders changed (texture; normals and uvs with the vertex mask, for a vertex mark)."""
        from ..data.dataset import vertex_mask
        from .gbuffer import composite, composite_surface

        bank = self.views
        texture = bank[f"{split}_textures"][views.item].float() / 255.0
        out = {"texture": texture}
        if views.surface is None:
            with self._autocast():
                out["marked"] = self.model.texture_encoder(texture, message).float()
            picture = self._down(composite(out["marked"], views, background))
        else:
            geometry = {key: value[views.item] for key, value in bank[f"{split}_geometry"].items()}
            mask = vertex_mask(geometry)
            with self._autocast():
                marked = self.model.embed(geometry["positions"], geometry["normals"], geometry["uvs"], texture, message,
                                          mask)
            normals, uvs, out["marked"] = (value.float() for value in marked)
            picture = self._down(composite_surface(out["marked"], normals, uvs, geometry["faces"], views, background))
            out |= {"normals": geometry["normals"], "normals_marked": normals, "uvs": geometry["uvs"],
                    "uvs_marked": uvs, "vertex_mask": mask}
        with torch.no_grad():
            out["original"] = self._down(composite(texture, views, background))
        seen = picture if attack is None else attack(picture, self.generator)
        with self._autocast():
            out["logits"] = self.model.decode(seen).float()
        out["picture"] = picture
        return out

    def _down(self, pictures: torch.Tensor) -> torch.Tensor:
        """Pictures composited from supersampled views, box-filtered to the frame size: the view as a
        picture rendered larger than the frame and shrunk with antialiasing (how `detect` frames a
        picture where the object spans more pixels than the frame)."""
        factor = self.config.train.gbuffer_supersample
        return pictures if factor == 1 else F.avg_pool2d(pictures, factor)

    def _gbuffer_step(self, index, message, distorting: bool):
        cfg, weights, bank = self.config.train, self.config.loss, self.views
        n = index.shape[0]
        background = (random_backgrounds(n, self.generator).to(self.device) if cfg.background == "random"
                      else torch.zeros(n, 3, device=self.device))
        attack = Distortions2D(cfg.distortion_2d) if distorting and cfg.distortion_2d > 0 else None
        share = self.world.share(n)  # this process's part of the global batch (all of it in one process)
        views, message, background = bank["train"][index[share]], message[share], background[share]
        out = self._gbuffer_pass(views, "train", message, background, attack)
        texture, marked, original, picture = out["texture"], out["marked"], out["original"], out["picture"]
        texture_term = (marked - texture).abs().mean()
        image_term = (picture - original).abs().mean()
        loss = (weights.message * message_loss(out["logits"], message) + self.texture_weight * texture_term
                + self.image_weight * image_term)
        if "vertex_mask" in out:  # the seed's per-component vertex loss, as the rendering pass adds it
            mask = out["vertex_mask"]
            loss = loss + self._ramp() * weights.vertex * (
                weights.normal_weight * masked_l1(out["normals_marked"], out["normals"], mask)
                + weights.uv_weight * masked_l1(out["uvs_marked"], out["uvs"], mask))
        stats = {"psnr_render": psnr(picture.detach(), original).mean(),
                 "psnr_texture": psnr(marked.detach(), texture).mean(), "stage": 2}
        return loss, out["logits"], stats, message

    @torch.no_grad()
    def recalibrate_batch_norm(self, batches: int = 16) -> None:
        """Batch-norm statistics measured afresh with the current weights over `batches` training
        batches (cumulative, not the running average of the weights' history): a decoder whose input
        changes as the mark is squeezed reads far better with them. Its own generator, so training's
        draws are untouched."""
        from .batch_norm import batch_norms, fresh_statistics

        norms = batch_norms(self.model)
        if not norms or self.views is None:
            return
        bank, was_training = self.views, self.model.training
        generator = torch.Generator().manual_seed(self.config.seed * 1_000_003 + self.step)
        self.model.train()
        size, share = self.config.train.batch_size, self.world.share(self.config.train.batch_size)
        with fresh_statistics(norms):
            for _ in range(batches):  # global batches, each process its share (batch norm sees the global batch)
                index = torch.randint(len(bank["train"]), (size,), generator=generator)[share].to(self.device)
                message = torch.randint(0, 2, (size, self.model.n_bits), generator=generator)[share].float().to(self.device)
                views = bank["train"][index]
                self._gbuffer_pass(views, "train", message, torch.zeros(len(index), 3, device=self.device))
        self.model.train(was_training)

    def statistics_from_renders(self) -> None:
        """The decoder's batch-norm statistics measured on `bn_renders` pictures the renderer makes of the
        training meshes, each framed by the object's box as the rendering pass frames it: what the model will
        read, where the baked views it trained on differ at the silhouette and in how the frame was
        filtered (`training.batch_norm`)."""
        from .batch_norm import decoder_statistics_from_renders

        cfg = self.config.train
        size = (400, 600) if self.method.paper_pictures else cfg.render_size
        started = time.time()
        decoder_statistics_from_renders(self.model, self.train_set.dataset, cfg.bn_renders, size, cfg.sampler,
                                        seed=self.config.seed * 1_000_003 + 7)
        self.log(f"decoder batch-norm statistics from {cfg.bn_renders} rendered pictures ({time.time() - started:.0f} s)")

    @torch.no_grad()
    def validate_gbuffers(self) -> dict:
        """Bit accuracy and visibility on the baked test views (the first `val_meshes` test meshes)."""
        bank, was_training = self.views, self.model.training
        self.model.eval()
        generator = torch.Generator().manual_seed(self.config.seed + 1_000_003)
        rows = {"bit_acc": [], "psnr_render": [], "ssim_render": [], "psnr_texture": []}
        for start in range(0, len(bank["test"]), self.config.train.batch_size):
            views = bank["test"][start:start + self.config.train.batch_size]
            n = len(views)
            message = torch.randint(0, 2, (n, self.model.n_bits), generator=generator).float().to(self.device)
            out = self._gbuffer_pass(views, "test", message, torch.zeros(n, 3, device=self.device))
            rows["bit_acc"].append(bit_accuracy(out["logits"], message))
            rows["psnr_render"].append(psnr(out["picture"], out["original"]))
            rows["ssim_render"].append(ssim(out["picture"], out["original"]))
            rows["psnr_texture"].append(psnr(out["marked"], out["texture"]))
        self.model.train(was_training)
        return {name: float(torch.cat(values).mean()) for name, values in rows.items()}

    def _start_from(self, path: Path) -> None:
        """Weights of another run of the same architecture (the paper's Table 8: a texture encoder trained
        on images alone; or a run continued under other settings, such as a quieter `texture_rms`): the
        weights' names and shapes must match, settings that hold no weights may differ."""
        from ..models.io import load_model

        weights = load_model(path).state_dict()
        own = self.model.state_dict()
        if {k: tuple(v.shape) for k, v in weights.items()} != {k: tuple(v.shape) for k, v in own.items()}:
            raise MeshsealError(f"{path}: its model differs from this config's (init_from needs the same architecture)")
        self.model.load_state_dict(weights)

    # -------------------------------------------------------- checkpoints
    def _checkpoint(self) -> None:
        if not self.world.main:
            return
        tensors = {f"model.{k}": v for k, v in self.model.state_dict().items()}
        tensors |= {f"optim.{k}": v for k, v in _optimizer_tensors(self.optimizer, self.parameters).items()}
        tensors["rng.generator"] = self.generator.get_state()
        tensors["rng.torch"] = torch.get_rng_state()
        if self.device_generator is not self.generator:
            tensors["rng.device"] = self.device_generator.get_state()
        state = {"step": self.step, "image_weight": self.image_weight, "texture_weight": self.texture_weight,
                 "elapsed": self.elapsed, "position": list(self.position)}
        save_tensors(tensors, self.out / "checkpoint.safetensors", {"state": json.dumps(state),
                                                                     "config": json.dumps(self.config.to_dict())})
        self._save_model()

    def _save_model(self) -> None:
        """The weights alone, usable by `meshseal eval/embed/detect --model` while training goes on."""
        if not self.world.main:
            return
        save_model(self.model, self.out / "model.safetensors",
                   {"name": self.config.name, "steps": self.step, "seed": self.config.seed,
                    "training_seconds": round(self.elapsed, 1), "train_config": self.config.to_dict(),
                    "device": torch.cuda.get_device_name(self.device) if self.device.type == "cuda" else "cpu"})

    def _restore(self) -> None:
        from safetensors import safe_open
        from safetensors.torch import load_file

        path = self.out / "checkpoint.safetensors"
        tensors = load_file(str(path))
        with safe_open(str(path), framework="pt") as handle:
            state = json.loads(handle.metadata()["state"])
        self.model.load_state_dict({k[6:]: v for k, v in tensors.items() if k.startswith("model.")})
        _load_optimizer_tensors(self.optimizer, self.parameters,
                                {k[6:]: v for k, v in tensors.items() if k.startswith("optim.")})
        self.generator.set_state(tensors["rng.generator"])
        torch.set_rng_state(tensors["rng.torch"])
        if self.device_generator is not self.generator and "rng.device" in tensors:
            self.device_generator.set_state(tensors["rng.device"])
        self.step, self.image_weight, self.elapsed = state["step"], state["image_weight"], state["elapsed"]
        self.texture_weight = state.get("texture_weight", self.texture_weight)
        self.position = tuple(state.get("position", (0, 0)))
        self.log(f"resumed from step {self.step}")

    # -------------------------------------------------------- data
    def _batches(self):
        """Batches in an order drawn from (seed, epoch) alone, so a resumed run continues exactly."""
        size = self.config.train.batch_size
        while True:
            epoch, offset = self.position
            self.train_set.set_epoch(epoch)
            order = torch.randperm(len(self.train_set),
                                   generator=torch.Generator().manual_seed(self.config.seed * 100_003 + epoch)).tolist()
            for start in range(offset, len(order) - size + 1, size):
                self.position = (epoch, start + size)
                items = [self.train_set[i] for i in order[start:start + size]]
                yield collate(items, self.device)
            self.position = (epoch + 1, 0)

    # -------------------------------------------------------- one step
    def _ramp(self) -> float:
        warmup = self.config.train.warmup_steps
        return 1.0 if warmup <= 0 else min(1.0, self.step / warmup)

    def _set_learning_rate(self) -> None:
        cfg = self.config.train
        if cfg.lr_decay_from is None or self.step < cfg.lr_decay_from:
            return
        progress = (self.step - cfg.lr_decay_from) / max(1, cfg.steps - cfg.lr_decay_from)
        for group in self.optimizer.param_groups:
            group["lr"] = cfg.lr * (0.05 + 0.95 * 0.5 * (1 + math.cos(math.pi * min(1.0, progress))))

    def _set_mark_power(self, ramp: float) -> None:
        """A loud mark while the decoder finds it, squeezed to the model's own RMS by the warmup's end."""
        start, encoder = self.config.train.texture_rms_start, self.model.texture_encoder
        if start is not None and encoder is not None and self.config.model.texture_rms > 0:
            encoder.rms = start + (self.config.model.texture_rms - start) * ramp

    def _reference_mix(self) -> float:
        """1 for the first half of `reference_steps`, then linearly down to 0 at `reference_steps`."""
        total = self.config.train.reference_steps
        if total <= 0:
            return 0.0
        return float(min(1.0, max(0.0, 2.0 * (1.0 - self.step / total))))

    def _dual(self, weight: float, target: float | None, measured: float) -> float:
        """Dual ascent on a PSNR constraint: raise the loss weight while below target, lower it above.

        The target itself ramps up from `target - target_slack` over `warmup_steps`: the mark may be
        strong while the decoder finds it, then is squeezed to the invisibility budget.
        """
        if target is None or not math.isfinite(measured):
            return weight
        target = target - self.config.train.target_slack * (1.0 - self._ramp())
        return float(min(max(weight * math.exp(self.config.train.dual_rate * (target - measured)), 1e-3), 1e4))

    def train_step(self, batch) -> dict[str, float]:
        cfg, weights = self.config.train, self.config.loss
        self.model.train()
        n = batch.shape[0] if torch.is_tensor(batch) else batch["positions"].shape[0]
        if self.views is not None and self.step >= cfg.pretrain_steps:
            message = torch.randint(0, 2, (n, self.model.n_bits), generator=self.device_generator,
                                    device=self.device).float()
        else:
            message = torch.randint(0, 2, (n, self.model.n_bits), generator=self.generator).float().to(self.device)
        distorting = self.step >= cfg.distortion_start
        ramp = self._ramp()
        self._set_mark_power(ramp)
        self._set_learning_rate()
        stats: dict[str, float] = {}
        if self.step < cfg.pretrain_steps and self.model.texture_encoder is not None:
            if self.views is not None:  # stage 1 reads the items' own textures
                batch = {"texture": self.views["train_textures"][self.views["train"].item[batch]].float() / 255.0}
            marked = self.model.texture_encoder(batch["texture"], message)
            views = texture_views(marked, self.model.config.frame_size, self.generator)
            if distorting and cfg.distortion_2d > 0:
                views = Distortions2D(cfg.distortion_2d)(views, self.generator)
            logits = self.model.decode(views)
            texture_term = (marked - batch["texture"]).abs().mean()
            loss = weights.message * message_loss(logits, message) + self.texture_weight * texture_term
            stats["psnr_texture"] = float(psnr(marked.detach(), batch["texture"]).mean())
            self.texture_weight = self._dual(self.texture_weight, cfg.target_psnr_texture, stats["psnr_texture"])
            stats["stage"] = 1
        elif self.views is not None:
            loss, logits, more, message = self._gbuffer_step(batch, message, distorting)
            stats.update(more)
            measured = torch.stack([more["psnr_render"], more["psnr_texture"]]).detach()
            self._pending_psnr = measured if self._pending_psnr is None else self._pending_psnr + measured
            self._pending_count += 1
            if self._pending_count >= self._log_every():  # dual ascent on the window's mean: one round trip
                mean_render, mean_texture = average(self._pending_psnr / self._pending_count, self.world).tolist()
                for _ in range(self._pending_count):
                    self.image_weight = self._dual(self.image_weight, cfg.target_psnr, mean_render)
                    self.texture_weight = self._dual(self.texture_weight, cfg.target_psnr_texture, mean_texture)
                self._pending_psnr, self._pending_count = None, 0
            stats["image_weight"] = self.image_weight
        else:
            background = (random_backgrounds(n, self.generator) if cfg.background == "random" else torch.zeros(n, 3))
            out = run_pass(self.model, batch, message, self.renderer, self.generator, cfg.render_size, cfg.sampler,
                           Distortions3D(cfg.distortion_3d) if distorting and cfg.distortion_3d > 0 else None,
                           Distortions2D(cfg.distortion_2d) if distorting and cfg.distortion_2d > 0 else None,
                           background, unrender_jitter=cfg.unrender_jitter * ramp,
                           reference_mix=self._reference_mix())
            logits = out.logits
            mask = out.vertex_mask
            vertex_term = (weights.normal_weight * masked_l1(out.normals_marked, out.normals, mask)
                           + weights.uv_weight * masked_l1(out.uvs_marked, out.uvs, mask))
            texture_term = (out.texture_marked - out.texture).abs().mean()
            image_term = (out.render_marked - out.render).abs().mean()
            loss = (weights.message * message_loss(logits, message) + ramp * weights.vertex * vertex_term
                    + self.texture_weight * texture_term + self.image_weight * image_term)
            batch_psnr = float(psnr(out.render_marked.detach(), out.render).mean())
            texture_psnr = float(psnr(out.texture_marked.detach(), out.texture).mean())
            self.image_weight = self._dual(self.image_weight, cfg.target_psnr, batch_psnr)
            self.texture_weight = self._dual(self.texture_weight, cfg.target_psnr_texture, texture_psnr)
            stats.update(psnr_render=batch_psnr, image_weight=self.image_weight, stage=2, psnr_texture=texture_psnr)
        self.optimizer.zero_grad(set_to_none=True)
        loss.backward()
        average_gradients(self.parameters, self.world)
        self.optimizer.step()
        stats.update(loss=loss.detach(), bit_acc=bit_accuracy(logits.detach(), message).mean())
        return stats  # tensors stay on the device until `fit` logs them

    def _log_every(self) -> int:
        every = self.config.train.log_every
        return every if every > 0 else (50 if self.device.type == "cuda" else 1)

    # -------------------------------------------------------- loop
    def fit(self) -> dict:
        from tqdm import tqdm

        from .validate import evaluate

        cfg = self.config.train
        if self.optimizer is None:  # nothing to learn: the model is its config and seeded pattern
            self._save_model()
            summary = {"steps": 0, "elapsed_s": 0.0, "stopped_by_time_limit": False}
            (self.out / "summary.json").write_text(json.dumps(summary, indent=2))
            return summary
        main = self.world.main  # the one process that logs, validates and writes
        log_path = self.out / "log.csv"
        columns = ["step", "stage", "loss", "bit_acc", "psnr_render", "psnr_texture", "image_weight", "elapsed_s"]
        if main and (not log_path.exists() or self.step == 0):
            with open(log_path, "w", newline="") as stream:
                csv.writer(stream).writerow(columns)
        val_path = self.out / "val.csv"
        if main and (not val_path.exists() or self.step == 0):
            val_path.write_text("step,bit_acc,psnr_render,ssim_render,psnr_texture,elapsed_s\n")
        for path in (log_path, val_path) if main else ():  # a resumed run drops rows logged after its checkpoint
            lines = path.read_text().splitlines(keepends=True)
            path.write_text("".join(lines[:1] + [line for line in lines[1:] if int(line.split(",")[0]) <= self.step]))
        batches = self._view_batches() if self.views is not None else self._batches()
        start = time.time() - self.elapsed
        recent: list[float] = []
        pending: list[tuple[int, dict]] = []  # rows not yet logged: their figures are still on the device
        bar = tqdm(total=cfg.steps, initial=self.step, desc=self.config.name, unit="step", dynamic_ncols=True,
                   disable=not main)
        stopped_early = False
        every = self._log_every()
        saved_at = time.time()
        while self.step < min(cfg.steps, cfg.stop_at or cfg.steps):
            stats = self.train_step(next(batches))
            self.step += 1
            self.elapsed = time.time() - start
            pending.append((self.step, stats))
            bar.update(1)
            last = self.step >= cfg.steps or (cfg.stop_at is not None and self.step >= cfg.stop_at)
            if cfg.time_limit_minutes is not None:
                over = self.elapsed > 60 * cfg.time_limit_minutes
                if self.world.distributed:  # several processes stop at the same step: they agree now and then
                    over = self.step % every == 0 and float(average(torch.tensor([float(over)], device=self.device),
                                                                        self.world)) > 0
                if over:
                    stopped_early = last = True
            overdue = cfg.checkpoint_minutes is not None and time.time() - saved_at > 60 * cfg.checkpoint_minutes
            if not main:
                pending = []
            elif len(pending) >= every or last or overdue or self.step % cfg.val_every == 0 or self.step % cfg.checkpoint_every == 0:
                names = ("loss", "bit_acc", "psnr_render", "psnr_texture")
                values = torch.stack([torch.as_tensor(row.get(name, float("nan")), dtype=torch.float32,
                                                      device=self.device).reshape(()) for _, row in pending
                                      for name in names]).reshape(len(pending), len(names)).tolist()  # one round trip
                with open(log_path, "a", newline="") as stream:
                    for (step, row), (loss, acc, p_render, p_texture) in zip(pending, values):
                        recent = (recent + [acc])[-50:]
                        csv.writer(stream).writerow([step, row["stage"], f"{loss:.5f}", f"{acc:.4f}", f"{p_render:.3f}",
                                                     f"{p_texture:.3f}", f"{row.get('image_weight', self.image_weight):.4f}",
                                                     f"{self.elapsed:.1f}"])
                bar.set_postfix(acc=f"{sum(recent) / len(recent):.3f}", psnr=f"{values[-1][2]:.1f}",
                                stage=pending[-1][1]["stage"])
                pending = []
            if self.views is not None and (self.step % cfg.val_every == 0 or self.step % cfg.checkpoint_every == 0
                                           or last or overdue):
                self.recalibrate_batch_norm()  # what validation reads and the weights keep
            if main and (self.step % cfg.val_every == 0 or last):
                metrics = self.validate_gbuffers() if self.views is not None else evaluate(
                    self.model, self.val_set, n_meshes=cfg.val_meshes, views=1, seed=self.config.seed,
                    render_size=cfg.render_size, sampler=cfg.sampler, batch_size=cfg.batch_size,
                    unrender_jitter=cfg.unrender_jitter)
                with open(val_path, "a") as stream:
                    stream.write(f"{self.step},{metrics['bit_acc']:.4f},{metrics['psnr_render']:.3f},"
                                 f"{metrics['ssim_render']:.4f},{metrics['psnr_texture']:.3f},{self.elapsed:.1f}\n")
                bar.write(f"step {self.step}: val bit_acc {metrics['bit_acc']:.4f} psnr_render {metrics['psnr_render']:.2f} "
                          f"ssim_render {metrics['ssim_render']:.4f} psnr_texture {metrics['psnr_texture']:.2f} "
                          f"({self.step / max(self.elapsed, 1e-9) * 60:.0f} steps/min)")
                plot_curves(self.out)
            if self.step % cfg.checkpoint_every == 0 or last or overdue:
                self._checkpoint()
                saved_at = time.time()
            if last:
                break
        bar.close()
        if main and self.views is not None and cfg.bn_renders > 0:
            self.statistics_from_renders()
        self._save_model()
        summary = {"steps": self.step, "elapsed_s": round(self.elapsed, 1), "stopped_by_time_limit": stopped_early}
        if main:
            (self.out / "summary.json").write_text(json.dumps(summary, indent=2))
        return summary


def plot_curves(out_dir) -> None:
    """log.csv and val.csv -> curves.png (training bit accuracy and PSNR, validation points)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    out_dir = Path(out_dir)
    rows = list(csv.DictReader(open(out_dir / "log.csv")))
    val = list(csv.DictReader(open(out_dir / "val.csv"))) if (out_dir / "val.csv").exists() else []
    if not rows:
        return
    step = np.array([float(r["step"]) for r in rows])
    acc = np.array([float(r["bit_acc"]) for r in rows])
    window = max(1, len(acc) // 100)
    smooth = np.convolve(acc, np.ones(window) / window, mode="same")
    figure, (left, right) = plt.subplots(1, 2, figsize=(11, 4))
    left.plot(step, smooth, label="train (smoothed)")
    if val:
        left.plot([float(v["step"]) for v in val], [float(v["bit_acc"]) for v in val], "o-", label="validation")
    left.set_xlabel("step"), left.set_ylabel("bit accuracy"), left.legend(), left.grid(alpha=0.3)
    p = np.array([float(r["psnr_render"]) for r in rows])
    right.plot(step, p, ".", ms=2, alpha=0.4, label="train render PSNR")
    if val:
        right.plot([float(v["step"]) for v in val], [float(v["psnr_render"]) for v in val], "o-", label="val render PSNR")
        right.plot([float(v["step"]) for v in val], [float(v["psnr_texture"]) for v in val], "s-", label="val texture PSNR")
    right.set_xlabel("step"), right.set_ylabel("dB"), right.legend(), right.grid(alpha=0.3)
    figure.tight_layout()
    temp = out_dir / ".curves.png.tmp.png"
    figure.savefig(temp, dpi=90)
    plt.close(figure)
    temp.replace(out_dir / "curves.png")
