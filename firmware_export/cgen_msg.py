"""The neighbour radio message in C for ``policy.h``: defines, the struct, packing and parsing with their
rejection reasons, all generated from ``runtime.radio_msg`` (the one definition) so that the Crazyflie app and
the Python runtime speak the same 60-byte packet (``tests/test_radio_msg.py`` has them exchange messages)."""
from __future__ import annotations

MSG_PREFIX = "SWARM_MSG"
_MSG_ERRORS = ("size", "magic", "version", "spec", "sender", "role", "target", "non-finite")
_MSG_PUT = {"uint8_t": "u8", "uint16_t": "u16", "uint32_t": "u32", "int16_t": "i16"}
_MSG_CONST = {"magic": f"{MSG_PREFIX}_MAGIC", "version": f"{MSG_PREFIX}_VERSION",
              "spec_hash": f"{MSG_PREFIX}_SPEC_HASH32"}


def _msg_defines(spec) -> list[str]:
    from firmware_export.cgen import c_float, c_ident
    from runtime import radio_msg as rm
    sc = rm.Scales.for_spec(spec)
    lines = [
        "/* Neighbour radio message, generated from runtime.radio_msg (the one definition; see its table for",
        " * units and ranges): little endian, header then n_sight sightings, at most one P2P packet. */",
        f"#define {MSG_PREFIX}_MAGIC 0x{rm.MAGIC:02x}u",
        f"#define {MSG_PREFIX}_VERSION {rm.VERSION}u",
        f"#define {MSG_PREFIX}_SPEC_HASH32 0x{rm.spec_hash32(spec):08x}u /* first 32 bits of the spec hash */",
        f"#define {MSG_PREFIX}_HEADER_SIZE {rm.HEADER.size}u",
        f"#define {MSG_PREFIX}_SIGHTING_SIZE {rm.SIGHTING.size}u",
        f"#define {MSG_PREFIX}_MAX_SIGHTINGS {rm.MAX_SIGHTINGS}u /* that fit in {rm.P2P_MAX_DATA_SIZE} B */",
        f"#define {MSG_PREFIX}_RELAY_SIGHTINGS {min(rm.MAX_SIGHTINGS, spec.team.n_evaders)}u "
        "/* this spec: min(evaders, MAX_SIGHTINGS) */",
        f"#define {MSG_PREFIX}_MAX_SIZE {rm.P2P_MAX_DATA_SIZE}u /* crazyflie-firmware P2P_MAX_DATA_SIZE */",
        f"#define {MSG_PREFIX}_SIZE(n) ({MSG_PREFIX}_HEADER_SIZE + (n) * {MSG_PREFIX}_SIGHTING_SIZE)",
        f"#define {MSG_PREFIX}_FLAG_CLAMPED 0x{rm.FLAG_CLAMPED:02x}u /* a value was saturated */",
        f"#define {MSG_PREFIX}_NAN_RAW ({rm.NAN_RAW}) /* int16: not a number, the message is rejected */",
        f"#define {MSG_PREFIX}_I16_MAX {rm.I16_MAX}",
        f"#define {MSG_PREFIX}_AGE_MAX {rm.AGE_MAX}",
    ]
    for name in ("pos_lsb", "vel_lsb", "age_lsb"):
        v = getattr(sc, name)
        unit = {"pos_lsb": "m", "vel_lsb": "m/s", "age_lsb": "s"}[name]
        lines.append(f"#define {MSG_PREFIX}_{name.upper()} {c_float(v)} /* [{unit}] one step */")
        lines.append(f"#define {MSG_PREFIX}_{name.upper()}_MS {round(v * 1000)}u /* the step in thousandths */")
    for prefix, fields in (("OFF", rm.HEADER_FIELDS), ("SIGHT_OFF", rm.SIGHTING_FIELDS)):
        for f in fields:
            lines.append(f"#define {MSG_PREFIX}_{prefix}_{c_ident(f.name)} {f.offset}u /* {f.ctype}: {f.doc} */")
    lines.append(f"enum {{ {MSG_PREFIX}_OK = 0, "
                 + ", ".join(f"{MSG_PREFIX}_ERR_{c_ident(e)}" for e in _MSG_ERRORS) + " };")
    return lines


def _msg_member(f) -> str:
    return f"float {f.name};" if f.scale else f"{f.ctype} {f.name};"


