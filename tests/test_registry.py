"""The one registry of learners (learners/registry.py): every learner declared once, in its own module,
found by name; nothing else tells learners apart by comparing their names."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

import learners
from engine.config import block_names
from learners.registry import LEARNERS, MODULES

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("door", "racing", "losses", "collectors", "learners", "engine", "analysis", "benchmark", "external", "pupil",
            "hydra_plugins", "speed")


def _project_modules():
    yield from ROOT.glob("*.py")
    for package in PACKAGES:
        yield from (ROOT / package).rglob("*.py")


def test_no_module_tells_learners_apart_by_name():
    """``algo.loss == "sac"``, ``kind in ("td3", "crossq")``: a comparison with a learner's name outside that
    learner's own module is a dispatch the registry should hold (a spec attribute or a function of the
    learner's module), and a new learner would silently take another's branch."""
    names = set(LEARNERS)
    own = {ROOT / (module.replace(".", "/") + ".py") for module in MODULES}
    found = []
    for path in _project_modules():
        if path in own:
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.Compare):
                continue
            for side in (node.left, *node.comparators):
                values = side.elts if isinstance(side, (ast.Tuple, ast.List, ast.Set)) else [side]
                if any(isinstance(v, ast.Constant) and v.value in names for v in values):
                    found.append(f"{path.relative_to(ROOT)}:{node.lineno}: {ast.unparse(node)[:80]}")
    assert not found, "learners told apart by name outside their modules (learners/registry.py):\n" + "\n".join(found)


def test_each_learner_is_declared_once_with_its_configuration():
    """Every spec names its own module and a family; every conf/algo file names a registered learner, and
    every learner has a conf/algo file of its name; AlgoConfig reads exactly the blocks they declare."""
    for name, spec in LEARNERS.items():
        assert spec.name == name and spec.family in learners.FAMILIES
        assert (ROOT / "conf" / "algo" / f"{name}.yaml").exists(), name
    declared = {block for spec in LEARNERS.values() for block in spec.blocks}
    declared |= {block for family in learners.FAMILIES.values() for block in family.BLOCKS}
    assert declared == block_names()
    for path in (ROOT / "conf" / "algo").glob("*.yaml"):
        node = yaml.safe_load(path.read_text())
        while "loss" not in node:  # an algorithm built on another (its defaults list)
            base = next(entry for entry in node["defaults"] if entry != "_self_")
            node = yaml.safe_load((path.parent / f"{base}.yaml").read_text())
        assert node["loss"] in LEARNERS, path


def test_the_registry_and_the_configuration_load_without_torch():
    """A run's configuration is checked before torch loads (its numerics are set first): the registry, every
    learner's declaration and its options import no torch."""
    code = ("import sys; import learners.registry, engine.config; "
            "from engine.config import RunConfig; RunConfig.compose('algo=trust_pcl', 'er=memory'); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stderr[-2000:]


def test_an_unknown_learner_is_refused_naming_every_one():
    from engine.config import ConfigError
    from learners.registry import spec

    try:
        spec("no_such_learner")
    except ConfigError as err:
        assert str(err) == f"algo.loss must be one of {', '.join(LEARNERS)}; got 'no_such_learner'"
    else:
        raise AssertionError("no_such_learner was found")


def test_a_new_learner_module_is_found_without_a_list_to_extend(tmp_path, monkeypatch):
    """The registry finds learners in the families' folders: a module that assigns ``SPEC`` is one (however
    it is spelled), a helper beside it is not imported, and a SPEC that names another module or family is
    refused when the registry loads, as is one that lacks what its family's ``LearnerModule`` requires."""
    import sys

    import learners.registry as registry
    import learners.td

    hooks = "METRICS = ((), ())\n" + "".join(f"def {name}(*args): pass\n" for name in
                                            ("actor", "critics", "exploration_noise", "loss", "prepare", "step"))
    (tmp_path / "toy.py").write_text(
        "from learners.registry import LearnerSpec\n"
        "SPEC: LearnerSpec = LearnerSpec(name='toy', title='Toy', family='td', module=__name__)\n" + hooks)
    (tmp_path / "toy_helper.py").write_text("raise AssertionError('a module without SPEC is not imported')\n")
    monkeypatch.setattr(learners.td, "__path__", [*learners.td.__path__, str(tmp_path)])
    monkeypatch.delitem(sys.modules, "learners.td.toy", raising=False)
    modules = registry._modules()
    assert "learners.td.toy" in modules and "learners.td.toy_helper" not in modules
    assert "learners.td.learner" not in modules  # the family's machinery beside its learners
    monkeypatch.setattr(registry, "MODULES", modules)
    assert registry._load()["toy"].title == "Toy"

    (tmp_path / "toy.py").write_text(
        "from learners.registry import LearnerSpec\n"
        "SPEC = LearnerSpec(name='toy', title='Toy', family='td', module=__name__)\n" + hooks.replace("def step", "def stop"))
    monkeypatch.delitem(sys.modules, "learners.td.toy", raising=False)
    with pytest.raises(RuntimeError, match="needs step or phase .learners.td.LearnerModule declares each"):
        registry._load()

    (tmp_path / "toy.py").write_text(
        "from learners.registry import LearnerSpec\n"
        "SPEC = LearnerSpec(name='toy', title='Toy', family='monte_carlo', module=__name__)\n")
    monkeypatch.delitem(sys.modules, "learners.td.toy", raising=False)
    with pytest.raises(RuntimeError, match="the family whose package holds it"):
        registry._load()
