"""snail-garbler: the server that garbles circuits from client-chosen seeds."""

from __future__ import annotations

import click

from snail_common import families
from snail_common.net import tls
from snail_common.net.cli import (
    address,
    addresses,
    arm_failpoints,
    choose_engine,
    configure_caches,
    daemon_options,
    fail,
    log_level_of,
    map_owner_option,
    options_from,
)
from snail_common.net.conn import format_addr
from snail_common.net.listener import run_daemon
from snail_common.net.logs import setup
from snail_common.net.parent import exit_with_parent

from .daemon import GarblerDaemon


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--listen", required=True, callback=address, metavar="HOST:PORT",
              help="Address to accept clients on (port 0: any free port).")
@click.option("--evaluator", "evaluators", required=True, multiple=True, callback=addresses,
              metavar="NAME:PORT",
              help="The evaluator to stream tables to (repeatable). A name may resolve to "
                   "several replicas (tasks.evaluator in a Docker swarm, a headless "
                   "Kubernetes Service): each session streams to the replica its client "
                   "talks to, which the client names by address and instance id. These "
                   "are the only evaluators this garbler dials: a client naming another "
                   "is refused as forbidden.")
@map_owner_option("garbler", "for the map-owner setting", "map-owner sessions",
                  names="The name is resolved (to all its addresses): clients may name it "
                        "as given here or by one of its addresses; a client's own host "
                        "name is compared, never resolved.")
@daemon_options
def main(listen: tuple[str, int], evaluators: tuple[tuple[str, int], ...],
         map_owners: tuple[tuple[str, int], ...], tls_dir: str, log_level: str,
         **kwargs) -> None:
    """Garbler daemon: garbles circuits from each client's seed and offset and streams the
    tables to the evaluator (see snail_garbler.daemon)."""
    exit_with_parent()
    logger = setup("garbler", log_level_of(log_level, kwargs))
    arm_failpoints("garbler", "snail-garbler", logger)
    try:
        server_ctx = tls.server_context(tls_dir, "garbler")
        client_ctx = tls.client_context(tls_dir, "garbler")
        daemon = GarblerDaemon(options_from({**kwargs, "tls_dir": tls_dir}), logger,
                               evaluators, client_ctx, map_owners)
    except (OSError, ValueError) as exc:
        fail(2, f"--tls-dir: {exc}", "snail-garbler")
    families.register_all()
    configure_caches(kwargs)
    daemon.use_engine(choose_engine("snail-garbler"))
    try:
        interrupted = run_daemon(daemon, listen, server_ctx)
    except OSError as exc:  # cannot bind the listening address
        raise click.ClickException(f"--listen {format_addr(*listen)}: {exc}") from None
    if interrupted:
        fail(130, "interrupted: running sessions ended with an error to their peers",
             "snail-garbler")
