/* Minimal stand-in for crazyflie-firmware's log.h (tests only): the LOG_* macros build a table the host
 * test harness can read. */
#pragma once
#include <stdint.h>
typedef uint16_t logVarId_t;
logVarId_t logGetVarId(const char *group, const char *name);
float logGetFloat(logVarId_t varid);
enum { LOG_UINT8 = 1, LOG_UINT16, LOG_UINT32, LOG_INT8, LOG_INT16, LOG_INT32, LOG_FLOAT };
struct stub_var { int type; const char *name; void *address; };
#define LOG_GROUP_START(NAME) const struct stub_var stub_log_##NAME[] = {
#define LOG_ADD(TYPE, NAME, ADDRESS) { TYPE, #NAME, (void *)(ADDRESS) },
#define LOG_GROUP_STOP(NAME) { 0, 0, 0 } };
