"""One rule and one vocabulary for every verdict the experiment pages state.

**The rule.** A gap between two means is judged against the spread of the means, not of single
trials. Each side's standard error is its std over trials divided by sqrt(n); the gap ``a - b``
is judged against ``Z = 2`` combined standard errors, ``sqrt(se_a^2 + se_b^2)``:

- ``ahead``: ``a - b > 2 se``;
- ``behind``: ``a - b < -2 se``;
- ``within the spread``: otherwise.

``n`` is the number of trials behind a mean. The pages pool trials across seeds (20 trials per
checkpoint and 3 seeds make n = 60; a scripted reference, one "seed", n = 20), so n counts every
pooled trial. ``std`` is the std over those trials as the tables print it (numpy's, ddof = 0;
calibration/best_scripted.py stores its own se, sample std / sqrt(n), and applies the same rule).
Pooled trials are not independent draws of a method: seeds can differ more than the trials of
one seed, so a resolved gap is one between these checkpoints; with 2-3 seeds, read "ahead" as "ahead
on these seeds", not as a property of the method's training. Two sides measured on the same
episodes (a method and a scripted reference, two thresholds of one checkpoint) are treated as
independent: conservative when they move together.

A bar ``a >= s x b`` (a target such as "at least half the blend's picks") is the same rule on
``a - s x b``, with ``s x se_b`` for b's standard error.

**The vocabulary.** A comparison reads ``ahead``, ``behind`` or ``within the spread``, with its gap
and 2 standard errors. A claim (the paper's, or a target the project set) made of comparisons
that must all come out ahead reads:

- ``holds``: every comparison it needs is ahead;
- ``does not hold``: one is behind;
- ``not resolved at this budget``: none behind, but one within the spread;
- ``not measured``: a number it needs is missing.

Pages state the claim, then the verdict after a colon: ``- **Paper: ...**: does not hold. ...``.
"""

# No ``from __future__ import annotations``: the dataclasses below then need no module lookup,
# so a script may load this file by path (as the tests do) as well as import it.
import csv
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

Z = 2.0  # standard errors a gap must exceed to be resolved

AHEAD, BEHIND, WITHIN = "ahead", "behind", "within the spread"
HOLDS, FAILS, OPEN, MISSING = (
    "holds",
    "does not hold",
    "not resolved at this budget",
    "not measured",
)

RULE = (
    "A gap between two means is *ahead* or *behind* when it exceeds 2 standard errors of the "
    "difference (sqrt(se_a^2 + se_b^2), se = std / sqrt(n)), *within the spread* otherwise; a "
    "claim *holds* when every gap it needs is ahead, *does not hold* when one is behind, and is "
    "*not resolved at this budget* otherwise (`experiments/verdict.py`)."
)


def _finite(x) -> bool:
    return isinstance(x, (int, float)) and math.isfinite(x)


@dataclass(frozen=True)
class Mean:
    """A mean over ``n`` trials with its std over those trials."""

    mean: float
    std: float
    n: int

    @property
    def se(self) -> float:
        """The standard error of the mean: ``std / sqrt(n)`` (NaN without trials)."""
        return self.std / math.sqrt(self.n) if self.n > 0 else math.nan

    @classmethod
    def of_row(cls, row: Mapping, metric: str = "reward") -> "Mean":
        """From a summary row (``evaluation.metrics.summarize``): ``metric``, ``metric_std`` and
        ``n``, the trials of the row (seeds pooled)."""
        return cls(row[metric], row[f"{metric}_std"], int(row["n"]))

    @classmethod
    def of_result(cls, entry: Mapping, metric: str, trials: int) -> "Mean":
        """From a ``results.json`` method entry (``{metric: {"mean", "std"}, "seeds"}``), whose
        ``trials`` per checkpoint pool across its seeds (a reference, 0 seeds, has one)."""
        value = entry.get(metric) or {"mean": math.nan, "std": math.nan}
        return cls(value["mean"], value["std"], trials * max(int(entry.get("seeds") or 0), 1))


def episode_mean(rows: Iterable[Mapping], metric: str = "reward", segment: str = "episode"):
    """The :class:`Mean` of ``metric`` over the ``segment`` rows of an evaluation's trials file
    (``*_trials.csv``; the whole episode by default), empty and non-finite values left out; None
    without one."""
    values = [float(r[metric]) for r in rows if r["segment"] == segment and r.get(metric)]
    values = [v for v in values if math.isfinite(v)]
    if not values:
        return None
    return Mean(float(np.mean(values)), float(np.std(values)), len(values))


