"""snail-client: the robot/phone side. Derives input labels, decodes results, drives LM."""

import click


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
def main() -> None:
    """Private camera localization with two non-colluding garbled-circuit servers.

    The localize, track and certs commands arrive with the service (issue 6); until then
    this prints its help only.
    """
