/*
 * ps_lab_avr: runs the compiled ps-lab light-controller sketch (an AVR ELF) in simavr, in step
 * with the wall clock, with UART0 on a pseudo-terminal and the light pins reported as they change.
 *
 *   ps_lab_avr --pins 3,5,6,9,10,11,2,4,7,8,12,13 [--state-file F] [--boot-ms 250]
 *              [--no-reset-on-open] [--every-cycle] [--mcu atmega328p] [--frequency 16000000]
 *              [--max-lag-ms 200] [--verbose] SKETCH.elf
 *
 * stdout, line 1: the device path of the pty (what `ps-lab rig serve-sim` prints first).
 * stdout, then:   one JSON line per change of the light pins, light i being on pins[i - 1]:
 *   {"t_ms": 812.44, "lit": [3], "level": 255, "levels": [0, 0, 255, ...], "duty": [...]}
 * --state-file F: the same object without t_ms, written to F atomically (temporary file +
 *   rename) on every change, before the MCU sends another byte; the format of
 *   `ps-lab rig serve-sim --state-file` ({"lit": [...], "level": v}, plus per-light detail;
 *   "level" is the brightest lit light's, 0 when none is lit).
 *
 * A light's level is what the pin drives, read from the MCU's own registers: 255 or 0 for a
 * digital output (PORTx/DDRx), and for a pin whose timer compare output is connected (COMnx bits)
 * the compare value scaled to 0-255 -- the value analogWrite() was given. "duty" is the exact
 * fraction of time the pin is high (timer0 runs fast PWM: (OCR + 1) / 256; timers 1 and 2
 * phase-correct PWM: OCR / 255). A pin that is not an output drives nothing: level 0.
 *
 * Reset on open: an Uno resets when the host opens its port (DTR). The harness watches the pty
 * with inotify; when another process opens it, the MCU is held in reset for --boot-ms (the
 * bootloader's time; every output is off, received bytes are lost, as the bootloader swallows
 * them), then the sketch starts from its reset vector and announces READY.
 *
 * Time: simavr counts cycles exactly (timer0 drives millis()); the main loop runs the MCU in
 * slices of 100 us and sleeps whenever it is ahead of the wall clock, so a watchdog of 400 ms is
 * 400 ms of wall time. If the host falls behind by more than --max-lag-ms, the MCU loses that
 * time (as if it had stalled) rather than racing to catch up. Between two calls of the sketch's
 * loop() the MCU idles until the next interrupt (see "Idle skip" below; --every-cycle turns
 * that off).
 *
 * SIGUSR1 resets the MCU at once, as a brown-out between commands does (tests of the driver's
 * recovery). SIGINT/SIGTERM (or the parent's death) end it with status 0 after removing the
 * state file.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <getopt.h>
#include <limits.h>
#include <signal.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/inotify.h>
#include <sys/ioctl.h>
#include <sys/prctl.h>
#include <termios.h>
#include <time.h>
#include <unistd.h>

#include <sim_avr.h>
#include <sim_elf.h>
#include <avr_ioport.h>
#include <avr_extint.h>
#include <avr_uart.h>
#include <uart_pty.h>

DEFINE_FIFO(uint8_t, uart_pty_fifo);

#define MAX_LIGHTS 64

/* ATmega328P data-space addresses of the timer registers (datasheet, "Register Summary"). */
enum {
  TCCR0A = 0x44, TCCR0B = 0x45, OCR0A = 0x47, OCR0B = 0x48,
  TCCR1A = 0x80, TCCR1B = 0x81, ICR1L = 0x86, OCR1AL = 0x88, OCR1BL = 0x8A,
  TCCR2A = 0xB0, TCCR2B = 0xB1, OCR2A = 0xB3, OCR2B = 0xB4,
};

/* A compare output: timer 0-2, channel 0 (A) or 1 (B). */
typedef struct {
  int timer, channel;
} compare_output_t;

