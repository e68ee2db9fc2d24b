"""``snail-bench netem`` and ``snail-bench paper``: the commands that run the network lab
(three hosts in network namespaces, links shaped) and the paper's evaluation on it. The
measuring lives in ``netem.py``, ``netlab/`` and ``paper.py``; here are the flags, their
checks and what a person reads."""

from __future__ import annotations

import json
import sys

import click
from click.core import ParameterSource

from snail_common.net.linkrates import CLIENT_SCHEMES

from .choices import SERVICE_POINTS, spec
from .netlab.profiles import PROFILES, profile_shapes
from .netlab.shaper import SHAPERS

SCHEME_CHOICES = list(CLIENT_SCHEMES)


@click.command()
@click.option("--server-delay-ms", type=click.FloatRange(0, 10_000), default=0.0,
              show_default=True, help="One-way delay on the garbler-evaluator link.")
@click.option("--server-rate-mbit", type=click.FloatRange(min=0.1), default=None,
              help="Rate of the garbler-evaluator link, each way (default: unlimited).")
@click.option("--client-delay-ms", type=click.FloatRange(0, 10_000), default=0.0,
              show_default=True, help="One-way delay on both of the client's links.")
@click.option("--client-rate-mbit", type=click.FloatRange(min=0.1), default=None,
              help="Rate of each of the client's links, each way (default: unlimited).")
@click.option("--jitter-ms", type=click.FloatRange(0, 10_000), default=0.0,
              show_default=True, help="Uniform +- jitter on every delayed link (at most "
                                      "its delay; packets keep their order).")
@click.option("--loss-pct", type=click.FloatRange(0, 99), default=0.0, show_default=True,
              help="Packet loss on the client's links (its WiFi), each way.")
@click.option("--server-loss-pct", type=click.FloatRange(0, 99), default=0.0,
              show_default=True, help="Packet loss on the garbler-evaluator link.")
@click.option("--algorithm", type=click.Choice(["lm", "gn"]), default="lm", show_default=True,
              help="Levenberg-Marquardt (damped) or Gauss-Newton.")
@click.option("--points", type=click.IntRange(4, 4096), multiple=True, metavar="N",
              help="Circuit size; repeat for several (default: 6 and 12).")
@click.option("--repeat", type=click.IntRange(1, 1000), default=5, show_default=True,
              help="Warm runs per circuit and shaping, after one first run.")
@click.option("--baseline/--no-baseline", default=True, show_default=True,
              help="Run the same lab unshaped first and report it under 'unshaped'.")
@click.option("--measure-seconds", type=click.FloatRange(0.1, 60), default=1.0,
              show_default=True, help="Length of each link's throughput blast.")
@click.option("--congestion-control", metavar="NAME", default=None,
              help="TCP congestion control on the lab's links (e.g. cubic, reno, bbr; "
                   "default: the kernel's), set on their routes: it overrides the cubic "
                   "the service asks for on the client's links.")
@click.option("--slow-start-after-idle/--no-slow-start-after-idle", default=None,
              help="The hosts' net.ipv4.tcp_slow_start_after_idle inside the lab "
                   "(default: the kernel's, on).")
@click.option("--shaper", type=click.Choice(SHAPERS), default="auto", show_default=True,
              help="How links are shaped: tc netem (the kernel's), the lab's forwarder "
                   "(delay, jitter and loss in user space, tbf for the rate), or auto: "
                   "netem where the kernel has it.")
@click.option("--control/--no-control", default=True, show_default=True,
              help="Also run every link through the shaper with zero delay and no rate "
                   "and report it under 'control': what the lab itself costs.")
@click.option("--profile", type=click.Choice(list(PROFILES)), default=None,
              help="Named link settings (one way / rate; explicit link flags override): "
                   "lan 0.25 ms / 10 Gbit/s between the servers, 0.25 ms / 1 Gbit/s to "
                   "the client; paper 5 ms / 2.5 Gbit/s, client unshaped; region 10 ms / "
                   "1 Gbit/s, 20 ms / 100 Mbit/s; continent 40 ms / 1 Gbit/s, 30 ms / "
                   "50 Mbit/s.")