def best_scripted(rows: Iterable[Mapping], metric: str = "reward"):
    """:func:`episode_mean` of the best scripted team's rows (``BEST_SCRIPTED_LABEL``)."""
    from icco_torchrl.envs.reference_policies import BEST_SCRIPTED_LABEL

    return episode_mean([r for r in rows if r["method"].startswith(BEST_SCRIPTED_LABEL)], metric)


def read_rows(path: Path) -> list[dict]:
    """The rows of a CSV file (an evaluation's trials), none when it is missing."""
    if not path.is_file():
        return []
    with path.open() as handle:
        return list(csv.DictReader(handle))


def share_entry(mean: "Mean | None", best: "Mean | None") -> dict | None:
    """A results entry: mean, std, trials and the share of ``best`` (the best scripted team's on
    the same episodes; None when it is missing or not positive)."""
    if mean is None:
        return None
    share = mean.mean / best.mean if best is not None and best.mean > 0 else None
    return {"mean": mean.mean, "std": mean.std, "n": mean.n, "share_of_best_scripted": share}


@dataclass(frozen=True)
class Gap:
    """``a - s x b`` and its standard error."""

    gap: float
    se: float

    @property
    def word(self) -> str:
        """``ahead``, ``behind`` or ``within the spread`` (``not measured`` when a side is
        missing)."""
        return gap_word(self.gap, self.se)

    def text(self, digits: int = 1) -> str:
        """The word with its numbers: ``behind (-56.3, 2 SE 17.4)``."""
        if self.word == MISSING:
            return MISSING
        return f"{self.word} ({self.gap:+.{digits}f}, 2 SE {Z * self.se:.{digits}f})"


def digits(measure: str) -> int:
    """Decimals a measure is shown and judged with: 3 for the measures that live in [0, 1] (swap
    consistency, in-place shares), 1 for rewards and nats."""
    return 3 if measure == "consistency" or measure.startswith("in_place") else 1


def gap_word(gap: float, se: float) -> str:
    """The rule on a gap and its standard error."""
    if not (_finite(gap) and _finite(se)):
        return MISSING
    if gap > Z * se:
        return AHEAD
    if gap < -Z * se:
        return BEHIND
    return WITHIN


def compare(a: Mean, b: Mean, scale: float = 1.0) -> Gap:
    """``a`` against ``scale x b``: the gap ``a.mean - scale x b.mean`` and its standard error
    ``sqrt(a.se^2 + (scale x b.se)^2)``."""
    return Gap(a.mean - scale * b.mean, math.hypot(a.se, scale * b.se))


def claim(words: Iterable[str]) -> str:
    """The verdict of a claim whose comparisons (``ahead``/``behind``/``within the spread``/
    ``not measured``) must all come out ahead: one behind settles it, then a missing number
    leaves it unmeasured, then one within the spread leaves it open."""
    words = list(words)
    if not words:
        return MISSING
    if BEHIND in words:
        return FAILS
    if MISSING in words:
        return MISSING
    if WITHIN in words:
        return OPEN
    return HOLDS


def any_of(verdicts: Iterable[str]) -> str:
    """The verdict of a claim that one of several candidates must meet (each verdict a
    :func:`claim`): holds when one holds, does not hold when every one does not, open when one
    is open, not measured otherwise."""
    verdicts = list(verdicts)
    if HOLDS in verdicts:
        return HOLDS
    if OPEN in verdicts:
        return OPEN
    if verdicts and all(v == FAILS for v in verdicts):
        return FAILS
    return MISSING


def pooled_n(ns: Mapping[str, int]) -> str:
    """``n`` per label, grouped: ``60 (ICCO, QMIX), 20 (follower)``, the largest first."""
    groups: dict[int, list[str]] = {}
    for label, n in ns.items():
        groups.setdefault(int(n), []).append(label)
    return ", ".join(
        f"{n} ({', '.join(labels)})" for n, labels in sorted(groups.items(), reverse=True)
    )


def unreproduced_references(results: dict, added: dict, tolerance: float) -> list[tuple]:
    """``(name, metrics)`` for each scripted reference of ``results`` (a page's ``results.json``)
    that ``added`` (the same policies evaluated again) lacks (``metrics`` empty) or gives other
    means or stds, beyond ``tolerance`` relative (at least absolute): a page takes new reference
    rows only from the episodes its own rows came from."""
    out = []
    for name, entry in results["methods"].items():
        if entry.get("seeds"):  # a learned method
            continue
        other = added.get(name)
        bad = (
            []
            if other is None
            else [
                metric
                for metric, value in entry.items()
                if isinstance(value, dict)
                and any(
                    abs(value[k] - other[metric][k]) > tolerance * max(1.0, abs(value[k]))
                    for k in ("mean", "std")
                )
            ]
        )
        if other is None or bad:
            out.append((name, bad))
    return out
