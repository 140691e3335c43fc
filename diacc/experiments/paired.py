"""Paired changes against a reference policy, with seeded bootstrap confidence intervals.

Every policy of an evaluation meets the same traffic draw in the episode of the
same seed (:meth:`diacc.experiments.grid.Cell.seed`), so a column is compared
with its reference (``same-mix``) episode by episode: pairs are the episodes
whose seed both hold, and the interval comes from resampling those pairs (the
same resample for both sides), which removes the traffic's own spread from
the comparison. A claim whose interval holds 0 is "no measurable difference"
(issue 42); how wide the intervals of a given episode count are, and so how many
episodes README's claims need, is in docs/concepts/baselines.md ("Seed streams").

A column may pool several training runs (``diacc reproduce`` pools a variant's
seeds into one column): each of its runs played the same episode seeds, so the
pairs are *episode seeds*, each holding every run's episode of that traffic, and
the bootstrap resamples both levels: the episode seeds (one resample for both
sides) and, on a side with several runs, its runs (independently per side, as
the runs of two policies are). The interval then carries the spread between
training seeds as well as the traffic's; with 3 runs that part is coarse, so
the per-seed numbers belong beside it. One run per side is the plain paired
bootstrap over episodes.

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
    speed (pooled over vehicles and steps, as the table's entry). ``run`` tells
    apart the training runs a pooled column holds (None: one run).
    """

    seed: np.ndarray  # (K,) int64
    value: np.ndarray  # (K,) float64, display units
    weight: np.ndarray  # (K,) float64
    run: np.ndarray | None = None  # (K,) int64 training-run index

    def finite(self) -> EpisodeValues:
        """The episodes whose value is defined."""
        ok = np.isfinite(self.value)  # (K,)
        run = None if self.run is None else self.run[ok]
        return EpisodeValues(self.seed[ok], self.value[ok], self.weight[ok], run)

    def sums(self, seeds: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Weighted value sums and weight sums per (run, episode seed), for ``seeds``
        (sorted, all held here): two (R, S) arrays."""
        keep = np.isin(self.seed, seeds)  # (K,)
        s = np.searchsorted(seeds, self.seed[keep])  # (K',) episode-seed index
        run = np.zeros(s.size, np.int64) if self.run is None else self.run[keep]
        _, r = np.unique(run, return_inverse=True)  # (K',) run index, 0..R-1
        shape = (int(r.max()) + 1, seeds.size)
        value_sums, weight_sums = np.zeros(shape), np.zeros(shape)  # (R, S)
        w = self.weight[keep]
        np.add.at(value_sums, (r, s), self.value[keep] * w)
        np.add.at(weight_sums, (r, s), w)
        return value_sums, weight_sums


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
    """Paired change with its bootstrap interval over the episode seeds both sides played
    (and their runs, module docstring); None with fewer than 2 such seeds, or where the
    reference's mean is 0 for a relative change. ``n_pairs`` counts episode seeds."""
    column, reference = column.finite(), reference.finite()
    seeds = np.intersect1d(column.seed, reference.seed)  # (S,) sorted
    n = int(seeds.size)
    if n < 2:
        return None
    sides = [v.sums(seeds) for v in (column, reference)]  # (R, S) value and weight sums
    point = float(_change(*(vs.sum() / ws.sum() for vs, ws in sides), relative))
    if not math.isfinite(point):
        return None
    rng = np.random.default_rng(BOOTSTRAP_SEED)
    picks = rng.integers(0, n, size=(RESAMPLES, n))  # (B, S): one resample for both sides
    seed_counts = _counts(picks, n)  # (B, S)
    means = []
    for value_sums, weight_sums in sides:
        runs = value_sums.shape[0]
        run_counts = np.ones((RESAMPLES, runs))  # (B, R): one run, or resampled runs
        if runs > 1:
            run_counts = _counts(rng.integers(0, runs, size=(RESAMPLES, runs)), runs)
        totals = [
            np.einsum("br,rs,bs->b", run_counts, a, seed_counts) for a in (value_sums, weight_sums)
        ]
        means.append(totals[0] / totals[1])  # (B,)
    changes = _change(means[0], means[1], relative)
    changes = changes[np.isfinite(changes)]
    tail = (1.0 - CONFIDENCE) / 2.0
    low, high = np.quantile(changes, [tail, 1.0 - tail])
    return PairedChange(point, float(low), float(high), n)


def _counts(picks: np.ndarray, n: int) -> np.ndarray:
    """How often each of ``n`` items is drawn in each resample: (B, n) from (B, k) picks."""
    counts = np.zeros((picks.shape[0], n))
    np.add.at(counts, (np.arange(picks.shape[0])[:, None], picks), 1.0)
    return counts
