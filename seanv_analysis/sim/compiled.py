"""The simulator's compiled entry points, compiled ahead of time where possible.

numba compiles the plant kernel, the servo track and the controllers'
replay over logged ticks (:mod:`.kernel`, :mod:`.control_law`) from the
package's Python source. Even from numba's on-disk cache a process pays
about 1.4 s before its first call: numba's import (0.5 s) and its compiler's
set-up while loading the cache (0.9 s). The kernel simulates the 190 s of
``simulate paper-position`` in 0.07 s, so that set-up was most of the command,
and of every pool worker's start.

So the same functions are also compiled ahead of time (``numba.pycc``:
the same source through the same LLVM, for this processor; equal to the JIT
bit for bit, ``tests/test_compiled.py``) into an extension module in the
user cache folder, which loads in a millisecond without importing numba. It
is built on the first call, in place of numba's first compile (10-30 s,
once per version of the compiled sources, numba, Python and processor);
concurrent first calls wait for one build. Where it cannot be built (no C
compiler or Python headers, a numba without ``pycc``) numba's JIT serves,
as before, and the reason is logged once (``-v``) and kept beside the
module's place (``build-failed.txt``: delete it to try again).

``SEANV_AOT=0`` turns it off (numba's JIT only), and so does
``NUMBA_DISABLE_JIT=1`` (numba's debugging mode runs the Python source).

Loading a module runs its code, so it is loaded only from a folder no one
else can write to: the cache folder and the module's folder must be this
user's, mode 0700 (made so, :func:`seanv_analysis.config.private_folder`;
another user's folder is refused with a warning and the JIT serves; a
folder that was open to others is emptied first), and only when the module's
SHA-256 matches the one recorded beside it at its build
(``<module>.sha256``). A module without a matching record (corrupt,
truncated, planted, or built by an older version) is built again before
anything loads it; one that loads without its functions is removed (the
next process builds it) and the JIT serves.
"""
from __future__ import annotations

import contextlib
import hashlib
import hmac
import importlib.util
import logging
import os
import platform
import sys
import sysconfig
import tempfile
import threading
import time
from pathlib import Path
from typing import Any, Callable

from ._pp import PP
from ._sources import cache_base, hash_compiled_sources, private_cache_folder

__all__ = ["simulate_kernel", "servo_track", "controller_replay", "aot_module_path", "aot_status",
           "build_aot", "stop_all", "SimulationStopped"]

log = logging.getLogger(__name__)

#: the extension module's name (its ``PyInit_`` symbol)
_MODULE = "_seanv_sim_aot"
_F8 = "f8[::1]"
#: the exported functions of :mod:`.kernel` and their numba signatures (all
#: arrays C-contiguous float64; :func:`_contiguous` makes them so)
SIGNATURES = {
    "simulate_kernel": ("Tuple((f8[:,::1], f8[:,::1], f8))("
                        + ", ".join([_F8] * 8 + ["i8"] + [_F8] * 13
                                    + ["f8[:,::1]", "i8", "f8", "f8", "f8", "f8"]) + ")"),
    "servo_track": f"{_F8}({_F8}, {_F8}, f8, f8, i8, f8, {_F8}, f8)",
    "controller_replay": f"{_F8}(i8, " + ", ".join([_F8] * 13) + ")",
}

_loaded: dict[str, Callable] = {}
_status: str | None = None
_module = None
_LOCK = threading.Lock()


def simulate_kernel() -> Callable:
    """:func:`.kernel.simulate_kernel`: ahead-of-time compiled, else numba's JIT."""
    return _function("simulate_kernel")


def servo_track() -> Callable:
    """:func:`.kernel.servo_track`: ahead-of-time compiled, else numba's JIT."""
    return _function("servo_track")


def controller_replay() -> Callable:
    """:func:`.control_law.controller_replay` (a controller over logged
    ticks; identify's controller part): ahead-of-time compiled, else
    numba's JIT (whose first call in a process took 1.4-1.7 s for a 2 ms
    replay)."""
    return _function("controller_replay")


def aot_status() -> str | None:
    """Why this process runs numba's JIT (None: the ahead-of-time module, or
    nothing called yet)."""
    return _status


def aot_module_path() -> Path:
    """Where the ahead-of-time module of these sources, numba, Python and
    processor lies (built or not)."""
    return cache_base() / f"aot-{_key()[:16]}" / (_MODULE + sysconfig.get_config_var("EXT_SUFFIX"))


