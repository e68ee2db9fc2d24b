"""What the benchmark commands share about their circuits: the default sizes, the --arith
option and the circuit a set of command-line choices names (pipeline.Options decides, as for
a client)."""

from __future__ import annotations

import click

from snail_common.pnp.spec import Spec

SERVICE_POINTS = (6, 12)  # what `service` and `netem` measure unless --points says otherwise

# --arith of circuit, service and accuracy
ARITH = click.option("--arith", type=click.Choice(["fixed", "float"]),
                     help="Per-point arithmetic of a SIL circuit: fixed (default; integer "
                          "Jacobian and sums, float32 residuals and cost) or float (narrow "
                          "floats). DO and SVD circuits are float.")


def spec(algorithm: str, mode: str, solve: str | None, solver: str, points: int,
         arith: str | None = None) -> Spec:
    """The circuit the client would run with these choices (ValueError names a bad one)."""
    from snail_common.loc.pipeline import Options

    return Options(algorithm=algorithm, mode=mode, solver=solver, solve=solve,
                   arith=arith).spec(points)
