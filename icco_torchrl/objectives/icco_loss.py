"""ICCOLoss: the QMIX TD loss conditioned on the coordinator's z, plus the consistency term.

One loss covers every Q-learning method of the paper (the presets of ``conf/method/``, listed
by :mod:`icco_torchrl.methods`): with a coordinator and ``ce_coef > 0`` it is ICCO, with
``ce_coef = 0`` ICCO w/o CE; without a coordinator it is QMIX, on agents that read their local
view (QMIX) or the global state as well (QMIX (FULL), in either state encoding).

Input: replayed sequences ``[S, L]`` (TorchRL layout, time last) that start at a broadcast
step (``step_count % period == 0``), as cut by
:class:`~icco_torchrl.training.segments.SegmentCutter`; ``L`` is any multiple of the broadcast
period ``T`` (``L = T``: one broadcast per item).

- Recurrent state (R2D2's "stored state"): the agent's GRU starts from the hidden state recorded
  at the sequence's first step during collection; the first ``burn_in`` steps only warm it up
  (no gradient, no loss). Steps after an episode end inside a sequence are masked out.
- z is rebuilt at every broadcast step inside the sequence as ``mu_phi(s) + sigma_phi(s) * eps``
  with the noise ``eps`` stored at collection, and held until the next broadcast, so the
  gradients of L_RL reach the coordinator through z. A broadcast at the final next-state (the
  bootstrap) draws fresh noise (COPA).
- Targets: lambda-returns over the sequence (:func:`~icco_torchrl.objectives.lambda_returns`),
  the target networks bootstrapping at every step, double Q.
- L_CE, averaged over every broadcast window of the batch:
  ``ce_coef * (-log q_xi(z | zeta, s, v)) + entropy_coef * (-H(N(mu_phi(s), sigma_phi(s))))``;
  with ``ce_clamp`` (COPA's) each dimension's log-density is clamped to [-1000, 0] (each step's
  too, for a posterior that sums its factors' log-likelihoods) and each dimension's entropy to
  [0, 10] before the sums, so a sharper posterior or a narrower z than that earns nothing.
- Defaults: :data:`~icco_torchrl.objectives.defaults.LOSS_DEFAULTS`, the ones ``icco train
  method=icco`` trains with (the config takes them from there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from tensordict import TensorDict, TensorDictBase, TensorDictParams
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey, unravel_key
from torch import nn
from torchrl.modules import set_recurrent_mode
from torchrl.objectives import LossModule
from torchrl.objectives.utils import ValueEstimators

from icco_torchrl.modules.coordinator import gaussian_entropy
from icco_torchrl.modules.tdmodule import TensorModule
from icco_torchrl.objectives.defaults import ENTROPY_CLAMP, LOG_Q_CLAMP, LOSS_DEFAULTS
from icco_torchrl.objectives.inputs import (
    LossBatch,
    assemble,
    next_key,
    present_robots,
    read_batch,
)
from icco_torchrl.objectives.returns import lambda_returns

if TYPE_CHECKING:
    from icco_torchrl.envs.layout import ObsLayout

REWARD_REDUCTIONS = ("mean", "sum")
# Modules whose call is exactly module(*in_keys) -> out_keys: the mixer skips the tensordict.
_PLAIN_MODULES = (TensorDictModule, TensorModule)


class NonFiniteLossError(FloatingPointError):
    """Raised instead of stepping an optimiser on a NaN/inf loss."""


def _check_weights(ce_coef: float, entropy_coef: float, reward_reduction: str) -> None:
    """:class:`ICCOLoss`'s checks of its CE weights and its reward reduction."""
    if ce_coef < 0 or entropy_coef < 0:
        raise ValueError(f"ce_coef and entropy_coef must be >= 0, got {ce_coef}, {entropy_coef}")
    if reward_reduction not in REWARD_REDUCTIONS:
        raise ValueError(
            f"reward_reduction must be one of {REWARD_REDUCTIONS}, got {reward_reduction!r}"
        )