def build_aot(path: Path | None = None) -> Path:
    """Compile the exported functions ahead of time into ``path`` (default:
    :func:`aot_module_path`), atomically; returns the path. Raises
    ``RuntimeError`` with the compiler's last words when it cannot."""
    path = Path(path) if path is not None else aot_module_path()
    path.parent.mkdir(parents=True, exist_ok=True)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pycc is pending deprecation (numba 0.57+)
        try:
            from numba.pycc import CC
        except ImportError as exc:  # a numba without pycc
            raise RuntimeError(f"numba.pycc is not available ({exc})") from None
    from . import kernel

    with tempfile.TemporaryDirectory(dir=path.parent, prefix=".build-") as tmp:
        with _output_to(Path(tmp) / "compiler.log") as said, _releasing_the_gil():
            try:
                cc = CC(_MODULE)  # (probes the C compiler)
                cc.output_dir = tmp
                cc.target_cpu = "host"  # as numba's JIT: the same machine code, bit for bit
                for name, sig in SIGNATURES.items():
                    cc.export(name, sig)(getattr(kernel, name).py_func)
                cc.compile()
            except Exception as exc:  # distutils' CompileError, LinkError, OSError ...
                last = said().strip().splitlines()[-3:]
                raise RuntimeError("; ".join([f"{type(exc).__name__}: {exc}"] + last)) from None
        built = Path(tmp) / (_MODULE + sysconfig.get_config_var("EXT_SUFFIX"))
        if not built.is_file():
            built = next(Path(tmp).glob(_MODULE + "*"))
        record = Path(tmp) / "record"
        record.write_text(_sha256(built) + "\n")
        os.replace(record, _record_path(path))   # the record first: a reader sees a mismatch,
        os.replace(built, path)                  # never an unrecorded module
    return path


def _record_path(path: Path) -> Path:
    """Where the SHA-256 of the module ``path`` is recorded at its build."""
    return path.with_name(path.name + ".sha256")


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def _verified(path: Path) -> bool:
    """The module at ``path`` is a regular file of this user's that no one
    else can write, and its SHA-256 is the one recorded at its build."""
    record = _record_path(path)
    if not (_own_file(path) and _own_file(record)):
        return False
    try:
        if record.stat().st_size > 200:
            return False
        want = record.read_text(encoding="ascii", errors="replace").strip()
        return hmac.compare_digest(want, _sha256(path))
    except OSError:
        return False


def _own_file(path: Path) -> bool:
    """``path`` is a regular file (not a link) of this user's that no one else can write."""
    import stat

    try:
        st = os.lstat(path)
    except OSError:
        return False
    uid = os.getuid() if hasattr(os, "getuid") else None
    return (stat.S_ISREG(st.st_mode) and not st.st_mode & 0o022
            and (uid is None or st.st_uid == uid))


def _function(name: str) -> Callable:
    fn = _loaded.get(name)
    if fn is None:
        with _LOCK:  # threads' first calls (scenarios simulate runs side by side): one build
            fn = _loaded.get(name)
            if fn is None:
                module = _aot_module()
                if module is not None:
                    fn = _contiguous(getattr(module, name))
                else:
                    from . import kernel  # numba: compiles or loads numba's cache

                    fn = getattr(kernel, name)
                _loaded[name] = fn = _stoppable(fn, name) if name in _CALLS else fn
    return fn


# Stopping a simulation ------------------------------------------------------
# A compiled kernel runs without returning to Python, so Python's signal
# handlers wait for it to finish. Each kernel reads the stop slot of its
# packed parameters (``PP.STOP``) every few hundred samples and returns when
# it is set: a long call from the main thread runs on a helper thread while
# the main thread waits, so Ctrl-C and SIGTERM reach it at once and set the
# slot; :func:`stop_all` (the CLI's signal handlers) sets every running
# kernel's slot and makes later calls refuse to start.

#: the packed parameters of the kernels running now, by call
_RUNNING: dict[object, Any] = {}
_STOPPED = False
#: plant steps above which a main-thread call runs on a helper thread (~0.3 s)
_HELPER_STEPS = 1_000_000
#: where each entry point takes its packed parameters, and its plant steps
#: (the controller's replay, milliseconds long, has no stop slot)
_CALLS = {"simulate_kernel": (0, lambda args: float(args[-5]) * float(args[0][PP.SUBSTEPS])),
          "servo_track": (6, lambda args: float(args[4]))}


class SimulationStopped(KeyboardInterrupt):
    """A simulation stopped before its end by Ctrl-C or SIGTERM (a
    ``KeyboardInterrupt``: no ``except Exception`` takes it for a failure)."""


