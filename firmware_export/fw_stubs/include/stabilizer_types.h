/* The part of crazyflie-firmware's stabilizer_types.h that velocity setpoints use (tests only). */
#pragma once
#include <stdbool.h>
#include <stdint.h>
typedef enum { modeDisable = 0, modeAbs, modeVelocity } stab_mode_t;
typedef struct { float x, y, z; } stub_vec3_t;
typedef struct { float roll, pitch, yaw; } stub_attitude_t;
typedef struct setpoint_s {
  uint32_t timestamp;
  stub_attitude_t attitude;
  stub_attitude_t attitudeRate;
  float thrust;
  stub_vec3_t position;
  stub_vec3_t velocity;
  stub_vec3_t acceleration;
  bool velocity_body;
  struct { stab_mode_t x, y, z, roll, pitch, yaw, quat; } mode;
} setpoint_t;
