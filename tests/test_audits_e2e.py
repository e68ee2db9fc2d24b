"""Trust no single server, with the real daemons: each failpoint makes the localization
fail naming the right party, never a pose; a garbler's valid-looking cheat is a silent
wrong pose without audits and is caught by them; the evidence convinces on its own; and
nothing the garbler receives depends on which runs were audited.

Daemons run as processes on loopback, misbehaving through $SNAIL_FAILPOINTS
(snail_common/failpoints.py), both settings: offload, and map-owner (a snail-mapd holds
the map; its circuits' labels come by OT)."""

from __future__ import annotations

import contextlib
import json
import math
import os
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import msgpack
import numpy as np
import pytest
from shared_paths import EXAMPLES
from test_mapowner_e2e import RECORDER, scene, write_map

from snail_client.audit import IntegrityFailure
from snail_client.blocking import SecureRunner
from snail_client.embedded import Daemon, embedded_services, start_daemon
from snail_client.evidence import Unproven, verify
from snail_client.localize import GarbledBackend, Options, localize
from snail_client.mapowner import MapOwnerLink
from snail_client.secure import DEFAULT_AHEAD
from snail_common.circuit import registry
from snail_common.loc import owner
from snail_common.loc.backends import CircuitBackend
from snail_common.loc.pipeline import Options as PipelineOptions
from snail_common.loc.problem import load_problem
from snail_common.net.tls import make_certs

PROBLEM = EXAMPLES / "synthetic_n6.json"
# failpoint -> the party an audited run names
PARTIES = {
    "garbler.table_bit": "garbler",
    "garbler.zero_label": "garbler",
    "garbler.and_as_or": "garbler",
    "garbler.stale_circuit": "garbler",
    "evaluator.output_label": "evaluator",
    "evaluator.digest": "evaluator",
}


@pytest.fixture(scope="module")
def cache() -> Path:
    """This run's circuit cache (conftest.py): the client's audits and the daemons share
    compiled circuits."""
    return Path(os.environ["SNAIL_CACHE_DIR"])


@contextlib.contextmanager
def cheating(cache: Path, failpoints: str) -> Iterator:
    with embedded_services(env={"SNAIL_CACHE_DIR": str(cache),
                                "SNAIL_FAILPOINTS": failpoints}) as svc:
        yield svc


def localize_with(svc, rate: float, evidence: Path | None = None, ahead: int = DEFAULT_AHEAD,
                  **kw) -> dict:
    with SecureRunner(svc.garbler_addr, svc.evaluator_addr, svc.tls_dir, audit_rate=rate,
                      evidence_dir=evidence, ahead=ahead) as runner:
        return localize(load_problem(PROBLEM), Options(audit_rate=rate, **kw),
                        GarbledBackend(runner))


@pytest.fixture(scope="module")
def honest(cache) -> dict:
    return localize(load_problem(PROBLEM), Options(backend="cleartext"), CircuitBackend())


@pytest.mark.parametrize("failpoint", sorted(PARTIES))
def test_every_failpoint_fails_the_localization_naming_its_party(cache, tmp_path, failpoint):
    with cheating(cache, f"{failpoint}=always") as svc:
        with pytest.raises(IntegrityFailure) as info:
            localize_with(svc, 1.0, tmp_path)
        failure = info.value
        assert failure.party == PARTIES[failpoint], failure
        assert failure.run == 0 and failure.audits["failed"] == 1
        assert failure.record()["kind"] == "integrity"
        written = list(tmp_path.glob("*.json"))
        if failure.party == "garbler":  # provably: the file convinces on its own
            assert [failure.evidence] == written
            assert verify(written[0], (svc.tls_dir / "ca.pem").read_bytes())["proven"]
        else:
            assert not written
        # the server caught is refused for the rest of the runner's session
        with SecureRunner(svc.garbler_addr, svc.evaluator_addr, svc.tls_dir,
                          audit_rate=1.0) as runner:
            backend = GarbledBackend(runner)
            with pytest.raises(IntegrityFailure):
                localize(load_problem(PROBLEM), Options(min_invocations=2), backend)
            with pytest.raises(Exception, match="refused for the rest of this session"):
                localize(load_problem(PROBLEM), Options(min_invocations=2), backend)


def test_a_swapped_zero_label_is_a_silent_wrong_pose_without_audits(cache, honest):
    """Why audits exist: every label is valid, the output decodes, to another bit."""
    with cheating(cache, "garbler.zero_label=always") as svc:
        result = localize_with(svc, 0.0)
    assert result["status"] == "converged"  # trusted, exit 0 ...
    assert result["audits"] == {"runs": 20, "audited": 0, "failed": 0}
    moved = max(abs(a - b) for a, b in zip(result["tvec"], honest["tvec"]))
    assert moved > 1e-3 and result["rms_px"] > 1.2 * honest["rms_px"]  # ... and wrong


