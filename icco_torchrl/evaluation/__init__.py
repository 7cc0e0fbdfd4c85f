"""Evaluation: greedy rollouts, protocols (random walk, quadrants, instructions), figures."""

from icco_torchrl.evaluation.rollout import EVENT_KEYS, episode_metrics, evaluate, greedy_rollout

__all__ = ["EVENT_KEYS", "episode_metrics", "evaluate", "greedy_rollout"]
