"""The board the simulated world and the per-drone runtimes share: a seqlock-protected block of shared memory
(time, episode, positions, velocities, obstacles, one command row per drone), and the two callables a drone's
runtime reads its state from (``WorldSource``) and writes its command to (``WorldSink``), the same two a ground
station plugs its links into (``runtime.swarm`` runs the world and the agents around it)."""
from __future__ import annotations

import multiprocessing as mp
import sys
from multiprocessing import shared_memory

import numpy as np

from runtime.agent import Perception
from runtime.spec import SwarmSpec

MP_CONTEXT = mp.get_context("fork" if sys.platform.startswith("linux") else "spawn")
"""How the run's processes (``runtime.swarm``) start: a board attached by name from a spawned interpreter must not
be unlinked by that interpreter's resource tracker."""

class WorldBoard:
    """World state and commands in one float64 block (plain memory, or shared memory by ``name``).

    Layout: ``[active, stop]``, two snapshot slots ``[seq, time_s, episode, pos (2N), vel (2N), obstacle_pos
    (2K), obstacle_radius (K)]``, then ``cmd (2N)``. ``publish`` writes the inactive slot (its ``seq`` odd while
    writing) and then makes it the active one, so a reader is never held up by a writer that the scheduler
    paused mid-write; a reader retries only if a slot was rewritten while it copied (two publishes within one
    copy)."""

    def __init__(self, spec: SwarmSpec, shared: bool = False, name: str | None = None) -> None:
        n, k = spec.n_agents, spec.arena.n_obstacles
        self.n, self.k = n, k
        self.slot_size = 3 + 4 * n + 3 * k
        size = 2 + 2 * self.slot_size + 2 * n
        self.shm = None
        if shared or name is not None:
            self.shm = shared_memory.SharedMemory(name=name, create=name is None, size=8 * size)
            if name is not None and MP_CONTEXT.get_start_method() != "fork":
                _untrack(self.shm)  # attached from a fresh interpreter: the creator unlinks it
            self.buf = np.ndarray((size,), dtype=np.float64, buffer=self.shm.buf)
            if name is None:
                self.buf[:] = 0.0
        else:
            self.buf = np.zeros(size)
        self.slots = [self._slot(2 + j * self.slot_size) for j in range(2)]
        o = 2 + 2 * self.slot_size
        self.cmd = self.buf[o:o + 2 * n].reshape(n, 2)
        """Normalised actions [-1, 1] per drone (velocity / max_speed), written by the sinks."""

    def _slot(self, o: int) -> dict[str, np.ndarray]:
        n, k, b = self.n, self.k, self.buf
        return {"head": b[o:o + 3], "pos": b[o + 3:o + 3 + 2 * n].reshape(n, 2),
                "vel": b[o + 3 + 2 * n:o + 3 + 4 * n].reshape(n, 2),
                "obstacle_pos": b[o + 3 + 4 * n:o + 3 + 4 * n + 2 * k].reshape(k, 2),
                "obstacle_radius": b[o + 3 + 4 * n + 2 * k:o + self.slot_size]}

    @property
    def name(self) -> str | None:
        return None if self.shm is None else self.shm.name

    def publish(self, pos: np.ndarray, vel: np.ndarray, obstacle_pos: np.ndarray, obstacle_radius: np.ndarray,
                time_s: float, episode: int) -> None:
        j = 1 - int(self.buf[0])
        s = self.slots[j]
        head = s["head"]
        head[0] += 1.0  # odd: being written
        s["pos"][:] = pos
        s["vel"][:] = vel
        s["obstacle_pos"][:] = obstacle_pos
        s["obstacle_radius"][:] = obstacle_radius
        head[1] = time_s
        head[2] = episode
        head[0] += 1.0
        self.buf[0] = j

    def read(self, pos: np.ndarray, vel: np.ndarray, obstacle_pos: np.ndarray,
             obstacle_radius: np.ndarray) -> tuple[float, int] | None:
        """Copy the newest snapshot into the arrays; (time_s, episode), or None before the first publish."""
        for _ in range(16):
            s = self.slots[int(self.buf[0])]
            head = s["head"]
            v1 = head[0]
            if v1 == 0.0:
                return None
            pos[:] = s["pos"]
            vel[:] = s["vel"]
            obstacle_pos[:] = s["obstacle_pos"]
            obstacle_radius[:] = s["obstacle_radius"]
            t, ep = head[1], head[2]
            if head[0] == v1 and v1 % 2.0 == 0.0:
                return float(t), int(ep)
        return None

    @property
    def stopped(self) -> bool:
        return bool(self.buf[1])

    def request_stop(self) -> None:
        self.buf[1] = 1.0

    def close(self, unlink: bool = False) -> None:
        if self.shm is not None:
            self.buf = self.cmd = self.slots = None
            self.shm.close()
            if unlink:
                self.shm.unlink()
            self.shm = None


def _untrack(shm: shared_memory.SharedMemory) -> None:
    """An attaching process must not let its resource tracker unlink (or warn about) the creator's block."""
    try:
        from multiprocessing import resource_tracker
        resource_tracker.unregister(shm._name, "shared_memory")  # noqa: SLF001 (no public API for this)
    except (ImportError, AttributeError, KeyError):
        pass


class WorldSource:
    """``StateSource`` over a ``WorldBoard``: own state, obstacles, and the other team's agents this drone
    senses (within ``sensing.sensing_range``; all of them with full observability)."""

    def __init__(self, board: WorldBoard, spec: SwarmSpec) -> None:
        self.board = board
        nt, n = spec.team.n_team, spec.n_agents
        self.other_team = np.zeros((n, n), dtype=bool)
        self.other_team[:nt, nt:] = True
        self.other_team[nt:, :nt] = True
        self.full = spec.sensing.observability == "full"
        self.r2 = spec.sensing.sensing_range ** 2
        self._d2 = [np.zeros(n) for _ in range(n)]

    def __call__(self, index: int, p: Perception) -> bool:
        got = self.board.read(p.others_pos, p.others_vel, p.obstacle_pos, p.obstacle_radius)
        if got is None:
            return False
        p.time_s, p.episode = got
        p.pos[:] = p.others_pos[index]
        p.vel[:] = p.others_vel[index]
        if self.full:
            p.sensed[:] = self.other_team[index]
        else:
            d2 = self._d2[index]
            dx = p.others_pos[:, 0] - p.pos[0]
            dy = p.others_pos[:, 1] - p.pos[1]
            np.multiply(dx, dx, out=d2)
            d2 += dy * dy
            np.less_equal(d2, self.r2, out=p.sensed)
            p.sensed &= self.other_team[index]
        return True


class WorldSink:
    """``CommandSink`` onto a ``WorldBoard``: velocity [m/s] -> the world's normalised action."""

    def __init__(self, board: WorldBoard, spec: SwarmSpec) -> None:
        self.board = board
        self.inv_speed = [1.0 / s for s in spec.per_agent("max_speed")]

    def __call__(self, index: int, velocity: np.ndarray) -> None:
        row = self.board.cmd[index]
        s = self.inv_speed[index]
        row[0] = velocity[0] * s
        row[1] = velocity[1] * s
