"""fit.fit_flow: parameter recovery with 95 % intervals, exclusions, robustness
to an outlier run, the JSON contract, outputs and Fig. 4."""
from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pyarrow.parquet as pq
import pytest
from numpy.testing import assert_allclose
from synthetic_flow import synthetic_flow_summary

from seanv_analysis.config import load_rig
from seanv_analysis.errors import ConfigError, DataError, FitError
from seanv_analysis.fit import fit_flow
from seanv_analysis.fit._perload import _stderr, group_loads
from seanv_analysis.io.model_file import read_model
from seanv_analysis.models import ValveModel

#: truth sets {side: (z0_mm, C)}: the paper's and two others
TRUTHS = {
    "paper": {"supply": (-0.155, 17.435), "drain": (-0.026, -22.636)},
    "set_a": {"supply": (-0.12, 14.0), "drain": (-0.06, -27.0)},
    "set_b": {"supply": (-0.19, 21.0), "drain": (0.01, -18.0)},
    # near the paper's thresholds: enough open runs on the simulator's coarse grid
    "set_c": {"supply": (-0.165, 19.5), "drain": (-0.015, -20.0)},
}
N_BOOT = 100


def truth_model(rig, name: str) -> ValveModel:
    m = ValveModel.from_rig(rig)
    for side, (z0, c) in TRUTHS[name].items():
        m = m.with_side(side, z0_mm=z0, c_flow=c)
    return m


@pytest.fixture(scope="module")
def paper_summary(rig):
    return synthetic_flow_summary(truth_model(rig, "paper"), rig, seed=3)


@pytest.fixture(scope="module")
def paper_fit(rig, paper_summary):
    return fit_flow(paper_summary, rig, n_boot=N_BOOT)


# recovery ---------------------------------------------------------------------

@pytest.mark.parametrize("procedure", ["joint", "two_step"])
@pytest.mark.parametrize("name", ["paper", "set_a", "set_b"])
def test_recovers_truth_with_interval(rig, name, procedure):
    truth = truth_model(rig, name)
    summary = synthetic_flow_summary(truth, rig, seed=11)
    fit = fit_flow(summary, rig, n_boot=N_BOOT, procedure=procedure)
    assert fit.success, fit.message
    for side in ("supply", "drain"):
        sf, t = fit.sides[side], truth.side(side)
        assert abs(sf.z0_mm - t.z0_mm) <= 0.01, (side, sf.z0_mm, t.z0_mm)
        assert_allclose(sf.c_flow, t.c_flow, rtol=0.03)
        assert sf.z0_ci95[0] <= t.z0_mm <= sf.z0_ci95[1], (side, sf.z0_ci95, t.z0_mm)
        assert min(sf.c_ci95) <= t.c_flow <= max(sf.c_ci95), (side, sf.c_ci95, t.c_flow)
        assert np.sign(sf.c_flow) == np.sign(t.c_flow)
        assert sf.n_runs == int(((summary["side"] == side) & (summary["excluded"] == "")).sum())
        # RMSE near the injected noise (sigma = 20 + 3 % |Q|)
        used = summary[(summary["side"] == side) & (summary["excluded"] == "")]
        sigma = 20 + 0.03 * np.abs(used["q_true_mm3_s"].to_numpy())
        assert 0.7 < sf.rmse_mm3_s / np.sqrt(np.mean(sigma ** 2)) < 1.3


def test_model_carries_fit_and_threshold_table(rig, paper_fit, paper_summary):
    m = paper_fit.model
    for side in ("supply", "drain"):
        assert m.side(side).z0_mm == paper_fit.sides[side].z0_mm
        assert m.side(side).c_flow == paper_fit.sides[side].c_flow
    # per-load theta_d agree with the fitted eq. (3)+(4) within their error bars
    pl = paper_fit.per_load
    assert set(pl["side"]) == {"supply", "drain"}
    ok = pl[pl["success"]]
    dev = np.abs(ok["theta_d_deg"] - ok["theta_d_model_deg"]) / ok["theta_d_se_deg"]
    assert float(np.median(dev)) < 2.0
    assert (np.sign(ok["alpha_mm3_s_deg2"]) == np.where(ok["side"] == "supply", 1, -1)).all()


