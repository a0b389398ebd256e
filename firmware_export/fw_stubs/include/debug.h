/* Minimal stand-in for crazyflie-firmware's debug.h (tests only). */
#pragma once
void stubDebugPrint(const char *fmt, ...);
#define DEBUG_PRINT(fmt, ...) stubDebugPrint(fmt, ##__VA_ARGS__)
