"""Work beside the main thread (spare_core.Beside): the same result as run in line, abandoned and joined on leaving."""
import threading
import time

import numpy as np
import pytest
from StomachUnfoldLib import spare_core
from StomachUnfoldLib.spare_core import Beside


def _threads():
    return {t for t in threading.enumerate() if t.name == "stomach-unfold-beside"}


def _slow_sum(n, check):
    total = 0
    for i in range(n):
        check()
        time.sleep(0.002)
        total += i
    return total


@pytest.mark.parametrize("spare", [True, False])
def test_the_result_is_the_same_beside_or_in_line(monkeypatch, spare):
    monkeypatch.setattr(spare_core, "SPARE_CORES", spare)
    with Beside(_slow_sum, 20) as job:
        assert job.started is spare
        assert job.result() == sum(range(20))
    assert not _threads()


def test_an_error_in_the_work_is_raised_by_result_and_only_then(monkeypatch):
    monkeypatch.setattr(spare_core, "SPARE_CORES", True)

    def broken(check):
        raise ValueError("broken on purpose")
    with Beside(broken) as job:
        pass                                    # never asked for: its error goes with it
    with pytest.raises(ValueError, match="broken on purpose"):
        with Beside(broken) as job:
            job.result()
    assert not _threads()


def test_leaving_the_block_abandons_the_work_and_joins_its_thread(monkeypatch):
    monkeypatch.setattr(spare_core, "SPARE_CORES", True)
    steps = []

    def endless(check):
        while True:
            check()
            steps.append(1)
            time.sleep(0.001)
    t = time.perf_counter()
    with pytest.raises(KeyError):
        with Beside(endless) as job:
            assert job.started
            time.sleep(0.05)
            raise KeyError("the main thread fails")   # e.g. a Cancel or a signal in the main thread
    assert time.perf_counter() - t < 5.0 and steps and not _threads()
    n = len(steps)
    time.sleep(0.02)
    assert len(steps) == n                              # stopped: nothing runs after the block


def test_work_goes_beside_only_where_a_core_is_spare(monkeypatch):
    main = threading.get_ident()
    monkeypatch.setattr(spare_core, "SPARE_CORES", None)
    monkeypatch.setattr(spare_core, "_cores", lambda: 2)
    with Beside(threading.get_ident, checked=False) as job:
        assert job.started and job.result() != main
    monkeypatch.setattr(spare_core, "_cores", lambda: 1)
    with Beside(threading.get_ident, checked=False) as job:
        assert not job.started and job.result() == main      # one core: nothing beside
    monkeypatch.setattr(spare_core, "_cores", lambda: 2)
    monkeypatch.setattr(spare_core, "SPARE_CORES", False)     # a batch worker: the other cores run other cases
    with Beside(threading.get_ident, checked=False) as job:
        assert not job.started and job.result() == main
    from StomachUnfoldLib.batch import run_case_in_worker
    monkeypatch.setattr("StomachUnfoldLib.batch.run_case", lambda job, record: spare_core.spare_cores())
    monkeypatch.setattr(spare_core, "SPARE_CORES", None)
    assert run_case_in_worker({}, {}) is False


def test_the_default_run_is_the_same_with_work_beside_and_without(monkeypatch):
    # the tiny J folds with the heavy distance terms: the light terms' map runs (beside the heavy one, or after it)
    # and is kept, the grade's mucosa points are drawn beside the method; the CT is scanned on file beside the
    # parameter check
    from StomachUnfoldEval.phantom import make_phantom
    from StomachUnfoldLib.io import read_volume, write_volume
    from StomachUnfoldLib.pipeline import UnfoldParameters, unfold

    ct, truth = make_phantom("j", "tiny")

    def run(tmp):
        path = str(tmp / "ct.nrrd")
        write_volume(ct, path)  # gzip NRRD
        res = unfold(read_volume(path, stream=True), np.array(truth["cardia_lps"]), np.array(truth["pylorus_lps"]),
                     UnfoldParameters(method="isometric", wall_thickness_mm=4.0))
        rep = res.report
        return res.unfolded.array, rep["quality"], {k: v for k, v in rep["method"].items() if "seconds" not in k}

    import pathlib
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        monkeypatch.setattr(spare_core, "SPARE_CORES", True)
        a_beside, q_beside, m_beside = run(pathlib.Path(d))
        monkeypatch.setattr(spare_core, "SPARE_CORES", False)
        a_line, q_line, m_line = run(pathlib.Path(d))
    assert "fold_retry_mm2" in m_line and "light_retry_mm2" in m_line
    np.testing.assert_array_equal(a_beside, a_line)
    assert q_beside == q_line and m_beside == m_line
    assert not _threads()


def test_a_bad_parameter_stops_the_scan_of_a_ct_on_file(tmp_path, monkeypatch):
    from StomachUnfoldEval.phantom import make_phantom
    from StomachUnfoldLib.errors import InputError
    from StomachUnfoldLib.io import read_volume, write_volume
    from StomachUnfoldLib.pipeline import UnfoldParameters, unfold

    monkeypatch.setattr(spare_core, "SPARE_CORES", True)
    ct, truth = make_phantom("j", "tiny")
    write_volume(ct, str(tmp_path / "ct.nrrd"))
    vol = read_volume(str(tmp_path / "ct.nrrd"), stream=True)
    bad = UnfoldParameters(method="isometric", air_threshold_hu=5000.0)
    with pytest.raises(InputError, match="air_threshold_hu must be at least"):
        unfold(vol, np.array(truth["cardia_lps"]), np.array(truth["pylorus_lps"]), bad)
    assert not _threads()


def test_a_signal_handled_as_the_work_starts_still_stops_and_joins_it(monkeypatch):
    # a Ctrl-C or SIGTERM handled just after the thread began: __enter__ raises, so no __exit__ would run; the
    # work must not outlive the block (at the interpreter's exit a thread inside VTK or ITK aborts the process)
    monkeypatch.setattr(spare_core, "SPARE_CORES", True)
    real = threading.Thread.start

    def start(self):
        real(self)
        raise KeyboardInterrupt

    def endless(check):
        while True:
            check()
            time.sleep(0.001)
    monkeypatch.setattr(threading.Thread, "start", start)
    with pytest.raises(KeyboardInterrupt):
        with Beside(endless):
            pass
    monkeypatch.undo()
    assert not _threads()
