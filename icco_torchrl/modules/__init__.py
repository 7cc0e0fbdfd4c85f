"""ICCO's networks as TensorDictModules: local agents, coordinator, mixer, posterior."""

from icco_torchrl.modules.agent import RecurrentQNet, make_agent
from icco_torchrl.modules.coordinator import Coordinator, gaussian_entropy, make_coordinator
from icco_torchrl.modules.encoders import EntityAttentionEncoder, MLPEncoder, make_encoder
from icco_torchrl.modules.mixer import make_mixer
from icco_torchrl.modules.posterior import (
    Posterior,
    combine_log_prob,
    diag_normal_log_prob,
    make_posterior,
)

__all__ = [
    "Coordinator",
    "EntityAttentionEncoder",
    "MLPEncoder",
    "Posterior",
    "RecurrentQNet",
    "combine_log_prob",
    "diag_normal_log_prob",
    "gaussian_entropy",
    "make_agent",
    "make_coordinator",
    "make_encoder",
    "make_mixer",
    "make_posterior",
]
