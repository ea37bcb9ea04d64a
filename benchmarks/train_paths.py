"""Training speed: the rendering pass against cached G-buffers, in one run on one machine.

Builds a `Trainer` twice from one config (default configs/blind8_gbuffer.yaml), once with
`gbuffer: off` (every step rasterizes, shades and splats the marked and the original mesh, then frames
the picture) and once with `gbuffer: auto` (views baked once, `training.gbuffer.composite` in the
step), and times `--steps` training steps of each after `--warmup` steps, synchronising the device
around the timed block. Prints training pictures per second for each path, their ratio, the bake's
one-off time and the machine's load.

Run: python benchmarks/train_paths.py --data data [--device cuda] [--steps 20] [--batch 64]
     [--config configs/blind8_gbuffer.yaml] [--meshes 64] [--large 512] [--channels-last]
The last line is machine-readable:
    train_render_pics_per_s=<float> train_gbuffer_pics_per_s=<float> ratio=<float>
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize()


def measure(config, device: str, steps: int, warmup: int, out: Path) -> tuple[float, float]:
    """(pictures per second, seconds to build the trainer: the bake for the G-buffer path)."""
    from meshseal.training.train import Trainer

    started = time.perf_counter()
    trainer = Trainer(config, out, device=device, log=lambda *_: None)
    built = time.perf_counter() - started
    batches = trainer._view_batches() if trainer.views is not None else trainer._batches()
    for _ in range(warmup):
        trainer.train_step(next(batches))
    _sync(device)
    started = time.perf_counter()
    for _ in range(steps):
        trainer.train_step(next(batches))
    _sync(device)
    return steps * config.train.batch_size / (time.perf_counter() - started), built


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=ROOT / "data")
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "blind8_gbuffer.yaml")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--steps", type=int, default=10)
    parser.add_argument("--warmup", type=int, default=2)
    parser.add_argument("--batch", type=int, default=None, help="batch size (default the config's)")
    parser.add_argument("--views", type=int, default=2, help="baked views per mesh for the G-buffer path")
    parser.add_argument("--large", type=int, nargs="*", default=[],
                        help="also time the rendering pass at these render sizes (the object then framed from a "
                             "large render, as the G-buffer views are)")
    parser.add_argument("--channels-last", action="store_true",
                        help="also time the G-buffer path with the networks in NHWC memory order (train.channels_last)")
    args = parser.parse_args()
    from meshseal.training.train import TrainConfig

    config = TrainConfig.load(args.config)
    config.data = str(args.data)
    config.train.gbuffer_views = args.views
    config.train.distortion_start = 0
    config.train.pretrain_steps = 0
    if args.batch:
        config.train.batch_size = args.batch
    print(f"device {args.device} ({torch.cuda.get_device_name() if args.device.startswith('cuda') else 'CPU'}), "
          f"torch threads {torch.get_num_threads()}, OMP_NUM_THREADS={os.environ.get('OMP_NUM_THREADS', 'unset')}, "
          f"load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}, cores {os.cpu_count()}")
    print(f"config {args.config.name}: batch {config.train.batch_size}, frame {config.model.frame_size}^2, "
          f"render {config.train.render_size}^2, {args.steps} timed steps after {args.warmup}")
    out = Path(tempfile.mkdtemp(prefix="train_paths-"))
    large_speeds = []
    try:
        config.train.gbuffer = "off"
        render, _ = measure(config, args.device, args.steps, args.warmup, out / "render")
        print(f"rendering pass at {config.train.render_size}^2: {render:.1f} pictures/s")
        size = config.train.render_size
        for large in args.large:  # the same framing as the baked views: render large, crop around the object
            config.train.render_size = large
            speed, _ = measure(config, args.device, args.steps, args.warmup, out / f"render{large}")
            print(f"rendering pass at {large}^2: {speed:.1f} pictures/s (ratio to the G-buffers below)")
            large_speeds.append((large, speed))
        config.train.render_size = size
        config.train.gbuffer = "auto"
        gbuffer, built = measure(config, args.device, args.steps, args.warmup, out / "gbuffer")
        print(f"cached G-buffers: {gbuffer:.1f} pictures/s (trainer built in {built:.1f} s, bake included if not cached)")
        if args.channels_last:
            config.train.channels_last = True
            nhwc, _ = measure(config, args.device, args.steps, args.warmup, out / "gbuffer_nhwc")
            print(f"cached G-buffers, channels_last: {nhwc:.1f} pictures/s ({nhwc / gbuffer:.2f} x the NCHW figure)")
    finally:
        shutil.rmtree(out, ignore_errors=True)
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    for large, speed in large_speeds:
        print(f"ratio to the rendering pass at {large}^2: {gbuffer / speed:.2f}")
    print(f"train_render_pics_per_s={render:.2f} train_gbuffer_pics_per_s={gbuffer:.2f} ratio={gbuffer / render:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
