"""Simulated neighbour communication: what one drone hears from the others, and how badly.

Every drone broadcasts, once per control period, a small binary message: who it is (id, role), its own
position and velocity with their timestamp, and the target sightings it knows (per evader: position,
velocity, when it was seen). The bytes travel over a ``Transport`` (``InProcessBus`` between threads,
``UdpTransport`` between processes on loopback); the channel effects are applied by each drone's ``Radio``:

- bandwidth (sender side): a message occupies the sender's channel for ``8 * bytes / bandwidth_bps`` s;
  messages queue behind each other and are dropped when the backlog exceeds ``max_backlog_s``;
- range (receiver side): a message sent from farther than ``comm_range`` from the receiver is not heard;
- loss (receiver side): each message is lost with probability ``loss`` (a generator seeded by
  ``(seed, receiver)``, so a run is reproducible given the same sequence of messages);
- latency (receiver side): a message is delivered ``latency_s`` (+ uniform ``jitter_s``) after it left
  the sender, on the shared swarm clock;
- malformed messages (bad magic, version, sender, role, length, non-finite numbers) and oversized ones
  (more than ``max_bytes``) are dropped and counted.

Wire format (little endian), ``HEADER`` then ``n_sightings`` times ``SIGHTING``:

=========  =====  ===========================================================================
field      type   meaning
=========  =====  ===========================================================================
magic      2s     ``b"SP"``
version    u8     ``WIRE_VERSION``
sender     u8     agent index in spec order
role       u8     ``runtime.spec.Role`` of the sender (checked against the spec)
n_sight    u8     sightings that follow (at most the number of evaders)
epoch      u16    episode / mission counter; messages of another epoch are ignored
seq        u32    sender's message counter
t_tx       f64    swarm-clock time the message finished leaving the sender [s]
t_state    f64    timestamp of the position and velocity [s]
x y vx vy  4 f64  sender's position [m] and velocity [m/s], world frame
--------   -----  per sighting:
target     u8     evader number (0 = first evader)
x y vx vy  4 f64  its position [m] and velocity [m/s] when seen
t_seen     f64    when it was seen [s]
=========  =====  ===========================================================================

Numbers travel as float64 so that a drone's belief of a neighbour is bit-identical to the neighbour's own
state (the observation a drone builds equals the training encoder's on the same state): 142 B for 2 evaders.
"""
from __future__ import annotations

import abc
import collections
import math
import socket
import struct
from dataclasses import dataclass

import numpy as np

from runtime.observation import SIGHTING
from runtime.spec import SpecError, SwarmSpec

MAGIC = b"SP"
WIRE_VERSION = 1
HEADER = struct.Struct("<2sBBBBHIdd4d")
SIGHT = struct.Struct("<B4dd")
MAX_BYTES = 256
"""Default largest accepted message [bytes]: a header (60 B) and up to 4 sightings (41 B each)."""
_RECV_BUF = 2048


def message_size(n_sightings: int) -> int:
    return HEADER.size + n_sightings * SIGHT.size


@dataclass(frozen=True)
class CommConfig:
    """Channel model of the simulated radio. Defaults: a perfect channel within the spec's comm range."""

    latency_s: float = 0.0
    """Delay from leaving the sender to delivery [s]."""
    jitter_s: float = 0.0
    """Extra delay drawn uniformly in [0, jitter_s] per message and receiver [s]."""
    loss: float = 0.0
    """Probability that a receiver misses a message [0..1]."""
    bandwidth_bps: float = math.inf
    """Channel rate of each sender [bit/s]; inf: no airtime."""
    max_backlog_s: float = 0.1
    """A message that would wait longer than this for the sender's channel is dropped [s]."""
    comm_range: float | None = None
    """Radio range [m]; None: the spec's ``sensing.comm_range`` with partial observability, unlimited with
    full observability (the spec: ranges then do not limit what is seen)."""
    max_bytes: int = MAX_BYTES
    """Largest accepted message [bytes]; longer ones are dropped as oversized."""
    queue: int = 512
    """Messages a receiver can hold while they are in flight (latency); more are dropped."""
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("latency_s", "jitter_s", "max_backlog_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise SpecError(f"comms.{name}: must be a finite number >= 0, got {v!r}")
        if not 0.0 <= self.loss <= 1.0:
            raise SpecError(f"comms.loss: a probability in [0, 1], got {self.loss!r}")
        if not self.bandwidth_bps > 0:
            raise SpecError(f"comms.bandwidth_bps: must be > 0 (inf for no limit), got {self.bandwidth_bps!r}")
        if self.comm_range is not None and not self.comm_range > 0:
            raise SpecError(f"comms.comm_range: must be > 0 (or None for the spec's), got {self.comm_range!r}")
        if self.max_bytes < HEADER.size:
            raise SpecError(f"comms.max_bytes: at least {HEADER.size} (one header), got {self.max_bytes}")
        if self.queue < 1:
            raise SpecError(f"comms.queue: must be >= 1, got {self.queue}")

    def range_for(self, spec: SwarmSpec) -> float:
        if self.comm_range is not None:
            return float(self.comm_range)
        return spec.sensing.comm_range if spec.sensing.observability == "partial" else math.inf


@dataclass
class CommStats:
    sent: int = 0
    received: int = 0
    """Messages taken off the transport (before range, loss and latency)."""
    delivered: int = 0
    dropped_loss: int = 0
    dropped_range: int = 0
    dropped_malformed: int = 0
    dropped_oversized: int = 0
    dropped_bandwidth: int = 0
    dropped_queue: int = 0
    dropped_epoch: int = 0
    ignored_other_team: int = 0
    """Messages of the other team (the pursuer team and the evaders do not share a channel)."""

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)

    def add(self, other: "CommStats") -> None:
        for k, v in other.__dict__.items():
            setattr(self, k, getattr(self, k) + v)


