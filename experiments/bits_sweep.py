"""Payload sweep: train one config at several message lengths and strategies, evaluate each on the
test split, and print the table (the issue's 8/16/32/48 bits x texture / vertex+texture grid).

    python experiments/bits_sweep.py --config configs/default.yaml --steps 1000 --schedule-from 6000 --out runs/sweep_default
    python experiments/bits_sweep.py --config configs/seed_paper.yaml --steps 600 --out runs/sweep_seed

Every run is the config with `n_bits`, `strategy` and the step budget overridden (step-based schedule
knobs scale with the budget: by steps / --schedule-from); runs resume, finished ones are skipped, and each result is appended to
OUT/results.jsonl. Evaluation: `--eval-meshes` test meshes, one view each from the seed's ranges, our
differentiable renderer, known camera (informed models: no registration error), seed fixed.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch

from meshseal.data.dataset import MeshDataset
from meshseal.training.validate import evaluate
from meshseal.training.train import TrainConfig, Trainer

SCALED = ("warmup_steps", "distortion_start", "reference_steps", "pretrain_steps")


def run_one(base: TrainConfig, bits: int, strategy: str, steps: int, out: Path, eval_meshes: int,
            schedule_from: int) -> dict:
    config = TrainConfig.from_dict(base.to_dict())
    scale = steps / schedule_from
    config.model.n_bits, config.model.strategy = bits, strategy
    for name in SCALED:
        setattr(config.train, name, int(round(getattr(config.train, name) * scale)))
    config.train.steps, config.train.val_every, config.train.time_limit_minutes = steps, steps, None
    config.name = f"{base.name}_{bits}_{strategy.replace('+', '_')}_{steps}"
    folder = out / config.name
    started = time.time()
    trainer = Trainer(config, folder, resume=True, log=lambda *_: None)
    trainer.fit()
    metrics = evaluate(trainer.model, MeshDataset(config.data, "test", seed=config.seed), n_meshes=eval_meshes,
                       views=1, seed=config.seed, render_size=config.train.render_size, sampler="seed")
    return {"config": base.name, "n_bits": bits, "strategy": strategy, "steps": steps,
            "seconds": round(time.time() - started, 1)} | {k: round(v, 4) if isinstance(v, float) else v
                                                          for k, v in metrics.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, required=True)
    parser.add_argument("--bits", type=int, nargs="+", default=[8, 16, 32, 48])
    parser.add_argument("--strategies", nargs="+", default=["texture", "vertex+texture"])
    parser.add_argument("--steps", type=int, default=1000)
    parser.add_argument("--eval-meshes", type=int, default=96)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--schedule-from", type=int, default=None,
                        help="the step budget the config's schedule knobs are scaled from (default: its steps)")
    args = parser.parse_args()
    base = TrainConfig.load(args.config)
    args.out.mkdir(parents=True, exist_ok=True)
    results_path = args.out / "results.jsonl"
    done = {}
    if results_path.exists():
        for line in results_path.read_text().splitlines():
            row = json.loads(line)
            done[(row["n_bits"], row["strategy"], row["steps"])] = row
    for strategy in args.strategies:
        for bits in args.bits:
            key = (bits, strategy, args.steps)
            if key not in done:
                torch.manual_seed(base.seed)
                done[key] = run_one(base, bits, strategy, args.steps, args.out, args.eval_meshes,
                                    args.schedule_from or base.train.steps)
                with open(results_path, "a") as stream:
                    stream.write(json.dumps(done[key]) + "\n")
            row = done[key]
            print(f"{base.name} {strategy:15s} {bits:3d} bits: bit_acc {row['bit_acc']:.4f} +- {row['bit_acc_std']:.3f}  "
                  f"psnr_render {row['psnr_render']:.2f}  ssim_render {row['ssim_render']:.4f}  "
                  f"psnr_texture {row['psnr_texture']:.2f}  ({row['seconds']:.0f} s)", flush=True)


if __name__ == "__main__":
    main()
