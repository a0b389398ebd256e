"""runtime.radio_msg: the one neighbour radio message. Python round trip (quantization within the documented
step, saturation, rejection with a reason), the generated C layout, and the Python runtime and the
host-compiled C app logic exchanging messages both ways, byte for byte and value for value."""
from __future__ import annotations

import ctypes
import logging
import math
import re
from pathlib import Path

import numpy as np
import pytest

from firmware_export import cgen
from firmware_export.c_export import TEMPLATE_DIR
from firmware_export.mlp_graph import ActorModel, Dense
from firmware_export.toolchain import APP_WARN_FLAGS, build_host_library
from runtime import radio_msg as rm
from runtime.comms import CommConfig, InProcessBus, Neighbours, Radio
from runtime.spec import Role, SwarmSpec

SPEC = SwarmSpec()
PARTIAL = SwarmSpec.from_dict({"sensing": {"observability": "partial"}})
F32 = np.float32


def _other_spec(spec: SwarmSpec) -> SwarmSpec:
    d = spec.to_dict()
    return SwarmSpec.from_dict({**d, "sensing": {**d["sensing"], "comm_range": d["sensing"]["comm_range"] + 1.0}})


def test_the_message_fits_a_crazyflie_peer_to_peer_packet_and_the_table_is_contiguous():
    assert rm.message_size(rm.MAX_SIGHTINGS) <= rm.P2P_MAX_DATA_SIZE < rm.message_size(rm.MAX_SIGHTINGS + 1)
    assert rm.MAX_SIGHTINGS >= SPEC.team.n_evaders  # the default spec relays every evader
    for fields, st in ((rm.HEADER_FIELDS, rm.HEADER), (rm.SIGHTING_FIELDS, rm.SIGHTING)):
        ends = [f.offset for f in fields[1:]] + [st.size]
        assert [e - f.offset for f, e in zip(fields, ends)] == [
            {"uint8_t": 1, "uint16_t": 2, "uint32_t": 4, "int16_t": 2}[f.ctype] for f in fields]
        assert all(f.scale in ("", "pos_lsb", "vel_lsb", "age_lsb") for f in fields)


def test_scales_follow_the_arena_and_speeds():
    s = rm.Scales.for_spec(SPEC)
    assert (s.pos_lsb, s.vel_lsb) == (0.001, 0.001)
    assert rm.I16_MAX * s.pos_lsb >= 2 * SPEC.arena.half_width
    assert rm.AGE_MAX * s.age_lsb >= SPEC.sensing.target_memory
    big = rm.Scales.for_spec(SwarmSpec.from_dict({"arena": {"half_width": 20.0}}))
    assert big.pos_lsb == 0.002 and rm.I16_MAX * big.pos_lsb >= 40.0


def test_round_trip_within_half_a_step():
    codec, s = rm.Codec(PARTIAL), rm.Scales.for_spec(PARTIAL)
    rng = np.random.default_rng(0)
    hw, v = 2 * PARTIAL.arena.half_width, PARTIAL.evader.max_speed
    for k in range(200):
        t_state = float(rng.uniform(0, 1e5))
        st = rng.uniform(-hw, hw, 2).tolist() + rng.uniform(-v, v, 2).tolist()
        sights = [(e, *rng.uniform(-hw, hw, 2), *rng.uniform(-v, v, 2), t_state - rng.uniform(0, 2.9))
                  for e in range(PARTIAL.team.n_evaders)]
        data = codec.pack(k % PARTIAL.n_agents, k, k, t_state + 0.01, t_state, *st, sights)
        assert len(data) == rm.message_size(len(sights))
        m = codec.unpack(data, now=t_state + 0.02)
        assert (m.sender, m.epoch, m.seq, m.clamped) == (k % PARTIAL.n_agents, k, k, False)
        assert m.role == int(PARTIAL.roles[m.sender])
        assert abs(m.t_state - t_state) <= 0.0005 + 1e-9 and abs(m.t_tx - t_state - 0.01) <= 0.0005 + 1e-9
        np.testing.assert_allclose([m.x, m.y], st[:2], atol=s.pos_lsb / 2 + 1e-12)
        np.testing.assert_allclose([m.vx, m.vy], st[2:], atol=s.vel_lsb / 2 + 1e-12)
        for got, want in zip(m.sightings, sights):
            assert got[0] == want[0]
            np.testing.assert_allclose(got[1:3], want[1:3], atol=s.pos_lsb / 2 + 1e-12)
            np.testing.assert_allclose(got[3:5], want[3:5], atol=s.vel_lsb / 2 + 1e-12)
            assert abs(got[5] - want[5]) <= s.age_lsb / 2 + 0.0005 + 1e-9


