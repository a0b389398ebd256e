/* Minimal stand-in for FreeRTOS.h as the crazyflie firmware configures it (1 kHz tick; tests only). */
#pragma once
#include <stdint.h>
typedef uint32_t TickType_t;
#define M2T(X) ((TickType_t)(X))
#define T2M(X) ((uint32_t)(X))
void stubEnterCritical(void);
void stubExitCritical(void);
#define taskENTER_CRITICAL() stubEnterCritical()
#define taskEXIT_CRITICAL() stubExitCritical()
