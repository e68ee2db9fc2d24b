"""Garbling engine benchmark: the numbers of DESIGN.md section 5, measured on this machine.

- AES: blocks/s of one batched ECB call, the hash's raw material;
- garble / evaluate: AND gates/s on a wide circuit (independent AND layers of 32 Ki gates
  with XOR logic between them), in one process: garbling as a stream whose frames are
  dropped once taken, evaluation from tables held in memory;
- step overhead: time per schedule step on a deep narrow circuit (4 gates per step), the
  slower of garbler and evaluator (they run in parallel in a real run);
- plan: one-time preparation of a schedule for the engine (cached per schedule).
Rates are the best of a few runs (the first pays for page faults and cold caches).
- end to end: garbler and evaluator in two processes over loopback TCP, frame by frame, so
  evaluation of frame k overlaps garbling of frame k+1; the result is decoded and checked;
- bytes per AND: the garbler -> evaluator stream of the wide circuit (header excluded);
- TLS, the seal and sockets: bytes per CPU second of the daemons' TLS path (encrypting
  into and decrypting from memory BIOs), of the table link's aead seal and of loopback
  TCP (transport.py): with the AND rates, the CPU floor of a table stream on this host.
Each scheme asked for is measured on the same circuits; the first one's numbers are the
report's top-level fields (with its ``scheme``), every scheme's are under ``schemes``, and
with both, ``bytes_ratio`` is three-halves' stream over half-gates'.

Each engine asked for (default: the native kernel where it can run, and numpy) is measured
the same way in the same run, its report under ``engines`` with its ``engine``; the
top-level fields are those of the engine the daemons would serve with (``serving``).
The native kernel cuts wide steps across ``kernel_threads`` threads (the report says how
many: with 2, its figures use both cores of this machine); numpy runs on one.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import queue
import socket
import struct
import threading
import time

import numpy as np

from snail_common.circuit import CircuitBuilder, run_schedule, schedule_circuit
from snail_common.circuit.plan import plan_for
from snail_common.circuit.schedule import Schedule
from snail_common.circuit.values import pack_lanes, unpack_lanes
from snail_common.gc import (
    Evaluator,
    Garbler,
    active_input_labels,
    decode_output_labels,
    fresh_delta,
    fresh_seed,
)
from snail_common.gc import engine as engines
from snail_common.gc.aes import AesBatch, byte_view
from snail_common.gc.native.run import THREADS_ENV, kernel_threads, program_for
from snail_common.gc.stream import BLOCK_GATES, DEFAULT_SCHEME, HEADER, SCHEMES

from .transport import seal_rates, socket_rate, tls_rates

WIDE_LANES = 1 << 15  # AND steps of 32 Ki and 64 Ki gates
WIDE_LAYERS = 192  # 6.3 M AND gates
DEEP_LANES = 4
DEEP_LAYERS = 1500
_LEN = struct.Struct("<I")



def available_engines() -> tuple[str, ...]:
    """The engines that can run here, the native kernel first."""
    try:
        engines.resolve("native")
    except engines.NativeUnavailable:
        return ("numpy",)
    return engines.ENGINES


def engine_report(wide_layers: int = WIDE_LAYERS, deep_layers: int = DEEP_LAYERS,
                  schemes: tuple[str, ...] = tuple(SCHEMES),
                  engine_names: tuple[str, ...] | None = None,
                  threads: int | None = None) -> dict:
    """Measure AES, garble, evaluate, per-step overhead, end-to-end rates and stream bytes
    per AND of each scheme on each engine (one run); ``schemes`` is any iterable of names
    (SCHEMES itself: every scheme); the native kernel on ``threads`` threads
    (``kernel_threads``). ValueError for an unknown scheme or engine;
    NativeUnavailable when the native kernel is asked for and cannot run."""
    threads = kernel_threads(threads)
    was = os.environ.get(THREADS_ENV)
    os.environ[THREADS_ENV] = str(threads)  # every run below, and the forked processes
    try:
        report = _engine_report(wide_layers, deep_layers, tuple(schemes), engine_names)
    finally:
        if was is None:
            del os.environ[THREADS_ENV]
        else:
            os.environ[THREADS_ENV] = was
    report["engine"]["kernel_threads"] = threads
    return report


def _engine_report(wide_layers: int, deep_layers: int, schemes: tuple[str, ...],
                   engine_names: tuple[str, ...] | None) -> dict:
    schemes = tuple(schemes)
    if not schemes or any(s not in SCHEMES for s in schemes):
        raise ValueError(f"schemes must be some of {', '.join(SCHEMES)}, got {schemes}")
    names = tuple(dict.fromkeys(engine_names or available_engines()))
    if any(e not in engines.ENGINES for e in names):
        raise ValueError(f"engines must be some of {', '.join(engines.ENGINES)}, got {names}")
    for name in names:
        engines.resolve(name)  # raises where it cannot run
    load = os.getloadavg()[0]  # other work on the machine: context for every rate below
    wide = schedule_circuit(_layered_circuit(WIDE_LANES, wide_layers))
    deep = schedule_circuit(_layered_circuit(DEEP_LANES, deep_layers))
    t0 = time.perf_counter()
    plan_for(wide)
    plan_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    program_for(wide, BLOCK_GATES)
    program_s = time.perf_counter() - t0
    per_engine = {}
    for name in names:
        per_scheme = {s: _scheme_report(wide, deep, s, name) for s in schemes}
        entry = {"engine": name, "scheme": schemes[0], **per_scheme[schemes[0]],
                 "schemes": per_scheme}
        if len(per_scheme) == len(SCHEMES):
            entry["bytes_ratio"] = round(per_scheme["threehalves"]["stream_bytes"]
                                         / per_scheme[DEFAULT_SCHEME]["stream_bytes"], 4)
        per_engine[name] = entry
    serving = engines.engine_status()
    top = serving["engine"] if serving["engine"] in per_engine else names[0]
    encrypt, decrypt = tls_rates()
    seal, open_ = seal_rates()
    report = {**per_engine[top], "serving": serving["engine"],
              "aes_blocks_per_s": round(_aes_rate()),
              "tls_encrypt_bytes_per_s": round(encrypt),
              "tls_decrypt_bytes_per_s": round(decrypt),
              "table_seal_bytes_per_s": round(seal),
              "table_open_bytes_per_s": round(open_),
              "socket_bytes_per_s": round(socket_rate())}
    if "reason" in serving:
        report["native_unavailable"] = serving["reason"]
    report.update({
        "plan_s": round(plan_s, 3),
        "program_s": round(program_s, 3),
        "wide_and": wide.n_and,
        "wide_steps": wide.n_steps,
        "deep_steps": deep.n_steps,
        "cpus": os.cpu_count(),
        "load_avg_1m": round(load, 2),
        "engines": per_engine,
    })
    return {"engine": report}


def _scheme_report(wide: Schedule, deep: Schedule, scheme: str, engine: str) -> dict:
    """One scheme's rates on the wide and deep circuits, and its stream size."""
    # best of a few runs: the first pays for page faults and cold caches
    garble_s, evaluate_s = _best(_time_in_process(wide, scheme, engine) for _ in range(2))
    deep_garble_s, deep_evaluate_s = _best(_time_in_process(deep, scheme, engine)
                                           for _ in range(3))
    e2e_s = min(_time_two_processes(wide, scheme, engine) for _ in range(2))
    stream = sum(len(f) for f in Garbler(wide, fresh_seed(), fresh_delta(), scheme=scheme,
                                         engine=engine).frames()) - HEADER.size
    return {
        "garble_and_per_s": round(wide.n_and / garble_s),
        "evaluate_and_per_s": round(wide.n_and / evaluate_s),
        "step_overhead_us": round(1e6 * max(deep_garble_s, deep_evaluate_s) / deep.n_steps, 2),
        "end_to_end_and_per_s": round(wide.n_and / e2e_s),
        "garble_step_us": round(1e6 * deep_garble_s / deep.n_steps, 2),
        "evaluate_step_us": round(1e6 * deep_evaluate_s / deep.n_steps, 2),
        "bytes_per_and": round(stream / wide.n_and, 3),
        "stream_bytes": stream,
    }


