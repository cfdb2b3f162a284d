"""Which format travels on a topic: the internal format, chosen among the declared ones.

Every producer and consumer of a topic declares the format it works in (its
external format). A declaration whose format differs from the topic's
internal format costs one conversion, in that component's SDK. Strategies:

- ``min_bandwidth``: the cheapest declared format, cost = channels × bits per
  sample × rate (bits per second); ties broken by fewer conversions;
- ``min_conversions``: the declared format that the fewest declarations differ
  from (formats compared by value: rate, sample type, endianness, channels);
  ties broken by ``min_bandwidth``.

Remaining ties keep the topic's current format (no needless switch), then
prefer a producer's format, then the earliest declaration. Pure functions, no
state: the registry calls :func:`choose` on every registration and death.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

Format = dict[str, Any]  # {"sample_rate_hz", "sample_type", "endianness", "channels"}
Strategy = Literal["min_conversions", "min_bandwidth"]
STRATEGIES: tuple[str, ...] = ("min_conversions", "min_bandwidth")

_BITS = {"int8": 8, "uint8": 8, "int16": 16, "uint16": 16, "int24": 24, "uint24": 24,
         "int32": 32, "uint32": 32, "float32": 32, "float64": 64}


@dataclass(frozen=True)
class Declaration:
    """One component's format on one topic, as a producer or as a consumer."""

    component: str
    role: Literal["producer", "consumer"]
    format: Format


def key(fmt: Format) -> tuple:
    return (fmt["sample_rate_hz"], fmt["sample_type"], fmt["endianness"], fmt["channels"])


def bits_per_second(fmt: Format) -> int:
    return fmt["channels"] * _BITS[fmt["sample_type"]] * fmt["sample_rate_hz"]


def bytes_per_second(fmt: Format) -> int:
    return bits_per_second(fmt) // 8


def conversions(declarations: list[Declaration], fmt: Format) -> int:
    """How many declarations differ from ``fmt``: each is one conversion in one component."""
    return sum(key(d.format) != key(fmt) for d in declarations)


def choose(declarations: list[Declaration], strategy: Strategy, current: Format | None = None) -> Format:
    """The internal format of a topic with these declarations (in declaration order)."""
    if not declarations:
        raise ValueError("a topic without declarations has no format")
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown format strategy {strategy!r}; known: {', '.join(STRATEGIES)}")
    candidates: dict[tuple, tuple[int, Format]] = {}
    for order, declaration in enumerate(declarations):
        candidates.setdefault(key(declaration.format), (order, declaration.format))
    producer_formats = {key(d.format) for d in declarations if d.role == "producer"}

    def rank(candidate: tuple) -> tuple:
        order, fmt = candidates[candidate]
        costs = (conversions(declarations, fmt), bits_per_second(fmt))
        if strategy == "min_bandwidth":
            costs = costs[::-1]
        keeps_current = current is not None and key(current) == candidate
        return (*costs, not keeps_current, candidate not in producer_formats, order)

    return candidates[min(candidates, key=rank)][1]
