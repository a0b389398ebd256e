"""The multi-drone separation filter every velocity setpoint passes before the geofence.

Frame: the ground station's world frame, horizontal x, y [m]; drones fly at one mission height, and the
horizontal distance never exceeds the 3-D one, so keeping horizontal centres ``min_distance`` apart keeps
the bodies apart whatever their heights.

Method: a braking-aware control barrier, solved jointly for every controlled drone as a QP with OSQP, with a
closed-form pairwise fallback. Why this and not the alternatives the issue names:

- reciprocal velocity obstacles (ORCA) assume that the new velocity is reached at once and say nothing about
  the acceleration limit or the latency; the buffered-Voronoi rule of the Crazyflie firmware
  (bitcraze/crazyflie-firmware ``src/modules/src/collision_avoidance.c``: in velocity mode the pseudo-goal
  ``horizonSecs * v`` is projected into the drone's cell, every gap halved, 1 s horizon, 0.5 m/s default
  speed) ignores the drone's momentum and holds half of every gap whether or not it is needed. A barrier
  that bounds the motion itself leaves safe commands alone (the QP's solution is the command when no
  constraint is active), shares a gap only where it must, and gives a bound that the tests can simulate.

The motion model the barrier is proved for (and that ``tests/test_separation.py`` simulates): over the next
``latency + period`` seconds drone ``i`` flies some velocity inside the triangle of its measured velocity
``v_i``, its previous command ``w_i`` and its new command ``u_i`` (first-order tracking of a held command and
one period of latency, during which the previous command is still flown, stay there), then brakes along a
straight line at ``max_decel``. Along the unit vector ``n`` from drone ``j`` to drone ``i`` drone ``i`` then
closes in by at most

    H_i * max(k_i, -n.u_i),   k_i = max(0, -n.v_i, -n.w_i),   H_i = latency + period + s_i / (2 max_decel)

where ``s_i >= |v_i|, |w_i|, |u_i|`` bounds its speed (commands are first cut to ``max_speed``, as the geofence
would cut them, and an octagon of radius ``s_i >= max_speed / cos(pi/8)`` keeps ``|u_i| <= s_i``). The centre distance
is at least the projection on ``n``, so a pair stays ``min_distance`` apart when the two bounds sum to at
most the gap ``c = |p_i - p_j| - min_distance``. ``max(a, b) + max(c, d) <= g`` is four linear inequalities, one
of them constant, so the constraint set is a polytope and the least change of the commands is a QP:

    minimise sum |u_i - desired_i|^2  over the controlled drones
    such that, per pair: H_i(-n.u_i) + H_j(n.u_j) <= c, H_i(-n.u_i) <= c - H_j k_j, H_j(n.u_j) <= c - H_i k_i

The rows use ``H_i + latency`` in place of ``H_i``: the next solve's plan flies this command for another
latency before its own command acts, and this margin is what makes braking (``u = 0``) feasible again at the
next solve (recursive feasibility, up to the turn of ``n`` in one period; the closed-loop test measures it).
An obstacle (holding, landing, lost, on the ground: it does not obey the filter) is a drone whose command is
its measured velocity. Per pair, by its constant part: with ``(H + latency) k`` within the gap the rows above;
with only ``H k`` within it (or already closer than ``min_distance``, from position noise) its drones may not
close in at all (``-n.u_i <= 0``), which keeps the plan safe; beyond that the pair's own momentum breaks the
bound and its controlled drones brake (``u = 0``, the most the filter can do). ``u = 0`` then satisfies every
row, so the QP is feasible by construction. Safe by construction is also the closed-form fallback used when OSQP
does not return a verified solution: each drone scales its own command down to its half of each gap.
Every result is checked against the constraints before it is returned; NaN input, coincident drones or a
failed check give a brake (zero velocity), never an unsafe command.
"""
from __future__ import annotations

import functools
import logging
import math
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping

import numpy as np

from runtime.spec import SpecError, SwarmSpec, from_mapping

log = logging.getLogger(__name__)

