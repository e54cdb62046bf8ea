"""Physics of models/: eq. (1)-(6) against hand computations and each other."""
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.testing import assert_allclose

from seanv_analysis import ValveModel, load_rig
from seanv_analysis.errors import ConfigError
from seanv_analysis.io.model_file import read_model
from seanv_analysis.models import (
    NeedleGeometry,
    fluid_force_n,
    needle_height_mm,
    side_pressures,
    spring_force_n,
    threshold_displacement_mm,
)

RIG = load_rig()
MODEL = ValveModel.from_rig(RIG)
GEOM_S = NeedleGeometry.from_rig(RIG, "supply")


def test_piston_area_is_papers():
    assert_allclose(RIG.piston_area_mm2, 201.06, atol=0.005)


def test_eq1_eq2_eq3_by_hand():
    # eq. (1): pi/4 (3^2 * 3.3 - 2.27^2 * 1.7) = 14.447 N
    assert_allclose(fluid_force_n(3.3, 1.7, GEOM_S), math.pi / 4 * (9 * 3.3 - 2.27 ** 2 * 1.7))
    assert_allclose(spring_force_n(-0.155, -0.2, GEOM_S), 544 * 0.045)
    # eq. (3) is where eq. (1) equals eq. (2)
    zc = threshold_displacement_mm(-0.155, 3.3, 1.7, GEOM_S)
    assert_allclose(spring_force_n(-0.155, zc, GEOM_S), fluid_force_n(3.3, 1.7, GEOM_S))


def test_eq4_sign_typo_fixed():
    """With '+ (z_p - r cos phi)' the head height at theta=0 is sub-millimetre,
    not the -63.7 mm the printed sign gives."""
    g = NeedleGeometry(3, 2.27, 20, 1, 544, 51.848, 31.848, 0.0, 0.0)
    z0 = needle_height_mm(0.0, g)
    expected = -20 * math.sin(math.radians(1)) * math.tan(math.radians(1)) + 51.848 - 20 * math.cos(math.radians(1)) - 31.848
    assert_allclose(z0, expected, atol=1e-12)
    assert abs(z0) < 0.01


@pytest.mark.parametrize("side,target", [("supply", -10.0), ("drain", -20.0)])
def test_default_thresholds_where_documented(side, target):
    """The chosen needle centres put the thresholds near -10 / -20 deg at the paper's pressures."""
    p1, dp = side_pressures(side, 3.3, 1.6, 0.0)
    assert abs(MODEL.side(side).threshold_deg(p1, dp) - target) < 0.5


def test_threshold_inverts_eq4():
    p1, dp = side_pressures("supply", 3.3, np.array([1.2, 1.6, 2.0]))
    theta_d = MODEL.supply.threshold_deg(p1, dp)
    assert_allclose(needle_height_mm(theta_d, GEOM_S),
                    threshold_displacement_mm(-0.155, p1, dp, GEOM_S), atol=2e-6)


def test_threshold_moves_with_z0_as_expected():
    """Larger z0 (more preload) needs more cam lift to open: supply threshold rises."""
    p1, dp = side_pressures("supply", 3.3, 1.6)
    assert MODEL.supply.threshold_deg(p1, dp, z0_mm=-0.1) > MODEL.supply.threshold_deg(p1, dp)


def test_eq5_by_hand():
    p1, dp = side_pressures("supply", 3.3, 1.6)
    theta_d = float(MODEL.supply.threshold_deg(p1, dp))
    assert_allclose(MODEL.supply.flow(theta_d + 10, p1, dp), 17.435 * 100 * math.sqrt(1.7))
    assert MODEL.supply.flow(theta_d - 1, p1, dp) == 0.0
    p1, dp = side_pressures("drain", 3.3, 1.6)
    theta_d = float(MODEL.drain.threshold_deg(p1, dp))
    assert_allclose(MODEL.drain.flow(theta_d - 10, p1, dp), -22.636 * 100 * math.sqrt(1.6))
    assert MODEL.drain.flow(theta_d + 1, p1, dp) == 0.0


@settings(max_examples=60, deadline=None)
@given(q=st.floats(-9000, 9000), ph=st.floats(0.8, 2.2))
def test_eq6_inverts_eq5(q, ph):
    theta = MODEL.cam_for_flow(q, 3.3, ph)
    if MODEL.cam_min_deg < theta < MODEL.cam_max_deg:
        assert_allclose(MODEL.net_flow(theta, 3.3, ph), q, atol=1e-6 * max(1.0, abs(q)))


