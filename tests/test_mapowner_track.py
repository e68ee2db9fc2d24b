"""Map-owner tracking through four real daemons: the map owner's OT runs with the
garble-ahead, so a session garbled ahead serves whichever frame comes (none is cancelled
for belonging to an earlier frame), frames overlap, and every garbled pose equals the
cleartext circuit's bit for bit. The map owner hands each session's pad correction out
once (snail_mapd/pads.py)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from snail_bench.track import OwnerFeed, _tracker
from snail_client.localize import Options
from snail_common.net.errors import ProtocolError
from snail_mapd.pads import SessionPads
from snail_sim.sequences import handheld

FRAMES = 6
OPTIONS = Options(mode="sil", solve="circuit", runs_per_frame=1)


@pytest.fixture(scope="module")
def walk():
    return handheld(np.random.default_rng(11), 6, FRAMES, map_points=300)


def _track(walk, tmp_path: Path, backend: str, in_flight: int) -> tuple[list, dict]:
    """Every frame's record, and what the servers and the device counted."""
    options = dataclasses.replace(OPTIONS, backend=backend, in_flight=in_flight)
    tmp_path.mkdir()
    with _tracker(options, walk, True, tmp_path) as tracker:
        records = [out for out, _ in tracker.run(OwnerFeed(walk, None).items())]
        counts = {}
        if backend == "garbled":
            runner = tracker.backend.secure
            counts = {"evaluator": runner.health("evaluator")["sessions"],
                      "depth": runner.async_runner.ahead.ahead,
                      "used": runner.async_runner.owner.used}
    return records, counts


def _poses(records: list) -> list:
    return [(r["rvec"], r["tvec"]) for r in records]


@pytest.mark.parametrize("in_flight", [1, 2])
def test_map_owner_tracking_is_the_cleartext_circuit_and_wastes_no_session(
        walk, tmp_path, in_flight):
    garbled, counts = _track(walk, tmp_path / "g", "garbled", in_flight)
    clear, _ = _track(walk, tmp_path / "c", "cleartext", in_flight)
    assert [r["runs"] for r in garbled] == [20, 2, 2] + [1] * (FRAMES - 3)  # warm-up
    assert all(r["setting"] == "map-owner" for r in garbled)
    assert _poses(garbled) == _poses(clear)
    runs = 20 + 2 + 2 + FRAMES - 3
    assert counts["used"] == runs  # one pad correction a run, padding runs included
    sessions = counts["evaluator"]  # as the stream ends, before the runner closes
    assert sessions["done"] == runs
    # none was given up: a session garbled ahead of a frame change served the next
    # frame (only the pool's last ones are still reserved)
    assert sessions["failed"] == 0 and sessions["reserved"] <= counts["depth"] + 1


def test_a_session_s_correction_is_given_once_and_forgotten_in_order():
    pads = SessionPads(limit=2)
    bits = [np.full(96, i % 2, np.uint8) for i in range(3)]
    for i, b in enumerate(bits):
        pads.add(bytes([i]) * 16, b)
    assert len(pads) == 2  # the oldest went first
    with pytest.raises(ProtocolError, match="field 'sid': no session"):
        pads.take(bytes([0]) * 16)
    assert np.array_equal(pads.take(bytes([1]) * 16), bits[1])
    with pytest.raises(ProtocolError, match=r"field 'sid': .* given already"):
        pads.take(bytes([1]) * 16)  # a second frame for one session would reveal pads
