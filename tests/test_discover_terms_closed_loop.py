"""Discover beyond its vocabulary (issue 19), in closed loop: the term search
proposes a correction of eq. (5) that the analysis was not told of, and
the closed-loop check on the twin shows the flow error fall.

(Beside tests/test_discover_terms.py, whose module fixture it does not
use: in its own module the two run on both xdist workers, --dist loadfile.)
"""
from __future__ import annotations

from test_foreign_rig import run_cli


def test_a_proposal_is_checked_in_closed_loop(tmp_path):
    """The package's own simulator with a supply leak 60 dp^2 injected (a
    ``term`` effect the analysis is not told of) in the flow steps and the
    paper's two position-control runs: discover proposes the leak, and its
    closed-loop check (the paper's controllers re-run on the plant with the
    valve model + proposed term, ``validate``) shows the flow error fall."""
    leak = "term:side=supply,mode=add,expr=60*dp**2"
    data = tmp_path / "data"
    run_cli("simulate", "paper-flowsteps-small", "--effect", leak, "--out", data / "flow", "-q")
    run_cli("simulate", "paper-position", "--effect", leak, "--out", data / "pos", "-q")
    doc = run_cli("discover", data, "--out", tmp_path / "out", "--json", "--no-figures", "-q")
    term = doc["proposed_term"]
    assert (term["side"], term["mode"]) == ("supply", "add")
    (c,) = term["coefficients"]
    # within 3 %: the plant's own small leak path (linear in dp) is not in eq. (5) either
    assert c["feature"] == "dp**2" and abs(c["value_mm3_per_s_mpa2"] - 60.0) < 1.8
    assert (c["name"], c["unit"]) == ("supply.term.a1", "mm^3/(s MPa^2)")
    # before: eq. (5) fitted on the same data (z0, C), not the paper's valve;
    # both on the twin discover identified from the position-control logs
    for ctrl in ("cam", "flow_model"):
        before, after = (doc["validation"][k][ctrl]["rmse_flow_mm3_s"] for k in ("before", "after"))
        assert after < 0.35 * before, (ctrl, before, after)
