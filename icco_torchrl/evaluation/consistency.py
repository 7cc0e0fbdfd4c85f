"""What the consistency term is for, measured on any checkpoint with a coordinator.

Two measures, both from one set of rollouts of the checkpoint's policy on the training
distribution (random-walk instructions, the env's own generator), defined and justified in
``docs/consistency.md``:

- :func:`mi_lower_bound`: the paper's lower bound on the mutual information between the
  coordinator's z and the team's behaviour, ``I(z; zeta, s, v) >= E[log q(z | zeta, s, v)] +
  H(z | s, v)`` (Eq. "mutual information"), per robot, in nats. ``H`` is the coordinator's own
  Gaussian entropy (exact); ``q`` is a posterior of the checkpoint's architecture (its
  ``method.posterior`` and ``method.posterior_input``) **fitted after training**, from scratch, on
  the rollouts of 3/4 of the episodes, and scored on the other, held-out, episodes. Every
  checkpoint (ICCO, ICCO w/o CE, any CE weight) is thus measured by the same procedure, whatever
  its own posterior learned or whether it had one.
- :func:`swap_consistency`: do robots interpret one z alike? Robot i is handed robot j's z in its
  own situation (its observation history kept), and acts; the measure is how much more often it
  then does what robot j did with that z than it did with its own, on Cohen's kappa scale: 1 when
  every robot's action is a function of its z alone (one shared reading), 0 when z changes no
  action, below 0 when robots read z in opposite ways.

How z is drawn. The evaluation policy acts on the coordinator's mean; then behaviour is a function
of ``(s, v)`` alone, the information z's noise carries about it is zero, and the bound says
nothing. Here the coordinator samples ``z ~ N(mu(s, v), Sigma(s, v))`` every ``T`` steps, as in
training, and the agents act greedily (no epsilon) on the sampled z: the bound then measures how
much of the sampled z the behaviour reveals beyond what ``(s, v)`` already say (0 when the agents
ignore z and the posterior learns the coordinator's mean; positive when behaviour follows z).

Examples:
    >>> import torch
    >>> z = torch.tensor([[[0.0], [1.0]], [[1.0], [1.0]]])  # 2 steps, 2 robots, z of width 1
    >>> follow = lambda z: z[..., 0].long()  # every robot's action is its z
    >>> swap_consistency(follow, z).kappa
    1.0
    >>> ignore = lambda z: torch.arange(2).expand(z.shape[:-1])  # robot i takes action i
    >>> swap_consistency(ignore, z).kappa
    0.0
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictSequential
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import EGreedyModule

from icco_torchrl.modules.coordinator import gaussian_entropy
from icco_torchrl.modules.posterior import combine_log_prob, make_posterior
from icco_torchrl.training.config import CoordinationConfig

# The default budget of an ``icco eval`` measurement (``eval.coordination``): about 20 s a
# checkpoint on one core for the default task.
# The defaults are ``eval.coordination``'s (its fields say what each is): one home.
EPISODES = CoordinationConfig.episodes  # rollouts (one episode each)
HELDOUT = CoordinationConfig.heldout  # share of the episodes the posterior never fits on
FIT_STEPS = CoordinationConfig.fit_steps  # Adam steps of the fresh posterior
BATCH = 128  # broadcast windows per step
LR = 1e-3

# The columns ``icco eval`` adds (results JSON summary rows, the trials-pooled table); per
# checkpoint, then mean and std over the checkpoints (seeds) of a method.
COLUMNS = (
    "mi_bound",
    "mi_null",
    "mi_log_q",
    "mi_entropy",
    "consistency",
    "swap_agreement",
    "own_agreement",
)
# The ones the whole-episode table of ``icco eval`` shows (all of them go to its JSON and CSV).
TABLE_COLUMNS = ("mi_bound", "mi_null", "consistency")


@dataclass(frozen=True)
class MIEstimate:
    """The mutual-information lower bound of one checkpoint, per robot, in nats.

    ``bound = log_q + entropy`` on the held-out episodes. ``null``: the same estimate with z
    redrawn from the coordinator's Gaussian independently of the behaviour (:func:`redrawn`), a
    bound on zero information, so what the estimator gives when the behaviour reveals nothing
    (below 0 by the posterior's fitting error); ``bound - null`` is what the behaviour adds.
    ``log_q_train``: the fitted posterior's mean on the episodes it was fitted on (a gap to
    ``log_q`` is overfitting); ``windows``: broadcast windows (fitted on, held out);
    ``anchor``: the coordinator's Gaussian was a factor of q (:func:`window_log_q`)."""

    bound: float
    log_q: float
    entropy: float
    null: float
    log_q_train: float
    windows: tuple[int, int]
    fit_steps: int
    anchor: bool


