"""What the benchmark commands share about their circuits: the default sizes, the --arith
option and the circuit a set of command-line choices names (pipeline.Options decides, as for
a client)."""

from __future__ import annotations

from collections.abc import Callable

import click

from snail_common.net.messages import TABLE_LINKS
from snail_common.pnp.spec import Spec

SERVICE_POINTS = (6, 12)  # what `service` and `netem` measure unless --points says otherwise

# --table-link of service and audits
TABLE_LINK = click.option(
    "--table-link", type=click.Choice(TABLE_LINKS), default=None,
    help="Embedded daemons only: their --table-link (how the tables travel from garbler to "
         "evaluator; default: the daemons' own). The JSON says which served.")


def link_args(table_link: str | None) -> tuple[str, ...]:
    """The embedded daemons' flags for ``--table-link`` (none: their default)."""
    return ("--table-link", table_link) if table_link else ()


# --arith of circuit, service and accuracy
ARITH = click.option("--arith", type=click.Choice(["fixed", "float"]),
                     help="Per-point arithmetic of a SIL circuit: fixed (default; integer "
                          "Jacobian and sums, float32 residuals and cost) or float (narrow "
                          "floats). DO and SVD circuits are float.")

_CIRCUIT_OPTIONS = (
    click.option("--algorithm", type=click.Choice(["lm", "gn"]), default="lm",
                 show_default=True, help="Levenberg-Marquardt (damped) or Gauss-Newton."),
    click.option("--mode", type=click.Choice(["sil", "do"]), default="sil", show_default=True,
                 help="sil: one iteration per circuit; do: the data-oblivious 20-iteration "
                      "baseline."),
    click.option("--solve", type=click.Choice(["client", "circuit"]),
                 help="client (default for sil): the circuit returns the normal equations "
                      "and the client solves; circuit (forced for do): the paper's "
                      "in-circuit solve."),
    click.option("--solver", type=click.Choice(["ldlt", "svd"]), default="ldlt",
                 show_default=True,
                 help="Linear solver for the 6x6 step inside the circuit (--solve circuit)."),
)


def circuit_options(command: Callable) -> Callable:
    """--algorithm, --mode, --solve and --solver of circuit and service: the choices
    ``spec`` turns into a circuit."""
    for option in reversed(_CIRCUIT_OPTIONS):
        command = option(command)
    return command


def spec(algorithm: str, mode: str, solve: str | None, solver: str, points: int,
         arith: str | None = None) -> Spec:
    """The circuit the client would run with these choices (ValueError names a bad one)."""
    from snail_common.loc.pipeline import Options

    return Options(algorithm=algorithm, mode=mode, solver=solver, solve=solve,
                   arith=arith).spec(points)
