"""The flight session's failsafe supervisor: one thread that judges every drone and follows every landing.

Failsafes, per drone, judged by the supervisor thread every ``1 / supervisor_rate`` s; the others fly on:

=========================  ==================================================================  ================
condition                  detection                                                           response
=========================  ==================================================================  ================
link loss                  telemetry silent for ``link_loss_timeout`` (cflib's UDP and radio   land commands are
                           drivers do not report a silent peer)                                repeated; roles
                                                                                               reassigned
stale or invalid position  the position source older than ``position_stale_after``, or the     hold (hover),
                           estimator's variance above ``max_position_variance``                land after
                                                                                               ``position_hold_time``
low battery                voltage below ``low_battery_v`` for ``low_battery_time``            land, reassign
agent fault                ``report_agent_fault`` (non-finite policy output, a crashed agent)  land, reassign
                           or no command for ``command_timeout``
outside the fence          ``safety.FenceGuard``: hold, then land after ``fence.hold_time``    land, reassign
=========================  ==================================================================  ================

A drone whose link is lost cannot be commanded: its own firmware levels out after 0.5 s without a setpoint
(horizontal control off: it coasts) and cuts the motors after 2 s (a Crazyflie drops from its flight height);
a Crazyflie link also arms the firmware's emergency-stop watchdog, which cuts the motors 1 s after the ground
station falls silent in any phase (``cflib_link``). The ground station keeps sending land commands in case
the link comes back.

Two things that would otherwise fake a failure: a ground station that itself did not run for a while (a
late supervisor tick) makes every link look silent, so silence is judged again only after a short grace;
and a takeoff or land command lost on the radio is repeated every 50 ms until the vehicle reports its
planner active (``Telemetry.planner_active``), because a Crazyflie whose priority was handed over
(notify-setpoint-stop) but whose planner got no command takes the idle planner's null setpoint: motors off.
A landing seen active is not re-sent once it has ended (the drone reports "flying" 2 s past touchdown).
"""
from __future__ import annotations

import logging
import math
import threading
import time

from groundstation.flight_types import (AIRBORNE, LAND_CONFIRM_RETRY, STALL_GAP, STALL_GRACE, DroneState,
                                        DroneStatus)
from groundstation.link import FlightState, LinkError
from groundstation.role_repair import RoleRepair

log = logging.getLogger(__name__)