@dataclass(frozen=True)
class SwapConsistency:
    """Swap consistency (:func:`swap_consistency`): ``kappa = (swap - own) / (1 - own)``.

    ``swap``: the share of ordered pairs of robots (i, j), at every step, where robot i handed
    robot j's z takes the action robot j took with it; ``own``: the same share with robot i on its
    own z (agreement by circumstance); ``pairs``: how many robot pairs and steps were scored."""

    kappa: float
    swap: float
    own: float
    pairs: int


# ----------------------------------------------------------------------------- rollouts
def sampling_policy(policy: TensorDictSequential) -> TensorDictSequential:
    """``policy`` without its epsilon-greedy module: run under ``ExplorationType.RANDOM`` the
    coordinator samples z and the agents act greedily on it."""
    return TensorDictSequential(*(m for m in policy.module if not isinstance(m, EGreedyModule)))


def coordinator_rollouts(run, *, seed: int, steps: int | None = None) -> TensorDictBase:
    """One episode in each env of ``run.env`` (``[B, L]``, ``L`` the env's ``max_steps``): the
    coordinator draws ``z ~ N(mu, Sigma)`` every ``T`` steps (held in between), the agents act
    greedily on it. Seeded (the env's initial states and the z draws); torch's global random
    state is left as it was."""
    if run.coordinator is None:
        raise ValueError("the coordination measures need a method with a coordinator")
    steps = run.env.base_env.max_steps if steps is None else steps
    policy = sampling_policy(run.policy)
    run.env.set_seed(seed)
    with (
        torch.random.fork_rng(devices=[]),
        torch.no_grad(),
        set_exploration_type(ExplorationType.RANDOM),
    ):
        torch.manual_seed(seed)
        return run.env.rollout(steps, policy, break_when_any_done=False)


def broadcast_windows(rollout: TensorDictBase, coordinator, layout=None) -> dict:
    """The rollout's whole broadcast windows ``[B, W, ...]`` (window w: steps ``wT .. wT+T-1``,
    its z drawn at step ``wT``): ``z`` ``[B, W, N, Z]`` and the coordinator's ``loc`` and ``scale``
    there,
    ``state [B, W, T, D]``, ``action [B, W, T, N]``, ``obs [B, W, T, N, F]``, ``present
    [B, W, N]`` (robots present at the window's start, all without a ``layout``, and with an
    adaptive broadcast only those that received the window's draw).

    The rollout must be one episode per env from its reset (``step_count`` 0, 1, ...)."""
    T = coordinator.module.period
    step = rollout.get("step_count").reshape(rollout.shape)
    B, L = rollout.shape
    if not bool((step == torch.arange(L)).all()):
        raise ValueError("broadcast_windows needs one episode per env from its reset")
    W = L // T
    if W < 1:
        raise ValueError(f"an episode of {L} steps holds no whole broadcast window of {T}")

    def cut(value):
        return value[:, : W * T].reshape(B, W, T, *value.shape[2:])

    state = cut(rollout.get("state").reshape(B, L, -1))
    with torch.no_grad():
        loc, scale = coordinator.module.distribution(state[:, :, 0])
    z = cut(rollout.get(("agents", "z")))[:, :, 0]
    present = (
        layout.robot_mask(state[:, :, 0])
        if layout is not None
        else torch.ones(z.shape[:-1], dtype=torch.bool)
    )
    sent = rollout.get(("agents", "z_sent"), None)
    if sent is not None:  # an adaptive broadcast: only the robots that received the new draw
        present = present & cut(sent.reshape(B, L, -1))[:, :, 0]
    return dict(
        z=z,
        loc=loc,
        scale=scale,
        state=state,
        action=cut(rollout.get(("agents", "action"))),
        obs=cut(rollout.get(("agents", "observation"))),
        present=present,
    )


# ----------------------------------------------------------------------------- the MI bound
def _flat(windows: dict, episodes: slice) -> dict:
    """The windows of ``episodes``, the episode and window dims flattened: ``[S, ...]``."""
    return {k: v[episodes].flatten(0, 1) for k, v in windows.items()}


