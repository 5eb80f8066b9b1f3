"""Native code built against the installed Pinocchio's own C++ (its headers and ``libpinocchio``):
the brake rollout's loop (``brake_rollout.cpp``, :mod:`qpctl.safety.rollout`) and the tick's rigid-body
pass (``rigid_pass.cpp``, called by the compiled tick: :mod:`qpctl.kernels.pin_native`). Every
rigid-body quantity in them is ``pinocchio::rnea`` / ``aba`` / ``crba`` / ``nonLinearEffects`` — the
code the Python bindings call — so this is Pinocchio without the interpreter between its calls, not a
second dynamics.

The library is compiled on first use (``python -m qpctl.native`` does it ahead; ``make env`` calls
that) with the system's C++ compiler into :func:`build_dir` (``qpctl/native/_build/`` in a
checkout), one file per set of sources, Pinocchio version and install prefix, and loaded with :mod:`ctypes`. Where it cannot
be built (no compiler, no Eigen headers, another Pinocchio layout) :func:`library` returns None
with the reason in :func:`why_unavailable`, and the rollout runs its Python path (the same states).
Eigen's headers come from the ``cmeel-eigen`` wheel, a dependency.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import pinocchio as pin

SOURCES = tuple(Path(__file__).with_name(f) for f in ("brake_rollout.cpp", "rigid_pass.cpp"))
#: Pinocchio's compile definitions for a consumer of ``pinocchio::pinocchio_default`` (from the
#: wheel's pinocchioTargets.cmake): the extern templates of its instantiated algorithms, and the
#: Boost.MPL limits its headers were built with.
DEFINES = ("PINOCCHIO_ENABLE_TEMPLATE_INSTANTIATION", "BOOST_MPL_LIMIT_LIST_SIZE=30",
           "BOOST_MPL_LIMIT_VECTOR_SIZE=30", "BOOST_MPL_CFG_NO_PREPROCESSED_HEADERS",
           "BOOST_FUSION_INVOKE_MAX_ARITY=12")
#: No -march: Eigen's alignment must be the library's (generic x86-64); no contraction into FMAs, so
#: the arithmetic is the Python path's operation for operation.
FLAGS = ("-O2", "-std=c++17", "-fPIC", "-shared", "-ffp-contract=off", "-fno-fast-math")

_lib: ctypes.CDLL | None = None
_why: str | None = None


class NativeBuildError(RuntimeError):
    """The native library could not be built (the message says why)."""


def prefix() -> Path:
    """The install prefix holding Pinocchio's headers and ``libpinocchio_default`` (the cmeel
    prefix of the ``pin`` wheel)."""
    for p in Path(pin.__file__).resolve().parents:
        if (p / "include" / "pinocchio").is_dir():
            return p
    raise NativeBuildError(f"no include/pinocchio above {pin.__file__}")


def eigen_include(pre: Path) -> Path:
    """Eigen's headers: beside Pinocchio's (the ``cmeel-eigen`` wheel) or the system's."""
    for d in (pre / "include" / "eigen3", Path(sys.prefix) / "include" / "eigen3", Path("/usr/include/eigen3")):
        if (d / "Eigen" / "Core").is_file():
            return d
    raise NativeBuildError("no Eigen headers (the cmeel-eigen wheel, a dependency, provides them)")


def library_path() -> Path:
    """Where the built library lives: its name carries the sources', Pinocchio's and the prefix's hash."""
    pre = prefix()
    key = hashlib.sha256(b"".join(s.read_bytes() for s in SOURCES) + pin.__version__.encode() + str(pre).encode()
                         + " ".join(FLAGS + DEFINES).encode()).hexdigest()[:16]
    return build_dir() / f"qpctl_native-{key}.so"


def build_dir() -> Path:
    """``$QPCTL_NATIVE_DIR``, else ``qpctl/native/_build`` beside this file where the package's
    directory is writable (a checkout), else the user's cache (``$XDG_CACHE_HOME/qpctl/native``)."""
    if "QPCTL_NATIVE_DIR" in os.environ:
        return Path(os.environ["QPCTL_NATIVE_DIR"])
    here = Path(__file__).parent
    if os.access(here, os.W_OK):
        return here / "_build"
    return Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")) / "qpctl" / "native"


