/* Minimal stand-in for crazyflie-firmware's radiolink.h peer-to-peer API (tests only). */
#pragma once
#include <stdbool.h>
#include <stdint.h>
#define P2P_MAX_DATA_SIZE 60
typedef struct _P2PPacket {
  uint8_t size;
  uint8_t rssi;
  uint8_t port;
  uint8_t data[P2P_MAX_DATA_SIZE];
} P2PPacket;
typedef void (*P2PCallback)(P2PPacket *);
void p2pRegisterCB(P2PCallback cb);
bool radiolinkSendP2PPacketBroadcast(P2PPacket *p2pp);
