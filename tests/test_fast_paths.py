"""What a researcher edits is what runs: every fast path steps aside for an edit to the code it copies.

A fast path (the paper's fused phases, SAC's, TQC's, CrossQ's and TD3's fused steps) computes a loss
module's numbers on plain tensors. ``learners.fast_paths`` is its one guard: these tests edit, one at a
time, every method of the loss module that a default run of each such learner calls, and see the run
take the loss module's path with the edit in effect and say why; in a copy of the code, the same
through ``train.py``, and a docstring's edit leaves the fast path on.
"""

from __future__ import annotations

import ast
import json
import os
import shutil
import subprocess
import sys
import textwrap
import inspect
from pathlib import Path

import pytest
import torch

from engine.setup import make_env, make_generators, make_learner
from learners import fast_paths, kernels
from learners.base import MetricTotals
from learners.registry import LEARNERS
from tests.test_config import load

ROOT = Path(__file__).resolve().parents[1]
SEEDS = (2067791, 5468063)
# every learner that may have a fast path: the off-policy ones whose module declares fused_available, and
# the paper's family (its phases are fused for SPGLoss and LogClipPPOLoss where the products are the
# project's kernels; a new learner's loss of its own has none: ``_has_fast_path``)
FAST = sorted([name for name, spec in LEARNERS.items()
               if spec.family == "monte_carlo" or hasattr(spec.torch_half(), "fused_available")])


def _has_fast_path(learner) -> bool:
    """Whether the built ``learner``'s loss is one a fast path was written for; a Monte-Carlo learner with a
    loss of its own runs its loss module, and its path says so (asserted)."""
    from losses import LogClipPPOLoss, SPGLoss

    if learner.monte_carlo and not isinstance(learner.loss, (SPGLoss, LogClipPPOLoss)):
        assert learner.phases.path["critic"] == "loss module" and "has no fused phases" in learner.phases.path["why"]
        return False
    return True


@pytest.fixture(autouse=True)
def _project_kernels():
    if kernels.use(True):
        pytest.skip("the project's kernels cannot be built here (no C++ compiler): the paper's phases are not fused")
    yield


def _learner(name: str):
    td = ["algo.td.warmup_episodes=1"] if LEARNERS[name].family == "td" else []
    cfg = load(f"algo={name}", "er=memory", f"seeds=[{','.join(map(str, SEEDS))}]", *td)
    generators = make_generators(SEEDS)
    return cfg, make_learner(cfg, make_env(cfg, SEEDS), generators), generators


def _data(learner, members: int = len(SEEDS), n: int = 64) -> "TensorDict":
    """Transitions of every key the learner's phases read."""
    from tensordict import TensorDict

    g = torch.Generator().manual_seed(0)
    obs = learner.networks.actor_net.obs_dim if hasattr(learner.networks.actor_net, "obs_dim") else 6
    data = TensorDict({"observation": torch.rand(members, n, obs, generator=g),
                       "action": torch.rand(members, n, 2, generator=g) * 2 - 1,
                       "value_target": torch.randn(members, n, 1, generator=g),
                       "advantage": torch.randn(members, n, 1, generator=g),
                       "sample_log_prob": -torch.rand(members, n, generator=g),
                       "next": TensorDict({"observation": torch.rand(members, n, obs, generator=g),
                                           "reward": torch.rand(members, n, 1, generator=g),
                                           "done": torch.zeros(members, n, 1, dtype=torch.bool),
                                           "terminated": torch.zeros(members, n, 1, dtype=torch.bool)},
                                          batch_size=[members, n])}, batch_size=[members, n])
    return data


def _update(learner, data) -> None:
    """One update phase: a Monte-Carlo phase, or the off-policy steps owed before episode 2."""
    learner.phases.run(data, 16, MetricTotals(), episode=2)


def _methods_a_step_calls(name: str) -> list[tuple[type, str]]:
    """(class, member) of every method of the loss's classes (the project's and TorchRL's, within
    ``fast_paths.SCOPE``) that an update through the loss module calls."""
    cfg, learner, _ = _learner(name)
    if not _has_fast_path(learner):
        return []  # nothing copied, nothing to guard: its edits run as written
    loss = learner.loss
    owners = {}
    for klass in type(loss).__mro__:
        if fast_paths.in_scope(klass):
            for member, value in vars(klass).items():
                function = value.fget if isinstance(value, property) else getattr(value, "__func__", value)
                code = getattr(inspect.unwrap(function), "__code__", None) if callable(function) else None
                if code is not None and not code.co_filename.startswith("<"):
                    owners.setdefault(code, (klass, member))
    called = {}

    def profile(frame, event, _):
        if event == "call" and frame.f_code in owners:
            called.setdefault(owners[frame.f_code], None)

    _module_path(learner)
    data = _data(learner)
    sys.setprofile(profile)
    try:
        _update(learner, data)
    finally:
        sys.setprofile(None)
    return list(called)


