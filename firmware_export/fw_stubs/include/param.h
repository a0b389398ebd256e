/* Minimal stand-in for crazyflie-firmware's param.h (tests only): the PARAM_* macros build a table the host
 * test harness writes parameters through. */
#pragma once
#include "log.h"
enum { PARAM_UINT8 = 1, PARAM_UINT16, PARAM_UINT32, PARAM_INT8, PARAM_INT16, PARAM_INT32, PARAM_FLOAT };
#define PARAM_GROUP_START(NAME) const struct stub_var stub_param_##NAME[] = {
#define PARAM_ADD(TYPE, NAME, ADDRESS) { TYPE, #NAME, (void *)(ADDRESS) },
#define PARAM_GROUP_STOP(NAME) { 0, 0, 0 } };
