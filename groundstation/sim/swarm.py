"""``SimSwarm``: N simulated Crazyflies behind UDP sockets (ports ``base_port + i``), one thread.

One selector loop serves every drone: it answers each datagram as it arrives (setpoints take effect at
once), steps the batched flight model at a fixed rate, and sends log blocks when they fall due. In-process
use (tests, the demo)::

    with SimSwarm(n=3, base_port=19850, seed=1) as sims:
        uris = sims.uris            # ["udp://127.0.0.1:19850", ...]
        ...                         # connect cflib / open_link(uri)
        sims.kill_link(0)           # drone 0 stops answering (keeps flying on its own watchdogs)
        sims.positioning_outage(1, 3.0)  # drone 1 gets no positioning for 3 s (its variance grows)
        sims.drone_contacts         # how many times two drones touched (both crashed: motors off, locked)

Drones touch when their centres come closer than the sum of their radii (``radii``, default the spec's
pursuer radius): both crash, as hardware would, counted once per contact.

``swarm-gs sim --drones N`` runs the same thing standalone for any cflib client.
"""
from __future__ import annotations

import errno
import logging
import selectors
import socket
import threading
import time
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from groundstation.sim.crazyflie import SimCrazyflie
from groundstation.sim.firmware import SupervisorState
from groundstation.sim.flight_model import QuadBatch, QuadParams
from runtime.spec import SwarmSpec

logger = logging.getLogger(__name__)

DEFAULT_BASE_PORT = 19850
"""cflib's UDP driver scans 19850-19859 (CrazySim's convention)."""


def free_base_port(n: int, low: int = 20000, high: int = 40000, seed: int | None = None) -> int:
    """A base port with ``n`` consecutive free UDP ports on 127.0.0.1, drawn at random in [low, high), so
    that parallel runs (tests, several demos) do not collide."""
    rng = np.random.default_rng(seed)
    for _ in range(200):
        base = int(rng.integers(low, high - n))
        probes = []
        try:
            for i in range(n):
                sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                probes.append(sock)
                sock.bind(("127.0.0.1", base + i))
            return base
        except OSError:
            continue
        finally:
            for sock in probes:
                sock.close()
    raise SimError(f"no {n} consecutive free UDP ports in [{low}, {high}): free some or widen the range")


SIM_STALL_S = 0.1
"""A simulator loop iteration later than this [s] (beyond its select timeout) counts as a stall of the
simulator's own process; the simulated time skips it."""
CONTACT_EVERY = 2
"""Contacts are looked for every this many physics steps (10 ms at the default 5 ms step: two drones closing
at 3 m/s move 3 cm in that time, a fifth of two radii)."""


class SimError(RuntimeError):
    """The simulator cannot start or was used wrongly; the message says how to fix it."""


@dataclass(frozen=True)
class DroneTruth:
    """Ground truth of one simulated drone, for tests and the demo (not what the drone reports)."""

    position: tuple[float, float, float]
    """[m]"""
    velocity: tuple[float, float, float]
    """[m/s]"""
    supervisor: str
    """Supervisor state: disarmed, ready, flying, level_out, landed, locked."""
    motors_on: bool
    battery_v: float
    """[V]"""
    link_alive: bool
    watchdog_armed: bool = False
    """An emergency-stop-watchdog packet has arrived since boot: the drone now locks when they stop."""