def window_log_q(posterior, w: dict, *, anchor: bool = True) -> torch.Tensor:
    """``log q(z | window)`` ``[S, N]`` of the windows ``w`` (:func:`broadcast_windows`, flat) under
    ``posterior``'s factors (``posterior.factors(state, action, obs)``: one Gaussian per step and
    robot), multiplied as Gaussians (a normalised density, whatever the posterior's own
    ``combine``: a sum of log-likelihoods bounds nothing).

    ``anchor``: the coordinator's own ``N(mu, Sigma)`` (``w["loc"]``, ``w["scale"]``: it is
    ``p(z | s, v)``) is one more factor and the fitted factors read what the behaviour says of
    ``z - mu``; without, the factors must also find ``mu`` from the state."""
    loc, scale = posterior.factors(w["state"], w["action"], w["obs"])  # [S, T, N, Z]
    mask = torch.ones(loc.shape[:2], dtype=torch.bool, device=loc.device)
    z = w["z"]
    if anchor:
        loc = torch.cat([torch.zeros_like(w["loc"]).unsqueeze(1), loc], 1)
        scale = torch.cat([w["scale"].unsqueeze(1), scale], 1)
        mask = torch.cat([mask[:, :1], mask], 1)
        z = z - w["loc"]
    return combine_log_prob(z, loc, scale, mask, "product")


def _present_mean(value: torch.Tensor, present: torch.Tensor) -> torch.Tensor:
    """Mean of ``value [S, N]`` over the present robots (``present [S, N]``)."""
    weight = present.to(value.dtype)
    return (weight * value).sum() / weight.sum().clamp_min(1.0)


def fit_posterior(
    posterior: torch.nn.Module,
    windows: dict,
    *,
    steps: int = FIT_STEPS,
    batch: int = BATCH,
    lr: float = LR,
    seed: int = 0,
    anchor: bool = True,
) -> torch.nn.Module:
    """Fit ``posterior`` by maximum likelihood of the windows' z (:func:`window_log_q`; Adam,
    ``steps`` minibatches of ``batch`` windows drawn with a generator seeded by ``seed``);
    returns it."""
    if steps == 0:  # nothing to fit (a posterior given whole, e.g. an exact one)
        return posterior
    generator = torch.Generator().manual_seed(seed)
    optim = torch.optim.Adam(posterior.parameters(), lr=lr)
    n = windows["z"].shape[0]
    for _ in range(steps):
        index = torch.randint(n, (min(batch, n),), generator=generator)
        w = {k: v[index] for k, v in windows.items()}
        loss = -_present_mean(window_log_q(posterior, w, anchor=anchor), w["present"])
        optim.zero_grad()
        loss.backward()
        optim.step()
    return posterior


def split_episodes(episodes: int, heldout: float = HELDOUT) -> tuple[slice, slice]:
    """``(train, held out)`` slices of ``episodes`` episodes: the last ``heldout`` share (at least
    one episode each)."""
    if episodes < 2:
        raise ValueError(f"the held-out split needs at least 2 episodes, got {episodes}")
    if not 0 < heldout < 1:
        raise ValueError(f"heldout must be in (0, 1), got {heldout}")
    n_held = min(max(1, round(heldout * episodes)), episodes - 1)
    return slice(0, episodes - n_held), slice(episodes - n_held, episodes)


def redrawn(windows: dict, seed: int) -> dict:
    """``windows`` with every z replaced by a fresh draw ``mu + sigma * eps'`` of the
    coordinator's Gaussian, independent of the behaviour: ``I(z'; zeta | s, v) = 0``, so the
    bound estimated on them is the estimator's own floor (:attr:`MIEstimate.null`)."""
    generator = torch.Generator().manual_seed(seed)
    noise = torch.randn(windows["loc"].shape, generator=generator, dtype=windows["loc"].dtype)
    return {**windows, "z": windows["loc"] + windows["scale"] * noise}


def _bound(make, windows, train, held, *, fit: dict, anchor: bool) -> tuple[float, float, float]:
    """Fit a fresh posterior (``make()``) on the ``train`` episodes of ``windows``; return its
    mean ``log q`` on the ``held`` ones and on ``train``, and the held-out mean entropy."""
    train_w, held_w = _flat(windows, train), _flat(windows, held)
    posterior = fit_posterior(make(), train_w, anchor=anchor, **fit)
    with torch.no_grad():
        log_q = _present_mean(window_log_q(posterior, held_w, anchor=anchor), held_w["present"])
        log_q_train = _present_mean(
            window_log_q(posterior, train_w, anchor=anchor), train_w["present"]
        )
        entropy = _present_mean(gaussian_entropy(held_w["scale"]), held_w["present"])
    return float(log_q), float(log_q_train), float(entropy)


