"""The real daemons inside the lab: the evaluator and the garbler each in its namespace,
with certificates naming the lab's addresses, the garbler streaming to the evaluator over
the garbler-evaluator link; the client reaches them over its own two links."""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from snail_client.embedded import Daemon, start_daemon
from snail_common.net.conn import format_addr, parse_addr
from snail_common.net.tls import make_certs

from .namespaces import Lab


@dataclass
class LabServices:
    """Both daemons and the addresses the client's namespace reaches them by."""

    garbler: Daemon
    evaluator: Daemon
    tls_dir: Path
    garbler_addr: str
    evaluator_addr: str

    def client_args(self) -> list[str]:
        """``--garbler/--evaluator/--tls-dir`` for a client run in the lab."""
        return ["--garbler", self.garbler_addr, "--evaluator", self.evaluator_addr,
                "--tls-dir", str(self.tls_dir)]


def _port(daemon: Daemon) -> int:
    return parse_addr(daemon.address)[1]


@contextlib.contextmanager
def lab_services(lab: Lab, workdir: Path, daemon_args: tuple[str, ...] = (),
                 log_level: str = "warning") -> Iterator[LabServices]:
    """Start both daemons in their namespaces (logs and certificates in ``workdir``) for
    the ``with`` block; they stop when it ends, and with the lab at the latest."""
    tls_dir = make_certs(workdir / "tls", lab.addresses())
    common = ["--tls-dir", str(tls_dir), "--log-level", log_level, *daemon_args]
    started: list[Daemon] = []
    try:
        evaluator = start_daemon("evaluator", common, workdir / "evaluator.log",
                                 host="0.0.0.0", wrap=lab.exec_prefix("evaluator"))
        started.append(evaluator)
        lab.adopt(evaluator.process)
        to_evaluator = format_addr(lab.address("garbler_evaluator", "evaluator"),
                                   _port(evaluator))
        garbler = start_daemon("garbler", ["--evaluator", to_evaluator, *common],
                               workdir / "garbler.log", host="0.0.0.0",
                               wrap=lab.exec_prefix("garbler"))
        started.append(garbler)
        lab.adopt(garbler.process)
        yield LabServices(
            garbler, evaluator, tls_dir,
            format_addr(lab.address("client_garbler", "garbler"), _port(garbler)),
            format_addr(lab.address("client_evaluator", "evaluator"), _port(evaluator)))
    finally:
        for daemon in reversed(started):
            daemon.stop()
