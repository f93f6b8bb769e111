"""Cohorts (issue 14): ``stomach-unfold batch`` on a local Dask cluster and on a scheduler started apart, resumable.

Real parts throughout: tiny phantoms written to files, the command line's ``main``, Dask's LocalCluster, and a
``dask scheduler`` and ``dask worker`` started as separate processes on localhost.
"""
import csv
import hashlib
import json
import os
import socket
import subprocess
import sys
import time

import pytest

from StomachUnfoldLib.batch import (OUTPUT_FILES, RECORD_NAME, WORKER_OVERHEAD_BYTES, parse_sweep, read_manifest,
                                    table1, worker_plan, write_summary)
from StomachUnfoldLib.cli import main
from StomachUnfoldLib.errors import InputError

pytest.importorskip("dask.distributed", reason="the batch tests need dask[distributed] (the bench extra)")


@pytest.fixture(scope="module")
def cohort(tmp_path_factory):
    """Two tiny phantoms (straight, bent) with their points, in one folder."""
    from StomachUnfoldEval.phantom import write_phantom

    d = tmp_path_factory.mktemp("cohort")
    for shape in ("straight", "bent"):
        write_phantom(str(d / f"{shape}.nrrd"), shape=shape, size="tiny")
    return d


def _manifest(folder, kappa_bent="0.5"):
    # the cylindrical method keeps the tests fast; the method and kappa columns are parameter overrides
    text = ("case,input,points,method,kappa\n"
            "straight,straight.nrrd,straight.mrk.json,cylindrical,\n"
            f"bent,bent.nrrd,bent.mrk.json,cylindrical,{kappa_bent}\n"
            "missing,no_such_ct.nrrd,straight.mrk.json,cylindrical,\n")
    path = folder / "manifest.csv"
    path.write_text(text)
    return str(path)


def _summary(out):
    with open(os.path.join(out, "summary.csv"), newline="") as f:
        return {r["case"]: r for r in csv.DictReader(f)}


def _stamp(out, case):
    """mtime (ns) and sha256 of every output file of a case."""
    res = {}
    for name in OUTPUT_FILES + (RECORD_NAME,):
        p = os.path.join(out, case, name)
        res[name] = (os.stat(p).st_mtime_ns, hashlib.sha256(open(p, "rb").read()).hexdigest())
    return res


