"""Dynamic Window Approach for unicycle robots: a velocity command toward a target point.

The policy decides *where* each robot goes next (a point one move away); a real robot needs a
linear and an angular velocity that respect its limits. As in the paper's robot experiments,
:func:`dwa_command` searches the window of velocities reachable within one control period
(acceleration limits), rolls each pair forward for ``horizon`` seconds and picks the one that
ends closest to the target and best headed toward it, among those that keep ``2 * radius``
clear of the other robots. Vectorised over the sampled window (numpy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from icco_torchrl.training.config import LiveConfig

_LIVE = LiveConfig()  # the live.* settings hold the default limits


@dataclass(frozen=True)
class RobotLimits:
    """A unicycle's limits (SI units). Defaults: ``live.max_speed`` ... ``live.robot_radius``
    (:class:`~icco_torchrl.training.config.LiveConfig`, where they are documented)."""

    max_speed: float = _LIVE.max_speed  # m/s, forward only
    max_turn: float = _LIVE.max_turn  # rad/s
    max_accel: float = _LIVE.max_accel  # m/s^2
    max_turn_accel: float = _LIVE.max_turn_accel  # rad/s^2
    radius: float = _LIVE.robot_radius  # m

    def __post_init__(self):
        for name in ("max_speed", "max_turn", "max_accel", "max_turn_accel", "radius"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and value > 0):
                raise ValueError(f"robot limit {name} must be a positive number, got {value!r}")


DEFAULT_LIMITS = RobotLimits()


def dwa_command(
    pose,
    velocity,
    target,
    limits: RobotLimits,
    dt: float,
    *,
    others=None,
    horizon: float = 1.0,
    samples: int = 11,
) -> tuple[float, float]:
    """``(v, w)`` for a robot at ``pose`` (x, y, theta) moving at ``velocity`` (v, w) toward
    ``target`` (x, y).

    ``others`` [M, 2] are the other robots' positions (kept ``2 * radius`` away); ``dt`` is the
    control period (the window's size is ``accel * dt``).
    """
    x, y, theta = map(float, pose)
    L = limits
    v, w = _window(velocity, L, dt, samples)  # [S]
    steps = max(1, int(round(horizon / dt)))
    t = np.arange(1, steps + 1) * dt  # [H]
    heading = theta + w[:, None] * t  # [S, H]
    px = x + np.cumsum(v[:, None] * np.cos(heading) * dt, axis=1)
    py = y + np.cumsum(v[:, None] * np.sin(heading) * dt, axis=1)
    tx, ty = map(float, target)
    dist = np.hypot(tx - px[:, -1], ty - py[:, -1])
    bearing = np.arctan2(ty - py[:, -1], tx - px[:, -1]) - heading[:, -1]
    align = np.abs(np.arctan2(np.sin(bearing), np.cos(bearing)))  # [0, pi]
    cost = dist + 0.3 * align - 0.05 * v
    if others is not None and len(others):
        others = np.asarray(others, dtype=float).reshape(-1, 2)
        gap = np.hypot(px[:, :, None] - others[:, 0], py[:, :, None] - others[:, 1]).min(
            axis=(1, 2)
        )
        cost = np.where(gap < 2 * L.radius, np.inf, cost)
    if np.hypot(tx - x, ty - y) < 0.02:  # arrived: brake
        cost = np.abs(v) + 0.1 * np.abs(w)
    best = int(np.argmin(cost))
    if not np.isfinite(cost[best]):  # boxed in: stop turning in place
        return 0.0, 0.0
    return float(v[best]), float(w[best])


def _window(velocity, L: RobotLimits, dt: float, samples: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``(v, w)`` pairs ``[S]`` reachable from ``velocity`` within ``dt``: ``samples`` speeds
    by ``2 * samples - 1`` turn rates."""
    v0, w0 = map(float, velocity)
    vs = np.linspace(
        max(0.0, v0 - L.max_accel * dt), min(L.max_speed, v0 + L.max_accel * dt), samples
    )
    ws = np.linspace(
        max(-L.max_turn, w0 - L.max_turn_accel * dt),
        min(L.max_turn, w0 + L.max_turn_accel * dt),
        2 * samples - 1,
    )
    return tuple(a.ravel() for a in np.meshgrid(vs, ws))
