"""The payload's soft decoding against hard decoding alone: right / wrong / failed messages.

1. Simulated soft bits +-mu + N(0, 1) (seeded), for the 64- and 32-bit schemas.
2. With --data: the default model's soft bits read from pictures of the first --meshes test meshes (one
   seeded view each, 256^2, camera known, marked with a random ID at strength 1) after picture attacks;
   only pictures whose mark is detected (as `meshseal detect` reports a message only then). Of those
   the decoding leaves without a message, how many no decoder could read: another codeword correlates
   with the soft bits better than the true one (`likelier_than_truth`), so a maximum-likelihood decoder
   would name it; the rest are left by the decoder's caution (its posterior rule) or its search.

    python experiments/soft_decoding.py [--draws 400] [--data data --meshes 284 --attacks none,jpeg90,...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "src"))


def outcome(message, truth) -> str:
    return "failed" if message is None else ("right" if message == truth else "wrong")


def simulate(draws: int) -> None:
    from meshseal import payload

    print("| N | mu | hard decoding alone: right / wrong / failed | with the check and the soft retry |")
    print("|---|---|---|---|")
    for n_bits, mus in ((64, (1.0, 1.25, 1.5, 2.0)), (32, (1.0, 1.5, 2.0))):
        for mu in mus:
            rng = np.random.default_rng([n_bits, int(mu * 100)])
            counts = {False: {"right": 0, "wrong": 0, "failed": 0}, True: {"right": 0, "wrong": 0, "failed": 0}}
            for _ in range(draws):
                value = int(rng.integers(0, 2 ** payload.payload_bits(n_bits)))
                z = mu * (2.0 * payload.encode(value, "k", n_bits).numpy() - 1) + rng.standard_normal(n_bits)
                for retry in (False, True):
                    counts[retry][outcome(payload.decode(z, "k", soft_retry=retry).message, value)] += 1
            cells = [" / ".join(str(counts[r][k]) for k in ("right", "wrong", "failed")) for r in (False, True)]
            print(f"| {n_bits} | {mu} | {cells[0]} | {cells[1]} (of {draws}) |")


def likelier_than_truth(soft, identity: int) -> bool:
    """Whether a codeword other than the one of `identity` correlates better with the soft bits (N,):
    the ordered-statistics candidates (`payload._candidates`), under the public key."""
    from meshseal import payload

    z = np.asarray(soft, dtype=np.float64)
    ordered, order, candidates, correlation, whitening = payload._candidates(z, None)
    truth = payload.encode(identity, None, len(z)).numpy().astype(np.uint8)
    own = (truth ^ whitening)[order].astype(np.int64)
    own_correlation = float(((2.0 * own - 1.0) * ordered).sum())
    others = correlation[~(candidates == own).all(1)]
    return bool(len(others)) and float(others.max()) > own_correlation


def marked_picture(encoder, item: dict, generator):
    """A dataset item charted and marked by a spread model at strength 1 with a random ID, rendered by our
    renderer from one seeded view of the seed's range at 256^2 over a random background: (the 8-bit
    picture (H, W, 3), the original as a MeshBatch, the cameras, the ID). Draws from `generator`."""
    import torch

    from meshseal import payload
    from meshseal.data.dataset import collate
    from meshseal.methods.batches import batch_mark_grid, batch_texels_used, charted_item
    from meshseal.render import MeshBatch, MeshRenderer
    from meshseal.render.views import sample_views
    from meshseal.training.views import random_backgrounds

    batch = charted_item(collate([item]))
    identity = int(torch.randint(0, 2 ** 31, (1,), generator=generator))
    message = payload.encode(identity, None, encoder.n_bits)[None]
    positions, normals, uvs, faces, texture = (batch[k] for k in ("positions", "normals", "uvs", "faces", "texture"))
    with torch.no_grad():
        marked = encoder.texture_encoder(texture, message, 1.0, payload.key_seed(None),
                                         batch_mark_grid(encoder.texture_encoder, batch), batch_texels_used(batch))
        cameras, lights = sample_views(1, "seed", generator)
        out = MeshRenderer()(MeshBatch.from_tensors(positions, normals, uvs, faces, marked), cameras, lights, 256, 256,
                             random_backgrounds(1, generator))
        picture = np.round(out.image.clamp(0, 1)[0].permute(1, 2, 0).numpy() * 255).astype(np.uint8)
    return picture, MeshBatch.from_tensors(positions, normals, uvs, faces, texture), cameras, identity


def pictures(data: Path, meshes: int, attacks: list[str], model: str) -> None:
    import torch

    import meshseal
    from meshseal import payload
    from meshseal.data.dataset import MeshDataset
    from meshseal.evaluation.attacks import apply as attack_picture

    watermarker = meshseal.load(model)
    encoder = watermarker.model
    dataset = MeshDataset(data, "test", seed=0)
    generator = torch.Generator().manual_seed(2_000_003)
    counts = {a: {False: {"right": 0, "wrong": 0, "failed": 0}, True: {"right": 0, "wrong": 0, "failed": 0}}
              for a in attacks}
    detected = {a: 0 for a in attacks}
    beyond = {a: 0 for a in attacks}  # failed reads where another codeword is likelier than the true one
    for index in range(min(meshes, len(dataset))):
        picture, original, cameras, identity = marked_picture(encoder, dataset[index], generator)
        for number, name in enumerate(attacks):
            hit = picture if name == "none" else attack_picture(name, picture, np.random.default_rng([0, index, 0, number]))
            try:
                decision = watermarker.decide([watermarker.read(hit.astype(np.float32) / 255.0, original, camera=cameras)])
            except meshseal.MeshsealError:
                continue
            if not decision.detected:
                continue
            detected[name] += 1
            for retry in (False, True):
                result = outcome(payload.decode(decision.soft, None, soft_retry=retry).message, identity)
                counts[name][retry][result] += 1
                if retry and result == "failed" and likelier_than_truth(decision.soft, identity):
                    beyond[name] += 1
        print(f"mesh {index + 1}/{meshes}", file=sys.stderr, flush=True)
    print(f"\n{model}, first {meshes} test meshes, one view each, camera known; of the pictures detected:\n")
    print("| attack | pictures detected | hard decoding alone: right / wrong / failed | with the check and the soft retry "
          "| of its failed, another codeword likelier than the true one |")
    print("|---|---|---|---|---|")
    for name in attacks:
        cells = [" / ".join(str(counts[name][r][k]) for k in ("right", "wrong", "failed")) for r in (False, True)]
        print(f"| {name} | {detected[name]} | {cells[0]} | {cells[1]} | {beyond[name]} |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--draws", type=int, default=400)
    parser.add_argument("--data", type=Path, default=None)
    parser.add_argument("--meshes", type=int, default=284)
    parser.add_argument("--attacks", default="none,jpeg90,jpeg75,jpeg50,webp80")
    parser.add_argument("--model", default="default")
    args = parser.parse_args()
    from meshseal.threads import configure

    configure()
    simulate(args.draws)
    if args.data is not None:
        pictures(args.data, args.meshes, args.attacks.split(","), args.model)


if __name__ == "__main__":
    main()
