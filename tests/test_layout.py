"""The house's floors: a package imports only packages below it (docs/layout.md), read from the code."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# Each package's floor, the bottom first; packages on one floor do not import each other.
FLOORS = {
    "door": 0,
    "racing": 1, "losses": 1, "collectors": 1,
    "learners": 2,
    "engine": 3,
    "analysis": 4,
    "external": 5,
    "benchmark": 6,
    "pupil": 7,
    "hydra_plugins": 8,
}


def _imports(path: Path) -> list[tuple[int, str]]:
    """(line, module) of every absolute import in ``path``, at any depth (a function's own imports too),
    except under ``if __name__ == "__main__":`` (a command's entry point is the top of the house)."""
    tree = ast.parse(path.read_text(), str(path))
    entry = {id(node) for top in tree.body if isinstance(top, ast.If) and "__main__" in ast.unparse(top.test)
             for node in ast.walk(top)}
    found = []
    for node in ast.walk(tree):
        if id(node) in entry:
            continue
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.append((node.lineno, node.module))
    return found


def test_no_package_imports_one_above_it_or_beside_it():
    wrong = []
    for package, floor in FLOORS.items():
        for path in sorted((ROOT / package).rglob("*.py")):
            for line, module in _imports(path):
                other = module.split(".")[0]
                if other in FLOORS and other != package and FLOORS[other] >= floor:
                    wrong.append(f"{path.relative_to(ROOT)}:{line} imports {module} (floor {FLOORS[other]} >= {floor})")
    assert not wrong, "\n".join(wrong)


def test_every_package_has_a_floor():
    """A new package is placed on a floor here (and in docs/layout.md) before anything imports it."""
    packages = {p.parent.name for p in ROOT.glob("*/__init__.py")} - {"tests", "conf", "speed"}
    assert packages <= set(FLOORS), sorted(packages - set(FLOORS))


def test_the_layout_page_names_the_floors_in_order():
    text = (ROOT / "docs" / "layout.md").read_text()
    block = text[text.index("```"):text.index("```", text.index("```") + 3)]
    positions = {package: block.find(f"{package}/") for package in FLOORS}
    assert all(position >= 0 for position in positions.values()), positions
    floors = sorted(set(FLOORS.values()))
    for lower, upper in zip(floors, floors[1:]):  # the page draws the house top down
        assert min(positions[p] for p, f in FLOORS.items() if f == upper) < \
            min(positions[p] for p, f in FLOORS.items() if f == lower), (lower, upper)