def test_out_of_range_values_saturate_and_are_flagged_never_wrap():
    codec = rm.Codec(SPEC)
    m = codec.unpack(codec.pack(0, 0, 0, 1.0, 1.0, 100.0, -math.inf, 50.0, 0.0, [(1, 0, 0, 0, 0, 2.0)]), now=1.0)
    assert m.clamped and (m.x, m.y, m.vx) == (32.767, -32.767, 32.767)
    assert m.sightings[0][5] == 1.0  # a sighting "from the future" is sent as age 0, flagged
    assert not codec.unpack(codec.pack(0, 0, 0, 1.0, 1.0, 32.767, 0, 0, 0), now=1.0).clamped
    # counters wrap by definition (documented modulo 2^16), times are read back near the receiver's clock
    m = codec.unpack(codec.pack(0, 70000, 65537, 4294967.5, 4294967.295, 0, 0, 0, 0), now=4294967.3)
    assert (m.epoch, m.seq) == (70000 - 65536, 1) and m.t_state == 4294967.295 and m.t_tx == 4294967.5
    assert rm.unwrap_ms(5, 4294967.29) == 4294967.301  # across the 2^32 ms wrap
    with pytest.raises(rm.RadioMsgError) as e:
        codec.pack(0, 0, 0, math.nan, 1.0, 0, 0, 0, 0)
    assert e.value.reason == "non-finite"


@pytest.mark.parametrize("change, reason, words", [
    ({"version": rm.VERSION + 1}, "version", "version"),
    ({"magic": 0x50}, "magic", "magic"),
    ({"sender": 99}, "sender", "99"),
    ({"role": 2}, "role", "role 2"),
    ({"n_sight": 1}, "size", "1 sightings"),
    ({"x": rm.NAN_RAW}, "non-finite", "non-finite"),
])
def test_a_message_that_is_not_for_us_is_rejected_with_the_reason(change, reason, words):
    codec = rm.Codec(SPEC)
    h = dict(zip([f.name for f in rm.HEADER_FIELDS], rm.HEADER.unpack(codec.pack(0, 0, 0, 0.0, 0.0, 0, 0, 0, 0))))
    h.update(change)
    with pytest.raises(rm.RadioMsgError, match=words) as e:
        codec.unpack(rm.HEADER.pack(*h.values()))
    assert e.value.reason == reason


def test_another_spec_is_rejected_naming_both_hashes_and_the_radio_counts_and_logs_it(caplog):
    other = _other_spec(SPEC)
    data = rm.Codec(other).pack(1, 0, 0, 0.0, 0.0, 0, 0, 0, 0)
    with pytest.raises(rm.RadioMsgError) as e:
        rm.Codec(SPEC).unpack(data)
    assert e.value.reason == "spec"
    assert f"{rm.spec_hash32(other):08x}" in str(e.value) and f"{rm.spec_hash32(SPEC):08x}" in str(e.value)
    bus = InProcessBus(SPEC.n_agents)
    rx = Radio(SPEC, 0, bus.endpoint(0))
    with caplog.at_level(logging.WARNING, logger="runtime.comms"):
        for _ in range(3):
            bus.endpoint(1).send(data)
        assert rx.poll(0.0, np.zeros(2), Neighbours(SPEC.n_agents)) == 0
    assert rx.stats.dropped_spec == 3 and rx.stats.dropped_malformed == 0
    assert len([r for r in caplog.records if "spec" in r.getMessage()]) == 1  # said once, not at 10 Hz


# --------------------------------------------------------------------------------------------------
# the generated C

