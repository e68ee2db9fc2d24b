"""The client's side of a secure invocation: one garbled run of a circuit on private bits.

The client keeps one TLS connection to each server for its whole lifetime (handshakes
per invocation would cost more than small circuits). A session is *prepared* before its
inputs exist, since garbling does not depend on them: the client draws a fresh session
id, label seed, offset delta and hash key from the OS CSPRNG,
- sends the garbler ``garble_request`` {sid, circuit, hash, seed, delta, key}: it garbles
  and streams the tables to the evaluator (which holds them) and returns the output
  zero-labels;
- sends the evaluator ``session_start`` {sid, circuit, hash}.
Invoking it then costs one round trip to the evaluator: the client sends its active
input labels ``L0(w) ^ bit(w) * delta`` (derived from the seed, so no oblivious transfer
is needed), the evaluator evaluates and returns the active output labels, and the client
decodes: a label that is neither L0 nor L0 ^ delta means tampering (ServiceError).

A caller that knows how many invocations of a circuit are coming (``expect``) lets the
runner keep sessions prepared (``ahead.py``), so the next one is garbled while the current
one is evaluated. The caller may also name the input bits every coming invocation
shares (a frame's image and map points; only the pose changes): their labels go to the
evaluator when the session is prepared, so an invocation sends only the rest. That
keeps its round trip's bytes small: on a delayed link, TCP paces or windows a 30 kB
burst over more than one trip. A session whose shared bits turn out different is
cancelled, never given a second label per wire.

Both connections are multiplexed by sid, so invocations may run concurrently. Any
failure (an ``error`` from a server, a lost connection, the timeout) tells the other
server to drop the session; a retryable one (busy, draining, a replica lost) runs again
on another replica within ``busy_wait`` (retry.py), else it raises ServiceError naming
the server and cause. Each address may stand for several replicas (replicas.py): every
session goes to the next garbler and evaluator in turn, and names its evaluator replica
to the garbler, which streams there only if its own operator's names reach it.
"""

from __future__ import annotations

import asyncio
import functools
import secrets
import time
from pathlib import Path
from typing import Any

import numpy as np

from snail_common import families
from snail_common.circuit import registry
from snail_common.gc import (
    active_input_labels,
    fresh_delta,
    labels_to_bytes,
)
from snail_common.net import messages, tls
from snail_common.net.chunks import runs, write_labels
from snail_common.net.conn import connect, format_addr
from snail_common.net.errors import (
    EVICTED,
    PEER_LOST,
    TOO_LARGE,
    ConnectionClosed,
    ProtocolError,
    RemoteError,
)
from snail_common.net.linkrates import AUTO, CLIENT_SCHEMES
from snail_common.pnp.spec import owner_bits

from .ahead import AheadPool
from .audit import Audits, named_signer
from .links import DEFAULT_LINK_TIMEOUT, Link, ServiceError
from .owner_pads import OwnerInputs, OwnerRefused
from .replicas import ReplicaSet
from .retry import blame, retryable
from .sessions import (
    LINKS,
    OWNER_LINKS,
    ROOMLESS,
    Address,
    FixedInputs,
    Invocation,
    Prepared,
    collect_answers,
    label_slots_to_send,
    parse_address,
    send_fixed_labels,
)
from .tuning import RunTuning

DEFAULT_TIMEOUT = 300.0
DEFAULT_BUSY_WAIT = 30.0  # seconds a run retries servers that answer busy
BACKOFF_FIRST, BACKOFF_MAX = 0.05, 2.0
DEFAULT_AHEAD = 1  # sessions garbled ahead of need, when the caller says more are coming


