"""Issue 34, point 3: a hypothesis fuzz of the files the package reads back
from an output folder (cache entries with a valid SHA-256 header, the
pipeline memo with its result.json, the figure keys): whatever they hold is
a value of the allowed kinds or a miss, never an exception, never a path
outside the folder."""
from __future__ import annotations

import hashlib
import json
import os
import tempfile
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from seanv_analysis.batch.cache import read_entry
from seanv_analysis.batch.memo import MEMO_NAME, recorded_run
from seanv_analysis.io.readback import inside
from seanv_analysis.stages.dataset import is_summary_entry
from seanv_analysis.stages.figures import _FigureKeys, figure_files_exist
from seanv_analysis.stages.validate import is_validation_entry

SETTINGS = settings(max_examples=150, deadline=None, database=None,
                    suppress_health_check=[HealthCheck.too_slow])

_scalars = st.one_of(st.none(), st.booleans(), st.integers(-10**6, 10**20),
                     st.floats(allow_nan=False), st.text(max_size=8))
_TAGS = ["dict", "kvdict", "list", "tuple", "ndarray", "objarray", "frame", "series",
         "timestamp", "path", "dataclass", "float", "range", "index", "values", "x"]
_KEYS = ["t", "v", "dtype", "shape", "b64", "columns", "data", "index", "name"]


def _tagged(children):
    return st.one_of(
        st.lists(children, max_size=4),
        st.dictionaries(st.sampled_from(_KEYS), children, max_size=5),
        st.fixed_dictionaries({"t": st.sampled_from(_TAGS)},
                              optional={k: children for k in _KEYS[1:]}),
        st.fixed_dictionaries({"t": st.just("ndarray"),
                               "dtype": st.sampled_from(["<f8", "<i8", "|O", "<U3", "x", "<f4"]),
                               "shape": st.lists(st.integers(-2, 5), max_size=3),
                               "b64": st.sampled_from(["", "AAAAAAAAAAA=", "AAAAAAAAAAAAAAAA",
                                                       "!!"])}))


_payloads = st.recursive(_scalars, _tagged, max_leaves=25)


def _plant(folder: Path, key: str, payload: bytes) -> None:
    (folder / f"{key}.json").write_bytes(b"seanv-cache-entry/2 "
                                         + hashlib.sha256(payload).hexdigest().encode()
                                         + b"\n" + payload)


@SETTINGS
@given(_payloads)
def test_fuzzed_cache_entries_decode_or_miss(doc):
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        _plant(folder, "k", json.dumps(doc).encode())
        rejected: list[str] = []
        value = read_entry(folder, "k", rejected=rejected)   # never raises
        assert (value is None) == bool(rejected) or doc is None
        for check in (is_summary_entry, is_validation_entry,
                      lambda v: figure_files_exist(v, str(folder))):
            assert check(value) in (True, False)


_paths = st.one_of(st.sampled_from(["/etc/passwd", "/dev/zero", "../x", "out/result.json",
                                    "out/.cache/pipeline.json", "out/figures/fig4.png"]),
                   st.text(max_size=10))
_stat = st.one_of(st.lists(st.integers(-5, 10**12), max_size=3), _scalars)


@SETTINGS
@given(memo=st.one_of(_scalars, st.fixed_dictionaries(
    {"schema": st.sampled_from(["seanv-pipeline-memo/1", "x"]), "key": st.sampled_from(["k", 1])},
    optional={"outputs": st.dictionaries(_paths, _stat, max_size=3)})),
    result=st.one_of(_scalars, st.dictionaries(
        st.sampled_from(["schema", "runs_found", "runs_read", "failed", "excluded", "figures",
                         "stage_errors", "stage_notes", "outputs", "report"]),
        st.recursive(_scalars, lambda c: st.one_of(st.lists(c, max_size=3),
                                                   st.dictionaries(st.text(max_size=4), c,
                                                                   max_size=3)),
                     max_leaves=10), max_size=10)))
def test_fuzzed_memos_reuse_nothing_outside_or_miss(memo, result):
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        (out / ".cache").mkdir(parents=True)
        (out / "result.json").write_text(json.dumps(result))
        if isinstance(memo, dict) and isinstance(memo.get("outputs"), dict):
            # the result file recorded with its true stat, so the rest is what is tested
            st_ = (out / "result.json").stat()
            memo["outputs"][str((out / "result.json").resolve())] = [st_.st_size, st_.st_mtime_ns]
        (out / ".cache" / MEMO_NAME).write_text(json.dumps(memo))
        doc = recorded_run(out, "k")                         # never raises
        if doc is not None:
            for p in doc["outputs"]:
                assert inside(p, out)


@SETTINGS
@given(st.one_of(_scalars, st.dictionaries(
    st.sampled_from(["fig4", "fig7", "x"]),
    st.one_of(_scalars, st.fixed_dictionaries(
        {"key": st.sampled_from(["k", 1, None])},
        optional={"files": st.one_of(_scalars, st.dictionaries(_paths, _stat, max_size=3))})),
    max_size=3)))
def test_fuzzed_figure_keys_reuse_only_the_folders_files(doc):
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp) / "figures"
        folder.mkdir()
        (folder / "fig4.png").write_bytes(b"png")
        (folder / _FigureKeys.NAME).write_text(json.dumps(doc))
        cwd = os.getcwd()
        os.chdir(tmp)   # relative paths in the file resolve against here
        try:
            keys = _FigureKeys(folder)
            for name in ("fig4", "fig7", "x"):
                got = keys.reuse(name, "k", ("png", "svg"))   # never raises
                for p in got or ():
                    assert p.resolve().parent == folder.resolve()
        finally:
            os.chdir(cwd)