def test_per_run_residual_is_measured_minus_model(paper_fit, paper_summary):
    pr = paper_fit.per_run
    steps = paper_summary[paper_summary["kind"] == "flow_step"]
    assert len(pr) == len(steps)
    assert_allclose(pr["residual_mm3_s"], pr["q_mm3_s"] - pr["q_model_mm3_s"])
    assert pr["used"].sum() == (steps["excluded"] == "").sum()
    assert_allclose(pr["theta_deg"], steps["cam_measured_deg"])  # cam='measured' default
    used = pr[pr["used"]]
    # eq. (6) inverted per run lands on the fitted eq. (3)+(4) threshold
    assert float(np.median(np.abs(used["theta_d_implied_deg"] - used["theta_d_model_deg"]))) < 0.3
    row = pr[pr["used"]].iloc[0]
    side = paper_fit.model.side(row["side"])
    # the model's flow: eq. (5) of the side plus the fitted seat leakage g (dp_s - dp_d)
    g = paper_fit.leakage.conductance_mm3_s_per_mpa
    assert_allclose(row["q_leak_mm3_s"], g * row["dp_leak_mpa"])
    assert_allclose(row["q_model_mm3_s"], side.flow(row["cam_deg"], row["p1_mpa"], row["dp_mpa"])
                    + row["q_leak_mm3_s"])


# exclusions and robustness --------------------------------------------------------

def test_exclusion_counts_leakage_friction_cam_range(rig):
    truth = truth_model(rig, "paper")
    cams = tuple(np.arange(-45.0, 15.0 + 1e-9, 2.5))  # some outside [-40, 10]
    s = synthetic_flow_summary(truth, rig, seed=5, cams_deg=cams, repeats=2,
                               friction_drain_load_mpag=0.2)
    fit = fit_flow(s, rig, n_boot=0)
    q, cam, load = s["q_mm3_s"].abs(), s["cam_deg"], s["load_mpag"]
    out = (cam < -40) | (cam > 10)
    leak = ~out & (q <= 50)
    fric = ~out & ~leak & (s["side"] == "drain") & (load <= 0.2) & (q <= 500)
    expected = {"leakage": int(leak.sum()), "friction": int(fric.sum()),
                "cam_range": int(out.sum()), "invalid": 0}
    assert fit.excluded == expected
    assert expected["friction"] > 10 and expected["cam_range"] == 2 * 2 * 7 * 4
    # no low-load drain run is fitted
    used = fit.per_run[fit.per_run["used"]]
    assert not ((used["side"] == "drain") & (used["load_mpag"] <= 0.2)).any()
    assert abs(fit.sides["drain"].z0_mm - truth.drain.z0_mm) <= 0.01


def test_invalid_rows_counted_and_skipped(rig, paper_summary):
    s = paper_summary.copy()
    idx = s.index[(s["excluded"] == "") & (s["side"] == "supply")][:3]
    s.loc[idx, "q_mm3_s"] = np.nan
    from seanv_analysis.signals.filters import apply_filters
    fit = fit_flow(apply_filters(s, rig), rig, n_boot=0)
    assert fit.excluded["invalid"] == 3
    assert fit.sides["supply"].n_runs == (paper_summary["excluded"][
        paper_summary["side"] == "supply"] == "").sum() - 3


@pytest.mark.parametrize("side", ["supply", "drain"])
def test_one_outlier_run_moves_c_less_than_3_percent(rig, paper_summary, side):
    clean = fit_flow(paper_summary, rig, sides=(side,), n_boot=0)
    s = paper_summary.copy()
    used = s[(s["side"] == side) & (s["excluded"] == "")]
    worst = used["q_mm3_s"].abs().idxmax()  # the largest flow: the most leverage
    s.loc[worst, "q_mm3_s"] *= 3.0
    bad = fit_flow(s, rig, sides=(side,), n_boot=0)
    c0, c1 = clean.sides[side].c_flow, bad.sides[side].c_flow
    assert abs(c1 / c0 - 1) < 0.03
    assert abs(bad.sides[side].z0_mm - clean.sides[side].z0_mm) < 0.005
    pr = bad.per_run.set_index("run_id")
    assert abs(pr.loc[s.loc[worst, "run_id"], "z_score"]) > 10  # flagged in the table


