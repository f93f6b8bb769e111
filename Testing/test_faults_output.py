"""Faults round two: the output side (folder checks, a full disk), signals, and inputs that used to pass silently.

Signals, the closed pipe and the full disk run the real command in real processes; the full disk is a real tmpfs
where this machine lets the test mount one (root, or a user namespace), else the test skips saying why.
"""
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from StomachUnfoldLib.cli import main
from StomachUnfoldLib.errors import InputError, OutputError, PointError
from StomachUnfoldLib.pipeline import OUTPUT_NAMES

#: the fastest whole run (a peer method, no grade): these tests are about the files, not the view
FAST = ("--method", "cylindrical", "--no-quality", "--quiet")
# the console script's own two lines, with a marker once the interpreter has started (site imports done)
ENTRY = ("import sys; sys.argv[0] = 'stomach-unfold'; sys.stderr.write('ready\\n'); sys.stderr.flush(); "
         "from StomachUnfoldLib.cli import main; sys.exit(main())")


def _command(*args):
    return [sys.executable, "-c", ENTRY, *map(str, args)]


def _start(*args, stdout=subprocess.PIPE):
    # Ctrl-C at its default in the child, as on a terminal (a test run started in the background ignores it)
    proc = subprocess.Popen(_command(*args), stdout=stdout, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert proc.stderr.readline() == "ready\n"
    return proc


def _files(folder):
    """{name: bytes} of every file in a folder, hidden ones included (a staging folder counts as a name)."""
    return {n: (open(os.path.join(folder, n), "rb").read() if os.path.isfile(os.path.join(folder, n)) else None)
            for n in sorted(os.listdir(folder))}


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    """A tiny phantom and one complete run of the command into ``prev/``, made with stdout a closed pipe."""
    root = tmp_path_factory.mktemp("faults2")
    from StomachUnfoldEval.phantom import write_phantom

    ct, _ = write_phantom(str(root / "ph.nrrd"), shape="j", size="tiny")
    pts = root / "ph.mrk.json"
    prev = root / "prev"
    r, w = os.pipe()
    os.close(r)  # the reader left before the run ended (`stomach-unfold ... | head -0`)
    proc = subprocess.run(_command("unfold", ct, "--points", pts, "-o", prev, *FAST), stdout=w,
                          stderr=subprocess.PIPE, text=True, timeout=300)
    os.close(w)
    return dict(root=root, ct=ct, pts=str(pts), prev=prev, closed_pipe=proc)


def test_a_closed_stdout_pipe_gives_no_traceback_and_complete_outputs(case):
    proc = case["closed_pipe"]
    assert proc.returncode == 0 and "Traceback" not in proc.stderr, proc.stderr
    names = set(os.listdir(case["prev"]))
    assert set(OUTPUT_NAMES) - {"landmarks_unfolded.mrk.json"} == names


def test_outputs_get_the_users_file_mode(case):
    umask = os.umask(0o022)
    os.umask(umask)
    modes = {n: os.stat(case["prev"] / n).st_mode & 0o777 for n in os.listdir(case["prev"])}
    assert set(modes.values()) == {0o666 & ~umask}, modes


def _run(argv, capsys):
    rc = main([str(a) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    return rc, err[-1] if err else ""


def test_output_folder_problems_are_refused_before_any_work(case, tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    base = ["unfold", case["ct"], "--points", case["pts"], "--quiet", "-o"]
    for out, text in ((a_file, "is a file, not a folder"), (a_file / "sub", "is a file"), ("", "output folder is empty"),
                      ("/proc/stomach", "/proc file system"), ("/sys/x", "/sys file system")):
        rc, err = _run(base + [out], capsys)
        assert rc == 2 and err.startswith("error: ") and text in err, (out, err)
    assert a_file.read_text() == "x" and not (a_file.parent / "sub").exists()


def test_the_output_folder_may_not_hold_the_input(case, tmp_path, capsys):
    out = tmp_path / "o"
    shutil.copytree(case["prev"], out)
    shutil.copy(case["ct"], out / "unfolded.nrrd")  # a CT that happens to bear an output's name
    before = _files(out)
    rc, err = _run(["unfold", out / "unfolded.nrrd", "--points", case["pts"], "-o", out, "--quiet"], capsys)
    assert rc == 2 and "holds the input" in err and "would overwrite" in err, err
    rc, err = _run(["unfold", case["ct"], "--points", case["pts"], "--landmarks", out / "incision.mrk.json", "-o", out,
                    "--quiet"], capsys)
    assert rc == 2 and "holds the input" in err, err
    assert _files(out) == before
    dicom = tmp_path / "dicom"  # a DICOM folder as its own output folder, or one inside it
    dicom.mkdir()
    for o in (dicom, dicom / "out"):
        rc, err = _run(["unfold", dicom, "--points", case["pts"], "-o", o, "--quiet"], capsys)
        assert rc == 2 and "inside the input folder" in err, err
    assert os.listdir(dicom) == []


def _mount_tmpfs(where, size_kb, read_only=False):
    """Mount a tmpfs of ``size_kb`` at ``where`` (skip, saying why, where this user may not)."""
    os.makedirs(where, exist_ok=True)
    opts = f"size={size_kb}k" + (",ro" if read_only else "")
    p = subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(where)], capture_output=True, text=True)
    if p.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({p.stderr.strip() or 'mount failed'}): needs root")
    return where


def _umount(where):
    subprocess.run(["umount", str(where)], capture_output=True)


def _read_only_folder(where):
    """A read-only folder: a read-only tmpfs for root (whom permissions do not stop), else a folder made 0555."""
    if os.geteuid() == 0:
        return _mount_tmpfs(where, 1024, read_only=True)
    os.makedirs(where)
    os.chmod(where, 0o555)
    return where


def test_a_read_only_folder_is_refused_before_any_work(case, tmp_path, capsys):
    ro = _read_only_folder(tmp_path / "ro")
    try:
        rc, err = _run(["unfold", case["ct"], "--points", case["pts"], "-o", ro / "out", "--quiet"], capsys)
        assert rc == 2 and "read-only" in err and "writable --output-dir" in err, err
        rc, err = _run(["phantom", ro / "ph.nrrd", "--size", "tiny"], capsys)
        assert rc == 2 and "read-only" in err, err
        assert os.listdir(ro) == []
    finally:
        _umount(ro)
        os.chmod(ro, 0o755)


def test_a_disk_too_small_for_the_estimated_outputs_is_refused_before_the_run(case, tmp_path, capsys):
    tiny = _mount_tmpfs(tmp_path / "tiny", 64)
    try:
        rc, err = _run(["unfold", case["ct"], "--points", case["pts"], "-o", tiny / "out", "--quiet"], capsys)
        assert rc == 2 and "MB are free" in err and "need about" in err, err
        assert os.listdir(tiny) == []
    finally:
        _umount(tiny)


def test_a_disk_that_fills_while_writing_leaves_the_previous_outputs_and_no_staging_folder(case, tmp_path):
    from StomachUnfoldLib.io import estimate_output_bytes, read_volume

    need = sum(os.path.getsize(case["prev"] / n) for n in os.listdir(case["prev"]))
    estimate = estimate_output_bytes(read_volume(case["ct"]))
    assert estimate < need, "the up-front estimate must stay below a real run's outputs"
    # room for the previous run (in 4 KiB pages) and just over the estimate, less than a second set: full while writing
    pages_kb = sum(-(-os.path.getsize(case["prev"] / n) // 4096) * 4 for n in os.listdir(case["prev"]))
    disk = _mount_tmpfs(tmp_path / "disk", pages_kb + estimate // 1024 + 16)
    try:
        out = disk / "out"
        shutil.copytree(case["prev"], out)
        before = _files(out)
        proc = subprocess.run(_command("unfold", case["ct"], "--points", case["pts"], "-o", out, *FAST),
                              capture_output=True, text=True, timeout=300)
        assert proc.returncode == 2, (proc.returncode, proc.stderr)  # not 134/139: no native abort
        last = proc.stderr.strip().splitlines()[-1]
        assert last.startswith("error: cannot write the outputs") and "No space left" in last, proc.stderr
        assert "Traceback" not in proc.stderr
        assert _files(out) == before  # no .unfold-* folder, the previous outputs intact
        assert shutil.disk_usage(disk).free > estimate  # the disk is not left full
    finally:
        _umount(disk)


def _wait_for_staging(folder, proc, timeout=240.0):
    t = time.time()
    while time.time() - t < timeout and proc.poll() is None:
        if any(n.startswith(".unfold-") for n in os.listdir(folder)):
            return True
        time.sleep(0.002)
    return False


def test_sigterm_while_writing_keeps_the_previous_outputs(case, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(case["prev"], out)
    before = _files(out)
    proc = _start("unfold", case["ct"], "--points", case["pts"], "-o", out, *FAST)
    assert _wait_for_staging(out, proc), "the run never began writing"
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 143, (proc.returncode, stderr)
    assert "stopped by SIGTERM" in stderr and "Traceback" not in stderr, stderr
    assert _files(out) == before


def test_sighup_during_the_run_leaves_nothing(case, tmp_path):
    out = tmp_path / "new"
    # not --quiet: the first stage's line says the run is under way (a fixed sleep raced the run's end once it took
    # about as long: a signal during the interpreter's exit gets the default action)
    proc = _start("unfold", case["ct"], "--points", case["pts"], "-o", out, *[a for a in FAST if a != "--quiet"])
    first = proc.stderr.readline()
    assert first.startswith("reading the CT"), first
    proc.send_signal(signal.SIGHUP)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGHUP and "stopped by SIGHUP" in stderr, (proc.returncode, stderr)
    assert not out.exists() or os.listdir(out) == []


def test_sigterm_inside_an_import_waits_for_the_import_to_finish(case, tmp_path):
    # a SIGTERM raised inside an import: a compiled module (VTK) turns the exception into an ImportError (a traceback
    # and status 1) or is left half set up (it crashed once, SIGSEGV); the command holds the signal until the import
    # is done. Here a pure-Python module, imported while the view is drawn, sends it and then marks its end
    (tmp_path / "slow_module.py").write_text(
        "import os, pathlib, signal, time\nos.kill(os.getpid(), signal.SIGTERM)\ntime.sleep(0.3)\n"
        f"pathlib.Path({str(tmp_path / 'imported')!r}).write_text('done')\n")
    child = (f"import sys; sys.argv[0] = 'stomach-unfold'; sys.path.insert(0, {str(tmp_path)!r})\n"
             "from StomachUnfoldLib import cli, figure\n"
             "draw = figure.write_view\n"
             "def write_view(*a, **k):\n    import slow_module\n    return draw(*a, **k)\n"
             "figure.write_view = write_view\n"
             "sys.exit(cli.main())\n")
    out = tmp_path / "new"
    proc = subprocess.run([sys.executable, "-c", child, "unfold", case["ct"], "--points", case["pts"], "-o", out,
                           *FAST], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 143 and "Traceback" not in proc.stderr, (proc.returncode, proc.stderr)
    assert "stopped by SIGTERM" in proc.stderr
    assert (tmp_path / "imported").read_text() == "done"          # the import ran to its end first
    assert not out.exists() or os.listdir(out) == []


def test_a_ctrl_c_that_python_drops_in_a_weakref_callback_still_cancels(case, tmp_path):
    # Python drops what a signal handler raises while a weakref callback runs (the import system's module locks have
    # one; CI once saw it at 0.06 s after start): the run went on and wrote its outputs, status 0. Here the callback
    # is made to run as the unfolding starts, and the Ctrl-C comes inside it
    child = ("import os, signal, sys, time, weakref\n"
             "sys.argv[0] = 'stomach-unfold'\n"
             "from StomachUnfoldLib import cli, pipeline\n"
             "real = pipeline.unfold\n"
             "class Thing:\n    pass\n"
             "def unfold(*a, **k):\n"
             "    t = Thing()\n"
             "    def cb(ref):\n        os.kill(os.getpid(), signal.SIGINT)\n        time.sleep(0.2)\n"
             "    r = weakref.ref(t, cb)\n"
             "    del t\n"
             "    return real(*a, **k)\n"
             "pipeline.unfold = unfold\n"
             "sys.exit(cli.main())\n")
    out = tmp_path / "new"
    proc = subprocess.run([sys.executable, "-c", child, "unfold", case["ct"], "--points", case["pts"], "-o", out,
                           "--method", "cylindrical", "--no-quality"], capture_output=True, text=True, timeout=120,
                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    assert proc.returncode == 130 and "Traceback" not in proc.stderr, (proc.returncode, proc.stderr)
    assert proc.stderr.strip().splitlines()[-1] == "error: cancelled (Ctrl-C); no output was written"
    assert not out.exists() or os.listdir(out) == []


@pytest.mark.parametrize("delay", [0.03, 0.06, 0.1])  # the imports: NumPy alone took ~0.1 s
def test_ctrl_c_while_the_command_starts_gives_one_line(case, delay):
    proc = _start("unfold", case["ct"], "--points", case["pts"], "-o", case["root"] / "never")
    time.sleep(delay)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=60)
    assert proc.returncode == 130 and "Traceback" not in stderr, (proc.returncode, stderr)
    assert stderr.strip().splitlines() == ["error: cancelled (Ctrl-C); no output was written"]
