"""Paired changes against a reference policy, with seeded bootstrap confidence intervals.

Every policy of an evaluation meets the same traffic draw in the episode of the
same seed (:meth:`diacc.experiments.grid.Cell.seed`), so a column is compared
with its reference (``same-mix``) episode by episode: pairs are the episodes
whose seed both hold, and the interval comes from resampling those pairs (the
same resample for both sides), which removes the traffic's own spread from
the comparison. A claim whose interval holds 0 is "no measurable difference"
(issue 42); how wide the intervals of a given episode count are, and so how many
episodes README's claims need, is in docs/concepts/baselines.md ("Seed streams").

The bootstrap is the percentile interval over :data:`RESAMPLES` resamples,
drawn by a generator seeded with :data:`BOOTSTRAP_SEED` for every comparison,
so that the same files give the same table, whatever else is in it. With few
pairs (below about 10) a percentile bootstrap is too narrow: 2 episodes that
differ by the same amount give a zero-width interval.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Resamples of the bootstrap.
RESAMPLES = 4000
#: Seed of every comparison's resampling generator.
BOOTSTRAP_SEED = 0x42B0_075A
#: Two-sided coverage of the interval.
CONFIDENCE = 0.95


@dataclass(frozen=True)
class EpisodeValues:
    """One metric of one column in one cell: per-episode values keyed by episode seed.

    ``weight`` is 1 for per-episode metrics, the speed-sample count for mean
    speed (pooled over vehicles and steps, as the table's entry).
    """

    seed: np.ndarray  # (K,) int64
    value: np.ndarray  # (K,) float64, display units
    weight: np.ndarray  # (K,) float64


@dataclass(frozen=True)
class PairedChange:
    """Change of a column's mean against its reference over the paired episodes."""

    change: float  # percent, or percentage points (``relative`` False)
    low: float  # 95 % bootstrap interval
    high: float
    n_pairs: int

    @property
    def measurable(self) -> bool:
        """False when the interval holds 0: no measurable difference."""
        return not (self.low <= 0.0 <= self.high)


def _change(x: np.ndarray, y: np.ndarray, relative: bool) -> np.ndarray:
    """Change of means ``x`` against ``y`` (any shape): percent or plain difference."""
    if not relative:
        return x - y
    with np.errstate(divide="ignore", invalid="ignore"):
        return 100.0 * (x - y) / y


def paired_change(
    column: EpisodeValues, reference: EpisodeValues, relative: bool
) -> PairedChange | None:
    """Paired change with its bootstrap interval; None with fewer than 2 pairs, or where
    the reference's mean is 0 for a relative change."""
    _, i, j = np.intersect1d(column.seed, reference.seed, return_indices=True)
    finite = np.isfinite(column.value[i]) & np.isfinite(reference.value[j])
    i, j = i[finite], j[finite]
    n = int(i.size)
    if n < 2:
        return None
    x, wx = column.value[i], column.weight[i]  # (P,)
    y, wy = reference.value[j], reference.weight[j]  # (P,)
    point = float(_change(np.average(x, weights=wx), np.average(y, weights=wy), relative))
    if not math.isfinite(point):
        return None
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    picks = rng.integers(0, n, size=(RESAMPLES, n))  # (B, P): one resample for both sides
    mean_x = (x[picks] * wx[picks]).sum(1) / wx[picks].sum(1)  # (B,)
    mean_y = (y[picks] * wy[picks]).sum(1) / wy[picks].sum(1)  # (B,)
    changes = _change(mean_x, mean_y, relative)
    changes = changes[np.isfinite(changes)]
    tail = (1.0 - CONFIDENCE) / 2.0
    low, high = np.quantile(changes, [tail, 1.0 - tail])
    return PairedChange(point, float(low), float(high), n)
