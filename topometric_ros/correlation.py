"""Correlation of metric values with RPE over windows: Pearson, Spearman, Kendall and Multi-relation.

Each function takes 1-D samples of equal length and returns a float coefficient; NaN when it is undefined
(fewer than two finite pairs, or a constant variable). Pairs with a NaN in any variable are dropped.
"""
from __future__ import annotations

import numpy as np
from scipy import stats


def _finite_columns(*variables) -> np.ndarray:
    """(n, k) matrix of the samples where every variable is finite."""
    cols = [np.asarray(v, dtype=np.float64).ravel() for v in variables]
    if len({len(c) for c in cols}) > 1:
        raise ValueError(f"variables differ in length: {[len(c) for c in cols]}")
    m = np.stack(cols, axis=1) if cols else np.empty((0, 0))
    return m[np.all(np.isfinite(m), axis=1)]


def _defined(m: np.ndarray) -> bool:
    return len(m) >= 2 and bool(np.all(np.ptp(m, axis=0) > 0))


def pearson(x, y) -> float:
    """Pearson's linear correlation coefficient r ∈ [−1, 1]."""
    m = _finite_columns(x, y)
    return float(stats.pearsonr(m[:, 0], m[:, 1])[0]) if _defined(m) else float("nan")


def spearman(x, y) -> float:
    """Spearman's rank correlation ρ ∈ [−1, 1]."""
    m = _finite_columns(x, y)
    return float(stats.spearmanr(m[:, 0], m[:, 1])[0]) if _defined(m) else float("nan")


def kendall(x, y) -> float:
    """Kendall's τ-b ∈ [−1, 1]."""
    m = _finite_columns(x, y)
    return float(stats.kendalltau(m[:, 0], m[:, 1])[0]) if _defined(m) else float("nan")


def multi_relation(*variables, ranks: bool = False) -> float:
    """Multi-relation (paper Eq. 9) of two or more variables: standardise each, R = their correlation
    matrix, MR = 1 − λ_min(R) ∈ [0, 1]; 1 when one variable is an exact linear function of the others,
    near 0 for independent variables. ranks=True: the same on each variable's ranks (Spearman-style, 1 for
    exactly monotone relations of two variables; not the paper's definition)."""
    if len(variables) < 2:
        raise ValueError("multi_relation needs at least two variables")
    m = _finite_columns(*variables)
    if not _defined(m):
        return float("nan")
    if ranks:
        m = stats.rankdata(m, axis=0)
    z = (m - m.mean(axis=0)) / m.std(axis=0)
    r = (z.T @ z) / len(z)
    return float(np.clip(1.0 - np.linalg.eigvalsh(r)[0], 0.0, 1.0))
