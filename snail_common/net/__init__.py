"""Networking shared by the three roles: frames, messages, TLS, connections, daemons.

See ``messages`` for the protocol, ``snail_garbler.daemon`` and ``snail_evaluator.daemon``
for each server's side of a session and ``snail_client.secure`` for the client's.
"""

from .errors import ConnectionClosed, ProtocolError, RemoteError
from .frames import MAX_FRAME, PROTOCOL_VERSION

__all__ = ["MAX_FRAME", "PROTOCOL_VERSION", "ConnectionClosed", "ProtocolError",
           "RemoteError"]
