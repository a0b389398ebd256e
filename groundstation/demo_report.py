"""The demo's results: what it measured, as a dict (``results``), a printed summary (``format_summary``) and a
top-down picture of the flight (``plot_flight``, also drawn by ``swarm-gs replay`` from a log)."""
from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from groundstation.demo_metrics import EpisodeMetrics, PairMonitor, on_ground
from groundstation.flight import FlightSession
from groundstation.mission import AgentPilot
from groundstation.positioning import AnchorLayout
from groundstation.safety import FenceConfig
from runtime.paper import FLIGHT_TEAM, PAPER


def separation_results(session: FlightSession, sims, pairs: PairMonitor) -> dict:
    """The separation filter's counters and the simulator's contacts (``sims``: ``SimSwarm`` or ``SimProcess``)."""
    return {
        "separation": session.separation_stats(),
        "drone_contacts": sims.drone_contacts,  # two drones that touched: both crashed (motors off, locked)
        "drone_contact_events": [[round(float(t), 3), a, b] for t, a, b in sims.contact_events],
        "min_pair_distance": round(pairs.closest, 4) if math.isfinite(pairs.closest) else None,
        "pairs_below_min_distance": pairs.below,
        "pairs_touching": pairs.touching,
        "min_distance": session.separation_config.min_distance,
        "capture_distance": session.separation_config.capture_distance,
    }


def results(opts, spec, session: FlightSession, sims, metrics: EpisodeMetrics, pilot: AgentPilot,
            ids, sent0, sent1, t_mission, t_end, t_start, t_connected, kill, kill_at, relay) -> dict[str, Any]:
    """The demo's result dict (``demo.RESULT_KEYS`` and more) after the flight."""
    truth = sims.truths()
    landed = sum(1 for tr in truth if on_ground(tr))
    lat = np.array(session.latencies) * 1e3
    e2e = np.array(sims.latency_samples()) * 1e3
    span = max(t_end - t_mission, 1e-9)
    per_link = {}
    for d, a, b in zip(ids, sent0, sent1):
        per_link[d] = {"packets_sent_per_s": round((b.packets_sent - a.packets_sent) / span, 1),
                       "packets_received_per_s": round((b.packets_received - a.packets_received) / span, 1),
                       "telemetry_per_s": round((b.telemetry_received - a.telemetry_received) / span, 1),
                       "link_lost": b.link_lost}
    sent = np.array([v["packets_sent_per_s"] for v in per_link.values()])
    recv = np.array([v["packets_received_per_s"] for v in per_link.values()])
    summary = metrics.summary()
    events = [{"t": round(e.t - t_mission, 3), "drone": e.drone, "kind": e.kind, "detail": e.detail}
              for e in session.events if e.kind not in ("status",)]
    res: dict[str, Any] = {k: summary.get(k) for k in ("mean_min_dist", "mean_avg_dist", "mean_max_dist",
                                                       "tracking_rate", "coverage", "coverage_instant",
                                                       "collisions_per_episode", "captures_per_episode")}
    t = spec.team
    if (t.n_pursuers, t.n_scouts, t.n_evaders) == FLIGHT_TEAM:  # the paper's real-drone team: its figure beside
        res["paper_flight_mean_avg_dist"] = PAPER["paper_flight"]["mean_avg_dist"]
    res.update({
        "episodes": summary.get("episodes", 0),
        "landed": landed,
        "locked": sum(1 for tr in truth if tr.supervisor == "locked"),
        "drones": len(ids),
        "geofence_violations": session.geofence_violations(),
        "ground_station_stalls": session.stalls,
        "setpoint_latency_p99_ms": float(np.percentile(e2e, 99)) if e2e.size else None,
        "setpoint_latency_p50_ms": float(np.percentile(e2e, 50)) if e2e.size else None,
        "setpoint_latency_samples": int(e2e.size),
        "ground_station_latency_p99_ms": float(np.percentile(lat, 99)) if lat.size else None,
        "ground_station_latency_p50_ms": float(np.percentile(lat, 50)) if lat.size else None,
        "setpoints": int(lat.size),
        "mission_s": round(span, 2),
        "connect_s": round(t_connected - t_start, 2),
        "wall_s": round(time.monotonic() - t_start, 2),
        "control_periods": pilot.ticks,
        "agents": pilot.stats(),
        "final_status": {d: s.value for d, s in session.statuses().items()},
        "final_truth": {d: {"z": round(tr.position[2], 3), "motors_on": tr.motors_on, "supervisor": tr.supervisor}
                        for d, tr in zip(ids, truth)},
        "final_roles": session.assignment.by_drone,
        "role_changes": [c.describe() for c in session.role_changes],
        "events": events,
        "links": {"per_drone": per_link,
                  "mean_packets_sent_per_s": float(sent.mean()), "mean_packets_received_per_s": float(recv.mean()),
                  "total_packets_per_s": float(sent.sum() + recv.sum()),
                  "telemetry_period_ms": opts.telemetry_period_ms, "loss": opts.loss,
                  "relay_dropped": relay.dropped if relay else 0},
        "spec_hash": spec.hash,
        "models": str(opts.models), "engine": opts.engine,
        "seed": opts.seed,
        "speed": opts.speed,
        "duration": opts.duration,
        "simulator": "in-process" if opts.sim_in_process else "own process",
    })
    if kill is not None:
        lost = [e for e in session.events if e.kind == "link_lost" and e.drone == kill[0]]
        cut = kill_at
        res["kill_link"] = {"drone": kill[0], "at_s": kill[1], "cut": cut is not None,
                            "detected_after_ms": round((lost[0].t - cut) * 1e3, 1) if lost and cut else None}
    return res


