"""Environments: the batched TorchRL task, its waypoint sources (random walk, quadrant reference,
fixed waypoints), its PettingZoo view and rendering."""

from icco_torchrl.envs.layout import ObsLayout
from icco_torchrl.envs.resource_collection import (
    EVENT_KEYS,
    EVENTS,
    N_ACTIONS,
    ResourceCollectionEnv,
)
from icco_torchrl.envs.waypoints import (
    FixedSource,
    InstructionSource,
    QuadrantSource,
    RandomWalkSource,
)

__all__ = [
    "EVENTS",
    "EVENT_KEYS",
    "N_ACTIONS",
    "FixedSource",
    "InstructionSource",
    "ObsLayout",
    "QuadrantSource",
    "RandomWalkSource",
    "ResourceCollectionEnv",
    "parallel_env",
]


def parallel_env(**params):
    """A PettingZoo ``ParallelEnv`` of one env, running the same dynamics code."""
    from icco_torchrl.envs.pettingzoo import ResourceCollectionParallelEnv

    return ResourceCollectionParallelEnv(**params)