# --------------------------------------------------------------------------------------------------
# transports: move bytes, nothing else


class Transport(abc.ABC):
    """One drone's endpoint: broadcast bytes to every other endpoint, take received bytes one at a time."""

    @abc.abstractmethod
    def send(self, data: bytes | bytearray | memoryview) -> None:
        """Broadcast ``data`` (copied before returning)."""

    @abc.abstractmethod
    def recv(self) -> bytes | memoryview | None:
        """The next received message, or None when there is none (never blocks). A memoryview is valid
        until the next call."""

    def close(self) -> None:
        """Release the endpoint."""


class InProcessBus:
    """Endpoints that share one process (one thread per drone)."""

    def __init__(self, n: int) -> None:
        self.queues = [collections.deque() for _ in range(n)]
        self.endpoints = [_BusEndpoint(self, i) for i in range(n)]

    def endpoint(self, index: int) -> "Transport":
        return self.endpoints[index]


class _BusEndpoint(Transport):
    def __init__(self, bus: InProcessBus, index: int) -> None:
        self.bus = bus
        self.index = index
        self._inbox = bus.queues[index]

    def send(self, data: bytes | bytearray | memoryview) -> None:
        blob = bytes(data)
        for j, q in enumerate(self.bus.queues):
            if j != self.index:
                q.append(blob)  # deque.append/popleft are thread-safe

    def recv(self) -> bytes | None:
        try:
            return self._inbox.popleft()
        except IndexError:
            return None


class UdpTransport(Transport):
    """UDP datagrams on loopback: endpoint ``index`` is bound to ``ports[index]`` and sends to all others."""

    def __init__(self, index: int, ports: list[int], host: str = "127.0.0.1") -> None:
        self.index = index
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
        try:
            self.sock.bind((host, ports[index]))
        except OSError as exc:
            self.sock.close()
            raise OSError(f"agent {index}: cannot bind UDP {host}:{ports[index]} ({exc}): pick other ports "
                          f"(free_udp_ports) or stop the process holding it") from None
        self.sock.setblocking(False)
        self.peers = [(host, p) for j, p in enumerate(ports) if j != index]
        self._buf = bytearray(_RECV_BUF)
        self._view = memoryview(self._buf)

    def send(self, data: bytes | bytearray | memoryview) -> None:
        for peer in self.peers:
            try:
                self.sock.sendto(data, peer)
            except OSError:  # a peer that is gone (ECONNREFUSED) or a full buffer is a lost message
                pass

    def recv(self) -> memoryview | None:
        try:
            n = self.sock.recv_into(self._buf)
        except (BlockingIOError, InterruptedError):
            return None
        except OSError:  # ICMP port unreachable from an earlier send surfaces here on Linux
            return None
        return self._view[:n] if n < _RECV_BUF else self._view  # a full buffer: oversized, caught by size

    def close(self) -> None:
        self.sock.close()


def free_udp_ports(n: int, host: str = "127.0.0.1") -> list[int]:
    """``n`` loopback UDP ports that were free a moment ago."""
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
    try:
        for s in socks:
            s.bind((host, 0))
        return [s.getsockname()[1] for s in socks]
    finally:
        for s in socks:
            s.close()


# --------------------------------------------------------------------------------------------------
# what a drone knows of its neighbours