def build(force: bool = False) -> Path:
    """Compile the library if it is not there (atomically: concurrent builders each write their
    own file and the last rename wins); returns its path. Raises :class:`NativeBuildError`."""
    out = library_path()
    if out.is_file() and not force:
        return out
    cxx = os.environ.get("CXX") or shutil.which("g++") or shutil.which("c++")
    if cxx is None:
        raise NativeBuildError("no C++ compiler (g++ or $CXX)")
    pre = prefix()
    lib, eigen = pre / "lib", eigen_include(pre)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(suffix=".so", dir=out.parent)
    os.close(fd)
    objs = [f"{tmp}.{i}.o" for i in range(len(SOURCES))]
    common = [cxx, *FLAGS, *(f"-D{d}" for d in DEFINES), f"-I{pre / 'include'}", f"-I{eigen}"]
    try:  # the sources compiled side by side (each parses Pinocchio's headers: ~30 s), then linked
        procs = [subprocess.Popen([*common, "-c", str(src), "-o", obj], stdout=subprocess.DEVNULL,
                                  stderr=subprocess.PIPE, text=True) for src, obj in zip(SOURCES, objs)]
        errors = [proc.communicate()[1] for proc in procs]  # (every one finished before any is judged)
        for proc, err in zip(procs, errors):
            _check(cxx, proc.returncode, err)
        r = subprocess.run([*common, *objs, "-o", tmp, f"-L{lib}", "-lpinocchio_default", "-lboost_serialization",
                            f"-Wl,-rpath,{lib}"], check=False, capture_output=True, text=True)
        _check(cxx, r.returncode, r.stderr)
        os.replace(tmp, out)
    finally:
        for f in (tmp, *objs):
            if os.path.exists(f):
                os.unlink(f)
    return out


def _check(cxx: str, returncode: int, stderr: str) -> None:
    """Raise :class:`NativeBuildError` with the compiler's first error line when it failed."""
    if returncode != 0:
        lines = stderr.strip().splitlines()
        first = next((ln for ln in lines if "error" in ln), lines[-1] if lines else f"exit {returncode}")
        raise NativeBuildError(f"{cxx} failed: {first}")


def _declare(lib: ctypes.CDLL) -> ctypes.CDLL:
    p, i, L = ctypes.c_void_p, ctypes.c_int, ctypes.c_long
    sig = {"qpb_new": (p, [ctypes.c_char_p, L]), "qpb_free": (None, [p]), "qpb_nv": (i, [p]),
           "qpb_io_size": (i, []), "qpb_error": (ctypes.c_char_p, []),
           "qpb_aba": (None, [p, p, p, p, p]), "qpb_rnea": (None, [p, p, p, p, p]),
           "qpb_advance": (i, [p] * 11),
           "qpb_step": (ctypes.c_double, [p, p, p, p, ctypes.c_double, p]),
           "qpb_walk_size": (i, []), "qpb_walk_plan": (i, [p] * 11), "qpb_walk_clear": (i, [p] * 11),
           "qpr_new": (p, [ctypes.c_char_p, L]), "qpr_free": (None, [p]), "qpr_error": (ctypes.c_char_p, []),
           "qpr_addresses": (None, [p, p]), "qpr_pass": (i, [p] * 4)}
    for name, (res, args) in sig.items():
        f = getattr(lib, name)
        f.restype, f.argtypes = res, args
    return lib


def library() -> ctypes.CDLL | None:
    """The loaded library (built on first use), or None where it cannot be built
    (:func:`why_unavailable`)."""
    global _lib, _why
    if _lib is not None or _why is not None:
        return _lib
    if os.environ.get("QPCTL_NATIVE", "1") == "0":
        _why = "QPCTL_NATIVE=0"
        return None
    try:
        _lib = _declare(ctypes.CDLL(str(build())))
    except (NativeBuildError, OSError) as e:
        _why = str(e)
    return _lib


def why_unavailable() -> str | None:
    """Why :func:`library` returned None (None when it did not)."""
    library()
    return _why
