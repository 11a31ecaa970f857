#!/usr/bin/env bash
# Runs INSIDE the virtme-ng VM started by deploy/vm/run-in-vm.sh (root, a real Debian
# kernel with SocketCAN; the host filesystem is mounted read-only, only OUT is writable).
#
#   deploy/vm/in-vm.sh OUT
#
# Steps (each prints PASS/FAIL/SKIP; the exit status is the number of failures, capped):
#   vcan-up       deploy/vcan-up.sh creates vcan0; a second run is a no-op
#   candump       `candump -L vcan0` records all traffic of the run (to the guest's tmpfs,
#                 copied to OUT/vcan0.log at the end)
#   cansend       a DBC Sync frame sent with cansend is seen by candump
#   python-can    deploy/vm/can_exchange.py: sync/feedback round trips on socketcan/vcan0
#   driver-tests  tests/drives/swpc/test_driver_{lifecycle,commands,faults}.py (the driver's
#                 back-to-back suite) with SWPC_TEST_CAN_INTERFACE=socketcan on vcan1..vcanN
#                 (one interface per test), SWPC_TEST_TIME_FACTOR=8 (SWPC_VM_TIME_FACTOR)
#   deadman       deploy/vm/deadman.py on vcan40: held ACTIVE beside busy loops (kernel
#                 refresh, C-emulated controllers), then kill -STOP: every axis free in time
#   sim-calibration  `swpc sim` as a separate process on vcan0 + `swpc serve` calibrating
#                 through it over HTTP (OUT/sim-calibration.json; compared by run-in-vm.sh
#                 with an in-process run of the same configuration on the host)
#   odrive        ODrive drives (firmware 0.5.x) on vcan41: `swpc sim --robot-config` with
#                 virtual ODrives + `swpc serve`; a run through them (activate, home,
#                 lock, spin), then kill -STOP of the service mid-spin: every axis
#                 stopped by its own watchdog within the bound (deploy/vm/odrive_deadman.py)
#   cia402        `swpc sim --drives cia402` and `swpc serve` (robot config drives: cia402) on
#                 vcan50: a run through them to a spin, then kill -STOP of the service:
#                 every CiA 402 drive's heartbeat consumer must fault it within D + W
#                 (deploy/vm/cia402_deadman.py)
# A whole calibration over SocketCAN is sim-calibration's (the swpc drives: the solve under
# TCG alone takes 70 s, 50x the host's); one through ODrive and CiA 402 drives is the
# in-process suite's (tests/services/whole_runs/).
#   can-up        deploy/can-up.sh on can0/can1, two SJA1000 (kvaser_pci) controllers that
#                 QEMU emulates on one CAN bus; python-can exchange can0 -> can1
#   robot-install deploy/vm/robot-install.sh: deploy/README.md's robot set-up on systemd
#                 (PID 1 of a container in the VM), the service on can0 and the
#                 simulator's unit on can1 (OUT/robot-install.log)
# OUT/vcan0.log is decoded afterwards on the host (run-in-vm.sh: `cantools decode`).
set -uo pipefail

OUT="${1:?usage: in-vm.sh OUT}"
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
cd "$ROOT"
PY="$ROOT/.venv/bin/python"
export PATH="$ROOT/.venv/bin:$PATH:/usr/sbin:/sbin"
export PYTHONDONTWRITEBYTECODE=1
# One BLAS thread: the solver's matrices are small, and OpenBLAS workers spin-waiting on
# the second emulated CPU only take it from the simulator, which needs 1.3 of the 2.
export OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1
mkdir -p "$OUT"

# Python under TCG: remount the read-only 9p shares of the venv and its base Python (see
# run-in-vm.sh) with cache=loose, so that each Python process after the first reads its
# modules from the guest page cache.  The host files do not change during the run.
while read -r tag mnt fstype opts _; do
    [[ "$fstype" == 9p && "$tag" == virtme.initmount* && "$mnt" != "$OUT" ]] || continue
    [[ "$mnt" == "$ROOT/.venv" || -x "$mnt/bin/python3" ]] || continue
    umount "$mnt" && mount -t 9p -o \
        ro,version=9p2000.L,trans=virtio,access=any,msize=524288,cache=loose "$tag" "$mnt" \
        || echo "warning: could not remount $mnt with cache=loose ($opts)"
