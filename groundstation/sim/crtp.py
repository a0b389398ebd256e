"""CRTP wire format as the Crazyflie firmware speaks it: ports, channels, commands, and the typed
tables of contents (log and param) with their CRCs. Formats follow cflib 0.1.34 (``crazyflie/log.py``,
``param.py``, ``toc.py``, ``commander.py``, ``high_level_commander.py``, ``localization.py``,
``supervisor.py``, ``platformservice.py``) and crazyflie-firmware (``log.c``, ``param_logic.c``,
``crtp_commander_generic.c``, ``crtp_commander_high_level.c``, ``crtp_localization_service.c``,
``platformservice.c``, ``crtp_supervisor.c``, ``crtpservice.c``).

Over UDP (the SITL convention cflib's ``udpdriver`` follows) one datagram is one packet: the header byte
``port << 4 | channel`` and up to 30 payload bytes, no checksum.
"""
from __future__ import annotations

import enum
import struct
import zlib
from dataclasses import dataclass
from typing import Callable, Sequence

MAX_PAYLOAD = 30
PROTOCOL_VERSION = 12
"""CRTP protocol version this simulator reports (12: supervisor port, param misc V2)."""
FIRMWARE_VERSION = "2025.12+swarmpursuit-sim"
DEVICE_TYPE = "CF21"


class Port(enum.IntEnum):
    CONSOLE = 0x0
    PARAM = 0x2
    COMMANDER = 0x3
    MEM = 0x4
    LOGGING = 0x5
    LOCALIZATION = 0x6
    COMMANDER_GENERIC = 0x7
    SETPOINT_HL = 0x8
    SUPERVISOR = 0x9
    PLATFORM = 0xD
    LINKCTRL = 0xF


def header(port: int, channel: int) -> int:
    """CRTP_HEADER(port, channel) as the firmware builds it."""
    return ((port & 0x0F) << 4) | (channel & 0x03)


def packet(port: int, channel: int, payload: bytes) -> bytes:
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"CRTP payload of {len(payload)} bytes exceeds {MAX_PAYLOAD}")
    return bytes((header(port, channel),)) + payload


def split(datagram: bytes) -> tuple[int, int, bytes]:
    """(port, channel, payload) of one datagram."""
    h = datagram[0]
    return (h >> 4) & 0x0F, h & 0x03, datagram[1:]


# Log and param element types: the ids the firmware puts in its TOCs, with struct formats.
class LogType(enum.IntEnum):
    UINT8 = 0x01
    UINT16 = 0x02
    UINT32 = 0x03
    INT8 = 0x04
    INT16 = 0x05
    INT32 = 0x06
    FLOAT = 0x07
    FP16 = 0x08


LOG_FORMAT = {LogType.UINT8: "<B", LogType.UINT16: "<H", LogType.UINT32: "<L", LogType.INT8: "<b",
              LogType.INT16: "<h", LogType.INT32: "<i", LogType.FLOAT: "<f", LogType.FP16: "<e"}


class ParamType(enum.IntEnum):
    INT8 = 0x00
    INT16 = 0x01
    INT32 = 0x02
    INT64 = 0x03
    FP16 = 0x05
    FLOAT = 0x06
    DOUBLE = 0x07
    UINT8 = 0x08
    UINT16 = 0x09
    UINT32 = 0x0A
    UINT64 = 0x0B


PARAM_FORMAT = {ParamType.INT8: "<b", ParamType.INT16: "<h", ParamType.INT32: "<i", ParamType.INT64: "<q",
                ParamType.FP16: "<e", ParamType.FLOAT: "<f", ParamType.DOUBLE: "<d", ParamType.UINT8: "<B",
                ParamType.UINT16: "<H", ParamType.UINT32: "<L", ParamType.UINT64: "<Q"}
PARAM_READ_ONLY = 0x40

TOC_CMD_ITEM_V2 = 2
TOC_CMD_INFO_V2 = 3

LOG_MAX_BLOCKS = 16
LOG_MAX_OPS = 128
LOG_MAX_BLOCK_BYTES = 26


@dataclass(frozen=True)
class LogVar:
    group: str
    name: str
    type: LogType
    read: Callable[[dict], float]
    """Picks this variable's value from the per-tick snapshot the simulator builds."""

    @property
    def full_name(self) -> str:
        return f"{self.group}.{self.name}"


@dataclass(frozen=True)
class ParamVar:
    group: str
    name: str
    type: ParamType
    default: float
    read_only: bool = False

    @property
    def full_name(self) -> str:
        return f"{self.group}.{self.name}"

    @property
    def type_byte(self) -> int:
        return int(self.type) | (PARAM_READ_ONLY if self.read_only else 0)


def toc_item_payload(ident: int, type_byte: int, group: str, name: str) -> bytes:
    """TOC item V2 reply: command, 16-bit id, type, group and name as NUL-terminated strings."""
    body = struct.pack("<BHB", TOC_CMD_ITEM_V2, ident, type_byte) + group.encode() + b"\0" + name.encode() + b"\0"
    if len(body) > MAX_PAYLOAD:
        raise ValueError(f"TOC entry {group}.{name} is too long for one CRTP packet")
    return body


def toc_crc(entries: Sequence[tuple[int, str, str]]) -> int:
    """A CRC over (type, group, name) of every entry: cflib caches TOCs by it, so it changes with the TOC."""
    blob = b"".join(bytes((t,)) + g.encode() + b"\0" + n.encode() + b"\0" for t, g, n in entries)
    return zlib.crc32(blob) & 0xFFFFFFFF


def encode_value(fmt: str, value: float) -> bytes:
    if fmt[-1] in "efd":
        return struct.pack(fmt, float(value))
    lo, hi = _INT_RANGE[fmt[-1]]
    return struct.pack(fmt, min(max(int(round(value)), lo), hi))


_INT_RANGE = {"b": (-2**7, 2**7 - 1), "B": (0, 2**8 - 1), "h": (-2**15, 2**15 - 1), "H": (0, 2**16 - 1),
              "i": (-2**31, 2**31 - 1), "l": (-2**31, 2**31 - 1), "L": (0, 2**32 - 1),
              "q": (-2**63, 2**63 - 1), "Q": (0, 2**64 - 1)}
