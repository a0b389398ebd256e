"""runtime.comms: wire format, channel effects (range, loss, latency, bandwidth), drops, determinism, transports."""
from __future__ import annotations

import math
import struct
import time

import numpy as np
import pytest

from runtime import radio_msg
from runtime.comms import (HEADER, SIGHT, CommConfig, InProcessBus, Neighbours, Radio, UdpTransport, decode_message,
                           free_udp_ports, message_size)
from runtime.observation import SIGHTING
from runtime.spec import SpecError, SwarmSpec

SPEC = SwarmSpec()  # 5 pursuers, 5 scouts, 2 evaders
PARTIAL = SwarmSpec.from_dict({"sensing": {"observability": "partial"}})
NT = SPEC.team.n_team


def sightings(t: float = 1.0) -> np.ndarray:
    s = np.zeros((SPEC.team.n_evaders, SIGHTING))
    s[:, 4] = -np.inf
    s[1] = [0.5, -0.25, 0.1, 0.2, t]
    return s


def pair(cfg: CommConfig | None = None, spec: SwarmSpec = SPEC, a: int = 0, b: int = 1):
    bus = InProcessBus(spec.n_agents)
    return bus, Radio(spec, a, bus.endpoint(a), cfg), Radio(spec, b, bus.endpoint(b), cfg)


def test_wire_roundtrip_carries_id_role_state_and_timestamped_sightings():
    bus, tx, rx = pair(CommConfig(exact_values=True))
    tx.broadcast(2.0, 1.9, np.array([1.0, -2.0]), np.array([0.3, 0.4]), sightings(1.5))
    raw = bus.queues[1][0]
    assert message_size(1) == HEADER.size + SIGHT.size <= radio_msg.P2P_MAX_DATA_SIZE
    assert len(raw) > message_size(1)  # the packet, then the simulation's exact values (CommConfig.exact_values)
    msg = decode_message(raw, SPEC)
    assert msg["exact"] and not msg["clamped"]
    assert msg["sender"] == 0 and msg["role"] == int(SPEC.roles[0])
    assert msg["pos"] == (1.0, -2.0) and msg["vel"] == (0.3, 0.4) and msg["t_state"] == 1.9
    assert msg["sightings"] == [{"target": 1, "pos": (0.5, -0.25), "vel": (0.1, 0.2), "t_seen": 1.5}]
    table, kn = Neighbours(SPEC.n_agents), sightings(-np.inf)
    kn[1, 4] = -np.inf
    assert rx.poll(2.0, np.zeros(2), table, kn) == 1
    np.testing.assert_array_equal(table.pos[0], [1.0, -2.0])
    np.testing.assert_array_equal(table.vel[0], [0.3, 0.4])
    assert table.t_state[0] == 1.9 and table.t_recv[0] == 2.0
    np.testing.assert_array_equal(kn[1], [0.5, -0.25, 0.1, 0.2, 1.5])
    assert kn[0, 4] == -np.inf  # never-seen targets are not sent


def test_fresher_sighting_wins_and_older_state_does_not_overwrite():
    bus, tx, rx = pair()
    table, kn = Neighbours(SPEC.n_agents), sightings(5.0)
    tx.broadcast(1.0, 1.0, np.array([1.0, 1.0]), np.zeros(2), sightings(4.0))  # older sighting than rx's
    rx.poll(1.0, np.zeros(2), table, kn)
    assert kn[1, 4] == 5.0 and kn[1, 0] == 0.5
    tx.broadcast(1.1, 0.5, np.array([9.0, 9.0]), np.zeros(2))  # a state older than the one held
    rx.poll(1.1, np.zeros(2), table, kn)
    np.testing.assert_array_equal(table.pos[0], [1.0, 1.0])


def _header(**kw) -> bytes:
    """A state-only packet of SPEC's sender 0 with ``kw`` replacing header fields (radio_msg.HEADER_FIELDS)."""
    h = dict(zip([f.name for f in radio_msg.HEADER_FIELDS],
                 HEADER.unpack(radio_msg.Codec(SPEC).pack(0, 0, 0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))))
    h.update(kw)
    return HEADER.pack(*h.values())


