// ps-lab light controller firmware, protocol v1 (docs/rig-protocol.md).
//
// The protocol lives in protocol_core.h/.cpp (plain C++, tested on a PC against
// ../protocol-vectors.txt); this sketch only connects it to the serial port and the pins.
// To drive a shift register or a MOSFET board instead of direct pins, change drive_light()
// (see ../README.md).
#include <Arduino.h>

// The AVR hardware watchdog resets a hung sketch after 2 s (a reset switches every output off).
// Boards with an old bootloader (some Nano clones, not the Uno's optiboot) loop on a watchdog
// reset: build them with -DPS_LAB_HARDWARE_WATCHDOG=0 (make PS_LAB_DEFINES=...).
#ifndef PS_LAB_HARDWARE_WATCHDOG
#define PS_LAB_HARDWARE_WATCHDOG 1
#endif
#if PS_LAB_HARDWARE_WATCHDOG && !defined(__AVR__)
#undef PS_LAB_HARDWARE_WATCHDOG
#define PS_LAB_HARDWARE_WATCHDOG 0
#endif
#if PS_LAB_HARDWARE_WATCHDOG
#include <avr/wdt.h>
#endif

#include "protocol_core.h"

// Light i (1-based, the order of the rig file) is on pin kLightPins[i - 1]. Pins 0 and 1 carry
// the serial port. On an Uno only 3, 5, 6, 9, 10, 11 can dim (PWM); the others switch fully on
// for any level above 0.
static const uint8_t kLightPins[] = {3, 5, 6, 9, 10, 11, 2, 4, 7, 8, 12, 13};
static const uint8_t kLightCount = sizeof(kLightPins) / sizeof(kLightPins[0]);

// true when a light is on while its pin is LOW (P-channel MOSFETs, many relay boards).
static const bool kActiveLow = false;

static void drive_light(uint8_t light, uint8_t level, void* /*context*/) {
  uint8_t pin = kLightPins[light - 1];
#ifdef digitalPinHasPWM
  if (digitalPinHasPWM(pin)) {
    analogWrite(pin, kActiveLow ? 255 - level : level);
    return;
  }
#endif
  bool on = level > 0;
  digitalWrite(pin, (on != kActiveLow) ? HIGH : LOW);
}

static pslab::Controller controller(kLightCount, drive_light, 0);
static pslab::LineReader reader;
static char reply[pslab::kMaxReply + 1];

static void send_reply(size_t length) {
  if (length == 0) return;
  Serial.write(reinterpret_cast<const uint8_t*>(reply), length);
  Serial.write('\n');
}

void setup() {
#if PS_LAB_HARDWARE_WATCHDOG
  wdt_disable();
#endif
  for (uint8_t i = 0; i < kLightCount; ++i) {
    digitalWrite(kLightPins[i], kActiveLow ? HIGH : LOW);
    pinMode(kLightPins[i], OUTPUT);
  }
  Serial.begin(115200);
  send_reply(controller.boot(millis(), reply, sizeof(reply)));
#if PS_LAB_HARDWARE_WATCHDOG
  wdt_enable(WDTO_2S);
#endif
}

void loop() {
#if PS_LAB_HARDWARE_WATCHDOG
  wdt_reset();
#endif
  controller.poll(millis());
  while (Serial.available() > 0) {
    if (reader.feed(static_cast<char>(Serial.read()))) {
      send_reply(controller.handle_line(reader.line(), reader.too_long(), millis(), reply, sizeof(reply)));
    }
  }
}