def mi_estimate(
    run,
    windows: dict,
    *,
    heldout: float = HELDOUT,
    fit_steps: int = FIT_STEPS,
    batch: int = BATCH,
    lr: float = LR,
    seed: int = 0,
    anchor: bool = True,
    posterior_factory: Callable[[], torch.nn.Module] | None = None,
) -> MIEstimate:
    """:func:`mi_lower_bound` from the :func:`broadcast_windows` of ``run``'s rollouts (``run``:
    what the fresh posterior is built for; ``posterior_factory`` replaces that build)."""
    train, held = split_episodes(windows["z"].shape[0], heldout)

    def make() -> torch.nn.Module:
        with torch.random.fork_rng(devices=[]):  # the same initial weights for both fits
            torch.manual_seed(seed)
            if posterior_factory is not None:
                return posterior_factory()
            m = run.cfg.method
            return make_posterior(
                run.layout,
                n_actions=int(run.env.full_action_spec[run.env.action_key].space.n),
                z_dim=m.z_dim,
                hidden=m.hidden,
                combine=m.posterior,
                inputs=m.posterior_input,
            )

    fit = dict(steps=fit_steps, batch=batch, lr=lr, seed=seed)
    log_q, log_q_train, entropy = _bound(make, windows, train, held, fit=fit, anchor=anchor)
    null_q, _, null_h = _bound(make, redrawn(windows, seed), train, held, fit=fit, anchor=anchor)
    n_train, n_held = (windows["z"][part].flatten(0, 1).shape[0] for part in (train, held))
    return MIEstimate(
        bound=log_q + entropy,
        log_q=log_q,
        entropy=entropy,
        null=null_q + null_h,
        log_q_train=log_q_train,
        windows=(n_train, n_held),
        fit_steps=fit_steps,
        anchor=anchor,
    )


def _restored(checkpoint, episodes: int, seed: int, env_overrides: dict):
    """A restored run of ``checkpoint`` (a path) with ``episodes`` envs, or ``checkpoint`` itself
    (a :class:`~icco_torchrl.training.build.Run`)."""
    if not isinstance(checkpoint, (str, Path)):
        return checkpoint
    from icco_torchrl.training.restore import restore  # heavy: networks, Hydra config

    return restore(checkpoint, num_envs=episodes, seed=seed, **env_overrides)


def mi_lower_bound(
    checkpoint,
    *,
    episodes: int = EPISODES,
    heldout: float = HELDOUT,
    fit_steps: int = FIT_STEPS,
    batch: int = BATCH,
    lr: float = LR,
    seed: int = 0,
    anchor: bool = True,
    **env_overrides,
) -> MIEstimate:
    """The paper's bound ``E[log q(z | zeta, s, v)] + H(z | s, v)`` of ``checkpoint`` (a path, or
    a restored run whose env runs the episodes), per robot, in nats, with a posterior fitted after
    training on held-out rollouts (the module doc). Deterministic given ``seed``.

    ``episodes`` rollouts of one episode each (z sampled, actions greedy), random-walk
    instructions; the last ``heldout`` share of them is held out; a fresh posterior of the
    checkpoint's architecture is fitted for ``fit_steps`` Adam steps of ``batch`` windows at
    ``lr``, anchored on the coordinator's Gaussian (``anchor``; :func:`window_log_q`), once on the
    z the team acted on and once on z redrawn independently of its behaviour (the floor,
    :attr:`MIEstimate.null`). ``env_overrides`` change the env (e.g. ``n_agents``).

    Examples:
        >>> from icco_torchrl.training.build import build_components
        >>> run = build_components(method="icco", num_envs=4)  # an untrained ICCO team
        >>> est = mi_lower_bound(run, fit_steps=20, seed=0)
        >>> est.windows  # broadcast windows (fitted on, held out): 145 steps hold 36 each
        (108, 36)
        >>> abs(est.bound - (est.log_q + est.entropy)) < 1e-9
        True
    """
    run = _restored(checkpoint, episodes, seed, env_overrides)
    windows = broadcast_windows(coordinator_rollouts(run, seed=seed), run.coordinator, run.layout)
    return mi_estimate(
        run,
        windows,
        heldout=heldout,
        fit_steps=fit_steps,
        batch=batch,
        lr=lr,
        seed=seed,
        anchor=anchor,
    )


