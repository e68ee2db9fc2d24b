"""The lab's choice of shaper and the tc arguments of each, and the C wire's build: no
root needed (the lab itself is tested in test_netlab.py)."""

from __future__ import annotations

import subprocess

import pytest

from snail_bench.netlab import wire_native
from snail_bench.netlab.shaper import ShaperUnavailable, choose, netem_args, tbf_args


def test_auto_takes_netem_where_the_kernel_has_it_and_the_forwarder_elsewhere():
    assert choose("auto", None) == "netem"
    assert choose("auto", "Error: Specified qdisc kind is unknown.") == "forwarder"
    assert choose("forwarder", None) == "forwarder"
    assert choose("netem", None) == "netem"


def test_netem_asked_for_on_a_kernel_without_it_says_why():
    with pytest.raises(ShaperUnavailable, match=r"no netem qdisc.*kind is unknown"):
        choose("netem", "Error: Specified qdisc kind is unknown.")
    with pytest.raises(ValueError, match="shaper must be one of"):
        choose("fast", None)


def test_netem_arguments_are_a_users_own_tc_netem_experiment():
    assert netem_args(5, 0, 0, 2500) == ["netem", "limit", "100000", "delay", "5ms",
                                         "rate", "2500mbit"]
    assert netem_args(20, 2, 1.5, None) == ["netem", "limit", "100000", "delay", "20ms",
                                            "2ms", "distribution", "uniform", "loss", "1.5%"]
    tbf = tbf_args(1000)
    assert tbf[:3] == ["tbf", "rate", "1000mbit"] and int(tbf[4]) >= 2 * 65536


def test_the_c_wire_builds_once_and_runs(tmp_path):
    try:
        built = wire_native.native_wire(tmp_path)
    except wire_native.NoNativeWire as exc:
        pytest.skip(f"no C compiler here: {exc}")
    assert wire_native.native_wire(tmp_path) == built  # cached by source version
    usage = subprocess.run([str(built)], capture_output=True, text=True)
    assert usage.returncode == 2 and "no --link" in usage.stderr


def test_without_a_compiler_the_python_wire_runs_and_says_so(monkeypatch, capsys, tmp_path):
    monkeypatch.setenv("CC", str(tmp_path / "no-such-cc"))
    monkeypatch.setattr(wire_native, "cache_dir", lambda: tmp_path)
    command, kind = wire_native.wire_command()
    assert kind == "python" and command[-1] == "snail_bench.netlab.wire"
    assert "using the Python wire" in capsys.readouterr().err
