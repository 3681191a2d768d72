// specgpu LED controller firmware: protocol version 1 (docs/guide/led-controller.md).
//
// A sequence of per-channel PWM duty vectors (and all-off dark steps) is uploaded over USB serial; once armed, each
// rising edge on the trigger pin (the camera's exposure-active output) shows the next step. The interrupt routine
// itself writes the duties, so a step never waits for the serial loop. An edge that comes sooner than the hold-off
// after the previous step is counted as missed and does not step; the host reads the counters (STAT) before it
// accepts each frame.
//
// Boards: a Teensy 4.x (13 channels, 12-bit PWM at 36.6 kHz) or an Arduino Uno / Nano class board (6 channels,
// 8-bit PWM at the core's 490 Hz). Pins are set below. Build with the Arduino IDE or arduino-cli (Teensyduino for
// a Teensy). specgpu.hardware.led.SimulatedLedBoard is this program's state machine in Python: keep both in step.

#include <Arduino.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#define PROTOCOL_VERSION 1
#define FIRMWARE_VERSION "1.0.0"
#define MAX_LINE 128

#if defined(TEENSYDUINO)
const uint8_t MAX_CHANNELS = 13;
const uint8_t CHANNEL_PINS[MAX_CHANNELS] = {2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 15};
const uint8_t TRIGGER_PIN = 22;
const uint8_t PWM_BITS = 12;
const uint32_t PWM_HZ = 36621;  // the highest frequency at 12 bit on a Teensy 4 (its ideal frequency table)
const uint16_t MAX_STEPS = 256;
#else
const uint8_t MAX_CHANNELS = 6;
const uint8_t CHANNEL_PINS[MAX_CHANNELS] = {3, 5, 6, 9, 10, 11};
const uint8_t TRIGGER_PIN = 2;  // INT0
const uint8_t PWM_BITS = 8;
const uint32_t PWM_HZ = 490;
const uint16_t MAX_STEPS = 32;  // 2 KiB of RAM
#endif

const uint16_t FULL_SCALE = (1u << PWM_BITS) - 1;

// ---- the sequence table (written by the serial loop while disarmed, read by the interrupt while armed) -------------
uint16_t table[MAX_STEPS][MAX_CHANNELS];
bool darkStep[MAX_STEPS];
bool filled[MAX_STEPS];
uint16_t seqLen = 0;
bool complete = false;
uint8_t channels = MAX_CHANNELS;

// ---- trigger state, shared with the interrupt routine ---------------------------------------------------------------
volatile bool armed = false;
volatile uint32_t pulses = 0;
volatile uint32_t steps = 0;
volatile uint32_t missed = 0;
volatile int32_t firstMissed = -1;
volatile int32_t current = -1;  // the step shown, -1 none
volatile uint32_t lastStepUs = 0;
volatile bool stepped = false;
volatile uint32_t holdoffUs = 20;

char line[MAX_LINE + 1];
uint16_t lineLen = 0;
bool overflow = false;
char reply[MAX_LINE + 1];

// CRC-8/SMBUS: polynomial 0x07, initial 0, no reflection, no final XOR ("123456789" -> 0xF4).
uint8_t crc8(const char *data, size_t n) {
  uint8_t crc = 0;
  for (size_t i = 0; i < n; i++) {
    crc ^= (uint8_t)data[i];
    for (uint8_t b = 0; b < 8; b++) crc = (crc & 0x80) ? (uint8_t)((crc << 1) ^ 0x07) : (uint8_t)(crc << 1);
  }
  return crc;
}

// Write the outputs of step k (-1: all off). Called from the interrupt routine and, disarmed, from the loop.
void showStep(int32_t k) {
  for (uint8_t c = 0; c < MAX_CHANNELS; c++) {
    uint16_t duty = (k >= 0 && c < channels && !darkStep[k]) ? table[k][c] : 0;
    analogWrite(CHANNEL_PINS[c], duty);
  }
}

void onTrigger() {
  if (!armed) return;
  uint32_t now = micros();
  uint32_t p = pulses++;
  if (stepped && (uint32_t)(now - lastStepUs) < holdoffUs) {  // too soon after the last step: a missed trigger
    missed++;
    if (firstMissed < 0) firstMissed = (int32_t)p;
    return;
  }
  lastStepUs = now;
  stepped = true;
  int32_t k = (int32_t)(steps % seqLen);
  steps++;
  current = k;
  showStep(k);
}

