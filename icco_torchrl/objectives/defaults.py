"""The one home of the loss's defaults: what :class:`~icco_torchrl.objectives.ICCOLoss` uses when
an argument is left out, and what ``icco train method=icco`` trains with (the config schema,
:mod:`icco_torchrl.training.config`, takes its defaults from here; imports point down, so the
loss never reads the config). ``ICCOLoss(agent, mixer, coordinator, posterior)`` is therefore the
method ``icco train`` trains (``tests/test_loss.py`` checks it).

Each value is measured or argued where the config field is commented (``method.ce_coef``,
``train.td_lambda``, ...).

Examples:
    >>> from icco_torchrl.objectives.defaults import LOSS_DEFAULTS
    >>> LOSS_DEFAULTS.ce_coef, LOSS_DEFAULTS.td_lambda, LOSS_DEFAULTS.ce_clamp
    (0.001, 0.6, True)
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class LossDefaults:
    """The defaults of :class:`~icco_torchrl.objectives.ICCOLoss`'s keyword arguments that the
    config sets (``train.gamma``, ``train.td_lambda``, ``train.burn_in``, ``train.double_q``,
    ``train.ce_clamp``, ``method.ce_coef``, ``method.entropy_coef``)."""

    gamma: float = 0.99
    # lambda of the lambda-return over each replayed sequence (pymarl2: 0.6; 0: one-step targets)
    td_lambda: float = 0.6
    burn_in: int = 0
    double_q: bool = True
    # weight of -log q (COPA: 1e-3; the paper: 1), chosen by the screen in experiments/consistency
    ce_coef: float = 1e-3
    # weight of -H (COPA: 1e-4), chosen with ce_coef
    entropy_coef: float = 1e-3
    # COPA's clamps of the consistency term: log q per dimension to [-1000, 0], entropy per
    # dimension to [0, 10]
    ce_clamp: bool = True


LOSS_DEFAULTS = LossDefaults()
# COPA's clamps (``ce_clamp``): each dimension's log-density (and each step's, for a posterior
# that sums its factors' log-likelihoods), and each dimension's entropy.
LOG_Q_CLAMP = (-1000.0, 0.0)
ENTROPY_CLAMP = (0.0, 10.0)
