"""Table formats registry: the shipped formats match the contract, and a new
format is one module (a parse function and its registry entry); the contract's
formats come first, a format it does not name is looked for after them."""
from __future__ import annotations

from pathlib import Path

import pandas as pd
import pyarrow as pa
import pytest

from seanv_analysis.errors import ConfigError, DataError
from seanv_analysis.io import formats, read_dataset, read_run, write_run
from seanv_analysis.io.atomic import atomic_path
from seanv_analysis.io.contract import TableSpec, canonical_names, contract
from seanv_analysis.io.formats import (
    TableFormat,
    register_format,
    registered_formats,
    table_formats,
    table_suffixes,
)

# a toy format: tab-separated text, parsed by pandas ---------------------------

def _parse_tsv(path: Path, spec: TableSpec, head: bytes, pool: pa.MemoryPool) -> pa.Table:
    try:
        df = pd.read_csv(path, sep="\t")
    except (ValueError, UnicodeDecodeError) as exc:
        raise DataError(f"not a readable TSV table ({exc})", path=path) from None
    table = pa.Table.from_pandas(df, preserve_index=False)
    return table.rename_columns(canonical_names(table.column_names, spec))


def _write_tsv(df: pd.DataFrame, path: Path) -> None:
    with atomic_path(path) as tmp:
        df.to_csv(tmp, sep="\t", index=False, float_format="%.9g", na_rep="")


TSV = TableFormat("tsv", "TSV", (".tsv",), _parse_tsv, _write_tsv, text=True)


@pytest.fixture
def tsv(monkeypatch):
    """The toy format registered and named in the contract, for this test only."""
    saved = dict(formats.FORMATS)
    monkeypatch.setitem(contract(), "table_formats", [*contract()["table_formats"], "tsv"])
    try:
        yield register_format(TSV)
    finally:
        formats.FORMATS.clear()
        formats.FORMATS.update(saved)


def _same_run(a, b) -> None:
    assert (a.run_id, a.kind, a.meta.started_at, a.meta.controller) == \
           (b.run_id, b.kind, b.meta.started_at, b.meta.controller)
    assert list(a.tables) == list(b.tables)
    for name in a.tables:
        pd.testing.assert_frame_equal(a.tables[name], b.tables[name], check_exact=True)


# the shipped registry -----------------------------------------------------------

def test_shipped_registry_matches_contract():
    names = [fmt.name for fmt in registered_formats()]
    assert names == list(contract()["table_formats"]) == ["csv", "parquet"]
    assert [fmt.name for fmt in table_formats()] == names
    assert table_suffixes() == (".csv", ".parquet")
    for fmt in table_formats():
        assert callable(fmt.parse) and callable(fmt.write)
        assert all(formats.FORMATS[s] is fmt for s in fmt.suffixes)


# a new format -------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["flow_step", "position_control"])
def test_toy_format_reads_like_csv(tmp_path, make_run, tsv, kind):
    as_csv = make_run(tmp_path / "csv", kind, duration_s=0.3, seed=4, fmt="csv")
    as_tsv = make_run(tmp_path / "tsv", kind, duration_s=0.3, seed=4, fmt="tsv")
    assert {p.suffix for p in as_tsv.iterdir()} == {".json", ".tsv"}
    a, b = read_run(as_csv), read_run(as_tsv)
    _same_run(a, b)
    assert b.files["encoder"].suffix == ".tsv" and str(b.files["encoder"]) in b.file_sha256


def test_toy_format_in_a_data_set(tmp_path, make_dataset, tsv):
    a = read_dataset(make_dataset(tmp_path / "csv", n_flow=2, n_position=1, fmt="csv"))
    b = read_dataset(make_dataset(tmp_path / "tsv", n_flow=2, n_position=1, fmt="tsv"))
    assert a.success and b.success and len(a.runs) == len(b.runs) == 3
    for x, y in zip(a.runs, b.runs):
        _same_run(x, y)


def test_toy_format_joins_the_reader_messages(tmp_path, make_run, tsv):
    run_dir = make_run(tmp_path, duration_s=0.2, fmt="tsv")
    (run_dir / "encoder.tsv").rename(run_dir / "gone")
    with pytest.raises(DataError, match=r"no encoder\.csv, encoder\.parquet or encoder\.tsv"):
        read_run(run_dir)
    (run_dir / "gone").rename(run_dir / "encoder.tsv")
    write_run(tmp_path / "other", {}, {"encoder": pd.read_csv(run_dir / "encoder.tsv", sep="\t")})
    (tmp_path / "other" / "encoder.csv").rename(run_dir / "encoder.csv")
    with pytest.raises(DataError, match=r"both encoder\.csv and encoder\.tsv exist"):
        read_run(run_dir)


def test_toy_text_format_reports_binary_data(tmp_path, make_run, tsv):
    run_dir = make_run(tmp_path, duration_s=0.2, fmt="tsv")
    with open(run_dir / "servo.tsv", "r+b") as fh:
        fh.seek(40)
        fh.write(b"\x00")
    with pytest.raises(DataError, match=r"servo\.tsv: binary data .*UTF-8 TSV text table"):
        read_run(run_dir)


# contract and registry must agree ---------------------------------------------

def test_format_named_in_contract_without_parser_is_a_config_error(tmp_path, make_run,
                                                                     make_dataset, monkeypatch):
    run_dir = make_run(tmp_path / "run", duration_s=0.2)
    data = make_dataset(tmp_path / "data", n_flow=2)
    monkeypatch.setitem(contract(), "table_formats", ["csv", "parquet", "feather"])
    with pytest.raises(ConfigError, match=r"contract\.toml: table_formats names 'feather' but "
                                          r"no parser is registered"):
        read_run(run_dir)
    with pytest.raises(ConfigError, match="'feather'"):  # once, not as one error per run
        read_dataset(data)


def test_a_format_the_contract_does_not_name_is_an_extension(tmp_path, make_run):
    """Registered without a contract change (the one-file recipe): read after
    the contract's formats, which keep their order."""
    run_dir = make_run(tmp_path, duration_s=0.2)
    saved = dict(formats.FORMATS)
    try:
        register_format(TSV)
        assert [f.name for f in table_formats()] == ["csv", "parquet", "tsv"]
        assert table_suffixes() == (".csv", ".parquet", ".tsv")
        read_run(run_dir)
    finally:
        formats.FORMATS.clear()
        formats.FORMATS.update(saved)
    assert [f.name for f in table_formats()] == ["csv", "parquet"]


def test_register_format_refuses_a_taken_or_bad_suffix():
    with pytest.raises(ValueError, match=r"suffix '\.csv' is already read by format 'csv'"):
        register_format(TableFormat("csv2", "CSV", (".csv",), _parse_tsv))
    with pytest.raises(ValueError, match="with their dot"):
        register_format(TableFormat("tsv", "TSV", ("tsv",), _parse_tsv))
    assert [fmt.name for fmt in registered_formats()] == ["csv", "parquet"]


def test_write_run_names_the_writable_formats(tmp_path):
    with pytest.raises(ValueError, match=r"fmt: expected 'csv' or 'parquet', got 'xlsx'"):
        write_run(tmp_path / "r", {}, {}, fmt="xlsx")
    assert not (tmp_path / "r").exists()
