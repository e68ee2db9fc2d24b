"""Circuit cache: round trip, content hash, rebuild on corruption, the client's interface
sidecar; bench CLI contract."""

import json
import os
import threading
import time
import tracemalloc
import zlib

import numpy as np
import pytest
from click.testing import CliRunner
from shared_paths import BRISTOL

from snail_bench.cli import main as bench
from snail_common.circuit import CircuitBuilder, cache, encode_inputs, evaluate
from snail_common.circuit.cache import cache_dir, cached, cached_interface, load
from snail_common.circuit.schedule import SCHEDULE_VERSION


def _adder():
    b = CircuitBuilder()
    x = b.input("x", (3,), 8, "uint8")
    y = b.input("y", (3,), 8, "uint8")
    carry, out = 0, []
    for i in range(8):
        t = b.xor(x[:, i], carry)
        out.append(b.xor(t, y[:, i]))
        carry = b.xor(carry, b.and_(t, b.xor(y[:, i], carry)))
    b.output("s", np.stack(out, axis=1), "uint8")
    return b.build()


def test_cache_round_trip_keeps_function_and_hash(tmp_path):
    calls = []

    def build():
        calls.append(1)
        return _adder()

    c1, _ = cached("adder-v1", build, tmp_path)
    c2, s2 = cached("adder-v1", build, tmp_path)
    assert len(calls) == 1
    assert c1.content_hash() == c2.content_hash()
    x = np.array([1, 200, 255], np.uint8)
    y = np.array([2, 100, 1], np.uint8)
    assert list(evaluate(c2, {"x": x, "y": y}, s2)["s"]) == list(x + y)


def test_disk_cache_evicts_the_least_recently_used_entries(tmp_path, monkeypatch):
    entry = tmp_path / f"adder-a.s{SCHEDULE_VERSION}.arrays"
    cached("adder-a", _adder, tmp_path)
    size = cache.entry_bytes(entry)
    monkeypatch.setattr(cache, "_settings", dict(cache._settings))
    cache.configure(max_bytes=int(2.5 * size))  # room for two entries
    cached("adder-b", _adder, tmp_path)
    os.utime(entry, (1, 1))  # a long time ago ...
    cached("adder-a", _adder, tmp_path)  # ... until used again: now b is the oldest
    cached("adder-c", _adder, tmp_path)
    left = sorted(p.name.split(".")[0] for p in tmp_path.glob("*.arrays"))
    assert left == ["adder-a", "adder-c"]
    assert (tmp_path / f"adder-b.s{SCHEDULE_VERSION}.interface.json").exists()
    cache.configure(max_bytes=1)  # an entry bigger than the bound still serves its run
    cached("adder-d", _adder, tmp_path)
    assert [p.name.split(".")[0] for p in tmp_path.glob("*.arrays")] == ["adder-d"]


def test_hash_changes_with_the_netlist():
    c = _adder()
    h = c.content_hash()
    c.a = c.a.copy()
    c.a[-1] = 2
    c._hash = None
    assert c.content_hash() != h


def test_corrupt_cache_file_is_detected_and_rebuilt(tmp_path):
    cached("adder-v1", _adder, tmp_path)
    path = tmp_path / f"adder-v1.s{SCHEDULE_VERSION}.arrays"
    for name in ("a", "schedule_and_a"):
        file = path / f"{name}.npy"
        data = bytearray(file.read_bytes())
        data[-1] ^= 1  # one bit of the last element
        file.write_bytes(bytes(data))
        with pytest.raises(ValueError, match=f"{name}.npy fails its CRC"):
            load(path)
        c, _ = cached("adder-v1", _adder, tmp_path)  # rebuilt, and right
        assert c.content_hash() == _adder().content_hash()
        load(path)


def test_a_loaded_circuit_is_mapped_read_only_and_keeps_its_hash(tmp_path):
    """Servers map the arrays instead of reading them (the netlist is never touched),
    so nothing may write into them; the stored hash is the built circuit's."""
    cached("adder-v1", _adder, tmp_path)
    circuit, schedule = load(tmp_path / f"adder-v1.s{SCHEDULE_VERSION}.arrays")
    assert circuit._hash == _adder().content_hash()
    for arr in (circuit.a, schedule.and_a, schedule.lin_terms):
        assert isinstance(arr.base, np.memmap) or isinstance(arr, np.memmap)
        assert not arr.flags.writeable


def test_a_fresh_build_is_served_mapped_from_its_entry(tmp_path):
    """The compiling server drops the built arrays for the entry it wrote (they are not
    held twice, and its plans are stored there: see test_plan_store)."""
    circuit, schedule = cached("adder-v1", _adder, tmp_path)
    assert circuit.content_hash() == _adder().content_hash()
    for arr in (circuit.a, schedule.and_a, schedule.lin_terms):
        assert isinstance(arr.base, np.memmap) or isinstance(arr, np.memmap)
    assert schedule.plan_source.entry == tmp_path / f"adder-v1.s{SCHEDULE_VERSION}.arrays"