def _module_path(learner) -> None:
    phases = learner.phases
    if hasattr(phases, "fused_critic"):
        phases.fused_critic = phases.fused_actor = None
    else:
        phases.fused = False


def _edited(klass: type, member: str, prelude: str):
    """``klass.member`` with ``prelude`` as its first statement, compiled from its source (a property's
    getter for a property)."""
    value = vars(klass)[member]
    function = value.fget if isinstance(value, property) else getattr(value, "__func__", value)
    tree = ast.parse(textwrap.dedent(inspect.getsource(function)))
    definition = tree.body[0]
    scope = dict(vars(sys.modules[klass.__module__]))
    # kept: contextmanager and the like (a wrapper the raise must run inside); dropped: the descriptor
    # (re-made below) and any whose name the module does not hold at its top (TorchRL's dispatch)
    definition.decorator_list = [d for d in definition.decorator_list
                                 if ast.unparse(d) not in ("property", "staticmethod", "classmethod")
                                 and next(n.id for n in ast.walk(d) if isinstance(n, ast.Name)) in scope]
    definition.body.insert(0, ast.parse(prelude).body[0])
    namespace: dict = {}
    exec(compile(ast.fix_missing_locations(ast.Module(body=[ast.ClassDef(
        name="_Edit", bases=[], keywords=[], body=[definition], decorator_list=[], type_params=[])],
        type_ignores=[])), f"<edit of {member}>", "exec"), scope, namespace)
    edited = vars(namespace["_Edit"])[member]
    if isinstance(value, property):
        return property(edited, value.fset, value.fdel)
    return type(value)(edited) if isinstance(value, (staticmethod, classmethod)) else edited


def test_the_record_is_the_code_as_it_is():
    """learners/fast_paths.json holds the code every fast path was last checked against. An edit to
    any of it turns those fast paths off (the loss module computes, and the run says so): mirror the
    change in the fast path, pass its bit-for-bit tests (tests/test_fused_phases.py,
    tests/test_offpolicy.py), then run ``python -m learners.fast_paths --record``."""
    now, record = fast_paths.record_now(), fast_paths.recorded()
    differ = sorted(name for name in set(now) | set(record) if now.get(name) != record.get(name))
    assert not differ, "changed since the fast paths were checked against them: " + ", ".join(differ)


@pytest.mark.parametrize("name", FAST)
def test_a_default_run_takes_the_fast_path(name):
    _, learner, _ = _learner(name)
    if _has_fast_path(learner):
        assert learner.phases.path["critic"] == "fused" and learner.phases.code_refusal is None, learner.phases.path


@pytest.mark.slow
@pytest.mark.parametrize("name", FAST)
def test_an_edit_to_any_method_a_step_calls_runs_and_says_so(name, monkeypatch):
    """Every method of the loss module an update calls, edited in place (a raise as its first line): the
    learner takes the loss module's path, names the method in its one line, and the update raises the
    edit's error (the edit ran). The digest that notices it ignores a docstring and sees a changed
    constant (checked on each method's own source)."""
    methods = _methods_a_step_calls(name)
    assert len(methods) >= 3 or not methods, methods
    ran = []
    for klass, member in methods:
        qualified = f"{klass.__module__}.{klass.__qualname__}.{member}"
        with monkeypatch.context() as patch:
            patch.setattr(klass, member, _edited(klass, member, f"raise RuntimeError('edited {qualified}')"))
            try:
                _, learner, _ = _learner(name)  # a method the build calls raises here: the edit ran
                assert learner.phases.path["critic"] == "loss module", (qualified, learner.phases.path)
                assert qualified in learner.phases.code_refusal or "and" in learner.phases.code_refusal
                _update(learner, _data(learner))
            except RuntimeError as err:
                assert f"edited {qualified}" in str(err), err
                ran.append(member)
            # not raised: this update did not call it (a clean-up TorchRL runs only when the garbage collector
            # has left it something, say); what the guard says was checked above
        source = textwrap.dedent(inspect.getsource(_function(klass, member)))
        assert fast_paths.source_digest(_with_docstring(source)) == fast_paths.source_digest(source), qualified
        changed = _constant_changed(source)
        assert fast_paths.source_digest(changed) != fast_paths.source_digest(source), qualified
    loss_methods = {member for _, member in methods if member in ("forward", "actor_loss", "qvalue_loss", "value_loss",
                                                                  "qvalue_v2_loss", "critic_loss", "draw")}
    assert loss_methods and loss_methods <= set(ran), (loss_methods, ran)  # the losses themselves: always run


