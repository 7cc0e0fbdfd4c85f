"""Hostile probes against the bridge (issue 50): robots reported from other ports, a captured
datagram replayed, wrong tokens from the robots' own IP (docs/live.md, "Bridge safety contract").

Everything runs over 127.0.0.1, every loop bounded by a count or a deadline.
"""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import time

from test_bridge_safety import _bridge, _crowd, _moving, _Robots, _serving, _stops_all, _wait

TOKEN = "udp-s3cret-token"


class _TokenRobots(_Robots):
    """Robots 0-2 whose states carry ``token`` and a growing ``time``, as the simulated fleet's."""

    def __init__(self, bridge_address, token: str = TOKEN):
        super().__init__(bridge_address)
        self.token = token

    def datagram(self) -> bytes:
        robots = [{"id": i, "pose": [0.9 * i - 0.9, -0.5, 0.1]} for i in self.ids]
        msg = {"type": "state", "time": time.time(), "robots": robots, "token": self.token}
        return json.dumps(msg).encode()

    def state(self) -> None:
        self.sock.sendto(self.datagram(), self.bridge)


def _drain(sock: socket.socket) -> list[dict]:
    """The datagrams already queued on ``sock`` (none waited for)."""
    got = []
    sock.setblocking(False)
    with contextlib.suppress(BlockingIOError):
        for _ in range(100_000):
            got.append(json.loads(sock.recvfrom(65_507)[0]))
    return got


def _stop_lines(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records if "sent a stop command" in r.getMessage()]


# ---------------------------------------------------------------------- spoofed robots
def test_senders_naming_the_robots_are_contested_never_given_their_commands(caplog):
    """Eight other ports report robots 0-2 right after each of the robots' own datagrams (no
    token, the default): the robots stay bound to the address that reported them first, are
    stopped as contested and keep hearing every command there, and get every copy of the exit
    stop; the spoofers get no drive command, only stops."""
    caplog.set_level(logging.INFO, logger="icco.bridge")
    bridge = _bridge()
    robots, spoofers = _Robots(bridge.address), _crowd(8)
    spoof = [{"id": i, "pose": [2.0, 2.0 + i, 0.0]} for i in range(3)]
    spoofed = json.dumps({"type": "state", "time": time.time(), "robots": spoof}).encode()
    try:
        with _serving(bridge) as (_, errors, thread):
            assert _moving(robots.drive(0.3)), "no command before the spoofers"
            got, end = [], time.monotonic() + 1.0
            while time.monotonic() < end:
                robots.state()
                for sock in spoofers:
                    sock.sendto(spoofed, bridge.address)
                got += [(time.monotonic(), m) for m in robots.receive(0.05)]
            last = [m for t, m in got if t >= end - 0.3]
            assert len(last) >= 3, "the robots' own address got no command in the last 0.3 s"
            assert all(_stops_all(m, "contested") for m in last), last[-1]
            assert bridge.poses[:3, 1].tolist() == [-0.5] * 3  # the spoofed poses were not taken
            fleet = bridge.fleet()
            assert fleet["contested"] > 0 and all(
                r["reason"] == "contested" for r in fleet["robots"]
            )
            for sock in spoofers:  # nothing for the spoofers while serving
                assert _drain(sock) == []
            # The spoofers go: after live.timeout_s the robots are commanded again, there.
            assert _moving(robots.drive(1.2)[-5:])
            robots.commands.clear()
            assert thread.is_alive() and not errors
        robots.receive(0.2)
        assert len([m for m in robots.commands if _stops_all(m, "bridge stopped")]) == 3
        for sock in spoofers:  # the exit stop reaches every address that named a robot, too
            stops = _drain(sock)
            assert len(stops) == 3 and all(_stops_all(m, "bridge stopped") for m in stops)
        assert _stop_lines(caplog) == [
            "bridge: sent a stop command (v = w = 0) to all 3 robots at 1 address and 8 other "
            "addresses that reported them (bridge stopped)"
        ]
        lines = [r.getMessage() for r in caplog.records if "contested" in r.getMessage()]
        assert lines and len(lines) <= 4 and all(len(line) <= 300 for line in lines)
        assert "not from its address 127.0.0.1:" in lines[0]
    finally:
        robots.close()
        for sock in spoofers:
            sock.close()


def test_a_captured_datagram_replayed_is_refused_and_the_robots_keep_going(caplog):
    """With a token, one captured datagram of the robots replayed from eight other ports and from
    the robots' own address: refused as replays (their time is not after the robot's last), so
    it neither contests nor moves the robots, and every command still reaches them."""
    caplog.set_level(logging.INFO, logger="icco.bridge")
    bridge = _bridge(token=TOKEN)
    robots, spoofers = _TokenRobots(bridge.address), _crowd(8)
    captured = robots.datagram()
    try:
        with _serving(bridge) as (_, errors, thread):
            assert _moving(robots.drive(0.3)), "no command before the replays"
            got, end = [], time.monotonic() + 1.0
            while time.monotonic() < end:
                robots.state()
                robots.send(captured)
                for sock in spoofers:
                    sock.sendto(captured, bridge.address)
                got += [(time.monotonic(), m) for m in robots.receive(0.05)]
            last = [m for t, m in got if t >= end - 0.3]
            assert len(last) >= 3 and all(_moving([m]) for m in last), last[-1:]
            assert bridge.stats["refused_by"].get("replay", 0) >= 9 * 10
            assert bridge.fleet()["contested"] == 0
            assert all(_drain(sock) == [] for sock in spoofers)
            # A state without "time" cannot be told from a replay: refused too.
            refused = bridge.stats["refused_by"]["replay"]
            untimed = {"type": "state", "robots": [], "token": TOKEN}
            robots.send(json.dumps(untimed).encode())
            assert _wait(lambda: bridge.stats["refused_by"]["replay"] == refused + 1)
            assert thread.is_alive() and not errors
            robots.commands.clear()
        robots.receive(0.2)
        assert len([m for m in robots.commands if _stops_all(m, "bridge stopped")]) == 3
        assert all(_drain(sock) == [] for sock in spoofers)  # refused: no address of anyone's
    finally:
        robots.close()
        for sock in spoofers:
            sock.close()


