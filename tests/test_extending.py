"""docs/extending.md is true: a new method preset is one YAML file (the guide's own example,
composed, built and trained for one loss step), a new method option is three library files, a
preset and a converter row (the guide's own blocks, applied to a copy of the package, trained end
to end), the files and names its worked examples cite exist, and network sizes are declared once
(required keyword arguments, MethodConfig's values)."""

from __future__ import annotations

import importlib.util
import inspect
import os
import re
import shutil
import subprocess
import sys

import pytest
import torch
import yaml
from conftest import ROOT
from hydra import compose, initialize_config_dir

from icco_torchrl import methods
from icco_torchrl.modules import (
    Posterior,
    RecurrentQNet,
    make_agent,
    make_coordinator,
    make_posterior,
)
from icco_torchrl.modules.coordinator import Coordinator
from icco_torchrl.modules.mixer import MIXERS, TokenMixer, make_mixer
from icco_torchrl.paths import CONF_DIR
from icco_torchrl.training.build import build
from icco_torchrl.training.config import ConfigError, MethodConfig, compose_config, validate

GUIDE = ROOT / "docs" / "extending.md"


def converter_tables() -> dict:
    """The converter's tables (tools/convert_checkpoint.py, a script outside the package)."""
    spec = importlib.util.spec_from_file_location(
        "convert_checkpoint", ROOT / "tools" / "convert_checkpoint.py"
    )
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.METHOD_FIELDS_ADDED


def guide() -> str:
    return GUIDE.read_text()


def example_preset() -> tuple[str, str]:
    """The guide's preset: (its file's path, as the block's first line names it; its text)."""
    block = re.search(r"```yaml\n# (conf/method/\S+\.yaml)\n(.*?)```", guide(), re.S)
    assert block, "docs/extending.md shows a preset as a yaml block headed by its path"
    return block.group(1), block.group(2)


@pytest.fixture
def conf_with_example(tmp_path, monkeypatch):
    """A copy of conf/ with the guide's preset added, and nothing else changed; the method
    registry reads it."""
    conf = tmp_path / "conf"
    shutil.copytree(CONF_DIR, conf)
    path, text = example_preset()
    (tmp_path / path).write_text(text)
    monkeypatch.setattr(methods, "CONF_DIR", conf)
    methods.labels.cache_clear()
    yield conf, yaml.safe_load(text)
    methods.labels.cache_clear()


def test_a_new_method_preset_is_one_yaml_file(conf_with_example):
    conf, preset = conf_with_example
    name = preset["name"]
    assert not (CONF_DIR / "method" / f"{name}.yaml").exists()  # the example is not shipped
    with initialize_config_dir(config_dir=str(conf), version_base=None):
        cfg = validate(compose("config", [f"method={name}", "experiment=smoke", "device=cpu"]))
    parent = compose_config(["method=icco", "experiment=smoke", "device=cpu"])
    # the preset is its parent plus exactly the lines it writes, each a change
    changed = {k for k in parent.method if cfg.method[k] != parent.method[k]}
    assert changed == set(preset) - {"defaults"} and preset["period"] == cfg.method.period
    # the registry, the labels and the results keys know it with no other edit
    assert name in methods.names() and methods.label(name) == preset["label"]
    assert methods.result_name(preset["label"]) == name
    # it builds and trains: one loss step on items cut from a rollout
    torch.manual_seed(0)
    run = build(cfg, num_envs=2)
    assert run.coordinator.module.period == preset["period"]
    with torch.no_grad():
        rollout = run.env.rollout(2 * cfg.train.sequence_length, run.policy)
    out = run.loss(run.cutter(rollout.select(*run.loss.in_keys, strict=False)))
    total = sum(v for k, v in out.items() if k.startswith("loss_"))
    total.backward()
    assert torch.isfinite(total)


def test_the_guides_note_on_the_period_holds():
    """A period the sequence length is not a multiple of is refused naming that field."""
    assert "`period: 5` would be refused" in guide()
    with pytest.raises(ConfigError, match="'train.sequence_length'"):
        compose_config(["method.period=5"])
    assert compose_config(["method.period=5", "train.sequence_length=20"]).method.period == 5


def test_the_files_the_guide_names_exist():
    example, _ = example_preset()
    paths = set(re.findall(r"`((?:icco_torchrl|conf|tests|docs|assets|tools)/[\w/.-]+)`", guide()))
    assert len(paths) > 10
    missing = [p for p in sorted(paths - {example}) if not (ROOT / p).exists()]
    assert not missing, missing


def test_the_worked_network_is_as_the_guide_says():
    text = guide()
    build_src = (ROOT / "icco_torchrl" / "training" / "build.py").read_text()
    fields = MethodConfig.__dataclass_fields__
    added = converter_tables()  # the value older checkpoints get when they are converted
    # the network: its choice list declared once, read in build.py, the old value for checkpoints
    assert MIXERS == ("qmix", "attention") and fields["mixer"].metadata["choices"] is MIXERS
    assert "kind=m.mixer" in build_src and added["mixer"] == "qmix"
    assert "TokenMixer(layout, *, embed_dim, hidden)" in text
    assert "hidden=m.hidden" in build_src and make_mixer.__module__ == TokenMixer.__module__


# A block of the option's section: ``# PATH, after: LINE``, then the lines that go after LINE.
EDIT = re.compile(r"```python\n# ((?:icco_torchrl|tools)/[\w/.]+), after: (.+?)\n(.*?)```", re.S)


def option_section() -> str:
    return guide().split("## Add a method option", 1)[1].split("\n## ", 1)[0]