def stop_all() -> None:
    """Stop every simulation of this process now and refuse new ones: each
    running kernel returns at its next check (within milliseconds) and its
    call raises :class:`SimulationStopped`. For a process that is ending (the
    CLI's Ctrl-C and SIGTERM handlers); safe in a signal handler."""
    global _STOPPED
    _STOPPED = True
    for pp in list(_RUNNING.values()):
        pp[PP.STOP] = 1.0


def _stoppable(fn: Callable, name: str) -> Callable:
    """``fn`` (an entry point) that can be stopped (see above)."""
    import numpy as np

    at, steps = _CALLS[name]

    def call(*args):
        if _STOPPED:
            raise SimulationStopped(f"{name}: this process is stopping")
        args = list(args)
        pp = args[at] = np.ascontiguousarray(args[at], dtype=np.float64)
        token = object()
        _RUNNING[token] = pp
        try:
            if steps(args) > _HELPER_STEPS and threading.current_thread() is threading.main_thread():
                out = _on_helper_thread(fn, args, pp)
            else:
                out = fn(*args)
        finally:
            _RUNNING.pop(token, None)
        if pp[PP.STOP] != 0.0:
            raise SimulationStopped(f"{name}: stopped before its end")
        return out

    call.__name__ = call.__qualname__ = name
    call.__doc__ = fn.__doc__
    call.__wrapped__ = fn
    return call


def _on_helper_thread(fn: Callable, args: list, pp) -> Any:
    """``fn(*args)`` on a helper thread while this (the main) thread waits,
    so a signal's handler runs now; on any exception here (Ctrl-C, SIGTERM)
    the kernel is stopped and the exception raised."""
    box: dict[str, Any] = {}
    done = threading.Event()

    def work():
        try:
            box["out"] = fn(*args)
        except BaseException as exc:  # handed to the waiting thread
            box["exc"] = exc
        finally:
            done.set()

    threading.Thread(target=work, name="seanv-kernel", daemon=True).start()
    try:
        while not done.wait(0.2):
            pass
    except BaseException:
        pp[PP.STOP] = 1.0
        raise
    if "exc" in box:
        raise box["exc"]
    return box["out"]


def _aot_module():
    """The ahead-of-time module, built first if need be (loaded once per
    process); None: use the JIT."""
    global _status, _module
    if _module is not None:
        return _module
    if _status is not None:
        return None
    if os.environ.get("SEANV_AOT", "1").strip() in ("0", "no", "off", "false") or \
            os.environ.get("NUMBA_DISABLE_JIT", "0").strip() not in ("", "0"):
        _status = "turned off (SEANV_AOT=0 or NUMBA_DISABLE_JIT=1)"
        return None
    from ..errors import ConfigError

    try:
        path = aot_module_path()
        try:
            private_cache_folder(path.parent)
        except ConfigError as exc:   # another user's folder: nothing loaded from it, said once
            _status = f"the simulator runs on numba's JIT: {exc}"
            log.warning("%s", _status)
            return None
        if not _verified(path):
            _build_once(path)
        module = _load(path)
        missing = [name for name in SIGNATURES if not callable(getattr(module, name, None))]
        if missing:
            for p in (path, _record_path(path)):
                p.unlink(missing_ok=True)   # the next process builds it again
            raise RuntimeError(f"{path}: lacks {', '.join(missing)} (removed: built again "
                               "by the next command)")
        _module = module
        return _module
    except Exception as exc:  # never fatal: the JIT computes the same numbers
        _status = f"the simulator runs on numba's JIT: {exc}"
        log.debug(_status)
        return None


def _build_once(path: Path) -> None:
    failed = path.parent / "build-failed.txt"
    path.parent.mkdir(parents=True, exist_ok=True)
    with _lock(path.parent / ".build.lock"):
        if _verified(path):  # another process built it while we waited
            return
        if os.path.lexists(path):
            log.info("%s: its SHA-256 is not the one recorded at its build (corrupt, or not "
                     "built here): building it again", path)
        if failed.is_file():
            raise RuntimeError(f"an earlier build failed ({failed}: "
                               f"{failed.read_text(errors='replace').strip()[:300]}; "
                               "delete that file to try again)")
        log.info("compiling the simulator ahead of time, once for this version "
                 "(10-30 s) ...")
        t0 = time.perf_counter()
        try:
            build_aot(path)
        except RuntimeError as exc:
            failed.write_text(f"{exc}\n")
            raise
        log.info("compiled the simulator in %.0f s: %s", time.perf_counter() - t0, path)