def test_a_silent_robot_may_move_to_a_new_address_said_in_a_line(caplog):
    """A robot's sender restarts on another port (its old one silent for live.timeout_s): the
    robot is bound to the new one, and the line says so; its old address still gets the exit
    stop, and reporting again from it contests the robot."""
    caplog.set_level(logging.INFO, logger="icco.bridge")
    bridge = _bridge()
    old, new = _Robots(bridge.address), _Robots(bridge.address)
    try:
        with _serving(bridge) as (_, errors, thread):
            assert _moving(old.drive(0.3))
            time.sleep(0.7)  # old goes silent past live.timeout_s (0.5 s): stopped
            assert _moving(new.drive(0.6)[-3:])
            heard = _drain(old.sock)  # its stale stops; nothing since the robots moved
            assert heard and all(r["stopped"] for r in heard[-1]["robots"])
            time.sleep(0.1)
            assert _drain(old.sock) == []
            lines = [r.getMessage() for r in caplog.records if "now reported from" in r.message]
            assert lines and "was 127.0.0.1:" in lines[0]
            # The old address reports again: the robots are contested, stopped at the new one.
            end, got = time.monotonic() + 0.4, []
            while time.monotonic() < end:
                old.state()
                got += new.drive(0.05)
            assert got and _stops_all(got[-1], "contested")
            new.commands.clear()
            assert thread.is_alive() and not errors
        new.receive(0.2)
        assert len([m for m in new.commands if _stops_all(m, "bridge stopped")]) == 3
        old_stops = [m for m in _drain(old.sock) if _stops_all(m, "bridge stopped")]
        assert len(old_stops) == 3
    finally:
        old.close()
        new.close()


# ---------------------------------------------------------------------- wrong tokens
def test_wrong_tokens_from_the_robots_own_ip_do_not_stop_the_fleet():
    """A guesser on the robots' IP (127.0.0.1) sends thousands of wrong tokens: they are refused
    (the guesses still limited), and the robots, whose right token the bridge already knows from
    their address, are commanded throughout: no stale stop."""
    bridge = _bridge(token=TOKEN)
    robots = _TokenRobots(bridge.address)
    guesser = _crowd(1)[0]
    robots_state = json.loads(robots.datagram())
    try:
        with _serving(bridge) as (_, errors, thread):
            assert _moving(robots.drive(0.3))
            got, end, k = [], time.monotonic() + 1.2, 0
            while time.monotonic() < end:
                robots.state()
                for _ in range(20):
                    k += 1
                    wrong = {**robots_state, "time": time.time(), "token": f"guess-{k}"}
                    guesser.sendto(json.dumps(wrong).encode(), bridge.address)
                got += [(time.monotonic(), m) for m in robots.receive(0.05)]
            assert bridge.stats["stale_stops"] == 0 and bridge.team() == [0, 1, 2]
            assert all(_moving([m]) for t, m in got), [m for _, m in got if not _moving([m])][:1]
            assert len([m for t, m in got if t >= end - 0.3]) >= 3
            assert bridge.stats["refused_by"]["token"] >= 200
            assert bridge.token.unchecked > 0  # the guesser's IP is over its limit
            assert bridge.token.guesses <= 25 + 10 * 1.5
            assert thread.is_alive() and not errors
    finally:
        robots.close()
        guesser.close()


def test_a_datagram_without_the_token_is_refused_before_it_is_parsed(monkeypatch):
    """Without the token's bytes in it a datagram is refused unparsed (cheap under a flood)."""
    from icco_torchrl.live import wire

    bridge = _bridge(token=TOKEN)
    parsed = []
    parse = wire.parse_message
    monkeypatch.setattr(wire, "parse_message", lambda data: parsed.append(1) or parse(data))
    try:
        deep = b'{"token": "guess", "robots": ' + b"[" * 8_000 + b"]" * 8_000 + b"}"
        for data in (deep, b"{" * 100, json.dumps({"type": "state", "token": "x"}).encode()):
            bridge.handle(data, ("127.0.0.1", 9))
        assert parsed == [] and bridge.stats["refused_by"] == {"token": 3}
        bridge.handle(json.dumps({"type": "state", "token": TOKEN}).encode(), ("127.0.0.1", 9))
        assert parsed == [1]  # the token's bytes: parsed (and refused for its missing time)
    finally:
        bridge.close()
