"""Training speed of the networks alone, in NCHW and in NHWC (channels_last) memory order, in one run.

A G-buffer training step is the texture encoder, a bilinear lookup and the decoder; on a GPU the two
networks are most of it. This builds the config's model twice (default configs/blind8_gbuffer.yaml) and
times `--steps` steps of encoder -> decoder -> message loss -> backward -> fused Adam on random textures
and messages (bfloat16 autocast on CUDA, as `meshseal train` runs them), after `--warmup` steps, the
device synchronised around the timed block. Prints steps per second for each order and their ratio.

Run: python benchmarks/train_networks.py [--config CONFIG] [--device cuda] [--steps 30] [--batch 64]
The last line is machine-readable:
    nchw_steps_per_s=<float> nhwc_steps_per_s=<float> nhwc_over_nchw=<float>
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parents[1]


def measure(config, device: torch.device, channels_last: bool, steps: int, warmup: int, batch: int) -> float:
    """Steps per second of the networks' forward and backward pass and an Adam step."""
    from meshseal.models import WatermarkModel
    from meshseal.training.losses import message_loss

    torch.manual_seed(0)
    model = WatermarkModel(config.model).to(device)
    if channels_last:
        model.to(memory_format=torch.channels_last)
    model.train()
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4, fused=device.type == "cuda")
    size, bits = config.model.texture_size, config.model.n_bits
    texture = torch.rand(batch, 3, size, size, device=device)
    message = torch.randint(0, 2, (batch, bits), device=device).float()
    amp = torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda")

    def step():
        with amp:
            marked = model.texture_encoder(texture, message).float()
            frame = torch.nn.functional.interpolate(marked, size=config.model.frame_size, mode="bilinear")
            logits = model.decode(frame).float()
        loss = message_loss(logits, message)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()

    for _ in range(warmup):
        step()
    if device.type == "cuda":
        torch.cuda.synchronize()
    started = time.perf_counter()
    for _ in range(steps):
        step()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return steps / (time.perf_counter() - started)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "blind8_gbuffer.yaml")
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--warmup", type=int, default=5)
    parser.add_argument("--batch", type=int, default=None, help="batch size (default the config's)")
    args = parser.parse_args()
    sys.path.insert(0, str(ROOT / "src"))
    from meshseal.training.train import TrainConfig

    config = TrainConfig.load(args.config)
    device = torch.device(args.device)
    if device.type == "cuda":
        torch.backends.cudnn.benchmark = True
    batch = args.batch or config.train.batch_size
    print(f"{config.name}: batch {batch}, {args.device}, load {os.getloadavg()[0]:.2f}, "
          f"torch {torch.__version__}, {torch.get_num_threads()} threads")
    nchw = measure(config, device, False, args.steps, args.warmup, batch)
    nhwc = measure(config, device, True, args.steps, args.warmup, batch)
    print(f"NCHW {nchw:.2f} steps/s ({nchw * batch:.0f} pictures/s), NHWC {nhwc:.2f} steps/s "
          f"({nhwc * batch:.0f} pictures/s)")
    print(f"nchw_steps_per_s={nchw:.3f} nhwc_steps_per_s={nhwc:.3f} nhwc_over_nchw={nhwc / nchw:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