// ---- replies ------------------------------------------------------------------------------------------------------
void send(const char *body) {
  Serial.print(body);
  char tail[6];
  snprintf(tail, sizeof tail, "*%02X\n", crc8(body, strlen(body)));
  Serial.print(tail);
}

void ok(const char *fmt, ...) {
  char values[MAX_LINE - 8];
  va_list args;
  va_start(args, fmt);
  vsnprintf(values, sizeof values, fmt, args);
  va_end(args);
  snprintf(reply, sizeof reply, values[0] ? "OK %s" : "OK%s", values);
  send(reply);
}

void err(int code, const char *fmt, ...) {
  char text[MAX_LINE - 16];
  va_list args;
  va_start(args, fmt);
  vsnprintf(text, sizeof text, fmt, args);
  va_end(args);
  snprintf(reply, sizeof reply, "ERR %d %s", code, text);
  send(reply);
}

// ---- commands -----------------------------------------------------------------------------------------------------
#define MAX_ARGS (MAX_CHANNELS + 1)
long args[MAX_ARGS];
int nargs;

bool count(int n, const char *name) {
  if (nargs == n) return true;
  err(3, "%s takes %d argument%s", name, n, n == 1 ? "" : "s");
  return false;
}

bool checkStep(long i) {  // may step i of the table be written or shown now?
  if (armed) { err(4, "stop before uploading"); return false; }
  if (seqLen == 0) { err(5, "send SEQ first"); return false; }
  if (i < 0 || i >= seqLen) { err(3, "step must be 0 to %u", (unsigned)(seqLen - 1)); return false; }
  return true;
}

void execute(const char *word) {
  if (!strcmp(word, "ID")) {
    if (count(0, "ID"))
      ok("SPECGPU-LED %d %s %u %u %lu %u", PROTOCOL_VERSION, FIRMWARE_VERSION, MAX_CHANNELS, PWM_BITS,
         (unsigned long)PWM_HZ, MAX_STEPS);
  } else if (!strcmp(word, "CH")) {
    if (!count(1, "CH")) return;
    if (armed) return err(4, "stop before changing the channel count");
    if (args[0] < 1 || args[0] > MAX_CHANNELS) return err(3, "channel count must be 1 to %u", MAX_CHANNELS);
    channels = (uint8_t)args[0];
    seqLen = 0;
    complete = false;
    ok("%u", channels);
  } else if (!strcmp(word, "SEQ")) {
    if (!count(1, "SEQ")) return;
    if (armed) return err(4, "stop before uploading");
    if (args[0] < 1 || args[0] > MAX_STEPS) return err(3, "step count must be 1 to %u", MAX_STEPS);
    seqLen = (uint16_t)args[0];
    for (uint16_t i = 0; i < seqLen; i++) { filled[i] = false; darkStep[i] = true; }
    complete = false;
    ok("%u", seqLen);
  } else if (!strcmp(word, "STEP")) {
    if (!count(1 + channels, "STEP") || !checkStep(args[0])) return;
    for (uint8_t c = 0; c < channels; c++)
      if (args[1 + c] < 0 || args[1 + c] > FULL_SCALE) return err(3, "duty out of range 0 to %u", FULL_SCALE);
    for (uint8_t c = 0; c < channels; c++) table[args[0]][c] = (uint16_t)args[1 + c];
    darkStep[args[0]] = false;
    filled[args[0]] = true;
    ok("%ld", args[0]);
  } else if (!strcmp(word, "DARK")) {
    if (!count(1, "DARK") || !checkStep(args[0])) return;
    darkStep[args[0]] = true;
    filled[args[0]] = true;
    ok("%ld", args[0]);
  } else if (!strcmp(word, "END")) {
    if (!count(0, "END")) return;
    if (seqLen == 0) return err(5, "send SEQ first");
    for (uint16_t i = 0; i < seqLen; i++)
      if (!filled[i]) return err(3, "step %u not uploaded", i);
    complete = true;
    ok("%u", seqLen);
  } else if (!strcmp(word, "HOLD")) {
    if (!count(1, "HOLD")) return;
    if (args[0] < 0 || args[0] > 1000000L) return err(3, "hold-off must be 0 to 1000000 us");
    noInterrupts();
    holdoffUs = (uint32_t)args[0];
    interrupts();
    ok("%ld", args[0]);
  } else if (!strcmp(word, "ARM")) {
    if (!count(0, "ARM")) return;
    if (!complete) return err(5, "upload a sequence first");
    noInterrupts();
    pulses = steps = missed = 0;
    firstMissed = current = -1;
    stepped = false;
    showStep(-1);
    armed = true;
    interrupts();
    ok("%u", seqLen);
  } else if (!strcmp(word, "STAT")) {
    if (!count(0, "STAT")) return;
    noInterrupts();  // one consistent snapshot of the counters
    bool a = armed;
    uint32_t p = pulses, s = steps, m = missed;
    int32_t f = firstMissed, k = current;
    interrupts();
    ok("%d %lu %lu %lu %ld %ld", a ? 1 : 0, (unsigned long)p, (unsigned long)s, (unsigned long)m, (long)f, (long)k);
  } else if (!strcmp(word, "STOP")) {
    if (!count(0, "STOP")) return;
    noInterrupts();
    armed = false;
    showStep(-1);
    uint32_t p = pulses, s = steps, m = missed;
    interrupts();
    ok("%lu %lu %lu", (unsigned long)p, (unsigned long)s, (unsigned long)m);
  } else if (!strcmp(word, "SHOW")) {
    if (!count(1, "SHOW") || !checkStep(args[0])) return;
    if (!complete) return err(5, "upload a sequence first");
    current = args[0];
    showStep(args[0]);
    ok("%ld", args[0]);
  } else {
    err(2, "unknown command %.16s", word);
  }
}