_SHIM = r"""
#include <stddef.h>
#include <string.h>
#include "swarm_logic.h"

size_t shim_world_size(void) { return sizeof(swarm_world_t); }
void shim_set_epoch(swarm_world_t *w, uint16_t e) { w->epoch = e; }

/* ints: sender, epoch, seq, t_tx_ms, t_state_ms, n_sight, targets...; f: x, y, vx, vy, then age, x, y, vx, vy */
uint8_t shim_encode(const uint32_t *ints, const float *f, uint8_t *buf, uint8_t cap)
{
    swarm_msg_t m;
    uint8_t k;
    memset(&m, 0, sizeof(m));
    m.sender = (uint8_t)ints[0]; m.epoch = (uint16_t)ints[1]; m.seq = (uint16_t)ints[2];
    m.t_tx_ms = ints[3]; m.t_state_ms = ints[4]; m.n_sight = (uint8_t)ints[5];
    m.x = f[0]; m.y = f[1]; m.vx = f[2]; m.vy = f[3];
    for (k = 0; k < m.n_sight && k < SWARM_MSG_MAX_SIGHTINGS; ++k) {
        m.sight[k].target = (uint8_t)ints[6 + k];
        m.sight[k].age = f[4 + 5 * k]; m.sight[k].x = f[5 + 5 * k]; m.sight[k].y = f[6 + 5 * k];
        m.sight[k].vx = f[7 + 5 * k]; m.sight[k].vy = f[8 + 5 * k];
    }
    return swarm_msg_encode(&m, buf, cap);
}

/* ints: sender, role, epoch, seq, t_tx_ms, t_state_ms, n_sight, flags, targets...; f as above */
int shim_decode(const uint8_t *buf, uint8_t size, uint32_t *ints, float *f)
{
    swarm_msg_t m;
    uint8_t k;
    const int err = swarm_msg_decode(buf, size, &m);
    if (err != SWARM_MSG_OK) return err;
    ints[0] = m.sender; ints[1] = m.role; ints[2] = m.epoch; ints[3] = m.seq;
    ints[4] = m.t_tx_ms; ints[5] = m.t_state_ms; ints[6] = m.n_sight; ints[7] = m.flags;
    f[0] = m.x; f[1] = m.y; f[2] = m.vx; f[3] = m.vy;
    for (k = 0; k < m.n_sight; ++k) {
        ints[8 + k] = m.sight[k].target;
        f[4 + 5 * k] = m.sight[k].age; f[5 + 5 * k] = m.sight[k].x; f[6 + 5 * k] = m.sight[k].y;
        f[7 + 5 * k] = m.sight[k].vx; f[8 + 5 * k] = m.sight[k].vy;
    }
    return SWARM_MSG_OK;
}

/* f: x, y, vx, vy, seen_x, seen_y, seen_vx, seen_vy; ints: heard_ms, seen_ms, heard, seen */
void shim_agent(const swarm_world_t *w, uint8_t i, float *f, uint32_t *ints)
{
    const swarm_agent_t *a = &w->agents[i];
    f[0] = a->x; f[1] = a->y; f[2] = a->vx; f[3] = a->vy;
    f[4] = a->seen_x; f[5] = a->seen_y; f[6] = a->seen_vx; f[7] = a->seen_vy;
    ints[0] = a->heard_ms; ints[1] = a->seen_ms; ints[2] = a->heard; ints[3] = a->seen;
}
"""


def _generated_header(spec: SwarmSpec, role: Role = Role.PURSUER) -> str:
    rng = np.random.default_rng(0)
    dims = [spec.obs_dim(role), 8, 2]
    layers = tuple(Dense(rng.normal(0, 0.3, (b, a)).astype(F32), np.zeros(b, F32), act)
                   for a, b, act in zip(dims, dims[1:], ("relu", "tanh")))
    return cgen.generate(ActorModel(layers, spec, role, f"{role.label}_0", "test")).header


