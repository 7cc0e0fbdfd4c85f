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
from tensordict.utils import NestedKey
from torchrl.objectives import LossModule

from icco_torchrl.modules.coordinator import gaussian_entropy


class NonFiniteLossError(FloatingPointError):
    """Raised instead of stepping an optimiser on a NaN/inf loss."""


class ICCOLoss(LossModule):
    """TD + consistency loss over segments for ICCO and its QMIX baselines.

    Args:
        agent: TensorDictModule wrapping a :class:`~icco_torchrl.modules.RecurrentQNet` (shared by robots),
            or any module with ``sequence(obs, prev_action, hidden0, z=None, state=None)`` and the
            attributes ``hidden``, ``z_dim``, ``full_state``; with ``step(...)`` and
            ``sequence(..., return_hidden=True)`` as well, double-Q skips the backward pass of the
            bootstrap step.
        mixer: TensorDictModule wrapping a monotone mixer ``(Q [.., N, 1], state) -> [.., 1]``.
        coordinator: TensorDictModule wrapping a :class:`~icco_torchrl.modules.Coordinator`, or None (QMIX).
        posterior: TensorDictModule wrapping a :class:`~icco_torchrl.modules.Posterior`, or None.

    Keyword Args:
        gamma: discount.
        td_lambda: lambda of the TD(lambda) target inside each segment (0: one-step TD, the
            default). The lambda-return of step t mixes the target Q_tot of the next states of
            steps t..T-1 (Peng's uncorrected Q(lambda), pymarl2's recipe), bootstrapping from the
            target networks at the segment's end and at an episode end inside the segment.
        double_q: bootstrap with the online argmax evaluated by the target networks.
        ce_coef: weight of ``-log q`` (COPA: 1e-3); 0 disables the CE term (ICCO w/o CE).
        entropy_coef: weight of ``-H`` (COPA: 1e-4).
        check_finite: raise :class:`NonFiniteLossError` on a NaN/inf loss (one host sync per call).
    """

    @dataclass
    class _AcceptedKeys:
        """Every key the loss reads; rename with ``set_keys(...)``.

        ``reward`` and ``terminated`` are read under ``"next"``; ``mask`` is optional
        (absent means every step is valid).
        """

        observation: NestedKey = ("agents", "observation")
        state: NestedKey = "state"
        action: NestedKey = ("agents", "action")
        prev_action: NestedKey = ("agents", "prev_action")
        rnn_hidden: NestedKey = ("agents", "rnn_hidden")
        z: NestedKey = ("agents", "z")
        z_noise: NestedKey = ("agents", "z_noise")
        step_count: NestedKey = "step_count"
        reward: NestedKey = "reward"
        terminated: NestedKey = "terminated"
        mask: NestedKey = "mask"

    default_keys = _AcceptedKeys
    tensor_keys: _AcceptedKeys

    agent: TensorDictModule
    agent_params: TensorDictParams
    target_agent_params: TensorDictParams
    mixer: TensorDictModule
    mixer_params: TensorDictParams
    target_mixer_params: TensorDictParams
    coordinator: TensorDictModule
    coordinator_params: TensorDictParams
    target_coordinator_params: TensorDictParams

    def __init__(self, agent: TensorDictModule, mixer: TensorDictModule, coordinator: TensorDictModule | None = None,
                 posterior: TensorDictModule | None = None, *, gamma: float = 0.99, td_lambda: float = 0.0,
                 double_q: bool = True,
                 ce_coef: float = 1e-3, entropy_coef: float = 1e-4, check_finite: bool = True):
        super().__init__()
        if not 0 <= gamma <= 1:
            raise ValueError(f"gamma must be in [0, 1], got {gamma}")
        if not 0 <= td_lambda <= 1:
            raise ValueError(f"td_lambda must be in [0, 1], got {td_lambda}")
        self.td_lambda = float(td_lambda)
        if ce_coef < 0 or entropy_coef < 0:
            raise ValueError(f"ce_coef and entropy_coef must be >= 0, got {ce_coef}, {entropy_coef}")
        self.has_coordinator = coordinator is not None
        if self.has_coordinator != bool(agent.module.z_dim):
            raise ValueError("the agent takes z (z_dim > 0) exactly when a coordinator is given")
        if ce_coef > 0 and self.has_coordinator and posterior is None:
            raise ValueError("ce_coef > 0 needs a posterior module")
        self.gamma, self.double_q, self.check_finite = float(gamma), double_q, check_finite
        self.use_ce = self.has_coordinator and (ce_coef > 0 or entropy_coef > 0)
        self.ce_coef, self.entropy_coef = float(ce_coef), float(entropy_coef)
        self.convert_to_functional(agent, "agent", create_target_params=True)
        self.convert_to_functional(mixer, "mixer", create_target_params=True)
        if self.has_coordinator:
            self.convert_to_functional(coordinator, "coordinator", create_target_params=True)
            self.period = coordinator.module.period
        # The posterior has no target copy: it only appears in L_CE.
        self.posterior = posterior if self.has_coordinator and ce_coef > 0 else None

    def _forward_value_estimator_keys(self, **kwargs) -> None:  # no value estimator: keys are read directly
        pass

    # ------------------------------------------------------------------ input checks
    def _get(self, td: TensorDictBase, key: NestedKey, expected: str, ndim: int | None = None, trailing=None):
        value = td.get(key, None)
        if value is None:
            raise KeyError(f"ICCOLoss needs key {key!r} with shape {expected}; present: "
                           f"{sorted(map(str, td.keys(True, True)))[:20]}")
        if (ndim is not None and value.dim() != ndim) or (trailing is not None and tuple(value.shape[2:]) != trailing):
            raise ValueError(f"ICCOLoss: key {key!r} must have shape {expected}, got {list(value.shape)}")
        return value

    def _read(self, td: TensorDictBase) -> dict[str, torch.Tensor]:
        if td.batch_dims != 2:
            raise ValueError(f"ICCOLoss expects segments with batch [S, T] (time last), got batch {list(td.batch_size)}")
        k, net = self.tensor_keys, self.agent.module
        S, T = td.batch_size
        N = self._get(td, k.action, "[S, T, N]", ndim=3).shape[-1]
        obs_shape = (N, self._get(td, k.observation, "[S, T, N, obs_dim]", ndim=4).shape[-1])
        out = dict(
            obs=self._get(td, k.observation, "[S, T, N, obs_dim]", trailing=obs_shape),
            next_obs=self._get(td, _next(k.observation), "[S, T, N, obs_dim]", trailing=obs_shape),
            action=td.get(k.action),
            prev_action=self._get(td, k.prev_action, "[S, T, N]", trailing=(N,)),
            hidden=self._get(td, k.rnn_hidden, f"[S, T, N, {net.hidden}]", trailing=(N, net.hidden)),
            state=self._get(td, k.state, "[S, T, state_dim]", ndim=3),
            next_state=self._get(td, _next(k.state), "[S, T, state_dim]", ndim=3),
            reward=self._get(td, _next(k.reward), "[S, T, 1]", trailing=(1,)),
            terminated=self._get(td, _next(k.terminated), "[S, T, 1]", trailing=(1,)),
        )
        mask = td.get(k.mask, None)
        if mask is None:
            mask = torch.ones(S, T, dtype=torch.bool, device=td.device)
        elif tuple(mask.shape) not in ((S, T), (S, T, 1)):
            raise ValueError(f"ICCOLoss: key {k.mask!r} must have shape [S, T] or [S, T, 1], got {list(mask.shape)}")
        out["mask"] = mask.reshape(S, T).bool()
        if self.has_coordinator:
            z_shape = (N, net.z_dim)
            out["z"] = self._get(td, k.z, f"[S, T, N, {net.z_dim}]", trailing=z_shape)
            out["z_noise"] = self._get(td, k.z_noise, f"[S, T, N, {net.z_dim}]", trailing=z_shape)
            out["step_count"] = self._get(td, k.step_count, "[S, T, 1]", trailing=(1,)).squeeze(-1)
            out["next_step_count"] = self._get(td, _next(k.step_count), "[S, T, 1]", trailing=(1,)).squeeze(-1)
            # Does a broadcast fall inside a segment (z redrawn before its last next-state)? Then the
            # coordinator runs on every state; the check costs a host sync, so accelerators always do.
            inner = out["next_step_count"][:, :-1] % self.period == 0
            out["broadcast_inside"] = out["state"].device.type != "cpu" or bool(inner.any())
        # The T+1 inputs of the segment (its T steps and the final next-step), shared by the online
        # and the target networks.
        out["obs_seq"] = torch.cat([out["obs"][:, :1], out["next_obs"]], 1)                     # [S, T+1, N, F]
        out["prev_seq"] = torch.cat([out["prev_action"][:, :1], out["action"]], 1)
        out["state_seq"] = torch.cat([out["state"][:, :1], out["next_state"]], 1) if net.full_state else None
        return out

    # ------------------------------------------------------------------ pieces
    def _z_sequences(self, x: dict, params: TensorDictParams, first_noise: torch.Tensor, fresh_noise: torch.Tensor,
                     every_step: bool | None = None):
        """z for the T+1 inputs of the segment under ``params``, plus (loc, scale) at step 0.

        Step 0: rebuilt from the stored noise if it is a broadcast step, else the stored z. Step
        k+1: a new draw at ``next_state[k]`` where ``next step_count % period == 0``, else held.

        Segments cut at broadcast steps with length ``period`` broadcast again only at their
        last next-state, so the coordinator runs on 2 states instead of T+1 (same values).
        ``every_step`` forces (True) or forbids (False) the all-states path; by default it is
        ``x["broadcast_inside"]`` (see ``_read``).
        """
        new = (x["next_step_count"] % self.period == 0)[..., None, None]                        # [S, T, 1, 1]
        if every_step is None:
            every_step = x["broadcast_inside"]
        states = torch.cat([x["state"][:, :1], x["next_state"] if every_step else x["next_state"][:, -1:]], 1)
        with params.to_module(self.coordinator, preserve_module_state=False):
            loc, scale = self.coordinator.module.distribution(states)                          # one call
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

    def _q_sequence(self, params: TensorDictParams, x: dict, z_seq: torch.Tensor | None) -> torch.Tensor:
        """Q over the T+1 inputs of the segment, ``[S, T+1, N, A]``, in one GRU call."""
        with params.to_module(self.agent, preserve_module_state=False):
            return self.agent.module.sequence(x["obs_seq"], x["prev_seq"], x["hidden"][:, 0], z=z_seq,
                                              state=x["state_seq"])

    def _q_online(self, x: dict, z_seq: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Online Q over steps 0..T-1 (with autograd) and, for double-Q, at the bootstrap step T.

        Step T only feeds the double-Q argmax, so it is computed without autograd from the GRU
        state after step T-1 (agents with a ``step`` method; others run the T+1 sequence) and
        skipped altogether without double-Q. Same values as slicing one T+1 sequence.
        """
        net, h0 = self.agent.module, x["hidden"][:, 0]
        obs, prev, state = x["obs_seq"], x["prev_seq"], x["state_seq"]
        first, last = slice(None, -1), -1  # steps 0..T-1, step T
        with self.agent_params.to_module(self.agent, preserve_module_state=False):
            if not self.double_q:
                return net.sequence(obs[:, first], prev[:, first], h0, z=_at(z_seq, first), state=_at(state, first)), None
            if not hasattr(net, "step"):
                q = net.sequence(obs, prev, h0, z=z_seq, state=state)
                return q[:, first], q[:, last].detach()
            q, h_last = net.sequence(obs[:, first], prev[:, first], h0, z=_at(z_seq, first), state=_at(state, first),
                                     return_hidden=True)
            with torch.no_grad():
                q_boot, _ = net.step(obs[:, last], prev[:, last], h_last, _at(z_seq, last), _at(state, last))
        return q, q_boot

    def _mix(self, params: TensorDictParams, q: torch.Tensor, state: torch.Tensor) -> torch.Tensor:
        with params.to_module(self.mixer, preserve_module_state=False):
            return self.mixer.module(q.unsqueeze(-1).contiguous(), state.contiguous())          # [S, T, 1]

    # ------------------------------------------------------------------ forward
    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        x = self._read(tensordict)
        S, T = tensordict.batch_size
        mask = x["mask"]
        z_on = z_tgt = None
        if self.has_coordinator:
            fresh = torch.randn_like(x["z_noise"])                                               # [S, T, N, Z]
            z_on, loc0, scale0 = self._z_sequences(x, self.coordinator_params, x["z_noise"][:, 0], fresh)
            with torch.no_grad():
                z_tgt, _, _ = self._z_sequences(x, self.target_coordinator_params, x["z_noise"][:, 0], fresh)

        q_online, q_boot = self._q_online(x, z_on)                                             # [S, T, N, A], [S, N, A]
        chosen = q_online.gather(-1, x["action"].long().unsqueeze(-1)).squeeze(-1)               # [S, T, N]
        q_tot = self._mix(self.mixer_params, chosen, x["state"])
        with torch.no_grad():
            q_target = self._q_sequence(self.target_agent_params, x, z_tgt)[:, 1:]
            greedy_source = torch.cat([q_online[:, 1:], q_boot.unsqueeze(1)], 1) if self.double_q else q_target
            greedy = greedy_source.argmax(-1, keepdim=True)
            next_value = q_target.gather(-1, greedy).squeeze(-1)
            q_tot_next = self._mix(self.target_mixer_params, next_value, x["next_state"])
            target = self._targets(x["reward"], (~x["terminated"]).to(q_tot.dtype), q_tot_next, mask)

        td_error = (q_tot - target).squeeze(-1)                                                  # [S, T]
        weight = mask.to(td_error.dtype)
        n_valid = weight.sum().clamp_min(1.0)
        loss_td = (weight * td_error.pow(2)).sum() / n_valid
        out = {"loss_td": loss_td,
               "q_taken": (weight.unsqueeze(-1) * chosen.detach()).sum() / (n_valid * chosen.shape[-1]),
               "q_tot": (weight * q_tot.detach().squeeze(-1)).sum() / n_valid,
               "td_error": (weight * td_error.detach().abs()).sum() / n_valid}
        if self.use_ce:
            out.update(self._consistency(x, z_on[:, 0], loc0, scale0, mask))
        if self.check_finite:
            bad = [name for name, v in out.items() if name.startswith("loss_") and not torch.isfinite(v).all()]
            if bad:
                raise NonFiniteLossError(f"non-finite loss terms {bad}: "
                                         + ", ".join(f"{n}={v.item():.4g}" for n, v in out.items()))
        return TensorDict(out, [])

    def _targets(self, reward: torch.Tensor, alive: torch.Tensor, q_next: torch.Tensor, mask: torch.Tensor):
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
        starts = x["step_count"][:, 0] % self.period == 0                                        # [S]
        period_id = x["step_count"] // self.period
        held = mask & (period_id == period_id[:, :1]) & starts[:, None]                          # [S, T]
        w = starts.to(z0.dtype)
        denom = (w.sum() * z0.shape[1]).clamp_min(1.0)
        entropy = (w[:, None] * gaussian_entropy(scale0)).sum() / denom
        out = {"entropy": entropy.detach(), "ce_neg_entropy": -self.entropy_coef * entropy}
        loss = out["ce_neg_entropy"]
        if self.posterior is not None:
            # Rows that start mid-period keep one (dummy) factor so the product stays defined.
            factor_mask = held | (~starts[:, None] & (torch.arange(held.shape[1], device=held.device) == 0))
            log_q = self.posterior.module(z0, x["state"], x["action"], x["obs"], factor_mask)       # [S, N]
            mean_log_q = (w[:, None] * log_q).sum() / denom
            out.update(log_q=mean_log_q.detach(), ce_nll=-self.ce_coef * mean_log_q)
            loss = loss + out["ce_nll"]
        out["loss_ce"] = loss
        return out


def _at(value: torch.Tensor | None, steps) -> torch.Tensor | None:
    """``value[:, steps]`` for optional inputs (z without a coordinator, state without full_state)."""
    return None if value is None else value[:, steps]


def _next(key: NestedKey) -> tuple:
    return ("next", *key) if isinstance(key, tuple) else ("next", key)


def total_loss(losses: TensorDictBase) -> torch.Tensor:
    """Sum of the ``loss_*`` entries (the convention of TorchRL losses)."""
    return sum(v for k, v in losses.items() if k.startswith("loss_"))
