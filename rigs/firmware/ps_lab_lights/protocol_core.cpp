// ps-lab light controller, protocol v1: see protocol_core.h and docs/rig-protocol.md.
#include "protocol_core.h"

#include <string.h>

namespace pslab {

namespace {

// Numbers saturate here (any value this large is out of range for every argument), so the
// arithmetic stays in 32 bits; the Python simulator does the same.
const uint32_t kNumberCap = 100000000UL;

// Appends to a reply buffer, always leaving it NUL-terminated and never overflowing.
class Writer {
 public:
  Writer(char* buffer, size_t capacity) : buffer_(buffer), capacity_(capacity), length_(0) {
    if (capacity_ > 0) buffer_[0] = '\0';
  }
  void text(const char* s) {
    while (*s) put(*s++);
  }
  void number(uint32_t value) {
    char digits[11];
    size_t n = 0;
    do {
      digits[n++] = static_cast<char>('0' + value % 10);
      value /= 10;
    } while (value > 0);
    while (n > 0) put(digits[--n]);
  }
  size_t length() const { return length_; }

 private:
  void put(char c) {
    if (length_ + 1 < capacity_) {
      buffer_[length_++] = c;
      buffer_[length_] = '\0';
    }
  }
  char* buffer_;
  size_t capacity_;
  size_t length_;
};

bool is_space(char c) { return c == ' ' || c == '\t'; }

// Walks the words of a line (runs of spaces/tabs separate them) without copying; keeps no
// array of words, because a 200-character line could hold 100 and RAM on an Uno is 2 KB.
struct Word {
  const char* start;
  size_t length;
};

class Words {
 public:
  explicit Words(const char* line) : p_(line) {}
  bool next(Word* word) {
    while (is_space(*p_)) ++p_;
    if (!*p_) return false;
    word->start = p_;
    while (*p_ && !is_space(*p_)) ++p_;
    word->length = static_cast<size_t>(p_ - word->start);
    return true;
  }