# contract and errors --------------------------------------------------------------

def test_json_contract(paper_fit):
    C = "C_mm3_s_deg2_sqrtMPa"  # the unit in the key
    doc = paper_fit.to_json_dict()
    assert list(doc) == ["supply", "drain", "excluded", "units", "flow_method"]
    for side in ("supply", "drain"):
        d = doc[side]
        assert list(d) == ["z0_mm", C, "z0_ci95_mm", "C_ci95" + C[1:], "rmse_mm3_s", "n_runs",
                           "lack_of_fit", "lack_of_fit_ratio", "lack_of_fit_p"]
        assert all(isinstance(d[k], float) for k in ("z0_mm", C, "rmse_mm3_s"))
        assert isinstance(d["n_runs"], int)
        assert len(d["z0_ci95_mm"]) == 2 and all(isinstance(v, float) for v in d["z0_ci95_mm"])
        lo, hi = d["C_ci95" + C[1:]]
        assert lo <= d[C] <= hi
    assert doc["drain"]["C_mm3_s_deg2_sqrtMPa"] < 0 < doc["supply"]["C_mm3_s_deg2_sqrtMPa"]
    assert set(doc["excluded"]) == {"leakage", "friction", "cam_range", "invalid"}
    assert all(isinstance(v, int) for v in doc["excluded"].values())
    assert doc["units"] == {C: "mm^3/(s deg^2 MPa^0.5)", "z0_mm": "mm"}
    assert json.loads(json.dumps(doc, allow_nan=False)) == doc
    json.dumps(paper_fit.to_dict(), allow_nan=False)
    text = paper_fit.report()
    assert "supply" in text and "95%" in text and "measured - model" in text


def test_singular_covariance_gives_null_intervals(rig, paper_summary, monkeypatch):
    import seanv_analysis.fit.flowfit as ff

    real = ff.fit_joint

    def no_se(*a, **k):
        jf = real(*a, **k)
        jf.z0_se_mm = jf.c_se = math.nan
        return jf

    monkeypatch.setattr(ff, "fit_joint", no_se)
    with pytest.warns(UserWarning, match="covariance singular"):
        fit = fit_flow(paper_summary, rig, sides=("supply",), n_boot=50)
    sf = fit.sides["supply"]
    assert "covariance singular" in sf.message and math.isfinite(sf.z0_mm)
    doc = fit.to_json_dict()
    assert doc["supply"]["z0_ci95_mm"] == [None, None] and doc["supply"]["C_ci95_mm3_s_deg2_sqrtMPa"] == [None, None]
    assert list(doc) == ["supply", "excluded", "units", "flow_method"]
    assert "covariance singular" in fit.report()


def test_stderr_singular_jacobian_is_nan():
    jac = np.array([[1.0, 2.0], [2.0, 4.0], [3.0, 6.0]])
    assert np.isnan(_stderr(jac, np.ones(3), n_par=2)).all()
    assert np.isfinite(_stderr(np.eye(3)[:, :2], np.ones(3), n_par=2)).all()


def test_group_loads_clusters_close_loads():
    lv = group_loads(np.array([0.301, 0.299, 0.35, 0.352, np.nan, 0.5]))
    assert_allclose(lv[:4], [0.3, 0.3, 0.351, 0.351])
    assert np.isnan(lv[4]) and lv[5] == 0.5


def test_errors(rig, paper_summary):
    with pytest.raises(ConfigError, match="sides"):
        fit_flow(paper_summary, rig, sides=("left",))
    with pytest.raises(ConfigError, match="cam"):
        fit_flow(paper_summary, rig, cam="guessed")
    with pytest.raises(ConfigError, match="procedure"):
        fit_flow(paper_summary, rig, procedure="magic")
    with pytest.raises(DataError, match="dp_mpa"):
        fit_flow(paper_summary.drop(columns=["dp_mpa"]), rig)
    few = paper_summary[paper_summary["excluded"] == ""].head(2)
    with pytest.raises(FitError, match="no side could be fitted.*need >= 3 runs"):
        fit_flow(few, rig)


