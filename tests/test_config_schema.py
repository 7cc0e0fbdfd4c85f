"""Typed configs (issue 11, part 3): the schema holds every default with its comment, the YAML files
only presets that differ from it, and a bad value on the command line is one line naming the
field."""

import ast
import dataclasses
from pathlib import Path

import pytest
import yaml
from conftest import run_cli
from omegaconf import OmegaConf

from icco_torchrl import methods
from icco_torchrl.envs import ResourceCollectionEnv
from icco_torchrl.paths import CONF_DIR
from icco_torchrl.training import config as config_module
from icco_torchrl.training.config import Config, EnvParams, check_command_line, compose_config

PACKAGES = {
    "method": "method",
    "env": "env",
    "llm": "llm",
    "reward": "env.params",
    "experiment": "",
}


def _leaves(node, prefix=""):
    if isinstance(node, dict):
        for key, value in node.items():
            yield from _leaves(value, f"{prefix}{key}.")
    else:
        yield prefix[:-1], node


def _presets():
    for group, package in PACKAGES.items():
        for path in sorted((CONF_DIR / group).glob("*.yaml")):
            yield group, package, path


@pytest.mark.parametrize(
    "group, package, path", list(_presets()), ids=lambda v: getattr(v, "stem", None) or ""
)
def test_presets_hold_only_what_differs_from_their_parent(group, package, path):
    data = yaml.safe_load(path.read_text()) or {}
    defaults = data.pop("defaults", [])
    parent = next(
        (d for d in defaults if isinstance(d, str) and d != "_self_" and not d.startswith("base_")),
        None,
    )
    # what the preset starts from: its parent preset, else the schema's defaults
    base = compose_config([f"{group}={parent}"]) if parent else OmegaConf.structured(Config)
    for key, value in _leaves(data):
        full = f"{package}.{key}" if package else key
        assert OmegaConf.select(base, full) != value, (
            f"{path.name}: {full}={value!r} repeats the default"
        )


def test_every_schema_field_is_commented():
    source = Path(config_module.__file__).read_text()
    tree = ast.parse(source)
    lines = source.splitlines()
    checked = 0
    for node in tree.body:
        if (
            isinstance(node, ast.ClassDef)
            and node.name.endswith("Config")
            and node.name != "LiveConfig"
        ):
            for item in node.body:
                if isinstance(item, ast.AnnAssign) and not isinstance(
                    item.annotation, ast.Constant
                ):
                    # a trailing comment, or one on the line above the field
                    text = lines[item.lineno - 1] + lines[item.lineno - 2].strip()[:1]
                    nested = (
                        isinstance(item.value, ast.Call)
                        and getattr(item.value.func, "id", "") == "field"
                    )
                    assert "#" in text or nested, f"{node.name}.{item.target.id} has no comment"
                    checked += 1
    assert checked > 50
    # env.params are the env's keyword arguments, documented in its docstring
    doc = ResourceCollectionEnv.__doc__
    assert all(f.name in doc for f in dataclasses.fields(EnvParams))


def test_env_params_defaults_are_the_envs_own():
    params = compose_config(["reward=paper"]).env.params
    env = ResourceCollectionEnv(num_envs=1)
    assert params.n_agents == env.n_agents and params.vision_radius == env.vision_radius
    assert params.inst_reward_scale == env.inst_reward_scale == 1.3
    assert compose_config([]).env.params.inst_reward_scale == 0.3  # the calibrated default preset


def test_schema_is_registered_once_in_the_config_store():
    from hydra.core.config_store import ConfigStore

    repo = ConfigStore.instance().repo
    assert "base_config.yaml" in repo and "base_method.yaml" in repo["method"]
    config_module.register_configs()  # again: same entries, nothing added
    assert sorted(ConfigStore.instance().repo["method"]) == sorted(repo["method"])


@pytest.mark.parametrize(
    "override, field",
    [
        ("train.total_frames=lots", "train.total_frames"),
        ("+env.params.bogus=1", "env.params.bogus"),
        ("llm.timeout_s=abc", "llm.timeout_s"),
        ("env.params.n_agents=0", "env.params.n_agents"),
        ("train.updates_per_batch=0", "train.updates_per_batch"),
        ("method.posterior=average", "method.posterior"),
    ],
)
def test_command_line_check_names_the_field_in_one_line(override, field):
    message = check_command_line(["experiment=smoke", override])
    assert message is not None and f"'{field}'" in message and "\n" not in message
    assert check_command_line(["experiment=smoke", "-m", "seed=0,1", "method=qmix,icco"]) is None
    bad_sweep = check_command_line(["-m", "experiment=smoke", "train.lr=1e-3,0"])
    assert bad_sweep is not None and "train.lr" in bad_sweep


@pytest.mark.parametrize(
    "override, field",
    [
        ("train.total_frames=lots", "train.total_frames"),
        ("+env.params.bogus=1", "env.params.bogus"),
    ],
)
def test_a_bad_value_ends_the_command_in_one_line_with_exit_2(tmp_path, override, field):
    proc = run_cli("train", "experiment=smoke", override, f"hydra.run.dir={tmp_path}", check=False)
    assert proc.returncode == 2 and field in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1 and not (tmp_path / "train.csv").exists()


def test_a_pickled_config_validates_again():
    """Launchers (submitit, Ray) pickle the composed config into the job."""
    import pickle

    from icco_torchrl.training.config import validate

    cfg = compose_config(["method=qmix"])
    again = validate(pickle.loads(pickle.dumps(cfg)))
    assert OmegaConf.to_container(again) == OmegaConf.to_container(cfg)


def test_the_method_registry_is_the_presets_of_conf_method():
    names = methods.names()
    assert names == tuple(sorted(p.stem for p in (CONF_DIR / "method").glob("*.yaml")))
    for name in names:  # each preset names itself and has a label of its own
        assert compose_config([f"method={name}"]).method.name == name
    labels = [methods.label(name) for name in names]
    assert len(set(labels)) == len(labels) and all(labels)
    assert [methods.result_name(text) for text in labels] == list(names)
    assert methods.result_name("QMIX-TAP w/o TR") == "qmix_tap_wo_tr"
    assert methods.result_name("ICCO + teacher data") == "icco_teacher"  # removed, still on pages

    assert methods.result_name("not a method") is None
