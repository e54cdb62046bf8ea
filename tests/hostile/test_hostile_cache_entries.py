"""Issue 34, point 3 (cache entries): an entry of <out>/.cache/runs is
untrusted input. One with a valid SHA-256 header and a malformed payload, or
a payload that decodes to something its stage never stores, is a miss: the
run is recomputed, the entry removed, and a note says so."""
from __future__ import annotations

import hashlib

import pytest

from seanv_analysis.batch import run_pipeline
from seanv_analysis.batch.cache import read_entry
from seanv_analysis.io.readback import conforms, load_json_back, read_back

INGEST = {"pipeline": {"name": "ingest"}, "stages": [{"name": "ingest"}]}


def plant(path, payload: bytes) -> None:
    """An entry whose SHA-256 header matches its (malformed) payload."""
    path.write_bytes(b"seanv-cache-entry/2 " + hashlib.sha256(payload).hexdigest().encode()
                     + b"\n" + payload)


MALFORMED = [b'{"t":"dict"}', b'{"t":"dict","v":[]}', b"[1, 2]", b'{"t":"list","v":{}}',
             b'{"t":"ndarray","dtype":"<f8","shape":[-1],"b64":""}', b"[" * 5000 + b"]" * 5000,
             b'{"t":"dataclass","name":"RunValidation","v":{}}', b'{"t":"kvdict","v":[[1]]}',
             b'{"t":"frame","columns":[],"data":[],"index":{"t":"range","v":[0,"x",1]}}']


@pytest.mark.parametrize("payload", MALFORMED, ids=range(len(MALFORMED)))
def test_a_malformed_entry_with_a_valid_header_is_a_miss(tmp_path, payload):
    plant(tmp_path / "k.json", payload)
    rejected: list[str] = []
    assert read_entry(tmp_path, "k", rejected=rejected) is None
    assert len(rejected) == 1 and not (tmp_path / "k.json").exists()


def test_malformed_entries_are_recomputed_with_a_note(hostile_data, tmp_path):
    """The probe: one entry with a valid SHA header and no 'v' aborted the
    run ('stage ingest FAILED: KeyError', then 'add an ingest stage first')."""
    out = tmp_path / "out"
    run_pipeline(INGEST, hostile_data, out_dir=out, workers=1, quiet=True)
    entries = sorted((out / ".cache" / "runs").glob("*.json"))
    plant(entries[0], b'{"t":"dict"}')
    plant(entries[1], b'{"t":"dict","v":{"row":{"t":"list","v":[]}}}')   # decodes, wrong shape
    res = run_pipeline(INGEST, hostile_data, out_dir=out, workers=1, quiet=True)
    assert res.success and res.runs_read == 8, res.summary_text()
    assert res.computed["ingest"] == 2 and res.cached["ingest"] == 6
    assert "2 malformed cache entries removed and recomputed" in res.stage_notes["cache"]
    again = run_pipeline(INGEST, hostile_data, out_dir=out, workers=1, quiet=True)
    assert again.cached["ingest"] == 8 and "cache" not in again.stage_notes


def test_a_wrong_shaped_entry_is_a_miss_in_a_worker_too(hostile_data, tmp_path):
    out = tmp_path / "out"
    run_pipeline(INGEST, hostile_data, out_dir=out, workers=1, quiet=True)
    (out / ".cache" / "index.json").unlink()          # the workers look the entries up
    for e in (out / ".cache" / "runs").glob("*.json"):
        plant(e, b'{"t":"dict","v":{"row":{"t":"dict","v":{}},"meta":{"t":"dict","v":{}}}}')
    res = run_pipeline(INGEST, hostile_data, out_dir=out, workers=2, quiet=True)
    assert res.success and res.computed["ingest"] == 8, res.summary_text()
    assert "8 malformed cache entries" in res.stage_notes["cache"]


def test_a_failed_ingest_is_not_blamed_on_the_pipeline_file(hostile_data, tmp_path, monkeypatch):
    """After a failed ingest the later stages say they had nothing to work
    on; no 'add an ingest stage first' about a pipeline that has one."""
    import seanv_analysis.stages.dataset as dataset

    def boom(*args, **kwargs):
        raise KeyError("v")

    monkeypatch.setattr(dataset, "collect", boom)
    res = run_pipeline("flowfit", hostile_data, out_dir=tmp_path / "out", workers=1, quiet=True)
    assert "ingest" in res.stage_errors
    assert "gave no result" in res.stage_errors["flowfit"]
    assert not any("add an 'ingest' stage" in m for m in res.stage_errors.values())


def test_read_back_refuses_links_and_outside_paths(tmp_path):
    outside = tmp_path / "secret.txt"
    outside.write_text("secret")
    root = tmp_path / "out"
    (root / "sub").mkdir(parents=True)
    (root / "link.json").symlink_to(outside)
    (root / "sublink").symlink_to(tmp_path, target_is_directory=True)
    assert read_back(root / "link.json", root=root) is None
    assert read_back(root / "sublink" / "secret.txt", root=root) is None
    assert read_back(root / ".." / "secret.txt", root=root) is None
    assert read_back(outside, root=root) is None
    (root / "sub" / "ok.json").write_text('{"a": [1]}')
    assert load_json_back(root / "sub" / "ok.json", root=root, shape={"a": [int]}) == {"a": [1]}
    assert load_json_back(root / "sub" / "ok.json", root=root, shape={"a": [str]}) is None
    assert not conforms({"a": True}, {"a": int})