typedef struct {
  int arduino_pin;       /* Uno numbering: D0-D13, A0-A5 = 14-19 */
  char port;             /* 'B', 'C', 'D' */
  int bit;
  compare_output_t oc;   /* timer < 0: no PWM on this pin */
} light_pin_t;

typedef struct {
  int level;     /* 0-255 */
  double duty;   /* 0-1 */
} pin_output_t;

static volatile sig_atomic_t stop_requested = 0;
static volatile sig_atomic_t reset_requested = 0;
static void on_signal(int sig) { (void)sig; stop_requested = 1; }
static void on_reset_signal(int sig) { (void)sig; reset_requested = 1; }

static int64_t monotonic_ns(void) {
  struct timespec ts;
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return (int64_t)ts.tv_sec * 1000000000LL + ts.tv_nsec;
}

static void sleep_ns(int64_t ns) {
  if (ns <= 0) return;
  struct timespec ts = {ns / 1000000000LL, ns % 1000000000LL};
  nanosleep(&ts, NULL);
}

static int describe_pin(int pin, light_pin_t *out) {
  static const compare_output_t none = {-1, 0};
  out->arduino_pin = pin;
  out->oc = none;
  if (pin >= 0 && pin <= 7) {
    out->port = 'D';
    out->bit = pin;
  } else if (pin >= 8 && pin <= 13) {
    out->port = 'B';
    out->bit = pin - 8;
  } else if (pin >= 14 && pin <= 19) {
    out->port = 'C';
    out->bit = pin - 14;
  } else {
    return -1;
  }
  /* OC2B = D3, OC0B = D5, OC0A = D6, OC1A = D9, OC1B = D10, OC2A = D11. */
  switch (pin) {
    case 3: out->oc = (compare_output_t){2, 1}; break;
    case 5: out->oc = (compare_output_t){0, 1}; break;
    case 6: out->oc = (compare_output_t){0, 0}; break;
    case 9: out->oc = (compare_output_t){1, 0}; break;
    case 10: out->oc = (compare_output_t){1, 1}; break;
    case 11: out->oc = (compare_output_t){2, 0}; break;
    default: break;
  }
  return 0;
}

/* What a connected compare output drives, from the timer's mode (WGM), COM bits and OCR. */
static pin_output_t compare_output_level(const avr_t *avr, compare_output_t oc, int com) {
  const uint8_t *d = avr->data;
  unsigned wgm, top, ocr;
  int fast = 0, pwm = 0;
  if (oc.timer == 1) {
    wgm = (d[TCCR1A] & 3u) | (((d[TCCR1B] >> 3) & 3u) << 2);
    unsigned icr = d[ICR1L] | (d[ICR1L + 1] << 8);
    unsigned ocra = d[OCR1AL] | (d[OCR1AL + 1] << 8);
    ocr = oc.channel == 0 ? ocra : (unsigned)(d[OCR1BL] | (d[OCR1BL + 1] << 8));
    static const int tops[16] = {0xFFFF, 0xFF, 0x1FF, 0x3FF, -1, 0xFF, 0x1FF, 0x3FF,
                                 -2, -1, -2, -1, -2, 0, -2, -1};
    int t = tops[wgm];
    top = t == -1 ? ocra : t == -2 ? icr : (unsigned)t;
    fast = wgm == 5 || wgm == 6 || wgm == 7 || wgm == 14 || wgm == 15;
    pwm = fast || wgm == 1 || wgm == 2 || wgm == 3 || wgm == 8 || wgm == 9 || wgm == 10 ||
          wgm == 11;
  } else {
    int a = oc.timer == 0 ? TCCR0A : TCCR2A, b = oc.timer == 0 ? TCCR0B : TCCR2B;
    int ra = oc.timer == 0 ? OCR0A : OCR2A, rb = oc.timer == 0 ? OCR0B : OCR2B;
    wgm = (d[a] & 3u) | (((d[b] >> 3) & 1u) << 2);
    top = (wgm == 5 || wgm == 7) ? d[ra] : 0xFF;
    ocr = oc.channel == 0 ? d[ra] : d[rb];
    fast = wgm == 3 || wgm == 7;
    pwm = fast || wgm == 1 || wgm == 5;
  }
  pin_output_t out = {0, 0.0};
  if (!pwm) {
    /* Normal/CTC: 1 toggles (a square wave), 2 clears, 3 sets the pin on compare. */
    out.duty = com == 1 ? 0.5 : com == 3 ? 1.0 : 0.0;
  } else if (com == 1) {
    /* Reserved for channel B; channel A toggles only with TOP = OCRA: treat as a square wave. */
    out.duty = 0.5;
  } else {
    double duty;
    if (top == 0) duty = 1.0;
    else if (fast) duty = ocr >= top ? 1.0 : (ocr + 1.0) / (top + 1.0);
    else duty = ocr >= top ? 1.0 : (double)ocr / top;
    double scaled = top == 0 ? 255.0 : 255.0 * (ocr > top ? top : ocr) / top;
    if (com == 3) {
      duty = 1.0 - duty;
      scaled = 255.0 - scaled;
    }
    out.duty = duty;
    out.level = (int)(scaled + 0.5);
    return out;
  }
  out.level = (int)(out.duty * 255.0 + 0.5);
  return out;
}