class ICCOLoss(LossModule):
    """TD + consistency loss over replayed sequences for ICCO and its QMIX baselines.

    Args:
        agent: the agents' Q-network as a TensorDictModule writing ``action_value`` ``[..., N, A]``.
            A :class:`~icco_torchrl.modules.RecurrentQNet` (or any module with
            ``sequence(obs, prev_action, hidden0, z=None, state=None)`` and the attributes
            ``hidden``, ``z_dim``, ``full_state``) runs each sequence in one call from the stored
            hidden state. Any other TensorDictModule (a TorchRL ``MultiAgentMLP``, a ``GRUModule``
            pipeline, ...) is called through its keys on the ``[S, L+1]`` inputs under TorchRL's
            ``set_recurrent_mode(True)``, with ``is_init`` for the steps that start an episode.
        mixer: TensorDictModule mixing ``local_value [.., N, 1]`` (and whatever else it reads, e.g.
            the state, from the batch or its ``"next"`` entry) into ``global_value [.., 1]``:
            TorchRL's ``QMixer`` or ``VDNMixer``, or :func:`~icco_torchrl.modules.make_mixer`.
        coordinator: TensorDictModule wrapping a :class:`~icco_torchrl.modules.Coordinator`, or
            None (QMIX).
        posterior: a :class:`~icco_torchrl.modules.Posterior` (``make_posterior``), or None.

    Keyword Args:
        gamma: discount.
        td_lambda: lambda of the lambda-return over each sequence (0: one-step targets).
            :meth:`make_value_estimator` sets the same thing TorchRL's way.
        burn_in: leading steps of each sequence that only warm up the GRU from its stored state
            (no loss, no gradient); needs an agent with ``step`` and ``sequence(...,
            return_hidden=True)``.
        double_q: bootstrap with the online argmax evaluated by the target networks.
        ce_coef: weight of ``-log q`` (COPA: 1e-3); 0 disables the CE term (ICCO w/o CE).
        entropy_coef: weight of ``-H`` (COPA: 1e-4).
        ce_clamp: COPA's clamps in L_CE: each dimension's ``log q`` to [-1000, 0] (each step's
            too with a posterior that sums log-likelihoods; needs a posterior with
            ``log_prob_terms``, as :class:`~icco_torchrl.modules.Posterior` has), each dimension's
            entropy to [0, 10]. The ``log_q`` and ``entropy`` entries stay the unclamped values.
        reward_reduction: how per-agent rewards ``[S, L, N, 1]`` (TorchRL multi-agent envs such as
            VMAS) become the team reward: ``"mean"`` (TorchRL's QMIX example) or ``"sum"``.
        check_finite: raise :class:`NonFiniteLossError` on a NaN/inf loss (one host sync a call).
        layout: the env's :class:`~icco_torchrl.envs.layout.ObsLayout`, with which the loss reads
            who is present off the state (:meth:`~icco_torchrl.envs.layout.ObsLayout.robot_mask`;
            a team of any size: absent robots are left out of L_CE and of the per-robot metrics);
            None: every robot is (a fixed team, or an env without a layout).

    Left out, each setting is :data:`~icco_torchrl.objectives.defaults.LOSS_DEFAULTS`', the one
    ``icco train method=icco`` trains with: ``ICCOLoss(agent, mixer, coordinator, posterior)`` is
    ICCO as the project trains it.

    Examples:
        >>> import torch
        >>> from icco_torchrl.training.build import build_components
        >>> from icco_torchrl.training.segments import SegmentCutter
        >>> torch.manual_seed(0)  # doctest: +ELLIPSIS
        <torch._C.Generator object at ...>
        >>> run = build_components(method="icco", num_envs=4)
        >>> with torch.no_grad():
        ...     rollout = run.env.rollout(32, run.policy, break_when_any_done=False)
        >>> items = SegmentCutter(length=16)(rollout)  # 16-step items: 4 broadcasts each
        >>> items.batch_size
        torch.Size([8, 16])
        >>> losses = run.loss(items)
        >>> sorted(key for key in losses.keys() if key.startswith("loss_"))
        ['loss_ce', 'loss_td']
        >>> total_loss(losses).backward()
    """

    @dataclass
    class _AcceptedKeys:
        """Every key the loss reads or writes; rename with ``set_keys(...)``.

        ``reward``, ``done`` and ``terminated`` are read under ``"next"`` (team ``[S, L, 1]`` or
        per agent ``[S, L, N, 1]``). ``mask`` is optional: without it, the steps after an episode
        end (``done``) or a new start (``is_init``) are left out. ``state`` may have any trailing
        shape. ``prev_action`` and ``rnn_hidden`` are read for recurrent agents, ``z``,
        ``z_noise`` and ``step_count`` with a coordinator, ``z_sent`` (which robots received a z,
        ``[S, T, N, 1]``) with an adaptive broadcast (a coordinator ``threshold > 0``).
        ``action_value`` is what the agent writes, ``local_value``/``global_value`` what the mixer
        reads/writes.
        """

        observation: NestedKey = ("agents", "observation")
        state: NestedKey = "state"
        action: NestedKey = ("agents", "action")
        prev_action: NestedKey = ("agents", "prev_action")
        rnn_hidden: NestedKey = ("agents", "rnn_hidden")
        z: NestedKey = ("agents", "z")
        z_noise: NestedKey = ("agents", "z_noise")
        z_sent: NestedKey = ("agents", "z_sent")
        step_count: NestedKey = "step_count"
        is_init: NestedKey = "is_init"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        mask: NestedKey = "mask"
        action_value: NestedKey = ("agents", "action_value")
        local_value: NestedKey = ("agents", "chosen_action_value")
        global_value: NestedKey = "chosen_action_value"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    default_value_estimator = ValueEstimators.TDLambda

    agent: TensorDictModule
    agent_params: TensorDictParams
    target_agent_params: TensorDictParams
    mixer: TensorDictModule
    mixer_params: TensorDictParams
    target_mixer_params: TensorDictParams
    coordinator: TensorDictModule
    coordinator_params: TensorDictParams
    target_coordinator_params: TensorDictParams

    def __init__(
        self,
        agent: TensorDictModule,
        mixer: TensorDictModule,
        coordinator: TensorDictModule | None = None,
        posterior: nn.Module | None = None,
        *,
        gamma: float = LOSS_DEFAULTS.gamma,
        td_lambda: float = LOSS_DEFAULTS.td_lambda,
        burn_in: int = LOSS_DEFAULTS.burn_in,
        double_q: bool = LOSS_DEFAULTS.double_q,
        ce_coef: float = LOSS_DEFAULTS.ce_coef,
        entropy_coef: float = LOSS_DEFAULTS.entropy_coef,
        ce_clamp: bool = LOSS_DEFAULTS.ce_clamp,
        reward_reduction: str = "mean",
        check_finite: bool = True,
        layout: ObsLayout | None = None,
    ):
        super().__init__()
        self.layout = layout
        self._set_discount(gamma, td_lambda)
        _check_weights(ce_coef, entropy_coef, reward_reduction)
        net = agent.module
        self._set_agent_protocol(net, burn_in)
        self.has_coordinator = coordinator is not None
        if hasattr(net, "z_dim") and self.has_coordinator != bool(net.z_dim):
            raise ValueError("the agent takes z (z_dim > 0) exactly when a coordinator is given")
        if ce_coef > 0 and self.has_coordinator and posterior is None:
            raise ValueError("ce_coef > 0 needs a posterior module")
        self.reward_reduction, self.burn_in = reward_reduction, burn_in
        self.double_q, self.check_finite = double_q, check_finite
        self.use_ce = self.has_coordinator and (ce_coef > 0 or entropy_coef > 0)
        self.ce_coef, self.entropy_coef = float(ce_coef), float(entropy_coef)
        self.ce_clamp = bool(ce_clamp)
        self.convert_to_functional(agent, "agent", create_target_params=True)
        self.convert_to_functional(mixer, "mixer", create_target_params=True)
        if self.has_coordinator:
            self.convert_to_functional(coordinator, "coordinator", create_target_params=True)
            self.period = coordinator.module.period
            self.threshold = float(getattr(coordinator.module, "threshold", 0.0))
        # The posterior has no target copy: it only appears in L_CE. Held as ``posterior.module``
        # (the parameter names of checkpoints made when it came wrapped in a TensorDictModule).
        if posterior is not None and not isinstance(posterior, TensorDictModule):
            posterior = _Holder(posterior)
        self.posterior = posterior if self.has_coordinator and ce_coef > 0 else None
        if self.ce_clamp and self.posterior is not None:
            if not hasattr(self.posterior.module, "log_prob_terms"):
                raise ValueError(
                    "ce_clamp clamps log q per dimension: it needs a posterior with "
                    "log_prob_terms(z, state, action, obs, mask), as Posterior has"
                )

    @property
    def settings(self) -> dict:
        """The loss's hyperparameters, by keyword argument (what makes two losses over the same
        networks the same method)."""
        return dict(
            gamma=self.gamma,
            td_lambda=self.td_lambda,
            burn_in=self.burn_in,
            double_q=self.double_q,
            ce_coef=self.ce_coef,
            entropy_coef=self.entropy_coef,
            ce_clamp=self.ce_clamp,
            reward_reduction=self.reward_reduction,
            check_finite=self.check_finite,
        )

    def _set_agent_protocol(self, net: nn.Module, burn_in: int) -> None:
        """What the agent ``net`` can do (a sequence in one call, a step), checked against
        ``burn_in``."""
        # The sequence protocol (RecurrentQNet and stand-ins): a sequence in one call.
        self._sequence_agent = hasattr(net, "sequence")
        if not isinstance(burn_in, int) or burn_in < 0:
            raise ValueError(f"burn_in must be an integer >= 0, got {burn_in!r}")
        # With step(...) and sequence(..., return_hidden=True) as well: burn-in, and double Q
        # without the backward pass of the bootstrap input.
        self._stepping_agent = self._sequence_agent and hasattr(net, "step")
        if burn_in and not self._stepping_agent:
            raise ValueError(
                "burn_in needs an agent with step(...) and sequence(..., return_hidden=True), "
                "as RecurrentQNet has"
            )

    def _set_discount(self, gamma: float, td_lambda: float) -> None:
        if not 0 <= gamma <= 1:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if not 0 <= td_lambda <= 1:
            raise ValueError(f"td_lambda must be in [0, 1], got {td_lambda}")
        self.gamma, self.td_lambda = float(gamma), float(td_lambda)

    def make_value_estimator(self, value_type: ValueEstimators | None = None, **hyperparams):
        """TorchRL's way to choose the target: ``TD0`` (one-step), ``TD1`` (the return to the
        sequence's end) or ``TDLambda`` (``lmbda``; the default, at the loss's ``td_lambda``, or
        at the default ``td_lambda`` where it is 0), each with ``gamma``. Other estimators (GAE,
        V-trace) are for actor-critic losses and are refused."""
        value_type = self.default_value_estimator if value_type is None else value_type
        hp = dict(hyperparams)
        gamma = hp.pop("gamma", self.gamma)
        hp.pop("differentiable", None)  # TorchRL's default kwarg; targets never carry gradient
        lambdas = {ValueEstimators.TD0: 0.0, ValueEstimators.TD1: 1.0}
        if value_type == ValueEstimators.TDLambda:
            lam = hp.pop("lmbda", self.td_lambda or LOSS_DEFAULTS.td_lambda)
        elif value_type in lambdas:
            lam = lambdas[value_type]
        else:
            raise NotImplementedError(
                f"ICCOLoss computes Q-learning targets (TD0, TD1, TDLambda); {value_type} "
                f"is not one of them"
            )
        if hp:
            raise TypeError(f"unknown hyperparameters for {value_type}: {sorted(hp)}")
        self._set_discount(gamma, lam)
        self.value_type = value_type
        return self

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        self._in_keys = None  # set_keys renamed something: derive the keys again

    @property
    def in_keys(self) -> list[NestedKey]:
        """Every batch key the loss reads, from its ``tensor_keys`` and the mixer's ``in_keys``:
        what a replay buffer must store (``("next", ...)`` entries included). ``mask`` is the
        cutter's; ``is_init`` is read when present and otherwise derived from ``step_count``."""
        if getattr(self, "_in_keys", None) is None:
            self._in_keys = self._derive_in_keys()
        return list(self._in_keys)

    def _derive_in_keys(self) -> list[NestedKey]:
        k = self.tensor_keys
        keys = [k.observation, k.state, k.action]
        if self.reads_prev_action:
            keys.append(k.prev_action)
        if self.recurrent:
            keys.append(k.rnn_hidden)
        if self.has_coordinator:
            keys += [k.z, k.z_noise] + ([k.z_sent] if self.threshold > 0 else [])
        keys += [k.step_count, k.mask]
        keys += [next_key(key) for key in (k.observation, k.state, k.reward, k.done)]
        keys += [next_key(k.terminated), next_key(k.step_count)]
        local = unravel_key(k.local_value)
        for key in self.mixer.in_keys:
            if unravel_key(key) != local:
                keys += [key, next_key(key)]
        unique = {}
        for key in keys:
            unique.setdefault(unravel_key(key), key)
        return list(unique.values())

    @property
    def metric_keys(self) -> tuple[str, ...]:
        """The entries :meth:`forward` returns (``loss_*`` are summed by :func:`total_loss`; the
        others are detached summaries)."""
        keys = ("loss_td", "q_taken", "q_tot", "td_error")
        if self.use_ce:
            keys += ("loss_ce", "ce_neg_entropy", "entropy")
            if self.posterior is not None:
                keys += ("ce_nll", "log_q")
        return keys

    @property
    def out_keys(self) -> list[str]:
        """The entries :meth:`forward` writes (:attr:`metric_keys`)."""
        return list(self.metric_keys)

    @property
    def recurrent(self) -> bool:
        """Whether the agent starts each sequence from the stored hidden state (``rnn_hidden``):
        an agent of the sequence protocol, or a TensorDictModule that reads it."""
        return self._sequence_agent or self._reads(self.tensor_keys.rnn_hidden)

    @property
    def reads_prev_action(self) -> bool:
        """Whether the agent reads the previous actions (``prev_action``)."""
        return self._sequence_agent or self._reads(self.tensor_keys.prev_action)

    @property
    def reads_state(self) -> bool:
        """Whether the loss's tensor part reads the global state of the ``L + 1`` inputs: with a
        coordinator, an agent that reads the state (QMIX (FULL)), or a TensorDictModule agent
        with the state among its ``in_keys``."""
        return (
            self.has_coordinator
            or getattr(self.agent.module, "full_state", False)
            or (not self._sequence_agent and self._reads_own_state())
        )

    def _reads_own_state(self) -> bool:
        """Whether the (non-sequence) agent reads the state under its own key (not as its
        observation)."""
        k = self.tensor_keys
        return self._reads(k.state) and unravel_key(k.state) != unravel_key(k.observation)

    def _reads(self, key: NestedKey) -> bool:
        """Whether the (non-sequence) agent's TensorDictModule reads ``key``."""
        return unravel_key(key) in [unravel_key(k) for k in self.agent.in_keys]

    # ------------------------------------------------------------------ forward
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        batch = self.read_batch(tensordict)
        fresh = None
        if self.has_coordinator:
            # Fresh noise for a broadcast at the bootstrap step, shared by online and target;
            # drawn at the items' shape so the random stream is the one-broadcast learner's
            # (tests/data/loss_reference_t4.json pins it).
            fresh = torch.randn_like(batch.z_noise)[:, -1]
        out = self._losses(batch, fresh)
        if self.check_finite:
            self._check_finite(out)
        return TensorDict(out, [])

    def compile_losses(self, **kwargs) -> ICCOLoss:
        """Compile the loss's tensor part (:meth:`losses`: every network, the targets and both
        terms, with the backward AOTAutograd derives from it) with ``torch.compile(**kwargs)``;
        reading and checking the batch stays eager. Returns ``self``.

        Not ``nn.Module.compile``, which this class leaves as it is (it would compile the whole
        ``forward``, the batch checks included, in place)."""
        self._losses = torch.compile(self.losses, **kwargs)
        return self

    def read_batch(self, tensordict: TensorDictBase) -> LossBatch:
        """The checked inputs of the loss from ``tensordict`` ``[S, L]`` (time last): every key
        it reads (:attr:`in_keys`), checked once with an error naming the key and the shape it
        needs, as a :class:`~icco_torchrl.objectives.inputs.LossBatch` of views of the batch (the
        argument of :meth:`losses`; the raw tensordict stays out of it).

        Examples:
            >>> import torch
            >>> from icco_torchrl.training.build import build_components
            >>> from icco_torchrl.training.segments import SegmentCutter
            >>> run = build_components(method="icco", num_envs=2)
            >>> with torch.no_grad():
            ...     rollout = run.env.rollout(8, run.policy, break_when_any_done=False)
            >>> batch = run.loss.read_batch(SegmentCutter(length=4)(rollout))
            >>> batch.obs.shape[:3], batch.z.shape[:3], batch.step_count.shape  # S, L, N robots
            (torch.Size([4, 4, 3]), torch.Size([4, 4, 3]), torch.Size([4, 4]))
            >>> sorted(map(str, batch.mixer_inputs))
            ['state']
        """
        return read_batch(self, tensordict)

    def _losses(self, batch: LossBatch, fresh: torch.Tensor | None) -> dict[str, torch.Tensor]:
        return self.losses(batch, fresh)

    def losses(self, batch: LossBatch, fresh: torch.Tensor | None) -> dict[str, torch.Tensor]:
        """The loss terms and summaries from the checked ``batch`` (:meth:`read_batch`) and the
        bootstrap noise ``fresh``: tensors in, tensors out, fixed shapes, no host sync (what
        :meth:`compile_losses` traces)."""
        batch = assemble(batch, self.reads_state)
        z_on = z_tgt = None
        if self.has_coordinator:
            z_on, loc_w, scale_w = self._z_sequence(batch, self.coordinator_params, fresh)
            with torch.no_grad():
                z_tgt = self._z_sequence(batch, self.target_coordinator_params, fresh)[0]

        q_online, q_boot = self._q_online(batch, z_on)  # [S, L, N, A], [S, N, A]
        chosen = _taken(q_online, batch.action.long().unsqueeze(-1))  # [S, L, N]
        q_tot = self._mix(self.mixer_params, chosen, batch.mixer_inputs)
        with torch.no_grad():
            q_target = self._q_sequence(self.target_agent_params, batch, z_tgt)[:, 1:]
            if self.double_q:
                greedy_source = torch.cat([q_online[:, 1:], q_boot.unsqueeze(1)], 1)
            else:
                greedy_source = q_target
            next_value = _taken(q_target, greedy_source.argmax(-1, keepdim=True))
            q_tot_next = self._mix(self.target_mixer_params, next_value, batch.next_mixer_inputs)
            target = self._targets(batch, batch.reward, q_tot_next)

        weight = self._loss_weight(batch.mask).to(q_tot.dtype)  # [S, L]
        n_valid = weight.sum().clamp_min(1.0)
        td_error = (q_tot - target).squeeze(-1)  # [S, L]
        # per-robot summaries average the present robots (absent ones: all-zero state tokens)
        robot_weight = weight.unsqueeze(-1) * present_robots(
            self.layout, batch.state, chosen.shape[2]
        )
        n_robots = robot_weight.sum().clamp_min(1.0)
        taken = chosen.detach()
        out = {
            "loss_td": (weight * td_error.pow(2)).sum() / n_valid,
            "q_taken": (robot_weight * taken).sum() / n_robots,
            "q_tot": (weight * q_tot.detach().squeeze(-1)).sum() / n_valid,
            "td_error": (weight * td_error.detach().abs()).sum() / n_valid,
        }
        if self.use_ce:
            out.update(self._consistency(batch, z_on, loc_w, scale_w))
        return out

    def _loss_weight(self, mask: torch.Tensor) -> torch.Tensor:
        """The steps the TD loss scores: in the sequence's episode and past the burn-in."""
        if not self.burn_in:
            return mask
        return mask & (torch.arange(mask.shape[1], device=mask.device) >= self.burn_in)

    def _targets(
        self, batch: LossBatch, reward: torch.Tensor, next_value: torch.Tensor
    ) -> torch.Tensor:
        """Lambda-return targets of ``reward`` from the target values of each next state: the
        team's ``[S, L, 1]`` (``Q_tot``), or per robot ``[S, L, N]``."""
        mask = batch.mask
        # The return of step t continues into step t+1 only within one episode (mask[t+1]).
        cont = torch.cat([mask[:, 1:], torch.zeros_like(mask[:, :1])], 1).unsqueeze(-1)
        alive = (~batch.terminated).to(next_value.dtype)
        return lambda_returns(
            reward, alive, next_value, cont, gamma=self.gamma, lmbda=self.td_lambda
        )

    def _check_finite(self, out: dict) -> None:
        bad = [n for n, v in out.items() if n.startswith("loss_") and not torch.isfinite(v).all()]
        if bad:
            values = ", ".join(f"{n}={v.item():.4g}" for n, v in out.items())
            raise NonFiniteLossError(f"non-finite loss terms {bad}: {values}")

    # ------------------------------------------------------------------ z
    def _z_sequence(self, batch: LossBatch, params: TensorDictParams, fresh: torch.Tensor):
        """z for the ``L + 1`` inputs of each sequence under ``params`` ``[S, L+1, N, Z]``, and the
        coordinator's ``(loc, scale)`` at the window starts ``0, T, 2T, ...`` ``[S, W, N, Z]``.

        Within a sequence's episode the broadcasts are every T-th input from the first broadcast
        step (input 0 when the sequence starts at one, as the cutter's do): each is a new draw
        from the stored noise (``fresh`` at the bootstrap input ``L``), held until the next. The
        inputs before the first broadcast hold the stored z. The coordinator runs on these
        ``L // T + 1`` inputs of every row, a fixed shape; a broadcast off this grid can only
        follow an episode end inside the sequence, on inputs no term reads.
        """
        step, T = batch.step_count, self.period
        S, L = step.shape
        device = step.device
        P = L // T + 1  # broadcasts a sequence can hold
        phase = (-step[:, :1]) % T  # [S, 1]: input of the first broadcast
        at = (phase + T * torch.arange(P, device=device)).clamp_max(L)  # [S, P]
        state = batch.state_seq.gather(1, at.unsqueeze(-1).expand(S, P, batch.state_seq.shape[-1]))
        with params.to_module(self.coordinator, preserve_module_state=False):
            loc, scale = self.coordinator.module.distribution(state)  # [S, P, N, Z]
        noise = torch.cat([batch.z_noise, fresh.unsqueeze(1)], 1)
        noise = noise.gather(1, at[..., None, None].expand(S, P, *noise.shape[2:]))
        draws = loc + scale * noise
        if self.threshold > 0:  # robot i holds its z until a broadcast moved it (COPA's beta)
            draws = self._held_draws(batch, draws, at)
        # Slot 0: the stored z (held from before the sequence); slot p + 1: broadcast p.
        draws = torch.cat([batch.z[:, :1], draws], 1)
        j = torch.arange(L + 1, device=device)
        slot = torch.where(j < phase, 0, 1 + torch.div(j - phase, T, rounding_mode="floor"))
        z_seq = draws.gather(1, slot[..., None, None].expand(S, L + 1, *draws.shape[2:]))
        W = max(L // T, 1)  # whole broadcast windows (one shorter window when L < T); scored
        return z_seq, loc[:, :W], scale[:, :W]  # only where the sequence starts at a broadcast

    def _held_draws(self, batch: LossBatch, draws: torch.Tensor, at: torch.Tensor) -> torch.Tensor:
        """``draws [S, P, N, Z]`` at the broadcast inputs ``at [S, P]`` -> the z each robot holds
        after each of them: the draw where it was sent (the stored ``z_sent`` inside the sequence;
        at the bootstrap input, where the draw moved more than the threshold from the held z),
        else the z held before."""
        S, P = at.shape
        L, N = batch.z_sent.shape[1:3]
        stored = batch.z_sent.gather(1, at.clamp_max(L - 1)[..., None, None].expand(S, P, N, 1))
        held, out = batch.z[:, 0], []
        for p in range(P):  # P = L // T + 1 broadcasts, each depends on the last one
            moved = (draws[:, p] - held).norm(dim=-1, keepdim=True) > self.threshold
            sent = torch.where((at[:, p] < L)[:, None, None], stored[:, p], moved)
            held = torch.where(sent, draws[:, p], held)
            out.append(held)
        return torch.stack(out, 1)

    # ------------------------------------------------------------------ Q-values
    def _agent_state(self, batch: LossBatch, steps: slice = slice(None)) -> torch.Tensor | None:
        """The global state the agent reads (QMIX (FULL)), else None."""
        return (
            batch.state_seq[:, steps] if getattr(self.agent.module, "full_state", False) else None
        )

    def _q_sequence(self, params: TensorDictParams, batch: LossBatch, z_seq) -> torch.Tensor:
        """Q over the ``L + 1`` inputs of each sequence, ``[S, L+1, N, A]``, in one GRU call."""
        with params.to_module(self.agent, preserve_module_state=False):
            if not self._sequence_agent:
                return self._call_agent(batch, z_seq, slice(None))
            return self.agent.module.sequence(
                batch.obs_seq,
                batch.prev_seq,
                batch.hidden[:, 0],
                z=z_seq,
                state=self._agent_state(batch),
            )

    def _q_online(self, batch: LossBatch, z_seq) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Online Q over steps 0..L-1 (with autograd past the burn-in) and, for double Q, at the
        bootstrap input L (without autograd: it only feeds the argmax). Same values as slicing
        one ``L + 1`` sequence."""
        net, L, B = self.agent.module, batch.obs.shape[1], self.burn_in
        with self.agent_params.to_module(self.agent, preserve_module_state=False):
            if not self._sequence_agent:  # through the agent's keys
                q = self._call_agent(batch, z_seq, slice(None) if self.double_q else slice(0, L))
                return q[:, :L], (q[:, L].detach() if self.double_q else None)
            h0, obs, prev = batch.hidden[:, 0], batch.obs_seq, batch.prev_seq
            if not self._stepping_agent:  # the minimal protocol: one call, sliced
                q = net.sequence(obs, prev, h0, z=z_seq, state=self._agent_state(batch))
                return q[:, :L], (q[:, L].detach() if self.double_q else None)
            pieces, hidden = [], h0
            for start, end, grad in ((0, B, False), (B, L, True)):  # burn-in, learned steps
                if start == end:
                    continue
                steps = slice(start, end)
                with torch.set_grad_enabled(grad and torch.is_grad_enabled()):
                    q, hidden = net.sequence(
                        obs[:, steps],
                        prev[:, steps],
                        hidden,
                        z=_at(z_seq, steps),
                        state=self._agent_state(batch, steps),
                        return_hidden=True,
                    )
                pieces.append(q)
            q_boot = None
            if self.double_q:  # one more step from the last hidden state, without autograd
                with torch.no_grad():
                    state = self._agent_state(batch, L)
                    q_boot, _ = net.step(obs[:, L], prev[:, L], hidden, _at(z_seq, L), state)
        return torch.cat(pieces, 1) if len(pieces) > 1 else pieces[0], q_boot

    def _call_agent(self, batch: LossBatch, z_seq, steps: slice) -> torch.Tensor:
        """The agent's TensorDictModule on ``steps`` of the ``L + 1`` inputs under TorchRL's
        recurrent mode; returns ``action_value [S, steps, N, A]``."""
        k = self.tensor_keys
        obs = batch.obs_seq[:, steps]
        S, L = obs.shape[:2]
        inputs = TensorDict({}, batch_size=[S, L], device=obs.device)
        inputs.set(k.observation, obs)
        if batch.prev_seq is not None:
            inputs.set(k.prev_action, batch.prev_seq[:, steps])
        if batch.hidden is not None:  # the stored state at the start (recurrent agents read step 0)
            h0 = batch.hidden[:, :1]
            inputs.set(k.rnn_hidden, h0.expand(S, L, *h0.shape[2:]))
        if batch.is_init is not None:  # the bootstrap input never starts an episode
            is_init = torch.cat([batch.is_init, torch.zeros_like(batch.is_init[:, :1])], 1)
            inputs.set(k.is_init, is_init[:, steps].unsqueeze(-1))
        if z_seq is not None:
            inputs.set(k.z, z_seq[:, steps])
        if self._reads_own_state():
            state = batch.state_seq[:, steps]  # with the trailing dims the batch gives it
            inputs.set(k.state, state.reshape(*state.shape[:2], *batch.state_shape))
        with set_recurrent_mode(True):
            q = self.agent(inputs).get(k.action_value, None)
        if q is None:
            raise KeyError(
                f"ICCOLoss: the agent did not write action_value={k.action_value!r} (its "
                f"out_keys: {self.agent.out_keys}); rename with set_keys(action_value=...)"
            )
        return q

    def mixer_inputs(self, tensordict: TensorDictBase) -> tuple[dict, dict]:
        """Every input the mixer reads besides ``local_value``, from the batch and from its
        ``"next"`` entry (``{key: tensor}`` each); a key the mixer reads and the batch lacks, or
        a ``local_value``/``global_value`` the mixer does not read/write, fails naming it."""
        k, mixer = self.tensor_keys, self.mixer
        local = unravel_key(k.local_value)
        in_keys = [unravel_key(key) for key in mixer.in_keys]
        if local not in in_keys:
            raise KeyError(
                f"ICCOLoss writes the agents' chosen values to local_value={k.local_value!r} but "
                f"the mixer reads {mixer.in_keys}: rename with set_keys(local_value=...)"
            )
        if not _is_plain(mixer, k.global_value) and unravel_key(k.global_value) not in [
            unravel_key(key) for key in mixer.out_keys
        ]:
            raise KeyError(
                f"ICCOLoss reads global_value={k.global_value!r} but the mixer writes "
                f"{mixer.out_keys}: rename with set_keys(global_value=...)"
            )
        found = []
        for source in (tensordict, tensordict.get("next")):
            inputs = {}
            for key in in_keys:
                if key != local:
                    value = source.get(key, None)
                    if value is None:
                        raise KeyError(
                            f"ICCOLoss: the mixer reads {key!r}, absent from the batch (or its "
                            f"'next' entry); mixer in_keys {mixer.in_keys}, the agents' values go "
                            f"to local_value={k.local_value!r}"
                        )
                    inputs[key] = value.contiguous()
            found.append(inputs)
        return found[0], found[1]

    def _mix(self, params: TensorDictParams, q: torch.Tensor, inputs: dict) -> torch.Tensor:
        """The mixer through its keys: ``q [S, L, N]`` as ``local_value`` and ``inputs`` (from
        :meth:`mixer_inputs`); returns ``[S, L, 1]``."""
        k, mixer = self.tensor_keys, self.mixer
        local = unravel_key(k.local_value)
        inputs = {local: q.unsqueeze(-1).contiguous(), **inputs}
        with params.to_module(mixer, preserve_module_state=False):
            if _is_plain(mixer, k.global_value):  # what TensorDictModule does, without the td
                return mixer.module(*(inputs[unravel_key(key)] for key in mixer.in_keys))
            td = TensorDict({}, batch_size=q.shape[:2], device=q.device)
            for key, value in inputs.items():
                td.set(key, value)
            return mixer(td).get(k.global_value)

    # ------------------------------------------------------------------ consistency
    def _consistency(self, batch: LossBatch, z_seq, loc_w, scale_w) -> dict[str, torch.Tensor]:
        """L_CE over the broadcast windows ``[wT, (w+1)T)`` of every sequence: a window that starts
        at a broadcast step in the sequence's episode is scored on the steps its z is held."""
        T, (S, L) = self.period, batch.mask.shape
        W = loc_w.shape[1]

        def windows(value):  # [S, L, ...] -> [S * W, T, ...] (a trailing partial window dropped)
            return value[:, : W * T].reshape(S * W, min(T, L), *value.shape[2:])

        step, mask = windows(batch.step_count), windows(batch.mask)
        starts = (step[:, 0] % T == 0) & mask[:, 0]  # [S * W]
        period_id = step // T
        held = mask & (period_id == period_id[:, :1]) & starts[:, None]
        z0 = z_seq[:, : W * T : T].flatten(0, 1)  # [S * W, N, Z]
        scale0 = scale_w.flatten(0, 1)
        present = present_robots(self.layout, windows(batch.state)[:, 0], z0.shape[1])  # [S * W, N]
        w = starts.to(z0.dtype)[:, None] * present  # scored windows x robots present at their start
        denom = w.sum().clamp_min(1.0)
        entropy = (w * gaussian_entropy(scale0)).sum() / denom
        scored = entropy  # what the loss weighs: the entropy, or its clamped dimensions (COPA)
        if self.ce_clamp:
            scored = (w * _entropy_terms(scale0).clamp(*ENTROPY_CLAMP).sum(-1)).sum() / denom
        out = {"entropy": entropy.detach(), "ce_neg_entropy": -self.entropy_coef * scored}
        loss = out["ce_neg_entropy"]
        if self.posterior is not None:
            # Windows that are not scored keep one (dummy) factor so the product stays defined.
            first = torch.arange(held.shape[1], device=held.device) == 0
            factor_mask = held | (~starts[:, None] & first)
            inputs = (z0, windows(batch.state), windows(batch.action), windows(batch.obs))
            scored = None
            if self.ce_clamp:  # COPA: each dimension's (and step's) log-density in [-1000, 0]
                terms = self.posterior.module.log_prob_terms(*inputs, factor_mask)
                log_q = terms.sum((1, -1))
                scored = (w * terms.clamp(*LOG_Q_CLAMP).sum((1, -1))).sum() / denom
            else:
                log_q = self.posterior.module(*inputs, factor_mask)  # [S * W, N]
            mean_log_q = (w * log_q).sum() / denom
            scored = mean_log_q if scored is None else scored
            out.update(log_q=mean_log_q.detach(), ce_nll=-self.ce_coef * scored)
            loss = loss + out["ce_nll"]
        out["loss_ce"] = loss
        return out


class _Holder(nn.Module):
    """Holds a module as ``.module`` (the state-dict names of a TensorDictModule wrapper)."""

    def __init__(self, module: nn.Module):
        super().__init__()
        self.module = module


def _is_plain(module, out_key) -> bool:
    """Whether ``module`` is a plain keyed call ``module(*in_keys) -> out_key`` (no hooks)."""
    return (
        type(module) in _PLAIN_MODULES
        and module._kwargs is None
        and module.method is None
        and not module.method_kwargs
        and module._forward_hooks == {}
        and module._forward_pre_hooks == {}
        and [unravel_key(key) for key in module.out_keys] == [unravel_key(out_key)]
    )


def _entropy_terms(scale: torch.Tensor) -> torch.Tensor:
    """Each dimension's entropy of a diagonal Gaussian (their sum: ``gaussian_entropy``)."""
    return 0.5 * math.log(2 * math.pi * math.e) + scale.log()


def _taken(q: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """The values of the actions ``index [..., N, 1]`` in ``q [..., N, A]`` -> ``[..., N]``, or in
    every channel of ``q [..., N, C, A]`` -> ``[..., N, C]``."""
    if q.dim() > index.dim():
        index = index.unsqueeze(-2).expand(*q.shape[:-1], 1)
    return q.gather(-1, index).squeeze(-1)


def _at(value: torch.Tensor | None, steps) -> torch.Tensor | None:
    """``value[:, steps]`` for optional inputs (z without a coordinator)."""
    return None if value is None else value[:, steps]


def total_loss(losses: TensorDictBase) -> torch.Tensor:
    """Sum of the ``loss_*`` entries (the convention of TorchRL losses)."""
    return sum(v for k, v in losses.items() if k.startswith("loss_"))
