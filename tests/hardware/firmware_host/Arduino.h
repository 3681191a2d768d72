// A host-side stand-in for the Arduino core, just enough to run the LED controller firmware as a program:
// Serial reads the bytes main.cpp hands it and writes to stdout, analogWrite records each pin's duty, micros() is
// the time the test sets, attachInterrupt keeps the trigger routine for main.cpp to call.
#pragma once
#include <stdint.h>
#include <stdio.h>
#include <string>

#define INPUT 0
#define OUTPUT 1
#define RISING 3

extern uint32_t host_micros;
extern int host_pwm[64];
extern void (*host_isr)();

inline uint32_t micros() { return host_micros; }
inline void noInterrupts() {}
inline void interrupts() {}
inline void pinMode(int, int) {}
inline void analogWrite(int pin, int value) { host_pwm[pin] = value; }
inline void analogWriteResolution(int) {}
inline void analogWriteFrequency(int, float) {}
inline int digitalPinToInterrupt(int pin) { return pin; }
inline void attachInterrupt(int, void (*isr)(), int) { host_isr = isr; }

struct HostSerial {
  std::string input;
  size_t at = 0;
  void begin(long) {}
  int available() { return (int)(input.size() - at); }
  int read() { return at < input.size() ? (unsigned char)input[at++] : -1; }
  void print(const char *s) { fputs(s, stdout); }
};
extern HostSerial Serial;
