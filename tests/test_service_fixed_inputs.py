"""A frame's fixed inputs: their labels go to the evaluator with each prepared session,
so an invocation sends only the pose's. Results stay the cleartext circuit's; a session
prepared for other fixed bits is never given a second label for a wire; padding runs
keep the frame's bits, so the servers see them as they see real runs."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from snail_client.localize import GarbledBackend
from snail_client.secure import AsyncSecureRunner
from snail_client.sessions import FixedInputs, Invocation
from snail_common.circuit import evaluate_bits, registry
from snail_common.loc.backends import frame_inputs, frame_wires, interface, shared_bits, sil_values
from snail_common.loc.types import Normalized, Pose
from snail_common.net.chunks import LabelAssembler, runs
from snail_common.net.errors import ProtocolError
from snail_common.net.messages import LABEL_BYTES
from snail_common.pnp.spec import Spec
from tests.daemons import daemons_with

CIRCUIT = "ops/fmul-x4"


def _chunk(start: int, labels: np.ndarray, total: int) -> dict:
    return {"start": start, "total": total, "labels": labels.tobytes()}


def test_chunks_assemble_in_any_order_but_each_label_once():
    labels = np.arange(20, dtype=np.uint64).reshape(10, 2)
    asm = LabelAssembler("input_labels", 10)
    asm.add(_chunk(6, labels[6:], 10))
    asm.add(_chunk(0, labels[:2], 10))
    assert not asm.complete
    asm.add(_chunk(2, labels[2:6], 10))
    np.testing.assert_array_equal(asm.labels(), labels)
    for start, part, why in ((4, labels[4:7], "overlap"), (10, labels[:1], "'start'"),
                             (8, labels[:3], "'labels'")):
        again = LabelAssembler("input_labels", 10)
        again.add(_chunk(4, labels[4:6], 10))
        with pytest.raises(ProtocolError, match=why):
            again.add(_chunk(start, part, 10))


def test_runs_are_the_true_stretches():
    mask = np.array([1, 1, 0, 1, 0, 0, 1, 1, 1], bool)
    assert runs(mask) == [(0, 2), (3, 4), (6, 9)]
    assert runs(np.zeros(3, bool)) == [] and runs(np.ones(2, bool)) == [(0, 2)]


@pytest.fixture(scope="module")
def services(tmp_path_factory):
    yield from daemons_with(tmp_path_factory)


def _bits_with(fixed: FixedInputs, rng: np.random.Generator) -> np.ndarray:
    """Random input bits that keep ``fixed``'s bits where its mask says so."""
    bits = rng.random(fixed.mask.size) < 0.5
    bits[fixed.mask] = fixed.bits[fixed.mask]
    return bits


def _cleartext(bits: np.ndarray) -> np.ndarray:
    _, schedule = registry.compiled(CIRCUIT)
    return evaluate_bits(schedule, bits[None])[0]