POSITION_ERROR = 0.1
"""Largest horizontal position-estimate error of one drone [m] that ``min_distance`` absorbs: the Loco
Positioning System's error is about 0.03 m standard deviation per axis (the simulator's ``lps_sigma_xy``),
so 0.1 m is over 3 sigma in the plane."""
COINCIDENT = 1e-6
"""Centres closer than this [m] have no direction between them: both drones brake."""
VERIFY_TOL = 1e-6
"""Slack [m] of the final constraint check: the solver's accuracy on constraints that are tight at zero (a
micrometre over the whole horizon, against the 0.2 m that ``POSITION_ERROR`` keeps)."""
QP_MARGIN = 1e-5
"""The QP's constraints with room for it are tightened by this [m] (10 um over the horizon), so that OSQP's
tolerance (``QP_EPS``) does not end outside them."""
_OCTAGON = np.array([[math.cos(k * math.pi / 4), math.sin(k * math.pi / 4)] for k in range(8)])
_APOTHEM = math.cos(math.pi / 8)
"""An octagon with apothem ``s cos(pi/8)`` lies inside the circle of radius ``s``."""


def default_min_distance(spec: SwarmSpec | None = None) -> float:
    """Two of the spec's largest body radii plus both drones' ``POSITION_ERROR`` [m, centre to centre]."""
    spec = spec or SwarmSpec()
    biggest = max(spec.pursuer.radius, spec.scout.radius, spec.evader.radius)
    return 2.0 * biggest + 2.0 * POSITION_ERROR


@dataclass(frozen=True)
class SeparationConfig:
    """The separation filter (TOML table ``[separation]`` of a fleet file)."""

    enabled: bool = True
    """Filter every velocity setpoint. False only for comparisons (``--no-separation``): drones may touch."""
    min_distance: float = field(default_factory=default_min_distance)
    """Smallest horizontal centre-to-centre distance between two drones [m]; default two body radii of
    ``runtime.spec`` plus ``POSITION_ERROR`` for each drone (0.35 m with the default spec)."""
    capture_distance: float = field(default_factory=lambda: SwarmSpec().sensing.sensing_range)
    """A pursuer-team drone within this distance of an evader has captured it [m] (default the spec's
    sensing range); in flight a capture is never contact."""

    def __post_init__(self) -> None:
        if not isinstance(self.enabled, bool):
            raise SpecError(f"separation.enabled: must be true or false, got {self.enabled!r}")
        for name in ("min_distance", "capture_distance"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise SpecError(f"separation.{name}: must be a finite number > 0 [m], got {v!r}")

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "separation") -> "SeparationConfig":
        return from_mapping(cls, data, where)


@dataclass(frozen=True)
class Limits:
    """What the barrier assumes of the vehicles."""

    min_distance: float
    """[m]"""
    period: float
    """How long one command is held, the setpoint period [s]."""
    max_decel: float
    """Deceleration every drone is sure to reach when braking [m/s^2] (the fence's ``max_decel``)."""
    max_speed: float
    """Speed bound [m/s] used for a drone flying slower than this (the fence's ``max_speed``)."""
    latency: float | None = None
    """Measurement to command in effect [s]; None: one ``period``."""

    @property
    def horizon(self) -> float:
        return self.period + (self.period if self.latency is None else self.latency)


@dataclass
class SeparationResult:
    velocity: np.ndarray
    """[N, 2] filtered commands [m/s]; zero for obstacles (the filter does not command them)."""
    braked: np.ndarray
    """[N] bool: controlled drones braked because nothing safer was possible (or an input was bad)."""
    method: str
    """"unchanged" (the commands were safe), "qp", "pairwise" (fallback), "brake" (bad input), "none"."""


NORMAL, NO_CLOSING, HOPELESS = 0, 1, 2
"""Pair tiers: constrained as in the module docstring; may only stop closing in (too close already, or too
little slack left for the recursive margin); nothing helps (its drones brake)."""


@dataclass
class _Pairs:
    """The constraint data of every pair that can matter: index arrays and per-pair numbers."""

    i: np.ndarray
    j: np.ndarray
    n: np.ndarray
    """[P, 2] unit vector from j to i."""
    gap: np.ndarray
    """[P] distance - min_distance [m]; negative for pairs already too close."""
    k_i: np.ndarray
    """[P] how fast i closes in on its momentum and previous command alone [m/s]."""
    k_j: np.ndarray
    tier: np.ndarray
    """[P] NORMAL, NO_CLOSING or HOPELESS."""

    def take(self, keep: np.ndarray) -> "_Pairs":
        return _Pairs(*(getattr(self, f)[keep] for f in ("i", "j", "n", "gap", "k_i", "k_j", "tier")))


