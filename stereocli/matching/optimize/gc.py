"""Graph cuts: α-expansion (Boykov, Veksler & Zabih 2001) with PyMaxflow.

Energy on the 4-connected pixel grid::

    E(d) = Σ_p D_p(d_p) + Σ_{(p,q) ∈ N4} λ · w_pq · V(d_p, d_q)
    D_p(d) = min(C(p, d), data_trunc)
    V = [d_p ≠ d_q] (Potts)   or   min(|d_p − d_q|, T) (truncated linear)

Both V are metrics, so every expansion move is a submodular binary problem solved exactly by
one max-flow (Kolmogorov & Zabih 2004 construction); cycles over all labels until no move
lowers E. The pairwise graph is built with PyMaxflow's grid calls from numpy arrays (no
per-pixel Python).

PyMaxflow is an optional extra: ``pip install "stereocli[maxflow]"``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ...errors import ConfigError
from ...registry import StageTraits, param, register
from ..kernels.dp import edge_weights, warp_to_right
from ..kernels.winners import wta_left
from ..state import MatchState

_RIGHT = np.array([[0, 0, 0], [0, 0, 1], [0, 0, 0]])
_DOWN = np.array([[0, 0, 0], [0, 0, 0], [0, 1, 0]])


@dataclass(frozen=True)
class GCParams:
    smoothness: float = param(0.3, "λ: cost of a disparity change between 4-neighbours (per px for truncated_linear), "
                              "as a fraction of cost_max", low=0.0, high=1e6)
    model: str = param("potts", "smoothness term V", choices=("potts", "truncated_linear"))
    truncate: float = param(2.0, "T of the truncated-linear term (ignored for potts)", unit="px", low=1.0, high=1e4)
    data_trunc: float = param(0.0, "truncate the data cost at this fraction of cost_max (0 = off)", low=0.0, high=1.0)
    cycles: int = param(3, "maximum passes over all labels (stops early when no move helps)", low=1, high=50)
    edge_threshold: float = param(8.0, "grey difference below which neighbours count as the same surface",
                                  unit="grey levels", low=0.0, high=255.0)
    edge_factor: float = param(2.0, "smoothness multiplier between same-surface neighbours (1 = off)",
                               low=1.0, high=100.0)


def _import_maxflow():
    try:
        import maxflow
    except ImportError:
        raise ConfigError(
            'optimizer.name: gc needs the PyMaxflow package; install the extra with pip install "stereocli[maxflow]"'
        ) from None
    return maxflow


def _pair_cost(a: np.ndarray, b: np.ndarray, model: str, trunc: float) -> np.ndarray:
    if model == "potts":
        return (a != b).astype(np.float64)
    return np.minimum(np.abs(a - b), trunc).astype(np.float64)


def energy(data: np.ndarray, labels: np.ndarray, wh: np.ndarray, wv: np.ndarray, lam: float, model: str,
           trunc: float) -> float:
    """E(labels) of :mod:`this module's <stereocli.matching.optimize.gc>` energy (for tests)."""
    unary = np.take_along_axis(data, labels[..., None], 2).sum(dtype=np.float64)
    ph = _pair_cost(labels[:, :-1], labels[:, 1:], model, trunc) * wh[:, :-1]
    pv = _pair_cost(labels[:-1], labels[1:], model, trunc) * wv[:-1]
    return float(unary + lam * (ph.sum() + pv.sum()))


def expansion(data: np.ndarray, labels: np.ndarray, alpha: int, wh: np.ndarray, wv: np.ndarray,
              lam: float, model: str, trunc: float, maxflow) -> np.ndarray:
    """One α-expansion move: the labelling within one expansion of ``labels`` minimising E.

    Binary variable x_p = 1 means "p switches to α". Each pairwise term with
    E00 = V(f_p, f_q), E01 = V(f_p, α), E10 = V(α, f_q), E11 = 0 is written as
    E00 + (E10 − E00)·x_p − E10·x_q + (E01 + E10 − E00)·(1 − x_p)·x_q; the last coefficient is
    ≥ 0 because V is a metric (triangle inequality), giving an edge p → q. x_p = 1 is the sink
    side, so a positive unary coefficient goes on the source t-link and a negative one on the
    sink t-link.
    """
    h, w = labels.shape
    fa = np.full((1, 1), alpha)
    coef = (data[:, :, alpha].astype(np.float64)
            - np.take_along_axis(data, labels[..., None], 2)[..., 0].astype(np.float64))
    g = maxflow.Graph[float]()
    nodes = g.add_grid_nodes((h, w))
    for axis, wgt, struct in ((1, wh, _RIGHT), (0, wv, _DOWN)):
        if axis == 1:
            fp, fq, lw = labels[:, :-1], labels[:, 1:], lam * wgt[:, :-1]
        else:
            fp, fq, lw = labels[:-1], labels[1:], lam * wgt[:-1]
        e00 = lw * _pair_cost(fp, fq, model, trunc)
        e01 = lw * _pair_cost(fp, fa, model, trunc)
        e10 = lw * _pair_cost(fa, fq, model, trunc)
        cap = np.zeros((h, w))
        if axis == 1:
            coef[:, :-1] += e10 - e00
            coef[:, 1:] -= e10
            cap[:, :-1] = np.maximum(e01 + e10 - e00, 0.0)
        else:
            coef[:-1] += e10 - e00
            coef[1:] -= e10
            cap[:-1] = np.maximum(e01 + e10 - e00, 0.0)
        g.add_grid_edges(nodes, weights=cap, structure=struct, symmetric=False)
    g.add_grid_tedges(nodes, np.maximum(coef, 0.0), np.maximum(-coef, 0.0))
    g.maxflow()
    switch = g.get_grid_segments(nodes)
    return np.where(switch, alpha, labels)


# Extra volumes: truncated data term (when data_trunc > 0) + per-expansion graph.
@register("optimizer", "gc", GCParams, traits=StageTraits(volume_copies=2.0))
def gc(state: MatchState, p: GCParams) -> None:
    """Graph cuts (α-expansion, Boykov–Veksler–Zabih) with Potts or truncated-linear smoothness.

    Energy: Σ_p min(C, data_trunc) + Σ_{4-neighbours} λ·w_pq·V(d_p, d_q), V = Potts or
    min(|Δd|, T). Each move is solved exactly by max-flow (PyMaxflow, optional extra:
    pip install "stereocli[maxflow]"); a strong local minimum within a known factor of the
    optimum. Slower than BP (one max-flow per label per cycle) but crisp fronto-parallel
    surfaces with Potts. Starts from winner-take-all. The right-view disparity is the
    z-buffered warp of the result (``lr_check`` then removes occlusions). In row strips each strip is optimised on
    its own. λ and data_trunc are fractions of the cost range ``cost_max``.
    """
    maxflow = _import_maxflow()
    cost = state.cost
    if cost is None:  # (never: the pipeline runs a cost stage first)
        raise RuntimeError("optimizer.gc: no cost volume")
    h, w, nd = cost.shape
    data = cost if p.data_trunc <= 0 else np.minimum(cost, np.float32(p.data_trunc * state.cost_max))
    wh, wv = edge_weights(np.ascontiguousarray(state.gray("left")), float(p.edge_threshold), float(p.edge_factor))
    wta, _ = wta_left(cost, state.min_disp, np.float32(state.cost_max))
    labels = np.argmin(cost, axis=2).astype(np.int64)
    lam, trunc = float(p.smoothness) * state.cost_max, float(p.truncate)
    e = energy(data, labels, wh, wv, lam, p.model, trunc)
    for _ in range(p.cycles):
        improved = False
        for alpha in range(nd):
            new = expansion(data, labels, alpha, wh, wv, lam, p.model, trunc, maxflow)
            e_new = energy(data, new, wh, wv, lam, p.model, trunc)
            if e_new < e - 1e-6 * max(1.0, abs(e)):
                labels, e, improved = new, e_new, True
        if not improved:
            break
    disp = (labels + state.min_disp).astype(np.float32)
    disp[~np.isfinite(wta)] = np.inf  # nothing could be matched there
    state.disparity = disp
    # No two-view volume: the right view is the z-buffered warp of the labelling, so lr_check
    # removes occluded pixels instead of disagreeing with a raw winner-take-all.
    state.disparity_right = warp_to_right(disp)
