"""Shared library of snail: circuits, arithmetic, garbling, localization, networking."""
