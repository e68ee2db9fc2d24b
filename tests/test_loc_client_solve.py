"""The client-solve circuit (``ne-sil-nN``): its cleartext evaluation is the mirror bit for
bit, its normal equations are the float64 ones up to the narrow format, and a pipeline
on it re-damps rejected LM steps without a secure run, landing where the in-circuit
solve lands."""

from __future__ import annotations

import numpy as np
import pytest
from shared_paths import EXAMPLES
from test_loc_circuits import _bits, random_values

from snail_common.circuit.cleartext import evaluate
from snail_common.circuit.schedule import schedule_circuit
from snail_common.loc.backends import MirrorBackend
from snail_common.loc.pipeline import Options, _symmetric, localize
from snail_common.loc.problem import load_problem
from snail_common.loc.quadratic import damped_step
from snail_common.pnp.do import normal_equations64
from snail_common.pnp.normal import NORMAL_FRAC
from snail_common.pnp.spec import Spec, build, run_mirror

N = 5
SPEC = Spec("lm", "sil", "client", N)


def test_one_circuit_serves_lm_and_gn_and_its_id_round_trips():
    assert SPEC.circuit_id == Spec("gn", "sil", "client", N).circuit_id == "ne-sil-n5"
    assert Spec.parse("ne-sil-n5") == SPEC
    with pytest.raises(ValueError, match="solver 'client' is for mode 'sil'"):
        Spec("lm", "do", "client", N)
    with pytest.raises(ValueError, match="--solve client: --mode do"):
        Options(mode="do", solve="client")
    assert Options(arith="float").spec(6).circuit_id == "ne-sil-n6"
    assert Options(mode="do").spec(6).circuit_id == "lm-do-ldlt-n6"
    assert Options(solve="circuit").spec(6).circuit_id == "lm-sil-ldlt-n6-x"


def test_cleartext_equals_mirror_and_float64():
    circuit = build(SPEC)
    schedule = schedule_circuit(circuit)
    assert [g.name for g in circuit.inputs] == ["R", "t", "image", "world", "weights"]
    rng = np.random.default_rng(5)
    for _ in range(8):
        values = random_values(SPEC, rng)
        values.pop("lam")  # damping is the client's
        out = evaluate(circuit, values, schedule=schedule)
        mirror = run_mirror(SPEC, values)
        for name in ("hess", "grad", "cost"):
            assert np.array_equal(_bits(out[name]), _bits(mirror[name])), name
        v = {k: np.asarray(x, np.float64) for k, x in values.items()}
        hess, _, cost = normal_equations64(v["R"], v["t"], v["image"], v["world"],
                                           v["weights"])
        got = _symmetric(mirror["hess"])
        assert np.linalg.norm(got - hess) <= 2.0 ** (1 - NORMAL_FRAC) * np.linalg.norm(hess)
        assert abs(float(mirror["cost"]) - cost) <= 1e-4 * cost


def test_damped_step_solves_the_damped_system():
    rng = np.random.default_rng(2)
    a = rng.normal(size=(12, 6))
    hess, grad = a.T @ a, rng.normal(size=6)
    step = damped_step(hess, grad, 0.1)
    np.testing.assert_allclose((hess + 0.1 * np.diag(np.diag(hess))) @ step, -grad,
                               atol=1e-10)
    assert np.isnan(damped_step(hess * np.nan, grad, 0.1)).all()


class Counting(MirrorBackend):
    """The mirror, remembering the pose of every invocation."""

    def __init__(self) -> None:
        super().__init__()
        self.poses: list[bytes] = []

    def _run(self, spec, values):
        self.poses.append(values["R"].tobytes() + values["t"].tobytes())
        return super()._run(spec, values)


@pytest.mark.parametrize("algorithm", ["lm", "gn"])
def test_a_rejected_step_costs_no_invocation(algorithm):
    """From a poor start LM rejects steps; each rejection is re-damped at the client, so
    every invocation is at a new pose, and the result matches the in-circuit solve."""
    problem = load_problem(EXAMPLES / "synthetic_n12.json")
    start = problem.initial_pose
    far = type(start)(start.rvec + 0.8, start.tvec * 1.5)
    client, inside = Counting(), MirrorBackend()
    mine = localize(problem, Options(algorithm=algorithm, min_invocations=0), client, far)
    theirs = localize(problem, Options(algorithm=algorithm, min_invocations=0,
                                       solve="circuit"), inside, far)
    assert mine.converged and theirs.converged
    assert len(set(client.poses)) == len(client.poses) == mine.invocations
    assert mine.invocations == len(mine.walls) <= mine.iterations + 1
    assert abs(mine.rms_px - theirs.rms_px) <= 0.01
    if algorithm == "lm":
        assert mine.invocations < theirs.invocations  # theirs paid for its 2 retries
