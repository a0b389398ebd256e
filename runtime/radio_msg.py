"""The neighbour radio message: one definition for the Python runtime and the Crazyflie app.

A drone broadcasts its own state and the target sightings it knows in one Crazyflie peer-to-peer packet
(crazyflie-firmware ``src/hal/interface/radiolink.h``: ``P2P_MAX_DATA_SIZE 60`` bytes of payload; an
older release says 61, so 60 fits both, and ``swarm_app.c`` checks it against the firmware's header when it
is built). The
layout below is the single source: ``runtime.comms`` packs and parses it with ``Codec``, and
``firmware_export.cgen`` generates the C struct offsets, scales and pack/unpack functions of the app from
``header_fields`` / ``sighting_fields`` (no size or offset is written by hand anywhere else).

Wire format, little endian, ``HEADER`` (30 B) then ``n_sight`` times ``SIGHTING`` (10 B), at most
``MAX_SIGHTINGS`` = 3 (60 B):

=========  ========  =====================================================================================
field      C type    meaning (value = raw * scale)
=========  ========  =====================================================================================
magic      uint8_t   ``MAGIC`` 0x53 ('S')
version    uint8_t   ``VERSION``; another version is rejected (``RadioMsgError.reason == "version"``)
spec_hash  uint32_t  first 32 bits of ``SwarmSpec.hash``; drones of another spec ignore each other ("spec")
sender     uint8_t   agent index in spec order
role       uint8_t   ``runtime.spec.Role`` of the sender (checked against the spec)
n_sight    uint8_t   sightings that follow
flags      uint8_t   bit 0 ``FLAG_CLAMPED``: a value was out of its range and was saturated
epoch      uint16_t  episode / mission counter
seq        uint16_t  sender's message counter (modulo 2^16)
t_tx_ms    uint32_t  sender's clock when the message left [ms, modulo 2^32]
t_state_ms uint32_t  timestamp of the position and velocity [ms, modulo 2^32]
x, y       int16_t   position, world frame [pos_lsb m]
vx, vy     int16_t   velocity, world frame [vel_lsb m/s]
---------  --------  per sighting:
target     uint8_t   evader number (0 = first evader)
age        uint8_t   t_state - t_seen [age_lsb s]
x, y       int16_t   its position when seen [pos_lsb m]
vx, vy     int16_t   its velocity when seen [vel_lsb m/s]
=========  ========  =====================================================================================

Quantization, from the spec (``Scales``): positions cover twice the arena's half width and velocities four
times the fastest role's ``max_speed`` with int16 (+-32767 steps); the step is 1 mm and 1 mm/s unless the
arena or speeds need coarser ones (a 3 m arena: 1 mm, range +-32.767 m; max speed 1.3 m/s: 1 mm/s). The
age step is ``target_memory`` / 254 rounded up to a whole ms (12 ms for 3 s). Rounding is to the nearest
step (halves away from zero), so the error is at most half a step. Values beyond the last step saturate
at +-32767 (ages at 0 and 254; a non-finite age at 254) and set ``FLAG_CLAMPED``; a non-finite position or
velocity is sent as ``NAN_RAW`` (-32768) and the receiver rejects the whole message (``"non-finite"``);
nothing wraps. Times are whole ms modulo 2^32 and are
read back as the value nearest to the receiver's clock (``unwrap_ms``): exact within +-24 days.

Relay policy: sightings younger than ``target_memory`` (older ones are unknown to the observation anyway),
freshest first, as many as fit (``MAX_SIGHTINGS``, or fewer when the caller's byte budget is smaller).
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass

from runtime.spec import SwarmSpec

MAGIC = 0x53
VERSION = 2
P2P_MAX_DATA_SIZE = 60
"""Payload of one Crazyflie peer-to-peer packet [bytes] (crazyflie-firmware radiolink.h)."""
FLAG_CLAMPED = 0x01
NAN_RAW = -32768
"""int16 raw value meaning "not a number": the message (or sighting) is rejected."""
I16_MAX = 32767
AGE_MAX = 254
TIME_MOD = 1 << 32


@dataclass(frozen=True)
class Field:
    name: str
    ctype: str
    offset: int
    scale: str
    """Name of the ``Scales`` attribute the raw value is multiplied by ("" for raw integers)."""
    doc: str


_CT = {"uint8_t": "B", "uint16_t": "H", "uint32_t": "I", "int16_t": "h"}


def _table(rows: list[tuple[str, str, str, str]]) -> tuple[Field, ...]:
    out, off = [], 0
    for name, ctype, scale, doc in rows:
        out.append(Field(name, ctype, off, scale, doc))
        off += struct.calcsize("<" + _CT[ctype])
    return tuple(out)


HEADER_FIELDS = _table([
    ("magic", "uint8_t", "", "0x53"),
    ("version", "uint8_t", "", "message layout version"),
    ("spec_hash", "uint32_t", "", "first 32 bits of the spec hash"),
    ("sender", "uint8_t", "", "agent index in spec order"),
    ("role", "uint8_t", "", "runtime.spec.Role of the sender"),
    ("n_sight", "uint8_t", "", "sightings that follow"),
    ("flags", "uint8_t", "", "bit 0: a value was saturated"),
    ("epoch", "uint16_t", "", "episode / mission counter"),
    ("seq", "uint16_t", "", "message counter, modulo 2^16"),
    ("t_tx_ms", "uint32_t", "", "sender clock at transmission [ms mod 2^32]"),
    ("t_state_ms", "uint32_t", "", "timestamp of the state [ms mod 2^32]"),
    ("x", "int16_t", "pos_lsb", "position x [m]"),
    ("y", "int16_t", "pos_lsb", "position y [m]"),
    ("vx", "int16_t", "vel_lsb", "velocity x [m/s]"),
    ("vy", "int16_t", "vel_lsb", "velocity y [m/s]"),
])
SIGHTING_FIELDS = _table([
    ("target", "uint8_t", "", "evader number"),
    ("age", "uint8_t", "age_lsb", "t_state - t_seen [s]"),
    ("x", "int16_t", "pos_lsb", "position x when seen [m]"),
    ("y", "int16_t", "pos_lsb", "position y when seen [m]"),
    ("vx", "int16_t", "vel_lsb", "velocity x when seen [m/s]"),
    ("vy", "int16_t", "vel_lsb", "velocity y when seen [m/s]"),
])
HEADER = struct.Struct("<" + "".join(_CT[f.ctype] for f in HEADER_FIELDS))
SIGHTING = struct.Struct("<" + "".join(_CT[f.ctype] for f in SIGHTING_FIELDS))
MAX_SIGHTINGS = (P2P_MAX_DATA_SIZE - HEADER.size) // SIGHTING.size


def message_size(n_sightings: int) -> int:
    """Bytes of a message with ``n_sightings`` sightings."""
    return HEADER.size + n_sightings * SIGHTING.size


def spec_hash32(spec: SwarmSpec) -> int:
    """The spec hash's first 32 bits, as carried in every message."""
    return int(spec.hash[:8], 16)