class AsyncSecureRunner:
    """Runs circuits securely on a garbler and an evaluator (asyncio API)."""

    def __init__(self, garbler_addr: Address, evaluator_addr: Address,
                 tls_dir: str | Path, timeout: float = DEFAULT_TIMEOUT,
                 connect_timeout: float = 10.0, ahead: int = DEFAULT_AHEAD,
                 busy_wait: float = DEFAULT_BUSY_WAIT, cert_name: str = "client",
                 link_timeout: float = DEFAULT_LINK_TIMEOUT,
                 scheme: str = AUTO, audits: Audits | None = None) -> None:
        families.register_all()
        self.audits = audits if audits is not None else Audits()  # audit.py
        # each a NAME:PORT that may stand for several replicas (replicas.py)
        self.garbler_addr = parse_address(garbler_addr, "garbler address")
        self.evaluator_addr = parse_address(evaluator_addr, "evaluator address")
        self.tls_dir = tls_dir
        self.ctx = tls.client_context(tls_dir, "client", cert_name)
        self.timeout = timeout
        self.connect_timeout = connect_timeout
        self.busy_wait = busy_wait
        self.link_timeout = link_timeout
        if scheme not in CLIENT_SCHEMES:
            raise ValueError(f"scheme must be one of {', '.join(CLIENT_SCHEMES)}, "
                             f"got {scheme!r}")
        self.last: Invocation | None = None
        self.totals = dict.fromkeys(LINKS, 0)
        self.invocations = 0
        self.retries = 0  # invocations run again after a retryable failure (retry.py)
        self.replicas = {role: ReplicaSet(role, addr, functools.partial(self._open, role))
                         for role, addr in (("garbler", self.garbler_addr),
                                            ("evaluator", self.evaluator_addr))}
        self.ahead = AheadPool(ahead, functools.partial(self._prepare, ahead=True),
                               self._cancel, self._adopt)
        # the garbling scheme of every session this runner asks for (auto: per session,
        # from what the garbler measured) and its garble-ahead depth: tuning.py
        self.tuning = RunTuning(scheme, self.ahead, ahead)
        self.owner = OwnerInputs(self.ctx, connect_timeout, timeout)  # owner_pads.py

    def use_frame(self, handle: bytes, map_owner: str, relay: str | None = None) -> None:
        """Runs of map-owner circuits from now on take the map owner's inputs of this
        frame unless they name their own (the handle its selection gave; its address as
        the garbler and this device reach it). Sessions garbled ahead serve any frame:
        each takes its frame's pad correction when it runs (owner_pads.py), through the
        evaluator at ``relay`` when given (relay.py)."""
        self.owner.use(handle, map_owner, relay)

    @property
    def scheme(self) -> str:
        """The scheme this runner asks for (``auto``: chosen per session)."""
        return self.tuning.scheme

    async def _open(self, role: str, addr: tuple[str, int]) -> Link:
        """A link to the ``role`` replica at ``addr``; its certificate must carry the name
        the replicas were reached by (their addresses are not in it)."""
        conn = await connect(*addr, self.ctx, "client", role, self.connect_timeout,
                             server_name=self.replicas[role].target[0])
        return Link(conn, self.link_timeout)

    async def connect(self) -> tuple[Link, Link]:
        """Links to the next garbler and evaluator replicas in turn (replicas.py)."""
        links = await asyncio.gather(self.replicas["garbler"].pick(),
                                     self.replicas["evaluator"].pick(),
                                     return_exceptions=True)  # both settle, no orphan task
        for link in links:
            if isinstance(link, BaseException):
                raise link
        return links[0], links[1]

    def expect(self, circuit_id: str, count: int, fixed: FixedInputs | None = None) -> None:
        """At least ``count`` invocations of ``circuit_id`` are coming, sharing the
        ``fixed`` input bits: their garbling starts now (``AheadPool.expect``)."""
        self.ahead.expect(circuit_id, count, fixed)

    def fixed(self, circuit_id: str) -> FixedInputs | None:
        """The input bits ``expect`` last declared shared by ``circuit_id``'s runs."""
        return self.ahead.fixed(circuit_id)

    async def run(self, circuit_id: str, input_bits: np.ndarray) -> np.ndarray:
        """Decoded output bits of one secure run; details in ``self.last``."""
        return (await self.invoke(circuit_id, input_bits)).outputs

    async def invoke(self, circuit_id: str, input_bits: np.ndarray,
                     frame: bytes | None = None) -> Invocation:
        """One secure run of ``circuit_id`` on ``input_bits`` (bool, one per input wire);
        a map-owner circuit's for the map owner's ``frame`` (default: ``use_frame``'s).

        A run refused as busy runs again, and one refused as draining or whose replica
        was lost does where another replica answers (retry.py): with a fresh session,
        after a jittered, doubling pause, for up to ``busy_wait`` seconds in all
        (``client_busy_wait_s`` in the timing; ``self.retries`` counts the runs again).
        A run whose reservation was evicted runs again at once; busy or evicted, the
        pool holds fewer sessions ahead (ahead.py)."""
        t0 = time.perf_counter()
        pause, attempt = BACKOFF_FIRST, 0
        while True:
            try:
                inv = await self._invoke_once(circuit_id, input_bits, attempt == 0, frame)
            except ServiceError as exc:
                if exc.code in ROOMLESS:
                    self.ahead.refused()
                waited = time.perf_counter() - t0
                again = exc.retry if exc.retry is not None else exc.code in ROOMLESS
                if not again or waited + pause > self.busy_wait:
                    if again:
                        raise ServiceError(f"{exc} (retried {attempt} times for "
                                           f"{waited:.1f} s, the --busy-wait limit is "
                                           f"{self.busy_wait:g} s)", exc.code) from None
                    raise
                attempt += 1
                self.retries += 1
                if exc.code != EVICTED:  # a server with no room: give it a moment
                    await asyncio.sleep(pause * (0.5 + secrets.randbelow(1000) / 1000))
                    pause = min(2 * pause, BACKOFF_MAX)
                continue
            if attempt:  # the time the refused attempts and their pauses took
                inv.timing["client_busy_wait_s"] = round(
                    time.perf_counter() - t0 - inv.wall_s, 4)
            return inv

    async def _invoke_once(self, circuit_id: str, input_bits: np.ndarray,
                           first: bool = True, frame: bytes | None = None) -> Invocation:
        t0 = time.perf_counter()
        bits = np.asarray(input_bits)
        session = (self.ahead.take(circuit_id, bits)
                   or await self.ahead.in_flight(circuit_id, bits)
                   or await self._prepare(circuit_id, fixed=False))
        self.audits.admit(session, self._cancel, self.replicas)  # none caught cheating
        iface, sid = session.iface, session.sid
        if bits.dtype != np.bool_ or bits.shape != (iface.n_inputs,):
            self._cancel(session)
            raise ValueError(f"input_bits must be a bool vector of {iface.n_inputs} bits "
                             f"for {circuit_id}, got {bits.dtype} {bits.shape}")
        if first:  # one use per invocation, however many attempts it takes
            self.ahead.used(circuit_id)
        owner_traffic: dict[str, int] = {}  # the pad correction's, map-owner runs only
        try:
            if session.tables_changed:  # while it was garbled ahead (ahead.take)
                await collect_answers(session)  # raises the evaluator's word
            if session.owner_bits:
                bits, owner_traffic = await self.owner.corrected(
                    session, bits, frame, functools.partial(collect_answers, session))
            labels = active_input_labels(session.seed, session.delta, bits)
            sent_e = sum(write_labels(session.evaluator.conn, "input_labels", sid,
                                      labels[a:b], a, len(session.todo))
                         for a, b in runs(session.todo))
            self.ahead.fill(circuit_id)  # the next sessions garble while this one evaluates
            await session.evaluator.conn.drain()
            results = await asyncio.wait_for(collect_answers(session), self.timeout)
        except asyncio.TimeoutError:
            self._cancel(session)
            raise ServiceError(f"{circuit_id}: no result within {self.timeout:g} s") \
                from None
        except OwnerRefused as exc:  # the map owner's word: neither server is to blame
            self._cancel(session)
            raise ServiceError(f"{circuit_id}: {exc}", exc.code, retry=False) from None
        except (ServiceError, ConnectionClosed) as exc:
            self._cancel(session)
            # a write that found the evaluator's link closing is its loss, retryable like
            # one the link reported: its connection_lost may not have come yet
            code = PEER_LOST if isinstance(exc, ConnectionClosed) else exc.code
            failed = ServiceError(f"{circuit_id}: {exc}", code,
                                  getattr(exc, "link", None) or session.evaluator)
            failed.retry = retryable(failed, session, self.replicas)
            blame(failed, session, self.replicas.values())
            raise failed from None
        finally:
            session.garbler.waiting.pop(sid, None)
            session.evaluator.waiting.pop(sid, None)
        (zero, g_in, g_stats), (active, e_in, e_stats) = results
        wall = time.perf_counter() - t0
        # decoded once the signed digests hold and, if drawn or failing, an audit (audit.py)
        outputs = await self.audits.check(session, zero, active, g_stats, e_stats,
                                          self.replicas)
        traffic = {"client_to_garbler": session.sent_g,
                   "client_to_evaluator": session.sent_e + sent_e,
                   "garbler_to_evaluator": int(g_stats["traffic"]["garbler_to_evaluator"]),
                   "evaluator_to_client": e_in, "garbler_to_client": g_in,
                   **{k: int(v) for k, v in g_stats["traffic"].items()
                      if k in OWNER_LINKS}, **owner_traffic}
        timing = {f"garbler_{k}": v for k, v in g_stats["timing"].items()}
        timing.update({f"evaluator_{k}": v for k, v in e_stats["timing"].items()})
        ahead = int(e_stats["traffic"].get("garbled_ahead", 0))
        self.tuning.measured_run(g_stats["timing"], session, traffic["garbler_to_evaluator"],
                                 wall,
                                 float(e_stats["timing"].get("wait_s", 0.0)) if ahead else 0.0)
        self.tuning.cycled(session, e_stats["timing"], wall)
        timing["client_ahead"] = float(self.ahead.depth)  # the depth it sized from them
        self.last = Invocation(outputs, traffic, wall + self.audits.audit_s, timing, ahead,
                               sent_e, session.scheme)
        self.invocations += 1
        for k, v in traffic.items():
            self.totals[k] = self.totals.get(k, 0) + v
        return self.last

    async def _prepare(self, circuit_id: str, fixed: bool = True,
                       ahead: bool = False) -> Prepared:
        """Ask for a session's garbling now, with fresh secrets (and, ``fixed``, send the
        labels of the inputs the coming invocations share; ``ahead``: a reservation for
        the pool, which a full server may refuse or take back). A link that died while
        this client was idle (a restarted server: its end of the connection is found
        closed only when written to) is reconnected once, with new secrets."""
        shared = self.ahead.fixed(circuit_id) if fixed else None
        try:
            return await self._prepare_once(circuit_id, shared, ahead)
        except ConnectionClosed:
            pass
        try:
            return await self._prepare_once(circuit_id, shared, ahead)
        except ConnectionClosed as exc:  # a replica lost twice over: another one?
            raise ServiceError(f"{circuit_id}: {exc}", PEER_LOST, retry=any(
                r.several() for r in self.replicas.values())) from None

    async def _prepare_once(self, circuit_id: str, fixed: FixedInputs | None,
                            ahead: bool) -> Prepared:
        loop = asyncio.get_running_loop()
        try:
            registry.check_id(circuit_id)
        except registry.UnknownCircuit as exc:
            raise ServiceError(str(exc)) from None
        garbler, evaluator = await self.connect()
        limits = [link.conn.info.get("max_and_gates") for link in (garbler, evaluator)]
        limit = min((x for x in limits if x is not None), default=None)
        try:  # nothing beyond the servers' limit is built, nor asked of them
            iface = await loop.run_in_executor(None, registry.interface, circuit_id, limit)
        except registry.CircuitTooLarge as exc:
            raise ServiceError(f"{exc}: more than the servers compile (their "
                               f"--max-and-gates)", TOO_LARGE) from None
        n_owner = owner_bits(iface)
        if n_owner and self.owner.frame is None:
            raise ServiceError(f"{circuit_id} takes the map owner's input: no frame was "
                               f"selected from a map owner")
        map_owner = self.owner.frame[1] if n_owner else ""
        owner = {"map_owner": map_owner} if n_owner else {}
        if fixed is not None and fixed.mask.shape != (iface.n_inputs,):
            raise ServiceError(f"{circuit_id}: the fixed inputs cover {fixed.mask.size} "
                               f"wires, the circuit has {iface.n_inputs}")
        todo = label_slots_to_send(iface, fixed)
        sid, seed, key = (secrets.token_bytes(16) for _ in range(3))
        delta = fresh_delta()
        scheme = self.tuning.next_scheme(circuit_id)
        to_g, to_e = garbler.open(sid), evaluator.open(sid)
        chash = iface.content_hash
        # said either way: a reservation's requests are the size of a live session's
        reserve = {"ahead": ahead}
        try:
            sent_e = evaluator.conn.write(messages.make(
                "session_start", sid=sid, circuit=circuit_id, hash=chash,
                scheme=scheme, **reserve, **named_signer(garbler)))
            if fixed is not None:
                sent_e += send_fixed_labels(evaluator, sid, seed, delta, fixed, todo)
            sent_g = garbler.conn.write(messages.make(
                "garble_request", sid=sid, circuit=circuit_id, hash=chash, seed=seed,
                delta=labels_to_bytes(delta), key=key, scheme=scheme, **reserve, **owner,
                **_replica(evaluator)))
            await asyncio.gather(evaluator.conn.drain(), garbler.conn.drain())
        except ConnectionClosed:
            garbler.cancel(sid)
            evaluator.cancel(sid)
            raise
        return Prepared(circuit_id, iface, sid, seed, delta, garbler, evaluator, to_g, to_e,
                        sent_g, sent_e, n_owner, map_owner, fixed, todo, scheme, key)

    @staticmethod
    def _adopt(session: Prepared, fixed: FixedInputs) -> bool:
        """Give a session prepared without a frame's labels (kept garbled between
        frames) this frame's ``fixed`` ones now; False where it cannot take them (its
        link broke, or they do not fit its circuit): it is then cancelled."""
        n_inputs = session.iface.n_inputs
        if session.fixed is not None or not session.usable \
                or fixed.mask.shape != (n_inputs,):
            return False
        todo = label_slots_to_send(session.iface, fixed)
        try:
            session.sent_e += send_fixed_labels(session.evaluator, session.sid, session.seed,
                                          session.delta, fixed, todo)
        except ConnectionClosed:
            return False
        session.fixed, session.todo = fixed, todo
        return True

    @staticmethod
    def _cancel(session: Prepared) -> None:
        """Tell both servers to drop a session this client gave up."""
        session.garbler.cancel(session.sid)
        session.evaluator.cancel(session.sid)

    async def health(self, role: str) -> dict[str, Any]:
        """The ``health`` message of the garbler or the evaluator (session counters)."""
        link = await self.replicas[role].pick()
        link.health = asyncio.get_running_loop().create_future()
        link.conn.write(messages.make("health_request"))
        try:
            return await asyncio.wait_for(asyncio.shield(link.health), self.connect_timeout)
        except (ConnectionClosed, ProtocolError, RemoteError, asyncio.TimeoutError) as exc:
            raise ServiceError(f"{role} health request failed: {exc!r}") from None

    async def close(self) -> None:
        await self.ahead.close()
        await asyncio.gather(*(r.close() for r in self.replicas.values()), self.owner.close(),
                             return_exceptions=True)

    async def __aenter__(self) -> AsyncSecureRunner:
        await self.connect()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()



def _replica(evaluator: Link) -> dict[str, str]:
    """How a garble request names the evaluator replica its session streams to: the
    address this client reached it at and the instance it announced (the garbler checks
    both against its own --evaluator names: snail_common.net.replicas)."""
    named: dict[str, str] = {}
    if evaluator.conn.peer:
        named["evaluator"] = format_addr(*evaluator.conn.peer[:2])
    if evaluator.conn.info.get("instance"):
        named["evaluator_id"] = evaluator.conn.info["instance"]
    return named

