/* Minimal stand-in for crazyflie-firmware's src/modules/interface/app.h (tests only). */
#pragma once
void appMain(void);
