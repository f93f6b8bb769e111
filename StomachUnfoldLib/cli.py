"""The ``stomach-unfold`` command line: ``unfold``, ``batch``, ``phantom`` and ``bench``.

Points on the command line are RAS mm (Slicer's frame); the library works in LPS internally.
Errors print one line ``error: ...`` and exit with status 2; Ctrl-C exits with 130, SIGTERM with 143 and SIGHUP with
129, leaving no partial output. The output folder is checked before the work starts.
"""
from __future__ import annotations

import argparse
import os
import signal
import sys
import time

# only the standard library, the package's Ctrl-C list and the errors here: NumPy and the library are imported inside
# main()'s try, so a Ctrl-C in the first milliseconds gives the same one line as later
from . import CTRL_C
from .errors import Cancelled, InputError, PointError, StomachUnfoldError

__all__ = ["main", "build_parser", "parse_point"]


def parse_point(text: str):
    """Parse ``"R,A,S"`` (mm) into a float array of 3; InputError on anything else."""
    import numpy as np

    try:
        p = np.array([float(v) for v in text.replace(" ", "").split(",")], float)
    except ValueError:
        raise InputError(f"a point must be three numbers R,A,S in mm, got {text!r}") from None
    if p.shape != (3,) or not np.all(np.isfinite(p)):
        raise InputError(f"a point must be three finite numbers R,A,S in mm, got {text!r}")
    return p


def _points_from_file(path: str):
    """Cardia and pylorus (LPS mm) from a Slicer .mrk.json or a phantom truth .json."""
    from .geometry import ras_to_lps
    from .io import cardia_pylorus_from_markups, point3, read_json

    if path.endswith(".mrk.json"):
        return cardia_pylorus_from_markups(path)
    data = read_json(path, "points file")
    if isinstance(data, dict) and "markups" in data:
        return cardia_pylorus_from_markups(path)
    if isinstance(data, dict) and "cardia_lps" in data and "pylorus_lps" in data:
        return point3(data["cardia_lps"], f"cardia_lps in {path}"), point3(data["pylorus_lps"], f"pylorus_lps in {path}")
    if isinstance(data, dict) and "cardia_ras" in data and "pylorus_ras" in data:
        return (ras_to_lps(point3(data["cardia_ras"], f"cardia_ras in {path}")),
                ras_to_lps(point3(data["pylorus_ras"], f"pylorus_ras in {path}")))
    raise PointError(f"{path} holds no cardia/pylorus points: give a Slicer .mrk.json with control points "
                     "labelled 'cardia' and 'pylorus', or --cardia/--pylorus R,A,S")


