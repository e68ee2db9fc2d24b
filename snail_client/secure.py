"""The client's side of a secure invocation: one garbled run of a circuit on private bits.

The client keeps one TLS connection to each server for its whole lifetime (handshakes
per invocation would cost more than small circuits). Per invocation it draws a fresh
session id, label seed, offset delta and hash key from the OS CSPRNG and

- sends the garbler ``garble_request`` {sid, circuit, hash, seed, delta, key};
- sends the evaluator ``session_start`` {sid, circuit, hash} and its active input labels
  ``L0(w) ^ bit(w) * delta`` (derived from the seed, so no oblivious transfer is needed);
- collects the evaluator's active output labels and the garbler's output zero-labels,
  each followed by a ``stats`` message, and decodes: a label that is neither L0 nor
  L0 ^ delta means tampering and raises ServiceError.

Both connections are multiplexed by sid, so invocations may run concurrently. Any
failure (an ``error`` from a server, a lost connection, the timeout) raises ServiceError
naming the server and cause, tells the other server to drop the session, and the next
invocation reconnects as needed.
"""

from __future__ import annotations

import asyncio
import contextlib
import secrets
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from snail_common import families
from snail_common.circuit import registry
from snail_common.gc import (
    IntegrityError,
    active_input_labels,
    decode_output_labels,
    fresh_delta,
    labels_to_bytes,
)
from snail_common.net import messages, tls
from snail_common.net.chunks import LabelAssembler, write_labels
from snail_common.net.conn import Connection, connect, format_addr, new_event_loop, parse_addr
from snail_common.net.errors import UNEXPECTED, ConnectionClosed, ProtocolError, RemoteError

LINKS = ("client_to_garbler", "client_to_evaluator", "garbler_to_evaluator",
         "evaluator_to_client", "garbler_to_client")
DEFAULT_TIMEOUT = 300.0


class ServiceError(Exception):
    """A secure invocation failed (network, server error, timeout or integrity)."""


@dataclass
class Invocation:
    """One secure run: decoded outputs, bytes per link, wall time, server timings."""

    outputs: np.ndarray
    traffic: dict[str, int]
    wall_s: float
    timing: dict[str, float] = field(default_factory=dict)


Address = str | tuple[str, int]


def _addr(value: Address, name: str) -> tuple[str, int]:
    if isinstance(value, tuple):
        return value
    try:
        return parse_addr(value)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None


class _Link:
    """One server connection, its frames dispatched to waiting invocations by sid."""

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self.role = conn.peer_role
        self.waiting: dict[bytes, asyncio.Queue] = {}
        self.health: asyncio.Future | None = None
        self.failure: Exception | None = None
        self._task = asyncio.get_running_loop().create_task(self._dispatch())

    @property
    def alive(self) -> bool:
        return self.failure is None and not self.conn.ended

    async def _dispatch(self) -> None:
        try:
            while True:
                msg, size = await self.conn.recv()
                sid = msg.get("sid")
                if sid is not None:
                    queue = self.waiting.get(sid)
                    if queue is not None:  # else: a session already given up
                        queue.put_nowait((msg, size))
                elif msg["t"] == "health" and self.health and not self.health.done():
                    self.health.set_result(msg)
                elif msg["t"] == "error":
                    raise RemoteError(msg["code"], msg["message"])
                elif msg["t"] == "bye":
                    raise ConnectionClosed(f"the {self.role} is shutting down")
                else:
                    raise ProtocolError(UNEXPECTED, f"the {self.role} sent {msg['t']}")
        except (ConnectionClosed, ProtocolError, RemoteError) as exc:
            self._broken(exc)

    def _broken(self, exc: Exception) -> None:
        self.failure = exc
        for queue in self.waiting.values():
            queue.put_nowait((exc, 0))
        if self.health and not self.health.done():
            self.health.set_exception(exc)
        self.conn.abort()

    def open(self, sid: bytes) -> asyncio.Queue:
        queue: asyncio.Queue = asyncio.Queue()
        self.waiting[sid] = queue
        return queue

    async def close(self) -> None:
        self._task.cancel()
        await asyncio.gather(self._task, return_exceptions=True)
        await self.conn.close(messages.make("bye"))


