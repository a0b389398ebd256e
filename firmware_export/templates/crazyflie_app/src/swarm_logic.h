/* The flight app's logic, free of firmware calls so that it builds and is tested on any host:
 * the table of agents heard over the radio, the observation encoder (the C twin of
 * runtime/observation.py, laid out by the generated policy.h), radio message packing, the avoidance layer
 * (the C twin of runtime/avoidance.py, its numbers generated into policy.h), the action to velocity
 * conversion and the dead-man timer. swarm_app.c is the thin firmware shell around it. */
#ifndef SWARM_LOGIC_H
#define SWARM_LOGIC_H

#include <stdint.h>

#include "policy.h"

#define SWARM_N_TEAM (SWARM_SPEC_N_PURSUERS + SWARM_SPEC_N_SCOUTS)
#define SWARM_N_AGENTS SWARM_SPEC_N_AGENTS
#define SWARM_MAX_OBSTACLES 8
#define SWARM_CONTROL_PERIOD_MS ((uint32_t)(SWARM_SPEC_CONTROL_PERIOD_S * 1000.0f + 0.5f))
#define SWARM_PEER_TIMEOUT_MS 1000u   /* a teammate or threat not heard for this long is dropped */
#define SWARM_DEADMAN_MS 500u         /* no ground-station heartbeat for this long stops the policy */
#define SWARM_WALL_MARGIN 0.15f       /* [m] layer off only: no velocity towards a wall closer than this
                                        * (see swarm_action_to_velocity) */
/* The radio message (SWARM_MSG_*, swarm_msg_t, swarm_msg_encode/decode) is generated into policy.h from
 * runtime/radio_msg.py, the definition the Python runtime uses too. */

typedef struct {
    float x, y, vx, vy;   /* last state heard [m, m/s; world frame] */
    uint32_t heard_ms;    /* when it was heard */
    float seen_x, seen_y, seen_vx, seen_vy;  /* last state while within sensing range (partial observability) */
    uint32_t seen_ms;
    uint8_t heard, seen;
} swarm_agent_t;

typedef struct {
    float x, y, r;        /* centre [m], radius [m] */
} swarm_obstacle_t;

typedef struct {
    uint8_t self;         /* own agent index in spec order (pursuers, scouts, evaders) */
    swarm_agent_t agents[SWARM_N_AGENTS];  /* agents[self]: own state estimate */
    swarm_obstacle_t obstacles[SWARM_MAX_OBSTACLES];
    uint8_t n_obstacles;
    uint16_t epoch;       /* mission counter: messages of another epoch are ignored (0 unless set) */
    uint16_t seq;         /* own message counter */
} swarm_world_t;

typedef struct {
    uint16_t last_beat;
    uint32_t last_change_ms;
    uint8_t armed;
} swarm_deadman_t;

/* Returns 0 when `self` is not an agent of the generated policy's role. */
int swarm_world_init(swarm_world_t *w, uint8_t self);
void swarm_world_set_agent(swarm_world_t *w, uint8_t index, float x, float y, float vx, float vy, uint32_t now_ms);
int swarm_world_set_obstacle(swarm_world_t *w, uint8_t slot, float x, float y, float r);

/* Radio: pack the own state (stamped with its heard_ms) and the known targets, freshest first (returns the
 * size, 0 if cap is too small); receive a peer's message: 1 if accepted, 0 for an echo of our own or another
 * epoch, -SWARM_MSG_ERR_* (the reason) for another protocol, version, spec or a malformed message. */
uint8_t swarm_msg_pack(swarm_world_t *w, uint8_t *buf, uint8_t cap);
int swarm_msg_receive(swarm_world_t *w, const uint8_t *buf, uint8_t size, uint32_t now_ms);

/* The observation of agent w->self at now_ms, as runtime.observation.encode_observations builds it. */
void swarm_build_observation(const swarm_world_t *w, uint32_t now_ms, float obs[SWARM_POLICY_OBS_DIM]);

/* The spec's avoidance layer on the policy's action, in place (runtime.avoidance.avoid_rows for one row, in
 * float): the velocity nearest the action's among those whose speed towards every obstacle, wall and teammate
 * of obs lets the drone stop before them, within the max speed and reachable from the own velocity in one
 * control period (if none is both safe and reachable: the nearest safe one within the max speed). Leaves act
 * as it is when SWARM_AVOID_ENABLED is 0, when obs holds a non-finite value, or when act does
 * (swarm_action_to_velocity turns that into a stop). */
void swarm_avoid(const float obs[SWARM_POLICY_OBS_DIM], float act[SWARM_POLICY_ACT_DIM]);

/* Action to velocity [m/s] as the Python runtime does it (runtime.world.World.sanitize_actions and
 * action_to_velocity: a non-finite action is a stop, each component clipped to [-1, 1], times max speed, the norm
 * limited to it). With the avoidance layer off, also no motion towards a wall within SWARM_WALL_MARGIN of it:
 * the Python runtime's commands pass the ground station's geofence, this app's setpoints do not. With the
 * layer on, the layer is the wall rule, so the velocity is exactly the runtime's. */
void swarm_action_to_velocity(const float act[SWARM_POLICY_ACT_DIM], float x, float y, float v[2]);

/* 1 while the heartbeat counter changed within SWARM_DEADMAN_MS, 0 before the first change and after a gap. */
int swarm_deadman_alive(swarm_deadman_t *d, uint16_t beat, uint32_t now_ms);

#endif /* SWARM_LOGIC_H */
