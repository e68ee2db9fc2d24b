"""Named network settings (``snail-bench netem --profile``, FORMATS.md round 3): where the
two servers and the client might really sit. One way delays; rates each way."""

from __future__ import annotations

from .namespaces import Shape

CLIENT_LINKS = ("client_garbler", "client_evaluator")
# name: (garbler-evaluator, each client link)
PROFILES: dict[str, tuple[Shape, Shape]] = {
    "lan": (Shape(0.25, rate_mbit=10_000), Shape(0.25, rate_mbit=1_000)),
    "paper": (Shape(5, rate_mbit=2_500), Shape()),  # the paper's servers; client unshaped
    "region": (Shape(10, rate_mbit=1_000), Shape(20, rate_mbit=100)),
    "continent": (Shape(40, rate_mbit=1_000), Shape(30, rate_mbit=50)),
}


def profile_shapes(name: str) -> dict[str, Shape]:
    """The links' shaping of profile ``name`` (KeyError for an unknown one)."""
    server, client = PROFILES[name]
    return {"garbler_evaluator": server, **dict.fromkeys(CLIENT_LINKS, client)}