done < <(cat /proc/mounts)
# cantools' CLI imports matplotlib: use the font cache built on the host by setup.sh.
if [[ -n "${SWPC_VM_MPLCONFIGDIR:-}" && -d "$SWPC_VM_MPLCONFIGDIR" ]]; then
    mkdir -p /tmp/mpl && cp -r "$SWPC_VM_MPLCONFIGDIR"/. /tmp/mpl/ && export MPLCONFIGDIR=/tmp/mpl
fi

echo "@@SWPC_VM_READY uptime=$(cut -d' ' -f1 /proc/uptime) kernel=$(uname -r)"
failures=0
declare -a SUMMARY=()
now() { date +%s.%N; }
secs() { awk -v a="$1" -v b="$2" 'BEGIN {printf "%.1f", b - a}'; }
result() { # result NAME STATUS(PASS|FAIL|SKIP) DETAIL
    SUMMARY+=("$(printf '%-16s %-4s %s' "$1" "$2" "$3")")
    echo "== $1: $2 $3"
    [[ "$2" == FAIL ]] && failures=$((failures + 1))
    return 0
}
selected() { # selected NAME: the step runs (vcan-up always; else as SWPC_VM_ONLY says)
    [[ -z "${SWPC_VM_ONLY:-}" || $1 == vcan-up || " $SWPC_VM_ONLY " == *" $1 "* ]]
}
step() { # step NAME CMD...: run CMD, PASS on status 0 (SKIP if not in SWPC_VM_ONLY)
    local name=$1; shift
    if ! selected "$name"; then
        result "$name" SKIP "(not in SWPC_VM_ONLY)"; return 0
    fi
    local t0 rc log="$OUT/step-$name.log"; t0=$(now)
    echo "-- $name: $*"
    # the step's output also to OUT/step-NAME.log: a failure's last lines go to
    # OUT/failures.txt, which .ci/run prints last (CI keeps only the tail of its output)
    "$@" > >(tee "$log") 2>&1
    rc=$?
    if ((rc == 0)); then result "$name" PASS "($(secs "$t0" "$(now)") s)"; return 0; fi
    result "$name" FAIL "(status $rc, $(secs "$t0" "$(now)") s)"
    sleep 0.5  # tee's last lines
    { echo "-- $name failed (status $rc); its last lines:"; tail -n 12 "$log"; } \
        >> "$OUT/failures.txt"
}

# --- vcan0 ---------------------------------------------------------------------------------
vcan_up_twice() {
    deploy/vcan-up.sh vcan0 && deploy/vcan-up.sh vcan0 || return 1
    ip -details link show dev vcan0 | tee "$OUT/vcan0.link"
    grep -q 'state UNKNOWN\|,UP' "$OUT/vcan0.link" && grep -qE '^ +vcan' "$OUT/vcan0.link"
}
step vcan-up vcan_up_twice

# Recorded to the guest's tmpfs: a write per frame over the 9p share cost candump CPU that
# the simulator needs, and it dropped frames.
DUMP=/tmp/vcan0.log
candump -L vcan0 > "$DUMP" 2> "$OUT/candump.err" &
CANDUMP_PID=$!
sleep 0.3
if kill -0 "$CANDUMP_PID" 2>/dev/null; then result candump PASS "(pid $CANDUMP_PID)"
else result candump FAIL "$(cat "$OUT/candump.err")"; fi

cansend_seen() {
    # candump may not have bound its socket yet (the 0.3 s above are not enough on a slow
    # host, and a frame sent before that is never recorded): send again until it is seen
    local i j
    for ((i = 0; i < 10; i++)); do
        cansend vcan0 000#2A || return 1
        for ((j = 0; j < 10; j++)); do
            grep -q ' vcan0 000#2A$' "$DUMP" && return 0
            sleep 0.2
        done
    done
    return 1
}
step cansend cansend_seen