# ----------------------------------------------------------------------------- consistency
def swap_consistency(
    act: Callable[[torch.Tensor], torch.Tensor],
    z: torch.Tensor,
    present: torch.Tensor | None = None,
) -> SwapConsistency:
    """Do robots interpret one z alike? ``z [M, N, Z]``: the z each of N robots holds at M steps;
    ``act(z [K, M, N, Z]) -> [K, M, N]``: the action each robot takes at each step when it holds
    the z given (its own observation history otherwise unchanged); ``present [M, N]``: the robots
    there (default all).

    For every ordered pair of present robots (i, j) and step, robot i is handed robot j's z.
    ``swap`` is the share of these where it then takes the action j took with that z, ``own`` the
    share where its action on its own z already was j's (agreement by circumstance), and
    ``kappa = (swap - own) / (1 - own)`` (Cohen's kappa with ``own`` as chance): 1 when actions
    depend on z alone, 0 when z changes no action, negative when robots read z in opposite ways;
    NaN when every pair already agrees. One batched call of ``act`` with N shifted copies of z.

    Examples:
        >>> import torch
        >>> z = torch.tensor([[[0.0], [1.0]], [[1.0], [1.0]]])  # 2 steps, 2 robots
        >>> def mirrored(z):  # robot 0 takes its z's action, robot 1 the other one
        ...     a = z[..., 0].long()
        ...     a[..., 1] = 1 - a[..., 1]
        ...     return a
        >>> c = swap_consistency(mirrored, z)
        >>> c.swap, c.own, c.kappa  # own: step 0 agrees (0, 0), step 1 not (1, 0)
        (0.0, 0.5, -1.0)
    """
    M, N = z.shape[:2]
    if N < 2:
        raise ValueError("swap consistency compares robots: it needs at least 2")
    robots = torch.arange(N, device=z.device)
    source = (robots + robots[:, None]) % N  # [K=N shifts, N]: robot i holds robot source[k, i]'s
    actions = act(z[:, source].transpose(0, 1))  # [K, M, N]; shift 0: every robot its own z
    if actions.shape != (N, M, N):
        raise ValueError(f"act returned {tuple(actions.shape)}, expected {(N, M, N)}")
    own = actions[0]  # [M, N]
    theirs = own[:, source[1:]]  # [M, K-1, N]: what the source robot did with its own z
    swapped = actions[1:].transpose(0, 1)  # [M, K-1, N]
    present = torch.ones(M, N, dtype=torch.bool) if present is None else present.bool()
    weight = present[:, None, :] & present[:, source[1:]]
    pairs = int(weight.sum())  # counts: the shares below are exact ratios of integers
    p_swap = int((weight & (swapped == theirs)).sum()) / max(pairs, 1)
    p_own = int((weight & (own[:, None, :] == theirs)).sum()) / max(pairs, 1)
    kappa = (p_swap - p_own) / (1 - p_own) if p_own < 1 and pairs > 0 else math.nan
    return SwapConsistency(kappa=kappa, swap=p_swap, own=p_own, pairs=pairs)


def agent_actions(run, rollout: TensorDictBase) -> Callable[[torch.Tensor], torch.Tensor]:
    """``act`` of :func:`swap_consistency` for ``run``'s agents on the steps of ``rollout``: the
    greedy action of each robot from its recorded inputs (observation, previous action, GRU state,
    step) with the z given in place of the one it held."""
    agent, z_key = run.agent, ("agents", "z")
    steps = rollout.exclude("next").select(*agent.in_keys, strict=False).reshape(-1)
    M = steps.shape[0]

    def act(z: torch.Tensor) -> torch.Tensor:
        K = z.shape[0]
        td = steps.expand(K, M).reshape(K * M).clone(recurse=False)
        td.set(z_key, z.reshape(K * M, *z.shape[2:]))
        with torch.no_grad():
            q = agent(td).get(("agents", "action_value"))
        return q.argmax(-1).reshape(K, M, -1)

    return act


def rollout_consistency(run, rollout: TensorDictBase) -> SwapConsistency:
    """:func:`swap_consistency` of ``run``'s agents on every step of ``rollout``."""
    z = rollout.get(("agents", "z")).flatten(0, 1)
    state = rollout.get("state").flatten(0, 1)
    present = run.layout.robot_mask(state.flatten(1)) if run.layout is not None else None
    return swap_consistency(agent_actions(run, rollout), z, present)