@pytest.fixture(scope="module")
def clib(tmp_path_factory):
    """The app's logic (template swarm_logic.c) and the generated message code, host-compiled for PARTIAL."""
    d: Path = tmp_path_factory.mktemp("radio_c")
    (d / "policy.h").write_text(_generated_header(PARTIAL))
    for name in ("swarm_logic.c", "swarm_logic.h"):
        (d / name).write_text((TEMPLATE_DIR / "src" / name).read_text())
    (d / "shim.c").write_text(_SHIM)
    lib = ctypes.CDLL(str(build_host_library([d / "swarm_logic.c", d / "shim.c"], d / "libradio.so",
                                             ("-O2", f"-I{d}"), APP_WARN_FLAGS)))
    u8, u16, u32, vp = ctypes.c_uint8, ctypes.c_uint16, ctypes.c_uint32, ctypes.c_void_p
    lib.shim_world_size.restype = ctypes.c_size_t
    lib.shim_encode.argtypes = [vp, vp, vp, u8]
    lib.shim_encode.restype = u8
    lib.shim_decode.argtypes = [vp, u8, vp, vp]
    lib.shim_agent.argtypes = [vp, u8, vp, vp]
    lib.shim_set_epoch.argtypes = [vp, u16]
    lib.swarm_world_init.argtypes = [vp, u8]
    lib.swarm_world_set_agent.argtypes = [vp, u8] + [ctypes.c_float] * 4 + [u32]
    lib.swarm_msg_pack.argtypes = [vp, vp, u8]
    lib.swarm_msg_pack.restype = u8
    lib.swarm_msg_receive.argtypes = [vp, vp, u8, u32]
    return lib


def test_the_generated_header_carries_the_table_and_the_template_copies_nothing():
    text = _generated_header(SPEC)
    for prefix, fields in (("OFF", rm.HEADER_FIELDS), ("SIGHT_OFF", rm.SIGHTING_FIELDS)):
        for f in fields:
            assert re.search(rf"#define SWARM_MSG_{prefix}_{f.name.upper()} {f.offset}u ", text), f.name
    for name, value in (("HEADER_SIZE", rm.HEADER.size), ("SIGHTING_SIZE", rm.SIGHTING.size),
                        ("MAX_SIGHTINGS", rm.MAX_SIGHTINGS), ("MAX_SIZE", rm.P2P_MAX_DATA_SIZE),
                        ("VERSION", rm.VERSION), ("SPEC_HASH32", rm.spec_hash32(SPEC))):
        assert re.search(rf"#define SWARM_MSG_{name} (0x[0-9a-f]+|\d+)u", text).group(1) in (
            str(value), f"0x{value:08x}", f"0x{value:02x}"), name
    for path in (TEMPLATE_DIR / "src").iterdir():  # sizes, offsets and magic live in the generated header only
        src = path.read_text()
        assert not re.search(r"#define SWARM_MSG_", src) and "0x53" not in src, path.name


def _c_encode(lib, sender, epoch, seq, t_tx_ms, t_state_ms, state, sights) -> bytes:
    ints = np.zeros(6 + rm.MAX_SIGHTINGS, np.uint32)
    ints[:6] = [sender, epoch, seq, t_tx_ms, t_state_ms, len(sights)]
    f = np.zeros(4 + 5 * rm.MAX_SIGHTINGS, F32)
    f[:4] = state
    for k, (e, age, *vals) in enumerate(sights):
        ints[6 + k] = e
        f[4 + 5 * k:9 + 5 * k] = [age, *vals]
    buf = (ctypes.c_uint8 * rm.P2P_MAX_DATA_SIZE)()
    n = lib.shim_encode(ints.ctypes.data, f.ctypes.data, buf, rm.P2P_MAX_DATA_SIZE)
    return bytes(buf[:n])


def _c_decode(lib, data: bytes):
    ints = np.zeros(8 + rm.MAX_SIGHTINGS, np.uint32)
    f = np.zeros(4 + 5 * rm.MAX_SIGHTINGS, F32)
    buf = (ctypes.c_uint8 * len(data)).from_buffer_copy(data) if data else (ctypes.c_uint8 * 1)()
    return lib.shim_decode(buf, len(data), ints.ctypes.data, f.ctypes.data), ints, f


