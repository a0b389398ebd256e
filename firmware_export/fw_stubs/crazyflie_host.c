/* Host implementation of the minimal firmware headers in include/, so that the app's appMain runs in a test:
 * time advances one control period per vTaskDelayUntil, a test callback scripts the state estimate, the
 * parameters and the received radio packets before each period, setpoints and priority hand-overs are
 * recorded, and appMain's endless loop is left with longjmp when the scripted time is over. Tests only. */
#include <setjmp.h>
#include <stdarg.h>
#include <stdint.h>
#include <string.h>

#include "FreeRTOS.h"
#include "app.h"
#include "commander.h"
#include "debug.h"
#include "log.h"
#include "radiolink.h"
#include "task.h"
#include "usec_time.h"

#define STUB_MAX_RECORDS 4096

typedef struct {
    uint32_t ms;
    int priority;   /* -1: commanderRelaxPriority */
    float vx, vy, z;
    int mode_x, mode_y, mode_z;
} stub_record_t;

typedef void (*stub_step_fn)(uint32_t now_ms);

static jmp_buf stub_exit;
static uint32_t stub_ms;
static uint32_t stub_end_ms;
static stub_step_fn stub_step;
static P2PCallback stub_p2p;
static int stub_critical;
float stub_state[4];  /* x, y, vx, vy as the state estimator reports them */
stub_record_t stub_records[STUB_MAX_RECORDS];
int stub_n_records;
int stub_n_broadcasts;
P2PPacket stub_last_broadcast;
int stub_critical_violations;

void stubEnterCritical(void) { if (stub_critical++) stub_critical_violations++; }
void stubExitCritical(void) { if (--stub_critical) stub_critical_violations++; }

TickType_t xTaskGetTickCount(void) { return stub_ms; }

void vTaskDelayUntil(TickType_t *previousWakeTime, TickType_t increment)
{
    if (stub_critical) stub_critical_violations++;
    *previousWakeTime += increment;
    stub_ms = *previousWakeTime;
    if (stub_ms > stub_end_ms) longjmp(stub_exit, 1);
    if (stub_step) stub_step(stub_ms);
}

uint64_t usecTimestamp(void) { return (uint64_t)stub_ms * 1000u; }

void commanderSetSetpoint(setpoint_t *sp, int priority)
{
    stub_record_t *r;
    if (stub_n_records >= STUB_MAX_RECORDS) return;
    r = &stub_records[stub_n_records++];
    r->ms = stub_ms; r->priority = priority;
    r->vx = sp->velocity.x; r->vy = sp->velocity.y; r->z = sp->position.z;
    r->mode_x = sp->mode.x; r->mode_y = sp->mode.y; r->mode_z = sp->mode.z;
}

void commanderRelaxPriority(void)
{
    if (stub_n_records >= STUB_MAX_RECORDS) return;
    memset(&stub_records[stub_n_records], 0, sizeof(stub_record_t));
    stub_records[stub_n_records].ms = stub_ms;
    stub_records[stub_n_records].priority = -1;
    stub_n_records++;
}

logVarId_t logGetVarId(const char *group, const char *name)
{
    static const char *names[4] = {"x", "y", "vx", "vy"};
    logVarId_t i;
    if (strcmp(group, "stateEstimate") != 0) return 0xffff;
    for (i = 0; i < 4; ++i) if (strcmp(name, names[i]) == 0) return i;
    return 0xffff;
}

float logGetFloat(logVarId_t varid) { return varid < 4 ? stub_state[varid] : 0.0f; }

void p2pRegisterCB(P2PCallback cb) { stub_p2p = cb; }

bool radiolinkSendP2PPacketBroadcast(P2PPacket *p)
{
    stub_n_broadcasts++;
    stub_last_broadcast = *p;
    return true;
}

void stubDebugPrint(const char *fmt, ...) { (void)fmt; }

/* test entry points */

void stub_deliver(const uint8_t *data, uint8_t size)
{
    P2PPacket p;
    memset(&p, 0, sizeof(p));
    p.size = size;
    memcpy(p.data, data, size);
    if (stub_p2p) stub_p2p(&p);
}

int stub_run_app(uint32_t duration_ms, stub_step_fn step)
{
    stub_ms = 0;
    stub_end_ms = duration_ms;
    stub_step = step;
    stub_n_records = 0;
    stub_n_broadcasts = 0;
    if (setjmp(stub_exit) == 0) appMain();
    return stub_n_records;
}
