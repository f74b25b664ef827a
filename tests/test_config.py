"""Every config combination composes and validates; bad values fail in one clear sentence."""

import itertools
from pathlib import Path

import pytest
import yaml
from hydra.errors import MissingConfigException


from engine.config import ConfigError, RunConfig

CONF = Path(__file__).resolve().parent.parent / "conf"


def _paper_algos() -> set[str]:
    """The algorithms of the paper's Table 1 (its committed values: analysis/data/paper_table1.csv); every
    other algorithm, of either family, is beyond the paper (a new learner needs no change here)."""
    from analysis.report import read_paper_table

    return {algo for _, algo in read_paper_table()}


# the algorithms and replay modes beyond the paper's (tests/test_offpolicy.py)
BEYOND_ALGOS = tuple(sorted(p.stem for p in (CONF / "algo").glob("*.yaml") if p.stem not in _paper_algos()))
BEYOND_ERS = ("prioritised",)
ALGOS = sorted(p.stem for p in (CONF / "algo").glob("*.yaml") if p.stem not in BEYOND_ALGOS)
ERS = sorted(p.stem for p in (CONF / "er").glob("*.yaml") if p.stem not in BEYOND_ERS)


def _beyond(cell: str) -> bool:
    er, algo = cell.split("-")
    return algo.startswith(BEYOND_ALGOS) or er in BEYOND_ERS


CELLS = sorted(p.stem for p in (CONF / "cell").glob("*.yaml") if not _beyond(p.stem))
BEYOND_CELLS = sorted(p.stem for p in (CONF / "cell").glob("*.yaml") if _beyond(p.stem))


def load(*overrides: str) -> RunConfig:
    return RunConfig.compose(*overrides)


def test_the_groups_hold_the_papers_columns_and_rows():
    assert ALGOS == ["ppo", "ppo_log", "spg", "spg_multi", "spg_p", "spg_p_multi"]
    assert ERS == ["hybrid", "memory", "recent"]
    assert len(CELLS) == 15
    assert BEYOND_CELLS == ["memory-crossq", "memory-naf", "memory-sac", "memory-sac_sb3", "memory-td3", "memory-tqc", "memory-trust_pcl", "prioritised-sac", "prioritised-spg_p_multi",
                            "prioritised-td3"]


@pytest.mark.parametrize("cell", BEYOND_CELLS)
def test_the_beyond_the_paper_cells_compose(cell):
    cfg = load(f"+cell={cell}")
    assert cell == f"{cfg.er.name}-{cfg.algo.name}" and (cfg.algo.bootstrapped or cfg.er.priority is not None)


@pytest.mark.parametrize("algo, er", list(itertools.product(ALGOS, ERS)))
def test_every_combination_composes(algo, er):
    cfg = load(f"algo={algo}", f"er={er}")
    assert (cfg.algo.name, cfg.er.name) == (algo, er)


@pytest.mark.parametrize("cell", CELLS)
def test_every_table_cell_composes(cell):
    cfg = load(f"+cell={cell}")
    assert cell == f"{cfg.er.name}-{cfg.algo.name}"


def test_paper_hyperparameters():
    ppo = load("algo=ppo").algo
    assert (ppo.critic_lr, ppo.actor_lr, ppo.value_epochs, ppo.policy_epochs, ppo.minibatch_size) == (
        0.0005, 0.001, 50, 10, 200)
    assert (ppo.entropy_coeff, ppo.ppo.clip_epsilon, ppo.ppo.ratio_space) == (0.02, 0.2, "linear")
    assert load("algo=ppo_log").algo.ppo.ratio_space == "log"
    spg = load("algo=spg").algo
    assert (spg.actor_lr, spg.policy_epochs, spg.entropy_coeff, spg.spg.prioritised) == (0.01, 1, 0.0, False)
    assert (spg.spg.num_samples, spg.spg.temperature, spg.spg.temperature_decay) == (5, 1.0, 0.01)
    multi = load("algo=spg_p_multi").algo
    assert (multi.actor_lr, multi.policy_epochs, multi.spg.prioritised, multi.critic_lr) == (0.001, 10, True, 0.0005)
    hybrid = load("er=hybrid").er
    assert (hybrid.train_on_memory, hybrid.train_on_recent, hybrid.minibatch_fraction) == (True, True, 0.5)
    top = load()
    assert (top.episodes, top.gamma, top.final_window, top.er.buffer_size) == (201, 0.9, 20, 10000)
    assert top.network.actor_hidden == (100,) and top.network.critic_hidden == (100, 100)


@pytest.mark.parametrize("override, message", [
    ("algo.actor_lr=-0.1", "actor_lr must be > 0"),
    ("algo.critic_lr=0", "critic_lr must be > 0"),
    ("episodes=0", "episodes must be >= 1"),
    ("algo.minibatch_size=500", "larger than the 200 transitions of one episode"),
    ("algo.ppo.ratio_space=sqrt", "ratio_space must be one of linear, log"),
    ("env.track=circle", "env.track must be one of fixed, random"),
    ("env.collector=magic", "env.collector must be one of direct, torchrl"),
    ("algo.value_epochs=2.5", "value_epochs must be an integer"),
    ("+algo.learning_rate=0.1", "unknown key(s) ['learning_rate']; valid keys are"),
    ("+env.options.max_speeed=3", "unknown keyword(s) ['max_speeed']"),
    ("seed=-1", "seed must be in [0, 2**32)"),
    ("gamma=1.5", "gamma must be in [0, 1]"),
    ("logger=wandb", "logger must be one of csv, tensorboard, none"),
])
def test_bad_values_fail_in_one_sentence(override, message):
    overrides = ["algo=ppo"] if "ratio_space" in override else []
    with pytest.raises(ConfigError) as err:
        load(*overrides, override, "er=recent")
    assert message in str(err.value)
    assert "\n" not in str(err.value)


