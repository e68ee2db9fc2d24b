"""The floor plan holds: no module imports a package on its own floor or above it.

Floors, bottom up (docs/architecture.md draws them): the failpoints registry; the circuit
compiler; arithmetic and the garbling engine; the PnP circuit families and the network
layer; the client-side localization and the family registration; the roles; the
benchmarks and demos. A lower
floor that needs something from above takes it as a parameter or a registration.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
FLOORS = {
    "snail_common.failpoints": 0,
    "snail_common.circuit": 1,
    "snail_common.arith": 2,
    "snail_common.gc": 2,
    "snail_common.pnp": 3,
    "snail_common.net": 3,
    "snail_common.loc": 4,
    "snail_common.ot": 4,
    "snail_common.families": 4,
    "snail_client": 5,
    "snail_garbler": 5,
    "snail_evaluator": 5,
    "snail_mapd": 5,
    "snail_sim": 6,
    "snail_bench": 7,
    "snail_demo": 7,
}


def package_of(module: str) -> str | None:
    """The FLOORS entry a dotted module name belongs to (longest prefix)."""
    best = None
    for name in FLOORS:
        if (module == name or module.startswith(name + ".")) and (
                best is None or len(name) > len(best)):
            best = name
    return best


def modules() -> list[tuple[str, Path]]:
    found = []
    for top in {name.split(".")[0] for name in FLOORS}:
        for path in sorted((ROOT / top).rglob("*.py")) if (ROOT / top).is_dir() else []:
            parts = path.relative_to(ROOT).with_suffix("").parts
            if parts[-1] == "__init__":
                parts = parts[:-1]
            found.append((".".join(parts), path))
    return found


def imports_of(module: str, path: Path) -> list[tuple[int, str]]:
    """(line, absolute module) of every import in the file, relative ones resolved."""
    tree = ast.parse(path.read_text(), str(path))
    is_package = path.name == "__init__.py"
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")
                base = base[: len(base) - node.level + (1 if is_package else 0)]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            names = [f"{target}.{alias.name}" for alias in node.names]
            out += [(node.lineno, target)] + [(node.lineno, n) for n in names
                                                if package_of(n) != package_of(target)]
    return out


def violations() -> list[str]:
    bad = []
    for module, path in modules():
        own = package_of(module)
        if own is None:
            continue
        for line, target in imports_of(module, path):
            theirs = package_of(target)
            if theirs is None or theirs == own:
                continue
            if FLOORS[theirs] >= FLOORS[own]:
                bad.append(f"{path.relative_to(ROOT)}:{line}: {own} (floor {FLOORS[own]}) "
                           f"imports {target} (floor {FLOORS[theirs]})")
    return bad


def test_every_module_is_on_a_floor():
    unplaced = [m for m, _ in modules() if package_of(m) is None
                and m not in ("snail_common",)]
    assert not unplaced, f"modules on no floor (add them to FLOORS): {unplaced}"


def test_no_import_runs_up_or_across_a_floor():
    bad = violations()
    assert not bad, "imports that run up or across a floor:\n" + "\n".join(bad)


@pytest.mark.parametrize(("source", "expect"), [
    ("from snail_client.secure import X\n", "snail_client"),
    ("import snail_bench.cli\n", "snail_bench"),
    ("from ..loc import driver\n", "snail_common.loc"),
    ("from snail_common import loc\n", "snail_common.loc"),
])
def test_the_check_sees_every_form_of_import(tmp_path, source, expect):
    """An upward import in snail_common/net is found whatever its spelling."""
    path = tmp_path / "snail_common" / "net" / "x.py"
    path.parent.mkdir(parents=True)
    path.write_text(source)
    targets = [t for _, t in imports_of("snail_common.net.x", path)]
    assert expect in {package_of(t) for t in targets}