@pytest.mark.parametrize("blob, what", [
    (b"", "malformed"), (b"XX" + bytes(HEADER.size - 2), "malformed"),
    (_header(version=9), "version"),
    (_header(spec_hash=radio_msg.spec_hash32(SPEC) ^ 1), "spec"),
    (_header(sender=200), "malformed"),  # no such sender
    (_header(role=2), "malformed"),  # sender 0 is no evader
    (_header(n_sight=1), "malformed"),  # announces a missing sighting
    (_header(x=radio_msg.NAN_RAW), "malformed"),  # NaN position
    (_header(n_sight=1) + SIGHT.pack(7, 0, 0, 0, 0, 0), "malformed"),  # no such evader
    (bytes(300), "oversized"),
])
def test_malformed_and_oversized_messages_are_dropped_and_counted(blob, what):
    bus, tx, rx = pair()
    bus.endpoint(0).send(blob)
    table = Neighbours(SPEC.n_agents)
    assert rx.poll(0.0, np.zeros(2), table) == 0
    assert getattr(rx.stats, f"dropped_{what}") == 1 and rx.stats.received == 1
    assert sum(v for k, v in rx.stats.as_dict().items() if k.startswith("dropped_")) == 1
    assert not np.isfinite(table.t_state).any()


def test_range_is_judged_between_sender_and_receiver_positions():
    r = PARTIAL.sensing.comm_range
    bus, tx, rx = pair(spec=PARTIAL)
    table = Neighbours(PARTIAL.n_agents)
    tx.broadcast(0.0, 0.0, np.array([r + 0.01, 0.0]), np.zeros(2))
    tx.broadcast(0.0, 0.1, np.array([r - 0.01, 0.0]), np.zeros(2))
    assert rx.poll(0.0, np.zeros(2), table) == 1
    assert rx.stats.dropped_range == 1
    assert CommConfig().range_for(SPEC) == math.inf  # full observability: ranges do not limit
    assert CommConfig(comm_range=1.0).range_for(SPEC) == 1.0


def test_latency_holds_messages_until_due():
    bus, tx, rx = pair(CommConfig(latency_s=0.05))
    table = Neighbours(SPEC.n_agents)
    tx.broadcast(1.0, 1.0, np.ones(2), np.zeros(2))
    assert rx.poll(1.0, np.zeros(2), table) == 0
    assert rx.poll(1.049, np.zeros(2), table) == 0
    assert rx.poll(1.0501, np.zeros(2), table) == 1
    assert table.t_recv[0] == 1.0501


def _losses(seed: int, loss: float, n: int = 400) -> list[bool]:
    bus, tx, rx = pair(CommConfig(loss=loss, seed=seed))
    table = Neighbours(SPEC.n_agents)
    got = []
    for k in range(n):
        tx.broadcast(float(k), float(k), np.zeros(2), np.zeros(2))
        got.append(rx.poll(float(k), np.zeros(2), table) == 1)
    return got


def test_loss_is_seeded_and_has_the_configured_rate():
    a, b, c = _losses(1, 0.3), _losses(1, 0.3), _losses(2, 0.3)
    assert a == b and a != c
    assert 0.22 < 1 - np.mean(a) < 0.38
    assert all(_losses(0, 0.0, 50)) and not any(_losses(0, 1.0, 50))


def test_bandwidth_adds_airtime_and_drops_past_the_backlog():
    bps = 8 * message_size(0) / 0.01  # one state-only message takes 10 ms of airtime
    bus, tx, rx = pair(CommConfig(bandwidth_bps=bps, max_backlog_s=0.035))
    table = Neighbours(SPEC.n_agents)
    sent = [tx.broadcast(0.0, 0.0, np.zeros(2), np.zeros(2)) for _ in range(5)]
    assert sent == [True, True, True, True, False]  # queued at 0, 10, 20, 30 ms; the 5th would wait 40 ms
    assert tx.stats.dropped_bandwidth == 1
    # the packet's departure time is in whole ms: latency counts from the earliest it can mean (half a ms early)
    assert rx.poll(0.0094, np.zeros(2), table) == 0
    assert rx.poll(0.0101, np.zeros(2), table) == 1
    assert rx.poll(0.0401, np.zeros(2), table) == 3


def test_other_team_and_other_epoch_are_ignored():
    bus = InProcessBus(SPEC.n_agents)
    pursuer = Radio(SPEC, 0, bus.endpoint(0))
    evader = Radio(SPEC, NT, bus.endpoint(NT))
    scout = Radio(SPEC, NT - 1, bus.endpoint(NT - 1))
    pursuer.broadcast(0.0, 0.0, np.zeros(2), np.zeros(2))
    table = Neighbours(SPEC.n_agents)
    assert evader.poll(0.0, np.zeros(2), table) == 0 and evader.stats.ignored_other_team == 1
    scout.clear(epoch=3)
    assert scout.poll(0.0, np.zeros(2), table) == 0 and scout.stats.dropped_epoch == 1
    pursuer.clear(epoch=3)
    pursuer.broadcast(0.1, 0.1, np.zeros(2), np.zeros(2))
    assert scout.poll(0.1, np.zeros(2), table) == 1


