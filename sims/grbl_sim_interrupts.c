/*
  grbl_sim_interrupts.c - gonio's test-harness addition to grbl-sim (NOT part of GRBL firmware).

  grbl-sim runs GRBL's main loop on one thread and plays the AVR's interrupts (the serial RX and
  TX-empty ISRs, the stepper and limit timers) on another, with no exclusion between them. GRBL's
  code assumes the AVR's: an ISR runs between two main-loop instructions, never beside one, and a
  main-loop section bracketed by cli() ... SREG = sreg runs with no ISR beside it. On the host the
  two threads run side by side on two cores, and GCC -O2 also stores the ring-buffer index before
  the byte (serial.c's serial_write and ISR(SERIAL_RX); the indices are not volatile). Seen:
    - a stale byte sent in a reply ("-l.000": the TX ISR read the slot before the byte landed);
    - command bytes replaced the same way (the RX ISR's store vs the main loop's serial_read);
    - a real-time flag lost: the ISR thread's sys_rt_exec_state |= flag between the main loop's
      load and store of its own &= ~other, and the two threads' SREG save/restore interleaved.
  This file restores the exclusion the firmware relies on, with one recursive mutex standing for
  "interrupts disabled / an ISR is running": the serial ISRs and every system_*_exec_* flag
  update run under it on the ISR thread, and the main loop's serial_write, serial_read,
  serial_reset_read_buffer and flag updates run under it too. GRBL's code is unchanged: the
  functions are wrapped at link time (ld --wrap=NAME: calls from other objects go to
  __wrap_NAME, which calls the original as __real_NAME).

  serial_write waits for room in the TX ring outside the mutex (the original busy-waits for the
  ISR to drain it, which it cannot do while the waiter holds the mutex), then writes under it.
*/
#include <pthread.h>
#include "../grbl.h"

static pthread_mutex_t irq_mutex;
static pthread_once_t irq_once = PTHREAD_ONCE_INIT;

static void irq_init(void) {
  pthread_mutexattr_t attr;
  pthread_mutexattr_init(&attr);
  pthread_mutexattr_settype(&attr, PTHREAD_MUTEX_RECURSIVE);  /* an ISR sets flags inside its own section */
  pthread_mutex_init(&irq_mutex, &attr);
}

static void irq_lock(void) {
  pthread_once(&irq_once, irq_init);
  pthread_mutex_lock(&irq_mutex);
}

static void irq_unlock(void) { pthread_mutex_unlock(&irq_mutex); }

/* serial.c (GRBL's, serial_read renamed orig_serial_read by grbl-sim's serial_hooks.h) */
void __real_serial_write(uint8_t data);
uint8_t __real_orig_serial_read(void);
void __real_serial_reset_read_buffer(void);
void __real_interrupt_SERIAL_UDRE(void);
void __real_interrupt_SERIAL_RX(void);

void __wrap_serial_write(uint8_t data) {
  while (serial_get_tx_buffer_count() >= TX_BUFFER_SIZE) {
    if (sys_rt_exec_state & EXEC_RESET) { return; }  /* as the original: abort waiting on a reset */
  }
  irq_lock();
  __real_serial_write(data);
  irq_unlock();
}

uint8_t __wrap_orig_serial_read(void) {
  irq_lock();
  uint8_t data = __real_orig_serial_read();
  irq_unlock();
  return data;
}

void __wrap_serial_reset_read_buffer(void) {
  irq_lock();
  __real_serial_reset_read_buffer();
  irq_unlock();
}

void __wrap_interrupt_SERIAL_UDRE(void) {
  irq_lock();
  __real_interrupt_SERIAL_UDRE();
  irq_unlock();
}

void __wrap_interrupt_SERIAL_RX(void) {
  irq_lock();
  __real_interrupt_SERIAL_RX();
  irq_unlock();
}

/* system.c: the real-time flags, written from both threads */
#define WRAP_MASK(name) \
  void __real_##name(uint8_t mask); \
  void __wrap_##name(uint8_t mask) { irq_lock(); __real_##name(mask); irq_unlock(); }
#define WRAP_VOID(name) \
  void __real_##name(void); \
  void __wrap_##name(void) { irq_lock(); __real_##name(); irq_unlock(); }

WRAP_MASK(system_set_exec_state_flag)
WRAP_MASK(system_clear_exec_state_flag)
WRAP_MASK(system_set_exec_alarm)
WRAP_VOID(system_clear_exec_alarm)
WRAP_MASK(system_set_exec_motion_override_flag)
WRAP_MASK(system_set_exec_accessory_override_flag)
WRAP_VOID(system_clear_exec_motion_overrides)
WRAP_VOID(system_clear_exec_accessory_overrides)
