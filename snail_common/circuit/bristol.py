"""Bristol Fashion netlists (the MPC world's interchange format): import and export.

Imported values become input groups ``in0, in1, ...`` and output groups ``out0, ...``,
least-significant bit first (the convention of the shared SCALE-MAMBA files). EQW wire
copies and EQ constants are resolved at import, so gate counts keep only real gates.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .ir import AND, FIRST_INPUT, NOT, ONE, XOR, ZERO, Circuit, Group, compute_depths

_GATES_2 = {"XOR": XOR, "AND": AND}


class BristolError(ValueError):
    """A malformed Bristol Fashion file; the message names the line."""


def load_bristol(path: str | Path) -> Circuit:
    return parse_bristol(Path(path).read_text())


def parse_bristol(text: str) -> Circuit:
    lines = [ln.split() for ln in text.splitlines()]
    lines = [ln for ln in lines if ln]
    try:
        n_gates, n_wires = int(lines[0][0]), int(lines[0][1])
        in_sizes = [int(v) for v in lines[1][1 : 1 + int(lines[1][0])]]
        out_sizes = [int(v) for v in lines[2][1 : 1 + int(lines[2][0])]]
    except (IndexError, ValueError) as e:
        raise BristolError(f"bad header: {e}") from None
    gate_lines = lines[3:]
    if len(gate_lines) != n_gates:
        raise BristolError(f"header says {n_gates} gates, file has {len(gate_lines)}")
    n_in = sum(in_sizes)
    ours = np.full(n_wires, -1, np.int64)  # bristol wire -> our wire id
    ours[:n_in] = np.arange(FIRST_INPUT, FIRST_INPUT + n_in)
    kind, a, b = [], [], []
    next_wire = FIRST_INPUT + n_in
    for lineno, g in enumerate(gate_lines, start=4):
        try:
            n_i, n_o = int(g[0]), int(g[1])
            op = g[2 + n_i + n_o]
            ins = [int(w) for w in g[2 : 2 + n_i]]
            out = int(g[2 + n_i])
        except (IndexError, ValueError):
            raise BristolError(f"line {lineno}: cannot parse {' '.join(g)!r}") from None
        if op == "EQ":  # constant: input field is the literal bit
            ours[out] = ONE if ins[0] else ZERO
            continue
        src = [int(ours[w]) for w in ins]
        if min(src, default=0) < 0:
            raise BristolError(f"line {lineno}: reads a wire before it is driven")
        if op == "EQW":
            ours[out] = src[0]
            continue
        if op == "INV":
            kind.append(NOT)
            a.append(src[0])
            b.append(ONE)
        elif op in _GATES_2:
            kind.append(_GATES_2[op])
            a.append(src[0])
            b.append(src[1])
        else:
            raise BristolError(f"line {lineno}: unsupported gate {op!r}")
        ours[out] = next_wire
        next_wire += 1
    n_out = sum(out_sizes)
    outputs = ours[n_wires - n_out :]
    if np.any(outputs < 0):
        raise BristolError("an output wire is never driven")
    kind_a = np.array(kind, np.uint8)
    a_a, b_a = np.array(a, np.int32), np.array(b, np.int32)
    depth, xdepth = compute_depths(n_in, kind_a, a_a, b_a)
    circuit = Circuit(n_in, kind_a, a_a, b_a, outputs.astype(np.int32),
                      [Group(f"in{i}", (), n, _dtype(n)) for i, n in enumerate(in_sizes)],
                      [Group(f"out{i}", (), n, _dtype(n)) for i, n in enumerate(out_sizes)],
                      depth, xdepth)
    circuit.validate()
    return circuit


def dump_bristol(circuit: Circuit) -> str:
    """Bristol Fashion text of a circuit; each group becomes one value (its bits, flattened).

    Output values must be the last wires, so output gates are numbered last; outputs that
    are inputs, constants or repeated wires are copied out with EQW. Constants are made
    with EQ gates when used.
    """
    c = circuit
    n_in = c.n_inputs
    F = c.first_gate_wire
    out_wires = c.outputs.astype(np.int64)
    gate_out = out_wires - F
    first_use = np.zeros(len(out_wires), bool)
    is_gate = gate_out >= 0
    _, first_idx = np.unique(out_wires, return_index=True)
    first_use[first_idx] = True
    direct = is_gate & first_use  # outputs numbered directly as their gate
    n_copies = int((~direct).sum())
    used = np.zeros(FIRST_INPUT, bool)
    used[[w for w in (ZERO, ONE) if np.any(c.a == w) or np.any(c.b == w) or
          np.any(out_wires == w)]] = True
    used[ONE] = used[ONE] or bool(np.any(c.kind == NOT))
    n_const = int(used.sum())
    n_gates_total = n_const + c.n_gates + n_copies
    n_wires = n_in + n_const + c.n_gates + n_copies
    n_out = len(out_wires)

    # our wire -> bristol wire
    num = np.full(c.n_wires, -1, np.int64)
    num[FIRST_INPUT:F] = np.arange(n_in)
    inner = np.ones(c.n_gates, bool)
    inner[gate_out[direct]] = False
    inner_idx = np.flatnonzero(inner)
    num[F + inner_idx] = n_in + n_const + np.arange(inner_idx.size)
    num[F + gate_out[direct]] = n_wires - n_out + np.flatnonzero(direct)
    const_wires = [w for w in (ZERO, ONE) if used[w]]
    for i, w in enumerate(const_wires):
        num[w] = n_in + i

    lines = [f"{n_gates_total} {n_wires}",
             " ".join(map(str, [len(c.inputs), *(g.size for g in c.inputs)])),
             " ".join(map(str, [len(c.output_groups), *(g.size for g in c.output_groups)])),
             ""]
    lines += [f"1 1 {w} {num[w]} EQ" for w in const_wires]
    names = {XOR: "XOR", AND: "AND"}
    na, nb, no = num[c.a], num[c.b], num[F:]
    for k, x, y, o in zip(c.kind.tolist(), na.tolist(), nb.tolist(), no.tolist()):
        lines.append(f"1 1 {x} {o} INV" if k == NOT else f"2 1 {x} {y} {o} {names[k]}")
    for pos in np.flatnonzero(~direct):
        lines.append(f"1 1 {num[out_wires[pos]]} {n_wires - n_out + pos} EQW")
    return "\n".join(lines) + "\n"


def _dtype(bits: int) -> str:
    return "uint64" if bits <= 64 else "int"
