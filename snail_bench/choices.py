"""What the benchmark commands share about their circuits: the default sizes and the
circuit a set of command-line choices names (pipeline.Options decides, as for a client)."""

from __future__ import annotations

from snail_common.pnp.spec import Spec

SERVICE_POINTS = (6, 12)  # what `service` and `netem` measure unless --points says otherwise


def spec(algorithm: str, mode: str, solve: str | None, solver: str, points: int,
         arith: str | None = None) -> Spec:
    """The circuit the client would run with these choices (ValueError names a bad one)."""
    from snail_common.loc.pipeline import Options

    return Options(algorithm=algorithm, mode=mode, solver=solver, solve=solve,
                   arith=arith).spec(points)
