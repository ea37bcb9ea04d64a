"""What a reading found about a picture, kept with its tensor for a second reading of the same tensor
(a second look under other cameras): its codec, its JPEG grid, its footprint."""

from __future__ import annotations

import torch

from ..versions import version as version_of


def kept_with(image: torch.Tensor, registry: list):
    """What `registry` ((picture tensor, its version, value) entries, the latest first) keeps for the
    tensor `image`, as long as it is unchanged; None if nothing. What a reading found about a picture
    (its codec, its JPEG grid, its footprint) is kept this way for a second reading of the same tensor."""
    for kept, version, value in registry:
        if (kept.data_ptr(), kept.shape, kept.dtype, version) == (image.data_ptr(), image.shape, image.dtype,
                                                                  version_of(image)):
            return value
    return None


def keep_with(image: torch.Tensor, registry: list, value) -> None:
    """Keep `value` for the tensor `image` in `registry` (`kept_with`), with the three latest others."""
    registry[:] = [(image, version_of(image), value)] + [entry for entry in registry if entry[0] is not image][:3]