def test_bad_comm_config_names_the_field():
    for kw, field in [({"loss": 1.5}, "comms.loss"), ({"latency_s": -1.0}, "comms.latency_s"),
                      ({"bandwidth_bps": 0.0}, "comms.bandwidth_bps"), ({"max_bytes": 10}, "comms.max_bytes")]:
        with pytest.raises(SpecError, match=field):
            CommConfig(**kw)
    with pytest.raises(SpecError, match="max_bytes"):
        CommConfig(max_bytes=100)  # more than a Crazyflie peer-to-peer packet


def test_a_small_byte_budget_relays_the_freshest_sightings_that_fit():
    bus, tx, rx = pair(CommConfig(max_bytes=HEADER.size + SIGHT.size))
    s = sightings(1.5)
    s[0] = [0.1, 0.2, 0.0, 0.0, 1.0]  # older than evader 1's
    tx.broadcast(2.0, 2.0, np.zeros(2), np.zeros(2), s)
    msg = decode_message(bus.queues[1][0], SPEC)
    assert [g["target"] for g in msg["sightings"]] == [1] and tx.stats.sightings_left_out == 1
    s[0, 4] = 2.0 - SPEC.sensing.target_memory  # as old as the memory: unknown, not relayed
    tx.broadcast(2.1, 2.0, np.zeros(2), np.zeros(2), s)
    assert len(decode_message(bus.queues[1][1], SPEC)["sightings"]) == 1 and tx.stats.sightings_left_out == 1


def test_quantized_channel_delivers_the_packet_values():
    bus, tx, rx = pair(CommConfig(exact_values=False))
    tx.broadcast(2.0, 1.9, np.array([1.0004, -2.0]), np.array([0.3, 0.4]), sightings(1.5))
    assert len(bus.queues[1][0]) == message_size(1)
    table, kn = Neighbours(SPEC.n_agents), sightings(-np.inf)
    kn[1, 4] = -np.inf
    assert rx.poll(2.0, np.zeros(2), table, kn) == 1
    np.testing.assert_array_equal(table.pos[0], [1.0, -2.0])  # 1 mm steps
    assert table.t_state[0] == 1.9
    lsb = radio_msg.Scales.for_spec(SPEC).age_lsb
    assert abs(kn[1, 4] - 1.5) <= lsb / 2 + 1e-3 and kn[1, 0] == 0.5


def test_a_message_is_heard_at_once_without_latency_whatever_its_rounded_departure():
    """The packet's departure time is rounded to the ms and can read up to half a ms late; a message polled right
    after it was sent must not wait for the next poll as if still in flight (the defect that left full-observability
    agents waiting to hear every teammate when the channel carried only the packet)."""
    for now in (1.0, 1.0004, 1.0005, 1.0006, 1.000999, 12345.6789):
        bus, tx, rx = pair()
        table = Neighbours(SPEC.n_agents)
        tx.broadcast(now, now, np.ones(2), np.zeros(2))
        assert rx.poll(now, np.zeros(2), table) == 1, now
        assert rx.stats.delivered == 1 and not rx._pending


def test_udp_loopback_transport_carries_the_same_messages():
    ports = free_udp_ports(3)
    eps = [UdpTransport(i, ports) for i in range(3)]
    try:
        radios = [Radio(SPEC, i, eps[i]) for i in range(3)]
        radios[0].broadcast(1.0, 1.0, np.array([0.25, 0.5]), np.array([0.1, 0.0]), sightings(0.9))
        eps[2].send(struct.pack("<4B", 1, 2, 3, 4))  # junk from a peer
        for r in radios[1:]:
            table, kn = Neighbours(SPEC.n_agents), sightings(-np.inf)
            kn[1, 4] = -np.inf
            for _ in range(100):  # loopback delivery is asynchronous
                if r.poll(1.0, np.zeros(2), table, kn):
                    break
                time.sleep(0.005)
            np.testing.assert_allclose(table.pos[0], [0.25, 0.5], atol=1e-12)  # whole mm: exact in the packet
            assert abs(kn[1, 4] - 0.9) <= radio_msg.Scales.for_spec(SPEC).age_lsb / 2 + 1e-3
        for _ in range(100):
            radios[1].poll(1.0, np.zeros(2), Neighbours(SPEC.n_agents))
            if radios[1].stats.dropped_malformed:
                break
            time.sleep(0.005)
        assert radios[1].stats.dropped_malformed == 1
    finally:
        for e in eps:
            e.close()
