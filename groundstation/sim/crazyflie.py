"""A simulated Crazyflie that answers CRTP over UDP the way the firmware does, so that unmodified cflib
(``udp://host:port``; ``SyncCrazyflie``, ``SyncLogger``, ``Commander``, ``HighLevelCommander``,
``Localization``, ``Supervisor``, ``Swarm``) connects, logs, flies and lands it like a CrazySim SITL.

``SimCrazyflie`` is the protocol: bytes in, bytes out, explicit time, no sockets. ``SimSwarm``
(``groundstation/sim/swarm.py``) runs a batch of them behind UDP sockets.

Implemented services (port: what):

* link control (15): echo (ch 0), source with the "Bitcraze Crazyflie" magic (ch 1), sink (ch 2), null;
* platform (13): protocol version, firmware version string, device type;
* log (5): TOC v2, create/append v2 (and v1), start, stop, delete, reset, periodic data blocks;
* param (2): TOC v2, read, write (echoed as the firmware does), set-by-name, default value v2;
* memory (4): number of memories (none);
* generic commander (7): stop, position, velocity-world, hover, z-distance; notify-setpoint-stop (ch 1);
* legacy commander (3): roll/pitch/yawrate/thrust, where thrust 0 (what cflib sends on close) is a stop;
* high-level commander (8): group mask, takeoff, land (v1 and v2), go_to (v1 and v2), stop;
* localization (6): external position (ch 0); emergency stop and its watchdog (ch 1);
* supervisor (9): state bitfield and single bits (ch 0), arm, crash recovery, emergency stop and its watchdog
  (ch 1) (``crtp_supervisor.c``).
"""
from __future__ import annotations

import logging
import math
import struct
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from groundstation.sim import crtp
from groundstation.sim.cf_tables import LOG_TOC, LOG_TOC_CRC, PARAM_INDEX, PARAM_TOC, PARAM_TOC_CRC
from groundstation.sim.crtp import LogType, LogVar, Port
from groundstation.sim.firmware import Firmware, Mode
from groundstation.sim.flight_model import QuadBatch

logger = logging.getLogger(__name__)

LINK_MAGIC = b"Bitcraze Crazyflie"
RSSI_DBM = 35
"""What radio.rssi reports over UDP: a good radio link (-35 dBm, logged as 35)."""

# errno values the firmware answers log commands with
ENOENT, E2BIG, ENOMEM, ENOEXEC, EEXIST = 2, 7, 12, 8, 17


@dataclass
class LogBlock:
    ident: int
    ops: list[tuple[LogVar, str]] = field(default_factory=list)
    """(variable, struct format it is fetched as)."""
    period_s: float = 0.0
    next_due: float = math.inf
    started: bool = False

    def size(self) -> int:
        return sum(struct.calcsize(fmt) for _, fmt in self.ops)


