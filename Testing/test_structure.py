"""The shape of the code (issue 7): method-only core, pluggable methods, parameters defined once, no drift.

Each test reads the source or the registry and fails when the structure drifts: a core function grows past
120 lines, a private name is imported across modules, the incision sides or a parameter default are written
twice, the command line or the Slicer module disagree with ``params.parameter_specs``, or the extension's
CMake list and the core's files part ways.
"""
import ast
import glob
import os
import re

import pytest

from StomachUnfoldLib.cli import build_parser
from StomachUnfoldLib.methods import Method, Unfolding, get_method, method_names, register
from StomachUnfoldLib.params import UnfoldParameters, parameter_specs

from conftest import REPO

CORE = os.path.join(REPO, "StomachUnfoldLib")


def _py(folder):
    return sorted(glob.glob(os.path.join(folder, "**", "*.py"), recursive=True))


def _functions(path):
    tree = ast.parse(open(path).read())
    return [n for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))]


def test_no_core_function_over_120_lines_and_unfold_at_most_60():
    long = [f"{os.path.relpath(p, REPO)}:{n.name} ({n.end_lineno - n.lineno + 1})" for p in _py(CORE)
            for n in _functions(p) if n.end_lineno - n.lineno + 1 > 120]
    assert not long, long
    unfold = [n for n in _functions(os.path.join(CORE, "pipeline.py")) if n.name == "unfold"][0]
    assert unfold.end_lineno - unfold.lineno + 1 <= 60


@pytest.mark.parametrize("folder", ["StomachUnfoldLib", "StomachUnfoldEval", "StomachUnfold", "Testing"])
def test_no_private_name_is_imported_from_another_module(folder):
    bad = []
    for path in _py(os.path.join(REPO, folder)):
        for node in ast.walk(ast.parse(open(path).read())):
            if isinstance(node, ast.ImportFrom) and node.module != "__future__":
                bad += [f"{os.path.relpath(path, REPO)}: {node.module}.{a.name}" for a in node.names
                        if a.name.startswith("_") and not a.name.startswith("__")]
    assert not bad, bad


def test_the_core_imports_no_evaluation_plotting_or_progress_bar_package():
    pattern = re.compile(r"^\s*(from|import)\s+(StomachUnfoldEval|matplotlib|dask|tqdm|skimage|qt|slicer)\b", re.M)
    # the command line (not shipped in the extension) reaches the evaluation package for `phantom` and `bench`
    hits = [os.path.relpath(p, REPO) for p in _py(CORE) if pattern.search(open(p).read())
            and not p.endswith("cli.py")]
    assert not hits, hits


def test_incision_sides_are_listed_once():
    literal = re.compile(r'"greater",\s*"lesser",\s*"anterior",\s*"posterior"')
    places = [os.path.relpath(p, REPO) for folder in ("StomachUnfoldLib", "StomachUnfoldEval", "StomachUnfold")
              for p in _py(os.path.join(REPO, folder)) if literal.search(open(p).read())]
    assert places == [os.path.join("StomachUnfoldLib", "params.py")], places
    with pytest.raises(Exception, match="incision must be one of"):
        UnfoldParameters(incision="user").validate()


def test_each_parameter_has_one_default_and_the_command_line_follows_it():
    specs = parameter_specs()
    names = [s.name for s in specs]
    assert len(names) == len(set(names))
    unfold = build_parser()._subparsers._group_actions[0].choices["unfold"]
    actions = {a.dest: a for a in unfold._actions}
    for s in specs:
        a = actions[s.name]
        # booleans as --flag/--no-flag
        assert a.option_strings == ([s.flag, "--no-" + s.flag[2:]] if s.kind is bool else [s.flag])
        assert a.default == s.default, s.name
        assert (tuple(a.choices) if a.choices else None) == s.choices, s.name
    # the Python keywords are the same names, flat or grouped, each with its one default
    p = UnfoldParameters()
    assert all(getattr(p, s.name) == s.default for s in specs)
    assert UnfoldParameters.from_dict(UnfoldParameters(kappa=0.2, method="lscm").to_dict()) == \
        UnfoldParameters(kappa=0.2, method="lscm")
    assert UnfoldParameters(kappa=0.2).solver.kappa == 0.2
    with pytest.raises(Exception, match="unknown parameter"):
        UnfoldParameters(kapa=0.2)


@pytest.mark.parametrize("name,value", [("kappa", 0.0), ("kappa", -1.0), ("grid_size", 0), ("grid_size", 2.5),
                                        ("wall_thickness_mm", 0.0), ("incision", "left"), ("method", "magic"),
                                        ("inner_iterations", 0), ("integrator", "rk4"), ("swap_check", "yes")])
def test_out_of_range_parameters_are_refused_by_name(name, value):
    with pytest.raises(Exception, match=name):
        UnfoldParameters(**{name: value}).validate()


