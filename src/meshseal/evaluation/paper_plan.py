"""The plan of the seed paper's re-run (Yoo et al., "Deep 3D-to-2D Watermarking", CVPR 2022): its tables
as rows of settings over a base training config, the paper's figures beside them, and which training runs
the re-run makes, keyed by a hash of each run's settings so that tables needing the same training share it
and parallel shards (`--shard K/N`) never train a run twice or apart from the run it starts from.

`experiments/paper.py` trains, evaluates and reports from this plan; nothing here trains.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path

import yaml

CONFIGS = Path(__file__).resolve().parents[3] / "configs"


@lru_cache(maxsize=None)
def config_settings(name: str) -> dict:
    """The model section of `configs/NAME` as row settings ("model.knob": value)."""
    model = yaml.safe_load((CONFIGS / name).read_text())["model"]
    return {f"model.{knob}": value for knob, value in model.items()}


SCALED = ("warmup_steps", "distortion_start", "reference_steps", "pretrain_steps", "lr_decay_from")
PAPER_KINDS = ["noise", "real"]
BITS = (4, 8, 16, 32, 48)


@dataclass
class Row:
    """One row of a table: the base config with `settings` ("model.x" / "loss.x" / "train.x": value),
    the evaluation's 3D distortion (`distortion`: None, or the one kind applied to every picture), and
    the paper's figures by column."""

    label: str
    settings: dict
    paper: dict
    distortion: str | None = None
    start_from: str | None = None  # label of a row (same table) whose run of the same seed this one starts from
    from_config: str | None = None  # a config in configs/ whose model section is added to `settings`

    def all_settings(self) -> dict:
        """`settings` with the model section of `from_config` (read when first needed) under them."""
        return (config_settings(self.from_config) if self.from_config else {}) | self.settings


@dataclass
class Table:
    number: int
    title: str
    columns: list  # (heading, metric) pairs; metrics: best / mean / sigma of bit accuracy, or an evaluate() key
    rows: list = field(default_factory=list)
    note: str = ""  # a line under the table


VT = {"model.strategy": "vertex+texture"}
# The shipped blind surface code (configs/blind.yaml's model; models/surface.py): nothing learned, so a
# "run" is the code drawn from its seed and the evaluation; 32 cells up to 16 bits, 64 above (as shipped).
SURFACE_ROW = "Surface code (ours, blind, no training)"
PAPER_PICTURE = (400, 600)  # the seed paper's picture (height, width), where the surface code is read
FIXED_WEIGHTS = {"train.target_psnr": None, "train.target_psnr_texture": None}
QUALITY = [("Best", "best"), ("μ", "mean"), ("σ", "sigma")]
GEOMETRY = [("Normal L1", "l1_normal"), ("Texcoord L1", "l1_uv"), ("PSNR", "psnr_render"), ("SSIM", "ssim_render")]

