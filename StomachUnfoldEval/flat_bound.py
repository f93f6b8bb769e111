"""The best flat layout of markers: a reference for the pairwise distortion of any unfolded view.

The benchmark's statistic for a view is the median over marker pairs of |log(d2 / g)|, d2 the 2D distance of
two markers in the view (mm) and g their geodesic distance on the mucosa (mm), over pairs with g in
[pair_min_mm, pair_max_mm] (10-80 mm by default). ``flat_layout_bound`` minimises the relative errors over the
2D positions of the markers directly (weighted SMACOF stress majorisation, weights 1/g^2, from classical MDS and
random starts, then a polish of sum log^2(d2/g)): the issue's "best possible flat layout of the same markers",
and the ratio method / bound tells how far a method is from it (a sphere cap cannot be laid flat; a cut-open
cylinder can). ``pairwise_distortion`` gives the same statistic for a method's view.

It is not a lower bound of that statistic. It is the best layout for the sum of squared log errors (an upper
estimate of that minimum: a local optimiser), not for their median: with ``robust=True`` the
layouts are also polished for a smoothed sum of |log(d2/g)|, which fits many pairs exactly and a few badly, and
the median falls (to 0.08-0.19 of the bound, median per seed set, over 330 random stomachs: a free layout of 16-24
points has 2M - 3 degrees of freedom for 40-169 pairs). ``surface_layout_reference`` lays out the whole mucosa instead (the markers among
many other points of it, all pairs fitted) and scores the markers: what a layout that does not know where the
markers are can reach.
"""
from __future__ import annotations

import numpy as np
from scipy.optimize import minimize
from scipy.sparse.csgraph import shortest_path

#: smoothing widths (log units) of the robust polish: the layout with the lowest median is kept
ROBUST_EPS = (0.003, 0.001)

__all__ = ["flat_layout_bound", "pair_indices", "pairwise_distortion", "surface_layout_reference"]


def pair_indices(geodesic_mm, pair_min_mm: float = 10.0, pair_max_mm: float = 80.0):
    """Index arrays (I, J), I < J, of marker pairs whose geodesic (mm) is finite and within [min, max]."""
    G = np.asarray(geodesic_mm, float)
    I, J = np.triu_indices(len(G), 1)
    g = G[I, J]
    ok = np.isfinite(g) & (g >= pair_min_mm) & (g <= pair_max_mm) & (g > 0)
    return I[ok], J[ok]


def _stats(X, I, J, g):
    d = np.linalg.norm(X[I] - X[J], axis=1)
    lr = np.log(np.maximum(d, 1e-9) / g)
    return float(np.median(np.abs(lr))), float(np.median(np.abs(d / g - 1.0))), lr


def _classical_mds(G):
    """2D classical MDS of a distance matrix (missing entries completed by shortest paths)."""
    M = len(G)
    A = np.where(np.isfinite(G), G, 0.0)
    D = shortest_path(A, directed=False)
    if not np.all(np.isfinite(D)):
        D[~np.isfinite(D)] = np.nanmax(D[np.isfinite(D)]) * 1.5 if np.isfinite(D).any() else 1.0
    Jc = np.eye(M) - 1.0 / M
    B = -0.5 * Jc @ (D ** 2) @ Jc
    w, V = np.linalg.eigh(B)
    o = np.argsort(w)[::-1][:2]
    return V[:, o] * np.sqrt(np.maximum(w[o], 1e-9))


def _smacof(X, I, J, g, wt, M, iters=400, tol=1e-9):
    W = np.zeros((M, M))
    W[I, J] = wt
    W[J, I] = wt
    Vm = np.diag(W.sum(1)) - W
    Vp = np.linalg.pinv(Vm)
    Dg = np.zeros((M, M))
    Dg[I, J] = g
    Dg[J, I] = g
    prev = np.inf
    for _ in range(iters):
        d = np.linalg.norm(X[:, None, :] - X[None, :, :], axis=2)
        with np.errstate(divide="ignore", invalid="ignore"):
            Bm = np.where(d > 1e-12, -W * Dg / d, 0.0)
        np.fill_diagonal(Bm, 0.0)
        np.fill_diagonal(Bm, -Bm.sum(1))
        X = Vp @ Bm @ X
        dd = np.linalg.norm(X[I] - X[J], axis=1)
        stress = float(np.sum(wt * (dd - g) ** 2))
        if prev - stress < tol * max(prev, 1e-12):
            break
        prev = stress
    return X


def _polish(X, I, J, g, eps: float | None = None, maxiter: int = 500):
    """Layout X (M,2 mm) polished for the sum of squared log distance ratios log(d2/g)^2, or with ``eps`` for the
    smoothed absolute values sqrt(log(d2/g)^2 + eps^2) (L-BFGS)."""
    M = len(X)

    def fun(x):
        """The sum and its gradient."""
        Y = x.reshape(M, 2)
        v = Y[I] - Y[J]
        d = np.maximum(np.linalg.norm(v, axis=1), 1e-9)
        lr = np.log(d / g)
        if eps is None:
            loss, dl = lr ** 2, 2 * lr
        else:
            loss = np.sqrt(lr ** 2 + eps ** 2)
            dl = lr / loss
        gv = (dl / d / d)[:, None] * v
        G = np.zeros_like(Y)
        np.add.at(G, I, gv)
        np.add.at(G, J, -gv)
        return float(np.sum(loss)), G.ravel()

    r = minimize(fun, X.ravel(), jac=True, method="L-BFGS-B", options={"maxiter": maxiter})
    return r.x.reshape(M, 2)


