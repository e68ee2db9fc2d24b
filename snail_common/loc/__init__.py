"""Localization: PnP pose refinement as float32 programs that run as circuits.

``types`` fixes the conventions; ``fops`` lets one program run as gates or as its numpy
float32 mirror; ``normal``/``ldlt``/``svd`` are the SIL building blocks, ``sil``/``do`` the
programs, ``circuits`` names and builds them, ``backends`` turns a circuit into one
iteration for the client's driver. ``problem``/``preprocess``/``reference``/``driver`` are the
clear-text side the client runs.
"""
