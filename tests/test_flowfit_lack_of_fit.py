"""flowfit's lack-of-fit check: the F test on arrays with known pure error and
known lack of fit, and on the simulator's flow steps: clean (no lack of fit on
either side) and with the paper's drain-side drift (lack of fit on the drain
side only), in the text report, the JSON, the stage's files, the CLI and the
HTML model table."""
from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pandas as pd
import pytest
from scipy.stats import f as f_dist

from seanv_analysis.fit import fit_flow
from seanv_analysis.fit._perload import LOF_SYSTEMATIC_MIN, lack_of_fit_test
from seanv_analysis.models import ValveModel

JSON_KEYS = ("lack_of_fit", "lack_of_fit_ratio", "lack_of_fit_p")


# the statistic on arrays -------------------------------------------------------------

def test_known_answer_decomposition():
    """3 conditions x 2 repeats, equal weights, one parameter:
    SS_pe = 2 + 0 + 2 = 4 (df 3), SS_lof = 2 (2^2 + 1^2 + 1^2) = 12 (df 2), F = 6 / (4/3) = 4.5."""
    r = [1.0, 3.0, -1.0, -1.0, 0.0, 2.0]
    lof = lack_of_fit_test(r, ["a", "a", "b", "b", "c", "c"], n_params=1)
    assert (lof.df_lof, lof.df_pe, lof.n_conditions, lof.n_repeated) == (2, 3, 3, 3)
    assert lof.f_stat == pytest.approx(4.5, rel=1e-12)
    assert lof.ratio == pytest.approx(math.sqrt(4.5), rel=1e-12)
    assert lof.p_value == pytest.approx(f_dist.sf(4.5, 2, 3), rel=1e-12)
    assert lof.flagged is False                 # p = 0.12
    assert lof.reason is None and math.isnan(lof.systematic)   # no flow: not judged


def _campaign(rng, *, bias_rms, sigma=10.0, n_cond=25, repeats=3, flow=1000.0):
    """Residuals of n_cond conditions x repeats: per-condition bias ~ N(0, bias_rms)
    (the lack of fit) + per-run noise ~ N(0, sigma) (the pure error)."""
    cond = np.repeat(np.arange(n_cond), repeats)
    bias = rng.normal(0.0, bias_rms, n_cond) if bias_rms else np.zeros(n_cond)
    r = bias[cond] + rng.normal(0.0, sigma, cond.size)
    return r, cond, np.full(cond.size, sigma), np.full(cond.size, flow)


def test_pure_error_only_is_not_flagged():
    rng = np.random.default_rng(1)
    ratios, ps = [], []
    for _ in range(40):
        r, cond, sig, q = _campaign(rng, bias_rms=0.0)
        lof = lack_of_fit_test(r, cond, sigma_mm3_s=sig, flow_mm3_s=q)
        assert lof.flagged is False
        ratios.append(lof.ratio)
        ps.append(lof.p_value)
    assert 0.85 < np.median(ratios) < 1.15          # sqrt(F) ~ 1
    assert 0.3 < np.mean(ps) < 0.7                   # p ~ uniform under no lack of fit


def test_known_lack_of_fit_is_flagged_with_its_size():
    """Bias 5 sigma, 3 repeats: E[F] = 1 + 3 x 25 = 76 (ratio ~ 8.7); systematic
    = 50 / 1000 = 5 % of the flow."""
    rng = np.random.default_rng(2)
    r, cond, sig, q = _campaign(rng, bias_rms=50.0, n_cond=40)
    lof = lack_of_fit_test(r, cond, sigma_mm3_s=sig, flow_mm3_s=q)
    assert lof.flagged is True
    assert lof.p_value < 1e-12
    assert 6.0 < lof.ratio < 12.0
    assert lof.systematic == pytest.approx(0.05, rel=0.3)
    # a uniform noise scale does not change the test; the repeats set the scale
    same = lack_of_fit_test(r, cond, sigma_mm3_s=7 * sig, flow_mm3_s=q)
    assert same.f_stat == pytest.approx(lof.f_stat, rel=1e-12)


def test_tiny_systematic_on_very_clean_data_is_not_flagged():
    """0.2 % of the flow, repeats agreeing to 0.1 %: significant, 10x the repeats'
    scatter, immaterial."""
    rng = np.random.default_rng(3)
    r, cond, sig, q = _campaign(rng, bias_rms=2.0, sigma=1.0, n_cond=30)
    lof = lack_of_fit_test(r, cond, sigma_mm3_s=sig, flow_mm3_s=q)
    assert lof.p_value < 1e-9 and lof.ratio > 1.5
    assert lof.systematic < LOF_SYSTEMATIC_MIN
    assert lof.flagged is False