 private:
  const char* p_;
};

// Case-insensitive (ASCII letters only) comparison of a word with an upper-case keyword.
bool word_is(const Word& word, const char* keyword) {
  size_t n = strlen(keyword);
  if (word.length != n) return false;
  for (size_t i = 0; i < n; ++i) {
    char c = word.start[i];
    if (c >= 'a' && c <= 'z') c = static_cast<char>(c - 'a' + 'A');
    if (c != keyword[i]) return false;
  }
  return true;
}

// Decimal digits only; saturates at kNumberCap. Returns false for anything else.
bool parse_number(const Word& word, uint32_t* value) {
  if (word.length == 0) return false;
  uint32_t v = 0;
  for (size_t i = 0; i < word.length; ++i) {
    char c = word.start[i];
    if (c < '0' || c > '9') return false;
    if (v < kNumberCap) v = v * 10 + static_cast<uint32_t>(c - '0');
    if (v > kNumberCap) v = kNumberCap;
  }
  *value = v;
  return true;
}

void error(Writer& out, int code) {
  if (code == 1) out.text("ERR 1 unknown command");
  if (code == 2) out.text("ERR 2 bad argument");
  if (code == 3) out.text("ERR 3 light out of range");
}

void identity(Writer& out, const char* word, uint8_t lights) {
  out.text(word);
  out.text(" ");
  out.text(kProtocolName);
  out.text(" ");
  out.number(kProtocolVersion);
  out.text(" ");
  out.number(lights);
}

}  // namespace

LineReader::LineReader() : length_(0), overflow_(false), too_long_(false), complete_(false) {
  buffer_[0] = '\0';
}

bool LineReader::feed(char c) {
  if (complete_) {  // the previous line was consumed: start a new one
    length_ = 0;
    overflow_ = false;
    complete_ = false;
    buffer_[0] = '\0';
  }
  if (c == '\r') return false;
  if (c == '\n') {
    buffer_[length_] = '\0';
    too_long_ = overflow_;
    complete_ = true;
    return true;
  }
  if (length_ < kMaxLine) {
    buffer_[length_++] = c;
    buffer_[length_] = '\0';
  } else {
    overflow_ = true;
  }
  return false;
}

Controller::Controller(uint8_t lights, LightOutput output, void* context)
    : lights_(lights < 1 ? 1 : (lights > kMaxLights ? kMaxLights : lights)),
      output_(output),
      context_(context),
      level_(kMaxLevel),
      watchdog_ms_(kDefaultWatchdogMs),
      last_command_ms_(0),
      watchdog_fired_(false) {
  memset(lit_, 0, sizeof(lit_));
}

bool Controller::is_lit(uint8_t light) const {
  if (light < 1 || light > lights_) return false;
  return (lit_[(light - 1) / 8] >> ((light - 1) % 8)) & 1;
}

void Controller::apply(const uint8_t* lit, uint8_t level) {
  if (lit != lit_) memcpy(lit_, lit, sizeof(lit_));
  level_ = level;
  if (output_ == 0) return;
  for (uint8_t light = 1; light <= lights_; ++light) {
    output_(light, is_lit(light) ? level_ : 0, context_);
  }
}

size_t Controller::boot(uint32_t now_ms, char* reply, size_t capacity) {
  uint8_t none[sizeof(lit_)];
  memset(none, 0, sizeof(none));
  apply(none, kMaxLevel);
  watchdog_ms_ = kDefaultWatchdogMs;
  last_command_ms_ = now_ms;
  watchdog_fired_ = false;
  Writer out(reply, capacity);
  identity(out, "READY", lights_);
  return out.length();
}

bool Controller::poll(uint32_t now_ms) {
  if (watchdog_ms_ == 0 || watchdog_fired_) return false;
  // Unsigned subtraction is correct across the 49-day millis() wrap-around.
  if (static_cast<uint32_t>(now_ms - last_command_ms_) < watchdog_ms_) return false;
  watchdog_fired_ = true;
  uint8_t none[sizeof(lit_)];
  memset(none, 0, sizeof(none));
  apply(none, level_);
  return true;
}

size_t Controller::handle_line(const char* line, bool too_long, uint32_t now_ms, char* reply,
                               size_t capacity) {
  if (capacity > 0) reply[0] = '\0';
  if (!too_long) {
    const char* p = line;
    while (is_space(*p)) ++p;
    if (*p == '\0') return 0;  // a blank line is not a command
  }
  poll(now_ms);
  last_command_ms_ = now_ms;
  watchdog_fired_ = false;
  return execute(line, too_long, reply, capacity);
}

size_t Controller::execute(const char* line, bool too_long, char* reply, size_t capacity) {
  Writer out(reply, capacity);
  if (too_long) {
    error(out, 2);
    return out.length();
  }
  Words words(line);
  Word name;
  words.next(&name);  // the line is not blank, so there is a first word
  size_t nargs = 0;
  Word arg;
  for (Words rest = words; rest.next(&arg);) ++nargs;

  if (word_is(name, "ID") || word_is(name, "OFF") || word_is(name, "STATE")) {
    if (nargs != 0) {
      error(out, 2);
    } else if (word_is(name, "ID")) {
      identity(out, "ID", lights_);
    } else if (word_is(name, "OFF")) {
      uint8_t none[sizeof(lit_)];
      memset(none, 0, sizeof(none));
      apply(none, level_);
      out.text("OK OFF");
    } else {
      out.text("STATE");
      bool any = false;
      for (uint8_t light = 1; light <= lights_; ++light) {
        if (is_lit(light)) {
          out.text(" ");
          out.number(light);
          any = true;
        }
      }
      if (!any) out.text(" NONE");
    }
    return out.length();
  }

  if (word_is(name, "ON")) {
    if (nargs == 0) {
      error(out, 2);
      return out.length();
    }
    uint8_t wanted[sizeof(lit_)];
    memset(wanted, 0, sizeof(wanted));
    for (Words rest = words; rest.next(&arg);) {  // validate everything before changing anything
      uint32_t light = 0;
      if (!parse_number(arg, &light)) {
        error(out, 2);
        return out.length();
      }
      if (light < 1 || light > lights_) {
        error(out, 3);
        return out.length();
      }
      wanted[(light - 1) / 8] |= static_cast<uint8_t>(1u << ((light - 1) % 8));
    }
    apply(wanted, level_);
    out.text("OK ON");
    for (Words rest = words; rest.next(&arg);) {
      uint32_t light = 0;
      parse_number(arg, &light);
      out.text(" ");
      out.number(light);
    }
    return out.length();
  }

  bool is_level = word_is(name, "LEVEL");
  if (is_level || word_is(name, "WATCHDOG")) {
    uint32_t value = 0;
    uint32_t limit = is_level ? kMaxLevel : kMaxWatchdogMs;
    Words rest = words;
    if (nargs != 1 || !rest.next(&arg) || !parse_number(arg, &value) || value > limit) {
      error(out, 2);
      return out.length();
    }
    if (is_level) {
      apply(lit_, static_cast<uint8_t>(value));
      out.text("OK LEVEL ");
    } else {
      watchdog_ms_ = value;
      out.text("OK WATCHDOG ");
    }
    out.number(value);
    return out.length();
  }

  error(out, 1);
  return out.length();
}

}  // namespace pslab