def test_a_local_cluster_batch_reports_each_case_and_reruns_only_what_changed(cohort, tmp_path, capsys):
    out = str(tmp_path / "out")
    manifest = _manifest(cohort)
    assert main(["batch", manifest, "--output-dir", out, "--workers", "2", "--quiet"]) == 1
    rows = _summary(out)
    assert list(rows) == ["straight", "bent", "missing"]
    assert [rows[c]["status"] for c in rows] == ["ok", "ok", "error"]
    assert "no_such_ct.nrrd" in rows["missing"]["error"] and "does not exist" in rows["missing"]["error"]
    assert "no_such_ct.nrrd" in capsys.readouterr().err
    # two worker processes of the local cluster ran the two cases, not this process
    pids = {rows[c]["worker"].rsplit(":", 1)[1] for c in ("straight", "bent")}
    assert len(pids) == 2 and str(os.getpid()) not in pids
    for c in ("straight", "bent"):
        assert rows[c]["grade"] in ("excellent", "good", "fair", "bad") and rows[c]["method"] == "cylindrical"
        assert all(os.path.exists(os.path.join(out, c, n)) for n in OUTPUT_FILES)
        assert json.load(open(os.path.join(out, c, "report.json")))["parameters"]["method"] == "cylindrical"
    doc = json.load(open(os.path.join(out, "summary.json")))
    assert (doc["cases"], doc["ok"], doc["error"]) == (3, 2, 1)
    assert os.path.getsize(os.path.join(out, "contact_sheet.png")) > 1000
    before = {c: _stamp(out, c) for c in ("straight", "bent")}

    # a rerun reuses both done cases: their outputs are untouched
    assert main(["batch", manifest, "--output-dir", out, "--workers", "2", "--quiet"]) == 1
    rows = _summary(out)
    assert [rows[c]["reused"] for c in ("straight", "bent")] == ["True", "True"]
    assert {c: _stamp(out, c) for c in ("straight", "bent")} == before

    # a changed kappa column reruns that case alone
    manifest = _manifest(cohort, kappa_bent="0.3")
    assert main(["batch", manifest, "--output-dir", out, "--workers", "2", "--quiet"]) == 1
    rows = _summary(out)
    assert (rows["straight"]["reused"], rows["bent"]["reused"], rows["bent"]["status"]) == ("True", "False", "ok")
    assert _stamp(out, "straight") == before["straight"]
    assert _stamp(out, "bent")["unfolded.nrrd"][0] > before["bent"]["unfolded.nrrd"][0]
    assert json.load(open(os.path.join(out, "bent", "report.json")))["parameters"]["solver"]["kappa"] == 0.3

    # the same files moved to another folder are the same inputs (named by content): nothing reruns
    import shutil

    moved = tmp_path / "moved"
    shutil.copytree(cohort, moved)
    stamps = {c: _stamp(out, c) for c in ("straight", "bent")}
    assert main(["batch", _manifest(moved, kappa_bent="0.3"), "--output-dir", out, "--workers", "2", "--quiet"]) == 1
    rows = _summary(out)
    assert [rows[c]["reused"] for c in ("straight", "bent")] == ["True", "True"]
    assert {c: _stamp(out, c)["unfolded.nrrd"] for c in stamps} == {c: stamps[c]["unfolded.nrrd"] for c in stamps}


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stop(proc):
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def test_the_scheduler_address_runs_cases_on_a_separately_started_worker(cohort, tmp_path):
    from dask.distributed import Client

    dask_cmd = os.path.join(os.path.dirname(sys.executable), "dask")
    if not os.path.exists(dask_cmd):
        pytest.skip(f"no dask command beside {sys.executable}")
    port = _free_port()
    addr = f"tcp://127.0.0.1:{port}"
    log = open(tmp_path / "dask.log", "w")
    procs = []
    try:
        procs.append(subprocess.Popen([dask_cmd, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                       "--no-dashboard"], stdout=log, stderr=log))
        procs.append(subprocess.Popen([dask_cmd, "worker", addr, "--nthreads", "1", "--no-nanny",
                                       "--no-dashboard", "--memory-limit", "2GiB"], stdout=log, stderr=log))
        with Client(addr, timeout="60s") as client:
            client.wait_for_workers(1, timeout=60)
        (tmp_path / "one.csv").write_text("case,input,points,method\n"
                                          f"straight,{cohort / 'straight.nrrd'},{cohort / 'straight.mrk.json'},"
                                          "cylindrical\n")
        out = str(tmp_path / "out")
        assert main(["batch", str(tmp_path / "one.csv"), "--output-dir", out, "--scheduler", addr, "--quiet"]) == 0
        row = _summary(out)["straight"]
        assert row["status"] == "ok"
        assert row["worker"].rsplit(":", 1)[1] == str(procs[1].pid)  # the worker process started above ran it
    finally:
        for p in reversed(procs):
            _stop(p)
        log.close()
    assert all(p.returncode is not None for p in procs)


