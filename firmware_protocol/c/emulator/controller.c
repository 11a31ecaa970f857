/*
 * The SWPC controller's state machine (see controller.h): a line-by-line port of
 * simulators/drives/swpc.py's VirtualController (handle, _apply, step, _advance,
 * _integrate, heartbeat, _feedback, _fault), without its test hooks (muted, lose).
 */
#define _DEFAULT_SOURCE
#include "controller.h"

#include <math.h>
#include <string.h>

#include "swpc.h"

#define NODE_SHIFT 5
#define CMD_MASK 0x1fu
#define SYNC_ID 0x000u
#define OVER_SPEED_FACTOR 1.2
/* Steering position wrap period (codec.STEER_SPAN): 2**20 counts of 2 pi / 2**17 rad. */
#define STEER_SPAN (1048576.0 * 4.7936899621426287e-05)

enum {
    CMD_SET_AXIS_STATE = 0x01,
    CMD_SET_CONTROL = 0x02,
    CMD_FAULT_REPORT = 0x03,
    CMD_FEEDBACK_POSITION = 0x04,
    CMD_FEEDBACK_VELOCITY_TORQUE = 0x05,
    CMD_HEARTBEAT = 0x06,
    CMD_CLEAR_ERRORS = 0x07,
    CMD_SET_LIMITS = 0x08,
    CMD_SET_WATCHDOG = 0x09,
    CMD_SET_FEEDBACK = 0x0a,
    CMD_START_HOMING = 0x0b,
    CMD_HOMING_STATUS = 0x0c,
};

static double clamp(double x, double limit)
{
    /* Python: max(-limit, min(limit, x)) */
    double m = x < limit ? x : limit;
    return m > -limit ? m : -limit;
}

static void emit(struct ctrl_out *out, const struct ctrl *c, unsigned cmd, const uint8_t *data,
                 int len)
{
    if (len < 0 || out->n >= CTRL_OUT_MAX) {
        return; /* cannot happen: every pack below fits its buffer */
    }
    struct ctrl_frame *f = &out->f[out->n++];
    f->id = ((uint32_t)c->node << NODE_SHIFT) | cmd;
    f->len = (uint8_t)len;
    memcpy(f->data, data, (size_t)len);
}

void ctrl_init(struct ctrl *c, int node)
{
    memset(c, 0, sizeof *c);
    c->node = node;
    c->rate_hz = 1000 / SWPC_N1_FEEDBACK_POSITION_CYCLE_TIME_MS;
    c->watchdog_ms = 100; /* codec.POWER_UP_WATCHDOG_MS */
    c->heartbeat_period = SWPC_N1_HEARTBEAT_CYCLE_TIME_MS / 1000.0;
    c->homing_duration = 0.2;
    c->sensor_position = 0.3;
    for (int i = 0; i < 2; i++) {
        struct ctrl_axis *ax = &c->axes[i];
        ax->state = ST_DISABLED;
        ax->mode = MODE_FREE;
        ax->max_torque = 5.0;
        ax->max_velocity = 40.0;
        ax->inertia = 0.01;
        ax->friction = 0.02;
    }
}

/* ------------------------------------------------------------------ outputs */

static void fault(struct ctrl *c, int axis, uint16_t error, struct ctrl_out *out)
{
    struct ctrl_axis *ax = &c->axes[axis];
    uint16_t fresh = (uint16_t)(error & ~ax->errors);
    ax->errors |= error;
    ax->state = ST_FAULT;
    ax->mode = MODE_FREE;
    ax->setpoint = 0.0;
    ax->torque = 0.0;
    if (error & ERR_WATCHDOG_TIMEOUT) {
        c->watchdog_faults++;
    }
    struct swpc_n1_fault_report_t m = {(uint8_t)axis, fresh, ax->errors, ST_FAULT};
    uint8_t buf[8];
    emit(out, c, CMD_FAULT_REPORT, buf, swpc_n1_fault_report_pack(buf, &m, sizeof buf));
}

