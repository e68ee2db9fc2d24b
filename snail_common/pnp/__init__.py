"""PnP circuit families: what runs inside the garbled circuit.

``fops`` lets one float32 program run as gates or as its numpy mirror; ``normal``,
``ldlt`` and ``svd`` are the building blocks; ``sil`` (one iteration) and ``do`` (the
data-oblivious baseline) the programs; ``spec`` names and builds them; ``family``
registers them with the circuit registry. Nothing here knows the client's geometry.
"""