def _best(runs) -> tuple[float, ...]:
    """Element-wise minimum of timing tuples."""
    return tuple(float(v) for v in np.min(list(runs), axis=0))


def _aes_rate(blocks: int = 1 << 16, seconds: float = 0.3) -> float:
    aes = AesBatch(os.urandom(16))
    src = np.zeros((blocks, 2), np.uint64)
    dst = np.zeros((blocks + 1, 2), np.uint64)
    sv, dv = byte_view(src), byte_view(dst)
    aes.encrypt_into(sv, dv)
    n, t0 = 0, time.perf_counter()
    while (elapsed := time.perf_counter() - t0) < seconds:
        aes.encrypt_into(sv, dv)
        n += blocks
    return n / elapsed


def _layered_circuit(lanes: int, layers: int):
    """``lanes`` independent chains of ``layers`` AND gates with XOR/NOT logic in between:
    every AND step is ``lanes`` wide (or 2x when two layers' ANDs share a depth)."""
    b = CircuitBuilder()
    x = b.input("x", (lanes, 4), 1)[..., 0]
    acc = x[:, 0]
    for i in range(1, layers + 1):
        u = b.xor(acc, x[:, i % 4])
        v = b.not_(b.xor(acc, x[:, (i + 1) % 4]))
        acc = b.and_(u, v)
        if i % 3 == 0:  # a second operand pattern, so lanes are not all alike
            acc = b.xor(acc, x[:, (i + 2) % 4])
    b.output("y", acc[:, None])
    return b.build()


def _inputs(schedule: Schedule, seed: int = 1) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 2, schedule.n_inputs).astype(bool)


