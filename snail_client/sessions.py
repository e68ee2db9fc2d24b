"""What a secure invocation is made of on the client: the result of one run
(``Invocation``), a session prepared ahead of its inputs (``Prepared``), the input bits a
frame's invocations share (``FixedInputs``) and which label slots a session still needs,
and the links whose bytes are counted."""

from __future__ import annotations

import asyncio
from dataclasses import dataclass, field

import numpy as np

from snail_common.circuit.ir import FIRST_INPUT, Interface
from snail_common.gc import active_input_labels
from snail_common.gc.stream import DEFAULT_SCHEME
from snail_common.net.chunks import runs, write_labels
from snail_common.net.conn import parse_addr
from snail_common.net.errors import BUSY, EVICTED, PEER_LOST, TABLES_CHANGED
from snail_common.pnp.spec import masked_wires, owner_bits

from .links import Inbox, Link, ServiceError, labels_and_stats

LINKS = ("client_to_garbler", "client_to_evaluator", "garbler_to_evaluator",
         "evaluator_to_client", "garbler_to_client")
OWNER_LINKS = ("garbler_to_mapowner", "mapowner_to_garbler")  # map-owner circuits only
ROOMLESS = frozenset({BUSY, EVICTED})  # a server's answers to a client that holds too much
# how long a run whose garbler lost the evaluator waits for the evaluator's own word (it
# comes at once where the evaluator closed the link on purpose: collect_answers)
EVALUATOR_GRACE = 2.0


@dataclass
class Invocation:
    """One secure run: decoded outputs, bytes per link, wall time, server timings, how
    many table bytes reached the evaluator before this run's inputs (garble-ahead), and
    the input-label bytes sent when it was invoked (the rest went ahead: FixedInputs)."""

    outputs: np.ndarray
    traffic: dict[str, int]
    wall_s: float
    timing: dict[str, float] = field(default_factory=dict)
    garbled_ahead: int = 0
    labels_on_call: int = 0
    scheme: str = DEFAULT_SCHEME  # the garbling scheme of its session


@dataclass(eq=False)
class Prepared:
    """A session whose garbling was requested: its secrets and both servers' inboxes."""

    circuit_id: str
    iface: Interface
    sid: bytes
    seed: bytes
    delta: np.ndarray
    garbler: Link
    evaluator: Link
    to_g: Inbox
    to_e: Inbox
    sent_g: int
    sent_e: int
    owner_bits: int = 0  # input wires (the last ones) whose labels the map owner gives
    map_owner: str = ""  # the address of that map owner (its OT ran for this session)
    fixed: FixedInputs | None = None  # input bits whose labels were sent when prepared
    # the client's label slots (two constants, one per input wire but the map owner's)
    # still to send when invoked: those not sent with ``fixed``
    todo: np.ndarray = field(default_factory=lambda: np.ones(0, bool))
    scheme: str = DEFAULT_SCHEME  # the garbling scheme asked of both servers
    key: bytes = b""  # the hash key asked of the garbler (an audit garbles again with it)

    @property
    def usable(self) -> bool:
        return (self.garbler.alive and self.evaluator.alive
                and not self.to_g.failed and not self.to_e.failed)

    @property
    def tables_changed(self) -> bool:
        """The evaluator failed it because the garbler's tables reached it changed (on
        the server link, or sent so): a failure the run it was for must report."""
        return self.to_e.error_code in TABLES_CHANGED

    @property
    def refused(self) -> bool:
        """A server had no room for it (busy) or gave its place to a live session
        (evicted): the client holds more ahead than the servers can spare."""
        return bool({self.to_g.error_code, self.to_e.error_code} & ROOMLESS)


Address = str | tuple[str, int]