# ----------------------------------------------------------------------------- both, for eval
def measure_coordination(
    checkpoint,
    *,
    episodes: int = EPISODES,
    heldout: float = HELDOUT,
    fit_steps: int = FIT_STEPS,
    batch: int = BATCH,
    lr: float = LR,
    seed: int = 0,
    anchor: bool = True,
    **env_overrides,
) -> dict:
    """Both measures of ``checkpoint`` (a path or a restored run) from one set of rollouts (see
    :func:`mi_lower_bound` for the arguments): a flat dict of :data:`COLUMNS` and the details
    (``mi``: :class:`MIEstimate`, ``swap``: :class:`SwapConsistency`, as dicts)."""
    run = _restored(checkpoint, episodes, seed, env_overrides)
    rollout = coordinator_rollouts(run, seed=seed)
    windows = broadcast_windows(rollout, run.coordinator, run.layout)
    mi = mi_estimate(
        run,
        windows,
        heldout=heldout,
        fit_steps=fit_steps,
        batch=batch,
        lr=lr,
        seed=seed,
        anchor=anchor,
    )
    swap = rollout_consistency(run, rollout)
    return dict(
        mi_bound=mi.bound,
        mi_null=mi.null,
        mi_log_q=mi.log_q,
        mi_entropy=mi.entropy,
        consistency=swap.kappa,
        swap_agreement=swap.swap,
        own_agreement=swap.own,
        mi=asdict(mi),
        swap=asdict(swap),
    )


def for_eval(checkpoint, node, *, seed: int, **env_overrides) -> dict:
    """:func:`measure_coordination` of ``checkpoint`` at the budget of an ``eval.coordination``
    config ``node`` (``episodes``, ``heldout``, ``fit_steps``): what ``icco eval`` records per
    checkpoint."""
    return measure_coordination(
        checkpoint,
        episodes=int(node.episodes),
        heldout=float(node.heldout),
        fit_steps=int(node.fit_steps),
        seed=seed,
        **env_overrides,
    )


def add_columns(summary: Sequence[dict], measured: Mapping[str, Sequence[Mapping]]) -> None:
    """Add :data:`COLUMNS` (and their ``_std``) to every row of ``summary`` in place: the mean and
    population std over ``measured[method]`` (one dict per checkpoint) for the methods measured,
    NaN for the others (methods without a coordinator, the scripted references)."""
    for row in summary:
        values = measured.get(row["method"], ())
        for column in COLUMNS:
            xs = torch.tensor([float(v[column]) for v in values], dtype=torch.float64)
            xs = xs[torch.isfinite(xs)]
            mean = float(xs.mean()) if len(xs) else math.nan
            std = float(xs.std(unbiased=False)) if len(xs) else math.nan
            row[column], row[f"{column}_std"] = mean, std


# How :func:`coordination_table` prints each column: header, digits.
_TABLE = {
    "mi_bound": ("I lower bound (nats)", 1),
    "mi_null": ("its floor (nats)", 1),
    "mi_log_q": ("E log q (nats)", 1),
    "mi_entropy": ("H of z (nats)", 1),
    "consistency": ("swap consistency", 3),
    "swap_agreement": ("agree, swapped z", 3),
    "own_agreement": ("agree, own z", 3),
}


def coordination_table(summary: Sequence[Mapping], segment: str = "episode") -> str:
    """A Markdown section with one row per method that was measured (:func:`add_columns`): the
    columns of :data:`COLUMNS`, mean ± std over its checkpoints. Empty without any."""
    rows = [
        r for r in summary if r["segment"] == segment and math.isfinite(r.get("mi_bound", math.nan))
    ]
    if not rows:
        return ""

    def cell(row, column):
        digits = _TABLE[column][1]
        mean, std = row[column], row[f"{column}_std"]
        return "–" if not math.isfinite(mean) else f"{mean:.{digits}f} ± {std:.{digits}f}"

    head = ["method"] + [_TABLE[c][0] for c in COLUMNS]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += [
        "| " + " | ".join([str(r["method"])] + [cell(r, c) for c in COLUMNS]) + " |" for r in rows
    ]
    return (
        "\n## Coordinator: information and consistency\n\n"
        "Per robot, on the training distribution with z sampled from the coordinator "
        "(docs/consistency.md); mean ± std over checkpoints. The bound minus its floor is what "
        "the behaviour reveals of z beyond the state and instructions.\n\n"
        + "\n".join(lines)
        + "\n"
    )
