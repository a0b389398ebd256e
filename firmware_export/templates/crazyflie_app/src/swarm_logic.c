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

#if !SWARM_POLICY_ROLE_IS_EVADER && defined(SWARM_OBS_ASSIGNED_START)
/* runtime.observation._assigned (spec sensing.share_assignment): 1 for the target this pursuer takes in the split
 * of the pursuers it hears (itself always) between the targets it knows, each target at most ceil(m / 2) of the
 * m pursuers: ordered by (distance to target 0 - distance to target 1), ties to the lower index, the first c go
 * to target 0, c the negative differences clipped to [m - ceil(m / 2), ceil(m / 2)]. Scouts: all 0. */
typedef char swarm_check_assigned_layout[(SWARM_OBS_ASSIGNED_ROWS == SWARM_SPEC_N_EVADERS
    && SWARM_SPEC_N_EVADERS <= 2 && SWARM_OBS_ASSIGNED_COLS == 1) ? 1 : -1];

static void fill_assigned(const swarm_world_t *w, uint32_t now_ms, const float *targets, float *out)
{
    const swarm_agent_t *me = &w->agents[w->self];
    const int i = w->self;
    int k;
    for (k = 0; k < SWARM_OBS_ASSIGNED_ROWS; ++k) out[k] = 0.0f;
    if (i >= SWARM_SPEC_N_PURSUERS) return;
#if SWARM_SPEC_N_EVADERS == 1
    out[0] = targets[SWARM_OBS_TARGETS_KNOWN];
#else
    {
        const int kn0 = targets[SWARM_OBS_TARGETS_KNOWN] == 1.0f;
        const int kn1 = targets[SWARM_OBS_TARGETS_COLS + SWARM_OBS_TARGETS_KNOWN] == 1.0f;
        const swarm_agent_t *e0 = &w->agents[SWARM_N_TEAM], *e1 = &w->agents[SWARM_N_TEAM + 1];
        const float tx0 = SWARM_SPEC_FULL_OBSERVABILITY ? e0->x : e0->seen_x;
        const float ty0 = SWARM_SPEC_FULL_OBSERVABILITY ? e0->y : e0->seen_y;
        const float tx1 = SWARM_SPEC_FULL_OBSERVABILITY ? e1->x : e1->seen_x;
        const float ty1 = SWARM_SPEC_FULL_OBSERVABILITY ? e1->y : e1->seen_y;
        float diff[SWARM_SPEC_N_PURSUERS], own;
        int j, m = 0, neg = 0, ahead = 0, slots, c;
        if (!(kn0 && kn1)) {
            out[0] = kn0 ? 1.0f : 0.0f;
            out[1] = kn1 ? 1.0f : 0.0f;
            return;
        }
        for (j = 0; j < SWARM_SPEC_N_PURSUERS; ++j) {
            const swarm_agent_t *a = &w->agents[j];
            const float dx0 = a->x - tx0, dy0 = a->y - ty0, dx1 = a->x - tx1, dy1 = a->y - ty1;
            diff[j] = sqrtf(dx0 * dx0 + dy0 * dy0) - sqrtf(dx1 * dx1 + dy1 * dy1);
        }
        own = diff[i];
        for (j = 0; j < SWARM_SPEC_N_PURSUERS; ++j) {
            const swarm_agent_t *a = &w->agents[j];
            if (j != i && (!a->heard || now_ms - a->heard_ms > SWARM_PEER_TIMEOUT_MS
                           || (!SWARM_SPEC_FULL_OBSERVABILITY
                               && dist2(a, me->x, me->y) > SWARM_SPEC_COMM_RANGE * SWARM_SPEC_COMM_RANGE)))
                continue;  /* not heard: not in this drone's split */
            ++m;
            neg += diff[j] < 0.0f;
            ahead += diff[j] < own || (diff[j] == own && j < i);
        }
        slots = (m + 1) / 2;
        c = neg < m - slots ? m - slots : neg > slots ? slots : neg;
        out[0] = ahead < c ? 1.0f : 0.0f;
        out[1] = ahead < c ? 0.0f : 1.0f;
    }
#endif
    (void)now_ms;
    (void)me;
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
#ifdef SWARM_OBS_ASSIGNED_START
    fill_assigned(w, now_ms, obs + SWARM_OBS_TARGETS_START, obs + SWARM_OBS_ASSIGNED_START);
#endif
#endif
}

/* -------------------------------------------------------------------------------------- avoidance */

/* Not NaN and not infinite, tested on the bits (no compiler flag can fold it away). */
static int finite_bits(float v)
{
    uint32_t bits;
    memcpy(&bits, &v, sizeof(bits));
    return (bits & 0x7f800000u) != 0x7f800000u;
}