def plot_flight(path: str, rows: list[dict], fence: FenceConfig, anchors: AnchorLayout, ids: list[str],
                teams: dict[str, str], result: dict[str, Any]) -> None:
    """Top-down trajectories from the flight log on the arena, fence, keep-outs and anchors."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from groundstation.positioning import draw_layout

    colors = {"pursuer": "tab:red", "scout": "tab:blue", "evader": "tab:green", None: "tab:gray"}  # as training.plots
    fig, ax = plt.subplots(figsize=(7, 7))
    draw_layout(ax, fence, anchors)
    for d in ids:
        pts = [(r["position"], r.get("role"), r["state"]) for r in rows
               if r.get("drone") == d and "event" not in r and r.get("position") is not None
               and r["state"] in ("flying", "holding", "landing", "lost", "taking_off")]
        if not pts:
            continue
        xy = np.array([p[0][:2] for p in pts])
        role = next((p[1] for p in reversed(pts) if p[1]), None)
        ax.plot(xy[:, 0], xy[:, 1], "-", color=colors.get(role, "tab:gray"), linewidth=0.9, alpha=0.8)
        ax.plot(xy[0, 0], xy[0, 1], "o", color=colors.get(role, "tab:gray"), markersize=4)
        end = pts[-1][2]
        ax.plot(xy[-1, 0], xy[-1, 1], "x" if end == "lost" else "s", color=colors.get(role, "tab:gray"),
                markersize=6 if end == "lost" else 4)
        ax.annotate(d, xy[-1], fontsize=6, xytext=(3, 3), textcoords="offset points")
    for role, c in colors.items():
        if role:
            ax.plot([], [], "-", color=c, label=role)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"swarm-gs demo: {result.get('drones')} drones, {result.get('mission_s')} s, "
                 f"landed {result.get('landed')}, fence violations {result.get('geofence_violations')}", fontsize=9)
    ax.legend(loc="upper right", fontsize=7)
    lo, hi = fence.bounds()
    ax.set_xlim(lo[0] - 0.5, hi[0] + 0.5)
    ax.set_ylim(lo[1] - 0.5, hi[1] + 0.5)
    from runtime.cliutil import atomic_path
    try:
        with atomic_path(path) as tmp:  # never a half-drawn picture after an error or Ctrl-C
            fig.savefig(tmp, dpi=120, bbox_inches="tight")
    finally:
        plt.close(fig)


def format_summary(res: dict[str, Any]) -> str:
    """The printed report of a demo run."""
    f = lambda v, d=3: "-" if v is None else (f"{v:.{d}f}" if isinstance(v, float) else str(v))  # noqa: E731
    links = res["links"]
    ag = res["agents"]
    sep = res["separation"]
    lines = [
        f"mission {res['mission_s']} s, {res['episodes']} episode(s), {res['control_periods']} control periods; "
        f"agents: {ag['actions']} actions, {ag['deadline_misses']} deadline misses, {ag['faults']} faults, tick to "
        f"command p50 {f(ag['tick_to_command_p50_ms'], 2)} ms p99 {f(ag['tick_to_command_p99_ms'], 2)} ms",
        f"distance to targets  min {f(res['mean_min_dist'])}  mean {f(res['mean_avg_dist'])}  "
        f"max {f(res['mean_max_dist'])} m"
        + (f"   (paper's real flight, 2 pursuers + 3 scouts vs 1 evader: mean {res['paper_flight_mean_avg_dist']} m)"
           if "paper_flight_mean_avg_dist" in res else ""),
        f"tracking rate {f(res['tracking_rate'])}   coverage {f(res['coverage'])}   "
        f"collisions/episode {f(res['collisions_per_episode'], 2)}   captures/episode "
        f"{f(res['captures_per_episode'], 2)} (within {f(res['capture_distance'], 2)} m)",
        f"separation {'on' if res['separation']['enabled'] else 'OFF'} (min {f(res['min_distance'], 2)} m): drone "
        f"contacts {f(res['drone_contacts'])}, closest pair {f(res['min_pair_distance'])} m, "
        f"{res['pairs_below_min_distance']} times closer than min, {res['pairs_touching']} touching (truth)"
        + (f"; changed {sep['changed_setpoints']} of {sep['setpoints']} setpoints, braked {sep['braked_setpoints']} "
           f"({sep['unplaced_setpoints']} without a fresh position)" if sep["enabled"] else ""),
        f"landed {res['landed']}/{res['drones']} ({res['locked']} locked)   geofence violations "
        f"{res['geofence_violations']}   ground-station stalls {res['ground_station_stalls']}",
        f"measurement-to-setpoint at the drone (through cflib and UDP) p50 {f(res['setpoint_latency_p50_ms'], 2)} ms "
        f"p99 {f(res['setpoint_latency_p99_ms'], 2)} ms; in the ground station p50 "
        f"{f(res['ground_station_latency_p50_ms'], 2)} ms p99 {f(res['ground_station_latency_p99_ms'], 2)} ms",
        f"links: {f(links['mean_packets_sent_per_s'], 1)} packets/s sent and {f(links['mean_packets_received_per_s'], 1)} "
        f"received per drone; {f(links['total_packets_per_s'], 0)} packets/s in all (telemetry every "
        f"{links['telemetry_period_ms']} ms, loss {links['loss']}, {links['relay_dropped']} dropped)",
    ]
    for e in res["events"]:
        if e["kind"] in ("link_lost", "low_battery", "agent_fault", "position_invalid", "fence_breach",
                         "roles_reassigned", "abort", "emergency_stop", "dropped", "ground_station_stall"):
            lines.append(f"  t={e['t']:+.2f} s {e['drone'] or '':>5} {e['kind']}: {e['detail']}")
    if "kill_link" in res:
        k = res["kill_link"]
        lines.append(f"link of {k['drone']} cut at {k['at_s']} s: detected after {f(k['detected_after_ms'], 0)} ms")
    return "\n".join(lines)
