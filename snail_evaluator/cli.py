"""snail-evaluator: the server that evaluates garbled tables on the client's labels."""

from __future__ import annotations

import click

from snail_common import families
from snail_common.net import tls
from snail_common.net.cli import (
    address,
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

from .daemon import EvaluatorDaemon


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("--listen", required=True, callback=address, metavar="HOST:PORT",
              help="Address to accept clients and the garbler on (port 0: any free port).")
@map_owner_option("evaluator", "to relay devices, so that the map owner sees this "
                  "evaluator's address and never a device's", "relays",
                  how="The device's TLS with the map owner runs end to end through the "
                      "relay: the evaluator cannot read it.",
                  names="Names are resolved as the garbler's --map-owner.")
@daemon_options
def main(listen: tuple[str, int], map_owners: tuple[tuple[str, int], ...], tls_dir: str,
         log_level: str, **kwargs) -> None:
    """Evaluator daemon: evaluates the garbler's table stream on each client's active input
    labels and returns the active output labels (see snail_evaluator.daemon)."""
    exit_with_parent()
    logger = setup("evaluator", log_level_of(log_level, kwargs))
    arm_failpoints("evaluator", "snail-evaluator", logger)
    try:
        ctx = tls.server_context(tls_dir, "evaluator")
        daemon = EvaluatorDaemon(options_from({**kwargs, "tls_dir": tls_dir}), logger,
                                 map_owners)
    except (OSError, ValueError) as exc:
        fail(2, f"--tls-dir: {exc}", "snail-evaluator")
    families.register_all()
    configure_caches(kwargs)
    daemon.use_engine(choose_engine("snail-evaluator"))
    try:
        interrupted = run_daemon(daemon, listen, ctx)
    except OSError as exc:  # cannot bind the listening address
        raise click.ClickException(f"--listen {format_addr(*listen)}: {exc}") from None
    if interrupted:
        fail(130, "interrupted: running sessions ended with an error to their peers",
             "snail-evaluator")
