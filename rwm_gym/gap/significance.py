"""Is one simulator's held-out error larger than another's on the same windows? A paired test on block means.

Windows of one episode overlap and share its noise, so they are pooled into blocks (`block_rows` rows of an episode,
`block_ids`) and the test runs on the blocks' mean errors: a one-sided Wilcoxon signed-rank test, or where there are
too few blocks for it to reach the significance asked, a t-test on the blocks' log error ratios (`paired_p_value`).
"""

from __future__ import annotations

import numpy as np
from scipy import stats

from rwm_gym.gap.resim import Windows

MIN_BLOCKS = 8
"""Blocks `block_ids` halves the block length for: the exact one-sided Wilcoxon test on n blocks cannot give p below
2^-n, so with 6 blocks no gap, however large, could reach p < 0.01. Where even one window per block leaves too few,
`paired_p_value` falls back to a t-test on log ratios."""


def block_ids(windows: Windows, block_rows: int) -> np.ndarray:
    """(W,) block of each window: `block_rows` rows of one episode, halved until there are `MIN_BLOCKS` blocks (or
    every window is its own block)."""
    while True:
        blocks = windows.episode * 100_000 + windows.start // block_rows
        if len(np.unique(blocks)) >= MIN_BLOCKS or block_rows <= 1:
            return blocks
        block_rows = max(1, block_rows // 2)


def block_means(values: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """Mean of per-window `values` (W,) in each block, in the order of `np.unique(blocks)`."""
    return np.array([values[blocks == b].mean() for b in np.unique(blocks)])


def paired_p_value(
    larger: np.ndarray, smaller: np.ndarray, windows: Windows, block_rows: int, significance: float = 0.01
) -> float:
    """One-sided p-value that per-window errors `larger` (W,) exceed `smaller` (W,) of the same windows, on block means
    (windows pooled into independent-ish blocks, `block_ids`). Wilcoxon signed-rank test on the differences: rank-based
    because a gap that lives in rare events, such as torque saturation, is heavy-tailed. On n blocks it cannot go below
    2^-n, so where it could not reach `significance` at all (a log whose robot falls at once has few windows), a t-test
    on the blocks' log ratios decides instead: it weighs how many times larger each block's error is (`paired_test`)."""
    blocks = block_ids(windows, block_rows)
    big, small = block_means(larger, blocks), block_means(smaller, blocks)
    if rank_test_can_reach(len(big), significance):
        difference = big - small
        if len(difference) < 3 or np.allclose(difference, difference[0]):
            return 1.0
        return float(stats.wilcoxon(difference, alternative="greater").pvalue)
    logs = np.log(np.maximum(big, 1e-300) / np.maximum(small, 1e-300))
    if len(logs) < 2 or np.allclose(logs, logs[0]):
        return 1.0
    return float(stats.ttest_1samp(logs, 0.0, alternative="greater").pvalue)


def rank_test_can_reach(blocks: int, significance: float) -> bool:
    """Whether the exact one-sided Wilcoxon test on `blocks` blocks can give p below `significance` (2^-n < it)."""
    return 2.0**-blocks < significance


def paired_test(windows: Windows, block_rows: int, significance: float) -> str:
    """Which test `paired_p_value` runs on these windows, in words."""
    n = len(np.unique(block_ids(windows, block_rows)))
    if rank_test_can_reach(n, significance):
        return f"one-sided Wilcoxon signed-rank on {n} block means"
    return (
        f"one-sided t-test on the log ratios of {n} block means (too few blocks for the rank test to reach "
        f"p < {significance})"
    )
