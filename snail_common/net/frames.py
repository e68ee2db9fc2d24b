"""Framing: a 4-byte big-endian length, then one msgpack map (protocol version ``v``, type
``t``, fields; see messages.py).

Decoding is strict: a frame longer than the receiver's maximum is refused before its body
is read; the body must be exactly one msgpack map with string keys, no duplicate keys and
no extension types (msgpack never builds objects beyond plain data, and pickle is never
used); the version must match and the message must fit the schema. Every violation is a
ProtocolError naming it. Large binary fields (garbled tables, labels) are written as a
separate buffer after their msgpack header, so they are not copied into the frame; on the
receiving side a large frame's ``tables`` data is a view of the buffer TLS decrypted it
into, not a copy (FrameReader, ``lent``).
"""

from __future__ import annotations

import struct
from collections.abc import Mapping
from typing import Any

import msgpack

from .errors import MALFORMED, OVERSIZE, VERSION, ProtocolError
from .messages import MAX_TEXT, validate
from .seal import SLACK, TAG, FrameSeal

PROTOCOL_VERSION = 1
MAX_FRAME = 4 << 20  # bytes of one frame body; table frames are ~1 MiB
LENGTH = struct.Struct(">I")
_INLINE_BIN = 1 << 14  # shorter binary fields are packed inline


def encode(msg: Mapping[str, Any]) -> list[bytes | memoryview]:
    """The frame of ``msg`` (a dict from messages.make) as buffers to write in order; a
    large binary field (bytes or a byte memoryview) is one of them, uncopied."""
    packer = msgpack.Packer(use_bin_type=True, autoreset=True)
    parts: list[bytes] = []
    head = bytearray(packer.pack_map_header(len(msg) + 1))
    head += packer.pack("v") + packer.pack(PROTOCOL_VERSION)
    for key, value in msg.items():
        head += packer.pack(key)
        if isinstance(value, (bytes, memoryview)) and len(value) > _INLINE_BIN:
            head += _bin_header(len(value))
            parts += [bytes(head), value]
            head = bytearray()
        else:
            head += packer.pack(bytes(value) if isinstance(value, memoryview) else value)
    if head:
        parts.append(bytes(head))
    size = sum(len(p) for p in parts)
    if size > MAX_FRAME:
        raise ProtocolError(OVERSIZE, f"{msg.get('t')} frame of {size} bytes exceeds the "
                                      f"maximum of {MAX_FRAME}")
    return [LENGTH.pack(size), *parts]


def _bin_header(n: int) -> bytes:
    """msgpack's bin 8/16/32 header for ``n`` bytes."""
    if n < 1 << 8:
        return b"\xc4" + n.to_bytes(1, "big")
    if n < 1 << 16:
        return b"\xc5" + n.to_bytes(2, "big")
    return b"\xc6" + n.to_bytes(4, "big")


def encode_bytes(msg: Mapping[str, Any]) -> bytes:
    """The frame of ``msg`` as one bytes object (tests, small messages)."""
    return b"".join(encode(msg))


# Bounds from the message catalogue (messages.py): a message is one map of at most a few
# dozen fields, holding at most a couple of small maps or lists (traffic and timing
# numbers, family names); bulk data is always one bin field. A frame that needs more is
# refused by the unpacker while it has built only a few hundred small objects (a 4 MiB
# frame of four million empty maps used to become ~300 MB of Python objects).
MAX_CONTAINERS = 8  # maps and lists in one frame
LIMITS = {"max_map_len": 32, "max_array_len": 64, "max_str_len": 4 * MAX_TEXT,
          "max_bin_len": MAX_FRAME, "max_ext_len": 0}


class _Containers:
    """unpackb hooks: maps without repeated keys, and at most MAX_CONTAINERS of all."""

    def __init__(self) -> None:
        self.left = MAX_CONTAINERS

    def _count(self) -> None:
        self.left -= 1
        if self.left < 0:
            raise ProtocolError(MALFORMED, f"frame holds more than {MAX_CONTAINERS} maps "
                                           f"and lists")

    def pairs(self, pairs: list[tuple[Any, Any]]) -> dict[str, Any]:
        self._count()
        out = dict(pairs)
        if len(out) != len(pairs):
            raise ProtocolError(MALFORMED, "a map in the frame repeats a key")
        return out

    def items(self, items: list[Any]) -> list[Any]:
        self._count()
        return items


