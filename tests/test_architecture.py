"""The package's floor plan, machine-checked (docs/architecture.md).

- ``lint-imports``: the layer contracts in pyproject.toml (each layer imports
  only those below it; models numpy/scipy only; discover and fit never
  simulate; results never write files; click only in the CLI; no cycles);
- every module of the package belongs to a layer of those contracts;
- no private name (``_x``) is imported from another package of the project;
- ``ruff check`` with the project's rules (pyflakes, import order, bugbear).
"""
from __future__ import annotations

import ast
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "seanv_analysis"


def _tool(name: str) -> str:
    exe = Path(sys.executable).parent / name
    if exe.exists():
        return str(exe)
    found = shutil.which(name)
    if found is None:
        pytest.fail(f"{name} not installed; `make test` installs it with the test extra")
    return found


def test_import_contracts_kept():
    res = subprocess.run([_tool("lint-imports"), "--no-cache"], cwd=ROOT, capture_output=True,
                         text=True)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]
    assert "BROKEN" not in res.stdout


def test_every_module_is_in_a_layer():
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    contracts = doc["tool"]["importlinter"]["contracts"]
    layers = next(c["layers"] for c in contracts if c["type"] == "layers")
    named = {m.strip() for layer in layers for m in layer.replace("|", ":").split(":")}
    top = {f"seanv_analysis.{p.stem if p.is_file() else p.name}" for p in PKG.iterdir()
           if (p.suffix == ".py" and p.stem not in ("__init__", "__main__"))
           or (p.is_dir() and (p / "__init__.py").exists())}
    assert top - named == set(), "modules outside every layer"


def _package_of(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2])


def _private_imports() -> list[str]:
    """``from X import _name`` or ``import X._mod`` where X is another
    top-level package of the project than the importer's."""
    bad = []
    for path in PKG.rglob("*.py"):
        rel = path.relative_to(ROOT).with_suffix("")
        module = ".".join(rel.parts)
        if path.name == "__init__.py":
            module = module.rsplit(".", 1)[0]
        package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
        tree = ast.parse(path.read_text(), str(path))
        for node in ast.walk(tree):
            if not isinstance(node, ast.ImportFrom):
                continue
            if node.level:
                base = package.split(".")
                base = base[:len(base) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            if not target.startswith("seanv_analysis"):
                continue
            same = _package_of(target) == _package_of(module)
            names = [a.name for a in node.names]
            private_mod = any(p.startswith("_") and not p.startswith("__")
                              for p in target.split(".")[1:])
            private_name = [n for n in names if n.startswith("_") and not n.startswith("__")]
            if not same and (private_mod or private_name):
                bad.append(f"{path.relative_to(ROOT)}:{node.lineno}: from {target} import "
                           f"{', '.join(names)}")
    return bad


def test_no_private_name_imported_across_packages():
    assert _private_imports() == []


def test_ruff_clean():
    res = subprocess.run([sys.executable, "-m", "ruff", "check", "--no-cache", "."], cwd=ROOT,
                         capture_output=True, text=True)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]


def test_no_dead_code():
    """vulture finds no unused function, class, method, attribute or variable
    in the package, its scripts and benchmarks (tests/vulture_whitelist.py
    lists what is used where vulture cannot see it, each with why)."""
    res = subprocess.run([sys.executable, "-m", "vulture", "seanv_analysis", "scripts",
                          "benchmarks", "tests/vulture_whitelist.py", "--min-confidence", "60"],
                         cwd=ROOT, capture_output=True, text=True)
    assert res.returncode == 0, res.stdout[-4000:] + res.stderr[-2000:]


def test_constraints_pin_every_dependency_within_pyproject():
    """constraints.txt (what `make venv` installs with) pins every package
    pyproject.toml asks for, at a version pyproject allows."""
    from packaging.requirements import Requirement

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    wanted = [Requirement(r) for r in project["dependencies"]]
    for extra in ("test", "dask"):
        wanted += [Requirement(r) for r in project["optional-dependencies"][extra]]
    pins = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line.strip() and not line.startswith("#"):
            name, version = line.split("==")
            pins[name.lower().replace("_", "-")] = version.strip()
    for req in wanted:
        name = req.name.lower().replace("_", "-")
        assert name in pins, f"{req.name} is not pinned in constraints.txt"
        assert req.specifier.contains(pins[name]), f"{req.name}=={pins[name]} vs {req}"


def test_license_is_an_spdx_expression():
    """Issue 33, point 6: ``license = { text = "MIT" }`` made setuptools warn
    (a 14-line BuildBackendWarning, twice) at every install; an SPDX string
    needs setuptools >= 77, which the build requires."""
    doc = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert doc["project"]["license"] == "MIT"
    assert "setuptools>=77" in doc["build-system"]["requires"]
