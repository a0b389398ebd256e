"""The separation filter's joint solve in a process of its own (``JointFilter(process=True)``; the demo and
``swarm-gs fly`` use it).

In the ground station's interpreter the joint solve (building the constraints, OSQP's set-up and update, the
checks: about 1-3 ms of Python per setpoint period, the OSQP iterations themselves without the GIL) competes for
the interpreter with every link's receive thread. Here the interpreter only takes the snapshot and hands five
small arrays over a pipe; ``filter_velocities`` with its kept ``QPSolver`` runs in the child, and the result
comes back the same way. Every request carries a number, so a late answer is never taken for a newer one.

If the child cannot start, dies or fails, the caller (``JointFilter``) solves in its own thread from then on; an
answer later than the timeout leaves the cache as it is (it ages, and stale it brakes, as a slow solve in the
thread would): the filter never depends on the child being there.
"""
from __future__ import annotations

import itertools
import logging
import multiprocessing as mp
from typing import Any

import numpy as np

log = logging.getLogger(__name__)

class SolverGone(RuntimeError):
    """The child is gone or failed: solve in the ground station from now on."""


START_TIMEOUT_S = 60.0
"""How long the child may take to import numpy, scipy and OSQP [s] (seconds on a cold, busy machine)."""


def _serve(conn, limits) -> None:
    """The child: answer (number, arrays) with (number, velocity, braked, method, setups, updates) until told
    to stop or the parent goes away."""
    from groundstation.separation import QPSolver, filter_velocities
    solver = QPSolver()
    try:  # the first solve imports OSQP and scipy.sparse: before the ground station asks
        filter_velocities(np.array([[0.0, 0.0], [0.5, 0.0]]), np.zeros((2, 2)), np.array([[1.0, 0.0], [-1.0, 0.0]]),
                          np.ones(2, dtype=bool), limits, solver=QPSolver())
        conn.send(("ready",))
        while True:
            try:
                msg = conn.recv()
            except (EOFError, OSError):
                return  # the ground station is gone
            if msg is None:
                return
            key, pos, vel, want, ctrl, prev = msg
            try:
                res = filter_velocities(pos, vel, want, ctrl, limits, prev, solver=solver)
                conn.send((key, res.velocity, res.braked, res.method, solver.setups, solver.updates))
            except Exception as exc:  # the parent solves this one itself
                conn.send((key, None, None, f"{type(exc).__name__}: {exc}", solver.setups, solver.updates))
    finally:
        conn.close()


class SolverProcess:
    """``filter_velocities`` in a child process, one request at a time (see the module docstring)."""

    def __init__(self, limits) -> None:
        self.limits = limits
        self._proc = None
        self._conn = None
        self._keys = itertools.count()
        self.setups = 0
        """The child's OSQP set-ups so far."""
        self.updates = 0
        """The child's warm-started updates so far."""

    @property
    def alive(self) -> bool:
        return self._proc is not None and self._proc.is_alive()

    def start(self) -> "SolverProcess":
        ctx = mp.get_context("spawn")  # no fork of the ground station's threads
        parent, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child, self.limits), name="swarm-separation", daemon=True)
        self._proc.start()
        child.close()
        self._conn = parent
        try:
            ok = parent.poll(START_TIMEOUT_S) and parent.recv() == ("ready",)
        except (EOFError, OSError):
            ok = False
        if not ok:
            self.stop()
            raise RuntimeError(f"the separation solver's process did not start in {START_TIMEOUT_S:.0f} s")
        return self

    def solve(self, positions: np.ndarray, velocities: np.ndarray, desired: np.ndarray, controlled: np.ndarray,
              previous: np.ndarray, timeout: float) -> tuple[np.ndarray, np.ndarray, str] | None:
        """(velocity [N, 2], braked [N], method) as ``filter_velocities`` returns them, or None when the child did
        not answer within ``timeout`` [s] (its late answer is dropped at the next call). ``SolverGone`` when the
        child is gone or failed on this input."""
        conn = self._conn
        if conn is None:
            raise SolverGone("the separation solver's process is not running")
        key = next(self._keys)
        try:
            while conn.poll(0):  # an answer that came too late for its request
                conn.recv()
            conn.send((key, positions, velocities, desired, controlled, previous))
            while conn.poll(timeout):
                got, velocity, braked, method, self.setups, self.updates = conn.recv()
                if got == key:
                    if velocity is None:
                        raise SolverGone(f"the separation solver's process failed: {method}")
                    return velocity, braked, method
        except (EOFError, OSError, ValueError):
            code = self._proc.exitcode if self._proc is not None else None
            raise SolverGone(f"the separation solver's process is gone (exit code {code})") from None
        return None

    def stop(self) -> None:
        proc, conn = self._proc, self._conn
        self._proc = self._conn = None
        if conn is not None:
            try:
                conn.send(None)
            except (OSError, ValueError):
                pass
        if proc is not None:
            proc.join(timeout=2.0)
            if proc.is_alive():
                proc.terminate()
                proc.join(timeout=2.0)
            if proc.is_alive():
                proc.kill()
                proc.join(timeout=2.0)
        if conn is not None:
            conn.close()

    def stats(self) -> dict[str, Any]:
        return {"qp_setups": self.setups, "qp_updates": self.updates}