static void heartbeat(struct ctrl *c, struct ctrl_out *out)
{
    const struct ctrl_axis *s = &c->axes[AXIS_STEER], *w = &c->axes[AXIS_WHEEL];
    struct swpc_n1_heartbeat_t m = {
        .steer_state = (uint8_t)s->state,
        .steer_mode = (uint8_t)s->mode,
        .wheel_state = (uint8_t)w->state,
        .wheel_mode = (uint8_t)w->mode,
        .steer_errors = s->errors,
        .wheel_errors = w->errors,
        .homed = c->homed,
        .sync_mode = c->sync_mode,
        .counter = c->hb_counter,
    };
    c->hb_counter = (uint8_t)(c->hb_counter + 1);
    uint8_t buf[8];
    emit(out, c, CMD_HEARTBEAT, buf, swpc_n1_heartbeat_pack(buf, &m, sizeof buf));
}

static void feedback(struct ctrl *c, uint8_t counter, struct ctrl_out *out)
{
    const struct ctrl_axis *s = &c->axes[AXIS_STEER], *w = &c->axes[AXIS_WHEEL];
    uint8_t buf[8];
    /* the 20- and 36-bit position signals wrap as the controller's counters do */
    struct swpc_n1_feedback_position_t p = {
        swpc_n1_feedback_position_steer_position_encode(s->position),
        swpc_n1_feedback_position_wheel_position_encode(w->position),
        counter,
    };
    emit(out, c, CMD_FEEDBACK_POSITION, buf, swpc_n1_feedback_position_pack(buf, &p, sizeof buf));
    struct swpc_n1_feedback_velocity_torque_t v = {
        swpc_n1_feedback_velocity_torque_steer_velocity_encode(clamp(s->velocity, 32.767)),
        swpc_n1_feedback_velocity_torque_wheel_velocity_encode(clamp(w->velocity, 65.534)),
        swpc_n1_feedback_velocity_torque_steer_torque_encode(clamp(s->torque, 20.47)),
        swpc_n1_feedback_velocity_torque_wheel_torque_encode(clamp(w->torque, 20.47)),
        counter,
    };
    emit(out, c, CMD_FEEDBACK_VELOCITY_TORQUE, buf,
         swpc_n1_feedback_velocity_torque_pack(buf, &v, sizeof buf));
}

static void homing_status(struct ctrl *c, int axis, int status, double sensor,
                          struct ctrl_out *out)
{
    struct swpc_n1_homing_status_t m = {
        (uint8_t)axis, (uint8_t)status, swpc_n1_homing_status_sensor_position_encode(sensor)};
    uint8_t buf[8];
    emit(out, c, CMD_HOMING_STATUS, buf, swpc_n1_homing_status_pack(buf, &m, sizeof buf));
}

/* ------------------------------------------------------------------ time */

static void integrate(struct ctrl_axis *ax, double dt)
{
    if (dt <= 0.0) {
        return;
    }
    bool powered = ax->state == ST_ENABLED || ax->state == ST_HOMING;
    int mode = ax->state == ST_ENABLED ? ax->mode : MODE_FREE;
    double v;
    if (ax->state == ST_HOMING) {
        v = 0.5; /* homing search speed, rad/s */
        ax->torque = ax->friction * v;
    } else if (!powered || mode == MODE_FREE) {
        v = ax->velocity * exp(-dt * ax->friction / ax->inertia);
        ax->torque = 0.0;
    } else if (mode == MODE_HOLD) {
        v = 0.0;
        ax->position = ax->hold_target;
        ax->torque = 0.0;
    } else if (mode == MODE_VELOCITY) {
        v = ax->setpoint;
        ax->torque = clamp(ax->friction * v, ax->max_torque);
    } else if (mode == MODE_POSITION) {
        v = clamp((ax->setpoint - ax->position) / (dt > 0.02 ? dt : 0.02), ax->max_velocity);
        ax->torque = clamp(ax->friction * v, ax->max_torque);
    } else { /* TORQUE */
        double tau = clamp(ax->setpoint, ax->max_torque);
        double decay = exp(-dt * ax->friction / ax->inertia);
        double v_inf = tau / ax->friction;
        v = v_inf + (ax->velocity - v_inf) * decay;
        ax->torque = tau;
    }
    /* the position loop moves by its own velocity alone: averaged with the velocity of the
     * step before (the trapezoid), it overshot its set-point whenever a step was longer
     * than the one before, and under uneven steps (a loaded host) never settled */
    if (mode == MODE_POSITION) {
        ax->position += v * dt;
    } else {
        ax->position += 0.5 * (ax->velocity + v) * dt;
    }
    ax->velocity = v;
}

