r"""Confidence intervals of mean test scores over test pairs and training seeds: a two-way bootstrap.

A score table is a ``(S, P)`` array: one row per training seed (or a single row for a setting that does not depend
on one, such as the blurred input), one column per test pair. Pairs come in **clusters** (the pairs of one scene:
its f-numbers, its cameras; the tiles of one photo), which are not independent. One bootstrap replicate draws
``S`` seeds and ``C`` clusters with replacement, independently of each other (the "pigeonhole" bootstrap of a
crossed design, Owen 2007), and takes the mean over the drawn seeds x the pairs of the drawn clusters:

.. math:: \bar v^* = \frac{\sum_s \sum_p w_s w_{c(p)} v_{sp}}{\sum_s \sum_p w_s w_{c(p)}}

(``w``: how often a seed or cluster was drawn; non-finite scores are left out of both sums). The 95 % interval is
the 2.5 and 97.5 % percentiles of :math:`\bar v^*`. It covers two sources of variation: which test scenes were
drawn and the training randomness of the seeds. With few seeds (3) the seed dimension is coarse (10 distinct
resamples) and the interval is somewhat too narrow in it; with one seed it covers the test scenes only.

**Differences** between two settings use the *same* replicates for both (they were scored on the same pairs, and
the same seed index means the same seed), so what the two share cancels; a difference is **resolved** when its
interval excludes 0. :class:`Resampler` holds the replicates of one test set; every row and difference of a table
draws from it, so they are all consistent.

With one seed and one pair per cluster this is the ordinary percentile bootstrap over pairs.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from dp5k_common.errors import BadInputError

LEVEL = 0.95
"""Coverage of every interval."""
N_BOOT = 4000
"""Bootstrap replicates (the percentiles move by about 0.01 of the interval's width between runs of 4000)."""


@dataclass(frozen=True)
class Estimate:
    """A mean with its bootstrap interval, in the scores' unit (dB for PSNR)."""

    mean: float
    lo: float
    hi: float

    @property
    def resolved(self) -> bool:
        """The interval excludes 0 (meaningful for a difference)."""
        return self.lo > 0.0 or self.hi < 0.0

    def to_json(self) -> dict[str, Any]:
        return {"mean": self.mean, "ci95": [self.lo, self.hi]}

    def text(self, digits: int = 2, signed: bool = False) -> str:
        """``mean [lo, hi]``."""
        f = f"{{:{'+' if signed else ''}.{digits}f}}"
        return f"{f.format(self.mean)} [{f.format(self.lo)}, {f.format(self.hi)}]"


@dataclass(frozen=True)
class Difference:
    """``a - b`` (e.g. PSNR in dB) over the same pairs and seeds, oriented so that ``a`` has the higher mean."""

    a: str
    b: str
    estimate: Estimate

    @classmethod
    def oriented(cls, a: str, b: str, e: Estimate) -> Difference:
        """``a - b``, or ``b - a`` with the interval mirrored when ``a``'s mean is the lower."""
        return cls(b, a, Estimate(-e.mean, -e.hi, -e.lo)) if e.mean < 0 else cls(a, b, e)

    def to_json(self) -> dict[str, Any]:
        return {"a": self.a, "b": self.b, "difference": self.estimate.to_json(), "resolved": self.estimate.resolved}

    def words(self, unit: str = "dB") -> str:
        e = self.estimate
        return f"{self.a} +{e.mean:.2f} {unit} over {self.b} [{e.lo:+.2f}, {e.hi:+.2f}]"


def verdict(diffs: Sequence[Difference], what: str = "PSNR difference", unit: str = "dB") -> str:
    """The differences in words: which are resolved (the 95 % interval excludes 0) and which are not."""
    done = [d.words(unit) for d in diffs if d.estimate.resolved]
    open_ = [d.words(unit) for d in diffs if not d.estimate.resolved]
    return (f"**Resolved** ({len(done)} of {len(diffs)}; the 95 % interval of the {what} excludes 0): "
            + ("; ".join(done) if done else "none") + ".\n\n"
            + f"**Not resolved** ({len(open_)}): " + ("; ".join(open_) if open_ else "none") + ".\n")


class Resampler:
    """The bootstrap replicates of one test set: ``n_seeds`` seeds x the pairs, grouped by ``clusters``.

    Args:
        clusters: one label per test pair (e.g. its scene); pairs of one label are drawn together.
        n_seeds: training seeds of the seed-dependent rows.
        n_boot: replicates.
        seed: seeds the draws (the intervals are reproducible).

    Raises:
        BadInputError: no pairs or no seeds.
    """

    def __init__(self, clusters: Sequence[str], n_seeds: int, n_boot: int = N_BOOT, seed: int = 0) -> None:
        if not len(clusters) or n_seeds < 1:
            raise BadInputError(f"a bootstrap needs pairs and seeds, got {len(clusters)} pairs and {n_seeds} seeds")
        labels, index = np.unique(np.asarray(list(clusters), dtype=str), return_inverse=True)
        rng = np.random.default_rng(seed)
        n_clusters = len(labels)
        drawn = rng.integers(0, n_clusters, (n_boot, n_clusters))
        cluster_w = np.zeros((n_boot, n_clusters))
        np.add.at(cluster_w, (np.arange(n_boot)[:, None], drawn), 1.0)
        self.pair_weights: NDArray[np.float64] = cluster_w[:, index]
        """(B, P) how often each pair's cluster was drawn in each replicate."""
        seeds = rng.integers(0, n_seeds, (n_boot, n_seeds))
        self.seed_weights: NDArray[np.float64] = np.zeros((n_boot, n_seeds))
        """(B, S) how often each seed was drawn in each replicate."""
        np.add.at(self.seed_weights, (np.arange(n_boot)[:, None], seeds), 1.0)
        self.n_pairs, self.n_seeds, self.n_clusters = len(index), n_seeds, n_clusters

    def _grid(self, values: ArrayLike) -> NDArray[np.float64]:
        v = np.asarray(values, dtype=np.float64)
        if v.ndim == 1:
            v = v[None]
        if v.ndim != 2 or v.shape[1] != self.n_pairs or v.shape[0] not in (1, self.n_seeds):
            raise BadInputError(f"scores must be (seeds, pairs) = ({self.n_seeds}, {self.n_pairs}) or ({self.n_pairs},), "
                                f"got {v.shape}")
        return np.broadcast_to(v, (self.n_seeds, self.n_pairs))

    def estimate(self, values: ArrayLike) -> Estimate:
        """Mean and 95 % interval of ``values``: ``(S, P)`` per seed and pair, or ``(P,)`` / ``(1, P)`` for a setting
        without seeds (the same scores for every seed).

        Raises:
            BadInputError: a shape that does not match, or no finite score.
        """
        v = self._grid(values)
        finite = np.isfinite(v)
        if not finite.any():
            raise BadInputError("no finite score to average")
        vz = np.where(finite, v, 0.0)
        num = np.einsum("bs,sp,bp->b", self.seed_weights, vz, self.pair_weights)
        den = np.einsum("bs,sp,bp->b", self.seed_weights, finite.astype(np.float64), self.pair_weights)
        boot = num / np.where(den > 0, den, np.nan)
        a = (1.0 - LEVEL) / 2.0
        lo, hi = np.nanquantile(boot, [a, 1.0 - a])
        return Estimate(float(vz.sum() / finite.sum()), float(lo), float(hi))

    def difference(self, a: ArrayLike, b: ArrayLike) -> Estimate:
        """Mean and 95 % interval of ``a - b`` (paired by seed and pair; either may be seed-independent)."""
        return self.estimate(self._grid(a) - self._grid(b))

    def compare(self, a: str, va: ArrayLike, b: str, vb: ArrayLike) -> Difference:
        """The :class:`Difference` of the settings named ``a`` and ``b`` with scores ``va`` and ``vb``."""
        return Difference.oriented(a, b, self.difference(va, vb))
