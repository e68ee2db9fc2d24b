"""snail-evaluator: the server that evaluates garbled tables on the client's labels."""

import click


@click.command(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Evaluator daemon (arrives with the service, issue 6): evaluates the garbled stream on
    the client's input labels and returns the active output labels."""
    raise click.UsageError("the evaluator daemon is not built yet (issue 6)")
