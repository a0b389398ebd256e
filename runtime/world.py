"""The one batch-first world model: positions, velocities, obstacles, walls, contacts.

Every array is ``[n_envs, ...]``; training steps thousands of environments at once and the simulators step
one (``n_envs = 1``) through exactly the same code.

Dynamics are those of a position-controlled drone flown by velocity commands: the commanded velocity
(``action_to_velocity``: action x the role's ``max_speed``, norm-limited) is tracked with an acceleration limit, then the position is
integrated. Walls and circular obstacles are solid: an agent that would end inside one is put back on its
surface and loses the velocity component pointing into it, so nobody passes through. Agent-agent contacts
are detected (for rewards and metrics) but not resolved: real drones must avoid them, not bounce.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from runtime.spec import SwarmSpec

_PLACEMENT_TRIES = 64


def action_to_velocity(max_speed: np.ndarray, actions: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """What an action means (the spec's action layout): the commanded velocity [m/s, world frame] of normalised
    actions ``[..., N, 2]`` (batch-first; values in [-1, 1]) for agents of max speeds ``max_speed [N]`` [m/s]
    (``spec.per_agent("max_speed")``, or one role's ``[max_speed]`` for one drone's ``[1, 2]``): each action
    times its agent's max speed, the vector's norm limited to that max speed. The one definition, used by the
    world (training, evaluation, the simulators) and by each drone's runtime; ``out`` (float64, the shape of
    ``actions``, C-contiguous) is written and returned."""
    if out is None:
        out = np.empty(np.shape(actions))
    _velocity_kernel(actions.reshape(-1, 2), max_speed, out.reshape(-1, 2))
    return out


@njit(cache=True, nogil=True)
def _velocity_kernel(actions, max_speed, out):
    """Row ``r`` of ``actions [R, 2]`` is agent ``r % N``'s (``max_speed [N]``). Plain IEEE arithmetic (no
    fastmath), in the order numpy would use, so vectorised and per-drone callers agree to the bit."""
    n = max_speed.shape[0]
    for r in range(actions.shape[0]):
        ms = max_speed[r % n]
        vx = actions[r, 0] * ms
        vy = actions[r, 1] * ms
        speed = np.sqrt(vx * vx + vy * vy)
        if speed > ms:
            s = ms / max(speed, 1e-12)
            vx *= s
            vy *= s
        out[r, 0] = vx
        out[r, 1] = vy


@dataclass
class WorldState:
    """A batch of world states. Arrays are owned by the world and updated in place."""

    pos: np.ndarray
    """[B, N, 2] agent positions [m]."""
    vel: np.ndarray
    """[B, N, 2] agent velocities [m/s]."""
    obstacle_pos: np.ndarray
    """[B, K, 2] obstacle centres [m]."""
    obstacle_radius: np.ndarray
    """[B, K] obstacle radii [m]."""
    step: np.ndarray
    """[B] control periods since the env's last reset."""

    @property
    def n_envs(self) -> int:
        return self.pos.shape[0]

    def copy(self) -> "WorldState":
        return WorldState(self.pos.copy(), self.vel.copy(), self.obstacle_pos.copy(),
                          self.obstacle_radius.copy(), self.step.copy())

    def select(self, env_ids: np.ndarray | slice) -> "WorldState":
        """A copy of some envs (for logging and plotting)."""
        return WorldState(self.pos[env_ids].copy(), self.vel[env_ids].copy(),
                          self.obstacle_pos[env_ids].copy(), self.obstacle_radius[env_ids].copy(),
                          self.step[env_ids].copy())