def test_untestable_cases_give_none_with_a_reason():
    r = np.array([1.0, -2.0, 0.5, 3.0])
    lof = lack_of_fit_test(r, ["a", "b", "c", "d"])
    assert lof.flagged is None and "repeat" in lof.reason and lof.n_repeated == 0
    assert math.isnan(lof.ratio) and math.isnan(lof.p_value)
    lof = lack_of_fit_test(r, ["a", "a", "b", "b"], n_params=2)   # 2 conditions, 2 parameters
    assert lof.flagged is None and "degree of freedom" in lof.reason
    lof = lack_of_fit_test([1.0, 1.0, 2.0, 2.0, 0.0, 0.0], list("aabbcc"), n_params=1)
    assert lof.flagged is None and "exactly" in lof.reason


# the simulator's flow steps ------------------------------------------------------------

def _simulated(effects) -> pd.DataFrame:
    """Summary of the simulator's paper-flowsteps-small (144 runs: 4 loads x 3
    sweeps), in memory."""
    from seanv_analysis.sim.scenarios import iter_scenario_runs
    from seanv_analysis.stages.dataset import summarize_runs

    runs = list(iter_scenario_runs("paper-flowsteps-small", seed=0, effects=effects))
    summary, failed = summarize_runs(runs, _rig())
    assert not failed
    return summary


def _rig():
    from seanv_analysis.config import load_rig

    return load_rig()


