"""The resource-collection env's parameters, declared once: :class:`ResourceCollectionParams`.

Each parameter is one field of the table, with its type, its default, its constraint and its doc.
What else names the parameters is generated from it:

- :class:`~icco_torchrl.envs.ResourceCollectionEnv` takes them as keyword arguments and builds
  the table from them (:attr:`ResourceCollectionEnv.params`); its signature (``inspect``,
  ``help``), the Keyword Args of its docstring and its read-only attributes (``env.dt``...) come
  from the fields;
- the checks run when the table is built (:meth:`ResourceCollectionParams.__post_init__`), each
  error one line that starts with the field's name;
- the constants a step reads (:meth:`ResourceCollectionParams.kernel_params`), computed once;
- the config schema ``env.params`` (:mod:`icco_torchrl.training.config`).

To add a parameter: one :func:`param` field here (the env reads ``self.params.<name>``); the
config, the docs and the checks follow.

    >>> from icco_torchrl.envs.params import ResourceCollectionParams
    >>> p = ResourceCollectionParams(n_agents=4, pick_reward=3)
    >>> p.n_agents, p.pick_reward, p.field_size
    (4, 3.0, 6.5)
    >>> ResourceCollectionParams(vision_radius=0)
    Traceback (most recent call last):
    ...
    ValueError: vision_radius must be a positive finite number, got 0
"""

import dataclasses
import math
import numbers
import textwrap
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from icco_torchrl.envs._kernels import Params
from icco_torchrl.envs.routes import DEFAULT_STEP

SPAWN_MODES = ("uniform", "copa")
WAYPOINT_MODES = ("random_walk", "external")

# A constraint: (field name, value, the table being checked) -> None, or a ValueError whose message
# starts with the field name. The table is passed for the rules between fields.
Check = Callable[[str, Any, "ResourceCollectionParams"], None]


def positive(name: str, value, params=None, integer: bool = False) -> None:
    """A positive finite number (``integer``: a positive int; bools are neither)."""
    ok = isinstance(value, int) if integer else isinstance(value, (int, float))
    if not ok or isinstance(value, bool) or not value > 0 or not math.isfinite(value):
        kind = "a positive integer" if integer else "a positive finite number"
        raise ValueError(f"{name} must be {kind}, got {value!r}")


def positive_int(name: str, value, params=None) -> None:
    positive(name, value, integer=True)


def number(name: str, value, params=None) -> None:
    """Any real number (the type of a float field without a range)."""
    if not isinstance(value, numbers.Real) or isinstance(value, bool):
        raise ValueError(f"{name} must be a number, got {value!r}")


def at_least(bound: float, why: str = "") -> Check:
    def check(name, value, params=None):
        if not value >= bound:
            raise ValueError(f"{name} must be >= {bound}{why}, got {value}")

    return check


def within(low: float, high: float, closed_high: bool = True) -> Check:
    """In ``[low, high]`` (``closed_high=False``: ``[low, high)``)."""

    def check(name, value, params=None):
        if not (low <= value <= high if closed_high else low <= value < high):
            raise ValueError(
                f"{name} must be in [{low}, {high}{']' if closed_high else ')'}, got {value}"
            )

    return check


def one_of(choices: tuple) -> Check:
    def check(name, value, params=None):
        if value not in choices:
            raise ValueError(f"{name} must be one of {choices}, got {value!r}")

    return check


def inside_field(low_open: bool) -> Check:
    """In ``(0, field_size/2)`` (``low_open``) or ``[0, field_size/2)``: a radius around home
    that leaves room in the field."""

    def check(name, value, params):
        low_ok = 0 < value if low_open else 0 <= value
        if not (low_ok and value < params.field_size / 2):
            interval = "(0, field_size/2)" if low_open else "[0, field_size/2)"
            raise ValueError(f"{name} must be in {interval}, got {value}")

    return check


def param(default, doc: str, *checks: Check):
    """A field of the table: its default, its doc (one paragraph) and its checks, run in order."""
    return dataclasses.field(default=default, metadata={"doc": doc, "checks": checks})