def apply_edit(root, path: str, after: str, lines: str) -> None:
    """Put ``lines`` after the one line of ``root/path`` that reads ``after``."""
    file = root / path
    text = file.read_text().splitlines(keepends=True)
    at = [i for i, line in enumerate(text) if line.strip() == after.strip()]
    assert len(at) == 1, f"{path}: {len(at)} lines read {after!r}, where the guide needs one"
    text[at[0] + 1 : at[0] + 1] = [lines]
    file.write_text("".join(text))


def test_a_new_method_option_is_three_library_files_a_preset_and_a_converter_row(tmp_path):
    """The guide's worked option, applied block by block to a copy of the package (the field, where
    it is read, the module that implements it: three library files), with its preset and its row
    in the converter: a smoke training of the preset runs end to end, its checkpoint records the
    option and holds the option's weights, and the converter converts the demo policy (written
    before the option existed) at the value the row gives."""
    section = option_section()
    edits = EDIT.findall(section)
    library = {path for path, _, _ in edits if path.startswith("icco_torchrl/")}
    assert len(library) <= 3, library
    assert {path for path, _, _ in edits} - library == {"tools/convert_checkpoint.py"}
    listed = section.split("\nFiles: ", 1)[1].split("\n\n", 1)[0]
    assert set(re.findall(r"`(icco_torchrl/[\w/.]+)`", listed)) == library
    assert "three in the" in listed and "No checkpoint format changes" in listed
    preset_path, preset_text = re.search(
        r"```yaml\n# (conf/method/\S+\.yaml)\n(.*?)```", section, re.S
    ).groups()
    preset = yaml.safe_load(preset_text)
    [option] = set(preset) - {"defaults", "name", "label"}
    assert option not in MethodConfig.__dataclass_fields__  # the example is not shipped

    copy = tmp_path / "copy"
    for folder in ("icco_torchrl", "conf", "tools", "assets"):
        shutil.copytree(ROOT / folder, copy / folder, ignore=shutil.ignore_patterns("__pycache__"))
    for path, after, lines in edits:
        apply_edit(copy, path, after, lines)
    (copy / preset_path).write_text(preset_text)

    # python in the copy: its package, not the checkout's
    env = {**os.environ, "PYTHONPATH": str(copy), "OMP_NUM_THREADS": "1", "WANDB_MODE": "disabled"}
    python = dict(cwd=copy, env=env, capture_output=True, text=True, timeout=900)
    run = tmp_path / "run"
    smoke = [f"method={preset['name']}", "experiment=smoke", "logger.progress=false"]
    train = subprocess.run(
        [sys.executable, "-m", "icco_torchrl", "train", *smoke, f"hydra.run.dir={run}"], **python
    )
    assert train.returncode == 0, train.stderr[-3000:]
    assert "done: 2,048 env steps" in train.stdout, train.stdout[-2000:]
    ckpt = torch.load(run / "checkpoint.pt", weights_only=True)
    assert ckpt["cfg"]["method"][option] == preset[option]
    parent = build(compose_config(["method=icco", "device=cpu"]), num_envs=2).loss.state_dict()
    assert set(ckpt["loss"]) > set(parent), "the option's module adds no weights"

    demo = ["tools/convert_checkpoint.py", "assets/demo_icco.pt", str(tmp_path / "demo.pt")]
    convert = subprocess.run([sys.executable, *demo], **python)
    assert convert.returncode == 0, convert.stderr
    assert f"method.{option}=" in convert.stdout, convert.stdout


REQUIRED = inspect.Parameter.empty


@pytest.mark.parametrize(
    "cls, sizes",
    [
        (RecurrentQNet, ("n_actions", "hidden")),
        (Coordinator, ("z_dim", "hidden", "period", "init_logvar")),
        (Posterior, ("n_actions", "z_dim", "hidden", "combine")),
        (TokenMixer, ("embed_dim", "hidden")),
    ],
)
def test_network_sizes_are_required_keyword_arguments(cls, sizes):
    params = inspect.signature(cls).parameters
    for size in sizes:
        assert params[size].kind is params[size].KEYWORD_ONLY, size
        assert params[size].default is REQUIRED, f"{cls.__name__}({size}=...) has a default"
    with pytest.raises(TypeError, match=sizes[-1]):
        cls(None, **{s: 4 for s in sizes[:-1]})


@pytest.mark.parametrize("factory", [make_agent, make_coordinator, make_posterior])
def test_factories_forward_to_their_class_and_declare_no_size(factory):
    params = inspect.signature(factory).parameters
    assert not {"hidden", "z_dim", "period", "n_actions", "init_logvar", "combine"} & set(params)
    assert any(p.kind is p.VAR_KEYWORD for p in params.values())


def test_a_factory_builds_what_its_class_builds():
    torch.manual_seed(0)
    agent = make_agent(obs_dim=8, n_actions=5, hidden=16, z_dim=4, full_state=True, state_dim=6)
    torch.manual_seed(0)
    net = RecurrentQNet(obs_dim=8, n_actions=5, hidden=16, z_dim=4, full_state=True, state_dim=6)
    assert all(torch.equal(a, b) for a, b in zip(agent.module.parameters(), net.parameters()))
    names = {k if isinstance(k, str) else k[-1] for k in agent.in_keys}
    assert {"z", "state"} <= names  # the keys follow the class's z_dim and full_state
    plain = make_agent(obs_dim=8, n_actions=5, hidden=16)
    assert not {"z", "state"} & {k if isinstance(k, str) else k[-1] for k in plain.in_keys}