// One received line (without its newline): check the checksum, split the fields, run the command.
void handleLine(char *text, uint16_t n) {
  if (n && text[n - 1] == '\r') text[--n] = 0;
  char *star = strrchr(text, '*');
  char *end;
  if (!star || strlen(star + 1) != 2) return err(1, "checksum mismatch");
  unsigned long want = strtoul(star + 1, &end, 16);
  if (*end || want != crc8(text, (size_t)(star - text))) return err(1, "checksum mismatch");
  *star = 0;
  char *word = text;
  char *rest = strchr(text, ' ');
  nargs = 0;
  if (rest) {
    *rest++ = 0;
    while (rest && *rest) {
      char *next = strchr(rest, ' ');
      if (next) *next++ = 0;
      long v = strtol(rest, &end, 10);
      if (*end || end == rest) return err(3, "arguments must be integers");
      if (nargs < MAX_ARGS) args[nargs] = v;
      nargs++;  // counted past MAX_ARGS too, so a long line is refused by its argument count
      rest = next;
    }
  }
  if (nargs > MAX_ARGS) nargs = MAX_ARGS + 1;
  execute(word);
}

void setup() {
  Serial.begin(115200);
#if defined(TEENSYDUINO)
  analogWriteResolution(PWM_BITS);
  for (uint8_t c = 0; c < MAX_CHANNELS; c++) analogWriteFrequency(CHANNEL_PINS[c], PWM_HZ);
#endif
  for (uint8_t c = 0; c < MAX_CHANNELS; c++) {
    pinMode(CHANNEL_PINS[c], OUTPUT);
    analogWrite(CHANNEL_PINS[c], 0);
  }
  pinMode(TRIGGER_PIN, INPUT);
  attachInterrupt(digitalPinToInterrupt(TRIGGER_PIN), onTrigger, RISING);
}

void loop() {
  while (Serial.available()) {
    char c = (char)Serial.read();
    if (c == '\n') {
      line[lineLen] = 0;
      if (overflow) err(6, "line too long");
      else handleLine(line, lineLen);
      lineLen = 0;
      overflow = false;
    } else if (lineLen < MAX_LINE - 1) {  // MAX_LINE counts the newline
      line[lineLen++] = c;
    } else {
      overflow = true;
    }
  }
}
