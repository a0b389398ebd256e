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
- malformed messages (bad magic, sender, role, length, non-finite numbers), messages of another message version
  or spec (counted apart, and logged once per sender with the reason) and oversized ones are dropped.

Wire format: ``runtime.radio_msg`` (the one definition the Crazyflie app's C is generated from): one 60-byte
peer-to-peer packet at most, positions and velocities in int16 fixed point (1 mm, 1 mm/s with the default
spec), times in whole ms, up to three relayed sightings (freshest first, younger than the target memory).
Airtime (``bandwidth_bps``) and ``max_bytes`` count the packet's bytes. The packet budget: one packet per drone
and control period, at most ``P2P_MAX_DATA_SIZE`` (60) bytes, on the channel the Crazyradio's CRTP link uses
(the firmware's P2P documentation, ``docs/functional-areas/p2p_api.md``, advises polling the link at
``rate_limit=100`` to leave airtime for them); the channel's share is not modelled by default (no airtime
limit): ``bandwidth_bps`` models one sender's.

By default a drone receives exactly what a Crazyflie peer would: the packet's values (the quantization error
stays within ``radio_msg.Scales``) and its departure time in whole ms, from which latency is counted (from the
earliest moment the rounded time can mean, so rounding never holds a message back).

Exact values (``CommConfig.exact_values``, off by default; ``swarm-runtime run --exact-values``): the simulated
channel then carries, after the packet, the sender's float64 numbers (``_EXACT``: t_tx, t_state, x, y, vx, vy,
then x, y, vx, vy, t_seen per sighting) and the receiver uses them instead of the packet's quantized ones, so
that a simulated drone's observation is bit-identical to the training encoder's on the same state (the parity
tests use it). The packet itself (its layout, checks, sighting budget and size) is the same either way.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import logging

import numpy as np

from runtime import radio_msg
from runtime.radio_msg import HEADER, MAX_SIGHTINGS, SIGHTING, Codec, RadioMsgError, message_size
from runtime.spec import SpecError, SwarmSpec
from runtime.transports import InProcessBus, Transport, UdpTransport, free_udp_ports

log = logging.getLogger(__name__)

SIGHT = SIGHTING
WIRE_VERSION = radio_msg.VERSION
MAX_BYTES = radio_msg.P2P_MAX_DATA_SIZE
"""Default and largest accepted packet [bytes]: one Crazyflie peer-to-peer packet."""


def _exact(n_sightings: int) -> struct.Struct:
    """The simulation's float64 trailer after a packet with ``n_sightings`` sightings (see the module doc)."""
    return struct.Struct("<" + "d" * (6 + 5 * n_sightings))


