"""The data-set stage cache (batch.stage_memo): a stage whose inputs did not
change is reused bit for bit; one whose inputs changed runs again and gives
what a fresh run gives; the codec stores the stages' results exactly."""
from __future__ import annotations

import json
import shutil
import warnings
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from seanv_analysis.batch import run_pipeline
from seanv_analysis.batch.cache import read_entry
from seanv_analysis.batch.codec import CodecError, decode, encode
from seanv_analysis.io.hashing import content_sha256
from seanv_analysis.stages import discover, identify

PIPE = {"pipeline": {"name": "memo"}, "stages": [
    {"name": "ingest"}, {"name": "flowfit", "n_boot": 20},
    {"name": "identify", "parts": ["geometry"], "n_boot": 0},
    {"name": "figures", "figs": [4], "formats": ["png"]}]}
OUTPUTS = ("flowfit/flowfit.json", "flowfit/flowfit_details.json", "identify/identify.json",
           "identify/rig-identified.toml")


def _run(data: Path, out: Path, **kw):
    return run_pipeline(PIPE, data, out_dir=out, workers=1, quiet=True, **kw)


def _edit_pressure(run: Path, row: slice, dp: float) -> None:
    """Add ``dp`` [MPa] to the supply pressure logged at ``row`` of one run."""
    path = run / "pressure.csv"
    df = pd.read_csv(path)
    df.loc[row, "p_supply_mpag"] += dp
    df.to_csv(path, index=False)


@pytest.fixture(scope="module")
def memo_runs(golden_data, tmp_path_factory):
    """The golden flow steps copied; the pipeline run, one sample before the
    steady window edited and run again, then the whole pressure log of that
    run edited and run again; and a fresh run (--force) of the last data."""
    tmp = tmp_path_factory.mktemp("memo")
    data = tmp / "flow"
    shutil.copytree(golden_data / "flow", data)
    out = tmp / "out"
    first = _run(data, out)
    outputs = {f: (out / f).read_bytes() for f in OUTPUTS}
    fig4 = out / "figures" / "fig4.png"
    fig4_stat = fig4.stat().st_mtime_ns
    edited = sorted(p for p in data.iterdir() if p.is_dir())[0]
    _edit_pressure(edited, slice(5, 5), 0.001)
    second = _run(data, out)
    same = {f: (out / f).read_bytes() == outputs[f] for f in OUTPUTS}
    fig4_kept = fig4.stat().st_mtime_ns == fig4_stat
    _edit_pressure(edited, slice(None), 0.02)
    third = _run(data, out)
    fresh = _run(data, tmp / "fresh", force=True)
    return {"first": first, "second": second, "third": third, "fresh": fresh, "same": same,
            "fig4_kept": fig4_kept, "out": out, "fresh_out": tmp / "fresh", "outputs": outputs}


def test_unchanged_inputs_reuse_the_stages_bit_for_bit(memo_runs):
    """One sample before a flow step's steady window leaves the per-run
    summary as it was: the flow fit and identify are reused, their files
    byte for byte, and Fig. 4 (keyed by the fit's content) is not redrawn."""
    first, second = memo_runs["first"], memo_runs["second"]
    assert "stage_cache" not in first.stage_notes
    assert second.computed["ingest"] == 1          # the edited run's own work
    assert "flowfit, identify reused" in second.stage_notes["stage_cache"]
    assert all(memo_runs["same"].values()), memo_runs["same"]
    assert memo_runs["fig4_kept"]
    assert second.timings_s["flowfit"] < 0.5 * first.timings_s["flowfit"]


def test_changed_inputs_run_again_as_a_fresh_run(memo_runs):
    """The whole supply pressure log of one flow step 20 kPa higher changes its
    summary: both stages run again, and give what a fresh run gives."""
    third, out, fresh = memo_runs["third"], memo_runs["out"], memo_runs["fresh_out"]
    assert "stage_cache" not in third.stage_notes
    for f in OUTPUTS:
        assert (out / f).read_bytes() == (fresh / f).read_bytes(), f
    assert (out / OUTPUTS[1]).read_bytes() != memo_runs["outputs"][OUTPUTS[1]]


def test_stored_results_decode_to_the_same_content(golden_run, tmp_path):
    """The paper pipeline's stored stages (the golden data: the drain drift
    found, the closed-loop check run) decode to values with the content
    digest of a second round trip and the JSON each stage wrote."""
    _, out = golden_run
    folder = out / ".cache" / "stages"
    stored = {p.stem: read_entry(folder, p.stem) for p in folder.glob("*.json")}
    assert set(stored) == {"flowfit", "identify", "discover"}
    for name, entry in stored.items():
        value = entry["value"]
        again = decode(json.loads(json.dumps(encode(value))))
        assert content_sha256(again) == content_sha256(value), name
    disc = stored["discover"]["value"]
    assert disc.discovery.effects and disc.after is not None
    # the files the decoded values write are those the pipeline wrote
    for name, stage, files in (("discover", discover, ("discover.json", "discover.txt")),
                               ("identify", identify, ("identify.json", "rig-identified.toml"))):
        stage.write(stored[name]["value"], tmp_path / name)
        for f in files:
            assert (tmp_path / name / f).read_bytes() == (out / name / f).read_bytes(), f


