"""The 3D scene of the live view: the guideway, its sensors, the vehicle and mismatch zones.

Frames: ``line`` (x along the line from the metadata's positions, y to the left, z up, the girder's
top at z = 0) and ``vehicle`` (its origin at the vehicle reference point, moved along x by
:func:`vehicle_transform` from ``/testline/vehicle/position``). Entities are plain dicts in the
layout of foxglove.SceneEntity (``cubes`` / ``spheres`` / ``texts`` with ``position``, ``size``,
``color``), which the bridge turns into the SDK's messages. A span is drawn as the rectangle of the
same area and second moment as its design section (h = sqrt(12 I / A), b = A / h): the metadata
gives no outline, and this keeps a stiffer or heavier span visibly larger.
"""
from __future__ import annotations

import math

import numpy as np

GREY = (0.62, 0.64, 0.68, 1.0)
SENSOR = (0.15, 0.55, 0.95, 1.0)
BODY = (0.92, 0.92, 0.95, 0.55)
MAGNET = (0.95, 0.6, 0.1, 1.0)
MISMATCH = (0.9, 0.1, 0.1, 0.35)
TEXT = (1.0, 1.0, 1.0, 1.0)
SPAN_JOINT_M = 0.05            # drawn gap between neighbouring spans
MISMATCH_SHOWN = 5             # mismatch zones kept in the scene (the newest)
VEHICLE_HEIGHT_M = 3.0
VEHICLE_WIDTH_M = 3.7
MAGNET_SIZE_M = (1.2, 0.4, 0.2)


def _cube(x, y, z, sx, sy, sz, color) -> dict:
    return {"position": [float(x), float(y), float(z)], "size": [float(sx), float(sy), float(sz)],
            "color": list(color)}


def _text(x, y, z, text, size=0.6) -> dict:
    return {"position": [float(x), float(y), float(z)], "text": str(text), "font_size": float(size),
            "color": list(TEXT)}


def girder_section_m(area_m2: float, second_moment_m4: float) -> tuple[float, float]:
    """(width, height) of the rectangle with this area and second moment (module docstring)."""
    h = math.sqrt(12.0 * second_moment_m4 / area_m2)
    return area_m2 / h, h


def _spans(metadata: dict):
    """The spans with their guideway properties (design block over the twin's defaults; only the
    guideway part is read, so a vehicle the scene does not need cannot stop the drawing)."""
    from maglev_ros.twin.design import line_spans, twin_config
    design = metadata.get("design") if isinstance(metadata.get("design"), dict) else {}
    return line_spans(metadata.get("line"), twin_config({"guideway": design.get("guideway") or {}}))


def girder_width_m(metadata: dict) -> float:
    spans = _spans(metadata)
    return max(girder_section_m(s.props.area_m2, s.props.second_moment_m4)[0] for s in spans)


def line_entities(metadata: dict) -> list[dict]:
    """One entity per span (box + label) and one for the guideway sensors (spheres + labels)."""
    out = []
    for s in _spans(metadata):
        b, h = girder_section_m(s.props.area_m2, s.props.second_moment_m4)
        out.append({"id": f"span/{s.span_id}", "frame_id": "line", "frame_locked": False,
                    "cubes": [_cube(s.start_m + s.length_m / 2, 0.0, -h / 2,
                                    max(s.length_m - SPAN_JOINT_M, 0.01), b, h, GREY)],
                    "texts": [_text(s.start_m + s.length_m / 2, 0.0, -h - 0.6, s.span_id)]})
    b = girder_width_m(metadata)
    side_y = {"left": b / 2, "right": -b / 2, "center": 0.0}
    spheres, texts = [], []
    for sid, sen in (metadata.get("sensors") or {}).items():
        if isinstance(sen, dict) and sen.get("position_m") is not None:
            y = side_y.get(sen.get("side"), 0.0)
            spheres.append(_cube(sen["position_m"], y, 0.15, 0.3, 0.3, 0.3, SENSOR))
            texts.append(_text(sen["position_m"], y, 0.7, sid, 0.35))
    if spheres:
        out.append({"id": "sensors", "frame_id": "line", "frame_locked": False, "spheres": spheres,
                    "texts": texts})
    return out


