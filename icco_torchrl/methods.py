"""The methods: the presets in ``conf/method/`` are the one list.

A method is an option of the ``method`` config group, ``conf/method/<name>.yaml``: the file
name is its name (``method=<name>``, run folders, ``results.json`` keys) and the preset's
``method.label`` is what tables and figures print. This module reads both from there (each
preset composed once per process), so no other list of methods is kept anywhere.

    >>> from icco_torchrl import methods
    >>> methods.names()
    ('icco', 'icco_wo_ce', 'qmix', 'qmix_full', 'qmix_full_flat')
    >>> methods.label("qmix_full"), methods.result_name("QMIX (FULL)")
    ('QMIX (FULL)', 'qmix_full')
"""

from __future__ import annotations

from functools import cache

from icco_torchrl.paths import CONF_DIR

# What a table label may carry after the method's label, with its results.json spelling: the
# task-aligned prompt of ``icco instruct llm.prompt=tap`` ("QMIX-TAP"), agents trained on the
# instruction reward alone ("QMIX-TAP w/o TR", ``experiment=inst_only``) and agents that learned
# from a scripted team's data ("ICCO + teacher data": an option measured and removed, named on the
# pages of its screens in experiments/best_team), in that order.
TAP = "-TAP"
WITHOUT_TASK_REWARD = " w/o TR"
TEACHER = " + teacher data"
SUFFIX_NAMES = ((TAP, "_tap"), (WITHOUT_TASK_REWARD, "_wo_tr"), (TEACHER, "_teacher"))


def names() -> tuple[str, ...]:
    """The methods, one per preset file in ``conf/method/``, in table order (by name)."""
    return tuple(sorted(path.stem for path in (CONF_DIR / "method").glob("*.yaml")))


@cache
def labels() -> dict[str, str]:
    """``{name: label}`` of every method, read from its preset composed alone (once per process)."""
    from contextlib import nullcontext

    from hydra import compose, initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    from icco_torchrl.training.config import register_configs

    register_configs()
    # Inside a running ``icco`` command Hydra is already set up on conf/: compose there.
    inside_app = GlobalHydra.instance().is_initialized()
    context = (
        nullcontext() if inside_app else initialize_config_dir(str(CONF_DIR), version_base=None)
    )
    with context:
        return {
            name: compose(config_name=f"method/{name}").method.label or name for name in names()
        }


def label(name: str) -> str:
    """The label of method ``name`` as tables print it (an unknown name is its own label)."""
    return labels().get(name, name)


def result_name(table_label: str) -> str | None:
    """The ``results.json`` key of a method's table label (``"QMIX (FULL)"`` -> ``qmix_full``,
    ``"QMIX-TAP w/o TR"`` -> ``qmix_tap_wo_tr``); None when it names no method."""
    tail = ""
    for suffix, key in reversed(SUFFIX_NAMES):
        if table_label.endswith(suffix):
            table_label, tail = table_label[: -len(suffix)], key + tail
    name = {text: name for name, text in labels().items()}.get(table_label)
    return None if name is None else name + tail