class SimSwarm:
    """N simulated Crazyflies on ``host:base_port + i``."""

    def __init__(self, n: int, base_port: int = DEFAULT_BASE_PORT, host: str = "127.0.0.1", seed: int = 0,
                 params: QuadParams = QuadParams(), spacing: float = 0.5,
                 start_positions: np.ndarray | None = None, physics_dt: float = 0.005,
                 latency_probe: bool = False, radii: float | Sequence[float] | None = None) -> None:
        if n < 1:
            raise SimError(f"SimSwarm needs at least one drone, got n={n}")
        r = np.asarray(SwarmSpec().pursuer.radius if radii is None else radii, dtype=float)
        r = np.full(n, float(r)) if r.ndim == 0 else r
        if r.shape != (n,) or not np.all(np.isfinite(r)) or np.any(r <= 0):
            raise SimError(f"radii: expected one radius > 0 [m] or one per drone ({n}), got {radii!r}")
        self.radii = r.copy()
        """Body radius of each drone [m]: closer than the sum of two, they touch and both crash."""
        self._contact_d2 = (self.radii[:, None] + self.radii[None, :]) ** 2
        self._steps = 0
        self._in_contact: set[tuple[int, int]] = set()
        self._contact_events: list[tuple[float, int, int]] = []
        self.host, self.base_port, self.physics_dt = host, base_port, physics_dt
        if start_positions is None:
            cols = max(1, int(np.ceil(np.sqrt(n))))
            start_positions = np.array([[(i % cols) * spacing, (i // cols) * spacing, 0.0] for i in range(n)])
        self.model = QuadBatch(n, params, start_positions, seed)
        self._paused = 0.0
        self.stalls = 0
        """Times the simulator itself did not run for longer than ``SIM_STALL_S`` (its world paused)."""
        now = self.clock()
        self.drones = [SimCrazyflie(i, self.model, now, latency_probe) for i in range(n)]
        self._alive = [True] * n
        self._clients: list[tuple[str, int] | None] = [None] * n
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._sockets: list[socket.socket] = []
        self._selector: selectors.BaseSelector | None = None

    @property
    def n(self) -> int:
        return len(self.drones)

    @property
    def uris(self) -> list[str]:
        return [f"udp://{self.host}:{self.base_port + i}" for i in range(self.n)]

    # ---- lifecycle ---------------------------------------------------------------------------------

    def start(self) -> "SimSwarm":
        if self._thread is not None:
            raise SimError("SimSwarm already started")
        self._selector = selectors.DefaultSelector()
        try:
            for i in range(self.n):
                sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
                self._sockets.append(sock)
                sock.bind((self.host, self.base_port + i))
                sock.setblocking(False)
                self._selector.register(sock, selectors.EVENT_READ, i)
        except OSError as exc:
            where = f"{self.host}:{self.base_port + len(self._sockets) - 1}"
            self._close_sockets()
            if exc.errno == errno.EADDRINUSE:
                raise SimError(f"cannot bind UDP {where}: the port is taken (another simulator?); pick another "
                               f"base port (swarm-gs sim --base-port P)") from exc
            if exc.errno == errno.EADDRNOTAVAIL:
                raise SimError(f"cannot bind UDP {where}: {self.host} is not an address of this machine; use "
                               f"127.0.0.1 or one of its own addresses (swarm-gs sim --host H)") from exc
            raise SimError(f"cannot bind UDP {where}: {exc.strerror or exc}; check --host and --base-port") from exc
        self._thread = threading.Thread(target=self._run, name="SimSwarm", daemon=True)
        self._thread.start()
        logger.info("simulating %d Crazyflies on %s:%d-%d", self.n, self.host, self.base_port,
                    self.base_port + self.n - 1)
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        self._close_sockets()

    def __enter__(self) -> "SimSwarm":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _close_sockets(self) -> None:
        if self._selector is not None:
            self._selector.close()
            self._selector = None
        for sock in self._sockets:
            sock.close()
        self._sockets = []

    # ---- failure injection and inspection ---------------------------------------------------------

    def kill_link(self, i: int) -> None:
        """Drone ``i`` stops answering and stops sending (a radio out of range); it keeps flying."""
        with self._lock:
            self._alive[i] = False

    def restore_link(self, i: int) -> None:
        with self._lock:
            self._alive[i] = True

    def reboot(self, i: int) -> None:
        """Power-cycle drone ``i`` (the only way out of the locked state)."""
        with self._lock:
            self.drones[i].reboot(self.clock())

    def truth(self, i: int) -> DroneTruth:
        with self._lock:
            d, m = self.drones[i], self.model
            return DroneTruth(tuple(float(v) for v in m.pos[i]), tuple(float(v) for v in m.vel[i]),
                              d.firmware.state.value, d.firmware.motors_on,
                              float(m.battery_voltage(i, d.firmware.motors_on)), self._alive[i],
                              d.firmware.watchdog_armed)

    def truths(self) -> list[DroneTruth]:
        """Every drone's ground truth (one call; ``SimProcess`` answers it in one message)."""
        return [self.truth(i) for i in range(self.n)]

    def set_charge(self, i: int, charge_as: float) -> None:
        """Set drone ``i``'s battery charge [A s] (drain it to test the low-battery failsafe)."""
        with self._lock:
            self.model.charge_as[i] = charge_as

    def param(self, i: int, name: str) -> float:
        with self._lock:
            return self.drones[i].params[name]

    def latency_samples(self) -> list[float]:
        """Measurement-to-setpoint delays [s] of every drone (``latency_probe=True`` only)."""
        with self._lock:
            return [s for d in self.drones for s in d.latency_samples]

    def packet_counts(self) -> list[tuple[int, int]]:
        """(received, sent) CRTP packets per drone."""
        with self._lock:
            return [(d.rx_packets, d.tx_packets) for d in self.drones]

    def is_locked(self, i: int) -> bool:
        with self._lock:
            return self.drones[i].firmware.state is SupervisorState.LOCKED

    def positioning_outage(self, i: int, seconds: float) -> None:
        """No positioning measurement reaches drone ``i`` for ``seconds``: its estimate dead-reckons and its
        ``kalman.varP*`` grows (a blocked anchor, a UWB dropout)."""
        with self._lock:
            self.model.estimator.outage(i, seconds)

    @property
    def drone_contacts(self) -> int:
        """How many times two drones touched (each pair counted again only after it has separated)."""
        with self._lock:
            return len(self._contact_events)

    @property
    def contact_events(self) -> list[tuple[float, int, int]]:
        """Every contact as (time [s, ``clock()``: time.monotonic() less the simulator's own stalls], i, j),
        i < j."""
        with self._lock:
            return list(self._contact_events)

    # ---- the loop ----------------------------------------------------------------------------------

    def clock(self) -> float:
        """The simulated drones' time [s]: ``time.monotonic()`` less the time this simulator did not run."""
        return time.monotonic() - self._paused

    def _note_stall(self, real_gap: float) -> None:
        """A loop iteration that comes later than ``SIM_STALL_S``: the simulator's process was not scheduled.
        Real drones do not pause with it, but the best model of that gap is a world that paused: otherwise
        the firmware's watchdogs would count time in which neither the drones nor (in-process) the ground
        station ran, and lock drones that a real ground station had kept alive."""
        if real_gap > SIM_STALL_S:
            self._paused += real_gap - SIM_STALL_S
            self.stalls += 1
            logger.debug("simulator did not run for %.0f ms: the simulated world paused", real_gap * 1e3)

    def _run(self) -> None:
        dt = self.physics_dt
        next_step = self.clock()
        last = time.monotonic()
        while not self._stop.is_set():
            now = self.clock()
            next_log = min(d.next_log_due() for d in self.drones)
            timeout = min(max(min(next_step, next_log) - now, 0.0), 0.05)
            try:
                events = self._selector.select(timeout)
            except (OSError, ValueError):
                break  # sockets closed under us by stop()
            real = time.monotonic()
            self._note_stall(real - last - timeout)
            last = real
            for key, _ in events:
                self._drain(key.fileobj, key.data)
            with self._lock:
                now = self.clock()
                steps = 0
                while next_step <= now and steps < 10:
                    self._physics_step(next_step, dt)
                    next_step += dt
                    steps += 1
                if next_step <= now:
                    logger.debug("simulator fell behind by %.1f ms", (now - next_step) * 1e3)
                    next_step = now + dt
                self._send_logs(now)

    def _drain(self, sock: socket.socket, i: int) -> None:
        while True:
            try:
                data, addr = sock.recvfrom(64)
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:  # e.g. ICMP port unreachable from a client that went away
                logger.debug("drone %d: recv error %s", i, exc)
                return
            with self._lock:
                if not self._alive[i]:
                    continue
                self._clients[i] = addr
                replies = self.drones[i].handle(data, self.clock())
                self._send(i, replies)

    def _send(self, i: int, datagrams: list[bytes]) -> None:
        addr = self._clients[i]
        if addr is None or not datagrams:
            return
        sock = self._sockets[i]
        for datagram in datagrams:
            try:
                sock.sendto(datagram, addr)
                self.drones[i].tx_packets += 1
            except OSError as exc:
                logger.debug("drone %d: send error %s", i, exc)

    def _send_logs(self, now: float) -> None:
        for i, drone in enumerate(self.drones):
            if drone.next_log_due() > now:
                continue
            packets = drone.due_log_packets(now)
            if not self._alive[i] or self._clients[i] is None:
                continue
            for datagram, ts in packets:
                self._send(i, [datagram])
                drone.note_log_sent(ts, self.clock())

    def _physics_step(self, t: float, dt: float) -> None:
        n = self.n
        v_des = np.zeros((n, 3))
        yaw_rate = np.zeros(n)
        motors = np.zeros(n, dtype=bool)
        coasting = np.zeros(n, dtype=bool)
        for i, drone in enumerate(self.drones):
            v_des[i], yaw_rate[i], motors[i], coasting[i] = drone.control(t)
        extpos = np.array([d.firmware.extpos_fresh(t) for d in self.drones])
        self.model.step(dt, v_des, yaw_rate, motors, coasting, extpos)
        self._steps += 1
        if n > 1 and self._steps % CONTACT_EVERY == 0:
            self._check_contacts(t, motors)

    def _check_contacts(self, t: float, motors: np.ndarray) -> None:
        """Pairs closer than the sum of their radii crash, both: motors off and locked, as on hardware
        where touching propellers end the flight. Two drones resting on the floor side by side do not."""
        pos = self.model.pos
        diff = pos[:, None, :] - pos[None, :, :]
        d2 = np.einsum("ijk,ijk->ij", diff, diff)
        touching = d2 < self._contact_d2
        np.fill_diagonal(touching, False)
        if not touching.any():
            self._in_contact.clear()
            return
        d = np.sqrt(d2)
        resting = ~motors & (pos[:, 2] <= self.model.params.ground_z + 1e-6)
        now_in: set[tuple[int, int]] = set()
        for i, j in zip(*np.nonzero(np.triu(touching, 1))):
            i, j = int(i), int(j)
            if resting[i] and resting[j]:
                continue
            now_in.add((i, j))
            if (i, j) not in self._in_contact:
                self._contact_events.append((t, i, j))
                logger.warning("drones %d and %d touched (%.3f m apart): both crash", i, j, d[i, j])
                for k in (i, j):
                    self.drones[k].firmware.crash(t, f"drone {k}: collision with drone {j if k == i else i}")
        self._in_contact = now_in
