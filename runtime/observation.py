"""The one observation encoder, shared by training and flight.

``encode_observations`` turns world arrays (``[B, N, 2]`` positions and velocities, obstacles) plus what each
pursuer-team agent knows of the evaders into the observation vectors laid out by ``runtime.spec.ObsLayout``.
Training calls it on thousands of envs; the per-drone runtime calls it with ``B = 1`` on the state the drone
believes (its own estimate, its neighbours' messages) and ``observers=[its index]``.

Target knowledge (the paper's assumption (b)): every pursuer-team agent keeps, per evader, the last sighting
``(x, y, vx, vy, t_seen)``. ``update_knowledge`` applies one control period of it: first each agent takes the
freshest sighting among teammates within comm range (one hop per period, from their previous knowledge),
then its own sensing within ``sensing_range`` overrides. With ``observability = "full"`` every agent knows
every evader's true state.

With ``sensing.share_assignment`` the pursuers' rows end with the team's split (``_assigned``, ``runtime.spec``):
the classical team's assignment, which each pursuer computes from the pursuers it hears and the targets it knows.
"""
from __future__ import annotations

import numpy as np
from numba import njit

from runtime.spec import Role, SwarmSpec
from runtime.world import pairwise_distances  # noqa: F401  (re-exported for callers)

SIGHTING = 5
"""Values per sighting: x [m], y [m], vx [m/s], vy [m/s], t_seen [s] (-inf: never seen)."""


def new_knowledge(spec: SwarmSpec, n_envs: int) -> np.ndarray:
    """Empty knowledge ``[B, n_team, n_evaders, 5]``: nothing seen yet."""
    k = np.zeros((n_envs, spec.team.n_team, spec.team.n_evaders, SIGHTING))
    k[..., 4] = -np.inf
    return k


def update_knowledge(spec: SwarmSpec, knowledge: np.ndarray, pos: np.ndarray, vel: np.ndarray,
                     time_s: np.ndarray | float, dist: np.ndarray | None = None) -> np.ndarray:
    """One period of sensing and relaying, in place on ``knowledge`` ``[B, n_team, E, 5]``."""
    nt = spec.team.n_team
    b = pos.shape[0]
    t = np.broadcast_to(np.asarray(time_s, dtype=np.float64), (b,))
    truth = np.concatenate([pos[:, nt:], vel[:, nt:], np.broadcast_to(t[:, None, None], (b, pos.shape[1] - nt, 1))],
                           axis=-1)  # [B, E, 5]
    if spec.sensing.observability == "full":
        knowledge[:] = truth[:, None]
        return knowledge
    if dist is None:
        dist = pairwise_distances(pos)
    # relay: freshest sighting among teammates in comm range (self included), from last period's knowledge
    comm = dist[:, :nt, :nt] <= spec.sensing.comm_range  # [B, M, M], diagonal true
    seen_at = np.where(comm[..., None], knowledge[:, None, :, :, 4], -np.inf)  # [B, recv, src, E]
    src = seen_at.argmax(axis=2)  # [B, recv, E]
    own = np.arange(nt)[None, :, None]
    # keep one's own entry unless a neighbour's is strictly fresher (argmax of all -inf would pick agent 0)
    src = np.where(np.take_along_axis(seen_at, src[:, :, None], axis=2)[:, :, 0] > knowledge[..., 4], src, own)
    merged = np.take_along_axis(knowledge, src[..., None], axis=1)  # gathers knowledge[b, src, e]
    knowledge[:] = merged
    # own sensing overrides
    sees = dist[:, :nt, nt:] <= spec.sensing.sensing_range  # [B, M, E]
    if sees.any():
        knowledge[:] = np.where(sees[..., None], truth[:, None], knowledge)
    return knowledge


def merge_sightings(knowledge: np.ndarray, incoming: np.ndarray) -> np.ndarray:
    """Keep the fresher of two sighting tables ``[..., E, 5]`` (used by the runtime for received messages)."""
    newer = incoming[..., 4] > knowledge[..., 4]
    knowledge[:] = np.where(newer[..., None], incoming, knowledge)
    return knowledge