/* Integrate to `now`, then the over-speed, homing and watchdog checks (VirtualController
 * ._advance; `watchdog_at` NAN is Python's None). */
static void advance(struct ctrl *c, double now, bool on_frame, double watchdog_at,
                    struct ctrl_out *out)
{
    if (!c->started) {
        c->started = true;
        c->t = now;
        c->last_command = now;
        c->next_feedback = now;
        c->next_heartbeat = now;
    }
    double dt = now - c->t > 0.0 ? now - c->t : 0.0;
    c->t = now;
    for (int axis = 0; axis < 2; axis++) {
        struct ctrl_axis *ax = &c->axes[axis];
        integrate(ax, dt);
        if ((dt > 0.0 || !on_frame) && ax->state == ST_ENABLED && ax->mode != MODE_FREE &&
            fabs(ax->velocity) > OVER_SPEED_FACTOR * ax->max_velocity) {
            fault(c, axis, ERR_OVER_SPEED, out);
        }
    }
    struct ctrl_axis *steer = &c->axes[AXIS_STEER];
    if (steer->state == ST_HOMING && now >= c->homing_end) {
        steer->position -= c->sensor_position;
        c->homed = true;
        steer->state = ST_ENABLED;
        steer->mode = MODE_HOLD;
        steer->hold_target = steer->position;
        steer->setpoint = 0.0;
        homing_status(c, AXIS_STEER, HOMING_DONE, c->sensor_position, out);
    }
    double at = isnan(watchdog_at) ? now : (now < watchdog_at ? now : watchdog_at);
    if (c->watchdog_ms > 0 && at - c->last_command > c->watchdog_ms / 1000.0) {
        for (int axis = 0; axis < 2; axis++) {
            int st = c->axes[axis].state;
            if (st == ST_ENABLED || st == ST_HOMING) {
                fault(c, axis, ERR_WATCHDOG_TIMEOUT, out);
            }
        }
    }
}

void ctrl_step(struct ctrl *c, double now, double watchdog_at, struct ctrl_out *out)
{
    advance(c, now, false, watchdog_at, out);
    if (now >= c->next_heartbeat) {
        double next = c->next_heartbeat + c->heartbeat_period;
        c->next_heartbeat = next > now ? next : now;
        heartbeat(c, out);
    }
    if (c->rate_hz > 0 && !c->sync_mode && now >= c->next_feedback) {
        double period = 1.0 / c->rate_hz;
        double next = c->next_feedback + period, floor = now - 2 * period;
        /* catch up without bursting if the caller was late by more than 2 periods */
        c->next_feedback = next > floor ? next : floor;
        feedback(c, c->sample_counter, out);
        c->sample_counter = (uint8_t)(c->sample_counter + 1);
    }
}

double ctrl_next_due(const struct ctrl *c)
{
    double due = c->next_heartbeat;
    if (c->rate_hz > 0 && !c->sync_mode && c->next_feedback < due) {
        due = c->next_feedback;
    }
    bool homing = false, powered = false;
    for (int i = 0; i < 2; i++) {
        homing = homing || c->axes[i].state == ST_HOMING;
        powered = powered || c->axes[i].state == ST_ENABLED || c->axes[i].state == ST_HOMING;
    }
    if (homing && c->homing_end < due) {
        due = c->homing_end;
    }
    if (c->watchdog_ms > 0 && powered) {
        double wd = c->last_command + c->watchdog_ms / 1000.0;
        if (wd < due) {
            due = wd;
        }
    }
    return due;
}

/* ------------------------------------------------------------------ host frames */

/* A host command, decoded and checked as codec.parse does (DLC as in the DBC, every
 * signal present within its DBC range); false: invalid. */
union command {
    struct swpc_n1_set_axis_state_t axis_state;
    struct swpc_n1_set_control_t control;
    struct swpc_n1_clear_errors_t clear;
    struct swpc_n1_set_limits_t limits;
    struct swpc_n1_set_watchdog_t watchdog;
    struct swpc_n1_set_feedback_t fb;
    struct swpc_n1_start_homing_t homing;
};

