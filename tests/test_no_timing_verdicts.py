"""No test's verdict depends on how fast the machine is (docs/development.md, timing-sensitive
tests): no assert bounds a time from above or a rate from below by a fixed figure. A loaded
core makes every time longer and every rate lower, so such a bound fails by chance on a busy
CI machine; the figures belong to ``snail-bench``. What stays allowed holds at any speed: a
time bounded from below (a timeout never fires early, a sleep is never short), a rate bounded
from above, a figure above zero, and a poll's deadline (a hang guard, ``< deadline``)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

TESTS = Path(__file__).parent
RATE = re.compile(r"fps|per_s(?![a-z])|per_second|mbit|throughput")
TIME = re.compile(r"latency|took|elapsed|waited|wall|delay|seconds|rtt|_s\b|_ms\b|monotonic|"
                  r"perf_counter|time\.time")
UPPER = (ast.Lt, ast.LtE)  # ``x < c``: c bounds x from above
LOWER = (ast.Gt, ast.GtE)


def _fixed(node: ast.expr) -> bool:
    """A figure fixed in the test: a non-zero number, a sum of them, or a module constant."""
    if isinstance(node, ast.Constant):
        return isinstance(node.value, (int, float)) and not isinstance(node.value, bool) \
            and node.value != 0
    if isinstance(node, ast.Name):
        return node.id.isupper()
    if isinstance(node, ast.UnaryOp):
        return _fixed(node.operand)
    if isinstance(node, ast.BinOp):
        return (_fixed(node.left) or isinstance(node.left, ast.Constant)) and \
            (_fixed(node.right) or isinstance(node.right, ast.Constant))
    return False


def _verdicts(source: str) -> list[tuple[int, str]]:
    """(line, why) for each bound in an assert that a slower machine could break."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, ast.Assert):
            continue
        for compare in (n for n in ast.walk(node.test) if isinstance(n, ast.Compare)):
            sides = [compare.left, *compare.comparators]
            for left, op, right in zip(sides, compare.ops, sides[1:]):
                if not isinstance(op, (*UPPER, *LOWER)):
                    continue
                for measured, bound, above in ((left, right, isinstance(op, UPPER)),
                                               (right, left, isinstance(op, LOWER))):
                    if not _fixed(bound) or _fixed(measured):
                        continue
                    text = ast.unparse(measured)
                    if text.startswith("len("):
                        continue  # a count, not a figure
                    if RATE.search(text):
                        if not above:
                            found.append((compare.lineno, f"a rate bounded below: {text}"))
                    elif TIME.search(text) and above:
                        found.append((compare.lineno, f"a time bounded above: {text}"))
    return found


@pytest.mark.parametrize("path", sorted(TESTS.glob("*.py")), ids=lambda p: p.name)
def test_no_assert_bounds_a_time_above_or_a_rate_below(path):
    found = _verdicts(path.read_text())
    assert not found, "\n".join(f"{path.name}:{line}: {why}" for line, why in found)


@pytest.mark.parametrize(("code", "caught"), [
    ("assert time.monotonic() - t0 < 8", True),
    ("assert took < BOUND_S", True),
    ("assert summary['fps'] >= 20", True),
    ("assert 30 <= report['runs_per_s']", True),
    ("assert 0 < row['median_s'] <= 0.25", True),
    ("assert took > 0.8", False),  # a timeout never fires early
    ("assert summary['fps'] > 0", False),
    ("assert report['and_per_s'] < 2_000_000", False),  # a rate from above: any speed
    ("assert time.monotonic() < deadline", False),  # a poll's hang guard
    ("assert len(timing['per_iteration_s']) < 7", False),
])
def test_the_guard_tells_a_speed_bound_from_one_that_holds_at_any_speed(code, caught):
    assert bool(_verdicts(code)) is caught
