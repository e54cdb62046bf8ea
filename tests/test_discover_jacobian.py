"""discover's static fits difference the residual in groups of parameters
that move disjoint runs (discover/static.py ``_grouped_jacobian``): the
Jacobian, and so every fit, must be the one ``least_squares`` makes with
``jac='2-point'``, bit for bit, for the base model (with the needle centre
y_c) and every candidate effect on either side.
"""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize._numdiff import approx_derivative
from test_discover_engine import MODEL, synth_summary

from seanv_analysis.discover import static
from seanv_analysis.discover.candidates import candidate_specs, fit_candidate
from seanv_analysis.discover.engine import _fit_base
from seanv_analysis.discover.static import FlowData


@pytest.fixture(scope="module")
def case():
    data = FlowData.from_summary(synth_summary(4, ("drift", "drain", 0.04)).query("excluded == ''"))
    base, sigma = _fit_base(MODEL, data)
    return data, base, sigma


def _dense(monkeypatch):
    monkeypatch.setattr(static, "_jacobian_structure", lambda *a, **k: None)


def _same_fit(a, b):
    assert np.array_equal(a.weighted_residual, b.weighted_residual)
    assert a.model == b.model and a.message == b.message
    assert all(np.array_equal(a.effects[k][1], b.effects[k][1]) for k in a.effects)
    assert np.array_equal(a.covariance, b.covariance, equal_nan=True)


def test_every_candidate_fit_equals_the_dense_difference(case, monkeypatch):
    data, base, sigma = case
    specs = candidate_specs(data, base)
    assert {s.side for s in specs} == {"supply", "drain", "both"}
    grouped = [fit_candidate(base, data, sigma, spec, []) for spec in specs]
    _dense(monkeypatch)
    for spec, (fit, _) in zip(specs, grouped):
        _same_fit(fit, fit_candidate(base, data, sigma, spec, [])[0])


def test_base_fit_with_the_needle_centre_equals_the_dense_difference(case, monkeypatch):
    data, base, sigma = case
    grouped = static.fit_static(base.model, data, sigma, geometry=("supply", "drain"))
    assert len(grouped.param_names) == 6
    _dense(monkeypatch)
    _same_fit(grouped, static.fit_static(base.model, data, sigma, geometry=("supply", "drain")))


def test_the_grouped_jacobian_is_scipys_and_costs_fewer_evaluations(case):
    data, base, sigma = case
    calls = []

    def resid(x):
        calls.append(1)
        a, b = x[:2], x[2:]
        q = np.where(data.side == "supply", a[1] * (data.theta_deg - a[0]) ** 2,
                     b[1] * (data.theta_deg - b[0]) ** 2)
        return (data.q_mm3_s - q) / sigma

    structure = static._jacobian_structure(data, ["supply", "drain"], [], [])
    lo, hi = np.array([-1.0, 0.0, -1.0, -60.0]), np.array([1.0, 60.0, 1.0, 0.0])
    fun, jac = static._grouped_jacobian(resid, structure, (lo, hi), [])
    x = np.array([-0.2, 17.0, 1.0 - 1e-12, -22.0])     # one at its bound: a backward step
    f0 = fun(x)
    calls.clear()
    got = jac(x)
    assert len(calls) == 2      # two groups, not four columns
    want = approx_derivative(resid, x, f0=f0, method="2-point", bounds=(lo, hi))
    assert np.array_equal(got, want) and got.flags.f_contiguous == want.flags.f_contiguous
    assert np.array_equal(np.signbit(got), np.signbit(want))    # the zeros' signs too


@pytest.mark.parametrize("x", [[-0.2, 17.0, 1.0 - 1e-12, -22.0], [0.0, 0.0, -1.0, 0.0],
                               [-1.0 + 1e-300, 60.0, 0.999999999, -1e-9], [0.5, 30.0, 0.0, -30.0]])
def test_the_steps_and_the_dense_fallback_are_scipys(x):
    """The steps (scipy's private rule, written out in the package) and the
    column-by-column fallback equal scipy's bit for bit, at and near bounds."""
    from scipy.optimize._numdiff import (
        _adjust_scheme_to_bounds,
        _compute_absolute_step,
        _prepare_bounds,
    )

    x = np.asarray(x, float)
    lo, hi = np.array([-1.0, 0.0, -1.0, -60.0]), np.array([1.0, 60.0, 1.0, 0.0])
    f0 = np.array([1.0, 2.0])
    want = _adjust_scheme_to_bounds(x, _compute_absolute_step(None, x, f0, "2-point"), 1,
                                    "1-sided", *_prepare_bounds((lo, hi), x))[0]
    got = static._forward_steps(x, (lo, hi))
    assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))

    def fun(v):
        return np.array([np.sin(v).sum(), (v ** 2 * np.arange(1, 5)).sum()])

    f0 = fun(x)
    dense = static._dense_forward(fun, x, f0, got)
    assert np.array_equal(dense, approx_derivative(fun, x, f0=f0, method="2-point",
                                                   bounds=(lo, hi)))


def test_the_package_uses_no_private_scipy():
    """scipy's private modules may change under a pinned version's patch
    release; the package imports none (tests compare against them)."""
    import re
    from pathlib import Path

    import seanv_analysis

    root = Path(seanv_analysis.__file__).parent
    private = [str(p.relative_to(root)) for p in root.rglob("*.py")
               if re.search(r"\bscipy(\.\w+)*\._\w+", p.read_text())]
    assert private == []
