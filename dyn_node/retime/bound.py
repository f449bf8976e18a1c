"""T*, a lower bound on the duration certified against its grid (issue 39 item 4).

TOPP-RA's optimum on a grid is not a bound: its rows hold at the grid points only, and a finer
grid can be faster (issue 39: 5.7 % on a 250-waypoint path). Here every row a(s)·u + b(s)·x +
c(s) ≤ 0 (x = ṡ², u = s̈; :func:`topp.joint_rows` with ``lower_bound=True``) is relaxed so
that the *true* motion's samples x_i = x(s_i) and each stage's mean ū = (x_{i+1} − x_i)/(2Δ)
satisfy it. Averaging the row over the stage [s_i, s_i + Δ] and writing a = a_m + (a − a_m)
etc. about the stage's midpoint m:

    a_m·ū + b_m·(x_i + x_{i+1})/2 + c_m ≤ V_a·U + V_b·X + |b_m|·Δ·(U⁺ + U⁻)/4 + V_c

with V_r the largest |r(s) − r_m| over the stage, X the largest x there, u in [−U⁻, U⁺]
there (U = max of both), and |mean of x − (x_i + x_{i+1})/2| ≤ Δ(U⁺ + U⁻)/4 (x' = 2u lies
in [−2U⁻, 2U⁺]: the tent bound). X is the least of the first-order rows' bound (x ≤ xmax:
1/√xmax, the path's speed per unit ṡ over the limits, bounded below on the stage) and the
stage's *ceiling*: the largest x some u allows with every row at its most permissive over the
stage (a·u ≥ (a_m ∓ V_a)·u, b ≥ b_m − V_b, c ≥ c_m − V_c: :func:`reach.stage_ceiling`, which
needs no U), and from the second round on the peak of the tent below. U⁺ (U⁻) is the least,
over rows whose a keeps its sign > 0 (< 0) on the stage, of (max(0, −c) + max(0, −b)·X)/|a|.
Where U or a V is unbounded (q' → 0 at a stop by s) the stage's rows are dropped.

*How V is bounded*: from the rows at the stage's ends and midpoint, V_r = max(|r_i − r_m|,
|r_{i+1} − r_m|) + |r_i − 2r_m + r_{i+1}|: exact for a row linear or monotone cubic in s,
3× the excursion of a quadratic; what it assumes is that no row swings inside half a stage by
more than its second difference shows (the rows are smooth functions of the path's
polynomials). A knot of the path (q'' jumps on a C¹ path) is a grid point, with the rows there
from each side (the stage ending there gets the left limit): no stage holds a jump. The same
rule bounds 1/√xmax and |a| from below.

The relaxed problem's controllable sets (backward) and reachable sets (forward,
:func:`reach.relaxed_backward`, :func:`reach.relaxed_forward`: exact projections, no TOPP-RA
variable bounds, widened by 1e-10 for rounding) hold every true x(s_i): x̄_i, the reachable
set's upper end, bounds x(s_i) from above. Between grid points x(s) ≤ min(x̄_i + 2U⁺σ,
x̄_{i+1} + 2U⁻(Δ − σ), X), and T* = Σ ∫ ds/√(that), in closed form (:func:`stage_times`).

The slack is first order in Δ: stages whose slack exceeds 5 % of a row's scale are cut in
four, the costliest first (looseness × the stage's time), at most three times and up to as
many new stages as the grid had. A path that starts or ends at rest is taken by its arc length
(:class:`ByArc`: at the base path's s, so its knots stay exact), where ṡ = 0 at rest and the
rows stay bounded; in s, q' → 0 there makes U and X unbounded and the bound loose.
"""
from __future__ import annotations

import math

import numpy as np

from dyn_node.core.robot.dynamics import Dynamics
from dyn_node.retime import reach, topp
from dyn_node.retime.path import ArcPath

#: rounds of the relaxation: each bounds the stages' largest x (X) by the last round's x̄
ROUNDS = 2
#: a stage is cut where a row's slack exceeds this share of its scale (|limit| + |c|) ...
TOLERANCE = 0.05
#: ... at most this many times, and at most as many stages in all as the grid had
LEVELS = 3
#: the stages a loose stage is cut into
SPLIT = 4
#: the least stages per polynomial piece of the path (before any is cut)
PER_SEGMENT = 16


