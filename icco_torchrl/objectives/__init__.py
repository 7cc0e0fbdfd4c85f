"""Losses and target-network updaters."""

from torchrl.objectives import HardUpdate, SoftUpdate

from icco_torchrl.objectives.icco_loss import ICCOLoss, NonFiniteLossError, total_loss
from icco_torchrl.objectives.inputs import LossBatch
from icco_torchrl.objectives.returns import lambda_returns

__all__ = [
    "ICCOLoss",
    "LossBatch",
    "NonFiniteLossError",
    "lambda_returns",
    "make_target_updater",
    "total_loss",
]


def make_target_updater(
    loss: ICCOLoss, kind: str = "hard", *, interval: int = 200, tau: float = 0.005
):
    """TorchRL updater for every ``target_*_params`` of ``loss``.

    ``kind="hard"`` copies on every ``interval``-th ``step()`` call. TorchRL's ``HardUpdate``
    copies when its counter (starting at 0) equals the interval, i.e. on call ``interval + 1``;
    we pass ``interval - 1`` so the period is exactly ``interval``. ``kind="soft"`` moves the
    targets by ``tau`` toward the online weights on every call.
    """
    if kind == "hard":
        if interval < 1:
            raise ValueError(f"target update interval must be >= 1, got {interval}")
        return HardUpdate(loss, value_network_update_interval=interval - 1)
    if kind == "soft":
        if not 0 < tau <= 1:
            raise ValueError(f"tau must be in (0, 1], got {tau}")
        return SoftUpdate(loss, tau=tau)
    raise ValueError(f"target update kind must be 'hard' or 'soft', got {kind!r}")