class World:
    """``n_envs`` independent worlds of one spec.

    >>> w = World(SwarmSpec(), n_envs=4, seed=0); w.reset()
    >>> contacts = w.step(np.zeros((4, w.n_agents, 2)))
    """

    def __init__(self, spec: SwarmSpec, n_envs: int = 1, seed: int | None = None) -> None:
        if n_envs < 1:
            raise ValueError(f"n_envs must be >= 1, got {n_envs}")
        self.spec = spec
        self.n_envs = n_envs
        self.n_agents = spec.n_agents
        self.rng = np.random.default_rng(seed)
        self.radius = np.array(spec.per_agent("radius"))
        self.max_speed = np.array(spec.per_agent("max_speed"))
        self.max_accel = np.array(spec.per_agent("max_accel"))
        self.dt = spec.timing.control_period
        self.half_width = spec.arena.half_width
        self.contact_dist = self.radius[:, None] + self.radius[None, :]
        k = spec.arena.n_obstacles
        self.state = WorldState(
            pos=np.zeros((n_envs, self.n_agents, 2)),
            vel=np.zeros((n_envs, self.n_agents, 2)),
            obstacle_pos=np.zeros((n_envs, k, 2)),
            obstacle_radius=np.zeros((n_envs, k)),
            step=np.zeros(n_envs, dtype=np.int64),
        )
        self.nonfinite_actions = 0
        """Action entries that were NaN or inf and were replaced by a zero velocity command."""
        self._eye = np.eye(self.n_agents, dtype=bool)

    # ------------------------------------------------------------------------------------------ reset
    def reset(self, env_ids: np.ndarray | None = None) -> WorldState:
        """Reset all envs, or only ``env_ids``: new obstacles, agents placed at random, at rest."""
        ids = np.arange(self.n_envs) if env_ids is None else np.asarray(env_ids, dtype=np.int64).reshape(-1)
        if ids.size == 0:
            return self.state
        s = self.state
        centres, radii = self._place_obstacles(ids.size)
        s.obstacle_pos[ids] = centres
        s.obstacle_radius[ids] = radii
        s.pos[ids] = self._place_agents(centres, radii)
        s.vel[ids] = 0.0
        s.step[ids] = 0
        return s

    def _place_obstacles(self, b: int) -> tuple[np.ndarray, np.ndarray]:
        a = self.spec.arena
        k = a.n_obstacles
        centres = np.zeros((b, k, 2))
        radii = np.zeros((b, k))
        todo = np.arange(b)
        for _attempt in range(100):
            if todo.size == 0:
                return centres, radii
            ok_all = np.ones(todo.size, dtype=bool)
            for j in range(k):
                r = self.rng.uniform(a.obstacle_radius_min, a.obstacle_radius_max, (todo.size, _PLACEMENT_TRIES))
                lim = a.half_width - r - a.obstacle_clearance
                c = self.rng.uniform(-1.0, 1.0, (todo.size, _PLACEMENT_TRIES, 2)) * lim[..., None]
                ok = np.ones(r.shape, dtype=bool)
                for i in range(j):
                    gap = np.linalg.norm(c - centres[todo, i][:, None, :], axis=-1) - r - radii[todo, i][:, None]
                    ok &= gap >= a.obstacle_clearance
                first = ok.argmax(axis=1)
                found = ok[np.arange(todo.size), first]
                centres[todo, j] = c[np.arange(todo.size), first]
                radii[todo, j] = r[np.arange(todo.size), first]
                ok_all &= found
            todo = todo[~ok_all]
        raise RuntimeError("could not place the obstacles; the arena spec validation should have prevented this")

    def _place_agents(self, centres: np.ndarray, radii: np.ndarray) -> np.ndarray:
        b = centres.shape[0]
        gap = self.spec.arena.start_clearance
        pos = np.zeros((b, self.n_agents, 2))
        rows = np.arange(b)
        for i in range(self.n_agents):
            r = self.radius[i]
            placed = np.zeros(b, dtype=bool)
            for _attempt in range(100):
                todo = rows[~placed]
                if todo.size == 0:
                    break
                lim = self.half_width - r - gap
                c = self.rng.uniform(-lim, lim, (todo.size, _PLACEMENT_TRIES, 2))
                d_obs = np.linalg.norm(c[:, :, None, :] - centres[todo][:, None, :, :], axis=-1)
                ok = (d_obs >= radii[todo][:, None, :] + r + gap).all(axis=-1)
                if i:
                    d_ag = np.linalg.norm(c[:, :, None, :] - pos[todo, None, :i, :], axis=-1)
                    ok &= (d_ag >= self.radius[None, None, :i] + r + gap).all(axis=-1)
                first = ok.argmax(axis=1)
                found = ok[np.arange(todo.size), first]
                pos[todo[found], i] = c[np.arange(todo.size), first][found]
                placed[todo[found]] = True
            if not placed.all():
                raise RuntimeError(f"could not place agent {i}; the spec validation should have prevented this")
        return pos

    # ------------------------------------------------------------------------------------------- step
    def sanitize_actions(self, actions: np.ndarray) -> np.ndarray:
        """Actions as float64 ``[B, N, 2]`` in [-1, 1]; NaN or inf entries become a zero velocity command
        for that agent and are counted in ``nonfinite_actions``."""
        a = np.asarray(actions, dtype=np.float64)
        if a.shape != (self.n_envs, self.n_agents, 2):
            raise ValueError(f"actions must have shape {(self.n_envs, self.n_agents, 2)}, got {a.shape}")
        finite = np.isfinite(a).all(axis=-1)
        if not finite.all():
            self.nonfinite_actions += int((~finite).sum())
            a = np.where(finite[..., None], a, 0.0)
        return np.clip(a, -1.0, 1.0)

    def step(self, actions: np.ndarray) -> np.ndarray:
        """Advance every env by one control period. Returns the agent-agent contact matrix ``[B, N, N]``
        (symmetric, false on the diagonal); the distances behind it stay in ``last_distances``."""
        a = self.sanitize_actions(actions)
        s = self.state
        dt = self.dt
        vcmd = action_to_velocity(self.max_speed, a)
        dv = vcmd - s.vel
        dvn = np.sqrt((dv * dv).sum(-1))
        lim = self.max_accel[None, :] * dt
        dv *= np.minimum(1.0, lim / np.maximum(dvn, 1e-12))[..., None]
        s.vel += dv
        s.pos += s.vel * dt
        self._resolve_obstacles()
        self._resolve_walls()
        s.step += 1
        self.last_distances = self.distances()
        return self.contacts(self.last_distances)

    def _resolve_walls(self) -> None:
        s = self.state
        lim = (self.half_width - self.radius)[None, :, None]
        hi = s.pos > lim
        lo = s.pos < -lim
        if hi.any() or lo.any():
            np.clip(s.pos, -lim, lim, out=s.pos)
            s.vel[hi & (s.vel > 0)] = 0.0
            s.vel[lo & (s.vel < 0)] = 0.0

    def _resolve_obstacles(self) -> None:
        s = self.state
        if s.obstacle_pos.shape[1] == 0:
            return
        # component-wise [B, N, K] arrays: numpy is several times faster than on a trailing axis of 2
        dx = s.pos[:, :, 0, None] - s.obstacle_pos[:, None, :, 0]
        dy = s.pos[:, :, 1, None] - s.obstacle_pos[:, None, :, 1]
        dist = np.sqrt(dx * dx + dy * dy)
        pen = s.obstacle_radius[:, None, :] + self.radius[None, :, None] - dist  # > 0: inside
        inside = pen > 0
        if not inside.any():
            return
        # Obstacles keep a clearance wider than any agent, so an agent can touch at most one at a time.
        b, n, k = np.nonzero(inside)
        d = dist[b, n, k]
        centre = d < 1e-12  # an agent exactly at a centre is pushed along +x
        safe = np.where(centre, 1.0, d)
        nx = np.where(centre, 1.0, dx[b, n, k] / safe)
        ny = np.where(centre, 0.0, dy[b, n, k] / safe)
        push = pen[b, n, k]
        s.pos[b, n, 0] += nx * push
        s.pos[b, n, 1] += ny * push
        vn = s.vel[b, n, 0] * nx + s.vel[b, n, 1] * ny  # negative = moving into the obstacle
        vn = np.minimum(vn, 0.0)
        s.vel[b, n, 0] -= vn * nx
        s.vel[b, n, 1] -= vn * ny

    # ----------------------------------------------------------------------------------------- queries
    def distances(self) -> np.ndarray:
        """[B, N, N] centre-to-centre distances between agents."""
        return pairwise_distances(self.state.pos)

    def contacts(self, dist: np.ndarray | None = None) -> np.ndarray:
        """[B, N, N] true where two agents touch (distance <= R_i + R_j)."""
        if dist is None:
            dist = self.distances()
        c = dist <= self.contact_dist[None]
        c &= ~self._eye[None]
        return c

    def obstacle_contacts(self) -> np.ndarray:
        """[B, N] true where an agent touches an obstacle (distance <= R_obstacle + R_agent + 1e-9)."""
        s = self.state
        if s.obstacle_pos.shape[1] == 0:
            return np.zeros(s.pos.shape[:2], dtype=bool)
        dx = s.pos[:, :, 0, None] - s.obstacle_pos[:, None, :, 0]
        dy = s.pos[:, :, 1, None] - s.obstacle_pos[:, None, :, 1]
        reach = s.obstacle_radius[:, None, :] + self.radius[None, :, None] + 1e-9
        return (dx * dx + dy * dy <= reach * reach).any(-1)


def pairwise_distances(pos: np.ndarray) -> np.ndarray:
    """[B, N, N] centre distances of positions [B, N, 2] (component-wise: numpy is slow on an axis of 2)."""
    px = np.ascontiguousarray(pos[..., 0])
    py = np.ascontiguousarray(pos[..., 1])
    dx = px[:, :, None] - px[:, None, :]
    dy = py[:, :, None] - py[:, None, :]
    dx *= dx
    dy *= dy
    dx += dy
    return np.sqrt(dx, out=dx)
