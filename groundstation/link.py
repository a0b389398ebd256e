"""One ``Link`` interface to a vehicle, opened by URI like cflib's drivers.

``open_link(uri)`` picks the implementation by the URI's scheme:

=====================================  =============================================================
``radio://0/80/2M/E7E7E7E701``         ``CflibLink`` (``groundstation.cflib_link``): a Crazyflie over a Crazyradio
``udp://127.0.0.1:19850``              ``CflibLink``: a simulated Crazyflie (``swarm-gs sim``, CrazySim SITL)
``usb://0``                            ``CflibLink``: a Crazyflie on USB
``mavlink:udpin:127.0.0.1:14550``      ``MavlinkLink`` (``groundstation.mavlink_link``): the text after
                                       ``mavlink:`` is a pymavlink connection string, so ``udp://`` stays cflib's
``mavlink:/dev/ttyACM0,57600``         ``MavlinkLink`` over a serial port (baud after the comma)
=====================================  =============================================================

Loss of a silent peer: cflib's radio and UDP drivers do not report one, so every link judges it from
telemetry silence: ``link.telemetry_age()`` [s] and ``link.link_lost`` (age > ``link_loss_timeout``, 0.25 s
by default; pass ``link_loss_timeout=`` to ``open_link``). Each ``Telemetry`` carries its arrival time ``t``.

A ``Link`` is the raw transport: it sends what it is told. Every setpoint that leaves the ground station
must first pass the geofence (``groundstation.safety``); the flight-operations layer does that before it
calls ``send_velocity`` / ``send_position``, and nothing else may call them.

Units: SI, world frame, z up; yaw [rad], yaw rate [rad/s]; times from ``time.monotonic()`` [s].
"""
from __future__ import annotations

import abc
import enum
import importlib
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Callable

logger = logging.getLogger(__name__)


class FlightState(str, enum.Enum):
    """What the vehicle says it is doing."""

    UNKNOWN = "unknown"
    DISARMED = "disarmed"
    LANDED = "landed"
    """Armed, on the ground, motors idle."""
    FLYING = "flying"
    LOCKED = "locked"
    """Motors cut by a safety function (emergency stop, setpoint watchdog); needs a reboot."""
    CRASHED = "crashed"


@dataclass(frozen=True)
class Telemetry:
    """One telemetry sample as the ground station received it."""

    t: float
    """Time the sample arrived at the ground station [s, time.monotonic()]."""
    position: tuple[float, float, float]
    """Estimated position [m, world frame]."""
    velocity: tuple[float, float, float]
    """Estimated velocity [m/s, world frame]."""
    battery: float
    """Battery voltage [V]."""
    link_quality: float
    """Link quality [0..1]: the radio's own figure where it reports one, else the fraction of expected
    telemetry samples that arrived over the last second."""
    flight_state: FlightState
    position_variance: tuple[float, float, float] | None = None
    """Variance of the position estimate per axis [m^2], when the vehicle reports it."""
    rssi: float | None = None
    """Received signal strength [dBm], when the vehicle reports it."""
    vehicle_time_ms: int | None = None
    """The vehicle's own timestamp of the measurement [ms] (Crazyflie: 24-bit tick; MAVLink: time_boot_ms)."""
    planner_active: bool | None = None
    """The onboard planner (Crazyflie: high-level commander) flies a trajectory (takeoff, land, go_to), when
    the vehicle reports it; tells the ground station that a takeoff or land command got through."""


@dataclass(frozen=True)
class LinkStats:
    """Counters of one link."""

    packets_sent: int
    packets_received: int
    telemetry_received: int
    telemetry_age: float
    """Seconds since the latest telemetry sample arrived [s]; inf before the first."""
    link_lost: bool
    opened_at: float
    """[s, time.monotonic()]"""


class LinkError(RuntimeError):
    """A link cannot be opened or used. Carries the URI and how to fix it."""

    def __init__(self, uri: str, problem: str, fix: str) -> None:
        self.uri, self.problem, self.fix = uri, problem, fix
        super().__init__(f"{uri}: {problem}\n  - fix: {fix}")


class UnknownScheme(LinkError):
    """No link implementation is registered for the URI's scheme."""


TelemetryCallback = Callable[[Telemetry], None]


