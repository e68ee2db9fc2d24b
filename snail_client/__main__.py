"""python -m snail_client: the snail-client command."""

from .cli import main

main()