def _function(klass, member):
    value = vars(klass)[member]
    return value.fget if isinstance(value, property) else getattr(value, "__func__", value)


def _with_docstring(source: str) -> str:
    """``source`` with its docstring replaced (or one added)."""
    tree = ast.parse(source)
    body = tree.body[0].body
    doc = ast.Expr(ast.Constant("Another docstring, as a researcher might write it."))
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant) and isinstance(body[0].value.value, str):
        body[0] = doc
    else:
        body.insert(0, doc)
    return ast.unparse(ast.fix_missing_locations(tree))


def _constant_changed(source: str) -> str:
    """``source`` with its first number changed (or, with none, a statement added)."""
    tree = ast.parse(source)
    for node in ast.walk(tree.body[0]):
        if isinstance(node, ast.Constant) and type(node.value) in (int, float) and not isinstance(node.value, bool):
            node.value = node.value + 1
            return ast.unparse(tree)
    tree.body[0].body.append(ast.parse("_ = 1").body[0])
    return ast.unparse(ast.fix_missing_locations(tree))


def test_a_subclass_or_a_method_added_in_place_is_new_code(monkeypatch):
    """A subclass written outside the project's files, a method added to the loss class and a method
    replaced on the class at run time: each keeps the fast path off, named."""
    from losses.sac import MemberSACLoss
    from losses.td3 import MemberTD3Loss

    _, learner, _ = _learner("td3")
    assert fast_paths.refusal(learner.loss) is None

    def actor_loss(self, tensordict):  # an override added in place (the TD3 case)
        return super(MemberTD3Loss, self).actor_loss(tensordict)
    monkeypatch.setattr(MemberTD3Loss, "actor_loss", actor_loss, raising=False)
    assert "losses.td3.MemberTD3Loss.actor_loss" in fast_paths.refusal(learner.loss)
    monkeypatch.undo()
    _, learner, _ = _learner("sac")
    learner.loss.__class__ = type("MySACLoss", (MemberSACLoss,), {"__module__": "my_experiment"})
    assert "my_experiment.MySACLoss" in fast_paths.refusal(learner.loss)


# ---------------------------------------------------------------- through train.py, in a copy of the code
EDITS = {  # learner: (file, the line a researcher's edit follows, the edit), each a method its default run calls
    "sac": ("losses/sac.py", "    def actor_loss(self, tensordict: TensorDictBase):\n", "        raise RuntimeError('my SAC')\n"),
    "tqc": ("losses/tqc.py", "    def qvalue_v2_loss(self, tensordict: TensorDictBase) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:\n",
            "        raise RuntimeError('my TQC')\n"),
    "td3": ("losses/td3.py", "        self.smoothing, self.generators = policy_noise, list(generators) if generators is not None else None\n",
            "\n    def actor_loss(self, tensordict):\n        raise RuntimeError('my TD3')\n"),
    "crossq": ("losses/crossq.py", "    def alpha_loss(self, log_prob: torch.Tensor, tensordict: TensorDictBase | None = None) -> torch.Tensor:\n",
               "        raise RuntimeError('my CrossQ')\n"),
    "spg": ("losses/spg.py", "    def actor_loss(self, tensordict: TensorDictBase) -> TensorDictBase:\n",
            "        raise RuntimeError('my SPG')\n"),
}


def _code_copy(tmp_path: Path) -> Path:
    copy = tmp_path / "code"
    shutil.copytree(ROOT, copy, ignore=shutil.ignore_patterns(".git", ".venv", "outputs", "__pycache__", "*.egg-info"))
    return copy


