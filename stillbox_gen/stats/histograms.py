"""Depth bands and fine histograms of ``stillbox-gen stats`` (medians and percentiles are read
from them, interpolated inside the bin)."""

from __future__ import annotations

import numpy as np

#: Pixel-depth bands in metres: [0, 5), [5, 10), ..., [75, 100), then [100, inf) ("> 100", which
#: also holds pixels whose ray met no surface, stored as formats.NO_SURFACE_DEPTH).
BAND_EDGES_M = (0.0, 5.0, 10.0, 15.0, 20.0, 25.0, 30.0, 50.0, 75.0, 100.0)
BAND_LABELS = tuple(
    [f"{lo:g}-{hi:g}" for lo, hi in zip(BAND_EDGES_M[:-1], BAND_EDGES_M[1:], strict=True)]
    + [f">{BAND_EDGES_M[-1]:g}"]
)

DEPTH_BIN_M = 0.01  # fine depth histogram: 1 cm bins from 0 to DEPTH_HIST_TOP_M, then overflow
DEPTH_HIST_TOP_M = 250.0
FLOW_LOG_RANGE = (-3.0, 3.0)  # fine flow histogram: log10 px bounds, FLOW_BINS log bins between
FLOW_BINS = 3000  # (plus [0, 1e-3) below and [1e3, inf) above)
PLOT_FLOW_BINS = 60  # coarse log bins of the flow histogram in stats.png / stats.json
PLOT_DEPTH_BINS = 100  # bins of the 0..--max-depth depth histogram in stats.png / stats.json


class Histogram:
    """Counts of values in fixed bins ``edges[b] <= x < edges[b + 1]``, the last bin open."""

    def __init__(self, edges: np.ndarray) -> None:
        self.edges = np.asarray(edges, dtype=np.float64)  # last bin: [edges[-1], inf)
        self.counts = np.zeros(len(self.edges), dtype=np.int64)

    def add(self, values: np.ndarray) -> None:
        """Count finite or infinite values (NaN is ignored); values below edges[0] go in bin 0."""
        v = np.asarray(values, dtype=np.float64).ravel()
        v = v[~np.isnan(v)]
        b = np.clip(np.searchsorted(self.edges, v, side="right") - 1, 0, len(self.edges) - 1)
        self.counts += np.bincount(b, minlength=len(self.edges))

    @property
    def total(self) -> int:
        return int(self.counts.sum())

    def quantile(self, q: float) -> float | None:
        """Value below which a share ``q`` of the counts lies, interpolated linearly inside its
        bin; None when empty or when it falls in the open last bin."""
        n = self.total
        if n == 0:
            return None
        cum = np.cumsum(self.counts)
        target = q * n
        b = int(np.searchsorted(cum, target, side="left"))
        b = min(b, len(self.counts) - 1)
        if b == len(self.edges) - 1:
            return None
        before = cum[b] - self.counts[b]
        frac = (target - before) / self.counts[b] if self.counts[b] else 0.0
        lo, hi = self.edges[b], self.edges[b + 1]
        return float(lo + frac * (hi - lo))


def depth_histogram() -> Histogram:
    """Fine depth histogram: 1 cm bins from 0 to 250 m, then [250 m, inf)."""
    n = int(round(DEPTH_HIST_TOP_M / DEPTH_BIN_M))
    return Histogram(np.arange(n + 1) * DEPTH_BIN_M)


def flow_histogram() -> Histogram:
    """Fine flow-magnitude histogram (pixels): [0, 1e-3), log bins up to 1e3, [1e3, inf)."""
    return Histogram(np.concatenate([[0.0], np.logspace(*FLOW_LOG_RANGE, FLOW_BINS + 1)]))


def band_shares(depths: np.ndarray) -> dict[str, float]:
    """Share of the pixels of ``depths`` (metres, any shape) in each band of BAND_EDGES_M.

    Bands are half-open, [lo, hi); the last, ``">100"``, is [100 m, inf) and also holds misses
    (formats.NO_SURFACE_DEPTH) and infinities. NaN pixels are ignored. Shares sum to 1 (all 0
    for an empty array).
    """
    counts = band_counts(depths)
    n = counts.sum()
    return {k: float(c / n) if n else 0.0 for k, c in zip(BAND_LABELS, counts, strict=True)}


def band_counts(depths: np.ndarray) -> np.ndarray:
    """Pixel counts per band of BAND_EDGES_M (see :func:`band_shares`)."""
    d = np.asarray(depths, dtype=np.float64).ravel()
    d = d[~np.isnan(d)]
    b = np.clip(np.searchsorted(BAND_EDGES_M, d, side="right") - 1, 0, len(BAND_EDGES_M) - 1)
    return np.bincount(b, minlength=len(BAND_EDGES_M)).astype(np.int64)