step python-can "$PY" deploy/vm/can_exchange.py --interface socketcan --tx vcan0 --rx vcan0

# --- the emulation's speed -------------------------------------------------------------------
# Python under TCG runs 12-25x slower than on the host, and the host's speed varies ~2x over
# a day.  Before each timed step deploy/vm/speed.py times a Python loop and scales the time
# factor and the simulator's time scale with it, so the CPU load stays where it passed with
# margin (unless SWPC_VM_TIME_FACTOR / SWPC_VM_SIM_TIME_SCALE fix them).  Sets SPEED_LOOP_S,
# SPEED_SLOWNESS, SPEED_TIME_FACTOR, SPEED_SIM_TIME_SCALE; nothing if STEP does not run or
# FIXED (the knob that fixes its value) is set.
measure_speed() { # measure_speed STEP FIXED
    local line kv
    selected "$1" && [[ -z "$2" ]] || return 0
    line=$("$PY" -S deploy/vm/speed.py) || { echo "speed.py failed"; return 1; }
    for kv in $line; do declare -g "SPEED_$kv"; done
    echo "speed before $1: $line" | tee -a "$OUT/speed.txt"
}

# --- the driver's back-to-back suite ---------------------------------------------------------
shopt -s nullglob
driver_tests=(tests/drives/swpc/test_driver_lifecycle.py tests/drives/swpc/test_driver_commands.py
              tests/drives/swpc/test_driver_faults.py)