class FailsafeSupervisor(RoleRepair):
    """The supervisor thread (``_supervise``) and the landings it starts and follows. Roles are repaired
    (``RoleRepair._reassign``) whenever a drone leaves the mission."""

    def _init_supervisor(self) -> None:
        self._stop = threading.Event()
        self._supervisor: threading.Thread | None = None
        self._next_record = 0.0
        self._last_tick = time.monotonic()
        self._grace_until = 0.0
        self.stalls = 0
        """Times the supervisor found that the ground station itself had not run for ``STALL_GAP``."""

    def _start_supervisor(self) -> None:
        self._supervisor = threading.Thread(target=self._supervise, name="FlightSupervisor", daemon=True)
        self._supervisor.start()

    def _stop_supervisor(self) -> None:
        self._stop.set()
        if self._supervisor is not None:
            self._supervisor.join(timeout=2.0)

    def _supervise(self) -> None:
        period = 1.0 / self.config.supervisor_rate
        next_t = time.monotonic()
        while not self._stop.is_set():
            now = time.monotonic()
            try:
                self._tick(now)
            except Exception:  # the failsafes must keep running whatever one check raised
                log.exception("flight supervisor tick failed")
            next_t += period
            delay = next_t - time.monotonic()
            if delay < 0:
                next_t = time.monotonic()
                delay = 0.0
            self._stop.wait(delay)

    def _tick(self, now: float) -> None:
        cfg = self.config
        reassign: list[str] = []
        gap = now - self._last_tick
        self._last_tick = now
        if gap > STALL_GAP:
            # The ground station itself did not run (CPU starvation, a paused process): every link looks
            # silent for that long. Give the receive threads time to deliver what queued up before telemetry
            # silence is judged again, or one stall would "lose" the whole swarm.
            self._grace_until = now + STALL_GRACE
            self.stalls += 1
            self._event(None, "ground_station_stall", f"supervisor did not run for {gap * 1e3:.0f} ms",
                        {"gap_s": gap})
        judge_silence = now >= self._grace_until
        for d in self.drones.values():
            if d.status in AIRBORNE:
                why = self._failsafe(d, now, judge_silence)
                if why is not None:
                    reassign.append(f"{d.id}: {why}")
        self._check_landings(now)
        if reassign and self.actors:
            self._reassign("; ".join(reassign))
        if now >= self._next_record:
            self._next_record = now + 1.0 / cfg.record_rate
            self._write_rows(now)

    def _failsafe(self, d: DroneState, now: float, judge_silence: bool = True) -> str | None:
        """Judge one airborne drone; returns why it left the mission, or None. ``judge_silence`` False: the
        ground station has just stalled, so telemetry silence and stale positions are not judged yet."""
        cfg = self.config
        link = d.link
        silence = link.telemetry_age(now)
        if judge_silence and (link.link_lost or silence > cfg.link_loss_timeout):
            with d.lock:
                self._set_status(d, DroneStatus.LOST, f"no telemetry for {silence * 1e3:.0f} ms")
            self._event(d.id, "link_lost", f"telemetry silent for {silence * 1e3:.0f} ms",
                        {"silence_s": silence})
            self._send_land(d, now)
            return "link lost"
        tel = link.telemetry()
        if d.status is DroneStatus.TAKING_OFF:
            s = self.tracker.get(d.id)
            if s is not None and abs(s.position[2] - self.height) <= cfg.takeoff_tolerance:
                with d.lock:
                    self._set_status(d, DroneStatus.FLYING, "at mission height")
            elif now - d.takeoff_t > cfg.takeoff_duration + cfg.takeoff_timeout:
                self._begin_landing(d, "did not reach mission height")
                return "takeoff failed"
            elif tel is not None and tel.flight_state is FlightState.LANDED and not tel.planner_active \
                    and tel.t > d.land_sent_t and now - d.land_sent_t >= 4 * LAND_CONFIRM_RETRY:
                # the takeoff command was lost (radio links drop packets): ask again; a drone already
                # climbing reports FLYING and is left alone
                with d.lock:
                    d.land_sent_t = now
                    try:
                        d.link.takeoff(self.height, cfg.takeoff_duration)
                    except LinkError as exc:
                        log.warning("%s: takeoff command not sent: %s", d.id, exc)
            return None
        if tel is not None and tel.battery < cfg.low_battery_v:
            if d.low_battery_since is None:
                d.low_battery_since = now
            elif now - d.low_battery_since >= cfg.low_battery_time:
                self._event(d.id, "low_battery", f"{tel.battery:.2f} V < {cfg.low_battery_v:.2f} V",
                            {"battery_v": tel.battery})
                self._begin_landing(d, f"low battery {tel.battery:.2f} V")
                return "low battery"
        else:
            d.low_battery_since = None
        if d.fault is None and self._mission and self.assignment.by_drone.get(d.id) is not None:
            last = max(d.command_t, d.actor_since)
            if now - last > cfg.command_timeout:
                d.fault = f"no command from its runtime for {now - last:.2f} s"
        if d.fence_breach:
            self._event(d.id, "fence_breach", "measured outside the fence for longer than fence.hold_time")
            self._begin_landing(d, "outside the fence")
            return "outside the fence"
        if d.fault is not None:
            if d.retire_actor:
                actor = self.assignment.by_drone.get(d.id)
                if actor is not None:
                    self._retired.add(actor)
            self._event(d.id, "agent_fault", d.fault, {"actor": self.assignment.by_drone.get(d.id),
                                                       "actor_retired": d.retire_actor})
            self._begin_landing(d, f"agent fault: {d.fault}")
            return "agent fault"
        pos = self.tracker.position(d.id)
        var = tel.position_variance if tel is not None else None
        if pos is None and not judge_silence:
            return None
        invalid = pos is None or (var is not None and not max(var) <= cfg.max_position_variance)
        if invalid:
            if d.invalid_since is None:
                d.invalid_since = now
                why = "stale" if pos is None else f"variance {max(var):.3g} m^2"
                with d.lock:
                    self._set_status(d, DroneStatus.HOLDING, f"position {why}")
                self._event(d.id, "position_invalid", why, {"age_s": self.tracker.age(d.id)})
            elif now - d.invalid_since >= cfg.position_hold_time:
                self._begin_landing(d, "position stale or invalid")
                return "position lost"
        elif d.invalid_since is not None:
            d.invalid_since = None
            with d.lock:
                self._set_status(d, DroneStatus.FLYING, "position valid again")
        return None

    def _begin_landing(self, d: DroneState, reason: str) -> None:
        with d.lock:
            if d.status in (DroneStatus.LANDING, DroneStatus.LANDED, DroneStatus.STOPPED, DroneStatus.EXCLUDED):
                return
            if d.status is DroneStatus.READY:
                self._set_status(d, DroneStatus.LANDED, reason)
                return
            lost = d.status is DroneStatus.LOST
            self._set_status(d, DroneStatus.LOST if lost else DroneStatus.LANDING, reason)
            self._send_land(d, time.monotonic())

    def _send_land(self, d: DroneState, now: float) -> None:
        s = self.tracker.get(d.id)
        z = s.position[2] if s is not None and math.isfinite(s.position[2]) else self.height
        d.land_sent_t, d.land_acked = now, False
        try:
            d.link.land(max(z, 0.1) / self.config.land_speed + 0.2)
        except LinkError as exc:
            log.warning("%s: land command not sent: %s", d.id, exc)

    def _check_landings(self, now: float) -> None:
        """Follow every landing to the ground. A land command can be lost on the radio: until the vehicle
        reports its planner active (or, for links that do not report it, until the landing should have
        ended) the command is repeated, every ``LAND_CONFIRM_RETRY`` s at first; a Crazyflie that took the
        hand-over but not the land cuts its motors at once."""
        for d in self.drones.values():
            if d.status is DroneStatus.LOST:
                # land commands keep going out in case the link comes back; once it answers, land it properly
                if now - d.land_sent_t >= self.config.land_retry:
                    self._send_land(d, now)
                    if not d.link.link_lost:
                        with d.lock:
                            if d.status is DroneStatus.LOST:  # not already moved on by the other caller
                                self._set_status(d, DroneStatus.LANDING, "link back")
                continue
            if d.status is not DroneStatus.LANDING:
                continue
            tel = d.link.telemetry()
            # DISARMED: ArduPilot and PX4 disarm by themselves once down
            if tel is not None and not d.link.link_lost and tel.flight_state in (FlightState.LANDED,
                                                                                 FlightState.LOCKED,
                                                                                 FlightState.DISARMED):
                with d.lock:
                    self._set_status(d, DroneStatus.LANDED, f"on the ground at z = {tel.position[2]:.2f} m")
                if tel.flight_state is FlightState.LOCKED:
                    self._event(d.id, "dropped", "the firmware cut the motors (locked) instead of landing")
            elif d.link.link_lost:
                with d.lock:
                    self._set_status(d, DroneStatus.LOST, "link lost while landing")
            elif tel is not None and tel.planner_active and tel.t > d.land_sent_t:
                # Taken. Not again once the landing has ended: a Crazyflie reports "flying" for 2 s after
                # touchdown (supervisor.c), and a land sent to its idle planner would spin the motors again.
                d.land_acked = True
            elif d.land_acked:
                continue
            elif tel is not None and tel.planner_active is False and tel.t > d.land_sent_t \
                    and now - d.land_sent_t >= LAND_CONFIRM_RETRY:
                self._send_land(d, now)
            elif now - d.land_sent_t > max(self.config.land_retry, self.height / self.config.land_speed + 1.0):
                self._send_land(d, now)
