#!/usr/bin/env bash
# deploy/README.md's robot set-up, step by step, on a machine that runs systemd: the
# container that deploy/vm/robot-install.sh boots in the test VM.  Runs as a oneshot
# unit there, as root; /opt/swpc is the checkout (make install already done: its venv).
#
#   robot-install-test.sh OUT
#
# The robot's bus is can0, an SJA1000 that QEMU emulates; the caster controllers are
# `swpc sim` on can1, on the same emulated bus, installed from the lab unit
# (swpc-sim.service) with a drop-in for can1.  Each check prints PASS/FAIL; the number of
# failures goes to /run/swpc-robot-install.status, and the container's systemd exits
# with it (see robot-install.sh).
set -uo pipefail

OUT="${1:?usage: robot-install-test.sh OUT}"
cd /opt/swpc
PY=/opt/swpc/.venv/bin/python
TS="${SWPC_VM_SIM_TIME_SCALE:-0.3}"
TOKEN=vm-robot-token-0123456789
URL=http://127.0.0.1:8080
failures=0
now() { date +%s.%N; }
since() { awk -v a="$1" -v b="$(now)" 'BEGIN {printf "%.1f", b - a}'; }
T0=$(now)
check() { # check NAME CMD...: PASS on status 0
    local name=$1 t0; shift; t0=$(now)
    echo "-- $name: $*"
    if "$@"; then
        printf '== robot-install %-20s PASS (%s s)\n' "$name" "$(since "$t0")"
    else
        printf '== robot-install %-20s FAIL (status %s, %s s)\n' "$name" "$?" "$(since "$t0")"
        failures=$((failures + 1))
        return 1
    fi
}
diagnose() { # the units' status and journal, then stop: the later steps need these
    systemctl --no-pager status swpc-sim.service swpc-service.service
    journalctl --no-pager -n 40 -u swpc-sim.service -u swpc-service.service
    exit
}
finish() {
    echo "== robot-install: $failures failure(s) in $(since "$T0") s"
    echo "$failures" > /run/swpc-robot-install.status
}
trap finish EXIT

echo "== robot-install: systemd $(systemctl --version | head -n1 | cut -d' ' -f2) as PID 1" \
    "($(cat /proc/1/comm)), state $(systemctl is-system-running)"

# --- 2. user, config and data dir (deploy/README.md, "Robot set-up") ----------------------
sysusers() {
    install -D -m 0644 deploy/systemd/swpc.sysusers.conf /etc/sysusers.d/swpc.conf &&
        systemd-sysusers && getent passwd swpc && getent group swpc
}
check sysusers sysusers || exit

config() {
    install -d -m 0750 -o root -g swpc /etc/swpc &&
        install -m 0640 -o root -g swpc deploy/swpc.env.example /etc/swpc/swpc.env &&
        install -m 0640 -o root -g swpc deploy/robot.example.yaml /etc/swpc/robot.yaml &&
        install -m 0640 -o root -g swpc deploy/zenoh/robot-peer.json5 /etc/swpc/zenoh.json5 ||
        return 1
    # this robot's zenoh password, known to the mocap PC (here the lab simulator)
    local password; password=$(head -c 18 /dev/urandom | base64 | tr '+/' '-_')
    sed -i -e "s|replace-with-this-robot's-password|$password|" /etc/swpc/zenoh.json5 &&
        install -d -m 0755 /etc/zenoh &&
        install -m 0640 -o root -g swpc /dev/null /etc/zenoh/robots.txt &&
        echo "swpc-robot07:$password" > /etc/zenoh/robots.txt &&
        grep -q "password: \"$password\"" /etc/swpc/zenoh.json5 || return 1
    # the edits the README asks for: token, bus, mocap endpoint (the simulator on this
    # machine, wall-clock stamps); the emulation's timing (a slow machine); and its disk:
    # the container's /var has ~500 MB free, less than the defaults ask of a run (a
    # 256 MiB reserve above SWPC_MIN_FREE 256 MiB: refused with 507 otherwise)
    local window; window=$(awk -v s="$TS" 'BEGIN {printf "%.2f", 1.5 / s}')
    sed -i -e "s|^SWPC_TOKEN=.*|SWPC_TOKEN=$TOKEN|" \
        -e 's|^SWPC_CAN_BITRATE=.*|SWPC_CAN_BITRATE=500000|' \
        -e "s|^#SWPC_ZENOH_CONNECT=.*|SWPC_ZENOH_CONNECT='[\"tcp/127.0.0.1:7447\"]'|" \
        -e 's|^#SWPC_MOCAP_CLOCK=.*|SWPC_MOCAP_CLOCK=wall|' \
        -e "s|^#SWPC_HEARTBEAT_TIMEOUT=.*|SWPC_HEARTBEAT_TIMEOUT=$window|" \
        -e "s|^#SWPC_MOCAP_STALE_AFTER=.*|SWPC_MOCAP_STALE_AFTER=$window|" \
        -e 's|^#SWPC_FEEDBACK_RATE=.*|SWPC_FEEDBACK_RATE=50|' \
        -e 's|^#SWPC_DISK_BUDGET=.*|SWPC_DISK_BUDGET=512MiB|' \
        -e 's|^#SWPC_MIN_FREE=.*|SWPC_MIN_FREE=64MiB|' \
        /etc/swpc/swpc.env &&
        grep -q "^SWPC_TOKEN=$TOKEN" /etc/swpc/swpc.env &&
        grep -q '^SWPC_ZENOH_CONNECT=' /etc/swpc/swpc.env &&
        grep -q '^SWPC_MIN_FREE=64MiB' /etc/swpc/swpc.env || return 1
    # "Check the robot config loads", as the swpc user that will read it
    setpriv --reuid=swpc --regid=swpc --init-groups env "LD_LIBRARY_PATH=${LD_LIBRARY_PATH:-}" "$PY" -c \
        'from services.config.robot import load_robot_config as l; print(l("/etc/swpc/robot.yaml").robot)'
}
check config config || exit

