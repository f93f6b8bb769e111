"""The benchmark's memory part (issue 14): one run's peak resident memory against its crop, and its chart.

The run here is in this process (the benchmark spawns a fresh one per run); only the bookkeeping is checked,
no memory target (targets live in the benchmark, not in timed tests).
"""
import os

import pytest

from StomachUnfoldEval.memory import memory_markdown, memory_plot, memory_runs


def test_a_memory_row_has_the_peak_the_ct_and_the_crop_and_is_charted(tmp_path):
    matplotlib = pytest.importorskip("matplotlib", reason="the chart needs matplotlib (the bench extra)")
    matplotlib.use("Agg")  # as the benchmark does: no GUI backend (another test may have loaded Qt)
    import matplotlib.pyplot as plt
    rows = memory_runs((("straight-tiny", {"shape": "straight", "size": "tiny"}),), method="cylindrical",
                       isolated=lambda fn, *args: fn(*args))
    (r,) = rows
    assert r["ok"], r.get("error")
    assert r["group"] == "memory" and r["method"] == "cylindrical"
    assert 0 < r["crop_voxels"] <= r["size_ijk"][0] * r["size_ijk"][1] * r["size_ijk"][2]
    assert r["peak_memory_mb"] >= r["peak_before_write_mb"] >= r["after_read_mb"] > 0
    assert r["ratio_to_ct"] == pytest.approx(r["peak_memory_mb"] / r["ct_mb"])
    assert [s for s, _ in r["stage_peaks_mb"]][:2] == ["air region", "centerline"]
    made = []
    memory_plot(rows, str(tmp_path), made, plt)
    assert made == ["memory.png"] and os.path.getsize(tmp_path / "memory.png") > 5000
    text = "\n".join(memory_markdown(rows))
    assert "straight-tiny/memory" in text and f"**{r['peak_memory_mb']:.0f}**" in text
