// ps-lab light controller, protocol v1 (docs/rig-protocol.md): line reader and state machine.
//
// Plain C++ (C++11, no Arduino headers, no heap): the sketch ps_lab_lights.ino drives the pins,
// and rigs/firmware/host/host_test.cpp runs the same code on a PC against protocol-vectors.txt.
#ifndef PS_LAB_PROTOCOL_CORE_H
#define PS_LAB_PROTOCOL_CORE_H

#include <stddef.h>
#include <stdint.h>

namespace pslab {

const uint8_t kProtocolVersion = 1;
const char kProtocolName[] = "ps-lab-lights";
// Lights a controller can drive (bit set size); a board's pin table usually has fewer.
const uint8_t kMaxLights = 64;
// Longest command line accepted, without its terminator; longer lines get ERR 2.
const size_t kMaxLine = 200;
// A reply never exceeds this (the echo of a 200-character ON line, plus "OK ").
const size_t kMaxReply = kMaxLine + 8;
const uint32_t kDefaultWatchdogMs = 10000;
const uint32_t kMaxWatchdogMs = 3600000;
const uint8_t kMaxLevel = 255;

// Collects received bytes into lines: '\n' ends a line, '\r' is ignored everywhere, a line
// longer than kMaxLine is remembered as too long (its content is not needed: it is refused).
class LineReader {
 public:
  LineReader();
  // Returns true when `c` completed a line; then line() and too_long() describe it until the
  // next call.
  bool feed(char c);
  const char* line() const { return buffer_; }
  bool too_long() const { return too_long_; }

 private:
  char buffer_[kMaxLine + 1];
  size_t length_;
  bool overflow_;
  bool too_long_;
  bool complete_;
};

// Called whenever a light's output must change: `light` is 1-based, `level` 0 (off) to 255.
typedef void (*LightOutput)(uint8_t light, uint8_t level, void* context);

class Controller {
 public:
  // `lights` is clamped to 1..kMaxLights. `output` may be null (host tests).
  Controller(uint8_t lights, LightOutput output, void* context);

  // Power-up state (all off, level 255, default watchdog); writes the READY line (no
  // terminator) into `reply` and returns its length.
  size_t boot(uint32_t now_ms, char* reply, size_t capacity);

  // Handles one received line (without terminator). Writes the reply line (no terminator) and
  // returns its length; 0 means no reply (a blank line, which is not a command).
  size_t handle_line(const char* line, bool too_long, uint32_t now_ms, char* reply, size_t capacity);

  // Call from the main loop: switches everything off when no command arrived for the watchdog
  // period. Returns true when it fired just now. millis() wrap-around is handled.
  bool poll(uint32_t now_ms);

  uint8_t lights() const { return lights_; }
  bool is_lit(uint8_t light) const;
  uint8_t level() const { return level_; }
  uint32_t watchdog_ms() const { return watchdog_ms_; }

 private:
  void apply(const uint8_t* lit, uint8_t level);
  size_t execute(const char* line, bool too_long, char* reply, size_t capacity);

  uint8_t lights_;
  LightOutput output_;
  void* context_;
  uint8_t lit_[(kMaxLights + 7) / 8];
  uint8_t level_;
  uint32_t watchdog_ms_;
  uint32_t last_command_ms_;
  bool watchdog_fired_;
};

}  // namespace pslab

#endif  // PS_LAB_PROTOCOL_CORE_H