class Link(abc.ABC):
    """A connection to one vehicle. Use as a context manager; ``close()`` is idempotent.

    Implementations call ``_publish(sample)`` for every telemetry sample; the base class keeps the latest,
    runs the callbacks and answers ``telemetry()``, ``telemetry_age()`` and ``link_lost``.
    """

    arms_on_takeoff = False
    """True where the vehicle sits disarmed on the ground and ``takeoff`` arms it (ArduPilot, PX4): preflight
    then accepts DISARMED as ready; a Crazyflie arms itself and must report LANDED."""

    link_loss_timeout: float = 0.25
    """Telemetry silence after which ``link_lost`` is True [s]. Radio and UDP drivers do not notice a
    silent peer, so loss is judged from telemetry alone."""

    def __init__(self, uri: str) -> None:
        self.uri = uri
        self._latest: Telemetry | None = None
        self._callbacks: list[TelemetryCallback] = []
        self._telemetry_count = 0
        self._opened_at = time.monotonic()
        self._fresh = threading.Condition()

    # ---- telemetry ---------------------------------------------------------------------------------

    def telemetry(self) -> Telemetry | None:
        """The latest sample, or None before the first."""
        return self._latest

    def telemetry_age(self, now: float | None = None) -> float:
        """Seconds since the latest sample arrived [s]; inf before the first."""
        latest = self._latest
        if latest is None:
            return math.inf
        return (time.monotonic() if now is None else now) - latest.t

    @property
    def link_lost(self) -> bool:
        """True once telemetry has been silent for ``link_loss_timeout`` (or never came)."""
        return self.telemetry_age() > self.link_loss_timeout

    def add_telemetry_callback(self, callback: TelemetryCallback) -> None:
        """Call ``callback(sample)`` on every sample, on the link's receive thread: keep it short."""
        self._callbacks.append(callback)

    def remove_telemetry_callback(self, callback: TelemetryCallback) -> None:
        self._callbacks.remove(callback)

    def wait_telemetry(self, timeout: float, predicate: Callable[[Telemetry], bool] | None = None) -> Telemetry:
        """Block until a sample newer than now arrives (and satisfies ``predicate``); LinkError on timeout."""
        deadline = time.monotonic() + timeout
        start = time.monotonic()
        with self._fresh:
            while True:
                latest = self._latest
                if latest is not None and latest.t >= start and (predicate is None or predicate(latest)):
                    return latest
                left = deadline - time.monotonic()
                if left <= 0:
                    raise LinkError(self.uri, f"no matching telemetry within {timeout:.1f} s",
                                    "check that the vehicle is powered and in range, and that its "
                                    "telemetry is not blocked")
                self._fresh.wait(left)

    def _publish(self, sample: Telemetry) -> None:
        self._latest = sample
        self._telemetry_count += 1
        for callback in list(self._callbacks):
            try:
                callback(sample)
            except Exception:  # a failing consumer must not stop the link's receive thread
                logger.exception("%s: telemetry callback %r failed", self.uri, callback)
        with self._fresh:
            self._fresh.notify_all()

    # ---- commands ----------------------------------------------------------------------------------

    @abc.abstractmethod
    def send_velocity(self, vx: float, vy: float, vz: float, yaw_rate: float = 0.0) -> None:
        """Stream a velocity setpoint [m/s, world frame; yaw rate rad/s]. Must be repeated (>= 10 Hz):
        vehicles level out after 0.5 s without one and cut their motors after 2 s."""

    @abc.abstractmethod
    def send_position(self, x: float, y: float, z: float, yaw: float = 0.0) -> None:
        """Stream a position setpoint [m, world frame; yaw rad]. Must be repeated like ``send_velocity``."""

    @abc.abstractmethod
    def takeoff(self, height: float, duration: float) -> None:
        """Take off vertically to ``height`` [m, absolute] in ``duration`` [s] with the onboard planner;
        the vehicle then holds that point without further setpoints."""

    @abc.abstractmethod
    def land(self, duration: float, height: float = 0.0) -> None:
        """Descend vertically to ``height`` [m, absolute] in ``duration`` [s] and stop the motors."""

    @abc.abstractmethod
    def emergency_stop(self) -> None:
        """Cut the motors now. The vehicle falls and stays locked until rebooted."""

    @abc.abstractmethod
    def stats(self) -> LinkStats:
        """Packet and telemetry counters."""

    @abc.abstractmethod
    def close(self) -> None:
        """Release the connection. Idempotent. Land first: closing does not land."""

    def __enter__(self) -> "Link":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.uri!r})"


# ---- opening links by URI ------------------------------------------------------------------------

LinkFactory = Callable[..., Link]

_REGISTRY: dict[str, str | LinkFactory] = {
    "radio": "groundstation.cflib_link:CflibLink",
    "udp": "groundstation.cflib_link:CflibLink",
    "usb": "groundstation.cflib_link:CflibLink",
    "mavlink": "groundstation.mavlink_link:MavlinkLink",
}
"""scheme -> factory, or "module:attribute" imported on first use (so a missing optional dependency only
matters to the URIs that need it)."""


def register_scheme(scheme: str, factory: str | LinkFactory) -> None:
    """Make ``open_link`` hand URIs of ``scheme`` to ``factory(uri, **options)``."""
    _REGISTRY[scheme.lower()] = factory


def schemes() -> list[str]:
    return sorted(_REGISTRY)


def scheme_of(uri: str) -> str:
    """``radio://0/80/2M/E7E7E7E701`` -> ``radio``; ``mavlink:udpin:127.0.0.1:14550`` -> ``mavlink``."""
    scheme, sep, _ = uri.partition(":")
    return scheme.lower() if sep else ""


def open_link(uri: str, **options) -> Link:
    """Open a link to the vehicle at ``uri`` (see the module docstring for the URI forms).

    ``options`` go to the implementation (e.g. ``CflibLink(period_ms=10)``). Raises ``UnknownScheme`` for a
    scheme nobody registered and ``LinkError`` when the vehicle does not answer.
    """
    scheme = scheme_of(uri)
    factory = _REGISTRY.get(scheme)
    if factory is None:
        examples = "radio://0/80/2M/E7E7E7E701, udp://127.0.0.1:19850, mavlink:udpin:127.0.0.1:14550"
        raise UnknownScheme(uri, f"no link for scheme {scheme!r}; known schemes: {', '.join(schemes())}",
                            f"write the URI as one of those, e.g. {examples}")
    if isinstance(factory, str):
        factory = _import_factory(uri, scheme, factory)
    return factory(uri, **options)


def _import_factory(uri: str, scheme: str, target: str) -> LinkFactory:
    module_name, _, attr = target.partition(":")
    try:
        module = importlib.import_module(module_name)
    except ModuleNotFoundError as exc:
        if exc.name == module_name:
            raise LinkError(uri, f"{scheme}:// links are implemented by {module_name}, which is not available",
                            f"make sure {module_name.replace('.', '/')}.py exists in this checkout") from exc
        raise LinkError(uri, f"{module_name} needs the package {exc.name!r}, which is not installed",
                        f"pip install 'swarmpursuit[{'mavlink' if scheme == 'mavlink' else 'crazyflie'}]'") from exc
    return getattr(module, attr)
