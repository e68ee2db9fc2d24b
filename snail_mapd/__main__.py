"""python -m snail_mapd"""

from .cli import main

main(prog_name="snail-mapd")
