"""The numbers the README and docs quote for parameters are the code's defaults (read from the code, not copied)."""
import os
import re

import pytest

from StomachUnfoldLib.params import DEFAULT_CELL_MM, DEFAULT_METHOD, parameter_specs
from StomachUnfoldLib.quality import GRADE_THRESHOLDS

ROOT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "..")
DOCS = ["README.md", "docs/slicer.md"]


def text(name):
    with open(os.path.join(ROOT, name), encoding="utf-8") as f:
        return f.read()


def quoted_defaults(doc: str):
    """(parameter name, number) pairs the text states as a default: "`name` (N)", "`--flag`, default N", "`--flag N`"."""
    pats = [r"`([a-z_]+)` \((-?[0-9.]+)\)", r"`--([a-z-]+)`, default (-?[0-9.]+)", r"`--([a-z-]+) (-?[0-9.]+)`"]
    for p in pats:
        for m in re.finditer(p, doc):
            yield m.group(1).replace("-", "_"), float(m.group(2).rstrip("."))


@pytest.mark.parametrize("name", DOCS)
def test_quoted_parameter_defaults_are_the_codes(name):
    specs = {s.name: s for s in parameter_specs()}
    code = {n: s.default for n, s in specs.items()}
    code["grid_mm"] = DEFAULT_CELL_MM  # its spec default is None: "from DEFAULT_CELL_MM"
    found = [(n, v) for n, v in quoted_defaults(text(name)) if n in code]
    for n, v in found:
        assert code[n] is not None and float(code[n]) == v, f"{name} says {n} = {v:g}, the code's default is {code[n]}"
    if name == "README.md":
        assert {n for n, _ in found} >= {"fluid_max_hu", "ramp_iterations", "flattening_stiffness", "grid_mm"}


def test_readme_default_method_and_grade_table():
    doc = text("README.md")
    assert re.search(rf"\| `{DEFAULT_METHOD}` \(default\) \|", doc)
    assert f"cells of {DEFAULT_CELL_MM:g} mm" in text("docs/slicer.md") or f"{DEFAULT_CELL_MM:g} mm" in text("docs/slicer.md")
    for grade, t in GRADE_THRESHOLDS.items():
        row = re.search(rf"^\| {grade} \| (at most|over) ([0-9.]+) % \| (none|at most one|any) \|$", doc, re.M)
        assert row, grade
        assert float(row.group(2)) == pytest.approx(100 * t["max_hidden"] if row.group(1) == "at most"
                                                    else 100 * GRADE_THRESHOLDS["fair"]["max_hidden"])
        parts = {"none": 0, "at most one": 1}.get(row.group(3))
        if parts is not None:
            assert t.get("max_failure_parts") == parts
    for name in DOCS:
        m = re.search(r"default `([a-z]+)`", text(name))
        if m and "method" in text(name)[max(0, m.start() - 40):m.start()].lower():
            assert m.group(1) == DEFAULT_METHOD, name
