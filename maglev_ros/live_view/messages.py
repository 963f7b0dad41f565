"""The graph's results as display messages (JSON-able dicts; NaN and inf become null).

Inputs are plain dicts with the ROS messages' field names (the bridge converts each message), so
these functions are tested without ROS. Parameter names are the twin's dotted design paths
(``levitation.kp_a_per_m``); ``values`` / ``std`` nest them by the dots, so a plot path reads
``/maglev/view/parameters.values.levitation.kp_a_per_m``.
"""
from __future__ import annotations

import json
import math
import warnings

import numpy as np

from maglev_ros.updating.parameters import GUIDEWAY_PARAMS, MAGNET_PARAMS

MAX_PROFILE_POINTS = 4000     # irregularity samples per message (more: means of consecutive samples)
MISMATCH_LOG_LENGTH = 200     # events kept in the mismatch log


def jsonable(obj):
    """``obj`` with every non-finite float as None and numpy scalars / arrays as Python ones."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return [jsonable(v) for v in obj.tolist()]
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def stamp_s(msg: dict) -> float:
    """Header stamp of a converted message [s] (0 without one)."""
    st = (msg.get("header") or {}).get("stamp") or {}
    return float(st.get("sec", 0)) + float(st.get("nanosec", 0)) * 1e-9


def _parse_json(text: str):
    try:
        return json.loads(text) if text else None
    except (json.JSONDecodeError, RecursionError):
        return {"text": text}


# ----------------------------------------------------------------------------------- modes
def modes_message(est: dict) -> dict:
    """A ModalEstimate: its modes, and ``frequency_hz`` / ``damping_ratio`` keyed by mode id (a
    plot path per tracked mode: ``.frequency_hz.M1``)."""
    modes = []
    for m in est.get("modes", []):
        modes.append({"id": m.get("id", ""), "status": m.get("status", ""),
                      "frequency_hz": m.get("frequency_hz"), "damping_ratio": m.get("damping_ratio"),
                      "std_frequency_hz": m.get("std_frequency_hz"),
                      "std_damping_ratio": m.get("std_damping_ratio"), "mpc": m.get("mpc"),
                      "shape": dict(zip(m.get("channels", []), m.get("mode_shape", [])))})
    live = [m for m in modes if m["status"] != "lost"]
    return jsonable({"t_s": stamp_s(est), "method": est.get("method", ""), "window_s": est.get("window_s"),
                     "modes": modes, "frequency_hz": {m["id"]: m["frequency_hz"] for m in live},
                     "damping_ratio": {m["id"]: m["damping_ratio"] for m in live}})


def modes_schema() -> dict:
    """Schema of :func:`modes_message` (mode ids M1-M12 named: they appear as modes are found)."""
    mode = {"id": "M1", "status": "new", "frequency_hz": 1.0, "damping_ratio": 0.01, "std_frequency_hz": 0.1,
            "std_damping_ratio": 0.1, "mpc": 1.0, "channels": [], "mode_shape": []}
    s = infer_schema(modes_message({"header": {}, "method": "", "window_s": 1.0, "modes": [mode]}), "maglev.view.Modes")
    ids = {"type": "object", "properties": {f"M{i}": {"type": "number"} for i in range(1, 13)}}
    s["properties"]["frequency_hz"] = s["properties"]["damping_ratio"] = ids
    s["properties"]["modes"]["items"]["properties"]["shape"] = {"type": "object"}
    return s


class ModeHistory:
    """Every mode id seen so far: first / last time, updates, latest status, frequency (latest,
    lowest, highest) and damping (latest); a table sorted by frequency."""

    def __init__(self) -> None:
        self.rows: dict[str, dict] = {}

    def add(self, message: dict) -> dict:
        t = message["t_s"]
        for m in message["modes"]:
            f = m["frequency_hz"]
            r = self.rows.setdefault(m["id"], {"id": m["id"], "first_t_s": t, "updates": 0,
                                               "frequency_min_hz": f, "frequency_max_hz": f})
            r.update(last_t_s=t, status=m["status"], frequency_hz=f, damping_ratio=m["damping_ratio"])
            r["updates"] += 1
            if f is not None:
                r["frequency_min_hz"] = f if r["frequency_min_hz"] is None else min(r["frequency_min_hz"], f)
                r["frequency_max_hz"] = f if r["frequency_max_hz"] is None else max(r["frequency_max_hz"], f)
        return self.message(t)

    def message(self, t_s: float = 0.0) -> dict:
        rows = sorted(self.rows.values(), key=lambda r: (r["frequency_hz"] is None, r["frequency_hz"] or 0.0))
        return jsonable({"t_s": t_s, "modes": rows})


# -------------------------------------------------------------------------------- mismatch
MISMATCH_FIELDS = ("t0_s", "t1_s", "position_start_m", "position_end_m", "f0_hz", "f1_hz", "severity",
                   "effect", "category", "explanation")


def mismatch_message(report: dict) -> dict:
    """A MismatchReport: its fields, ``channels`` and ``detail`` (detail_json parsed)."""
    out = {"t_s": stamp_s(report), "channels": list(report.get("channels", []))}
    out.update({k: report.get(k) for k in MISMATCH_FIELDS})
    out["detail"] = _parse_json(report.get("detail_json", ""))
    return jsonable(out)


def mismatch_schema() -> dict:
    """Schema of :func:`mismatch_message` (``detail`` is free JSON)."""
    s = infer_schema(mismatch_message({"channels": ["M1A"], **{k: 1.0 for k in MISMATCH_FIELDS[:7]},
                                       **{k: "" for k in MISMATCH_FIELDS[7:]}}), "maglev.view.Mismatch")
    s["properties"]["detail"] = {"type": "object"}
    return s


class MismatchLog:
    """The last ``MISMATCH_LOG_LENGTH`` mismatch events as table rows (newest first)."""

    def __init__(self, length: int = MISMATCH_LOG_LENGTH) -> None:
        self.rows: list[dict] = []
        self.length = int(length)

    def add(self, message: dict) -> dict:
        row = {k: message.get(k) for k in ("t_s", *MISMATCH_FIELDS)}
        row["channels"] = " ".join(message.get("channels", []))
        self.rows = [row] + self.rows[: self.length - 1]
        return self.message()

    def message(self) -> dict:
        return jsonable({"t_s": self.rows[0]["t_s"] if self.rows else 0.0, "count": len(self.rows),
                         "events": self.rows})


def diagnosis_message(text: str) -> dict:
    """The /maglev/diagnosis report (maglev-diagnosis/1 JSON) as is, plus ``summary``: one row per
    missing-physics entry (name, category, the entry's scalar fields)."""
    doc = _parse_json(text)
    if not isinstance(doc, dict):
        doc = {"text": text}
    rows = []
    for e in doc.get("missing_physics") or []:
        if isinstance(e, dict):
            rows.append({k: v for k, v in e.items() if isinstance(v, (str, int, float, bool)) or v is None})
    return jsonable({**doc, "summary": rows})


# ------------------------------------------------------------------------------ parameters
def _nest(names, values) -> dict:
    out: dict = {}
    for name, v in zip(names, values):
        node = out
        parts = str(name).split(".")
        for p in parts[:-1]:
            nxt = node.setdefault(p, {})
            if not isinstance(nxt, dict):          # a leaf and a branch of one name: keep the leaf
                nxt = node[p] = {"value": nxt}
            node = nxt
        node[parts[-1]] = v
    return out


def parameters_message(params: dict, t_s: float) -> dict:
    """TwinParameters: ``revision``, ``values`` / ``std`` nested by the names' dots, a ``table``
    (name, value, unit, std, identifiable) and ``provenance`` (provenance_json parsed)."""
    names = list(params.get("names", []))
    values = list(params.get("values", []))
    std = list(params.get("std", []))
    units = list(params.get("units", []))
    ident = list(params.get("identifiable", []))
    n = len(names)
    std += [float("nan")] * (n - len(std))
    units += [""] * (n - len(units))
    ident += [False] * (n - len(ident))
    table = [{"name": names[i], "value": values[i], "unit": units[i], "std": std[i],
              "identifiable": bool(ident[i])} for i in range(n)]
    return jsonable({"t_s": t_s, "revision": params.get("revision", 0), "values": _nest(names, values),
                     "std": _nest(names, std), "table": table,
                     "provenance": _parse_json(params.get("provenance_json", ""))})


# ---------------------------------------------------------------------------- irregularity
def profile_points(start_m: float, spacing_m: float, values, max_points: int = MAX_PROFILE_POINTS):
    """(position_m, values) of an even-grid profile, at most ``max_points``: beyond that the means
    of ``ceil(n / max_points)`` consecutive samples (and of their positions). NaN-aware."""
    v = np.asarray(values, float)
    x = float(start_m) + float(spacing_m) * np.arange(v.size)
    m = int(math.ceil(v.size / max_points)) if v.size > max_points else 1
    if m == 1:
        return x, v
    n = (v.size // m) * m
    groups = [v[:n].reshape(-1, m)] + ([v[n:][None, :]] if n < v.size else [])
    xs = [x[:n].reshape(-1, m)] + ([x[n:][None, :]] if n < v.size else [])
    with warnings.catch_warnings():               # an all-NaN group (no valid sample) is NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        vv = np.concatenate([np.nanmean(g, axis=1) for g in groups])
    return np.concatenate([g.mean(axis=1) for g in xs]), vv


def irregularity_message(prof: dict) -> dict:
    """IrregularityProfile with ``position_m`` beside ``irregularity_m`` (and ``std_m`` when given),
    thinned to :data:`MAX_PROFILE_POINTS`; plot ``irregularity_m[:]`` against ``position_m[:]``."""
    start, step = float(prof.get("start_position_m", 0.0)), float(prof.get("spacing_m", 0.0) or 0.0)
    x, v = profile_points(start, step, prof.get("irregularity_m", []))
    std = prof.get("std_m", [])
    s = profile_points(start, step, std)[1] if len(std) == len(prof.get("irregularity_m", [])) and len(std) else []
    return jsonable({"t_s": stamp_s(prof), "kind": prof.get("kind", ""), "start_position_m": start,
                     "spacing_m": step, "min_wavelength_m": prof.get("min_wavelength_m"),
                     "max_wavelength_m": prof.get("max_wavelength_m"), "sources": list(prof.get("sources", [])),
                     "points": int(len(v)), "position_m": x, "irregularity_m": v, "std_m": s})


def infer_schema(obj, title: str | None = None) -> dict:
    """A JSON schema of a message's shape (from an example), named ``title``: the app reads its
    fields from it (message-path completion). Numbers may be null in messages (NaN)."""
    if isinstance(obj, dict):
        out = {"type": "object", "properties": {str(k): infer_schema(v) for k, v in obj.items()}}
    elif isinstance(obj, list):
        first = next((v for v in obj if v is not None), None)
        out = {"type": "array", "items": infer_schema(first) if first is not None else {}}
    elif isinstance(obj, bool):
        out = {"type": "boolean"}
    elif isinstance(obj, int):
        out = {"type": "integer"}
    elif isinstance(obj, float):
        out = {"type": "number"}
    elif isinstance(obj, str):
        out = {"type": "string"}
    else:
        out = {}
    if title is not None:
        out = {"title": title, **out}
    return out


# ------------------------------------------------------------------------------- schemas
# the names the updater publishes (updating.pipeline.TWIN_NAMES; a test keeps the two equal)
PARAMETER_NAMES = (tuple(f"guideway.{n}" for n in GUIDEWAY_PARAMS)
                   + tuple(f"levitation.{n}" for n in MAGNET_PARAMS) + ("levitation.static_current_a",))


def parameters_schema(names=PARAMETER_NAMES) -> dict:
    n = len(names)
    s = infer_schema(parameters_message({"revision": 1, "names": list(names), "values": [1.0] * n,
                                         "units": [""] * n, "std": [1.0] * n, "identifiable": [True] * n}, 0.0),
                     "maglev.view.Parameters")
    s["properties"]["provenance"] = {"type": "object"}
    return s


def mode_history_schema() -> dict:
    h = ModeHistory()
    h.add(modes_message({"modes": [{"id": "M1", "status": "new", "frequency_hz": 1.0, "damping_ratio": 0.1}]}))
    return infer_schema(h.message(0.0), "maglev.view.ModeHistory")


def mismatch_log_schema() -> dict:
    log = MismatchLog()
    return infer_schema(log.add(mismatch_message({"channels": ["M1A"], **{k: 1.0 for k in MISMATCH_FIELDS[:7]},
                                                  **{k: "" for k in MISMATCH_FIELDS[7:]}})),
                        "maglev.view.MismatchLog")


def irregularity_schema() -> dict:
    return infer_schema(irregularity_message({"header": {}, "start_position_m": 0.0, "spacing_m": 1.0,
                                              "irregularity_m": [1.0], "std_m": [1.0], "min_wavelength_m": 1.0,
                                              "max_wavelength_m": 1.0, "kind": "", "sources": [""]}),
                        "maglev.view.Irregularity")


def diagnosis_schema() -> dict:
    """The report's keys vary; ``summary`` is a table of objects."""
    return {"title": "maglev.view.Diagnosis", "type": "object",
            "properties": {"summary": {"type": "array", "items": {"type": "object"}}}}


def metadata_schema() -> dict:
    """The recording's metadata document (the contract's, unknown keys allowed)."""
    return {"title": "maglev.view.Metadata", "type": "object",
            "properties": {"schema": {"type": "string"}, "description": {"type": "string"},
                           "line": {"type": "object"}, "sensors": {"type": "object"},
                           "vehicle": {"type": "object"}, "run": {"type": "object"}, "design": {"type": "object"}}}
