"""Output folder hygiene (issue 16, points 3, 6, 11, 13): each stage owns its
folder (a re-run with another data set leaves no file of the first), the
manifest lists every output with its hash, temp files of a killed run are
removed, outputs follow the umask, figures are reproducible byte for byte."""
from __future__ import annotations

import hashlib
import json
import os
import stat
from pathlib import Path

import pytest
from click.testing import CliRunner
from conftest import write_synthetic_dataset, write_synthetic_run

from seanv_analysis.batch import run_pipeline
from seanv_analysis.io.atomic import OWNER_MARKER
from seanv_analysis.io.outdir import LOCK_NAME

#: files the package keeps in an output folder for itself (not outputs)
BOOKKEEPING = {OWNER_MARKER, LOCK_NAME}

#: position-control runs: per-run tables (tracking/) and per-run figures (figures/fig6/)
POSITION = {"pipeline": {"name": "pos"},
            "stages": [{"name": "ingest"}, {"name": "tracking"},
                       {"name": "figures", "figs": [6], "formats": ["png", "svg"]},
                       {"name": "report"}]}
INGEST_ONLY = {"pipeline": {"name": "ingest-only"}, "stages": [{"name": "ingest"}]}


def _position_data(root: Path, prefix: str, n: int = 2) -> Path:
    """``n`` short position-control runs with ids ``<prefix>0``, ``<prefix>1``, ..."""
    for i in range(n):
        write_synthetic_run(root, "position_control", run_id=f"{prefix}{i}", seed=10 + i,
                            duration_s=0.5, started_at=f"2026-03-02T10:0{i}:00Z")
    return root


@pytest.fixture(scope="module")
def two_datasets(tmp_path_factory):
    base = tmp_path_factory.mktemp("outputs")
    return _position_data(base / "first", "alpha"), _position_data(base / "second", "beta")


def _files(out: Path) -> set[str]:
    """Regular files under ``out`` (relative), the hidden cache excluded."""
    found = set()
    for dirpath, dirnames, filenames in os.walk(out):
        dirnames[:] = [d for d in dirnames if d != ".cache"]
        found |= {str((Path(dirpath) / f).relative_to(out)) for f in filenames}
    return found


def _sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def test_second_dataset_leaves_no_file_of_the_first(two_datasets, tmp_path):
    first, second = two_datasets
    out = tmp_path / "out"
    run_pipeline(POSITION, first, out_dir=out, workers=1, quiet=True)
    before = _files(out)
    assert {"figures/fig6/fig6_alpha0.png", "tracking/tracking_alpha0.parquet"} <= before
    # a cached re-run: per-run figures from the cache, still where the cache says
    again = run_pipeline(POSITION, first, out_dir=out, workers=1, quiet=True)
    assert again.cached.get("fig6") == 2 and again.computed.get("fig6") == 0
    assert _files(out) == before and all(p.is_file() for p in again.figures["fig6"])
    res = run_pipeline(POSITION, second, out_dir=out, workers=1, quiet=True)
    assert not res.stage_errors
    files = _files(out)
    assert not [f for f in files if "alpha" in f], "a file of the first data set remains"
    assert {"figures/fig6/fig6_beta0.png", "tracking/tracking_beta1.parquet"} <= files
    assert not [p for p in out.iterdir() if ".tmp-" in p.name or ".old-" in p.name]
    # the manifest lists every file of the folder but itself and result.json, hashes matching
    manifest = json.loads((out / "manifest.json").read_text())
    listed = {e["path"]: e for e in manifest["outputs"]}
    markers = {f for f in files if Path(f).name in BOOKKEEPING}   # bookkeeping, not outputs
    assert {"figures/" + OWNER_MARKER, "tracking/" + OWNER_MARKER} <= markers
    assert set(listed) == files - {"manifest.json", "result.json"} - markers
    for rel, entry in listed.items():
        assert entry["sha256"] == _sha256(out / rel), rel
        assert entry["size"] == (out / rel).stat().st_size, rel
    assert "report.html" in listed  # the manifest is written again after the report


def test_stage_giving_nothing_removes_its_old_folder(two_datasets, tmp_path):
    first, _ = two_datasets
    out = tmp_path / "out"
    run_pipeline(POSITION, first, out_dir=out, workers=1, quiet=True)
    flow = write_synthetic_dataset(tmp_path / "flow", n_flow=2)
    res = run_pipeline(POSITION, flow, out_dir=out, workers=1, quiet=True)
    assert "tracking" in res.stage_notes  # no position-control run: skipped
    assert not (out / "tracking").exists()
    assert not [f for f in _files(out) if "alpha" in f]


