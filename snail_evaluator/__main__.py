"""python -m snail_evaluator"""

from .cli import main

main(prog_name="snail-evaluator")