#if SWARM_AVOID_ENABLED
/* The layout swarm_avoid reads is the one the observation encoder writes (both generated from the spec). */
typedef char swarm_check_avoid_layout[(SWARM_AVOID_SELF_POS == SWARM_OBS_SELF_POS_START
    && SWARM_AVOID_SELF_VEL == SWARM_OBS_SELF_VEL_START
    && SWARM_AVOID_OBSTACLES == SWARM_OBS_OBSTACLES_START && SWARM_AVOID_N_OBSTACLES == SWARM_OBS_OBSTACLES_ROWS
    && SWARM_AVOID_OBSTACLE_COLS == SWARM_OBS_OBSTACLES_COLS && SWARM_AVOID_MATES == SWARM_OBS_TEAMMATES_START
    && SWARM_AVOID_N_MATES == SWARM_OBS_TEAMMATES_ROWS && SWARM_AVOID_MATE_COLS == SWARM_OBS_TEAMMATES_COLS
    && SWARM_OBS_TEAMMATES_VALID == SWARM_AVOID_MATE_COLS - 1 && SWARM_OBS_OBSTACLES_RADIUS == 2) ? 1 : -1];

#define SWARM_AVOID_N_CON (SWARM_AVOID_N_MATES + 4 + SWARM_AVOID_N_OBSTACLES)

/* runtime.avoidance._limit: the approach speed [m/s] allowed at `gap` from a surface. */
static float avoid_limit(float gap, float margin, float braking)
{
    const float g = gap - margin;
    float brake, step;
    if (!(g > 0.0f)) return 0.0f;
    brake = sqrtf(2.0f * braking * g);
    step = g / SWARM_AVOID_DT;
    return step < brake ? step : brake;
}

/* One call's program (runtime.avoidance.nearest_feasible's arguments): the velocity nearest (wx, wy) with
 * c . n_j >= -lim_j for j < m and |c - e_j| <= r_j for j < nd; disc 0 is the speed limit, disc 1 the velocities
 * reachable in one control period. best, found and out: the nearest feasible candidate so far. */
typedef struct {
    float nx[SWARM_AVOID_N_CON], ny[SWARM_AVOID_N_CON], lim[SWARM_AVOID_N_CON];
    float ex[2], ey[2], er[2];
    int m, nd;
    float wx, wy, best;
    int found;
    float out[2];
} avoid_qp_t;

/* runtime.avoidance._feasible, with the float32 slack SWARM_AVOID_FEASIBLE_TOL. */
static int avoid_feasible(const avoid_qp_t *q, float cx, float cy)
{
    int j;
    for (j = 0; j < q->m; ++j) {
        if (cx * q->nx[j] + cy * q->ny[j] < -q->lim[j] - SWARM_AVOID_FEASIBLE_TOL) return 0;
    }
    for (j = 0; j < q->nd; ++j) {
        const float dx = cx - q->ex[j], dy = cy - q->ey[j];
        if (sqrtf(dx * dx + dy * dy) > q->er[j] + SWARM_AVOID_FEASIBLE_TOL) return 0;
    }
    return 1;
}

/* A candidate: kept when strictly nearer than the best so far and feasible (ties keep the earlier one). */
static void avoid_try(avoid_qp_t *q, float cx, float cy)
{
    const float d = (cx - q->wx) * (cx - q->wx) + (cy - q->wy) * (cy - q->wy);
    if (d < q->best && avoid_feasible(q, cx, cy)) {
        q->best = d;
        q->found = 1;
        q->out[0] = cx;
        q->out[1] = cy;
    }
}

/* Two active constraints with a line: two lines, or line i and circle j. */
static void avoid_try_line_pairs(avoid_qp_t *q)
{
    int i, j, k;
    for (i = 0; i < q->m; ++i) {
        for (j = i + 1; j < q->m; ++j) {
            const float det = q->nx[i] * q->ny[j] - q->ny[i] * q->nx[j];
            if (fabsf(det) < 1e-12f) continue;
            avoid_try(q, (-q->lim[i] * q->ny[j] + q->lim[j] * q->ny[i]) / det,
                      (-q->nx[i] * q->lim[j] + q->nx[j] * q->lim[i]) / det);
        }
    }
    for (i = 0; i < q->m; ++i) {
        for (j = 0; j < q->nd; ++j) {
            const float s = q->ex[j] * q->nx[i] + q->ey[j] * q->ny[i] + q->lim[i];  /* centre to line, signed */
            const float h2 = q->er[j] * q->er[j] - s * s;
            float h, fx, fy;
            if (h2 < 0.0f) continue;
            h = sqrtf(h2);
            fx = q->ex[j] - s * q->nx[i];
            fy = q->ey[j] - s * q->ny[i];
            for (k = -1; k <= 1; k += 2) {
                const float sign = (float)k;
                avoid_try(q, fx - sign * h * q->ny[i], fy + sign * h * q->nx[i]);
            }
        }
    }
}

