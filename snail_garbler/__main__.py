"""python -m snail_garbler"""

from .cli import main

main(prog_name="snail-garbler")
