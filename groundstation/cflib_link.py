"""``CflibLink``: a Crazyflie (real or simulated) through unmodified cflib.

URIs: ``radio://0/80/2M/E7E7E7E701`` (Crazyradio), ``udp://127.0.0.1:19850`` (``swarm-gs sim``, CrazySim
SITL; cflib 0.1.32+), ``usb://0``.

Telemetry comes from two log blocks: a fast one (position, velocity, ``supervisor.info``: 26 bytes, the
most one CRTP log packet carries) every ``period_ms`` and a slow one (battery, RSSI, position variance)
every ``aux_period_ms``; samples are published on the fast block. Streamed setpoints go through
``Commander``, takeoff and landing through ``HighLevelCommander``, each followed by ``notify_setpoint_stop``
(every time, retries included: a streamed setpoint has priority over the onboard planner and stops it, and
only that hand-over lets the planner's setpoints through, ``commander.c``), the emergency stop through the
supervisor port (cflib falls back to the localization port on firmware older than protocol 12).

No drone flies uncommanded: before the first command that can make it fly, the link arms the firmware's
emergency-stop watchdog and then feeds it every ``ESTOP_FEED_PERIOD_S`` from its own thread. When the ground
station dies, freezes or loses the radio, the packets stop and the firmware cuts the motors and locks within
``cf_firmware.ESTOP_WATCHDOG_S`` (1 s) in every phase, takeoff and landing included (``supervisor.c``
checkEmergencyStopWatchdog). The watchdog stays armed until the drone is rebooted: after a flight the
ground station closes its links and the drones, already landed, lock on the ground (a landed one once the
supervisor's 3 s landing timeout has passed). Reboot them before the next flight.

cflib's UDP and radio drivers do not report a silent peer: ``link_lost`` is judged from telemetry
silence (``link_loss_timeout``, default 0.25 s) and from cflib's own connection-lost callback.
"""
from __future__ import annotations

import collections
import logging
import math
import threading
import time
from pathlib import Path

import cflib.crtp
from cflib.crazyflie import Crazyflie
from cflib.crazyflie.log import LogConfig

from groundstation.cf_firmware import ESTOP_WATCHDOG_S
from groundstation.link import FlightState, Link, LinkError, LinkStats, Telemetry

logger = logging.getLogger(__name__)

FAST_VARS = ("stateEstimate.x", "stateEstimate.y", "stateEstimate.z",
             "stateEstimate.vx", "stateEstimate.vy", "stateEstimate.vz", "supervisor.info")
NOTIFY_STOP_VALID_MS = 200
"""The notify-setpoint-stop packet's remain-valid field [ms]; firmware since 2023 ignores it and hands over at
once (``crtp_commander_generic.c`` notifySetpointsStopDecoder), older firmware kept the last streamed
setpoint valid this long."""
ESTOP_FEED_PERIOD_S = ESTOP_WATCHDOG_S / 5.0
"""Interval of the emergency-stop watchdog packets [s]: five per timeout, so that lost packets or a stall of
the ground station shorter than 0.8 s do not drop the drone."""
SLOW_VARS = ("pm.vbat", "radio.rssi", "kalman.varPX", "kalman.varPY", "kalman.varPZ")

_drivers_lock = threading.Lock()
_drivers_ready = False


def init_drivers() -> None:
    """``cflib.crtp.init_drivers()`` once per process."""
    global _drivers_ready
    with _drivers_lock:
        if not _drivers_ready:
            cflib.crtp.init_drivers()
            _drivers_ready = True


def flight_state_from_supervisor(info: int) -> FlightState:
    """Decode the firmware's ``supervisor.info`` bitfield."""
    if info & (1 << 6):
        return FlightState.LOCKED
    if info & (1 << 7):
        return FlightState.CRASHED
    if info & (1 << 4):
        return FlightState.FLYING
    if info & (1 << 1):
        return FlightState.LANDED
    return FlightState.DISARMED


def _fix_for(uri: str) -> str:
    if uri.startswith("udp://"):
        return ("start the simulator (swarm-gs sim --drones N --base-port P) or CrazySim, and check the port; "
                "cflib's UDP driver waits silently when nobody answers")
    if uri.startswith("radio://"):
        return "plug in the Crazyradio, power the Crazyflie, and check channel, data rate and address"
    return "check that the Crazyflie is connected and powered"


