"""Stored engine plans: a cached schedule's plan is loaded instead of rebuilt, equal to the
built one, and a changed plan builder cannot pass for the stored version."""

import hashlib
import threading
import time

import numpy as np
import pytest
from shared_paths import BRISTOL

from snail_common.circuit import cache, evaluate_bits, schedule_circuit
from snail_common.circuit.bristol import load_bristol
from snail_common.circuit.plan import PLAN_VERSION, _build, plan_for
from snail_common.circuit.plan_store import decode, encode
from snail_common.gc import garbled_run

# digest of the stored plans of mult64 (labels, then cleartext) for each PLAN_VERSION:
# if this fails, the plan builder changed: bump PLAN_VERSION in plan.py and add its digest
PLAN_DIGESTS = {1: "6eb819e0d82e861d7a5e7e0df3d4e9ed717c1d72a79651708cca62d8f336aa7e"}


def _mult():
    return load_bristol(BRISTOL / "mult64.txt")


def _digest(schedule) -> str:
    h = hashlib.sha256()
    for strided in (False, True):
        for arr in encode(_build(schedule, strided)):
            h.update(np.ascontiguousarray(arr).tobytes())
    return h.hexdigest()


def _same(p, q) -> None:
    """Field by field: slices and flags equal, index lists equal in dtype and values."""
    if isinstance(p, np.ndarray):
        assert type(q) is np.ndarray and p.dtype == q.dtype and np.array_equal(p, q)
    elif isinstance(p, tuple):
        assert type(p) is type(q) and len(p) == len(q)
        for a, b in zip(p, q):
            _same(a, b)
    else:
        assert p == q


def test_encode_decode_round_trip():
    schedule = schedule_circuit(_mult())
    for strided in (False, True):
        plan = _build(schedule, strided)
        _same(decode(encode(plan)), plan)


def test_the_plan_builder_matches_its_version():
    got = _digest(schedule_circuit(_mult()))
    assert PLAN_DIGESTS.get(PLAN_VERSION) == got, (
        f"plans changed: bump PLAN_VERSION and pin {got} (garbler and evaluator number "
        f"gates in plan order, and stored plans are keyed by the version)")


def test_a_cached_schedule_stores_its_plan_and_loads_it(tmp_path, monkeypatch):
    built = []
    cache.cached("mult-v1", _mult, tmp_path)
    _, schedule = cache.load(next(tmp_path.glob("mult-v1.*.arrays")))

    import snail_common.circuit.plan as plan_module

    def counting(s, strided):
        built.append(strided)
        return _build(s, strided)

    monkeypatch.setattr(plan_module, "_build", counting)
    first = plan_for(schedule)
    assert built == [False]
    _, again = cache.load(next(tmp_path.glob("mult-v1.*.arrays")))
    second = plan_for(again)
    assert built == [False]  # loaded, not rebuilt
    _same(second, first)
    bits = np.random.default_rng(3).random((2, again.n_inputs)) < 0.5
    for row, want in zip(bits, evaluate_bits(again, bits)):
        np.testing.assert_array_equal(garbled_run(again, row), want)


def test_the_compiling_process_stores_its_plan_for_the_next_load(tmp_path, monkeypatch):
    """A server that compiled the circuit stores its plan: the next server to start loads
    it instead of building it again."""
    _, schedule = cache.cached("mult-v1", _mult, tmp_path)
    first = plan_for(schedule)
    entry = next(tmp_path.glob("mult-v1.*.arrays"))
    assert list(entry.glob(f"plan*-v{PLAN_VERSION}-adjacent.json"))

    import snail_common.circuit.plan as plan_module

    monkeypatch.setattr(plan_module, "_build", lambda s, strided: pytest.fail("rebuilt"))
    _, again = cache.load(entry)
    _same(plan_for(again), first)


def test_concurrent_first_uses_of_a_stored_schedule_build_its_plan_once(tmp_path):
    """Two servers loading an entry without its plan: one builds and stores it, the other
    waits and loads it (threads stand in for processes: the lock is per open file)."""
    cache.cached("mult-v1", _mult, tmp_path)
    entry = next(tmp_path.glob("mult-v1.*.arrays"))
    schedules = [cache.load(entry)[1] for _ in range(2)]
    builds, barrier, plans = [], threading.Barrier(2), []

    def slow_build(schedule):
        builds.append(1)
        time.sleep(0.3)
        return _build(schedule, False)

    def first_use(schedule):
        barrier.wait()
        plans.append(schedule.plan_source.get("test", lambda: slow_build(schedule)))

    threads = [threading.Thread(target=first_use, args=(s,)) for s in schedules]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len(builds) == 1
    _same(plans[0], plans[1])
    assert not list(entry.glob("*.lock"))  # removed once released


def test_loading_a_stored_plan_waits_for_no_lock(tmp_path):
    cache.cached("mult-v1", _mult, tmp_path)
    entry = next(tmp_path.glob("mult-v1.*.arrays"))
    plan_for(cache.load(entry)[1])  # stored
    source, done = cache.StoredPlans(entry), []
    kind = f"v{PLAN_VERSION}-adjacent"
    with cache._exclusive(entry / f"plan1-{kind}.lock"):  # as if another process held it
        loader = threading.Thread(target=lambda: done.append(
            source.get(kind, lambda: pytest.fail("rebuilt"))))
        loader.start()
        loader.join(10)
        assert done
    loader.join()


def test_a_corrupt_stored_plan_is_rebuilt(tmp_path):
    cache.cached("mult-v1", _mult, tmp_path)
    entry = next(tmp_path.glob("mult-v1.*.arrays"))
    _, schedule = cache.load(entry)
    plan = plan_for(schedule)
    pool = next(entry.glob("plan*-pool32.npy"))
    data = bytearray(pool.read_bytes())
    data[-1] ^= 1
    pool.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="CRC"):
        cache.StoredPlans(entry)._load(pool.name.removesuffix("-pool32.npy"))
    _, again = cache.load(entry)
    _same(plan_for(again), plan)  # rebuilt, and stored intact again
    cache.StoredPlans(entry)._load(pool.name.removesuffix("-pool32.npy"))