def test_memory_minibatch_cannot_exceed_the_memory():
    with pytest.raises(ConfigError, match="larger than the replay memory"):
        load("er=memory", "er.buffer_size=100")


def test_options_of_the_other_loss_are_rejected():
    with pytest.raises(ConfigError, match="does not apply to loss ppo"):
        load("algo=ppo", "+algo.spg.prioritised=true")


def test_unknown_algorithm_names_the_choices():
    with pytest.raises(MissingConfigException) as err:
        load("algo=a2c")
    assert "spg_p_multi" in str(err.value)


def test_tensorboard_logger_without_the_package_is_a_config_error(monkeypatch):
    import importlib.util

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "tensorboard" else real(name, *a))
    with pytest.raises(ConfigError, match=r"logger=tensorboard needs the tensorboard package: pip install"):
        load("logger=tensorboard")


@pytest.mark.parametrize("override, message", [
    ("seeds=[3,4,3]", "seeds lists [3] more than once"),
    ("seeds=[]", "non-empty list of track seeds"),
    ("seeds=[1,-2]", "seeds must be a list of non-negative integers"),
    ("seeds=[4294967296]", "seeds must be in [0, 2**32)"),
    ("network.critic_hidden=[]", "non-empty list of positive layer sizes"),
])
def test_bad_population_seeds_are_config_errors(override, message):
    with pytest.raises(ConfigError) as err:
        load(override)
    assert message in str(err.value)


def test_a_population_of_seeds():
    cfg = load("seeds=[5,3]")
    assert cfg.members == (5, 3) and load("seed=7").members == (7,)


def test_beyond_paper_wide_is_beyond_paper_on_the_wide_grids_tracks():
    """The 25-track beyond-the-paper preset composes to exactly beyond_paper with the wide grid's
    seeds, so in beyond_paper's folder it recognises (and skips) the runs beyond_paper made."""
    wide = load("+experiment=wide_grid").seeds
    assert len(wide) == 25 and wide[:5] == load("+experiment=beyond_paper").seeds
    for cell in ("memory-sac", "recent-ppo"):
        assert load("+experiment=beyond_paper_wide", f"+cell={cell}") == load(
            "+experiment=beyond_paper", f"+cell={cell}", f"seeds=[{','.join(map(str, wide))}]")


@pytest.mark.parametrize("experiment, key, expected", [
    ("paper_grid", "+cell", CELLS), ("wide_grid", "+cell", CELLS), ("full_grid", "algo", ALGOS),
    ("full_grid", "er", ERS)])
def test_the_paper_sweeps_expand_to_the_papers_cells_only(experiment, key, expected):
    """The paper's grids choose their cells by name or by glob over conf/: a new beyond-the-paper config
    must not slip into Table 1 (the values expanded here as Hydra's sweeper expands them)."""
    from hydra.core.override_parser.overrides_parser import OverridesParser

    params = yaml.safe_load((CONF / "experiment" / f"{experiment}.yaml").read_text())["hydra"]["sweeper"]["params"]
    override = OverridesParser.create().parse_override(f"{key}={params[key]}")
    group = {"+cell": "cell", "algo": "algo", "er": "er"}[key]
    value = override.value()
    values = (value.filter([p.stem for p in (CONF / group).glob("*.yaml")]) if hasattr(value, "filter")  # a glob
              else list(override.sweep_string_iterator()))
    assert sorted(values) == expected


def test_every_key_of_every_algorithm_is_commented_on_its_line():
    """A reader of conf/algo/*.yaml finds what each key does where it is set (its name aside)."""
    import re

    bare = [f"{path.name}:{i}: {line.strip()}" for path in sorted((CONF / "algo").glob("*.yaml"))
            for i, line in enumerate(path.read_text().splitlines(), 1)
            if re.match(r"\s*\w+:\s*\S", line) and "#" not in line and not line.startswith("name:")]
    assert not bare, bare


def test_the_future_work_comparison_runs_the_papers_best_cell_beside_the_methods_it_names_on_25_tracks():
    wide = load("+experiment=wide_grid").seeds
    params = yaml.safe_load((CONF / "experiment" / "future_work.yaml").read_text())["hydra"]["sweeper"]["params"]
    cells = params["+cell"].split(",")
    assert cells == ["memory-spg_p_multi", "memory-td3", "memory-naf", "memory-trust_pcl"]
    for cell in cells:
        cfg = load("+experiment=future_work", f"+cell={cell}")
        assert cfg.seeds == wide and cfg.episodes == 201 and cfg.er.name == "memory"
