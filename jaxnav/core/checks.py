"""Validation shared by the config dataclasses."""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable


def require_finite(config, label: Callable[[str], str] | None = None) -> None:
    """Raises ValueError naming the first float field (or number in a tuple field) that is NaN or
    infinite. Run it first in `__post_init__`: NaN passes every range comparison."""
    label = label or (lambda name: f"{type(config).__name__}.{name}")
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        values = value if isinstance(value, tuple) else (value,)
        numbers = [v for v in values if isinstance(v, float)]
        if not all(math.isfinite(v) for v in numbers):
            raise ValueError(f"{label(f.name)}: must be finite, got {value}")