def test_manifest_and_sweep_errors_are_one_line_and_table1_counts_the_paper_categories(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("case,input,points,kapa\na,a.nrrd,a.mrk.json,0.2\n")
    with pytest.raises(InputError, match="unknown column.*kapa"):
        read_manifest(bad)
    assert main(["batch", str(bad), "--output-dir", str(tmp_path / "o"), "--quiet"]) == 2
    assert capsys.readouterr().err.startswith("error: ")
    (tmp_path / "twice.csv").write_text("case,input,points\na,a.nrrd,p.json\na,b.nrrd,p.json\n")
    with pytest.raises(InputError, match="used twice"):
        read_manifest(tmp_path / "twice.csv")
    assert parse_sweep("kappa=0.2,0.5") == ("kappa", ["0.2", "0.5"])
    for text in ("kappa", "kapa=1", "kappa=a,b", "kappa=1,1"):
        with pytest.raises(InputError):
            parse_sweep(text)
    rows = [{"case": "a", "sweep": "kappa=0.2", "status": "ok", "grade": "good", "overlap_area_fraction": 0.02},
            {"case": "b", "sweep": "kappa=0.2", "status": "ok", "grade": "bad", "hole_area_fraction": 0.1},
            {"case": "a", "sweep": "kappa=1", "status": "error", "error": "x"}]
    t = table1(rows)
    assert t["kappa=0.2"] == {"good": 1, "overlapping": 1, "bending": 0, "broken": 1, "n": 2, "failed": 0}
    assert t["kappa=1"]["failed"] == 1 and t["kappa=1"]["n"] == 0
    write_summary(str(tmp_path), rows)
    assert json.load(open(tmp_path / "summary.json"))["table1"] == json.loads(json.dumps(t))


def test_local_workers_are_sized_from_the_largest_cases_memory_estimate(tmp_path):
    from StomachUnfoldLib.geometry import Volume
    from StomachUnfoldLib.io import write_volume
    import numpy as np

    small, big = str(tmp_path / "s.nrrd"), str(tmp_path / "b.nrrd")
    write_volume(Volume(np.zeros((20, 30, 30), np.int16)), small)
    write_volume(Volume(np.zeros((200, 400, 400), np.int16)), big)
    n1, lim_small = worker_plan([{"input": small}] * 4, cores=4, available_bytes=64 * 2**30)
    n2, lim_big = worker_plan([{"input": small}, {"input": big}], cores=4, available_bytes=64 * 2**30)
    assert n1 == 4 and n2 == 2 and lim_big > lim_small
    ct_bytes = 200 * 400 * 400 * 2
    assert lim_big >= 1.25 * 2 * ct_bytes + WORKER_OVERHEAD_BYTES  # the CT, its working memory, headroom, the worker
    _, lim_mask = worker_plan([{"input": big, "mask": big}], cores=4, available_bytes=64 * 2**30)
    assert lim_mask > lim_big  # a mask resampled onto the CT grid costs whole-grid masks
    n3, _ = worker_plan([{"input": big}] * 8, cores=8, available_bytes=int(2.5 * lim_big))
    assert n3 == 2  # as many as the memory allows


def test_the_slicer_console_call_runs_a_folder_here_one_case_after_the_other(cohort, tmp_path):
    from StomachUnfoldLib.batch import manifest_from_folder, run_batch

    cases = manifest_from_folder(cohort)
    assert [c["case"] for c in cases] == ["bent", "straight"]
    seen = []
    rows = run_batch(cases[1:], str(tmp_path / "out"), base_params={"method": "cylindrical"}, contact=False,
                     progress=lambda stage, fraction: seen.append((stage, fraction)))
    assert [r["status"] for r in rows] == ["ok"] and rows[0]["worker"].endswith(f":{os.getpid()}")
    assert seen[-1] == ("cases 1/1 straight", 1.0)
    assert os.path.exists(tmp_path / "out" / "straight" / "view.png")


def test_a_worker_killed_for_memory_is_an_error_row_not_a_stop(cohort, tmp_path):
    import logging

    import dask
    from dask.distributed import Client, LocalCluster

    from StomachUnfoldLib.batch import manifest_from_folder, run_batch

    cases = manifest_from_folder(cohort)  # bent, straight
    config = {"distributed.scheduler.allowed-failures": 0, "distributed.worker.memory.pause": False,
              "distributed.worker.memory.target": False, "distributed.worker.memory.spill": False,
              "distributed.worker.memory.monitor-interval": "20ms"}
    with dask.config.set(config):  # a worker limit below what a run needs: the nanny kills it mid-case
        with LocalCluster(n_workers=1, threads_per_worker=1, memory_limit="200MiB", dashboard_address=":0",
                          silence_logs=logging.CRITICAL) as cluster, Client(cluster) as client:
            rows = run_batch(cases, str(tmp_path / "out"), executor=client.get_executor(pure=False),
                             base_params={"method": "cylindrical"}, contact=False)
    assert [r["status"] for r in rows] == ["error", "error"]
    assert all(r["error"].startswith("KilledWorker: the worker running it died (killed for memory") for r in rows)
    assert _summary(str(tmp_path / "out"))["bent"]["status"] == "error"