static pin_output_t pin_output(avr_t *avr, const light_pin_t *pin) {
  pin_output_t out = {0, 0.0};
  avr_ioport_state_t state;
  if (avr_ioctl(avr, AVR_IOCTL_IOPORT_GETSTATE(pin->port), &state) != 0) return out;
  if (!((state.ddr >> pin->bit) & 1)) return out; /* an input drives nothing */
  if (pin->oc.timer >= 0) {
    int reg = pin->oc.timer == 0 ? TCCR0A : pin->oc.timer == 1 ? TCCR1A : TCCR2A;
    int com = (avr->data[reg] >> (pin->oc.channel == 0 ? 6 : 4)) & 3;
    if (com != 0) return compare_output_level(avr, pin->oc, com);
  }
  if ((state.port >> pin->bit) & 1) {
    out.level = 255;
    out.duty = 1.0;
  }
  return out;
}

typedef struct {
  avr_t *avr;
  light_pin_t pins[MAX_LIGHTS];
  int count;
  pin_output_t last[MAX_LIGHTS];
  int reported;
  FILE *out;
  const char *state_file;
  char state_tmp[PATH_MAX];
} reporter_t;

static int format_state(const reporter_t *r, const pin_output_t *now, char *buf, size_t size) {
  size_t n = 0;
  int level = 0;
  n += snprintf(buf + n, size - n, "\"lit\": [");
  int first = 1;
  for (int i = 0; i < r->count; ++i) {
    if (now[i].level > 0) {
      n += snprintf(buf + n, size - n, "%s%d", first ? "" : ", ", i + 1);
      first = 0;
      if (now[i].level > level) level = now[i].level;
    }
  }
  n += snprintf(buf + n, size - n, "], \"level\": %d, \"levels\": [", level);
  for (int i = 0; i < r->count; ++i)
    n += snprintf(buf + n, size - n, "%s%d", i ? ", " : "", now[i].level);
  n += snprintf(buf + n, size - n, "], \"duty\": [");
  for (int i = 0; i < r->count; ++i)
    n += snprintf(buf + n, size - n, "%s%.6g", i ? ", " : "", now[i].duty);
  n += snprintf(buf + n, size - n, "], \"pins\": [");
  for (int i = 0; i < r->count; ++i)
    n += snprintf(buf + n, size - n, "%s%d", i ? ", " : "", r->pins[i].arduino_pin);
  n += snprintf(buf + n, size - n, "]");
  return n < size ? 0 : -1;
}

static void write_state_file(reporter_t *r, const char *body) {
  FILE *f = fopen(r->state_tmp, "w");
  if (f == NULL) {
    fprintf(stderr, "ps_lab_avr: cannot write %s: %s\n", r->state_tmp, strerror(errno));
    return;
  }
  fprintf(f, "{%s}\n", body);
  if (fclose(f) != 0 || rename(r->state_tmp, r->state_file) != 0)
    fprintf(stderr, "ps_lab_avr: cannot write %s: %s\n", r->state_file, strerror(errno));
}

