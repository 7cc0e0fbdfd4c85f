"""Where the project's files are: the Hydra config tree.

A leaf module (it imports nothing of the package), so the config schema, the assembler, the CLI
and the method registry can all read it without importing each other.
"""

from __future__ import annotations

from pathlib import Path


def _conf_dir() -> Path:
    """The Hydra config tree: ``conf/`` of a source checkout, else the copy a wheel installs as
    ``icco_torchrl/conf`` (pyproject maps the top-level folder into the package)."""
    checkout = Path(__file__).resolve().parents[1] / "conf"
    if (checkout / "config.yaml").is_file():
        return checkout
    return Path(__file__).resolve().parent / "conf"


CONF_DIR = _conf_dir()
