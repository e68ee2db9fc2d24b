"""The map-owner iteration circuit: the map points enter as two XOR shares (the device's
xyz ^ P and the map owner's P, its last input group), and the circuit's outputs are the
plain SIL circuit's bit for bit on xyz."""

from __future__ import annotations

import secrets

import numpy as np
import pytest
from test_loc_circuits import random_values

from snail_common.circuit import registry
from snail_common.circuit.cleartext import evaluate
from snail_common.circuit.schedule import schedule_circuit
from snail_common.families import register_all
from snail_common.pnp.spec import MASKED, OWNER_PAD, Spec, build, owner_bits, run_mirror

N = 5


@pytest.fixture(scope="module")
def circuits():
    plain, owner = Spec("lm", "sil", "ldlt", N), Spec("lm", "sil", "ldlt", N, owner=True)
    return {spec: (c := build(spec), schedule_circuit(c)) for spec in (plain, owner)}


def shares(values: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The owner circuit's inputs: world split into device and map-owner shares."""
    bits = np.asarray(values["world"], np.float32).view(np.uint32)
    pad = np.frombuffer(secrets.token_bytes(bits.nbytes), np.uint32).reshape(bits.shape)
    out = {k: v for k, v in values.items() if k != "world"}
    return {**out, MASKED: bits ^ pad, OWNER_PAD: pad}


def test_the_shares_give_the_plain_circuits_outputs_bit_for_bit(circuits):
    (plain, (pc, ps)), (owner, (oc, os_)) = circuits.items()
    rng = np.random.default_rng(3)
    for _ in range(8):
        values = random_values(plain, rng)
        want = evaluate(pc, values, ps)
        got = evaluate(oc, shares(values), os_)
        mirror = run_mirror(owner, shares(values))
        for name in want:
            assert np.array_equal(np.asarray(got[name], np.float32).view(np.uint32),
                                  np.asarray(want[name], np.float32).view(np.uint32))
            assert np.array_equal(mirror[name].view(np.uint32),
                                  np.asarray(want[name], np.float32).view(np.uint32))


def test_the_pad_is_free_and_the_map_owners_wires_come_last(circuits):
    (pc, _), (oc, _) = circuits.values()
    assert oc.counts()["and"] == pc.counts()["and"]  # XOR shares cost no AND gate
    assert oc.inputs[-1].name == OWNER_PAD and owner_bits(oc) == 96 * N
    assert owner_bits(pc) == 0
    assert oc.n_inputs == pc.n_inputs + 96 * N


def test_ids_and_registration():
    spec = Spec.parse("lm-sil-ldlt-n6-mo")
    assert spec.owner and spec.circuit_id == "lm-sil-ldlt-n6-mo"
    assert Spec.parse("gn-sil-svd-n8-mo").owner
    with pytest.raises(ValueError):
        Spec("lm", "sil", "client", 6, owner=True)  # J^T J would reveal the map
    with pytest.raises(ValueError):
        Spec("lm", "do", "ldlt", 6, owner=True)
    register_all()
    iface = registry.interface("loc/lm-sil-ldlt-n4-mo")
    assert owner_bits(iface) == 96 * 4
    with pytest.raises(registry.UnknownCircuit):
        registry.interface("loc/ne-sil-n4-mo")
