"""The per-run ingest's shortcuts give what the general paths give.

- ``signals.stats``: median, nanmedian, nanmean equal numpy's, bit for bit;
- ``io.scan.scan_file``: a small file is kept whole (parsed from memory), a
  larger one is not, and the hash is the same either way;
- ``io.table_file.locate_table`` with a folder listing: the same file as
  file by file, and anything unusual (a name in two cases, a link) left to
  the general path;
- a table parsed from the bytes read for its hash equals one read from disk.
"""
from __future__ import annotations

import hashlib
import os
import warnings

import numpy as np
import pyarrow as pa
import pytest

from seanv_analysis.errors import DataError
from seanv_analysis.io import read_run
from seanv_analysis.io import scan as scan_mod
from seanv_analysis.io.contract import table_specs
from seanv_analysis.io.formats import table_formats
from seanv_analysis.io.scan import scan_file
from seanv_analysis.io.table_file import folder_listing, locate_table
from seanv_analysis.signals import stats


def _same(a: float, b: float) -> bool:
    """Equal as doubles, NaN equal to NaN and the sign of zero compared."""
    return (np.array_equal(np.float64(a), np.float64(b), equal_nan=True)
            and bool(np.signbit(a)) == bool(np.signbit(b)))


def _samples():
    rng = np.random.default_rng(7)
    for n in (1, 2, 3, 4, 5, 50, 51, 3800):
        x = rng.normal(size=n) * 3.0
        yield x
        yield np.round(x, 1)                                 # ties
        yield np.where(rng.random(n) < 0.5, -0.0, 0.0)       # signed zeros
        y = x.copy()
        y[rng.integers(0, n)] = np.nan
        yield y
        y = x.copy()
        y[rng.integers(0, n)] = np.inf
        yield y
        yield np.full(n, np.nan)
        yield x[::2] if n > 1 else x                         # a strided view


@pytest.mark.parametrize("ours, numpys", [(stats.median, np.median),
                                          (stats.nanmedian, np.nanmedian),
                                          (stats.nanmean, np.nanmean)])
def test_stats_equal_numpy_bit_for_bit(ours, numpys):
    for x in _samples():
        before = x.copy()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)   # all-NaN slices
            got, want = ours(x), float(numpys(x))
        assert _same(got, want), (ours.__name__, x[:8], got, want)
        assert np.array_equal(x, before, equal_nan=True)      # argument untouched


def test_scan_keeps_a_small_file_whole_and_a_large_one_not(tmp_path, monkeypatch):
    small, large = tmp_path / "small.bin", tmp_path / "large.bin"
    small.write_bytes(b"abc" * 1000)
    large.write_bytes(bytes(range(256)) * 400)                # 102400 bytes
    for path in (small, large):
        s = scan_file(path, want_hash=True, find_nul=False)
        assert s.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
        assert s.data == path.read_bytes()
        assert (s.stat.st_ino, s.stat.st_size) == (os.stat(path).st_ino, path.stat().st_size)
    monkeypatch.setattr(scan_mod, "_CHUNK", 1 << 16)          # the large file takes two reads
    s = scan_file(large, want_hash=True, find_nul=False)
    assert s.data is None and s.size == 102400
    assert s.sha256 == hashlib.sha256(large.read_bytes()).hexdigest()
    assert scan_file(large, want_hash=False, find_nul=False).data is None
    assert scan_file(small, want_hash=False, find_nul=False).data == small.read_bytes()


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_parse_from_bytes_equals_parse_from_disk(tmp_path, make_run, fmt):
    run_dir = make_run(tmp_path, "flow_step", fmt=fmt, duration_s=0.3, seed=2)
    table_format = next(f for f in table_formats() if f.name == fmt)
    assert table_format.parses_bytes
    for name in ("encoder", "pressure", "servo"):
        path = run_dir / f"{name}.{fmt}"
        s = scan_file(path, want_hash=True, find_nul=table_format.text)
        spec, pool = table_specs()[name], pa.default_memory_pool()
        from_bytes = table_format.parse(path, spec, s.head, pool, data=s.data)
        from_disk = table_format.parse(path, spec, s.head, pool, data=None)
        assert from_bytes.equals(from_disk)


def test_listing_finds_what_file_by_file_finds(tmp_path, make_run):
    run_dir = make_run(tmp_path, "flow_step", fmt="parquet", duration_s=0.2)
    listing = folder_listing(run_dir)
    for spec in table_specs().values():
        if "flow_step" in spec.kinds:
            assert (locate_table(run_dir, spec, "flow_step", listing=listing)
                    == locate_table(run_dir, spec, "flow_step"))


def test_unusual_entries_are_left_to_the_general_path(tmp_path, make_run):
    run_dir = make_run(tmp_path, "flow_step", fmt="csv", duration_s=0.2)
    spec = table_specs()["encoder"]
    # the same name in another case (a second file on a case-sensitive disk)
    (run_dir / "ENCODER.CSV").write_bytes((run_dir / "encoder.csv").read_bytes())
    listing = folder_listing(run_dir)
    assert (locate_table(run_dir, spec, "flow_step", listing=listing)
            == locate_table(run_dir, spec, "flow_step"))
    os.remove(run_dir / "ENCODER.CSV")
    # a table that is a link inside the data set: followed, as without a listing
    shared = tmp_path / "shared-servo.csv"
    os.replace(run_dir / "servo.csv", shared)
    (run_dir / "servo.csv").symlink_to(shared)
    servo = table_specs()["servo"]
    assert (locate_table(run_dir, servo, "flow_step", listing=folder_listing(run_dir))
            == (run_dir / "servo.csv", next(f for f in table_formats() if f.name == "csv")))
    # two formats of one table: still refused
    (run_dir / "pressure.parquet").write_bytes(b"PAR1")
    with pytest.raises(DataError, match="both pressure.csv and pressure.parquet exist"):
        read_run(run_dir)


def test_a_linked_run_folder_is_refused_when_listed(tmp_path, make_run):
    run_dir = make_run(tmp_path, "flow_step", fmt="csv", duration_s=0.2)
    link = tmp_path / "linked"
    link.symlink_to(run_dir)
    with pytest.raises(DataError, match="symbolic link to a folder"):
        folder_listing(link)
