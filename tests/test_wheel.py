"""A non-editable install works: the wheel carries the data contract, the
default rig and the shipped pipelines (issue: ``simulate`` said
"data_schema folder not found next to the package" from a wheel).

The wheel is built from a copy of the sources (the checkout is not written
to), installed with ``pip install --target`` into a temporary folder, and
run from another folder with only that copy of the package importable (its
dependencies come from the test environment).
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("wheel")
    src = tmp / "src"
    shutil.copytree(REPO / "seanv_analysis", src / "seanv_analysis",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy(REPO / name, src / name)
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(src), "--no-deps",
                    "--no-build-isolation", "-w", str(tmp / "dist"), "-q"],
                   check=True, capture_output=True)
    wheel = next((tmp / "dist").glob("seanv_analysis-*.whl"))
    site = tmp / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "--target", str(site),
                    str(wheel), "-q"], check=True, capture_output=True)
    work = tmp / "work"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(site), "MPLBACKEND": "Agg"}
    return wheel, site, work, env


def _run(installed, *args, timeout=300):
    _, _, work, env = installed
    return subprocess.run([sys.executable, "-m", "seanv_analysis", *map(str, args)], cwd=work,
                          env=env, capture_output=True, text=True, timeout=timeout)


def test_wheel_carries_the_package_data(installed):
    wheel = installed[0]
    names = set(zipfile.ZipFile(wheel).namelist())
    for need in ("seanv_analysis/_data_schema/contract.toml",
                 "seanv_analysis/_data_schema/rig/default.toml",
                 "seanv_analysis/_data_schema/json/run.schema.json",
                 "seanv_analysis/_pipelines/paper.toml"):
        assert need in names


def test_installed_copy_simulates_and_runs_the_shipped_pipelines(installed):
    """Every use of the package data from an installed copy: the data
    contract and default rig (simulate, ingest), the shipped pipelines found
    by name (the flowfit and tracking pipelines run; the paper pipeline, whose
    stages are all tested in the checkout, is found and parsed)."""
    _, site, work, env = installed
    where = subprocess.run([sys.executable, "-c", "import seanv_analysis; print(seanv_analysis.__file__)"],
                           cwd=work, env=env, capture_output=True, text=True, check=True).stdout
    assert where.startswith(str(site)), where          # the wheel's copy, not the checkout
    for scenario, folder in (("paper-flowsteps-small", "flow"), ("paper-position", "position")):
        res = _run(installed, "simulate", scenario, "--out", f"data/{folder}")
        assert res.returncode == 0, res.stderr
    # figures are Python only (nothing shipped): tested in the checkout
    for name, folder in (("flowfit", "flow"), ("tracking", "position")):
        res = _run(installed, "run", name, f"data/{folder}", "--out", f"out-{name}",
                   "--workers", "1", "--json", "-q", "--no-figures")
        assert res.returncode == 0, res.stderr + res.stdout[-2000:]
        doc = json.loads(res.stdout)
        assert doc["runs_read"] >= 2 and not doc["failed"] and not doc["stage_errors"]
        assert doc[name] is not None, name
        assert (work / f"out-{name}" / "report.html").is_file()
    shipped = subprocess.run(
        [sys.executable, "-c", "from seanv_analysis.stages.pipeline import load_pipeline; "
         "print(' '.join(load_pipeline('paper').stage_names))"],
        cwd=work, env=env, capture_output=True, text=True)
    assert shipped.returncode == 0, shipped.stderr
    assert shipped.stdout.split() == ["ingest", "flowfit", "identify", "tracking", "validate",
                                      "discover", "figures", "report"]
