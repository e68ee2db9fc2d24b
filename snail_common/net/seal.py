"""Sealed frames for the table data link (datalink.py, ``--table-link aead``): each frame
body is encrypted and authenticated whole with AES-256-GCM from OpenSSL (through
``cryptography``), a frame of about a MiB at a time where TLS works in 16 KiB records.

The key is fresh per data link, handed out over the mutual-TLS control connection. The
nonce is the direction (4 bytes) and the frame's number in that direction (8 bytes), never
sent: a frame dropped, replayed, reordered or moved to the other direction fails its tag,
as does any changed byte. The frame's length prefix is authenticated with it.
"""

from __future__ import annotations

import struct

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives.ciphers import Cipher, algorithms, modes

from .errors import LINK, ProtocolError

TAG = 16  # GCM tag bytes after each sealed body
SLACK = 15  # update_into writes into a buffer at least a block minus one longer
KEY_BYTES = 32
SPARE = 4  # sealed frame buffers kept for reuse
GARBLER_TO_EVALUATOR = b"g2e\x00"
EVALUATOR_TO_GARBLER = b"e2g\x00"
_LENGTH = struct.Struct(">I")
_COUNTER = struct.Struct(">Q")


class FrameSeal:
    """One end of a sealed link: frames it sends are numbered in ``sending``, frames it
    receives must come numbered in ``receiving``, in order."""

    def __init__(self, key: bytes, sending: bytes, receiving: bytes) -> None:
        if len(key) != KEY_BYTES:
            raise ValueError(f"a link key is {KEY_BYTES} bytes, not {len(key)}")
        self._aes = algorithms.AES(key)
        self._sending, self._receiving = sending, receiving
        self._sent = self._received = 0
        self._lent: list[bytearray] = []  # sealed frames handed to the transport
        self._free: list[bytearray] = []

    def seal(self, parts: list[bytes | memoryview],
             written: bool = False) -> list[bytes | memoryview]:
        """A frame from ``frames.encode`` (its length, then the body's buffers) -> the
        sealed frame: the new length, then the encrypted body and its tag. ``written``:
        the transport holds none of the frames sealed before (its buffer is empty), so
        their buffers take the next frames: fresh pages cost a fault and a zeroing each,
        more than sealing them does."""
        size = sum(len(p) for p in parts[1:])
        length = _LENGTH.pack(size + TAG)
        if written:
            self._free = (self._free + self._lent)[-SPARE:]
            self._lent = []
        out = self._buffer(size + TAG + SLACK)
        self._lent.append(out)
        view = memoryview(out)
        enc = Cipher(self._aes, modes.GCM(self._nonce(self._sending, self._sent))).encryptor()
        self._sent += 1
        enc.authenticate_additional_data(length)
        at = 0
        for part in parts[1:]:
            at += enc.update_into(part, view[at:])
        enc.finalize()
        view[at : at + TAG] = enc.tag
        return [length, view[: at + TAG]]

    def open(self, sealed: memoryview, out: memoryview) -> int:
        """Decrypt the sealed body ``sealed`` into ``out`` (at least ``len(sealed) +
        SLACK`` bytes); the plaintext's length. ProtocolError (LINK) if its tag fails."""
        if len(sealed) < TAG:
            raise ProtocolError(LINK, f"a sealed frame of {len(sealed)} bytes is shorter "
                                      f"than its tag")
        body = len(sealed) - TAG
        dec = Cipher(self._aes, modes.GCM(self._nonce(self._receiving, self._received),
                                          bytes(sealed[body:]))).decryptor()
        self._received += 1
        dec.authenticate_additional_data(_LENGTH.pack(len(sealed)))
        n = dec.update_into(sealed[:body], out)
        try:
            dec.finalize()
        except InvalidTag:
            raise ProtocolError(LINK, f"frame {self._received - 1} of the table link fails "
                                      f"its seal: changed on the wire, or not sealed by the "
                                      f"other server with this link's key") from None
        return n

    def _buffer(self, size: int) -> bytearray:
        """A buffer of ``size`` to twice ``size`` bytes, reused if one is free."""
        for i, buf in enumerate(self._free):
            if size <= len(buf) <= 2 * size:
                return self._free.pop(i)
        return bytearray(size)

    @staticmethod
    def _nonce(direction: bytes, number: int) -> bytes:
        return direction + _COUNTER.pack(number)