# --- 3. the CAN interface and the receive buffer --------------------------------------------
can_and_sysctl() {
    deploy/can-up.sh can0 --bitrate 500000 --restart-ms 100 &&
        ip -details link show can0 | grep -q 'restart-ms 100' &&
        install -D -m 0644 deploy/sysctl/60-swpc-can.conf /etc/sysctl.d/60-swpc-can.conf &&
        sysctl -p /etc/sysctl.d/60-swpc-can.conf &&
        (($(sysctl -n net.core.rmem_max) >= 1048576))
}
check can-and-sysctl can_and_sysctl

# --- the controllers: swpc-sim.service (lab unit) on can1 ------------------------------------
sim_unit() {
    install -m 0644 deploy/systemd/swpc-sim.service /etc/systemd/system/ &&
        mkdir -p /etc/systemd/system/swpc-sim.service.d &&
        cat > /etc/systemd/system/swpc-sim.service.d/can1.conf <<EOF || return 1
[Service]
ExecStartPre=
ExecStartPre=+/opt/swpc/deploy/can-up.sh can1 --bitrate 500000 --restart-ms 100
ExecStart=
ExecStart=/opt/swpc/.venv/bin/swpc sim --interface socketcan --channel can1 --zenoh-listen tcp/127.0.0.1:7447 --zenoh-config /opt/swpc/deploy/zenoh/mocap-peer.json5 --time-scale $TS --physics-dt 5 --feedback-rate 50 --stats-every 60
EOF
    ip link set dev lo up &&
        systemctl daemon-reload && systemctl start swpc-sim.service &&
        systemctl is-active swpc-sim.service
}
check sim-unit sim_unit || diagnose

# --- 4. the service ---------------------------------------------------------------------------
service_unit() {
    install -m 0644 deploy/systemd/swpc-service.service /etc/systemd/system/ &&
        systemctl daemon-reload && systemctl enable --now swpc-service.service &&
        [[ $(systemctl is-enabled swpc-service.service) == enabled ]] &&
        systemctl is-active swpc-service.service
}
check service-unit service_unit || diagnose
check health "$PY" deploy/vm/sim_calibration.py health --url "$URL" --timeout 400 || diagnose

sandbox() {
    local pid user
    pid=$(systemctl show -p MainPID --value swpc-service.service)
    user=$(ps -o user= -p "$pid")
    echo "main pid $pid runs as $user"
    [[ $user == swpc ]] || return 1
    stat -c '%U:%G %a %n' /var/lib/swpc /var/lib/swpc/* &&
        [[ $(stat -c '%U %a' /var/lib/swpc) == "swpc 750" ]] || return 1
    # ProtectSystem=strict: the service sees /etc and /opt read-only
    [[ $(nsenter -t "$pid" -m sh -c 'touch /etc/swpc/x 2>&1 || echo denied') == *denied* ]] \
        || return 1
    systemd-analyze security --no-pager swpc-service.service | tail -n 1
}
check sandbox sandbox

# a run moves the robot (the simulator on can1) through the installed service, then an
# abort stops it (in its first spin: no fast part before it, which sim-calibration runs)
check run-and-abort "$PY" deploy/vm/sim_calibration.py run --url "$URL" --token "$TOKEN" \
    --overrides '{"protocol": {"sweep_deg": 45, "precheck": false}}' --out "$OUT/robot-install-run.json" \
    --health-timeout 60 --timeout 900 --abort-in SPIN

# Restart=on-failure: a killed service comes back by itself
restart() {
    local n0 n1
    n0=$(systemctl show -p NRestarts --value swpc-service.service)
    systemctl kill -s SIGKILL swpc-service.service
    for _ in $(seq 120); do
        sleep 1
        n1=$(systemctl show -p NRestarts --value swpc-service.service)
        [[ $n1 -gt $n0 ]] && systemctl is-active -q swpc-service.service && break
    done
    echo "NRestarts $n0 -> $n1"
    [[ $n1 -gt $n0 ]] && "$PY" deploy/vm/sim_calibration.py health --url "$URL" --timeout 400
}
check restart-on-failure restart

stop() {
    systemctl stop swpc-service.service swpc-sim.service &&
        ! systemctl is-active -q swpc-service.service &&
        journalctl -u swpc-service.service --no-pager | tail -n 5
}
check stop stop
journalctl -u swpc-service.service --no-pager > "$OUT/robot-install-journal.txt" 2>&1