/* Report the light pins if any changed since the last report (or always, with force). */
static void report_pins(reporter_t *r, int force) {
  pin_output_t now[MAX_LIGHTS];
  int changed = force || !r->reported;
  for (int i = 0; i < r->count; ++i) {
    now[i] = pin_output(r->avr, &r->pins[i]);
    if (now[i].level != r->last[i].level || now[i].duty != r->last[i].duty) changed = 1;
  }
  if (!changed) return;
  memcpy(r->last, now, sizeof(now));
  r->reported = 1;
  char body[8192];
  if (format_state(r, now, body, sizeof(body)) != 0) return;
  if (r->state_file != NULL) write_state_file(r, body);
  double t_ms = (double)r->avr->cycle * 1000.0 / r->avr->frequency;
  fprintf(r->out, "{\"t_ms\": %.3f, %s}\n", t_ms, body);
  fflush(r->out);
}

static int parse_pins(const char *text, reporter_t *r) {
  char *copy = strdup(text), *save = NULL;
  r->count = 0;
  for (char *tok = strtok_r(copy, ", ", &save); tok; tok = strtok_r(NULL, ", ", &save)) {
    char *end;
    long pin = strtol(tok, &end, 10);
    if (*end != '\0' || r->count >= MAX_LIGHTS || describe_pin((int)pin, &r->pins[r->count]) != 0 ||
        pin <= 1) {
      fprintf(stderr, "ps_lab_avr: bad pin %s in --pins (Uno pins 2-19, at most %d)\n", tok,
              MAX_LIGHTS);
      free(copy);
      return -1;
    }
    r->count++;
  }
  free(copy);
  return r->count > 0 ? 0 : -1;
}

static void no_sleep(avr_t *avr, avr_cycle_count_t how_long) {
  /* The main loop keeps the MCU in step with the wall clock; a SLEEP needs no extra wait. */
  (void)avr;
  (void)how_long;
}

/* Flash byte address of the sketch's loop() from the ELF's symbols, or -1. */
static long find_symbol(const elf_firmware_t *firmware, const char *name) {
  for (uint32_t i = 0; i < firmware->symbolcount; ++i) {
    if (firmware->symbol[i] != NULL && strcmp(firmware->symbol[i]->symbol, name) == 0)
      return (long)firmware->symbol[i]->addr;
  }
  return -1;
}

/* avr_reset(), then undo what a reset of simavr's modules turns back on: D2 and D3 are INT0 and
 * INT1, and while such a pin is low simavr polls it on every cycle in case the low-level
 * interrupt is enabled ("strict" level triggering), which slows the simulation far below real
 * time. The sketch uses no external interrupt; edges still trigger without the polling. */
static void reset_mcu(avr_t *avr) {
  avr_reset(avr);
  avr_extint_set_strict_lvl_trig(avr, 0, 0);
  avr_extint_set_strict_lvl_trig(avr, 1, 0);
}

static void usage(void) {
  fprintf(stderr,
          "usage: ps_lab_avr --pins P1,P2,... [--state-file F] [--boot-ms MS] "
          "[--no-reset-on-open] [--every-cycle] [--mcu NAME] [--frequency HZ] [--max-lag-ms MS] "
          "[--verbose] "
          "SKETCH.elf\n");
}