def _nearest(dist: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Indices of the ``k`` smallest along the last axis (ties: lower index first), and whether each is
    finite (valid). Slots beyond the axis length are invalid."""
    n = dist.shape[-1]
    shape = dist.shape[:-1] + (k,)
    if k == 0 or n == 0:
        return np.zeros(shape, dtype=np.int64), np.zeros(shape, dtype=bool)
    kk = min(k, n)
    idx = np.argsort(dist, axis=-1, kind="stable")[..., :kk]
    valid = np.isfinite(np.take_along_axis(dist, idx, axis=-1))
    if kk < k:
        idx = np.concatenate([idx, np.zeros(shape[:-1] + (k - kk,), dtype=np.int64)], axis=-1)
        valid = np.concatenate([valid, np.zeros(shape[:-1] + (k - kk,), dtype=bool)], axis=-1)
    return idx, valid


def _field(block: np.ndarray, lay, name: str) -> np.ndarray:
    """View ``[B, M, rows, cols]`` of one field inside ``block`` ``[B, M, D]``."""
    f = lay[name]
    return block[..., f.start:f.start + f.size].reshape(block.shape[:2] + (f.rows, len(f.columns)))


def _fill_agents(view: np.ndarray, ox: np.ndarray, oy: np.ndarray, px: np.ndarray, py: np.ndarray,
                 vx: np.ndarray, vy: np.ndarray, dist: np.ndarray) -> None:
    """Fill ``view`` [B, M, k, 5] with dx, dy, vx, vy, valid of the k nearest finite entries of ``dist``
    [B, M, O]; observers at ``ox, oy`` [B, M], others' components ``px ... vy`` [B, O]."""
    k = view.shape[2]
    if k == 0:
        return
    idx, valid = _nearest(dist, k)
    take = lambda a: np.take_along_axis(a[:, None, :], idx, axis=2)  # noqa: E731
    view[..., 0] = take(px) - ox[..., None]
    view[..., 1] = take(py) - oy[..., None]
    view[..., 2] = take(vx)
    view[..., 3] = take(vy)
    view[..., 4] = 1.0
    view *= valid[..., None]


def _assigned(view: np.ndarray, who: np.ndarray, p: int, px: np.ndarray, py: np.ndarray, kn: np.ndarray,
              known: np.ndarray, heard: np.ndarray | None) -> None:
    """The ``assigned`` field ``view`` [B, M, E] of observers ``who`` (see ``runtime.spec``): the split of the
    pursuers ``0..p-1`` each observer hears (``heard`` [B, M, p]; None: all) between the targets it knows (``kn``
    [B, M, E, 5] sightings, ``known`` [B, M, E])."""
    view[...] = 0.0
    isp = who < p
    if not isp.any():
        return
    e = view.shape[-1]
    if e == 1:
        view[..., 0] = known[..., 0] * isp
        return
    dx0 = px[:, None, :p] - kn[:, :, None, 0, 0]  # [B, M, p]: every pursuer to target 0, then to target 1
    dy0 = py[:, None, :p] - kn[:, :, None, 0, 1]
    dx1 = px[:, None, :p] - kn[:, :, None, 1, 0]
    dy1 = py[:, None, :p] - kn[:, :, None, 1, 1]
    diff = np.sqrt(dx0 * dx0 + dy0 * dy0) - np.sqrt(dx1 * dx1 + dy1 * dy1)
    jl = np.arange(p)
    me = np.minimum(who, p - 1)  # scouts: any row, masked below
    hear = np.ones(diff.shape, dtype=bool) if heard is None else heard.copy()
    hear[:, np.arange(who.size), me] = True  # oneself always
    m = hear.sum(-1)
    slots = (m + 1) // 2
    c = np.clip(((diff < 0) & hear).sum(-1), m - slots, slots)
    own = np.take_along_axis(diff, np.broadcast_to(me[None, :, None], diff.shape[:2] + (1,)), axis=-1)
    ahead = hear & ((diff < own) | ((diff == own) & (jl < me[:, None])))
    first = ahead.sum(-1) < c
    both = known[..., 0] & known[..., 1]
    view[..., 0] = np.where(both, first, known[..., 0]) * isp
    view[..., 1] = np.where(both, ~first, known[..., 1]) * isp


def encode_observations(spec: SwarmSpec, pos: np.ndarray, vel: np.ndarray, obstacle_pos: np.ndarray,
                        obstacle_radius: np.ndarray, knowledge: np.ndarray, time_s: np.ndarray | float,
                        observers: np.ndarray | None = None, visible: np.ndarray | None = None,
                        dist: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """Observations ``[B, len(observers), spec.max_obs_dim]`` (rows of roles with a shorter layout are
    zero-padded at the end; ``spec.obs_dim(role)`` tells how many entries are real).

    ``observers``: agent indices to encode (default: all, in order). ``visible`` ``[B, N, N]``: which agents
    each agent currently sees or hears from (default: computed from the spec's ranges, or everyone with
    full observability); the runtime passes what its messages and sensors actually delivered.
    """
    s = spec.sensing
    team = spec.team
    nt, n = team.n_team, team.n_agents
    b = pos.shape[0]
    obs_idx = np.arange(n) if observers is None else np.asarray(observers, dtype=np.int64).reshape(-1)
    dim = spec.max_obs_dim
    if out is None:
        out = np.zeros((b, obs_idx.size, dim))
    if dist is None:
        dist = pairwise_distances(pos)
    full = s.observability == "full"
    if visible is None and not full:
        rng = np.full((n, n), s.comm_range)
        rng[:nt, nt:] = s.sensing_range  # the pursuer team sees evaders by sensing (relay is in knowledge)
        rng[nt:, :nt] = s.sensing_range  # evaders see threats by sensing only
        visible = dist <= rng[None]
    px, py = np.ascontiguousarray(pos[..., 0]), np.ascontiguousarray(pos[..., 1])
    vx, vy = np.ascontiguousarray(vel[..., 0]), np.ascontiguousarray(vel[..., 1])
    t = np.broadcast_to(np.asarray(time_s, dtype=np.float64), (b,))
    for group_team in (True, False):
        sel = np.nonzero((obs_idx < nt) if group_team else (obs_idx >= nt))[0]
        if sel.size == 0:
            continue
        who = obs_idx[sel]
        m = who.size
        lay = spec.layout(Role.PURSUER if group_team else Role.EVADER)
        contiguous = sel[-1] - sel[0] + 1 == m
        block = out[:, sel[0]:sel[-1] + 1] if contiguous else np.empty((b, m, dim))
        block[..., lay.dim:] = 0.0
        ox, oy = px[:, who], py[:, who]
        me = _field(block, lay, "self_pos")
        me[..., 0, 0], me[..., 0, 1] = ox, oy
        mv = _field(block, lay, "self_vel")
        mv[..., 0, 0], mv[..., 0, 1] = vx[:, who], vy[:, who]
        ob = _field(block, lay, "obstacles")
        k_obs = ob.shape[2]
        if k_obs:
            dxo = obstacle_pos[:, None, :, 0] - ox[..., None]
            dyo = obstacle_pos[:, None, :, 1] - oy[..., None]
            rad = np.broadcast_to(obstacle_radius[:, None, :], dxo.shape)
            order = np.argsort(np.sqrt(dxo * dxo + dyo * dyo) - rad, axis=-1, kind="stable")[..., :k_obs]
            ob[..., 0] = np.take_along_axis(dxo, order, axis=-1)
            ob[..., 1] = np.take_along_axis(dyo, order, axis=-1)
            ob[..., 2] = np.take_along_axis(rad, order, axis=-1)
        d = dist[:, who]  # [B, M, N]
        rows = np.arange(m)
        if group_team:
            kn = knowledge[:, who]  # [B, M, E, 5]
            age = t[:, None, None] - kn[..., 4]
            known = age < s.target_memory
            tg = _field(block, lay, "targets")
            tg[..., 0] = kn[..., 0] - ox[..., None]
            tg[..., 1] = kn[..., 1] - oy[..., None]
            tg[..., 2:4] = kn[..., 2:4]
            tg[..., 4] = np.minimum(age, s.target_memory)
            tg[..., 5] = 1.0
            tg *= known[..., None]
            tg[..., 4] += np.where(known, 0.0, s.target_memory)
            mates = d[:, :, :nt].copy() if full else np.where(visible[:, who, :nt], d[:, :, :nt], np.inf)
            mates[:, rows, who] = np.inf  # not oneself
            _fill_agents(_field(block, lay, "teammates"), ox, oy, px[:, :nt], py[:, :nt], vx[:, :nt], vy[:, :nt],
                         mates)
            if s.share_assignment:
                heard = None if full else visible[:, who, :team.n_pursuers]
                _assigned(_field(block, lay, "assigned")[..., 0], who, team.n_pursuers, px, py, kn, known, heard)
        else:
            threats = d[:, :, :nt] if full else np.where(visible[:, who, :nt], d[:, :, :nt], np.inf)
            _fill_agents(_field(block, lay, "threats"), ox, oy, px[:, :nt], py[:, :nt], vx[:, :nt], vy[:, :nt],
                         threats)
            mates = d[:, :, nt:].copy() if full else np.where(visible[:, who, nt:], d[:, :, nt:], np.inf)
            mates[:, rows, who - nt] = np.inf
            _fill_agents(_field(block, lay, "teammates"), ox, oy, px[:, nt:], py[:, nt:], vx[:, nt:], vy[:, nt:],
                         mates)
        if not contiguous:
            out[:, sel] = block
    return out


# ------------------------------------------------------------------------------------------------------------
# One observer, no batch: the per-drone runtime's fast path.
#
# ``encode_observations`` with B = 1 spends ~0.4 ms in numpy's per-call overhead on arrays of a dozen entries.
# The kernel below is its scalar twin for one observer, compiled by numba: the same operations on the same
# float64 values in the same order (numba does not reorder or fuse floating-point arithmetic without
# fastmath), the same stable nearest-first order (ties: lower index; NaN last), the same padding, so its
# output is bit-identical (tests/test_observation.py checks it on random states).


@njit(cache=True)
def _less(a: float, b: float) -> bool:
    """numpy's sort order: every number before NaN."""
    return a < b or (b != b and a == a)


@njit(cache=True)
def _nearest_one(key: np.ndarray, n: int, k: int, idx: np.ndarray) -> int:
    """The first ``min(k, n)`` indices of a stable ascending sort of ``key[:n]`` into ``idx``; returns how many."""
    kk = min(k, n)
    for s in range(kk):
        best = -1
        for j in range(n):
            taken = False
            for q in range(s):
                if idx[q] == j:
                    taken = True
                    break
            if not taken and (best < 0 or _less(key[j], key[best])):
                best = j
        idx[s] = best
    return kk


@njit(cache=True)
def _fill_one(out: np.ndarray, off: int, k: int, key: np.ndarray, n: int, base: int, ox: float, oy: float,
              pos: np.ndarray, vel: np.ndarray, idx: np.ndarray) -> None:
    """``_fill_agents`` for one observer: k slots of dx, dy, vx, vy, valid of the agents ``base + j`` (j < n)
    nearest by ``key`` (inf: not seen); every value times the valid flag, padding slots from agent ``base``."""
    kk = _nearest_one(key, n, k, idx)
    for s in range(k):
        j = base + (idx[s] if s < kk else 0)
        v = 1.0 if (s < kk and np.isfinite(key[idx[s]])) else 0.0
        o = off + 5 * s
        out[o] = (pos[j, 0] - ox) * v
        out[o + 1] = (pos[j, 1] - oy) * v
        out[o + 2] = vel[j, 0] * v
        out[o + 3] = vel[j, 1] * v
        out[o + 4] = 1.0 * v


@njit(cache=True)
def _assigned_one(out: np.ndarray, off_asg: int, off_tg: int, n_tg: int, i: int, n_pur: int, full: bool, comm: float,
                  dist: np.ndarray, visible: np.ndarray, has_visible: bool, knowledge: np.ndarray, pos: np.ndarray,
                  diff: np.ndarray) -> None:
    """``_assigned`` for one observer ``i``, from the known flags already written at ``off_tg``; ``dist`` its
    distances to every agent, ``diff`` scratch [>= n_pur]."""
    for e in range(n_tg):
        out[off_asg + e] = 0.0
    if i >= n_pur:
        return
    if n_tg == 1:
        out[off_asg] = out[off_tg + 5]
        return
    kn0 = out[off_tg + 5] == 1.0
    kn1 = out[off_tg + 11] == 1.0
    if not (kn0 and kn1):
        out[off_asg] = 1.0 if kn0 else 0.0
        out[off_asg + 1] = 1.0 if kn1 else 0.0
        return
    tx0, ty0 = knowledge[i, 0, 0], knowledge[i, 0, 1]
    tx1, ty1 = knowledge[i, 1, 0], knowledge[i, 1, 1]
    for j in range(n_pur):
        dx0 = pos[j, 0] - tx0
        dy0 = pos[j, 1] - ty0
        dx1 = pos[j, 0] - tx1
        dy1 = pos[j, 1] - ty1
        diff[j] = np.sqrt(dx0 * dx0 + dy0 * dy0) - np.sqrt(dx1 * dx1 + dy1 * dy1)
    own = diff[i]
    m = 0
    neg = 0
    ahead = 0
    for j in range(n_pur):
        if not (full or j == i or (visible[j] if has_visible else dist[j] <= comm)):
            continue
        m += 1
        if diff[j] < 0:
            neg += 1
        if diff[j] < own or (diff[j] == own and j < i):
            ahead += 1
    slots = (m + 1) // 2
    c = min(max(neg, m - slots), slots)
    first = ahead < c
    out[off_asg] = 1.0 if first else 0.0
    out[off_asg + 1] = 0.0 if first else 1.0


@njit(cache=True)
def _encode_one_kernel(prm: np.ndarray, ranges: np.ndarray, pos: np.ndarray, vel: np.ndarray,
                       obstacle_pos: np.ndarray, obstacle_radius: np.ndarray, knowledge: np.ndarray, time_s: float,
                       visible: np.ndarray, has_visible: bool, scratch: np.ndarray, iscratch: np.ndarray,
                       out: np.ndarray) -> None:
    """One observer's row of ``encode_observations`` into ``out``. ``prm``: ``_observer_params``; ``ranges``:
    sensing range, comm range, target memory; ``scratch`` [3 * max(N, K, 1)], ``iscratch`` [max(N, K, 1)]."""
    i, nt, n, in_team, full, dim = prm[0], prm[1], prm[2], prm[3], prm[4], prm[5]
    off_pos, off_vel, off_obs, k_obs = prm[6], prm[7], prm[8], prm[9]
    off_oth, k_oth, off_mate, k_mate = prm[10], prm[11], prm[12], prm[13]
    off_asg, n_pur = prm[14], prm[15]
    sensing, comm, memory = ranges[0], ranges[1], ranges[2]
    w = iscratch.shape[0]
    key, k1, k2 = scratch[:w], scratch[w:2 * w], scratch[2 * w:3 * w]
    for c in range(dim, out.shape[0]):
        out[c] = 0.0
    ox, oy = pos[i, 0], pos[i, 1]
    out[off_pos] = ox
    out[off_pos + 1] = oy
    out[off_vel] = vel[i, 0]
    out[off_vel + 1] = vel[i, 1]
    if k_obs > 0:  # obstacles by surface distance
        m = obstacle_radius.shape[0]
        for j in range(m):
            dx = obstacle_pos[j, 0] - ox
            dy = obstacle_pos[j, 1] - oy
            key[j] = np.sqrt(dx * dx + dy * dy) - obstacle_radius[j]
        _nearest_one(key, m, k_obs, iscratch)
        for s in range(k_obs):
            j = iscratch[s]
            out[off_obs + 3 * s] = obstacle_pos[j, 0] - ox
            out[off_obs + 3 * s + 1] = obstacle_pos[j, 1] - oy
            out[off_obs + 3 * s + 2] = obstacle_radius[j]
    for j in range(n):  # distances as pairwise_distances computes them (row i: pos[i] - pos[j])
        dx = pos[i, 0] - pos[j, 0]
        dy = pos[i, 1] - pos[j, 1]
        dx *= dx
        dy *= dy
        dx += dy
        key[j] = np.sqrt(dx)
    if in_team:
        for e in range(k_oth):  # targets, as this agent knows them
            age = time_s - knowledge[i, e, 4]
            kf = 1.0 if age < memory else 0.0
            o = off_oth + 6 * e
            out[o] = (knowledge[i, e, 0] - ox) * kf
            out[o + 1] = (knowledge[i, e, 1] - oy) * kf
            out[o + 2] = knowledge[i, e, 2] * kf
            out[o + 3] = knowledge[i, e, 3] * kf
            a = age if (age != age or age < memory) else memory  # np.minimum (NaN propagates)
            out[o + 4] = a * kf + (0.0 if kf == 1.0 else memory)
            out[o + 5] = 1.0 * kf
        for j in range(nt):  # teammates: the pursuer team but oneself, within comm range or heard
            d = key[j]
            if not full and not (visible[j] if has_visible else d <= comm):
                d = np.inf
            k1[j] = d
        k1[i] = np.inf
        _fill_one(out, off_mate, k_mate, k1, nt, 0, ox, oy, pos, vel, iscratch)
        if off_asg >= 0:
            _assigned_one(out, off_asg, off_oth, k_oth, i, n_pur, full != 0, comm, key, visible, has_visible, knowledge, pos,
                          k2)
    else:
        for j in range(nt):  # threats: the pursuer team within sensing range
            d = key[j]
            if not full and not (visible[j] if has_visible else d <= sensing):
                d = np.inf
            k1[j] = d
        for j in range(n - nt):  # teammates: the other evaders
            d = key[nt + j]
            if not full and not (visible[nt + j] if has_visible else d <= comm):
                d = np.inf
            k2[j] = d
        k2[i - nt] = np.inf
        _fill_one(out, off_oth, k_oth, k1, nt, 0, ox, oy, pos, vel, iscratch)
        _fill_one(out, off_mate, k_mate, k2, n - nt, nt, ox, oy, pos, vel, iscratch)


def _observer_params(spec: SwarmSpec, observer: int) -> np.ndarray:
    """The integers ``_encode_one_kernel`` reads for ``observer``: where each field starts, how many slots."""
    team = spec.team
    nt, n = team.n_team, team.n_agents
    in_team = observer < nt
    lay = spec.layout(Role.PURSUER if in_team else Role.EVADER)
    other = lay["targets"] if in_team else lay["threats"]
    return np.array([observer, nt, n, int(in_team), int(spec.sensing.observability == "full"), lay.dim,
                     lay["self_pos"].start, lay["self_vel"].start, lay["obstacles"].start, lay["obstacles"].rows,
                     other.start, other.rows, lay["teammates"].start, lay["teammates"].rows,
                     lay["assigned"].start if "assigned" in lay.names() else -1, team.n_pursuers], dtype=np.int64)


def _checked(name: str, a: np.ndarray, shape: tuple, dtype=np.float64) -> np.ndarray:
    a = np.asarray(a)
    if a.shape != shape or a.dtype != dtype or not a.flags.c_contiguous:
        raise ValueError(f"{name}: expected a C-contiguous {np.dtype(dtype).name} array of shape {shape}, got "
                         f"{a.dtype.name} {a.shape}{'' if a.flags.c_contiguous else ' (not contiguous)'}: "
                         f"use np.ascontiguousarray(..., dtype={np.dtype(dtype).name})")
    return a


class OneObserverEncoder:
    """``encode_observations(..., observers=[observer])`` for one drone, without the batch axis, in ~1 us.

    >>> enc = OneObserverEncoder(spec, 3)                                          # doctest: +SKIP
    >>> enc(pos, vel, obstacle_pos, obstacle_radius, knowledge, t, visible, out)   # doctest: +SKIP

    Arrays (float64 unless said, C-contiguous): ``pos``, ``vel`` [N, 2]; ``obstacle_pos`` [K, 2];
    ``obstacle_radius`` [K]; ``knowledge`` [n_team, n_evaders, 5] (``new_knowledge(...)[0]``; not read for an
    evader); ``visible`` [N] bool, the observer's row of ``encode_observations``' ``visible`` (None: from the
    spec's ranges; ignored with full observability); ``out`` [>= obs_dim], entries past the role's
    ``obs_dim`` are zeroed. ``__call__`` does no checking (the per-tick path); ``check`` does, once.
    ``compile()`` runs numba's compile (or loads it from the on-disk cache) so that no tick pays for it.
    """

    def __init__(self, spec: SwarmSpec, observer: int) -> None:
        n = spec.n_agents
        if not 0 <= observer < n:
            raise ValueError(f"observer: agent index {observer} is outside the spec's {n} agents (0..{n - 1})")
        self.spec = spec
        self.observer = int(observer)
        self.params = _observer_params(spec, self.observer)
        s = spec.sensing
        self.ranges = np.array([s.sensing_range, s.comm_range, s.target_memory])
        w = max(n, spec.arena.n_obstacles, 1)
        self._scratch = np.zeros(3 * w)
        self._iscratch = np.zeros(w, dtype=np.int64)
        self._no_visible = np.zeros(n, dtype=bool)

    def check(self, pos, vel, obstacle_pos, obstacle_radius, knowledge, visible=None, out=None) -> None:
        """Raise ValueError naming the first argument whose shape, dtype or layout the kernel cannot take."""
        spec = self.spec
        n, k, nt, e = spec.n_agents, spec.arena.n_obstacles, spec.team.n_team, spec.team.n_evaders
        _checked("pos", pos, (n, 2))
        _checked("vel", vel, (n, 2))
        _checked("obstacle_pos", obstacle_pos, (k, 2))
        _checked("obstacle_radius", obstacle_radius, (k,))
        _checked("knowledge", knowledge, (nt, e, SIGHTING))
        if visible is not None:
            _checked("visible", visible, (n,), bool)
        if out is not None:
            out = np.asarray(out)
            if out.ndim != 1 or out.dtype != np.float64 or not out.flags.c_contiguous or out.size < self.params[5]:
                raise ValueError(f"out: expected a C-contiguous float64 vector of at least {self.params[5]} entries "
                                 f"(spec.obs_dim), got {out.dtype.name} {out.shape}")

    def __call__(self, pos: np.ndarray, vel: np.ndarray, obstacle_pos: np.ndarray, obstacle_radius: np.ndarray,
                 knowledge: np.ndarray, time_s: float, visible: np.ndarray | None, out: np.ndarray) -> np.ndarray:
        has = visible is not None
        _encode_one_kernel(self.params, self.ranges, pos, vel, obstacle_pos, obstacle_radius, knowledge,
                           float(time_s), visible if has else self._no_visible, has, self._scratch,
                           self._iscratch, out)
        return out

    def compile(self) -> None:
        """Compile the kernel (or load it from numba's cache) now, on dummy inputs of this spec's shapes."""
        spec = self.spec
        n, k = spec.n_agents, spec.arena.n_obstacles
        kn = new_knowledge(spec, 1)[0]
        z = np.zeros((n, 2))
        self(z, z, np.zeros((k, 2)), np.ones(k), kn, 0.0, None, np.zeros(spec.max_obs_dim))


def encode_one(spec: SwarmSpec, pos: np.ndarray, vel: np.ndarray, obstacle_pos: np.ndarray,
               obstacle_radius: np.ndarray, knowledge: np.ndarray, time_s: float, observer: int,
               visible: np.ndarray | None = None, out: np.ndarray | None = None) -> np.ndarray:
    """``encode_observations(spec, pos[None], ..., observers=[observer], visible=V)[0, 0]``, bit for bit, where
    ``V[0, observer] = visible`` (arrays without the batch axis; see ``OneObserverEncoder``). Returns ``out``
    ([spec.max_obs_dim], allocated when None). Checks its inputs; a loop should keep a ``OneObserverEncoder``."""
    enc = OneObserverEncoder(spec, observer)
    if out is None:
        out = np.zeros(spec.max_obs_dim)
    enc.check(pos, vel, obstacle_pos, obstacle_radius, knowledge, visible, out)
    return enc(pos, vel, obstacle_pos, obstacle_radius, knowledge, time_s, visible, out)