TABLES = [
    Table(1, "Vertex encoders with a texture encoder (8 bits)", QUALITY + GEOMETRY, [
        Row("PointNet", VT | {"model.vertex_encoder": "pointnet"},
            {"best": 0.8553, "mean": 0.7591, "sigma": 0.0789, "l1_normal": 0.0529, "l1_uv": 0.0805,
             "psnr_render": 25.57, "ssim_render": 0.9425}),
        Row("PointNet v2", VT | {"model.vertex_encoder": "pointnet2"},
            {"best": 0.8207, "mean": 0.7213, "sigma": 0.0754, "l1_normal": 0.0415, "l1_uv": 0.0745,
             "psnr_render": 25.10, "ssim_render": 0.9416}),
    ]),
    Table(2, "Vertex encoders without a texture encoder (8 bits)", QUALITY + GEOMETRY, [
        Row("PointNet", {"model.strategy": "vertex", "model.vertex_encoder": "pointnet"},
            {"best": 0.6837, "mean": 0.6151, "sigma": 0.0366, "l1_normal": 0.1873, "l1_uv": 0.0546,
             "psnr_render": 28.47, "ssim_render": 0.9563}),
        Row("PointNet v2", {"model.strategy": "vertex", "model.vertex_encoder": "pointnet2"},
            {"best": 0.6616, "mean": 0.6255, "sigma": 0.0216, "l1_normal": 0.1506, "l1_uv": 0.0430,
             "psnr_render": 28.83, "ssim_render": 0.9557}),
    ]),
    Table(3, "Texture encoders (8 bits)", QUALITY + [("Texture L1", "l1_texture"), ("Texture PSNR", "psnr_texture"),
                                                    ("Texture SSIM", "ssim_texture")], [
        Row("CNN (HiDDeN)", {"model.texture_encoder": "hidden"},
            {"best": 0.8269, "mean": 0.7614, "sigma": 0.0411, "l1_texture": 0.03536, "psnr_texture": 26.20,
             "ssim_texture": 0.9113}),
        Row("U-Net", {"model.texture_encoder": "unet"},
            {"best": 0.8474, "mean": 0.7451, "sigma": 0.1289, "l1_texture": 0.05692, "psnr_texture": 23.55,
             "ssim_texture": 0.9143}),
    ]),
    Table(4, "Decoders (8 bits)", QUALITY, [
        Row("Simple CNN (4 layers)", {"model.decoder": "simple"}, {"best": 0.6396, "mean": 0.6184, "sigma": 0.0415}),
        Row("Residual CNN (4 layers)", {"model.decoder": "residual"},
            {"best": 0.7390, "mean": 0.6453, "sigma": 0.0332}),
        Row("CNN (HiDDeN)", {"model.decoder": "hidden"}, {"best": 0.8269, "mean": 0.7614, "sigma": 0.0411}),
    ]),
    Table(5, "Message loss weight θ (8 bits, vertex + texture, fixed loss weights)",
          QUALITY + [("Normal L1", "l1_normal"), ("Texcoord L1", "l1_uv"), ("Texture L1", "l1_texture"),
                     ("Texture PSNR", "psnr_texture"), ("Texture SSIM", "ssim_texture"), ("Render L1", "l1_render"),
                     ("Render PSNR", "psnr_render"), ("Render SSIM", "ssim_render")],
          [Row(f"θ = {theta}", VT | FIXED_WEIGHTS | {"loss.message": theta},
               dict(zip(("best", "mean", "sigma", "l1_normal", "l1_uv", "l1_texture", "psnr_texture", "ssim_texture",
                         "l1_render", "psnr_render", "ssim_render"), paper)))
           for theta, paper in (
               (0.01, (0.5475, 0.4997, 0.0090, 0.0475, 0.0537, 0.0042, 46.57, 0.9849, 0.0055, 36.91, 0.9700)),
               (0.1, (0.7947, 0.7256, 0.0396, 0.0472, 0.0621, 0.0056, 41.11, 0.9844, 0.0062, 35.67, 0.9614)),
               (1.0, (0.9262, 0.8857, 0.0255, 0.0437, 0.0699, 0.0186, 30.74, 0.8639, 0.0063, 35.35, 0.9609)),
               (2.0, (0.9325, 0.8921, 0.0432, 0.2071, 0.2404, 0.0229, 29.37, 0.8062, 0.0071, 34.70, 0.9603)),
               (5.0, (0.8775, 0.8562, 0.0146, 0.2563, 0.2873, 0.0363, 25.45, 0.6626, 0.0088, 32.90, 0.9552)),
               (10.0, (0.9362, 0.8288, 0.1135, 0.1041, 0.1810, 0.0549, 22.42, 0.5088, 0.0105, 31.10, 0.9426)))]),
    Table(6, "Embedding strategies x message length (mean bit accuracy)", [(f"{b} bits", f"mean@{b}") for b in BITS], [
        Row("Vertex only", {"model.strategy": "vertex"},
            {f"mean@{b}": v for b, v in zip(BITS, (0.7646, 0.6289, 0.5717, 0.5627, 0.5370))}),
        Row("Texture only", {"model.strategy": "texture"},
            {f"mean@{b}": v for b, v in zip(BITS, (0.9554, 0.8970, 0.7975, 0.6364, 0.5679))}),
        Row("Vertex + Texture", VT, {f"mean@{b}": v for b, v in zip(BITS, (0.9208, 0.8480, 0.8000, 0.6441, 0.5905))}),
        Row(SURFACE_ROW, {}, {}, from_config="blind.yaml"),
    ], note=f"The paper has no row like \"{SURFACE_ROW}\" (its – cells): compare it with the paper's Texture only "
            "row. It is read from 600 x 400 pictures (the paper's size); the learned rows from the base config's render size."),
    Table(7, "Distortions at evaluation (8 bits, texture; the model trained with all of them)", [("Bit accuracy", "mean")], [
        Row("No distortion", {}, {"mean": 0.9046}),
        Row("Noise (σ = 0.01)", {}, {"mean": 0.9036}, distortion="noise"),
        Row("Rotation (± π/6)", {}, {"mean": 0.9028}, distortion="rotation"),
        Row("Scaling (< 25 %)", {}, {"mean": 0.8953}, distortion="scaling"),
        Row("Cropping (< 20 %)", {}, {"mean": 0.8840}, distortion="crop"),
    ]),
    Table(8, "Deep image watermarking (HiDDeN trained on textures alone) vs. ours with its encoder fixed",
          [("Bit accuracy", "mean")], [
        Row("HiDDeN", VT | {"train.pretrain_steps": "budget"}, {"mean": 0.5132}),
        Row("Our method", VT | {"train.frozen": ["texture_encoder"]}, {"mean": 0.8213}, start_from="HiDDeN"),
    ]),
]