def test_c_and_python_encode_the_same_bytes_and_decode_the_same_values(clib):
    codec = rm.Codec(PARTIAL)
    rng = np.random.default_rng(3)
    hw = 2 * PARTIAL.arena.half_width
    for k in range(100):
        n = k % (PARTIAL.team.n_evaders + 1)
        t_ms = int(rng.integers(0, 2**32))
        state = rng.uniform(-hw, hw, 4).astype(F32)
        state[2:] /= 4
        if k % 10 == 0:
            state[0] = 40.0  # saturates on both sides
        # whole ms, never on a half age step: the C rounds its float32 product, Python the double one
        ages_ms = sorted(a + (a % 12 == 6) for a in rng.integers(0, 2900, n).tolist())
        sv = rng.uniform(-hw, hw, (n, 4)).astype(F32)
        c_sights = [(e, F32(a / 1000), *sv[e]) for e, a in enumerate(ages_ms)]
        py_sights = [(e, *map(float, sv[e]), (t_ms - a) / 1000) for e, a in enumerate(ages_ms)]
        c_bytes = _c_encode(clib, k % PARTIAL.n_agents, k, k, t_ms, t_ms, state, c_sights)
        py_bytes = codec.pack(k % PARTIAL.n_agents, k, k, t_ms / 1000, t_ms / 1000, *map(float, state), py_sights)
        assert c_bytes == py_bytes, k
        err, ints, f = _c_decode(clib, py_bytes)
        m = codec.unpack(py_bytes, now=t_ms / 1000)
        assert err == 0
        assert list(ints[:8]) == [m.sender, m.role, m.epoch, m.seq, t_ms, t_ms, n, int(m.clamped)]
        np.testing.assert_allclose(f[:4], [m.x, m.y, m.vx, m.vy], rtol=1e-6)
        for j, g in enumerate(m.sightings):
            assert ints[8 + j] == g[0]
            np.testing.assert_allclose(f[5 + 5 * j:9 + 5 * j], g[1:5], rtol=1e-6)
            assert abs(m.t_state - float(f[4 + 5 * j]) - g[5]) < 1e-6


def test_c_rejects_what_python_rejects_with_the_same_reason(clib):
    codec = rm.Codec(PARTIAL)
    good = codec.pack(0, 0, 0, 0.0, 0.0, 0, 0, 0, 0)
    h = dict(zip([f.name for f in rm.HEADER_FIELDS], rm.HEADER.unpack(good)))
    cases = [good[:10], rm.Codec(_other_spec(PARTIAL)).pack(0, 0, 0, 0.0, 0.0, 0, 0, 0, 0)]
    cases += [rm.HEADER.pack(*{**h, **c}.values()) for c in (
        {"magic": 1}, {"version": 9}, {"sender": 200}, {"role": 1}, {"n_sight": 1}, {"vy": rm.NAN_RAW})]
    cases.append(rm.HEADER.pack(*{**h, "n_sight": 1}.values()) + rm.SIGHTING.pack(0, 0, 0, 0, 0, rm.NAN_RAW))
    cases.append(good + b"\x00")  # longer than it says
    cases.append(rm.HEADER.pack(*{**h, "n_sight": 1}.values()) + rm.SIGHTING.pack(9, 0, 0, 0, 0, 0))
    for data in cases:
        with pytest.raises(rm.RadioMsgError) as e:
            codec.unpack(data)
        err, _, _ = _c_decode(clib, data)
        assert err == 1 + cgen._MSG_ERRORS.index(e.value.reason), (e.value.reason, err)


def _c_world(lib, me: int):
    w = ctypes.create_string_buffer(lib.shim_world_size())
    assert lib.swarm_world_init(w, me) == 1
    return w


def _c_agent(lib, w, i: int):
    f, ints = np.zeros(8, F32), np.zeros(4, np.uint32)
    lib.shim_agent(w, i, f.ctypes.data, ints.ctypes.data)
    return f, ints


