"""On-disk cache of compiled circuits and their schedules (under the user cache dir).

Building and scheduling a large localization circuit takes seconds; both servers load it
from here instead. The content hash stored with it is what peers compare before a run.
A name is the circuit's name (which carries its family's version, see registry.py) and
the scheduler's version, so a changed circuit or scheduler never loads a stale entry,
while an edit that changes neither (a comment, a refactoring) keeps the cache.

An entry is a folder of ``.npy`` files, one per array, and ``meta.json`` (interface,
content hash, a CRC-32 per file). Loading checks the CRCs through mapped windows and then
memory-maps the arrays read-only: a server that only runs the schedule never touches
the netlist (a gigabyte at n = 256), and nothing is copied or hashed again (loading the
n = 256 circuit took 6.6 s of reads, copies and page faults from an npz).

The cache is bounded (``configure``; default 20 GiB): after an entry is written, the
least recently used others are removed until the entries fit. A load marks an entry used
(its folder's mtime). An entry another process has mapped survives its removal until
unmapped (POSIX unlink semantics); a removed entry is rebuilt when next asked for.
Processes that find an entry or a plan missing build it one at a time (a lock file beside
the entry, and one per plan in it): the others wait for it and load it.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import mmap
import os
import re
import shutil
import tempfile
import zlib
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import BinaryIO

import numpy as np

from . import plan_store
from .ir import Circuit, Group, Interface
from .schedule import SCHEDULE_VERSION, Schedule, schedule_circuit

CACHE_ENV = "SNAIL_CACHE_DIR"
DEFAULT_MAX_BYTES = 20 << 30
_NAME_OK = re.compile(r"^[A-Za-z0-9_.-]+$")
_ENTRY_GLOB = "*.arrays"
_settings: dict[str, Path | int | None] = {"directory": None, "max_bytes": DEFAULT_MAX_BYTES}


def configure(directory: Path | None = None, max_bytes: int | None = None) -> None:
    """Set this process's cache folder (default: see ``cache_dir``) and its size bound."""
    _settings["directory"] = directory
    _settings["max_bytes"] = DEFAULT_MAX_BYTES if max_bytes is None else max_bytes


def cache_dir() -> Path:
    """The configured folder, else $SNAIL_CACHE_DIR, else $XDG_CACHE_HOME/snail, else
    ~/.cache/snail."""
    if _settings["directory"] is not None:
        return Path(_settings["directory"])
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "snail"


# Warnings go to the "snail" logger's JSON lines (fields under the formatter's key).
_log = logging.getLogger("snail.cache")


def _warn(event: str, **fields: object) -> None:
    _log.warning(event, extra={"snail_fields": fields})


_NETLIST = ("kind", "a", "b", "outputs", "and_depth", "xor_depth")
_WINDOW = 1 << 24  # bytes of a file mapped at a time while its CRC is checked