def _slicer_parameter_node():
    """The Slicer module's parameter node fields {name: (annotation, default)} and its PARAMETER_MAP, from its AST."""
    tree = ast.parse(open(os.path.join(REPO, "StomachUnfold", "StomachUnfold.py")).read())
    fields, mapping = {}, {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ClassDef) and any(
                isinstance(d, ast.Name) and d.id == "parameterNodeWrapper" or
                isinstance(d, ast.Attribute) and d.attr == "parameterNodeWrapper" for d in node.decorator_list):
            fields = {n.target.id: (n.annotation, n.value) for n in node.body if isinstance(n, ast.AnnAssign)}
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "PARAMETER_MAP"
                                                for t in node.targets):
            mapping = ast.literal_eval(node.value)
    return fields, mapping


def test_slicer_parameter_node_agrees_with_the_one_definition():
    fields, mapping = _slicer_parameter_node()
    assert fields and mapping, "no @parameterNodeWrapper class or PARAMETER_MAP in StomachUnfold.py"
    specs = {s.name: s for s in parameter_specs()}
    assert set(mapping) <= set(fields) and set(mapping.values()) <= set(specs)
    assert {"method", "incision", "kappa", "wall_thickness_mm"} <= set(mapping.values())
    for node_name, lib_name in mapping.items():
        annotation, default = fields[node_name]
        spec = specs[lib_name]
        text = ast.unparse(annotation)
        if spec.choices:
            # the choices come from the one definition (a name), not a second literal list
            call = [n for n in ast.walk(annotation) if isinstance(n, ast.Call) and getattr(n.func, "id", "") == "Choice"]
            assert call and isinstance(call[0].args[0], ast.Name), (node_name, text)
            continue
        if spec.kind in (int, float):
            call = [n for n in ast.walk(annotation) if isinstance(n, ast.Call) and getattr(n.func, "id", "") ==
                    "WithinRange"]
            assert call, (node_name, text)
            lo, hi = (ast.literal_eval(a) for a in call[0].args[:2])
            value = ast.literal_eval(default)
            if spec.default is None:
                assert value == lo, (node_name, "an 'automatic' special value at the bottom of the range")
            else:
                assert value == pytest.approx(spec.default), (node_name, value, spec.default)
                # the panel's range lies within the library's valid range
                spec.check(lo if not (spec.lo_open and lo == spec.lo) else hi)
                spec.check(hi)


def test_methods_are_registered_once_and_share_one_contract():
    names = method_names()
    assert {"massspring", "paper", "cylindrical", "lscm"} <= set(names)
    for n in names:
        m = get_method(n)
        assert isinstance(m, Method) and m.name == n and m.description
    assert next(s for s in parameter_specs() if s.name == "method").choices == names


def test_a_new_method_is_one_class_and_one_registration(tmp_path):
    """A fourth method written as one class runs through the same front end, judge and output files."""
    import numpy as np

    from StomachUnfoldEval.phantom import make_phantom
    from StomachUnfoldLib import methods as registry
    from StomachUnfoldLib.pipeline import unfold

    @register
    class Shifted(Method):
        name = "test-shifted"
        description = "the cylindrical unrolling, moved 5 mm along i (a test method)"

        def unfold(self, prep, progress):
            out = get_method("cylindrical").unfold(prep, progress)
            fwd, inv = out.correspondence.to_unfolded, out.correspondence.to_original
            shift = np.array([5.0, 0.0, 0.0])
            vol = out.unfolded
            moved = type(vol)(vol.array, vol.spacing, vol.origin + shift, vol.direction)
            from StomachUnfoldLib.correspondence import MapCorrespondence

            corr = MapCorrespondence(lambda p: fwd(p) + shift, lambda q: inv(q - shift))
            return Unfolding(moved, corr, out.mesh, {"shift_mm": 5.0}, out.warnings, out.seconds)

    try:
        ct, truth = make_phantom("straight", "tiny")
        res = unfold(ct, truth["cardia_lps"], truth["pylorus_lps"], UnfoldParameters(method="test-shifted",
                                                                                   wall_thickness_mm=4.0))
        assert res.report["method"]["name"] == "test-shifted" and res.report["method"]["shift_mm"] == 5.0
        assert res.report["quality"]["visible_fraction"] > 0.9
        files = res.write(str(tmp_path))
        assert {"unfolded.nrrd", "report.json", "view.png", "model_rest.vtu", "model_unfolded.vtu"} <= set(files)
    finally:
        registry._REGISTRY.pop("test-shifted", None)


def test_the_extension_ships_the_core_alone_listed_explicitly():
    text = open(os.path.join(REPO, "StomachUnfold", "CMakeLists.txt")).read()
    assert "GLOB" not in text
    listed = set(re.findall(r"StomachUnfoldLib/[\w/]+\.py", text))
    core = {os.path.relpath(p, REPO) for p in _py(CORE)} - {os.path.join("StomachUnfoldLib", "cli.py")}
    assert listed == core, (sorted(core - listed), sorted(listed - core))
    assert "StomachUnfoldEval" not in text
