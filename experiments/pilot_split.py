"""How the any-mark decision should split its false-positive rate between the pilot's test and the bits'
test (`payload.any_mark_pvalue`, `PILOT_SHARE`). Runs `meshseal eval ARGS` with every any-mark decision
logged (the bits' p-value times the cameras and grids tried, the pilot's times the cameras tried), then
counts the pictures detected at FPR 1e-6 under each share s of the pilot: p = min(pilot / s, bits / (1 - s)),
s = 0.5 being twice the smaller. Every decision counts once (`meshseal eval` decides a clean picture's reading
twice, as read and as read with its camera: one; a mesh's views pooled and a registered picture's first look
are one more each).

    python experiments/pilot_split.py --log OUT.jsonl -- --data data --meshes 100 --views 2 --size 256 --attacks none,jpeg90,jpeg75,jpeg50,webp80
    python experiments/pilot_split.py --summarise OUT.jsonl [MORE.jsonl ...]
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import math

SHARES = (0.0, 0.5, 0.8, 0.9, 0.95, 0.99, 1.0)


def run(log_path: str, eval_args: list[str]) -> None:
    import torch

    from meshseal import payload
    from meshseal.cli import main
    from meshseal.methods import base

    real = base.Method.decide
    out = open(log_path, "w")

    def decide(self, readings, key=None, expect=None):
        decision = real(self, readings, key, expect)
        if expect is None and decision.p_value is not None:
            evidence = torch.stack([r.evidence for r in readings]).sum(0, keepdim=True)
            soft, weights, tries = self.soft_bits(evidence, key, None)
            looks = math.prod(r.tries for r in readings)
            bits = min(1.0, tries * looks * float(payload.detection_pvalue(soft, weights)))
            pilot = self.pilot_pvalue(evidence, key)
            out.write(json.dumps({"bits": bits, "pilot": None if pilot is None else min(1.0, looks * pilot),
                                  "p": decision.p_value, "detected": bool(decision.detected)}) + "\n")
            out.flush()
        return decision

    base.Method.decide = decide
    with contextlib.redirect_stdout(io.StringIO()):  # the eval's own table: not what this script reports
        main(["eval", *eval_args])
    out.close()


def summarise(paths: list[str]) -> None:
    from meshseal import payload

    rows = []
    for path in paths:
        previous = None
        for line in open(path):
            if not line.strip():
                continue
            row = json.loads(line)
            key = (row["bits"], row["pilot"])
            if row["pilot"] is not None and key != previous:  # the same reading decided again counts once
                rows.append(row)
            previous = key
    print(f"{len(rows)} decisions with a pilot")
    print("| pilot's share s | detected at 1e-6 |")
    print("|---|---|")
    counts = {}
    for s in SHARES:
        found = 0
        for r in rows:
            found += payload.detected(payload.any_mark_pvalue(r["bits"], r["pilot"], s))
        counts[s] = found
        print(f"| {s:g}{' (twice the smaller)' if s == 0.5 else ''}{' (shipped)' if s == payload.PILOT_SHARE else ''} | {found} |")
    alone = [r for r in rows if payload.detected(r["bits"]) and not payload.detected(r["pilot"])]
    missed = [r["bits"] for r in rows if not payload.detected(r["pilot"])]
    print(f"bits' test below 1e-6 where the pilot's is not: {len(alone)}; "
          f"smallest bits' p where the pilot's is not below 1e-6: {min(missed) if missed else float('nan'):.3g}")
    print(" ".join(f"detected_s{s:g}={n}" for s, n in counts.items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--log", help="run `meshseal eval` (arguments after --) and write its decisions here")
    parser.add_argument("--summarise", nargs="+", help="count detections under each split from these logs")
    args, rest = parser.parse_known_args()
    rest = [a for a in rest if a != "--"]
    if args.log:
        run(args.log, rest)
    summarise(args.summarise or [args.log])


if __name__ == "__main__":
    main()