def flat_layout_bound(geodesic_mm, pair_min_mm: float = 10.0, pair_max_mm: float = 80.0, restarts: int = 6,
                      seed: int = 0, robust: bool = False) -> dict:
    """Best 2D layout (mm) of markers against their geodesic distances (M,M mm; NaN = unknown).

    The layout minimises the squared log errors; ``robust`` also polishes each for their smoothed absolute value
    and keeps the lowest median (see the module's docstring).

    Returns ``median_relative_error`` (median |log(d2/g)| over pairs with g in [min, max] mm, the benchmark's
    statistic), ``median_abs_relative_error`` (median |d2/g - 1|), ``positions_mm`` (M,2), ``n_pairs``.
    """
    G = np.array(geodesic_mm, float)
    G = 0.5 * (G + G.T)
    M = len(G)
    I, J = pair_indices(G, pair_min_mm, pair_max_mm)
    out = {"n_pairs": len(I), "pair_min_mm": float(pair_min_mm), "pair_max_mm": float(pair_max_mm),
           "n_markers": int(M)}
    if len(I) == 0:
        out.update(median_relative_error=float("nan"), median_abs_relative_error=float("nan"),
                   positions_mm=np.full((M, 2), np.nan).tolist(), restarts=0)
        return out
    g = G[I, J]
    wt = 1.0 / g ** 2
    rng = np.random.default_rng(seed)
    inits = [_classical_mds(G)]
    scale = float(np.median(g))
    inits += [rng.normal(0, scale, (M, 2)) for _ in range(max(0, restarts - 1))]
    best = None
    for X0 in inits:
        X = _smacof(X0.copy(), I, J, g, wt, M)
        cands = [X, _polish(X, I, J, g)]
        if robust:
            cands += [_polish(cands[1], I, J, g, eps, maxiter=2000) for eps in ROBUST_EPS]
        for cand in cands:
            med, mabs, _ = _stats(cand, I, J, g)
            if best is None or med < best[0]:
                best = (med, mabs, cand)
    med, mabs, X = best
    X = X - X.mean(0)
    out.update(median_relative_error=med, median_abs_relative_error=mabs, positions_mm=X.tolist(),
               restarts=len(inits))
    return out


def pairwise_distortion(view_xy, geodesic_mm, pair_min_mm: float = 10.0, pair_max_mm: float = 80.0,
                        bound: dict | float | None = None) -> dict:
    """The same statistic for a method's view: marker 2D positions (M,2 mm, NaN = not seen) against geodesics (mm).

    With ``bound`` (a ``flat_layout_bound`` result or its median), also ``ratio_to_bound``.
    """
    X = np.asarray(view_xy, float)
    I, J = pair_indices(geodesic_mm, pair_min_mm, pair_max_mm)
    seen = np.all(np.isfinite(X[I]), 1) & np.all(np.isfinite(X[J]), 1)
    I, J = I[seen], J[seen]
    out = {"n_pairs": len(I), "pair_min_mm": float(pair_min_mm), "pair_max_mm": float(pair_max_mm)}
    if len(I) == 0:
        out.update(median_relative_error=float("nan"), median_abs_relative_error=float("nan"))
    else:
        g = np.asarray(geodesic_mm, float)[I, J]
        med, mabs, _ = _stats(X, I, J, g)
        out.update(median_relative_error=med, median_abs_relative_error=mabs)
    if bound is not None:
        b = bound["median_relative_error"] if isinstance(bound, dict) else float(bound)
        out["bound_median_relative_error"] = float(b)
        out["ratio_to_bound"] = float(out["median_relative_error"] / b) if b > 0 else float("inf")
    return out


def surface_layout_reference(geodesic_mm, n_markers: int, pair_min_mm: float = 10.0, pair_max_mm: float = 80.0,
                             robust: bool = False, restarts: int = 2, seed: int = 0) -> dict:
    """The best flat layout of the whole mucosa scored on its markers: geodesics (M,M mm) among the markers (the
    first ``n_markers`` rows) and other points of the mucosa (``random_stomach.surface_reference_geodesics``).

    All points are laid out together against all their pairs (``flat_layout_bound``; ``robust`` as there, the
    layout chosen by the median over all pairs, never by the markers'), then the markers' own statistic is read:
    the median |log(d2/g)| over marker pairs with g in [min, max] mm. Returns ``median_relative_error`` (that
    statistic), ``all_pairs_median`` (the layout's own), ``n_points``, ``n_pairs`` (marker pairs).
    """
    G = np.array(geodesic_mm, float)
    G = 0.5 * (G + G.T)
    lay = flat_layout_bound(G, pair_min_mm, pair_max_mm, restarts=restarts, seed=seed, robust=robust)
    X = np.array(lay["positions_mm"], float)[:n_markers]
    I, J = pair_indices(G[:n_markers, :n_markers], pair_min_mm, pair_max_mm)
    med = _stats(X, I, J, G[I, J])[0] if len(I) else float("nan")
    return {"median_relative_error": med, "all_pairs_median": lay["median_relative_error"], "n_points": len(G),
            "n_pairs": int(len(I)), "robust": bool(robust)}
