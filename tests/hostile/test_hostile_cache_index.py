"""Issue 34, point 3 (the cache's index and folder): ``index.json`` is
untrusted input: a malformed one is empty, one naming a file that is not a
regular file of its run folder (``/dev/zero``, ``../x``) hashes nothing, a
FIFO is never opened for reading; a ``.cache`` or ``.cache/runs`` that is a
link is refused (one line, exit 2), never followed."""
from __future__ import annotations

import json
import os
import threading

import pytest
from click.testing import CliRunner

from seanv_analysis.batch import run_pipeline
from seanv_analysis.batch.cache import RunCache
from seanv_analysis.batch.memo import MEMO_NAME
from seanv_analysis.cli import cli
from seanv_analysis.errors import OutputError
from seanv_analysis.io.hashing import file_sha256
from seanv_analysis.io.readback import read_back

INGEST = {"pipeline": {"name": "ingest"}, "stages": [{"name": "ingest"}]}


def test_an_index_naming_a_device_is_not_read(hostile_data, tmp_path):
    """The probe: index.json naming /dev/zero hung forever."""
    out = tmp_path / "out"
    run_pipeline(INGEST, hostile_data, out_dir=out, workers=1, quiet=True)
    index = out / ".cache" / "index.json"
    doc = json.loads(index.read_text())
    for rec in doc["runs"].values():
        rec["files"]["/dev/zero"] = [0, 0, "0" * 64]
        rec["files"]["../../../../../../dev/zero"] = [0, 0, "0" * 64]
    index.write_text(json.dumps(doc))
    cache = RunCache(out / ".cache")
    run_dirs = [d for d in hostile_data.iterdir() if d.is_dir()]
    done = threading.Event()
    results = []
    worker = threading.Thread(target=lambda: (results.extend(cache.known_hashes(d)
                                                              for d in run_dirs), done.set()),
                              daemon=True)
    worker.start()
    assert done.wait(20), "known_hashes read a device"
    assert results == [None] * len(run_dirs)
    with pytest.raises(OSError, match="not a regular file"):
        file_sha256("/dev/zero")
    res = run_pipeline(INGEST, hostile_data, out_dir=out, workers=1, quiet=True)
    assert res.success


@pytest.mark.parametrize("doc", ['{"schema": 1}', '{"schema":"seanv-batch-index/1","runs":[]}',
                                 '{"schema":"seanv-batch-index/1","runs":{"/x":{"listing":"a"}}}',
                                 "[" * 100000, b"\xff\xfe"])
def test_a_malformed_index_is_empty(tmp_path, doc):
    (tmp_path / "runs").mkdir()
    (tmp_path / "index.json").write_bytes(doc.encode() if isinstance(doc, str) else doc)
    assert RunCache(tmp_path)._index == {}


def test_a_fifo_is_never_opened_for_reading(tmp_path):
    os.mkfifo(tmp_path / "index.json")
    (tmp_path / "runs").mkdir()
    assert RunCache(tmp_path)._index == {}             # returns at once: no blocking open
    assert read_back(tmp_path / "index.json", root=tmp_path) is None


def test_a_cache_folder_that_is_a_link_is_refused(hostile_data, tmp_path):
    """The probe: an existing <out>/.cache symlink was followed."""
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    (elsewhere / MEMO_NAME).write_text("keep")
    out = tmp_path / "out"
    out.mkdir()
    (out / ".cache").symlink_to(elsewhere, target_is_directory=True)
    with pytest.raises(OutputError, match=r"\.cache: a link; expected the per-run cache"):
        run_pipeline(INGEST, hostile_data, out_dir=out, workers=1, quiet=True)
    assert sorted(p.name for p in elsewhere.iterdir()) == [MEMO_NAME]
    assert (elsewhere / MEMO_NAME).read_text() == "keep"
    res = CliRunner().invoke(cli, ["run", "flowfit", str(hostile_data), "--out", str(out), "-q",
                                   "--workers", "1"])
    assert res.exit_code == 2 and "Traceback" not in res.output, res.output
    assert len(res.output.strip().splitlines()) == 1
    assert sorted(p.name for p in elsewhere.iterdir()) == [MEMO_NAME]


def test_a_runs_folder_that_is_a_link_is_refused(tmp_path):
    (tmp_path / "c").mkdir()
    (tmp_path / "c" / "runs").symlink_to(tmp_path, target_is_directory=True)
    with pytest.raises(OutputError, match="runs: a link"):
        RunCache(tmp_path / "c")


