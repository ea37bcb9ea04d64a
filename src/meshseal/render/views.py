"""Views to render from: cameras and lights drawn from the seed paper's ranges or from anywhere."""

from __future__ import annotations

import torch

from .cameras import sample_any_view_cameras, sample_seed_cameras
from .lighting import sample_any_lights, sample_seed_lights


def sample_views(n: int, sampler: str, generator: torch.Generator):
    """Cameras and lights from the seed's ranges ('seed') or from anywhere ('any')."""
    if sampler == "seed":
        return sample_seed_cameras(n, generator), sample_seed_lights(n, generator)
    if sampler == "any":
        return sample_any_view_cameras(n, generator), sample_any_lights(n, generator)
    raise ValueError(f"unknown view sampler '{sampler}' (seed | any)")