def test_temp_files_of_a_killed_run_are_removed(tmp_path):
    data = write_synthetic_dataset(tmp_path / "data", n_flow=2)
    out = tmp_path / "out"
    leftovers = [out / "figures" / ".fig4.png.abc.tmp",
                 out / "figures" / "fig6" / ".fig6_x.svg.k2j4h_9a.tmp",
                 out / ".summary.parquet.xyz12345.tmp",
                 out / ".flowfit.tmp-q8w7e6r5" / "flowfit.json",
                 out / ".figures.old-1a2b3c4d" / "fig4.png"]
    kept = [out / "notes.txt", out / ".notes.tmp", out / "mine" / ".a.b.tmp",
            out / ".mine.tmp-1" / "x.txt", out / "figures.tmp",
            out / ".tracking.tmp-u7y6t5r4" / "x.txt"]     # named like ours, but no marker
    for p in leftovers + kept:
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(b"partial")
    for folder in ("figures", ".flowfit.tmp-q8w7e6r5", ".figures.old-1a2b3c4d"):
        (out / folder / OWNER_MARKER).write_text("")  # what a killed run's folders hold
    res = run_pipeline(INGEST_ONLY, data, out_dir=out, workers=1, quiet=True)
    for p in leftovers:
        assert not p.exists(), p
    assert not (out / ".flowfit.tmp-q8w7e6r5").exists()
    assert not (out / ".figures.old-1a2b3c4d").exists()
    for p in kept:  # only the package's own temp names are touched
        assert p.read_bytes() == b"partial", p
    assert "resume" in res.stage_notes


@pytest.fixture
def umask():
    """Set the process umask for a test, restore it afterwards."""
    old = os.umask(0o022)
    yield os.umask
    os.umask(old)


@pytest.mark.parametrize("mask,file_mode,dir_mode", [(0o022, 0o644, 0o755), (0o027, 0o640, 0o750)])
def test_outputs_follow_the_umask(umask, tmp_path, mask, file_mode, dir_mode):
    umask(mask)
    data = _position_data(tmp_path / "data", "pos", n=1)  # written by io.writer.write_run
    for f in (data / "pos0").iterdir():
        assert stat.S_IMODE(f.stat().st_mode) == file_mode, f
    out = tmp_path / "out"
    run_pipeline(POSITION, data, out_dir=out, workers=1, quiet=True)
    files = _files(out)
    assert {"report.html", "manifest.json", "figures/fig6/fig6_pos0.svg",
            "tracking/tracking.json"} <= files
    for rel in files:
        assert stat.S_IMODE((out / rel).stat().st_mode) == file_mode, rel
    for folder in ("tracking", "figures", "figures/fig6"):
        assert stat.S_IMODE((out / folder).stat().st_mode) == dir_mode, folder


def test_figures_are_byte_identical_across_runs(two_datasets, tmp_path):
    first, _ = two_datasets
    outs = [tmp_path / "a", tmp_path / "b"]
    for out in outs:  # separate folders: nothing from a cache, every figure drawn
        run_pipeline(POSITION, first, out_dir=out, workers=1, quiet=True)
    figs = sorted(f for f in _files(outs[0]) if f.startswith("figures/"))
    assert any(f.endswith(".svg") for f in figs) and any(f.endswith(".png") for f in figs)
    for rel in figs:
        assert (outs[0] / rel).read_bytes() == (outs[1] / rel).read_bytes(), rel
    svg = (outs[0] / "figures" / "fig6" / "fig6_alpha0.svg").read_text()
    assert "<dc:date>" not in svg


def test_command_manifest_lists_outputs_with_hashes(two_datasets, tmp_path):
    from seanv_analysis.cli import cli

    first, _ = two_datasets
    out = tmp_path / "out"
    res = CliRunner().invoke(cli, ["tracking", str(first), "--out", str(out), "--formats", "png"])
    assert res.exit_code == 0, res.output
    manifest = json.loads((out / "manifest.json").read_text())
    listed = {e["path"]: e for e in manifest["outputs"]}
    assert {"tracking.json", "tracking_alpha0.parquet"} <= set(listed)
    assert any(p.endswith(".png") for p in listed)  # figures drawn by the command
    assert set(listed) == {f for f in _files(out) if Path(f).name not in BOOKKEEPING} - {
        "manifest.json"}
    for rel, entry in listed.items():
        assert entry["sha256"] == _sha256(out / rel), rel
