/* See swarm_logic.h. Mirrors runtime/observation.py: nearest-first slots with ties to the lower agent index,
 * missing slots all zero, targets in fixed evader order with their age clamped to the target memory. */
#include "swarm_logic.h"

#include <math.h>
#include <string.h>

typedef char swarm_check_agents_fit_mask[(SWARM_N_AGENTS <= 32) ? 1 : -1];

#if SWARM_POLICY_ROLE_ID == 0
#define SWARM_ROLE_FIRST 0
#define SWARM_ROLE_END SWARM_SPEC_N_PURSUERS
#elif SWARM_POLICY_ROLE_ID == 1
#define SWARM_ROLE_FIRST SWARM_SPEC_N_PURSUERS
#define SWARM_ROLE_END SWARM_N_TEAM
#else
#define SWARM_ROLE_FIRST SWARM_N_TEAM
#define SWARM_ROLE_END SWARM_N_AGENTS
#endif

int swarm_world_init(swarm_world_t *w, uint8_t self)
{
    memset(w, 0, sizeof(*w));
    w->self = self;
    return (int)self - SWARM_ROLE_FIRST >= 0 && self < SWARM_ROLE_END;
}

static int is_team(int index) { return index < SWARM_N_TEAM; }

static float dist2(const swarm_agent_t *a, float x, float y)
{
    const float dx = a->x - x, dy = a->y - y;
    return dx * dx + dy * dy;
}

void swarm_world_set_agent(swarm_world_t *w, uint8_t index, float x, float y, float vx, float vy, uint32_t now_ms)
{
    swarm_agent_t *a;
    const swarm_agent_t *me = &w->agents[w->self];
    if (index >= SWARM_N_AGENTS) return;
    a = &w->agents[index];
    a->x = x; a->y = y; a->vx = vx; a->vy = vy;
    a->heard_ms = now_ms;
    a->heard = 1;
    /* own sensing of an evader (the sim's update_knowledge); relayed sightings arrive in swarm_msg_receive */
    if (index != w->self && !is_team(index) && is_team(w->self) && me->heard
        && dist2(a, me->x, me->y) <= SWARM_SPEC_SENSING_RANGE * SWARM_SPEC_SENSING_RANGE) {
        a->seen_x = x; a->seen_y = y; a->seen_vx = vx; a->seen_vy = vy;
        a->seen_ms = now_ms;
        a->seen = 1;
    }
}

int swarm_world_set_obstacle(swarm_world_t *w, uint8_t slot, float x, float y, float r)
{
    if (slot >= SWARM_MAX_OBSTACLES) return 0;
    w->obstacles[slot].x = x; w->obstacles[slot].y = y; w->obstacles[slot].r = r;
    if (slot >= w->n_obstacles) w->n_obstacles = (uint8_t)(slot + 1);
    return 1;
}

/* ------------------------------------------------------------------------------------------ radio */

/* A pursuer-team drone's knowledge of evader k: its own sensing (partial observability) or what it heard. */
static int target_known(const swarm_agent_t *e, uint32_t *at_ms)
{
    *at_ms = SWARM_SPEC_FULL_OBSERVABILITY ? e->heard_ms : e->seen_ms;
    return SWARM_SPEC_FULL_OBSERVABILITY ? e->heard : e->seen;
}

