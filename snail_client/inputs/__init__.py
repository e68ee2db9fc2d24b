"""Turning what a user has (a camera image and a tag map, a COLMAP model) into a
``snail-problem/1``, in the clear and on the client: nothing here talks to a server."""

from .fields import InputError

__all__ = ["InputError"]
