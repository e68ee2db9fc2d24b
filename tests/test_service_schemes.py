"""The garbling scheme is chosen per session by the client: three-halves sessions run over
the daemons equal to cleartext with about 0.77x the garbler -> evaluator bytes of
half-gates; lanes batch half-gates sessions only; both halves must agree on the scheme."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys

import numpy as np
import pytest
from daemons import daemons_with
from shared_paths import EXAMPLES

from snail_client.blocking import SecureRunner
from snail_client.secure import AsyncSecureRunner
from snail_common.circuit import evaluate_bits, registry
from snail_common.gc import Evaluator, Garbler, StreamError, active_input_labels, fresh_delta
from snail_common.gc.stream import SCHEME_HALF_GATES

CIRCUIT = "ops/fmul-x64"


@pytest.fixture(scope="module")
def services(tmp_path_factory):
    yield from daemons_with(tmp_path_factory, "--lane-window-ms", "300")


@pytest.fixture(scope="module")
def case():
    _, schedule = registry.compiled(CIRCUIT)
    bits = np.random.default_rng(4).random((4, schedule.n_inputs)) < 0.5
    return schedule, bits, evaluate_bits(schedule, bits)


def test_three_halves_over_the_daemons_equals_cleartext_in_fewer_bytes(services, case):
    _, bits, want = case
    sent = {}
    for scheme in ("halfgates", "threehalves"):
        with SecureRunner(services.garbler_addr, services.evaluator_addr, services.tls_dir,
                          scheme=scheme) as runner:
            for row, expected in zip(bits[:2], want[:2]):
                np.testing.assert_array_equal(runner.run(CIRCUIT, row), expected)
            sent[scheme] = runner.last.traffic["garbler_to_evaluator"]
    ratio = sent["threehalves"] / sent["halfgates"]
    assert 0.765 < ratio < 0.775, sent  # 197 of 256 bits per AND, plus the same framing


def test_concurrent_three_halves_sessions_run_alone_and_correct(services, case):
    _, bits, want = case

    async def client(row):
        async with AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                                     services.tls_dir, scheme="threehalves") as r:
            return await r.invoke(CIRCUIT, row)

    async def fleet():
        return await asyncio.gather(*(client(row) for row in bits))

    for inv, expected in zip(asyncio.run(fleet()), want):
        np.testing.assert_array_equal(inv.outputs, expected)
        assert inv.timing["garbler_lanes"] == inv.timing["evaluator_lanes"] == 1


def test_an_unknown_scheme_is_refused_by_the_client(services):
    with pytest.raises(ValueError, match="scheme"):
        SecureRunner(services.garbler_addr, services.evaluator_addr, services.tls_dir,
                     scheme="fourthirds")


def test_a_stream_in_another_scheme_than_agreed_is_refused(case):
    schedule, bits, _ = case
    seed, delta = bytes(16), fresh_delta()
    stream = b"".join(Garbler(schedule, seed, delta, scheme="threehalves").frames())
    ev = Evaluator(schedule, active_input_labels(seed, delta, bits[0]), SCHEME_HALF_GATES)
    with pytest.raises(StreamError, match="scheme"):
        ev.feed(stream)


def test_localize_with_three_halves_equals_cleartext():
    def localize(*args: str) -> dict:
        proc = subprocess.run([sys.executable, "-m", "snail_client", "localize", "--input",
                               str(EXAMPLES / "synthetic_n6.json"), "--min-invocations", "1",
                               "--json", *args], capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr
        return json.loads(proc.stdout)

    garbled = localize("--scheme", "threehalves")
    clear = localize("--backend", "cleartext")
    assert garbled["scheme"] == "threehalves" and "scheme" not in clear
    for key in ("rvec", "tvec", "iterations", "cost", "status"):
        assert garbled[key] == clear[key], key
