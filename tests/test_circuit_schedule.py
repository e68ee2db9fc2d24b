"""Schedule invariants on random circuits: every gate once, reads after writes, no clobbering."""

import numpy as np
from circuit_oracle import direct_eval
from hypothesis import given, settings
from hypothesis import strategies as st

from snail_common.circuit import CircuitBuilder, evaluate_bits, schedule_circuit
from snail_common.circuit.ir import AND, FIRST_INPUT
from snail_common.circuit.schedule import AND_STEP, _allocate_slots, _fold


@st.composite
def random_circuits(draw):
    """Random netlists through the builder; ops draw operands from all earlier wires,
    including the constants, so folding and long XOR chains both occur."""
    n_in = draw(st.integers(1, 12))
    b = CircuitBuilder()
    wires = list(b.input("x", (), n_in, "int").ravel()) + [0, 1]
    for _ in range(draw(st.integers(1, 120))):
        op = draw(st.sampled_from(["xor", "and", "not", "mux", "or"]))
        pick = st.integers(0, len(wires) - 1)
        x, y, z = (wires[draw(pick)] for _ in range(3))
        if op == "not":
            out = b.not_(x)
        elif op == "mux":
            out = b.mux(x, y, z)
        else:
            out = getattr(b, {"xor": "xor", "and": "and_", "or": "or_"}[op])(x, y)
        wires.append(int(out))
    n_out = draw(st.integers(1, min(16, len(wires))))
    outs = [wires[draw(st.integers(0, len(wires) - 1))] for _ in range(n_out)]
    b.output("y", np.array(outs), "int")
    return b.build()


def _random_inputs(circuit, lanes=200, seed=0):
    return np.random.default_rng(seed).random((lanes, circuit.n_inputs)) < 0.5


def _check_slot_discipline(circuit, plan, slot_of):
    """Replay the schedule on wire ids held by slots: every read must find its wire."""
    held = np.full(slot_of.max() + 1, -1, np.int64)
    F = FIRST_INPUT + circuit.n_inputs
    held[:F] = np.arange(F)
    for s in range(len(plan.kind)):
        lo, hi = plan.lo[s], plan.hi[s]
        if plan.kind[s] == AND_STEP:
            reads = np.concatenate([plan.and_a[lo:hi], plan.and_b[lo:hi]])
            outs = plan.and_out[lo:hi]
        else:
            reads = plan.lin_terms[plan.lin_ptr[lo] : plan.lin_ptr[hi]]
            outs = plan.lin_out[lo:hi]
        assert np.array_equal(held[slot_of[reads]], reads), f"step {s} reads a clobbered slot"
        assert len(np.unique(slot_of[outs])) == len(outs)
        held[slot_of[outs]] = outs
    assert np.array_equal(held[slot_of[circuit.outputs]], circuit.outputs)


@settings(max_examples=150, deadline=None)
@given(random_circuits())
def test_schedule_matches_gate_by_gate_evaluation(circuit):
    circuit.validate()
    bits = _random_inputs(circuit)
    expected = direct_eval(circuit, bits)
    for reuse in (True, False):
        for max_terms in (2, 16):
            sched = schedule_circuit(circuit, reuse_slots=reuse, max_terms=max_terms)
            assert np.array_equal(evaluate_bits(sched, bits), expected)


@settings(max_examples=150, deadline=None)
@given(random_circuits())
def test_every_and_gate_scheduled_once_and_reads_follow_writes(circuit):
    plan = _fold(circuit, 4)
    and_gates = np.flatnonzero(circuit.kind == AND) + circuit.first_gate_wire
    assert np.array_equal(np.sort(plan.and_out), and_gates)
    # each AND step holds exactly one AND-depth, in increasing order
    depth = np.zeros(circuit.n_wires, np.int64)
    depth[circuit.first_gate_wire :] = circuit.and_depth
    and_steps = [s for s in range(len(plan.kind)) if plan.kind[s] == AND_STEP]
    step_depths = [np.unique(depth[plan.and_out[plan.lo[s] : plan.hi[s]]]) for s in and_steps]
    assert all(len(d) == 1 for d in step_depths)
    assert [int(d[0]) for d in step_depths] == sorted({int(d[0]) for d in step_depths})
    assert len(np.unique(plan.lin_out)) == len(plan.lin_out)
    slot_of, n_slots = _allocate_slots(circuit, plan, reuse=True)
    _check_slot_discipline(circuit, plan, slot_of)
    _, n_plain = _allocate_slots(circuit, plan, reuse=False)
    assert n_slots <= n_plain


def test_slot_reuse_bounds_memory_by_live_width():
    """A long chain of 64-wide AND layers needs ~2 layers of slots, not the whole circuit."""
    b = CircuitBuilder()
    x = b.input("x", (64,), 1, "bool")[:, 0]
    k = b.input("k", (64,), 1, "bool")[:, 0]
    for _ in range(200):
        x = b.and_(b.xor(x, k), np.roll(x, 1))
    b.output("y", x[:, None], "bool")
    circuit = b.build()
    sched = schedule_circuit(circuit)
    assert circuit.n_gates > 200 * 64
    assert sched.n_slots <= 2 + 128 + 4 * 64
    assert sched.n_steps <= 2 * circuit.depth() + 1


def test_xor_chains_fold_into_two_steps_per_and_level():
    b = CircuitBuilder()
    x = b.input("x", (), 32, "uint32")
    acc = x[0]
    for i in range(1, 32):  # 31-deep XOR chain between two AND levels
        acc = b.xor(acc, x[i])
    y = b.and_(acc, x[0])
    b.output("y", np.array([y, acc]), "int")
    sched = schedule_circuit(b.build())
    assert sched.n_steps <= 4

