"""snail-garbler: the server that garbles circuits from client-chosen seeds."""

import click


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Garbler daemon (arrives with the service, issue 6): garbles the cached localization
    circuit from the client's seed and delta and streams tables to the evaluator."""
    raise click.UsageError("the garbler daemon is not built yet (issue 6)")