@dataclass(frozen=True)
class Scales:
    pos_lsb: float
    """Position step [m]."""
    vel_lsb: float
    """Velocity step [m/s]."""
    age_lsb: float
    """Sighting age step [s]."""

    @classmethod
    def for_spec(cls, spec: SwarmSpec) -> "Scales":
        vmax = max(spec.pursuer.max_speed, spec.scout.max_speed, spec.evader.max_speed)
        return cls(pos_lsb=_step_ms(2.0 * spec.arena.half_width / I16_MAX),
                   vel_lsb=_step_ms(4.0 * vmax / I16_MAX),
                   age_lsb=math.ceil(spec.sensing.target_memory * 1000.0 / AGE_MAX) / 1000.0)


def _step_ms(need: float) -> float:
    """The smallest whole number of thousandths (at least one) that is >= ``need``."""
    return max(1, math.ceil(need * 1000.0 - 1e-9)) / 1000.0


class RadioMsgError(ValueError):
    """A message this drone cannot use; ``reason`` is one word: size, magic, version, spec, sender, role,
    target, non-finite."""

    def __init__(self, reason: str, text: str) -> None:
        super().__init__(text)
        self.reason = reason


@dataclass(frozen=True)
class Message:
    sender: int
    role: int
    epoch: int
    seq: int
    t_tx: float
    t_state: float
    x: float
    y: float
    vx: float
    vy: float
    sightings: tuple[tuple[int, float, float, float, float, float], ...]
    """(evader, x, y, vx, vy, t_seen) each."""
    clamped: bool


