"""The package's one table of units in key names (seanv_analysis.jsonable)."""
from __future__ import annotations

import pytest

from seanv_analysis.jsonable import UNIT_SUFFIXES, unit_of_key, unit_suffix


def test_a_longer_suffix_comes_before_the_shorter_ones_it_ends_with():
    names = list(UNIT_SUFFIXES)
    for i, short in enumerate(names):
        for long in names[i + 1:]:
            assert not long.endswith(short), f"{long} after {short}: keys ending {long} get {short}'s unit"


@pytest.mark.parametrize("key,expected", [
    ("C_mm3_s_deg2_sqrtMPa", ("C", "mm^3/(s deg^2 MPa^0.5)")),
    ("alpha_mm3_s_deg2", ("alpha", "mm^3/(s deg^2)")),
    ("rmse_mm3_s", ("rmse", "mm^3/s")),
    ("gain_mm3_s_per_mm", ("gain", "mm^3/s per mm")),
    ("lag_s", ("lag", "s")),
    ("load_mpag", ("load", "MPaG")),
    ("dp_mpa", ("dp", "MPa")),
    ("heldout_MPa", ("heldout", "MPa")),
    ("train_N", ("train", "N")),
    ("length_m", ("length", "m")),
    ("z0_mm", ("z0", "mm")),
    ("cam_deg", ("cam", "deg")),
    ("run_id", None), ("n_runs", None), ("_s", None),
])
def test_unit_of_key(key, expected):
    assert unit_of_key(key) == expected


def test_unit_suffix_is_the_first_of_its_unit_and_round_trips():
    assert unit_suffix("mm^3/s") == "_mm3_s"
    assert unit_suffix("MPa") == "_MPa"   # the identification's score keys (not "_mpa")
    assert unit_suffix("N") == "_N"
    assert unit_suffix("%") == "_pct"
    assert unit_suffix("furlong") is None
    for unit in UNIT_SUFFIXES.values():
        assert unit_of_key("x" + unit_suffix(unit)) == ("x", unit)
