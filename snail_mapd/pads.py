"""The random choice bits of each session's OT, held until the device's run asks for them.

A map-owner session's OT runs while the garbler garbles it, ahead of its run, with fresh
random bits r as the map owner's choices (the map owner then holds the labels of r at the
evaluator). The run's frame is known only when the device runs it: the device then asks
for the frame's pad bits XOR r, once. Given twice for two frames, the two answers would
XOR to the two frames' pads, and with them the device's two masked shares to the XOR of
two map points: so a session's r is handed out once and forgotten. The device asks only
once the garbler has answered for the session, which it does after this OT: a session
not held here is unknown, forgotten or given already, never still to come.
"""

from __future__ import annotations

from collections import OrderedDict

import numpy as np

from snail_common.net.errors import BAD_REQUEST, ProtocolError

MAX_SESSIONS = 4096  # sessions whose bits are held (the oldest forgotten first)
MAX_GIVEN = 4096  # recently given sessions, remembered to name a second request


class SessionPads:
    """Random OT choice bits by session id, each given out at most once."""

    def __init__(self, limit: int = MAX_SESSIONS) -> None:
        self.limit = limit
        self._bits: OrderedDict[bytes, np.ndarray] = OrderedDict()
        self._given: OrderedDict[bytes, None] = OrderedDict()

    def __len__(self) -> int:
        return len(self._bits)

    def add(self, sid: bytes, bits: np.ndarray) -> None:
        """The OT of ``sid`` is done with choices ``bits``."""
        self._bits[sid] = bits
        while len(self._bits) > self.limit:
            self._bits.popitem(last=False)

    def take(self, sid: bytes) -> np.ndarray:
        """The bits of ``sid``, once; ProtocolError naming ``sid`` otherwise."""
        if sid in self._given:
            raise ProtocolError(BAD_REQUEST, "field 'sid': this session's correction was "
                                             "given already (one frame per session)")
        bits = self._bits.pop(sid, None)
        if bits is None:
            raise ProtocolError(BAD_REQUEST, f"field 'sid': no session with that id took "
                                             f"this map owner's OT (unknown, or forgotten "
                                             f"after {self.limit} newer ones)")
        self._given[sid] = None
        while len(self._given) > MAX_GIVEN:
            self._given.popitem(last=False)
        return bits
