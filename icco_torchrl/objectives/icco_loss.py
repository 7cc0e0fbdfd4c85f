"""ICCOLoss: QMIX TD loss conditioned on the coordinator's z, plus the consistency (CE) term.

One loss covers every Q-learning method of the paper:

=================  ==========================  ==================
method             modules                     flags
=================  ==========================  ==================
ICCO               agent(z), coordinator,      ce_coef > 0
                   mixer, posterior
ICCO w/o CE        agent(z), coordinator, mixer ce_coef = 0
QMIX               agent, mixer                (no coordinator)
QMIX (FULL)        agent(full_state), mixer    (no coordinator)
=================  ==========================  ==================

Input: segments ``[S, T]`` (TorchRL layout, time last) that start at a broadcast step
(``step_count % period == 0``), as cut by :class:`icco_torchrl.training.segments.SegmentCutter`.

Recurrent state (R2D2 "stored state"): the agent's GRU starts from the hidden state recorded at
the segment's first step during collection, and the whole segment (T+1 observations: the T
steps and the final next-observation) runs through one ``nn.GRU`` call for the target network;
the online network runs the T steps with autograd and, for double-Q, the bootstrap step
without. Steps after an episode end inside a segment are masked out.

z: the online z of the segment is rebuilt as ``mu_phi(s_0) + sigma_phi(s_0) * eps_0`` with the
noise ``eps_0`` stored at collection, so gradients of L_RL reach the coordinator through z. The
bootstrap at a new broadcast step uses the target coordinator with fresh noise (COPA).

L_CE = ce_coef * (-log q_xi(z_0 | zeta, s_0, v_0)) + entropy_coef * (-H(N(mu_phi(s_0), sigma_phi(s_0)))).
"""

from __future__ import annotations

from dataclasses import dataclass

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

REWARD_REDUCTIONS = ("mean", "sum")
_PLAIN_MODULES = (
    TensorDictModule,
    TensorModule,
)  # modules whose call is exactly module(*in_keys) -> out_keys


class NonFiniteLossError(FloatingPointError):
    """Raised instead of stepping an optimiser on a NaN/inf loss."""