uint8_t swarm_msg_pack(swarm_world_t *w, uint8_t *buf, uint8_t cap)
{
    const swarm_agent_t *me = &w->agents[w->self];
    swarm_msg_t m;
    uint32_t age[SWARM_SPEC_N_EVADERS];
    uint32_t used = 0;  /* evaders < agents <= 32 (swarm_check_agents_fit_mask) */
    uint8_t k, size;
    memset(&m, 0, sizeof(m));
    m.sender = w->self;
    m.epoch = w->epoch;
    m.seq = w->seq;
    m.t_tx_ms = m.t_state_ms = me->heard_ms;
    m.x = me->x; m.y = me->y; m.vx = me->vx; m.vy = me->vy;
    for (k = 0; k < SWARM_SPEC_N_EVADERS; ++k) {
        uint32_t at;
        age[k] = UINT32_MAX;  /* not known, or as old as the target memory: not relayed */
        if (is_team(w->self) && target_known(&w->agents[SWARM_N_TEAM + k], &at)
            && (float)(me->heard_ms - at) < SWARM_SPEC_TARGET_MEMORY * 1000.0f)
            age[k] = me->heard_ms - at;
    }
    /* runtime.radio_msg's relay policy: freshest first (ties: lower evader), as many as fit */
    while (m.n_sight < SWARM_MSG_RELAY_SIGHTINGS && cap >= SWARM_MSG_SIZE(m.n_sight + 1)) {
        int best = -1;
        for (k = 0; k < SWARM_SPEC_N_EVADERS; ++k) {
            if (age[k] == UINT32_MAX || (used >> k) & 1u) continue;
            if (best < 0 || age[k] < age[best]) best = k;
        }
        if (best < 0) break;
        used |= 1u << best;
        {
            const swarm_agent_t *e = &w->agents[SWARM_N_TEAM + best];
            swarm_msg_sighting_t *g = &m.sight[m.n_sight++];
            g->target = (uint8_t)best;
            g->age = (float)age[best] * 0.001f;
            g->x = SWARM_SPEC_FULL_OBSERVABILITY ? e->x : e->seen_x;
            g->y = SWARM_SPEC_FULL_OBSERVABILITY ? e->y : e->seen_y;
            g->vx = SWARM_SPEC_FULL_OBSERVABILITY ? e->vx : e->seen_vx;
            g->vy = SWARM_SPEC_FULL_OBSERVABILITY ? e->vy : e->seen_vy;
        }
    }
    size = swarm_msg_encode(&m, buf, cap);
    if (size) w->seq++;
    return size;
}

int swarm_msg_receive(swarm_world_t *w, const uint8_t *buf, uint8_t size, uint32_t now_ms)
{
    swarm_msg_t m;
    uint8_t k;
    const int err = swarm_msg_decode(buf, size, &m);
    if (err != SWARM_MSG_OK) return -err;
    if (m.sender == w->self || m.epoch != w->epoch) return 0;
    swarm_world_set_agent(w, m.sender, m.x, m.y, m.vx, m.vy, now_ms);
    /* relayed sightings (runtime.observation.update_knowledge's one hop): a fresher one replaces ours */
    if (!SWARM_SPEC_FULL_OBSERVABILITY && is_team(w->self) && is_team(m.sender)) {
        for (k = 0; k < m.n_sight; ++k) {
            const swarm_msg_sighting_t *g = &m.sight[k];
            swarm_agent_t *e = &w->agents[SWARM_N_TEAM + g->target];
            const uint32_t at = now_ms - (uint32_t)(g->age * 1000.0f + 0.5f);
            if (e->seen && (int32_t)(at - e->seen_ms) <= 0) continue;
            e->seen_x = g->x; e->seen_y = g->y; e->seen_vx = g->vx; e->seen_vy = g->vy;
            e->seen_ms = at;
            e->seen = 1;
        }
    }
    return 1;
}

/* ------------------------------------------------------------------------------------ observation */

/* rows x 5 (dx, dy, vx, vy, valid) of the nearest agents in [first, end) that are heard, recent, not self and
 * within range (any distance with full observability). */
static void fill_agents(const swarm_world_t *w, uint32_t now_ms, int first, int end, float range, int rows,
                        float *out)
{
    const swarm_agent_t *me = &w->agents[w->self];
    float d2[SWARM_N_AGENTS];
    uint32_t taken = 0;
    int i, s;
    for (i = first; i < end; ++i) {
        const swarm_agent_t *a = &w->agents[i];
        d2[i] = -1.0f;
        if (i == w->self || !a->heard || now_ms - a->heard_ms > SWARM_PEER_TIMEOUT_MS) continue;
        d2[i] = dist2(a, me->x, me->y);
        if (!SWARM_SPEC_FULL_OBSERVABILITY && d2[i] > range * range) d2[i] = -1.0f;
    }
    for (s = 0; s < rows; ++s) {
        float *row = out + 5 * s;
        int best = -1;
        for (i = first; i < end; ++i) {
            if (d2[i] < 0.0f || (taken >> i) & 1u) continue;
            if (best < 0 || d2[i] < d2[best]) best = i;
        }
        if (best < 0) {
            row[0] = row[1] = row[2] = row[3] = row[4] = 0.0f;
            continue;
        }
        taken |= 1u << best;
        row[0] = w->agents[best].x - me->x;
        row[1] = w->agents[best].y - me->y;
        row[2] = w->agents[best].vx;
        row[3] = w->agents[best].vy;
        row[4] = 1.0f;
    }
}

