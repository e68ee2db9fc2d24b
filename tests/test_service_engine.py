"""The daemons say which garbling engine serves: on their start-up line and in ``health``.
Without a C compiler the numpy engine serves, says so and why, and sessions run; an engine
setting that cannot be honoured stops a daemon at start with exit status 2."""

import json
import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from test_service_e2e import hello, raw, read_msg

from snail_client.blocking import SecureRunner
from snail_client.embedded import ServiceError, embedded_services, start_daemon
from snail_common.circuit import evaluate_bits, registry
from snail_common.gc import engine as engines
from snail_common.net import messages
from snail_common.net.frames import encode_bytes
from snail_common.net.tls import make_certs

CIRCUIT = "ops/fadd-x2"


def listening(log: Path) -> dict:
    for line in log.read_text().splitlines():
        entry = json.loads(line)
        if entry["event"] == "listening":
            return entry
    raise AssertionError(f"no listening line in {log}")


def health(services, daemon) -> dict:
    """A health request to ``daemon`` over a client's TLS link."""
    with raw(daemon.address, services.tls_dir) as sock:
        hello(sock)
        sock.sendall(encode_bytes(messages.make("health_request")))
        return read_msg(sock)


def run_once(services) -> None:
    _, schedule = registry.compiled(CIRCUIT)
    row = np.random.default_rng(3).random(schedule.n_inputs) < 0.5
    with SecureRunner(services.garbler_addr, services.evaluator_addr, services.tls_dir,
                      timeout=60, busy_wait=0) as runner:
        np.testing.assert_array_equal(runner.run(CIRCUIT, row),
                                      evaluate_bits(schedule, row[None])[0])


def test_without_a_compiler_the_daemons_serve_with_numpy_and_say_why(tmp_path):
    env = {"CC": str(tmp_path / "no-such-cc"), "SNAIL_KERNEL_DIR": str(tmp_path / "kernel"),
           engines.ENGINE_ENV: "auto"}
    with embedded_services(env=env, log_level="info") as services:
        for daemon in (services.garbler, services.evaluator):
            line = listening(daemon.log)
            assert line["engine"] == "numpy"
            assert "no C compiler" in line["engine_reason"]
            answer = health(services, daemon)
            assert answer["engine"] == "numpy" and "no-such-cc" in answer["engine_reason"]
        run_once(services)


@pytest.mark.skipif(shutil.which(os.environ.get("CC") or "cc") is None,
                    reason="no C compiler: the native kernel cannot be built here")
def test_the_daemons_say_the_native_kernel_serves():
    try:
        engines.resolve("native")
    except engines.NativeUnavailable as exc:
        pytest.skip(f"the native kernel cannot run here: {exc}")
    env = {engines.ENGINE_ENV: "native", "SNAIL_KERNEL_THREADS": "2"}
    with embedded_services(env=env, log_level="info") as services:
        for daemon in (services.garbler, services.evaluator):
            line = listening(daemon.log)
            assert line["engine"] == "native" and "engine_reason" not in line
            assert line["engine_threads"] == 2
            answer = health(services, daemon)
            assert answer["engine"] == "native" and answer["engine_threads"] == 2
        run_once(services)


@pytest.mark.parametrize(("setting", "env", "named"), [
    ("fast", {}, "$SNAIL_ENGINE"),
    ("native", {"CC": "/nonexistent/cc"}, "$SNAIL_ENGINE"),
    ("auto", {"SNAIL_KERNEL_THREADS": "3"}, "$SNAIL_KERNEL_THREADS must be"),
])
def test_an_engine_that_cannot_serve_stops_the_daemon(tmp_path, setting, env, named):
    env = {**env, engines.ENGINE_ENV: setting, "SNAIL_KERNEL_DIR": str(tmp_path / "k")}
    tls_dir = make_certs(tmp_path / "tls")
    with pytest.raises(ServiceError, match="status 2") as err:
        start_daemon("evaluator", ["--tls-dir", str(tls_dir)], tmp_path / "e.log", env=env)
    assert named in str(err.value)
