"""The lumen found against the lumen a random stomach drew (StomachUnfoldEval.lumen_truth)."""
import numpy as np
import pytest

from StomachUnfoldEval.lumen_truth import lumen_against_drawn
from StomachUnfoldEval.random_stomach import random_stomach
from StomachUnfoldLib.preprocessing import air_region


@pytest.fixture(scope="module")
def stomach_with_water():
    ct, truth = random_stomach(3, "tiny", fluid=True, fluid_depth_fraction=0.35)
    assert truth["fluid_level_lps_y"] is not None
    return ct, truth


def test_the_lumen_found_holds_nearly_all_the_drawn_water(stomach_with_water):
    ct, truth = stomach_with_water
    lumen, info = air_region(ct, truth["cardia_lps"], truth["pylorus_lps"])
    assert info["fluid_voxels"] > 0
    r = lumen_against_drawn(ct, truth, lumen)
    assert r["drawn"] > 500 and r["level_lps_y"] == truth["fluid_level_lps_y"]
    assert r["missed_fraction"] < 0.1 and r["over"] < 0.1 * r["drawn"]
    # the air alone leaves the water out, and the whole lumen counted against the whole drawn lumen is larger
    air, _ = air_region(ct, truth["cardia_lps"], truth["pylorus_lps"], fluid_max_hu=-1000.0)
    r_air = lumen_against_drawn(ct, truth, air)
    assert r_air["drawn"] == r["drawn"] and r_air["missed_fraction"] > 0.9 and r_air["missed_depth_mm"][1] > 3.0
    r_all = lumen_against_drawn(ct, truth, lumen, region="all")
    assert r_all["drawn"] > r["drawn"] and r_all["missed_fraction"] < 0.1


def test_a_mask_of_everything_is_all_over_and_a_wrong_grid_is_refused(stomach_with_water):
    ct, truth = stomach_with_water
    full = np.ones(tuple(ct.size[::-1]), bool)
    r = lumen_against_drawn(ct, truth, full)
    assert r["missed"] == 0 and r["over"] > r["drawn"]
    with pytest.raises(ValueError, match="shape"):
        lumen_against_drawn(ct, truth, full[:-1])
    with pytest.raises(ValueError, match="region"):
        lumen_against_drawn(ct, truth, full, region="fluid")


def test_a_stomach_without_water_has_nothing_under_a_level():
    ct, truth = random_stomach(3, "tiny", fluid=False)
    r = lumen_against_drawn(ct, truth, np.zeros(tuple(ct.size[::-1]), bool))
    assert r["level_lps_y"] is None and r["drawn"] == 0 and r["missed"] == 0