class CflibLink(Link):
    """One Crazyflie through cflib. Opening blocks until the TOCs are in and the first telemetry arrived."""

    def __init__(self, uri: str, *, period_ms: int = 10, aux_period_ms: int = 100,
                 connect_timeout: float = 10.0, link_loss_timeout: float = 0.25,
                 rw_cache: str | None = None) -> None:
        super().__init__(uri)
        self.period_ms, self.aux_period_ms = period_ms, aux_period_ms
        self.link_loss_timeout = link_loss_timeout
        self._sent = 0
        self._received = 0
        self._closed = False
        self._watchdog: threading.Thread | None = None
        self._watchdog_stop = threading.Event()
        self._connection_lost = False
        self._slow: dict[str, float] = {}
        self._radio_quality: float | None = None
        self._arrivals: collections.deque[float] = collections.deque(maxlen=max(2, 1000 // period_ms))
        init_drivers()
        if rw_cache is not None:
            # cflib creates a missing cache folder itself, by "exists? else makedirs": links opened in parallel on
            # a machine that never had the folder (the first `make demo`) raced there and failed with
            # FileExistsError. Created here first, it exists before any link's cflib looks.
            Path(rw_cache).mkdir(parents=True, exist_ok=True)
        self._cf = Crazyflie(rw_cache=rw_cache)
        self._cf.packet_sent.add_callback(self._count_sent)
        self._cf.packet_received.add_callback(self._count_received)
        self._cf.link_statistics.link_quality_updated.add_callback(self._on_radio_quality)
        self._connect(connect_timeout)
        # cflib pings every link 10 times a second from a thread of its own, for a latency figure nothing here
        # reads (12 links: 12 threads, 240 packets/s and a numpy percentile per echo in the ground station's
        # interpreter, about 5 % of its GIL time in the demo); the radio's link quality is reported apart.
        latency = getattr(self._cf.link_statistics, "latency", None)
        if latency is not None:
            latency.stop()
        try:
            self._start_logging()
            self.wait_telemetry(connect_timeout, lambda s: not math.isnan(s.battery))
        except LinkError:
            self.close()
            raise

    # ---- connection --------------------------------------------------------------------------------

    def _connect(self, timeout: float) -> None:
        done = threading.Event()
        failure: list[str] = []

        def connected(uri: str) -> None:
            done.set()

        def failed(uri: str, message: str) -> None:
            failure.append(message)
            done.set()

        cf = self._cf
        cf.connected.add_callback(connected)
        cf.connection_failed.add_callback(failed)
        cf.connection_lost.add_callback(self._on_connection_lost)
        try:
            cf.open_link(self.uri)
            if not done.wait(timeout):
                cf.close_link()
                raise LinkError(self.uri, f"no answer within {timeout:.1f} s", _fix_for(self.uri))
            if failure:
                cf.close_link()
                raise LinkError(self.uri, f"connection failed: {failure[0].splitlines()[0]}", _fix_for(self.uri))
        finally:
            cf.connected.remove_callback(connected)
            cf.connection_failed.remove_callback(failed)

    def _start_logging(self) -> None:
        toc = self._cf.log.toc
        missing = [v for v in FAST_VARS + SLOW_VARS if toc.get_element_by_complete_name(v) is None]
        if missing:
            raise LinkError(self.uri, f"the firmware does not log {', '.join(missing)}",
                            "flash a firmware with the Kalman estimator and the supervisor (2023.06 or later)")
        self._fast = LogConfig("swarmpursuit_fast", self.period_ms)
        for name in FAST_VARS:
            self._fast.add_variable(name, "uint16_t" if name == "supervisor.info" else "float")
        self._aux = LogConfig("swarmpursuit_aux", self.aux_period_ms)
        for name in SLOW_VARS:
            self._aux.add_variable(name, "uint8_t" if name == "radio.rssi" else "float")
        for config, callback in ((self._fast, self._on_fast), (self._aux, self._on_slow)):
            try:
                self._cf.log.add_config(config)
            except (KeyError, AttributeError) as exc:
                raise LinkError(self.uri, f"log block {config.name} rejected: {exc}",
                                "use a period between 10 and 2540 ms") from exc
            config.data_received_cb.add_callback(callback)
            config.start()

    # ---- receive side (cflib's incoming thread) ----------------------------------------------------

    def _count_sent(self, pk) -> None:
        self._sent += 1

    def _count_received(self, pk) -> None:
        self._received += 1

    def _on_radio_quality(self, percent: float) -> None:
        self._radio_quality = percent / 100.0

    def _on_connection_lost(self, uri: str, message: str) -> None:
        logger.warning("%s: connection lost: %s", uri, message.splitlines()[0] if message else "")
        self._connection_lost = True

    def _on_slow(self, timestamp: int, data: dict, config: LogConfig) -> None:
        self._slow = data

    def _on_fast(self, timestamp: int, data: dict, config: LogConfig) -> None:
        now = time.monotonic()
        self._arrivals.append(now)
        slow = self._slow
        variance = None
        if "kalman.varPX" in slow:
            variance = (slow["kalman.varPX"], slow["kalman.varPY"], slow["kalman.varPZ"])
        rssi = slow.get("radio.rssi")
        self._publish(Telemetry(
            t=now,
            position=(data["stateEstimate.x"], data["stateEstimate.y"], data["stateEstimate.z"]),
            velocity=(data["stateEstimate.vx"], data["stateEstimate.vy"], data["stateEstimate.vz"]),
            battery=slow.get("pm.vbat", math.nan),
            link_quality=self._link_quality(now),
            flight_state=flight_state_from_supervisor(data["supervisor.info"]),
            position_variance=variance,
            rssi=None if rssi is None else -float(rssi),
            vehicle_time_ms=timestamp,
            planner_active=bool(data["supervisor.info"] & (1 << 8)),  # BIT_HL_CONTROL_ACTIVE
        ))

    def _link_quality(self, now: float) -> float:
        if self._radio_quality is not None:
            return self._radio_quality
        recent = sum(1 for t in self._arrivals if now - t <= 1.0)
        window = min(1.0, now - self._arrivals[0])
        expected = window * 1000.0 / self.period_ms + 1.0
        return min(1.0, recent / expected)

    @property
    def link_lost(self) -> bool:
        return self._connection_lost or super().link_lost

    # ---- commands ----------------------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise LinkError(self.uri, "the link is closed", "open a new one with open_link(uri)")

    def send_velocity(self, vx: float, vy: float, vz: float, yaw_rate: float = 0.0) -> None:
        self._check_open()
        self._arm_watchdog()
        self._cf.commander.send_velocity_world_setpoint(vx, vy, vz, math.degrees(yaw_rate))

    def send_position(self, x: float, y: float, z: float, yaw: float = 0.0) -> None:
        self._check_open()
        self._arm_watchdog()
        self._cf.commander.send_position_setpoint(x, y, z, math.degrees(yaw))

    def _hand_over_to_planner(self) -> None:
        """Sent after every high-level command, retries included. A streamed setpoint outranks the planner
        and stops it (``commander.c`` commanderSetSetpoint); until the priority is relaxed the planner's
        setpoints are dropped and the last streamed one ages into the setpoint watchdog. The command goes
        first: relaxed with an idle planner, the firmware takes the planner's null setpoint (motors off)."""
        self._cf.commander.send_notify_setpoint_stop(remain_valid_milliseconds=NOTIFY_STOP_VALID_MS)

    def takeoff(self, height: float, duration: float) -> None:
        self._check_open()
        self._arm_watchdog()
        self._cf.high_level_commander.takeoff(height, duration)
        self._hand_over_to_planner()

    def land(self, duration: float, height: float = 0.0) -> None:
        self._check_open()
        latest = self.telemetry()
        if latest is not None and latest.flight_state is FlightState.FLYING:
            self._arm_watchdog()  # a drone found in the air is put under the watchdog as well
        self._cf.high_level_commander.land(height, duration)
        self._hand_over_to_planner()

    # ---- the emergency-stop watchdog ---------------------------------------------------------------

    def _arm_watchdog(self) -> None:
        if self._watchdog is not None:
            return
        self._cf.supervisor.send_emergency_stop_watchdog()  # armed before the command that follows
        self._watchdog = threading.Thread(target=self._feed_watchdog, name=f"estop watchdog {self.uri}",
                                          daemon=True)
        self._watchdog.start()
        logger.info("%s: emergency-stop watchdog armed (%.1f s): the drone stops its motors if this ground "
                    "station goes silent", self.uri, ESTOP_WATCHDOG_S)

    def _feed_watchdog(self) -> None:
        while not self._watchdog_stop.wait(ESTOP_FEED_PERIOD_S):
            try:
                self._cf.supervisor.send_emergency_stop_watchdog()
            except Exception as exc:  # a failing driver must not kill the thread silently
                logger.warning("%s: emergency-stop watchdog packet not sent: %s", self.uri, exc)

    @property
    def watchdog_armed(self) -> bool:
        """Whether this link has armed the drone's emergency-stop watchdog (it then feeds it until closed)."""
        return self._watchdog is not None

    def emergency_stop(self) -> None:
        self._check_open()
        for _ in range(3):  # idempotent; repeated because radio links can drop a packet
            self._cf.supervisor.send_emergency_stop()

    def stats(self) -> LinkStats:
        return LinkStats(self._sent, self._received, self._telemetry_count, self.telemetry_age(),
                         self.link_lost, self._opened_at)

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._watchdog_stop.set()
        if self._watchdog is not None:
            self._watchdog.join(timeout=1.0)
            logger.info("%s: emergency-stop watchdog no longer fed: the drone locks (reboot before flying "
                        "again)", self.uri)
        latest = self.telemetry()
        if latest is not None and latest.flight_state is FlightState.FLYING and not self.link_lost:
            logger.warning("%s: closing while flying; cflib sends a zero-thrust setpoint on close, so the "
                           "drone will drop. Land first.", self.uri)
        # cflib's close_link() sends the zero setpoint, closes the driver, then waits up to 1 s for its packet
        # handler thread to time out of an empty queue. Return once the driver is closed and leave that wait
        # to a daemon thread, so that closing 12 links does not take 12 s.
        closer = threading.Thread(target=self._cf.close_link, name=f"close {self.uri}", daemon=True)
        closer.start()
        deadline = time.monotonic() + 2.0
        while closer.is_alive() and self._cf.link is not None and time.monotonic() < deadline:
            time.sleep(0.002)

    @property
    def crazyflie(self) -> Crazyflie:
        """The underlying cflib object (for parameters, extpos and anything the Link does not cover)."""
        return self._cf
