"""Language layer: offline rule planner, prompts, litellm path, validation, fallbacks, cache.

No test touches a network: replies come from litellm's ``mock_response`` (:func:`replying`), from
custom providers registered in ``litellm.custom_provider_map``, or from a fake
OpenAI-compatible server on 127.0.0.1 (``fake_openai.py``).
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import threading
import time
from pathlib import Path
from typing import Any
from unittest import mock

import numpy as np
import pytest
from fake_openai import FakeOpenAI, closed_port

from icco_torchrl.instructions import llm
from icco_torchrl.instructions.llm import (
    LLMPlanner,
    LLMUnavailable,
    ReplyError,
    build_messages,
    last_json_object,
    parse_reply,
    plan_waypoints,
    response_format,
)
from icco_torchrl.instructions.planner import DEFAULT_MODEL, register_offline_provider, rule_plan
from icco_torchrl.training.build import compose_config

HALF = 3.25
K = 4
CONF = Path(__file__).resolve().parents[1] / "conf" / "llm"


@pytest.fixture(scope="module")
def litellm() -> Any:
    """litellm imported once (seconds), offline, with the rule planner registered."""
    os.environ.setdefault("LITELLM_LOCAL_MODEL_COST_MAP", "True")
    import litellm as module

    register_offline_provider(module)
    return module


@pytest.fixture
def offline_handler(litellm: Any) -> Any:
    return next(
        e["custom_handler"] for e in litellm.custom_provider_map if e["provider"] == "offline"
    )


class Scripted:
    """A custom provider whose replies the test sets (for replies ``mock_response`` cannot
    express)."""

    def __init__(self, litellm: Any) -> None:
        from litellm import CustomLLM

        script = self

        class Handler(CustomLLM):
            def completion(self, *args: Any, **kwargs: Any) -> Any:
                script.requests.append(kwargs)
                message = {"role": "assistant", "content": script.replies.pop(0)}
                return litellm.ModelResponse(
                    choices=[{"index": 0, "finish_reason": "stop", "message": message}]
                )

        self.handler, self.replies, self.requests = Handler(), [], []


@pytest.fixture
def scripted(litellm: Any, monkeypatch: pytest.MonkeyPatch) -> Scripted:
    script = Scripted(litellm)
    entry = {"provider": "scripted", "custom_handler": script.handler}
    monkeypatch.setattr(litellm, "custom_provider_map", [*litellm.custom_provider_map, entry])
    return script


class Replying:
    """litellm with the replies a test sets: its own ``mock_response``, one a request, the last
    repeating (an exception is raised as the provider's error)."""

    def __init__(self, module: Any, replies: Any):
        self.module, self.requests = module, 0
        self.replies = list(replies) if isinstance(replies, (list, tuple)) else [replies]

    def __getattr__(self, name: str) -> Any:
        return getattr(self.module, name)

    def completion(self, **kwargs: Any) -> Any:
        reply = self.replies[min(self.requests, len(self.replies) - 1)]
        self.requests += 1
        return self.module.completion(**kwargs, mock_response=reply)


@contextlib.contextmanager
def replying(replies: Any):
    """Every planner's provider answers with ``replies`` (:class:`Replying`) in this block."""
    import litellm as module

    with mock.patch.object(llm, "_litellm", lambda: Replying(module, replies)):
        yield


def ask(planner: LLMPlanner, *args: Any, replies: Any, **kwargs: Any) -> Any:
    """``planner.plan(*args, **kwargs)``, its provider answering ``replies``."""
    with replying(replies):
        return planner.plan(*args, **kwargs)


def mocked(**settings: Any) -> LLMPlanner:
    """A planner for mock replies; its api_base is a closed local port, so a mock that
    litellm ignored would fail at once instead of reaching a real provider."""
    return LLMPlanner(
        model="openai/gpt-4o", api_base="http://127.0.0.1:9", backoff_s=0.0, **settings
    )


def starts(seed: int, n: int = 3, extent: float = 3.0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(-extent, extent, size=(n, 2))


def final(instruction: str, positions: np.ndarray, **context: Any) -> np.ndarray:
    return plan_waypoints(instruction, positions, n_waypoints=K, **context)[:, -1]


def pairwise(points: np.ndarray) -> np.ndarray:
    distances = np.linalg.norm(points[:, None] - points[None], axis=-1)
    return distances[np.triu_indices(len(points), k=1)]


def valid_reply(n: int = 3, value: float = 1.0, prose: str = "") -> str:
    body = {"movement_strategy": "s", **{f"agent_{i}": [[value, -value]] * K for i in range(n)}}
    return prose + json.dumps(body)


# --- the paper's four instructions ---------------------------------------------------------


@pytest.mark.parametrize("seed", range(5))
def test_go_right_is_a_vertical_line_on_the_right(seed: int) -> None:
    pos = starts(seed)
    end = final("Go right", pos)
    assert (end[:, 0] > 0.5 * HALF).all()
    assert np.ptp(end[:, 0]) < 1e-6 and pairwise(end[:, 1:]).min() > 1.0
    # agents keep their vertical order, so no paths cross
    assert (np.argsort(end[:, 1]) == np.argsort(pos[:, 1])).all()


@pytest.mark.parametrize("seed", range(5))
def test_move_top_is_a_horizontal_line_at_the_top(seed: int) -> None:
    pos = starts(seed)
    end = final("Move top", pos)
    assert (end[:, 1] > 0.5 * HALF).all()
    assert np.ptp(end[:, 1]) < 1e-6 and pairwise(end[:, :1]).min() > 1.0
    assert (np.argsort(end[:, 0]) == np.argsort(pos[:, 0])).all()


@pytest.mark.parametrize("seed", range(5))
def test_gather_center_converges_to_the_origin(seed: int) -> None:
    end = final("Gather center", starts(seed))
    assert (np.linalg.norm(end, axis=1) < 0.5).all()
    assert pairwise(end).min() > 0.3  # a tight cluster, not a pile-up (agent radius ~0.15 m)


@pytest.mark.parametrize("seed", range(5))
def test_spread_out_moves_agents_apart_and_away_from_the_centre(seed: int) -> None:
    pos = starts(seed, extent=1.5)
    end = final("Spread out", pos)
    assert pairwise(end).min() > 2.0
    assert pairwise(end).min() > pairwise(pos).max()
    assert (np.linalg.norm(end, axis=1) > np.linalg.norm(pos, axis=1)).all()


def test_waypoints_go_smoothly_from_the_agent_to_its_target() -> None:
    pos = starts(7)
    waypoints = plan_waypoints("Go right", pos, n_waypoints=K)
    assert waypoints.shape == (3, K, 2) and waypoints.dtype == np.float32
    steps = np.diff(np.concatenate([pos[:, None], waypoints], axis=1), axis=1)
    assert np.allclose(steps, steps[:, :1], atol=2e-3)  # equal steps along a straight segment
    first_step = np.linalg.norm(waypoints[:, 0] - pos, axis=1)
    assert (first_step <= np.linalg.norm(waypoints[:, -1] - pos, axis=1) / K + 1e-3).all()


# --- paraphrases, places, formations ------------------------------------------------------

PARAPHRASES = {
    "Go right": [
        "head to the right side",
        "Move right!",
        "everyone go east",
        "line up on the right",
    ],
    "Move top": ["everyone go up", "go to the top", "move up", "head north"],
    "Gather center": [
        "come together in the middle",
        "regroup at home",
        "converge on the centre",
        "go home",
    ],
    "Spread out": ["fan out", "disperse", "scatter", "spread apart from the center"],
    "go left": ["move to the left side", "head west"],
    "move down": ["go to the bottom", "everyone move downwards"],
}


@pytest.mark.parametrize(
    ("canonical", "paraphrase"), [(c, p) for c, ps in PARAPHRASES.items() for p in ps]
)
def test_paraphrases_give_the_canonical_formation(canonical: str, paraphrase: str) -> None:
    pos = starts(11)
    assert np.allclose(final(paraphrase, pos), final(canonical, pos), atol=1e-3)


def test_other_directions() -> None:
    pos = starts(3)
    assert (final("go left", pos)[:, 0] < -0.5 * HALF).all()
    assert (final("move to the bottom", pos)[:, 1] < -0.5 * HALF).all()
    top_right = final("go to the top right corner", pos)
    assert (top_right > 0.0).all() and (top_right.sum(axis=1) > HALF).all()
    assert (final("head south-west", pos) < 0.0).all()


@pytest.mark.parametrize(
    ("instruction", "signs"),
    [("go to quadrant 1", (1, 1)), ("go to quadrant 2", (-1, 1)),
     ("move into the third quadrant", (-1, -1)), ("quadrant IV", (1, -1))],
)  # fmt: skip
def test_quadrants_follow_the_maths_convention(instruction: str, signs: tuple[int, int]) -> None:
    end = final(instruction, starts(5))
    assert (end * np.asarray(signs) > 0.0).all()


def test_named_point_and_formations() -> None:
    pos = starts(9)
    assert (np.linalg.norm(final("go to (1, -2)", pos) - [1.0, -2.0], axis=1) < 0.5).all()
    circle = final("form a circle", pos)
    assert np.allclose(np.linalg.norm(circle, axis=1), np.linalg.norm(circle, axis=1)[0], atol=1e-3)
    line = final("form a horizontal line", pos)
    assert np.ptp(line[:, 1]) < 1e-6 and pairwise(line[:, :1]).min() > 1.0
    assert np.allclose(final("hold position", pos), pos, atol=1e-3)


def test_task_orders_use_the_task_aligned_prompt() -> None:
    pos = np.array([[-2.0, -2.0], [2.0, 2.0], [2.5, -2.5]])
    resources = np.array([[-1.5, -1.5], [1.5, 1.8], [0.0, 3.0]])
    invader = np.array([[3.0, -3.0]])
    collect = final(
        "collect the resources", pos, prompt="tap", resources=resources, invader=invader
    )
    assert np.allclose(collect, resources, atol=1e-3)
    task = final("do the task", pos, prompt="tap", resources=resources, invader=invader)
    path = np.linspace(invader[0], [0.0, 0.0], 50)
    assert np.linalg.norm(path - task[2], axis=1).min() < 0.2  # the nearest agent intercepts
    with pytest.raises(ValueError, match="collect the resources"):
        final("collect the resources", pos)  # the plain prompt has no resource positions


@pytest.mark.parametrize("instruction", ["bake a cake", "don't go left", "go left and right", ""])
def test_unknown_instruction_raises_value_error_naming_it(instruction: str) -> None:
    with pytest.raises(ValueError) as error:
        plan_waypoints(instruction, starts(0))
    assert repr(instruction) in str(error.value)


def test_offline_planner_is_fast(litellm: Any) -> None:
    pos = starts(1)
    begin = time.perf_counter()
    for _ in range(100):
        rule_plan("Spread out", pos, n_waypoints=K, half=HALF)
    assert (time.perf_counter() - begin) / 100 < 0.005  # the rules alone: ~0.1 ms
    planner = LLMPlanner()
    planner.plan("Spread out", pos)  # warm-up: litellm's first call builds caches
    begin = time.perf_counter()
    for _ in range(50):
        planner.plan("Spread out", pos)
    assert (
        time.perf_counter() - begin
    ) / 50 < 0.025  # whole litellm round trip: ~4 ms on a quiet 2-core CPU, 13 ms loaded


def test_offline_results_are_clipped_to_the_field() -> None:
    waypoints = plan_waypoints("go to (10, -10)", starts(2))
    assert np.abs(waypoints).max() <= HALF
    assert np.allclose(waypoints[:, -1], [HALF, -HALF], atol=0.5)


# --- prompts and schema -----------------------------------------------------------------


def test_prompts_follow_the_paper() -> None:
    pos = starts(4)
    plain = build_messages("Go right", pos)[-1]["content"]
    for text in (
        "+x is right",
        "+y is up",
        "STRICTLY COMPLY with the following order",
        "Movement Strategy",
        "Trajectory Generation",
        "POSITIONS_JSON",
        '"Go right"',
        "[-3.25, 3.25]",
    ):
        assert text in plain
    assert "+5" not in plain and "invader" not in plain
    tap = build_messages(
        "Go right", pos, prompt="tap", resources=[[1.0, 2.0]], invader=[[3.0, 0.0]]
    )[-1]["content"]
    for text in (
        "collect resources",
        "defend home",
        "+5",
        "+1",
        "+4",
        "-4",
        "RESOURCES_JSON: [[1.0, 2.0]]",
        "INVADER_JSON: [[3.0, 0.0]]",
        "STRICTLY COMPLY",
    ):
        assert text in tap


def test_response_format_is_a_strict_schema_with_fixed_agent_keys(scripted: Scripted) -> None:
    """The request reaches the provider with our schema and settings, through litellm.completion."""
    scripted.replies = [valid_reply()]
    assert LLMPlanner(model="scripted/x", temperature=0.3).plan("Go right", starts(0)).ok
    params = scripted.requests[0]["optional_params"]
    assert params["temperature"] == 0.3
    assert params["response_format"]["json_schema"]["strict"] is True
    schema = params["response_format"]["json_schema"]["schema"]
    assert schema == response_format(3, K)["json_schema"]["schema"]
    assert schema["required"] == ["movement_strategy", "agent_0", "agent_1", "agent_2"]
    assert (
        schema["properties"]["agent_0"]["minItems"]
        == schema["properties"]["agent_0"]["maxItems"]
        == K
    )


def test_last_json_object_skips_prose_and_takes_the_last_object() -> None:
    text = 'Movement Strategy: go to {x, y}.\n```json\n{"a": {"b": 1}}\n```\nFinal: {"a": 2} thanks'
    assert last_json_object(text) == {"a": 2}
    assert last_json_object("no json here") is None


# --- litellm path: custom provider and mock responses -----------------------------------


def test_custom_provider_round_trip(litellm: Any) -> None:
    pos = starts(6)
    response = litellm.completion(
        model=DEFAULT_MODEL,
        messages=build_messages("Gather center", pos),
        response_format=response_format(3, K),
    )
    raw = response.choices[0].message.content
    assert "not an LLM" in json.loads(raw)["movement_strategy"]
    waypoints = parse_reply(raw, 3, K, 2 * HALF)
    assert (np.linalg.norm(waypoints[:, -1], axis=1) < 0.5).all()


def test_registration_is_idempotent_and_keeps_other_providers(
    litellm: Any, monkeypatch: pytest.MonkeyPatch
) -> None:
    other = {"provider": "someone-else", "custom_handler": object()}
    monkeypatch.setattr(litellm, "custom_provider_map", [other])
    first = register_offline_provider(litellm)
    assert register_offline_provider(litellm) is first
    assert [e["provider"] for e in litellm.custom_provider_map] == ["someone-else", "offline"]


def test_mock_string_with_prose_is_parsed(litellm: Any) -> None:
    planner = mocked()
    reply = valid_reply(
        value=1.5, prose="Movement Strategy: everyone to (1.5, -1.5).\nTrajectory Generation:\n"
    )
    result = ask(planner, "Go right", starts(0), replies=reply)
    assert result.ok and result.attempts == 1 and result.raw == reply and result.fallback is None
    assert np.allclose(result.waypoints, [1.5, -1.5])


def test_out_of_field_coordinates_are_clipped(litellm: Any) -> None:
    result = ask(mocked(), "Go right", starts(0), replies=valid_reply(value=7.0))
    assert result.ok and np.allclose(result.waypoints, [HALF, -HALF])


def _with(replace: str) -> str:
    return valid_reply().replace("[[1.0, -1.0], [1.0, -1.0], [1.0, -1.0], [1.0, -1.0]]", replace, 1)


BAD_REPLIES = {
    "not json": "Sure! The robots should go right.",
    "refusal": "I'm sorry, but I can't help with that.",
    "wrong shape": _with("[[1.0, -1.0], [1.0, -1.0]]"),
    "not pairs": _with("[1.0, 2.0, 3.0, 4.0]"),
    "wrong agent count": valid_reply(n=2),
    "extra agent": valid_reply(n=4),
    "nan": _with("[[NaN, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]"),
    "inf": _with("[[1e999, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]"),
    "absurd": _with("[[100.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, 0.0]]"),
    "string coordinates": _with('[["1", "2"], [0, 0], [0, 0], [0, 0]]'),
}


def _errors(litellm: Any) -> dict[str, BaseException]:
    return {
        "timeout": litellm.Timeout(
            message="request timed out", model="gpt-4o", llm_provider="openai"
        ),
        "provider error": litellm.APIConnectionError(
            message="refused", llm_provider="openai", model="gpt-4o"
        ),
        "server error": litellm.ServiceUnavailableError(
            message="overloaded", llm_provider="openai", model="gpt-4o"
        ),
    }


@pytest.mark.parametrize("case", [*BAD_REPLIES, "timeout", "provider error", "server error"])
@pytest.mark.parametrize("with_previous", [False, True])
def test_bad_output_is_retried_then_falls_back(
    litellm: Any, caplog: pytest.LogCaptureFixture, case: str, with_previous: bool
) -> None:
    mock = BAD_REPLIES.get(case) if case in BAD_REPLIES else _errors(litellm)[case]
    pos = starts(0)
    previous = np.full((3, K, 2), 0.5) if with_previous else None
    planner = mocked(
        max_retries=2, fallback_on_error=case not in BAD_REPLIES
    )  # no reply at all: opt in
    with caplog.at_level(logging.WARNING, logger="icco_torchrl.instructions.llm"):
        result = ask(planner, "Go right", pos, previous, replies=mock)
    assert not result.ok and result.attempts == 3 and result.error
    assert planner.stats == {
        "calls": 1,
        "backend_calls": 3,
        "failures": 3,
        "fallbacks": 1,
        "cache_hits": 0,
    }
    assert result.waypoints.shape == (3, K, 2) and result.waypoints.dtype == np.float32
    if with_previous:
        assert result.fallback == "previous" and np.allclose(result.waypoints, 0.5)
    else:
        assert result.fallback == "positions" and np.allclose(
            result.waypoints, pos[:, None].repeat(K, 1)
        )
    if isinstance(mock, str):
        assert result.raw == mock
        assert (
            caplog.text.count("raw reply: " + repr(mock)[:40]) == 3
        )  # each attempt logs the raw reply
    else:
        assert result.raw is None and type(mock).__name__ in result.error
    assert "falling back to " + result.fallback in caplog.text


def test_a_bad_reply_is_retried_until_a_good_one(litellm: Any) -> None:
    planner = mocked(max_retries=2)
    timeout = _errors(litellm)["timeout"]
    result = ask(planner, "Go right", starts(0), replies=["not json", timeout, valid_reply()])
    assert result.ok and result.attempts == 3 and np.allclose(result.waypoints, [1.0, -1.0])
    assert planner.stats["failures"] == 2 and planner.stats["fallbacks"] == 0


def test_mismatched_previous_falls_back_to_positions(litellm: Any) -> None:
    planner = mocked(max_retries=0)
    pos = starts(0)
    result = ask(planner, "Go right", pos, previous=np.zeros((2, K, 2)), replies="nope")
    assert result.fallback == "positions" and np.allclose(
        result.waypoints, pos[:, None].repeat(K, 1)
    )


def test_empty_replies_fall_back(scripted: Scripted) -> None:
    scripted.replies = ["", None, "   "]
    planner = LLMPlanner(model="scripted/x", max_retries=2)
    result = planner.plan("Go right", starts(0))
    assert not result.ok and result.fallback == "positions" and result.error == "empty reply"
    assert planner.stats["failures"] == 3 and planner.stats["fallbacks"] == 1


def test_retry_shows_the_model_its_mistake(scripted: Scripted) -> None:
    scripted.replies = ["The robots go right.", valid_reply()]
    result = LLMPlanner(model="scripted/x", max_retries=1).plan("Go right", starts(0))
    assert result.ok and result.attempts == 2
    retry = scripted.requests[1]["messages"]
    assert retry[-2] == {"role": "assistant", "content": "The robots go right."}
    assert "no JSON object" in retry[-1]["content"] and '"agent_2"' in retry[-1]["content"]


def test_other_backends_never_raise_on_bad_output(litellm: Any) -> None:
    pos = starts(0)
    with replying("garbage"):
        waypoints = plan_waypoints(
            "Go right", pos, backend="openai", api_base="http://127.0.0.1:9", max_retries=0
        )
    assert np.allclose(waypoints, pos[:, None].repeat(K, 1))


def test_offline_decline_is_not_retried(offline_handler: Any) -> None:
    planner, before = LLMPlanner(max_retries=2), offline_handler.invocations
    result = planner.plan("bake a cake", starts(0))
    assert not result.ok and result.fallback == "positions" and "bake a cake" in result.error
    assert offline_handler.invocations - before == 1 and planner.stats["failures"] == 1


# --- cache ----------------------------------------------------------------------------------


def test_cache_replays_without_calling_the_backend(offline_handler: Any, tmp_path: Path) -> None:
    pos = starts(8)
    planner = LLMPlanner(cache_dir=tmp_path)
    before = offline_handler.invocations
    first = planner.plan("Spread out", pos)
    second = planner.plan("Spread out", pos)
    replay = LLMPlanner(cache_dir=tmp_path).plan("Spread out", pos)  # a later evaluation
    assert offline_handler.invocations - before == 1
    assert not first.cached and second.cached and replay.cached and second.attempts == 0
    assert second.raw == first.raw == replay.raw and np.array_equal(
        second.waypoints, first.waypoints
    )
    assert planner.stats["cache_hits"] == 1 and planner.stats["backend_calls"] == 1
    assert len(list(tmp_path.glob("*.json"))) == 1

    planner.plan("Go right", pos)  # a different prompt is a different key
    assert offline_handler.invocations - before == 2 and len(list(tmp_path.glob("*.json"))) == 2


def test_failures_are_not_cached_and_cache_can_be_disabled(
    offline_handler: Any, tmp_path: Path
) -> None:
    planner = mocked(cache_dir=tmp_path, max_retries=0)
    assert not ask(planner, "Go right", starts(0), replies="garbage").ok
    assert list(tmp_path.glob("*.json")) == []
    uncached, before = LLMPlanner(cache_dir=None), offline_handler.invocations
    uncached.plan("Go right", starts(0))
    uncached.plan("Go right", starts(0))
    assert offline_handler.invocations - before == 2 and uncached.stats["cache_hits"] == 0


# --- configuration --------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["offline", "openai", "ollama"])
def test_llm_configs_are_commented_and_build_a_planner(name: str) -> None:
    path = CONF / f"{name}.yaml"
    for line in path.read_text().splitlines():
        assert not line.strip() or "#" in line, f"uncommented line in {path.name}: {line!r}"
    cfg = compose_config([f"llm={name}"]).llm  # the preset over the schema's defaults
    planner = LLMPlanner.from_config(cfg, field_size=2 * HALF)
    assert planner.model.split("/")[0] in ("offline", "openai", "ollama_chat")
    assert planner.prompt in ("plain", "tap") and planner.n_waypoints == K


def test_task_aligned_prompt_bends_the_plan_toward_the_task():
    """Offline QMIX-TAP differs from plain planning: an interceptor and resource detours."""
    from icco_torchrl.instructions.planner import rule_plan

    positions = np.array([[0.0, 0.0], [1.0, 1.0], [-1.0, -2.0]])
    plain, _ = rule_plan("Go right", positions, n_waypoints=4, half=3.25)
    invader, resource = np.array([[3.2, -3.0]]), np.array([[1.5, 1.2], [-2.5, 2.5]])
    tap, strategy = rule_plan(
        "Go right", positions, n_waypoints=4, half=3.25, resources=resource, invader=invader
    )
    assert "intercepts the invader" in strategy
    interceptor = int(strategy.split("agent_")[1][0])
    path = invader[0] * (1 - np.linspace(0, 1, 50))[:, None]  # the invader's straight path home
    assert np.min(np.linalg.norm(path - tap[interceptor, -1], axis=1)) < 0.2
    detour = [
        i for i in range(3) if i != interceptor and np.allclose(tap[i, 1], resource[0], atol=1e-6)
    ]
    assert detour, "the robot next to a resource should pass through it"
    others = [i for i in range(3) if i != interceptor]
    np.testing.assert_allclose(
        tap[others, -1], plain[others, -1]
    )  # they still end on the instructed line


# --- a provider that does not reply ---------------------------------------------------------
# A fake OpenAI-compatible server on 127.0.0.1 (tests/fake_openai.py): refused, hanging, 401.


@pytest.fixture
def openai_key(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("OPENAI_API_KEY", "sk-test")  # litellm wants one before it sends anything


def remote(url: str, **settings: Any) -> LLMPlanner:
    options = {"timeout": 0.5, "deadline_s": 2.0, "max_retries": 2, "backoff_s": 0.05, **settings}
    return LLMPlanner(model="openai/gpt-4o", api_base=url, **options)


@contextlib.contextmanager
def provider(case: str):
    """``(url, server or None)`` of a provider that refuses connections, hangs, or refuses the
    key."""
    if case == "refused":
        yield f"http://127.0.0.1:{closed_port()}/v1", None
        return
    with FakeOpenAI("hang" if case == "hang" else "401", lifetime=20.0) as server:
        yield server.url, server


NO_REPLY = {"refused": "Connection refused", "hang": "Timeout", "401": "AuthenticationError"}


@pytest.mark.parametrize("case", NO_REPLY)
@pytest.mark.fault
def test_a_model_that_never_replies_fails_fast_in_one_line(
    litellm: Any, openai_key: None, case: str
) -> None:
    with provider(case) as (url, server):
        # 6 s: litellm's first request can take seconds on a loaded machine before the refusal
        # comes back; a hung provider would still take its 20 s.
        planner = remote(url, deadline_s=6.0)
        begin = time.monotonic()
        with pytest.raises(LLMUnavailable) as info:
            planner.plan("Go right", starts(0))
        elapsed = time.monotonic() - begin
    message = str(info.value)
    # The deadline holds (a hung provider would take its 20 s), with room for a loaded machine.
    assert elapsed < planner.deadline_s + 2.0, (
        f"took {elapsed:.1f} s for a {planner.deadline_s:.0f} s deadline"
    )
    assert (
        "\n" not in message
        and NO_REPLY[case] in message
        and "llm.fallback_on_error=true" in message
    )
    assert url.removesuffix("/v1") in message
    if case == "401":  # a refused key is refused again: not retried
        assert len(server.requests) == 1 and planner.stats["backend_calls"] == 1
    assert planner.stats["fallbacks"] == 0


@pytest.mark.parametrize("case", NO_REPLY)
@pytest.mark.fault
def test_with_fallbacks_a_model_that_never_replies_falls_back_and_records_it(
    litellm: Any, openai_key: None, case: str
) -> None:
    with provider(case) as (url, _):
        planner = remote(url, fallback_on_error=True)
        begin = time.monotonic()
        result = planner.plan("Go right", starts(0), previous=np.full((3, K, 2), 0.5))
        elapsed = time.monotonic() - begin
    assert elapsed < 3.0
    # A hung provider ends in its request's timeout or, on a loaded machine where the retries
    # eat the plan's time first, in the plan's deadline: either way recorded, and a fallback.
    recorded = (NO_REPLY[case], "DeadlineExceeded") if case == "hang" else (NO_REPLY[case],)
    assert not result.ok and result.fallback == "previous"
    assert any(word in result.error for word in recorded), result.error
    assert np.allclose(result.waypoints, 0.5) and planner.stats["fallbacks"] == 1


@pytest.mark.fault
def test_retries_and_timeouts_never_outlast_the_deadline(litellm: Any, openai_key: None) -> None:
    with FakeOpenAI("hang", lifetime=20.0) as server:
        planner = remote(server.url, timeout=10.0, deadline_s=1.0, max_retries=5, backoff_s=0.0)
        begin = time.monotonic()
        with pytest.raises(LLMUnavailable, match="deadline"):
            planner.plan("Go right", starts(0))
        assert time.monotonic() - begin < 2.0 and len(server.requests) == 1


@pytest.mark.fault
def test_a_provider_that_ignores_its_timeout_still_ends_at_the_deadline(scripted: Scripted) -> None:
    release = threading.Event()
    original = scripted.handler.completion

    def stuck(*args: Any, **kwargs: Any) -> Any:
        release.wait(10.0)  # a request that never times out by itself (bounded for the test)
        return original(*args, **kwargs)

    scripted.handler.completion = stuck
    scripted.replies = [valid_reply()]
    planner = LLMPlanner(model="scripted/x", timeout=30.0, deadline_s=0.5, max_retries=3)
    begin = time.monotonic()
    try:
        with pytest.raises(LLMUnavailable, match="DeadlineExceeded"):
            planner.plan("Go right", starts(0))
        assert time.monotonic() - begin < 1.5
    finally:
        release.set()


def test_a_fake_openai_server_that_answers_gives_a_plan(litellm: Any, openai_key: None) -> None:
    with FakeOpenAI("ok", reply=valid_reply(value=0.5)) as server:
        result = remote(server.url).plan("Go right", starts(0))
    assert result.ok and result.attempts == 1 and np.allclose(result.waypoints, [0.5, -0.5])
    assert (
        server.requests[0]["model"] == "gpt-4o"
        and server.requests[0]["messages"][-1]["role"] == "user"
    )


def test_a_bad_reply_still_falls_back_without_fallback_on_error(litellm: Any) -> None:
    planner = mocked(max_retries=1)
    assert not planner.fallback_on_error
    result = ask(planner, "Go right", starts(0), replies="no plan here")
    assert (
        not result.ok
        and result.fallback == "positions"
        and result.error == "no JSON object in the reply"
    )


# --- replies that are too large, too deep or too slow to parse ------------------------------


def test_a_huge_reply_costs_one_short_error_a_few_log_lines_and_no_time(
    litellm: Any, caplog: pytest.LogCaptureFixture
) -> None:
    points = [[1.0, 2.0]] * 300_000  # 2.4 MB of JSON
    huge = json.dumps({"movement_strategy": "s", **{f"agent_{i}": points for i in range(3)}})
    planner = mocked(max_retries=2, deadline_s=1.0)
    with caplog.at_level(logging.WARNING, logger="icco_torchrl.instructions.llm"):
        begin = time.monotonic()
        result = ask(planner, "Go right", starts(0), replies=huge)
        elapsed = time.monotonic() - begin
    assert not result.ok and result.attempts == 3 and elapsed < 1.5
    assert result.error.startswith("reply too long: ") and len(result.error) < 100
    assert len(caplog.text) < 4_000 and len(caplog.records) == 4  # 3 attempts and the fallback


def test_a_bad_value_is_quoted_in_a_few_characters() -> None:
    many = {"movement_strategy": "s", **{f"agent_{i}": [[1.0, 2.0]] * 1500 for i in range(3)}}
    with pytest.raises(ReplyError) as info:  # 1500 points a robot: under the size limit
        parse_reply(json.dumps(many), 3, K, 2 * HALF)
    assert "1500 items" in str(info.value) and len(str(info.value)) < 200
    keys = json.dumps({f"agent_{i}": [[0, 0]] * K for i in range(1000)})
    with pytest.raises(ReplyError, match=r"\(1000 keys\)") as info:
        parse_reply(keys, 3, K, 2 * HALF)
    assert len(str(info.value)) < 200
    digits = valid_reply().replace("-1.0", "1" * 400, 1)  # a 400-digit coordinate
    with pytest.raises(ReplyError, match="out of range"):
        parse_reply(digits, 3, K, 2 * HALF)
    declined = json.dumps({"error": "no " * 20_000})
    with pytest.raises(ReplyError, match="planner declined") as info:
        parse_reply(declined, 3, K, 2 * HALF)
    assert len(str(info.value)) <= 500
    deep = '{"agent_0": ' + "[" * 50_000 + "]" * 50_000 + "}"
    with pytest.raises(ReplyError):  # nested past the recursion limit: a bad reply, no crash
        parse_reply(deep, 3, K, 2 * HALF)


@pytest.mark.parametrize(
    "unit",
    ['{"a": 1, ', '{"s": "{', '{"a": [', '{"a": {"b": {'],
    ids=["keys", "str", "list", "deep"],
)
def test_finding_the_last_json_object_is_linear(unit: str) -> None:
    """``json``'s search from every ``{`` took 15 s on a 300 KB reply (its error messages count
    lines from the start; about 7 s on this 600 KB text) or crashed on deep nesting; the search
    here takes a second at most (a reply the planner parses is at most 64 KiB)."""
    text = unit * (600_000 // len(unit)) + 'then {"a": 2}'
    begin = time.perf_counter()
    assert last_json_object(text) in ({"a": 2}, None)  # the budget may stop before the end
    assert time.perf_counter() - begin < 3.0
    assert last_json_object(unit * 1000 + ' then {"a": 2}') == {"a": 2}
