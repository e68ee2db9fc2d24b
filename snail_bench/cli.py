"""snail-bench: measure what the budgets and targets in DESIGN.md talk about.

The group and its flags; each subcommand lives in a module by job: ``circuitcmd.py``
(bristol, compiler, ops, circuit, engine), ``servicecmd.py`` (service), ``checkcmd.py``
(soak, accuracy, fuzz), ``netcmd.py`` (netem, paper) and ``trackcmd.py`` (track)."""

from __future__ import annotations

import sys

import click

from snail_client.verbosity import VerbosityGroup
from snail_common import families

from .auditcmd import audits, verify_evidence
from .checkcmd import accuracy, fuzz_cmd, soak
from .circuitcmd import bristol, circuit, compiler, engine, ops
from .netcmd import netem, paper
from .servicecmd import service
from .trackcmd import track


@click.group(cls=VerbosityGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="snail", prog_name="snail-bench")
@click.option("-v", "--verbose", is_flag=True, help="Report each measurement on stderr "
                                                    "as it finishes.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bars.")
@click.pass_context
def main(ctx: click.Context, verbose: bool, quiet: bool) -> None:
    """Benchmarks and gate counts of snail's circuits and engines."""
    families.register_all()
    ctx.obj = {"verbose": verbose, "quiet": quiet}


for command in (netem, paper, bristol, compiler, ops, circuit, engine, service, soak, accuracy,
                fuzz_cmd, audits, verify_evidence, track):
    main.add_command(command)


if __name__ == "__main__":
    sys.exit(main())
