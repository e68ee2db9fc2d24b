"""On-disk cache of compiled circuits and their schedules (npz under the user cache dir).

Building and scheduling a large localization circuit takes seconds; both servers load it
from here instead. The content hash stored with it is what peers compare before a run.
A file name is the circuit's name (which carries its family's version, see registry.py)
and the scheduler's version, so a changed circuit or scheduler never loads a stale file,
while an edit that changes neither (a comment, a refactoring) keeps the cache.
"""

from __future__ import annotations

import json
import os
import re
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO

import numpy as np

from .ir import Circuit, Group, Interface
from .schedule import SCHEDULE_VERSION, Schedule, schedule_circuit

CACHE_ENV = "SNAIL_CACHE_DIR"
_NAME_OK = re.compile(r"^[A-Za-z0-9_.-]+$")


def cache_dir() -> Path:
    """$SNAIL_CACHE_DIR, else $XDG_CACHE_HOME/snail, else ~/.cache/snail."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "snail"


def save(path: Path, circuit: Circuit, schedule: Schedule) -> None:
    """Write the circuit and schedule, and the interface sidecar next to them."""
    meta = {"n_inputs": circuit.n_inputs, "hash": circuit.content_hash(),
            "inputs": [g.to_json() for g in circuit.inputs],
            "outputs": [g.to_json() for g in circuit.output_groups]}
    arrays = {"kind": circuit.kind, "a": circuit.a, "b": circuit.b, "outputs": circuit.outputs,
              "and_depth": circuit.and_depth, "xor_depth": circuit.xor_depth,
              "meta": np.frombuffer(json.dumps(meta).encode(), np.uint8),
              **schedule.to_arrays()}
    _write_atomic(path, lambda f: np.savez(f, **arrays))
    save_interface(_interface_path(path), circuit.interface())


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
    with np.load(path, allow_pickle=False) as d:
        meta = json.loads(d["meta"].tobytes())
        circuit = Circuit(meta["n_inputs"], d["kind"], d["a"], d["b"], d["outputs"],
                          [Group.from_json(g) for g in meta["inputs"]],
                          [Group.from_json(g) for g in meta["outputs"]],
                          d["and_depth"], d["xor_depth"])
        schedule = Schedule.from_arrays(d)
    if circuit.content_hash() != meta["hash"]:
        raise ValueError(f"cached circuit {path} is corrupt (content hash mismatch)")
    return circuit, schedule


def cached(name: str, build: Callable[[], Circuit],
           directory: Path | None = None) -> tuple[Circuit, Schedule]:
    """The compiled circuit called ``name`` (which must encode every build parameter and
    the builder's version), built and scheduled on first use, loaded from disk afterwards."""
    path = _path(name, directory)
    if path.exists():
        try:
            return load(path)
        except (OSError, ValueError, KeyError):
            path.unlink(missing_ok=True)  # corrupt or stale format: rebuild
    circuit = build()
    schedule = schedule_circuit(circuit)
    save(path, circuit, schedule)
    return circuit, schedule


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
    save_interface(path, iface)
    return iface


def _path(name: str, directory: Path | None) -> Path:
    if not _NAME_OK.match(name):
        raise ValueError(f"circuit cache name {name!r} must match {_NAME_OK.pattern}")
    return (directory or cache_dir()) / f"{name}.s{SCHEDULE_VERSION}.npz"


def _interface_path(npz: Path) -> Path:
    return npz.with_suffix(".interface.json")
