"""Batch-norm statistics measured afresh: a cumulative average over chosen batches with the weights as
they are, instead of the running average of the weights' history.

Two uses in training: before each validation and checkpoint, on baked views (`Trainer.recalibrate_batch_norm`:
the running average lags a mark that is being squeezed); and at the end of a G-buffer run, the decoder's
statistics on pictures the renderer makes of the training meshes (`decoder_statistics_from_renders`): a
baked view has hard silhouettes and one texture sample per frame pixel, a rendered picture splatted edges
and a frame shrunk with antialiasing, and a decoder normalised with the baked views' statistics reads the
rendered pictures worse.
"""

from __future__ import annotations

from contextlib import contextmanager

import torch


def batch_norms(module: torch.nn.Module) -> list:
    return [m for m in module.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]


@contextmanager
def fresh_statistics(norms: list):
    """Inside: `norms` start from empty statistics and average every batch they see in training mode
    equally (momentum None); their momenta are given back on leaving."""
    momenta = [norm.momentum for norm in norms]
    for norm in norms:
        norm.reset_running_stats()
        norm.momentum = None
    try:
        yield
    finally:
        for norm, momentum in zip(norms, momenta):
            norm.momentum = momentum


@torch.no_grad()
def decoder_statistics_from_renders(model, dataset, pictures: int, size, sampler: str = "seed", seed: int = 0,
                                    batch_size: int = 16) -> None:
    """The decoder's batch-norm statistics measured over `pictures` renders of `dataset`'s items (cycled in
    an order drawn from `seed`), each marked with a random message, rendered at `size` ((H, W) or S) from a
    `sampler` view and framed as the rendering pass frames it (`training.step.run_pass`). The encoders run
    in eval mode; no weight changes. The model is left in eval mode."""
    from ..data.dataset import collate
    from ..render import MeshRenderer
    from .step import run_pass

    norms = batch_norms(model.decoder)
    if not norms or pictures <= 0:
        return
    generator = torch.Generator().manual_seed(seed)
    renderer = MeshRenderer()
    order = torch.randperm(len(dataset), generator=generator).tolist()
    model.eval()
    model.decoder.train()
    try:
        with fresh_statistics(norms):
            for start in range(0, pictures, batch_size):
                index = [order[i % len(order)] for i in range(start, min(pictures, start + batch_size))]
                batch = collate([dataset[i] for i in index], model.device)
                message = torch.randint(0, 2, (len(index), model.n_bits), generator=generator).float().to(model.device)
                run_pass(model, batch, message, renderer, generator, size, sampler, None, None)
    finally:
        model.eval()
