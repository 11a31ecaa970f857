/*
 * swpc-ctrl-emu: SWPC module controllers emulated in C (controller.c), as firmware would
 * run them: on a SocketCAN interface, or on a trace for the host tests.
 *
 *   swpc-ctrl-emu [--nodes 1,2,3,4] [--rate HZ] --can IFACE
 *       One raw CAN socket for every node (kernel filters: Sync and the host commands);
 *       frames are handled as they arrive (the watchdog judges a command by its kernel
 *       receive stamp), heartbeats and feedback go out when due.  Prints "EMULATING" once
 *       bound, runs until SIGTERM/SIGINT, then prints its counts to stderr.  Run it at
 *       real-time priority (chrt -f) to stand for firmware next to a loaded computer.
 *
 *   swpc-ctrl-emu [--nodes 1,2,3,4] [--rate HZ] --trace
 *       Reads events from stdin, one a line: "T step" (advance every controller to T) or
 *       "T ID#HEX" (a frame seen at T, hex id and data as candump -L writes them); writes
 *       every frame sent as "T ID#HEX".  The same as VirtualController.handle / .step in
 *       Python (tests/firmware/test_c_emulator.py compares them).
 *
 * --rate: the feedback rate at power-on (VirtualController's rate_hz, default 200 Hz;
 * SetFeedback changes it).
 *
 * Build: make ctrl-emu (build/swpc-ctrl-emu); deploy/vm/setup.sh builds it for the VM.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <math.h>
#include <net/if.h>
#include <poll.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <time.h>
#include <unistd.h>

#include <linux/can.h>
#include <linux/can/raw.h>

#include "controller.h"
#include "swpc.h"

#define MAX_NODES 8
#define WAIT_MAX 0.05 /* longest wait for a frame (s), as ControllerEmulator */

static struct ctrl ctrls[MAX_NODES];
static int n_ctrls;

static int parse_nodes(const char *text, int rate_hz)
{
    char *copy = strdup(text), *save = NULL;
    n_ctrls = 0;
    for (char *tok = strtok_r(copy, ",", &save); tok; tok = strtok_r(NULL, ",", &save)) {
        int node = atoi(tok);
        if (node < 1 || node > 63 || n_ctrls == MAX_NODES) {
            free(copy);
            return -1;
        }
        ctrl_init(&ctrls[n_ctrls], node);
        ctrls[n_ctrls++].rate_hz = rate_hz;
    }
    free(copy);
    return n_ctrls > 0 ? 0 : -1;
}

/* ------------------------------------------------------------------ trace mode */

static void print_out(const char *t, const struct ctrl_out *out)
{
    for (int i = 0; i < out->n; i++) {
        printf("%s %03X#", t, (unsigned)out->f[i].id);
        for (int j = 0; j < out->f[i].len; j++) {
            printf("%02X", out->f[i].data[j]);
        }
        putchar('\n');
    }
}

static int run_trace(void)
{
    char line[256], t_text[64], ev[128];
    while (fgets(line, sizeof line, stdin)) {
        if (sscanf(line, "%63s %127s", t_text, ev) != 2) {
            continue;
        }
        double t = strtod(t_text, NULL);
        struct ctrl_out out;
        if (strcmp(ev, "step") == 0) {
            for (int i = 0; i < n_ctrls; i++) {
                out.n = 0;
                ctrl_step(&ctrls[i], t, NAN, &out);
                print_out(t_text, &out);
            }
            continue;
        }
        char *hash = strchr(ev, '#');
        if (!hash) {
            fprintf(stderr, "bad event: %s", line);
            return 2;
        }
        struct ctrl_frame f = {0};
        f.id = (uint32_t)strtoul(ev, NULL, 16);
        const char *hex = hash + 1;
        size_t n = strlen(hex) / 2;
        if (n > 8) {
            fprintf(stderr, "bad frame: %s", line);
            return 2;
        }
        for (size_t j = 0; j < n; j++) {
            unsigned byte;
            sscanf(hex + 2 * j, "%2x", &byte);
            f.data[j] = (uint8_t)byte;
        }
        f.len = (uint8_t)n;
        for (int i = 0; i < n_ctrls; i++) {
            out.n = 0;
            ctrl_handle(&ctrls[i], &f, t, NAN, &out);
            print_out(t_text, &out);
        }
    }
    return 0;
}

/* ------------------------------------------------------------------ SocketCAN mode */