class Neighbours:
    """Latest state heard from every agent (rows in spec order; one's own row unused)."""

    def __init__(self, n: int) -> None:
        self.pos = np.zeros((n, 2))
        self.vel = np.zeros((n, 2))
        self.t_state = np.full(n, -np.inf)
        """Timestamp of the newest state heard from each agent [s]; -inf: never heard."""
        self.t_recv = np.full(n, -np.inf)
        """When that state was delivered [s]."""

    def reset(self) -> None:
        self.pos[:] = 0.0
        self.vel[:] = 0.0
        self.t_state[:] = -np.inf
        self.t_recv[:] = -np.inf


# --------------------------------------------------------------------------------------------------
# one drone's radio: encode, channel effects, decode


class Radio:
    """The channel model around one drone's ``Transport`` endpoint.

    ``broadcast`` encodes and sends this drone's state; ``poll`` takes everything the transport holds,
    applies range, loss and latency, and delivers due messages into a ``Neighbours`` table and a sighting
    table ``[n_evaders, 5]`` (fresher sightings win, as ``runtime.observation.merge_sightings``)."""

    def __init__(self, spec: SwarmSpec, index: int, transport: Transport, config: CommConfig | None = None,
                 clock=None) -> None:
        self.spec = spec
        self.index = index
        self.transport = transport
        self.config = config or CommConfig()
        self.n = spec.n_agents
        self.n_evaders = spec.team.n_evaders
        self.roles = bytes(int(r) for r in spec.roles)
        self.range = self.config.range_for(spec)
        self.range2 = self.range * self.range
        nt = spec.team.n_team
        self.same_team = [(j < nt) == (index < nt) for j in range(self.n)]
        self.stats = CommStats()
        self.rng = np.random.default_rng([int(self.config.seed), int(index)])
        self.epoch = 0
        self.seq = 0
        self.busy_until = -math.inf
        e = self.n_evaders
        if message_size(e) > self.config.max_bytes:
            raise SpecError(f"comms.max_bytes: {self.config.max_bytes} B cannot hold a message with {e} sightings "
                            f"({message_size(e)} B): raise comms.max_bytes")
        self._out = bytearray(message_size(e))
        self._pending: list[tuple] = []
        """Messages in flight (latency): (due, sender, t_state, x, y, vx, vy, sightings), oldest first."""

    # ----------------------------------------------------------------------------------------- send
    def broadcast(self, now: float, t_state: float, pos: np.ndarray, vel: np.ndarray,
                  sightings: np.ndarray | None = None) -> bool:
        """Send own state and the known sightings ``[n_evaders, 5]`` (rows with a finite ``t_seen``).
        Returns False when the sender's channel backlog dropped it."""
        cfg = self.config
        n_s = 0
        off = HEADER.size
        if sightings is not None:
            for e in range(sightings.shape[0]):
                row = sightings[e]
                if math.isfinite(row[4]):
                    SIGHT.pack_into(self._out, off, e, row[0], row[1], row[2], row[3], row[4])
                    off += SIGHT.size
                    n_s += 1
        t_tx = now
        if cfg.bandwidth_bps != math.inf:
            start = max(now, self.busy_until)
            if start - now > cfg.max_backlog_s:
                self.stats.dropped_bandwidth += 1
                return False
            t_tx = start + 8.0 * off / cfg.bandwidth_bps
            self.busy_until = t_tx
        HEADER.pack_into(self._out, 0, MAGIC, WIRE_VERSION, self.index, self.roles[self.index], n_s,
                         self.epoch & 0xFFFF, self.seq & 0xFFFFFFFF, t_tx, t_state,
                         pos[0], pos[1], vel[0], vel[1])
        self.seq += 1
        self.transport.send(memoryview(self._out)[:off])
        self.stats.sent += 1
        return True

    # -------------------------------------------------------------------------------------- receive
    def _decode(self, data: bytes | memoryview, now: float, mx: float, my: float, table: Neighbours,
                sightings: np.ndarray | None) -> int:
        st = self.stats
        st.received += 1
        size = len(data)
        if size > self.config.max_bytes:
            st.dropped_oversized += 1
            return 0
        if size < HEADER.size:
            st.dropped_malformed += 1
            return 0
        (magic, version, sender, role, n_s, epoch, _seq, t_tx, t_state,
         x, y, vx, vy) = HEADER.unpack_from(data, 0)
        if (magic != MAGIC or version != WIRE_VERSION or sender >= self.n or sender == self.index
                or role != self.roles[sender] or n_s > self.n_evaders or size != message_size(n_s)
                or not math.isfinite(t_tx + t_state + x + y + vx + vy)):
            st.dropped_malformed += 1
            return 0
        if not self.same_team[sender]:
            st.ignored_other_team += 1
            return 0
        if epoch != (self.epoch & 0xFFFF):
            st.dropped_epoch += 1
            return 0
        dx = x - mx
        dy = y - my
        if dx * dx + dy * dy > self.range2:
            st.dropped_range += 1
            return 0
        loss = self.config.loss
        if loss > 0.0 and self.rng.random() < loss:
            st.dropped_loss += 1
            return 0
        sights = ()
        if n_s:
            sights = tuple(SIGHT.unpack_from(data, HEADER.size + j * SIGHT.size) for j in range(n_s))
            for sg in sights:
                if sg[0] >= self.n_evaders or not math.isfinite(sg[1] + sg[2] + sg[3] + sg[4] + sg[5]):
                    st.dropped_malformed += 1
                    return 0
        due = t_tx + self.config.latency_s
        if self.config.jitter_s > 0.0:
            due += self.rng.random() * self.config.jitter_s
        if due <= now:
            self._deliver(now, sender, t_state, x, y, vx, vy, sights, table, sightings)
            return 1
        if len(self._pending) >= self.config.queue:
            st.dropped_queue += 1
            return 0
        self._pending.append((due, sender, t_state, x, y, vx, vy, sights))
        return 0

    def _deliver(self, now: float, sender: int, t_state: float, x: float, y: float, vx: float, vy: float,
                 sights: tuple, table: Neighbours, sightings: np.ndarray | None) -> None:
        if t_state > table.t_state[sender]:
            table.t_state[sender] = t_state
            table.t_recv[sender] = now
            p, v = table.pos[sender], table.vel[sender]
            p[0] = x
            p[1] = y
            v[0] = vx
            v[1] = vy
        if sightings is not None:
            for e, sx, sy, svx, svy, ts in sights:
                row = sightings[e]
                if ts > row[4]:
                    row[0] = sx
                    row[1] = sy
                    row[2] = svx
                    row[3] = svy
                    row[4] = ts
        self.stats.delivered += 1

    def poll(self, now: float, my_pos: np.ndarray, table: Neighbours,
             sightings: np.ndarray | None = None) -> int:
        """Receive everything pending, deliver what is due by ``now`` into ``table`` and ``sightings``
        ``[n_evaders, 5]``; returns messages delivered."""
        tr = self.transport
        mx, my = float(my_pos[0]), float(my_pos[1])
        n = 0
        while True:
            data = tr.recv()
            if data is None:
                break
            n += self._decode(data, now, mx, my, table, sightings)
        pend = self._pending
        if pend:
            ready = [m for m in pend if m[0] <= now]
            if ready:
                pend[:] = [m for m in pend if m[0] > now]
                ready.sort(key=_due)
                for m in ready:
                    self._deliver(now, m[1], m[2], m[3], m[4], m[5], m[6], m[7], table, sightings)
                n += len(ready)
        return n

    def clear(self, epoch: int) -> None:
        """Forget messages in flight (already decoded) and start ``epoch`` (a new episode or mission); messages
        still on the transport are checked against the new epoch when polled."""
        self.epoch = int(epoch)
        self._pending.clear()

    def close(self) -> None:
        self.transport.close()