def test_one_side_missing_still_fits_the_other(rig, paper_summary):
    s = paper_summary[paper_summary["side"] == "supply"]
    with pytest.warns(UserWarning, match="drain"):
        fit = fit_flow(s, rig, n_boot=0)
    assert fit.sides["supply"].success and not fit.sides["drain"].success
    assert not fit.success and "drain" in fit.message
    assert fit.to_json_dict()["drain"]["C_mm3_s_deg2_sqrtMPa"] is None
    assert fit.model.drain.z0_mm == ValveModel.from_rig(rig).drain.z0_mm  # rig's kept


# outputs ---------------------------------------------------------------------------

def test_write_outputs_and_model_file_roundtrip(tmp_path, paper_fit):
    from seanv_analysis.stages import flowfit as flowfit_stage

    paths = flowfit_stage.write(paper_fit, tmp_path)
    names = {p.name for p in paths}
    assert {"flowfit.json", "model.toml", "model.json", "per_run.parquet"} <= names
    assert json.loads((tmp_path / "flowfit.json").read_text()) == paper_fit.to_json_dict()
    for fname in ("model.toml", "model.json"):
        m = read_model(tmp_path / fname, rig=load_rig())
        for side in ("supply", "drain"):
            assert_allclose(m.side(side).z0_mm, paper_fit.sides[side].z0_mm)
            assert_allclose(m.side(side).c_flow, paper_fit.sides[side].c_flow)
        assert m.supply.geometry == paper_fit.model.supply.geometry
    table = pq.read_table(tmp_path / "per_run.parquet")
    assert table.num_rows == len(paper_fit.per_run)
    assert table.schema.field("residual_mm3_s").metadata[b"unit"] == b"mm^3/s"
    assert not list(tmp_path.glob(".*.tmp"))