class ICCOLoss(LossModule):
    """TD + consistency loss over segments for ICCO and its QMIX baselines.

    Args:
        agent: the agents' Q-network as a TensorDictModule writing ``action_value`` ``[..., N, A]``.
            A :class:`~icco_torchrl.modules.RecurrentQNet` (or any module with
            ``sequence(obs, prev_action, hidden0, z=None, state=None)`` and the attributes ``hidden``,
            ``z_dim``, ``full_state``) runs each segment in one call from the stored hidden state;
            with ``step(...)`` and ``sequence(..., return_hidden=True)`` as well, double-Q skips the
            backward pass of the bootstrap step. Any other TensorDictModule (a TorchRL
            ``MultiAgentMLP``, a ``GRUModule`` pipeline, ...) is called through its keys on the
            segment's ``[S, T+1]`` tensordict under TorchRL's ``set_recurrent_mode(True)``; the
            loss writes the inputs it reads under its own key names (``set_keys``), with
            ``is_init`` for the steps that start an episode.
        mixer: TensorDictModule mixing ``local_value [.., N, 1]`` (and whatever else it reads, e.g.
            the state, read from the segment and its ``"next"`` entry) into ``global_value [.., 1]``:
            TorchRL's ``QMixer`` or ``VDNMixer``, or :func:`~icco_torchrl.modules.make_mixer`.
        coordinator: TensorDictModule wrapping a :class:`~icco_torchrl.modules.Coordinator`, or None (QMIX).
        posterior: a :class:`~icco_torchrl.modules.Posterior` (``make_posterior``), or None. It scores
            whole segments with the tensors the loss reads through its own keys.

    Keyword Args:
        gamma: discount.
        td_lambda: lambda of the TD(lambda) target inside each segment (0: one-step TD, the
            default). The lambda-return of step t mixes the target Q_tot of the next states of
            steps t..T-1 (Peng's uncorrected Q(lambda), pymarl2's recipe), bootstrapping from the
            target networks at the segment's end and at an episode end inside the segment.
            :meth:`make_value_estimator` sets the same thing TorchRL's way.
        double_q: bootstrap with the online argmax evaluated by the target networks.
        ce_coef: weight of ``-log q`` (COPA: 1e-3); 0 disables the CE term (ICCO w/o CE).
        entropy_coef: weight of ``-H`` (COPA: 1e-4).
        reward_reduction: how per-agent rewards ``[S, T, N, 1]`` (TorchRL multi-agent envs such as
            VMAS) become the team reward: ``"mean"`` (TorchRL's QMIX example) or ``"sum"``. A team
            reward ``[S, T, 1]`` is used as it is.
        split_instruction: learn the instruction reward with its own value head (Q = Q_task + Q_inst
            per agent, the agent built with ``value_heads=2``): Q_task is mixed by ``mixer`` and
            trained on ``reward - inst_reward``, Q_inst is summed over agents (VDN: the instruction
            reward is a sum of per-robot terms) and trained on ``inst_reward`` (read under
            ``"next"``, the team's scaled instruction reward). Both bootstrap at the argmax of the
            summed Q, so the greedy policy is the one the joint Q would give; the small dense
            instruction reward no longer has to be learned through the task's noisy values.
        check_finite: raise :class:`NonFiniteLossError` on a NaN/inf loss (one host sync per call).
    """

    @dataclass
    class _AcceptedKeys:
        """Every key the loss reads or writes; rename with ``set_keys(...)``.

        ``reward``, ``done`` and ``terminated`` are read under ``"next"`` (team ``[S, T, 1]`` or per
        agent ``[S, T, N, 1]``). ``mask`` is optional: without it, the steps after an episode end
        (``done``) or a new start (``is_init``) inside a segment are left out. ``state`` may have
        any trailing shape (flattened for the coordinator and posterior, as it is for the mixer).
        ``prev_action`` and ``rnn_hidden`` are read for recurrent agents, ``z``, ``z_noise`` and
        ``step_count`` with a coordinator. ``action_value`` is what the agent writes,
        ``local_value``/``global_value`` what the mixer reads/writes.
        """

        observation: NestedKey = ("agents", "observation")
        state: NestedKey = "state"
        action: NestedKey = ("agents", "action")
        prev_action: NestedKey = ("agents", "prev_action")
        rnn_hidden: NestedKey = ("agents", "rnn_hidden")
        z: NestedKey = ("agents", "z")
        z_noise: NestedKey = ("agents", "z_noise")
        step_count: NestedKey = "step_count"
        is_init: NestedKey = "is_init"
        reward: NestedKey = "reward"
        done: NestedKey = "done"
        terminated: NestedKey = "terminated"
        mask: NestedKey = "mask"
        inst_reward: NestedKey = ("events", "inst_reward")
        action_value: NestedKey = ("agents", "action_value")
        local_value: NestedKey = ("agents", "chosen_action_value")
        global_value: NestedKey = "chosen_action_value"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys
    default_value_estimator = ValueEstimators.TD0

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
        posterior: TensorDictModule | None = None,
        *,
        gamma: float = 0.99,
        td_lambda: float = 0.0,
        double_q: bool = True,
        ce_coef: float = 1e-3,
        entropy_coef: float = 1e-4,
        reward_reduction: str = "mean",
        split_instruction: bool = False,
        check_finite: bool = True,
    ):
        super().__init__()
        self._set_discount(gamma, td_lambda)
        if ce_coef < 0 or entropy_coef < 0:
            raise ValueError(
                f"ce_coef and entropy_coef must be >= 0, got {ce_coef}, {entropy_coef}"
            )
        if reward_reduction not in REWARD_REDUCTIONS:
            raise ValueError(
                f"reward_reduction must be one of {REWARD_REDUCTIONS}, got {reward_reduction!r}"
            )
        self.reward_reduction = reward_reduction
        self.has_coordinator = coordinator is not None
        net = agent.module
        # The sequence protocol (RecurrentQNet and stand-ins): segments in one call from the stored state.
        self._sequence_agent = hasattr(net, "sequence")
        if hasattr(net, "z_dim") and self.has_coordinator != bool(net.z_dim):
            raise ValueError("the agent takes z (z_dim > 0) exactly when a coordinator is given")
        if ce_coef > 0 and self.has_coordinator and posterior is None:
            raise ValueError("ce_coef > 0 needs a posterior module")
        self.double_q, self.check_finite = double_q, check_finite
        self.split_instruction = bool(split_instruction)
        if self.split_instruction and getattr(net, "value_heads", 1) != 2:
            raise ValueError(
                "split_instruction needs an agent with two value heads (make_agent(..., value_heads=2))"
            )
        self.use_ce = self.has_coordinator and (ce_coef > 0 or entropy_coef > 0)
        self.ce_coef, self.entropy_coef = float(ce_coef), float(entropy_coef)
        self.convert_to_functional(agent, "agent", create_target_params=True)
        self.convert_to_functional(mixer, "mixer", create_target_params=True)
        if self.has_coordinator:
            self.convert_to_functional(coordinator, "coordinator", create_target_params=True)
            self.period = coordinator.module.period
        # The posterior has no target copy: it only appears in L_CE. Held as ``posterior.module`` (the
        # parameter names of checkpoints made when it came wrapped in a TensorDictModule).
        if posterior is not None and not isinstance(posterior, TensorDictModule):
            posterior = _Holder(posterior)
        self.posterior = posterior if self.has_coordinator and ce_coef > 0 else None

    def _set_discount(self, gamma: float, td_lambda: float) -> None:
        if not 0 <= gamma <= 1:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if not 0 <= td_lambda <= 1:
            raise ValueError(f"td_lambda must be in [0, 1], got {td_lambda}")
        self.gamma, self.td_lambda = float(gamma), float(td_lambda)

    def make_value_estimator(
        self, value_type: ValueEstimators | None = None, **hyperparams
    ) -> ICCOLoss:
        """TorchRL's way to choose the target: ``TD0`` (one-step, the default), ``TD1`` (the return to the
        segment's end) or ``TDLambda`` (``lmbda``), each with ``gamma``. The targets are computed inside
        the loss's segments (see ``td_lambda``); other estimators (GAE, V-trace) are for actor-critic
        losses and are refused."""
        value_type = self.default_value_estimator if value_type is None else value_type
        hp = dict(hyperparams)
        gamma = hp.pop("gamma", self.gamma)
        hp.pop(
            "differentiable", None
        )  # TorchRL's default kwarg; the targets never carry gradient here
        lambdas = {ValueEstimators.TD0: 0.0, ValueEstimators.TD1: 1.0}
        if value_type == ValueEstimators.TDLambda:
            lam = hp.pop("lmbda", self.td_lambda or 0.95)
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

    def _forward_value_estimator_keys(
        self, **kwargs
    ) -> None:  # no value estimator object: keys are read directly
        pass

    @property
    def metric_keys(self) -> tuple[str, ...]:
        """The entries :meth:`forward` returns with this configuration (``loss_*`` are summed by
        :func:`total_loss`; the others are detached summaries)."""
        keys = ("loss_td", "q_taken", "q_tot", "td_error")
        if self.split_instruction:
            keys += ("loss_td_inst", "q_inst")
        if self.use_ce:
            keys += ("loss_ce", "ce_neg_entropy", "entropy")
            if self.posterior is not None:
                keys += ("ce_nll", "log_q")
        return keys

    def _reads(self, key: NestedKey) -> bool:
        """Whether the (non-sequence) agent's TensorDictModule reads ``key``."""
        return unravel_key(key) in [unravel_key(k) for k in self.agent.in_keys]

    # ------------------------------------------------------------------ input checks
    def _get(
        self,
        td: TensorDictBase,
        key: NestedKey,
        expected: str,
        ndim: int | None = None,
        trailing=None,
        optional: bool = False,
    ):
        value = td.get(key, None)
        if value is None:
            if optional:
                return None
            raise KeyError(
                f"ICCOLoss needs key {key!r} with shape {expected}; present: "
                f"{sorted(map(str, td.keys(True, True)))[:20]}"
            )
        if (ndim is not None and value.dim() != ndim) or (
            trailing is not None and tuple(value.shape[2:]) != trailing
        ):
            raise ValueError(
                f"ICCOLoss: key {key!r} must have shape {expected}, got {list(value.shape)}"
            )
        return value

    def _team(self, td: TensorDictBase, key: NestedKey, N: int, kind: str, optional: bool = False):
        """A team quantity ``[S, T, 1]`` from a team ``[S, T, 1]`` or per-agent ``[S, T, N, 1]`` entry."""
        expected = "[S, T, 1] (or per agent [S, T, N, 1])"
        value = self._get(td, key, expected, optional=optional)
        if value is None:
            return None
        if tuple(value.shape[2:]) == (N, 1):
            if kind == "reward":
                return value.mean(-2) if self.reward_reduction == "mean" else value.sum(-2)
            return value.all(-2)  # a team's episode ends when every agent's does
        if tuple(value.shape[2:]) != (1,):
            raise ValueError(
                f"ICCOLoss: key {key!r} must have shape {expected}, got {list(value.shape)}"
            )
        return value

    def _read(self, td: TensorDictBase) -> dict[str, torch.Tensor]:
        if td.batch_dims != 2:
            raise ValueError(
                f"ICCOLoss expects segments with batch [S, T] (time last), got batch {list(td.batch_size)}"
            )
        k, net = self.tensor_keys, self.agent.module
        S, T = td.batch_size
        N = self._get(td, k.action, "[S, T, N]", ndim=3).shape[-1]
        obs_shape = (N, self._get(td, k.observation, "[S, T, N, obs_dim]", ndim=4).shape[-1])
        recurrent = self._sequence_agent or self._reads(k.rnn_hidden)
        hidden_shape = f"[S, T, N, {net.hidden}]" if hasattr(net, "hidden") else "[S, T, N, hidden]"
        hidden = self._get(
            td,
            k.rnn_hidden,
            hidden_shape,
            optional=not recurrent,
            trailing=(N, net.hidden) if hasattr(net, "hidden") else None,
        )
        state = self._get(td, k.state, "[S, T, state_dim] (trailing dims are flattened)")
        next_state = self._get(
            td, _next(k.state), "[S, T, state_dim] (trailing dims are flattened)"
        )
        out = dict(
            td=td,
            obs=self._get(td, k.observation, "[S, T, N, obs_dim]", trailing=obs_shape),
            next_obs=self._get(td, _next(k.observation), "[S, T, N, obs_dim]", trailing=obs_shape),
            action=td.get(k.action),
            prev_action=self._get(
                td,
                k.prev_action,
                "[S, T, N]",
                trailing=(N,),
                optional=not (self._sequence_agent or self._reads(k.prev_action)),
            ),
            hidden=hidden,
            state=_flat_state(state, S, T),
            next_state=_flat_state(next_state, S, T),
            reward=self._team(td, _next(k.reward), N, "reward"),
            inst_reward=(
                self._get(td, _next(k.inst_reward), "[S, T] or [S, T, 1]").reshape(S, T, 1)
                if self.split_instruction
                else None
            ),
            terminated=self._team(td, _next(k.terminated), N, "flag"),
        )
        step_count = self._get(
            td, k.step_count, "[S, T, 1]", trailing=(1,), optional=not self.has_coordinator
        )
        is_init = self._team(td, k.is_init, N, "flag", optional=True)
        if is_init is None and step_count is not None:
            is_init = step_count == 0  # derived
        out["is_init"] = None if is_init is None else is_init.reshape(S, T).bool()
        mask = td.get(k.mask, None)
        if (
            mask is None
        ):  # steps after an episode end (done) or a new start (is_init) inside the segment
            done = self._team(td, _next(k.done), N, "flag", optional=True)
            mask = _episode_mask(out["terminated"] if done is None else done, out["is_init"])
        elif tuple(mask.shape) not in ((S, T), (S, T, 1)):
            raise ValueError(
                f"ICCOLoss: key {k.mask!r} must have shape [S, T] or [S, T, 1], got {list(mask.shape)}"
            )
        out["mask"] = mask.reshape(S, T).bool()
        if self.has_coordinator:
            z_shape = (N, net.z_dim)
            out["z"] = self._get(td, k.z, f"[S, T, N, {net.z_dim}]", trailing=z_shape)
            out["z_noise"] = self._get(td, k.z_noise, f"[S, T, N, {net.z_dim}]", trailing=z_shape)
            out["step_count"] = step_count.squeeze(-1)
            out["next_step_count"] = self._get(
                td, _next(k.step_count), "[S, T, 1]", trailing=(1,)
            ).squeeze(-1)
            # Does a broadcast fall inside a segment (z redrawn before its last next-state)? Then the
            # coordinator runs on every state; the check costs a host sync, so accelerators always do.
            inner = out["next_step_count"][:, :-1] % self.period == 0
            out["broadcast_inside"] = out["state"].device.type != "cpu" or bool(inner.any())
        # The T+1 inputs of the segment (its T steps and the final next-step), shared by the online
        # and the target networks.
        out["obs_seq"] = torch.cat([out["obs"][:, :1], out["next_obs"]], 1)  # [S, T+1, N, F]
        out["prev_seq"] = (
            torch.cat([out["prev_action"][:, :1], out["action"]], 1)
            if out["prev_action"] is not None
            else None
        )
        full_state = getattr(net, "full_state", False)
        out["state_seq"] = (
            torch.cat([out["state"][:, :1], out["next_state"]], 1) if full_state else None
        )
        return out

    # ------------------------------------------------------------------ pieces
    def _z_sequences(
        self,
        x: dict,
        params: TensorDictParams,
        first_noise: torch.Tensor,
        fresh_noise: torch.Tensor,
        every_step: bool | None = None,
    ):
        """z for the T+1 inputs of the segment under ``params``, plus (loc, scale) at step 0.

        Step 0: rebuilt from the stored noise if it is a broadcast step, else the stored z. Step
        k+1: a new draw at ``next_state[k]`` where ``next step_count % period == 0``, else held.

        Segments cut at broadcast steps with length ``period`` broadcast again only at their
        last next-state, so the coordinator runs on 2 states instead of T+1 (same values).
        ``every_step`` forces (True) or forbids (False) the all-states path; by default it is
        ``x["broadcast_inside"]`` (see ``_read``).
        """
        new = (x["next_step_count"] % self.period == 0)[..., None, None]  # [S, T, 1, 1]
        if every_step is None:
            every_step = x["broadcast_inside"]
        states = torch.cat(
            [x["state"][:, :1], x["next_state"] if every_step else x["next_state"][:, -1:]], 1
        )
        with params.to_module(self.coordinator, preserve_module_state=False):
            loc, scale = self.coordinator.module.distribution(states)  # one call
        loc0, scale0, loc_n, scale_n = loc[:, 0], scale[:, 0], loc[:, 1:], scale[:, 1:]
        broadcast0 = (x["step_count"][:, 0] % self.period == 0)[:, None, None]
        z0 = torch.where(broadcast0, loc0 + scale0 * first_noise, x["z"][:, 0])
        held = z0.unsqueeze(1)
        if every_step:
            z_next = torch.where(new, loc_n + scale_n * fresh_noise, held)
        else:  # steps 1..T-1 hold z0; only the last next-state may broadcast
            last = torch.where(new[:, -1:], loc_n + scale_n * fresh_noise[:, -1:], held)
            z_next = torch.cat([held.expand(-1, new.shape[1] - 1, -1, -1), last], 1)
        return torch.cat([held, z_next], 1), loc0, scale0

    def _q_sequence(
        self, params: TensorDictParams, x: dict, z_seq: torch.Tensor | None
    ) -> torch.Tensor:
        """Q over the T+1 inputs of the segment, ``[S, T+1, N, A]``, in one GRU call."""
        with params.to_module(self.agent, preserve_module_state=False):
            if not self._sequence_agent:
                return self._call_agent(x, z_seq, slice(None))[0]
            return self.agent.module.sequence(
                x["obs_seq"], x["prev_seq"], x["hidden"][:, 0], z=z_seq, state=x["state_seq"]
            )

    def _q_online(
        self, x: dict, z_seq: torch.Tensor | None
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Online Q over steps 0..T-1 (with autograd) and, for double-Q, at the bootstrap step T.

        Step T only feeds the double-Q argmax, so it is computed without autograd from the GRU
        state after step T-1 (agents with a ``step`` method; others run the T+1 sequence) and
        skipped altogether without double-Q. Same values as slicing one T+1 sequence.
        """
        net = self.agent.module
        first, last = slice(None, -1), -1  # steps 0..T-1, step T
        with self.agent_params.to_module(self.agent, preserve_module_state=False):
            if not self._sequence_agent:  # through the agent's keys
                if not self.double_q:
                    return self._call_agent(x, _at(z_seq, first), first)[0], None
                q = self._call_agent(x, z_seq, slice(None))[0]
                return q[:, first], q[:, last].detach()
            h0, obs, prev, state = x["hidden"][:, 0], x["obs_seq"], x["prev_seq"], x["state_seq"]
            if not self.double_q:
                return net.sequence(
                    obs[:, first], prev[:, first], h0, z=_at(z_seq, first), state=_at(state, first)
                ), None
            if not hasattr(net, "step"):
                q = net.sequence(obs, prev, h0, z=z_seq, state=state)
                return q[:, first], q[:, last].detach()
            q, h_last = net.sequence(
                obs[:, first],
                prev[:, first],
                h0,
                z=_at(z_seq, first),
                state=_at(state, first),
                return_hidden=True,
            )
            with torch.no_grad():
                q_boot, _ = net.step(
                    obs[:, last], prev[:, last], h_last, _at(z_seq, last), _at(state, last)
                )
        return q, q_boot

    def _call_agent(
        self, x: dict, z_seq: torch.Tensor | None, steps: slice
    ) -> tuple[torch.Tensor, TensorDictBase]:
        """The agent's TensorDictModule on the segment's inputs ``[S, L]`` (``steps`` of the T+1), under
        TorchRL's recurrent mode; returns ``action_value [S, L, N, A]`` and the tensordict."""
        k, td = self.tensor_keys, x["td"]
        obs = x["obs_seq"][:, steps]
        S, L = obs.shape[:2]
        inputs = TensorDict({}, batch_size=[S, L], device=obs.device)
        inputs.set(k.observation, obs)
        if x["prev_seq"] is not None:
            inputs.set(k.prev_action, x["prev_seq"][:, steps])
        if (
            x["hidden"] is not None
        ):  # the stored state at the segment's start (recurrent agents read step 0)
            h0 = x["hidden"][:, :1]
            inputs.set(k.rnn_hidden, h0.expand(S, L, *h0.shape[2:]))
        if x["is_init"] is not None:  # the bootstrap step T never starts an episode
            is_init = torch.cat([x["is_init"], torch.zeros_like(x["is_init"][:, :1])], 1)
            inputs.set(k.is_init, is_init[:, steps].unsqueeze(-1))
        if z_seq is not None:
            inputs.set(k.z, z_seq)
        if self._reads(k.state) and unravel_key(k.state) != unravel_key(k.observation):
            state = torch.cat(
                [td.get(k.state)[:, :1], td.get(_next(k.state))], 1
            )  # as the env gives it
            inputs.set(k.state, state[:, steps])
        with set_recurrent_mode(True):
            out = self.agent(inputs)
        q = out.get(k.action_value, None)
        if q is None:
            raise KeyError(
                f"ICCOLoss: the agent did not write action_value={k.action_value!r} "
                f"(its out_keys: {self.agent.out_keys}); rename with set_keys(action_value=...)"
            )
        return q, out

    def _mix(
        self, params: TensorDictParams, q: torch.Tensor, source: TensorDictBase
    ) -> torch.Tensor:
        """The mixer through its keys: ``q [S, T, N]`` as ``local_value``, every other input it reads
        from ``source`` (the segment, or its ``"next"`` entry); returns ``global_value [S, T, 1]``."""
        k = self.tensor_keys
        local, mixer = unravel_key(k.local_value), self.mixer
        in_keys = [unravel_key(key) for key in mixer.in_keys]
        if local not in in_keys:
            raise KeyError(
                f"ICCOLoss writes the agents' chosen values to local_value={k.local_value!r} but the "
                f"mixer reads {mixer.in_keys}: rename with set_keys(local_value=...)"
            )
        inputs = {local: q.unsqueeze(-1).contiguous()}
        for key in in_keys:
            if key != local:
                value = source.get(key, None)
                if value is None:
                    raise KeyError(
                        f"ICCOLoss: the mixer reads {key!r}, absent from the segment (or its 'next' "
                        f"entry); mixer in_keys {mixer.in_keys}, the agents' values go to "
                        f"local_value={k.local_value!r}"
                    )
                inputs[key] = value.contiguous()
        with params.to_module(mixer, preserve_module_state=False):
            if (
                type(mixer) in _PLAIN_MODULES
                and mixer._kwargs is None
                and mixer.method is None
                and not mixer.method_kwargs
                and mixer._forward_hooks == {}
                and mixer._forward_pre_hooks == {}
                and [unravel_key(key) for key in mixer.out_keys] == [unravel_key(k.global_value)]
            ):
                # What TensorDictModule does with positional in_keys and one output, without the tensordict.
                return mixer.module(*(inputs[key] for key in in_keys))  # [S, T, 1]
            td = TensorDict({}, batch_size=q.shape[:2], device=q.device)
            for key, value in inputs.items():
                td.set(key, value)
            value = mixer(td).get(k.global_value, None)
        if value is None:
            raise KeyError(
                f"ICCOLoss reads global_value={k.global_value!r} but the mixer writes "
                f"{mixer.out_keys}: rename with set_keys(global_value=...)"
            )
        return value  # [S, T, 1]

    # ------------------------------------------------------------------ forward
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        x = self._read(tensordict)
        mask = x["mask"]
        z_on = z_tgt = None
        if self.has_coordinator:
            fresh = torch.randn_like(x["z_noise"])  # [S, T, N, Z]
            z_on, loc0, scale0 = self._z_sequences(
                x, self.coordinator_params, x["z_noise"][:, 0], fresh
            )
            with torch.no_grad():
                z_tgt, _, _ = self._z_sequences(
                    x, self.target_coordinator_params, x["z_noise"][:, 0], fresh
                )

        q_online, q_boot = self._q_online(x, z_on)  # [S, T, N, A(*2)]
        action = x["action"].long().unsqueeze(-1)
        with torch.no_grad():
            q_target = self._q_sequence(self.target_agent_params, x, z_tgt)[:, 1:]
            greedy_source = (
                torch.cat([q_online[:, 1:], q_boot.unsqueeze(1)], 1) if self.double_q else q_target
            )
            if self.split_instruction:  # act on Q_task + Q_inst, as the policy does
                greedy_source = self.agent.module.combine(greedy_source)
            greedy = greedy_source.argmax(-1, keepdim=True)
        alive = (~x["terminated"]).to(q_online.dtype)
        weight = mask.to(q_online.dtype)
        n_valid = weight.sum().clamp_min(1.0)
        if self.split_instruction:
            A = q_online.shape[-1] // 2
            q_online, q_inst, q_target, q_target_inst = (
                q_online[..., :A],
                q_online[..., A:],
                q_target[..., :A],
                q_target[..., A:],
            )
            inst = q_inst.gather(-1, action).squeeze(-1).sum(-1, keepdim=True)  # VDN [S, T, 1]
            with torch.no_grad():
                inst_next = q_target_inst.gather(-1, greedy).squeeze(-1).sum(-1, keepdim=True)
                inst_target = self._targets(x["inst_reward"], alive, inst_next, mask)
            task_reward = x["reward"] - x["inst_reward"]
        chosen = q_online.gather(-1, action).squeeze(-1)  # [S, T, N]
        q_tot = self._mix(self.mixer_params, chosen, tensordict)
        with torch.no_grad():
            next_value = q_target.gather(-1, greedy).squeeze(-1)
            q_tot_next = self._mix(self.target_mixer_params, next_value, tensordict.get("next"))
            target = self._targets(
                task_reward if self.split_instruction else x["reward"], alive, q_tot_next, mask
            )

        td_error = (q_tot - target).squeeze(-1)  # [S, T]
        loss_td = (weight * td_error.pow(2)).sum() / n_valid
        out = {
            "loss_td": loss_td,
            "q_taken": (weight.unsqueeze(-1) * chosen.detach()).sum()
            / (n_valid * chosen.shape[-1]),
            "q_tot": (weight * q_tot.detach().squeeze(-1)).sum() / n_valid,
            "td_error": (weight * td_error.detach().abs()).sum() / n_valid,
        }
        if self.split_instruction:
            inst_error = (inst - inst_target).squeeze(-1)
            out["loss_td_inst"] = (weight * inst_error.pow(2)).sum() / n_valid
            out["q_inst"] = (weight * inst.detach().squeeze(-1)).sum() / n_valid
        if self.use_ce:
            out.update(self._consistency(x, z_on[:, 0], loc0, scale0, mask))
        if self.check_finite:
            bad = [
                name
                for name, v in out.items()
                if name.startswith("loss_") and not torch.isfinite(v).all()
            ]
            if bad:
                raise NonFiniteLossError(
                    f"non-finite loss terms {bad}: "
                    + ", ".join(f"{n}={v.item():.4g}" for n, v in out.items())
                )
        return TensorDict(out, [])

    def _targets(
        self, reward: torch.Tensor, alive: torch.Tensor, q_next: torch.Tensor, mask: torch.Tensor
    ):
        """One-step or lambda-return targets ``[S, T, 1]`` from the target ``Q_tot`` of each next state."""
        one_step = reward + self.gamma * alive * q_next
        if self.td_lambda == 0:
            return one_step
        # The return of step t continues into step t+1 only within one episode (mask[t+1]).
        cont = torch.cat([mask[:, 1:], torch.zeros_like(mask[:, :1])], 1).unsqueeze(-1)
        lam = self.td_lambda
        out = [one_step[:, -1]]
        for t in range(reward.shape[1] - 2, -1, -1):  # T - 1 steps of a short segment, backwards
            ahead = torch.where(cont[:, t], (1 - lam) * q_next[:, t] + lam * out[-1], q_next[:, t])
            out.append(reward[:, t] + self.gamma * alive[:, t] * ahead)
        return torch.stack(out[::-1], 1)

    def _consistency(self, x: dict, z0, loc0, scale0, mask) -> dict[str, torch.Tensor]:
        """L_CE on segments whose first step is a broadcast; factors limited to z0's hold period."""
        starts = x["step_count"][:, 0] % self.period == 0  # [S]
        period_id = x["step_count"] // self.period
        held = mask & (period_id == period_id[:, :1]) & starts[:, None]  # [S, T]
        w = starts.to(z0.dtype)
        denom = (w.sum() * z0.shape[1]).clamp_min(1.0)
        entropy = (w[:, None] * gaussian_entropy(scale0)).sum() / denom
        out = {"entropy": entropy.detach(), "ce_neg_entropy": -self.entropy_coef * entropy}
        loss = out["ce_neg_entropy"]
        if self.posterior is not None:
            # Rows that start mid-period keep one (dummy) factor so the product stays defined.
            factor_mask = held | (
                ~starts[:, None] & (torch.arange(held.shape[1], device=held.device) == 0)
            )
            log_q = self.posterior.module(
                z0, x["state"], x["action"], x["obs"], factor_mask
            )  # [S, N]
            mean_log_q = (w[:, None] * log_q).sum() / denom
            out.update(log_q=mean_log_q.detach(), ce_nll=-self.ce_coef * mean_log_q)
            loss = loss + out["ce_nll"]
        out["loss_ce"] = loss
        return out


class _Holder(nn.Module):
    """Holds a module as ``.module`` (the state-dict names of a TensorDictModule wrapper)."""

    def __init__(self, module: nn.Module):
        super().__init__()
        self.module = module


def _at(value: torch.Tensor | None, steps) -> torch.Tensor | None:
    """``value[:, steps]`` for optional inputs (z without a coordinator, state without full_state)."""
    return None if value is None else value[:, steps]


def _flat_state(state: torch.Tensor, S: int, T: int) -> torch.Tensor:
    """``[S, T, ...]`` -> ``[S, T, D]`` (any trailing shape flattened, a scalar state widened)."""
    return state.reshape(S, T, -1)


def _episode_mask(done: torch.Tensor, is_init: torch.Tensor | None) -> torch.Tensor:
    """``[S, T]``: False from the step after an episode end (``done [S, T, 1]``) or from a step that
    starts a new episode (``is_init [S, T]``, the first step excepted) to the segment's end."""
    ended = done.reshape(done.shape[0], -1).long()
    valid = (torch.cumsum(ended, 1) - ended) == 0
    if is_init is not None:
        started = is_init.long().clone()
        started[:, 0] = 0
        valid &= torch.cumsum(started, 1) == 0
    return valid


def _next(key: NestedKey) -> tuple:
    return ("next", *key) if isinstance(key, tuple) else ("next", key)


def total_loss(losses: TensorDictBase) -> torch.Tensor:
    """Sum of the ``loss_*`` entries (the convention of TorchRL losses)."""
    return sum(v for k, v in losses.items() if k.startswith("loss_"))
