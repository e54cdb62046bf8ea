"""Issue 34, point 6 (the small ones): --workers beyond the processors, a bad
Dask address, a linked sub-folder of the data set, SVG ids that depended on
the other formats asked for. (Non-UTF-8 or nested pipelines, seeds and
bootstrap counts: test_hostile_pipeline_file.py.)"""
from __future__ import annotations

import json
import time

import pytest
from click.testing import CliRunner

from seanv_analysis.batch.executor import make_executor, usable_cpus
from seanv_analysis.cli import cli
from seanv_analysis.errors import ConfigError


def test_workers_beyond_the_processors_are_capped():
    """The probe: --workers 1000 started 1000 processes on 2 cores."""
    limit = max(usable_cpus(), 2)
    with make_executor(workers=1000) as ex:
        assert ex.kind == "process" and ex.workers == limit
        assert "1000 asked, capped at the processors" in ex.describe()
    with make_executor(workers=2) as ex:
        assert ex.workers == 2 and "capped" not in ex.describe()


def test_the_run_says_it_capped_the_workers(hostile_data, tmp_path):
    pipe = tmp_path / "p.toml"
    pipe.write_text('[[stages]]\nname = "ingest"\n')
    res = CliRunner().invoke(cli, ["run", str(pipe), str(hostile_data), "--out",
                                   str(tmp_path / "o"), "-q", "--workers", "1000", "--json"])
    assert res.exit_code == 0, res.output
    assert "1000 asked, capped" in json.loads(res.stdout)["executor"]


@pytest.mark.parametrize("address", ["foo://x", "garbage", "tcp://[::1", "tcp://127.0.0.1:99999",
                                     "tcp://host", "tcp://a b:1"])
def test_a_bad_dask_address_is_one_line_at_once(address):
    """The probe: a bad Dask address was a traceback."""
    t0 = time.monotonic()
    with pytest.raises(ConfigError, match="is not a dask scheduler address"):
        make_executor(scheduler=address)
    assert time.monotonic() - t0 < 2.0


def test_a_bad_dask_address_on_the_command_line(hostile_data, tmp_path):
    res = CliRunner().invoke(cli, ["run", "flowfit", str(hostile_data), "--out",
                                   str(tmp_path / "o"), "-q", "--scheduler", "foo://x"])
    assert res.exit_code == 2 and res.output.count("\n") == 1, res.output
    assert "'foo://x' is not a dask scheduler address" in res.output


def test_a_linked_sub_folder_of_the_data_set_is_named(hostile_data, tmp_path):
    """The probe: a symlinked sub-folder (a folder of runs) was skipped
    without a word."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(hostile_data, data)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    shutil.move(str(data / "z001-drain"), elsewhere / "z001-drain")
    (data / "more").symlink_to(elsewhere, target_is_directory=True)
    res = CliRunner().invoke(cli, ["ingest", str(data), "--out", str(tmp_path / "o"), "--json"])
    assert res.exit_code == 1, res.output
    bad = {b["path"]: b["message"] for b in json.loads(res.stdout)["bad_runs"]}
    assert list(bad) == [str(data / "more")]
    assert "is a symbolic link to a folder" in bad[str(data / "more")]


def test_svg_bytes_do_not_depend_on_the_other_formats(flowfit_out, tmp_path):
    """The probe: `--formats svg` and `png,svg` gave different SVG clip-path
    ids (a constrained layout solved again from the PNG's)."""
    from seanv_analysis.plots import FIGURES

    fit = _flowfit_of(flowfit_out)
    svg_only = FIGURES["fig4"].draw({"flowfit": fit}, tmp_path / "a", formats=("svg",))
    both = FIGURES["fig4"].draw({"flowfit": fit}, tmp_path / "b", formats=("png", "svg"))
    assert svg_only[0].read_bytes() == both[1].read_bytes()


def _flowfit_of(out):
    """The flow fit of the shared run, computed again from its summary."""
    import warnings

    import pandas as pd

    from seanv_analysis.config import load_rig
    from seanv_analysis.fit import fit_flow

    summary = pd.read_parquet(out / "summary.parquet")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")   # 8 synthetic runs: no intervals (a warning says so)
        return fit_flow(summary, rig=load_rig(), n_boot=0)
