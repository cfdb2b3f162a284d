"""Aggregates of a fused result's results, weighted by how much of the window each covers.

- SSL: the talker's direction: of the tracked sources heard within the window, the heaviest one
  not marked background, and the circular mean of its directions' azimuths (never an arithmetic
  mean of angles, which would put 350° and 10° at 180°), each weighted by its result's overlap
  with the window times the direction's probability (0, i.e. unset, counts as 1);
- labels (emotion, gender, voice_id, and any other kind whose results have labels): the
  overlap-weighted distribution over labels (a result's ``class_probabilities``, or its
  ``label`` alone if it has none; for voice_id its label with its probability, the rest
  "unknown") and its top label;
- values (any other kind whose results carry a number): the overlap-weighted mean value.
"""
from __future__ import annotations

import math
from collections.abc import Iterable
from typing import Any

from esiaf.results import LABEL_PAYLOADS, RESULT_TYPES

LABEL_TYPES = LABEL_PAYLOADS  # emotion, gender, voice_id: derived from the proto


def overlap_ns(start_ns: int, end_ns: int, w_start_ns: int, w_end_ns: int) -> int:
    return max(0, min(end_ns, w_end_ns) - max(start_ns, w_start_ns))


def overlaps(start_ns: int, end_ns: int, w_start_ns: int, w_end_ns: int) -> bool:
    """Spans overlap at all; a zero-length span overlaps what contains it (ends included)."""
    if start_ns == end_ns or w_start_ns == w_end_ns:
        return start_ns <= w_end_ns and w_start_ns <= end_ns
    return start_ns < w_end_ns and w_start_ns < end_ns


def _weight(result: dict[str, Any], window: tuple[int, int]) -> float:
    span = result["span"]
    if window[0] == window[1]:
        return 1.0
    return overlap_ns(span["start_ns"], span["end_ns"], *window) / 1e9


def ssl_aggregate(results: Iterable[dict[str, Any]],
                  window: tuple[int, int]) -> dict[str, Any] | None:
    """``{"azimuth_deg", "elevation_deg", "concentration", "overlap_s", "directions", "source_id",
    "background", "tracks"}`` or None without directions.

    The directions are grouped by the tracked source they belong to (``source_id``); the
    utterance's direction is that of the talker's track: of the tracks not marked background
    (loudspeakers, a TV), the one with the most weight within the window (overlap × probability).
    Only where every track is background is the heaviest background track taken. ``concentration``
    is the mean resultant length of that track's directions: 1 when they agree, near 0 when they
    cancel out; ``tracks`` how many tracks were heard within the window."""
    groups: dict[str, list[float]] = {}  # source id -> [sin, cos, elevation, weight, count, background]
    overlap_total = 0.0
    for result in results:
        weight = _weight(result, window)
        directions = result.get("ssl", {}).get("directions", [])
        if directions:
            overlap_total += weight
        for direction in directions:
            w = weight * (direction["probability"] or 1.0)
            azimuth = math.radians(direction["azimuth_deg"])
            group = groups.setdefault(direction.get("source_id", ""), [0.0, 0.0, 0.0, 0.0, 0, False])
            group[0] += w * math.sin(azimuth)
            group[1] += w * math.cos(azimuth)
            group[2] += w * direction["elevation_deg"]
            group[3] += w
            group[4] += 1
            group[5] = group[5] or bool(direction.get("background"))
    candidates = [(key, g) for key, g in groups.items() if g[3] > 0]
    talkers = [(key, g) for key, g in candidates if not g[5]] or candidates
    if not talkers:
        return None
    source_id, (sin_sum, cos_sum, elevation_sum, total, count, background) = max(talkers, key=lambda kg: kg[1][3])
    return {"azimuth_deg": round(math.degrees(math.atan2(sin_sum, cos_sum)) % 360.0, 6),
            "elevation_deg": round(elevation_sum / total, 6),
            "concentration": round(math.hypot(sin_sum, cos_sum) / total, 6),
            "overlap_s": round(overlap_total, 9), "directions": int(count), "source_id": source_id,
            "background": bool(background), "tracks": len(candidates)}


def label_aggregate(results: Iterable[dict[str, Any]], type_name: str,
                    window: tuple[int, int]) -> dict[str, Any] | None:
    """``{"label", "probability", "distribution", "overlap_s"}`` or None without labels."""
    mass: dict[str, float] = {}
    overlap_total = 0.0
    for result in results:
        payload = result.get(type_name)
        if not payload:
            continue
        weight = _weight(result, window)
        if not payload.get("class_probabilities") and not payload.get("label"):
            continue  # a generic result with a value but no label
        classes = payload.get("class_probabilities") or {payload["label"]: 1.0}
        if type_name == "voice_id":  # its class_probabilities are every enrolled voice's cosine score
            p = payload.get("probability", 1.0)
            classes = {payload["label"]: p}  # "unknown" itself for a segment under the voiceid's quality gate
            classes["unknown"] = classes.get("unknown", 0.0) + 1.0 - p
        norm = sum(classes.values())
        if norm <= 0:
            continue
        overlap_total += weight
        for label, probability in classes.items():
            mass[label] = mass.get(label, 0.0) + weight * probability / norm
    total = sum(mass.values())
    if total <= 0:
        return None
    distribution = {label: round(value / total, 6)
                    for label, value in sorted(mass.items(), key=lambda kv: (-kv[1], kv[0]))}
    top = next(iter(distribution))
    return {"label": top, "probability": distribution[top], "distribution": distribution,
            "overlap_s": round(overlap_total, 9)}


def value_aggregate(results: Iterable[dict[str, Any]], type_name: str,
                    window: tuple[int, int]) -> dict[str, Any] | None:
    """``{"value", "overlap_s", "results"}``: the overlap-weighted mean of the results' values
    (each result's weight at least a nanosecond's, so instants count), or None without values."""
    weighted = total = overlap_total = 0.0
    count = 0
    for result in results:
        payload = result.get(type_name) or {}
        if not payload.get("has_value"):
            continue
        weight = max(_weight(result, window), 1e-9)
        weighted += weight * payload["value"]
        total += weight
        overlap_total += _weight(result, window)
        count += 1
    if count == 0:
        return None
    return {"value": round(weighted / total, 9), "overlap_s": round(overlap_total, 9), "results": count}


def generic_aggregate(results: list[dict[str, Any]], type_name: str,
                      window: tuple[int, int]) -> dict[str, Any] | None:
    """A kind that is not built in: its label distribution where its results have labels, the
    mean of their values where they have values (both, where both)."""
    labels = label_aggregate(results, type_name, window)
    values = value_aggregate(results, type_name, window)
    either = labels or values
    if either is None:
        return None
    return {**(labels or {}), **({"value": values["value"]} if values else {}), "overlap_s": either["overlap_s"]}


def aggregates(results: dict[str, list[dict[str, Any]]],
               window: tuple[int, int]) -> dict[str, Any]:
    """One aggregate per fused kind that has one (ssl, the label kinds, every kind that is not
    built in), None if empty."""
    out: dict[str, Any] = {}
    for type_name, items in results.items():
        if type_name == "ssl":
            out[type_name] = ssl_aggregate(items, window)
        elif type_name in LABEL_TYPES:
            out[type_name] = label_aggregate(items, type_name, window)
        elif type_name not in RESULT_TYPES:
            out[type_name] = generic_aggregate(items, type_name, window)
    return out
