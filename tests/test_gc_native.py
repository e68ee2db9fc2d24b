"""The native kernel is the numpy engine bit for bit, and runs only what it may.

Fixed seeds, offsets and keys: the stream's bytes (a digest and every frame's length), the
output zero-labels and the evaluator's active labels must be the numpy engine's, on
circuits of every family, under both schemes, in one run and in lanes; the decoded
outputs are the cleartext evaluation's. The library is built in a private folder and
loaded only when its record matches (a planted one is never loaded); without a compiler
the numpy engine runs and says why.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from snail_common.arith import catalog
from snail_common.circuit import CircuitBuilder, evaluate_bits, registry, schedule_circuit
from snail_common.circuit.plan import LinearPlan, Plan, RunGroup, plan_for
from snail_common.gc import Evaluator, Garbler, active_input_labels, decode_output_labels
from snail_common.gc import engine as engines
from snail_common.gc.lanes import LaneEvaluator, LaneGarbler
from snail_common.gc.native import build
from snail_common.gc.native.program import build_program
from snail_common.gc.native.run import NativeRun, kernel_threads

try:
    engines.resolve("native")
except build.NativeUnavailable as exc:  # pragma: no cover - where no compiler or AES-NI
    pytest.skip(f"the native kernel cannot run here: {exc}", allow_module_level=True)

SCHEMES = ("halfgates", "threehalves")
CIRCUITS = [f"ops/f{op}-x1" for op in catalog.SERVED] + [
    "loc/nx-sil-n4",  # the default: client solve, fixed-point per-point work
    "loc/ne-sil-n4",  # client solve, float
    "loc/lm-sil-ldlt-n4-x",  # the solve in the circuit
]


ISAS = [0, 1] if build.library().snail_isa(-1) else [0]  # AES-NI alone; VAES where it runs


@pytest.fixture(params=ISAS, ids=lambda isa: ("aesni", "vaes")[isa])
def isa(request):
    """Each instruction set the kernel's AND ops may use on this CPU, the CPU's choice
    restored after the test."""
    lib = build.library()
    was = lib.snail_isa(-1)
    assert lib.snail_isa(request.param) == request.param
    yield request.param
    lib.snail_isa(was)


def secrets(tag: str, lanes: int = 1):
    """Fixed seeds, offsets (lowest bit set) and keys."""
    rng = np.random.default_rng(int(hashlib.sha256(tag.encode()).hexdigest()[:8], 16))
    deltas = rng.integers(0, 2**63, (lanes, 2), dtype=np.uint64) | np.array([1, 0], np.uint64)
    return [rng.bytes(16) for _ in range(lanes)], list(deltas), [rng.bytes(16)
                                                               for _ in range(lanes)]


def garble(schedule, engine, scheme, tag, block=8192, frame=1 << 20):
    (seed,), (delta,), (key,) = secrets(tag)
    g = Garbler(schedule, seed, delta, key, scheme=scheme, engine=engine, block_gates=block,
                frame_bytes=frame)
    frames = [bytes(f) for f in g.frames()]
    return frames, g.output_zero_labels, seed, delta


def evaluate(schedule, engine, labels, frames, cut=None):
    ev = Evaluator(schedule, labels, engine=engine)
    data = b"".join(frames)
    step = cut or max(1, len(data))
    for i in range(0, len(data), step):
        ev.feed(data[i : i + step])
    return ev.output_labels()


def digest(frames):
    return hashlib.sha256(b"".join(frames)).hexdigest(), [len(f) for f in frames]


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("circuit_id", CIRCUITS)
def test_native_is_numpy_bit_for_bit_on_every_family(circuit_id, scheme, isa):
    _, schedule = registry.compiled(circuit_id)
    tag = f"{circuit_id}/{scheme}"
    frames = {}
    for engine in ("numpy", "native"):  # the reference first
        frames[engine], zero, seed, delta = garble(schedule, engine, scheme, tag,
                                                   frame=1 << 16)
        if engine == "numpy":
            want_zero = zero
        else:
            assert np.array_equal(zero, want_zero)
    assert digest(frames["native"]) == digest(frames["numpy"])
    bits = np.random.default_rng(7).integers(0, 2, schedule.n_inputs).astype(bool)
    labels = active_input_labels(seed, delta, bits)
    active = {e: evaluate(schedule, e, labels, frames["numpy"], cut=40_003)
              for e in engines.ENGINES}
    assert np.array_equal(active["native"], active["numpy"])
    out = decode_output_labels(delta, want_zero, active["native"])
    assert np.array_equal(out, evaluate_bits(schedule, bits[None])[0])


def _strided_circuit(lanes: int, layers: int):
    """Chains over the columns of a (lanes, 4) input: each XOR reads a column at a step of
    4 slots, and each NOT XORs one constant slot into every row."""
    b = CircuitBuilder()
    x = b.input("x", (lanes, 4), 1)[..., 0]
    acc = x[:, 0]
    for i in range(1, layers + 1):
        u = b.xor(acc, x[:, i % 4])
        acc = b.and_(u, b.not_(b.xor(acc, x[:, (i + 1) % 4])))
    b.output("y", acc[:, None])
    return b.build()


def test_strided_and_repeated_columns_run_as_slices_bit_for_bit(isa):
    schedule = schedule_circuit(_strided_circuit(1025, 5))  # odd: each AND op has a lone gate
    program = build_program(plan_for(schedule), schedule.n_slots, 8192)
    xor_rows = [program.rows[op[3] + 1 : op[3] + 1 + op[2]] for op in program.ops
                if op[0] & 0xFF == 1]
    assert xor_rows and all((rows[:, 0] == 0).all() for rows in xor_rows)  # no index lists
    assert any((rows[:, 2] == 4).any() for rows in xor_rows)  # a column at a step of 4
    assert any((rows[:, 2] == 0).any() for rows in xor_rows)  # one slot for every row
    frames, zero = {}, {}
    for engine in engines.ENGINES:
        frames[engine], zero[engine], seed, delta = garble(schedule, engine, "halfgates",
                                                           "strided")
    assert digest(frames["native"]) == digest(frames["numpy"])
    assert np.array_equal(zero["native"], zero["numpy"])
    bits = np.random.default_rng(3).integers(0, 2, schedule.n_inputs).astype(bool)
    labels = active_input_labels(seed, delta, bits)
    active = {e: evaluate(schedule, e, labels, frames["numpy"]) for e in engines.ENGINES}
    assert np.array_equal(active["native"], active["numpy"])
    out = decode_output_labels(delta, zero["numpy"], active["native"])
    assert np.array_equal(out, evaluate_bits(schedule, bits[None])[0])


def test_strided_columns_in_lanes_are_numpy_bit_for_bit(isa):
    """XOR ops of slices and ragged rows with several lanes a row (the garbler's lanes)."""
    schedule = schedule_circuit(_strided_circuit(1025, 5))
    seeds, deltas, keys = secrets("strided-lanes", 3)
    streams = {}
    for engine in engines.ENGINES:
        g = LaneGarbler(schedule, seeds, deltas, keys, engine=engine)
        per_lane = [[] for _ in range(3)]
        for frame in g.frames():
            for lane, part in enumerate(frame):
                per_lane[lane].append(bytes(part))
        streams[engine] = [digest(frames) for frames in per_lane], g.output_zero_labels
    assert streams["native"][0] == streams["numpy"][0]
    for a, b in zip(streams["native"][1], streams["numpy"][1], strict=True):
        assert np.array_equal(a, b)


def _xor_of_columns(values: np.ndarray, groups) -> np.ndarray:
    """What a linear step writes: each group's out rows, the XOR of its columns' rows."""
    want = values.copy()
    for g in groups:
        acc = np.zeros_like(values[g.out])
        for col in g.columns:
            acc ^= values[col]  # a slice of one slot without a step: that slot, each row
        want[g.out] = acc
    return want


@pytest.mark.parametrize("lanes", [1, 2])
def test_xor_ops_of_many_slice_columns_are_the_xor_of_their_columns(lanes, monkeypatch):
    """More columns than one pass takes (9: 4 + 4 + 1; 6 into scratch rows), over more
    rows than one block: written in place and, for a step that may not, through scratch."""
    rng = np.random.default_rng(11)
    n_slots, rows = 6000, 301
    values = rng.integers(0, 1 << 63, (n_slots, 2 * lanes), dtype=np.uint64)
    def run(first: int, step: int = 1) -> slice:
        return slice(first, first + step * (rows - 1) + 1, step)

    wide = RunGroup(run(4000), (*(run(300 * j, 2) for j in range(8)), slice(3900, 3901)))
    few = RunGroup(run(4400), (run(0), run(rows)))
    waits = RunGroup(run(5000), (run(5000), *(run(300 * j) for j in range(1, 6))))  # reads
    # the rows it writes: a step that computes into scratch, then publishes
    plan = Plan((LinearPlan((wide, few), True), LinearPlan((waits,), False)), 0)
    program = build_program(plan, n_slots, 64)
    assert [int(op[2]) for op in program.ops if op[0] & 0xFF == 1] == [9, 2, 6]
    assert (program.rows[:, 0] == 0).all()  # every row descriptor a slice
    want = _xor_of_columns(_xor_of_columns(values, (wide, few)), (waits,))
    monkeypatch.setattr("snail_common.gc.native.run.program_for", lambda *_: program)
    run = NativeRun(None, 64, 1, values, [bytes(16)] * lanes)
    run.run(run.program.n_ops, None)
    assert np.array_equal(values, want)


def test_the_stream_digest_of_a_fixed_run_is_pinned(isa):
    """The same bytes as the numpy engine pinned them (test_gc_garbled pins its digest);
    here small blocks and frames, so ops are cut across blocks and frames."""
    _, schedule = registry.compiled("ops/fmul-x4")
    for scheme in SCHEMES:
        got = {e: digest(garble(schedule, e, scheme, "pin", block=37, frame=4096)[0])
               for e in engines.ENGINES}
        assert got["native"] == got["numpy"]
        assert len(got["native"][1]) > 10


@pytest.mark.parametrize("lanes", [1, 3])
def test_lanes_are_numpy_bit_for_bit(lanes, isa):
    _, schedule = registry.compiled("ops/fdiv-x2")
    seeds, deltas, keys = secrets(f"lanes{lanes}", lanes)
    streams = {}
    for engine in engines.ENGINES:
        g = LaneGarbler(schedule, seeds, deltas, keys, block_gates=100, frame_bytes=8192,
                        engine=engine)
        per_lane = [[] for _ in range(lanes)]
        for frame in g.frames():
            for lane, part in enumerate(frame):
                per_lane[lane].append(bytes(part))
        streams[engine] = (per_lane, g.output_zero_labels)
    assert [digest(s) for s in streams["native"][0]] == [digest(s) for s in streams["numpy"][0]]
    for a, b in zip(streams["native"][1], streams["numpy"][1]):
        assert np.array_equal(a, b)
    # a lane's stream is the single-run stream of its secrets
    single = Garbler(schedule, seeds[0], deltas[0], keys[0], block_gates=100,
                     frame_bytes=8192, engine="native")
    assert b"".join(single.frames()) == b"".join(streams["native"][0][0])
    rng = np.random.default_rng(lanes)
    bits = rng.integers(0, 2, (lanes, schedule.n_inputs)).astype(bool)
    labels = [active_input_labels(s, d, b) for s, d, b in zip(seeds, deltas, bits)]
    outs = {}
    for engine in engines.ENGINES:
        ev = LaneEvaluator(schedule, labels, engine=engine)
        if lanes > 1:
            ev.drop(1)  # its session failed: the others go on
        data = [b"".join(s) for s in streams["numpy"][0]]
        for lane, stream in enumerate(data):
            if lane != 1 or lanes == 1:
                for i in range(0, len(stream), 5000):
                    ev.feed(lane, stream[i : i + 5000])
        outs[engine] = [ev.output_labels(k) for k in range(lanes) if k != 1 or lanes == 1]
    for a, b in zip(outs["native"], outs["numpy"]):
        assert np.array_equal(a, b)
    want = evaluate_bits(schedule, bits)
    for k, active in zip([k for k in range(lanes) if k != 1 or lanes == 1], outs["native"]):
        zero = streams["native"][1][k]
        assert np.array_equal(decode_output_labels(deltas[k], zero, active), want[k])


def test_the_evaluator_waits_for_a_block_cut_by_a_read():
    _, schedule = registry.compiled("ops/fadd-x2")
    frames, zero, seed, delta = garble(schedule, "native", "halfgates", "cut", block=64)
    bits = np.ones(schedule.n_inputs, bool)
    labels = active_input_labels(seed, delta, bits)
    ev = Evaluator(schedule, labels, engine="native")
    data = b"".join(frames)
    for i in range(len(data)):  # one byte at a time
        assert not ev.done
        ev.feed(data[i : i + 1])
    assert ev.done
    out = decode_output_labels(delta, zero, ev.output_labels())
    assert np.array_equal(out, evaluate_bits(schedule, bits[None])[0])


def test_every_index_is_checked_before_the_kernel_runs():
    _, schedule = registry.compiled("ops/fadd-x1")
    plan = plan_for(schedule)
    build_program(plan, schedule.n_slots, 64)  # the real one passes
    with pytest.raises(ValueError, match="leave"):
        build_program(plan, schedule.n_slots - 1, 64)  # one slot short: some index is out
    run = NativeRun(schedule, 64, 1, np.zeros((schedule.n_slots, 2), np.uint64), [bytes(16)])
    end, words = run.fit(1 << 30)
    assert end == run.program.n_ops and words == 4 * schedule.n_and
    with pytest.raises(ValueError, match="tables"):
        run.run(end, np.zeros((1, words - 1), np.uint64))  # tables a word short
    with pytest.raises(ValueError, match="values"):
        NativeRun(schedule, 64, 1, np.zeros((schedule.n_slots - 1, 2), np.uint64), [bytes(16)])
    garbling = NativeRun(schedule, 64, 1, np.zeros((schedule.n_slots, 2), np.uint64),
                         [bytes(16)], np.array([[1, 0]], np.uint64))
    read_only = np.frombuffer(bytes(8 * words), np.uint64).reshape(1, -1)
    with pytest.raises(ValueError, match="writable"):
        garbling.run(end, read_only)


# ---------------------------------------------------------------- building and loading


def _compile_planted(tmp: Path, marker: Path) -> bytes:
    """A shared library whose constructor writes ``marker``: loading it would show."""
    src = tmp / "planted.c"
    src.write_text('#include <stdio.h>\n__attribute__((constructor)) static void p(void) '
                   f'{{ FILE *f = fopen("{marker}", "w"); if (f) fclose(f); }}\n'
                   "int snail_cpu_ok(void) { return 1; }\n")
    out = tmp / "planted.so"
    subprocess.run([os.environ.get("CC") or "cc", "-shared", "-fPIC", "-o", out, src],
                   check=True)
    return out.read_bytes()


def test_a_planted_library_is_never_loaded(tmp_path):
    root = folder = tmp_path / "kernel"
    _, how = build.build_and_load(root)
    assert how.startswith("compiled")
    assert folder.stat().st_mode & 0o777 == 0o700
    _, how = build.build_and_load(root)
    assert how.startswith("loaded")  # the record matched: no rebuild
    record = next(folder.glob("*.json"))
    library = folder / json.loads(record.read_text())["library"]
    marker = tmp_path / "planted-ran"
    library.write_bytes(_compile_planted(tmp_path, marker))  # swapped in place
    lib, how = build.build_and_load(root)
    assert how.startswith("compiled") and not marker.exists()
    assert lib.snail_cpu_ok() == 1
    # a record naming another source is stale: rebuilt, not loaded
    text = record.read_text()
    record.write_text(text.replace('"source_sha256": "', '"source_sha256": "0'))
    _, how = build.build_and_load(root)
    assert how.startswith("compiled")


def test_without_a_compiler_a_library_built_for_this_source_serves(tmp_path, monkeypatch):
    """An image's build step compiles the kernel; where it runs there is no compiler."""
    folder = tmp_path / "kernel"
    build.build_and_load(folder)
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    lib, how = build.build_and_load(folder)
    assert how.startswith("prebuilt") and lib.snail_cpu_ok() == 1
    record = next(folder.glob("*.json"))
    library = folder / json.loads(record.read_text())["library"]
    library.write_bytes(library.read_bytes() + b"planted")  # not what the record says
    with pytest.raises(build.NativeUnavailable, match="no C compiler"):
        build.build_and_load(folder)


def test_a_folder_others_may_enter_is_refused(tmp_path):
    folder = tmp_path / "kernel"
    folder.mkdir(mode=0o755)
    folder.chmod(0o755)
    with pytest.raises(build.NativeUnavailable, match="mode 0700"):
        build.build_and_load(folder)


@pytest.fixture
def no_compiler(monkeypatch, tmp_path):
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    monkeypatch.setenv(build.KERNEL_DIR_ENV, str(tmp_path / "kernel"))
    build.reset()
    yield
    build.reset()


def test_without_a_compiler_numpy_serves_and_says_why(no_compiler, monkeypatch):
    monkeypatch.delenv(engines.ENGINE_ENV, raising=False)
    status = engines.engine_status()
    assert status["engine"] == "numpy" and status["requested"] == "auto"
    assert "no C compiler" in status["reason"] and "no-such-cc" in status["reason"]
    _, schedule = registry.compiled("ops/fadd-x1")
    (seed,), (delta,), (key,) = secrets("fallback")
    g = Garbler(schedule, seed, delta, key)
    assert g.engine == "numpy"
    bits = np.zeros(schedule.n_inputs, bool)
    active = evaluate(schedule, None, active_input_labels(seed, delta, bits), list(g.frames()))
    assert np.array_equal(decode_output_labels(delta, g.output_zero_labels, active),
                          evaluate_bits(schedule, bits[None])[0])
    with pytest.raises(build.NativeUnavailable, match="no C compiler"):
        engines.resolve("native")  # asked for explicitly: an error, not a fallback
    monkeypatch.setenv(engines.ENGINE_ENV, "native")
    with pytest.raises(build.NativeUnavailable):
        Garbler(schedule, seed, delta, key)
    monkeypatch.setenv(engines.ENGINE_ENV, "numpy")
    assert engines.engine_status() == {"engine": "numpy", "requested": "numpy"}
    monkeypatch.setenv(engines.ENGINE_ENV, "fast")
    with pytest.raises(ValueError, match="SNAIL_ENGINE"):
        engines.resolve()


def test_a_compiler_that_fails_is_a_reason_not_a_crash(monkeypatch, tmp_path):
    fake = tmp_path / "cc"
    fake.write_text("#!/bin/sh\n[ \"$1\" = --version ] && echo 'fake cc 1.0' && exit 0\n"
                    "echo 'cannot compile' >&2; exit 1\n")
    fake.chmod(0o755)
    monkeypatch.setenv("CC", str(fake))
    with pytest.raises(build.NativeUnavailable, match="cannot compile"):
        build.build_and_load(tmp_path / "kernel")
    assert shutil.which(str(fake))


@pytest.mark.parametrize("scheme", SCHEMES)
def test_ops_cut_across_two_threads_are_numpy_bit_for_bit(scheme, isa, monkeypatch):
    """Wide steps (AND ops of 8192 gates, XOR ops of 12288 rows) cut into pieces that two
    threads take in turn: the same stream and labels as numpy's."""
    from snail_bench.engine import _layered_circuit
    from snail_common.circuit import schedule_circuit
    from snail_common.gc.native.program import OP_PARALLEL, PAR_MIN_AND

    schedule = schedule_circuit(_layered_circuit(12288, 5))
    program = build_program(plan_for(schedule), schedule.n_slots, 8192)
    wide = program.ops[(program.ops[:, 0] & OP_PARALLEL > 0) & (program.ops[:, 1] >= 8192)]
    assert len(wide) > 4 and (program.ops[:, 1] >= PAR_MIN_AND).any()
    monkeypatch.setenv("SNAIL_KERNEL_THREADS", "2")
    assert kernel_threads() == 2
    frames, zero, seed, delta = garble(schedule, "native", scheme, "threads")
    monkeypatch.delenv("SNAIL_KERNEL_THREADS")
    want, want_zero, _, _ = garble(schedule, "numpy", scheme, "threads")
    assert digest(frames) == digest(want) and np.array_equal(zero, want_zero)
    bits = np.random.default_rng(3).integers(0, 2, schedule.n_inputs).astype(bool)
    labels = active_input_labels(seed, delta, bits)
    monkeypatch.setenv("SNAIL_KERNEL_THREADS", "2")
    active = evaluate(schedule, "native", labels, frames, cut=300_001)
    monkeypatch.delenv("SNAIL_KERNEL_THREADS")
    assert np.array_equal(active, evaluate(schedule, "numpy", labels, frames))


def test_runs_from_several_threads_share_one_helper_bit_for_bit(monkeypatch):
    """Four Python threads garble and evaluate wide runs at once with two kernel threads
    each: the one holding the process's helper thread shares its ops, the others run
    alone, and every run is numpy's bit for bit."""
    from concurrent.futures import ThreadPoolExecutor

    from snail_bench.engine import _layered_circuit
    from snail_common.circuit import schedule_circuit

    schedule = schedule_circuit(_layered_circuit(12288, 3))
    tags = [f"helper-{k}" for k in range(4)]
    want = {tag: garble(schedule, "numpy", "halfgates", tag) for tag in tags}
    bits = np.random.default_rng(5).integers(0, 2, schedule.n_inputs).astype(bool)
    monkeypatch.setenv("SNAIL_KERNEL_THREADS", "2")

    def run(tag):
        frames, zero, seed, delta = garble(schedule, "native", "halfgates", tag)
        labels = active_input_labels(seed, delta, bits)
        return digest(frames), zero, evaluate(schedule, "native", labels, frames, 200_003)

    with ThreadPoolExecutor(4) as pool:
        got = dict(zip(tags, pool.map(run, tags), strict=True))
    for tag in tags:
        frames, zero, seed, delta = want[tag]
        labels = active_input_labels(seed, delta, bits)
        assert got[tag][0] == digest(frames) and np.array_equal(got[tag][1], zero)
        assert np.array_equal(got[tag][2], evaluate(schedule, "numpy", labels, frames))


def test_a_forked_child_starts_a_helper_of_its_own(monkeypatch):
    """The parent's helper thread does not exist in a forked child: the child's first
    two-thread run starts its own (it would wait forever for the parent's)."""
    import multiprocessing as mp

    from snail_bench.engine import _layered_circuit
    from snail_common.circuit import schedule_circuit

    schedule = schedule_circuit(_layered_circuit(12288, 2))
    monkeypatch.setenv("SNAIL_KERNEL_THREADS", "2")
    parent = digest(garble(schedule, "native", "halfgates", "fork")[0])  # the helper starts
    ctx = mp.get_context("fork")
    with ctx.Pool(1) as pool:
        child = pool.apply_async(_digest_of_a_run, (schedule, "fork")).get(timeout=60)
    assert child == parent


def _digest_of_a_run(schedule, tag):
    return digest(garble(schedule, "native", "halfgates", tag)[0])


def test_a_direct_piece_that_reads_what_it_writes_stays_on_one_thread():
    """Order matters in such a piece (a row may read a slot before a later row writes it):
    it is never marked for cutting, while a piece writing other slots is."""
    from snail_common.circuit.plan import AndPlan
    from snail_common.gc.native.program import _rows_independent

    n = 2048
    apart = AndPlan(slice(2 * n, 3 * n, 1), slice(0, n, 1), slice(n, 2 * n, 1), 0, n, True)
    reads_own = AndPlan(slice(n, 2 * n, 1), slice(0, n, 1), np.arange(n, 2 * n)[::-1].copy(),
                        0, n, True)
    assert _rows_independent(apart, 3 * n)
    assert not _rows_independent(reads_own, 3 * n)
    assert _rows_independent(reads_own._replace(direct=False), 3 * n)