def vehicle_entities(metadata: dict) -> list[dict]:
    """The vehicle in its own frame: a body over its magnets and one box per magnet (labelled)."""
    offsets = [float(x) for x in ((metadata.get("vehicle") or {}).get("magnet_offsets_m") or [])]
    if not offsets:
        return []
    pitch = min((abs(a - b) for a, b in zip(offsets, offsets[1:]) if a != b), default=1.5)
    lo, hi = min(offsets) - pitch / 2, max(offsets) + pitch / 2
    cubes = [_cube((lo + hi) / 2, 0.0, 0.4 + VEHICLE_HEIGHT_M / 2, hi - lo, VEHICLE_WIDTH_M,
                   VEHICLE_HEIGHT_M, BODY)]
    texts = []
    for k, x in enumerate(offsets, start=1):
        cubes.append(_cube(x, 0.0, 0.2, *MAGNET_SIZE_M, MAGNET))
        texts.append(_text(x, 0.0, 0.55, f"M{k}", 0.3))
    return [{"id": "vehicle", "frame_id": "vehicle", "frame_locked": True, "cubes": cubes, "texts": texts}]


def vehicle_transform(t_ns: int, x_m: float) -> dict:
    """The ``line`` -> ``vehicle`` transform with the vehicle reference point at ``x_m``."""
    return {"timestamp_ns": int(t_ns), "parent_frame_id": "line", "child_frame_id": "vehicle",
            "translation": [float(x_m), 0.0, 0.0], "rotation": [0.0, 0.0, 0.0, 1.0]}


def transform_samples(t_ns: np.ndarray, period_ns: int, last_slot: int | None) -> tuple[np.ndarray, int | None]:
    """Indices of the samples that move the vehicle: the first sample of each ``period_ns`` slot
    of stream time later than ``last_slot`` (the slot of the last one sent), or over a second
    earlier (the stream started again: a loop, a new recording). Returns the indices and the new
    last slot. Exact samples, not averages: the scene shows where the vehicle was."""
    slots = np.asarray(t_ns, np.int64) // int(period_ns)
    idx = []
    back = max(1, int(1e9 // period_ns))
    for i in np.flatnonzero(np.r_[True, slots[1:] != slots[:-1]] if slots.size else []):
        s = int(slots[i])
        if last_slot is None or s > last_slot or s < last_slot - back:
            idx.append(int(i))
            last_slot = s
    return np.asarray(idx, int), last_slot


def mismatch_entity(message: dict, index: int, girder_width: float = 2.0) -> dict | None:
    """A translucent box over a mismatch's stretch of line (None when it has no position), labelled
    with the effect (or the channels) and the severity; ids cycle over :data:`MISMATCH_SHOWN`."""
    a, b = message.get("position_start_m"), message.get("position_end_m")
    if a is None or b is None or not (math.isfinite(a) and math.isfinite(b)):
        return None
    a, b = min(a, b), max(a, b)
    length = max(b - a, 0.5)
    label = message.get("effect") or " ".join(message.get("channels", [])[:4])
    sev = message.get("severity")
    if sev is not None:
        label += f" ({sev:.3g}x)"
    return {"id": f"mismatch/{index % MISMATCH_SHOWN}", "frame_id": "line", "frame_locked": False,
            "cubes": [_cube((a + b) / 2, 0.0, 1.0, length, girder_width + 0.6, 2.0, MISMATCH)],
            "texts": [_text((a + b) / 2, 0.0, 2.4, label, 0.45)]}


def grid_origin_m(x0_m: float, girder_width: float, group_index: int, n_bands: int,
                  band_height_m: float) -> tuple[float, float]:
    """(x, y) of a residual map grid's corner: flat beside the line (to its right), one strip per
    group, its columns along x on the map's position bins."""
    strip = n_bands * band_height_m + 0.5
    return float(x0_m), -girder_width / 2 - 1.0 - (group_index + 1) * strip