def save(path: Path, circuit: Circuit, schedule: Schedule) -> None:
    """Write the circuit and schedule as the entry folder ``path`` (atomically: a reader
    sees the whole entry or none), and the interface sidecar next to it."""
    arrays = {k: getattr(circuit, k) for k in _NETLIST} | schedule.to_arrays()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    try:
        for name, arr in arrays.items():
            np.save(tmp / f"{name}.npy", np.ascontiguousarray(arr))
        meta = {"n_inputs": circuit.n_inputs, "hash": circuit.content_hash(),
                "inputs": [g.to_json() for g in circuit.inputs],
                "outputs": [g.to_json() for g in circuit.output_groups],
                "crc32": {name: _crc(tmp / f"{name}.npy") for name in arrays}}
        (tmp / "meta.json").write_text(json.dumps(meta))
        try:
            os.rename(tmp, path)
        except OSError:  # another process stored the same entry first: keep theirs
            if not path.is_dir():
                raise
            shutil.rmtree(tmp, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    save_interface(_interface_path(path), circuit.interface())


def _crc(file: Path) -> int:
    """CRC-32 of ``file``, read through one mapped window at a time: plain reads copied
    every byte into a fresh chunk (the kernel's copies and the chunks' page faults were
    0.35 s of system time per daemon loading the n = 256 circuit), a whole-file mapping
    would count the file in the process's peak RSS."""
    crc = 0
    with open(file, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        for offset in range(0, size, _WINDOW):
            with mmap.mmap(f.fileno(), min(_WINDOW, size - offset), prot=mmap.PROT_READ,
                           offset=offset) as window:
                crc = zlib.crc32(window, crc)
    return crc


def save_interface(path: Path, iface: Interface) -> None:
    data = json.dumps(iface.to_json()).encode()
    _write_atomic(path, lambda f: f.write(data))


def _write_atomic(path: Path, write: Callable[[BinaryIO], object]) -> None:
    """Temp file + rename, so a concurrent reader never sees half a file."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def load(path: Path) -> tuple[Circuit, Schedule]:
    """The entry folder ``path``, its arrays memory-mapped read-only; ValueError if a
    file does not match the CRC written with it."""
    meta = json.loads((path / "meta.json").read_bytes())
    for name, want in meta["crc32"].items():
        if _crc(path / f"{name}.npy") != want:
            raise ValueError(f"cached circuit {path} is corrupt ({name}.npy fails its CRC)")
    return _mapped(path, meta)


def _mapped(path: Path, meta: dict) -> tuple[Circuit, Schedule]:
    """The entry folder ``path`` with its ``meta``, arrays memory-mapped unchecked."""
    d = {name: np.load(path / f"{name}.npy", mmap_mode="r") for name in meta["crc32"]}
    circuit = Circuit(meta["n_inputs"], *(d[k] for k in _NETLIST[:4]),
                      [Group.from_json(g) for g in meta["inputs"]],
                      [Group.from_json(g) for g in meta["outputs"]],
                      d["and_depth"], d["xor_depth"], _hash=meta["hash"])
    schedule = Schedule.from_arrays(d)
    schedule.plan_source = StoredPlans(path)
    return circuit, schedule


@contextlib.contextmanager
def _exclusive(lock: Path) -> Iterator[None]:
    """Hold an advisory lock on the file ``lock`` (made if need be), so that processes or
    threads about to build the same entry or plan wait for the first and load its result
    (two daemons started on a cold cache each built the n = 256 circuit, then its plan:
    twice the CPU, 1.5 GB peak RSS each). The holder removes the file (names come from
    requests: a refused build leaves nothing behind); a process that opened it before may
    then race one that makes a new one, and both may build: saving tolerates that. Unlocked
    if the file cannot be made: the cache is an optimization. The kernel drops the lock
    of a process that dies."""
    fd = None
    with contextlib.suppress(OSError):
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        if fd is not None:
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        if fd is not None:
            with contextlib.suppress(OSError):
                os.unlink(lock)
            os.close(fd)


class StoredPlans:
    """Engine plans kept in a cache entry (plan_store.py says why): loaded if present and
    intact, else built and stored for the next load. A plan that cannot be stored is
    still returned: the cache is an optimization."""

    def __init__(self, entry: Path) -> None:
        self.entry = entry

    def get(self, kind: str, build: Callable[[], plan_store.Plan]) -> plan_store.Plan:
        name = f"plan{plan_store.FORMAT}-{kind}"
        plan = self._stored(name)
        if plan is not None:
            return plan
        with _exclusive(self.entry / f"{name}.lock"):
            plan = self._stored(name)  # stored by another process while this one waited
            if plan is not None:
                return plan
            plan = build()
            with contextlib.suppress(OSError):
                self._save(name, plan_store.encode(plan))
        return plan

    def _stored(self, name: str) -> plan_store.Plan | None:
        """The stored plan ``name``, or None if it is absent, partly written or corrupt."""
        try:
            return plan_store.decode(self._load(name))
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def _load(self, name: str) -> plan_store.StoredPlan:
        crcs = json.loads((self.entry / f"{name}.json").read_bytes())
        parts = []
        for field in plan_store.StoredPlan._fields:
            file = self.entry / f"{name}-{field}.npy"
            if _crc(file) != crcs[field]:
                raise ValueError(f"{file} fails its CRC")
            parts.append(np.load(file, mmap_mode="r"))
        return plan_store.StoredPlan(*parts)

    def _save(self, name: str, stored: plan_store.StoredPlan) -> None:
        crcs = {}
        for field, arr in zip(stored._fields, stored):
            file = self.entry / f"{name}-{field}.npy"
            _write_atomic(file, lambda f, arr=arr: np.save(f, arr))
            crcs[field] = _crc(file)
        _write_atomic(self.entry / f"{name}.json", lambda f: f.write(json.dumps(crcs).encode()))


def cached(name: str, build: Callable[[], Circuit],
           directory: Path | None = None) -> tuple[Circuit, Schedule]:
    """The compiled circuit called ``name`` (which must encode every build parameter and
    the builder's version), built and scheduled on first use, loaded from disk afterwards."""
    path = _path(name, directory)
    loaded = _load_entry(path)  # unlocked: daemons loading one entry check it side by side
    if loaded is not None:
        return loaded
    with contextlib.suppress(OSError):  # for the lock; save() says why it cannot store
        path.parent.mkdir(parents=True, exist_ok=True)
    with _exclusive(path.with_suffix(".lock")):
        loaded = _load_entry(path)  # built by another process while this one waited
        if loaded is not None:
            return loaded
        circuit = build()
        schedule = schedule_circuit(circuit)
        try:
            save(path, circuit, schedule)
            # serve the entry just written (checksummed as it was), mapped like any load:
            # the built arrays are freed instead of held while the circuit is in use, and
            # the plans are stored with it (a built schedule's plans were not, so the next
            # daemon to load the entry rebuilt them: 3-4 s, ~0.9 GB peak RSS at n = 256)
            circuit, schedule = _mapped(path, json.loads((path / "meta.json").read_bytes()))
        except OSError as exc:  # a full or read-only disk: serve from memory, say so
            _warn("cache_store_failed", entry=path.name, reason=str(exc))
            return circuit, schedule
        evict(path.parent, int(_settings["max_bytes"]), keep=path)
    return circuit, schedule


def _load_entry(path: Path) -> tuple[Circuit, Schedule] | None:
    """The entry ``path``, marked used; None if there is none or it is unusable (then
    it is removed, to be rebuilt)."""
    if not path.exists():
        return None
    try:
        loaded = load(path)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        _warn("cache_entry_rebuilt", entry=path.name, reason=str(exc))
        shutil.rmtree(path, ignore_errors=True)  # corrupt or stale format: rebuild
        return None
    with contextlib.suppress(OSError):
        os.utime(path)  # used now: the last to be evicted
    return loaded


def entry_bytes(entry: Path) -> int:
    """Bytes on disk of a cache entry folder."""
    with os.scandir(entry) as files:
        return sum(f.stat().st_size for f in files if f.is_file())


def evict(directory: Path, max_bytes: int, keep: Path | None = None) -> list[Path]:
    """Remove the least recently used entries of ``directory`` (never ``keep``) until
    the rest take at most ``max_bytes``; returns the entries removed."""
    entries = []
    for entry in directory.glob(_ENTRY_GLOB):
        with contextlib.suppress(OSError):  # another process may be removing it
            entries.append((entry.stat().st_mtime, entry_bytes(entry), entry))
    total = sum(size for _, size, _ in entries)
    removed = []
    for _, size, entry in sorted(entries, key=lambda e: e[0]):
        if total <= max_bytes:
            break
        if entry == keep:
            continue
        shutil.rmtree(entry, ignore_errors=True)
        total -= size
        removed.append(entry)
    return removed


def cached_interface(name: str, build: Callable[[], Circuit],
                     directory: Path | None = None) -> Interface:
    """The interface of the circuit called ``name``: read from its sidecar (written with the
    compiled circuit, or by an earlier call), else built without scheduling. Clients use
    this instead of ``cached``: they never load the netlist or the schedule."""
    path = _interface_path(_path(name, directory))
    if path.exists():
        try:
            return Interface.from_json(json.loads(path.read_bytes()))
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            path.unlink(missing_ok=True)  # corrupt: rebuild
    iface = build().interface()
    try:
        save_interface(path, iface)
    except OSError as exc:
        _warn("cache_store_failed", entry=path.name, reason=str(exc))
    return iface


def _path(name: str, directory: Path | None) -> Path:
    if not _NAME_OK.match(name):
        raise ValueError(f"circuit cache name {name!r} must match {_NAME_OK.pattern}")
    return (directory or cache_dir()) / f"{name}.s{SCHEDULE_VERSION}.arrays"


def _interface_path(entry: Path) -> Path:
    return entry.with_suffix(".interface.json")