def test_fig4_png_and_svg(tmp_path, paper_fit):
    from seanv_analysis.plots import fig4

    paths = fig4.plot_fig4(paper_fit, tmp_path)
    assert [p.suffix for p in paths] == [".png", ".svg"]
    assert paths[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    svg = paths[1].read_text()
    assert "Cam rotation angle [deg]" in svg and "excluded: leakage" in svg


# the simulator's data set ------------------------------------------------------------

@pytest.mark.parametrize("name", ["paper", "set_c"])
def test_paper_flowsteps_simulated_recovers_truth(tmp_path, rig, name):
    """The simulator's flow-step data set (written to disk, read, derived, filtered)."""
    sim = pytest.importorskip("seanv_analysis.sim")
    from seanv_analysis.stages import run_stages

    scenario = ("paper-flowsteps-small" if "paper-flowsteps-small" in sim.SCENARIOS
                else "paper-flowsteps")
    truth = truth_model(rig, name)
    path = sim.simulate_scenario(scenario, tmp_path / "ds", seed=0, rig=rig, valve=truth)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ctx = run_stages(path, rig=rig, options={"flowfit": {"n_boot": 60}})
        fit, ds = ctx.result("flowfit"), ctx.result("ingest")
    assert not ds.failed
    for side in ("supply", "drain"):
        sf, t = fit.sides[side], truth.side(side)
        assert abs(sf.z0_mm - t.z0_mm) <= 0.01
        assert_allclose(sf.c_flow, t.c_flow, rtol=0.03)
        assert sf.z0_ci95[0] <= t.z0_mm <= sf.z0_ci95[1], (side, sf.z0_ci95, t.z0_mm)
        assert min(sf.c_ci95) <= t.c_flow <= max(sf.c_ci95), (side, sf.c_ci95, t.c_flow)


def test_bootstrap_jacobian_is_the_derivative_of_eq5():
    """The bootstrap's analytic Jacobian of eq. (5) against central differences,
    and its residual equal to side_flow's, on both sides."""
    from seanv_analysis.fit._joint import Eq5Residual
    from seanv_analysis.fit._perload import side_flow

    model = ValveModel.from_rig(load_rig())
    rng = np.random.default_rng(3)
    for name in ("supply", "drain"):
        side = model.side(name)
        theta, p1, dp = rng.uniform(-40, 10, 60), rng.uniform(1, 3.3, 60), rng.uniform(0.5, 2, 60)
        x = np.array([side.z0_mm, side.c_flow])
        q = side_flow(side, *x, theta, p1, dp) + rng.normal(0, 5, 60)
        r = Eq5Residual(side, theta, p1, dp, q, np.full(60, 4.0))
        assert np.array_equal(r.fun(x), (q - side_flow(side, *x, theta, p1, dp)) / 4.0)
        h = np.array([1e-7, 1e-6])
        numeric = np.column_stack([(r.fun(x + e * hi) - r.fun(x - e * hi)) / (2 * hi)
                                   for e, hi in zip(np.eye(2), h)])
        assert np.abs(r.jac(x)).max(axis=0) == pytest.approx(np.abs(numeric).max(axis=0),
                                                             rel=1e-6)
        np.testing.assert_allclose(r.jac(x), numeric, rtol=0,
                                   atol=1e-6 * np.abs(numeric).max())


@pytest.mark.parametrize("opens_upward", [True, False])
def test_per_load_jacobian_is_the_derivative_of_the_quadratic(opens_upward):
    """fit_load's analytic Jacobian of (q - alpha max(+-(theta - theta_d), 0)^2)
    / sigma against central differences."""
    from seanv_analysis.fit._perload import _quadratic, _quadratic_residual_jac

    rng = np.random.default_rng(5)
    theta, q, sig = rng.uniform(-10, 10, 40), rng.uniform(0, 900, 40), rng.uniform(1, 5, 40)
    x = np.array([-2.3, 14.0 if opens_upward else -14.0])

    def r(p):
        return (q - _quadratic(theta, p[0], p[1], opens_upward)) / sig

    h = np.array([1e-6, 1e-6])
    numeric = np.column_stack([(r(x + e * hi) - r(x - e * hi)) / (2 * hi) for e, hi in zip(np.eye(2), h)])
    got = _quadratic_residual_jac(theta, *x, opens_upward, sig)
    assert np.count_nonzero(got[:, 0]) >= 10       # open runs: the theta_d column is checked
    np.testing.assert_allclose(got, numeric, rtol=0, atol=1e-5 * np.abs(numeric).max())


def _bootstrap_case(seed: int = 4):
    """(side, runs, fit) of one side: a simulated summary with outliers,
    repeats clustered as fit_flow clusters them."""
    from seanv_analysis.fit._joint import fit_joint

    model = ValveModel.from_rig(load_rig())
    side = model.side("drain")
    rng = np.random.default_rng(seed)
    cams = np.repeat(rng.uniform(-40, -20, 14), 3)
    theta, p1, dp = cams + rng.normal(0, 0.05, cams.size), rng.uniform(1, 3.3, cams.size), \
        rng.uniform(0.5, 2, cams.size)
    q = side_flow_of(side, theta, p1, dp) + rng.standard_t(2, cams.size) * 6.0
    sigma = np.full(cams.size, 5.0)
    fit = fit_joint(side, theta, p1, dp, q, sigma, z0_start_mm=side.z0_mm + 0.03)
    return side, (theta, p1, dp, q, sigma), np.round(cams, 6), fit


def side_flow_of(side, theta, p1, dp):
    from seanv_analysis.fit._perload import side_flow

    return side_flow(side, side.z0_mm, side.c_flow, theta, p1, dp)


def _scipy_resample_fits(side, runs, clusters, fit, n_boot, seed):
    """The bootstrap by one scipy least_squares call per resample (what
    bootstrap_joint did before it fitted the resamples together)."""
    from scipy.optimize import least_squares

    from seanv_analysis.fit._joint import Eq5Residual, _cluster_members, resample_indices

    theta, p1, dp, q, sigma = runs
    rng = np.random.default_rng(seed)
    members = _cluster_members(q.size, clusters)
    x0 = np.array([fit.z0_mm, fit.c_flow])
    out = []
    for _ in range(n_boot):
        idx = resample_indices(rng, members)
        if np.unique(theta[idx]).size < 2:
            continue
        r = Eq5Residual(side, theta[idx], p1[idx], dp[idx], q[idx], sigma[idx])
        out.append(least_squares(r.fun, x0, jac=r.jac, loss="soft_l1", f_scale=fit.f_scale,
                                 x_scale=[0.01, abs(x0[1])]).x)
    return np.array(out)


@pytest.mark.parametrize("batched_iterations", [None, 1])
def test_bootstrap_fits_equal_scipy_fits_of_each_resample(monkeypatch, batched_iterations):
    """The resamples fitted together (iteratively reweighted Gauss-Newton on
    the run counts) give scipy's least_squares estimate of every resample,
    to its tolerance, and the same 95 % interval; with one iteration allowed
    none converges and scipy refits each (the fallback), same numbers."""
    import scipy.optimize

    from seanv_analysis.fit import _joint

    side, runs, clusters, fit = _bootstrap_case()
    want = _scipy_resample_fits(side, runs, clusters, fit, 120, seed=7)
    if batched_iterations is not None:
        monkeypatch.setattr(_joint, "_BATCH_ITER", batched_iterations)
    refits = []
    scipy_fit = scipy.optimize.least_squares
    monkeypatch.setattr(scipy.optimize, "least_squares",
                        lambda *a, **k: refits.append(1) or scipy_fit(*a, **k))
    got = _joint.bootstrap_joint(side, *runs, x_hat=(fit.z0_mm, fit.c_flow),
                                 f_scale=fit.f_scale, n_boot=120, seed=7, clusters=clusters)
    assert len(refits) == (120 if batched_iterations else 0)
    assert got.shape == want.shape == (120, 2)
    assert_allclose(got, want, rtol=2e-5, atol=0)
    assert_allclose(np.percentile(got, [2.5, 97.5], axis=0),
                    np.percentile(want, [2.5, 97.5], axis=0), rtol=1e-6)


def test_params_and_eval_as_lmfit(paper_fit, paper_summary):
    """Issue 33: an lmfit-like way to a fit's numbers,
    ``fit.params["supply.C"].value / .stderr / .ci95`` and
    ``fit.eval(theta, dp, side)`` for the model's prediction."""
    p = paper_fit.params
    assert list(p) == ["supply.z0", "supply.C", "drain.z0", "drain.C", "leakage.g"]
    g = p["leakage.g"]       # the seat leakage fitted beside them (issue 32: one estimate type)
    assert (g.value, g.ci95, g.unit) == (paper_fit.leakage.conductance_mm3_s_per_mpa,
                                         paper_fit.leakage.ci95, "mm^3/(s MPa)")
    for side in ("supply", "drain"):
        sf = paper_fit.sides[side]
        c, z0 = p[f"{side}.C"], p[f"{side}.z0"]
        assert (c.value, c.ci95, c.unit) == (sf.c_flow, sf.c_ci95, "mm^3/(s deg^2 MPa^0.5)")
        assert (z0.value, z0.ci95, z0.unit) == (sf.z0_mm, sf.z0_ci95, "mm")
        assert c.stderr == sf.joint["c_se"] and z0.stderr == sf.joint["z0_se_mm"] > 0
        assert c.ci95[0] < c.value < c.ci95[1] and "95 %" in repr(c)
    used = paper_fit.per_run[paper_fit.per_run["used"].astype(bool)]
    for side in ("supply", "drain"):
        rows = used[used["side"] == side]
        assert_allclose(paper_fit.eval(rows["theta_deg"], rows["dp_mpa"], side,
                                       p1_mpa=rows["p1_mpa"]),
                        rows["q_model_mm3_s"] - rows["q_leak_mm3_s"].fillna(0.0), rtol=1e-9)
    # default p1: the supply runs' supply pressure; the drain's head = dp + tank
    sup = used[used["side"] == "supply"]
    q = paper_fit.eval([5.0, 10.0], 2.0, "supply")
    assert_allclose(q, paper_fit.model.supply.flow(np.array([5.0, 10.0]),
                                                   float(np.median(sup["p1_mpa"])), 2.0))
    assert paper_fit.eval(-30.0, 1.0, "drain") < 0 < paper_fit.eval(5.0, 2.0, "supply")
    with pytest.raises(ValueError, match="side: expected one of supply, drain"):
        paper_fit.eval(0.0, 1.0, "both")
