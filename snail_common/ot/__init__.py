"""Oblivious transfer for the map-owner setting: base OTs over a vetted prime-order group
(libsodium through PyNaCl), IKNP extension with AES (random, chosen-message and correlated
OT), and oblivious selection of padded values (1-out-of-N OT), as transport-agnostic state
machines that produce and consume msgpack-able dicts (see ``iknp`` for the flow and its
semi-honest caveat). A malformed or out-of-bounds message raises a ProtocolError that
names the field.
"""

from .base import BaseReceiver, BaseSender
from .iknp import MAX_BATCH, ExtReceiver, ExtSender
from .selection import SelectReceiver, SelectSender

__all__ = ["MAX_BATCH", "BaseReceiver", "BaseSender", "ExtReceiver", "ExtSender",
           "SelectReceiver", "SelectSender"]