class SimCrazyflie:
    """The CRTP side of one simulated drone: decodes requests, drives its ``Firmware``, encodes replies.

    Not thread-safe; ``SimSwarm`` serialises every call under one lock.
    """

    def __init__(self, index: int, model: QuadBatch, boot_time: float, latency_probe: bool = False) -> None:
        self.index = index
        self.model = model
        self.boot_time = boot_time
        self.firmware = Firmware(model.params, boot_time)
        self.params = {v.full_name: v.default for v in PARAM_TOC}
        self.blocks: dict[int, LogBlock] = {}
        self.latency_probe = latency_probe
        self.latency_samples: list[float] = []
        """Measurement-to-setpoint delays [s] seen with the latency probe (see ``note_log_sent``)."""
        self._log_sent: OrderedDict[int, float] = OrderedDict()
        self.rx_packets = 0
        self.tx_packets = 0

    # ---- time and state -----------------------------------------------------------------------------

    def timestamp_ms(self, now: float) -> int:
        """The 24-bit millisecond tick the firmware stamps log data with."""
        return int((now - self.boot_time) * 1000.0) & 0xFFFFFF

    def _snapshot(self, now: float) -> dict:
        """The values log blocks read at ``now``, each group computed only when a block asks for it (the
        simulator answers every drone's blocks at 50-100 Hz)."""
        return _Snapshot(self, now)

    def _snapshot_group(self, group: str, now: float) -> dict:
        i, fw, m = self.index, self.firmware, self.model
        if group == "pos":
            pos = m.estimated_position(i, fw.extpos_fresh(now), fw.extpos, fw.extpos_age(now))
            return {"x": pos[0], "y": pos[1], "z": pos[2], "yaw": m.yaw_deg[i]}
        if group == "vel":
            vel = m.estimated_velocity(i)
            return {"vx": vel[0], "vy": vel[1], "vz": vel[2]}
        if group == "var":
            var = m.position_variance(i)
            return {"varPX": var[0], "varPY": var[1], "varPZ": var[2]}
        if group == "pm":
            vbat = m.battery_voltage(i, fw.motors_on)
            return {"vbat": vbat, "pm_state": 3 if vbat < self.params["pm.lowVoltage"] else 0, "rssi": RSSI_DBM}
        info = fw.supervisor_info()
        return {"info": info, "canfly": int(bool(info & 0x8)), "isFlying": int(bool(info & 0x10))}

    # ---- inbound -----------------------------------------------------------------------------------

    def handle(self, datagram: bytes, now: float) -> list[bytes]:
        """Answer one datagram; returns the datagrams to send back (possibly none)."""
        if not datagram:
            return []
        self.rx_packets += 1
        port, channel, data = crtp.split(datagram)
        handler = _HANDLERS.get(port)
        if handler is None:
            logger.debug("drone %d: no service on port %d", self.index, port)
            return []
        try:
            return handler(self, channel, bytes(data), now)
        except (struct.error, IndexError, ValueError) as exc:
            logger.warning("drone %d: malformed packet on port %d ch %d (%s): %s", self.index, port, channel,
                           exc, datagram.hex())
            return []

    def _linkctrl(self, channel: int, data: bytes, now: float) -> list[bytes]:
        if channel == 0:  # echo
            return [crtp.packet(Port.LINKCTRL, 0, data)]
        if channel == 1:  # source: the magic string, padded to a full packet
            return [crtp.packet(Port.LINKCTRL, 1, LINK_MAGIC.ljust(crtp.MAX_PAYLOAD, b"\0"))]
        if channel == 3 and not data:  # null packet (the UDP driver's scan probe)
            return [crtp.packet(Port.LINKCTRL, 3, b"")]
        return []  # sink

    def _platform(self, channel: int, data: bytes, now: float) -> list[bytes]:
        if channel == 1 and data:  # version commands
            cmd = data[0]
            if cmd == 0:
                return [crtp.packet(Port.PLATFORM, 1, bytes((0, crtp.PROTOCOL_VERSION)))]
            if cmd == 1:
                return [crtp.packet(Port.PLATFORM, 1, bytes((1,)) + crtp.FIRMWARE_VERSION.encode()[:29])]
            if cmd == 2:
                return [crtp.packet(Port.PLATFORM, 1, bytes((2,)) + crtp.DEVICE_TYPE.encode())]
        if channel == 0 and data:  # platform commands
            if data[0] == 1 and len(data) > 1:  # legacy arming request
                self.firmware.arm(bool(data[1]))
        return []

    def _log(self, channel: int, data: bytes, now: float) -> list[bytes]:
        if channel == 0:
            return self._toc(Port.LOGGING, data, [(int(v.type), v.group, v.name) for v in LOG_TOC], LOG_TOC_CRC,
                             extra=bytes((crtp.LOG_MAX_BLOCKS, crtp.LOG_MAX_OPS)))
        if channel != 1 or not data:
            return []
        cmd = data[0]
        ident = data[1] if len(data) > 1 else 0
        status = self._log_control(cmd, ident, data[2:], now)
        if status is None:
            return []
        return [crtp.packet(Port.LOGGING, 1, bytes((cmd, ident, status)))]

    def _log_control(self, cmd: int, ident: int, body: bytes, now: float) -> int | None:
        if cmd in (0, 6):  # create block (v1, v2)
            if ident in self.blocks:
                return EEXIST
            if len(self.blocks) >= crtp.LOG_MAX_BLOCKS:
                return ENOMEM
            block = LogBlock(ident)
            status = self._append_ops(block, body, v2=(cmd == 6))
            if status == 0:
                self.blocks[ident] = block
            return status
        if cmd in (1, 7):  # append (v1, v2)
            block = self.blocks.get(ident)
            return ENOENT if block is None else self._append_ops(block, body, v2=(cmd == 7))
        if cmd == 2:  # delete
            return 0 if self.blocks.pop(ident, None) is not None else ENOENT
        if cmd == 3:  # start: period in units of 10 ms
            block = self.blocks.get(ident)
            if block is None:
                return ENOENT
            block.period_s = max(body[0], 1) * 0.010 if body else 0.1
            block.started, block.next_due = True, now
            return 0
        if cmd == 4:  # stop
            block = self.blocks.get(ident)
            if block is None:
                return ENOENT
            block.started, block.next_due = False, math.inf
            return 0
        if cmd == 5:  # reset: delete every block
            self.blocks.clear()
            return 0
        return ENOEXEC

    def _append_ops(self, block: LogBlock, body: bytes, v2: bool) -> int:
        step = 3 if v2 else 2
        ops = []
        for k in range(0, len(body) - step + 1, step):
            type_byte = body[k]
            ident = struct.unpack_from("<H", body, k + 1)[0] if v2 else body[k + 1]
            if ident >= len(LOG_TOC):
                return ENOENT  # raw memory logging is not simulated
            fetch = LogType(type_byte & 0x0F)
            ops.append((LOG_TOC[ident], crtp.LOG_FORMAT[fetch]))
        if len(block.ops) + len(ops) > crtp.LOG_MAX_OPS:
            return ENOMEM
        trial = LogBlock(block.ident, block.ops + ops)
        if trial.size() > crtp.LOG_MAX_BLOCK_BYTES:
            return E2BIG
        block.ops.extend(ops)
        return 0

    def _toc(self, port: int, data: bytes, entries: list[tuple[int, str, str]], crc: int,
             extra: bytes = b"") -> list[bytes]:
        if not data:
            return []
        if data[0] == crtp.TOC_CMD_INFO_V2:
            return [crtp.packet(port, 0, struct.pack("<BHL", crtp.TOC_CMD_INFO_V2, len(entries), crc) + extra)]
        if data[0] == crtp.TOC_CMD_ITEM_V2:
            ident = struct.unpack_from("<H", data, 1)[0]
            if ident >= len(entries):
                return [crtp.packet(port, 0, bytes((crtp.TOC_CMD_ITEM_V2,)))]
            t, g, n = entries[ident]
            return [crtp.packet(port, 0, crtp.toc_item_payload(ident, t, g, n))]
        if data[0] in (0, 1):  # TOC v1: not supported by current firmware either, report an empty TOC
            return [crtp.packet(port, 0, bytes((data[0], 0)) + bytes(4))]
        return []

    def _param(self, channel: int, data: bytes, now: float) -> list[bytes]:
        if channel == 0:
            return self._toc(Port.PARAM, data, [(v.type_byte, v.group, v.name) for v in PARAM_TOC], PARAM_TOC_CRC)
        if channel == 1:  # read: id -> id, status, value
            ident = struct.unpack_from("<H", data)[0]
            if ident >= len(PARAM_TOC):
                return [crtp.packet(Port.PARAM, 1, struct.pack("<HB", ident, ENOENT))]
            var = PARAM_TOC[ident]
            value = crtp.encode_value(crtp.PARAM_FORMAT[var.type], self.params[var.full_name])
            return [crtp.packet(Port.PARAM, 1, struct.pack("<HB", ident, 0) + value)]
        if channel == 2:  # write: id, value -> echoed back
            ident = struct.unpack_from("<H", data)[0]
            if ident >= len(PARAM_TOC) or PARAM_TOC[ident].read_only:
                return []
            var = PARAM_TOC[ident]
            (value,) = struct.unpack(crtp.PARAM_FORMAT[var.type], data[2:])
            self._set_param(var.full_name, value, now)
            return [crtp.packet(Port.PARAM, 2, data)]
        if channel == 3 and data:
            return self._param_misc(data, now)
        return []

    def _param_misc(self, data: bytes, now: float) -> list[bytes]:
        cmd = data[0]
        if cmd == 0:  # set by name: group\0name\0 type value
            group_end = data.index(b"\0", 1)
            name_end = data.index(b"\0", group_end + 1)
            full = data[1:group_end].decode() + "." + data[group_end + 1:name_end].decode()
            var = PARAM_TOC[PARAM_INDEX[full]] if full in PARAM_INDEX else None
            if var is None or var.read_only or data[name_end + 1] != int(var.type):
                return [crtp.packet(Port.PARAM, 3, data[:name_end + 1] + bytes((ENOENT,)))]
            (value,) = struct.unpack(crtp.PARAM_FORMAT[var.type], data[name_end + 2:])
            self._set_param(full, value, now)
            return [crtp.packet(Port.PARAM, 3, data[:name_end + 1] + bytes((0,)))]
        if cmd in (7, 8):  # get extended type / default value (v2): id -> status [, value]
            ident = struct.unpack_from("<H", data, 1)[0]
            if ident >= len(PARAM_TOC):
                return [crtp.packet(Port.PARAM, 3, struct.pack("<BHB", cmd, ident, ENOENT))]
            var = PARAM_TOC[ident]
            tail = bytes((0,)) if cmd == 7 else crtp.encode_value(crtp.PARAM_FORMAT[var.type], var.default)
            return [crtp.packet(Port.PARAM, 3, struct.pack("<BHB", cmd, ident, 0) + tail)]
        return []

    def _set_param(self, full_name: str, value: float, now: float) -> None:
        self.params[full_name] = value
        if full_name == "kalman.resetEstimation" and value:
            self.model.reset_estimate_error(self.index)
            self.params[full_name] = 0  # the estimator clears the flag once it has reset
        elif full_name == "stabilizer.stop" and value:
            self.firmware.emergency_stop(now)

    def _mem(self, channel: int, data: bytes, now: float) -> list[bytes]:
        if channel == 0 and data and data[0] == 1:  # number of memories
            return [crtp.packet(Port.MEM, 0, bytes((1, 0)))]
        if channel == 0 and data and data[0] == 2 and len(data) > 1:  # details of a memory that is not there
            return [crtp.packet(Port.MEM, 0, bytes((2, data[1])))]
        return []

    def _commander_generic(self, channel: int, data: bytes, now: float) -> list[bytes]:
        fw = self.firmware
        if channel == 1:  # meta commands
            if data and data[0] == 0:
                struct.unpack_from("<I", data, 1)  # remain-valid [ms]: ignored by current firmware
                fw.notify_setpoint_stop(now)
            return []
        if channel != 0 or not data:
            return []
        kind = data[0]
        if kind == 0:
            fw.stream_stop(now)
        elif kind == 7:
            fw.stream(now, Mode.POSITION, struct.unpack_from("<ffff", data, 1))
        elif kind == 8:
            target = struct.unpack_from("<ffff", data, 1)
            self._probe_latency(target[3], now)
            fw.stream(now, Mode.VELOCITY, target)
        elif kind == 10:
            fw.stream(now, Mode.HOVER, struct.unpack_from("<ffff", data, 1))
        elif kind == 9:  # z-distance: roll, pitch, yawrate, z -> hold position horizontally
            _, _, yaw_rate, z = struct.unpack_from("<ffff", data, 1)
            fw.stream(now, Mode.HOVER, (0.0, 0.0, yaw_rate, z))
        else:
            logger.warning("drone %d: generic setpoint type %d is not simulated", self.index, kind)
        return []

    def _commander_rpyt(self, channel: int, data: bytes, now: float) -> list[bytes]:
        _, _, _, thrust = struct.unpack("<fffH", data[:14])
        if thrust == 0:  # crtp_commander_rpyt.c: zero thrust, taken at CRTP priority (motors off)
            self.firmware.stream_stop(now)
        else:
            logger.warning("drone %d: attitude/thrust setpoints are not simulated", self.index)
        return []

    def _high_level(self, channel: int, data: bytes, now: float) -> list[bytes]:
        fw, m, i = self.firmware, self.model, self.index
        pos, yaw = m.pos[i].copy(), float(m.yaw_deg[i])
        cmd = data[0]
        if cmd == 0:
            fw.group_mask = data[1]
        elif cmd in (1, 2):  # takeoff / land v1: group, height, duration
            group, height, duration = struct.unpack_from("<Bff", data, 1)
            action = fw.hl_takeoff if cmd == 1 else fw.hl_land
            action(now, group, pos, yaw, height, duration, None)
        elif cmd in (7, 8):  # takeoff / land v2: group, height, yaw [rad], use current yaw, duration
            group, height, yaw_rad, use_current, duration = struct.unpack_from("<Bff?f", data, 1)
            action = fw.hl_takeoff if cmd == 7 else fw.hl_land
            action(now, group, pos, yaw, height, duration, None if use_current else math.degrees(yaw_rad))
        elif cmd == 3:
            fw.hl_stop(now, data[1])
        elif cmd == 4:  # go_to v1: group, relative, x, y, z, yaw [rad], duration
            group, relative, x, y, z, yaw_rad, duration = struct.unpack_from("<BBfffff", data, 1)
            fw.hl_go_to(now, group, pos, yaw, (x, y, z), math.degrees(yaw_rad), duration, bool(relative), False)
        elif cmd == 12:  # go_to v2: group, relative, linear, x, y, z, yaw [rad], duration
            group, relative, linear, x, y, z, yaw_rad, duration = struct.unpack_from("<BBBfffff", data, 1)
            fw.hl_go_to(now, group, pos, yaw, (x, y, z), math.degrees(yaw_rad), duration, bool(relative),
                        bool(linear))
        else:
            logger.warning("drone %d: high-level command %d is not simulated", self.index, cmd)
        return []

    def _localization(self, channel: int, data: bytes, now: float) -> list[bytes]:
        if channel == 0:
            self.firmware.set_extpos(now, struct.unpack_from("<fff", data))
        elif channel == 1 and data:
            if data[0] == 3:
                self.firmware.emergency_stop(now)
            elif data[0] == 4:
                self.firmware.emergency_stop_watchdog(now)
            elif data[0] == 8:  # external pose: position and quaternion
                self.firmware.set_extpos(now, struct.unpack_from("<fff", data, 1))
        return []

    def _supervisor(self, channel: int, data: bytes, now: float) -> list[bytes]:
        if not data:
            return []
        cmd, fw = data[0], self.firmware
        if channel == 0:
            info = fw.supervisor_info()
            if cmd == 0x0C:  # the whole state bitfield
                return [crtp.packet(Port.SUPERVISOR, 0, struct.pack("<BH", 0x80 | cmd, info))]
            if 0x01 <= cmd <= 0x0B:  # one bit, CMD_CAN_BE_ARMED (bit 0) ... CMD_HL_CONTROL_DISABLED (bit 10)
                return [crtp.packet(Port.SUPERVISOR, 0, bytes((0x80 | cmd, (info >> (cmd - 1)) & 1)))]
            return []
        if channel == 1:
            if cmd == 0x01:
                success, armed = fw.arm(bool(data[1]) if len(data) > 1 else True)
                return [crtp.packet(Port.SUPERVISOR, 1, bytes((0x81, success, armed)))]
            if cmd == 0x02:  # crash recovery: a simulated collision locks instead (reboot), nothing to recover
                return [crtp.packet(Port.SUPERVISOR, 1, bytes((0x82, 1, 1)))]
            if cmd == 0x03:
                fw.emergency_stop(now)
            elif cmd == 0x04:
                fw.emergency_stop_watchdog(now)
        return []

    # ---- outbound ----------------------------------------------------------------------------------

    def next_log_due(self) -> float:
        return min((b.next_due for b in self.blocks.values()), default=math.inf)

    def due_log_packets(self, now: float) -> list[tuple[bytes, int]]:
        """Log data packets due at ``now`` with their timestamps; schedules the next ones."""
        due = [b for b in self.blocks.values() if b.started and b.next_due <= now]
        if not due:
            return []
        snap = self._snapshot(now)
        ts = self.timestamp_ms(now)
        out = []
        for block in due:
            values = b"".join(crtp.encode_value(fmt, var.read(snap)) for var, fmt in block.ops)
            out.append((crtp.packet(Port.LOGGING, 2, bytes((block.ident,)) + struct.pack("<L", ts)[:3] + values), ts))
            block.next_due += block.period_s
            if block.next_due <= now:  # fell behind (a stalled host): skip rather than burst
                block.next_due = now + block.period_s
        return out

    def note_log_sent(self, ts: int, t_sent: float) -> None:
        """Latency probe: remember when the measurement stamped ``ts`` left, keyed by ``ts mod 2^16``."""
        if not self.latency_probe:
            return
        self._log_sent.setdefault(ts & 0xFFFF, t_sent)
        while len(self._log_sent) > 512:
            self._log_sent.popitem(last=False)

    def _probe_latency(self, yaw_rate_deg: float, now: float) -> None:
        """With the probe on, a velocity setpoint's yaw rate [rad/s] carries the timestamp (mod 2^16) of the
        measurement it answers; the delay from that measurement leaving to this setpoint arriving is recorded."""
        if not self.latency_probe:
            return
        tag = int(round(math.radians(yaw_rate_deg)))
        t_sent = self._log_sent.pop(tag, None)
        if t_sent is not None:
            self.latency_samples.append(now - t_sent)

    def reboot(self, now: float) -> None:
        """Power cycle: a fresh firmware (clears a lock and the emergency-stop watchdog) and a fresh estimator
        where the drone now lies; forgets log blocks."""
        self.firmware = Firmware(self.model.params, now)
        self.model.reset_estimate_error(self.index)
        self.boot_time = now
        self.blocks.clear()
        self.params = {v.full_name: v.default for v in PARAM_TOC}

    def control(self, now: float) -> tuple[np.ndarray, float, bool, bool]:
        i, m = self.index, self.model
        return self.firmware.control(now, m.pos[i], m.vel[i], float(m.yaw_deg[i]))