/* Two active circles. */
static void avoid_try_circle_pairs(avoid_qp_t *q)
{
    int i, j, k;
    for (i = 0; i < q->nd; ++i) {
        for (j = i + 1; j < q->nd; ++j) {
            const float dx = q->ex[j] - q->ex[i], dy = q->ey[j] - q->ey[i];
            const float dd = sqrtf(dx * dx + dy * dy);
            float a, h, px, py;
            if (dd < 1e-12f || dd > q->er[i] + q->er[j] || dd < fabsf(q->er[i] - q->er[j])) continue;
            a = (q->er[i] * q->er[i] - q->er[j] * q->er[j] + dd * dd) / (2.0f * dd);
            h = q->er[i] * q->er[i] - a * a;
            h = sqrtf(h > 0.0f ? h : 0.0f);
            px = q->ex[i] + a * dx / dd;
            py = q->ey[i] + a * dy / dd;
            for (k = -1; k <= 1; k += 2) {
                const float sign = (float)k;
                avoid_try(q, px - sign * h * dy / dd, py + sign * h * dx / dd);
            }
        }
    }
}

/* runtime.avoidance.nearest_feasible: the same candidates in the same order (the wish; the projection onto each
 * line, then onto each circle; every two lines, line and circle, two circles), the nearest feasible one into
 * q->out. Returns 0 when none is feasible. */
static int avoid_nearest(avoid_qp_t *q, int nd)
{
    int i;
    q->nd = nd;
    q->best = INFINITY;
    q->found = 0;
    if (avoid_feasible(q, q->wx, q->wy)) {
        q->out[0] = q->wx;
        q->out[1] = q->wy;
        return 1;
    }
    for (i = 0; i < q->m; ++i) {
        const float t = -q->lim[i] - (q->wx * q->nx[i] + q->wy * q->ny[i]);
        avoid_try(q, q->wx + t * q->nx[i], q->wy + t * q->ny[i]);
    }
    for (i = 0; i < nd; ++i) {
        const float dx = q->wx - q->ex[i], dy = q->wy - q->ey[i];
        const float dn = sqrtf(dx * dx + dy * dy);
        if (dn > 0.0f) avoid_try(q, q->ex[i] + q->er[i] * dx / dn, q->ey[i] + q->er[i] * dy / dn);
    }
    avoid_try_line_pairs(q);
    avoid_try_circle_pairs(q);
    return q->found;
}

/* The half-planes of runtime.avoidance.avoid_rows, in its order: valid teammates (half the budget each, plus the
 * teammate_credit share of the teammate's own speed away), walls +x -x +y -y, used obstacle slots (radius > 0). */
static void avoid_constraints(const float obs[SWARM_POLICY_OBS_DIM], avoid_qp_t *q)
{
    const float x = obs[SWARM_AVOID_SELF_POS], y = obs[SWARM_AVOID_SELF_POS + 1];
    int k, m = 0;
    for (k = 0; k < SWARM_AVOID_N_MATES; ++k) {
        const float *t = obs + SWARM_AVOID_MATES + SWARM_AVOID_MATE_COLS * k;
        const float d = sqrtf(t[0] * t[0] + t[1] * t[1]);
        if (t[SWARM_AVOID_MATE_COLS - 1] > 0.5f && d > 1e-9f) {
            q->nx[m] = -t[0] / d;
            q->ny[m] = -t[1] / d;
            const float away = -(t[2] * q->nx[m] + t[3] * q->ny[m]);  /* the teammate's own speed away */
            q->lim[m] = 0.5f * avoid_limit(d - SWARM_AVOID_OWN_RADIUS - SWARM_AVOID_MATE_RADIUS,
                                           SWARM_AVOID_MATE_MARGIN, SWARM_AVOID_MATE_BRAKING);
            if (away > 0.0f) q->lim[m] += SWARM_AVOID_MATE_CREDIT * away;
            ++m;
        }
    }
    for (k = 0; k < 4; ++k, ++m) {
        const float s = (k % 2 == 0) ? 1.0f : -1.0f;
        const float p = k < 2 ? x : y;
        q->nx[m] = k < 2 ? -s : 0.0f;
        q->ny[m] = k < 2 ? 0.0f : -s;
        q->lim[m] = avoid_limit(SWARM_AVOID_HALF_WIDTH - SWARM_AVOID_OWN_RADIUS - s * p, SWARM_AVOID_OBS_MARGIN,
                                SWARM_AVOID_BRAKING);
    }
    for (k = 0; k < SWARM_AVOID_N_OBSTACLES; ++k) {
        const float *o = obs + SWARM_AVOID_OBSTACLES + SWARM_AVOID_OBSTACLE_COLS * k;
        const float d = sqrtf(o[0] * o[0] + o[1] * o[1]);
        if (o[2] > 0.0f && d > 1e-9f) {  /* radius 0: an empty slot */
            q->nx[m] = -o[0] / d;
            q->ny[m] = -o[1] / d;
            q->lim[m] = avoid_limit(d - o[2] - SWARM_AVOID_OWN_RADIUS, SWARM_AVOID_OBS_MARGIN, SWARM_AVOID_BRAKING);
            ++m;
        }
    }
    q->m = m;
}
#endif

