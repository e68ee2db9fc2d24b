"""A whole padded localization against what its links allow (``snail-bench netem
--localize``).

The bound a localization can reach is set by its links alone (DESIGN.md, round 3): its
garbler-to-evaluator bytes over the server link's measured rate, or its invocations times
the client's measured round trip, whichever is larger. ``bound_ratio`` = wall time / bound
says how close a run came: 1.0 is the link's own limit, and what lies above it is compute
and protocol.

Run as ``python -m snail_bench.linkbound --points N --repeat K --garbler ... --evaluator
... --tls-dir ...`` (in the lab's client namespace): one connected client localizes a
random scene of N points once to warm up (the daemons load the circuit), then K times,
padded to the privacy floor, and prints one JSON object: the median wall time, the
invocations and bytes per link of the median run, and the scheme of its sessions.
"""

from __future__ import annotations

import argparse
import json
import secrets
import sys
import time

import numpy as np

MIN_INVOCATIONS = 20  # snail-client's default floor: what a user's localization pays


def link_bound(server_bytes: int, server_rate_mbit: float, invocations: int,
               client_rtt_ms: float) -> float:
    """Seconds the links alone need: max(bytes over the server rate, invocations x the
    client's round trip)."""
    transfer = server_bytes * 8 / (server_rate_mbit * 1e6) if server_rate_mbit > 0 else 0.0
    return max(transfer, invocations * client_rtt_ms / 1000)


def bounded(run: dict, links: dict[str, dict]) -> dict:
    """``run`` (this module's output) with ``link_bound_s`` and ``bound_ratio`` from the
    links as measured (``{"rtt_ms", "rate_mbit"}`` per link)."""
    bound = link_bound(run["bytes"]["garbler_to_evaluator"],
                       links["garbler_evaluator"]["rate_mbit"], run["invocations"],
                       links["client_evaluator"]["rtt_ms"])
    return {**run, "link_bound_s": round(bound, 4),
            "bound_ratio": round(run["wall_s"] / bound, 3) if bound > 0 else None}


def localize_runs(points: int, repeat: int, garbler: str, evaluator: str, tls_dir: str,
                  scheme: str | None = None) -> dict:
    """Localize a random ``points``-point scene once to warm up, then ``repeat`` times
    on one connected client; the median run's figures."""
    from snail_client.localize import Options, backend_for, localize
    from snail_common import families
    from snail_common.loc.synthetic import random_scene

    families.register_all()
    options = Options(backend="garbled", garbler=garbler, evaluator=evaluator,
                      tls_dir=tls_dir, min_invocations=MIN_INVOCATIONS,
                      **({"scheme": scheme} if scheme else {}))
    runs = []
    with backend_for(options) as backend:
        for _ in range(repeat + 1):
            problem = random_scene(np.random.default_rng(secrets.randbits(64)), points)
            t0 = time.perf_counter()
            result = localize(problem, options, backend)
            runs.append((time.perf_counter() - t0, result))
    runs = sorted(runs[1:], key=lambda run: run[0])
    wall, result = runs[len(runs) // 2]
    return {"points": points, "wall_s": round(wall, 4),
            "walls_s": [round(w, 4) for w, _ in runs],
            "invocations": result["invocations"], "bytes": result["traffic"],
            "scheme": result.get("scheme"), "status": result["status"]}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=int, required=True)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--garbler", required=True)
    parser.add_argument("--evaluator", required=True)
    parser.add_argument("--tls-dir", required=True)
    parser.add_argument("--scheme", default=None)
    args = parser.parse_args(argv)
    print(json.dumps(localize_runs(args.points, args.repeat, args.garbler, args.evaluator,
                                   args.tls_dir, args.scheme)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
