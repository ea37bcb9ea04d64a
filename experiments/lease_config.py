"""Size a training config to one short GPU lease (#48): the config's `steps`, `warmup_steps` and `lr_decay_from`
scaled together to the steps the card runs in the seconds given, at the rate a calibration run measured.

python experiments/lease_config.py CONFIG --log CALIBRATION/log.csv --seconds S [--channels-last]
    [--bn-from CALIBRATION_OUTPUT] --out OUT.yaml
Prints the steps chosen and the rate they assume, then `train_seconds=T`: the seconds the training itself may
take, S less those kept for the batch-norm measurement on rendered pictures that follows it (`bn_renders`,
timed on a few pictures by the calibration run, whose printed output --bn-from reads). With --calibration
instead of --log and --seconds: the config for the calibration run itself (no validation or timed
checkpoints before its end; `bn_renders` at most 64, or --bn-renders N: 0 for a run that only bakes views).
"""

from __future__ import annotations

import argparse
import csv
import math
import re
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


CALIBRATION_BN_RENDERS = 64


def bn_seconds(output: Path, count: int) -> float:
    """Seconds the final run's batch-norm measurement of `count` rendered pictures will take, from the
    calibration run's output (its line "decoder batch-norm statistics from N rendered pictures (S s)": S
    is rounded to whole seconds, so S + 1 is scaled, from N pictures to `count`); 0 where the config
    measures none or the line is missing."""
    found = re.findall(r"statistics from (\d+) rendered pictures \((\d+) s\)", output.read_text() if output.is_file() else "")
    if not count or not found:
        return 0.0
    pictures, seconds = (int(value) for value in found[-1])
    return math.ceil((seconds + 1) * count / max(1, pictures))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", type=Path)
    parser.add_argument("--log", type=Path, help="the calibration run's log.csv")
    parser.add_argument("--seconds", type=float, help="training seconds the run may take")
    parser.add_argument("--calibration", action="store_true", help="write the calibration run's config")
    parser.add_argument("--margin", type=float, default=0.93, help="share of the seconds the steps are sized to")
    parser.add_argument("--channels-last", action="store_true")
    parser.add_argument("--bn-from", type=Path, default=None,
                        help="the calibration run's output: the final batch-norm measurement's seconds, timed there, "
                             "come off --seconds")
    parser.add_argument("--bn-renders", type=int, default=None,
                        help="with --calibration: the pictures its batch-norm measurement renders (default at most "
                             f"{CALIBRATION_BN_RENDERS}, to time the final one; 0 for the bake run)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    values = yaml.safe_load(args.config.read_text())
    train = values["train"]
    train["channels_last"] = bool(args.channels_last)
    if args.calibration:
        train.update(val_every=10**6, checkpoint_minutes=None)
        # The run's batch-norm measurement on rendered pictures (`bn_renders`) comes after its time limit: the
        # calibration renders a few of them to time it (the final run reserves the time), the bake none.
        few = min(train.get("bn_renders") or 0, CALIBRATION_BN_RENDERS)
        train["bn_renders"] = few if args.bn_renders is None else args.bn_renders
        args.out.write_text(yaml.safe_dump(values, sort_keys=False))
        return 0
    if args.log is None or args.seconds is None:
        parser.error("--log and --seconds are required (except with --calibration)")
    rate = measured_rate(args.log)
    reserved = bn_seconds(args.bn_from, train.get("bn_renders") or 0) if args.bn_from else 0.0
    seconds = args.seconds - reserved
    steps = max(100, int(rate * seconds * args.margin) // 100 * 100)
    scale = steps / train["steps"]
    for key in ("warmup_steps", "lr_decay_from"):
        if train.get(key):
            train[key] = int(round(train[key] * scale))
    train["steps"] = steps
    args.out.write_text(yaml.safe_dump(values, sort_keys=False))
    print(f"{rate:.2f} steps/s measured: {steps} steps in {seconds:.0f} s (warmup {train.get('warmup_steps')}, "
          f"decay from {train.get('lr_decay_from')}, channels_last {train['channels_last']}"
          + (f"; {reserved:.0f} s kept for the batch-norm measurement of {train.get('bn_renders')} rendered pictures)"
             if reserved else ")"))
    print(f"train_seconds={seconds:.0f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