shopt -u nullglob
# One vcan interface per test (vcan1..vcanN, used round robin by tests/can_rig.py): no
# frame of one test reaches the next.  The rig runs F times slower (SWPC_TEST_TIME_FACTOR:
# feedback 200/F Hz, watchdog/heartbeat/refresh periods and all test windows x F): Python
# runs ~12x slower under TCG than on the host, ~25x with the host's other core busy; at
# F = 4 a loaded host still starved the 400 ms controller watchdog.  F = 8 at the reference
# speed (deploy/vm/speed.py), more on a slower host.
TEST_VCANS="${SWPC_VM_TEST_VCANS:-24}"
# The suite needs none of the installed pytest plugins but pytest-timeout (the Makefile's
# way); loading schemathesis', hypothesis' and anyio's took ~45 s of the step under TCG.
# test_recording_decodes_with_cantools is left to make test: it decodes a file with the
# cantools CLI in a subprocess (a minute of imports under TCG), which run-in-vm.sh does
# on the host for this run's own recording.
NO_PLUGINS=(-p pytest_timeout -k "not test_recording_decodes_with_cantools")
measure_speed driver-tests "${SWPC_VM_TIME_FACTOR:-}"
TIME_FACTOR="${SWPC_VM_TIME_FACTOR:-${SPEED_TIME_FACTOR:-8}}"
make_test_vcans() {
    local i names=()
    for ((i = 1; i <= TEST_VCANS; i++)); do
        ip link show dev "vcan$i" >/dev/null 2>&1 || ip link add dev "vcan$i" type vcan || return 1
        ip link set dev "vcan$i" up || return 1
        names+=("vcan$i")
    done
    TEST_CHANNELS="$(IFS=,; echo "${names[*]}")"
}
if ((${#driver_tests[@]})); then
    make_test_vcans || result driver-tests FAIL "(could not create vcan1..vcan$TEST_VCANS)"
    step driver-tests env PYTEST_DISABLE_PLUGIN_AUTOLOAD=1 SWPC_TEST_CAN_INTERFACE=socketcan \
        SWPC_TEST_CAN_CHANNEL="$TEST_CHANNELS" SWPC_TEST_TIME_FACTOR="$TIME_FACTOR" \
        "$PY" -m pytest -q -p no:cacheprovider "${NO_PLUGINS[@]}" --junitxml="$OUT/driver-tests.xml" \
        "${driver_tests[@]}"
    echo "driver suite at time factor $TIME_FACTOR"
else
    result driver-tests SKIP "(no tests/drives/swpc/test_driver_*.py back-to-back modules yet)"
fi

# --- the watchdog refresh in the kernel, and its dead-man ------------------------------------
# deploy/vm/deadman.py: the service's CAN settings (200 ms watchdog, 20 ms refresh in the
# kernel's broadcast manager, 0.3 s heartbeat loss) held ACTIVE for 10 s, then 30 s beside
# two busy loops; the controllers emulated in C (build/swpc-ctrl-emu) at real-time priority
# (firmware, not the robot computer), ksoftirqd too (a precaution: under emulation the
# broadcast manager's timer can end up there); then kill -STOP of the service: every axis
# must be free within dead-man + watchdog.  The dead-man D is the robot's 0.5 s scaled with
# the emulation's measured slowness (speed.py: D = 2 s x s; Python here is 20-50x slower than on the host,
# and D / 2 is how late the driver's Python thread may renew it); SWPC_VM_DEADMAN_D fixes
# it.  A hold that fails when the emulation has become slower than the speed D was sized
# for (by 1.25x, measured again after it) is held once more with D sized for the speed it
# had: the step is judged against that speed, not the one before it.  A hold with the refresh
# sent from Python instead (informative, SWPC_VM_DEADMAN_CONTRAST s) is reported beside it.
# 30 s beside the loops (1 500 refresh periods; 60 s until 2026-11-29) and no contrast by
# default: CI's 25 minutes hold all of make test-vcan.
# OUT/deadman.json; docs/history/2026-11-25-deadman-vm.md has the figures.
measure_speed deadman "${SWPC_VM_DEADMAN_D:-}"
deadman() {
    local fixed=()
    [[ -n "${SWPC_VM_DEADMAN_D:-}" ]] && fixed=(--fixed-deadman)
    deploy/vcan-up.sh vcan40 >/dev/null || return 1
    "$PY" deploy/vm/deadman.py run --channel vcan40 --idle "${SWPC_VM_DEADMAN_IDLE:-10}" \
        --hold "${SWPC_VM_DEADMAN_HOLD:-30}" --contrast "${SWPC_VM_DEADMAN_CONTRAST:-0}" \
        --deadman "${SWPC_VM_DEADMAN_D:-${SPEED_DEADMAN_S:-0}}" --out "$OUT/deadman.json" \
        "$( ((${SWPC_VM_DEADMAN_SOFTIRQ_RT:-1})) && echo --softirq-rt || echo --no-softirq-rt)" \
        --speed "LOOP_S=${SPEED_LOOP_S:-} SLOWNESS=${SPEED_SLOWNESS:-}" "${fixed[@]}" \
        ${SWPC_VM_DEADMAN_ARGS:-}
}
step deadman deadman

# --- calibration through the simulator as a separate process on vcan0 ----------------------
# `swpc sim` (controllers + physics + mocap, its own process) on socketcan/vcan0, zenoh
# listening on loopback; `swpc serve` on the same bus, connected to it, calibrating over
# HTTP (deploy/vm/sim_calibration.py).  Both run SIM_TS times real time (each has one of
# the VM's two emulated CPUs, ~20x slower than the host for Python); the simulator steps
# its physics every PHYSICS_DT (5 ms: at 10 ms the VM's wheel radii came out 0.3-0.5 %
# below the in-process ones, 5-8 std devs, not yet explained); the service's host-time
# windows (heartbeat loss, mocap staleness) are widened to match.  candump records all of
# it on vcan0.  The result (OUT/sim-calibration.json) is compared on the host with an
# in-process run of the same configuration (run-in-vm.sh).
measure_speed sim-calibration "${SWPC_VM_SIM_TIME_SCALE:-}"
SIM_TS="${SWPC_VM_SIM_TIME_SCALE:-${SPEED_SIM_TIME_SCALE:-0.3}}"
PHYSICS_DT="${SWPC_VM_PHYSICS_DT:-0.005}"
SIM_OVERRIDES="${SWPC_VM_SIM_OVERRIDES:-{\}}"
SIM_SEED="${SWPC_VM_SIM_SEED:-1}"
FEEDBACK_RATE="${SWPC_VM_FEEDBACK_RATE:-50}"
calibration_through_simulator() {
    local ts=$SIM_TS ep=tcp/127.0.0.1:7447 port=8080 token=vm-token-0123456789 rc=0 sim_pid svc_pid
    local window data=/tmp/swpc-data
    # The data dir must not be on the 9p share (OUT): SQLite there fails ("disk I/O error",
    # no POSIX locks over 9p), which is why the service never answered /health before.
    # /tmp is the guest's own tmpfs; the run's files are copied to OUT afterwards.
    # 15 heartbeat periods, 150 mocap periods (of robot time), and the controllers'
    # watchdog as long: the emulation's scheduling hiccups are not what this step tests
    # (make test and the driver suite test the supervision).  7.5 periods lost every node
    # once on a slow host (2.5 s, in LOCK); a 1 s watchdog expired on every controller once
    # (the service starved mid-spin on a slow host).
    window=$(awk -v s="$ts" 'BEGIN {printf "%.2f", 1.5 / s}')
    ip link set dev lo up || return 1                     # no network device, but loopback
    swpc sim --interface socketcan --channel vcan0 --zenoh-listen "$ep" --time-scale "$ts" \
        --physics-dt "$(awk -v d="$PHYSICS_DT" 'BEGIN {print d * 1000}')" \
        --feedback-rate "$FEEDBACK_RATE" \
        --pose-sigma-xy 0.5 --pose-sigma-yaw 0.05 --seed "$SIM_SEED" --stats-every 20 \
        > "$OUT/sim.log" 2>&1 &
    sim_pid=$!
    SWPC_CAN_INTERFACE=socketcan SWPC_CAN_CHANNEL=vcan0 SWPC_ZENOH_CONNECT="[\"$ep\"]" \
    SWPC_TIME_SCALE="$ts" SWPC_SIM_HOST_WINDOW_S="$window" \
    SWPC_TOKEN="$token" SWPC_DATA_DIR="$data" SWPC_PORT="$port" \
    SWPC_FEEDBACK_RATE="$FEEDBACK_RATE" SWPC_MOCAP_CLOCK=wall \
    SWPC_DISK_BUDGET=256MiB SWPC_MIN_FREE=32MiB \
        swpc serve > "$OUT/service.log" 2>&1 &
    svc_pid=$!
    echo "simulator pid $sim_pid, service pid $svc_pid, time scale $ts," \
        "heartbeat timeout, mocap stale after and watchdog $window s"
    "$PY" deploy/vm/sim_calibration.py run --url "http://127.0.0.1:$port" --token "$token" \
        --overrides "$SIM_OVERRIDES" --out "$OUT/sim-calibration.json" \
        --service-log "$OUT/service.log" --health-timeout 300 --timeout 1500 || rc=1
    kill "$svc_pid" "$sim_pid" 2>/dev/null
    wait "$svc_pid" "$sim_pid" 2>/dev/null
    mkdir -p "$OUT/service-data" && cp -r "$data/runs" "$OUT/service-data/" 2>/dev/null
    echo "simulator log (tail):"; tail -n 4 "$OUT/sim.log"
    return $rc
}
step sim-calibration calibration_through_simulator

# --- ODrive drives: a run through virtual ODrives, then kill -STOP ---------------------------
# The same set-up as sim-calibration on its own vcan41, with ODrive drives (firmware 0.5.x,
# where every frame to an axis feeds its watchdog) in a robot config both processes read.
# The ODrive's watchdog is set on the drive, not by the host: the simulator gets the
# service's W (services/config/timing.py at this time scale) as its --watchdog-ms.  After a
# calibration (DONE), a second run is stopped mid-spin by kill -STOP of the service
# (deploy/vm/odrive_deadman.py): the kernel's refresh ends D after the driver's last
# renewal, then every axis' watchdog disarms it; bound (D + W + T_hb) / S host seconds.
# sim-calibration's time scale: the kernel renews each armed axis every T_ref of robot time
# (T_ref / S of host time), so 8 axis nodes cost the simulator's Python what they would at
# full speed.  (Renewed every T_ref of host time, they once stalled the simulator mid-spin at
# this scale for longer than L, and the step ran at half of it.)
# The ODrive and CiA 402 simulators cost more CPU per robot second than swpc's (eight
# axis nodes; canopen's nodes): at sim-calibration's time scale the ODrive simulator ran
# at 96 % of its CPU and behind the service's clock (its watchdogs reported 0.13 s past
# the bound, 2026-11-30), so these steps run at 3/4 of it (unless
# SWPC_VM_SIM_TIME_SCALE fixes it).
heavy_scale() { awk -v s="$1" 'BEGIN {printf "%.3f", 0.75 * s}'; }
measure_speed odrive "${SWPC_VM_SIM_TIME_SCALE:-}"
odrive_calibration() {
    local ts=${SWPC_VM_SIM_TIME_SCALE:-$(heavy_scale "${SPEED_SIM_TIME_SCALE:-0.3}")}
    local ep=tcp/127.0.0.1:7448 port=8081 token=vm-token-0123456789 rc=0
    local window data=/tmp/swpc-odrive cfg=/tmp/odrive-robot.yaml chan=vcan41 sim_pid svc_pid
    local w hb d
    window=$(awk -v s="$ts" 'BEGIN {printf "%.2f", 1.5 / s}')
    deploy/vcan-up.sh "$chan" >/dev/null || return 1
    ip link set dev lo up || return 1
    printf 'drives: {kind: odrive, firmware: "0.5", homing: index}\n' > "$cfg"
    read -r w hb d < <(SWPC_CAN_INTERFACE=socketcan SWPC_CAN_CHANNEL="$chan" \
        SWPC_TIME_SCALE="$ts" SWPC_SIM_HOST_WINDOW_S="$window" SWPC_ROBOT_CONFIG="$cfg" \
        SWPC_FEEDBACK_RATE="$FEEDBACK_RATE" "$PY" -c '
from services.config.robot import load_robot_config
from services.config.settings import ServiceSettings
from services.config.timing import timing_budget
s = ServiceSettings()
b = timing_budget(s, load_robot_config(s.robot_config))
print(b.watchdog, b.heartbeat_period, b.deadman)') || return 1
    echo "ODrive budget at time scale $ts: W $w s, T_hb $hb s (robot), D $d s (kernel)"
    swpc sim --robot-config "$cfg" --interface socketcan --channel "$chan" \
        --zenoh-listen "$ep" --time-scale "$ts" --physics-dt 10 \
        --feedback-rate "$FEEDBACK_RATE" --watchdog-ms "$(awk -v w="$w" 'BEGIN {print int(w * 1000 + 0.5)}')" \
        --pose-sigma-xy 0.5 --pose-sigma-yaw 0.05 --seed "$SIM_SEED" --stats-every 20 \
        > "$OUT/odrive-sim.log" 2>&1 &
    sim_pid=$!
    SWPC_CAN_INTERFACE=socketcan SWPC_CAN_CHANNEL="$chan" SWPC_ZENOH_CONNECT="[\"$ep\"]" \
    SWPC_TIME_SCALE="$ts" SWPC_SIM_HOST_WINDOW_S="$window" SWPC_ROBOT_CONFIG="$cfg" \
    SWPC_TOKEN="$token" SWPC_DATA_DIR="$data" SWPC_PORT="$port" \
    SWPC_FEEDBACK_RATE="$FEEDBACK_RATE" SWPC_MOCAP_CLOCK=wall \
    SWPC_DISK_BUDGET=256MiB SWPC_MIN_FREE=32MiB \
        swpc serve > "$OUT/odrive-service.log" 2>&1 &
    svc_pid=$!
    echo "simulator pid $sim_pid, service pid $svc_pid (ODrive drives on $chan)"
    "$PY" deploy/vm/sim_calibration.py health --url "http://127.0.0.1:$port" \
        --service-log "$OUT/odrive-service.log" --timeout 300 || rc=1
    if ((rc == 0)); then
        "$PY" deploy/vm/odrive_deadman.py --url "http://127.0.0.1:$port" --token "$token" \
            --service-pid "$svc_pid" --channel "$chan" --firmware 0.5 --time-scale "$ts" \
            --deadman "$d" --watchdog "$w" --heartbeat "$hb" \
            --out "$OUT/odrive-deadman.json" || rc=1
    fi
    kill "$svc_pid" "$sim_pid" 2>/dev/null
    wait "$svc_pid" "$sim_pid" 2>/dev/null
    echo "simulator log (tail):"; tail -n 3 "$OUT/odrive-sim.log"
    return $rc
}
step odrive odrive_calibration
# --- CiA 402 drives: a run through `swpc sim --drives cia402`, and their dead-man ------------
# The same configuration as sim-calibration (time scale, physics step, feedback rate,
# overrides) on its own interface (vcan50) with CiA 402 drives: the service's robot config
# says `drives: cia402`, the simulator's drives are canopen LocalNodes with the 402 state
# machine.  Then a long run, and once every drive reports OPERATION ENABLED, kill -STOP of
# the service (deploy/vm/cia402_deadman.py): its heartbeat, sent by the kernel's broadcast
# manager, must end at most D = 0.5 s of robot time (D / S host seconds: the kernel runs on
# the host's time) after the STOP, and every drive's heartbeat
# consumer (its time: the service's watchdog W, robot time) must then fault it within W of
# the drive's own time.  Eight CiA 402 drives in Python cost the simulator more than swpc's
# controllers: it steps its physics every 10 ms.  sim-calibration's time scale: the kernel
# renews the drives every T_ref of robot time (T_ref / S of host time).
measure_speed cia402 "${SWPC_VM_SIM_TIME_SCALE:-}"
cia402_step() {
    local ts=${SWPC_VM_SIM_TIME_SCALE:-$(heavy_scale "${SPEED_SIM_TIME_SCALE:-0.3}")} ep=tcp/127.0.0.1:7448
    local port=8081 token=vm-token-0123456789 rc=0 sim_pid svc_pid run_pid window
    local data=/tmp/swpc-cia402 robot=/tmp/cia402-robot.yaml
    # W = ts x window = 1.5 s of robot time (services/config/timing.py), D = 0.5 s host time
    window=$(awk -v s="$ts" 'BEGIN {printf "%.2f", 1.5 / s}')
    deploy/vcan-up.sh vcan50 >/dev/null || return 1
    ip link set dev lo up || return 1
    printf 'drives: cia402\n' > "$robot"
    # its traffic recorded (the guest's tmpfs, copied to OUT/vcan50.log): what a refusal
    # at CONNECT had on the bus (controlwords sent, statuswords answered)
    candump -L vcan50 > /tmp/vcan50.log 2>/dev/null &
    local dump_pid=$!
    swpc sim --drives cia402 --interface socketcan --channel vcan50 --zenoh-listen "$ep" \
        --time-scale "$ts" --physics-dt 10 \
        --pose-sigma-xy 0.5 --pose-sigma-yaw 0.05 --seed "$SIM_SEED" --stats-every 20 \
        > "$OUT/cia402-sim.log" 2>&1 &
    sim_pid=$!
    SWPC_CAN_INTERFACE=socketcan SWPC_CAN_CHANNEL=vcan50 SWPC_ZENOH_CONNECT="[\"$ep\"]" \
    SWPC_TIME_SCALE="$ts" SWPC_SIM_HOST_WINDOW_S="$window" SWPC_ROBOT_CONFIG="$robot" \
    SWPC_TOKEN="$token" SWPC_DATA_DIR="$data" SWPC_PORT="$port" \
    SWPC_FEEDBACK_RATE="$FEEDBACK_RATE" SWPC_MOCAP_CLOCK=wall \
    SWPC_DISK_BUDGET=256MiB SWPC_MIN_FREE=32MiB \
        swpc serve > "$OUT/cia402-service.log" 2>&1 &
    svc_pid=$!
    echo "cia402: simulator pid $sim_pid, service pid $svc_pid, time scale $ts"
    # the dead-man: a long spin, every drive enabled, then the service stopped
    "$PY" deploy/vm/sim_calibration.py run --url "http://127.0.0.1:$port" --token "$token" \
        --overrides '{"protocol": {"sweep_deg": 3600}}' --out "$OUT/cia402-stopped-run.json" \
        --service-log "$OUT/cia402-service.log" --health-timeout 300 --timeout 900 \
        > "$OUT/cia402-stopped-run.log" 2>&1 &
    run_pid=$!
    "$PY" deploy/vm/cia402_deadman.py --channel vcan50 --pid "$svc_pid" --nodes 1-8 \
        --run-pid "$run_pid" --deadman "$(awk -v s="$ts" 'BEGIN {printf "%.3f", 0.5 / s}')" \
        --consumer 1.5 --time-scale "$ts" --out "$OUT/cia402-deadman.json" \
        || rc=1
    kill "$run_pid" "$svc_pid" "$sim_pid" "$dump_pid" 2>/dev/null
    wait "$run_pid" "$svc_pid" "$sim_pid" "$dump_pid" 2>/dev/null
    cp /tmp/vcan50.log "$OUT/vcan50.log" 2>/dev/null
    echo "cia402 simulator log (tail):"; tail -n 3 "$OUT/cia402-sim.log"
    return $rc
}
step cia402 cia402_step

# --- real CAN controllers (QEMU kvaser_pci / SJA1000 on one emulated bus) ---------------------
if [[ -e /sys/class/net/can0 && -e /sys/class/net/can1 ]]; then
    can_up_both() {
        deploy/can-up.sh can0 --bitrate 500000 --restart-ms 100 \
            && deploy/can-up.sh can1 --bitrate 500000 --restart-ms 100 \
            && ip -details link show dev can0 | tee "$OUT/can0.link" \
            | grep -q 'restart-ms 100' \
            && grep -q 'bitrate 500000' "$OUT/can0.link"
    }
    step can-up can_up_both
    step python-can-sja1000 "$PY" deploy/vm/can_exchange.py --interface socketcan \
        --tx can0 --rx can1 --count 50
    # deploy/README.md's robot set-up under systemd (a container booted in this VM):
    # sysusers, config, can-up + sysctl, both units, health, a run aborted mid-spin,
    # restart on failure, stop
    step robot-install deploy/vm/robot-install.sh "$OUT"
else
    result can-up SKIP "(no can0/can1: QEMU started without kvaser_pci devices)"
fi

# --- stop the recording (decoded on the host with our DBC by run-in-vm.sh: cantools is
#     ~20x slower under TCG) --------------------------------------------------------------
kill "$CANDUMP_PID" 2>/dev/null
wait "$CANDUMP_PID" 2>/dev/null
if cp "$DUMP" "$OUT/vcan0.log"; then
    result candump-stop PASS "($(wc -l < "$OUT/vcan0.log") frames in $OUT/vcan0.log)"
else
    result candump-stop FAIL "(could not copy $DUMP to $OUT)"
fi

echo
echo "== summary (in VM, $(cut -d' ' -f1 /proc/uptime) s since boot)"
printf '%s\n' "${SUMMARY[@]}" | tee "$OUT/summary.txt"
echo "@@SWPC_VM_DONE failures=$failures"
exit $((failures > 100 ? 100 : failures))
