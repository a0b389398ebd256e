/* Minimal stand-in for crazyflie-firmware's usec_time.h (tests only). */
#pragma once
#include <stdint.h>
uint64_t usecTimestamp(void);