def _train(copy: Path, folder: Path, name: str) -> subprocess.CompletedProcess:
    command = [sys.executable, "train.py", f"algo={name}", "er=memory", "episodes=3", "progress=false", "logger=none",
               f"hydra.run.dir={folder}"]
    if LEARNERS[name].family == "td":
        command += ["algo.td.warmup_episodes=1", "algo.td.updates_per_step=0.02"]
    return subprocess.run(command, cwd=copy, env={**os.environ, "PYTHONPATH": str(copy)}, capture_output=True,
                          text=True, timeout=600)


@pytest.mark.slow
def test_an_edited_loss_in_a_copy_of_the_code_runs_and_a_docstring_does_not_matter(tmp_path):
    """The issue's trial, as a researcher runs it: a raise added to the method each learner's run calls
    (an override added to TD3's loss), in a copy of the code, then train.py: the run stops with the edit's
    error after one line naming the method; a copy whose edits are docstrings only trains on the fast path."""
    quiet = _code_copy(tmp_path / "quiet")
    docstrings = {"losses/sac.py": ('    """``torchrl.objectives.SACLoss`` with one entropy temperature',
                                   '    """``torchrl.objectives.SACLoss``, with one entropy temperature'),
                  "learners/networks.py": ('    """tanh(x) to within 2.4e-7 (absolute)',
                                           '    """The tanh of x, to within 2.4e-7 (absolute)')}
    for relative, (before, after) in docstrings.items():
        path = quiet / relative
        text = path.read_text()
        assert text.count(before) == 1, before
        path.write_text(text.replace(before, after))
    for name in ("sac", "td3", "spg"):
        done = _train(quiet, tmp_path / f"quiet-{name}", name)
        assert done.returncode == 0, done.stderr
        assert "fused update steps are off" not in done.stderr
        summary = json.loads((tmp_path / f"quiet-{name}" / "summary.json").read_text())
        assert summary["paths"][0]["critic"] == "fused" == summary["paths"][0]["actor"], summary["paths"]
    for name, (relative, marker, edit) in EDITS.items():
        copy = _code_copy(tmp_path / name)
        path = copy / relative
        text = path.read_text()
        assert text.count(marker) == 1, (name, marker)
        path.write_text(text.replace(marker, marker + edit))
        done = _train(copy, tmp_path / f"run-{name}", name)
        error = edit.split("raise ")[1].strip()
        assert done.returncode != 0 and error.replace("'", "") in done.stderr.replace("'", ""), done.stderr
        (note,) = [line for line in done.stderr.splitlines() if "fused update steps are off" in line]
        assert "changed since the fast path was checked against" in note, note


@pytest.mark.parametrize("prefix, name", [("losses.td3.fused_", "losses.td3.fused_td3_actor_losses"),
                                          ("learners.monte_carlo.fused.", "learners.monte_carlo.fused.copied_functions")])
def test_an_edit_to_a_fast_paths_own_code_is_found(monkeypatch, prefix, name):
    """On 35048d1 ``raise RuntimeError`` in losses/td3.py's fused_td3_actor_losses stopped a default TD3 run, but a
    compile=true run (TorchRL's TD3Loss.actor_loss) completed and said nothing: such an edit is now found and named."""
    assert fast_paths.own_edits((prefix,)) == []
    record = dict(fast_paths.recorded())
    assert name in record
    record[name] = "edited"
    monkeypatch.setattr(fast_paths, "_RECORD", record)
    assert fast_paths.own_edits((prefix,)) == [name]


def test_a_run_off_the_fast_path_names_an_edit_it_does_not_run(monkeypatch, capsys, tmp_path):
    """Every mode that takes the loss module's path (compile=true, a setting the fast path does not compute, the
    fast paths switched off) says in one line which path it took and why, and which edit does not run."""
    from engine.runner import train
    from learners.td import learner as td_learner

    record = dict(fast_paths.recorded())
    record["losses.td3.fused_td3_actor_losses"] = "edited"
    monkeypatch.setattr(fast_paths, "_RECORD", record)
    monkeypatch.setattr(td_learner, "FUSED", False)
    summary = train(load("algo=td3", "episodes=1", "progress=false", "logger=none", "seed=1"), tmp_path)
    err = capsys.readouterr().err
    assert ("Note: losses.td3.fused_td3_actor_losses changed, but this run's updates are the loss module's "
            "(learners.td.learner.FUSED is off): that edit does not run here") in err, err
    assert summary["paths"][0]["edits_not_run"] == ["losses.td3.fused_td3_actor_losses"]