def _at_once(call, n=2):
    """``call()`` from ``n`` threads started together; their results."""
    barrier, results = threading.Barrier(n), []

    def run():
        barrier.wait()
        results.append(call())

    threads = [threading.Thread(target=run) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return results


def test_concurrent_requests_for_a_missing_entry_build_it_once(tmp_path):
    """Two servers starting on a cold cache: one builds, the other waits and loads (the
    lock is per open file, so threads stand in for processes)."""
    builds = []

    def slow_build():
        builds.append(1)
        time.sleep(0.3)
        return _adder()

    results = _at_once(lambda: cached("adder-v1", slow_build, tmp_path))
    assert len(builds) == 1
    assert {c.content_hash() for c, _ in results} == {_adder().content_hash()}
    assert not list(tmp_path.glob("*.lock"))  # removed once released


def test_loading_an_existing_entry_waits_for_no_lock(tmp_path):
    """Daemons starting together on a warm cache check the entry side by side: only a
    missing entry is built one process at a time."""
    cached("adder-v1", _adder, tmp_path)
    path = tmp_path / f"adder-v1.s{SCHEDULE_VERSION}.arrays"
    done = []
    with cache._exclusive(path.with_suffix(".lock")):  # as if another process held it
        loader = threading.Thread(target=lambda: done.append(cached("adder-v1", _never,
                                                                    tmp_path)))
        loader.start()
        loader.join(10)
        assert done
    loader.join()


def test_crc_check_maps_the_file_instead_of_copying_it(tmp_path):
    """The CRC of a large file is read through mapped windows: no chunk is allocated (a
    16 MiB bytes object per read before), whatever the file's size."""
    data = np.random.default_rng(1).integers(0, 256, 40 << 20, np.uint8).tobytes()[:-123]
    file = tmp_path / "big.npy"
    file.write_bytes(data)
    (tmp_path / "empty.npy").write_bytes(b"")
    tracemalloc.start()
    try:
        got = cache._crc(file)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert got == zlib.crc32(data)
    assert peak < 1 << 20
    assert cache._crc(tmp_path / "empty.npy") == 0


def test_a_new_scheduler_never_loads_a_stale_schedule(tmp_path, monkeypatch):
    """Same name, another scheduler version: the cache builds anew instead of returning
    what the old scheduler made (garbler and evaluator number gates in schedule order)."""
    builds = []

    def build():
        builds.append(1)
        return _adder()

    cached("adder-v1", build, tmp_path)
    cached("adder-v1", build, tmp_path)
    assert len(builds) == 1
    monkeypatch.setattr("snail_common.circuit.cache.SCHEDULE_VERSION", SCHEDULE_VERSION + 1)
    cached("adder-v1", build, tmp_path)
    assert len(builds) == 2
    assert len(list(tmp_path.glob("adder-v1.*.arrays"))) == 2


def _never():
    raise AssertionError("built a circuit")


def test_interface_is_what_a_client_needs_of_the_circuit():
    circuit = _adder()
    iface = circuit.interface()
    values = {"x": np.array([1, 2, 3], np.uint8), "y": np.array([9, 8, 7], np.uint8)}
    assert np.array_equal(encode_inputs(iface, values), encode_inputs(circuit, values))
    assert (iface.n_inputs, iface.n_outputs) == (circuit.n_inputs, circuit.n_outputs)
    assert iface.content_hash == circuit.content_hash()
    assert (iface.counts, iface.depth) == (circuit.counts(), circuit.depth())
    assert type(iface).from_json(json.loads(json.dumps(iface.to_json()))) == iface


def test_interface_comes_from_the_sidecar_or_an_unscheduled_build(tmp_path, monkeypatch):
    """A compiled circuit leaves its interface next to it, so clients read a few hundred
    bytes; on a cold cache they build the netlist but never schedule it."""
    circuit, _ = cached("adder-v1", _adder, tmp_path)
    assert cached_interface("adder-v1", _never, tmp_path) == circuit.interface()
    monkeypatch.setattr(cache, "schedule_circuit", lambda _: _never())
    assert cached_interface("adder-v2", _adder, tmp_path) == circuit.interface()
    assert cached_interface("adder-v2", _never, tmp_path) == circuit.interface()
    assert not list(tmp_path.glob("adder-v2.*.arrays"))


def test_corrupt_interface_sidecar_is_rebuilt(tmp_path):
    iface = cached_interface("adder-v1", _adder, tmp_path)
    path = tmp_path / f"adder-v1.s{SCHEDULE_VERSION}.interface.json"
    for bad in (b"{not json", json.dumps({**iface.to_json(), "n_inputs": 5}).encode()):
        path.write_bytes(bad)
        assert cached_interface("adder-v1", _adder, tmp_path) == iface
        assert json.loads(path.read_bytes()) == iface.to_json()


def test_cache_dir_env_override(monkeypatch, tmp_path):
    monkeypatch.setenv("SNAIL_CACHE_DIR", str(tmp_path))
    assert cache_dir() == tmp_path


def test_bench_bristol_json_contract():
    r = CliRunner().invoke(bench, ["bristol", str(BRISTOL / "mult2_64.txt"), "--input",
                                   "0xffffffffffffffff", "--input", "3", "--json"])
    assert r.exit_code == 0, r.output
    out = json.loads(r.output)["bristol"]
    assert out["outputs"] == [2, (1 << 64) - 3]
    assert (out["and"], out["xor"], out["not"], out["garbled"]) == (8128, 19904, 0, False)


def test_bench_bristol_bad_input_is_usage_error():
    r = CliRunner().invoke(bench, ["bristol", str(BRISTOL / "adder64.txt"), "--input", "1",
                                   "--input", "x1"])
    assert r.exit_code == 2
    assert "x1" in r.output


def test_bench_bristol_garbled_matches_clear():
    args = ["bristol", str(BRISTOL / "mult64.txt"), "--input", "123456789", "--input",
            "0xfedcba987", "--json"]
    clear = json.loads(CliRunner().invoke(bench, args).output)["bristol"]
    r = CliRunner().invoke(bench, [*args, "--garbled"])
    assert r.exit_code == 0, r.output
    garbled = json.loads(r.output)["bristol"]
    assert garbled["garbled"] is True
    assert garbled["outputs"] == clear["outputs"] == [(123456789 * 0xFEDCBA987) % 2**64]