def _round(r: float) -> int:
    """Nearest integer, halves away from zero (as the generated C: ``(int)(q + 0.5f)`` / ``(q - 0.5f)``)."""
    return math.floor(r + 0.5) if r >= 0 else -math.floor(0.5 - r)


def unwrap_ms(raw: int, ref_s: float) -> float:
    """The time [s] whose whole ms are ``raw`` modulo 2^32 nearest to ``ref_s``."""
    ref = round(ref_s * 1000.0)
    d = (raw - ref) % TIME_MOD
    if d >= TIME_MOD // 2:
        d -= TIME_MOD
    return (ref + d) / 1000.0


class Codec:
    """Pack and parse the messages of one spec."""

    def __init__(self, spec: SwarmSpec) -> None:
        self.spec = spec
        self.scales = Scales.for_spec(spec)
        self.hash32 = spec_hash32(spec)
        self.n_agents = spec.n_agents
        self.n_evaders = spec.team.n_evaders
        self.roles = tuple(int(r) for r in spec.roles)
        self.target_memory = spec.sensing.target_memory
        s = self.scales
        self._pos_k, self._vel_k, self._age_k = 1.0 / s.pos_lsb, 1.0 / s.vel_lsb, 1.0 / s.age_lsb
        self._pos_m, self._vel_m = round(s.pos_lsb * 1000), round(s.vel_lsb * 1000)

    # ------------------------------------------------------------------------------------------- pack
    def select(self, sightings, t_state: float, limit: int = MAX_SIGHTINGS) -> list[int]:
        """Rows of ``sightings`` ``[n_evaders, 5]`` to relay: younger than target_memory, freshest first (ties:
        lower evader first), at most ``limit``."""
        rows = [e for e in range(len(sightings))
                if math.isfinite(sightings[e][4]) and t_state - sightings[e][4] < self.target_memory]
        rows.sort(key=lambda e: (-sightings[e][4], e))
        return rows[:max(0, limit)]

    def pack_into(self, buf, sender: int, epoch: int, seq: int, t_tx: float, t_state: float,
                  x: float, y: float, vx: float, vy: float, sightings=()) -> tuple[int, bool]:
        """Write a message into ``buf``; ``sightings``: (evader, x, y, vx, vy, t_seen) each, at most
        ``MAX_SIGHTINGS``. Returns (size, clamped). Raises RadioMsgError for a non-finite time."""
        if len(sightings) > MAX_SIGHTINGS:
            raise RadioMsgError("size", f"{len(sightings)} sightings: at most {MAX_SIGHTINGS} fit in "
                                        f"{P2P_MAX_DATA_SIZE} B (select them with Codec.select)")
        if not (math.isfinite(t_tx) and math.isfinite(t_state)):
            raise RadioMsgError("non-finite", f"t_tx={t_tx!r}, t_state={t_state!r}: times must be finite")
        clamp = [False]
        off = HEADER.size
        for (e, sx, sy, svx, svy, ts) in sightings:
            age = (t_state - ts) * self._age_k
            if not math.isfinite(age) or age >= AGE_MAX + 0.5 or age <= -0.5:
                a, clamp[0] = (0 if age <= -0.5 else AGE_MAX), True
            else:
                a = _round(age) if age > 0 else 0
            SIGHTING.pack_into(buf, off, int(e), a, self._q(sx, self._pos_k, clamp), self._q(sy, self._pos_k, clamp),
                               self._q(svx, self._vel_k, clamp), self._q(svy, self._vel_k, clamp))
            off += SIGHTING.size
        state = (self._q(x, self._pos_k, clamp), self._q(y, self._pos_k, clamp),
                 self._q(vx, self._vel_k, clamp), self._q(vy, self._vel_k, clamp))
        HEADER.pack_into(buf, 0, MAGIC, VERSION, self.hash32, sender, self.roles[sender], len(sightings),
                         FLAG_CLAMPED if clamp[0] else 0, epoch & 0xFFFF, seq & 0xFFFF,
                         round(t_tx * 1000.0) % TIME_MOD, round(t_state * 1000.0) % TIME_MOD, *state)
        return off, clamp[0]

    def pack(self, *args, **kw) -> bytes:
        buf = bytearray(P2P_MAX_DATA_SIZE)
        n, _ = self.pack_into(buf, *args, **kw)
        return bytes(buf[:n])

    @staticmethod
    def _q(v: float, k: float, clamp: list) -> int:
        if v != v:
            return NAN_RAW
        r = v * k
        if r >= I16_MAX + 0.5 or r <= -I16_MAX - 0.5:
            clamp[0] = True
            return I16_MAX if r > 0 else -I16_MAX
        return _round(r)

    # ------------------------------------------------------------------------------------------ parse
    def check_header(self, data) -> tuple:
        """The header tuple of a message of this spec; raises RadioMsgError naming why not."""
        size = len(data)
        if size < HEADER.size:
            raise RadioMsgError("size", f"{size} B is shorter than the {HEADER.size} B header")
        h = HEADER.unpack_from(data, 0)
        magic, version, hash32, sender, role, n_s = h[:6]
        if magic != MAGIC:
            raise RadioMsgError("magic", f"magic 0x{magic:02x}, expected 0x{MAGIC:02x}: not a swarm message")
        if version != VERSION:
            raise RadioMsgError("version", f"message version {version}, this drone speaks {VERSION}: "
                                           "fly the same release on every drone")
        if hash32 != self.hash32:
            raise RadioMsgError("spec", f"sender {sender} flies spec {hash32:08x}..., this drone "
                                        f"{self.hash32:08x}...: export every drone's model from one spec")
        if sender >= self.n_agents:
            raise RadioMsgError("sender", f"sender {sender}: the spec has {self.n_agents} agents")
        if role != self.roles[sender]:
            raise RadioMsgError("role", f"sender {sender} says role {role}, the spec gives {self.roles[sender]}")
        if n_s > min(self.n_evaders, MAX_SIGHTINGS) or size < message_size(n_s):
            raise RadioMsgError("size", f"{size} B announcing {n_s} sightings ({message_size(n_s)} B, at most "
                                        f"{min(self.n_evaders, MAX_SIGHTINGS)} sightings)")
        if NAN_RAW in h[11:15]:
            raise RadioMsgError("non-finite", f"sender {sender}: non-finite position or velocity")
        return h

    def unpack(self, data, now: float = 0.0) -> Message:
        """Parse a message (exactly ``message_size(n_sight)`` bytes) read at ``now`` [s] (for unwrap_ms)."""
        h = self.check_header(data)
        if len(data) != message_size(h[5]):
            raise RadioMsgError("size", f"{len(data)} B for {h[5]} sightings, expected {message_size(h[5])} B")
        t_state, sights = self.values(data, h, now)
        t_tx = unwrap_ms(h[9], now)
        pm, vm = self._pos_m, self._vel_m
        return Message(h[3], h[4], h[7], h[8], t_tx, t_state, h[11] * pm / 1000.0, h[12] * pm / 1000.0,
                       h[13] * vm / 1000.0, h[14] * vm / 1000.0, sights, bool(h[6] & FLAG_CLAMPED))

    def values(self, data, h: tuple, now: float) -> tuple[float, tuple]:
        """t_state [s] and the sightings (evader, x, y, vx, vy, t_seen) of a checked message."""
        t_state = unwrap_ms(h[10], now)
        pm, vm = self._pos_m, self._vel_m
        sights = []
        for j in range(h[5]):
            e, a, sx, sy, svx, svy = SIGHTING.unpack_from(data, HEADER.size + j * SIGHTING.size)
            if e >= self.n_evaders:
                raise RadioMsgError("target", f"sighting of evader {e}: the spec has {self.n_evaders}")
            if NAN_RAW in (sx, sy, svx, svy):
                raise RadioMsgError("non-finite", f"sighting of evader {e}: non-finite position or velocity")
            sights.append((e, sx * pm / 1000.0, sy * pm / 1000.0, svx * vm / 1000.0, svy * vm / 1000.0,
                           (round(t_state * 1000.0) - a * round(self.scales.age_lsb * 1000)) / 1000.0))
        return t_state, tuple(sights)


__all__ = ["MAGIC", "VERSION", "P2P_MAX_DATA_SIZE", "FLAG_CLAMPED", "NAN_RAW", "MAX_SIGHTINGS", "HEADER",
           "SIGHTING", "HEADER_FIELDS", "SIGHTING_FIELDS", "Field", "Scales", "Codec", "Message", "RadioMsgError",
           "message_size", "spec_hash32", "unwrap_ms"]