static bool parse(unsigned cmd, const struct ctrl_frame *f, union command *m)
{
    switch (cmd) {
    case CMD_SET_AXIS_STATE:
        return f->len == SWPC_N1_SET_AXIS_STATE_LENGTH &&
               swpc_n1_set_axis_state_unpack(&m->axis_state, f->data, f->len) == 0 &&
               swpc_n1_set_axis_state_axis_is_in_range(m->axis_state.axis) &&
               swpc_n1_set_axis_state_requested_state_is_in_range(m->axis_state.requested_state);
    case CMD_SET_CONTROL:
        if (f->len != SWPC_N1_SET_CONTROL_LENGTH ||
            swpc_n1_set_control_unpack(&m->control, f->data, f->len) != 0 ||
            !swpc_n1_set_control_axis_is_in_range(m->control.axis) ||
            !swpc_n1_set_control_mode_is_in_range(m->control.mode)) {
            return false;
        }
        switch (m->control.mode) {
        case MODE_POSITION:
            return swpc_n1_set_control_position_setpoint_is_in_range(
                m->control.position_setpoint);
        case MODE_VELOCITY:
            return swpc_n1_set_control_velocity_setpoint_is_in_range(
                m->control.velocity_setpoint);
        case MODE_TORQUE:
            return swpc_n1_set_control_torque_setpoint_is_in_range(m->control.torque_setpoint);
        default:
            return true;
        }
    case CMD_CLEAR_ERRORS:
        return f->len == SWPC_N1_CLEAR_ERRORS_LENGTH &&
               swpc_n1_clear_errors_unpack(&m->clear, f->data, f->len) == 0 &&
               swpc_n1_clear_errors_axis_mask_is_in_range(m->clear.axis_mask);
    case CMD_SET_LIMITS:
        return f->len == SWPC_N1_SET_LIMITS_LENGTH &&
               swpc_n1_set_limits_unpack(&m->limits, f->data, f->len) == 0 &&
               swpc_n1_set_limits_axis_is_in_range(m->limits.axis) &&
               swpc_n1_set_limits_max_torque_is_in_range(m->limits.max_torque) &&
               swpc_n1_set_limits_max_velocity_is_in_range(m->limits.max_velocity);
    case CMD_SET_WATCHDOG:
        return f->len == SWPC_N1_SET_WATCHDOG_LENGTH &&
               swpc_n1_set_watchdog_unpack(&m->watchdog, f->data, f->len) == 0 &&
               swpc_n1_set_watchdog_timeout_ms_is_in_range(m->watchdog.timeout_ms);
    case CMD_SET_FEEDBACK:
        return f->len == SWPC_N1_SET_FEEDBACK_LENGTH &&
               swpc_n1_set_feedback_unpack(&m->fb, f->data, f->len) == 0 &&
               swpc_n1_set_feedback_rate_hz_is_in_range(m->fb.rate_hz) &&
               swpc_n1_set_feedback_sync_mode_is_in_range(m->fb.sync_mode);
    case CMD_START_HOMING:
        return f->len == SWPC_N1_START_HOMING_LENGTH &&
               swpc_n1_start_homing_unpack(&m->homing, f->data, f->len) == 0 &&
               swpc_n1_start_homing_axis_is_in_range(m->homing.axis);
    default:
        return false;
    }
}

