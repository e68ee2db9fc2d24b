"""Compile kernel.c on first use and load it, refusing any library this process did not
verify.

The library is built with the system C compiler (``$CC``, else ``cc``) into a folder of
the circuit cache (or ``$SNAIL_KERNEL_DIR``: an image can build it once, tests share one)
that only this user may enter (0700, owned by us: checked before every use), keyed by the
source's hash and the compiler's identity. Beside it a record names
the source hash, the compiler and the library's own SHA-256. A library is loaded only when
the record matches this source and compiler and the library's bytes match the record; the
bytes hashed are the bytes loaded (copied into an anonymous memory file first), so a
library planted or swapped in the cache is never loaded: it is rebuilt instead.

Where there is no compiler, a library some compiler built from this very source into the
folder (an image's build step) is used, under the same checks. No Python headers and no
package: ctypes and the compiler. Where neither serves, or the CPU lacks the AES
instructions, ``build_and_load`` raises ``NativeUnavailable`` with the reason, and the
caller runs the numpy engine and says so.
"""

from __future__ import annotations

import ctypes
import hashlib
import json
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

from snail_common.circuit.cache import cache_dir

SOURCE = Path(__file__).with_name("kernel.c")
CC_ENV = "CC"
FLAGS = ("-O3", "-shared", "-fPIC", "-pthread", "-fno-strict-aliasing",
         "-fvisibility=default")
FOLDER = "native-kernel"  # under the circuit cache
KERNEL_DIR_ENV = "SNAIL_KERNEL_DIR"  # or here
COMPILE_TIMEOUT_S = 120


class NativeUnavailable(RuntimeError):
    """The native kernel cannot run here (the message says why)."""


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def compiler_identity(cc: str) -> str:
    """The compiler's resolved path and its version line; NativeUnavailable if absent."""
    path = shutil.which(cc)
    if path is None:
        raise NativeUnavailable(f"no C compiler: {cc!r} not found (set ${CC_ENV})")
    try:
        out = subprocess.run([path, "--version"], capture_output=True, text=True,
                             timeout=30, check=True).stdout
    except (OSError, subprocess.SubprocessError) as exc:
        raise NativeUnavailable(f"C compiler {path} does not run: {exc}") from None
    first = out.splitlines()[0] if out else "?"
    return f"{os.path.realpath(path)} {first}"


def _private_folder(folder: Path) -> Path:
    """``folder``, created 0700; NativeUnavailable unless it is ours and private."""
    folder.mkdir(mode=0o700, parents=True, exist_ok=True)
    st = folder.lstat()
    if not folder.is_dir() or folder.is_symlink():
        raise NativeUnavailable(f"{folder} is not a folder")
    if st.st_uid != os.geteuid() or st.st_mode & 0o077:
        raise NativeUnavailable(f"{folder} must be owned by this user with mode 0700, it is "
                                f"uid {st.st_uid} mode {oct(st.st_mode & 0o777)}")
    return folder


def _own_file(path: Path) -> bool:
    """A regular file owned by us that nobody else may write."""
    try:
        st = path.lstat()
    except OSError:
        return False
    return (path.is_file() and not path.is_symlink() and st.st_uid == os.geteuid()
            and not st.st_mode & 0o022)


