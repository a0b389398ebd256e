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

SIGHTING = 5
"""Values per sighting: x [m], y [m], vx [m/s], vy [m/s], t_seen [s] (-inf: never seen)."""


def new_knowledge(spec: SwarmSpec, n_envs: int) -> np.ndarray:
    """Empty knowledge ``[B, n_team, n_evaders, 5]``: nothing seen yet."""
    k = np.zeros((n_envs, spec.team.n_team, spec.team.n_evaders, SIGHTING))
    k[..., 4] = -np.inf
    return k


def pairwise_distances(pos: np.ndarray) -> np.ndarray:
    d = pos[:, :, None, :] - pos[:, None, :, :]
    return np.sqrt((d * d).sum(-1))


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
    """Indices of the ``k`` smallest along the last axis, and whether each is finite (valid)."""
    n = dist.shape[-1]
    if k == 0 or n == 0:
        shape = dist.shape[:-1] + (k,)
        return np.zeros(shape, dtype=np.int64), np.zeros(shape, dtype=bool)
    kk = min(k, n)
    idx = np.argsort(dist, axis=-1, kind="stable")[..., :kk]
    valid = np.isfinite(np.take_along_axis(dist, idx, axis=-1))
    if kk < k:
        pad = dist.shape[:-1] + (k - kk,)
        idx = np.concatenate([idx, np.zeros(pad, dtype=np.int64)], axis=-1)
        valid = np.concatenate([valid, np.zeros(pad, dtype=bool)], axis=-1)
    return idx, valid


def _agent_slots(pos_o: np.ndarray, others_pos: np.ndarray, others_vel: np.ndarray, dist: np.ndarray,
                 k: int) -> np.ndarray:
    """[B, M, k, 5] = dx, dy, vx, vy, valid for the k nearest finite entries of ``dist`` [B, M, O]."""
    idx, valid = _nearest(dist, k)
    b, m = dist.shape[:2]
    bi = np.arange(b)[:, None, None]
    rel = others_pos[bi, idx] - pos_o[:, :, None, :]
    v = others_vel[bi, idx]
    out = np.concatenate([rel, v, np.ones(idx.shape + (1,))], axis=-1)
    out *= valid[..., None]
    return out


def _obstacle_slots(pos_o: np.ndarray, obstacle_pos: np.ndarray, obstacle_radius: np.ndarray,
                    k: int) -> np.ndarray:
    b, m = pos_o.shape[:2]
    if k == 0:
        return np.zeros((b, m, 0, 3))
    d = obstacle_pos[:, None, :, :] - pos_o[:, :, None, :]  # [B, M, K, 2]
    surface = np.sqrt((d * d).sum(-1)) - obstacle_radius[:, None, :]
    idx = np.argsort(surface, axis=-1, kind="stable")[..., :k]
    rel = np.take_along_axis(d, idx[..., None], axis=2)
    r = np.take_along_axis(np.broadcast_to(obstacle_radius[:, None, :], surface.shape), idx, axis=2)
    return np.concatenate([rel, r[..., None]], axis=-1)


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
    else:
        out[:] = 0.0
    if dist is None:
        dist = pairwise_distances(pos)
    if visible is None:
        if s.observability == "full":
            visible = np.ones((b, n, n), dtype=bool)
        else:
            rng = np.full((n, n), s.comm_range)
            rng[:nt, nt:] = s.sensing_range  # the pursuer team sees evaders by sensing (relay is in knowledge)
            rng[nt:, :nt] = s.sensing_range  # evaders see threats by sensing only
            visible = dist <= rng[None]
    t = np.broadcast_to(np.asarray(time_s, dtype=np.float64), (b,))
    for group_team in (True, False):
        sel = np.nonzero((obs_idx < nt) if group_team else (obs_idx >= nt))[0]
        if sel.size == 0:
            continue
        who = obs_idx[sel]
        role = Role.PURSUER if group_team else Role.EVADER
        lay = spec.layout(role)
        p = pos[:, who]
        parts = [p, vel[:, who],
                 _obstacle_slots(p, obstacle_pos, obstacle_radius, lay["obstacles"].rows).reshape(b, who.size, -1)]
        d = dist[:, who]  # [B, M, N]
        vis = visible[:, who]
        if group_team:
            kn = knowledge[:, who]  # [B, M, E, 5]
            age = t[:, None, None] - kn[..., 4]
            known = age < s.target_memory
            tgt = np.empty(kn.shape[:3] + (6,))
            tgt[..., 0:2] = kn[..., 0:2] - p[:, :, None, :]
            tgt[..., 2:4] = kn[..., 2:4]
            tgt[..., 4] = np.minimum(age, s.target_memory)
            tgt[..., 5] = 1.0
            tgt *= known[..., None]
            tgt[..., 4] = np.where(known, tgt[..., 4], s.target_memory)
            parts.append(tgt.reshape(b, who.size, -1))
            mates = np.where(vis[:, :, :nt], d[:, :, :nt], np.inf)
            mates[:, np.arange(who.size), who] = np.inf  # not oneself
            parts.append(_agent_slots(p, pos[:, :nt], vel[:, :nt], mates,
                                      lay["teammates"].rows).reshape(b, who.size, -1))
        else:
            threats = np.where(vis[:, :, :nt], d[:, :, :nt], np.inf)
            parts.append(_agent_slots(p, pos[:, :nt], vel[:, :nt], threats,
                                      lay["threats"].rows).reshape(b, who.size, -1))
            mates = np.where(vis[:, :, nt:], d[:, :, nt:], np.inf)
            mates[:, np.arange(who.size), who - nt] = np.inf
            parts.append(_agent_slots(p, pos[:, nt:], vel[:, nt:], mates,
                                      lay["teammates"].rows).reshape(b, who.size, -1))
        block = np.concatenate(parts, axis=-1)
        assert block.shape[-1] == lay.dim, (block.shape, lay.dim)
        out[:, sel, :lay.dim] = block
    return out
