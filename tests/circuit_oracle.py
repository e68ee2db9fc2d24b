"""Gate-by-gate reference evaluation, independent of the scheduler: the oracle of the oracle."""

import numpy as np

from snail_common.circuit.ir import AND, FIRST_INPUT, Circuit


def direct_eval(circuit: Circuit, input_bits: np.ndarray) -> np.ndarray:
    """bool (L, n_inputs) -> bool (L, n_outputs), one gate at a time."""
    lanes = input_bits.shape[0]
    w = np.zeros((circuit.n_wires, lanes), bool)
    w[1] = True
    w[FIRST_INPUT : FIRST_INPUT + circuit.n_inputs] = input_bits.T
    base = circuit.first_gate_wire
    for g, (k, a, b) in enumerate(zip(circuit.kind.tolist(), circuit.a.tolist(),
                                      circuit.b.tolist())):
        w[base + g] = (w[a] & w[b]) if k == AND else (w[a] ^ w[b])
    return w[circuit.outputs].T
