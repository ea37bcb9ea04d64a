"""Argument types and helpers shared by the subcommands."""

from __future__ import annotations

import argparse
import math

from ..threads import available_cores  # noqa: F401 (the subcommands import it from here)


def vector3(text: str) -> tuple[float, float, float]:
    """'X,Y,Z' -> three finite floats (argparse type)."""
    parts = [p.strip() for p in text.replace(" ", ",").split(",") if p.strip()]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != 3 or not all(math.isfinite(v) for v in values):
        raise argparse.ArgumentTypeError(f"expected three numbers X,Y,Z, got '{text}'")
    return values  # type: ignore[return-value]


def colour(text: str) -> tuple[float, float, float]:
    """'R,G,B' in [0, 1] (or 0-255 integers) -> three floats in [0, 1] (argparse type)."""
    try:
        values = vector3(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected a colour R,G,B in [0, 1], got '{text}'") from None
    if any(v > 1.0 for v in values) and all(float(v).is_integer() and 0 <= v <= 255 for v in values):
        values = tuple(v / 255.0 for v in values)
    if not all(0.0 <= v <= 1.0 for v in values):
        raise argparse.ArgumentTypeError(f"colour components must be in [0, 1] (or 0-255), got '{text}'")
    return values  # type: ignore[return-value]




def positive_int(limit: int, minimum: int = 1):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a whole number, got '{text}'") from None
        if not minimum <= value <= limit:
            raise argparse.ArgumentTypeError(f"must be between {minimum} and {limit}, got {value}")
        return value
    return parse