def test_fixed_labels_go_ahead_and_results_stay_the_circuits(services):
    _, schedule = registry.compiled(CIRCUIT)
    n = schedule.n_inputs
    rng = np.random.default_rng(3)
    mask = np.zeros(n, bool)
    mask[n // 4:] = True  # the pose is the first quarter, as in the SIL circuits
    fixed = FixedInputs(mask, (rng.random(n) < 0.5) & mask)

    async def scenario():
        async with AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                                     services.tls_dir, timeout=60, ahead=2) as r:
            first = _bits_with(fixed, rng)
            plain = await r.invoke(CIRCUIT, first)  # nothing prepared yet: all labels
            r.expect(CIRCUIT, 4, fixed)
            await asyncio.sleep(0.5)
            runs_ = [(bits, await r.invoke(CIRCUIT, bits))
                     for bits in [_bits_with(fixed, rng) for _ in range(3)]]
            other = rng.random(n) < 0.5  # not the frame's bits: a fresh session
            runs_.append((other, await r.invoke(CIRCUIT, other)))
            return (first, plain), runs_

    (first, plain), runs_ = asyncio.run(scenario())
    np.testing.assert_array_equal(plain.outputs, _cleartext(first))
    for bits, inv in runs_:
        np.testing.assert_array_equal(inv.outputs, _cleartext(bits))
    pose_labels = (n // 4) * LABEL_BYTES
    for _, inv in runs_[:3]:  # only the pose's labels on the round trip
        assert pose_labels <= inv.labels_on_call < pose_labels + 200
        assert inv.labels_on_call < plain.labels_on_call / 2
    assert runs_[3][1].labels_on_call >= (n + 2) * LABEL_BYTES  # all, in a fresh session


def test_sessions_kept_between_frames_take_the_next_frames_labels(services):
    """In a sequence, the sessions garbled after a frame's last invocation get the next
    frame's fixed labels when it is declared, not before: the evaluator assembles each
    label vector from two sends far apart, and the results stay the circuit's."""
    _, schedule = registry.compiled(CIRCUIT)
    n = schedule.n_inputs
    rng = np.random.default_rng(8)
    mask = np.zeros(n, bool)
    mask[n // 4:] = True
    frames = [FixedInputs(mask, (rng.random(n) < 0.5) & mask) for _ in range(3)]

    async def scenario():
        async with AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                                     services.tls_dir, timeout=60, ahead=2) as r:
            results = []
            for number, fixed in enumerate(frames):
                r.expect(CIRCUIT, 3, fixed)
                if number == 2:  # what the second frame left garbled, now with labels
                    kept = list(r.ahead._prepared[CIRCUIT])
                for _ in range(3):
                    bits = _bits_with(fixed, rng)
                    results.append((bits, await r.invoke(CIRCUIT, bits)))
                await asyncio.sleep(0.3)
            return results, kept, frames[2]

    results, kept, last = asyncio.run(scenario())
    for bits, inv in results:
        np.testing.assert_array_equal(inv.outputs, _cleartext(bits))
    assert len(kept) == 2 and all(s.fixed is last for s in kept)
    pose_labels = (n // 4) * LABEL_BYTES
    for _, inv in results[6:]:  # the kept ones sent only the pose's on the round trip
        assert pose_labels <= inv.labels_on_call < pose_labels + 200


class _Recorder:
    """A secure runner that records what the backend asks of it."""

    def __init__(self, n_outputs: int) -> None:
        self.declared, self.runs, self.n_outputs = {}, [], n_outputs

    def expect(self, circuit_id: str, count: int, fixed: FixedInputs | None = None) -> None:
        self.declared[circuit_id] = fixed

    def fixed(self, circuit_id: str) -> FixedInputs | None:
        return self.declared.get(circuit_id)

    def invoke(self, circuit_id: str, bits: np.ndarray, frame: bytes | None = None
               ) -> Invocation:
        self.runs.append(bits)
        return Invocation(np.zeros(self.n_outputs, bool), {}, 0.0)


def test_a_frames_inputs_but_the_pose_are_fixed_and_padding_keeps_them():
    spec = Spec("lm", "sil", "client", 4, arith="fixed")
    iface = interface(spec)
    rng = np.random.default_rng(5)
    nrm = Normalized(image=rng.normal(size=(4, 2)), world=rng.normal(size=(4, 3)),
                     weights=np.ones(4), axis_weights=np.ones(2))
    values = sil_values(spec, nrm, Pose(np.eye(3), np.array([0, 0, 3.0])), 0.0)
    frame = frame_inputs(spec, nrm)
    assert set(values) - set(frame) == {"R", "t"}
    mask, bits = shared_bits(iface, frame)
    np.testing.assert_array_equal(mask, frame_wires(iface))
    assert mask[:12 * 32].sum() == 0 and mask[12 * 32:].all()  # R and t lead
    recorder = _Recorder(iface.n_outputs)
    backend = GarbledBackend(recorder)
    backend.expect(spec, 20, frame)
    np.testing.assert_array_equal(recorder.fixed(spec.registry_id).bits, bits)
    backend.pad(spec, 3)
    assert len(recorder.runs) == 3
    for run in recorder.runs:
        np.testing.assert_array_equal(run[mask], bits[mask])
    poses = np.array([run[~mask] for run in recorder.runs])
    assert 0.3 < poses.mean() < 0.7 and not (poses[0] == poses[1]).all()  # random poses
