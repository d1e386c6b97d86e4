/* Frame timer: Timer1 generates the camera frame trigger in hardware, counts frames, schedules
 * hardware-timed pulses and timestamps input events (protocol/SPEC.md section 3, "timer terms"). */
#ifndef FT_FRAME_TIMER_H
#define FT_FRAME_TIMER_H

#include <stdint.h>

/* Results of the frame-timer requests; the link layer maps them to ERROR codes. */
enum { FT_TIMER_OK = 0, FT_TIMER_BAD_ARG, FT_TIMER_BUSY };

/* Shortest frame period accepted, in CPU cycles: the interrupts of one frame must fit easily. */
#define FT_MIN_PERIOD_CYCLES 1600u
#define FT_MIN_TOP 15u

/* ATmega328P (INT0): CPU cycles from an edge on the event pin to the TCNT1 read in the INT0 stub,
 * when the CPU is free to take the interrupt at once: the interrupt response (4: PC pushed, I
 * cleared) + the vector's jmp (3) + push r24 (2); lds TCNT1L then samples the counter. (The
 * chip's input synchroniser adds about a cycle more, under a tick at /8: not compensated.)
 * Subtracted from every timestamp (rounded to ticks). Value checked against simavr's cycle
 * counts in tests/firmware (event timestamp error). */
#ifndef FT_EVT_LATENCY_CYCLES
#define FT_EVT_LATENCY_CYCLES 9u
#endif

typedef struct {
    uint8_t channel;
    uint8_t edge; /* 0 falling, 1 rising */
    uint32_t frame_count;
    uint16_t ticks;
} ft_event_t;

void ft_timer_init(void);
/* prescaler_code 1..5 (SPEC), top >= FT_MIN_TOP; only while stopped (else BUSY). */
uint8_t ft_timer_set_rate(uint8_t prescaler_code, uint16_t top);
void ft_timer_get_rate(uint8_t *prescaler_code, uint16_t *top);
void ft_timer_start(void);
void ft_timer_stop(void);
void ft_timer_stop_reset(void);
uint8_t ft_timer_running(void);
/* Frame count (trigger pulses started) and ticks into the frame under way, sampled atomically. */
void ft_timer_clock(uint32_t *frame_count, uint16_t *ticks);
/* Pulse on channel 0 during frame `frame` (0-based frame index, FT_TL_PULSE_NOW = the earliest
 * frame still reachable), high for width_ticks timer ticks from the frame start. */
uint8_t ft_timer_pulse(uint32_t frame, uint16_t width_ticks);
/* Takes the oldest queued input event; returns 0 when there is none. */
uint8_t ft_timer_pop_event(ft_event_t *ev);
/* Input events lost because the queue was full. */
uint16_t ft_timer_events_dropped(void);

#endif /* FT_FRAME_TIMER_H */