def _load(path: Path):
    spec = importlib.util.spec_from_file_location(_MODULE, path)
    if spec is None or spec.loader is None:
        raise RuntimeError(f"{path}: not an extension module")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _contiguous(fn: Callable) -> Callable:
    """The AOT function takes C-contiguous float64 arrays only (one signature);
    numba's JIT would compile another specialisation. Arrays that already are
    pass through as they are (the kernel writes into some of them)."""
    import numpy as np

    def call(*args):
        return fn(*(np.ascontiguousarray(a, dtype=np.float64) if isinstance(a, np.ndarray)
                    else a for a in args))

    call.__name__ = call.__qualname__ = fn.__name__
    call.__doc__ = f"{fn.__name__}, compiled ahead of time (:mod:`{__name__}`)"
    return call


def _key() -> str:
    """Hash of what the machine code depends on: the compiled sources, the
    exported signatures, numba and llvmlite, the Python ABI and the processor."""
    h = hashlib.sha256()
    for dist in ("numba", "llvmlite"):
        h.update(_version_stamp(dist))
    h.update(repr(sorted(SIGNATURES.items())).encode())
    h.update(f"{sys.implementation.cache_tag};{sysconfig.get_config_var('EXT_SUFFIX')};".encode())
    h.update(_processor().encode())
    hash_compiled_sources(h)
    return h.hexdigest()


def _version_stamp(package: str) -> bytes:
    """The installed ``package``'s version file (its version, found without
    importing the package or importlib.metadata: ~40 ms of a short command)."""
    spec = importlib.util.find_spec(package)
    if spec is not None and spec.origin:
        stamp = Path(spec.origin).with_name("_version.py")
        if stamp.is_file():
            return package.encode() + stamp.read_bytes()
    from importlib.metadata import PackageNotFoundError, version

    try:
        return f"{package}={version(package)};".encode()
    except PackageNotFoundError:
        return f"{package}=?;".encode()


def _processor() -> str:
    """The processor's model and features (the module is compiled for them)."""
    try:
        block = Path("/proc/cpuinfo").read_text(errors="replace").split("\n\n", 1)[0]
    except OSError:
        block = ""
    keep = [line for line in block.splitlines()
            if line.split(":", 1)[0].strip() in ("vendor_id", "model name", "flags",
                                                  "CPU implementer", "CPU part", "Features")]
    return "\n".join(keep) or f"{platform.machine()};{platform.processor()};{platform.platform()}"


@contextlib.contextmanager
def _releasing_the_gil():
    """pycc's exported wrappers keep the GIL; the JIT's (``nogil=True``) let it
    go, so a reader or writer thread runs beside the kernel. The wrappers are
    made from the compile flags, which pycc builds with their defaults: make
    ``release_gil`` one of them for this build."""
    from numba.pycc import compiler as pycc_compiler

    base = pycc_compiler.Flags

    class Flags(base):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            self.release_gil = True

    pycc_compiler.Flags = Flags
    try:
        yield
    finally:
        pycc_compiler.Flags = base


@contextlib.contextmanager
def _lock(path: Path):
    """An exclusive lock on ``path`` (POSIX ``flock``; elsewhere none)."""
    try:
        import fcntl
    except ImportError:  # Windows: concurrent first builds replace each other atomically
        yield
        return
    with open(path, "a+b") as fh:
        fcntl.flock(fh.fileno(), fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(fh.fileno(), fcntl.LOCK_UN)


@contextlib.contextmanager
def _output_to(path: Path):
    """Send this process's stdout and stderr (file descriptors 1 and 2: the C
    compiler's too) to ``path``; yields a function reading what was said."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    with open(path, "w+b") as out:
        try:
            os.dup2(out.fileno(), 1)
            os.dup2(out.fileno(), 2)
            yield lambda: path.read_text(errors="replace")
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)


def main() -> int:
    """Build the ahead-of-time module now, as the first simulation would
    (``make venv`` does, so the first command does not wait); prints where
    it is, or why numba's JIT serves. Returns 0 either way: the JIT
    computes the same numbers."""
    handler = logging.StreamHandler(sys.stderr)
    level = log.level
    log.addHandler(handler)
    log.setLevel(logging.INFO)
    try:
        simulate_kernel()
        servo_track()
    finally:
        log.removeHandler(handler)
        log.setLevel(level)
    status = aot_status()
    print(f"simulator compiled ahead of time: {aot_module_path()}" if status is None
          else f"simulator: {status}")
    return 0