static volatile sig_atomic_t stop;
static void on_signal(int sig) { (void)sig; stop = 1; }

static double clock_s(clockid_t id)
{
    struct timespec ts;
    clock_gettime(id, &ts);
    return (double)ts.tv_sec + ts.tv_nsec * 1e-9;
}

static long tx_frames, tx_errors, rx_frames;

static void transmit(int fd, const struct ctrl_out *out)
{
    for (int i = 0; i < out->n; i++) {
        struct can_frame cf;
        memset(&cf, 0, sizeof cf);
        cf.can_id = out->f[i].id;
        cf.can_dlc = out->f[i].len;
        memcpy(cf.data, out->f[i].data, out->f[i].len);
        if (write(fd, &cf, sizeof cf) == (ssize_t)sizeof cf) {
            tx_frames++;
        } else {
            tx_errors++;
        }
    }
}

/* Handle every frame queued on `fd` (non-blocking); returns -1 on a socket error. */
static int drain(int fd)
{
    for (;;) {
        struct can_frame cf;
        char ctl[CMSG_SPACE(sizeof(struct timeval))];
        struct iovec iov = {&cf, sizeof cf};
        struct msghdr msg = {0};
        msg.msg_iov = &iov;
        msg.msg_iovlen = 1;
        msg.msg_control = ctl;
        msg.msg_controllen = sizeof ctl;
        ssize_t got = recvmsg(fd, &msg, MSG_DONTWAIT);
        if (got < 0) {
            return errno == EAGAIN || errno == EWOULDBLOCK || errno == EINTR ? 0 : -1;
        }
        if (got < (ssize_t)sizeof cf || (cf.can_id & (CAN_EFF_FLAG | CAN_RTR_FLAG | CAN_ERR_FLAG))) {
            continue;
        }
        rx_frames++;
        double now = clock_s(CLOCK_MONOTONIC);
        double arrived = NAN;
        for (struct cmsghdr *cm = CMSG_FIRSTHDR(&msg); cm; cm = CMSG_NXTHDR(&msg, cm)) {
            if (cm->cmsg_level == SOL_SOCKET && cm->cmsg_type == SCM_TIMESTAMP) {
                struct timeval tv;
                memcpy(&tv, CMSG_DATA(cm), sizeof tv);
                /* the kernel's receive stamp (wall clock) on the monotonic axis */
                double wall = (double)tv.tv_sec + tv.tv_usec * 1e-6;
                arrived = now - (clock_s(CLOCK_REALTIME) - wall);
                if (arrived > now) {
                    arrived = now;
                }
            }
        }
        struct ctrl_frame f = {0};
        f.id = cf.can_id & CAN_SFF_MASK;
        f.len = cf.can_dlc > 8 ? 8 : cf.can_dlc;
        memcpy(f.data, cf.data, f.len);
        for (int i = 0; i < n_ctrls; i++) {
            struct ctrl_out out = {0};
            ctrl_handle(&ctrls[i], &f, now, arrived, &out);
            transmit(fd, &out);
        }
    }
}