LENT = frozenset({"tables"})  # messages whose large binary fields may be views of the body
_BIN_LEN = {0xC4: 1, 0xC5: 2, 0xC6: 4}  # msgpack bin 8/16/32: bytes of the length
_STR_LEN = {0xD9: 1, 0xDA: 2, 0xDB: 4}
_FIXED = {0xC0: 0, 0xC2: 0, 0xC3: 0, 0xCA: 4, 0xCB: 8, 0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8,
          0xD0: 1, 0xD1: 2, 0xD2: 4, 0xD3: 8}  # nil, bools, numbers: bytes after the tag
_EMPTY_BIN = b"\xc4\x00"
_ROUND = 64 << 10  # body buffers are whole multiples of this


def decode(body: bytes | memoryview, lend: bool = False) -> dict[str, Any]:
    """A frame body -> the validated message (without ``v``). With ``lend``, the large
    binary fields of a ``LENT`` message are views of ``body`` (which must then stay
    untouched while they are used), not copies. A refusal carries no traceback: a
    connection keeps its last error, and a traceback would keep what the frame decoded
    to."""
    try:
        return _decode(body, lend)
    except ProtocolError as exc:
        raise exc.with_traceback(None) from None


def lent(msg: Mapping[str, Any]) -> bool:
    """Whether ``msg`` holds views of the frame buffer it was decoded from."""
    return any(isinstance(v, memoryview) for v in msg.values())


def _decode(body: bytes | memoryview, lend: bool) -> dict[str, Any]:
    views: dict[bytes, memoryview] = {}
    if lend:
        body, views = _lift_bins(memoryview(body))
    hooks = _Containers()
    try:
        msg = msgpack.unpackb(body, raw=False, strict_map_key=True, use_list=True,
                              object_pairs_hook=hooks.pairs, list_hook=hooks.items,
                              **LIMITS)
    except ProtocolError:
        raise
    except (ValueError, msgpack.UnpackException) as exc:
        raise ProtocolError(MALFORMED, f"frame is not valid msgpack: {exc}") from None
    if not isinstance(msg, dict):
        raise ProtocolError(MALFORMED, f"frame holds a {type(msg).__name__}, not a map")
    for key, view in views.items():  # the lifted fields, as views or (not lent) copies
        name = msgpack.unpackb(key, raw=False)
        msg[name] = view if msg.get("t") in LENT else bytes(view)
    version = msg.pop("v", None)
    if version != PROTOCOL_VERSION:
        raise ProtocolError(VERSION, f"protocol version {version!r} is not supported "
                                     f"(this build speaks {PROTOCOL_VERSION})")
    validate(msg)
    return msg


def _lift_bins(body: memoryview) -> tuple[bytes | memoryview, dict[bytes, memoryview]]:
    """A flat top-level map with its large bin values cut out: the body with each one
    replaced by an empty bin (for msgpack's strict decoding) and the views of them by
    packed key. Anything else (a nested value, a short or cut frame) is left whole to
    msgpack, which decodes or refuses it as before."""
    size = len(body)
    if size < 3 or not (0x80 <= body[0] <= 0x8F or body[0] == 0xDE):
        return body, {}
    pairs, pos = (body[0] & 0x0F, 1) if body[0] != 0xDE else (
        int.from_bytes(body[1:3], "big"), 3)
    parts: list[memoryview | bytes] = []
    views: dict[bytes, memoryview] = {}
    start = 0  # of the body not yet in parts
    for _ in range(pairs):
        key = pos
        pos = _scalar_end(body, key)
        if pos is None or pos >= size:
            return body, {}
        tag = body[pos]
        if tag in _BIN_LEN:
            width = _BIN_LEN[tag]
            n = int.from_bytes(body[pos + 1 : pos + 1 + width], "big")
            data = pos + 1 + width
            if n > _INLINE_BIN and data + n <= size:
                parts += [body[start:pos], _EMPTY_BIN]
                views[bytes(body[key:pos])] = body[data : data + n]
                pos = start = data + n
                continue
        pos = _scalar_end(body, pos)
        if pos is None:
            return body, {}
    if not views:
        return body, {}
    parts.append(body[start:])
    return b"".join(parts), views


