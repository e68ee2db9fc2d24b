"""Signed table digests (snail_common/gc/attest.py): the garbler commits to each run's
stream with a key of its own, the evaluator checks the bytes it received against that
commitment before it answers, and forwards it to the client."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os

import numpy as np
import pytest
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from test_service_e2e import hello, raw, read_msg

from snail_client.embedded import embedded_services, start_daemon
from snail_client.secure import AsyncSecureRunner
from snail_common.circuit import registry
from snail_common.gc import Garbler, active_input_labels, fresh_delta, fresh_seed
from snail_common.gc.attest import (
    Statement,
    TableDigest,
    endorsement_message,
    outputs_digest,
    public_bytes,
)
from snail_common.gc.lanes import LaneGarbler
from snail_common.net import errors, messages, tls
from snail_common.net.frames import encode_bytes
from snail_common.net.tls import make_certs
from snail_evaluator.attest import Attested
from snail_evaluator.session import Session

CIRCUIT = "ops/fadd-x1"


def statement(**kw) -> Statement:
    base = dict(sid=bytes(16), circuit=CIRCUIT, content_hash="ab" * 32, scheme=1,
                block_gates=256, tables=bytes(32))
    return Statement(**{**base, **kw})


def test_a_signature_holds_for_its_statement_only():
    key = Ed25519PrivateKey.generate()
    pub, s = public_bytes(key), statement()
    signature = s.sign(key)
    assert s.verify(pub, signature)
    for changed in (statement(sid=b"\1" * 16), statement(circuit="ops/fadd-x4"),
                    statement(content_hash="cd" * 32), statement(scheme=2),
                    statement(block_gates=512), statement(tables=b"\1" * 32),
                    s.with_outputs(np.zeros((4, 2), np.uint64))):
        assert not changed.verify(pub, signature)
    other = public_bytes(Ed25519PrivateKey.generate())
    assert not s.verify(other, signature)
    assert not s.verify(pub[:31], signature) and not s.verify(pub, signature[:63])
    # the two kinds never encode alike, whatever their fields
    assert s.encode() != s.with_outputs(np.zeros((0, 2), np.uint64)).encode()


def test_the_digest_is_the_streams_whatever_the_frames_and_lanes():
    """A lane's stream hashes like a single run's with the same secrets: the client
    re-garbles alone what the garbler may have garbled in a batch."""
    _, schedule = registry.compiled("ops/fmul-x4")
    secrets3 = [(fresh_seed(), fresh_delta(), bytes([k]) * 16) for k in range(3)]
    lanes = LaneGarbler(schedule, *zip(*secrets3), block_gates=512, frame_bytes=8192)
    per_lane = [TableDigest() for _ in secrets3]
    for parts in lanes.frames():
        for digest, part in zip(per_lane, parts):
            digest.update(part)
    for (seed, delta, key), digest in zip(secrets3, per_lane):
        solo = Garbler(schedule, seed, delta, key, block_gates=512, frame_bytes=1 << 20)
        whole = TableDigest()
        whole.update(b"".join(bytes(f) for f in solo.frames()))
        assert whole.digest() == digest.digest()


@pytest.fixture(scope="module")
def services(tmp_path_factory):
    cache = tmp_path_factory.mktemp("cache")
    with embedded_services(log_level="info", env={"SNAIL_CACHE_DIR": str(cache)}) as svc:
        yield svc


def test_the_garbler_announces_its_key_signs_every_run_and_logs_it(services):
    _, schedule = registry.compiled(CIRCUIT)

    async def scenario():
        async with AsyncSecureRunner(services.garbler_addr, services.evaluator_addr,
                                     services.tls_dir) as runner:
            garbler, _ = await runner.connect()
            info = dict(garbler.conn.info)
            for k in range(3):
                await runner.invoke(CIRCUIT, np.arange(schedule.n_inputs) % (k + 2) == 0)
            return info, await runner.health("garbler"), runner.audits.counts()

    info, health, counts = asyncio.run(scenario())
    key = info["signing_key"]
    assert len(key) == 32 and health["signing_key"] == key.hex()
    cert = (services.tls_dir / "garbler.pem").read_bytes()
    der = x509.load_pem_x509_certificate(cert).public_bytes(serialization.Encoding.DER)
    assert tls.endorsed(der, endorsement_message(key), info["key_endorsement"])
    assert not tls.endorsed(der, endorsement_message(bytes(32)), info["key_endorsement"])
    assert counts["runs"] == 3 and counts["failed"] == 0  # every signature checked
    lines = [json.loads(x) for x in services.garbler.log.read_text().splitlines()]
    sessions = [x for x in lines if x["event"] == "session"]
    assert len(sessions) >= 3
    assert all(x["signer"] == key.hex() and len(x["digest"]) == 64 for x in sessions)
    assert len({x["digest"] for x in sessions}) == len(sessions)  # fresh secrets each run
    listening = next(x for x in lines if x["event"] == "listening")
    assert listening["signing_key"] == key.hex()


def test_a_signing_key_in_the_tls_dir_is_the_garblers(services, tmp_path):
    tls_dir = make_certs(tmp_path / "tls")
    key = Ed25519PrivateKey.generate()
    (tls_dir / "garbler.sign.key").write_bytes(key.private_bytes(
        serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
        serialization.NoEncryption()))
    garbler = start_daemon("garbler", ["--tls-dir", str(tls_dir), "--evaluator",
                                       "127.0.0.1:1", "--log-level", "info"],
                           tmp_path / "garbler.log")
    try:
        lines = [json.loads(x) for x in garbler.log.read_text().splitlines()]
        listening = next(x for x in lines if x["event"] == "listening")
        assert listening["signing_key"] == public_bytes(key).hex()
    finally:
        garbler.stop()


def _play(services, tamper: str) -> tuple[dict, list[dict]]:
    """Play the garbler and the client of one session against the real evaluator; the
    garbler's stream is honest, its sign-off ``tamper``ed; what the evaluator answers the
    garbler, and all it sends the client."""
    circuit, schedule = registry.compiled(CIRCUIT)
    key = Ed25519PrivateKey.generate()
    # a sid of its own each time: the evaluator answers a garbler half of a sid it ended
    sid, seed, delta = os.urandom(16), fresh_seed(), fresh_delta()
    bits = np.zeros(schedule.n_inputs, bool)
    garbler = Garbler(schedule, seed, delta, bytes(16), block_gates=256)
    frames = [bytes(f) for f in garbler.frames()]
    digest = TableDigest()
    for f in frames:
        digest.update(f)
    signed = Statement(sid, CIRCUIT, circuit.content_hash(), 1, 256, digest.digest())
    end = {"sid": sid, "digest": digest.digest(), "signature": signed.sign(key)}
    if tamper == "digest":
        end["digest"] = bytes(32)
    elif tamper == "key":
        end["signature"] = signed.sign(Ed25519PrivateKey.generate())
    start = dict(sid=sid, circuit=CIRCUIT, hash=circuit.content_hash())
    labels = active_input_labels(seed, delta, bits)
    with contextlib.closing(raw(services.evaluator_addr, services.tls_dir)) as client, \
            contextlib.closing(raw(services.evaluator_addr, services.tls_dir,
                                   "garbler")) as server:
        hello(client)
        hello(server, "garbler")
        client.sendall(encode_bytes(messages.make("session_start", signer=public_bytes(key),
                                                  **start)))
        client.sendall(encode_bytes(messages.make(
            "input_labels", sid=sid, start=0, total=len(labels), labels=labels.tobytes())))
        server.sendall(encode_bytes(messages.make("session_start", **start)))
        for f in frames:
            server.sendall(encode_bytes(messages.make("tables", sid=sid, data=f)))
        server.sendall(encode_bytes(messages.make("tables_end", **end)))
        verdict = read_msg(server)
        got = [read_msg(client)]
        while got[-1]["t"] not in ("stats", "error"):
            got.append(read_msg(client))
    return verdict, got


def test_the_evaluator_forwards_the_signed_digest_of_what_it_evaluated(services):
    verdict, got = _play(services, "")
    assert verdict["t"] == "done"
    stats = got[-1]
    assert stats["t"] == "stats" and got[0]["t"] == "output_labels"
    assert stats["block_gates"] == 256 and len(stats["tables_signature"]) == 64
    assert stats["timing"]["digest_s"] > 0


@pytest.mark.parametrize(("tamper", "says"), [
    ("digest", "not the ones the garbler signed"),
    ("key", "does not verify under the key the client named"),
])
def test_the_evaluator_answers_nothing_for_tables_the_garbler_did_not_sign(services, tamper,
                                                                            says):
    verdict, got = _play(services, tamper)
    assert verdict["t"] == "error" and verdict["code"] == errors.DIGEST
    assert len(got) == 1 and got[0]["t"] == "error" and got[0]["code"] == errors.DIGEST
    assert says in got[0]["message"] and "garbler or the server link" in got[0]["message"]


def test_a_sign_off_read_ahead_while_buffering_is_kept():
    """A buffered stream found complete when the labels came: the read still pending
    may already hold the tables_end that followed the last frame (it was lost: the
    session then waited for it until its timeout)."""
    async def scenario():
        loop = asyncio.get_running_loop()
        s = Session(b"\1" * 16, CIRCUIT, "ab" * 32, loop.create_future())
        took = loop.create_future()
        took.set_result(({"t": "tables_end", "sid": s.sid}, 100))
        Attested._read_ahead(s, took)
        pending = loop.create_future()
        Attested._read_ahead(s, pending)
        return s, pending

    s, pending = asyncio.run(scenario())
    assert s.read_ahead == ({"t": "tables_end", "sid": s.sid}, 100)
    assert pending.cancelled()


def test_output_digest_is_over_the_labels_in_wire_order():
    labels = np.arange(8, dtype=np.uint64).reshape(4, 2)
    assert outputs_digest(labels) != outputs_digest(labels[::-1])


def test_a_commitment_does_not_keep_its_garbling_alive():
    """The garbler keeps each session's commitment while its garbling lives (a weak
    dictionary): once the session is over, both go. A commitment that held its garbling
    (for the zero-labels) kept every session's labels for good: the garbler's memory
    grew by hundreds of MB over a soak."""
    import gc
    import weakref

    from snail_common.gc import Garbler
    from snail_common.gc.labels import labels_to_bytes
    from snail_garbler.attest import Attestor

    circuit, schedule = registry.compiled(CIRCUIT)
    attestor = Attestor(None)
    alive = []
    for _ in range(3):
        garbler = Garbler(schedule, fresh_seed(), labels_to_bytes(fresh_delta()), bytes(16))
        req = {"sid": os.urandom(16), "circuit": CIRCUIT, "hash": circuit.content_hash()}
        for _frame in attestor.frames(garbler, req):
            pass
        attestor.end(garbler)
        zero, _ = attestor.reply(garbler, {}, "robot")
        np.testing.assert_array_equal(zero, garbler.output_zero_labels)
        alive.append(weakref.ref(garbler))
        del garbler
    gc.collect()
    assert not any(ref() is not None for ref in alive)
