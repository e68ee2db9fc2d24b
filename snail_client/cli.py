"""snail-client: the robot/phone side. Derives input labels, decodes results, drives LM."""

from __future__ import annotations

from pathlib import Path

import click

from snail_common.net.tls import TLSFileError, add_client, make_certs

from .verbosity import VerbosityGroup


@click.group(cls=VerbosityGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="snail", prog_name="snail-client")
@click.option("-v", "--verbose", is_flag=True,
              help="Also say on stderr what each frame cost (secure runs, time, bytes).")
@click.option("-q", "--quiet", is_flag=True,
              help="Only results (the pose and its status, one line a frame) and errors: no "
                   "summaries, no progress bars.")
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
@click.option("--client", "client_name", metavar="NAME",
              help="Instead: add a client certificate NAME.pem/NAME.key, issued by the CA "
                   "already in DIRECTORY (one per device, so each can be revoked by listing "
                   "NAME in the servers' revoked.txt).")
def certs(directory: Path, hosts: tuple[str, ...], days: int,
          client_name: str | None) -> None:
    """Create a CA and TLS certificates for garbler, evaluator and client in DIRECTORY.

    Give each server its own certificate and key plus ca.pem, and the client
    client.pem/client.key plus ca.pem; keep ca.key offline. The servers refuse
    certificates named (or fingerprinted) in revoked.txt of their TLS directory, which
    they reread on SIGHUP.
    """
    if client_name is not None:
        try:
            path = add_client(directory, client_name, days)
        except TLSFileError as exc:
            raise click.UsageError(f"DIRECTORY: {exc}") from None
        except ValueError as exc:
            raise click.UsageError(f"--client: {exc}") from None
        click.echo(f"wrote client certificate {path} and its key")
        return
    if directory.exists() and any(directory.glob("*.key")):
        raise click.UsageError(f"DIRECTORY: {directory} already holds keys; choose an empty "
                               "directory")
    make_certs(directory, hosts, days)
    click.echo(f"wrote CA and garbler, evaluator, client certificates to {directory}")


from .health import health_cmd  # noqa: E402  (commands of the group above)
from .localize_cmd import localize_cmd  # noqa: E402
from .track_cmd import track_cmd  # noqa: E402

main.add_command(localize_cmd)
main.add_command(track_cmd)
main.add_command(health_cmd)