def _fit(summary, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return fit_flow(summary, _rig(), n_boot=0, **kw)


@pytest.fixture(scope="module")
def clean_summary():
    return _simulated([])


@pytest.fixture(scope="module")
def drift_summary():
    from seanv_analysis.sim.scenarios import PAPER_DRAIN_DRIFT

    return _simulated([PAPER_DRAIN_DRIFT])


@pytest.fixture(scope="module")
def clean_fit(clean_summary):
    return _fit(clean_summary)


@pytest.fixture(scope="module")
def drift_fit(drift_summary):
    return _fit(drift_summary)


def test_clean_simulated_data_no_lack_of_fit(clean_fit):
    truth = ValveModel.from_rig(_rig())
    for side in ("supply", "drain"):
        f = clean_fit.sides[side]
        assert f.c_flow == pytest.approx(truth.side(side).c_flow, rel=0.01)   # eq. (5) holds
        assert f.lack_of_fit is False, f.lack_of_fit_line()
        # the simulator's repeats agree to ~1 mm^3/s; with its seat leakage in
        # the model (fitted beside eq. 5) its departures are ~1-3 mm^3/s
        # (4-6 without: the leakage moves with the load), significant or
        # not, 0.1 % of the flow
        assert f.lack_of_fit_detail["systematic_pct"] < 0.3
        assert f.lack_of_fit_detail["n_repeated"] >= 9
        assert "none material" in f.lack_of_fit_line()
        assert "does not describe" not in f.message
    text = clean_fit.report()
    assert "supply: ok" in text and "drain: ok" in text and "lack of fit:" not in text


def test_drain_drift_is_lack_of_fit_on_drain_only(drift_fit, clean_fit):
    truth = ValveModel.from_rig(_rig())
    d, s = drift_fit.sides["drain"], drift_fit.sides["supply"]
    assert s.lack_of_fit is False                       # the supply side does not drift
    # the sides share only the seat leakage's conductance (one per needle,
    # fitted on both sides' runs, robustly): the drain's drift moves it a
    # little (3.21 -> 3.26 mm^3/(s MPa)), the supply's fit hardly
    assert s.lack_of_fit_ratio == pytest.approx(clean_fit.sides["supply"].lack_of_fit_ratio,
                                                rel=0.1)
    assert drift_fit.leakage.conductance_mm3_s_per_mpa == pytest.approx(
        clean_fit.leakage.conductance_mm3_s_per_mpa, rel=0.1)
    assert d.lack_of_fit is True
    assert d.lack_of_fit_p < 1e-5 and d.lack_of_fit_ratio > 3.0
    assert d.lack_of_fit_detail["systematic_pct"] > 3.0           # C falls ~0.5 % / 3 runs
    # what the check is for: the fitted C is far from the valve's (first-run) C
    assert abs(d.c_flow / truth.drain.c_flow - 1) > 0.1
    assert d.success                                     # the fit itself worked
    assert d.status == "lack of fit" and s.status == "ok"
    msg = d.message
    assert msg.startswith(f"residual scatter {d.lack_of_fit_ratio:.1f}x the repeats' scatter (p = ")
    assert "eq. (5) does not describe these runs (drift, or another effect)" in msg
    assert "the intervals assume it does" in msg and "seanv-analyze discover" in msg
    text = drift_fit.report()
    assert f"drain: lack of fit: {msg}" in text and "supply: ok" in text


def test_two_step_procedure_same_verdicts(clean_summary, drift_summary):
    """The test is of eq. (5), on the joint fit's residuals, whatever the procedure
    (the two-step C is a few % off on the simulator: a misfit of the procedure)."""
    for summary, want in ((clean_summary, {"supply": False, "drain": False}),
                          (drift_summary, {"supply": False, "drain": True})):
        fit = _fit(summary, procedure="two_step")
        assert {s: f.lack_of_fit for s, f in fit.sides.items()} == want


def test_json_contract_and_stage_files(drift_fit, clean_fit, tmp_path):
    from seanv_analysis.stages import flowfit as stage

    doc = drift_fit.to_json_dict()
    for side, want in (("supply", False), ("drain", True)):
        d = doc[side]
        assert list(d)[-3:] == list(JSON_KEYS)
        assert d["lack_of_fit"] is want
        assert isinstance(d["lack_of_fit_ratio"], float) and isinstance(d["lack_of_fit_p"], float)
    assert json.loads(json.dumps(doc, allow_nan=False)) == doc
    stage.write(drift_fit, tmp_path)
    assert json.loads((tmp_path / "flowfit.json").read_text()) == doc
    details = json.loads((tmp_path / "flowfit_details.json").read_text())
    det = details["sides"]["drain"]["lack_of_fit_detail"]
    assert det["df_lof"] > 0 and det["df_pe"] > 0 and det["reason"] is None
    assert "p < 0.01" in det["criteria"]
    assert details["sides"]["drain"]["lack_of_fit"] is True


def test_html_model_table_says_lack_of_fit(drift_fit, clean_fit, tmp_path):
    from seanv_analysis.batch import load_pipeline
    from seanv_analysis.batch.runner import PipelineResult
    from seanv_analysis.report import render_report
    from seanv_analysis.stages import report_sections

    def table_rows(fit):
        html = render_report(PipelineResult(load_pipeline("flowfit"), [tmp_path], tmp_path,
                                            results={"flowfit": fit}, rig=_rig(), command=["x"]),
                           report_sections())
        start = html.index("<th class='l verdict'>verdict (flowfit")
        return {side: html[html.index(f"<td class='l'>{side}</td>", start):].split("</tr>")[0]
                for side in ("supply", "drain")}, html

    rows, html = table_rows(drift_fit)
    assert "<span class='warn'>lack of fit (flowfit&#x27;s check" in rows["drain"]
    assert "class='ok'" not in rows["drain"]
    assert "does not describe these runs" in rows["drain"]
    assert "<span class='ok'>ok</span>" in rows["supply"]
    assert "supply: lack-of-fit check: none material" in html
    rows, _ = table_rows(clean_fit)
    assert all("<span class='ok'>ok</span>" in r for r in rows.values())


def test_cli_json_without_repeats_is_null_with_a_reason(tmp_path, monkeypatch):
    """One run per condition: no pure error, so no verdict (null), and why."""
    from types import SimpleNamespace

    from click.testing import CliRunner
    from conftest import write_synthetic_run

    from seanv_analysis.cli import cli
    from seanv_analysis.models import side_pressures
    from seanv_analysis.stages import figures

    # Fig. 4 is test_cli_flowfit's business; drawing it would double this test's time
    monkeypatch.setattr(figures, "draw_figures", lambda *a, **k: SimpleNamespace(all_paths=list))

    model = ValveModel.from_rig(_rig())
    data = tmp_path / "flow"
    k = 0
    for side, cams in (("supply", (-7.5, -2.5, 2.5)), ("drain", (-22.5, -27.5, -32.5))):
        for load in (0.3, 0.5):
            p1, dp = side_pressures(side, 3.3, 4 * load + (0.3 if side == "supply" else 0.0), 0.0)
            for cam in cams:
                write_synthetic_run(data, side=side, cam_deg=cam, load_mpag=load, seed=k,
                                    flow_mm3_s=float(model.side(side).flow(cam, p1, dp)),
                                    duration_s=0.5, run_id=f"{side}-l{load}-c{cam}",
                                    started_at=f"2026-03-02T10:00:{k:02d}Z")
                k += 1
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["flowfit", str(data), "--out", str(out), "--json",
                                   "--n-boot", "0", "--cam", "commanded"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    for side in ("supply", "drain"):
        assert doc[side]["lack_of_fit"] is None
        assert doc[side]["lack_of_fit_ratio"] is None and doc[side]["lack_of_fit_p"] is None
    details = json.loads((out / "flowfit_details.json").read_text())
    assert "no repeated condition" in details["sides"]["drain"]["lack_of_fit_detail"]["reason"]
    res = CliRunner().invoke(cli, ["flowfit", str(data), "--out", str(tmp_path / "o2"),
                                   "--n-boot", "0", "--cam", "commanded"])
    assert "drain: ok" in res.stdout
    assert "lack-of-fit check: not possible (no repeated condition" in res.stdout