def _msg_pack_lines(fields, base: str, src: str) -> list[str]:
    from firmware_export.cgen import c_ident
    out = []
    for f in fields:
        put = _MSG_PUT[f.ctype]
        off = f"{MSG_PREFIX}_{'OFF' if base == 'buf' else 'SIGHT_OFF'}_{c_ident(f.name)}"
        if f.name in _MSG_CONST and base == "buf":
            val = _MSG_CONST[f.name]
        elif f.name == "role" and base == "buf":
            val = f"swarm_msg_role_of({src}sender)"
        elif f.name == "flags":
            val = f"(uint8_t)({src}flags | (clamped ? {MSG_PREFIX}_FLAG_CLAMPED : 0u))"
        elif f.ctype == "uint8_t" and f.scale:
            val = f"swarm_msg_q_age({src}{f.name}, &clamped)"
        elif f.scale:
            val = f"swarm_msg_q16({src}{f.name}, 1.0f / {MSG_PREFIX}_{f.scale.upper()}, &clamped)"
        else:
            val = f"{src}{f.name}"
        out.append(f"    swarm_msg_put_{put}({base} + {off}, {val});")
    # the flags last: they say whether any value above was saturated
    return sorted(out, key=lambda ln: "_OFF_FLAGS," in ln)


def _msg_unpack_lines(fields, base: str, dst: str) -> list[str]:
    from firmware_export.cgen import c_ident
    out = []
    for f in fields:
        get = _MSG_PUT[f.ctype]
        off = f"{MSG_PREFIX}_{'OFF' if base == 'buf' else 'SIGHT_OFF'}_{c_ident(f.name)}"
        if f.name in _MSG_CONST and base == "buf":
            continue
        if f.ctype == "int16_t" and f.scale:
            out.append(f"    if (swarm_msg_get_i16({base} + {off}) == {MSG_PREFIX}_NAN_RAW) "
                       f"return {MSG_PREFIX}_ERR_NON_FINITE;")
            out.append(f"    {dst}{f.name} = (float)swarm_msg_get_i16({base} + {off}) * "
                       f"{MSG_PREFIX}_{f.scale.upper()};")
        elif f.scale:
            out.append(f"    {dst}{f.name} = (float)swarm_msg_get_{get}({base} + {off}) * "
                       f"{MSG_PREFIX}_{f.scale.upper()};")
        else:
            out.append(f"    {dst}{f.name} = swarm_msg_get_{get}({base} + {off});")
    return out


