"""Robot bridge: the live loop driven by external positions, commanding robots over JSON-over-UDP.

The messages (``state`` and ``instruct`` in, ``command`` out) and how each datagram is checked
are :mod:`icco_torchrl.live.wire`'s. This module serves them:

* in, on either message: with a ``token`` (``live.token``) every datagram must carry it; one
  without it or with a wrong one is refused (kind ``token``; one without the token's bytes
  before it is parsed), and wrong ones are limited
  (:class:`~icco_torchrl.live.guard.TokenCheck`: beyond, refused unchecked, but never from an
  address that gave the right token). With a token a state must carry a ``time`` after that of
  the last state taken for each robot it lists: a replayed one is refused (kind ``replay``).
* out, to the robots' own addresses: a ``command`` at the control rate: the policy's next point
  for each robot and a unicycle velocity command toward it from the Dynamic Window Approach
  (``dwa.py``) within the robot's limits. A robot is bound to the first address that reported
  its pose; its poses are taken from there only and each command goes to the address of every
  robot it lists. Another sender that reports it displaces nothing: the robot is contested,
  stopped (``"reason": "contested"``) until nobody else has reported it for ``timeout``
  seconds, and logged; a robot whose address has been silent for ``timeout`` seconds (and that
  nobody contested meanwhile) moves to the next address that reports it, said in a line. Other
  addresses that reported a robot (the ``ROBOT_ADDRESSES`` most recent) get its stops, never
  its drive commands. A state that gives no robot's pose makes its sender no robot's address:
  it gets the exit stop only, after the robots.

The team is the robots that report. A robot ``id`` is any integer in ``0..MAX_ROBOT_ID``; each
one in the team holds one of the env's ``n_agents`` places (its own index when that is free, so
ids ``0..n_agents-1`` keep theirs). A new id joins the team (``LiveLoop.add_robot``) while a place
is free; beyond that it is refused (one log line) and commanded to stop (``"reason": "team
full"``), and joins as soon as a place frees. A robot silent for ``timeout`` seconds leaves the
team (``LiveLoop.remove_robot``; the last one stays, stopped); the others keep being commanded.
Robots that left or were refused stay known (the ``MAX_KNOWN`` most recent) and get stop
commands; one that reports again joins again. Until the first robots report, the loop's own team
holds the places (listed by index, stopped as never seen); after ``timeout`` seconds of states,
places nobody claimed leave the team.

Safety contract (``docs/live.md``, "Bridge safety contract"):

* No datagram stops the bridge. Each is checked before it is used
  (:func:`~icco_torchrl.live.wire.parse_message`). A datagram that fails, or that the loop
  cannot take, is refused: counted in ``stats["malformed"]`` (by kind in
  ``stats["refused_by"]``) and logged in one line of at most about 300 characters, at most one
  line per ``LOG_EVERY`` seconds (the next line says how many were refused in between).
* A robot whose pose is older than ``timeout`` seconds (or never seen) gets ``v = w = 0`` with
  ``"stopped": true, "reason": "stale"``, and the event is logged once; it leaves the team, and
  the others keep going. A robot refused for a full team gets ``"reason": "team full"``.
  A control tick that fails stops every robot (``"reason": "control error"``) until one works.
* However :meth:`Bridge.serve` ends (``stop`` set, ``max_seconds`` out, SIGINT, SIGTERM or
  SIGHUP when it runs in the main thread, an exception), and on :meth:`Bridge.close`, every robot
  is sent a stop command (``"reason": "bridge stopped"``, ``STOP_REPEATS`` times) before the
  socket closes: in each round at the robots' own addresses first, then at the other addresses
  that reported them, then at the other senders of states (the ``MAX_PEERS`` most recent),
  none of which can displace the robots' addresses.
* With a ``token``, a datagram without it is refused: nobody who lacks it can report poses or
  instruct the team (UDP is not encrypted: anyone who reads the network can read the token).
* Joins, leaves, stale stops and refusals are each logged at most once per ``LOG_EVERY``
  seconds (the next line says how many were held back).
"""

from __future__ import annotations

import logging
import signal
import socket
import threading
import time
from collections import OrderedDict, deque

import numpy as np

from icco_torchrl.live import wire
from icco_torchrl.live.dwa import DEFAULT_LIMITS, RobotLimits, dwa_command
from icco_torchrl.live.guard import Throttle, TokenCheck, held, one_line
from icco_torchrl.live.loop import LiveLoop

