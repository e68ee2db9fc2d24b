"""Every parser of untrusted bytes survives mutations of valid inputs and random bytes,
raising only its documented error (the CI budget: 300 inputs per target, derandomized;
`snail-bench fuzz` runs them coverage-guided for 10^6). Findings become cases here."""

import json

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from snail_bench import fuzz_targets
from snail_bench.fuzz_targets import PARSERS, TARGETS, seeds
from snail_common.loc.problem import ProblemError, load_problem

CI_EXAMPLES = 300


@st.composite
def mutated(draw, target: str) -> bytes:
    """A seed of ``target`` with bytes flipped, cut, repeated or inserted, or noise."""
    if draw(st.integers(0, 4)) == 0:
        return draw(st.binary(max_size=512))
    data = bytearray(draw(st.sampled_from(seeds(target))))
    for _ in range(draw(st.integers(1, 8))):
        at = draw(st.integers(0, len(data)))
        action = draw(st.sampled_from(["flip", "cut", "insert", "repeat"]))
        if action == "flip" and at < len(data):
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif action == "cut":
            del data[at:at + draw(st.integers(1, 64))]
        elif action == "insert":
            data[at:at] = draw(st.binary(min_size=1, max_size=16))
        else:
            data[at:at] = data[at:at + draw(st.integers(1, 32))] * draw(st.integers(1, 4))
    return bytes(data)


@pytest.mark.parametrize("target", sorted(TARGETS))
def test_seeds_are_accepted(target, tmp_path, monkeypatch):
    """Mutation starts from inputs the parser accepts: each seed parses without error."""
    monkeypatch.setattr(fuzz_targets, "_SCRATCH", tmp_path)
    parse, _ = PARSERS[target]
    for seed in seeds(target):
        parse(seed)


@pytest.mark.parametrize("target", sorted(TARGETS))
def test_mutations_raise_only_documented_errors(target, tmp_path, monkeypatch):
    monkeypatch.setattr(fuzz_targets, "_SCRATCH", tmp_path)

    @settings(max_examples=CI_EXAMPLES, deadline=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(data=mutated(target))
    def run(data):
        TARGETS[target](data)

    run()


@pytest.mark.parametrize("text", ["[" * 5000 + "]" * 5000, '{"a":' * 3000 + "1" + "}" * 3000])
def test_json_nested_too_deeply_is_a_named_input_error(text, tmp_path, monkeypatch):
    """Found by fuzzing: a deeply nested file was a RecursionError traceback."""
    path = tmp_path / "deep.json"
    path.write_text(text)
    with pytest.raises(ProblemError, match="nested too deeply"):
        load_problem(path)
    monkeypatch.setattr(fuzz_targets, "_SCRATCH", tmp_path)
    for target in ("problem", "camera", "tagmap", "sequence"):
        TARGETS[target](text.encode())


@pytest.mark.parametrize("target, data", [
    # found by snail-bench fuzz: a list as the family was a TypeError (unhashable)
    ("tagmap", b'{"format": "snail-tagmap/1", "family":[{"id": 3, "": [0, 0, 0]}]}'),
    # and a POINT3D_ID beyond 64 bits was an OverflowError
    ("colmap_txt", fuzz_targets._split(b"1 PINHOLE 640 480 800 800 320 240\n",
                                       b"1 1 0 0 0 0 0 5 1 a.png\n300 200 " + b"8" * 40
                                       + b"\n", b"1 0 0 0 255 0 0 0.5 1 0\n")),
    # and a CA key whose algorithm OID is unknown was cryptography's UnsupportedAlgorithm
    ("certificates", b"\x07-----BEGIN PRIVATE KEY-----\nMIGHAgEAMBMGBxqGSM49AgEGCCqGSM49AwEHBG0w"
     b"awIBAQQgPdrR9A04i9Zh5jJP\nxxoZTZnpg2Zvc8wYp4EdXGBIBSihRANCAAS/OAkQOGDKSo1aXWp9LgnEotX7"
     b"ILIk\nguUY36dqOmD2WGSPFDRaHsJDmvsXvBQoqj+1sv7b/5IT4ehuD68eKZhZ\n-----END PRIVATE KEY"
     b"-----\n"),
    # and, once the target patched valid DER, an X.509 version of 3 in the CA certificate
    # was cryptography's InvalidVersion (no ValueError) when issuing a client certificate
    ("certificates", bytes([0 + 4 + 8]) + (12).to_bytes(2, "little") + b"\x01"),
])
def test_fuzz_findings_are_documented_errors(target, data, tmp_path, monkeypatch):
    monkeypatch.setattr(fuzz_targets, "_SCRATCH", tmp_path)
    parse, documented = PARSERS[target]
    with pytest.raises(documented):
        parse(data)


def test_fuzz_command_runs_coverage_guided_when_atheris_is_installed():
    atheris = pytest.importorskip("atheris", reason="the fuzz extra is not installed: "
                                                     "pip install 'snail[fuzz]'")
    assert atheris
    from snail_bench.fuzz import fuzz

    report = fuzz("message", runs=2000, seconds=60)
    assert report["ok"] and report["runs"] == 2000, report


def test_seed_problem_is_a_valid_problem():
    problem = json.loads(seeds("problem")[0])
    assert problem["format"] == "snail-problem/1"