static int run_can(const char *iface)
{
    int fd = socket(PF_CAN, SOCK_RAW, CAN_RAW);
    if (fd < 0) {
        perror("socket(PF_CAN)");
        return 1;
    }
    /* Sync, and the host commands addressed to our nodes (every other frame: not ours) */
    struct can_filter filters[1 + MAX_NODES];
    int nf = 0;
    filters[nf].can_id = 0;
    filters[nf++].can_mask = CAN_SFF_MASK | CAN_EFF_FLAG | CAN_RTR_FLAG;
    for (int i = 0; i < n_ctrls; i++) {
        filters[nf].can_id = (canid_t)ctrls[i].node << 5;
        filters[nf++].can_mask = (CAN_SFF_MASK & ~0x1fu) | CAN_EFF_FLAG | CAN_RTR_FLAG;
    }
    int one = 1;
    int rcvbuf = 1 << 20;
    if (setsockopt(fd, SOL_CAN_RAW, CAN_RAW_FILTER, filters, (socklen_t)(nf * sizeof filters[0])) ||
        setsockopt(fd, SOL_SOCKET, SO_TIMESTAMP, &one, sizeof one)) {
        perror("setsockopt");
        return 1;
    }
    if (setsockopt(fd, SOL_SOCKET, SO_RCVBUFFORCE, &rcvbuf, sizeof rcvbuf)) {
        setsockopt(fd, SOL_SOCKET, SO_RCVBUF, &rcvbuf, sizeof rcvbuf);
    }
    struct ifreq ifr;
    memset(&ifr, 0, sizeof ifr);
    snprintf(ifr.ifr_name, sizeof ifr.ifr_name, "%s", iface);
    if (ioctl(fd, SIOCGIFINDEX, &ifr) < 0) {
        perror(iface);
        return 1;
    }
    struct sockaddr_can addr = {0};
    addr.can_family = AF_CAN;
    addr.can_ifindex = ifr.ifr_ifindex;
    if (bind(fd, (struct sockaddr *)&addr, sizeof addr) < 0) {
        perror("bind");
        return 1;
    }
    struct sigaction sa;
    memset(&sa, 0, sizeof sa);
    sa.sa_handler = on_signal; /* no SA_RESTART: poll() returns on a signal */
    sigaction(SIGTERM, &sa, NULL);
    sigaction(SIGINT, &sa, NULL);
    printf("EMULATING %s nodes %d\n", iface, n_ctrls);
    fflush(stdout);

    int status = 0;
    while (!stop) {
        /* frames that arrived while this process was not running come first (a command
         * that arrived in time fed the watchdog); the watchdog is then judged at
         * `horizon`, before which every arrived frame has been handled */
        double horizon = clock_s(CLOCK_MONOTONIC);
        if (drain(fd) < 0) {
            perror("recvmsg");
            status = 1;
            break;
        }
        double now = clock_s(CLOCK_MONOTONIC), due = INFINITY;
        for (int i = 0; i < n_ctrls; i++) {
            struct ctrl_out out = {0};
            ctrl_step(&ctrls[i], now, horizon, &out);
            transmit(fd, &out);
            double d = ctrl_next_due(&ctrls[i]);
            due = d < due ? d : due;
        }
        double wait = due - clock_s(CLOCK_MONOTONIC);
        wait = wait < 0 ? 0 : (wait > WAIT_MAX ? WAIT_MAX : wait);
        struct pollfd p = {fd, POLLIN, 0};
        struct timespec ts = {(time_t)wait, (long)((wait - (time_t)wait) * 1e9)};
        if (ppoll(&p, 1, &ts, NULL) < 0 && errno != EINTR) {
            perror("ppoll");
            status = 1;
            break;
        }
    }
    long commands = 0, invalid = 0, watchdog = 0;
    for (int i = 0; i < n_ctrls; i++) {
        commands += ctrls[i].commands;
        invalid += ctrls[i].invalid_frames;
        watchdog += ctrls[i].watchdog_faults;
    }
    fprintf(stderr,
            "swpc-ctrl-emu: rx %ld, commands %ld, invalid %ld, tx %ld, tx errors %ld, "
            "watchdog faults %ld\n",
            rx_frames, commands, invalid, tx_frames, tx_errors, watchdog);
    close(fd);
    return status;
}

int main(int argc, char **argv)
{
    const char *nodes = "1,2,3,4", *iface = NULL;
    int trace = 0, rate_hz = 1000 / SWPC_N1_FEEDBACK_POSITION_CYCLE_TIME_MS;
    for (int i = 1; i < argc; i++) {
        if (strcmp(argv[i], "--nodes") == 0 && i + 1 < argc) {
            nodes = argv[++i];
        } else if (strcmp(argv[i], "--rate") == 0 && i + 1 < argc) {
            char *end;
            long r = strtol(argv[++i], &end, 10);
            if (*end || r < 0 || r > 500) {
                fprintf(stderr, "--rate: 0..500 Hz\n");
                return 2;
            }
            rate_hz = (int)r;
        } else if (strcmp(argv[i], "--can") == 0 && i + 1 < argc) {
            iface = argv[++i];
        } else if (strcmp(argv[i], "--trace") == 0) {
            trace = 1;
        } else {
            fprintf(stderr, "usage: %s [--nodes 1,2,3,4] [--rate HZ] (--can IFACE | --trace)\n",
                    argv[0]);
            return 2;
        }
    }
    if (parse_nodes(nodes, rate_hz) != 0) {
        fprintf(stderr, "--nodes: 1 to %d node ids in 1..63, comma-separated\n", MAX_NODES);
        return 2;
    }
    if (trace) {
        return run_trace();
    }
    if (!iface) {
        fprintf(stderr, "one of --can IFACE or --trace is needed\n");
        return 2;
    }
    return run_can(iface);
}
