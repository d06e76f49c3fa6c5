"""Where the feature variance lies: texture, recording condition, their interaction, and what is left.

A fidelity report for any encoded file (issue 13): a one-class-per-texture LDA pools well across speeds and forces
only when the textures differ in the same way under every condition. The decomposition splits the total sum of
squares of a variant's features (summed over feature columns, no scaling: the features the PCA sees) into

* **texture**: between the texture means, ``sum_t n_t ||m_t - m||^2``;
* **condition**: between the condition means (a condition is one speed x force x profile cell);
* **interaction**: between the texture x condition cell means, less the two main effects: how much a texture's
  features change *differently* from the other textures' when the condition changes (what a force or speed
  coefficient cannot undo, because it scales every texture alike);
* **residual**: within the cells (trial-to-trial variation).

The four shares add up to 1. In a balanced design (every texture under every condition, equal trial counts, as in
the paper's protocol) the main effects are orthogonal and every share is >= 0; in an unbalanced one they are not,
and the interaction share (computed as the rest) can be slightly negative: :attr:`VarianceShares.balanced` says
which.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from rigctl.analysis.data import FeatureSet, variant_title

__all__ = ["VarianceShares", "decompose", "decompose_all", "format_variance"]


@dataclass(frozen=True)
class VarianceShares:
    """Shares (fractions 0-1 of the total sum of squares) of one variant's feature variance.

    Attributes
    ----------
    variant : str
    texture, condition, interaction, residual : float
        Fractions of the total sum of squares; they add up to 1.
    n_trials, n_textures, n_conditions, n_cells : int
        Trials used, distinct textures, distinct conditions (speed x force x profile) and non-empty
        texture x condition cells.
    balanced : bool
        Every texture under every condition with the same trial count (main effects orthogonal).
    """

    variant: str
    texture: float
    condition: float
    interaction: float
    residual: float
    n_trials: int
    n_textures: int
    n_conditions: int
    n_cells: int
    balanced: bool

    def as_dict(self) -> dict:
        return asdict(self)


def _codes(*columns: np.ndarray) -> np.ndarray:
    """One integer code per distinct row of the given label columns (NaN is a value of its own)."""
    keys = [np.unique(np.asarray(c).astype(str), return_inverse=True)[1] for c in columns]
    return np.unique(np.stack(keys, axis=1), axis=0, return_inverse=True)[1].ravel()


def _between(x: np.ndarray, codes: np.ndarray, grand: np.ndarray) -> tuple[float, np.ndarray]:
    """Sum of squares of the group means about ``grand`` (weighted by group sizes), and the group sizes."""
    from scipy import sparse  # here: `rigctl analyze` imports this module for its printer (scipy.sparse ~0.4 s)

    n = x.shape[0]
    k = int(codes.max()) + 1
    onehot = sparse.csr_matrix((np.ones(n), (codes, np.arange(n))), shape=(k, n))
    sizes = np.asarray(onehot.sum(axis=1)).ravel()
    means = (onehot @ x) / sizes[:, None]
    return float((sizes * ((means - grand) ** 2).sum(axis=1)).sum()), sizes


def decompose(fs: FeatureSet, variant: str) -> VarianceShares:
    """Variance decomposition of one variant's features (module doc).

    Parameters
    ----------
    fs : FeatureSet
        Encoded features with texture labels; speed (mm/s), force (g) and profile define the condition (a missing
        speed or force counts as one value).
    variant : str
        A variant of ``fs.features``.

    Returns
    -------
    VarianceShares

    Raises
    ------
    KeyError
        ``variant`` is not in the file.
    ValueError
        Fewer than two trials, or features with no variance at all.
    """
    if variant not in fs.features:
        raise KeyError(f"variant {variant} is not in the file (it has {', '.join(fs.features)})")
    x = np.asarray(fs.features[variant], dtype=np.float64)
    if x.shape[0] < 2:
        raise ValueError("the variance decomposition needs at least two trials")
    grand = x.mean(axis=0)
    total = float(((x - grand) ** 2).sum())
    if total <= 0:
        raise ValueError(f"the {variant} features do not vary across trials")
    profile = fs.profile if fs.profile is not None else np.full(len(fs.texture), "")
    tex = _codes(fs.texture)
    cond = _codes(fs.speed_mm_s, fs.force_g, profile)
    cell = _codes(tex, cond)
    ss_tex, _ = _between(x, tex, grand)
    ss_cond, _ = _between(x, cond, grand)
    ss_cell, cell_sizes = _between(x, cell, grand)
    n_tex, n_cond = int(tex.max()) + 1, int(cond.max()) + 1
    balanced = bool(cell_sizes.size == n_tex * n_cond and np.all(cell_sizes == cell_sizes[0]))
    return VarianceShares(variant=variant, texture=ss_tex / total, condition=ss_cond / total,
                          interaction=(ss_cell - ss_tex - ss_cond) / total, residual=(total - ss_cell) / total,
                          n_trials=int(x.shape[0]), n_textures=n_tex, n_conditions=n_cond,
                          n_cells=int(cell_sizes.size), balanced=balanced)


def decompose_all(fs: FeatureSet, variants=None) -> list[VarianceShares]:
    """:func:`decompose` for each of ``variants`` (default: every variant of ``fs``, in the file's order)."""
    return [decompose(fs, v) for v in (variants or list(fs.features))]


def format_variance(rows: list[VarianceShares]) -> str:
    """Plain-text table: one line per variant, the four shares in % of the feature variance."""
    if not rows:
        return "variance decomposition: no variants"
    w = max(len(variant_title(r.variant)) for r in rows) + 2
    r0 = rows[0]
    lines = [f"Feature variance (% of the total sum of squares; {r0.n_trials} trials, {r0.n_textures} textures, "
             f"{r0.n_conditions} conditions, {r0.n_cells} texture x condition cells"
             + ("" if r0.balanced else "; unbalanced: the interaction is the rest after the main effects") + ")",
             f"{'':<{w}}{'texture':>10}{'condition':>11}{'interaction':>13}{'residual':>10}"]
    for r in rows:
        lines.append(f"{variant_title(r.variant):<{w}}{100 * r.texture:10.1f}{100 * r.condition:11.1f}"
                     f"{100 * r.interaction:13.1f}{100 * r.residual:10.1f}")
    return "\n".join(lines)
