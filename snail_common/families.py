"""Every circuit family this build serves, registered with the circuit registry.

The registry (circuit/registry.py) knows no family; the roles and benchmarks, which sit
above all of them, call ``register_all`` before they name a circuit.
"""

from __future__ import annotations

from snail_common.arith import catalog
from snail_common.circuit import registry
from snail_common.pnp import family


def register_all() -> None:
    """Register the ``ops`` and ``loc`` families (idempotent)."""
    registry.register(catalog.FAMILY)
    registry.register(family.FAMILY)