def _speed_bounds(vel: np.ndarray, prev: np.ndarray, lim: Limits) -> np.ndarray:
    """Per drone s >= |v|, |w| and the radius of the octagon that bounds |u| (which holds every command up to
    ``max_speed``)."""
    s = np.maximum(np.linalg.norm(vel, axis=1), np.linalg.norm(prev, axis=1))
    return np.maximum(s, lim.max_speed / _APOTHEM)


def _cap_speed(desired: np.ndarray, max_speed: float) -> np.ndarray:
    """Commands faster than ``max_speed`` cut to it, direction kept (as the geofence would cut them after),
    so that a fast request cannot lengthen its own braking horizon."""
    speed = np.linalg.norm(desired, axis=1)
    return desired * np.minimum(1.0, max_speed / np.maximum(speed, 1e-12))[:, None]


def _horizons(s: np.ndarray, lim: Limits) -> tuple[np.ndarray, np.ndarray]:
    """Per drone: H of the plan (latency, one period, braking from speed s), and H plus one more latency,
    used for the commands. The extra latency is the recursive margin: the next solve's plan flies this
    command for another latency before its own command acts, and must still find braking safe."""
    h = lim.horizon + s / (2.0 * lim.max_decel)
    return h, h + (lim.horizon - lim.period)


def _pairs(pos, vel, prev, s, active, lim: Limits) -> tuple[_Pairs, np.ndarray]:
    """Pairs with at least one ``active`` drone near enough to matter, and the drones of coincident pairs."""
    h, hl = _horizons(s, lim)
    i, j = np.triu_indices(len(pos), 1)
    keep = active[i] | active[j]
    i, j = i[keep], j[keep]
    delta = pos[i] - pos[j]
    dist = np.hypot(delta[:, 0], delta[:, 1])
    reach = hl[i] * s[i] + hl[j] * s[j]  # neither can close in by more
    near = dist - lim.min_distance <= reach
    i, j, delta, dist = i[near], j[near], delta[near], dist[near]
    coincident = dist < COINCIDENT
    bad = np.zeros(len(pos), dtype=bool)
    bad[i[coincident]] = bad[j[coincident]] = True
    ok = ~coincident
    i, j, delta, dist = i[ok], j[ok], delta[ok], dist[ok]
    n = delta / dist[:, None]
    k_i = np.maximum(0.0, np.maximum(-(n * vel[i]).sum(1), -(n * prev[i]).sum(1)))
    k_j = np.maximum(0.0, np.maximum((n * vel[j]).sum(1), (n * prev[j]).sum(1)))
    gap = dist - lim.min_distance
    tier = np.full(len(i), NORMAL)
    tier[hl[i] * k_i + hl[j] * k_j > gap] = NO_CLOSING
    tier[h[i] * k_i + h[j] * k_j > gap] = HOPELESS
    tier[gap < 0] = NO_CLOSING
    return _Pairs(i, j, n, gap, k_i, k_j, tier), bad


@dataclass
class _Rows:
    """Linear constraints ``A x <= b`` on the free drones' commands ``x = [u_0x, u_0y, u_1x, ...]``, as the
    nonzeros of ``A`` (row, column, value): at most four per row, built without a dense matrix."""

    row: np.ndarray
    col: np.ndarray
    val: np.ndarray
    b: np.ndarray

    def residual(self, x: np.ndarray) -> np.ndarray:
        """``A x - b`` for the flat command vector ``x``."""
        return np.bincount(self.row, self.val * x[self.col], minlength=len(self.b)) - self.b