log = logging.getLogger("icco.bridge")
MAX_PEERS = 32  # other senders of states (no robot's pose) remembered for the exit stop
ROBOT_ADDRESSES = 8  # other addresses that reported one robot, kept for its stops (most recent)
STOP_REPEATS = 3  # copies of the final stop command (UDP may drop one), 10 ms apart
RATE_WINDOW = 2.0  # seconds over which the actual control rate is measured (or 3 periods)
MAX_BATCH = 256  # datagrams read in one go between two control ticks
MAX_KNOWN = 64  # robots outside the team (left, refused) remembered for stop commands
STOP_SIGNALS = tuple(
    getattr(signal, name) for name in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, name)
)


def _peer(sender) -> str:
    try:
        host, port = sender[:2]
        return one_line(f"{host}:{int(port)}", 60)
    except (TypeError, ValueError):
        return one_line(repr(sender), 60)


def _source(sender) -> str:
    """The IP address of ``sender`` (whose wrong tokens are limited together)."""
    try:
        return str(sender[0])
    except (TypeError, IndexError):
        return repr(sender)


def _ids(ids) -> str:
    return ", ".join(str(i) for i in ids)


def _bind(host: str, port: int) -> socket.socket:
    """A UDP socket bound to ``host:port``, or ``OSError`` of one line naming them."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.bind((host, port))
    except OSError as err:
        sock.close()
        raise OSError(f"cannot listen on udp {host}:{port}: {err.strerror or err}") from None
    return sock


def _new_stats() -> dict:
    """A bridge's counters, all zero."""
    return {
        "messages": 0,
        "joined": 0,  # robots that joined the team (a return counts again)
        "dropped": 0,  # robots that left it after timeout s without a pose
        "refused_robots": 0,  # robots refused because the team was full
        "malformed": 0,  # every refused datagram (by kind in "refused_by")
        "refused_by": {},
        "commands": 0,
        "stale_stops": 0,
        "control_errors": 0,
        "stops_sent": 0,  # stop commands sent to all robots (control errors, the end)
        "contested": 0,  # robots' poses from another address than theirs (not taken)
        "moved": 0,  # robots bound to a new address after their own went silent
        "latency_ms": deque(maxlen=10_000),
    }


