"""The live loop: one team, a trained policy, instructions at any moment (what a live page and a
robot bridge drive).

:class:`LiveLoop` holds an env of one team (``num_envs=1``, external waypoints), a greedy
policy (argmax Q, the coordinator's mean) and a planner (the offline rule planner or any
litellm model, through :class:`~icco_torchrl.instructions.LLMPlanner` with its cache, retries,
deadline and fallbacks). :meth:`LiveLoop.tick` steps the team once and returns what a display
or a robot bridge needs; :meth:`LiveLoop.instruct` starts planning in a background thread and
returns at once, so the team keeps moving on its previous waypoints until the plan arrives
(the next tick applies it). One planner thread serves the loop: a newer instruction supersedes
(and cancels) one still being planned, so instructions never pile up threads or requests.
The team can change between ticks (:meth:`LiveLoop.add_robot`, :meth:`LiveLoop.remove_robot`, up
to the env's ``n_agents``): the others keep their recurrent state, a new robot starts from zero,
and the instruction in use is planned again for the new team (the planner plans for the present
robots only).
Episodes are as long as the policy's training episodes (145 steps): when one ends the next
starts at once, with the totals set to zero and the plan in use kept (a reset starts one the
same way, and the instruction stays). Each state carries the instruction of the plan in use,
each robot's distance to its nearest waypoint (the distance of the env's instruction reward) and
the mean totals of the episodes that ran to their end. :meth:`LiveLoop.run`
ticks at a fixed rate (default real time: one env step per ``env.dt`` seconds). No web code
here: a page or a bridge drives this object.
"""

from __future__ import annotations

import inspect
import threading
import time
from dataclasses import asdict, dataclass, field

import numpy as np
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type, step_mdp

from icco_torchrl.envs import EVENTS  # the env owns the event names
from icco_torchrl.envs.resource_collection import _ACTION_DIRS
from icco_torchrl.envs.waypoints import base_env
from icco_torchrl.evaluation import placement
from icco_torchrl.instructions.serving import PlanServer
from icco_torchrl.live.reading import explain, planner_reading, short_reason

MAX_INSTRUCTION = 200  # characters: longer instructions are refused with a message


def _takes_cancel(plan) -> bool:
    """Whether a planner's ``plan`` takes a ``cancel`` event (``LLMPlanner.plan`` does)."""
    try:
        params = inspect.signature(plan).parameters.values()
    except (TypeError, ValueError):
        return False
    return any(p.name == "cancel" or p.kind is p.VAR_KEYWORD for p in params)


def _names(team) -> str:
    return ", ".join(str(r) for r in team)


def _restore(path, device: str, seed: int | None, max_robots: int | None, length: dict):
    """The checkpoint's run on a one-team env of ``max_robots`` robots, and the team it was
    trained for (:func:`~icco_torchrl.training.restore.restore` with ``n_agents``: at another
    team size only the acting networks' weights are loaded)."""
    from icco_torchrl.training.checkpoint import load_checkpoint
    from icco_torchrl.training.restore import restore  # heavy: networks and Hydra config

    ckpt = load_checkpoint(path)
    trained = int((ckpt.get("layout") or {}).get("n_agents") or ckpt["cfg"]["env"]["params"].get(
        "n_agents", 3))  # fmt: skip
    if max_robots is not None and (isinstance(max_robots, bool) or int(max_robots) < 1):
        raise ValueError(f"live.max_robots must be an integer >= 1, got {max_robots!r}")
    team = {} if max_robots is None else {"n_agents": int(max_robots)}
    run = restore(
        path, num_envs=1, device=device, seed=seed, waypoint_mode="external", **team, **length
    )
    return run, trained


# The totals the page shows, and the yardstick's (:func:`scripted_yardstick`).
TOTALS = (*EVENTS, "inst_reward", "reward")


