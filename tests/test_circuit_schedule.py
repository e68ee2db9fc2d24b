"""Schedule invariants on random circuits: every gate once, reads after writes, no clobbering;
slot layout and the plan's strided runs on a wide circuit."""

import numpy as np
import pytest
from circuit_oracle import direct_eval
from hypothesis import given, settings
from hypothesis import strategies as st

from snail_bench.compiler import build_multipliers
from snail_common.circuit import CircuitBuilder, evaluate_bits, run_schedule, schedule_circuit
from snail_common.circuit.fold import AND_STEP, LINEAR_STEP, fold
from snail_common.circuit.ir import AND, FIRST_INPUT
from snail_common.circuit.layout import allocate_slots, order_rows
from snail_common.circuit.plan import (
    AndPlan,
    LinearGroup,
    RunGroup,
    plan_for,
)
from snail_common.circuit.runs import MIN_RUN
from snail_common.circuit.schedule import Schedule
from snail_common.circuit.slots import as_rows, part


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
            reads = plan.terms_of(s)
            outs = plan.lin_out[lo:hi]
        assert np.array_equal(held[slot_of[reads]], reads), f"step {s} reads a clobbered slot"
        assert len(np.unique(slot_of[outs])) == len(outs)
        assert not np.isin(slot_of[outs], slot_of[reads]).any(), f"step {s} writes its reads"
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
    plan = fold(circuit, 4)
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
    death = order_rows(circuit, plan)
    slot_of, n_slots = allocate_slots(circuit, plan, death, reuse=True)
    _check_slot_discipline(circuit, plan, slot_of)
    _, n_plain = allocate_slots(circuit, plan, death, reuse=False)
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


@settings(max_examples=60, deadline=None)
@given(random_circuits())
def test_linear_rows_sorted_by_term_count_and_schedule_round_trips(circuit):
    sched = schedule_circuit(circuit)
    for i, step in enumerate(sched.steps()):
        if sched.step_kind[i] == LINEAR_STEP:
            counts = np.diff(np.append(step.starts, len(step.terms)))
            assert np.all(np.diff(counts) >= 0)
    again = Schedule.from_arrays(sched.to_arrays())
    assert again.disjoint_io
    bits = _random_inputs(circuit)
    assert np.array_equal(evaluate_bits(again, bits), evaluate_bits(sched, bits))


@given(st.integers(0, 50), st.integers(1, 7), st.integers(1, 40), st.data())
def test_rows_name_the_same_slots_as_the_index_list(start, stride, n, data):
    slots = np.arange(400)
    idx = start + stride * np.arange(n)
    rows = as_rows(idx, strided=True)
    assert isinstance(rows, slice) == (stride == 1 or n == 1 or n >= 4)
    assert np.array_equal(slots[rows], idx)
    k = data.draw(st.integers(0, n - 1))
    m = data.draw(st.integers(1, n - k))
    assert np.array_equal(slots[part(rows, k, m)], idx[k : k + m])
    assert isinstance(as_rows(idx), slice) == (stride == 1 or n == 1)  # adjacent only


def test_wide_circuit_runs_entirely_on_strided_views():
    """160 multipliers side by side: every step row falls in a run, results are products."""
    circuit = build_multipliers(160)
    sched = schedule_circuit(circuit)
    plan = plan_for(sched, strided=True)
    pieces = [g for step in plan.steps
              for g in (step.groups if hasattr(step, "groups") else [step])]
    assert all(isinstance(p, (AndPlan, RunGroup)) for p in pieces)
    assert all(isinstance(p.out, slice) for p in pieces)
    rows = [len(range(*p.out.indices(sched.n_slots))) for p in pieces]
    assert sum(rows) == sched.n_and + len(sched.lin_out)
    assert min(rows) >= 160  # every run spans all multipliers
    rng = np.random.default_rng(3)
    lanes = 2  # 128 input vectors: two uint64 words per slot
    x, y = (rng.integers(0, 2**32, (64 * lanes, 160), dtype=np.uint64) for _ in range(2))
    bits = np.concatenate([((x[..., None] >> np.arange(32, dtype=np.uint64)) & 1),
                           ((y[..., None] >> np.arange(32, dtype=np.uint64)) & 1)], axis=1)
    out = evaluate_bits(sched, bits.reshape(64 * lanes, -1).astype(bool))
    got = (out.reshape(64 * lanes, 160, 32) << np.arange(32, dtype=np.uint64)).sum(axis=2)
    assert np.array_equal(got, (x * y) & np.uint64(0xFFFFFFFF))
    one_lane = evaluate_bits(sched, bits.reshape(64 * lanes, -1)[:64].astype(bool))
    assert np.array_equal(one_lane, out[:64])  # single-word rows: the strided plan


@pytest.mark.parametrize("n", [MIN_RUN, 2048])
def test_step_writing_its_own_reads_is_evaluated_before_writing(n):
    """An older schedule may let a step's outputs reuse slots the same step reads: the 2-term
    group overwrites x3's slot before the 3-term group reads it unless the step computes
    everything first. The 2-term rows form a run, the scrambled 3-term rows are left to
    gathers."""
    x = [FIRST_INPUT + k * n + np.arange(n) for k in range(4)]  # four input groups
    n_inputs = 4 * n
    fresh = FIRST_INPUT + n_inputs + np.arange(n)
    out = np.concatenate([x[3], fresh])  # 2-term rows overwrite x3
    scramble = np.random.default_rng(0).permutation(n)  # gathers for the 3-term rows
    terms = np.concatenate([np.stack([x[0], x[1]], axis=1).ravel(),
                            np.stack([x[1], x[2], x[3]], axis=1)[scramble].ravel()])
    ptr = np.concatenate([np.arange(0, 2 * n + 1, 2), 2 * n + 3 * np.arange(1, n + 1)])
    empty = np.zeros(0, np.int32)
    arrays = {"step_kind": np.array([LINEAR_STEP], np.uint8), "step_lo": np.array([0]),
              "step_hi": np.array([2 * n]), "and_out": empty, "and_a": empty,
              "and_b": empty, "lin_out": out.astype(np.int32), "lin_ptr": ptr,
              "lin_terms": terms.astype(np.int32), "output_slots": out.astype(np.int32),
              "meta": np.array([n_inputs, FIRST_INPUT + n_inputs + n])}  # no disjoint_io
    sched = Schedule.from_arrays(arrays, prefix="")
    assert not sched.disjoint_io
    plan = plan_for(sched, strided=True)
    assert not plan.steps[0].direct
    assert {type(g) for g in plan.steps[0].groups} == {RunGroup, LinearGroup}
    words = np.random.default_rng(1).integers(0, 2**63, (n_inputs, 1), dtype=np.uint64)
    v = {int(w): words[w - FIRST_INPUT] for w in np.concatenate(x)}
    want = [v[a] ^ v[b] for a, b in zip(x[0], x[1])]
    want += [v[a] ^ v[b] ^ v[c] for a, b, c in np.stack([x[1], x[2], x[3]], 1)[scramble]]
    assert np.array_equal(run_schedule(sched, words), np.array(want))


def test_max_terms_outside_the_byte_sized_term_counts_is_refused():
    circuit = build_multipliers(1)
    for bad in (1, 128):
        with pytest.raises(ValueError, match="max_terms"):
            schedule_circuit(circuit, max_terms=bad)