_SNAPSHOT_GROUP = {"x": "pos", "y": "pos", "z": "pos", "yaw": "pos", "vx": "vel", "vy": "vel", "vz": "vel",
                   "varPX": "var", "varPY": "var", "varPZ": "var", "vbat": "pm", "pm_state": "pm", "rssi": "pm",
                   "info": "sup", "canfly": "sup", "isFlying": "sup"}


class _Snapshot(dict):
    """One instant's log values, filled group by group on first read."""

    def __init__(self, drone: SimCrazyflie, now: float) -> None:
        super().__init__()
        self._drone, self._now = drone, now

    def __missing__(self, key: str):
        self.update(self._drone._snapshot_group(_SNAPSHOT_GROUP[key], self._now))
        return dict.__getitem__(self, key)


_HANDLERS = {
    Port.LINKCTRL: SimCrazyflie._linkctrl,
    Port.PLATFORM: SimCrazyflie._platform,
    Port.LOGGING: SimCrazyflie._log,
    Port.PARAM: SimCrazyflie._param,
    Port.MEM: SimCrazyflie._mem,
    Port.COMMANDER_GENERIC: SimCrazyflie._commander_generic,
    Port.COMMANDER: SimCrazyflie._commander_rpyt,
    Port.SETPOINT_HL: SimCrazyflie._high_level,
    Port.LOCALIZATION: SimCrazyflie._localization,
    Port.SUPERVISOR: SimCrazyflie._supervisor,
}