@pytest.mark.parametrize("failpoint", ["garbler.table_bit", "evaluator.output_label",
                                       "evaluator.digest"])
def test_a_cheat_that_spoils_a_label_or_signature_is_named_at_audit_rate_0(cache, failpoint):
    # run:3 counts the garbler's sessions in the order it garbles them, the evaluator's in
    # the order it evaluates them. Sessions garbled ahead are prepared side by side and
    # may serve runs in another order (a fresh clone's run named run 1 for the garbler's
    # third session): with none garbled ahead, the garbler's third session is run 2
    with cheating(cache, f"{failpoint}=run:3") as svc, \
            pytest.raises(IntegrityFailure) as info:
        localize_with(svc, 0.0, ahead=0)
    assert info.value.party == PARTIES[failpoint] and info.value.run == 2
    assert info.value.audits["audited"] == (0 if failpoint == "evaluator.digest" else 1)


def test_the_cli_exits_1_with_the_record_and_the_evidence_proves_it(cache, tmp_path):
    env = {**os.environ, "SNAIL_CACHE_DIR": str(cache),
           "SNAIL_FAILPOINTS": "garbler.stale_circuit=always"}
    done = subprocess.run([sys.executable, "-m", "snail_client", "localize", "--input",
                           str(PROBLEM), "--json", "--audit-rate", "1", "--evidence",
                           str(tmp_path / "ev"), "--output", str(tmp_path / "out.json")],
                          env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 1, done.stderr
    record = json.loads(done.stdout)
    assert record == json.loads((tmp_path / "out.json").read_text())
    assert record["status"] == "failed" and "rvec" not in record
    error = record["error"]
    assert (error["kind"], error["party"], error["run"]) == ("integrity", "garbler", 0)
    assert record["audits"] == {"runs": 1, "audited": 1, "failed": 1}
    assert "the garbler is to blame" in done.stderr
    evidence = Path(error["evidence"])
    check = [sys.executable, "-c", "from snail_bench.cli import main; main()",
             "verify-evidence", str(evidence)]
    proven = subprocess.run(check, env=env, capture_output=True, text=True, timeout=120)
    assert proven.returncode == 0 and json.loads(proven.stdout)["proven"], proven.stderr
    # what the file proves rests on the garbler's signature: forge it, it proves nothing
    doc = json.loads(evidence.read_text())
    doc["signed"]["tables"]["digest"] = doc["recomputed"]["digest"]
    doc["signed"]["outputs"]["digest"] = doc["recomputed"]["digest"]
    evidence.write_text(json.dumps(doc))
    forged = subprocess.run(check, env=env, capture_output=True, text=True, timeout=120)
    assert forged.returncode == 1 and not json.loads(forged.stdout)["proven"]


def test_evidence_holds_only_for_the_garblers_certificate(cache, tmp_path):
    with cheating(cache, "garbler.and_as_or=always") as svc, \
            pytest.raises(IntegrityFailure) as info:
        localize_with(svc, 1.0, tmp_path / "ev")
    path = info.value.evidence
    assert verify(path)["because"].startswith("the garbler signed tables")
    other_ca = make_certs(tmp_path / "other") / "ca.pem"
    with pytest.raises(Unproven, match="did not issue"):
        verify(path, other_ca.read_bytes())
    doc = json.loads(path.read_text())
    doc["servers"]["garbler"]["certificate_sha256"] = "00" * 32
    path.write_text(json.dumps(doc))
    with pytest.raises(Unproven, match="not the garbler's"):
        verify(path)


# ---- the map-owner setting -------------------------------------------------------------
MAP_OPTIONS = PipelineOptions(solve="circuit", min_invocations=3)
MAP_PARTIES = {"garbler.zero_label": "garbler", "garbler.table_bit": "garbler",
               "evaluator.output_label": "evaluator-or-ot", "evaluator.digest": "evaluator"}


@pytest.mark.parametrize("failpoint", sorted(MAP_PARTIES))
def test_map_owner_circuits_are_audited_and_attributed_alike(cache, tmp_path, failpoint):
    """Their tables depend on the client's seed and offset alone: audited the same way;
    a run with right tables and a bad label may come from the evaluator or from the map
    owner's labels (OT)."""
    tls_dir = make_certs(tmp_path / "tls")
    env = {"SNAIL_CACHE_DIR": str(cache), "SNAIL_FAILPOINTS": f"{failpoint}=always"}
    points, frame, _ = scene(64)
    started: list[Daemon] = []
    try:
        evaluator = start_daemon("evaluator", ["--tls-dir", str(tls_dir)],
                                 tmp_path / "evaluator.log", env=env)
        started.append(evaluator)
        mapd = start_daemon("mapd", ["--map", str(write_map(points, tmp_path / "map.json")),
                                     "--tls-dir", str(tls_dir), "--evaluator",
                                     evaluator.address], tmp_path / "mapd.log", env=env)
        started.append(mapd)
        garbler = start_daemon("garbler", ["--tls-dir", str(tls_dir), "--evaluator",
                                           evaluator.address, "--map-owner", mapd.address],
                               tmp_path / "garbler.log", env=env)
        started.append(garbler)
        with MapOwnerLink(mapd.address, tls_dir) as link, SecureRunner(
                garbler.address, evaluator.address, tls_dir, audit_rate=1.0) as runner:
            published = link.open()
            handle, masked = link.select(frame.map_ids)
            runner.use_frame(handle, mapd.address)
            with pytest.raises(IntegrityFailure) as info:
                owner.localize_shared(frame, published, masked, MAP_OPTIONS,
                                      GarbledBackend(runner))
    finally:
        for daemon in reversed(started):
            daemon.stop()
    assert info.value.party == MAP_PARTIES[failpoint]


# ---- what the garbler sees -------------------------------------------------------------
FROM_EVALUATOR = ("capabilities", "done")  # on the garbler's own links to the evaluator


def _garbler_frames(cache: Path, tmp_path: Path, rate: float) -> list[dict]:
    """Every frame the garbler received from the client while it localized with
    ``rate`` (the recorder takes every frame the process decodes: those that came on
    its links to the evaluator are left out)."""
    tls_dir = make_certs(tmp_path / "tls")
    evaluator = start_daemon("evaluator", ["--tls-dir", str(tls_dir)],
                             tmp_path / "evaluator.log", env={"SNAIL_CACHE_DIR": str(cache)})
    log = tmp_path / "garbler.frames"
    try:
        proc = subprocess.Popen(
            [sys.executable, "-c", RECORDER % ("garbler", "garbler"), str(log),
             "--listen", "127.0.0.1:0", "--log-level", "info", "--tls-dir", str(tls_dir),
             "--evaluator", evaluator.address],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
            stderr=open(tmp_path / "garbler.log", "wb"),  # noqa: SIM115
            env={**os.environ, "SNAIL_CACHE_DIR": str(cache)})
        try:
            garbler = Daemon("garbler", proc, _listening(tmp_path / "garbler.log", proc),
                             tmp_path / "garbler.log")
            with SecureRunner(garbler.address, evaluator.address, tls_dir,
                              audit_rate=rate) as runner:
                backend = GarbledBackend(runner)
                result = localize(load_problem(PROBLEM), Options(audit_rate=rate), backend)
                assert result["audits"]["audited"] == (20 if rate else 0)
        finally:
            garbler.stop()
    finally:
        evaluator.stop()
    with open(log, "rb") as f:
        return [m for m in msgpack.Unpacker(f, raw=False) if m["t"] not in FROM_EVALUATOR]


def _listening(log: Path, proc: subprocess.Popen) -> str:
    import time

    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        for line in log.read_text().splitlines():
            entry = json.loads(line)
            if entry.get("event") == "listening":
                return f"127.0.0.1:{entry['port']}"
        assert proc.poll() is None, log.read_text()
        time.sleep(0.05)
    raise AssertionError(log.read_text())


def _shape(msg: dict) -> tuple:
    """A frame as anything but its random contents: kind, fields, their types and sizes."""
    return (msg["t"], tuple(sorted((k, type(v).__name__, len(v) if isinstance(v, (bytes, str))
                                    else v if isinstance(v, int) else None)
                                   for k, v in msg.items() if k not in ("sid", "seed",
                                                                        "delta", "key",
                                                                        "evaluator",
                                                                        "evaluator_id"))))


def test_no_frame_the_garbler_receives_depends_on_the_audits(cache, tmp_path):
    """The same localization audited on every run and on none: the garbler receives the
    same frames, but for their fresh random secrets (and the evaluator replica named by
    its address and instance, which differ per daemon)."""
    audited = _garbler_frames(cache, tmp_path / "all", 1.0)
    unaudited = _garbler_frames(cache, tmp_path / "none", 0.0)
    assert sum(m["t"] == "garble_request" for m in audited) >= 20
    assert [_shape(m) for m in audited] == [_shape(m) for m in unaudited]
    fields = {k for m in audited for k in m}
    assert not fields & {"audit", "audited", "audit_rate"}


# ---- audits by chance ------------------------------------------------------------------
def test_a_garbler_cheating_on_every_run_is_caught_at_the_audit_rate(cache):
    """200 padded localizations (20 runs each) against a garbler that swaps a zero-label
    on every run, audit rate 1/8: the share caught is within three standard deviations
    of 1 - (7/8)^20 = 0.931. Real daemons and the client's own runner, localizing the
    4-point example (its circuit is the smallest localization circuit: 0.12 M AND)."""
    rate, frames, runs = 0.125, 200, 20
    problem = load_problem(EXAMPLES / "apriltag_4corners.json")
    options = Options(audit_rate=rate, min_invocations=runs)
    caught = 0
    with cheating(cache, "garbler.zero_label=always") as svc, SecureRunner(
            svc.garbler_addr, svc.evaluator_addr, svc.tls_dir, audit_rate=rate) as runner:
        backend = GarbledBackend(runner)
        for _ in range(frames):
            runner.audits.refused.clear()  # each localization a fresh client's
            before = runner.audits.runs
            try:
                result = localize(problem, options, backend)
                assert result["invocations"] == runs
            except IntegrityFailure as exc:
                assert exc.party == "garbler"
                caught += 1
            assert runner.audits.runs - before <= runs
    p = 1 - (1 - rate) ** runs
    sigma = math.sqrt(p * (1 - p) / frames)
    print(f"caught {caught} of {frames}: {caught / frames:.3f}, expected {p:.3f} +- {sigma:.3f}")
    assert abs(caught / frames - p) <= 3 * sigma, (caught, frames, p, sigma)


def test_a_garbler_cheating_on_one_run_in_ten_is_caught_in_every_stream(cache):
    """Ten streams of up to 600 runs (one per frame, as tracking makes them) against a
    garbler that swaps a zero-label on every tenth run, at the default audit rate: each
    stream is caught (it fails unless caught: 1 - (7/8)^60 per stream). The runner's
    own invocations of the 4-point circuit stand for the frames."""
    circuit = "loc/nx-sil-n4"
    n_inputs = registry.interface(circuit).n_inputs
    rng = np.random.default_rng(3)
    with cheating(cache, "garbler.zero_label=1/10") as svc:
        for _ in range(10):
            with SecureRunner(svc.garbler_addr, svc.evaluator_addr, svc.tls_dir) as runner:
                runner.expect(circuit, 600)
                with pytest.raises(IntegrityFailure) as info:
                    for _ in range(600):
                        runner.invoke(circuit, rng.random(n_inputs) < 0.5)
            assert info.value.party == "garbler"


def test_an_audit_rate_outside_0_1_is_bad_usage():
    done = subprocess.run([sys.executable, "-m", "snail_client", "localize", "--input",
                           str(PROBLEM), "--audit-rate", "1.5"], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2 and "--audit-rate" in done.stderr
    with pytest.raises(ValueError, match="--audit-rate"):
        Options(audit_rate=-0.1)


def test_in_a_fleet_a_cheating_replica_is_refused_and_the_run_served_by_another(
        cache, tmp_path, honest, monkeypatch):
    """Two evaluator replicas behind one name, one returning wrong labels: its first run
    fails the integrity check, runs again on the other, and the cheater gets no session
    after that; the pose is the honest one."""
    from snail_client import replicas
    from snail_common.net.conn import parse_addr

    name = "evaluators.snail.test"
    tls_dir = make_certs(tmp_path / "tls", hosts=[name])
    common = ["--tls-dir", str(tls_dir), "--log-level", "info"]
    env = {"SNAIL_CACHE_DIR": str(cache)}
    evaluators = [start_daemon("evaluator", common, tmp_path / f"evaluator{i}.log",
                               env={**env, "SNAIL_FAILPOINTS": fp})
                  for i, fp in enumerate(("evaluator.output_label=always", ""))]
    flags = [f for e in evaluators for f in ("--evaluator", e.address)]
    garbler = start_daemon("garbler", [*flags, *common], tmp_path / "garbler.log", env=env)
    addresses = [parse_addr(e.address) for e in evaluators]

    async def both(host, port):
        return list(addresses) if host == name else [(host, port)]

    monkeypatch.setattr(replicas, "resolve", both)
    try:
        with SecureRunner(garbler.address, f"{name}:{addresses[1][1]}", tls_dir,
                          audit_rate=0.0, busy_wait=60) as runner:
            result = localize(load_problem(PROBLEM), Options(audit_rate=0.0),
                              GarbledBackend(runner))
            again = localize(load_problem(PROBLEM), Options(audit_rate=0.0),
                             GarbledBackend(runner))
    finally:
        for daemon in (garbler, *evaluators):
            daemon.stop()
    assert result["audits"]["failed"] == 1 and result["retries"] >= 1
    assert again["audits"]["failed"] == 0
    for key in ("rvec", "tvec", "status"):
        assert result[key] == honest[key] == again[key], key
    served = [sum(json.loads(x).get("outcome") == "ok" for x in e.log.read_text()
                  .splitlines() if '"event": "session"' in x) for e in evaluators]
    assert served[1] >= 40 - served[0] and served[0] <= 3, served