TABLE9_PAPER = {"ours": ("Differentiable renderer", 0.7490), "workbench": ("Workbench (RT)", 0.6341),
                "cycles": ("Cycles (PB)", 0.6634), "eevee": ("Eevee (PB)", 0.5973)}


def row_bits(table: Table) -> tuple:
    """The message lengths a row trains at: each of them in Table 6, the base config's elsewhere."""
    return BITS if table.number == 6 else (None,)


def configure(base, settings: dict, bits: int | None, budget: int, seed: int,
              start_from: Path | None) :
    """The base config with a row's settings, `bits`, `seed`, the step budget (step-based schedule knobs
    scaled to it) and the paper's texture kinds."""
    config = type(base).from_dict(base.to_dict())
    scale = budget / base.train.steps
    for knob in SCALED:
        value = getattr(config.train, knob)
        if value:
            setattr(config.train, knob, int(round(value * scale)))
    for dotted, value in settings.items():
        part, knob = dotted.split(".")
        setattr(getattr(config, part), knob, budget if value == "budget" else value)
    if bits is not None:
        config.model.n_bits = bits
    config.train.steps, config.train.val_every, config.train.time_limit_minutes = budget, budget, None
    if config.model.method == "surface":  # nothing to train: the code is drawn from the seed
        config.model.chips, config.model.pattern_seed = (32 if config.model.n_bits <= 16 else 64), seed
        config.train.steps = config.train.val_every = 0
    config.train.val_meshes = 8  # a sanity check at the end; the evaluation below is the figure
    config.train.texture_kinds = PAPER_KINDS
    config.train.init_from = str(start_from) if start_from else None
    config.seed = seed
    return config


def described_run(config) -> dict:
    """What identifies a run: its config's settings that differ from the defaults (so that a knob
    added to the code later, at a default, leaves the keys of finished runs as they were)."""
    defaults = type(config)().to_dict()
    described = {}
    for section, values in (config.to_dict() | {"name": None}).items():
        if isinstance(values, dict):
            described[section] = {k: v for k, v in values.items() if defaults.get(section, {}).get(k, object()) != v}
        elif defaults.get(section, object()) != values:
            described[section] = values
    described.setdefault("train", {})
    return described


def planned(out: Path, base, table: Table, row: Row, bits: int | None, budget: int,
            seed: int) -> tuple[str, object]:
    """(key, config) of one training run; the key is the config's own hash, so tables that need the
    same training share it."""
    start = None
    if row.start_from:
        source = next(r for r in table.rows if r.label == row.start_from)
        start = out / "runs" / planned(out, base, table, source, bits, budget, seed)[0] / "model.safetensors"
    config = configure(base, row.all_settings(), bits, budget, seed, start)
    described = described_run(config)
    if start is not None:
        described["train"]["init_from"] = start.parent.name  # the key, not where OUT happens to be
    key = hashlib.sha1(json.dumps(described, sort_keys=True).encode()).hexdigest()[:12]
    config.name = f"paper_{key}"
    return key, config


def plan(args, base) -> list:
    """Every run to make, in order (seed by seed, so that a partial run fills every table with one run
    before the next seed starts): (seed, table, row, bits, shard group). Runs shared between tables,
    and a run with the one it starts from, fall in one group; `--shard K/N` takes every N-th group."""
    runs, groups = [], {}
    for seed in args.seeds or range(args.runs):
        for table in TABLES:
            if table.number not in args.tables or table.number == 9:
                continue
            for row in table.rows:
                if row.distortion:
                    continue  # read from the undistorted row's models
                source = next(r for r in table.rows if r.label == row.start_from) if row.start_from else row
                for bits in row_bits(table):
                    group = planned(args.out, base, table, source, bits, args.budget, seed)[0]
                    runs.append((seed, table, row, bits, groups.setdefault(group, len(groups))))
    return runs


def done_keys_of_seed(args, base, seed: int) -> set:
    """The distinct training runs one seed's pass over the chosen tables makes (shared runs once)."""
    return {planned(args.out, base, table, row, bits, args.budget, seed)[0]
            for table in TABLES if table.number in args.tables and table.number != 9
            for row in table.rows if not row.distortion for bits in row_bits(table)}