@dataclass(frozen=True)
class _NotListed:
    x: float = 1.0


@dataclass
class _Holder:
    a: np.ndarray
    items: list = field(default_factory=list)


def test_codec_is_exact_and_refuses_other_classes():
    """numpy scalars and text arrays come back with their dtype (a figure's
    key is the content of its inputs); a dataclass outside the package's
    result modules is not stored, and a file naming one is refused."""
    value = {"f": np.float64(0.1), "i": np.int32(-3), "b": np.bool_(True),
             "s": np.array(["supply", "drain"]), "t": (1, [2.5, None])}
    back = decode(json.loads(json.dumps(encode(value))))
    assert content_sha256(back) == content_sha256(value)
    assert type(back["f"]) is np.float64 and back["s"].dtype == np.dtype("<U6")
    with pytest.raises(CodecError, match="cannot store"):
        encode(_NotListed())
    with pytest.raises(CodecError, match="allow-list"):
        decode({"t": "dataclass", "module": "os", "name": "system", "v": {}})
    with pytest.raises(CodecError, match="not a dataclass"):
        decode({"t": "dataclass", "module": "seanv_analysis.fit.flowfit", "name": "fit_flow",
                "v": {}})
    with pytest.raises(CodecError, match="allow-list"):   # a dataclass, but no result
        decode({"t": "dataclass", "module": "seanv_analysis.stages.base", "name": "Context",
                "v": {}})


def test_warnings_of_a_reused_stage_are_given_again(tmp_path, monkeypatch):
    """A stage's warnings are stored with its value and given again when it is
    reused (a run's record lists them as when the stage ran)."""
    from seanv_analysis.batch.stage_memo import StageMemo

    class Stage:
        NAME = "flowfit"
        calls = 0

        @staticmethod
        def raw_inputs(ctx, options):
            return []

        @classmethod
        def run(cls, ctx, options):
            cls.calls += 1
            warnings.warn("bootstrap did not converge", RuntimeWarning, stacklevel=2)
            return {"z0_mm": np.float64(-0.155)}

    class Ctx:
        results: dict = {}
        start_model = None

        class rig:
            @staticmethod
            def to_dict():
                return {"name": "r"}

        @staticmethod
        def result(name):
            return Ingest() if name == "ingest" else None

    class Ingest:
        summary = pd.DataFrame({"q_mm3_s": [1.0, 2.0]})
        failed = ()
        input_hashes: dict = {}

    for _ in range(2):
        memo = StageMemo(tmp_path / ".cache")
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            value = memo.run(Stage, Ctx, {})
        assert [str(w.message) for w in caught] == ["bootstrap did not converge"]
        assert caught[0].category is RuntimeWarning and value == {"z0_mm": -0.155}
    assert Stage.calls == 1 and memo.reused == ["flowfit"]
    # an entry of another shape (its digest consistent: written by hand) is a miss
    from seanv_analysis.batch.cache import write_entry

    entry = read_entry(tmp_path / ".cache" / "stages", "flowfit")
    write_entry(tmp_path / ".cache" / "stages", "flowfit", {**entry, "warnings": [1]})
    with warnings.catch_warnings(record=True):
        warnings.simplefilter("always")
        StageMemo(tmp_path / ".cache").run(Stage, Ctx, {})
    assert Stage.calls == 2


def test_a_linked_or_tampered_stage_cache_is_never_followed(memo_runs, tmp_path):
    """``.cache/stages`` that is a link is refused (one line naming it); an
    entry whose content does not match its digest is a miss, removed, and
    the run says so."""
    from seanv_analysis.batch.stage_memo import StageMemo
    from seanv_analysis.errors import OutputError

    (tmp_path / "elsewhere").mkdir()
    (tmp_path / ".cache").mkdir()
    (tmp_path / ".cache" / "stages").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(OutputError, match="stages: a link"):
        StageMemo(tmp_path / ".cache")
    out = tmp_path / "out"
    shutil.copytree(memo_runs["out"], out)
    entry = out / ".cache" / "stages" / "flowfit.json"
    entry.write_bytes(entry.read_bytes().replace(b'"key"', b'"kex"'))
    res = _run(memo_runs["out"].parent / "flow", out)
    assert "flowfit" not in res.stage_notes.get("stage_cache", "")
    assert "flowfit.json: damaged entry" in res.stage_notes["cache"]
    assert (out / OUTPUTS[0]).read_bytes() == (memo_runs["out"] / OUTPUTS[0]).read_bytes()
