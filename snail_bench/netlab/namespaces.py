"""Three hosts on one machine: the client, the garbler and the evaluator in network
namespaces of their own, each pair joined by a link shaped on its own.

A link ``X_Y`` is two veth pairs through a fourth, middle namespace (the wire):
``X:to-Y <-> wire:xy-x | bridge or forwarder | wire:xy-y <-> Y:to-X``. X and Y hold
addresses in 10.99.L.0/24 (L the link's index); these exist only inside the lab's
namespaces, and no namespace has a route out. In the wire namespace a link's two ends are
either joined by a kernel bridge (the direct path: nothing in user space touches a frame)
or handed to the lab's forwarder (``wire.c``, else ``wire.py``), which delays, jitters and
drops frames. Which shaper a lab uses is chosen once (``shaper.py``): with ``tc netem``
where the kernel has it (every link bridged, netem on both endpoints), else the forwarder
for the links that need delay, jitter or loss, with tbf on the endpoints for a rate. A
control run (``shape(..., control=True)``) sends every link through the shaper with zero
delay and no rate, so the shaper's own cost shows beside the direct run. Namespace names
carry the pid, so concurrent labs never meet and a lab left by a killed process (SIGKILL
leaves no chance to tear down) is told by its owner being gone: a new lab removes such
leftovers first (``reap_stale``).

``Lab`` is a context manager: leaving it by any path (an exception, Ctrl-C, SIGTERM)
stops the processes it started and deletes every namespace it made, which takes their
veths, bridges and qdiscs with them; ``leftovers()`` says what would remain.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import os
import re
import shutil
import signal
import subprocess
import sys
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import FrameType

from . import shaper as shapers
from .wire_native import wire_command

ROLES = ("client", "garbler", "evaluator")
LINKS: dict[str, tuple[str, str]] = {"client_garbler": ("client", "garbler"),
                                     "client_evaluator": ("client", "evaluator"),
                                     "garbler_evaluator": ("garbler", "evaluator")}
CAP_NET_ADMIN, CAP_SYS_ADMIN = 12, 21
READY_TIMEOUT = 10.0
WIRE_PRIORITY = 10  # SCHED_FIFO priority of the forwarder (1-99)
PROBE_PORT = 5201  # the probe server's port (inside the lab's fresh namespaces)
_serial = itertools.count()


def process_cpu_s(pid: int) -> float:
    """CPU seconds ``pid`` has used: the scheduler's nanosecond sum over its threads
    where the kernel shows it, else user plus system time from /proc/PID/stat, which
    counts in clock ticks (10 ms: a short control run of the native forwarder reads 0)."""
    try:
        total = 0.0
        for sched in Path(f"/proc/{pid}/task").glob("*/sched"):
            for line in sched.read_text().splitlines():
                if line.startswith("se.sum_exec_runtime"):
                    total += float(line.split(":")[1]) / 1000  # milliseconds
        if total > 0:
            return total
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1]
    except (OSError, ValueError):
        return 0.0
    user, system = fields.split()[11:13]
    return (int(user) + int(system)) / os.sysconf("SC_CLK_TCK")


class LabUnavailable(Exception):
    """This process cannot build namespaces (not root, no CAP_NET_ADMIN, no ``ip``)."""


class LabError(Exception):
    """A command that builds or shapes the lab failed."""


@dataclass(frozen=True)
class Shape:
    """One link's shaping, the same in both directions (so RTT = 2 x delay)."""

    delay_ms: float = 0.0
    jitter_ms: float = 0.0
    loss_pct: float = 0.0
    rate_mbit: float | None = None

    def __post_init__(self) -> None:
        for name in ("delay_ms", "jitter_ms", "loss_pct"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.loss_pct >= 100:
            raise ValueError(f"loss_pct must be below 100, got {self.loss_pct}")
        if self.jitter_ms > self.delay_ms:
            raise ValueError(f"jitter_ms ({self.jitter_ms}) must not exceed delay_ms "
                             f"({self.delay_ms})")
        if self.rate_mbit is not None and self.rate_mbit <= 0:
            raise ValueError(f"rate_mbit must be > 0, got {self.rate_mbit}")


def check_capable() -> None:
    """Raise LabUnavailable (one line) unless namespaces can be made here."""
    if shutil.which("ip") is None or shutil.which("tc") is None:
        raise LabUnavailable("the network lab needs the 'ip' and 'tc' commands (iproute2)")
    caps = 0
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("CapEff:"):
            caps = int(line.split()[1], 16)
    missing = [name for bit, name in ((CAP_NET_ADMIN, "CAP_NET_ADMIN"),
                                      (CAP_SYS_ADMIN, "CAP_SYS_ADMIN")) if not caps >> bit & 1]
    if missing:
        raise LabUnavailable(f"the network lab needs root ({' and '.join(missing)} missing): "
                             f"run it as root or in a privileged container")


def _run(*cmd: str) -> str:
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise LabError(f"{' '.join(cmd)}: {proc.stderr.strip() or proc.returncode}")
    return proc.stdout


def netns_list() -> list[str]:
    """Names of all network namespaces ``ip netns`` knows."""
    return [line.split()[0] for line in _run("ip", "netns", "list").splitlines() if line]


_LAB_NAMESPACE = re.compile(r"snail-(\d+)-\d+-(?:client|garbler|evaluator|wire)")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def reap_stale() -> list[str]:
    """Delete the namespaces of labs whose process is gone, after killing what still runs
    in them (daemons, the wire); the names deleted."""
    reaped = []
    for name in netns_list():
        found = _LAB_NAMESPACE.fullmatch(name)
        if found is None or _alive(int(found[1])):
            continue
        for pid in _run("ip", "netns", "pids", name).split():
            with contextlib.suppress(ProcessLookupError):
                os.kill(int(pid), signal.SIGKILL)
        if subprocess.run(("ip", "netns", "del", name), capture_output=True).returncode == 0:
            reaped.append(name)
    return reaped


class Lab:
    """The namespaces, links, wire process and daemons of one lab (see the module doc)."""

    def __init__(self, shaper: str = "auto", native_wire: bool = True) -> None:
        if shaper not in shapers.SHAPERS:
            raise ValueError(f"shaper must be one of {', '.join(shapers.SHAPERS)}, "
                             f"got {shaper!r}")
        self.requested = shaper
        self.shaper = ""  # "netem" or "forwarder", once the lab is built
        self.native_wire = native_wire
        self.forwarder = ""  # "native" or "python", once a forwarder ran
        self.control = False  # every link through the shaper at zero delay and rate
        self.tag = f"snail-{os.getpid()}-{next(_serial)}"
        self.ns = {role: f"{self.tag}-{role}" for role in (*ROLES, "wire")}
        self.shapes: dict[str, Shape] = {link: Shape() for link in LINKS}
        self._made: list[str] = []
        self._procs: list[subprocess.Popen] = []
        self._wire: subprocess.Popen | None = None
        self._old_sigterm: object = None

    # names and addresses -------------------------------------------------------------
    @staticmethod
    def ifname(role: str, peer: str) -> str:
        """The endpoint veth in ``role``'s namespace that leads to ``peer``."""
        return f"to-{peer}"

    @staticmethod
    def wire_ifname(link: str, role: str) -> str:
        a, b = LINKS[link]
        return f"{a[0]}{b[0]}-{role[0]}"

    @staticmethod
    def bridge(link: str) -> str:
        """The bridge in the wire namespace that joins ``link``'s ends directly."""
        a, b = LINKS[link]
        return f"{a[0]}{b[0]}-br"

    @staticmethod
    def address(link: str, role: str) -> str:
        """``role``'s IPv4 address on ``link`` (private, inside the lab only)."""
        index = list(LINKS).index(link)
        return f"10.99.{index}.{LINKS[link].index(role) + 1}"

    def addresses(self) -> list[str]:
        return [self.address(link, role) for link, pair in LINKS.items() for role in pair]

    def exec_prefix(self, role: str) -> tuple[str, ...]:
        """Prefix that runs a command inside ``role``'s namespace."""
        return ("ip", "netns", "exec", self.ns[role])

    # life cycle ------------------------------------------------------------------------
    def __enter__(self) -> Lab:
        check_capable()
        reaped = reap_stale()
        if reaped:
            print(f"netlab: removed {len(reaped)} namespaces left by a killed lab: "
                  f"{', '.join(reaped)}", file=sys.stderr)
        if signal.getsignal(signal.SIGTERM) is signal.SIG_DFL:
            self._old_sigterm = signal.signal(signal.SIGTERM, _sigterm_to_exit)
        try:
            self._build()
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _build(self) -> None:
        for name in self.ns.values():
            _run("ip", "netns", "add", name)
            self._made.append(name)
        for role in (*ROLES, "wire"):
            _run("ip", "-n", self.ns[role], "link", "set", "lo", "up")
        wire = self.ns["wire"]
        for link, pair in LINKS.items():
            for role, peer in (pair, pair[::-1]):
                inner, outer = self.ifname(role, peer), self.wire_ifname(link, role)
                _run("ip", "link", "add", inner, "netns", self.ns[role], "type", "veth",
                     "peer", "name", outer, "netns", wire)
                _run("ip", "-n", self.ns[role], "addr", "add",
                     f"{self.address(link, role)}/24", "dev", inner)
                _run("ip", "-n", self.ns[role], "link", "set", inner, "up")
                _run("ip", "-n", wire, "link", "set", outer, "up")
            bridge = self.bridge(link)
            _run("ip", "-n", wire, "link", "add", bridge, "type", "bridge",
                 "forward_delay", "0")
            _run("ip", "-n", wire, "link", "set", bridge, "up")
            self._join(link, True)
        try:
            self.shaper = shapers.choose(self.requested, shapers.netem_probe(wire))
        except shapers.ShaperUnavailable as exc:
            raise LabUnavailable(str(exc)) from None

    def close(self) -> None:
        """Stop every process the lab started and delete its namespaces (idempotent)."""
        for proc in reversed(self._procs):
            _stop(proc)
        self._procs.clear()
        if self._wire is not None:
            _stop(self._wire)
            self._wire = None
        failures = []
        for name in reversed(self._made):
            proc = subprocess.run(("ip", "netns", "del", name), capture_output=True,
                                  text=True)
            if proc.returncode != 0 and name in netns_list():
                failures.append(f"{name}: {proc.stderr.strip()}")
        self._made.clear()
        if self._old_sigterm is not None:
            signal.signal(signal.SIGTERM, self._old_sigterm)  # type: ignore[arg-type]
            self._old_sigterm = None
        if failures:
            raise LabError("could not delete " + "; ".join(failures))

    def leftovers(self) -> list[str]:
        """Namespaces of this lab that still exist (empty after ``close``)."""
        return [name for name in netns_list() if name.startswith(self.tag + "-")]

    # shaping ---------------------------------------------------------------------------
    def shape(self, shapes: Mapping[str, Shape], control: bool = False) -> None:
        """Set the shaping of the named links (others keep theirs). ``control``: every
        link through the shaper as configured, but with zero delay and no rate (a
        zero shape sends nothing through the forwarder otherwise)."""
        for link, shape in shapes.items():
            if link not in LINKS:
                raise ValueError(f"unknown link {link!r}; links: {', '.join(LINKS)}")
            self.shapes[link] = shape
        self.control = control
        self._stop_wire()
        wired = []
        for link, shape in self.shapes.items():
            through = control or shape != Shape()
            delayed = control or (shape.delay_ms, shape.jitter_ms, shape.loss_pct) != (0, 0, 0)
            for role, peer in (LINKS[link], LINKS[link][::-1]):
                dev, ns = self.ifname(role, peer), self.ns[role]
                if not through:
                    args = None
                elif self.shaper == "netem":
                    args = shapers.netem_args(shape.delay_ms, shape.jitter_ms,
                                              shape.loss_pct, shape.rate_mbit)
                else:
                    args = None if shape.rate_mbit is None else shapers.tbf_args(
                        shape.rate_mbit)
                if args is None:
                    subprocess.run(("tc", "-n", ns, "qdisc", "del", "dev", dev, "root"),
                                   capture_output=True)  # none set is fine
                else:
                    _run("tc", "-n", ns, "qdisc", "replace", "dev", dev, "root", *args)
            forwarded = self.shaper == "forwarder" and delayed
            self._join(link, not forwarded)
            if forwarded:
                wired.append(link)
        if wired:
            self._start_wire(wired)

    def _join(self, link: str, bridged: bool) -> None:
        """Join ``link``'s two wire-side ends by its bridge, or free them for the
        forwarder (a bridged end would forward each frame a second time)."""
        for role in LINKS[link]:
            master = ("master", self.bridge(link)) if bridged else ("nomaster",)
            _run("ip", "-n", self.ns["wire"], "link", "set", self.wire_ifname(link, role),
                 *master)

    def running_wire(self) -> bool:
        """Whether the forwarder carries any link now."""
        return self._wire is not None

    def wire_cpu_s(self) -> float:
        """CPU seconds the running forwarder has used (0: none runs)."""
        if self._wire is None:
            return 0.0
        return process_cpu_s(self._wire.pid)

    def qdiscs(self, role: str) -> str:
        """``tc qdisc show`` inside ``role``'s namespace."""
        return _run("tc", "-n", self.ns[role], "qdisc", "show")

    def _stop_wire(self) -> None:
        if self._wire is not None:
            _stop(self._wire)
            self._wire = None

    def _start_wire(self, links: list[str]) -> None:
        """The forwarder on ``links`` (with their delay, jitter and loss; zero in a
        control run), at real-time priority where allowed: a wire is not a process that
        waits for the hosts' cores, and a descheduled one would add its own delay."""
        args = []
        for link in links:
            a, b = LINKS[link]
            shape = Shape() if self.control else self.shapes[link]
            args += ["--link", f"{self.wire_ifname(link, a)},{self.wire_ifname(link, b)},"
                               f"{shape.delay_ms},{shape.jitter_ms},{shape.loss_pct}"]
        command, self.forwarder = wire_command(self.native_wire)
        self._wire = self.spawn("wire", [*command, *args], track=False)
        with contextlib.suppress(OSError, AttributeError):
            os.sched_setscheduler(self._wire.pid, os.SCHED_FIFO, os.sched_param(WIRE_PRIORITY))

    # processes -------------------------------------------------------------------------
    def spawn(self, role: str, cmd: list[str], track: bool = True) -> subprocess.Popen:
        """Start ``cmd`` in ``role``'s namespace and wait for its ``ready`` line; it is
        stopped when the lab closes (or by ``stop``)."""
        proc = subprocess.Popen([*self.exec_prefix(role), *cmd], stdin=subprocess.DEVNULL,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        if track:
            self._procs.append(proc)
        line = _readline(proc, READY_TIMEOUT)
        if line.strip() != "ready":
            proc.kill()
            err = proc.communicate()[1].strip().splitlines()
            _stop(proc)
            raise LabError(f"{' '.join(cmd[:3])} in {role}: did not start "
                           f"({(err or [line.strip() or 'no output'])[-1]})")
        return proc

    def adopt(self, proc: subprocess.Popen) -> None:
        """Stop ``proc`` (started in a lab namespace by the caller) when the lab closes."""
        self._procs.append(proc)

    def measure(self, link: str, seconds: float = 1.0) -> dict[str, float]:
        """Measured ``{"rtt_ms", "rate_mbit"}`` of ``link``: TCP pings and a blast of
        ``seconds`` from its first role to its second (``probe.py``)."""
        a, b = LINKS[link]
        host = self.address(link, b)
        probe = [sys.executable, "-m", "snail_bench.netlab.probe"]
        server = self.spawn(b, [*probe, "serve", host, str(PROBE_PORT)])
        try:
            out = _run(*self.exec_prefix(a), *probe, "measure", host, str(PROBE_PORT),
                       "--seconds", str(seconds))
        finally:
            self.stop(server)
        return json.loads(out)

    def stop(self, proc: subprocess.Popen) -> None:
        _stop(proc)
        if proc in self._procs:
            self._procs.remove(proc)


def _readline(proc: subprocess.Popen, timeout: float) -> str:
    """The first stdout line of ``proc``, or '' if none came within ``timeout``."""
    import selectors

    assert proc.stdout is not None
    with selectors.DefaultSelector() as sel:
        sel.register(proc.stdout, selectors.EVENT_READ)
        if not sel.select(timeout):
            return ""
    return proc.stdout.readline()


def _stop(proc: subprocess.Popen, timeout: float = 10.0) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    for stream in (proc.stdout, proc.stderr):
        if stream is not None:
            stream.close()


def _sigterm_to_exit(signum: int, frame: FrameType | None) -> None:
    """SIGTERM unwinds like Ctrl-C does, so the lab's ``finally`` deletes what it made."""
    raise SystemExit(128 + signum)

