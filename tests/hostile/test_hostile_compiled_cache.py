"""Issue 34, point 2: code is loaded from the cache folder only when it is
safe. The compiled simulator module and numba's cache are used only from a
folder of this user's with mode 0700 (made so, or refused with a warning and
the JIT used); a module is loaded only when its recorded SHA-256 matches;
a corrupt one is built again; one missing its functions is no traceback.

No test compiles anything: the build and the load are replaced by stand-ins
that record what they were asked (loading a module is what runs its code)."""
from __future__ import annotations

import hashlib
import os
import stat
import subprocess
import sys
import types

import pytest

from seanv_analysis import config
from seanv_analysis.sim import compiled


@pytest.fixture
def fresh(monkeypatch, tmp_path):
    """compiled.py as in a new process, its cache under tmp_path/cache; the
    build and the load recorded (``calls``), the build writing ``BUILT``."""
    monkeypatch.setenv("SEANV_NUMBA_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("SEANV_AOT", raising=False)
    monkeypatch.delenv("NUMBA_DISABLE_JIT", raising=False)
    monkeypatch.setattr(compiled, "_loaded", {})
    monkeypatch.setattr(compiled, "_status", None)
    monkeypatch.setattr(compiled, "_module", None)
    calls = {"build": [], "load": []}

    def build(path=None):
        path = compiled.aot_module_path() if path is None else path
        calls["build"].append(path)
        path.write_bytes(BUILT)
        compiled._record_path(path).write_text(hashlib.sha256(BUILT).hexdigest() + "\n")
        return path

    def load(path):
        calls["load"].append(path.read_bytes())
        return types.SimpleNamespace(**{name: (lambda *a: "aot") for name in compiled.SIGNATURES})

    monkeypatch.setattr(compiled, "build_aot", build)
    monkeypatch.setattr(compiled, "_load", load)
    return calls


BUILT = b"\x7fELF built here"
PLANTED = b"\x7fELF planted: its init code would run on import"


def _plant(path, data=PLANTED, *, record=True, folder_mode=0o700):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    if record:
        compiled._record_path(path).write_text(hashlib.sha256(data).hexdigest())
    os.chmod(path.parent, folder_mode)


def _jit(name="simulate_kernel"):
    from seanv_analysis.sim import kernel

    return getattr(kernel, name)


def test_a_module_in_another_users_folder_is_not_loaded(fresh, monkeypatch, caplog):
    """The probe: a module planted at aot-<key>/ (another user's folder,
    mode 777) was imported and its init code ran."""
    path = compiled.aot_module_path()
    _plant(path, folder_mode=0o777)
    monkeypatch.setattr(config, "_uid", lambda: os.getuid() + 4242)   # the folder is not ours
    with caplog.at_level("WARNING", logger="seanv_analysis"):
        assert compiled.simulate_kernel().__wrapped__ is _jit()
    assert fresh["load"] == [] and fresh["build"] == []
    assert "owned by user id" in compiled.aot_status() and "not by you" in compiled.aot_status()
    assert any("numba's JIT" in r.getMessage() for r in caplog.records)
    assert path.read_bytes() == PLANTED                      # another user's file: left alone


@pytest.mark.skipif(not hasattr(os, "getuid") or os.getuid() != 0,
                    reason="needs root to give a folder to another user")
def test_a_folder_really_owned_by_another_user_is_refused(fresh):
    path = compiled.aot_module_path()
    _plant(path, folder_mode=0o777)
    os.chown(path.parent, 65534, 65534)
    os.chown(path, 65534, 65534)
    assert compiled.simulate_kernel().__wrapped__ is _jit()
    assert fresh["load"] == [] and "owned by user id 65534" in compiled.aot_status()


def test_a_folder_open_to_others_is_emptied_and_made_private(fresh):
    """Our folder, but mode 777: its module (even with a matching record)
    may be someone else's: removed, built again, the folder made 0700."""
    path = compiled.aot_module_path()
    _plant(path, folder_mode=0o777)
    assert compiled.simulate_kernel().__wrapped__() == "aot"
    assert fresh["build"] == [path] and fresh["load"] == [BUILT]
    assert stat.S_IMODE(os.stat(path.parent).st_mode) == 0o700
    assert stat.S_IMODE(os.stat(compiled.aot_module_path().parents[1]).st_mode) == 0o700


@pytest.mark.parametrize("record", ["none", "other", "garbage", "link"])
def test_a_module_without_its_recorded_sha256_is_rebuilt_before_any_load(fresh, record):
    """The probe: a corrupt .so was never rebuilt."""
    path = compiled.aot_module_path()
    _plant(path, record=False)
    rec = compiled._record_path(path)
    if record == "other":
        rec.write_text(hashlib.sha256(b"something else").hexdigest())
    elif record == "garbage":
        rec.write_bytes(b"\xff" * 5000)
    elif record == "link":
        target = path.parent / "elsewhere"
        target.write_text(hashlib.sha256(PLANTED).hexdigest())
        rec.symlink_to(target)
    assert compiled.servo_track().__wrapped__() == "aot"
    assert fresh["build"] == [path] and fresh["load"] == [BUILT]   # never the planted bytes


def test_a_module_with_its_recorded_sha256_is_loaded_without_a_build(fresh):
    path = compiled.aot_module_path()
    _plant(path, BUILT)
    assert compiled.simulate_kernel().__wrapped__() == "aot"
    assert fresh["build"] == [] and fresh["load"] == [BUILT]


def test_a_writable_module_file_is_rebuilt(fresh):
    path = compiled.aot_module_path()
    _plant(path, BUILT)
    os.chmod(path, 0o666)
    compiled.simulate_kernel()
    assert fresh["build"] == [path]


def test_a_module_missing_its_functions_is_removed_and_the_jit_serves(fresh, monkeypatch):
    """The probe: a module missing its functions gave an AttributeError traceback."""
    path = compiled.aot_module_path()
    _plant(path, BUILT)
    monkeypatch.setattr(compiled, "_load", lambda p: types.SimpleNamespace(servo_track=len))
    assert compiled.simulate_kernel().__wrapped__ is _jit()
    assert compiled.servo_track().__wrapped__ is _jit("servo_track")
    assert "lacks simulate_kernel" in compiled.aot_status()
    assert not path.exists() and not compiled._record_path(path).exists()


def test_private_folder_refuses_a_file_and_another_users_folder(tmp_path, monkeypatch):
    (tmp_path / "f").write_text("")
    with pytest.raises(config.ConfigError, match="not a folder"):
        config.private_folder(tmp_path / "f")
    monkeypatch.setattr(config, "_uid", lambda: os.getuid() + 1)
    with pytest.raises(config.ConfigError, match=r"owned by user id \d+, not by you"):
        config.private_folder(tmp_path)


def test_private_folder_tightens_and_tells_whether_others_could_write(tmp_path):
    (tmp_path / "a").mkdir(mode=0o755)
    os.chmod(tmp_path / "a", 0o755)
    assert config.private_folder(tmp_path / "a") is False      # readable only: contents trusted
    assert stat.S_IMODE(os.stat(tmp_path / "a").st_mode) == 0o700
    (tmp_path / "b").mkdir()
    os.chmod(tmp_path / "b", 0o777)
    assert config.private_folder(tmp_path / "b") is True
    assert config.private_folder(tmp_path / "new" / "c") is False
    assert stat.S_IMODE(os.stat(tmp_path / "new" / "c").st_mode) == 0o700


_NUMBA = """
import sys
import seanv_analysis.config as c
if sys.argv[1] == "other":
    c._uid = lambda: 4242 + __import__("os").getuid()
from seanv_analysis.sim.numba_cache import configure_numba_cache
print(configure_numba_cache())
"""


def _numba_cache_dir(base, who="me"):
    env = {**os.environ, "SEANV_NUMBA_CACHE": str(base)}
    env.pop("NUMBA_CACHE_DIR", None)
    res = subprocess.run([sys.executable, "-c", _NUMBA, who], capture_output=True, text=True,
                         env=env, timeout=120)
    assert res.returncode == 0, res.stderr
    return res.stdout.strip(), res.stderr


def test_numba_cache_of_another_user_is_not_used(tmp_path):
    """The probe: with SEANV_AOT=0 numba's index pickles planted in the cache
    folder ran. Another user's cache folder: numba caches in a fresh private
    folder of this process, and a warning says so."""
    base = tmp_path / "cache"
    base.mkdir()
    os.chmod(base, 0o777)
    folder, err = _numba_cache_dir(base, "other")
    assert not folder.startswith(str(base)), folder
    assert "not by you" in err and "numba's cache for this process" in err


def test_numba_cache_open_to_others_is_emptied(tmp_path):
    base = tmp_path / "cache"
    folder, _ = _numba_cache_dir(base)
    assert folder.startswith(str(base))
    planted = os.path.join(folder, "pkg", "models")
    os.makedirs(planted)
    with open(os.path.join(planted, "valve.flow-1.py311.nbi"), "wb") as fh:
        fh.write(b"a pickle of someone else's")
    os.chmod(folder, 0o777)
    again, _ = _numba_cache_dir(base)
    assert again == folder and os.listdir(folder) == []
    assert stat.S_IMODE(os.stat(folder).st_mode) == 0o700
    assert stat.S_IMODE(os.stat(base).st_mode) == 0o700
