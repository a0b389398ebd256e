"""The simulated Crazyflies in a process of their own, as real drones are: ``SimProcess``.

``SimSwarm`` in the ground station's interpreter shares its GIL with a dozen cflib links and the per-drone
runtimes, so the simulator's own wait for the interpreter shows up in every latency figure and a ground-station
stall pauses the drones' world with it. ``SimProcess`` runs the same ``SimSwarm`` in a child process (spawned:
no fork of the parent's threads) and talks to it over CRTP on UDP exactly like the in-process one; the ground
truth and the failure injection (``truth``, ``kill_link``, ...) go over a pipe to the child, one small call
each. It has the ``SimSwarm`` interface the demo and the tests use; ``truths()`` gets every drone in one call.

If the child dies, every call raises ``SimError`` naming it; ``stop()`` always ends the child (terminate, then
kill), so no simulator is left running after the parent exits.
"""
from __future__ import annotations

import logging
import multiprocessing as mp
import threading
from typing import Any

from groundstation.sim.swarm import DroneTruth, SimError, SimSwarm

logger = logging.getLogger(__name__)

START_TIMEOUT_S = 60.0
"""How long the child may take to import and bind its sockets [s] (seconds on a cold, busy machine)."""
CALL_TIMEOUT_S = 30.0
"""How long one call to the child may take [s]."""

_CALLS = frozenset({"truth", "truths", "kill_link", "restore_link", "reboot", "param", "latency_samples",
                    "packet_counts", "is_locked", "positioning_outage", "drone_contacts", "contact_events",
                    "set_charge", "stalls"})


def _serve(conn, kwargs: dict) -> None:
    """The child: one ``SimSwarm`` and a loop answering calls until "stop" or the parent goes away."""
    logging.basicConfig(level=logging.WARNING)
    try:
        sims = SimSwarm(**kwargs).start()
    except Exception as exc:  # the parent turns this into its one-line error
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        conn.close()
        return
    conn.send(("ready", {"uris": sims.uris, "radii": sims.radii.tolist()}))
    try:
        while True:
            try:
                name, args = conn.recv()
            except (EOFError, OSError):
                break  # the parent is gone: so are its drones
            if name == "stop":
                break
            try:
                conn.send(("ok", _call(sims, name, args)))
            except Exception as exc:
                conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        sims.stop()
        try:
            conn.send(("stopped", None))
        except OSError:
            pass
        conn.close()


def _call(sims: SimSwarm, name: str, args: tuple) -> Any:
    if name == "truths":
        return [sims.truth(i) for i in range(sims.n)]
    if name in ("drone_contacts", "contact_events", "stalls"):
        return getattr(sims, name)
    if name == "set_charge":  # (i, coulombs): drain a battery (the tests' low-battery failure)
        i, charge = args
        with sims._lock:
            sims.model.charge_as[i] = charge
        return None
    return getattr(sims, name)(*args)


class SimProcess:
    """``SimSwarm(n, **kwargs)`` in a child process. ``start()`` / ``stop()`` or a context manager."""

    def __init__(self, n: int, **kwargs: Any) -> None:
        if n < 1:
            raise SimError(f"SimSwarm needs at least one drone, got n={n}")
        self._kwargs = dict(kwargs, n=n)
        self._n = n
        self.host = kwargs.get("host", "127.0.0.1")
        self.base_port = kwargs.get("base_port")
        self._proc: mp.process.BaseProcess | None = None
        self._conn = None
        self._lock = threading.Lock()
        self._uris: list[str] = []
        self.radii: list[float] = []

    @property
    def n(self) -> int:
        return self._n

    @property
    def uris(self) -> list[str]:
        return list(self._uris)

    @property
    def pid(self) -> int | None:
        return self._proc.pid if self._proc is not None else None

    def start(self) -> "SimProcess":
        if self._proc is not None:
            raise SimError("SimProcess already started")
        ctx = mp.get_context("spawn")
        parent, child = ctx.Pipe()
        self._proc = ctx.Process(target=_serve, args=(child, self._kwargs), name="swarm-sim", daemon=True)
        self._proc.start()
        child.close()
        self._conn = parent
        if not parent.poll(START_TIMEOUT_S):
            self.stop()
            raise SimError(f"the simulator process did not start in {START_TIMEOUT_S:.0f} s")
        try:
            kind, payload = parent.recv()
        except EOFError:
            code = self._proc.exitcode
            self.stop()
            raise SimError(f"the simulator process exited at start-up (exit code {code})") from None
        if kind != "ready":
            self.stop()
            raise SimError(payload)
        self._uris, self.radii = payload["uris"], payload["radii"]
        return self

    def stop(self) -> None:
        proc, conn = self._proc, self._conn
        if proc is None:
            return
        try:
            if conn is not None and proc.is_alive():
                with self._lock:
                    conn.send(("stop", ()))
                    if conn.poll(5.0):
                        conn.recv()
        except (OSError, EOFError):
            pass
        proc.join(timeout=5.0)
        if proc.is_alive():
            proc.terminate()
            proc.join(timeout=2.0)
        if proc.is_alive():
            proc.kill()
            proc.join(timeout=2.0)
        if conn is not None:
            conn.close()
        self._proc = self._conn = None

    def __enter__(self) -> "SimProcess":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _rpc(self, name: str, *args: Any) -> Any:
        if name not in _CALLS:
            raise SimError(f"SimProcess has no call {name!r}")
        if self._conn is None:
            raise SimError("the simulator process is not running: start() it first")
        with self._lock:
            try:
                self._conn.send((name, args))
                if not self._conn.poll(CALL_TIMEOUT_S):
                    raise SimError(f"the simulator process did not answer {name} in {CALL_TIMEOUT_S:.0f} s")
                kind, payload = self._conn.recv()
            except (EOFError, OSError, BrokenPipeError):
                code = self._proc.exitcode if self._proc is not None else None
                raise SimError(f"the simulator process is gone (exit code {code})") from None
        if kind != "ok":
            raise SimError(f"simulator: {name}: {payload}")
        return payload

    # ---- the SimSwarm interface --------------------------------------------------------------------

    def truth(self, i: int) -> DroneTruth:
        return self._rpc("truth", i)

    def truths(self) -> list[DroneTruth]:
        """Every drone's ground truth in one call."""
        return self._rpc("truths")

    def kill_link(self, i: int) -> None:
        self._rpc("kill_link", i)

    def restore_link(self, i: int) -> None:
        self._rpc("restore_link", i)

    def reboot(self, i: int) -> None:
        self._rpc("reboot", i)

    def param(self, i: int, name: str) -> float:
        return self._rpc("param", i, name)

    def latency_samples(self) -> list[float]:
        return self._rpc("latency_samples")

    def packet_counts(self) -> list[tuple[int, int]]:
        return self._rpc("packet_counts")

    def is_locked(self, i: int) -> bool:
        return self._rpc("is_locked", i)

    def positioning_outage(self, i: int, seconds: float) -> None:
        self._rpc("positioning_outage", i, seconds)

    def set_charge(self, i: int, charge_as: float) -> None:
        """Set drone ``i``'s battery charge [A s] (drain it to test the low-battery failsafe)."""
        self._rpc("set_charge", i, charge_as)

    @property
    def drone_contacts(self) -> int:
        return self._rpc("drone_contacts")

    @property
    def contact_events(self) -> list[tuple[float, int, int]]:
        return self._rpc("contact_events")

    @property
    def stalls(self) -> int:
        return self._rpc("stalls")


__all__ = ["SimProcess", "START_TIMEOUT_S", "CALL_TIMEOUT_S"]
