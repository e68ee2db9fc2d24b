"""Both servers on loopback for one run: the default when no addresses are given.

Creates throwaway certificates in a temporary directory, starts ``python -m
snail_evaluator`` and ``python -m snail_garbler`` as subprocesses on free ports (port 0:
each daemon reports its port in its ``listening`` log line), and stops them on exit.
Map owners (``python -m snail_mapd``, one per map asked for) start before the garbler,
which may dial only the map owners it is told of (``--map-owner``), and before the
evaluator, which is told of them too (it relays devices to them: ``--relay``); they are
told the evaluator's address, a port held for it until it listens there.
Their JSON logs go to files in the temporary directory; a daemon that fails to start
raises ServiceError with the tail of its log.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

from snail_common.net.conn import format_addr
from snail_common.net.linkrates import AUTO
from snail_common.net.parent import child_env
from snail_common.net.tls import make_certs

from .audit import DEFAULT_AUDIT_RATE
from .blocking import SecureRunner
from .links import DEFAULT_LINK_TIMEOUT, ServiceError
from .secure import DEFAULT_BUSY_WAIT

STARTUP_TIMEOUT = 60.0
STOP_TIMEOUT = 10.0
# map owners log their sessions: the only record of the map owner's time (snail-bench)
MAP_OWNER_LOG_LEVEL = "info"


@dataclass
class Daemon:
    """A running daemon subprocess."""

    role: str
    process: subprocess.Popen
    address: str
    log: Path

    def stop(self, timeout: float = STOP_TIMEOUT, sig: int = signal.SIGTERM) -> int:
        """``sig`` (SIGTERM drains, SIGINT ends the sessions at once), then SIGKILL after
        ``timeout``; returns the exit status."""
        if self.process.poll() is None:
            self.process.send_signal(sig)
            try:
                self.process.wait(timeout)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()
        return self.process.returncode


@dataclass
class Services:
    """What a client needs to reach the embedded servers."""

    garbler: Daemon
    evaluator: Daemon
    tls_dir: Path
    map_owners: tuple[Daemon, ...] = ()  # one per map, in the order given

    @property
    def garbler_addr(self) -> str:
        return self.garbler.address

    @property
    def evaluator_addr(self) -> str:
        return self.evaluator.address


def start_daemon(role: str, args: list[str], log: Path, host: str = "127.0.0.1",
                 env: Mapping[str, str] | None = None,
                 timeout: float = STARTUP_TIMEOUT, wrap: tuple[str, ...] = (),
                 port: int = 0) -> Daemon:
    """Start ``python -m snail_<role> --listen HOST:PORT ARGS`` (port 0: any free one) and
    wait until it listens; ``wrap`` goes before the command (the network lab's ``ip
    netns exec NS``)."""
    cmd = [*wrap, sys.executable, "-m", f"snail_{role}", "--listen", format_addr(host, port),
           *args]
    with open(log, "wb") as err:
        proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                stderr=err, env={**os.environ, **child_env(), **(env or {})})
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        port = _listening_port(log)
        if port is not None:
            return Daemon(role, proc, format_addr(host, port), log)
        if proc.poll() is not None:
            raise ServiceError(f"the {role} exited with status {proc.returncode} at "
                               f"startup: {_tail(log)}")
        time.sleep(0.02)
    proc.kill()
    proc.wait()
    raise ServiceError(f"the {role} did not start listening within {timeout:g} s: "
                       f"{_tail(log)}")


def _listening_port(log: Path) -> int | None:
    for line in log.read_text(errors="replace").splitlines():
        with contextlib.suppress(ValueError):
            entry = json.loads(line)
            if isinstance(entry, dict) and entry.get("event") == "listening":
                return int(entry["port"])
    return None


def _tail(log: Path, lines: int = 5) -> str:
    text = log.read_text(errors="replace").strip().splitlines()
    return " | ".join(text[-lines:]) or "(no output)"


@contextlib.contextmanager
def embedded_services(log_level: str = "warning", env: Mapping[str, str] | None = None,
                      extra_args: tuple[str, ...] = (), maps: Sequence[str | Path] = (),
                      ) -> Iterator[Services]:
    """Run both daemons on loopback with fresh certificates for the ``with`` block, and a
    map owner for each of ``maps`` (snail-map/1 files) that the garbler may dial."""
    with tempfile.TemporaryDirectory(prefix="snail-") as tmp:
        root = Path(tmp)
        tls_dir = make_certs(root / "tls")
        common = ["--tls-dir", str(tls_dir), "--log-level", log_level, *extra_args]
        started: list[Daemon] = []
        stop_with = signal.SIGTERM  # drain: the client is done with every session
        try:
            # the map owners are told the evaluator's address, the evaluator theirs
            with _held_port() if maps else contextlib.nullcontext(0) as port:
                for i, map_path in enumerate(maps):
                    started.append(start_daemon("mapd", [
                        "--map", str(map_path), "--tls-dir", str(tls_dir),
                        "--evaluator", format_addr("127.0.0.1", port),
                        "--log-level", MAP_OWNER_LOG_LEVEL], root / f"mapd{i}.log", env=env))
                owners = tuple(started)
                allowed = [arg for owner in owners for arg in ("--map-owner", owner.address)]
                evaluator = start_daemon("evaluator", [*allowed, *common],
                                         root / "evaluator.log", env=env, port=port)
                started.append(evaluator)
            garbler = start_daemon("garbler", ["--evaluator", evaluator.address, *allowed,
                                               *common], root / "garbler.log", env=env)
            started.append(garbler)
            yield Services(garbler, evaluator, tls_dir, owners)
        except BaseException:
            # the client failed or was interrupted: nobody will finish the sessions left
            # (garbled ahead, say), so they end at once instead of draining for --grace
            stop_with = signal.SIGINT
            raise
        finally:
            for daemon in reversed(started):
                daemon.stop(sig=stop_with)


@contextlib.contextmanager
def _held_port(host: str = "127.0.0.1") -> Iterator[int]:
    """A free port on ``host`` that nobody else takes during the block: a socket bound
    there (never listening) with SO_REUSEADDR, beside which Linux lets the daemon started
    on that port in the block bind and listen (its listening sockets set SO_REUSEADDR
    too); elsewhere it is let go at once, and the port merely likely to stay free."""
    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind((host, 0))
        port = sock.getsockname()[1]
        if not sys.platform.startswith("linux"):
            sock.close()
        yield port


def check_addresses(garbler: str | None, evaluator: str | None,
                    tls_dir: str | None) -> None:
    """Remote servers need all three; none of them means embedded ones."""
    remote = (garbler, evaluator, tls_dir)
    if any(remote) and not all(remote):
        raise ValueError("--garbler, --evaluator and --tls-dir go together (or none, for "
                         "daemons on loopback)")


@contextlib.contextmanager
def connected(garbler: str | None = None, evaluator: str | None = None,
              tls_dir: str | None = None, daemon_args: tuple[str, ...] = (),
              busy_wait: float = DEFAULT_BUSY_WAIT, cert_name: str = "client",
              link_timeout: float = DEFAULT_LINK_TIMEOUT, scheme: str = AUTO,
              maps: Sequence[str | Path] = (), audit_rate: float = DEFAULT_AUDIT_RATE,
              evidence_dir: str | Path | None = None,
              ) -> Iterator[tuple[SecureRunner, Services | None]]:
    """A runner for the servers at these addresses, or for embedded ones started for the
    block with ``daemon_args`` and a map owner per map of ``maps`` (yielded too, so a
    caller can watch them; None for remote servers); ``audit_rate`` and
    ``evidence_dir``: its audits (audit.py)."""
    check_addresses(garbler, evaluator, tls_dir)
    audits = {"audit_rate": audit_rate, "evidence_dir": evidence_dir}
    if garbler:
        with SecureRunner(garbler, evaluator, tls_dir, busy_wait=busy_wait,
                          link_timeout=link_timeout, scheme=scheme,
                          cert_name=cert_name, **audits) as runner:
            yield runner, None
        return
    with embedded_services(extra_args=daemon_args, maps=maps) as services, SecureRunner(
            services.garbler_addr, services.evaluator_addr, services.tls_dir,
            busy_wait=busy_wait, link_timeout=link_timeout, scheme=scheme,
            **audits) as runner:
        yield runner, services
