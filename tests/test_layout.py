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


# The tools: every package above the engine but the launcher's plug-in, the benchmarks of speed/, and the commands at
# the top (train.py and clean_sweep.py launch runs: a run's writer and its exported code, not tools). They read runs, write outputs, run workers and take sizes only
# through the engine's services, which decide each question once for all of them (docs/guarantees.md).
TOOL_PACKAGES = ("analysis", "external", "benchmark", "pupil", "speed")
SERVICES = {
    "walk": "walks folders itself: read runs with engine.runset.read_runs (files.walk for anything else below engine)",
    "pool": "starts worker processes itself: run jobs with engine.pool.run_jobs",
    "size": "takes a number without a bound: declare it with engine.budget (count, real, SEED, ...)",
    "guard": "lifts the output writer's guard (engine.tool_output)",
}
_WALKS = {"walk", "listdir", "scandir", "glob", "rglob", "iterdir", "find", "tree"}
_POOLS = {"multiprocessing", "concurrent", "joblib"}


def tool_files() -> list[Path]:
    found = [p for package in TOOL_PACKAGES for p in sorted((ROOT / package).rglob("*.py"))]
    return found + [p for p in sorted(ROOT.glob("*.py")) if p.name not in ("train.py", "clean_sweep.py")]


def bypasses(path: Path) -> list[str]:
    """Each place in ``path`` where a tool does what a service decides (``SERVICES``)."""
    tree = ast.parse(path.read_text(), str(path))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute):
            name, owner = node.func.attr, ast.unparse(node.func.value)
            if name in _WALKS and (owner in ("os", "files") or name in ("glob", "rglob", "iterdir")):
                found.append(f"{node.lineno}: {ast.unparse(node.func)} {SERVICES['walk']}")
            if name == "fork" and owner == "os":
                found.append(f"{node.lineno}: os.fork {SERVICES['pool']}")
            if name == "guard_writes":
                found.append(f"{node.lineno}: {SERVICES['guard']}")
            if name == "add_argument":
                for keyword in node.keywords:
                    if keyword.arg == "type" and ast.unparse(keyword.value) in ("int", "float"):
                        found.append(f"{node.lineno}: {ast.unparse(node.args[0]) if node.args else '?'} {SERVICES['size']}")
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            modules = [a.name for a in node.names] if isinstance(node, ast.Import) else [node.module or ""]
            if any(m.split(".")[0] in _POOLS for m in modules):
                found.append(f"{node.lineno}: imports {', '.join(modules)}: {SERVICES['pool']}")
    return found


def test_no_tool_bypasses_a_service():
    wrong = [f"{path.relative_to(ROOT)}:{line}" for path in tool_files() for line in bypasses(path)]
    assert not wrong, "\n".join(wrong)


def test_the_bypass_check_sees_each_kind(tmp_path):
    sample = tmp_path / "tool.py"
    sample.write_text("import os\nfrom concurrent.futures import ProcessPoolExecutor\nimport multiprocessing\n"
                      "os.walk('.')\nos.listdir('.')\np.rglob('*')\nfiles.find(p, 'x')\nos.fork()\n"
                      "parser.add_argument('--n', type=int)\nparser.add_argument('--x', type=float)\n"
                      "files.guard_writes(None)\n")
    assert len(bypasses(sample)) == 10, bypasses(sample)
    sample.write_text("from engine.runset import read_runs\nfrom engine.pool import run_jobs\n"
                      "parser.add_argument('--n', type=count(1, 9))\nread_runs([p])\n")
    assert bypasses(sample) == []
