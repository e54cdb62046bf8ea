"""The CSV writer (pyarrow, floats rounded to 9 significant digits in numpy)
writes exactly the values pandas' ``float_format='%.9g'`` wrote."""
from __future__ import annotations

import numpy as np
import pandas as pd
from hypothesis import given, settings
from hypothesis import strategies as st

from seanv_analysis.io.format_csv import CSV_DIGITS, round_significant, write_csv

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)


@given(st.lists(finite | st.just(float("nan")), min_size=1, max_size=50))
@settings(max_examples=200, deadline=None)
def test_rounding_is_printf_g(values):
    x = np.array(values, dtype=float)
    want = np.array([float(f"{v:.{CSV_DIGITS}g}") for v in x])
    got = round_significant(x)
    # printf's value, or at a tie of the binary product its 9-digit neighbour
    assert np.allclose(got, want, rtol=1.01 * 10.0 ** (1 - CSV_DIGITS), atol=0, equal_nan=True)
    # each value prints in at most CSV_DIGITS significant digits
    for v in got[np.isfinite(got) & (got != 0)]:
        mantissa = repr(float(v)).lstrip("-").split("e")[0].replace(".", "").strip("0")
        assert len(mantissa) <= CSV_DIGITS


def test_file_reads_back_as_pandas_wrote_it(tmp_path):
    rng = np.random.default_rng(1)
    df = pd.DataFrame({"t_s": np.arange(1000) * 1e-3,
                       "p_head_mpag": rng.normal(1.4, 0.01, 1000),
                       "n": np.arange(1000)})
    df.loc[3, "p_head_mpag"] = np.nan
    write_csv(df, tmp_path / "new.csv")
    df.to_csv(tmp_path / "old.csv", index=False, float_format="%.9g", na_rep="")
    new, old = pd.read_csv(tmp_path / "new.csv"), pd.read_csv(tmp_path / "old.csv")
    pd.testing.assert_frame_equal(new, old)
    assert (tmp_path / "new.csv").read_text().splitlines()[:2] == ["t_s,p_head_mpag,n",
                                                                  f"0,{df.p_head_mpag[0]:.9g},0"]
    assert (tmp_path / "new.csv").read_text().splitlines()[4].split(",")[1] == ""  # NaN: empty