def add_parameter_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per parameter of ``params.parameter_specs`` (its type, default, choices and help), grouped by stage."""
    from .methods import methods
    from .params import parameter_specs

    groups = {}
    for spec in parameter_specs():
        g = groups.get(spec.group)
        if g is None:
            g = groups[spec.group] = parser.add_argument_group(f"{spec.group or 'method'} parameters")
        help_ = spec.help
        if spec.name == "method":
            help_ += ": " + "; ".join(f"{n} ({d})" for n, d in methods().items())
        elif spec.choices:
            help_ += f"; one of {', '.join(spec.choices)}"
        if spec.kind is bool:
            g.add_argument(spec.flag, dest=spec.name, action=argparse.BooleanOptionalAction, default=spec.default,
                           help=f"{help_} (default {'on' if spec.default else 'off'})")
            continue
        g.add_argument(spec.flag, dest=spec.name, type=spec.kind, default=spec.default, choices=spec.choices,
                       metavar=spec.name.upper() if spec.choices and spec.name != "method" else None,
                       help=help_ if spec.default is None else f"{help_} (default {spec.default})")


#: The end of ``unfold --help``.
UNFOLD_EXAMPLES = """examples:
  stomach-unfold unfold ct.nrrd --cardia -54.9,27.7,64 --pylorus 12.3,-40.1,-30.5 -o out
      (points in RAS mm as Slicer shows them; out/view.png is the view, out/report.json the run)
  stomach-unfold unfold ct.nii.gz --points points.mrk.json --mask seg.nii.gz --mask-label 6 -o out --view-size 800
      (a stomach without gas: pass its segmentation, e.g. TotalSegmentator's label 6)
"""


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``stomach-unfold`` command."""
    ap = argparse.ArgumentParser(prog="stomach-unfold",
                                 description="Virtual unfolded views of the stomach from CT (Oda et al.).")
    sub = ap.add_subparsers(dest="command", required=True)

    u = sub.add_parser("unfold", help="unfold the stomach of a CT volume", epilog=UNFOLD_EXAMPLES,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    u.add_argument("input", help="CT volume (HU): NRRD, NIfTI, MHA or a DICOM folder")
    u.add_argument("--cardia", metavar="R,A,S", help="cardia point in mm, Slicer's RAS frame, commas between")
    u.add_argument("--pylorus", metavar="R,A,S", help="pylorus point in mm, Slicer's RAS frame, commas between")
    u.add_argument("--points", metavar="FILE", help="Slicer .mrk.json with control points 'cardia' and 'pylorus' "
                                                    "(or a phantom's truth .json: its markers are then scored)")
    u.add_argument("--auto-points", action="store_true",
                   help="find the cardia and pylorus automatically: from the organs of a TotalSegmentator-like "
                        "--mask (its stomach label is then the mask), else from the stomach gas; refused when unsure")
    u.add_argument("--output-dir", "-o", required=True, metavar="DIR", help="folder for the output files")
    u.add_argument("--mask", metavar="FILE", help="stomach label volume on the CT's grid (replaces the air threshold)")
    u.add_argument("--mask-label", type=int, default=None, metavar="N",
                   help="label value of the stomach in --mask (default: every non-zero voxel)")
    u.add_argument("--incision-curve", metavar="FILE", help="user incision curve (.mrk.json, LPS or RAS mm)")
    u.add_argument("--landmarks", metavar="FILE",
                   help=".mrk.json of points (mm) to map into the unfolded volume and mark on view.png")
    u.add_argument("--series-uid", metavar="UID", help="DICOM series to read when a folder holds several")
    u.add_argument("--view-size", type=int, default=None, metavar="PIXELS",
                   help="width in pixels of each panel of view.png, resampled bilinearly (default: the view's own "
                        "width in pixels, at least 512)")
    u.add_argument("--dicom", action="store_true",
                   help="also write dicom/: view.png as a DICOM secondary capture and the unfolded volume as a CT "
                        "series, in the source study (its patient and study identifiers) when the input is DICOM")
    u.add_argument("--quiet", action="store_true", help="no progress bar")
    add_parameter_flags(u)

    p = sub.add_parser("phantom", help="write a synthetic CT of a gas-distended stomach with markers")
    p.add_argument("output", help="output volume path (e.g. phantom.nrrd); a .json and .mrk.json go beside it")
    p.add_argument("--shape", default="j",
                   metavar="SHAPE", help="one of straight, bent, j, twisted, thin_wall or hook (a sharp angular "
                                         "incisure) (default j)")
    p.add_argument("--size", default="small", metavar="SIZE",
                   help="tiny (1.8 mm voxels), small (1.2 mm), medium (0.9 mm) or full (512x512x400 at 0.7 mm) "
                        "(default small)")
    p.add_argument("--spacing", default=None, metavar="SX,SY,SZ", help="voxel spacing in mm (default: from --size)")
    p.add_argument("--wall-thickness-mm", type=float, default=4.0, help="stomach wall thickness in mm (default 4)")
    p.add_argument("--rugae", action="store_true", help="add gastric folds (rugae) to the mucosa")
    p.add_argument("--noise-hu", type=float, default=15.0, help="Gaussian image noise, standard deviation in HU "
                                                                  "(default 15)")
    p.add_argument("--markers", type=int, default=12, help="number of dense marker beads on the mucosa (default 12)")
    p.add_argument("--seed", type=int, default=0, help="random seed of the image noise (default 0)")
    p.add_argument("--flip", action="store_true", help="flipped direction matrix (det = -1)")
    p.add_argument("--random", type=int, default=None, metavar="SEED",
                   help="draw a stomach at random from the anatomical family (fundus dome, side openings, incisure, "
                        "narrow antrum, rugae, fluid, neighbouring gas); --size tiny, small or full; other shape "
                        "options are ignored")

    b = sub.add_parser("bench", help="run the benchmark and write tables and PNGs")
    b.add_argument("--output-dir", "-o", default="docs/benchmark", metavar="DIR",
                   help="folder for results.json, results.md and the charts (default docs/benchmark)")
    b.add_argument("--quick", action="store_true", help="a small version that runs in about a minute")
    b.add_argument("--full-size", action="store_true", help="include the 512x512x400 phantom timing and scaling")
    b.add_argument("--scheduler", default=None, help="Dask scheduler address (default: a local cluster)")
    b.add_argument("--parts", default=",".join(BENCH_DEFAULT_PARTS),
                   help="comma-separated parts to run (default: every part but surfacebound-fresh and clicks)")
    b.add_argument("--data-dir", default=None, help="folder of the real CTs (default ../shared/data)")
    b.add_argument("--merge", action="store_true",
                   help="replace only the rerun rows in OUTPUT_DIR/results.json and keep the others")
    b.add_argument("--methods", default=None,
                   help="comma-separated methods: run only their cases of the parts (e.g. isometric after a change "
                        "to it alone; with --merge the other rows are kept)")
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
    """A text progress bar on stderr for the library's (stage, fraction) callback.

    On a terminal: one line redrawn in place, at least once a second (a ticker thread), with the elapsed time and
    an estimate of the time left. In a log (stderr not a terminal): one line per finished stage with its seconds.
    ``span(lo, hi)`` maps the callback's fractions onto [lo, hi] of the whole run (reading, unfolding, writing).
    """

    def __init__(self, quiet: bool, stream=None, tick_s: float = 0.5):
        import threading

        self.quiet, self.stream = quiet, stream or sys.stderr
        self.tty = hasattr(self.stream, "isatty") and self.stream.isatty()
        self.t0 = self.t_stage = time.perf_counter()
        self.stage, self.fraction, self.lo, self.hi = None, 0.0, 0.0, 1.0
        self.lock, self.done = threading.Lock(), threading.Event()
        self.ticker = None
        if self.tty and not quiet:
            self.ticker = threading.Thread(target=self._tick, args=(tick_s,), daemon=True)
            self.ticker.start()

    def span(self, lo: float, hi: float) -> "_Bar":
        """Map the following fractions onto [lo, hi] of the bar."""
        self.lo, self.hi = lo, hi
        return self

    def _tick(self, tick_s: float) -> None:
        while not self.done.wait(tick_s):
            with self.lock:
                self._draw()

    def _draw(self) -> None:
        if self.stage is None:
            return
        f = self.fraction
        t = time.perf_counter() - self.t0
        eta = f"~{t / f * (1 - f):4.0f} s left" if 0.03 < f < 1.0 else " " * 12
        bar = "#" * int(25 * f)
        self.stream.write(f"\r{self.stage:<18} {int(100 * f):3d}% |{bar:<25}| {t:5.1f} s {eta}")
        self.stream.flush()

    def __call__(self, stage: str, fraction: float):
        if CTRL_C:  # a Ctrl-C whose KeyboardInterrupt Python dropped: the library cancels (Cancelled)
            return False
        if self.quiet:
            return
        f = self.lo + (self.hi - self.lo) * min(max(fraction, 0.0), 1.0)
        with self.lock:
            now = time.perf_counter()
            try:
                if stage != self.stage:
                    if not self.tty and self.stage is not None:
                        self.stream.write(f"{self.stage}: {now - self.t_stage:.1f} s\n")
                        self.stream.flush()
                    self.stage, self.t_stage = stage, now
                self.fraction = max(self.fraction, f)
                if self.tty:
                    self._draw()
            except OSError:  # stderr closed (a pipe whose reader left): the run goes on without a bar
                self.quiet = True
                self.done.set()

    def close(self, finished: bool = True):
        self.done.set()
        if self.quiet:
            return
        with self.lock:
            now = time.perf_counter()
            try:
                if self.tty:
                    self.stream.write("\n")
                elif self.stage is not None and finished:  # a failed run: its one error line says why
                    self.stream.write(f"{self.stage}: {now - self.t_stage:.1f} s\ntotal: {now - self.t0:.1f} s\n")
                self.stream.flush()
            except OSError:
                pass
            self.stage = None


def _sha256(path: str) -> str | None:
    """SHA-256 (hex) of a file, or of a folder's files (names and contents, sorted: a DICOM series); None if absent."""
    import hashlib

    if not path or not os.path.exists(path):
        return None
    h = hashlib.sha256()
    files = [path] if os.path.isfile(path) else sorted(
        os.path.join(d, f) for d, _, fs in os.walk(path) for f in fs)
    for fp in files:
        if len(files) > 1:
            h.update(os.path.relpath(fp, path).encode() + b"\0")
        with open(fp, "rb") as fh:
            for chunk in iter(lambda: fh.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()


def _reproduce(args, argv) -> dict:
    """The report's record of how the run was asked for: paths and checksums of the inputs, and the command line."""
    import shlex

    files = {}
    for key in ("input", "mask", "points", "incision_curve", "landmarks"):
        path = getattr(args, key, None)
        if path:
            files[key] = {"path": os.path.abspath(path), "sha256": _sha256(path)}
    line = ["stomach-unfold", *argv]
    return {"files": files, "mask_label": args.mask_label, "series_uid": args.series_uid,
            "command_line": shlex.join(line), "argv": line, "working_directory": os.getcwd()}


def _phantom_markers(path: str):
    """A phantom truth .json's markers {id: LPS mm}, or None for any other points file."""
    import json

    import numpy as np

    if not path or path.endswith(".mrk.json"):
        return None
    try:
        with open(path) as f:
            data = json.load(f)
    except (OSError, ValueError):
        return None
    marks = data.get("markers") if isinstance(data, dict) else None
    if not isinstance(marks, list) or not marks:
        return None
    return {str(m["id"]): np.asarray(m["lps"], float) for m in marks if isinstance(m, dict) and "lps" in m}


def _check_unfold_outputs(args) -> None:
    """Before any work: the output folder is usable (writable, a folder, a real file system) and no input is an output."""
    from .io import check_output_folder, check_outputs_spare_inputs
    from .pipeline import OUTPUT_NAMES

    check_output_folder(args.output_dir)
    check_outputs_spare_inputs(args.output_dir, OUTPUT_NAMES, [args.input, args.mask, args.points,
                                                              args.incision_curve, args.landmarks])


def _say(text: str, stream) -> None:
    """Print a line, dropping it when the stream is a closed pipe (``| head``): the outputs are complete by then."""
    try:
        print(text, file=stream)
        stream.flush()
    except BrokenPipeError:
        try:  # the interpreter's last flush at exit would raise again
            os.dup2(os.open(os.devnull, os.O_WRONLY), stream.fileno())
        except (OSError, ValueError):
            pass
    except (OSError, ValueError):
        pass


def _cmd_unfold(args) -> int:
    import numpy as np

    from .geometry import ras_to_lps
    from .io import check_output_folder, estimate_output_bytes, read_label_volume, read_markups_points, read_volume
    from .frontend import return_freed_memory
    from .params import parameter_specs
    from .pipeline import UnfoldParameters, unfold

    _check_unfold_outputs(args)
    return_freed_memory()
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
    params.validate()
    if args.view_size is not None and not 64 <= args.view_size <= 8000:
        raise InputError(f"--view-size is the width of each panel of view.png in pixels, 64 to 8000; got {args.view_size}")
    bar = _Bar(args.quiet)
    finished = False
    try:
        bar.span(0.0, 0.08)("reading the CT", 0.0)
        # left on file and read box by box (memory grows with the stomach, not the CT); --auto-points looks at it whole
        ct = read_volume(args.input, series_uid=args.series_uid, stream=not args.auto_points)
        check_output_folder(args.output_dir, estimate_output_bytes(ct))
        found = None
        if args.auto_points:
            cardia, pylorus, found, stomach_value = _auto_points(args, ct, params)
            mask = read_label_volume(args.mask, ct, label_value=stomach_value) if args.mask else None
        else:
            mask = read_label_volume(args.mask, ct, label_value=args.mask_label) if args.mask else None
        bar("reading the CT", 1.0)
        curve = None
        if args.incision_curve:
            curve = np.array(list(read_markups_points(args.incision_curve).values()), float)
        landmarks = read_markups_points(args.landmarks) if args.landmarks else None
        result = unfold(ct, cardia, pylorus, params, mask=mask, incision_curve_lps=curve, progress=bar.span(0.08, 0.95))
        _cancel_if_ctrl_c()
        bar.span(0.95, 1.0)("writing", 0.0)
        if found is not None:
            result.report["auto_points"] = found.to_dict()
        result.report["run"].update(_reproduce(args, getattr(args, "argv", [])))
        markers = _phantom_markers(args.points)
        if markers and _has_evaluation():
            from StomachUnfoldEval.markers import marker_metrics

            result.report["markers"] = marker_metrics(result, markers)
        study = None
        if args.dicom:
            from .dicom_export import source_study_tags

            study = source_study_tags(args.input, args.series_uid)
        result.write(args.output_dir, landmarks_lps=landmarks, view_size=args.view_size, dicom_study=study)
        bar("writing", 1.0)
        finished = True
    finally:
        bar.close(finished)
    r = result.report
    grade = f", grade {r.quality['grade']}" if r.quality else ""
    _say(f"unfolded by {r.method['name']} in {r.seconds['total']:.1f} s{grade} -> "
         f"{os.path.join(args.output_dir, 'unfolded.nrrd')}", sys.stdout)
    for w in r["warnings"]:
        _say(f"warning: {w}", sys.stderr)
    return 0


def _auto_points(args, ct, params):
    """--auto-points: (cardia, pylorus LPS mm, AutoPoints, stomach label value or None); PointError when unsure."""
    from .io import read_volume
    from .landmarks import auto_points_or_refuse, labels_on_grid

    labels = labels_on_grid(read_volume(args.mask), ct) if args.mask else None
    found = auto_points_or_refuse(ct, labels, threshold_hu=params.air_threshold_hu, max_snap_mm=params.max_snap_mm)
    value = args.mask_label if args.mask_label is not None else found.labels.get("stomach")
    return found.cardia_lps, found.pylorus_lps, found, value


def _has_evaluation() -> bool:
    """Whether the evaluation package (phantom marker metrics) is installed."""
    import importlib.util

    return importlib.util.find_spec("StomachUnfoldEval") is not None


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
    from .frontend import return_freed_memory
    from .params import parameter_specs

    return_freed_memory()  # for cases run here (--no-dask); the workers do it themselves
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
    from .io import check_output_folder

    _evaluation()
    if os.path.isdir(args.output):
        raise InputError(f"{args.output} is a folder; give the phantom's file name (e.g. {args.output}/phantom.nrrd)")
    check_output_folder(os.path.dirname(os.path.abspath(args.output)), 2_000_000)
    from StomachUnfoldEval.phantom import write_phantom

    if args.random is not None:
        from StomachUnfoldEval.random_stomach import write_random_stomach

        path, json_path = write_random_stomach(args.output, args.random, size=args.size)
        print(f"random stomach {args.random} written to {path} (truth: {json_path})")
        return 0

    spacing = None
    if args.spacing:
        spacing = parse_point(args.spacing)
        if not all(0.1 <= v <= 10.0 for v in spacing):
            raise InputError(f"--spacing must be three voxel sizes from 0.1 to 10 mm, got {args.spacing}")
    path, json_path = write_phantom(args.output, shape=args.shape, size=args.size, spacing=spacing,
                                    wall_thickness_mm=args.wall_thickness_mm, rugae=args.rugae,
                                    noise_hu=args.noise_hu, n_markers=args.markers, seed=args.seed,
                                    flip_direction=args.flip)
    print(f"phantom written to {path} (truth: {json_path})")
    return 0


#: The benchmark's parts (``bench --parts``).
BENCH_PARTS = ("shapes", "kappa", "sweep", "stability", "resolution", "peers", "real", "scaling", "stomachs", "memory",
               "zeroclicks", "meshsize", "autopoints", "hybrids", "fresh-4", "fresh-5", "fresh-6", "fresh-7",
               "fresh-8", "fresh-9", "surfacebound", "surfacebound-fresh", "clicks", "sizes", "hybrids-many", "phase",
               "oblique", "prone", "rolled", "contrast", "contents", "deep")
#: The parts a plain ``bench`` runs: all but the whole-mucosa references of the nine later held-out sets, the
#: clicks moved off their places and the judge's noise under a moved raster and depth samples (about 100 min here,
#: sizes 6 of them, hybrids-many 10, oblique 3, prone 3, rolled 3, contrast 2, contents 2, deep 3; surfacebound-fresh
#: about 85 min more, clicks 16, phase about 18).
BENCH_DEFAULT_PARTS = tuple(p for p in BENCH_PARTS if p not in ("surfacebound-fresh", "clicks", "phase"))


def _cmd_bench(args) -> int:
    from .io import check_output_folder

    _evaluation()
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = [p for p in parts if p not in BENCH_PARTS]
    if unknown or not parts:
        raise InputError(f"unknown benchmark part {', '.join(unknown) or '(none given)'}; choose from "
                         f"{', '.join(BENCH_PARTS)}")
    from StomachUnfoldEval.bench import check_methods, replot, run_benchmark

    methods = None if args.methods is None else check_methods(args.methods.split(","))
    check_output_folder(args.output_dir)

    if args.replot:
        made = replot(args.output_dir)
        print(f"bench: redrew {len(made)} PNGs and {args.output_dir}/results.md from results.json")
        return 0
    rows = run_benchmark(args.output_dir, quick=args.quick, full_size=args.full_size, scheduler=args.scheduler,
                         data_dir=args.data_dir, parts=tuple(parts), merge=args.merge, methods=methods)
    failed = sum(not r.get("ok") for r in rows)
    print(f"bench: {len(rows)} cases, {failed} failed (as data), results in {args.output_dir}/results.md")
    return 0


def _spaced_point(argv: list) -> str | None:
    """The message for a point given with spaces (``--cardia -54.9 27.7 64``), or None when every point is glued."""
    for i, a in enumerate(argv):
        for flag in ("--cardia", "--pylorus"):
            if a.startswith(flag + "=") or a == flag:
                value = a.split("=", 1)[1] if "=" in a else (argv[i + 1] if i + 1 < len(argv) else "")
                nxt = argv[i + 1:i + 3] if "=" in a else argv[i + 2:i + 4]
                numeric = [v for v in nxt if _is_number(v)]
                if ("," not in value and (len(value.split()) == 3 or len(numeric) == 2)):
                    return (f"{flag} takes one value R,A,S: use R,A,S with commas and no spaces, "
                            f"e.g. {flag} -54.9,27.7,64")
    return None


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


class _Signalled(KeyboardInterrupt):
    """SIGTERM or SIGHUP (``timeout``, a batch scheduler, ``docker stop``, a closed terminal), raised like Ctrl-C so
    that every ``finally`` removes what was half-written."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = signum


def _on_ctrl_c(signum, frame):
    CTRL_C.append(signum)  # an import that C code turned into an ImportError was a Ctrl-C; a dropped one is seen later
    raise KeyboardInterrupt


def _cancel_if_ctrl_c() -> None:
    """Raise KeyboardInterrupt if a Ctrl-C was pressed whose KeyboardInterrupt Python dropped (see CTRL_C)."""
    if CTRL_C:
        raise KeyboardInterrupt


def _in_import(frame) -> bool:
    """True while the interrupted code is inside an import (a frame of importlib's bootstrap on the stack)."""
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _on_signal(signum, frame):
    if _in_import(frame):
        # raised inside an import, a compiled module (VTK) turns it into an ImportError or is left half set up
        # (seen once as a crash, SIGSEGV): send the signal again in 50 ms, until the import is done
        import threading

        again = threading.Timer(0.05, os.kill, (os.getpid(), signum))
        again.daemon = True
        again.start()
        return
    for s in (signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if s is not None:
            signal.signal(s, signal.SIG_IGN)  # a second signal must not interrupt the clean-up
    raise _Signalled(signum)


def _catch_signals() -> None:
    """Ctrl-C as KeyboardInterrupt, SIGTERM and SIGHUP as _Signalled, in the main thread (elsewhere Python cannot set
    handlers); an ignored SIGINT (a background job) stays ignored."""
    import threading

    if threading.current_thread() is not threading.main_thread():
        return
    if signal.getsignal(signal.SIGINT) not in (signal.SIG_IGN, None):  # the package's early handler until here
        signal.signal(signal.SIGINT, _on_ctrl_c)
    for s in (signal.SIGTERM, getattr(signal, "SIGHUP", None)):
        if s is not None:
            signal.signal(s, _on_signal)


def _glue_points(argv: list) -> list:
    """"--cardia -54.9,27.7,64" would read as an option: glue point values to their flag."""
    for flag in ("--cardia", "--pylorus", "--spacing"):
        while flag in argv[:-1]:
            i = argv.index(flag)
            argv[i:i + 2] = [f"{flag}={argv[i + 1]}"]
    return argv


def main(argv=None) -> int:
    """Entry point of ``stomach-unfold``; returns the exit status (0 ok, 2 bad input or failure, 130 Ctrl-C,
    128 + the signal's number on SIGTERM (143) or SIGHUP (129)); no partial output is left on any of them."""
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, getattr(signal, "SIGHUP", None))
                if s is not None}
    if argv is None and CTRL_C:   # the command's early handler said so, and Python dropped its exit
        return 130
    CTRL_C.clear()                # called as a function: a Ctrl-C of an earlier call is not this one's
    try:
        _catch_signals()
        argv_list = _glue_points(list(sys.argv[1:] if argv is None else argv))
        spaced = _spaced_point(argv_list)
        if spaced:
            _say(f"error: {spaced}", sys.stderr)
            return 2
        args = build_parser().parse_args(argv_list)
        args.argv = argv_list
        _cancel_if_ctrl_c()
        if args.command == "unfold":
            return _cmd_unfold(args)
        if args.command == "phantom":
            return _cmd_phantom(args)
        if args.command == "batch":
            return _cmd_batch(args)
        return _cmd_bench(args)
    except _Signalled as e:
        _say(f"error: stopped by {signal.Signals(e.signum).name}; no partial output was left (a previous run's "
             "outputs are kept unless this run had finished writing)", sys.stderr)
        return 128 + e.signum
    except KeyboardInterrupt:
        _say("error: cancelled (Ctrl-C); no output was written", sys.stderr)
        return 130
    except ImportError:
        if not CTRL_C:  # a missing package: its own message
            raise
        _say("error: cancelled (Ctrl-C); no output was written", sys.stderr)  # NumPy's import turns it into this
        return 130
    except Cancelled as e:
        _say("error: cancelled (Ctrl-C); no output was written" if CTRL_C else f"error: {e}", sys.stderr)
        return 130
    except StomachUnfoldError as e:
        _say(f"error: {e}", sys.stderr)
        return 2
    except MemoryError:
        _say("error: out of memory; crop the volume or use a larger --grid-size / --output-spacing-mm", sys.stderr)
        return 2
    except OSError as e:  # a read or write the checks could not foresee (disk removed, quota, permissions)
        where = f" {e.filename}" if e.filename else ""
        _say(f"error: cannot access{where}: {e.strerror or e}; check the disk and the folder's permissions",
             sys.stderr)
        return 2
    finally:
        if argv is not None:  # called as a function (tests, batch): leave the caller's handlers as they were
            for s, h in previous.items():
                try:
                    signal.signal(s, h)
                except (ValueError, TypeError):
                    pass


if __name__ == "__main__":
    sys.exit(main())
