"""Simulated worlds and camera sequences made by the project: Turbo's room and drive, and
a hand-held camera walking through a room of points (floor 6: on the client's API, under
the benchmarks and demos that use them)."""
