"""Watermarking schemes behind one interface (`base.Method`): the keyed spread-spectrum mark (the
default), the blind surface code, and the paper's learned networks. `method_for(model)` is the one
place that maps a model's config to its scheme."""

from __future__ import annotations

from .base import Detection, Method

METHODS = ("spread", "surface", "learned")


def method_for(model) -> Method:
    """The Method that marks and reads with `model` (its config's `method`)."""
    name = model.config.method
    if name == "spread":
        from .spread import SpreadMethod

        return SpreadMethod(model)
    if name == "surface":
        from .surface import SurfaceMethod

        return SurfaceMethod(model)
    from .learned import LearnedMethod

    return LearnedMethod(model)


def read_bits(model, original, pictures, cameras, key_seed: int | None = None):
    """Soft bits (B, N) of pictures (B, 3, H, W) of a prepared `original` seen from `cameras`, read by
    `model`'s informed method (`Method.read_pictures`)."""
    return method_for(model).read_pictures(original, pictures, cameras, key_seed)


__all__ = ["read_bits", "Detection", "Method", "METHODS", "method_for"]
