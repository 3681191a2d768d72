// Runs the LED controller firmware on the host. Each stdin line is either a protocol line for the firmware's serial
// port, "!TRIG <us>" (a rising edge on the trigger pin at that time) or "!PWM" (print the channel pins' duties).
#include <iostream>
#include "Arduino.h"

uint32_t host_micros = 0;
int host_pwm[64] = {0};
void (*host_isr)() = nullptr;
HostSerial Serial;

#include "led_controller.ino"

int main() {
  setup();
  std::string text;
  while (std::getline(std::cin, text)) {
    if (text.rfind("!TRIG ", 0) == 0) {
      host_micros = (uint32_t)std::stoul(text.substr(6));
      host_isr();
    } else if (text == "!PWM") {
      fputs("PWM", stdout);
      for (uint8_t c = 0; c < MAX_CHANNELS; c++) printf(" %d", host_pwm[CHANNEL_PINS[c]]);
      fputs("\n", stdout);
    } else {
      Serial.input += text + "\n";
      while (Serial.available()) loop();
    }
    fflush(stdout);
  }
  return 0;
}