def scripted_yardstick(path, episodes: int, *, seed: int | None = None) -> dict | None:
    """The best scripted team's mean totals over ``episodes`` episodes of the checkpoint's
    training env (its team, its episode length, its own random instructions), for the page to
    show beside its running mean: ``{"label", "episodes", "steps", "pick", ..., "reward"}``;
    None for 0 episodes. The same evaluation as a run's ``references.json``."""
    if isinstance(episodes, bool) or int(episodes) != episodes or episodes < 0:
        raise ValueError(f"live.reference_episodes must be an integer >= 0, got {episodes!r}")
    if episodes == 0:
        return None
    from omegaconf import OmegaConf

    from icco_torchrl.envs.reference_policies import make_reference_policy, reference_label
    from icco_torchrl.evaluation.rollout import evaluate
    from icco_torchrl.training.build import make_env
    from icco_torchrl.training.checkpoint import load_checkpoint
    from icco_torchrl.training.config import validate

    # The checkpoint's env only: the scripted team needs no networks.
    cfg = validate(OmegaConf.create(load_checkpoint(path)["cfg"]))
    env = make_env(cfg, num_envs=int(episodes), seed=seed)
    means = evaluate(env, make_reference_policy("best_scripted", env), seed=seed)
    steps = int(getattr(env, "base_env", env).max_steps)
    return {
        "label": reference_label("best_scripted"),
        "episodes": int(episodes),
        "steps": steps,
        **{k: means[k] for k in TOTALS},
    }


def _np(tensor: torch.Tensor) -> np.ndarray:
    """A numpy copy (CPU tensors would otherwise share memory with the env's state)."""
    return tensor.detach().cpu().numpy().copy()


@dataclass
class PlannerStatus:
    """What the planner is doing: ``idle``, ``thinking``, ``used`` (a plan is driving the team) or
    ``fell back`` (the team keeps its previous waypoints; ``error`` says why). ``reading`` is how
    the planner read the instruction (its reply's ``movement_strategy``, e.g. "defend home").
    With the offline rule planner, ``understood`` lists what it understands (when it fell back
    on an instruction it does not know) and ``unused`` the words of a used instruction its
    reading did not use; ``hint`` says how to act on ``error`` (:func:`~icco_torchrl.live.
    reading.explain`)."""

    state: str = "idle"
    instruction: str | None = None
    error: str | None = None
    latency_s: float | None = None
    requests: int = 0
    reading: str | None = None
    understood: str | None = None
    unused: list[str] | None = None
    hint: str | None = None


@dataclass
class TickState:
    """One tick, as plain numpy/python values (ready for JSON)."""

    tick: int
    step: int  # step of the episode (1 .. episode_steps)
    positions: np.ndarray  # [N, 2]
    waypoints: np.ndarray  # [N, K, 2]
    resources: np.ndarray  # [R, 2]
    invader: np.ndarray  # [I, 2]
    invader_active: np.ndarray  # [I]
    carry: np.ndarray  # [N]
    z: np.ndarray | None  # [N, z_dim] (ICCO) or None
    present: np.ndarray | None = None  # [N] bool: the robots in the team (draw only these)
    events: dict = field(default_factory=dict)  # this step's counts and instruction reward
    totals: dict = field(default_factory=dict)  # running sums over this episode
    planner: dict = field(default_factory=dict)
    latency_ms: float = 0.0  # policy + env step + bookkeeping of this tick
    episode: int = 1  # episodes started since the loop was made (a reset starts one)
    episode_steps: int = 0  # the episode's length (the env's max_steps)
    plan: str | None = None  # the instruction whose plan drives the team (None: none yet)
    slots: np.ndarray | None = None  # [N, 2]: where the plan in use sends each robot
    slot_distance: np.ndarray | None = None  # [N] m: each robot to its own slot
    at_slot: np.ndarray | None = None  # [N] bool: within placement.SLOT_RADIUS of it
    intercepting: np.ndarray | None = None  # [N] bool: excused from the formation
    formation: bool | None = None  # every present robot not intercepting is at its slot
    finished: int = 0  # episodes that ran to their end (a reset's cut-short one is not)
    finished_mean: dict = field(default_factory=dict)  # their totals' mean (empty: none yet)

    def to_dict(self) -> dict:
        out = asdict(self)
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in out.items()}