class Bridge:
    """Serve one team over UDP (see the module docstring); :meth:`serve` runs until ``stop`` is
    set."""

    def __init__(
        self,
        loop: LiveLoop,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        rate_hz: float = 10.0,
        timeout: float = 0.5,
        limits: RobotLimits = DEFAULT_LIMITS,
        token: str | None = None,
    ):
        if not rate_hz > 0 or not timeout > 0:
            raise ValueError(f"rate_hz and timeout must be > 0, got {rate_hz!r} and {timeout!r}")
        if token is not None and not str(token).strip():
            raise ValueError("live.token must be a non-empty string, or null for none")
        self.token = None if token is None else TokenCheck(str(token))
        self.loop, self.limits = loop, limits
        self.rate_hz, self.timeout = float(rate_hz), float(timeout)
        self.n = loop.raw.n_agents
        self.sock = _bind(host, port)
        self.address = self.sock.getsockname()
        self.poses = np.zeros((self.n, 3))
        self.seen = np.full(self.n, -np.inf)  # monotonic time of each robot's latest pose
        self.velocity = np.zeros((self.n, 2))  # measured, m/s (for the policy)
        self.command = np.zeros((self.n, 2))  # last (v, w) sent
        self.resources = self.invader = None
        self.reply_to = None  # the latest sender of a robot's pose
        # Each known robot's address: the first that reported it, the only one its poses are
        # taken from and its commands go to; no other sender displaces it while it reports.
        self.bound: dict[int, tuple] = {}
        self.posed_at: dict[int, float] = {}  # monotonic time of each robot's last pose taken
        self.stamps: dict[int, float] = {}  # each robot's last pose's "time" (with a token)
        self.contested: dict[int, float] = {}  # when another address last reported a robot
        # Other addresses that reported a robot (contenders, its former address): they get its
        # stops (halt), never its drive commands.
        self.also_at: dict[int, OrderedDict] = {}
        self.peers: OrderedDict = OrderedDict()  # other senders of states (the exit stop too)
        self.stale_logged = np.zeros(self.n, bool)
        # The team: the robot id in each place (None: unclaimed), and robots outside it.
        self.slot_id: list[int | None] = [None] * self.n
        self.slot_of: dict[int, int] = {}
        self.outside: OrderedDict[int, dict] = OrderedDict()  # left ("stale") or "team full"
        self._first_state_at: float | None = None
        self.stats = _new_stats()
        self.halted: str | None = None  # why every robot was last sent a stop (None: commanding)
        self.stop_cause: str | None = None  # what ended serve() (a signal's name, an error)
        self._received_at = None
        self._last: dict[int, dict] = {}  # each robot's entry in the last command message
        self._command_times: deque = deque(maxlen=4096)  # monotonic times of recent commands
        self._first_command_at = self._last_command_at = None
        self._refusals, self._failures, self._full = Throttle(), Throttle(), Throttle()
        self._joins, self._leaves, self._stale = Throttle(), Throttle(), Throttle()
        self._contests, self._moves = Throttle(), Throttle()
        self._closed = False
        self.on_command = None  # called with each command message (e.g. the live page)

    # ------------------------------------------------------------------ datagrams in
    def handle(self, data: bytes, sender) -> None:
        """One datagram: update the measured state, or pass an instruction to the live loop; a
        datagram that cannot be used is refused (counted and logged), never raised."""
        try:
            if self.token is not None:
                self._screen(data, sender)
            msg = wire.parse_message(data)
            if self.token is not None:
                self._check_token(msg, sender)
            if msg["type"] == "instruct":
                self.loop.instruct(msg["text"])
            else:
                self._apply_state(msg, sender)
        except wire.ProtocolError as err:
            self._refuse(sender, len(data), err.kind, str(err))
            return
        except Exception as err:  # the loop refusing it (no planner), or a bug: never a crash
            self._refuse(sender, len(data), "not applied", f"{type(err).__name__}: {err}")
            return
        self.stats["messages"] += 1

    def _screen(self, data, sender) -> None:
        """With ``token``, refuse unparsed a datagram that does not hold the token's bytes (a
        flood of wrong tokens costs a byte search each, not a JSON parse); one that holds none
        at all counts as a wrong token (limited, :class:`~icco_torchrl.live.guard.TokenCheck`)."""
        if not isinstance(data, (bytes, bytearray)) or len(data) > wire.MAX_MESSAGE:
            return  # parse_message refuses it
        if self.token.spelled_in(data):
            return
        if b"token" not in data:
            raise wire.ProtocolError(
                'no "token": live.token is set, so every state and instruct datagram must carry it',
                "token",
            )
        refusal = self.token.check(None, _source(sender), peer=sender)
        raise wire.ProtocolError(f"{refusal} (live.token)", "token")

    def _check_token(self, msg: dict, sender) -> None:
        """With ``token``, a datagram must carry it (``"token"``); wrong ones are limited, but
        never for an address that gave the right one (its robots keep being heard)."""
        given = msg.get("token")
        if given is None:
            raise wire.ProtocolError(
                'no "token": live.token is set, so every state and instruct datagram must carry it',
                "token",
            )
        refusal = self.token.check(given, _source(sender), peer=sender)
        if refusal is not None:
            raise wire.ProtocolError(f"{refusal} (live.token)", "token")

    def _check_fresh(self, robots: list, stamp) -> None:
        """With ``token``, a state's ``time`` must be after the last one taken for each robot it
        lists: a replayed datagram is refused (kind ``replay``) before it changes anything."""
        if stamp is None:
            raise wire.ProtocolError(
                "no 'time': live.token is set, so every state must carry a time that grows "
                "(a replayed state could not be told apart)",
                "replay",
            )
        for r in robots:
            last = self.stamps.get(r["id"])
            if last is not None and stamp <= last:
                raise wire.ProtocolError(
                    f"robot {r['id']}: time {stamp!r} is not after its last state's {last!r} "
                    "(a replayed state?)",
                    "replay",
                )

    def _apply_state(self, msg: dict, sender) -> None:
        robots, stamp = msg.get("robots", []), msg.get("time")
        if self.token is not None:
            self._check_fresh(robots, stamp)
        now = time.monotonic()
        if self._first_state_at is None:
            self._first_state_at = now
        posed = contested = False  # whether it gave a known robot's pose; named one not its own
        for r in robots:
            rid, pose = r["id"], np.asarray(r["pose"], float)
            if not self._from_its_address(rid, sender, now):
                contested = True
                continue
            i = self.slot_of.get(rid)
            if i is None:
                i = self._join(rid, pose, now)
            if rid in self.slot_of or rid in self.outside:
                self.bound.setdefault(rid, sender)
                self.posed_at[rid] = now
                if stamp is not None:
                    self.stamps[rid] = stamp
                posed = True
            if i is None:
                continue
            if np.isfinite(self.seen[i]) and now > self.seen[i]:
                self.velocity[i] = (pose[:2] - self.poses[i, :2]) / (now - self.seen[i])
            self.poses[i], self.seen[i] = pose, now
            self.stale_logged[i] = False
        if not contested:  # a contender's field is not taken either
            if "resources" in msg:
                self.resources = np.asarray(msg["resources"], float).reshape(-1, 2)
            if "invader" in msg:
                self.invader = np.asarray(msg["invader"], float).reshape(-1, 2)
        if posed or contested:
            self.peers.pop(sender, None)
            if posed:
                self.reply_to, self._received_at = sender, time.perf_counter()
        else:  # a state with no robot: an address for the exit stop, after the robots'
            self.peers[sender] = now
            self.peers.move_to_end(sender)
            while len(self.peers) > MAX_PEERS:
                self.peers.popitem(last=False)

    def _from_its_address(self, rid: int, sender, now: float) -> bool:
        """Whether robot ``rid``'s pose from ``sender`` may be taken: from the address it is
        bound to (or any, while it has none). From another one it is refused and the robot is
        contested (stopped for ``timeout`` s, logged), unless the robot's own address has been
        silent for ``timeout`` s and nobody contested it meanwhile: then it moved there (a
        restarted sender), said in a line."""
        bound = self.bound.get(rid)
        if bound is None or bound == sender:
            return True
        silent = now - self.posed_at.get(rid, -np.inf)
        if silent > self.timeout and now - self.contested.get(rid, -np.inf) > self.timeout:
            self._also(rid, bound)
            self.bound[rid] = sender
            self.also_at[rid].pop(sender, None)
            self.stats["moved"] += 1
            due, n = self._moves.due()
            if due:
                log.warning(
                    "bridge: robot %d is now reported from %s (was %s, silent for %.2f s): its "
                    "commands go there%s",
                    rid,
                    _peer(sender),
                    _peer(bound),
                    silent,
                    held(n),
                )
            return True
        self.contested[rid] = now
        self._also(rid, sender)
        self.stats["contested"] += 1
        due, n = self._contests.due()
        if due:
            log.warning(
                "bridge: robot %d reported from %s, not from its address %s: its pose is not "
                "taken and it is stopped (contested)%s",
                rid,
                _peer(sender),
                _peer(bound),
                held(n),
            )
        return False

    def _also(self, rid: int, address) -> None:
        """Another address that reported robot ``rid`` (``ROBOT_ADDRESSES`` at most, the most
        recent): it gets the robot's stops."""
        addresses = self.also_at.setdefault(rid, OrderedDict())
        addresses[address] = None
        addresses.move_to_end(address)
        while len(addresses) > ROBOT_ADDRESSES:
            addresses.popitem(last=False)

    def addresses(self) -> list:
        """Where commands go: the address of each robot a command lists (the team's first),
        without repeats."""
        out: dict = {}
        for rid in [*self.team(), *self.outside]:
            address = self.bound.get(rid)
            if address is not None:
                out.setdefault(address, None)
        return list(out)

    def _other_addresses(self, own: list) -> list:
        """The other addresses that reported the robots a command lists (not in ``own``)."""
        mine, out = set(own), {}
        for rid in [*self.team(), *self.outside]:
            for address in reversed(self.also_at.get(rid, ())):
                if address not in mine:
                    out.setdefault(address, None)
        return list(out)

    # ------------------------------------------------------------------ the team
    def team(self) -> list[int]:
        """The ids of the robots in the team (claimed places), sorted."""
        return sorted(self.slot_of)

    def _place_for(self, rid: int) -> int | None:
        """A free place for robot ``rid``: its own index, the place it had, a place of the loop's
        team nobody claimed, then any free one; None when the team is full."""
        free = [i for i in range(self.n) if self.slot_id[i] is None]
        if not free:
            return None
        team = set(self.loop.team)
        before = self.outside.get(rid, {}).get("slot")
        for choice in (rid, before):
            if choice in free:
                return choice
        unclaimed = [i for i in free if i in team]
        return (unclaimed or free)[0]

    def _join(self, rid: int, pose: np.ndarray, now: float) -> int | None:
        """Robot ``rid`` reported and is not in the team: give it a place (the loop adds it), or
        refuse it (known, stopped) when the team is full."""
        i = self._place_for(rid)
        if i is None:  # a silent robot may be due to leave: its place is this one's
            self._leave(now)
            i = self._place_for(rid)
        if i is None:
            known = self.outside.pop(rid, None)
            if known is None or known["reason"] != "team full":
                self.stats["refused_robots"] += 1
                due, n = self._full.due()
                if due:
                    log.warning(
                        "bridge: robot %d refused: the team is full (%d robots, live.max_robots); "
                        "it is sent stop commands%s",
                        rid,
                        self.n,
                        held(n),
                    )
            self._remember(rid, {"reason": "team full", "pose": pose, "seen": now, "slot": None})
            return None
        if i not in self.loop.team:
            self.loop.add_robot(i)
        self.outside.pop(rid, None)
        self.slot_id[i], self.slot_of[rid] = rid, i
        self.seen[i], self.velocity[i], self.command[i] = -np.inf, 0.0, 0.0
        self.stats["joined"] += 1
        due, n = self._joins.due()
        if due:
            log.info(
                "bridge: robot %d joined the team (team: %s)%s",
                rid,
                one_line(_ids(self.team()), 120),
                held(n),
            )
        return i

    def _remember(self, rid: int, entry: dict) -> None:
        """Keep ``rid`` known outside the team (the ``MAX_KNOWN`` most recent)."""
        self.outside[rid] = entry
        self.outside.move_to_end(rid)
        while len(self.outside) > MAX_KNOWN:
            forgotten, _ = self.outside.popitem(last=False)
            for addresses in (self.bound, self.posed_at, self.stamps, self.contested, self.also_at):
                addresses.pop(forgotten, None)

    def _leave(self, now: float) -> None:
        """Robots silent for ``timeout`` s leave the team (the last one stays); after ``timeout``
        s of states, places of the loop's team nobody claimed leave it too."""
        team = self.loop.team
        for i in list(team):
            rid = self.slot_id[i]
            if now - self.seen[i] <= self.timeout:
                continue
            if rid is None and (
                self._first_state_at is None or now - self._first_state_at <= self.timeout
            ):
                continue  # a place waiting for its robot's first pose
            if len(self.loop.team) == 1:
                return  # a team keeps one robot: it stays, stopped as stale
            self.loop.remove_robot(i)
            if rid is None:
                continue
            self.slot_id[i] = None
            del self.slot_of[rid]
            target = self._last.get(rid, {}).get("target")
            entry = {"reason": "stale", "pose": self.poses[i].copy(), "seen": self.seen[i]}
            self._remember(rid, {**entry, "slot": i, "target": target})
            self.stats["dropped"] += 1
            if not self.stale_logged[i]:
                self.stats["stale_stops"] += 1
            due, n = self._leaves.due()
            if due:
                log.warning(
                    "bridge: robot %d sent no pose for %.2f s: stopped and out of the team "
                    "(team: %s)%s",
                    rid,
                    now - self.seen[i],
                    one_line(_ids(self.team()), 120) or "none",
                    held(n),
                )
            self.command[i], self.stale_logged[i] = 0.0, False

    def _listed(self) -> list[tuple[int, int | None]]:
        """``(id, place)`` of every robot a command lists: the team (a place nobody claimed by
        its index, unless a known robot has that id) and the known robots outside it (place
        None), by id."""
        known = set(self.slot_of) | set(self.outside)
        listed = []
        for i in self.loop.team:
            rid = self.slot_id[i]
            if rid is None and i in known:
                continue
            listed.append((i if rid is None else rid, i))
        listed += [(rid, None) for rid in self.outside]
        return sorted(listed, key=lambda pair: pair[0])

    def _refuse(self, sender, size: int, kind: str, reason: str) -> None:
        """Count a refused datagram and log it in one bounded line (at most one per LOG_EVERY)."""
        self.stats["malformed"] += 1
        by = self.stats["refused_by"]
        by[kind] = by.get(kind, 0) + 1
        due, n = self._refusals.due()
        if due:
            log.warning(
                "bridge: refused a datagram from %s (%d bytes, %s): %s%s",
                _peer(sender),
                size,
                kind,
                one_line(reason),
                held(n),
            )

    # ------------------------------------------------------------------ commands out
    def control(self) -> dict | None:
        """One control tick: the policy's targets and DWA commands; stale robots stopped."""
        if not self.bound:
            return None
        now = time.monotonic()
        self._leave(now)
        resources = (
            self.resources
            if self.resources is not None and len(self.resources) == self.loop.raw.n_resources
            else None
        )
        _, targets = self.loop.act_on(
            self.poses[:, :2], velocities=self.velocity, resources=resources, invader=self.invader
        )
        robots, command = self._entries(now, targets)
        message = wire.command_message(robots)
        data = wire.encode(message)
        for address in self.addresses():
            try:
                self.sock.sendto(data, address)
            except OSError as err:  # one unreachable address must not keep the others waiting
                self._failed(f"command to {_peer(address)}", err)
        self.command, self._last, self.halted = command, {r["id"]: r for r in robots}, None
        self._count_command()
        self._tell(message)
        return message

    def _entries(self, now: float, targets: np.ndarray) -> tuple[list[dict], np.ndarray]:
        """Each listed robot's command entry toward its target (a DWA command, or a stop for a
        stale or contested robot or one outside the team), and the ``(v, w)`` of each place."""
        robots, command = [], np.zeros_like(self.command)
        listed = self._listed()
        fresh = now - self.seen <= self.timeout
        nearby = [  # robots to keep clear of: the team's fresh ones and refused ones standing by
            *((i, self.poses[i, :2]) for _, i in listed if i is not None and fresh[i]),
            *(
                (None, e["pose"][:2])
                for e in self.outside.values()
                if now - e["seen"] <= self.timeout
            ),
        ]
        for rid, i in listed:
            if i is None:
                entry = self.outside[rid]
                target = entry.get("target") or entry["pose"][:2].tolist()
                robots.append(wire.stop(rid, target, entry["reason"]))
            elif not fresh[i]:
                self._stale_stop(rid, i, now)
                robots.append(wire.stop(rid, targets[i].tolist(), "stale"))
            elif now - self.contested.get(rid, -np.inf) <= self.timeout:
                robots.append(wire.stop(rid, targets[i].tolist(), "contested"))
            else:
                others = np.asarray([p for j, p in nearby if j != i], float).reshape(-1, 2)
                v, w = dwa_command(
                    self.poses[i],
                    self.command[i],
                    targets[i],
                    self.limits,
                    1.0 / self.rate_hz,
                    others=others,
                )
                command[i] = (v, w)
                robots.append(wire.drive(rid, targets[i].tolist(), v, w))
        return robots, command

    def _stale_stop(self, rid: int, i: int, now: float) -> None:
        """Robot ``rid`` (place ``i``) sent no pose for ``timeout`` s: counted and logged once."""
        if self.stale_logged[i]:
            return
        due, n = self._stale.due()
        if due:
            log.warning(
                "bridge: robot %d sent no pose for %.2f s: stopping it%s",
                rid,
                now - self.seen[i],
                held(n),
            )
        self.stale_logged[i] = True
        self.stats["stale_stops"] += 1

    def _count_command(self) -> None:
        """A command went out: counted, timed (the rates) and, after a state, its latency."""
        self.stats["commands"] += 1
        stamp = time.monotonic()
        self._command_times.append(stamp)
        self._last_command_at = stamp
        if self._first_command_at is None:
            self._first_command_at = stamp
        if self._received_at is not None:
            self.stats["latency_ms"].append((time.perf_counter() - self._received_at) * 1e3)
            self._received_at = None

    def halt(self, reason: str = "bridge stopped", repeats: int = STOP_REPEATS) -> dict:
        """Send every robot a stop command (``v = w = 0``, ``"stopped": true``, ``reason``) at its
        own address first (where each robot the bridge knows is bound), then at the other
        addresses that reported them, then at the other senders of states (``repeats`` copies,
        10 ms apart); returns the message."""
        robots = []
        for rid, i in self._listed():
            last = self.poses[i, :2].tolist() if i is not None else self.outside[rid]["pose"][:2]
            target = self._last.get(rid, {}).get("target") or list(map(float, last))
            robots.append(wire.stop(rid, target, reason))
        message = wire.command_message(robots)
        data = wire.encode(message)
        own = self.addresses() if not self._closed else []
        also = self._other_addresses(own) if not self._closed else []
        mine = set(own) | set(also)
        others = [p for p in self.peers if p not in mine] if not self._closed else []
        peers = own + also + others  # the robots' own addresses first, in every round
        delivered = 0
        for k in range(repeats if peers else 0):
            if k:
                time.sleep(0.01)
            for peer in peers:
                try:
                    self.sock.sendto(data, peer)
                    delivered += 1
                except OSError as err:  # the next address still gets its copy
                    self._failed(f"stop command to {_peer(peer)}", err)
        if self.halted != reason and peers:
            extra = []
            if also:
                extra.append(
                    f"{len(also)} other address{'es' * (len(also) > 1)} that reported them"
                )
            if others:
                extra.append(f"{len(others)} other sender{'s' * (len(others) > 1)} of states")
            tail = (
                ", " + " and ".join(extra)
                if len(extra) == 2
                else "".join(" and " + e for e in extra)
            )
            log.warning(
                "bridge: sent a stop command (v = w = 0) to all %d robots at %d address%s%s (%s)",
                len(robots),
                len(own),
                "" if len(own) == 1 else "es",
                tail,
                reason,
            )
        self.command[:] = 0.0
        self._last = {r["id"]: r for r in robots}
        self.halted = reason
        if delivered:
            self.stats["stops_sent"] += 1
        self._tell(message)
        return message

    def _tell(self, message: dict) -> None:
        if self.on_command is None:
            return
        try:
            self.on_command(message)
        except Exception as err:  # a watcher (the page) must not stop the robots' commands
            log.error("bridge: on_command failed: %s", one_line(f"{type(err).__name__}: {err}"))

    def actual_rate(self) -> float | None:
        """Commands per second over the last ``RATE_WINDOW`` seconds (or three periods, if
        longer): None before the first two commands, 0 when none was sent in that window."""
        times, now = self._command_times, time.monotonic()
        window = max(RATE_WINDOW, 3.0 / self.rate_hz)
        while times and now - times[0] > window:
            times.popleft()
        if len(times) < 2:
            return None if self.stats["commands"] < 2 else 0.0
        span = times[-1] - times[0]
        return (len(times) - 1) / span if span > 0 else None

    def mean_rate(self) -> float | None:
        """Commands per second from the first command to the last (a run's actual rate)."""
        if self._first_command_at is None or self.stats["commands"] < 2:
            return None
        span = self._last_command_at - self._first_command_at
        return (self.stats["commands"] - 1) / span if span > 0 else None

    def fleet(self) -> dict:
        """The fleet as the bridge sees it, for the live page: each robot's last pose, how old it
        is, whether it is in the team (``in_team``, its ``slot`` in the env), its last command
        and whether it is stopped (and why); ``team`` (the ids in it) and ``max_robots``; the
        message counts, the nominal and the actual control rate, and ``halted`` (why every robot
        was stopped, or None)."""
        now = time.monotonic()
        robots = [self._robot_view(rid, i, now) for rid, i in self._listed()]
        s = self.stats
        latency = list(s["latency_ms"])[-50:]
        actual = 0.0 if self.halted else self.actual_rate()  # stopped: no command moves them
        return {
            "robots": robots,
            "address": f"udp {self.address[0]}:{self.address[1]}",
            "rate_hz": self.rate_hz,
            "actual_hz": None if actual is None else round(actual, 2),
            "halted": self.halted,
            "timeout_s": self.timeout,
            "messages": s["messages"],
            "commands": s["commands"],
            "malformed": s["malformed"],
            "stale_stops": s["stale_stops"],
            "contested": s["contested"],
            "moved": s["moved"],
            "team": self.team(),
            "max_robots": self.n,
            "joined": s["joined"],
            "dropped": s["dropped"],
            "refused_robots": s["refused_robots"],
            "latency_ms": float(np.median(latency)) if latency else None,
        }

    def _robot_view(self, rid: int, i: int | None, now: float) -> dict:
        """Robot ``rid`` (place ``i``, None outside the team) as :meth:`fleet` lists it."""
        if i is None:
            entry = self.outside[rid]
            pose, at, v, w = entry["pose"], entry["seen"], 0.0, 0.0
        else:
            pose, at, (v, w) = self.poses[i], self.seen[i], self.command[i]
        seen = bool(np.isfinite(at))
        default = {"stopped": True, "reason": "no command yet"}
        last = self._last.get(rid, default) if i is not None else None
        return {
            "id": rid,
            "slot": i,
            "in_team": i is not None,
            "pose": np.round(pose, 3).tolist() if seen else None,
            "age_s": round(float(now - at), 3) if seen else None,
            "v": float(v),
            "w": float(w),
            "stopped": True if last is None else bool(last["stopped"]),
            "reason": (self.halted or self.outside[rid]["reason"]) if last is None
            else last["reason"],
            "address": None if rid not in self.bound else _peer(self.bound[rid]),
        }  # fmt: skip

    # ------------------------------------------------------------------ serving
    def serve(self, stop: threading.Event, max_seconds: float | None = None) -> None:
        """Receive datagrams and send commands at ``rate_hz`` until ``stop`` is set (or
        ``max_seconds`` pass); then every robot is sent a stop command, however it ends (see the
        module docstring). In the main thread, SIGINT, SIGTERM and SIGHUP set ``stop`` while it
        runs (the previous handlers are put back after the stop command)."""
        period = 1.0 / self.rate_hz
        end = None if max_seconds is None else time.monotonic() + max_seconds
        next_tick = time.monotonic() + period
        self.stop_cause = None
        previous = self._trap_signals(stop)
        try:
            while not stop.is_set() and (end is None or time.monotonic() < end):
                self._receive(max(1e-3, next_tick - time.monotonic()), period)
                now = time.monotonic()
                if now >= next_tick:  # late ticks are not made up for: at most one at once
                    next_tick = max(next_tick + period, now)
                    try:
                        self.control()
                    except Exception as err:  # a bad tick must not end the bridge: stop robots
                        self.stats["control_errors"] += 1
                        self._failed("control tick", err)
                        self.halt("control error", repeats=1)
            if self.stop_cause is None:
                self.stop_cause = "stopped" if stop.is_set() else "max_seconds ran out"
        except BaseException as err:
            self.stop_cause = one_line(f"{type(err).__name__}: {err}")
            raise
        finally:
            try:
                log.info("bridge: ending (%s)", self.stop_cause)
                self.halt("bridge stopped")
            finally:
                self._restore_signals(previous)

    def _receive(self, timeout: float, period: float) -> None:
        """Handle the datagrams that arrive within ``timeout`` seconds: the first one waited for,
        then those already queued (at most ``MAX_BATCH``)."""
        self.sock.settimeout(timeout)
        for _ in range(MAX_BATCH):
            try:
                data, sender = self.sock.recvfrom(wire.MAX_MESSAGE + 1)
            except (TimeoutError, BlockingIOError):
                return
            except OSError as err:  # e.g. an ICMP error reported on the socket: go on
                self._failed("receive", err)
                time.sleep(min(period, 0.01))
                return
            self.handle(data, sender)
            self.sock.settimeout(0)

    def _failed(self, what: str, err: Exception) -> None:
        due, n = self._failures.due()
        if due:
            log.error(
                "bridge: %s failed: %s%s",
                what,
                one_line(f"{type(err).__name__}: {err}"),
                held(n),
            )

    def _trap_signals(self, stop: threading.Event) -> dict:
        if threading.current_thread() is not threading.main_thread():
            return {}

        def on_signal(signum, _frame):
            self.stop_cause = signal.Signals(signum).name
            stop.set()

        return {sig: signal.signal(sig, on_signal) for sig in STOP_SIGNALS}

    @staticmethod
    def _restore_signals(previous: dict) -> None:
        for sig, handler in previous.items():
            signal.signal(sig, handler if handler is not None else signal.SIG_DFL)

    def close(self) -> None:
        """Stop every robot (unless the last thing sent was already that stop) and close the
        socket; closing twice is harmless."""
        if self._closed:
            return
        try:
            if self.halted != "bridge stopped":
                self.halt("bridge stopped")
        finally:
            self._closed = True
            self.sock.close()
