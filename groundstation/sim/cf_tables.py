"""The simulated Crazyflie's tables of contents: the log variables and parameters cflib downloads on connect
(``SimCrazyflie`` serves them; their CRCs let cflib's TOC cache skip the download on a reconnect)."""
from __future__ import annotations

from groundstation.sim import crtp
from groundstation.sim.crtp import LogType, LogVar, ParamType, ParamVar

# Log variables, in TOC order. Each reads from the snapshot built by ``SimCrazyflie._snapshot``.
LOG_TOC: tuple[LogVar, ...] = (
    LogVar("stateEstimate", "x", LogType.FLOAT, lambda s: s["x"]),
    LogVar("stateEstimate", "y", LogType.FLOAT, lambda s: s["y"]),
    LogVar("stateEstimate", "z", LogType.FLOAT, lambda s: s["z"]),
    LogVar("stateEstimate", "vx", LogType.FLOAT, lambda s: s["vx"]),
    LogVar("stateEstimate", "vy", LogType.FLOAT, lambda s: s["vy"]),
    LogVar("stateEstimate", "vz", LogType.FLOAT, lambda s: s["vz"]),
    LogVar("stateEstimate", "yaw", LogType.FLOAT, lambda s: s["yaw"]),
    LogVar("pm", "vbat", LogType.FLOAT, lambda s: s["vbat"]),
    LogVar("pm", "state", LogType.INT8, lambda s: s["pm_state"]),
    LogVar("radio", "rssi", LogType.UINT8, lambda s: s["rssi"]),
    LogVar("kalman", "varPX", LogType.FLOAT, lambda s: s["varPX"]),
    LogVar("kalman", "varPY", LogType.FLOAT, lambda s: s["varPY"]),
    LogVar("kalman", "varPZ", LogType.FLOAT, lambda s: s["varPZ"]),
    LogVar("supervisor", "info", LogType.UINT16, lambda s: s["info"]),
    LogVar("sys", "canfly", LogType.UINT8, lambda s: s["canfly"]),
    LogVar("sys", "isFlying", LogType.UINT8, lambda s: s["isFlying"]),
)

PARAM_TOC: tuple[ParamVar, ...] = (
    ParamVar("kalman", "resetEstimation", ParamType.UINT8, 0),
    ParamVar("stabilizer", "estimator", ParamType.UINT8, 2),
    ParamVar("stabilizer", "controller", ParamType.UINT8, 1),
    ParamVar("stabilizer", "stop", ParamType.UINT8, 0),
    ParamVar("commander", "enHighLevel", ParamType.UINT8, 1),
    ParamVar("hlCommander", "vtoff", ParamType.FLOAT, 0.5),
    ParamVar("hlCommander", "vland", ParamType.FLOAT, 0.2),
    ParamVar("locSrv", "extPosStdDev", ParamType.FLOAT, 0.01),
    ParamVar("pm", "lowVoltage", ParamType.FLOAT, 3.2),
    ParamVar("deck", "bcLoco", ParamType.UINT8, 1, read_only=True),
    ParamVar("firmware", "modified", ParamType.UINT8, 1, read_only=True),
)

LOG_TOC_CRC = crtp.toc_crc([(int(v.type), v.group, v.name) for v in LOG_TOC])
PARAM_TOC_CRC = crtp.toc_crc([(v.type_byte, v.group, v.name) for v in PARAM_TOC])
PARAM_INDEX = {v.full_name: i for i, v in enumerate(PARAM_TOC)}
