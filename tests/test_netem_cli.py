"""snail-bench netem's flags without a lab: profiles and the flags that override them,
the link bound of a localization, and what a person reads (the lab is faked)."""

from __future__ import annotations

import json

import pytest
from click.testing import CliRunner

from snail_bench import netem as netem_module
from snail_bench.cli import main
from snail_bench.linkbound import bounded, link_bound
from snail_bench.netlab.namespaces import Shape


@pytest.fixture
def captured(monkeypatch):
    calls: list[dict] = []

    def fake_report(specs, repeat, shapes, *args, **kwargs):
        calls.append({"specs": specs, "shapes": dict(shapes), "args": args})
        return {"netem": {"profile": args[-1], "shaper": "forwarder",
                          "forwarder": "native"}}

    monkeypatch.setattr(netem_module, "netem_report", fake_report)
    return calls


def test_a_profile_sets_every_link_and_explicit_flags_override_it(captured):
    out = CliRunner().invoke(main, ["netem", "--profile", "region", "--server-delay-ms",
                                    "3", "--points", "6", "--json"])
    assert out.exit_code == 0, out.output
    shapes = captured[0]["shapes"]
    assert shapes["garbler_evaluator"] == Shape(3, rate_mbit=1000)  # delay overridden
    assert shapes["client_garbler"] == shapes["client_evaluator"] == Shape(20,
                                                                            rate_mbit=100)
    assert json.loads(out.output)["netem"]["profile"] == "region"


def test_without_a_profile_links_are_as_the_flags_say(captured):
    out = CliRunner().invoke(main, ["netem", "--client-delay-ms", "20", "--json"])
    assert out.exit_code == 0, out.output
    shapes = captured[0]["shapes"]
    assert shapes["garbler_evaluator"] == Shape() and shapes["client_evaluator"] == Shape(20)


def test_an_unknown_profile_is_refused_naming_the_flag(captured):
    out = CliRunner().invoke(main, ["netem", "--profile", "moon"])
    assert out.exit_code == 2 and "--profile" in out.output and not captured


def test_the_link_bound_is_the_larger_of_transfer_and_round_trips():
    # 112.5 MB over 1 Gbit/s: 0.9 s; 20 round trips of 40 ms: 0.8 s
    assert link_bound(112_500_000, 1000, 20, 40) == pytest.approx(0.9)
    assert link_bound(1_000_000, 1000, 20, 40) == pytest.approx(0.8)
    run = {"wall_s": 1.8, "invocations": 20, "bytes": {"garbler_to_evaluator": 112_500_000}}
    links = {"garbler_evaluator": {"rate_mbit": 1000, "rtt_ms": 20},
             "client_evaluator": {"rate_mbit": 100, "rtt_ms": 40}}
    assert bounded(run, links)["link_bound_s"] == 0.9
    assert bounded(run, links)["bound_ratio"] == 2.0
