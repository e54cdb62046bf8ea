"""The package's one table of units in key names (seanv_analysis.units)."""
from __future__ import annotations

import pytest

from seanv_analysis.units import UNIT_SUFFIXES, unit_of_key, unit_suffix


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
    assert unit_suffix("MPa") == "_mpa"   # one spelling (issue 33, point 4: not heldout_MPa)
    assert unit_suffix("N") == "_n"       # as coulomb_friction_n (not train_N)
    assert unit_suffix("%") == "_pct"
    assert unit_suffix("furlong") is None
    for unit in UNIT_SUFFIXES.values():
        assert unit_of_key("x" + unit_suffix(unit)) == ("x", unit)


def test_the_contract_columns_and_the_unit_table_agree():
    """contract.toml's unit of every column and run.json field is the unit
    its name carries in the package's one table (the Parquet writer's too)."""
    from seanv_analysis.io.contract import contract, table_specs
    from seanv_analysis.units import units_of_columns

    checked = 0
    for spec in table_specs().values():
        for col in spec.columns:
            if col.unit:
                assert units_of_columns([col.name])[col.name] == col.unit, col.name
                checked += 1
    for name, field in contract()["run_json"]["fields"].items():
        if isinstance(field, dict) and field.get("unit"):
            assert unit_of_key(name)[1] == field["unit"], name
            checked += 1
    assert checked >= 15


@pytest.mark.parametrize("key,unit", [("max_rate_deg_s", "deg/s"), ("velocity_mm_s", "mm/s"),
                                      ("droop_mpa_s_per_mm3", "MPa s/mm^3"),
                                      ("viscous_friction_n_s_per_mm", "N s/mm"),
                                      ("rate_mm_per_run", "mm/run"), ("dead_volume_mm3", "mm^3")])
def test_compound_units_are_not_read_as_their_last_part(key, unit):
    assert unit_of_key(key)[1] == unit


@pytest.mark.parametrize("numerator,denominator,unit,suffix", [
    ("mm^3/s", "MPa^2", "mm^3/(s MPa^2)", "_mm3_per_s_mpa2"),   # an added flow per dp**2
    ("", "MPa", "1/MPa", "_per_mpa"),                           # a 'mul' term per dp
    ("deg", "MPa^0.5", "deg/MPa^0.5", "_deg_per_sqrtmpa"),     # a threshold shift per sqrt(dp)
    ("mm^3/s", "MPa", "mm^3/(s MPa)", "_mm3_s_per_mpa"),       # the table's own, kept
    ("mm^3/s", "run", "mm^3/(s run)", "_mm3_per_s_run"),
    ("", "mm^3/s", "s/mm^3", "_s_per_mm3"),
    ("deg", "deg", "", "_ratio"),
])
def test_a_ratio_of_units_is_derived_and_its_key_read_back(numerator, denominator, unit, suffix):
    from seanv_analysis.units import key_suffix, ratio_unit

    assert ratio_unit(numerator, denominator) == unit
    assert key_suffix(unit) == suffix
    if unit:
        assert unit_of_key("value" + suffix) == ("value", unit)


def test_a_derived_suffix_never_takes_a_table_spelling_of_another_unit():
    from seanv_analysis.units import key_suffix

    # '_mm3_s_per_mpa' is the table's mm^3/(s MPa): mm^3 s/MPa has no suffix
    with pytest.raises(ValueError, match="UNIT_SUFFIXES"):
        key_suffix("mm^3 s/MPa")
    with pytest.raises(ValueError, match="UNIT_SUFFIXES"):
        key_suffix("furlong/s")
    assert unit_of_key("viscous_n_s_per_mm") == ("viscous", "N s/mm")
    assert unit_of_key("conductance_mm3_s_per_mpa") == ("conductance", "mm^3/(s MPa)")
