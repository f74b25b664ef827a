"""Adding a learner of either family touches no file outside its own: in a copy of the code, a learner of
each family is added as docs/learners.md says (its module, its loss, its conf/algo file), then the
configuration, registry and layout tests pass unchanged and each trains; the Monte-Carlo one, with a loss of
its own, runs its loss module without a note (a note is for an edit a fast path would otherwise skip)."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _copy(tmp_path: Path) -> Path:
    copy = tmp_path / "code"
    shutil.copytree(ROOT, copy, ignore=shutil.ignore_patterns(".git", ".venv", "outputs", "__pycache__", "*.egg-info"))
    return copy


def _add_monte_carlo_learner(copy: Path) -> None:
    """``toy_ppo``: PPO's objective in a loss class of its own (``losses/toy_ppo.py``, not a subclass)."""
    loss = (copy / "losses" / "ppo.py").read_text().replace("LogClipPPOLoss", "ToyPPOLoss")
    (copy / "losses" / "toy_ppo.py").write_text(loss.replace('"""``ToyPPOLoss``', '"""``ToyPPOLoss`` (a new learner\'s)', 1))
    module = (copy / "learners" / "monte_carlo" / "ppo.py").read_text()
    module = module.replace('SPEC = LearnerSpec(name="ppo", title="PPO"', 'SPEC = LearnerSpec(name="toy_ppo", title="Toy PPO"')
    module = module.replace("    from losses import LogClipPPOLoss\n", "    from losses.toy_ppo import ToyPPOLoss\n")
    module = module.replace("return LogClipPPOLoss(", "return ToyPPOLoss(")
    (copy / "learners" / "monte_carlo" / "toy_ppo.py").write_text(module)
    conf = (copy / "conf" / "algo" / "ppo.yaml").read_text()
    conf = re.sub(r"^name: ppo", "name: toy_ppo", conf, flags=re.M)
    conf = re.sub(r"^title: PPO", "title: Toy PPO", conf, flags=re.M)
    (copy / "conf" / "algo" / "toy_ppo.yaml").write_text(re.sub(r"^loss: ppo", "loss: toy_ppo", conf, flags=re.M))


def _add_off_policy_learner(copy: Path) -> None:
    """``toy_td3``: TD3 under another name (its module reads ``algo.td3`` as TD3's does)."""
    module = (copy / "learners" / "td" / "td3.py").read_text()
    module = module.replace('SPEC = LearnerSpec(name="td3", title="TD3"', 'SPEC = LearnerSpec(name="toy_td3", title="Toy TD3"')
    module = re.sub(r"@dataclass\(frozen=True\)\nclass TD3Options:.*?\n\n\n", "", module, flags=re.S)
    module = module.replace("from learners.registry import LearnerSpec\n",
                            "from learners.registry import LearnerSpec\nfrom learners.td.td3 import TD3Options\n")
    (copy / "learners" / "td" / "toy_td3.py").write_text(module)
    conf = (copy / "conf" / "algo" / "td3.yaml").read_text()
    conf = re.sub(r"^name: td3", "name: toy_td3", conf, flags=re.M)
    conf = re.sub(r"^title: TD3", "title: Toy TD3", conf, flags=re.M)
    (copy / "conf" / "algo" / "toy_td3.yaml").write_text(re.sub(r"^loss: td3", "loss: toy_td3", conf, flags=re.M))


@pytest.mark.slow
def test_a_learner_of_each_family_is_its_own_files_only(tmp_path):
    copy = _copy(tmp_path)
    _add_monte_carlo_learner(copy)
    _add_off_policy_learner(copy)
    environment = {**os.environ, "PYTHONPATH": str(copy)}
    checks = subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-o", "addopts=",
                             "-m", "not slow", "tests/test_config.py", "tests/test_registry.py", "tests/test_layout.py",
                             "tests/test_fast_paths.py"],
                            cwd=copy, env=environment, capture_output=True, text=True, timeout=900)
    assert checks.returncode == 0, checks.stdout[-3000:]
    for name, extra in (("toy_ppo", ["er=recent"]), ("toy_td3", ["algo.td.warmup_episodes=1",
                                                                  "algo.td.updates_per_step=0.02"])):
        folder = tmp_path / name
        done = subprocess.run([sys.executable, "train.py", f"algo={name}", "episodes=3", "progress=false",
                               "logger=none", f"hydra.run.dir={folder}", *extra], cwd=copy, env=environment,
                              capture_output=True, text=True, timeout=600)
        assert done.returncode == 0, done.stderr
        assert "fused update steps are off" not in done.stderr, done.stderr
        summary = json.loads((folder / "summary.json").read_text())
        assert summary["status"] == "completed"
        if name == "toy_ppo":
            assert summary["paths"][0]["critic"] == "loss module"
            assert "ToyPPOLoss has no fused phases" in summary["paths"][0]["why"]