def for_retime(dynamics: Dynamics, path, parts: list[tuple], grid_points: int,
               start_speed) -> tuple[float, int]:
    """T* and its stages for the retimer (``parts``: its search's pieces, each (path, grid,
    terms); ``start_speed(p)``: ṡ₀ on p): on the search's own path and grid when it is one
    piece (by arc length, :class:`ByArc` at the same points, when it starts or ends at rest),
    else on the whole path by arc length (T* may pass its stops moving); with at least
    :data:`PER_SEGMENT` stages per piece of the path (up to 8 × ``grid_points``)."""
    # at least PER_SEGMENT stages per polynomial piece: the slack is first order in a stage's
    # width against the path's bends, and a waypoint path bends at every knot (up to 8× the
    # grid: the cost grows with the stages)
    n = max(grid_points, min(PER_SEGMENT * (len(path.pp.breaks) - 1), 8 * grid_points))
    if len(parts) == 1:
        p, grid, terms = parts[0]
        if n > grid_points:
            grid, terms = np.linspace(p.pp.breaks[0], p.pp.breaks[-1], n + 1), None
        if isinstance(p, ArcPath):
            out = certified(dynamics, ByArc(p.base), _s_grid(p, grid), sd_start=start_speed(p))
        else:
            out = certified(dynamics, p, grid, terms=terms, sd_start=start_speed(p))
        if math.isfinite(out[0]):
            return out
    # by arc length too, on the whole path's arc-length grid
    arc = ArcPath(path)
    grid = np.linspace(0.0, arc.length, n + 1)
    return certified(dynamics, ByArc(path), _s_grid(arc, grid), sd_start=start_speed(arc))


def _s_grid(arc: ArcPath, grid: np.ndarray) -> np.ndarray:
    """The base path's s at an arc-length grid (increasing, ends exact)."""
    s = np.maximum.accumulate(arc._s_of(grid))
    s[0], s[-1] = arc.base.pp.breaks[0], arc.base.pp.breaks[-1]
    return np.unique(s)