@click.option("--localize", "localize", type=click.IntRange(0, 100), default=0,
              is_flag=False, flag_value=3, metavar="[K]",
              help="Also K whole padded localizations per --points (default 3, after one "
                   "to warm up; 20 invocations each) in the shaped and unshaped runs: the "
                   "median's wall time, invocations and bytes per link against the bound "
                   "its links set: max(garbler->evaluator bytes / measured server rate, "
                   "invocations x measured client round trip).")
@click.option("--scheme", type=click.Choice(SCHEME_CHOICES), default=None,
              help="Garbling scheme of the sessions (default: the client's).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
@click.pass_context
def netem(ctx: click.Context, server_delay_ms: float, server_rate_mbit: float | None,
          client_delay_ms: float, client_rate_mbit: float | None, jitter_ms: float,
          loss_pct: float, server_loss_pct: float, algorithm: str, points: tuple[int, ...],
          repeat: int, baseline: bool, measure_seconds: float,
          congestion_control: str | None, slow_start_after_idle: bool | None, shaper: str,
          control: bool, profile: str | None, localize: int, scheme: str | None,
          as_json: bool) -> None:
    """`service` over shaped links: the client, garbler and evaluator as three hosts in
    network namespaces (needs root), each link with its own rate, delay, jitter and loss;
    every link's RTT and rate are measured before each run. Delays are one way. The same
    lab first runs unshaped (direct) and as a control run (through the shaper, zero
    shaping); headline figures are wall-time medians."""
    from .netem import netem_report
    from .netlab.namespaces import LabError, LabUnavailable, Shape

    def jitter(delay: float) -> float:
        return jitter_ms if delay else 0.0

    if profile is not None:  # the profile's values where no flag was given
        given = {name for name in ctx.params
                 if ctx.get_parameter_source(name) is not ParameterSource.DEFAULT}
        base = profile_shapes(profile)
        server_base, client_base = base["garbler_evaluator"], base["client_evaluator"]
        if "server_delay_ms" not in given:
            server_delay_ms = server_base.delay_ms
        if "server_rate_mbit" not in given:
            server_rate_mbit = server_base.rate_mbit
        if "client_delay_ms" not in given:
            client_delay_ms = client_base.delay_ms
        if "client_rate_mbit" not in given:
            client_rate_mbit = client_base.rate_mbit
    try:
        server = Shape(server_delay_ms, jitter(server_delay_ms), server_loss_pct,
                       server_rate_mbit)
        client = Shape(client_delay_ms, jitter(client_delay_ms), loss_pct, client_rate_mbit)
        specs = [spec(algorithm, "sil", None, "ldlt", n) for n in points or SERVICE_POINTS]
    except ValueError as e:
        raise click.UsageError(str(e)) from None
    flags = click.get_current_context().find_object(dict) or {}

    def done(phase: str, row: dict) -> None:
        if flags.get("verbose"):
            medians = ", ".join(f"{k} {v['median_s']:.3f} s" for k, v in row["service"].items())
            click.echo(f"snail-bench: {phase}: {medians}", err=True)

    shapes = {"garbler_evaluator": server, "client_garbler": client, "client_evaluator": client}
    try:
        report = netem_report(specs, repeat, shapes, baseline, measure_seconds,
                              congestion_control, slow_start_after_idle,
                              flags.get("quiet", False), done, shaper, control, scheme,
                              localize, profile)
    except LabUnavailable as e:
        click.echo(f"snail-bench: {e}", err=True)
        sys.exit(2)
    except LabError as e:
        click.echo(f"snail-bench: {e}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:  # the lab is gone by now: its `with` unwound
        click.echo("snail-bench: interrupted", err=True)
        sys.exit(130)
    if as_json:
        click.echo(json.dumps(report))
        return
    show_netem(report["netem"])


def show_netem(body: dict) -> None:
    """The netem report as a person reads it: per phase the links as measured and each
    circuit's wall-time median, the evaluator's wait for tables, the median session's
    timeline (where the time went), the forwarder's CPU; the
    control run and the shaped run against the unshaped one."""
    forwarder = f" ({body['forwarder']} forwarder)" if body.get("forwarder") else ""
    click.echo(f"shaper: {body['shaper']}{forwarder}; tcp: {body['tcp']['congestion_control']}"
               f", slow start after idle "
               f"{'on' if body['tcp']['slow_start_after_idle'] else 'off'}")
    base = body.get("unshaped", {}).get("service", {})
    for phase in ("unshaped", "control", None):
        row = body.get(phase) if phase else body
        if row is None:
            continue
        click.echo(f"{phase or 'shaped'}: forwarder CPU {row['wire_cpu_s']:.2f} s")
        for link, m in row["links"].items():
            click.echo(f"  {link:>18}: rtt {m['rtt_ms']:.2f} ms  rate {m['rate_mbit']:.0f} Mbit/s")
        for name, r in row["service"].items():
            versus = ""
            if phase != "unshaped" and name in base:
                versus = (f", {r['median_s'] / base[name]['median_s']:.2f} x unshaped "
                          f"({(r['median_s'] - base[name]['median_s']) * 1000:+.0f} ms)")
            click.echo(f"  {name:>18}: median {r['median_s']:.3f} s (min {r['min_s']:.3f}, "
                       f"max {r['max_s']:.3f}){versus}; evaluator waited for tables "
                       f"{r['evaluator_wait_s'] * 1000:.1f} ms; {r['scheme']}")
            if r.get("timeline_ms"):
                click.echo(f"  {'':>18}  ms after the garbler's request: " + ", ".join(
                    f"{event} {ms:.0f}" for event, ms in r["timeline_ms"].items()))
        for name, loc in row.get("localization", {}).items():
            mb = loc["bytes"]["garbler_to_evaluator"] / 1e6
            click.echo(f"  {name:>18}: localization {loc['wall_s']:.2f} s ({loc['invocations']}"
                       f" invocations, {mb:.1f} MB garbler->evaluator); its links' bound "
                       f"{loc['link_bound_s']:.2f} s: {loc['bound_ratio']:.2f} x the bound")


@click.command()
@click.option("--out", required=True, type=click.Path(file_okay=False),
              help="Directory for results.json, one PNG per figure and report.md.")
@click.option("--quick", is_flag=True,
              help="A subset for under 10 minutes: LM only, n = 6, 12 for totals and 6, 56 "
                   "per iteration, no DO.")
@click.option("--paper-results", type=click.Path(dir_okay=False), default=None,
              help="The paper's numbers (default: ../shared/paper_results.json).")
def paper(out: str, quick: bool, paper_results: str | None) -> None:
    """The paper's evaluation on this machine: SIL vs DO, seconds and bytes per iteration
    vs n at 0 and 5 ms between the servers (network lab, needs root), float32 operations
    per iteration, float vs integer ops, and a latency sweep; each figure with the paper's
    series beside ours. Needs the `bench` extra (matplotlib)."""
    from pathlib import Path

    from .paper import FULL, PAPER_RESULTS, QUICK, load_paper, write_paper

    plan = QUICK if quick else FULL
    flags = click.get_current_context().find_object(dict) or {}
    try:
        numbers = load_paper(Path(paper_results) if paper_results else PAPER_RESULTS)
    except ValueError as e:
        raise click.UsageError(f"--paper-results: {e}") from None
    click.echo(f"snail-bench: the {'quick' if quick else 'full'} plan takes about "
               f"{plan.expected_minutes():g} minutes on 2 idle cores with a cold circuit "
               f"cache (twice that with other work on them).", err=True)
    from snail_client.links import ServiceError

    from .netlab.namespaces import LabError

    try:
        report = write_paper(Path(out), plan, numbers, flags.get("quiet", False))
    except ImportError as e:
        click.echo(f"snail-bench: {e}", err=True)
        sys.exit(2)
    except (ServiceError, LabError, RuntimeError) as e:
        click.echo(f"snail-bench: {e}", err=True)
        sys.exit(1)
    except KeyboardInterrupt:
        click.echo("snail-bench: interrupted", err=True)
        sys.exit(130)
    click.echo(str(report))


