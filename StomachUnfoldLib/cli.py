"""The ``stomach-unfold`` command line: ``unfold``, ``batch``, ``phantom`` and ``bench``.

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
    b.add_argument("--parts", default="shapes,kappa,sweep,stability,resolution,peers,real,scaling,stomachs",
                   help="comma-separated parts to run")
    b.add_argument("--data-dir", default=None, help="folder of the real CTs (default ../shared/data)")
    b.add_argument("--merge", action="store_true",
                   help="replace only the rerun rows in OUTPUT_DIR/results.json and keep the others")
    b.add_argument("--replot", action="store_true",
                   help="only redraw the PNGs and results.md from OUTPUT_DIR/results.json (runs nothing)")

    c = sub.add_parser("batch", help="unfold every case of a CSV manifest (on Dask: a local or a given cluster)")
    c.add_argument("manifest", help="CSV with the header case,input,points[,mask,mask_label][,PARAMETER...]; "
                                    "paths relative to the manifest")
    c.add_argument("--output-dir", "-o", required=True, help="folder for OUT/CASE/ outputs and OUT/summary.csv")
    c.add_argument("--scheduler", default=None, help="Dask scheduler address tcp://HOST:PORT (default: a local "
                                                    "cluster sized from the cores and the largest case's memory)")
    c.add_argument("--workers", type=int, default=None, help="local cluster workers (default: from cores and memory)")
    c.add_argument("--sweep", default=None, metavar="NAME=V1,V2,...",
                   help="run every case for each value of one parameter into OUT/CASE/VALUE/ (with kappa: Table 1)")
    c.add_argument("--no-dask", action="store_true", help="run the cases here one after the other")
    c.add_argument("--quiet", action="store_true", help="no progress bar")
    add_parameter_flags(c)
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
    params = UnfoldParameters(**{spec.name: getattr(args, spec.name) for spec in parameter_specs()})
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
    grade = f", grade {r.quality['grade']}" if r.quality else ""
    print(f"unfolded by {r.method['name']} in {r.seconds['total']:.1f} s{grade} -> "
          f"{os.path.join(args.output_dir, 'unfolded.nrrd')}")
    for w in r["warnings"]:
        print(f"warning: {w}", file=sys.stderr)
    return 0


def _dask_executor(args, jobs, stack):
    """A concurrent.futures executor on Dask for the batch (None: run here), its clients closed by ``stack``."""
    from .batch import worker_plan

    try:
        import dask
        from dask.distributed import Client, LocalCluster
    except ImportError:
        if args.scheduler:
            raise InputError("--scheduler needs Dask: pip install 'dask[distributed]'") from None
        print("note: Dask is not installed; the cases run one after the other", file=sys.stderr)
        return None
    if args.scheduler:
        try:
            client = stack.enter_context(Client(args.scheduler, timeout="20s"))
        except (OSError, TimeoutError) as e:
            raise InputError(f"cannot reach the Dask scheduler at {args.scheduler}: {e}") from None
        return client.get_executor(pure=False)
    import logging

    workers, limit = worker_plan(jobs, args.workers)
    # the limit only kills a worker that outgrows it (its case becomes an error row): no pausing or spilling,
    # which are for Dask's own data (a paused worker would wait forever for memory a finished case keeps)
    stack.enter_context(dask.config.set({"distributed.scheduler.allowed-failures": 0,
                                         "distributed.worker.memory.target": False,
                                         "distributed.worker.memory.spill": False,
                                         "distributed.worker.memory.pause": False}))
    cluster = stack.enter_context(LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                               memory_limit=limit, dashboard_address=":0",
                                               silence_logs=logging.ERROR))
    client = stack.enter_context(Client(cluster))
    if not args.quiet:
        print(f"batch: local Dask cluster, {workers} workers of {limit / 2**30:.2f} GiB", file=sys.stderr)
    return client.get_executor(pure=False)


def _cmd_batch(args) -> int:
    import contextlib

    from .batch import parse_sweep, read_manifest, run_batch
    from .params import parameter_specs

    cases = read_manifest(args.manifest)
    sweep = parse_sweep(args.sweep)
    base = {spec.name: getattr(args, spec.name) for spec in parameter_specs()}
    bar = _Bar(args.quiet)
    with contextlib.ExitStack() as stack:
        ex = None if args.no_dask else (lambda jobs: _dask_executor(args, jobs, stack))  # only if a case must run
        try:
            rows = run_batch(cases, args.output_dir, sweep=sweep, executor=ex, progress=bar, base_params=base)
        finally:
            bar.close()
    bad = [r for r in rows if r["status"] != "ok"]
    reused = sum(bool(r.get("reused")) for r in rows)
    for r in bad:
        print(f"error: case {r['case']}{' ' + r['sweep'] if r['sweep'] else ''}: {r['error']}", file=sys.stderr)
    print(f"batch: {len(rows) - len(bad)} of {len(rows)} ok ({reused} reused), {len(bad)} failed -> "
          f"{os.path.join(args.output_dir, 'summary.csv')}")
    return 0 if not bad else 1


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
        if args.command == "batch":
            return _cmd_batch(args)
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