def _rows(pp: _Pairs, hl: np.ndarray, free: np.ndarray, col: np.ndarray, pos: np.ndarray) -> _Rows:
    """The constraints of the module docstring on the free drones' commands (see ``_Rows``), in a layout that
    depends on nothing but which drones are free: every pair with a free drone has its rows (both free: the
    joint row and one per drone; one free: that drone's row), and a row that does not bind now (a pair too far
    apart to matter, or the joint row of a pair that may only stop closing in) has ``b = inf``. So from one
    setpoint period to the next only numbers change, and ``QPSolver`` updates and warm-starts OSQP instead of
    setting it up anew. Coefficients are ``H_i(-n.u_i)`` and ``H_j(n.u_j)`` with the horizons of the commands."""
    i, j = np.triu_indices(len(free), 1)
    keep = free[i] | free[j]
    i, j = i[keep], j[keep]
    fi, fj = free[i], free[j]
    delta = pos[i, :2] - pos[j, :2]
    n = delta / np.maximum(np.hypot(delta[:, 0], delta[:, 1]), COINCIDENT)[:, None]  # coincident ones are not free
    ci, cj = -hl[i][:, None] * n, hl[j][:, None] * n
    b = np.full((len(i), 3), np.inf)  # joint row, row of i, row of j
    where = np.full((len(free), len(free)), -1)
    where[i, j] = np.arange(len(i))
    q = where[pp.i, pp.j]  # pairs of pp without a free drone (braked ones) have no rows
    normal, stop = (pp.tier == NORMAL) & (q >= 0), (pp.tier == NO_CLOSING) & (q >= 0)
    b[q[normal], 0] = pp.gap[normal]
    b[q[normal], 1] = (pp.gap - hl[pp.j] * pp.k_j)[normal]
    b[q[normal], 2] = (pp.gap - hl[pp.i] * pp.k_i)[normal]
    b[q[stop], 1:] = 0.0  # too close, or no slack for the margin: stop closing in
    present = np.stack([fi & fj, fi, fj], axis=1)
    row_id = (np.cumsum(present.reshape(-1)) - 1).reshape(-1, 3)
    rows, cols, vals = [], [], []
    for k, drone, coef in ((0, i, ci), (0, j, cj), (1, i, ci), (2, j, cj)):
        sel = present[:, k]
        c = 2 * col[drone[sel]]
        rows.append(np.repeat(row_id[sel, k], 2))
        cols.append(np.stack([c, c + 1], axis=1).reshape(-1))
        vals.append(coef[sel].reshape(-1))
    return _Rows(np.concatenate(rows), np.concatenate(cols), np.concatenate(vals), b[present])


def _violation(rows: _Rows, u: np.ndarray, free_idx: np.ndarray) -> float:
    """The largest amount [m] by which the commands ``u`` [N, 2] break a constraint (0 when none)."""
    if not len(rows.b):
        return 0.0
    return float(max(0.0, rows.residual(u[free_idx].reshape(-1)).max()))


@functools.lru_cache(maxsize=64)
def _hessian(m: int):
    """2 I for ``m`` drones' commands (the objective sum |u - desired|^2), built once per size."""
    from scipy import sparse
    return sparse.identity(2 * m, format="csc") * 2.0


