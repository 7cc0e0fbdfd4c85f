"""The observation layout contract between the resource-collection env and the networks that read
it.

The env writes per-robot observations and a global state in this layout; the entity-attention
and relative-state encoders of :mod:`icco_torchrl.modules` and the loss read it. It is a plain
record of sizes (no env code), with the columns of a state token and the rule that says which
robots are present, so networks can be built for any env that describes itself this way, and a
flat observation needs no layout at all (see ``make_agent(obs_dim=...)``).

A robot's observation is its own features (``own_dim``), then ``n_entities`` entity tokens of
``entity_dim`` features each, the others it sees (other robots, resources, invaders, home; a token
out of its vision radius is all zeros)::

    position  [dx, dy] relative to the robot   ENTITY_POSITION  (0:2)
    velocity  [dvx, dvy] relative to the robot ENTITY_VELOCITY  (2:4)
    type      one-hot (robot, resource, invader, home)
                                               ENTITY_TYPE      (4:8)
    flag      carry (robots), active (invaders)
                                               ENTITY_FLAG      (8)
    visible   1 within the vision radius       ENTITY_VISIBLE   (9)

The global state is ``state_tokens`` tokens (robots, then resources, then invaders) of
``state_token_dim`` features each::

    position  [x, y]                 POSITION   (0:2)
    velocity  [vx, vy]               VELOCITY   (2:4)
    type      one-hot (robot, resource, invader)
                                     TYPE       (4:7): ROBOT (4), RESOURCE (5), INVADER (6)
    flag      carry (robots), active (invaders)
                                     FLAG       (7)
    defended  (robots)               DEFENDED   (8)
    waypoints absolute, 2K (robots)  :attr:`ObsLayout.waypoints` (9:9+2K)

A robot absent from the team has an all-zero token, its type included: :meth:`ObsLayout.robot_mask`
reads who is present off the state (robot i's type flag ``ROBOT`` is set), and
:meth:`ObsLayout.typed` which tokens hold an entity at all.

Examples:
    >>> import torch
    >>> layout = ObsLayout.for_env(n_agents=2, n_resources=1, n_invaders=1, n_waypoints=1)
    >>> layout.state_tokens, layout.state_token_dim, layout.waypoints
    (4, 11, slice(9, 11, None))
    >>> state = torch.zeros(layout.state_tokens, layout.state_token_dim)
    >>> state[0, ObsLayout.ROBOT] = 1.0  # robot 0 present, robot 1 absent (an all-zero token)
    >>> layout.robot_mask(state.flatten())
    tensor([ True, False])
    >>> layout.with_agents(3) == ObsLayout.for_env(3, 1, 1, 1)
    True
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

import torch


@dataclass(frozen=True)
class ObsLayout:
    """Where things sit in the flat per-robot observation and in the global state.

    The fields are sizes (what a checkpoint records); the state-token columns are class constants
    (the same for every env of this kind) and :attr:`waypoints`, which depends on ``n_waypoints``.
    """

    n_agents: int
    n_waypoints: int
    own_dim: int  # [x, y, vx, vy, carry] + relative waypoints
    n_entities: int  # other robots + resources + invaders + home
    entity_dim: int
    state_tokens: int  # robots + resources + invaders
    state_token_dim: int

    # Columns of a state token (see the module doc).
    POSITION: ClassVar[slice] = slice(0, 2)
    VELOCITY: ClassVar[slice] = slice(2, 4)
    TYPE: ClassVar[slice] = slice(4, 7)  # one-hot: robot, resource, invader
    ROBOT: ClassVar[int] = 4  # the robot type flag: set for a present robot, 0 for an absent one
    RESOURCE: ClassVar[int] = 5
    INVADER: ClassVar[int] = 6
    FLAG: ClassVar[int] = 7  # a robot's carry flag, an invader's active flag
    DEFENDED: ClassVar[int] = 8
    WAYPOINTS_START: ClassVar[int] = 9  # then 2K absolute waypoint coordinates (robots)
    # Columns of a robot's own observation: [x, y, vx, vy, carry], then its relative waypoints.
    OWN_WAYPOINTS_START: ClassVar[int] = 5
    # Columns of an entity token of a robot's observation (see the module doc).
    ENTITY_POSITION: ClassVar[slice] = slice(0, 2)  # relative to the observing robot
    ENTITY_VELOCITY: ClassVar[slice] = slice(2, 4)  # relative to the observing robot
    ENTITY_TYPE: ClassVar[slice] = slice(4, 8)  # one-hot: robot, resource, invader, home
    ENTITY_FLAG: ClassVar[int] = 8  # a robot's carry flag, an invader's active flag
    ENTITY_VISIBLE: ClassVar[int] = 9  # 1 within the vision radius; 0: an all-zero token
    ENTITY_DIM: ClassVar[int] = 10

    @classmethod
    def for_env(
        cls, n_agents: int, n_resources: int, n_invaders: int, n_waypoints: int
    ) -> ObsLayout:
        """The layout of a resource-collection env with these counts (the env's rule: every
        other robot, resource, invader and home is an entity of a robot's view; every robot,
        resource and invader a state token)."""
        K2 = 2 * n_waypoints
        return cls(
            n_agents=n_agents,
            n_waypoints=n_waypoints,
            own_dim=cls.OWN_WAYPOINTS_START + K2,
            n_entities=(n_agents - 1) + n_resources + n_invaders + 1,
            entity_dim=cls.ENTITY_DIM,
            state_tokens=n_agents + n_resources + n_invaders,
            state_token_dim=cls.WAYPOINTS_START + K2,
        )

    def with_agents(self, n_agents: int) -> ObsLayout:
        """The layout of the same env holding ``n_agents`` robots: each robot more is one more
        entity of every robot's view and one more state token."""
        extra = n_agents - self.n_agents
        return dataclasses.replace(
            self,
            n_agents=n_agents,
            n_entities=self.n_entities + extra,
            state_tokens=self.state_tokens + extra,
        )

    @classmethod
    def from_dict(cls, values: dict) -> ObsLayout:
        """The layout a checkpoint saved (its fields; other keys are ignored)."""
        return cls(**{f.name: values[f.name] for f in dataclasses.fields(cls)})

    @property
    def obs_dim(self) -> int:
        return self.own_dim + self.n_entities * self.entity_dim

    @property
    def state_dim(self) -> int:
        return self.state_tokens * self.state_token_dim

    @property
    def waypoints(self) -> slice:
        """The state-token columns of a robot's absolute waypoints (``2 * n_waypoints``)."""
        return slice(self.WAYPOINTS_START, self.WAYPOINTS_START + 2 * self.n_waypoints)

    @property
    def visible_column(self) -> int:
        """The column of an entity token's visibility flag, which the networks' attention masks
        by: the token's last (:attr:`ENTITY_VISIBLE` in this env's tokens of :attr:`ENTITY_DIM`
        features; a layout of other entity tokens keeps its flag last too)."""
        return self.entity_dim - 1

    @property
    def own_waypoints(self) -> slice:
        """The columns of a robot's own waypoints (relative to it) in its observation."""
        return slice(self.OWN_WAYPOINTS_START, self.own_dim)

    def tokens(self, state: torch.Tensor) -> torch.Tensor:
        """``[..., state_dim]`` -> ``[..., state_tokens, state_token_dim]`` (a view)."""
        return state.unflatten(-1, (self.state_tokens, self.state_token_dim))

    def robot_mask(self, state: torch.Tensor) -> torch.Tensor:
        """``[..., state_dim]`` -> ``[..., n_agents]`` bool: robot i is present (its token's robot
        type flag is set; an absent robot's token is all zeros)."""
        return self.tokens(state)[..., : self.n_agents, self.ROBOT] > 0

    def typed(self, state: torch.Tensor) -> torch.Tensor:
        """``[..., state_dim]`` -> ``[..., state_tokens]`` bool: the token has a type (an entity;
        an absent robot's token has none)."""
        return self.tokens(state)[..., self.TYPE].ne(0).any(-1)