class LiveLoop:
    """A trained team driven live (see the module docstring).

    Args:
        env: a ``ResourceCollectionEnv`` (or a ``TransformedEnv`` over one) with ``num_envs=1`` and
            ``waypoint_mode="external"``; :meth:`from_checkpoint` builds one.
        policy: maps the root TensorDict to one with the action (a restored trained policy, or a
            reference policy); run greedily.
        planner: an :class:`~icco_torchrl.instructions.LLMPlanner`, or None (instructions refused).
        team: the robots in the team from the start (indices below the env's ``n_agents``);
            None: all of them. The team outlasts episodes and resets; :meth:`add_robot` and
            :meth:`remove_robot` change it.

    ``on_status``, when set, is called with the new :class:`PlannerStatus` each time it changes
    (from the thread that changed it: the caller's, or the planner's thread). ``totals`` are
    this episode's sums; ``episode`` counts the episodes begun.
    """

    def __init__(self, env, policy, planner=None, *, team=None):
        raw = base_env(env)
        if raw.num_envs != 1 or raw.waypoint_mode != "external":
            raise ValueError(
                "LiveLoop drives one team with external waypoints: build the env with num_envs=1 "
                "and waypoint_mode='external' (LiveLoop.from_checkpoint does)"
            )
        self.env, self.raw, self.policy, self.planner = env, raw, policy, planner
        self.status = PlannerStatus()
        self.on_status = None
        self.totals = dict.fromkeys(TOTALS, 0.0)
        self.ticks, self.episode, self.finished = 0, 1, 0
        self._finished_sums = dict.fromkeys(self.totals, 0.0)  # over the finished episodes
        self._lock = threading.Lock()  # one tick or plan hand-over at a time
        self._idle = threading.Condition(self._lock)  # the planner thread ended
        # A plan that arrived, for the next tick: the robots' positions it was made from [N, 2]
        # and the planner's waypoints [N, K, 2] (each robot's route; the last point its slot).
        self._pending: tuple[np.ndarray, np.ndarray] | None = None
        self.server = PlanServer(raw.n_waypoints)  # the plan in use, served every refresh
        self._job: tuple | None = None  # the newest instruction, waiting for the planner thread
        self._cancel: threading.Event | None = None  # cancels the plan being computed
        self._worker: threading.Thread | None = None  # the planner thread, while it has work
        self._generation = 0  # bumped by each instruction: older plans are dropped
        self._cancellable = planner is not None and _takes_cancel(planner.plan)
        self._plan_instruction: str | None = None  # the instruction of the latest plan
        self._plan_for: str | None = None  # the instruction of the plan in use
        self._team = np.ones(raw.n_agents, bool)
        if team is not None:
            members = [self._robot(r) for r in team]
            if not members:
                raise ValueError("a live team needs at least one robot, got team=[]")
            self._team[:] = False
            self._team[members] = True
        with torch.no_grad():
            self.td = env.reset()
            self._keep_team()

    @classmethod
    def from_checkpoint(
        cls,
        path,
        *,
        planner=None,
        device: str = "cpu",
        seed: int | None = None,
        episode_steps: int | None = None,
        max_robots: int | None = None,
    ) -> LiveLoop:
        """The checkpoint's policy on a one-team env, in episodes of ``episode_steps`` (default:
        the length it was trained on; a policy far past it acts on step counts it never saw);
        the next episode starts when one ends.

        ``max_robots`` (``live.max_robots``) is the most robots the team may hold (the env's
        ``n_agents``; default: the checkpoint's team). The team starts as the checkpoint's (or
        the first ``max_robots`` robots, when fewer); :meth:`add_robot` grows it up to
        ``max_robots``. The agents and the coordinator read any team (attention over tokens);
        the mixer and the posterior, sized for the trained team, are not used when acting."""
        length = {} if episode_steps is None else {"max_steps": int(episode_steps)}
        restored, trained = _restore(path, device, seed, max_robots, length)
        team = None if trained >= restored["env"].base_env.n_agents else range(trained)
        return cls(restored["env"], restored["policy"], planner, team=team)

    # ------------------------------------------------------------------ instructions
    def instruct(self, instruction: str) -> None:
        """Plan ``instruction`` in the background from the robots' current positions; returns at
        once.

        An instruction given while another is being planned supersedes it: the older one is
        cancelled (an :class:`~icco_torchrl.instructions.LLMPlanner` stops waiting for its
        reply) and its plan, should it still arrive, is dropped. One planner thread serves the
        loop, so a burst of instructions costs one request at a time, not a thread each.
        Unknown instructions fall back in the planner: the status says so and the team keeps
        its previous waypoints.
        """
        if not isinstance(instruction, str) or not instruction.strip():
            raise ValueError(f"an instruction must be a non-empty string, got {instruction!r}")
        if len(instruction.strip()) > MAX_INSTRUCTION:
            raise ValueError(
                f"instruction too long: {len(instruction.strip())} characters, at most "
                f"{MAX_INSTRUCTION} (the team keeps its last plan)"
            )
        if self.planner is None:
            raise ValueError(
                "this live loop has no planner: give one (LLMPlanner) to take instructions"
            )
        with self._lock:
            self._queue(instruction.strip())

    def _queue(self, instruction: str) -> None:
        """Plan ``instruction`` for the team as it is now (call under the lock)."""
        self._generation += 1
        team = np.flatnonzero(self._team)
        self._job = (
            self._generation,
            instruction,
            team,
            self.raw.pos[0].cpu().numpy().copy(),
            self.raw.waypoints[0].cpu().numpy().copy(),
            self.raw.res_pos[0].cpu().numpy().copy(),
            self.raw.inv_pos[0][self.raw.inv_active[0]].cpu().numpy().copy(),
        )
        if self._cancel is not None:
            self._cancel.set()
        self._set_status(PlannerStatus("thinking", instruction, requests=self.status.requests + 1))
        if self._worker is None:
            self._worker = threading.Thread(
                target=self._work, daemon=True, name="icco-live-planner"
            )
            self._worker.start()

    def _work(self) -> None:
        """The planner thread: plan the newest instruction until none waits, then end."""
        while True:
            with self._lock:
                job, self._job = self._job, None
                if job is None:
                    self._worker = self._cancel = None
                    self._idle.notify_all()
                    return
                cancel = self._cancel = threading.Event()
            self._plan(job, cancel)

    def _plan(self, job: tuple, cancel: threading.Event) -> None:
        """Plan one instruction (the planner thread) and hand the plan to the next tick."""
        generation, instruction, team, positions, previous, _, _ = job
        start = time.perf_counter()
        answer = self._ask(job, cancel)
        if answer is None:
            return  # superseded while it was asked: the newer instruction's status stands
        ok, error, waypoints, reading = answer
        notes = explain(self.planner, instruction, self.raw.field_size / 2, ok, error)
        with self._lock:
            if generation != self._generation:
                return  # superseded by a newer instruction
            latency, requests = time.perf_counter() - start, self.status.requests
            if ok:
                full = previous.astype(np.float32)  # absent robots keep theirs (ignored)
                full[team] = np.asarray(waypoints, dtype=np.float32).reshape(full[team].shape)
                self._pending = (positions.astype(np.float32), full)
                self._plan_instruction = instruction
                status = PlannerStatus("used", instruction, None, latency, requests, reading)
            else:
                reason = short_reason(error, instruction) or "no plan"
                status = PlannerStatus("fell back", instruction, reason, latency, requests)
            self._set_status(PlannerStatus(**{**asdict(status), **notes}))

    def _ask(self, job: tuple, cancel: threading.Event) -> tuple | None:
        """The planner's answer to ``job``: ``(ok, error, waypoints, reading)``; a planner that
        raises falls back with its error's first line; None when ``cancel`` was set."""
        _, instruction, team, positions, previous, resources, invader = job
        extra = {"cancel": cancel} if self._cancellable else {}
        try:
            result = self.planner.plan(  # the present robots only: a plan for the team that is in
                instruction,
                positions[team],
                previous=previous[team],
                resources=resources,
                invader=invader,
                **extra,
            )
        except Exception as err:  # an unreachable model must not stop the team: report, keep plan
            if cancel.is_set():
                return None
            return False, f"{type(err).__name__}: {err}".splitlines()[0], None, None
        reading = planner_reading(getattr(result, "raw", None)) if result.ok else None
        return result.ok, result.error, result.waypoints, reading

    def _set_status(self, status: PlannerStatus) -> None:
        """Replace the planner status (under the lock) and tell ``on_status``."""
        self.status = status
        if self.on_status is not None:
            self.on_status(status)

    def wait_for_plan(self, timeout: float | None = None) -> PlannerStatus:
        """Block until no instruction is being planned (tests, scripted demos)."""
        with self._idle:
            self._idle.wait_for(lambda: self._worker is None, timeout)
            return self.status

    # ------------------------------------------------------------------ stepping
    def tick(self) -> TickState:
        """One env step of the team under the current plan; applies a plan that arrived since."""
        start = time.perf_counter()
        with self._lock, torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            fresh = self._pending is not None
            if fresh:
                self._use_pending()
            self._serve(fresh)
            td = self.env.step(self.policy(self.td))
            nxt = td.get("next")
            events = {k: float(nxt.get(("events", k))[0]) for k in (*EVENTS, "inst_reward")}
            events["reward"] = float(nxt.get("reward")[0, 0])
            for k, v in events.items():
                self.totals[k] += v
            self.ticks += 1
            state = self._state(td.get(("agents", "z"), None), events)
            self.td = step_mdp(td)
            if bool(nxt.get("done").any()):  # the episode ended: the next tick starts another
                self.finished += 1
                for k, v in self.totals.items():
                    self._finished_sums[k] += v
                self._new_episode()
        state.latency_ms = (time.perf_counter() - start) * 1e3
        return state

    def _new_episode(self) -> None:
        """Start the next episode (call under the lock): new resources, invader and positions,
        the totals at zero; the team and the instruction kept. The robots start elsewhere, so
        the instruction is planned again from their new positions (one request per instruction
        and episode); until that plan arrives the old routes are served from where they are."""
        self.td = self.env.reset()
        self._keep_team()
        self.episode += 1
        self.totals = {k: 0.0 for k in self.totals}
        if self.server.routes is not None:  # the instruction still stands
            self._serve(True)
            self._replan()

    def _use_pending(self) -> None:
        """The plan that arrived becomes the plan in use (call under the lock)."""
        (start, planned), self._pending = self._pending, None
        device = self.raw.device
        self.server.set_plan(torch.as_tensor(start, device=device)[None],
                             torch.as_tensor(planned, device=device)[None])  # fmt: skip
        if self._plan_for != self._plan_instruction:  # a new instruction: a new running mean
            self.finished, self._finished_sums = 0, dict.fromkeys(self._finished_sums, 0.0)
        self._plan_for = self._plan_instruction

    def _serve(self, now: bool = False) -> None:
        """Write the plan in use as waypoints from where the robots are, when the env's clock
        says they are due (every ``waypoint_interval`` steps, as in training) or ``now`` (call
        under the lock)."""
        raw = self.raw
        if self.server.routes is None:
            return
        if now or bool((raw.t % raw.waypoint_interval == 0).any()):
            raw.write_waypoints(self.td, self.server.serve(raw.pos))

    def _state(self, z, events: dict) -> TickState:
        """The team as it is now (call under the lock)."""
        raw = self.raw
        positions, waypoints = _np(raw.pos[0]), _np(raw.waypoints[0])
        slots = self.server.slots
        arrival = None if slots is None else self._arrival(slots)
        n = self.finished
        return TickState(
            tick=self.ticks,
            step=int(raw.t[0]),
            positions=positions,
            waypoints=waypoints,
            resources=_np(raw.res_pos[0]),
            invader=_np(raw.inv_pos[0]),
            invader_active=_np(raw.inv_active[0]),
            carry=_np(raw.carry[0]),
            z=None if z is None else _np(z[0]),
            present=_np(raw.present[0]),
            events=events,
            totals=dict(self.totals),
            planner=asdict(self.status),
            episode=self.episode,
            episode_steps=int(raw.max_steps),
            plan=self._plan_for,
            slots=None if slots is None else _np(slots[0]),
            **(arrival or {}),
            finished=n,
            finished_mean={k: v / n for k, v in self._finished_sums.items()} if n else {},
        )

    def _arrival(self, slots: torch.Tensor) -> dict:
        """Each robot's distance to its slot and the person's judgements of it
        (:mod:`~icco_torchrl.evaluation.placement`; call under the lock)."""
        raw = self.raw
        present = raw.present
        at = placement.at_slot(raw.pos, slots)
        excused = placement.intercepting(raw.pos, present, raw.inv_pos, raw.inv_active)
        return {
            "slot_distance": np.round(_np((raw.pos - slots).norm(dim=-1)[0]), 3),
            "at_slot": _np(at[0]),
            "intercepting": _np(excused[0]),
            "formation": bool(placement.formation(at, present, excused)[0]),
        }

    def snapshot(self) -> TickState:
        """The team's current state without stepping it (what a display shows between ticks, or
        after :meth:`act_on` when the robots are real); no events."""
        with self._lock:
            return self._state(self.td.get(("agents", "z"), None), {})

    def reset(self) -> TickState:
        """A new episode now, as when one ends (new resources, invader and robot positions, the
        totals set to zero): the instruction stays, its plan in use (or on its way) drives the
        team on. The episode cut short is not counted among the finished ones."""
        with self._lock, torch.no_grad():
            self._new_episode()
            return self._state(None, {})

    # ------------------------------------------------------------------ team changes
    @property
    def team(self) -> list[int]:
        """The robots in the team (indices below ``raw.n_agents``)."""
        return np.flatnonzero(self._team).tolist()

    def add_robot(self, robot: int | None = None) -> int:
        """Bring a robot into the team between two ticks and return its index (``robot``, or the
        lowest one not in the team). It appears at rest at a free point of the field with zero
        recurrent state, previous action and z; the others keep theirs. The instruction in use
        (or the one being planned) is planned again for the new team. A full team, a robot
        already in it or an index out of range is a ``ValueError`` of one line (nothing
        changes)."""
        n = self.raw.n_agents
        with self._lock, torch.no_grad():
            if robot is None:
                free = np.flatnonzero(~self._team)
                if not len(free):
                    raise ValueError(
                        f"the team is full: {n} robots, the most this loop holds (live.max_robots)"
                    )
                robot = int(free[0])
            r = self._robot(robot)
            if self._team[r]:
                raise ValueError(f"robot {r} is already in the team (robots {_names(self.team)})")
            self.raw.add_robot(0, r, tensordict=self.td)
            self._team[r] = True
            for key in (("agents", "rnn_hidden"), ("agents", "prev_action"), ("agents", "z"),
                        ("agents", "z_noise")):  # fmt: skip
                value = self.td.get(key, None)
                if value is not None:
                    value = value.clone()
                    value[0, r] = 0
                    self.td.set(key, value)
            if self.server.routes is not None:  # until the new plan: it holds where it appeared
                routes = self.server.routes.clone()
                routes[0, r] = self.raw.pos[0, r]
                self.server.routes = routes
            self._replan()
        return r

    def remove_robot(self, robot: int) -> None:
        """Take ``robot`` out of the team between two ticks: it stops, drops what it carries and
        is left out of everything; the others keep their recurrent state, and the instruction in
        use is planned again for them. A robot not in the team, the last robot or an index out
        of range is a ``ValueError`` of one line (nothing changes)."""
        with self._lock, torch.no_grad():
            r = self._robot(robot)
            if not self._team[r]:
                raise ValueError(f"robot {r} is not in the team (robots {_names(self.team)})")
            if self._team.sum() == 1:
                raise ValueError(f"robot {r} is the last robot: a team keeps at least one")
            self.raw.remove_robot(0, r, tensordict=self.td)
            self._team[r] = False
            self._replan()

    def _robot(self, robot) -> int:
        n = self.raw.n_agents
        if isinstance(robot, (bool, np.bool_)) or not isinstance(robot, (int, np.integer)):
            shown = repr(robot) if len(repr(robot)) <= 40 else repr(robot)[:37] + "..."
            raise ValueError(f"robot must be an integer in 0..{n - 1}, got {shown}")
        if not 0 <= robot < n:
            raise ValueError(f"robot must be an integer in 0..{n - 1}, got {robot}")
        return int(robot)

    def _replan(self) -> None:
        """After a team change (under the lock): a plan made for the old team is dropped and its
        instruction planned again for the new one (with a planner, when there is one)."""
        if self.planner is None:
            return
        thinking = self.status.state == "thinking"
        instruction = self.status.instruction if thinking else self._plan_instruction
        if self._pending is not None:
            self._pending = None
            instruction = self._plan_instruction
        if instruction is not None:
            self._queue(instruction)

    def _keep_team(self) -> None:
        """Make the env's team this loop's after a reset (which brings every robot in)."""
        present = _np(self.raw.present[0])
        if np.array_equal(present, self._team):
            return
        for r in np.flatnonzero(self._team & ~present):
            self.raw.add_robot(0, int(r), tensordict=self.td)
        for r in np.flatnonzero(present & ~self._team):
            self.raw.remove_robot(0, int(r), tensordict=self.td)

    def act_on(
        self, positions, *, velocities=None, resources=None, invader=None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The policy's move for robots measured from outside (motion capture), without stepping
        the env.

        The env's state is overwritten by the measurements: ``positions`` [N, 2], ``velocities``
        [N, 2] (m/s; zero when not given), ``resources`` [R, 2] and ``invader`` [I', 2] (active
        ones; kept from the last call when None). The observation is rebuilt, the policy runs
        greedily, and its recurrent state, previous action and step counter carry over to the next
        call.
        Returns ``(actions [N], targets [N, 2])``: each robot's discrete move and the point one move
        (``max_speed * dt``) away in that direction, which a controller (DWA) then drives to.
        """
        raw = self.raw
        with self._lock, torch.no_grad(), set_exploration_type(ExplorationType.DETERMINISTIC):
            self._measure(positions, velocities, resources, invader)
            fresh = self._pending is not None
            if fresh:
                self._use_pending()
            self._serve(fresh)
            raw.write_waypoints(self.td, raw.waypoints)  # rebuilds the observation and the state
            td = self.policy(self.td)
            action = td.get(("agents", "action"))[0]
            self._carry_memory(td)
            raw._put(t=raw.t + 1)
            self.ticks += 1
            step = raw.max_speed * raw.dt
            dirs = torch.tensor(_ACTION_DIRS, device=raw.device)[action.long()]
            targets = raw.pos[0] + step * dirs
        return _np(action), _np(targets)

    def _measure(self, positions, velocities, resources, invader) -> None:
        """Overwrite the env's state with measurements (:meth:`act_on`; call under the lock)."""
        raw, dev = self.raw, self.raw.device
        lim = raw.half - raw.agent_radius
        shape = (1, raw.n_agents, 2)
        pos = torch.as_tensor(np.asarray(positions, np.float32), device=dev).reshape(shape)
        raw.pos = pos.clamp(-lim, lim)
        raw.vel = (
            torch.zeros_like(pos)
            if velocities is None
            else torch.as_tensor(np.asarray(velocities, np.float32), device=dev).reshape(shape)
        )
        if resources is not None:
            res = torch.as_tensor(np.asarray(resources, np.float32), device=dev).reshape(
                1, raw.n_resources, 2
            )
            raw.res_pos = res.clamp(-raw.half, raw.half)
        if invader is not None:
            inv = np.asarray(invader, np.float32).reshape(-1, 2)[: raw.n_invaders]
            full = np.zeros((raw.n_invaders, 2), np.float32)
            full[: len(inv)] = inv
            raw.inv_pos = torch.as_tensor(full, device=dev)[None]
            raw.inv_active = (torch.arange(raw.n_invaders, device=dev) < len(inv))[None]

    def _carry_memory(self, td) -> None:
        """Keep a trained policy's memory (recurrent state, previous action) and the step count
        for the next :meth:`act_on` (call under the lock)."""
        nxt = td.get("next", None)
        carried = td.exclude("next")
        for key in (("agents", "rnn_hidden"), ("agents", "prev_action")):
            if nxt is not None and key in nxt.keys(True):
                carried.set(key, nxt.get(key))
        carried.set("step_count", td.get("step_count") + 1)
        self.td = carried

    def run(
        self,
        ticks: int,
        rate_hz: float | None = None,
        on_tick=None,
        stop: threading.Event | None = None,
    ) -> list[float]:
        """``ticks`` ticks at ``rate_hz`` (default: real time, ``1 / env.dt``); ``on_tick(state)``
        is called after each. Returns the tick latencies (ms). Late ticks are not made up for."""
        rate = rate_hz or 1.0 / self.raw.dt
        if not rate > 0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
        period, latencies = 1.0 / rate, []
        next_time = time.perf_counter()
        for _ in range(ticks):
            if stop is not None and stop.is_set():
                break
            state = self.tick()
            latencies.append(state.latency_ms)
            if on_tick is not None:
                on_tick(state)
            next_time += period
            pause = next_time - time.perf_counter()
            if pause > 0:
                time.sleep(pause)
            else:
                next_time = time.perf_counter()
        return latencies
