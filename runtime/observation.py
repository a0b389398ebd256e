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
"""
from __future__ import annotations

import numpy as np

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