@dataclass(frozen=True, eq=False)
class FixedInputs:
    """Input bits that every coming invocation of a circuit shares: ``mask`` says which
    wires, ``bits`` their values (both bool, one per input wire)."""

    mask: np.ndarray
    bits: np.ndarray

    def __post_init__(self) -> None:
        if self.mask.dtype != np.bool_ or self.bits.dtype != np.bool_ \
                or self.mask.shape != self.bits.shape or self.mask.ndim != 1:
            raise ValueError("fixed inputs: mask and bits must be bool vectors of one length")

    @staticmethod
    def same(a: FixedInputs | None, b: FixedInputs | None) -> bool:
        return a is b or (a is not None and b is not None and np.array_equal(a.mask, b.mask)
                          and np.array_equal(a.bits, b.bits))

    def matches(self, bits: np.ndarray) -> bool:
        return bits.shape == self.bits.shape and np.array_equal(bits[self.mask],
                                                                 self.bits[self.mask])


def parse_address(value: Address, name: str) -> tuple[str, int]:
    """(host, port) of ``value``; a ValueError names the address (``name``) at fault."""
    if isinstance(value, tuple):
        return value
    try:
        return parse_addr(value)
    except ValueError as exc:
        raise ValueError(f"{name}: {exc}") from None


def label_slots_to_send(iface: Interface, fixed: FixedInputs | None) -> np.ndarray:
    """The client's label slots (two constants, then its input wires but the map owner's)
    still to send when a session is invoked: all of them, or those the ``fixed`` labels
    do not cover. A map-owner circuit's ``world_masked`` share is always among them: it
    takes the session's own pad correction, known only when the session runs."""
    n_inputs = iface.n_inputs - owner_bits(iface)
    todo = np.ones(FIRST_INPUT + n_inputs, bool)
    if fixed is not None:
        todo[:FIRST_INPUT] = False  # the constants' labels never change either
        todo[FIRST_INPUT:] = ~fixed.mask[:n_inputs]
        masked = masked_wires(iface)
        todo[FIRST_INPUT + masked.start:FIRST_INPUT + masked.stop] = True
    return todo


def send_fixed_labels(evaluator: Link, sid: bytes, seed: bytes, delta: np.ndarray,
                fixed: FixedInputs, todo: np.ndarray) -> int:
    """Queue the labels of the slots ``todo`` leaves out (the constants and the
    ``fixed`` inputs) to the evaluator; the bytes written."""
    labels = active_input_labels(seed, delta, fixed.bits)
    return sum(write_labels(evaluator.conn, "input_labels", sid, labels[a:b], a, todo.size)
               for a, b in runs(~todo))


async def collect_answers(session: Prepared) -> list[tuple[np.ndarray, int, dict]]:
    """Both servers' label vectors and stats of a run; the first failure cancels the
    other. A garbler that lost the evaluator only knows the link went: the evaluator's own
    word, the reason it may have closed it (the tables changed on it), is waited for up
    to EVALUATOR_GRACE and raised instead when it comes."""
    n_out = session.iface.n_outputs
    garbler = asyncio.ensure_future(labels_and_stats(
        session.garbler, session.to_g, "output_zero_labels", n_out))
    evaluator = asyncio.ensure_future(labels_and_stats(
        session.evaluator, session.to_e, "output_labels", n_out))
    tasks = [garbler, evaluator]
    try:
        done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_EXCEPTION)
        if _lost_evaluator(garbler):
            await asyncio.wait([evaluator], timeout=EVALUATOR_GRACE)
            if evaluator.done() and evaluator.exception() is not None:
                raise evaluator.exception()
        for task in done:
            if task.exception() is not None:
                raise task.exception()
        return [t.result() for t in tasks]
    finally:
        for task in tasks:
            task.cancel()


def _lost_evaluator(garbler: asyncio.Future) -> bool:
    """Whether the garbler's side of a run failed on its word that it lost the evaluator."""
    if not garbler.done() or garbler.exception() is None:
        return False
    failure = garbler.exception()
    return isinstance(failure, ServiceError) and failure.code == PEER_LOST