class AsyncSecureRunner:
    """Runs circuits securely on a garbler and an evaluator (asyncio API)."""

    def __init__(self, garbler_addr: Address, evaluator_addr: Address,
                 tls_dir: str | Path, timeout: float = DEFAULT_TIMEOUT,
                 connect_timeout: float = 10.0) -> None:
        families.register_all()
        self.garbler_addr = _addr(garbler_addr, "garbler address")
        self.evaluator_addr = _addr(evaluator_addr, "evaluator address")
        self.ctx = tls.client_context(tls_dir, "client")
        self.timeout = timeout
        self.connect_timeout = connect_timeout
        self.last: Invocation | None = None
        self.totals = dict.fromkeys(LINKS, 0)
        self.invocations = 0
        self._links: dict[str, _Link] = {}
        self._lock = asyncio.Lock()

    async def _link(self, role: str) -> _Link:
        async with self._lock:
            link = self._links.get(role)
            if link is None or not link.alive:
                addr = self.garbler_addr if role == "garbler" else self.evaluator_addr
                try:
                    conn = await connect(*addr, self.ctx, "client", role,
                                         self.connect_timeout)
                except ConnectionClosed as exc:
                    raise ServiceError(str(exc)) from None
                link = self._links[role] = _Link(conn)
            return link

    async def connect(self) -> tuple[_Link, _Link]:
        """Open both connections now (otherwise the first run does)."""
        links = await asyncio.gather(self._link("garbler"), self._link("evaluator"),
                                     return_exceptions=True)  # both settle, no orphan task
        for link in links:
            if isinstance(link, BaseException):
                raise link
        return links[0], links[1]

    async def run(self, circuit_id: str, input_bits: np.ndarray) -> np.ndarray:
        """Decoded output bits of one secure run; details in ``self.last``."""
        return (await self.invoke(circuit_id, input_bits)).outputs

    async def invoke(self, circuit_id: str, input_bits: np.ndarray) -> Invocation:
        """One secure run of ``circuit_id`` on ``input_bits`` (bool, one per input wire)."""
        loop = asyncio.get_running_loop()
        try:
            iface = await loop.run_in_executor(None, registry.interface, circuit_id)
        except registry.UnknownCircuit as exc:
            raise ServiceError(str(exc)) from None
        bits = np.asarray(input_bits)
        if bits.dtype != np.bool_ or bits.shape != (iface.n_inputs,):
            raise ValueError(f"input_bits must be a bool vector of {iface.n_inputs} bits "
                             f"for {circuit_id}, got {bits.dtype} {bits.shape}")
        garbler, evaluator = await self.connect()
        t0 = time.perf_counter()
        sid, seed, key = (secrets.token_bytes(16) for _ in range(3))
        delta = fresh_delta()
        labels = active_input_labels(seed, delta, bits)
        n_out, chash = iface.n_outputs, iface.content_hash
        to_g, to_e = garbler.open(sid), evaluator.open(sid)

        async def exchange() -> tuple[int, int, list]:
            sent_e = evaluator.conn.write(messages.make(
                "session_start", sid=sid, circuit=circuit_id, hash=chash))
            sent_e += write_labels(evaluator.conn, "input_labels", sid, labels)
            sent_g = garbler.conn.write(messages.make(
                "garble_request", sid=sid, circuit=circuit_id, hash=chash, seed=seed,
                delta=labels_to_bytes(delta), key=key))
            await asyncio.gather(evaluator.conn.drain(), garbler.conn.drain())
            results = await self._collect((garbler, to_g, "output_zero_labels"),
                                          (evaluator, to_e, "output_labels"), n_out)
            return sent_g, sent_e, results

        try:
            sent_g, sent_e, results = await asyncio.wait_for(exchange(), self.timeout)
        except asyncio.TimeoutError:
            self._cancel(sid, garbler, evaluator)
            raise ServiceError(f"{circuit_id}: no result within {self.timeout:g} s") \
                from None
        except (ServiceError, ConnectionClosed) as exc:
            self._cancel(sid, garbler, evaluator)
            raise ServiceError(f"{circuit_id}: {exc}") from None
        finally:
            garbler.waiting.pop(sid, None)
            evaluator.waiting.pop(sid, None)
        (zero, g_in, g_stats), (active, e_in, e_stats) = results
        wall = time.perf_counter() - t0
        try:
            outputs = decode_output_labels(delta, zero, active)
        except IntegrityError as exc:
            raise ServiceError(f"{circuit_id}: integrity check failed, the result was "
                               f"tampered with: {exc}") from None
        traffic = {"client_to_garbler": sent_g, "client_to_evaluator": sent_e,
                   "garbler_to_evaluator": int(g_stats["traffic"]["garbler_to_evaluator"]),
                   "evaluator_to_client": e_in, "garbler_to_client": g_in}
        timing = {f"garbler_{k}": v for k, v in g_stats["timing"].items()}
        timing.update({f"evaluator_{k}": v for k, v in e_stats["timing"].items()})
        self.last = Invocation(outputs, traffic, wall, timing)
        self.invocations += 1
        for k, v in traffic.items():
            self.totals[k] += v
        return self.last

    async def _collect(self, *args: Any) -> list[tuple[np.ndarray, int, dict[str, Any]]]:
        """Both servers' label vectors and stats; the first failure cancels the other."""
        *sides, n_out = args
        tasks = [asyncio.ensure_future(_labels_and_stats(link, queue, kind, n_out))
                 for link, queue, kind in sides]
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_EXCEPTION)
            for task in done:
                if task.exception() is not None:
                    raise task.exception()
            return [t.result() for t in tasks]
        finally:
            for task in tasks:
                task.cancel()

    @staticmethod
    def _cancel(sid: bytes, *links: _Link) -> None:
        """Tell both servers to drop a session this client gave up."""
        for link in links:
            if link.alive:
                link.conn.post(messages.error("aborted", "the client gave up the session",
                                              sid))

    async def health(self, role: str) -> dict[str, Any]:
        """The ``health`` message of the garbler or the evaluator (session counters)."""
        link = await self._link(role)
        link.health = asyncio.get_running_loop().create_future()
        link.conn.write(messages.make("health_request"))
        try:
            return await asyncio.wait_for(asyncio.shield(link.health), self.connect_timeout)
        except (ConnectionClosed, ProtocolError, RemoteError, asyncio.TimeoutError) as exc:
            raise ServiceError(f"{role} health request failed: {exc!r}") from None

    async def close(self) -> None:
        links, self._links = list(self._links.values()), {}
        await asyncio.gather(*(link.close() for link in links), return_exceptions=True)

    async def __aenter__(self) -> AsyncSecureRunner:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