@functools.lru_cache(maxsize=64)
def _octagon_rows(m: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(row, column, value) of ``|u_k| <= s_k`` as an octagon for ``m`` drones, rows from 0."""
    k = len(_OCTAGON)
    row = np.repeat(np.arange(m * k), 2)
    col = 2 * np.repeat(np.arange(m), 2 * k) + np.tile([0, 1], m * k)
    return row, col, np.tile(_OCTAGON.reshape(-1), m)


QP_EPS = 1e-6
"""OSQP's absolute and relative tolerance [m]; polishing then makes the active constraints exact, and a
solution outside them by more than ``VERIFY_TOL`` goes to the closed-form fallback."""
QP_MAX_ITER = 4000
"""OSQP's iteration limit (its default). A warm-started solve takes tens; one that hits this is not used."""


class QPSolver:
    """The joint QP of ``filter_velocities`` with its OSQP problem kept from one solve to the next. A solve with
    the constraint pattern of the last one (the same free drones and the same kinds of rows for the same pairs:
    the common case from one setpoint period to the next) hands OSQP only the new numbers (``update``) and
    starts from the last solution (warm start); a new pattern is set up anew. Not thread-safe: one per solving
    thread (``JointFilter`` owns one and solves one at a time)."""

    def __init__(self) -> None:
        self._prob = None
        self._key: tuple | None = None
        self.setups = 0
        """OSQP set-ups (a new constraint pattern)."""
        self.updates = 0
        """Solves that reused the problem set up before, with new numbers, warm-started."""
        self.iterations = 0
        """ADMM iterations of the last solve."""

    def solve(self, rows: _Rows, desired: np.ndarray, s: np.ndarray) -> np.ndarray | None:
        """The commands [m, 2] closest to ``desired`` [m, 2] under ``rows`` and ``|u_k| <= s_k`` [m/s]; None
        when OSQP reports no solution."""
        m = len(desired)
        n_pair = len(rows.b)
        o_row, o_col, o_val = _octagon_rows(m)
        row = np.concatenate([rows.row, o_row + n_pair])
        col = np.concatenate([rows.col, o_col])
        order = np.lexsort((row, col))  # compressed sparse column: by column, then row
        indices = row[order].astype(np.int32)
        data = np.concatenate([rows.val, o_val])[order]
        indptr = np.zeros(2 * m + 1, dtype=np.int32)
        np.cumsum(np.bincount(col, minlength=2 * m), out=indptr[1:])
        # u = 0 must stay feasible where it was: tighten by QP_MARGIN only rows with room for it
        upper = np.concatenate([rows.b - np.minimum(QP_MARGIN, np.maximum(rows.b, 0.0) / 2),
                                np.repeat(s * _APOTHEM, len(_OCTAGON))])
        q = -2.0 * desired.reshape(-1)
        key = (m, len(upper), indptr.tobytes(), indices.tobytes())
        if key == self._key:
            self._prob.update(q=q, u=upper, Ax=data)
            self.updates += 1
        else:
            import osqp
            from scipy import sparse
            self._prob = self._key = None
            a = sparse.csc_matrix((data, indices, indptr), shape=(len(upper), 2 * m))
            prob = osqp.OSQP(algebra="builtin")  # named: otherwise every OSQP() probes for the CUDA and MKL builds
            prob.setup(_hessian(m), q, a, np.full(len(upper), -np.inf), upper, verbose=False, polishing=True,
                       eps_abs=QP_EPS, eps_rel=QP_EPS, max_iter=QP_MAX_ITER, warm_starting=True)
            self._prob, self._key = prob, key
            self.setups += 1
        res = self._prob.solve(raise_error=False)
        self.iterations = int(res.info.iter)
        if res.info.status not in ("solved", "solved inaccurate") or res.x is None or not np.all(np.isfinite(res.x)):
            log.debug("separation QP: %s", res.info.status)
            self._key = None  # nothing worth warm-starting from
            return None
        return np.asarray(res.x, dtype=float).reshape(m, 2)


def _pairwise(pp: _Pairs, hl: np.ndarray, free: np.ndarray, desired: np.ndarray) -> np.ndarray:
    """Closed-form fallback: each free drone scales its own command down to its share of each gap (half the
    slack of a pair of free drones, all of it against an obstacle); NO_CLOSING pairs only stop closing in."""
    scale = np.ones(len(desired))
    for q in range(len(pp.i)):
        i, j, n = pp.i[q], pp.j[q], pp.n[q]
        hk_i, hk_j = hl[i] * pp.k_i[q], hl[j] * pp.k_j[q]
        slack = pp.gap[q] - hk_i - hk_j
        both = free[i] and free[j]
        for me, sign, hk in ((i, -1.0, hk_i), (j, 1.0, hk_j)):
            if not free[me]:
                continue
            closing = sign * float(n @ desired[me])
            if closing <= 0:
                continue
            budget = 0.0 if pp.tier[q] == NO_CLOSING else max(hk + (slack / 2 if both else slack), 0.0)
            scale[me] = min(scale[me], budget / (hl[me] * closing))
    return desired * np.clip(scale, 0.0, 1.0)[:, None]


def filter_velocities(positions: np.ndarray, velocities: np.ndarray, desired: np.ndarray, controlled: np.ndarray,
                      limits: Limits, previous: np.ndarray | None = None, use_qp: bool = True,
                      solver: QPSolver | None = None) -> SeparationResult:
    """Filtered horizontal velocity commands [N, 2] [m/s] for the ``controlled`` drones (see the module
    docstring). ``positions`` [N, 2+] [m] and ``velocities`` [N, 2+] [m/s] of every drone, measured;
    ``desired`` [N, 2] the commands asked for (rows of obstacles are ignored); ``previous`` [N, 2] the commands
    now in flight (default: the measured velocities). ``solver``: a ``QPSolver`` kept between calls (its OSQP
    problem is updated and warm-started); None solves from a cold start."""
    pos = np.asarray(positions, dtype=float)[:, :2]
    vel = np.asarray(velocities, dtype=float)[:, :2]
    want = np.array(desired, dtype=float).reshape(-1, 2)
    ctrl = np.asarray(controlled, dtype=bool).copy()
    prev = vel.copy() if previous is None else np.asarray(previous, dtype=float)[:, :2].copy()
    n = len(pos)
    out = np.zeros((n, 2))
    if not ctrl.any():
        return SeparationResult(out, np.zeros(n, dtype=bool), "none")
    if not (np.all(np.isfinite(pos)) and np.all(np.isfinite(vel))):
        return SeparationResult(out, ctrl.copy(), "brake")  # a drone we cannot place: nobody may move
    bad_cmd = ctrl & ~np.all(np.isfinite(want), axis=1)
    want[~ctrl | bad_cmd] = 0.0
    prev[~ctrl] = vel[~ctrl]  # an obstacle's command is what it does
    prev[~np.all(np.isfinite(prev), axis=1)] = vel[~np.all(np.isfinite(prev), axis=1)]
    want = _cap_speed(want, limits.max_speed)
    s = _speed_bounds(vel, prev, limits)
    pp, braked = _pairs(pos, vel, prev, s, ctrl, limits)
    _, hl = _horizons(s, limits)
    braked &= ctrl
    hopeless = pp.tier == HOPELESS  # momentum alone breaks the bound: brake, the most that can be done
    braked[pp.i[hopeless]] |= ctrl[pp.i[hopeless]]
    braked[pp.j[hopeless]] |= ctrl[pp.j[hopeless]]
    braked |= bad_cmd
    free = ctrl & ~braked
    want[braked] = 0.0
    free_idx = np.flatnonzero(free)
    col = np.full(n, -1)
    col[free_idx] = np.arange(len(free_idx))
    pp = pp.take(~hopeless)
    rows = _rows(pp, hl, free, col, pos)
    if _violation(rows, want, free_idx) <= VERIFY_TOL:
        out[free] = want[free]
        return SeparationResult(out, braked, "unchanged")
    method = "pairwise"
    u = None
    if use_qp and len(free_idx):
        x = (solver or QPSolver()).solve(rows, want[free_idx], s[free_idx])
        if x is not None:
            u = np.zeros((n, 2))
            u[free_idx] = x
            if _violation(rows, u, free_idx) <= VERIFY_TOL and np.all(
                    np.linalg.norm(x, axis=1) <= s[free_idx] + VERIFY_TOL):
                method = "qp"
            else:
                log.debug("separation QP solution failed the check: pairwise fallback")
                u = None
    if u is None:
        u = _pairwise(pp, hl, free, want)
        if _violation(rows, u, free_idx) > VERIFY_TOL:  # cannot happen; never send it anyway
            log.error("separation fallback failed its own check: braking every controlled drone")
            return SeparationResult(out, ctrl.copy(), "brake")
    out[free] = u[free]
    return SeparationResult(out, braked, method)


@dataclass
class Snapshot:
    """What the filter is fed: every drone the ground station can place, in one order."""

    ids: list[str]
    positions: np.ndarray
    """[N, 2+] measured [m]"""
    velocities: np.ndarray
    """[N, 2+] measured [m/s]"""
    desired: np.ndarray
    """[N, 2] commands asked for [m/s] (any value for obstacles)"""
    controlled: np.ndarray
    """[N] bool: obeys the filter (flying in the mission); the others are obstacles"""
    previous: np.ndarray
    """[N, 2] commands in flight [m/s]"""


STALE_PERIODS = 3
"""With the solver thread running, a cached solution older than this many intervals is not used: the setpoint
brakes (zero velocity, which every constraint allows) until the solver thread has solved again."""


class JointFilter:
    """The joint solve shared by every link's receive thread. Started (``start``), a solver thread re-solves for
    all drones from ``gather()`` every ``interval`` s and the receive threads only read the cached result: one
    QP per control period, none on the setpoint path, and a receive thread never waits for a solve. A drone
    missing from a running filter's cache (it just began to fly), or a cache older than ``STALE_PERIODS``
    intervals (the solver thread was starved of CPU), gives a brake until the next solve. Not started (tests),
    the asking thread solves when the cache is an interval old. The cache's age is part of ``limits.latency``.
    With ``process``, the solver thread only takes the snapshot and the solve itself runs in a child process
    (``separation_worker.SolverProcess``; this thread again if the child is lost).

    Why a stale cache brakes instead of being solved again on the receive thread (as before): on a loaded
    machine the solver thread's solve is slow because the interpreter is busy, and then every receive thread
    found the cache stale at once and solved in turn behind one lock (12 solves in a row, each as slow), which
    held every setpoint for 50-300 ms. A brake costs one setpoint period of progress, never a stall."""

    def __init__(self, limits: Limits, gather: Callable[[], "Snapshot"], interval: float,
                 clock: Callable[[], float] = time.monotonic, process: bool = False) -> None:
        self.limits = limits
        self.interval = interval
        self.process = process
        """Started, solve in a process of its own (``separation_worker``) instead of this interpreter's thread
        (the demo and ``swarm-gs fly``; tests keep the thread: a process costs a second to start)."""
        self._worker = None
        self._qp_base = (0, 0)
        self.solver_place = "thread"
        """Where the solves ran: "thread", "process", or "process, then thread" (the process was lost)."""
        self._gather = gather
        self._clock = clock
        self._lock = threading.Lock()
        """Guards the cache and the counters (held for lookups only)."""
        self._solve_lock = threading.Lock()
        """One solve at a time (the solver's OSQP problem is kept between solves)."""
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._t = -math.inf
        self._cache: dict[str, tuple[np.ndarray, bool, bool]] = {}
        self.solver = QPSolver()
        """The joint QP, set up once and then updated and warm-started while its pattern holds."""
        self.solves = 0
        self.methods: dict[str, int] = {}
        self.braked = 0
        """Setpoints handed out as a brake because nothing safer was possible."""
        self.unplaced = 0
        """Of those, setpoints of drones not in the cache (no fresh position, or not flying, at the solve)."""
        self.stale = 0
        """Of those, setpoints braked because the cached solution was older than ``STALE_PERIODS`` intervals."""
        self.changed = 0
        """Setpoints the filter changed (braked included)."""
        self.setpoints = 0
        self.solve_s: list[float] = []
        """Wall time of every joint solve [s] (snapshot included)."""
        # The solver's first use imports OSQP and scipy.sparse (seconds on a busy machine): here, before any
        # flight, and not at the first setpoint.
        filter_velocities(np.array([[0.0, 0.0], [0.5, 0.0]]), np.zeros((2, 2)), np.array([[1.0, 0.0], [-1.0, 0.0]]),
                          np.ones(2, dtype=bool), limits)

    def start(self) -> "JointFilter":
        if self.process and self._worker is None:
            from groundstation.separation_worker import SolverProcess
            try:
                self._worker = SolverProcess(self.limits).start()
                self.solver_place = "process"
            except RuntimeError as exc:
                log.warning("%s: the separation filter solves in the ground station", exc)
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="SeparationFilter", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._thread = None
        if self._worker is not None:
            self._qp_base = (self._worker.setups, self._worker.updates)
            self._worker.stop()
            self._worker = None

    def _run(self) -> None:
        next_t = self._clock()
        while not self._stop.is_set():
            try:
                self._solve()
            except Exception:  # the setpoints brake once the cache is stale
                log.exception("separation solve failed")
            next_t += self.interval
            delay = next_t - self._clock()
            if delay < 0:
                next_t, delay = self._clock(), 0.0
            self._stop.wait(delay)

    def command(self, drone_id: str, now: float | None = None) -> np.ndarray:
        """Filtered horizontal command [m/s] of ``drone_id``; zero (a brake) when the drone is not in the
        filter's picture (not controlled, or its state is unknown) or the picture is stale."""
        now = self._clock() if now is None else now
        running = self._thread is not None
        if not running:
            with self._lock:
                solve = now - self._t >= self.interval or drone_id not in self._cache
            if solve:
                self._solve(now)
        with self._lock:
            stale = running and now - self._t >= STALE_PERIODS * self.interval
            entry = None if stale else self._cache.get(drone_id)
            v, braked, changed = entry if entry is not None else (np.zeros(2), True, True)
            self.setpoints += 1
            self.braked += int(braked)
            self.stale += int(stale)
            self.unplaced += int(entry is None and not stale)
            self.changed += int(changed)
            return v.copy()

    def _solve(self, now: float | None = None) -> None:
        """Solve from a fresh snapshot; the cache is stamped ``now`` (default: the clock just before the
        snapshot is taken, so that the cache's age counts from the data it was solved on)."""
        with self._solve_lock:
            t0 = time.perf_counter()
            now = self._clock() if now is None else now
            snap: Snapshot = self._gather()
            cache: dict[str, tuple[np.ndarray, bool, bool]] = {}
            method = "none"
            if snap.ids:
                out = self._solve_in_worker(snap)
                if out is False:
                    return  # no answer in time: the cache ages (and brakes once stale), as a slow solve here would
                if out is None:
                    res = filter_velocities(snap.positions, snap.velocities, snap.desired, snap.controlled,
                                            self.limits, snap.previous, solver=self.solver)
                    out = res.velocity, res.braked, res.method
                velocity, braked, method = out
                want = _cap_speed(np.asarray(snap.desired, dtype=float).reshape(-1, 2), self.limits.max_speed)
                changed = ~np.all(np.abs(velocity - want) <= 1e-9, axis=1)
                cache = {d: (velocity[k], bool(braked[k]), bool(changed[k]))
                         for k, d in enumerate(snap.ids) if snap.controlled[k]}
            with self._lock:
                self._cache, self._t = cache, now
                self.solves += 1
                self.methods[method] = self.methods.get(method, 0) + 1
                if len(self.solve_s) < 1_000_000:
                    self.solve_s.append(time.perf_counter() - t0)

    def _solve_in_worker(self, snap: "Snapshot"):
        """The worker's (velocity, braked, method); False when it did not answer in time; None without a worker
        (none asked for, or it is gone: then this thread solves from now on)."""
        worker = self._worker
        if worker is None:
            return None
        from groundstation.separation_worker import SolverGone
        try:
            out = worker.solve(np.asarray(snap.positions, dtype=float), np.asarray(snap.velocities, dtype=float),
                               np.asarray(snap.desired, dtype=float), np.asarray(snap.controlled, dtype=bool),
                               np.asarray(snap.previous, dtype=float), timeout=STALE_PERIODS * self.interval)
        except SolverGone as exc:
            log.warning("%s: the separation filter solves in the ground station from now on", exc)
            self._qp_base = (worker.setups, worker.updates)
            worker.stop()
            self._worker = None
            self.solver_place = "process, then thread"
            return None
        return False if out is None else out

    def stats(self) -> dict[str, Any]:
        with self._lock:
            ms = np.array(self.solve_s) * 1e3
            timing = {"solve_ms_p50": float(np.percentile(ms, 50)), "solve_ms_p99": float(np.percentile(ms, 99))} \
                if ms.size else {}
            return {"solves": self.solves, "methods": dict(self.methods), "setpoints": self.setpoints, **timing,
                    "changed_setpoints": self.changed, "braked_setpoints": self.braked,
                    "unplaced_setpoints": self.unplaced, "stale_setpoints": self.stale,
                    "qp_setups": self.solver.setups + self._qp_counts()[0],
                    "qp_updates": self.solver.updates + self._qp_counts()[1],
                    "solver": self.solver_place}

    def _qp_counts(self) -> tuple[int, int]:
        """OSQP set-ups and updates done by the worker (the one running, or the last one)."""
        w = self._worker
        return (w.setups, w.updates) if w is not None else self._qp_base
