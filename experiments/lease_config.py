"""Size a training config to one short GPU lease (#48): the config's `steps`, `warmup_steps` and `lr_decay_from`
scaled together to the steps the card runs in the seconds given, at the rate a calibration run measured.

python experiments/lease_config.py CONFIG --log CALIBRATION/log.csv --seconds S [--channels-last] --out OUT.yaml
Prints the steps chosen and the rate they assume. With --calibration instead of --log and --seconds: the
config for the calibration run itself (no validation or timed checkpoints before its end).
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import yaml


def measured_rate(log: Path, skip_s: float = 4.0) -> float:
    """Training steps per second in a run's log.csv, leaving out its first seconds (cuDNN's timing of its
    algorithms, the first batches)."""
    rows = [(int(row["step"]), float(row["elapsed_s"])) for row in csv.DictReader(open(log))]
    start = next((row for row in rows if row[1] >= skip_s), rows[0])
    end = rows[-1]
    if end[0] <= start[0] or end[1] <= start[1]:
        raise SystemExit(f"{log}: too few rows to measure a rate")
    return (end[0] - start[0]) / (end[1] - start[1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", type=Path)
    parser.add_argument("--log", type=Path, help="the calibration run's log.csv")
    parser.add_argument("--seconds", type=float, help="training seconds the run may take")
    parser.add_argument("--calibration", action="store_true", help="write the calibration run's config")
    parser.add_argument("--margin", type=float, default=0.93, help="share of the seconds the steps are sized to")
    parser.add_argument("--channels-last", action="store_true")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    values = yaml.safe_load(args.config.read_text())
    train = values["train"]
    train["channels_last"] = bool(args.channels_last)
    if args.calibration:
        train.update(val_every=10**6, checkpoint_minutes=None)
        args.out.write_text(yaml.safe_dump(values, sort_keys=False))
        return 0
    if args.log is None or args.seconds is None:
        parser.error("--log and --seconds are required (except with --calibration)")
    rate = measured_rate(args.log)
    steps = max(100, int(rate * args.seconds * args.margin) // 100 * 100)
    scale = steps / train["steps"]
    for key in ("warmup_steps", "lr_decay_from"):
        if train.get(key):
            train[key] = int(round(train[key] * scale))
    train["steps"] = steps
    args.out.write_text(yaml.safe_dump(values, sort_keys=False))
    print(f"{rate:.2f} steps/s measured: {steps} steps in {args.seconds:.0f} s (warmup {train.get('warmup_steps')}, "
          f"decay from {train.get('lr_decay_from')}, channels_last {train['channels_last']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
