"""Ctrl-C: one line and exit 130, no traceback; a daemon ends its running sessions with
an error to their peers instead of waiting out its grace period."""

from __future__ import annotations

import asyncio
import os
import signal
import subprocess
import sys
import time

import pytest
from daemons import sigint_default
from shared_paths import EXAMPLES

from snail_client.blocking import SecureRunner
from snail_client.embedded import embedded_services
from snail_client.links import ServiceError
from snail_client.secure import AsyncSecureRunner
from snail_client.sessions import collect_answers
from snail_common.circuit import registry
from snail_common.net.tls import make_certs


def _wait_for(proc: subprocess.Popen, timeout: float = 60) -> None:
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise


def test_ctrl_c_in_the_client_is_one_line_and_exit_130(tmp_path):
    proc = subprocess.Popen(
        [sys.executable, "-m", "snail_client", "localize", "--input",
         str(EXAMPLES / "synthetic_n6.json"), "--min-invocations", "10000"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=sigint_default)
    time.sleep(8)  # the embedded servers are up and runs are under way
    proc.send_signal(signal.SIGINT)
    _wait_for(proc)
    err = proc.stderr.read()
    assert proc.returncode == 130, err
    assert "Traceback" not in err and err.strip().splitlines()[-1] == "snail-client: interrupted"


@pytest.mark.parametrize("role", ["garbler", "evaluator"])
def test_ctrl_c_ends_a_daemons_sessions_with_an_error(tmp_path, role):
    circuit = "ops/fmul-x4"
    registry.compiled(circuit)  # compiled here, so the daemons load it from the cache
    with embedded_services(extra_args=("--grace", "60")) as svc:
        daemon = svc.garbler if role == "garbler" else svc.evaluator

        async def stalled_session():
            async with AsyncSecureRunner(svc.garbler_addr, svc.evaluator_addr, svc.tls_dir,
                                         timeout=30) as r:
                session = await r._prepare(circuit)  # labels never sent: it stays open
                await asyncio.sleep(0.5)
                daemon.process.send_signal(signal.SIGINT)
                with pytest.raises(ServiceError) as caught:
                    await collect_answers(session)
                return str(caught.value)

        message = asyncio.run(stalled_session())
        _wait_for(daemon.process)
        assert daemon.process.returncode == 130
        # the interrupted daemon's own error, or the other server's word that it went:
        # not the client's "no result within 30 s" (the 60 s grace was not waited out)
        assert any(w in message for w in ("shutting down", "aborted", "peer_lost")), message
        log = daemon.log.read_text()
        assert "Traceback" not in log
        assert log.strip().splitlines()[-1].startswith(f"snail-{role}: interrupted")


def test_ctrl_c_inside_the_runners_loop_is_never_lost(tmp_path):
    """uvloop raises KeyboardInterrupt inside whichever callback runs, and protocols take
    any exception there for a lost connection (the fresh-clone CI saw the client carry on
    after Ctrl-C, and a run end 'connection lost' with exit 1): the runner turns SIGINT
    into a cancelled run and raises KeyboardInterrupt itself, even where the code it ran
    swallowed everything."""
    runner = SecureRunner("127.0.0.1:1", "127.0.0.1:2", make_certs(tmp_path / "tls"))

    async def swallows_everything() -> str:
        for _ in range(3):
            try:
                os.kill(os.getpid(), signal.SIGINT)
                await asyncio.sleep(0.05)
            except BaseException:  # what a protocol callback does with it
                pass
        return "carried on"

    # as in a terminal, whatever the job control of the shell that started pytest
    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with pytest.raises(KeyboardInterrupt):
            runner._complete(swallows_everything())
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
    finally:
        signal.signal(signal.SIGINT, before)
        runner._loop.close()
