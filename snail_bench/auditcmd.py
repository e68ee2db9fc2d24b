"""``snail-bench audits`` (what trusting no single server costs: ``audits.py``) and
``snail-bench verify-evidence`` (an evidence file checked on its own:
snail_client/evidence.py)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from .choices import ARITH, TABLE_LINK, circuit_options
from .choices import spec as _spec


@click.command()
@circuit_options
@click.option("--points", type=click.IntRange(4, 4096), multiple=True, metavar="N",
              help="Circuit size; repeat for several (default: 6; 256 compiles for "
                   "minutes the first time, and takes gigabytes).")
@click.option("--repeat", type=click.IntRange(1, 1000), default=10, show_default=True,
              help="Runs per batch (the servers' CPU is read per batch).")
@click.option("--batches", type=click.IntRange(1, 100), default=3, show_default=True,
              help="Batches per circuit: the spread reported is theirs.")
@click.option("--audits", "n_audits", type=click.IntRange(1, 1000), default=5,
              show_default=True, help="Client audits timed per circuit.")
@TABLE_LINK
@ARITH
def audits(algorithm: str, mode: str, solve: str | None, solver: str, arith: str | None,
           points: tuple[int, ...], repeat: int, batches: int, n_audits: int,
           table_link: str | None) -> None:
    """The cost of the signed digests and of the client's audits, per circuit: the
    garbler's digest and signature and the evaluator's digest and check as a share of
    that server's CPU per run (target: at most 10 %), and the client's CPU per audited
    run and per run at the default audit rate. One JSON object on stdout."""
    from .audits import audit_report

    try:
        specs = [_spec(algorithm, mode, solve, solver, n, arith) for n in points or (6,)]
    except ValueError as exc:
        raise click.UsageError(str(exc)) from None
    click.echo(json.dumps(audit_report(specs, repeat, batches, n_audits, table_link)))


@click.command("verify-evidence")
@click.argument("file", type=click.Path(exists=True, dir_okay=False))
@click.option("--ca", type=click.Path(exists=True, dir_okay=False),
              help="The CA certificate (ca.pem) the garbler's certificate must come from; "
                   "without it, the file's certificate is taken as the garbler's.")
def verify_evidence(file: str, ca: str | None) -> None:
    """Check a snail-evidence/1 file on its own: exit 0 when it proves that the garbler
    cheated (a run's tables or output zero-labels it signed are not the circuit's for
    that run's seed, offset and key), 1 when it does not. One JSON line says which and
    why."""
    from snail_client.evidence import Unproven, verify

    try:
        verdict = verify(Path(file), Path(ca).read_bytes() if ca else None)
    except Unproven as exc:
        click.echo(json.dumps({"proven": False, "because": str(exc)}))
        sys.exit(1)
    click.echo(json.dumps(verdict))
