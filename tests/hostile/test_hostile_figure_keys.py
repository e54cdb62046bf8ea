"""Issue 34, point 3 (figure keys and the report): ``figures/.figure-keys.json``
is untrusted input: a figure is reused only from files directly in its
folder (no link, nothing outside --out), and the report embeds only the
output folder's own figures: a PNG that is a PNG, an SVG without script."""
from __future__ import annotations

import json
import os
import shutil

import pytest
from click.testing import CliRunner

from seanv_analysis.batch.memo import MEMO_NAME
from seanv_analysis.cli import cli


def copy_out(src, tmp_path):
    """A copy of the shared output folder to plant files in."""
    dst = tmp_path / "out"
    shutil.copytree(src, dst, symlinks=True)
    return dst


def test_planted_figure_keys_pull_nothing_from_outside(flowfit_out, hostile_data, tmp_path):
    """The probe: a planted figures/.figure-keys.json pulled a file from
    outside --out (with its <script>) into report.html and listed it as an output."""
    out = copy_out(flowfit_out, tmp_path)
    evil = tmp_path / "evil.svg"
    evil.write_text("<svg xmlns='http://www.w3.org/2000/svg'><script>alert(1)</script></svg>")
    evil_png = tmp_path / "evil.png"
    evil_png.write_bytes(b"<script>alert(2)</script>")
    keys_path = out / "figures" / ".figure-keys.json"
    keys = json.loads(keys_path.read_text())
    files = {}
    for p in (evil, evil_png):
        st = p.stat()
        files[str(p)] = [st.st_size, st.st_mtime_ns]
    keys["fig4"]["files"] = files
    keys_path.write_text(json.dumps(keys))
    (out / ".cache" / MEMO_NAME).unlink()
    res = CliRunner().invoke(cli, ["run", "flowfit", str(hostile_data), "--out", str(out), "-q",
                                   "--workers", "1"])
    assert res.exit_code == 0, res.output
    report = (out / "report.html").read_text()
    assert "<script" not in report and "alert(" not in report
    doc = json.loads((out / "result.json").read_text())
    assert all(str(tmp_path / "evil") not in p for p in doc["outputs"])
    assert sorted(doc["figures"]["fig4"]) == [str(out / "figures" / f"fig4.{f}") for f in ("png", "svg")]


@pytest.mark.parametrize("keys", ['{"fig4": {"key": 1, "files": []}}', "[" * 100000, "[]",
                                  '{"fig4": {"key": "k", "files": {"x.png": "big"}}}'])
def test_malformed_figure_keys_are_empty(tmp_path, keys):
    from seanv_analysis.stages.figures import _FigureKeys

    (tmp_path / _FigureKeys.NAME).write_text(keys)
    assert _FigureKeys(tmp_path).doc == {}


def test_figure_keys_reuse_only_files_of_their_folder(tmp_path):
    from seanv_analysis.stages.figures import _FigureKeys

    folder = tmp_path / "figures"
    folder.mkdir()
    outside = tmp_path / "x.png"
    outside.write_bytes(b"png")
    inside = folder / "x.png"
    inside.symlink_to(outside)
    for target in (outside, inside, folder / ".." / "x.png"):
        st = os.stat(target)
        (folder / _FigureKeys.NAME).write_text(json.dumps(
            {"f": {"key": "k", "files": {str(target): [st.st_size, st.st_mtime_ns]}}}))
        assert _FigureKeys(folder).reuse("f", "k", ("png",)) is None


def test_a_cached_per_run_figure_outside_its_folder_is_a_miss(tmp_path):
    from seanv_analysis.stages.figures import figure_files_exist

    (tmp_path / "fig6").mkdir()
    (tmp_path / "fig6" / "a.png").write_bytes(b"x")
    (tmp_path / "b.png").write_bytes(b"x")
    folder = str(tmp_path / "fig6")
    assert figure_files_exist({"paths": [str(tmp_path / "fig6" / "a.png")], "run_id": "r"}, folder)
    assert not figure_files_exist({"paths": [str(tmp_path / "b.png")], "run_id": "r"}, folder)
    assert not figure_files_exist({"paths": "/etc/passwd", "run_id": "r"}, folder)
    assert not figure_files_exist({"paths": ["/dev/zero"], "run_id": "r"}, folder)


def test_the_report_embeds_only_figures_of_the_output_folder(tmp_path):
    from seanv_analysis.report._format import _figure

    out = tmp_path / "out"
    out.mkdir()
    (tmp_path / "a.svg").write_text("<svg><text>outside</text></svg>")
    assert _figure(tmp_path / "a.svg", root=out) == ""
    (out / "b.svg").write_text("<svg><script>alert(1)</script></svg>")
    (out / "c.svg").write_text("<svg><a href='https://x.example/'>x</a></svg>")
    (out / "d.png").write_bytes(b"not a png")
    (out / "e.svg").write_text("<svg><rect onload='alert(1)'/></svg>")
    for name in ("b.svg", "c.svg", "d.png", "e.svg"):
        assert _figure(out / name, root=out) == "", name
    (out / "f.svg").symlink_to(tmp_path / "a.svg")
    assert _figure(out / "f.svg", root=out) == ""
    (out / "g.svg").write_text("<?xml?><svg><use xlink:href='#p1'/></svg>")
    assert "<svg><use" in _figure(out / "g.svg", root=out)
