"""ICCO's networks as TensorDictModules: local agents, coordinator, mixer, posterior.

Each parameter is declared once. A network's sizes (``hidden``, ``z_dim``, ``period``,
``n_actions``) and a method's choices (the coordinator's ``init_logvar``, the posterior's
``combine``, the mixer's ``kind``) have no default here: they are required keyword arguments of its
class (or factory), and the project's values live in one place,
:class:`~icco_torchrl.training.config.MethodConfig`, which
:func:`~icco_torchrl.training.build.build` passes field by field. Each factory (``make_agent``,
``make_coordinator``, ``make_posterior``) adds only the TensorDict keys and forwards every other
keyword argument to its class, so a network's arguments are listed (and documented) once, on the
class. What keeps a default is a switch's neutral setting, a property of the network rather than
of a method: off (``full_state``, ``waypoint_features``, ``threshold=0``, the agent's
``z_dim=0``), inferred from the layout (``encoder``), or the reading that needs no layout
(``state_encoder="flat"``, the posterior's ``inputs="flat"``); ``make_mixer`` holds QMIX's
mixing width (``embed_dim=32``), which no config sets.

    >>> from icco_torchrl.modules import make_agent, make_coordinator
    >>> agent = make_agent(obs_dim=8, n_actions=5, hidden=16, z_dim=4)
    >>> coordinator = make_coordinator(
    ...     n_agents=3, state_dim=24, z_dim=4, hidden=16, period=4, init_logvar=0.0
    ... )
    >>> agent.module.hidden, coordinator.module.period
    (16, 4)
"""

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