@dataclass(frozen=True)
class ResourceCollectionParams:
    """Every parameter of :class:`~icco_torchrl.envs.ResourceCollectionEnv` (see the module doc).

    Built from keyword arguments, checked (``ValueError`` naming the field) and frozen; float
    fields hold floats (an int given is converted), bool fields bools.
    """

    n_agents: int = param(
        3,
        "the most robots an env holds (paper: 3); all of them unless ``team_sizes``.",
        positive_int,
    )
    n_resources: int = param(
        6, "resources on the field at all times; a picked one respawns at once.", positive_int
    )
    n_invaders: int = param(
        1, "invaders. Each walks straight to home and respawns after removal.", positive_int
    )
    field_size: float = param(
        6.5, "side of the square field in metres, centred on home at (0, 0).", positive
    )
    vision_radius: float = param(
        0.65, "robots see entities within this distance, inclusive.", positive
    )
    max_steps: int = param(
        145, "episode length; ``truncated`` is set on the step that reaches it.", positive_int
    )
    inst_reward_scale: float = param(
        1.3, "weight of the instruction reward ``r_inst``.", number, at_least(0)
    )
    inst_dist_coef: float = param(
        0.1,
        "weight of ``e_dist = -distance to nearest waypoint`` inside r_inst. The paper's text "
        "would reward being far away; we read it as a penalty.",
        number,
    )
    inst_hold: bool = param(
        False,
        "at a route's end (the two nearest waypoints coincide, as on a served slot) r_inst's "
        "direction term scores holding still, ``1 - |displacement| / (max_speed * dt)`` (at least "
        "0), instead of 0: without it arriving ends the instruction reward, so a team is paid to "
        "dawdle along a route rather than hold its slot (experiments/language/routes).",
    )
    n_waypoints: int = param(
        4, "waypoints K per robot.", positive_int, at_least(2, " (e_cossim needs two)")
    )
    waypoint_interval: int = param(
        4, "steps between random-walk refreshes of the waypoints.", positive_int
    )
    waypoint_sigma: float = param(
        0.19,
        "std (m) of each random-walk increment; about one robot step.",
        number,
        at_least(0),
    )
    waypoint_mode: str = param(
        "random_walk",
        '``"random_walk"`` (training default: the env regenerates waypoints) or ``"external"`` '
        "(the env keeps whatever the caller wrote; see ``write_waypoints``).",
        one_of(WAYPOINT_MODES),
    )
    waypoint_path_prob: float = param(
        0.0,
        'with ``waypoint_mode="random_walk"``, the probability that a robot\'s instruction for an '
        "episode is a *path*: a walk laid out independently of the robot, which starts at a "
        "uniform point of the field and, at each refresh, continues from its own last waypoint "
        "instead of restarting at the robot. The paper's walks (0) always start at the robot, so "
        "they never ask a robot to come back to an instruction it left (to pick a resource, say), "
        'which every evaluation instruction does (a quadrant, "go right").',
        number,
        within(0, 1),
    )
    waypoint_route_prob: float = param(
        0.0,
        'with ``waypoint_mode="random_walk"``, the probability that a robot\'s instruction for an '
        "episode is a *route*: a slot drawn uniform in the field, served at every refresh as "
        "evaluation serves a plan (``icco_torchrl.envs.routes``): K waypoints from the robot "
        "straight toward the slot, ``waypoint_route_step`` apart, collapsing onto it on arrival. "
        "A route takes precedence over a path. 0 (the paper) draws nothing.",
        number,
        within(0, 1),
    )
    waypoint_route_step: float = param(
        DEFAULT_STEP, "metres between the served waypoints of a route.", positive
    )
    pick_reward: float = param(5.0, "reward of a pick.", number)
    collect_reward: float = param(1.0, "reward of a delivery home.", number)
    defense_reward: float = param(4.0, "reward of removing an invader.", number)
    invasion_penalty: float = param(
        4.0,
        "penalty of an invasion, shared equally by the (present) robots so that the team reward "
        "(their sum) gets exactly ``-invasion_penalty`` per invasion.",
        number,
    )
    home_radius: float = param(
        0.3,
        "contact radius of home in metres (COPA's geometry scaled by ~3.8, as every radius). Two "
        "bodies touch when the distance between centres is below the sum of their radii.",
        positive,
    )
    resource_radius: float = param(0.19, "contact radius of a resource (m).", positive)
    agent_radius: float = param(0.15, "contact radius of a robot (m).", positive)
    invader_radius: float = param(0.11, "contact radius of an invader (m).", positive)
    dt: float = param(
        0.1,
        "time step (s) of the point-mass dynamics ``v <- damping*v + dt*accel*u``, speed capped "
        "at ``max_speed``, ``p <- p + dt*v`` (~0.19 m per step at full speed).",
        positive,
    )
    damping: float = param(
        0.75, "velocity kept from one step to the next.", number, within(0, 1, closed_high=False)
    )
    accel: float = param(5.0, "acceleration of an action (m/s^2).", positive)
    max_speed: float = param(1.9, "speed cap of a robot (m/s).", positive)
    invader_speed: float = param(0.19, "metres per step an invader walks toward home.", positive)
    invader_respawn_max: int = param(
        10, "an invader respawns U{1..this} steps after removal.", positive_int
    )
    spawn: str = param(
        "uniform",
        'where things appear. ``"uniform"`` (the paper: "Agents, Invaders, and Resources are '
        "sampled uniformly in the field's range for each episode\"): at reset robots, resources "
        "and the (active) invader are uniform in the field; a picked resource respawns uniform "
        "in the field and an invader, U{1..invader_respawn_max} steps after its removal, uniform "
        "in the field at least ``invader_min_radius`` from home. Respawns use the initial "
        "distribution, so the state distribution does not drift within an episode, and the "
        "invader's clearance leaves the team ``invader_min_radius / invader_speed`` steps to "
        'react. ``"copa"`` (COPA\'s code): invaders start inactive and appear on the field edge, '
        "resources on the annulus between ``resource_min_radius`` and the edge. Resources never "
        "overlap each other or home, in either mode.",
        one_of(SPAWN_MODES),
    )
    resource_min_radius: float = param(
        1.5,
        'with ``spawn="copa"``, resources spawn between this distance from home and the field '
        "edge.",
        number,
        inside_field(low_open=True),
    )
    invader_min_radius: float = param(
        1.5,
        'with ``spawn="uniform"``, invaders spawn at least this far from home (1.5 m: about 8 '
        "invader steps).",
        number,
        inside_field(low_open=False),
    )
    validate: bool = param(
        True, "check actions and supplied waypoints at every step (costs a device sync)."
    )

    def __post_init__(self):
        """Run every field's checks in table order, then store floats as floats and bools as
        bools (the values a step computes with are the same)."""
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            for check in f.metadata["checks"]:
                check(f.name, value, self)
            if f.type is float:
                object.__setattr__(self, f.name, float(value))
            elif f.type is bool:
                object.__setattr__(self, f.name, bool(value))

    def kernel_params(self) -> Params:
        """The constants of one step (:func:`~icco_torchrl.envs._kernels.dynamics`), derived once
        (squared radii: contacts compare squared distances)."""
        r2 = lambda a, b: (a + b) ** 2  # noqa: E731
        invasion = -self.invasion_penalty
        per_step = 1.0 / (self.max_speed * self.dt)  # r_inst's scale of a step's length
        return Params(
            damping=self.damping,
            max_speed=self.max_speed,
            dt=self.dt,
            wall=self.field_size / 2 - self.agent_radius,
            invader_speed=self.invader_speed,
            touch_invader2=r2(self.agent_radius, self.invader_radius),
            touch_resource2=r2(self.agent_radius, self.resource_radius),
            invader_home2=r2(self.home_radius, self.invader_radius),
            robot_home2=r2(self.home_radius, self.agent_radius),
            inst_scale=self.inst_reward_scale,
            inst_dist_coef=self.inst_dist_coef,
            inst_hold=per_step if self.inst_hold else 0.0,
            pick=self.pick_reward,
            collect=self.collect_reward,
            defense=self.defense_reward,
            invasion_share=invasion / self.n_agents,
            invasion=invasion,
        )


def keyword_args_doc(indent: str = "    ") -> str:
    """The table as a docstring's ``Keyword Args:`` entries, one per field with its default."""
    lines = []
    for f in dataclasses.fields(ResourceCollectionParams):
        entry = f"{f.name} ({f.type.__name__}, default {f.default!r}): {f.metadata['doc']}"
        lines.append(
            textwrap.fill(entry, 100, initial_indent=indent * 2, subsequent_indent=indent * 3)
        )
    return "\n".join(lines)
