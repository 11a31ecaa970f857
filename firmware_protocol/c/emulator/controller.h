/*
 * The SWPC controller's state machine in C, transport-free: the same semantics as
 * simulators/drives/swpc.py (VirtualController), on the pack/unpack code generated
 * from firmware_protocol/swpc.dbc (../swpc.h).  Feed it host frames with ctrl_handle()
 * and advance time with ctrl_step(); both append the frames the controller sends to an
 * output list.  Times are seconds on any monotonic axis (doubles, as in Python).
 *
 * tests/firmware/test_c_emulator.py runs the same frame sequences through this code (the
 * `--trace` mode of main.c) and through VirtualController and compares every frame.
 */
#ifndef SWPC_CTRL_H
#define SWPC_CTRL_H

#include <stdbool.h>
#include <stdint.h>

enum { AXIS_STEER = 0, AXIS_WHEEL = 1 };
enum { ST_DISABLED = 0, ST_ENABLED = 1, ST_HOMING = 2, ST_FAULT = 3 };
enum { MODE_FREE = 0, MODE_HOLD = 1, MODE_POSITION = 2, MODE_VELOCITY = 3, MODE_TORQUE = 4 };
enum { HOMING_NOT_HOMED = 0, HOMING_IN_PROGRESS = 1, HOMING_DONE = 2, HOMING_FAILED = 3 };
enum {
    ERR_WATCHDOG_TIMEOUT = 1 << 0,
    ERR_OVER_SPEED = 1 << 1,
    ERR_NOT_HOMED = 1 << 4,
};

struct ctrl_frame {
    uint32_t id;
    uint8_t len;
    uint8_t data[8];
};

/* Frames sent by one call (a handle or a step sends at most a few). */
#define CTRL_OUT_MAX 16
struct ctrl_out {
    int n;
    struct ctrl_frame f[CTRL_OUT_MAX];
};

struct ctrl_axis {
    int state;
    int mode;
    double setpoint;
    uint16_t errors;
    double position;
    double velocity;
    double torque;
    double max_torque;
    double max_velocity;
    double inertia;
    double friction;
    double hold_target;
};

struct ctrl {
    int node;
    int rate_hz;
    int watchdog_ms;
    double heartbeat_period;
    double homing_duration;
    double sensor_position;
    bool sync_mode;
    struct ctrl_axis axes[2];
    bool homed;
    long invalid_frames;
    long commands;
    long watchdog_faults;
    bool started; /* Python's _t is not None */
    double t;
    double last_command;
    double next_feedback;
    double next_heartbeat;
    double homing_end;
    uint8_t sample_counter;
    uint8_t hb_counter;
};

/* VirtualController's defaults (DEFAULT_RATE_HZ, DEFAULT_WATCHDOG_MS, ...). */
void ctrl_init(struct ctrl *c, int node);

/* A frame seen on the bus at `now` (arrived at `arrived` <= now, or NAN: at now). */
void ctrl_handle(struct ctrl *c, const struct ctrl_frame *f, double now, double arrived,
                 struct ctrl_out *out);

/* Advance to `now` (the watchdog judged at min(now, watchdog_at); NAN: at now). */
void ctrl_step(struct ctrl *c, double now, double watchdog_at, struct ctrl_out *out);

/* Time of the next frame this controller sends by itself. */
double ctrl_next_due(const struct ctrl *c);

#endif
