"""What this host's TLS, the table link's seal and loopback sockets cost per byte: the
floor under a table stream.

The daemons' TLS runs through memory BIOs (uvloop's SSL layer): the garbler encrypts every
table byte into its outgoing BIO and reads it out for the socket, the evaluator writes
what the socket gave into its incoming BIO and decrypts it into a frame buffer. Each byte
also crosses a socket once. With the kernel's garbling and evaluation rates, these rates
bound an invocation's CPU whatever the Python around them does.
"""

from __future__ import annotations

import os
import socket
import ssl
import tempfile
import threading
import time

from snail_common.net.seal import (
    EVALUATOR_TO_GARBLER,
    GARBLER_TO_EVALUATOR,
    KEY_BYTES,
    SLACK,
    TAG,
    FrameSeal,
)
from snail_common.net.tls import client_context, make_certs, server_context

CHUNK = 1 << 20  # the garbler's table frames are 1 MiB


def _bio_pair() -> tuple[ssl.SSLObject, ssl.MemoryBIO, ssl.SSLObject, ssl.MemoryBIO]:
    """A garbler -> evaluator TLS connection over memory BIOs, handshake done, with the
    daemons' own contexts: (garbler end, its outgoing BIO, evaluator end, its incoming)."""
    with tempfile.TemporaryDirectory(prefix="snail-tls-rate-") as tmp:
        make_certs(tmp)
        server, client = server_context(tmp, "evaluator"), client_context(tmp, "garbler")
    c_in, c_out, s_in, s_out = (ssl.MemoryBIO() for _ in range(4))
    garbler = client.wrap_bio(c_in, c_out, server_side=False, server_hostname="127.0.0.1")
    evaluator = server.wrap_bio(s_in, s_out, server_side=True)
    for _ in range(10):
        done = 0
        for end in (garbler, evaluator):
            try:
                end.do_handshake()
                done += 1
            except ssl.SSLWantReadError:
                pass
        s_in.write(c_out.read())
        c_in.write(s_out.read())
        if done == 2:
            return garbler, c_out, evaluator, s_in
    raise RuntimeError("the in-memory TLS handshake did not finish")


def tls_rates(rounds: int = 20) -> tuple[float, float]:
    """(encrypt, decrypt) bytes per CPU second of this thread on the daemons' TLS path,
    the best of ``rounds`` 1 MiB frames each way."""
    garbler, outgoing, evaluator, incoming = _bio_pair()
    frame, buf = memoryview(os.urandom(CHUNK)), bytearray(CHUNK)
    encrypt = decrypt = float("inf")
    for _ in range(rounds):
        t0 = time.thread_time()
        garbler.write(frame)
        records = outgoing.read()
        t1 = time.thread_time()
        incoming.write(records)
        got, view = 0, memoryview(buf)
        while got < CHUNK:
            got += evaluator.read(CHUNK - got, view[got:])
        t2 = time.thread_time()
        encrypt, decrypt = min(encrypt, t1 - t0), min(decrypt, t2 - t1)
    return CHUNK / max(encrypt, 1e-9), CHUNK / max(decrypt, 1e-9)


def seal_rates(rounds: int = 20) -> tuple[float, float]:
    """(seal, open) bytes per CPU second of this thread on the table link's ``aead`` path
    (snail_common/net/seal.py: AES-256-GCM over whole 1 MiB frames), the best of
    ``rounds`` frames each way, buffers reused as the daemons reuse theirs."""
    key = os.urandom(KEY_BYTES)
    garbler = FrameSeal(key, GARBLER_TO_EVALUATOR, EVALUATOR_TO_GARBLER)
    evaluator = FrameSeal(key, EVALUATOR_TO_GARBLER, GARBLER_TO_EVALUATOR)
    frame, plain = os.urandom(CHUNK), bytearray(CHUNK + TAG + SLACK)
    seal = open_ = float("inf")
    for _ in range(rounds):
        t0 = time.thread_time()
        sealed = garbler.seal([b"", frame], written=True)[1]
        t1 = time.thread_time()
        evaluator.open(sealed, memoryview(plain))
        t2 = time.thread_time()
        seal, open_ = min(seal, t1 - t0), min(open_, t2 - t1)
    return CHUNK / max(seal, 1e-9), CHUNK / max(open_, 1e-9)


def socket_rate(total: int = 64 << 20) -> float:
    """Bytes per CPU second of sending and receiving over loopback TCP (both ends' CPU
    together), 1 MiB writes."""
    with socket.create_server(("127.0.0.1", 0)) as listener:
        sender = socket.create_connection(listener.getsockname())
        receiver, _ = listener.accept()
    frame, cpu = os.urandom(CHUNK), {}

    def send() -> None:
        t0 = time.thread_time()
        for _ in range(total // CHUNK):
            sender.sendall(frame)
        cpu["send"] = time.thread_time() - t0

    with sender, receiver:
        thread = threading.Thread(target=send)
        thread.start()
        view, got = memoryview(bytearray(CHUNK)), 0
        t0 = time.thread_time()
        while got < total:
            n = receiver.recv_into(view)
            if not n:
                raise RuntimeError("the loopback connection closed early")
            got += n
        cpu["receive"] = time.thread_time() - t0
        thread.join()
    return total / max(cpu["send"] + cpu["receive"], 1e-9)
