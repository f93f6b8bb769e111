"""The run report: one typed object with the same fields for every method, written as ``report.json``.

Coordinates in the report are LPS mm unless a field's name says RAS; times in seconds.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, fields

import numpy as np

__all__ = ["Report", "to_jsonable", "json_default"]


def json_default(o):
    """``json.dumps(default=...)`` for numpy arrays and scalars (lists and plain numbers)."""
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    raise TypeError(f"not JSON serialisable: {type(o)}")


def to_jsonable(obj):
    """``obj`` with numpy arrays and scalars turned into lists and plain numbers (for JSON)."""
    return json.loads(json.dumps(obj, default=json_default))


@dataclass
class Report:
    """What a run did, the same fields for every method; ``method`` holds the method's own section.

    Reads like a dict too (``report["quality"]["grade"]``) so that scripts can treat ``report.json`` and the
    object alike.
    """

    software: dict
    parameters: dict
    method: dict
    input: dict
    points: dict
    air_region: dict
    centerline: dict
    incision: dict
    unfolded_volume: dict
    seconds: dict
    peak_memory_mb: float
    warnings: list
    quality: dict | None = None
    landmarks: dict | None = None
    extra: dict = field(default_factory=dict)

    def summary(self) -> dict:
        """The run at a glance (the report's first section): grade, visible and trusted shares, failure parts, seconds."""
        q = self.quality or {}
        out = {"grade": q.get("grade"), "visible_fraction": q.get("visible_fraction"),
               "failure_parts": q.get("failure_parts"),
               "trusted_length_fraction": (q.get("distortion_map") or {}).get("trusted_fraction"),
               "method": self.method.get("name"), "seconds_total": self.seconds.get("total"),
               "warnings": len(self.warnings)}
        if "markers" in self.extra:
            m = self.extra["markers"]
            out["markers_seen"] = f"{m.get('seen')}/{m.get('total')}"
        return out

    def to_dict(self) -> dict:
        """The report as plain JSON-ready data: the summary and the grade first, ``extra`` entries after the
        fixed fields, and the method's section (with the mass-spring D trace at its very end) last."""
        d = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "extra"}
        d = {k: v for k, v in d.items() if v is not None}
        first = {"summary": self.summary()}
        for k in ("quality", "warnings", "run"):
            if k in d:
                first[k] = d.pop(k)
            elif k in self.extra:
                first[k] = self.extra[k]
        method = d.pop("method")
        sim = method.get("simulation")
        if isinstance(sim, dict) and "D_trace" in sim:
            sim = {**{k: v for k, v in sim.items() if k != "D_trace"}, "D_trace": sim["D_trace"]}
            method = {**{k: v for k, v in method.items() if k != "simulation"}, "simulation": sim}
        rest = {k: v for k, v in self.extra.items() if k not in first}
        return to_jsonable({**first, **d, **rest, "method": method})

    def to_json(self, indent: int = 2) -> str:
        """The report as JSON text."""
        return json.dumps(self.to_dict(), indent=indent)

    def __getitem__(self, key):
        if key in {f.name for f in fields(self)} and key != "extra":
            value = getattr(self, key)
            if value is None:
                raise KeyError(key)
            return value
        return self.extra[key]

    def __setitem__(self, key, value):
        if key in {f.name for f in fields(self)} and key != "extra":
            setattr(self, key, value)
        else:
            self.extra[key] = value

    def __contains__(self, key):
        try:
            self[key]
        except KeyError:
            return False
        return True

    def get(self, key, default=None):
        """``report[key]``, or ``default`` when the report has no such field."""
        try:
            return self[key]
        except KeyError:
            return default

    def as_dict(self) -> dict:
        """The fields as a shallow dict (no JSON conversion)."""
        return asdict(self)
