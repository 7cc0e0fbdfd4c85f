"""The experiment scripts' run lists compose into valid configs (a typo there would only show after hours)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from icco_torchrl.training.build import compose_config

ROOT = Path(__file__).resolve().parents[1]


def _load(path: Path):
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_every_recipe_lever_composes_and_trains_its_method():
    levers = _load(ROOT / "experiments" / "recipe" / "run.py").LEVERS
    assert len(levers) > 20
    for name, (_, _, method, overrides) in levers.items():
        cfg = compose_config([f"method={method}", *overrides])
        assert cfg.method.name == method, name
    shaped = compose_config(["method=qmix", *levers["collect35_qmix"][3]])
    assert shaped.train.env_params.collect_reward == 3.5 and shaped.env.params.collect_reward == 1.0
