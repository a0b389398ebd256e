/* Minimal stand-in for FreeRTOS task.h (tests only). */
#pragma once
#include "FreeRTOS.h"
TickType_t xTaskGetTickCount(void);
void vTaskDelayUntil(TickType_t *previousWakeTime, TickType_t increment);
