"""``snail-bench bristol``, ``compiler``, ``ops``, ``circuit`` and ``engine``: the commands
that measure circuits and the garbling engine on this machine, without daemons. The
measuring lives in ``compiler.py``, ``ops.py``, ``circuit.py`` and ``engine.py``; here are
the flags, their checks and what a person reads."""

from __future__ import annotations

import json

import click
import numpy as np

from snail_common.circuit import evaluate_bits, schedule_circuit
from snail_common.circuit.bristol import BristolError, load_bristol
from snail_common.gc.stream import SCHEMES

from .choices import ARITH, circuit_options
from .choices import spec as _spec


def _parse_int(text: str) -> int:
    try:
        return int(text, 0)
    except ValueError:
        raise click.BadParameter(f"{text!r} is not an integer (decimal or 0x-hex)") from None


def _emit(report: dict, as_json: bool) -> None:
    """Print a one-section report as JSON (the FORMATS contract) or as aligned lines."""
    if as_json:
        click.echo(json.dumps(report))
        return
    for key, value in next(iter(report.values())).items():
        if isinstance(value, dict) and value and all(isinstance(v, dict)
                                                     for v in value.values()):
            for name, fields in value.items():  # one line per entry, its plain fields
                plain = "  ".join(f"{k} {v}" for k, v in fields.items()
                                  if not isinstance(v, dict))
                click.echo(f"{key + ' ' + name:>24}: {plain}")
            continue
        if isinstance(value, dict):
            value = "  ".join(f"{k} {v}" for k, v in value.items())
        click.echo(f"{key:>24}: {value}")



@click.command()
@click.argument("file", type=click.Path(exists=True, dir_okay=False))
@click.option("--input", "inputs", multiple=True, required=True, metavar="INT",
              help="One input value of the file, in order: an integer (decimal or 0x-hex) "
                   "whose bit i is the value's wire i. Repeat once per input value.")
@click.option("--garbled", is_flag=True,
              help="Garble and evaluate with half-gates (fresh seed and delta) instead of "
                   "evaluating in the clear.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def bristol(file: str, inputs: tuple[str, ...], garbled: bool, as_json: bool) -> None:
    """Run a Bristol Fashion circuit FILE and print its outputs."""
    try:
        circuit = load_bristol(file)
    except BristolError as e:
        raise click.UsageError(f"{file}: {e}") from None
    if len(inputs) != len(circuit.inputs):
        raise click.UsageError(f"{file} takes {len(circuit.inputs)} --input values, "
                               f"got {len(inputs)}")
    bits = []
    for group, text in zip(circuit.inputs, inputs):
        value = _parse_int(text)
        if value < 0:
            value &= (1 << group.bits) - 1  # two's complement
        if value >> group.bits:
            raise click.UsageError(f"--input {text} does not fit in {group.bits} bits")
        bits.extend((value >> i) & 1 for i in range(group.bits))
    schedule = schedule_circuit(circuit)
    if garbled:
        from snail_common.gc.run import garbled_run

        out_bits = np.asarray(garbled_run(schedule, np.array(bits, bool))).reshape(-1)
    else:
        out_bits = evaluate_bits(schedule, np.array([bits], bool))[0]
    outputs, pos = [], 0
    for group in circuit.output_groups:
        chunk = out_bits[pos : pos + group.bits]
        pos += group.bits
        outputs.append(sum(1 << i for i, bit in enumerate(chunk) if bit))
    counts = circuit.counts()
    result = {"outputs": outputs, **counts, "depth": circuit.depth(), "garbled": garbled}
    if as_json:
        click.echo(json.dumps({"bristol": result}))
    else:
        click.echo(" ".join(str(v) for v in outputs))
        click.echo(f"AND {counts['and']}  XOR {counts['xor']}  NOT {counts['not']}  "
                   f"depth {circuit.depth()}", err=True)


@click.command()
@click.option("--gates", default=50_000_000, show_default=True,
              help="Approximate size of the generated circuit.")
@click.option("--lane-words", default=1, show_default=True,
              help="64-bit words of input vectors per wire in the cleartext run.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def compiler(gates: int, lane_words: int, as_json: bool) -> None:
    """Build, schedule and evaluate a wide circuit of about --gates gates (foundation targets:
    <= 30 s and <= 3 GB for 50 M gates; >= 100 M gates/s in the clear)."""
    from .compiler import compiler_report

    _emit(compiler_report(gates, lane_words), as_json)


@click.command()
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def ops(as_json: bool) -> None:
    """AND, XOR and AND-depth of every arithmetic op (float32 and integer building blocks)."""
    from .ops import ops_report

    _emit(ops_report(), as_json)


@click.command()
@circuit_options
@click.option("--points", type=click.IntRange(4, 4096), default=6, show_default=True,
              help="Number of point correspondences the circuit takes.")
@ARITH
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def circuit(algorithm: str, mode: str, points: int, solve: str | None, solver: str,
            arith: str | None, as_json: bool) -> None:
    """AND/XOR gates, AND-depth, schedule steps and build time of a localization circuit."""
    from .circuit import circuit_report

    try:
        spec = _spec(algorithm, mode, solve, solver, points, arith)
    except ValueError as e:
        raise click.UsageError(str(e)) from None
    _emit(circuit_report(spec), as_json)


@click.command()
@click.option("--scheme", "schemes", type=click.Choice(list(SCHEMES)),
              multiple=True, help="Garbling scheme to measure; repeat for several (default: "
                                  "both, half-gates first). The first one's numbers are the "
                                  "top-level fields; each scheme's are under 'schemes'.")
@click.option("--engine", "engine_names", type=click.Choice(["native", "numpy"]),
              multiple=True, help="Engine to measure; repeat for several (default: the "
                                  "native kernel where it can run, and numpy, in the same "
                                  "run). Each engine's numbers are under 'engines'; the "
                                  "top-level fields are the engine the daemons would serve "
                                  "with ($SNAIL_ENGINE).")
@click.option("--threads", type=click.IntRange(1, 2),
              help="Threads the native kernel cuts wide steps across (default: "
                   "$SNAIL_KERNEL_THREADS, else 1). With 2 the native figures use two "
                   "cores; the report's kernel_threads says so.")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def engine(schemes: tuple[str, ...], engine_names: tuple[str, ...], threads: int | None,
           as_json: bool) -> None:
    """Garbling engine: AES rate, garble/evaluate AND gates per second on wide steps,
    per-step overhead on narrow ones, a two-process loopback rate, and the garbler ->
    evaluator bytes per AND gate, per scheme (with both: bytes_ratio, three-halves over
    half-gates) and per engine (the native kernel and numpy)."""
    from snail_common.gc.engine import NativeUnavailable

    from .engine import SCHEMES, engine_report

    try:
        report = engine_report(schemes=tuple(dict.fromkeys(schemes)) or tuple(SCHEMES),
                               engine_names=engine_names or None, threads=threads)
    except NativeUnavailable as exc:
        raise click.BadParameter(f"native: {exc}", param_hint="--engine") from None
    _emit(report, as_json)