def _due(message: tuple) -> float:
    return message[0]


def decode_message(data: bytes) -> dict:
    """A message as a dict (for tests and debugging); raises ValueError when malformed."""
    if len(data) < HEADER.size:
        raise ValueError(f"message of {len(data)} B is shorter than the {HEADER.size} B header")
    (magic, version, sender, role, n_s, epoch, seq, t_tx, t_state, x, y, vx, vy) = HEADER.unpack_from(data, 0)
    if magic != MAGIC or version != WIRE_VERSION:
        raise ValueError(f"bad magic/version {magic!r}/{version}")
    if len(data) != message_size(n_s):
        raise ValueError(f"{len(data)} B for {n_s} sightings, expected {message_size(n_s)} B")
    sights = [SIGHT.unpack_from(data, HEADER.size + j * SIGHT.size) for j in range(n_s)]
    return {"sender": sender, "role": role, "epoch": epoch, "seq": seq, "t_tx": t_tx, "t_state": t_state,
            "pos": (x, y), "vel": (vx, vy),
            "sightings": [{"target": s[0], "pos": s[1:3], "vel": s[3:5], "t_seen": s[5]} for s in sights]}


__all__ = ["CommConfig", "CommStats", "Transport", "InProcessBus", "UdpTransport", "Radio", "Neighbours",
           "free_udp_ports", "decode_message", "message_size", "HEADER", "SIGHT", "MAX_BYTES", "WIRE_VERSION"]