static void fill_obstacles(const swarm_world_t *w, float *out)
{
    const swarm_agent_t *me = &w->agents[w->self];
    float surf[SWARM_MAX_OBSTACLES];
    uint32_t taken = 0;
    int i, s;
    for (i = 0; i < w->n_obstacles; ++i) {
        const float dx = w->obstacles[i].x - me->x, dy = w->obstacles[i].y - me->y;
        surf[i] = sqrtf(dx * dx + dy * dy) - w->obstacles[i].r;
    }
    for (s = 0; s < SWARM_OBS_OBSTACLES_ROWS; ++s) {
        float *row = out + SWARM_OBS_OBSTACLES_COLS * s;
        int best = -1;
        for (i = 0; i < w->n_obstacles; ++i) {
            if ((taken >> i) & 1u) continue;
            if (best < 0 || surf[i] < surf[best]) best = i;
        }
        if (best < 0) {
            row[SWARM_OBS_OBSTACLES_DX] = row[SWARM_OBS_OBSTACLES_DY] = row[SWARM_OBS_OBSTACLES_RADIUS] = 0.0f;
            continue;
        }
        taken |= 1u << best;
        row[SWARM_OBS_OBSTACLES_DX] = w->obstacles[best].x - me->x;
        row[SWARM_OBS_OBSTACLES_DY] = w->obstacles[best].y - me->y;
        row[SWARM_OBS_OBSTACLES_RADIUS] = w->obstacles[best].r;
    }
}

#if !SWARM_POLICY_ROLE_IS_EVADER
static void fill_targets(const swarm_world_t *w, uint32_t now_ms, float *out)
{
    const swarm_agent_t *me = &w->agents[w->self];
    int k;
    for (k = 0; k < SWARM_OBS_TARGETS_ROWS; ++k) {
        const swarm_agent_t *e = &w->agents[SWARM_N_TEAM + k];
        float *row = out + SWARM_OBS_TARGETS_COLS * k;
        const int have = SWARM_SPEC_FULL_OBSERVABILITY ? e->heard : e->seen;
        const uint32_t at = SWARM_SPEC_FULL_OBSERVABILITY ? e->heard_ms : e->seen_ms;
        const float age = (float)(now_ms - at) * 0.001f;
        if (!have || !(age < SWARM_SPEC_TARGET_MEMORY)) {
            row[SWARM_OBS_TARGETS_DX] = row[SWARM_OBS_TARGETS_DY] = 0.0f;
            row[SWARM_OBS_TARGETS_VX] = row[SWARM_OBS_TARGETS_VY] = 0.0f;
            row[SWARM_OBS_TARGETS_AGE] = SWARM_SPEC_TARGET_MEMORY;
            row[SWARM_OBS_TARGETS_KNOWN] = 0.0f;
            continue;
        }
        row[SWARM_OBS_TARGETS_DX] = (SWARM_SPEC_FULL_OBSERVABILITY ? e->x : e->seen_x) - me->x;
        row[SWARM_OBS_TARGETS_DY] = (SWARM_SPEC_FULL_OBSERVABILITY ? e->y : e->seen_y) - me->y;
        row[SWARM_OBS_TARGETS_VX] = SWARM_SPEC_FULL_OBSERVABILITY ? e->vx : e->seen_vx;
        row[SWARM_OBS_TARGETS_VY] = SWARM_SPEC_FULL_OBSERVABILITY ? e->vy : e->seen_vy;
        row[SWARM_OBS_TARGETS_AGE] = age;
        row[SWARM_OBS_TARGETS_KNOWN] = 1.0f;
    }
}
#endif

void swarm_build_observation(const swarm_world_t *w, uint32_t now_ms, float obs[SWARM_POLICY_OBS_DIM])
{
    const swarm_agent_t *me = &w->agents[w->self];
    obs[SWARM_OBS_SELF_POS_START + SWARM_OBS_SELF_POS_X] = me->x;
    obs[SWARM_OBS_SELF_POS_START + SWARM_OBS_SELF_POS_Y] = me->y;
    obs[SWARM_OBS_SELF_VEL_START + SWARM_OBS_SELF_VEL_VX] = me->vx;
    obs[SWARM_OBS_SELF_VEL_START + SWARM_OBS_SELF_VEL_VY] = me->vy;
    fill_obstacles(w, obs + SWARM_OBS_OBSTACLES_START);
#if SWARM_POLICY_ROLE_IS_EVADER
    fill_agents(w, now_ms, 0, SWARM_N_TEAM, SWARM_SPEC_SENSING_RANGE, SWARM_OBS_THREATS_ROWS,
                obs + SWARM_OBS_THREATS_START);
    fill_agents(w, now_ms, SWARM_N_TEAM, SWARM_N_AGENTS, SWARM_SPEC_COMM_RANGE, SWARM_OBS_TEAMMATES_ROWS,
                obs + SWARM_OBS_TEAMMATES_START);
#else
    fill_targets(w, now_ms, obs + SWARM_OBS_TARGETS_START);
    fill_agents(w, now_ms, 0, SWARM_N_TEAM, SWARM_SPEC_COMM_RANGE, SWARM_OBS_TEAMMATES_ROWS,
                obs + SWARM_OBS_TEAMMATES_START);
#endif
}