def _cleartext(schedule: Schedule, bits: np.ndarray) -> np.ndarray:
    return unpack_lanes(run_schedule(schedule, pack_lanes(bits[:, None])), 1)[:, 0]


def _time_in_process(schedule: Schedule, scheme: str, engine: str) -> tuple[float, float]:
    """(garble seconds, evaluate seconds) in one process; checks the result.

    Garbling is timed as a stream (each frame dropped once taken, as a sender does), then
    the same run (same seed, offset and key) is garbled again into memory for the
    evaluator, whose time excludes producing its input."""
    bits = _inputs(schedule)
    seed, delta, key = fresh_seed(), fresh_delta(), os.urandom(16)
    t0 = time.perf_counter()
    for _ in Garbler(schedule, seed, delta, key, scheme=scheme, engine=engine).frames():
        pass
    garble_s = time.perf_counter() - t0
    garbler = Garbler(schedule, seed, delta, key, scheme=scheme, engine=engine)
    frames = list(garbler.frames())
    ev = Evaluator(schedule, active_input_labels(seed, delta, bits), engine=engine)
    t0 = time.perf_counter()
    for f in frames:
        ev.feed(f)
    evaluate_s = time.perf_counter() - t0
    out = decode_output_labels(delta, garbler.output_zero_labels, ev.output_labels())
    if not np.array_equal(out, _cleartext(schedule, bits)):
        raise AssertionError("garbled run disagrees with the cleartext evaluation")
    return garble_s, evaluate_s


def _recv_exact(conn: socket.socket, view: memoryview) -> None:
    while view:
        n = conn.recv_into(view)
        if not n:
            raise ConnectionError("peer closed the connection mid-frame")
        view = view[n:]


def _sender(conn: socket.socket, frames: queue.Queue) -> None:
    """Send queued frames, length-prefixed; None ends the stream. Runs in its own thread so
    the kernel's copies overlap garbling (sendall releases the GIL)."""
    while (frame := frames.get()) is not None:
        conn.sendall(_LEN.pack(len(frame)))
        conn.sendall(frame)
    conn.sendall(_LEN.pack(0))


def _receiver(conn: socket.socket, frames: queue.Queue) -> None:
    """Receive length-prefixed frames into fresh buffers until the empty frame."""
    head = bytearray(_LEN.size)
    while True:
        _recv_exact(conn, memoryview(head))
        (size,) = _LEN.unpack(head)
        if not size:
            break
        frame = bytearray(size)
        _recv_exact(conn, memoryview(frame))
        frames.put(frame)
    frames.put(None)


def _garbler_proc(schedule, seed, delta, port, results, scheme, engine) -> None:
    garbler = Garbler(schedule, seed, delta, scheme=scheme, engine=engine)
    with socket.create_connection(("127.0.0.1", port)) as conn:
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        frames: queue.Queue = queue.Queue(maxsize=4)
        sender = threading.Thread(target=_sender, args=(conn, frames))
        results.put(("start", time.monotonic()))
        sender.start()
        for frame in garbler.frames():
            frames.put(frame)
        frames.put(None)
        sender.join()
    results.put(("zero", garbler.output_zero_labels))


def _evaluator_proc(schedule, labels, listener, results, engine) -> None:
    ev = Evaluator(schedule, labels, engine=engine)  # before the clock starts, like the garbler
    conn, _ = listener.accept()
    with conn:
        frames: queue.Queue = queue.Queue(maxsize=8)
        receiver = threading.Thread(target=_receiver, args=(conn, frames))
        receiver.start()
        while (frame := frames.get()) is not None:
            ev.feed(frame)
        receiver.join()
        out = ev.output_labels()
    results.put(("end", time.monotonic()))
    results.put(("active", out))


def _time_two_processes(schedule: Schedule, scheme: str, engine: str) -> float:
    """Seconds from the garbler's first frame to the evaluator's last label, over TCP."""
    ctx = mp.get_context("fork")  # children share the schedule instead of pickling it
    bits = _inputs(schedule, 2)
    seed, delta = fresh_seed(), fresh_delta()
    labels = active_input_labels(seed, delta, bits)
    listener = socket.create_server(("127.0.0.1", 0))
    results = ctx.Queue()
    procs = [ctx.Process(target=_evaluator_proc,
                         args=(schedule, labels, listener, results, engine)),
             ctx.Process(target=_garbler_proc,
                         args=(schedule, seed, delta, listener.getsockname()[1], results,
                               scheme, engine))]
    for p in procs:
        p.start()
    got = dict(results.get(timeout=600) for _ in range(4))
    for p in procs:
        p.join()
    listener.close()
    out = decode_output_labels(delta, got["zero"], got["active"])
    if not np.array_equal(out, _cleartext(schedule, bits)):
        raise AssertionError("two-process garbled run disagrees with the cleartext evaluation")
    return got["end"] - got["start"]


if __name__ == "__main__":
    import json

    print(json.dumps(engine_report(), indent=1))
