"""A pipeline file's values are checked for type and range before any work
(issue 16, point 8): one line naming the file, the stage and the option, exit 2."""
from __future__ import annotations

import pytest
from click.testing import CliRunner

from seanv_analysis.cli import cli

#: (stage, option, TOML value) that must be refused
BAD = [
    ("ingest", "method", '"fast"'), ("ingest", "method", "1"),
    ("flowfit", "sides", '"supply"'), ("flowfit", "sides", "[]"),
    ("flowfit", "n_boot", "-1"), ("flowfit", "n_boot", "true"), ("flowfit", "n_boot", "1.5"),
    ("flowfit", "seed", '"zero"'), ("flowfit", "seed", "true"), ("flowfit", "seed", "-1"),
    ("identify", "parts", '["geometry", "x"]'), ("identify", "parts", '"servo"'),
    ("identify", "parts", "[]"), ("identify", "n_boot", "-3"), ("identify", "seed", "1.0"),
    ("tracking", "shift_s", '"0.25"'), ("tracking", "shift_s", "nan"),
    ("tracking", "shift_s", "-0.1"), ("tracking", "shift_s", "true"), ("tracking", "shift_s", "2.5"),
    ("tracking", "q_range", "[nan, 5]"), ("tracking", "q_range", "[5, 1]"),
    ("tracking", "q_range", "[1, inf]"), ("tracking", "q_range", "[1]"),
    ("validate", "threshold_pct", "nan"), ("validate", "threshold_pct", "150"),
    ("validate", "threshold_pct", '"80"'), ("validate", "threshold_pct", "true"),
    ("validate", "controller_model", '"x"'),
    ("discover", "holdout", '"x"'), ("discover", "seed", '"zero"'), ("discover", "seed", "true"),
    ("figures", "figs", "[true]"), ("figures", "figs", '"some"'),
    ("figures", "formats", '["jpg"]'), ("figures", "formats", '"svg"'), ("figures", "formats", "[]"),
    ("report", "filename", "3"),
]


@pytest.mark.parametrize("stage,key,value", BAD, ids=[f"{s}.{k}={v}" for s, k, v in BAD])
def test_bad_option_refused_before_any_work(tmp_path, make_dataset, stage, key, value):
    make_dataset(tmp_path / "data", n_flow=2)
    head = '[[stages]]\nname = "ingest"\n' if stage != "ingest" else ""
    (tmp_path / "p.toml").write_text(f'[pipeline]\nname = "p"\n{head}'
                                     f'[[stages]]\nname = "{stage}"\n{key} = {value}\n')
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["run", str(tmp_path / "p.toml"), str(tmp_path / "data"),
                                   "--out", str(out), "--workers", "1", "-q"])
    assert res.exit_code == 2, res.output
    lines = res.output.strip().splitlines()
    assert len(lines) == 1, res.output
    assert "p.toml" in lines[0] and f"'{stage}'" in lines[0] and f"'{key}'" in lines[0]
    assert not out.exists()                      # refused before any work


def test_svg_only_writes_no_png(tmp_path, make_dataset):
    make_dataset(tmp_path / "data", n_flow=2, n_position=1)
    (tmp_path / "p.toml").write_text(
        '[pipeline]\nname = "p"\n[[stages]]\nname = "ingest"\n[[stages]]\nname = "tracking"\n'
        '[[stages]]\nname = "figures"\nformats = ["svg"]\n')
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["run", str(tmp_path / "p.toml"), str(tmp_path / "data"),
                                   "--out", str(out), "--workers", "1", "-q"])
    assert res.exit_code == 0, res.output
    assert list(out.rglob("*.svg")), "no figure drawn"
    assert not list(out.rglob("*.png"))


def test_identify_default_parts_are_every_part():
    """The identify stage checks ``parts`` against its default (so a
    pipeline is checked without importing the identify layer): every part."""
    from seanv_analysis.identify import PARTS
    from seanv_analysis.stages import identify

    assert tuple(identify.OPTIONS["parts"]) == PARTS
