"""Issue 34, point 1: an input is never written over, a folder this package
did not make is never replaced or deleted (the runs of the hostile probe)."""
from __future__ import annotations

import os
import shutil

import pytest
from click.testing import CliRunner

from seanv_analysis.batch import run_pipeline
from seanv_analysis.cli import cli
from seanv_analysis.errors import DataError, OutputError
from seanv_analysis.io.atomic import (
    OWNER_MARKER,
    atomic_folder,
    claim_folder,
    remove_stale_temps,
    retire_folder,
)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    from conftest import write_synthetic_dataset

    return write_synthetic_dataset(tmp_path_factory.mktemp("sacred") / "data", n_flow=4,
                                   n_position=2)


def invoke(*args, cwd=None):
    runner = CliRunner()
    if cwd is None:
        return runner.invoke(cli, [*map(str, args)])
    old = os.getcwd()
    os.chdir(cwd)
    try:
        return runner.invoke(cli, [*map(str, args)])
    finally:
        os.chdir(old)


def assert_refused(res, pattern: str) -> None:
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    lines = [ln for ln in res.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and __import__("re").search(pattern, lines[0]), res.output


@pytest.mark.parametrize("where", ["tracking", "figures/data", "flowfit/data", ".cache/d"])
def test_data_where_a_stage_folder_goes_is_refused(data, tmp_path, where):
    """The probe's ``cp -r POSITION_RUNS proj/tracking; run tracking tracking --out .``
    (and the same under flowfit/ and figures/): refused before any work, not a file changed."""
    from conftest import snapshot

    proj = tmp_path / "proj"
    shutil.copytree(data, proj / where)
    before = snapshot(proj)
    res = invoke("run", "paper", where, "--out", ".", "-q", cwd=proj)
    assert_refused(res, r"would be written over, and it is or holds the input")
    assert snapshot(proj) == before


def test_data_reached_through_a_link_is_refused(data, tmp_path):
    """A second name of the data folder (a symbolic link where the stage folder goes)."""
    from conftest import snapshot

    out = tmp_path / "out"
    out.mkdir()
    (out / "tracking").symlink_to(data, target_is_directory=True)
    before = snapshot(data)
    res = invoke("run", "tracking", data, "--out", out, "-q")
    assert_refused(res, r"would be written over")
    assert snapshot(data) == before and (out / "tracking").is_symlink()


def test_out_inside_data_is_refused(data, tmp_path):
    res = invoke("run", "tracking", data, "--out", data / "out", "-q")
    assert_refused(res, r"--out: .* is inside the data folder")
    assert not (data / "out").exists()


def test_empty_out_is_refused(data, tmp_path):
    for cmd in (["run", "tracking", data], ["flowfit", data], ["tracking", data],
                ["simulate", "paper-position"]):
        assert_refused(invoke(*cmd, "--out", "", cwd=tmp_path), r"'--out': empty")
    assert list(tmp_path.iterdir()) == []


def test_rig_or_pipeline_file_inside_a_stage_folder_is_refused(data, tmp_path):
    out = tmp_path / "out"
    (out / "flowfit").mkdir(parents=True)
    pipe = out / "flowfit" / "mine.toml"
    pipe.write_text('[pipeline]\nname = "mine"\n[[stages]]\nname = "ingest"\n[[stages]]\nname = "flowfit"\n')
    res = invoke("run", pipe, data, "--out", out, "-q")
    assert_refused(res, r"holds the input .*mine\.toml")
    assert pipe.is_file()


def test_a_foreign_folder_where_a_stage_folder_goes_is_never_replaced(data, tmp_path):
    """Not an input, but not ours either (the user's notes, an older version's
    outputs): refused before any work, its file kept."""
    out = tmp_path / "out"
    (out / "tracking").mkdir(parents=True)
    (out / "tracking" / "notes.txt").write_text("mine")
    res = invoke("run", "tracking", data, "--out", out, "-q", "--no-figures")
    assert_refused(res, r"tracking: a folder this package did not write .*never replaced")
    assert (out / "tracking" / "notes.txt").read_text() == "mine"


def test_library_refuses_too(data, tmp_path):
    """The notebook API: the same check, the library's parameter name."""
    with pytest.raises(DataError, match=r"out_dir: the output folder .*tracking would be written"):
        run_pipeline("tracking", tmp_path / "tracking", out_dir=tmp_path, workers=1) \
            if shutil.copytree(data, tmp_path / "tracking") else None
    with pytest.raises(OutputError, match="out_dir: empty"):
        run_pipeline("tracking", data, out_dir="", workers=1)


def test_reruns_replace_their_own_folders(data, tmp_path):
    """The marker makes the run's own folders replaceable: a second run swaps
    them in anew, and a stage dropped from the pipeline retires its folder."""
    out = tmp_path / "out"
    assert invoke("run", "tracking", data, "--out", out, "-q", "--force",
                  "--formats", "png").exit_code in (0, 1)
    assert (out / "tracking" / OWNER_MARKER).is_file() and (out / "figures" / OWNER_MARKER).is_file()
    stale = out / "tracking" / "stale.txt"
    stale.write_text("from an earlier run")
    assert invoke("run", "tracking", data, "--out", out, "-q", "--force",
                  "--formats", "png").exit_code in (0, 1)
    assert not stale.exists() and (out / "tracking" / OWNER_MARKER).is_file()


def test_atomic_primitives_refuse_foreign_folders(tmp_path):
    foreign = tmp_path / "f"
    foreign.mkdir()
    (foreign / "x").write_text("keep")
    with pytest.raises(OutputError, match="did not write"):
        retire_folder(foreign)
    with pytest.raises(OutputError, match="did not write"):
        with atomic_folder(foreign) as tmp:
            (tmp / "y").write_text("new")
    with pytest.raises(OutputError, match="did not write"):
        claim_folder(foreign)
    assert (foreign / "x").read_text() == "keep" and not (foreign / "y").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["f"]      # no temp folder left
    link = tmp_path / "l"
    link.symlink_to(foreign, target_is_directory=True)
    (foreign / OWNER_MARKER).write_text("")                  # a link to an owned folder: not ours
    with pytest.raises(OutputError, match="a link"):
        retire_folder(link)
    owned = claim_folder(tmp_path / "o")
    with atomic_folder(owned) as tmp:
        (tmp / "y").write_text("new")
    assert (owned / "y").is_file() and (owned / OWNER_MARKER).is_file()
    retire_folder(owned)
    assert not owned.exists()


def test_stale_temps_only_of_our_folders(tmp_path):
    """A folder named like a temp folder but without the marker is the user's."""
    mine = tmp_path / ".flowfit.tmp-abc"
    mine.mkdir()
    (mine / OWNER_MARKER).write_text("")
    theirs = tmp_path / ".figures.tmp-xyz"
    theirs.mkdir()
    (theirs / "data.csv").write_text("t\n")
    assert remove_stale_temps(tmp_path, ["flowfit", "figures"]) == 1
    assert not mine.exists() and (theirs / "data.csv").is_file()


def test_a_single_command_writes_its_folder_whole(data, tmp_path):
    """A command's folder is swapped in whole: a file an earlier run left is
    gone; a folder of the user's is refused; an empty one is taken."""
    out = tmp_path / "out"
    assert invoke("tracking", data, "--out", out, "-q", "--no-figures").exit_code in (0, 1)
    (out / "stale_from_earlier.parquet").write_text("x")
    assert invoke("tracking", data, "--out", out, "-q", "--no-figures").exit_code in (0, 1)
    assert not (out / "stale_from_earlier.parquet").exists() and (out / "tracking.json").is_file()
    mine = tmp_path / "mine"
    mine.mkdir()
    (mine / "notes.txt").write_text("keep")
    assert_refused(invoke("tracking", data, "--out", mine, "-q"), r"did not write")
    assert (mine / "notes.txt").read_text() == "keep"
    empty = tmp_path / "empty"
    empty.mkdir()
    assert invoke("tracking", data, "--out", empty, "-q", "--no-figures").exit_code in (0, 1)
    assert (empty / "tracking.json").is_file()


def test_one_run_at_a_time_per_output_folder(data, tmp_path):
    """A second run into a folder another run holds is refused, one line."""
    from seanv_analysis.io.outdir import out_lock

    out = tmp_path / "out"
    out.mkdir()
    with out_lock(out):
        assert_refused(invoke("run", "tracking", data, "--out", out, "-q"),
                       r"another seanv-analyze run is writing there")
    with out_lock(out / "cmd", beside=True):
        assert_refused(invoke("tracking", data, "--out", out / "cmd", "-q"),
                       r"another seanv-analyze run is writing there")


def test_a_pipeline_run_retires_the_stage_folders_it_no_longer_has(data, tmp_path):
    out = tmp_path / "out"
    assert invoke("run", "tracking", data, "--out", out, "-q", "--no-figures").exit_code in (0, 1)
    assert (out / "tracking").is_dir()
    (out / "mine").mkdir()        # a folder of the user's stays
    assert invoke("run", "flowfit", data, "--out", out, "-q", "--no-figures").exit_code in (0, 1)
    assert not (out / "tracking").exists() and (out / "mine").is_dir()