/* -------------------------------------------------------------------------------------- avoidance */

#if SWARM_AVOID_ENABLED
/* Not NaN and not infinite, tested on the bits (no compiler flag can fold it away). */
static int finite_bits(float v)
{
    uint32_t bits;
    memcpy(&bits, &v, sizeof(bits));
    return (bits & 0x7f800000u) != 0x7f800000u;
}

/* The layout swarm_avoid reads is the one the observation encoder writes (both generated from the spec). */
typedef char swarm_check_avoid_layout[(SWARM_AVOID_SELF_POS == SWARM_OBS_SELF_POS_START
    && SWARM_AVOID_OBSTACLES == SWARM_OBS_OBSTACLES_START && SWARM_AVOID_N_OBSTACLES == SWARM_OBS_OBSTACLES_ROWS
    && SWARM_AVOID_OBSTACLE_COLS == SWARM_OBS_OBSTACLES_COLS && SWARM_AVOID_MATES == SWARM_OBS_TEAMMATES_START
    && SWARM_AVOID_N_MATES == SWARM_OBS_TEAMMATES_ROWS && SWARM_AVOID_MATE_COLS == SWARM_OBS_TEAMMATES_COLS
    && SWARM_OBS_TEAMMATES_VALID == SWARM_AVOID_MATE_COLS - 1 && SWARM_OBS_OBSTACLES_RADIUS == 2) ? 1 : -1];

#define SWARM_AVOID_N_CON (SWARM_AVOID_N_MATES + 4 + SWARM_AVOID_N_OBSTACLES)

/* runtime.avoidance._limit: the approach speed [m/s] allowed at `gap` from a surface. */
static float avoid_limit(float gap, float margin)
{
    const float g = gap - margin;
    float brake, step;
    if (!(g > 0.0f)) return 0.0f;
    brake = sqrtf(2.0f * SWARM_AVOID_BRAKING * g);
    step = g / SWARM_AVOID_DT;
    return step < brake ? step : brake;
}
#endif

/* runtime.avoidance.avoid_rows for one row: the same constraints in the same order (teammates, walls +x -x
 * +y -y, obstacles), the same cyclic projection and the same final speed limit, in float. The action is
 * written back only when the layer changed the velocity, so a safe action stays bit for bit what the policy
 * returned (as in Python, whose float64 round trip act * v / v rounds back to the float32 action). */
