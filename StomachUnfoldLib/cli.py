"""The ``stomach-unfold`` command line: ``unfold``, ``phantom`` and ``bench``.

Points on the command line are RAS mm (Slicer's frame); the library works in LPS internally.
Errors print one line ``error: ...`` and exit with status 2; Ctrl-C exits with 130 leaving no partial output.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import fields

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


_PARAM_HELP = {
    "grid_size": "cell size d in voxels (the paper's d; default: 5.6 mm cells, i.e. d = 8 at 0.7 mm)",
    "grid_mm": "cell size in mm (overrides --grid-size; default 5.6)",
    "kappa": "termination threshold |D(a-1)-D(a)| in mm", "incision": "incision side",
    "wall_thickness_mm": "stomach wall thickness in mm", "air_threshold_hu": "air threshold in HU",
    "output_spacing_mm": "unfolded volume spacing in mm (default: input in-plane spacing)",
}


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``stomach-unfold`` command."""
    from .pipeline import UnfoldParameters

    ap = argparse.ArgumentParser(prog="stomach-unfold",
                                 description="Virtual unfolded views of the stomach from CT (Oda et al.).")
    sub = ap.add_subparsers(dest="command", required=True)

    u = sub.add_parser("unfold", help="unfold the stomach of a CT volume")
    u.add_argument("input", help="CT volume: NRRD, NIfTI, MHA or a DICOM folder")
    u.add_argument("--cardia", help="cardia point R,A,S in mm (Slicer's RAS frame)")
    u.add_argument("--pylorus", help="pylorus point R,A,S in mm")
    u.add_argument("--points", help="Slicer .mrk.json with control points 'cardia' and 'pylorus' "
                                    "(or a phantom .json)")
    u.add_argument("--output-dir", "-o", required=True, help="folder for the outputs")
    u.add_argument("--mask", help="stomach label volume (replaces the air threshold)")
    u.add_argument("--mask-label", type=int, default=None, help="label value of the stomach in --mask")
    u.add_argument("--incision-curve", help="user incision curve (.mrk.json, LPS or RAS)")
    u.add_argument("--landmarks", help=".mrk.json of points to map into the unfolded volume")
    u.add_argument("--series-uid", help="DICOM series to read when a folder holds several")
    u.add_argument("--quiet", action="store_true", help="no progress bar")
    for f in fields(UnfoldParameters):
        flag = "--" + f.name.replace("_", "-")
        default = f.default
        kind = type(default) if default is not None else (int if str(f.type).startswith("int") else float)
        if kind is bool:
            u.add_argument(flag, type=lambda s: s.lower() in ("1", "true", "yes", "on"), default=default,
                           help=f"{_PARAM_HELP.get(f.name, f.name)} (default {default})")
        elif f.name == "incision":
            u.add_argument(flag, choices=["greater", "lesser", "anterior", "posterior"], default=default,
                           help="incision side (default greater curvature)")
        else:
            u.add_argument(flag, type=kind, default=default, help=f"{_PARAM_HELP.get(f.name, f.name)} "
                                                                 f"(default {default})")

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

    b = sub.add_parser("bench", help="run the benchmark and write tables and PNGs")
    b.add_argument("--output-dir", "-o", default="docs/benchmark")
    b.add_argument("--quick", action="store_true", help="a small version that runs in about a minute")
    b.add_argument("--full-size", action="store_true", help="include the 512x512x400 phantom timing and scaling")
    b.add_argument("--scheduler", default=None, help="Dask scheduler address (default: a local cluster)")
    b.add_argument("--parts", default="shapes,kappa,sweep,stability,resolution,peers,real,scaling",
                   help="comma-separated parts to run")
    b.add_argument("--data-dir", default=None, help="folder of the real CTs (default ../shared/data)")
    b.add_argument("--merge", action="store_true",
                   help="replace only the rerun rows in OUTPUT_DIR/results.json and keep the others")
    b.add_argument("--replot", action="store_true",
                   help="only redraw the PNGs and results.md from OUTPUT_DIR/results.json (runs nothing)")
    return ap


class _Bar:
    """tqdm progress bar on stderr driven by the library's (stage, fraction) callback."""

    def __init__(self, quiet: bool):
        self.bar = None
        if not quiet:
            from tqdm import tqdm

            self.bar = tqdm(total=1000, file=sys.stderr, bar_format="{desc:<18} {percentage:3.0f}%|{bar}| {elapsed}",
                            leave=False, mininterval=0.25 if sys.stderr.isatty() else 2.0)

    def __call__(self, stage: str, fraction: float):
        if self.bar is not None:
            n = int(fraction * 1000)
            if stage != self.bar.desc or n - self.bar.n >= 10:
                self.bar.set_description_str(stage, refresh=False)
                self.bar.update(n - self.bar.n)

    def close(self):
        if self.bar is not None:
            self.bar.close()


def _cmd_unfold(args) -> int:
    from .io import read_label_volume, read_markups_points, read_volume
    from .pipeline import UnfoldParameters, unfold

    if args.points:
        cardia, pylorus = _points_from_file(args.points)
        if args.cardia:
            cardia = ras_to_lps(parse_point(args.cardia))
        if args.pylorus:
            pylorus = ras_to_lps(parse_point(args.pylorus))
    else:
        if not (args.cardia and args.pylorus):
            raise PointError("give both --cardia R,A,S and --pylorus R,A,S (mm, RAS), or --points file.mrk.json")
        cardia, pylorus = ras_to_lps(parse_point(args.cardia)), ras_to_lps(parse_point(args.pylorus))
    params = UnfoldParameters(**{f.name: getattr(args, f.name) for f in fields(UnfoldParameters)})
    ct = read_volume(args.input, series_uid=args.series_uid)
    mask = read_label_volume(args.mask, ct, label_value=args.mask_label) if args.mask else None
    curve = None
    if args.incision_curve:
        curve = np.array(list(read_markups_points(args.incision_curve).values()), float)
    landmarks = read_markups_points(args.landmarks) if args.landmarks else None
    bar = _Bar(args.quiet)
    try:
        result = unfold(ct, cardia, pylorus, params, mask=mask, incision_curve_lps=curve, progress=bar)
        bar("writing", 1.0)
        result.write(args.output_dir, landmarks_lps=landmarks)
    finally:
        bar.close()
    r = result.report
    print(f"unfolded in {r['seconds']['total']:.1f} s, {r['iterations']} iterations, "
          f"{r['model']['hexahedra']} hexahedra -> {os.path.join(args.output_dir, 'unfolded.nrrd')}")
    for w in r["warnings"]:
        print(f"warning: {w}", file=sys.stderr)
    return 0


def _cmd_phantom(args) -> int:
    from .phantom import write_phantom

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
    from .bench import replot, run_benchmark

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