def test_smoothed_sqrt_matches_exact_away_from_zero():
    p1, dp = side_pressures("supply", 3.3, np.array([1.0, 2.0, 3.25]))
    exact = MODEL.supply.flow(5.0, p1, dp)
    smooth = MODEL.supply.flow(5.0, p1, dp, smooth_mpa=0.1)
    assert_allclose(smooth[:2], exact[:2])
    assert abs(smooth[2]) < abs(exact[2])  # dp = 0.05 < 0.1: linearised, smaller


def test_model_roundtrip_json_toml(tmp_path):
    m = MODEL.with_side("drain", c_flow=-20.0, z0_mm=-0.03)
    p = tmp_path / "model.json"
    p.write_text(json.dumps(m.to_dict()))
    assert read_model(p, rig=load_rig()) == m
    t = tmp_path / "model.toml"
    t.write_text('[supply]\nz0_mm = -0.155\nC = 17.435\n[drain]\nz0_mm = -0.026\nC = -22.636\n')
    m2 = read_model(t, rig=load_rig())
    assert m2.supply.c_flow == 17.435 and m2.drain.geometry == MODEL.drain.geometry


def test_model_load_errors(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        read_model(tmp_path / "nope.json", rig=load_rig())
    bad = tmp_path / "bad.json"
    bad.write_text('{"supply": {}}')
    with pytest.raises(ConfigError, match="not a valve model file"):
        read_model(bad, rig=load_rig())


def test_model_file_with_bad_geometry_names_the_file(tmp_path):
    d = MODEL.to_dict()
    d["supply"]["geometry"].update(needle_x_c_mm=0.0, needle_y_c_mm=0.0)
    p = tmp_path / "model.json"
    p.write_text(json.dumps(d))
    with pytest.raises(ConfigError, match=f"{p}: not a valve model file .*not monotonic"):
        read_model(p, rig=RIG)


def test_models_take_any_rig_like_object_and_raise_valueerror():
    """models read no files and know no project errors: a duck-typed rig
    works, and a model dict missing what only a rig gives is a ValueError."""
    class Rig:
        cam_range_deg = (-40.0, 10.0)

        def __getitem__(self, key):
            return RIG[key]

    assert ValveModel.from_rig(Rig()) == MODEL
    d = MODEL.to_dict()
    assert ValveModel.from_dict(d) == MODEL            # complete: no rig needed
    del d["supply"]["geometry"]
    with pytest.raises(ValueError, match="rig"):
        ValveModel.from_dict(d)
    assert ValveModel.from_dict(d, rig=Rig()) == MODEL
    with pytest.raises(ValueError, match="side"):
        MODEL.side("tank")


def test_rig_overrides_and_unknown_key():
    rig = RIG.with_overrides({"supply": {"pressure_mpag": 3.0}})
    assert rig["supply"]["pressure_mpag"] == 3.0 and RIG["supply"]["pressure_mpag"] == 3.3
    with pytest.raises(ConfigError, match="unknown rig key 'nope'"):
        RIG.with_overrides({"supply": {"nope": 1}})


def test_compiled_threshold_inverse_equals_numpy_interp():
    """sim.jit.angle_for_height (scalar binary search) == np.interp, ends clipped."""
    from seanv_analysis.sim import jit as J

    model = ValveModel.from_rig(load_rig())
    for side in (model.supply, model.drain):
        z, th = side.geometry.height_table
        x = np.random.default_rng(0).uniform(z[0] - 1.0, z[-1] + 1.0, 500)
        got = np.array([J.angle_for_height(v, z, th) for v in x])
        np.testing.assert_allclose(got, np.interp(x, z, th), rtol=0, atol=1e-12)


@settings(max_examples=25, deadline=None)
@given(st.floats(4.0, 80.0), st.booleans())
def test_height_table_is_eq4_on_its_grid_bit_for_bit(y_c, below):
    """The inversion table (made from the grid's cached cosines and sines)
    is eq. (4) of needle_height_mm at the same angles, exactly."""
    from dataclasses import replace

    from seanv_analysis.models import needle_height_mm
    from seanv_analysis.models.sealing import _TABLE_POINTS, _TABLE_RANGE_DEG

    geom = ValveModel.from_rig(load_rig()).side("supply").geometry
    geom = replace(geom, needle_y_c_mm=-y_c if below else y_c)
    theta = np.linspace(*_TABLE_RANGE_DEG, _TABLE_POINTS)
    try:
        z_tab, theta_tab = geom.height_table
    except ValueError:
        z = needle_height_mm(theta, geom)
        assert not (np.all(np.diff(z) > 0) or np.all(np.diff(z) < 0))
        return
    z = needle_height_mm(theta, geom)
    if theta_tab[0] > theta_tab[-1]:
        z, theta = z[::-1], theta[::-1]
    assert np.array_equal(z_tab, z) and np.array_equal(theta_tab, theta)
