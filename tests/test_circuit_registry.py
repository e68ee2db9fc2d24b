"""Circuit ids: strict parsing, the ops family against numpy, caching by id."""

import numpy as np
import pytest

from snail_common.arith import mirror
from snail_common.circuit import evaluate, registry


@pytest.fixture(autouse=True)
def private_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SNAIL_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(registry, "_lru", type(registry._lru)())
    registry._interface.cache_clear()


@pytest.mark.parametrize("bad", [
    "", "fadd-x4", "ops/", "ops/fadd", "ops/fadd-x0", "ops/fadd-x4097", "ops/fadd-x01",
    "ops/fnope-x4", "ops/fadd-x4/..", "../ops/fadd-x4", "OPS/fadd-x4", "zk/fadd-x4",
    "ops/fadd-x4 ", "loc/../../etc", "ops/" + "a" * 200, 7,
])
def test_malformed_or_unknown_ids_are_refused(bad):
    with pytest.raises(registry.UnknownCircuit):
        registry.compiled(bad)


def test_unknown_family_message_lists_the_known_ones():
    with pytest.raises(registry.UnknownCircuit, match="known: ops, loc"):
        registry.check_id("zk/thing")


@pytest.mark.parametrize("op, fn", [("fadd", mirror.add), ("fmul", mirror.mul),
                                    ("fdiv", mirror.div), ("flt", mirror.lt)])
def test_ops_circuits_compute_the_op(op, fn):
    circuit, schedule = registry.compiled(f"ops/{op}-x5")
    rng = np.random.default_rng(3)
    x = (rng.standard_normal(5) * 100).astype(np.float32)
    y = (rng.standard_normal(5) * 100).astype(np.float32)
    z = evaluate(circuit, {"x": x, "y": y}, schedule)["z"]
    np.testing.assert_array_equal(z, fn(x, y))
    assert [g.name for g in circuit.inputs] == ["x", "y"]
    assert circuit.inputs[0].shape == (5,)


def test_unary_op_has_one_input():
    circuit, _ = registry.compiled("ops/fsqrt-x2")
    assert [g.name for g in circuit.inputs] == ["x"]


def test_compiled_once_then_served_from_memory_and_disk(tmp_path, monkeypatch):
    first = registry.compiled("ops/fadd-x2")
    assert registry.compiled("ops/fadd-x2") is first
    assert registry.lookup("ops/fadd-x2") is first
    assert list(tmp_path.glob("ops-fadd-x2.*.arrays"))
    monkeypatch.setattr(registry, "_lru", type(registry._lru)())
    assert registry.lookup("ops/fadd-x2") is None
    again = registry.compiled("ops/fadd-x2")  # from the disk cache
    assert again[0].content_hash() == first[0].content_hash()


def test_memory_cache_is_bounded_in_bytes(monkeypatch):
    monkeypatch.setattr(registry, "_memory", dict(registry._memory))
    sizes = [registry.footprint(registry.compiled(f"ops/fadd-x{k}")) for k in (1, 2, 3)]
    assert all(registry.lookup(f"ops/fadd-x{k}") for k in (1, 2, 3))  # 8 GiB by default
    assert sizes[0] < sizes[1] < sizes[2]
    registry.configure(memory_bytes=sizes[2] + sizes[1])
    registry.compiled("ops/fadd-x1")  # the oldest two go: x2 + x3 + x1 > the bound
    assert [registry.lookup(f"ops/fadd-x{k}") is not None for k in (1, 2, 3)] == \
        [True, False, True]
    registry.configure(memory_bytes=1)  # the most recent circuit always stays
    registry.compiled("ops/fadd-x2")
    assert [registry.lookup(f"ops/fadd-x{k}") is not None for k in (1, 2, 3)] == \
        [False, True, False]


def test_interface_needs_no_schedule(monkeypatch):
    """Clients ask for the interface only: on a cold cache it is built, never scheduled."""
    with monkeypatch.context() as patched:
        patched.setattr("snail_common.circuit.cache.schedule_circuit", _refuse)
        iface = registry.interface("ops/fmul-x3")
    assert registry.lookup("ops/fmul-x3") is None
    circuit, _ = registry.compiled("ops/fmul-x3")
    assert iface == circuit.interface()


def _refuse(*_):
    raise AssertionError("scheduled a circuit for a client")


def test_a_circuit_over_the_and_limit_is_refused_and_not_cached(tmp_path, monkeypatch):
    # fmul is 906 AND gates per lane: x1 fits a limit of 1000, x4 does not
    assert registry.compiled("ops/fmul-x1", max_and=1000)[1].n_and == 906
    with pytest.raises(registry.CircuitTooLarge, match=r"ops/fmul-x4: .*more than 1,000"):
        registry.compiled("ops/fmul-x4", max_and=1000)
    assert not list(tmp_path.glob("ops-fmul-x4.*"))
    assert registry.lookup("ops/fmul-x4") is None
    assert "ops/fmul-x4" not in registry._build_locks  # a refusal leaves no lock behind


def test_a_cached_circuit_over_the_limit_is_refused(monkeypatch):
    registry.compiled("ops/fmul-x4")  # compiled without a limit: in memory and on disk
    with pytest.raises(registry.CircuitTooLarge, match="has 3,624 AND gates"):
        registry.compiled("ops/fmul-x4", max_and=1000)
    monkeypatch.setattr(registry, "_lru", type(registry._lru)())
    with pytest.raises(registry.CircuitTooLarge, match="has 3,624 AND gates"):
        registry.compiled("ops/fmul-x4", max_and=1000)  # loaded from disk
    assert registry.lookup("ops/fmul-x4") is None


def test_an_interface_over_the_limit_is_refused_without_building_it(tmp_path, monkeypatch):
    """What a client asks of servers that compile at most 100,000 AND gates: the n=256
    circuit (15 M AND gates, gigabytes to build) stops as soon as it crosses the limit."""
    import tracemalloc

    monkeypatch.setenv("SNAIL_CACHE_DIR", str(tmp_path))
    tracemalloc.start()
    try:
        with pytest.raises(registry.CircuitTooLarge, match="100,000"):
            registry.interface("loc/lm-sil-ldlt-n256", max_and=100_000)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert peak < 300 << 20, f"built {peak >> 20} MiB of a circuit it refuses"
    assert not list(tmp_path.glob("*.interface.json"))
