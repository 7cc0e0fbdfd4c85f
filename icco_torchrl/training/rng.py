"""The random streams a training run draws from, saved in a checkpoint and restored at resume,
so a resumed run continues them exactly."""

from __future__ import annotations

import numpy as np
import torch


def rng_state(env) -> dict:
    """torch (and CUDA), numpy and the env's own generator (``env.base_env._rng``)."""
    state = {
        "torch": torch.get_rng_state(),
        "env": env.base_env._rng.get_state(),
        "numpy": np.random.get_state(),
    }
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict, env) -> None:
    """Put back the streams of :func:`rng_state`."""
    torch.set_rng_state(state["torch"])
    env.base_env._rng.set_state(state["env"])
    np.random.set_state(state["numpy"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])