def test_the_c_app_and_the_python_runtime_hear_each_other(clib):
    spec, nt = PARTIAL, PARTIAL.team.n_team
    s = rm.Scales.for_spec(spec)
    # C app, pursuer 0: its own state, and two evaders it senses itself (within sensing range)
    w = _c_world(clib, 0)
    clib.swarm_world_set_agent(w, 0, 0.5, -0.25, 0.1, 0.2, 12000)
    clib.swarm_world_set_agent(w, nt + 1, 0.25, -0.125, -0.2, 0.05, 12000)
    clib.swarm_world_set_agent(w, nt, 0.75, -0.5, 0.3, -0.1, 12300)
    clib.swarm_world_set_agent(w, 0, 0.5, -0.25, 0.1, 0.2, 12345)
    buf = (ctypes.c_uint8 * rm.P2P_MAX_DATA_SIZE)()
    n = clib.swarm_msg_pack(w, buf, rm.P2P_MAX_DATA_SIZE)
    c_bytes = bytes(buf[:n])
    f32 = [float(F32(v)) for v in (0.5, -0.25, 0.1, 0.2, 0.75, -0.5, 0.3, -0.1, 0.25, -0.125, -0.2, 0.05)]
    want = rm.Codec(spec).pack(0, 0, 0, 12.345, 12.345, *f32[:4],
                               [(0, *f32[4:8], 12.3), (1, *f32[8:12], 12.0)])  # freshest first
    assert c_bytes == want
    # ... heard by the Python runtime of scout 5 (the channel as on the drones: exact_values off)
    bus = InProcessBus(spec.n_agents)
    py = Radio(spec, 5, bus.endpoint(5), CommConfig(exact_values=False))
    bus.endpoint(0).send(c_bytes)
    table, kn = Neighbours(spec.n_agents), np.zeros((spec.team.n_evaders, 5))
    kn[:, 4] = -np.inf
    assert py.poll(12.4, np.array([0.5, 0.5]), table, kn) == 1
    np.testing.assert_allclose(table.pos[0], [0.5, -0.25], atol=s.pos_lsb / 2)
    np.testing.assert_allclose(table.vel[0], [0.1, 0.2], atol=s.vel_lsb / 2)
    assert table.t_state[0] == 12.345
    np.testing.assert_allclose(kn[0, :4], [0.75, -0.5, 0.3, -0.1], atol=s.pos_lsb / 2)
    np.testing.assert_allclose(kn[:, 4], [12.3, 12.0], atol=s.age_lsb / 2)
    # the other way: the Python runtime of pursuer 1 broadcasts, the C app of pursuer 0 hears it
    py1 = Radio(spec, 1, bus.endpoint(1), CommConfig(exact_values=False))
    sight = np.zeros((spec.team.n_evaders, 5))
    sight[:, 4] = -np.inf
    sight[1] = [-0.6, 1.1, 0.25, -0.5, 19.6]
    assert py1.broadcast(20.0, 19.95, np.array([-1.234, 2.5]), np.array([0.4, -0.3]), sight)
    py_bytes = bus.queues[0][-1]
    assert len(py_bytes) == rm.message_size(1)
    buf = (ctypes.c_uint8 * len(py_bytes)).from_buffer_copy(py_bytes)
    assert clib.swarm_msg_receive(w, buf, len(py_bytes), 20000) == 1
    f, ints = _c_agent(clib, w, 1)
    np.testing.assert_allclose(f[:4], [-1.234, 2.5, 0.4, -0.3], atol=s.pos_lsb / 2 + 1e-6)
    assert ints[0] == 20000 and ints[2] == 1
    f, ints = _c_agent(clib, w, nt + 1)  # the relayed sighting is fresher than pursuer 0's own (12.0 s)
    np.testing.assert_allclose(f[4:8], [-0.6, 1.1, 0.25, -0.5], atol=s.pos_lsb / 2 + 1e-6)
    assert ints[3] == 1 and abs(int(ints[1]) - (20000 - 350)) <= s.age_lsb * 500
    # another epoch is ignored; another spec is refused with its reason; our own echo is ignored
    clib.shim_set_epoch(w, 3)
    assert clib.swarm_msg_receive(w, buf, len(py_bytes), 20100) == 0
    foreign = rm.Codec(_other_spec(spec)).pack(1, 3, 0, 20.1, 20.1, 0, 0, 0, 0)
    fb = (ctypes.c_uint8 * len(foreign)).from_buffer_copy(foreign)
    assert clib.swarm_msg_receive(w, fb, len(foreign), 20100) == -(1 + cgen._MSG_ERRORS.index("spec"))
    own = (ctypes.c_uint8 * len(c_bytes)).from_buffer_copy(c_bytes)
    clib.shim_set_epoch(w, 0)
    assert clib.swarm_msg_receive(w, own, len(c_bytes), 20100) == 0
