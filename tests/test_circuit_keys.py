"""Cache keys follow what a circuit is: a family's version and the scheduler's version.

``circuit_keys.json`` pins the content hash of sample circuits of every family (and the
schedule of a few) under the versions that made them. An edit that changes a circuit
without bumping its family's VERSION (or the schedule without SCHEDULE_VERSION) fails
here, since a stale cached circuit would otherwise be served under the old key; an edit
that changes neither keeps every key, so the cache survives comments and refactorings.
After bumping a version: ``python tests/test_circuit_keys.py --update``.
"""

from __future__ import annotations

import hashlib
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from snail_common.arith import catalog
from snail_common.circuit import CircuitBuilder, cache, registry, schedule_circuit
from snail_common.circuit.schedule import SCHEDULE_VERSION
from snail_common.pnp import family
from snail_common.pnp.fops import CircuitBackend, F
from snail_common.pnp.svd import svd_solve

GOLDEN = Path(__file__).with_name("circuit_keys.json")
FAMILIES = {"ops": catalog.FAMILY, "loc": family.FAMILY}
SAMPLES = {
    "ops": [f"f{op}-x1" for op in catalog.SERVED],
    "loc": ["lm-sil-ldlt-n4", "gn-sil-ldlt-n4", "lm-do-ldlt-n4-i1", "ne-sil-n4", "nx-sil-n4",
            "lm-sil-ldlt-n4-x"],
}
SCHEDULED = ["ops/fadd-x1", "ops/fdiv-x1", "loc/lm-sil-ldlt-n4"]
# building an SVD circuit takes minutes: its solver alone stands in for it
COMPONENTS = {"loc": {"svd_solve-sweeps1": lambda: _svd_component()}}


def _svd_component():
    b = CircuitBuilder()
    be = CircuitBackend(b)
    packed = F(be, b.input("h", (21,), bits=32, dtype="float32"))
    rhs = F(be, b.input("g", (6,), bits=32, dtype="float32"))
    b.output("x", svd_solve(packed, rhs, sweeps=1).v, dtype="float32")
    return b.build()


def _schedule_digest(circuit_id: str) -> str:
    name, rest = circuit_id.split("/")
    schedule = schedule_circuit(FAMILIES[name].resolve(rest)())
    digest = hashlib.sha256()
    for key, arr in sorted(schedule.to_arrays().items()):
        digest.update(key.encode())
        digest.update(np.ascontiguousarray(arr).tobytes())
    return digest.hexdigest()


def current() -> dict:
    """What this code builds, under the versions it claims."""
    out = {"scheduler": {"version": SCHEDULE_VERSION,
                         "schedules": {cid: _schedule_digest(cid) for cid in SCHEDULED}},
           "families": {}}
    for name, fam in FAMILIES.items():
        hashes = {rest: fam.resolve(rest)().content_hash() for rest in SAMPLES[name]}
        hashes.update({part: build().content_hash()
                       for part, build in COMPONENTS.get(name, {}).items()})
        out["families"][name] = {"version": fam.version, "circuits": hashes}
    return out


@pytest.fixture(scope="module")
def built() -> dict:
    return current()


@pytest.fixture(scope="module")
def golden() -> dict:
    return json.loads(GOLDEN.read_text())


@pytest.mark.parametrize("name", sorted(FAMILIES))
def test_a_changed_circuit_comes_with_a_new_family_version(name, built, golden):
    now, then = built["families"][name], golden["families"][name]
    if now["version"] == then["version"]:
        changed = sorted(k for k in then["circuits"] if now["circuits"].get(k)
                         != then["circuits"][k])
        assert not changed, (f"{name} circuits {changed} changed under version "
                             f"{now['version']!r}: bump its VERSION (cached circuits would "
                             f"be stale), then run tests/test_circuit_keys.py --update")
    else:
        pytest.fail(f"{name} version is {now['version']!r}, circuit_keys.json has "
                    f"{then['version']!r}: run tests/test_circuit_keys.py --update")


def test_a_changed_schedule_comes_with_a_new_scheduler_version(built, golden):
    now, then = built["scheduler"], golden["scheduler"]
    assert now["version"] == then["version"], "run tests/test_circuit_keys.py --update"
    assert now["schedules"] == then["schedules"], (
        "schedule_circuit makes different schedules: bump SCHEDULE_VERSION, then run "
        "tests/test_circuit_keys.py --update")


def test_the_cache_key_is_the_id_and_the_two_versions(tmp_path, monkeypatch):
    """Nothing else (no source text) goes into a cached circuit's file name."""
    monkeypatch.setenv("SNAIL_CACHE_DIR", str(tmp_path))
    name, _ = registry._resolve("loc/lm-sil-ldlt-n4")
    assert name == f"loc-lm-sil-ldlt-n4.{family.VERSION}"
    assert cache._path(name, None) == tmp_path / (
        f"loc-lm-sil-ldlt-n4.{family.VERSION}.s{SCHEDULE_VERSION}.arrays")
    bumped = registry.Family("loc", family.VERSION + "x", family.FAMILY.resolve, "e")
    monkeypatch.setitem(registry._families, "loc", bumped)
    assert registry._resolve("loc/lm-sil-ldlt-n4")[0] != name


if __name__ == "__main__":
    if sys.argv[1:] != ["--update"]:
        sys.exit(f"usage: {sys.argv[0]} --update  (rewrites {GOLDEN.name})")
    GOLDEN.write_text(json.dumps(current(), indent=1, sort_keys=True) + "\n")
    print(f"wrote {GOLDEN}")
