"""Send a well-formed snail ``hello`` frame over plain TCP (no TLS) and report the answer.

Run inside the client container by deploy/compose-test: ``python - HOST PORT < this file``.
Exit 0 when the server refused (closed the connection, at most with a TLS alert, and
never answered a frame), 1 when it answered anything else, 2 when it could not be reached.
"""

from __future__ import annotations

import socket
import sys

from snail_common.net import messages
from snail_common.net.conn import SOFTWARE
from snail_common.net.frames import MAX_FRAME, encode

TLS_ALERT = 0x15  # TLS record type of an alert


def main(host: str, port: int) -> int:
    hello = messages.make("hello", role="client", software=SOFTWARE, max_frame=MAX_FRAME)
    try:
        sock = socket.create_connection((host, port), timeout=5)
    except OSError as exc:
        print(f"plain TCP to {host}:{port}: cannot connect: {exc}")
        return 2
    answer = b""
    with sock:
        sock.sendall(b"".join(encode(hello)))
        try:
            while chunk := sock.recv(4096):
                answer += chunk
        except ConnectionResetError:
            pass
        except TimeoutError:
            print(f"plain TCP to {host}:{port}: still open after 5 s ({len(answer)} bytes)")
            return 1
    if answer and answer[0] != TLS_ALERT:
        print(f"plain TCP to {host}:{port}: answered {answer[:32]!r}")
        return 1
    print(f"plain TCP to {host}:{port}: refused "
          f"({'TLS alert' if answer else 'closed'}, no frame)")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], int(sys.argv[2])))
