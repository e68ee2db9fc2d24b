"""snail-client: the robot/phone side. Derives input labels, decodes results, drives LM."""

from __future__ import annotations

from pathlib import Path

import click

from snail_common.net.tls import make_certs


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="snail", prog_name="snail-client")
@click.option("-v", "--verbose", is_flag=True,
              help="Also say on stderr what each frame cost (secure runs, time, bytes).")
@click.option("-q", "--quiet", is_flag=True,
              help="Only results and errors: no summary lines, no progress bars.")
@click.pass_context
def main(ctx: click.Context, verbose: bool, quiet: bool) -> None:
    """Private camera localization with two non-colluding garbled-circuit servers."""
    if verbose and quiet:
        raise click.UsageError("-v and -q: choose one")
    ctx.obj = {"verbose": verbose, "quiet": quiet}


@main.command()
@click.argument("directory", type=click.Path(file_okay=False, path_type=Path))
@click.option("--host", "hosts", multiple=True, metavar="NAME",
              help="Extra DNS name or IP address of the servers (repeatable); localhost, "
                   "127.0.0.1 and ::1 are always included.")
@click.option("--days", type=click.IntRange(1, 3650), default=365, show_default=True,
              help="Validity of the certificates.")
def certs(directory: Path, hosts: tuple[str, ...], days: int) -> None:
    """Create a CA and TLS certificates for garbler, evaluator and client in DIRECTORY.

    Give each server its own certificate and key plus ca.pem, and the client
    client.pem/client.key plus ca.pem; keep ca.key offline.
    """
    if directory.exists() and any(directory.glob("*.key")):
        raise click.UsageError(f"DIRECTORY: {directory} already holds keys; choose an empty "
                               "directory")
    make_certs(directory, hosts, days)
    click.echo(f"wrote CA and garbler, evaluator, client certificates to {directory}")


from .health import health_cmd  # noqa: E402  (commands of the group above)
from .localize_cmd import localize_cmd, track_cmd  # noqa: E402

main.add_command(localize_cmd)
main.add_command(track_cmd)
main.add_command(health_cmd)