def certified(dynamics: Dynamics, path, grid: np.ndarray, *, terms: topp.Terms | None = None,
              sd_start: float = 0.0, free_ends: bool = True) -> tuple[float, int]:
    """(T*, the number of stages it holds for) on ``path`` (any object with ``derivatives``:
    :class:`Path` or :class:`ArcPath`) from ``grid`` (``terms``: :func:`topp.joint_terms` there
    when already computed), its stages cut where the relaxation is loose (:data:`LEVELS`);
    ``sd_start``: ṡ at the start; ``free_ends``: ṡ free at an end where q' = 0 (the robot is at
    rest there at any ṡ). T* is NaN when the relaxed rows admit no motion (then none does)."""
    grid = np.asarray(grid, dtype=float)
    knots = _knots(path, grid)
    if knots.size:
        grid, terms = np.union1d(grid, knots), None
    rows = topp.joint_rows(dynamics, path, grid, lower_bound=True, terms=terms)
    # each stage's end: the rows there, from the left where q'' (and so b) jumps at a knot
    last = _take(rows, np.arange(1, len(grid)))
    if knots.size:
        at = np.searchsorted(grid, knots) - 1
        left = topp.joint_rows(dynamics, path, np.nextafter(knots, -np.inf), lower_bound=True)
        last = _cat([_take(last, np.setdiff1d(np.arange(len(grid) - 1), at)), left],
                    np.argsort(np.concatenate([np.setdiff1d(np.arange(len(grid) - 1), at), at]),
                               kind="stable"))
    mid = topp.joint_rows(dynamics, path, 0.5 * (grid[1:] + grid[:-1]), lower_bound=True)
    ends = np.max(np.abs(path.derivatives(grid[[0, -1]])[1]), axis=1)
    budget = len(grid) - 1
    st = stages(_take(rows, np.arange(len(grid) - 1)), last, mid)
    st["d"] = _widths(path, grid)
    for level in range(LEVELS + 1):
        d = st["d"]
        final = level == LEVELS or budget <= 0
        xmax = np.where(np.isfinite(rows.xmax) & (rows.xmax < 1e300), rows.xmax, np.inf)
        out = _solve(st, xmax, d, ends, sd_start, free_ends, 1 if not final else ROUNDS)
        if out is None:
            return math.nan, len(d)
        xbar, up, down, X, loose = out
        bad = np.flatnonzero(loose > TOLERANCE)
        # the budget goes where the slack costs most time: looseness × the stage's time
        cost = np.minimum(loose, 1.0) * stage_times(xbar, up, down, X, d)
        bad = np.sort(bad[np.argsort(cost[bad])[::-1][:budget // (SPLIT - 1)]])
        if final or bad.size == 0:
            if not final and ROUNDS > 1:
                # no stage left to cut: this grid is the last, with all the rounds
                xbar, up, down, X, loose = _solve(st, xmax, d, ends, sd_start, free_ends,
                                                  ROUNDS)
            break
        budget -= bad.size * (SPLIT - 1)
        grid, rows, st = _split(dynamics, path, grid, rows, last, st, bad)
        last = st.pop("last")
    return float(np.sum(stage_times(xbar, up, down, X, d))), len(d)


def _solve(st, xmax, d, ends, sd_start, free_ends, rounds: int) -> tuple | None:
    """x̄ and the stages' U⁺, U⁻, X and looseness (largest slack ÷ the row's scale)."""
    X = st["X"]
    for _ in range(rounds):
        al, be, ga, up, down, loose = relaxed_rows(st, d, X)
        xbar = _upper(al, be, ga, xmax, d, ends, sd_start, free_ends)
        if xbar is None:
            return None
        # the stage's largest x under the tent bounds X in the next round
        X = np.minimum(X, peaks(xbar, up, down, X, d))
    return xbar, up, down, X, loose


class ByArc:
    """A :class:`Path` by its arc length ℓ (2-norm of q'), evaluated at the path's own s: a
    grid in s keeps the knots exact (:func:`_knots`), the stages' widths in ℓ come from
    :meth:`widths`. (q, q_ℓ, q_ℓℓ) as :class:`ArcPath` has them (q_ℓ = q'/|q'|, q_ℓℓ = (q'' −
    q_ℓ(q_ℓ·q''))/|q'|²; where q' = 0 the limits from the side asked for)."""

    #: Gauss–Legendre nodes and weights on [−1, 1] (3 points: exact to degree 5)
    _NODES, _WEIGHTS = np.polynomial.legendre.leggauss(3)

    def __init__(self, base):
        self.base, self.pp = base, base.pp
        self._speed = float(np.max(np.linalg.norm(
            base.derivatives(np.linspace(base.pp.breaks[0], base.pp.breaks[-1], 101))[1], axis=1)))

    def derivatives(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        s = np.asarray(s, dtype=float)
        q, d1, d2 = self.base.derivatives(s)
        n = np.linalg.norm(d1, axis=1)
        # where q' = 0 (an end or a stop, q' ∝ σ or σ² there) its direction is its limit from
        # the side asked for (a point just below a knot: its left): far enough inside that
        # rounding cannot flip q' (at 1e-9 of the length a quintic's q' ~ 1e-18 did)
        flat = n <= 1e-9 * self._speed
        if np.any(flat):
            br = self.pp.breaks
            near = br[np.clip(np.searchsorted(br, s[flat]), 0, len(br) - 1)]
            eps = 1e-6 * (br[-1] - br[0])
            at = np.clip(np.where(s[flat] < near, s[flat] - eps, s[flat] + eps),
                         br[0] + eps, br[-1] - eps)
            _, d1[flat], d2[flat] = self.base.derivatives(at)
            n[flat] = np.linalg.norm(d1[flat], axis=1)
        n = np.maximum(n, 1e-300)[:, None]
        t = d1 / n
        return q, t, (d2 - t * np.sum(t * d2, axis=1, keepdims=True)) / n**2

    def widths(self, grid: np.ndarray) -> np.ndarray:
        """Each stage's length in ℓ: ∫|q'|ds by Gauss–Legendre (the grid holds the knots, so
        |q'| is smooth on every stage: the rule's error is far below the bound's slack)."""
        h = np.diff(grid)[:, None] / 2
        s = (grid[:-1, None] + h) + h * self._NODES[None, :]
        speed = np.linalg.norm(self.base.pp.evaluate(s.ravel(), orders=2)[1],
                               axis=1).reshape(s.shape)
        return (h[:, 0] * (speed @ self._WEIGHTS))


def _knots(path, grid: np.ndarray) -> np.ndarray:
    """The path's knots strictly inside the grid (a :class:`Path`'s polynomial pieces: q'' of a
    C¹ path jumps there), none for a path of another kind."""
    coeffs = getattr(path.pp, "coeffs", None)
    br = np.asarray(path.pp.breaks, dtype=float)
    return br[(br > grid[0]) & (br < grid[-1])] if coeffs is not None else br[:0]


def _take(rows: topp.Rows, idx: np.ndarray) -> topp.Rows:
    return topp.Rows(rows.a[idx], rows.b[idx], rows.c[idx], rows.g, rows.xmax[idx])


def _cat(parts: list[topp.Rows], order: np.ndarray) -> topp.Rows:
    def cat(name):
        return np.concatenate([getattr(r, name) for r in parts])[order]
    return topp.Rows(cat("a"), cat("b"), cat("c"), parts[0].g, cat("xmax"))


def _split(dynamics, path, grid, rows, last, st, bad):
    """The grid with stages ``bad`` cut into :data:`SPLIT` equal stages, its rows, and the
    stages' :func:`stages` (plus ``last``: the rows at each stage's end, from the left at a
    knot), computed for the new stages only (one pass of the path's terms at the new points
    and midpoints)."""
    f = np.arange(1, 2 * SPLIT) / (2 * SPLIT)           # the new points and midpoints
    new = grid[bad, None] + np.diff(grid)[bad, None] * f[None, :]
    fresh = topp.joint_rows(dynamics, path, new.ravel(), lower_bound=True)
    idx = np.arange(new.size).reshape(new.shape)
    pts, mids = idx[:, 1::2], idx[:, ::2].ravel()
    g2 = np.concatenate([grid, new[:, 1::2].ravel()])
    order = np.argsort(g2, kind="stable")
    keep = np.setdiff1d(np.arange(len(grid) - 1), bad)
    piece = np.concatenate([grid[bad, None], new[:, 1::2]], axis=1)      # starts, B × SPLIT
    B, inner = len(bad), np.arange(len(bad))[:, None] * (SPLIT - 1) + np.arange(SPLIT - 1)
    # the new stages, piece j of cut stage r in row-major (r, j) order: piece j starts at the
    # cut stage's start (j = 0) or its new point j, ends at its new point j + 1 or its end
    col = np.arange(B)[:, None]
    first = _cat([_take(rows, bad), _take(fresh, pts.ravel())],
                  np.concatenate([col, B + inner], axis=1).ravel())
    end = _cat([_take(fresh, pts.ravel()), _take(last, bad)],
               np.concatenate([inner, B * (SPLIT - 1) + col], axis=1).ravel())
    sub = stages(first, end, _take(fresh, mids))
    sub["d"] = _widths(path, np.column_stack([piece, grid[bad + 1]]))
    sub["last"] = end
    kept = {k: v[keep] for k, v in st.items()}
    kept["last"] = _take(last, keep)
    by_start = np.argsort(np.concatenate([grid[keep], piece.ravel()]), kind="stable")
    out = {k: _splice(kept[k], sub[k], by_start) for k in sub}
    return g2[order], _cat([rows, _take(fresh, pts.ravel())], order), out


def _widths(path, grid: np.ndarray) -> np.ndarray:
    """The stages' widths in the path's parameter: of a grid (N+1,), or of rows of grids
    (B × (k+1): their stages row by row)."""
    if grid.ndim == 2:
        # one pass over the rows laid end to end, the steps between rows dropped
        w = _widths(path, grid.ravel())
        k = grid.shape[1]
        return np.delete(w, np.arange(k - 1, w.size, k))
    return path.widths(grid) if hasattr(path, "widths") else np.diff(grid)


def _splice(a, b, order):
    """Two stages' worth of arrays or rows (:class:`topp.Rows`) joined in ``order``."""
    if isinstance(a, topp.Rows):
        return _cat([a, b], order)
    return np.concatenate([a, b])[order]


def _upper(al, be, ga, xmax, d, ends, sd_start, free_ends) -> np.ndarray | None:
    """x̄_i: the upper ends of the relaxed problem's reachable sets (None: none)."""
    n = len(d)
    K = np.zeros((n + 1, 2))
    K[n] = [0.0, xmax[n] if free_ends and ends[1] == 0.0 else 0.0]
    if reach.relaxed_backward(al, be, ga, xmax, d, K) >= 0:
        return None
    R = np.full((n + 1, 2), np.nan)
    if free_ends and ends[0] == 0.0 and sd_start == 0.0:
        R[0] = K[0]
    else:
        x0 = sd_start**2
        if not K[0, 0] - topp._START_SLACK <= x0 <= K[0, 1] + topp._START_SLACK:
            return None
        R[0] = [x0, x0]
    if reach.relaxed_forward(al, be, ga, K, d, R) >= 0:
        return None
    return R[:, 1]


def variation(r0: np.ndarray, rm: np.ndarray, r1: np.ndarray) -> np.ndarray:
    """V_r over each stage from its ends and midpoint (module docstring)."""
    with np.errstate(invalid="ignore"):
        v = np.maximum(np.abs(r0 - rm), np.abs(r1 - rm)) + np.abs(r0 - 2 * rm + r1)
    return np.where(np.isfinite(v), v, np.inf)


def _times(v: np.ndarray, bound: np.ndarray) -> np.ndarray:
    """v·bound with 0·∞ = 0 (no variation: the term is 0 whatever the bound)."""
    with np.errstate(invalid="ignore"):
        return np.where(v == 0.0, 0.0, v * bound)


def stages(first: topp.Rows, last: topp.Rows, mid: topp.Rows) -> dict:
    """What the relaxation needs of each stage that no round changes, from the rows at its
    start, end and midpoint: the midpoint's rows (c − limit), their variations V, and the
    ceiling X (module docstring)."""
    am, bm, cm = mid.a, mid.b, mid.c - mid.g
    Va = variation(first.a, am, last.a)
    Vb = variation(first.b, bm, last.b)
    Vc = variation(first.c - first.g, cm, last.c - last.g)
    # the path's speed per unit ṡ over the limits, 1/√xmax, bounded below on the stage
    with np.errstate(divide="ignore"):
        w0, wm, w1 = (1.0 / np.sqrt(np.maximum(r.xmax, 1e-300)) for r in (first, mid, last))
    wlo = np.minimum(np.minimum(w0, wm), w1) - variation(w0, wm, w1)
    with np.errstate(divide="ignore"):
        X = np.where(wlo > 0, 1.0 / np.maximum(wlo, 1e-300) ** 2, np.inf)
    # the stage's largest x: its rows at their most permissive over the stage (a ceiling that
    # needs no bound on u, so the bound on u can use it)
    live = np.isfinite(Va) & np.isfinite(Vb) & np.isfinite(Vc)
    X = np.ascontiguousarray(X)
    reach.stage_ceiling(*(np.ascontiguousarray(np.where(live, v, dead)) for v, dead in (
        (am - Va, 0.0), (am + Va, 0.0), (bm - Vb, 0.0), (cm - Vc, -1.0))), X)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = 1.0 / (np.abs(mid.g) + np.abs(mid.c))
    return dict(am=am, bm=bm, cm=cm, Va=Va, Vb=Vb, Vc=Vc, X=X, scale=scale)


def relaxed_rows(st: dict, d: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, ...]:
    """The stages' relaxed rows α·ū + β·x_i + γ ≤ 0 (N×m each; a dropped row is 0·ū + 0·x − 1)
    for the stages' largest x ``X`` (:func:`stages`), U⁺, U⁻ and each stage's looseness (its
    largest slack ÷ the row's |limit| + |c|)."""
    am, bm, Va, Vb = st["am"], st["bm"], st["Va"], st["Vb"]
    alo = np.abs(am) - Va
    # u's range on the stage from every row whose a keeps its sign there
    with np.errstate(invalid="ignore", divide="ignore"):
        num = (np.maximum(0.0, st["Vc"] - st["cm"])
               + _times(np.maximum(0.0, Vb - bm), X[:, None]))
        lim = np.where(alo > 0, num / np.where(alo > 0, alo, 1.0), np.inf)
    lim = np.where(np.isnan(lim), np.inf, lim)
    up = np.min(np.where(am > 0, lim, np.inf), axis=1, initial=np.inf)
    down = np.min(np.where(am < 0, lim, np.inf), axis=1, initial=np.inf)
    U, dd = np.maximum(up, down)[:, None], d[:, None]
    slack = (_times(Va, U) + _times(Vb, X[:, None])
             + _times(np.abs(bm), dd * (up + down)[:, None] / 4) + st["Vc"])
    keep = np.isfinite(slack)
    with np.errstate(invalid="ignore"):
        share = np.where(slack == 0.0, 0.0, slack * st["scale"])
    loose = np.max(np.where(np.isnan(share), np.inf, share), axis=1, initial=0.0)
    al = np.where(keep, am + dd * bm, 0.0)
    be = np.where(keep, bm, 0.0)
    ga = np.where(keep, st["cm"] - slack, -1.0)
    return (np.ascontiguousarray(al), np.ascontiguousarray(be), np.ascontiguousarray(ga),
            up, down, loose)


def peaks(xbar, up, down, X, d) -> np.ndarray:
    """Each stage's largest x under min(x̄_i + 2U⁺σ, x̄_{i+1} + 2U⁻(Δ − σ), X)."""
    p, r = xbar[:-1], xbar[1:]
    sc = _meet(p, r, up, down, d)
    with np.errstate(invalid="ignore"):
        left = np.where(np.isinf(up), np.inf, p + 2 * up * sc)
        right = np.where(np.isinf(down), np.inf, r + 2 * down * (d - sc))
    return np.minimum(np.minimum(left, right), X)


def _meet(p, r, up, down, d) -> np.ndarray:
    """σ where the two lines meet, in [0, Δ] (one side unbounded: the other line alone)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        sc = np.where(np.isinf(up), 0.0, np.where(np.isinf(down), d,
                      (r - p + 2 * down * d) / (2 * (up + down))))
    return np.clip(np.where(np.isnan(sc), 0.0, sc), 0.0, d)


def stage_times(xbar: np.ndarray, up: np.ndarray, down: np.ndarray, X: np.ndarray,
                d: np.ndarray) -> np.ndarray:
    """Each stage's least time: ∫ dσ/√f over [0, Δ] with f(σ) = min(x̄_i + 2U⁺σ,
    x̄_{i+1} + 2U⁻(Δ − σ), X), in closed form (∫ dσ/√(p + 2Uσ) over [0, σ₁] is
    2σ₁/(√(p + 2Uσ₁) + √p))."""
    p, r = xbar[:-1], xbar[1:]
    sc = _meet(p, r, up, down, d)
    with np.errstate(invalid="ignore", divide="ignore"):

        def side(x0, U, length):
            room = np.where(np.isinf(X), np.inf, X - x0)
            s1 = np.minimum(length, np.maximum(0.0, room / (2 * U)))
            s1 = np.where(np.isfinite(U), s1, 0.0)
            ramp = np.where(s1 > 0, 2 * s1 / (np.sqrt(x0 + 2 * U * s1) + np.sqrt(x0)), 0.0)
            flat = np.where(length - s1 > 0, (length - s1) / np.sqrt(X), 0.0)
            return ramp + flat

        return side(p, up, sc) + side(r, down, d - sc)