int main(int argc, char **argv) {
  const char *mcu = "atmega328p", *pins_text = NULL, *state_file = NULL;
  long frequency = 16000000, boot_ms = 250, max_lag_ms = 200;
  int reset_on_open = 1, verbose = 0, idle_skip = 1;
  static const struct option options[] = {
      {"pins", required_argument, 0, 'p'},      {"state-file", required_argument, 0, 's'},
      {"boot-ms", required_argument, 0, 'b'},   {"no-reset-on-open", no_argument, 0, 'n'},
      {"mcu", required_argument, 0, 'm'},       {"frequency", required_argument, 0, 'f'},
      {"max-lag-ms", required_argument, 0, 'l'}, {"verbose", no_argument, 0, 'v'},
      {"every-cycle", no_argument, 0, 'e'},
      {"help", no_argument, 0, 'h'},            {0, 0, 0, 0}};
  for (int c; (c = getopt_long(argc, argv, "p:s:b:nm:f:l:veh", options, NULL)) != -1;) {
    switch (c) {
      case 'p': pins_text = optarg; break;
      case 's': state_file = optarg; break;
      case 'b': boot_ms = atol(optarg); break;
      case 'n': reset_on_open = 0; break;
      case 'm': mcu = optarg; break;
      case 'f': frequency = atol(optarg); break;
      case 'l': max_lag_ms = atol(optarg); break;
      case 'v': verbose = 1; break;
      case 'e': idle_skip = 0; break;
      default: usage(); return c == 'h' ? 0 : 2;
    }
  }
  if (optind != argc - 1 || pins_text == NULL || frequency <= 0 || boot_ms < 0 ||
      max_lag_ms <= 0) {
    usage();
    return 2;
  }
  const char *elf_path = argv[optind];
  static reporter_t reporter;
  if (parse_pins(pins_text, &reporter) != 0) return 2;
  reporter.state_file = state_file;
  if (state_file != NULL)
    snprintf(reporter.state_tmp, sizeof(reporter.state_tmp), "%s.%d.tmp", state_file,
             (int)getpid());

  /* Our stdout carries the device path and the pin reports; simavr prints chatter with printf
   * (pty name, baud rate): send that to stderr with --verbose, else nowhere. */
  int report_fd = dup(STDOUT_FILENO);
  int chatter = verbose ? dup(STDERR_FILENO) : open("/dev/null", O_WRONLY);
  if (report_fd < 0 || chatter < 0 || dup2(chatter, STDOUT_FILENO) < 0) {
    perror("ps_lab_avr: stdout");
    return 1;
  }
  close(chatter);
  reporter.out = fdopen(report_fd, "w");

  prctl(PR_SET_PDEATHSIG, SIGTERM); /* never outlive the process that started us */
  struct sigaction sa;
  memset(&sa, 0, sizeof(sa));
  sa.sa_handler = on_signal;
  sigaction(SIGINT, &sa, NULL);
  sigaction(SIGTERM, &sa, NULL);
  sa.sa_handler = on_reset_signal;
  sigaction(SIGUSR1, &sa, NULL);
  signal(SIGPIPE, SIG_IGN);

  elf_firmware_t firmware;
  memset(&firmware, 0, sizeof(firmware));
  if (elf_read_firmware(elf_path, &firmware) != 0 || firmware.flashsize == 0) {
    fprintf(stderr, "ps_lab_avr: cannot load %s (not an AVR ELF?)\n", elf_path);
    return 1;
  }
  /* An Arduino build carries no .mmcu section: the board is given on the command line. */
  snprintf(firmware.mmcu, sizeof(firmware.mmcu), "%s", mcu);
  firmware.frequency = (uint32_t)frequency;
  avr_t *avr = avr_make_mcu_by_name(firmware.mmcu);
  if (avr == NULL) {
    fprintf(stderr, "ps_lab_avr: simavr does not know the MCU %s\n", mcu);
    return 1;
  }
  avr_init(avr);
  avr_load_firmware(avr, &firmware);
  avr->log = verbose ? LOG_WARNING : LOG_NONE;
  avr->sleep = no_sleep;
  reset_mcu(avr);
  reporter.avr = avr;
  long loop_pc = idle_skip ? find_symbol(&firmware, "loop") : -1;
  if (idle_skip && loop_pc < 0)
    fprintf(stderr, "ps_lab_avr: no loop() symbol in %s: simulating every cycle\n", elf_path);
  int slept_at_loop = 0;
  long idle_sleeps = 0;
  if (verbose && loop_pc >= 0) fprintf(stderr, "ps_lab_avr: loop() at 0x%lx\n", loop_pc);

  static uart_pty_t pty;
  uart_pty_init(avr, &pty);
  uart_pty_connect(&pty, '0');
  uint32_t flags = 0; /* no stdio echo, no usleep while the sketch polls UCSR0A */
  avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
  /* uart_pty points /tmp/simavr-uart0 at its pty; several harnesses may run at once, and only
   * the path printed below is ours. */
  char link_target[64] = "";
  ssize_t link_len = readlink("/tmp/simavr-uart0", link_target, sizeof(link_target) - 1);
  if (link_len > 0 && (size_t)link_len < sizeof(link_target)) {
    link_target[link_len] = '\0';
    if (strcmp(link_target, pty.pty.slavename) == 0) unlink("/tmp/simavr-uart0");
  }

  /* Our own handle on the device side, to discard what the MCU sent while nobody had the port
   * open: a host reads a USB serial port only while it is open, so a real board's output before
   * the open (an unread READY, a reply cut short by the reset) never reaches the next program. */
  int device_fd = open(pty.pty.slavename, O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
  int watch = -1;
  if (reset_on_open) {
    watch = inotify_init1(IN_NONBLOCK | IN_CLOEXEC);
    if (watch < 0 ||
        inotify_add_watch(watch, pty.pty.slavename, IN_OPEN | IN_CLOSE_WRITE | IN_CLOSE_NOWRITE) < 0) {
      fprintf(stderr, "ps_lab_avr: cannot watch %s for opens: %s\n", pty.pty.slavename,
              strerror(errno));
      return 1;
    }
  }

  fprintf(reporter.out, "%s\n", pty.pty.slavename);
  fflush(reporter.out);
  report_pins(&reporter, 1);

  const int64_t slice_cycles = frequency / 10000; /* 100 us */
  const int64_t max_lag_cycles = frequency / 1000 * max_lag_ms;
  int64_t base_ns = monotonic_ns();
  int64_t base_cycle = (int64_t)avr->cycle;
  int64_t last_cycle = base_cycle;
  /* >= 0: the MCU is held in reset (the bootloader) until then. With reset on open it waits
   * for the first open: a board that booted long before anyone opened its port, whose READY
   * nobody heard. */
  int64_t hold_until_ns = reset_on_open ? INT64_MAX : -1;
  int clients = 0; /* processes that have the device open (other than us) */
  int status = 0;

  while (!stop_requested) {
    if (watch >= 0) {
      char events[4096] __attribute__((aligned(__alignof__(struct inotify_event))));
      int opened = 0;
      ssize_t n;
      while ((n = read(watch, events, sizeof(events))) > 0) {
        for (char *p = events; p < events + n;) {
          struct inotify_event *e = (struct inotify_event *)p;
          if (e->mask & IN_OPEN) {
            opened = 1;
            clients++;
          }
          if ((e->mask & (IN_CLOSE_WRITE | IN_CLOSE_NOWRITE)) && clients > 0) clients--;
          p += sizeof(*e) + e->len;
        }
      }
      int pending = 0;
      if (clients == 0 && device_fd >= 0 && ioctl(device_fd, FIONREAD, &pending) == 0 && pending > 0)
        tcflush(device_fd, TCIFLUSH); /* nobody has the port open: the output is lost */
      if (opened) {
        /* DTR: reset now (every pin an input, so every light off) and stay in the bootloader. */
        reset_mcu(avr);
        if (device_fd >= 0) tcflush(device_fd, TCIFLUSH);
        /* At least 2 ms, so that whatever the pty thread still holds is written, then dropped. */
        hold_until_ns = monotonic_ns() + (boot_ms > 2 ? boot_ms : 2) * 1000000LL;
        report_pins(&reporter, 0);
        if (verbose) fprintf(stderr, "ps_lab_avr: port opened, reset\n");
      }
    }
    if (reset_requested) {
      /* A brown-out between commands: the sketch restarts at once (no bootloader wait after a
       * power-on or brown-out reset) and announces READY unasked. */
      reset_requested = 0;
      reset_mcu(avr);
      report_pins(&reporter, 0);
      if (verbose) fprintf(stderr, "ps_lab_avr: reset (SIGUSR1)\n");
    }
    int64_t now = monotonic_ns();
    if (hold_until_ns >= 0) {
      if (now < hold_until_ns) {
        sleep_ns(hold_until_ns - now < 1000000 ? hold_until_ns - now : 1000000);
        continue;
      }
      /* The bootloader swallowed whatever arrived meanwhile (with --boot-ms 0 there is no
       * bootloader: bytes wait until the sketch's UART is on); the sketch starts from reset. */
      if (boot_ms > 0)
        while (!uart_pty_fifo_isempty(&pty.pty.out)) uart_pty_fifo_read(&pty.pty.out);
      if (device_fd >= 0) tcflush(device_fd, TCIFLUSH);
      reset_mcu(avr);
      hold_until_ns = -1;
      base_ns = now;
      base_cycle = last_cycle = (int64_t)avr->cycle;
    }
    int64_t cycle = (int64_t)avr->cycle;
    if (cycle < last_cycle) { /* the MCU reset itself (its watchdog): the counter restarted */
      avr_extint_set_strict_lvl_trig(avr, 0, 0);
      avr_extint_set_strict_lvl_trig(avr, 1, 0);
      base_ns = now;
      base_cycle = cycle;
    }
    int64_t target = base_cycle + (now - base_ns) * frequency / 1000000000LL;
    if (target - cycle > max_lag_cycles) { /* the host stalled: skip, do not race */
      base_cycle -= target - cycle - max_lag_cycles;
      target = cycle + max_lag_cycles;
    }
    if (cycle >= target) {
      sleep_ns((cycle - target + slice_cycles) * 1000000000LL / frequency);
      continue;
    }
    int64_t end = cycle + slice_cycles < target ? cycle + slice_cycles : target;
    while ((int64_t)avr->cycle < end) {
      if (loop_pc >= 0) {
        /* Idle skip: between two calls of loop() the MCU waits for the next interrupt (timer0's
         * millisecond tick, a received byte, ...) in simavr's sleep, which jumps the cycle
         * counter to the next timer event, instead of spinning through loop() ~100000 times a
         * second, which costs simavr a whole CPU core and falls behind the wall clock on a busy
         * machine (--every-cycle simulates every cycle anyway). The body of loop() then runs
         * once after every interrupt. Inside an ISR the I flag is clear; seeing the PC
         * elsewhere with I set means loop() ran since the last sleep. */
        if (avr->pc == (avr_flashaddr_t)loop_pc) {
          if (!slept_at_loop && avr->state == cpu_Running && avr->sreg[S_I]) {
            avr->state = cpu_Sleeping;
            slept_at_loop = 1;
            idle_sleeps++;
          }
        } else if (avr->sreg[S_I]) {
          slept_at_loop = 0;
        }
      }
      int state = avr_run(avr);
      if (state == cpu_Done || state == cpu_Crashed) {
        fprintf(stderr, "ps_lab_avr: the MCU %s at pc 0x%04x\n",
                state == cpu_Done ? "stopped (sleep with interrupts off)" : "crashed",
                (unsigned)avr->pc);
        status = 3;
        stop_requested = 1;
        break;
      }
    }
    last_cycle = (int64_t)avr->cycle;
    report_pins(&reporter, 0);
  }

  if (state_file != NULL) unlink(state_file);
  if (verbose)
    fprintf(stderr, "ps_lab_avr: %.3f s of MCU time in %.3f s since the last reset, %ld idle sleeps\n",
            (double)avr->cycle / frequency, (monotonic_ns() - base_ns) / 1e9, idle_sleeps);
  /* Not uart_pty_stop(): it signals the pty thread and joins it, and hangs when the signal
   * lands outside the thread's select(). Exiting ends the thread and closes the pty. */
  return status;
}
