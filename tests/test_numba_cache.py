"""The compiled simulator's cache is keyed by content, not by where the
package lies: a moved checkout or an installed wheel with the same sources
reuses it (tests/test_wheel.py runs an installed copy on it)."""
from __future__ import annotations

from pathlib import Path

from numba.core import config


def test_package_functions_are_cached_under_their_package_folder():
    from seanv_analysis.sim import jit
    from seanv_analysis.sim.numba_cache import PackageCacheLocator

    assert config.CACHE_LOCATOR_CLASSES.startswith("seanv_analysis.sim.numba_cache.")
    loc = PackageCacheLocator.from_function(jit.flow.py_func, jit._valve.__file__)
    assert loc is not None
    assert Path(loc.get_cache_path()) == Path(config.CACHE_DIR) / "pkg" / "models"
    # numba stamps entries by the source's content, not its path or mtime
    assert loc.get_source_stamp() == PackageCacheLocator.from_function(
        jit.flow.py_func, jit._valve.__file__).get_source_stamp()


def test_other_files_are_left_to_numbas_locators(tmp_path):
    from seanv_analysis.sim.numba_cache import PackageCacheLocator

    other = tmp_path / "mod.py"
    other.write_text("def f():\n    return 1\n")
    namespace: dict = {}
    exec(compile(other.read_text(), str(other), "exec"), namespace)
    assert PackageCacheLocator.from_function(namespace["f"], str(other)) is None
