"""A tensor's version, for caches that serve a result again only for the same, unchanged tensor."""

from __future__ import annotations

import torch


def version(tensor: torch.Tensor) -> int:
    """`tensor`'s version counter, which every in-place change bumps; -1 for an inference tensor (one made
    under `torch.inference_mode`, where detection runs), which keeps no counter: nothing changes such a
    tensor in place after it is made (and outside that mode nothing can)."""
    return -1 if tensor.is_inference() else tensor._version