static void apply(struct ctrl *c, unsigned cmd, const union command *m, double now,
                  struct ctrl_out *out)
{
    switch (cmd) {
    case CMD_SET_AXIS_STATE: {
        struct ctrl_axis *ax = &c->axes[m->axis_state.axis];
        bool enable = m->axis_state.requested_state == 1;
        if (enable && ax->state == ST_DISABLED && ax->errors == 0) {
            ax->state = ST_ENABLED;
            ax->mode = MODE_FREE;
            ax->setpoint = 0.0;
        } else if (!enable && (ax->state == ST_ENABLED || ax->state == ST_HOMING)) {
            ax->state = ST_DISABLED;
            ax->mode = MODE_FREE;
            ax->setpoint = 0.0;
        }
        break;
    }
    case CMD_SET_CONTROL: {
        const struct swpc_n1_set_control_t *sc = &m->control;
        struct ctrl_axis *ax = &c->axes[sc->axis];
        if (ax->state != ST_ENABLED) {
            break;
        }
        if (sc->mode == MODE_POSITION && sc->axis == AXIS_STEER && !c->homed) {
            fault(c, sc->axis, ERR_NOT_HOMED, out);
            break;
        }
        int prev_mode = ax->mode;
        ax->mode = sc->mode;
        if (sc->mode == MODE_VELOCITY) {
            ax->setpoint = clamp(
                swpc_n1_set_control_velocity_setpoint_decode(sc->velocity_setpoint),
                ax->max_velocity);
        } else if (sc->mode == MODE_TORQUE) {
            ax->setpoint = clamp(swpc_n1_set_control_torque_setpoint_decode(sc->torque_setpoint),
                                 ax->max_torque);
        } else if (sc->mode == MODE_POSITION && sc->axis == AXIS_STEER) {
            /* modulo the feedback's wrap (8 turns), nearest the position */
            double sp = swpc_n1_set_control_position_setpoint_decode(sc->position_setpoint);
            ax->setpoint = ax->position + remainder(sp - ax->position, STEER_SPAN);
        } else if (sc->mode == MODE_POSITION) {
            ax->setpoint = swpc_n1_set_control_position_setpoint_decode(sc->position_setpoint);
        } else if (sc->mode == MODE_HOLD) {
            if (prev_mode != MODE_HOLD) {
                ax->hold_target = ax->position;
            }
            ax->setpoint = 0.0;
        } else {
            ax->setpoint = 0.0;
        }
        break;
    }
    case CMD_CLEAR_ERRORS:
        for (int axis = 0; axis < 2; axis++) {
            if (m->clear.axis_mask & (1u << axis)) {
                struct ctrl_axis *ax = &c->axes[axis];
                ax->errors = 0;
                if (ax->state == ST_FAULT) {
                    ax->state = ST_DISABLED;
                }
            }
        }
        break;
    case CMD_SET_LIMITS: {
        struct ctrl_axis *ax = &c->axes[m->limits.axis];
        ax->max_torque = swpc_n1_set_limits_max_torque_decode(m->limits.max_torque);
        ax->max_velocity = swpc_n1_set_limits_max_velocity_decode(m->limits.max_velocity);
        break;
    }
    case CMD_SET_WATCHDOG:
        c->watchdog_ms = m->watchdog.timeout_ms;
        break;
    case CMD_SET_FEEDBACK:
        c->rate_hz = m->fb.rate_hz;
        c->sync_mode = m->fb.sync_mode != 0;
        c->next_feedback = now;
        break;
    case CMD_START_HOMING: {
        int axis = m->homing.axis;
        struct ctrl_axis *ax = &c->axes[axis];
        if (axis != AXIS_STEER || ax->state != ST_ENABLED) {
            homing_status(c, axis, HOMING_FAILED, 0.0, out);
        } else {
            ax->state = ST_HOMING;
            ax->mode = MODE_FREE;
            c->homing_end = now + c->homing_duration;
            homing_status(c, axis, HOMING_IN_PROGRESS, 0.0, out);
        }
        break;
    }
    default:
        break;
    }
}

void ctrl_handle(struct ctrl *c, const struct ctrl_frame *f, double now, double arrived,
                 struct ctrl_out *out)
{
    unsigned node = f->id >> NODE_SHIFT, cmd = f->id & CMD_MASK;
    if (f->id == SYNC_ID) {
        struct swpc_sync_t s;
        if (f->len != SWPC_SYNC_LENGTH || swpc_sync_unpack(&s, f->data, f->len) != 0) {
            c->invalid_frames++;
            return;
        }
        if (c->sync_mode) {
            /* what the time up to now brought first (homing done, a fault), then the sample */
            advance(c, now, true, NAN, out);
            feedback(c, s.sync_counter, out);
        }
        return;
    }
    bool host_command = cmd == CMD_SET_AXIS_STATE || cmd == CMD_SET_CONTROL ||
                        (cmd >= CMD_CLEAR_ERRORS && cmd <= CMD_START_HOMING);
    if (node != (unsigned)c->node || !host_command) {
        return;
    }
    union command m;
    memset(&m, 0, sizeof m);
    if (!parse(cmd, f, &m)) {
        c->invalid_frames++;
        return;
    }
    /* the frames the time up to now brought go out before the command's own answer */
    advance(c, now, true, arrived, out);
    c->last_command = now;
    c->commands++;
    apply(c, cmd, &m, now, out);
}