def _verified_bytes(folder: Path, key: str, source_hash: str, compiler: str) -> bytes | None:
    """The library's bytes if its record matches this source and compiler and the bytes
    match the record; None otherwise (missing, stale or planted)."""
    record_path = folder / f"{key}.json"
    if not _own_file(record_path):
        return None
    try:
        record = json.loads(record_path.read_text())
        library = folder / str(record["library"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if (record.get("source_sha256") != source_hash or record.get("compiler") != compiler
            or library.parent != folder or not _own_file(library)):
        return None
    data = library.read_bytes()
    return data if _sha256(data) == record.get("library_sha256") else None


def _built_elsewhere(folder: Path, source_hash: str) -> tuple[bytes, str] | None:
    """A verified library of this source by any compiler, and that compiler."""
    for record in sorted(folder.glob("*.json")):
        try:
            compiler = str(json.loads(record.read_text())["compiler"])
        except (OSError, ValueError, KeyError, TypeError):
            continue
        data = _verified_bytes(folder, record.stem, source_hash, compiler)
        if data is not None:
            return data, compiler
    return None


def _compile(folder: Path, key: str, source: bytes, source_hash: str, compiler: str,
             cc: str) -> bytes:
    """Compile into a fresh file, then publish its record atomically; the library's bytes."""
    fd, tmp = tempfile.mkstemp(prefix=f"{key}.", suffix=".so", dir=folder)
    os.close(fd)
    src_fd, src_tmp = tempfile.mkstemp(prefix=f"{key}.", suffix=".c", dir=folder)
    try:
        with os.fdopen(src_fd, "wb") as f:
            f.write(source)  # the bytes hashed are the bytes compiled
        proc = subprocess.run([cc, *FLAGS, "-o", tmp, src_tmp], capture_output=True,
                              text=True, timeout=COMPILE_TIMEOUT_S)
    except (OSError, subprocess.SubprocessError) as exc:
        os.unlink(tmp)
        raise NativeUnavailable(f"compiling {SOURCE.name} failed: {exc}") from None
    finally:
        os.unlink(src_tmp)
    if proc.returncode:
        os.unlink(tmp)
        raise NativeUnavailable(f"compiling {SOURCE.name} failed: {proc.stderr.strip()[:400]}")
    os.chmod(tmp, 0o700)
    data = Path(tmp).read_bytes()
    record = {"source_sha256": source_hash, "compiler": compiler,
              "library": Path(tmp).name, "library_sha256": _sha256(data)}
    fd, rec_tmp = tempfile.mkstemp(prefix=f"{key}.", suffix=".json.tmp", dir=folder)
    with os.fdopen(fd, "w") as f:
        json.dump(record, f)
    os.replace(rec_tmp, folder / f"{key}.json")
    return data


def _load_bytes(data: bytes, name: str) -> ctypes.CDLL:
    """Load exactly these bytes (an anonymous memory file, so nothing can swap them
    between the check and the load)."""
    fd = os.memfd_create(name, os.MFD_CLOEXEC)
    try:
        os.write(fd, data)
        return ctypes.CDLL(f"/proc/self/fd/{fd}")
    finally:
        os.close(fd)


def _bind(lib: ctypes.CDLL) -> ctypes.CDLL:
    p, i64, c_int = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int
    lib.snail_cpu_ok.restype = c_int
    lib.snail_cpu_ok.argtypes = []
    lib.snail_isa.restype = c_int
    lib.snail_isa.argtypes = [c_int]
    lib.snail_run.restype = c_int
    lib.snail_run.argtypes = [c_int, c_int, p, i64, i64, p, p, i64, p, p, i64, p, p, p, c_int]
    return lib


def kernel_dir() -> Path:
    """Where the library is built: $SNAIL_KERNEL_DIR, else the circuit cache's FOLDER."""
    return Path(os.environ.get(KERNEL_DIR_ENV) or cache_dir() / FOLDER)


def build_and_load(folder: Path | None = None) -> tuple[ctypes.CDLL, str]:
    """The kernel library (compiled into ``folder``, default ``kernel_dir()``, if needed)
    and a line saying what was loaded."""
    if platform.system() != "Linux" or platform.machine() not in ("x86_64", "AMD64"):
        raise NativeUnavailable(f"the native kernel needs Linux on x86-64, this is "
                                f"{platform.system()} {platform.machine()}")
    cc = os.environ.get(CC_ENV) or "cc"
    source = SOURCE.read_bytes()
    source_hash = _sha256(source)
    try:
        compiler = compiler_identity(cc)
    except NativeUnavailable:
        prebuilt = (_built_elsewhere(_private_folder(folder or kernel_dir()), source_hash)
                    if (folder or kernel_dir()).is_dir() else None)
        if prebuilt is None:
            raise
        data, compiler = prebuilt
        return _checked(_bind(_load_bytes(data, "snail-kernel"))), f"prebuilt ({compiler})"
    key = _sha256(f"{source_hash}\n{compiler}\n{' '.join(FLAGS)}".encode())[:24]
    folder = _private_folder(folder or kernel_dir())
    data = _verified_bytes(folder, key, source_hash, compiler)
    built = data is None
    if built:
        data = _compile(folder, key, source, source_hash, compiler, cc)
    lib = _checked(_bind(_load_bytes(data, f"snail-kernel-{key}")))
    how = "compiled" if built else "loaded"
    return lib, f"{how} {key} ({compiler.split(' ', 1)[1]})"


def _checked(lib: ctypes.CDLL) -> ctypes.CDLL:
    """``lib``, once it says the CPU has the instructions it uses."""
    if not lib.snail_cpu_ok():
        raise NativeUnavailable("the CPU lacks the AES-NI, SSSE3 or SSE4.1 instructions")
    return lib


_lock = threading.Lock()
_state: dict[str, object] = {}


def library() -> ctypes.CDLL:
    """The process's kernel library, built and loaded once; NativeUnavailable if not."""
    with _lock:
        if "lib" not in _state and "error" not in _state:
            try:
                _state["lib"], _state["how"] = build_and_load()
            except NativeUnavailable as exc:
                _state["error"] = exc
        if "error" in _state:
            raise _state["error"]  # type: ignore[misc]
        return _state["lib"]  # type: ignore[return-value]


def reset() -> None:
    """Forget the loaded library (tests that change the compiler or the cache)."""
    with _lock:
        _state.clear()
