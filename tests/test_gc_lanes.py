"""Lanes: L runs of one schedule garbled or evaluated in one pass, each lane exactly the
single run it stands for (same stream bytes, same decoded outputs as the cleartext)."""

import numpy as np
import pytest
from shared_paths import BRISTOL

from snail_common.circuit import evaluate_bits, registry, schedule_circuit
from snail_common.circuit.bristol import load_bristol
from snail_common.gc import (
    Evaluator,
    Garbler,
    StreamError,
    active_input_labels,
    decode_output_labels,
    fresh_delta,
    fresh_seed,
)
from snail_common.gc import engine as gc_engine
from snail_common.gc.lanes import LaneEvaluator, LaneGarbler
from snail_common.gc.native.build import NativeUnavailable


def schedules():
    yield "ops/fmul-x4", registry.compiled("ops/fmul-x4")[1]
    adder = BRISTOL / "adder64.txt"
    if adder.exists():
        yield "adder64", schedule_circuit(load_bristol(adder))


def secrets_for(lanes: int):
    rng = np.random.default_rng(lanes)
    return ([fresh_seed() for _ in range(lanes)], [fresh_delta() for _ in range(lanes)],
            [rng.bytes(16) for _ in range(lanes)])


def chunks(data: bytes, rng: np.random.Generator):
    """``data`` cut at random points, as socket reads would cut it."""
    cuts = np.sort(rng.integers(0, len(data) + 1, rng.integers(0, 6)))
    return [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)])]


@pytest.mark.parametrize("name,schedule", list(schedules()))
@pytest.mark.parametrize("lanes", [1, 3])
def test_each_lane_streams_what_a_single_garbler_would(name, schedule, lanes):
    seeds, deltas, keys = secrets_for(lanes)
    lane = LaneGarbler(schedule, seeds, deltas, keys, block_gates=64, frame_bytes=4096)
    streams = [b"".join(parts) for parts in zip(*lane.frames())]
    for k in range(lanes):
        single = Garbler(schedule, seeds[k], deltas[k], keys[k], block_gates=64,
                         frame_bytes=4096)
        assert streams[k] == b"".join(single.frames())
        np.testing.assert_array_equal(lane.output_zero_labels[k], single.output_zero_labels)


@pytest.mark.parametrize("name,schedule", list(schedules()))
def test_lanes_with_different_inputs_each_decode_to_their_own_cleartext(name, schedule):
    lanes = 4
    rng = np.random.default_rng(5)
    seeds, deltas, keys = secrets_for(lanes)
    bits = rng.random((lanes, schedule.n_inputs)) < 0.5
    want = evaluate_bits(schedule, bits)
    garblers = [Garbler(schedule, s, d, k, block_gates=128) for s, d, k in
                zip(seeds, deltas, keys)]
    streams = [b"".join(g.frames()) for g in garblers]
    ev = LaneEvaluator(schedule, [active_input_labels(s, d, b)
                                  for s, d, b in zip(seeds, deltas, bits)])
    pieces = [chunks(stream, rng) for stream in streams]
    while any(pieces):  # lanes arrive interleaved and unevenly cut
        for lane in rng.permutation(lanes):
            if pieces[lane]:
                ev.feed(int(lane), pieces[lane].pop(0))
    assert ev.done
    for k in range(lanes):
        got = decode_output_labels(deltas[k], garblers[k].output_zero_labels,
                                   ev.output_labels(k))
        np.testing.assert_array_equal(got, want[k])
    # and a lane-garbled stream is read by the single-run evaluator
    lane = LaneGarbler(schedule, seeds, deltas, keys)
    parts = list(lane.frames())
    for k in range(lanes):
        single = Evaluator(schedule, active_input_labels(seeds[k], deltas[k], bits[k]))
        for frame in parts:
            single.feed(frame[k])
        got = decode_output_labels(deltas[k], lane.output_zero_labels[k],
                                   single.output_labels())
        np.testing.assert_array_equal(got, want[k])


def test_lanes_must_share_a_block_size_and_end_with_their_stream():
    _, schedule = registry.compiled("ops/fmul-x4")
    seeds, deltas, keys = secrets_for(2)
    inputs = [active_input_labels(s, d, np.zeros(schedule.n_inputs, bool))
              for s, d in zip(seeds, deltas)]
    streams = [b"".join(Garbler(schedule, s, d, k, block_gates=b).frames())
               for s, d, k, b in zip(seeds, deltas, keys, (64, 128))]
    ev = LaneEvaluator(schedule, inputs)
    ev.feed(0, streams[0])
    with pytest.raises(StreamError, match="block size"):
        ev.feed(1, streams[1])
    same = [b"".join(Garbler(schedule, s, d, k, block_gates=64).frames())
            for s, d, k in zip(seeds, deltas, keys)]
    ev = LaneEvaluator(schedule, inputs)
    ev.feed(0, same[0])
    with pytest.raises(StreamError, match="trailing"):
        ev.feed(1, same[1] + b"x")


def test_a_dropped_lane_never_holds_up_the_others():
    """A session that fails mid-stream is dropped: the other lanes finish, exactly."""
    _, schedule = registry.compiled("ops/fmul-x4")
    lanes = 3
    rng = np.random.default_rng(9)
    seeds, deltas, keys = secrets_for(lanes)
    bits = rng.random((lanes, schedule.n_inputs)) < 0.5
    garblers = [Garbler(schedule, s, d, k, block_gates=64) for s, d, k in
                zip(seeds, deltas, keys)]
    streams = [b"".join(g.frames()) for g in garblers]
    for cut in (0, 10, len(streams[1]) // 2):  # before, inside and after the header
        ev = LaneEvaluator(schedule, [active_input_labels(s, d, b)
                                      for s, d, b in zip(seeds, deltas, bits)])
        ev.feed(1, streams[1][:cut])
        ev.feed(0, streams[0])
        ev.drop(1)
        ev.feed(1, b"late bytes are ignored")
        ev.feed(2, streams[2])
        assert ev.done
        want = evaluate_bits(schedule, bits)
        for k in (0, 2):
            got = decode_output_labels(deltas[k], garblers[k].output_zero_labels,
                                       ev.output_labels(k))
            np.testing.assert_array_equal(got, want[k])


def _engine(name: str):
    """``name`` as a test parameter, skipped with the reason where it cannot run."""
    try:
        gc_engine.resolve(name)
    except NativeUnavailable as exc:  # pragma: no cover - where no compiler or AES-NI
        return pytest.param(name, marks=pytest.mark.skip(reason=f"{name}: {exc}"))
    return name


@pytest.mark.parametrize("engine", [_engine(e) for e in gc_engine.ENGINES])
def test_lane_frames_are_uncopied_views_that_later_frames_never_overwrite(engine):
    """Each lane's table frame is a byte view of an array of its own (no copy on its way
    to TLS), and frames kept while the next ones are garbled keep their bytes."""
    _, schedule = registry.compiled("ops/fmul-x4")
    seeds, deltas, keys = secrets_for(2)

    def lane_garbler():
        return LaneGarbler(schedule, seeds, deltas, keys, block_gates=64, frame_bytes=4096,
                           engine=engine)

    kept = list(lane_garbler().frames())
    one_by_one = [[bytes(part) for part in parts] for parts in lane_garbler().frames()]
    tables = [part for parts in kept[1:] for part in parts]
    assert len(kept) > 3
    assert all(isinstance(f, memoryview) and f.format == "B" for f in tables)
    assert len({id(f.obj) for f in tables}) == len(tables)
    assert [[bytes(part) for part in parts] for parts in kept] == one_by_one