async def _labels_and_stats(link: _Link, queue: asyncio.Queue, kind: str,
                            n_out: int) -> tuple[np.ndarray, int, dict[str, Any]]:
    """Read one server's label chunks then its stats for a session."""
    labels = LabelAssembler(kind, n_out)
    received = 0
    where = f"the {link.role} at {format_addr(*link.conn.peer[:2])}" if link.conn.peer \
        else f"the {link.role}"
    while True:
        msg, size = await queue.get()
        if isinstance(msg, Exception):
            raise ServiceError(f"{where}: {msg}")
        received += size
        if msg["t"] == "error":
            raise ServiceError(f"{where} reported {msg['code']}: {msg['message']}")
        if msg["t"] == kind:
            try:
                labels.add(msg)
            except ProtocolError as exc:
                raise ServiceError(f"{where}: {exc}") from None
        elif msg["t"] == "stats" and labels.complete:
            return labels.labels(), received, msg
        else:
            raise ServiceError(f"{where} sent {msg['t']} out of order")


class SecureRunner:
    """Blocking wrapper of AsyncSecureRunner with its own event loop (uvloop)."""

    def __init__(self, garbler_addr: Address, evaluator_addr: Address,
                 tls_dir: str | Path, timeout: float = DEFAULT_TIMEOUT,
                 connect_timeout: float = 10.0) -> None:
        self._loop = new_event_loop()
        self._runner = AsyncSecureRunner(garbler_addr, evaluator_addr, tls_dir, timeout,
                                         connect_timeout)

    def run(self, circuit_id: str, input_bits: np.ndarray) -> np.ndarray:
        """Decoded output bits; traffic and time of the run in ``self.last``."""
        return self._loop.run_until_complete(self._runner.run(circuit_id, input_bits))

    def invoke(self, circuit_id: str, input_bits: np.ndarray) -> Invocation:
        return self._loop.run_until_complete(self._runner.invoke(circuit_id, input_bits))

    def health(self, role: str) -> dict[str, Any]:
        return self._loop.run_until_complete(self._runner.health(role))

    @property
    def last(self) -> Invocation | None:
        return self._runner.last

    @property
    def totals(self) -> dict[str, int]:
        return self._runner.totals

    @property
    def invocations(self) -> int:
        return self._runner.invocations

    def close(self) -> None:
        if not self._loop.is_closed():
            with contextlib.suppress(Exception):
                self._loop.run_until_complete(self._runner.close())
            self._loop.close()

    def __enter__(self) -> SecureRunner:
        self._loop.run_until_complete(self._runner.connect())
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
