"""Imports point down the layers: no package imports one above it, so there is no circle."""

from __future__ import annotations

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "icco_torchrl"
# Bottom to top; a module may import its own layer's and lower layers' modules only.
LAYERS = [
    {"paths"},
    {"envs"},
    {"modules"},
    {"objectives"},
    {"training"},
    {"evaluation", "instructions", "methods"},
    {"trainer", "live"},
    {"commands"},
    {"cli", "__main__", "__init__"},
]


def _layer(name: str) -> int:
    return next(i for i, layer in enumerate(LAYERS) if name in layer)


def test_every_import_points_down_the_layers():
    upward = []
    for path in PACKAGE.rglob("*.py"):
        source = path.relative_to(PACKAGE).with_suffix("").parts[0]
        for node in ast.walk(ast.parse(path.read_text())):  # function-level imports too
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("icco_torchrl."):
                target = node.module.split(".")[1]
                if target != source and _layer(target) > _layer(source):
                    upward.append(
                        f"{path.relative_to(PACKAGE)}:{node.lineno} imports {node.module}"
                    )
    assert not upward, "imports pointing up the layers:\n" + "\n".join(upward)


def test_every_package_has_a_layer():
    names = {p.stem if p.is_file() else p.name for p in PACKAGE.iterdir()}
    names = {n for n in names if not n.startswith(("_", ".")) or n in ("__main__", "__init__")}
    names -= {"conf", "static"}
    assert names <= set().union(*LAYERS), names - set().union(*LAYERS)