void swarm_avoid(const float obs[SWARM_POLICY_OBS_DIM], float act[SWARM_POLICY_ACT_DIM])
{
#if SWARM_AVOID_ENABLED
    float nx[SWARM_AVOID_N_CON], ny[SWARM_AVOID_N_CON], lim[SWARM_AVOID_N_CON];
    uint8_t use[SWARM_AVOID_N_CON];
    float x, y, vx, vy, speed;
    int i, k, c = 0, changed = 0;
    for (i = 0; i < SWARM_POLICY_OBS_DIM; ++i) {
        if (!finite_bits(obs[i])) return;
    }
    if (!finite_bits(act[0]) || !finite_bits(act[1])) return;
    x = obs[SWARM_AVOID_SELF_POS];
    y = obs[SWARM_AVOID_SELF_POS + 1];
    for (k = 0; k < SWARM_AVOID_N_MATES; ++k, ++c) {  /* teammates: half the budget each */
        const float *m = obs + SWARM_AVOID_MATES + SWARM_AVOID_MATE_COLS * k;
        const float d = sqrtf(m[0] * m[0] + m[1] * m[1]);
        use[c] = m[SWARM_AVOID_MATE_COLS - 1] > 0.5f && d > 1e-9f;
        if (use[c]) {
            nx[c] = -m[0] / d;
            ny[c] = -m[1] / d;
            lim[c] = 0.5f * avoid_limit(d - SWARM_AVOID_OWN_RADIUS - SWARM_AVOID_MATE_RADIUS,
                                        SWARM_AVOID_MATE_MARGIN);
        }
    }
    for (k = 0; k < 4; ++k, ++c) {  /* walls: +x, -x, +y, -y */
        const float s = (k % 2 == 0) ? 1.0f : -1.0f;
        const float p = k < 2 ? x : y;
        nx[c] = k < 2 ? -s : 0.0f;
        ny[c] = k < 2 ? 0.0f : -s;
        lim[c] = avoid_limit(SWARM_AVOID_HALF_WIDTH - SWARM_AVOID_OWN_RADIUS - s * p, SWARM_AVOID_OBS_MARGIN);
        use[c] = 1;
    }
    for (k = 0; k < SWARM_AVOID_N_OBSTACLES; ++k, ++c) {
        const float *o = obs + SWARM_AVOID_OBSTACLES + SWARM_AVOID_OBSTACLE_COLS * k;
        const float d = sqrtf(o[0] * o[0] + o[1] * o[1]);
        use[c] = o[2] > 0.0f && d > 1e-9f;  /* radius 0: an empty slot */
        if (use[c]) {
            nx[c] = -o[0] / d;
            ny[c] = -o[1] / d;
            lim[c] = avoid_limit(d - o[2] - SWARM_AVOID_OWN_RADIUS, SWARM_AVOID_OBS_MARGIN);
        }
    }
    vx = act[0] * SWARM_AVOID_MAX_SPEED;
    vy = act[1] * SWARM_AVOID_MAX_SPEED;
    for (i = 0; i < SWARM_AVOID_ROUNDS; ++i) {
        for (k = 0; k < SWARM_AVOID_N_CON; ++k) {
            float short_by;
            if (!use[k]) continue;
            short_by = -lim[k] - (vx * nx[k] + vy * ny[k]);  /* > 0: approaching faster than allowed */
            if (short_by > 0.0f) {
                vx += short_by * nx[k];
                vy += short_by * ny[k];
                changed = 1;
            }
        }
    }
    speed = sqrtf(vx * vx + vy * vy);
    if (speed > SWARM_AVOID_MAX_SPEED) {
        const float scale = SWARM_AVOID_MAX_SPEED / speed;
        vx *= scale;
        vy *= scale;
        changed = 1;
    }
    if (changed) {
        act[0] = vx / SWARM_AVOID_MAX_SPEED;
        act[1] = vy / SWARM_AVOID_MAX_SPEED;
    }
#else
    (void)obs;
    (void)act;
#endif
}

/* ------------------------------------------------------------------------------- command, safety */

void swarm_action_to_velocity(const float act[SWARM_POLICY_ACT_DIM], float x, float y, float v[2])
{
    const float lim = SWARM_SPEC_ARENA_HALF_WIDTH - SWARM_WALL_MARGIN;
    float a0 = act[0], a1 = act[1], n2;
    /* NaN (a broken policy) becomes a stop, as in runtime.world.World.sanitize_actions */
    if (!(a0 == a0) || !(a1 == a1)) a0 = a1 = 0.0f;
    a0 = a0 > 1.0f ? 1.0f : (a0 < -1.0f ? -1.0f : a0);
    a1 = a1 > 1.0f ? 1.0f : (a1 < -1.0f ? -1.0f : a1);
    v[0] = a0 * SWARM_SPEC_MAX_SPEED;
    v[1] = a1 * SWARM_SPEC_MAX_SPEED;
    n2 = v[0] * v[0] + v[1] * v[1];
    if (n2 > SWARM_SPEC_MAX_SPEED * SWARM_SPEC_MAX_SPEED) {
        const float k = SWARM_SPEC_MAX_SPEED / sqrtf(n2);
        v[0] *= k;
        v[1] *= k;
    }
    if ((x >= lim && v[0] > 0.0f) || (x <= -lim && v[0] < 0.0f)) v[0] = 0.0f;
    if ((y >= lim && v[1] > 0.0f) || (y <= -lim && v[1] < 0.0f)) v[1] = 0.0f;
}

int swarm_deadman_alive(swarm_deadman_t *d, uint16_t beat, uint32_t now_ms)
{
    if (beat != d->last_beat) {
        d->last_beat = beat;
        d->last_change_ms = now_ms;
        d->armed = 1;
    }
    return d->armed && now_ms - d->last_change_ms <= SWARM_DEADMAN_MS;
}