def radio_msg_text(spec) -> list[str]:
    """C99 text (for policy.h) of the radio message: constants, struct, static inline encode and decode."""
    from runtime import radio_msg as rm
    np_, nt = spec.team.n_pursuers, spec.team.n_team
    hdr_scaled = [f for f in rm.HEADER_FIELDS if f.name not in _MSG_CONST and f.name not in ("n_sight",)]
    lines = _msg_defines(spec) + [
        "",
        "typedef struct {",
        *[f"    {_msg_member(f)} /* {f.doc} */" for f in rm.SIGHTING_FIELDS],
        "} swarm_msg_sighting_t;",
        "",
        "typedef struct {",
        *[f"    {_msg_member(f)} /* {f.doc} */" for f in hdr_scaled],
        "    uint8_t n_sight; /* sightings that follow */",
        f"    swarm_msg_sighting_t sight[{MSG_PREFIX}_MAX_SIGHTINGS];",
        "} swarm_msg_t;",
        "",
        "static inline void swarm_msg_put_u8(uint8_t *p, uint8_t v) { p[0] = v; }",
        "static inline void swarm_msg_put_u16(uint8_t *p, uint16_t v) { p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); }",
        "static inline void swarm_msg_put_u32(uint8_t *p, uint32_t v)",
        "{",
        "    p[0] = (uint8_t)v; p[1] = (uint8_t)(v >> 8); p[2] = (uint8_t)(v >> 16); p[3] = (uint8_t)(v >> 24);",
        "}",
        "static inline void swarm_msg_put_i16(uint8_t *p, int16_t v) { swarm_msg_put_u16(p, (uint16_t)v); }",
        "static inline uint8_t swarm_msg_get_u8(const uint8_t *p) { return p[0]; }",
        "static inline uint16_t swarm_msg_get_u16(const uint8_t *p) { return (uint16_t)(p[0] | (p[1] << 8)); }",
        "static inline uint32_t swarm_msg_get_u32(const uint8_t *p)",
        "{",
        "    return (uint32_t)p[0] | ((uint32_t)p[1] << 8) | ((uint32_t)p[2] << 16) | ((uint32_t)p[3] << 24);",
        "}",
        "static inline int16_t swarm_msg_get_i16(const uint8_t *p) { return (int16_t)swarm_msg_get_u16(p); }",
        "",
        "/* Nearest step; NaN (tested on the bits: -ffast-math keeps it) to NAN_RAW; out of range saturates and",
        " * sets *clamped, never wraps. */",
        "static inline int16_t swarm_msg_q16(float v, float inv_lsb, uint8_t *clamped)",
        "{",
        "    uint32_t bits;",
        "    float q;",
        "    memcpy(&bits, &v, 4);",
        f"    if ((bits & 0x7f800000u) == 0x7f800000u && (bits & 0x007fffffu)) return {MSG_PREFIX}_NAN_RAW;",
        "    q = v * inv_lsb;",
        f"    if (q >= (float){MSG_PREFIX}_I16_MAX + 0.5f) {{ *clamped = 1; return {MSG_PREFIX}_I16_MAX; }}",
        f"    if (q <= -(float){MSG_PREFIX}_I16_MAX - 0.5f) {{ *clamped = 1; return -{MSG_PREFIX}_I16_MAX; }}",
        "    return (int16_t)(q >= 0.0f ? q + 0.5f : q - 0.5f);",
        "}",
        "",
        "static inline uint8_t swarm_msg_q_age(float age_s, uint8_t *clamped)",
        "{",
        f"    const float q = age_s * (1.0f / {MSG_PREFIX}_AGE_LSB);",
        "    uint32_t bits;",
        "    memcpy(&bits, &q, 4);",
        "    if ((bits & 0x7f800000u) == 0x7f800000u || q >= (float)SWARM_MSG_AGE_MAX + 0.5f) {",
        f"        *clamped = 1; return {MSG_PREFIX}_AGE_MAX; /* non-finite or too old */",
        "    }",
        "    if (q <= -0.5f) { *clamped = 1; return 0; }",
        "    return (uint8_t)(q > 0.0f ? q + 0.5f : 0.0f);",
        "}",
        "",
        "/* Role of an agent index in spec order (pursuers, scouts, evaders), as runtime.spec.Role. */",
        "static inline uint8_t swarm_msg_role_of(uint8_t index)",
        "{",
        f"    return (uint8_t)(index < {np_} ? 0 : (index < {nt} ? 1 : 2));",
        "}",
        "",
        "/* Write m (role from m->sender, n_sight at most RELAY_SIGHTINGS) into buf; returns the size, 0 when cap is",
        " * too small or n_sight too large. */",
        "static inline uint8_t swarm_msg_encode(const swarm_msg_t *m, uint8_t *buf, uint8_t cap)",
        "{",
        "    uint8_t clamped = 0, k;",
        f"    if (m->n_sight > {MSG_PREFIX}_RELAY_SIGHTINGS || cap < {MSG_PREFIX}_SIZE(m->n_sight)) return 0;",
        "    for (k = 0; k < m->n_sight; ++k) {",
        f"        uint8_t *s = buf + {MSG_PREFIX}_SIZE(k);",
        "        const swarm_msg_sighting_t *g = &m->sight[k];",
        *["    " + ln for ln in _msg_pack_lines(rm.SIGHTING_FIELDS, "s", "g->")],
        "    }",
        *_msg_pack_lines(rm.HEADER_FIELDS, "buf", "m->"),
        f"    return (uint8_t){MSG_PREFIX}_SIZE(m->n_sight);",
        "}",
        "",
        "/* Parse buf into m; returns SWARM_MSG_OK or the SWARM_MSG_ERR_* naming why it is not usable here. */",
        "static inline int swarm_msg_decode(const uint8_t *buf, uint8_t size, swarm_msg_t *m)",
        "{",
        "    uint8_t k;",
        f"    if (size < {MSG_PREFIX}_HEADER_SIZE) return {MSG_PREFIX}_ERR_SIZE;",
        f"    if (buf[{MSG_PREFIX}_OFF_MAGIC] != {MSG_PREFIX}_MAGIC) return {MSG_PREFIX}_ERR_MAGIC;",
        f"    if (buf[{MSG_PREFIX}_OFF_VERSION] != {MSG_PREFIX}_VERSION) return {MSG_PREFIX}_ERR_VERSION;",
        f"    if (swarm_msg_get_u32(buf + {MSG_PREFIX}_OFF_SPEC_HASH) != {MSG_PREFIX}_SPEC_HASH32) "
        f"return {MSG_PREFIX}_ERR_SPEC;",
        *_msg_unpack_lines([f for f in rm.HEADER_FIELDS if f.scale == ""], "buf", "m->"),
        f"    if (m->sender >= {spec.n_agents}) return {MSG_PREFIX}_ERR_SENDER;",
        f"    if (m->role != swarm_msg_role_of(m->sender)) return {MSG_PREFIX}_ERR_ROLE;",
        f"    if (m->n_sight > {MSG_PREFIX}_RELAY_SIGHTINGS || size != {MSG_PREFIX}_SIZE(m->n_sight)) "
        f"return {MSG_PREFIX}_ERR_SIZE;",
        *_msg_unpack_lines([f for f in rm.HEADER_FIELDS if f.scale], "buf", "m->"),
        "    for (k = 0; k < m->n_sight; ++k) {",
        f"        const uint8_t *s = buf + {MSG_PREFIX}_SIZE(k);",
        "        swarm_msg_sighting_t *g = &m->sight[k];",
        *["    " + ln for ln in _msg_unpack_lines(rm.SIGHTING_FIELDS, "s", "g->")],
        f"        if (g->target >= {spec.team.n_evaders}) return {MSG_PREFIX}_ERR_TARGET;",
        "    }",
        f"    return {MSG_PREFIX}_OK;",
        "}",
    ]
    return lines