/* runtime.avoidance.avoid_rows for one row, in float. The action is written back only when the layer changed
 * the velocity, so a safe, reachable action stays bit for bit what the policy returned (as in Python, whose
 * float64 round trip act * v / v rounds back to the float32 action). */
void swarm_avoid(const float obs[SWARM_POLICY_OBS_DIM], float act[SWARM_POLICY_ACT_DIM])
{
#if SWARM_AVOID_ENABLED
    avoid_qp_t q;
    float wx, wy, speed;
    int i;
    for (i = 0; i < SWARM_POLICY_OBS_DIM; ++i) {
        if (!finite_bits(obs[i])) return;
    }
    if (!finite_bits(act[0]) || !finite_bits(act[1])) return;
    avoid_constraints(obs, &q);
    wx = q.wx = act[0] * SWARM_AVOID_MAX_SPEED;
    wy = q.wy = act[1] * SWARM_AVOID_MAX_SPEED;
    speed = sqrtf(q.wx * q.wx + q.wy * q.wy);
    if (speed > SWARM_AVOID_MAX_SPEED) {  /* the world flies at most max_speed: the wish as it would take it */
        q.wx = q.wx * SWARM_AVOID_MAX_SPEED / speed;
        q.wy = q.wy * SWARM_AVOID_MAX_SPEED / speed;
    }
    q.ex[0] = 0.0f;
    q.ey[0] = 0.0f;
    q.er[0] = SWARM_AVOID_MAX_SPEED;
    q.ex[1] = obs[SWARM_AVOID_SELF_VEL];
    q.ey[1] = obs[SWARM_AVOID_SELF_VEL + 1];
    q.er[1] = SWARM_AVOID_MAX_ACCEL * SWARM_AVOID_DT * (1.0f - SWARM_AVOID_REACH_SHRINK);
    if (!avoid_nearest(&q, 2) && !avoid_nearest(&q, 1)) {  /* none safe and reachable: drop reachability */
        q.out[0] = q.out[1] = 0.0f;  /* unreachable in exact arithmetic: zero is always safe */
    }
    if (q.out[0] != wx || q.out[1] != wy) {
        act[0] = q.out[0] / SWARM_AVOID_MAX_SPEED;
        act[1] = q.out[1] / SWARM_AVOID_MAX_SPEED;
    }
#else
    (void)obs;
    (void)act;
#endif
}

/* ------------------------------------------------------------------------------- command, safety */

void swarm_action_to_velocity(const float act[SWARM_POLICY_ACT_DIM], float x, float y, float v[2])
{
    float a0 = act[0], a1 = act[1], n2;
    /* non-finite (a broken policy) becomes a stop, clipped to [-1, 1]: runtime.world.World.sanitize_actions */
    if (!finite_bits(a0) || !finite_bits(a1)) a0 = a1 = 0.0f;
    a0 = a0 > 1.0f ? 1.0f : (a0 < -1.0f ? -1.0f : a0);
    a1 = a1 > 1.0f ? 1.0f : (a1 < -1.0f ? -1.0f : a1);
    /* runtime.world.action_to_velocity */
    v[0] = a0 * SWARM_SPEC_MAX_SPEED;
    v[1] = a1 * SWARM_SPEC_MAX_SPEED;
    n2 = v[0] * v[0] + v[1] * v[1];
    if (n2 > SWARM_SPEC_MAX_SPEED * SWARM_SPEC_MAX_SPEED) {
        const float k = SWARM_SPEC_MAX_SPEED / sqrtf(n2);
        v[0] *= k;
        v[1] *= k;
    }
#if SWARM_AVOID_ENABLED
    /* The layer (swarm_avoid) already holds the walls with its braking barrier, as in the Python runtime:
     * no second wall rule, so the setpoint is the runtime's command. */
    (void)x;
    (void)y;
#else
    {   /* Layer off: the Python runtime's commands reach a drone through the ground station's geofence
         * (groundstation.safety); this app's setpoints do not, so it keeps its own stop at the walls. */
        const float lim = SWARM_SPEC_ARENA_HALF_WIDTH - SWARM_WALL_MARGIN;
        if ((x >= lim && v[0] > 0.0f) || (x <= -lim && v[0] < 0.0f)) v[0] = 0.0f;
        if ((y >= lim && v[1] > 0.0f) || (y <= -lim && v[1] < 0.0f)) v[1] = 0.0f;
    }
#endif
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
