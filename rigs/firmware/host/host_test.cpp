// Runs protocol-vectors.txt against the C++ core on a PC (no Arduino needed):
//   g++ -std=c++11 -I../ps_lab_lights ../ps_lab_lights/protocol_core.cpp host_test.cpp -o host_test
//   ./host_test ../protocol-vectors.txt
// Prints one line per failing vector and a summary; exit status 0 when every vector passes.
#include <cstdio>
#include <cstdlib>
#include <cstring>
#include <fstream>
#include <iostream>
#include <string>

#include "protocol_core.h"

namespace {

std::string strip(const std::string& s) {
  size_t begin = s.find_first_not_of(" \t");
  if (begin == std::string::npos) return "";
  size_t end = s.find_last_not_of(" \t");
  return s.substr(begin, end - begin + 1);
}

// \r \n \t \\ and \xNN, as documented at the top of protocol-vectors.txt.
bool unescape(const std::string& s, std::string* out) {
  out->clear();
  for (size_t i = 0; i < s.size(); ++i) {
    if (s[i] != '\\') {
      out->push_back(s[i]);
      continue;
    }
    if (++i >= s.size()) return false;
    char c = s[i];
    if (c == 'r') out->push_back('\r');
    else if (c == 'n') out->push_back('\n');
    else if (c == 't') out->push_back('\t');
    else if (c == '\\') out->push_back('\\');
    else if (c == 'x' && i + 2 < s.size()) {
      std::string hex = s.substr(i + 1, 2);
      char* end = 0;
      long value = std::strtol(hex.c_str(), &end, 16);
      if (end != hex.c_str() + 2) return false;
      out->push_back(static_cast<char>(value));
      i += 2;
    } else {
      return false;
    }
  }
  return true;
}

std::string visible(const std::string& s) {
  std::string out;
  char buffer[8];
  for (size_t i = 0; i < s.size(); ++i) {
    unsigned char c = static_cast<unsigned char>(s[i]);
    if (c >= 0x20 && c < 0x7f && c != '\\') {
      out.push_back(static_cast<char>(c));
    } else {
      std::snprintf(buffer, sizeof(buffer), "\\x%02x", c);
      out += buffer;
    }
  }
  return out;
}

}  // namespace

int main(int argc, char** argv) {
  if (argc != 2) {
    std::cerr << "usage: host_test protocol-vectors.txt\n";
    return 2;
  }
  std::ifstream file(argv[1]);
  if (!file) {
    std::cerr << "cannot read " << argv[1] << "\n";
    return 2;
  }
  pslab::Controller* controller = 0;
  pslab::LineReader reader;
  uint32_t now = 0;
  int passed = 0, failed = 0, number = 0;
  std::string raw;
  char reply[pslab::kMaxReply + 1];
  while (std::getline(file, raw)) {
    ++number;
    std::string text = strip(raw);
    if (text.empty() || text[0] == '#') continue;
    size_t arrow = text.find("=>");
    std::string left = strip(arrow == std::string::npos ? text : text.substr(0, arrow));
    std::string right = arrow == std::string::npos ? "" : strip(text.substr(arrow + 2));
    std::string command, expected;
    if (!unescape(left, &command) || !unescape(right, &expected)) {
      std::cerr << "line " << number << ": bad escape\n";
      return 2;
    }
    bool expect_none = (right == "(none)");
    if (command.compare(0, 8, "@advance") == 0) {
      now += static_cast<uint32_t>(std::strtoul(command.c_str() + 8, 0, 10));
      continue;
    }
    std::string got;
    bool got_reply = false;
    if (command.compare(0, 7, "@lights") == 0) {
      delete controller;
      unsigned long lights = std::strtoul(command.c_str() + 7, 0, 10);
      controller = new pslab::Controller(static_cast<uint8_t>(lights), 0, 0);
      reader = pslab::LineReader();
      now = 0;
      size_t n = controller->boot(now, reply, sizeof(reply));
      got.assign(reply, n);
      got_reply = true;
    } else {
      if (controller == 0) {
        std::cerr << "line " << number << ": a vector before any @lights\n";
        return 2;
      }
      std::string bytes = command + "\n";
      for (size_t i = 0; i < bytes.size(); ++i) {
        controller->poll(now);
        if (reader.feed(bytes[i])) {
          size_t n = controller->handle_line(reader.line(), reader.too_long(), now, reply, sizeof(reply));
          if (n > 0) {
            got.assign(reply, n);
            got_reply = true;
          }
        }
      }
    }
    bool ok = expect_none ? !got_reply : (got_reply && got == expected);
    if (ok) {
      ++passed;
    } else {
      ++failed;
      std::cout << "FAIL line " << number << ": sent '" << visible(command) << "', expected '"
                << (expect_none ? "(none)" : visible(expected)) << "', got '"
                << (got_reply ? visible(got) : "(none)") << "'\n";
    }
  }
  delete controller;
  std::cout << passed << " vectors passed, " << failed << " failed\n";
  return failed == 0 && passed > 0 ? 0 : 1;
}
