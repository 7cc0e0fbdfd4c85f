"""Environments: the batched TorchRL task, its PettingZoo view and rendering."""

from icco_torchrl.envs.resource_collection import (
    EVENT_KEYS,
    EVENTS,
    N_ACTIONS,
    ObsLayout,
    ResourceCollectionEnv,
)

__all__ = [
    "EVENTS",
    "EVENT_KEYS",
    "N_ACTIONS",
    "ObsLayout",
    "ResourceCollectionEnv",
    "parallel_env",
]


def parallel_env(**params):
    """A PettingZoo ``ParallelEnv`` of one env, running the same dynamics code."""
    from icco_torchrl.envs.pettingzoo import ResourceCollectionParallelEnv

    return ResourceCollectionParallelEnv(**params)