def _scalar_end(body: memoryview, pos: int) -> int | None:
    """Where the msgpack scalar (nil, bool, number, str, bin) at ``pos`` ends; None for
    anything else or past the end."""
    if pos >= len(body):
        return None
    tag = body[pos]
    if tag <= 0x7F or tag >= 0xE0:  # fixint
        end = pos + 1
    elif 0xA0 <= tag <= 0xBF:  # fixstr
        end = pos + 1 + (tag & 0x1F)
    elif tag in _FIXED:
        end = pos + 1 + _FIXED[tag]
    elif tag in _BIN_LEN or tag in _STR_LEN:
        width = _BIN_LEN.get(tag) or _STR_LEN[tag]
        end = pos + 1 + width + int.from_bytes(body[pos + 1 : pos + 1 + width], "big")
    else:
        return None
    return end if end <= len(body) else None


def _oversize(length: int, max_frame: int) -> ProtocolError:
    return ProtocolError(OVERSIZE, f"frame of {length} bytes exceeds the maximum of "
                                   f"{max_frame}")


class BodyPool:
    """Received frame bodies kept for later frames of the connections that share it, up to
    ``limit`` bytes: a buffer that comes back is memory already mapped, where a new one
    is fresh pages the kernel faults in and zeroes (at n = 256 most of the evaluator's
    page faults). It never makes a reader hold more: a buffer is only taken in place of
    one the reader would allocate."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self.held = 0
        self._free: list[bytearray] = []

    def take(self, size: int) -> bytearray | None:
        """The smallest kept buffer of ``size`` to twice ``size`` bytes, if there is one: a
        small frame does not pin a much larger buffer (what it holds is counted by its
        length, e.g. against the garbled-ahead budget)."""
        fits = [i for i, buf in enumerate(self._free) if size <= len(buf) <= 2 * size]
        if not fits:
            return None
        buf = self._free.pop(min(fits, key=lambda i: len(self._free[i])))  # the closest fit
        self.held -= len(buf)
        return buf

    def clear(self) -> None:
        """Let every kept buffer go (an idle daemon's memory follows its load)."""
        self._free.clear()
        self.held = 0

    def give(self, buf: bytearray) -> None:
        """Keep ``buf`` (no view of it may be read or written any more) if it fits."""
        if self.held + len(buf) <= self.limit and all(b is not buf for b in self._free):
            self._free.append(buf)
            self.held += len(buf)


class FrameReader:
    """Incremental decoder for a BufferedProtocol: the transport decrypts straight into
    ``buffer()``, ``filled(n)`` decodes the frames those bytes complete.

    Small frames share one buffer; a larger frame body (garbled tables) goes to a
    dedicated buffer, so the bytes are written once by TLS. A ``tables`` frame's data is
    then a view of that buffer: the frame keeps it, and the consumer may hand it back with
    ``recycle`` once done, to a BodyPool the next bodies are received into. Other frames
    are copied once by msgpack and the buffer is reused. A body buffer grows with the
    bytes that arrive (doubling, up to the announced length), not with what a header
    announces: a peer must send what it makes this side hold. The length is checked
    before any of the body is accepted, so an oversized frame costs nothing.
    """

    SMALL = 256 << 10
    BIG = 16 << 10  # incomplete frames longer than this go to the dedicated buffer
    MIN_FREE = 16 << 10
    POOL = 4 << 20  # bytes of recycled bodies a reader of its own keeps

    def __init__(self, max_frame: int = MAX_FRAME, pool: BodyPool | None = None,
                 seal: FrameSeal | None = None) -> None:
        self._seal = seal  # a sealed link's bodies are opened before they are decoded
        self.max_frame = max_frame + (TAG if seal is not None else 0)
        self._pool = pool if pool is not None else BodyPool(self.POOL)
        self._small = bytearray(self.SMALL)
        self._start = self._end = 0
        self._big = bytearray(0)
        self._big_len = 0  # > 0 while a body is being received into _big
        self._big_pos = 0

    @property
    def partial(self) -> bool:
        """Part of a frame is buffered (an EOF now cuts a frame)."""
        return self._big_len > 0 or self._end > self._start

    def buffer(self) -> memoryview:
        """Where the next received bytes must be written."""
        if self._big_len:
            if self._big_pos == len(self._big):  # full, the body is not: grow
                self._grow(min(self._big_len, 2 * len(self._big)))
            return memoryview(self._big)[self._big_pos : min(self._big_len, len(self._big))]
        if len(self._small) - self._end < self.MIN_FREE:
            n = self._end - self._start
            self._small[:n] = self._small[self._start : self._end]
            self._start, self._end = 0, n
        return memoryview(self._small)[self._end :]

    def filled(self, n: int) -> list[tuple[dict[str, Any], int]]:
        """Account ``n`` bytes written to ``buffer()``; the completed (message, wire size)
        pairs. Raises ProtocolError at the first bad frame (earlier ones are lost with
        the connection, which the caller closes)."""
        if self._big_len:
            self._big_pos += n
            if self._big_pos < self._big_len:
                return []
            length, self._big_len = self._big_len, 0
            return [(self._decode_big(length), LENGTH.size + length)] + self._parse()
        self._end += n
        return self._parse()

    def _parse(self) -> list[tuple[dict[str, Any], int]]:
        out = []
        buf = self._small
        while self._end - self._start >= LENGTH.size:
            (length,) = LENGTH.unpack_from(buf, self._start)
            if length > self.max_frame:
                raise _oversize(length, self.max_frame)
            body = self._start + LENGTH.size
            have = self._end - body
            if have >= length:
                with memoryview(buf) as view:
                    out.append((self._decode_small(view[body : body + length]),
                                LENGTH.size + length))
                self._start = body + length
            elif length > self.BIG:
                self._big_pos = 0
                if len(self._big) < length:  # a recycled body that holds it all, or grow
                    self._big = self._pool.take(length) or self._big
                self._grow(min(length, max(2 * have, self.SMALL)))
                self._big[:have] = buf[body : self._end]
                self._big_len, self._big_pos = length, have
                self._start = self._end = 0
                break
            else:
                break
        if self._start == self._end:
            self._start = self._end = 0
        return out

    def _decode_small(self, body: memoryview) -> dict[str, Any]:
        if self._seal is None:
            return decode(body)
        plain = bytearray(len(body) + SLACK)
        return decode(memoryview(plain)[: self._seal.open(body, memoryview(plain))])

    def _decode_big(self, length: int) -> dict[str, Any]:
        """The message in the body buffer: a ``tables`` frame's data stays a view of the
        buffer it is in (of the body's, or on a sealed link of the one it was opened
        into), and the next body goes to another."""
        body = memoryview(self._big)[:length]
        if self._seal is None:
            msg = decode(body, lend=True)
            if lent(msg):
                self._big = bytearray(0)
            return msg
        plain = self._pool.take(length + SLACK) or bytearray(length + SLACK)
        msg = decode(memoryview(plain)[: self._seal.open(body, memoryview(plain))], lend=True)
        if not lent(msg):
            self._pool.give(plain)
        return msg

    def release(self) -> None:
        """Drop the body buffers (after a refused frame: nothing more will be read)."""
        self._big, self._big_len, self._big_pos = bytearray(0), 0, 0

    def recycle(self, data: memoryview) -> None:
        """Take back the buffer under ``data``, a view from a ``tables`` frame this reader
        decoded, once nothing reads it any more (it will be overwritten)."""
        if isinstance(data.obj, bytearray) and data.obj is not self._big:
            self._pool.give(data.obj)

    def _grow(self, size: int) -> None:
        """Make the body buffer at least ``size`` bytes, keeping what it holds (a new
        buffer: the transport may still hold a view of the old one)."""
        if len(self._big) < size:  # whole 64 KiB: frames of about one size share buffers
            bigger = bytearray(max(size, min(self.max_frame, -(-size // _ROUND) * _ROUND)))
            bigger[: self._big_pos] = self._big[: self._big_pos]
            self._big = bigger
