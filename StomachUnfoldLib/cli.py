"""The ``stomach-unfold`` command line: ``unfold``, ``phantom`` and ``bench``.

Points on the command line are RAS mm (Slicer's frame); the library works in LPS internally.
Errors print one line ``error: ...`` and exit with status 2; Ctrl-C exits with 130 leaving no partial output.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from .errors import Cancelled, InputError, PointError, StomachUnfoldError
from .geometry import ras_to_lps

__all__ = ["main", "build_parser", "parse_point"]


def parse_point(text: str) -> np.ndarray:
    """Parse ``"R,A,S"`` (mm) into a float array of 3; InputError on anything else."""
    try:
        p = np.array([float(v) for v in text.replace(" ", "").split(",")], float)
    except ValueError:
        raise InputError(f"a point must be three numbers R,A,S in mm, got {text!r}") from None
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise InputError(f"a point must be three finite numbers R,A,S in mm, got {text!r}")
    return p


def _points_from_file(path: str):
    """Cardia and pylorus (LPS mm) from a Slicer .mrk.json or a phantom truth .json."""
    if path.endswith(".mrk.json"):
        from .io import cardia_pylorus_from_markups

        return cardia_pylorus_from_markups(path)
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read points file {path}: {e}") from None
    if "markups" in data:
        from .io import cardia_pylorus_from_markups

        return cardia_pylorus_from_markups(path)
    if "cardia_lps" in data and "pylorus_lps" in data:
        return np.array(data["cardia_lps"], float), np.array(data["pylorus_lps"], float)
    if "cardia_ras" in data and "pylorus_ras" in data:
        return ras_to_lps(data["cardia_ras"]), ras_to_lps(data["pylorus_ras"])
    raise PointError(f"{path} holds no cardia/pylorus points: give a Slicer .mrk.json with control points "
                     "labelled 'cardia' and 'pylorus', or --cardia/--pylorus R,A,S")


def _bool(text: str) -> bool:
    """Parse a command-line truth value (1/0, true/false, yes/no, on/off)."""
    t = text.strip().lower()
    if t in ("1", "true", "yes", "on"):
        return True
    if t in ("0", "false", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"expected true or false, got {text!r}")


def add_parameter_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per parameter of ``params.parameter_specs`` (its type, default, choices and help), grouped by stage."""
    from .methods import methods
    from .params import parameter_specs

    groups = {}
    for spec in parameter_specs():
        g = groups.get(spec.group)
        if g is None:
            g = groups[spec.group] = parser.add_argument_group(f"{spec.group or 'method'} parameters")
        kind = _bool if spec.kind is bool else spec.kind
        help_ = spec.help
        if spec.name == "method":
            help_ += ": " + "; ".join(f"{n} ({d})" for n, d in methods().items())
        g.add_argument(spec.flag, dest=spec.name, type=kind, default=spec.default, choices=spec.choices,
                       help=f"{help_} (default {spec.default})")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``stomach-unfold`` command."""
    ap = argparse.ArgumentParser(prog="stomach-unfold",
                                 description="Virtual unfolded views of the stomach from CT (Oda et al.).")
    sub = ap.add_subparsers(dest="command", required=True)

    u = sub.add_parser("unfold", help="unfold the stomach of a CT volume")
    u.add_argument("input", help="CT volume: NRRD, NIfTI, MHA or a DICOM folder")
    u.add_argument("--cardia", help="cardia point R,A,S in mm (Slicer's RAS frame)")
    u.add_argument("--pylorus", help="pylorus point R,A,S in mm")
    u.add_argument("--points", help="Slicer .mrk.json with control points 'cardia' and 'pylorus' "
                                    "(or a phantom .json)")
    u.add_argument("--auto-points", action="store_true",
                   help="find the cardia and pylorus automatically: from the organs of a TotalSegmentator-like "
                        "--mask (its stomach label is then the mask), else from the stomach gas; refused when unsure")
    u.add_argument("--output-dir", "-o", required=True, help="folder for the outputs")
    u.add_argument("--mask", help="stomach label volume (replaces the air threshold)")
    u.add_argument("--mask-label", type=int, default=None, help="label value of the stomach in --mask")
    u.add_argument("--incision-curve", help="user incision curve (.mrk.json, LPS or RAS)")
    u.add_argument("--landmarks", help=".mrk.json of points to map into the unfolded volume")
    u.add_argument("--series-uid", help="DICOM series to read when a folder holds several")
    u.add_argument("--quiet", action="store_true", help="no progress bar")
    add_parameter_flags(u)

    p = sub.add_parser("phantom", help="write a synthetic CT of a gas-distended stomach with markers")
    p.add_argument("output", help="output volume path (e.g. phantom.nrrd); a .json and .mrk.json go beside it")
    p.add_argument("--shape", default="j", help="straight, bent, j, twisted, thin_wall or hook (a sharp angular incisure)")
    p.add_argument("--size", default="small", help="tiny, small, medium or full (512x512x400 at 0.7 mm)")
    p.add_argument("--spacing", default=None, help="voxel spacing sx,sy,sz in mm")
    p.add_argument("--wall-thickness-mm", type=float, default=4.0)
    p.add_argument("--rugae", action="store_true")
    p.add_argument("--noise-hu", type=float, default=15.0)
    p.add_argument("--markers", type=int, default=12)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--flip", action="store_true", help="flipped direction matrix (det = -1)")
    p.add_argument("--random", type=int, default=None, metavar="SEED",
                   help="draw a stomach at random from the anatomical family (fundus dome, side openings, incisure, "
                        "narrow antrum, rugae, fluid, neighbouring gas); --size tiny, small or full; other shape "
                        "options are ignored")

    b = sub.add_parser("bench", help="run the benchmark and write tables and PNGs")
    b.add_argument("--output-dir", "-o", default="docs/benchmark")
    b.add_argument("--quick", action="store_true", help="a small version that runs in about a minute")
    b.add_argument("--full-size", action="store_true", help="include the 512x512x400 phantom timing and scaling")
    b.add_argument("--scheduler", default=None, help="Dask scheduler address (default: a local cluster)")
    b.add_argument("--parts", default="shapes,kappa,sweep,stability,resolution,peers,real,scaling,stomachs,zeroclicks,autopoints",
                   help="comma-separated parts to run")
    b.add_argument("--data-dir", default=None, help="folder of the real CTs (default ../shared/data)")
    b.add_argument("--merge", action="store_true",
                   help="replace only the rerun rows in OUTPUT_DIR/results.json and keep the others")
    b.add_argument("--replot", action="store_true",
                   help="only redraw the PNGs and results.md from OUTPUT_DIR/results.json (runs nothing)")
    return ap


class _Bar:
    """A text progress bar on stderr for the library's (stage, fraction) callback: redrawn in place on a terminal,
    one plain line per stage (and every 25 %) when stderr is a file, so a log stays readable."""

    def __init__(self, quiet: bool, stream=None):
        self.quiet, self.stream = quiet, stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.t0 = time.perf_counter()
        self.stage, self.quarter, self.shown = None, -1, -1.0

    def __call__(self, stage: str, fraction: float):
        if self.quiet:
            return
        pct = int(100 * min(max(fraction, 0.0), 1.0))
        t = time.perf_counter() - self.t0
        if self.tty:
            if stage != self.stage or pct - self.shown >= 1:
                bar = "#" * (pct // 4)
                self.stream.write(f"\r{stage:<18} {pct:3d}% |{bar:<25}| {t:5.1f} s")
                self.stream.flush()
                self.stage, self.shown = stage, pct
        elif stage != self.stage or pct // 25 > self.quarter:
            self.stream.write(f"{t:6.1f} s {pct:3d}% {stage}\n")
            self.stream.flush()
            self.stage, self.quarter = stage, pct // 25

    def close(self):
        if not self.quiet and self.tty:
            self.stream.write("\n")
            self.stream.flush()


def _cmd_unfold(args) -> int:
    from .io import read_label_volume, read_markups_points, read_volume
    from .params import parameter_specs
    from .pipeline import UnfoldParameters, unfold

    if args.auto_points:
        if args.points or args.cardia or args.pylorus:
            raise PointError("--auto-points finds the cardia and pylorus itself; leave out --cardia, --pylorus "
                             "and --points (or leave out --auto-points)")
        cardia = pylorus = None
    elif args.points:
        cardia, pylorus = _points_from_file(args.points)
        if args.cardia:
            cardia = ras_to_lps(parse_point(args.cardia))
        if args.pylorus:
            pylorus = ras_to_lps(parse_point(args.pylorus))
    else:
        if not (args.cardia and args.pylorus):
            raise PointError("give both --cardia R,A,S and --pylorus R,A,S (mm, RAS), or --points file.mrk.json")
        cardia, pylorus = ras_to_lps(parse_point(args.cardia)), ras_to_lps(parse_point(args.pylorus))
    params = UnfoldParameters(**{spec.name: getattr(args, spec.name) for spec in parameter_specs()})
    ct = read_volume(args.input, series_uid=args.series_uid)
    found = None
    if args.auto_points:
        cardia, pylorus, found, stomach_value = _auto_points(args, ct, params)
        mask = read_label_volume(args.mask, ct, label_value=stomach_value) if args.mask else None
    else:
        mask = read_label_volume(args.mask, ct, label_value=args.mask_label) if args.mask else None
    curve = None
    if args.incision_curve:
        curve = np.array(list(read_markups_points(args.incision_curve).values()), float)
    landmarks = read_markups_points(args.landmarks) if args.landmarks else None
    bar = _Bar(args.quiet)
    try:
        result = unfold(ct, cardia, pylorus, params, mask=mask, incision_curve_lps=curve, progress=bar)
        if found is not None:
            result.report["auto_points"] = found.to_dict()
        bar("writing", 1.0)
        result.write(args.output_dir, landmarks_lps=landmarks)
    finally:
        bar.close()
    r = result.report
    grade = f", grade {r.quality['grade']}" if r.quality else ""
    print(f"unfolded by {r.method['name']} in {r.seconds['total']:.1f} s{grade} -> "
          f"{os.path.join(args.output_dir, 'unfolded.nrrd')}")
    for w in r["warnings"]:
        print(f"warning: {w}", file=sys.stderr)
    return 0


def _auto_points(args, ct, params):
    """--auto-points: (cardia, pylorus LPS mm, AutoPoints, stomach label value or None); PointError when unsure."""
    from .io import read_volume
    from .landmarks import auto_points_or_refuse, labels_on_grid

    labels = labels_on_grid(read_volume(args.mask), ct) if args.mask else None
    found = auto_points_or_refuse(ct, labels, threshold_hu=params.air_threshold_hu, max_snap_mm=params.max_snap_mm)
    value = args.mask_label if args.mask_label is not None else found.labels.get("stomach")
    return found.cardia_lps, found.pylorus_lps, found, value


def _evaluation():
    """The evaluation package (phantoms, benchmark), which a Slicer install does not have."""
    try:
        import StomachUnfoldEval
    except ImportError:
        raise InputError("the evaluation package StomachUnfoldEval is not installed; install the project from "
                         "source (pip install -e .) to make phantoms and run the benchmark") from None
    return StomachUnfoldEval


def _cmd_phantom(args) -> int:
    _evaluation()
    from StomachUnfoldEval.phantom import write_phantom

    if args.random is not None:
        from StomachUnfoldEval.random_stomach import write_random_stomach

        path, json_path = write_random_stomach(args.output, args.random, size=args.size)
        print(f"random stomach {args.random} written to {path} (truth: {json_path})")
        return 0

    spacing = None
    if args.spacing:
        spacing = parse_point(args.spacing)
    path, json_path = write_phantom(args.output, shape=args.shape, size=args.size, spacing=spacing,
                                    wall_thickness_mm=args.wall_thickness_mm, rugae=args.rugae,
                                    noise_hu=args.noise_hu, n_markers=args.markers, seed=args.seed,
                                    flip_direction=args.flip)
    print(f"phantom written to {path} (truth: {json_path})")
    return 0


def _cmd_bench(args) -> int:
    _evaluation()
    from StomachUnfoldEval.bench import replot, run_benchmark

    if args.replot:
        made = replot(args.output_dir)
        print(f"bench: redrew {len(made)} PNGs and {args.output_dir}/results.md from results.json")
        return 0
    rows = run_benchmark(args.output_dir, quick=args.quick, full_size=args.full_size, scheduler=args.scheduler,
                         data_dir=args.data_dir, parts=tuple(p.strip() for p in args.parts.split(",") if p.strip()),
                         merge=args.merge)
    failed = sum(not r.get("ok") for r in rows)
    print(f"bench: {len(rows)} cases, {failed} failed (as data), results in {args.output_dir}/results.md")
    return 0


def main(argv=None) -> int:
    """Entry point of ``stomach-unfold``; returns the exit status (0 ok, 2 bad input or failure, 130 cancelled)."""
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    # "--cardia -54.9,27.7,64" would read as an option: glue point values to their flag
    for flag in ("--cardia", "--pylorus", "--spacing"):
        while flag in argv[:-1]:
            i = argv.index(flag)
            argv[i:i + 2] = [f"{flag}={argv[i + 1]}"]
    args = parser.parse_args(argv)
    try:
        if args.command == "unfold":
            return _cmd_unfold(args)
        if args.command == "phantom":
            return _cmd_phantom(args)
        return _cmd_bench(args)
    except KeyboardInterrupt:
        print("error: cancelled (Ctrl-C); no output was written", file=sys.stderr)
        return 130
    except Cancelled as e:
        print(f"error: {e}", file=sys.stderr)
        return 130
    except StomachUnfoldError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except MemoryError:
        print("error: out of memory; crop the volume or use a larger --grid-size / --output-spacing-mm",
              file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