_EXACT = [_exact(n) for n in range(MAX_SIGHTINGS + 1)]
_TX_ROUNDING = 0.5e-3
"""The packet's departure time is rounded to the ms (``radio_msg``): it can read up to half a ms after the
true one. Latency counts from the earliest departure it can mean, so that a message is never held back as
"still in flight" (with zero latency, until the next poll) for its rounding alone [s]."""
_SENDER_AT = next(f.offset for f in radio_msg.HEADER_FIELDS if f.name == "sender")


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
    """Largest packet [bytes] (at most the 60 of a Crazyflie peer-to-peer packet); a smaller budget relays
    fewer sightings, longer packets are dropped as oversized."""
    exact_values: bool = False
    """Carry the sender's float64 numbers beside the packet (see the module doc: bit-identical observations for
    parity tests); False (default): the receiver gets the packet's quantized values, as on the drones."""
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
        if not HEADER.size <= self.max_bytes <= MAX_BYTES:
            raise SpecError(f"comms.max_bytes: between {HEADER.size} (one header) and {MAX_BYTES} (a Crazyflie "
                            f"peer-to-peer packet), got {self.max_bytes}")
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
    dropped_version: int = 0
    """Messages of another message layout version (``runtime.radio_msg.VERSION``)."""
    dropped_spec: int = 0
    """Messages of a drone flying another spec (its hash prefix differs)."""
    sightings_left_out: int = 0
    """Sightings not relayed because the packet had no room for them (sender side)."""
    ignored_other_team: int = 0
    """Messages of the other team (the pursuer team and the evaders do not share a channel)."""

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)

    def add(self, other: "CommStats") -> None:
        for k, v in other.__dict__.items():
            setattr(self, k, getattr(self, k) + v)


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
        self.codec = Codec(spec)
        self.n = spec.n_agents
        self.n_evaders = spec.team.n_evaders
        self.range = self.config.range_for(spec)
        self.range2 = self.range * self.range
        nt = spec.team.n_team
        self.same_team = [(j < nt) == (index < nt) for j in range(self.n)]
        self.stats = CommStats()
        self.rng = np.random.default_rng([int(self.config.seed), int(index)])
        self.epoch = 0
        self.seq = 0
        self.busy_until = -math.inf
        self.n_relay = min(self.n_evaders, MAX_SIGHTINGS, (self.config.max_bytes - HEADER.size) // SIGHTING.size)
        """Sightings one packet carries at most (the packet's room within ``max_bytes``)."""
        n_max = min(self.n_evaders, MAX_SIGHTINGS)
        self._max_in = MAX_BYTES + _EXACT[n_max].size
        self._out = bytearray(MAX_BYTES + _EXACT[n_max].size)
        self._warned: set[tuple[str, int]] = set()
        self._pending: list[tuple] = []
        """Messages in flight (latency): (due, sender, t_state, x, y, vx, vy, sightings), oldest first."""

    # ----------------------------------------------------------------------------------------- send
    def broadcast(self, now: float, t_state: float, pos: np.ndarray, vel: np.ndarray,
                  sightings: np.ndarray | None = None) -> bool:
        """Send own state and the known sightings ``[n_evaders, 5]`` (rows with a finite ``t_seen`` younger
        than the target memory, freshest first, as many as the packet holds). Returns False when the sender's
        channel backlog dropped it."""
        cfg = self.config
        rows: list = []
        if sightings is not None:
            sel = self.codec.select(sightings, t_state, limit=self.n_evaders)
            if len(sel) > self.n_relay:
                self.stats.sightings_left_out += len(sel) - self.n_relay
            rows = [(e, *(float(v) for v in sightings[e][:5])) for e in sel[:self.n_relay]]
        size = message_size(len(rows))
        t_tx = now
        if cfg.bandwidth_bps != math.inf:
            start = max(now, self.busy_until)
            if start - now > cfg.max_backlog_s:
                self.stats.dropped_bandwidth += 1
                return False
            t_tx = start + 8.0 * size / cfg.bandwidth_bps
            self.busy_until = t_tx
        x, y, vx, vy = float(pos[0]), float(pos[1]), float(vel[0]), float(vel[1])
        self.codec.pack_into(self._out, self.index, self.epoch, self.seq, t_tx, t_state, x, y, vx, vy, rows)
        if cfg.exact_values:
            vals = [t_tx, t_state, x, y, vx, vy]
            for r in rows:
                vals += r[1:]
            _EXACT[len(rows)].pack_into(self._out, size, *vals)
            size += _EXACT[len(rows)].size
        self.seq += 1
        self.transport.send(memoryview(self._out)[:size])
        self.stats.sent += 1
        return True

    # -------------------------------------------------------------------------------------- receive
    def _reject(self, exc: RadioMsgError, data) -> None:
        st = self.stats
        if exc.reason in ("spec", "version"):
            setattr(st, f"dropped_{exc.reason}", getattr(st, f"dropped_{exc.reason}") + 1)
            key = (exc.reason, bytes(data[_SENDER_AT:_SENDER_AT + 1]))
            if key not in self._warned:  # once per sender and reason: a neighbour talks at 10 Hz
                self._warned.add(key)
                log.warning("agent %d ignores a neighbour: %s", self.index, exc)
        else:
            st.dropped_malformed += 1

    def _decode(self, data: bytes | memoryview, now: float, mx: float, my: float, table: Neighbours,
                sightings: np.ndarray | None) -> int:
        st = self.stats
        st.received += 1
        size = len(data)
        if size > self._max_in:
            st.dropped_oversized += 1
            return 0
        try:
            h = self.codec.check_header(data)
        except RadioMsgError as exc:
            self._reject(exc, data)
            return 0
        sender, n_s = h[3], h[5]
        packet = message_size(n_s)
        exact = size == packet + _EXACT[n_s].size
        if packet > self.config.max_bytes:
            st.dropped_oversized += 1
            return 0
        if sender == self.index or not (exact or size == packet):
            st.dropped_malformed += 1
            return 0
        if not self.same_team[sender]:
            st.ignored_other_team += 1
            return 0
        if h[7] != (self.epoch & 0xFFFF):
            st.dropped_epoch += 1
            return 0
        try:
            t_state, sights = self.codec.values(data, h, now)
        except RadioMsgError:
            st.dropped_malformed += 1
            return 0
        if exact:
            v = _EXACT[n_s].unpack_from(data, packet)
            if not all(math.isfinite(u) for u in v):
                st.dropped_malformed += 1
                return 0
            t_tx, t_state, x, y, vx, vy = v[:6]
            sights = tuple((sg[0], *v[6 + 5 * j:11 + 5 * j]) for j, sg in enumerate(sights))
        else:
            pm, vm = self.codec._pos_m / 1000.0, self.codec._vel_m / 1000.0
            t_tx = radio_msg.unwrap_ms(h[9], now) - _TX_ROUNDING
            x, y, vx, vy = h[11] * pm, h[12] * pm, h[13] * vm, h[14] * vm
        dx = x - mx
        dy = y - my
        if dx * dx + dy * dy > self.range2:
            st.dropped_range += 1
            return 0
        loss = self.config.loss
        if loss > 0.0 and self.rng.random() < loss:
            st.dropped_loss += 1
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


def decode_message(data: bytes, spec: SwarmSpec, now: float = 0.0) -> dict:
    """A message of ``spec`` as a dict (for tests and debugging), with the exact values when the simulation's
    trailer is there; raises ``radio_msg.RadioMsgError`` (a ValueError) naming the reason when it is unusable."""
    codec = Codec(spec)
    h = codec.check_header(data)
    packet = message_size(h[5])
    m = codec.unpack(bytes(data[:packet]), now)
    exact = len(data) == packet + _EXACT[h[5]].size
    t_tx, t_state, pos, vel = m.t_tx, m.t_state, (m.x, m.y), (m.vx, m.vy)
    sights = m.sightings
    if exact:
        v = _EXACT[h[5]].unpack_from(data, packet)
        t_tx, t_state, pos, vel = v[0], v[1], v[2:4], v[4:6]
        sights = tuple((sg[0], *v[6 + 5 * j:11 + 5 * j]) for j, sg in enumerate(sights))
    elif len(data) != packet:
        raise RadioMsgError("size", f"{len(data)} B for {h[5]} sightings, expected {packet} B")
    return {"sender": m.sender, "role": m.role, "epoch": m.epoch, "seq": m.seq, "t_tx": t_tx, "t_state": t_state,
            "pos": tuple(pos), "vel": tuple(vel), "clamped": m.clamped, "exact": exact,
            "sightings": [{"target": s[0], "pos": tuple(s[1:3]), "vel": tuple(s[3:5]), "t_seen": s[5]} for s in sights]}


__all__ = ["CommConfig", "CommStats", "Transport", "InProcessBus", "UdpTransport", "Radio", "Neighbours",
           "free_udp_ports", "decode_message", "message_size", "HEADER", "SIGHT", "MAX_BYTES", "WIRE_VERSION"]
