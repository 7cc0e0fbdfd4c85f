"""Q-learning targets over replayed sequences: one-step and lambda-returns.

The lambda-return is Peng's uncorrected Q(lambda) as pymarl2 builds it
(``build_td_lambda_targets``), written as the same backward recursion over the time dim:

    G_t = r_t + gamma * alive_t * [(1 - lambda) * Q'_{t+1} + lambda * G_{t+1}]

where ``Q'_{t+1}`` is the target network's value of the next state of step t. The recursion
bootstraps fully (``G_{t+1} -> Q'_{t+1}``) at the sequence's last step and where the next step
belongs to another episode (``cont_t`` False), so no return ever crosses an episode end.
"""

from __future__ import annotations

import torch


def lambda_returns(
    reward: torch.Tensor,
    alive: torch.Tensor,
    next_value: torch.Tensor,
    cont: torch.Tensor,
    *,
    gamma: float,
    lmbda: float,
) -> torch.Tensor:
    """Targets ``[S, L, 1]`` from ``reward``, ``alive`` (1 - terminated) and ``next_value``, all
    ``[S, L, 1]``, and ``cont [S, L, 1]`` (bool: step t+1 continues step t's episode inside the
    sequence). ``lmbda = 0`` gives the one-step targets, ``lmbda = 1`` the discounted return to
    the sequence's end (or the episode's).

    Examples:
        >>> import torch
        >>> r = torch.tensor([[[1.0], [0.0], [2.0]]])
        >>> ones, q = torch.ones(1, 3, 1), torch.tensor([[[10.0], [20.0], [30.0]]])
        >>> cont = torch.tensor([[[True], [True], [False]]])
        >>> lambda_returns(r, ones, q, cont, gamma=0.5, lmbda=0.0).flatten().tolist()
        [6.0, 10.0, 17.0]
        >>> lambda_returns(r, ones, q, cont, gamma=0.5, lmbda=1.0).flatten().tolist()
        [5.25, 8.5, 17.0]
    """
    one_step = reward + gamma * alive * next_value
    if lmbda == 0:
        return one_step
    L = reward.shape[1]
    out = [one_step[:, L - 1]]
    # A loop over time (the L of one sequence), as pymarl2's: each step needs the next one's return.
    for t in range(L - 2, -1, -1):
        ahead = torch.where(
            cont[:, t], (1 - lmbda) * next_value[:, t] + lmbda * out[-1], next_value[:, t]
        )
        out.append(reward[:, t] + gamma * alive[:, t] * ahead)
    return torch.stack(out[::-1], 1)
