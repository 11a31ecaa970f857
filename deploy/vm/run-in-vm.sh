#!/usr/bin/env bash
# `make test-vcan`: the real SocketCAN path on a real Linux CAN stack.
#
#   deploy/vm/run-in-vm.sh [IN-VM COMMAND...]     (default: deploy/vm/in-vm.sh OUT)
#
# 1. deploy/vm/setup.sh (idempotent, cached in .cache/vm/): Debian packages, the Debian
#    kernel unpacked and trimmed, pinned virtme-ng in .venv.
# 2. Boots that kernel ONCE with virtme-ng under QEMU software emulation (TCG; KVM is not
#    used: the development VM's /dev/kvm lets a process create a VM, but its nested KVM
#    stops the guest kernel at boot, "KVM internal error ... emulation failure" on lock
#    cmpxchg16b, then on xrstor with -cx16, and hangs with -cpu qemu64; tried 2026-11-30) over a read-only 9p view of this machine's filesystem, no network device, with
#    .cache/vm/run/ as the only writable host folder, and two emulated SJA1000 CAN
#    controllers (kvaser_pci) on one QEMU CAN bus (can0, can1 in the guest).
# 3. Runs deploy/vm/in-vm.sh inside; its exit status is this script's.
#    Steps odrive, cia402: a run on those drives and their dead-man (kill -STOP).
# Prints the set-up, boot and test times.  Results: .cache/vm/run/ (summary.txt,
# vcan0.log = candump, vcan0.decoded.txt = cantools decode, driver-tests.xml).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
CACHE="${SWPC_VM_CACHE:-$ROOT/.cache/vm}"
OUT="$CACHE/run"
TIMEOUT="${SWPC_VM_TIMEOUT:-1800}"
cd "$ROOT"

fmt() { awk -v a="$1" -v b="$2" 'BEGIN {printf "%.1f", b - a}'; }
t_setup0=$EPOCHREALTIME
envfile="$(bash deploy/vm/setup.sh | tail -n1)"
# shellcheck disable=SC1090
source "$envfile"
t_setup1=$EPOCHREALTIME

rm -rf "$OUT" && mkdir -p "$OUT"
# Our packages' bytecode, compiled here: the VM sees the checkout read-only, and compiling
# them in every Python process there costs seconds under TCG (__pycache__ is git-ignored).
"$ROOT/.venv/bin/python" -m compileall -q -j 0 swpc_hw services simulators firmware_protocol \
    tests deploy/vm > /dev/null
if (($#)); then cmd="$*"; else cmd="deploy/vm/in-vm.sh $OUT"; fi
# The calibration through the simulator: the same configuration in the VM (socketcan,
# separate simulator process) and in the in-process reference below.  A short protocol
# (4 modules x 2 angles, 45 deg sweeps: ~30 s of robot time; no fast part, whose four
# probes took 100 s of the emulation: make test runs it against the in-process simulator,
# on the same driver commands) at 50 Hz encoder feedback
# (100 Hz put 240 frames/s of wall time through the simulator's and the service's Python
# under TCG) with 5 ms physics steps, slowed down to a fraction of real time that in-vm.sh
# picks from the measured speed of the emulation (deploy/vm/speed.py).
: "${SWPC_VM_CPUS:=2}"
: "${SWPC_VM_PHYSICS_DT:=0.005}"
: "${SWPC_VM_SIM_SEED:=1}"
: "${SWPC_VM_FEEDBACK_RATE:=50}"
: "${SWPC_VM_SIM_OVERRIDES:={\"protocol\": {\"sweep_deg\": 45, \"settle_time\": 1.0, \"stop_time\": 0.5, \"align_time\": 0.5, \"resteer_time\": 1.5, \"precheck\": false\}\}}"
# The in-VM script's knobs pass through: SWPC_VM_ONLY, SWPC_VM_TIME_FACTOR,
# SWPC_VM_SIM_TIME_SCALE, SWPC_VM_SIM_OVERRIDES, SWPC_VM_SIM_SEED, SWPC_VM_FEEDBACK_RATE,
# SWPC_VM_PHYSICS_DT, SWPC_VM_TEST_VCANS, SWPC_VM_DEADMAN_IDLE, SWPC_VM_DEADMAN_HOLD,
# SWPC_VM_DEADMAN_CONTRAST, SWPC_VM_DEADMAN_D, SWPC_VM_DEADMAN_SOFTIRQ_RT,
# SWPC_VM_DEADMAN_ARGS (more deploy/vm/deadman.py run options, e.g. --profile-io).
for v in ONLY TIME_FACTOR SIM_TIME_SCALE SIM_OVERRIDES SIM_SEED FEEDBACK_RATE PHYSICS_DT TEST_VCANS \
    DEADMAN_IDLE DEADMAN_HOLD DEADMAN_CONTRAST DEADMAN_D DEADMAN_SOFTIRQ_RT DEADMAN_ARGS; do
    v="SWPC_VM_$v"
    [[ -n "${!v:-}" ]] && cmd="$v=$(printf '%q' "${!v}") $cmd"
done
cmd="SWPC_VM_MPLCONFIGDIR=$SWPC_VM_MPLCONFIGDIR $cmd"

export PATH="$ROOT/.venv/bin:$PATH"

# The venv and its base Python are also exported as separate read-only 9p shares, which
# in-vm.sh remounts with cache=loose (the root share is uncached: every Python import
# would otherwise go to the host again).
pybase="$("$ROOT/.venv/bin/python" -c 'import sys; print(sys.base_prefix)')"
vng_args=(
    -r "$SWPC_VM_KIMG" --disable-kvm --force-9p --cpus "$SWPC_VM_CPUS" --memory 1G
    --rwdir="$OUT" --rodir="$ROOT/.venv"
    --qemu-opts="-object can-bus,id=canbus0 -device kvaser_pci,canbus=canbus0 -device kvaser_pci,canbus=canbus0"
    --exec "$cmd"
)
case "$pybase" in /|/usr|/usr/local) ;; *) vng_args+=(--rodir="$pybase") ;; esac
echo "[test-vcan] vng ${vng_args[*]}"
ready_file="$OUT/.host-ready-time"
t_boot0=$EPOCHREALTIME
set +e
# stdin must be /dev/null and stdout a pipe: virtme-ng then runs non-interactively and
# returns the command's exit status.
timeout --kill-after=10 "$TIMEOUT" vng "${vng_args[@]}" </dev/null 2>&1 \
    | while IFS= read -r line; do
        [[ "$line" == @@SWPC_VM_READY* && ! -e "$ready_file" ]] && echo "$EPOCHREALTIME" > "$ready_file"
        printf '%s\n' "$line"
    done
status=${PIPESTATUS[0]}
set -e
t_end=$EPOCHREALTIME


# candump's recording of vcan0 in the VM, decoded here by `cantools decode` with our DBC:
# every frame must decode, and the run's message types must all be there.
decode_status=0
t_dec=$EPOCHREALTIME
if [[ -n "${SWPC_VM_ONLY:-}" ]]; then  # a partial run: every recorded frame must decode
    [[ -f "$OUT/vcan0.log" ]] || : > "$OUT/vcan0.log"
    "$ROOT/.venv/bin/cantools" decode --single-line firmware_protocol/swpc.dbc \
        < "$OUT/vcan0.log" > "$OUT/vcan0.decoded.txt" || decode_status=1
    if grep -q 'Unknown frame id' "$OUT/vcan0.decoded.txt"; then decode_status=1; fi
    echo "[test-vcan] decode (partial run): $(wc -l < "$OUT/vcan0.log") frames, status $decode_status"
elif [[ -s "$OUT/vcan0.log" ]]; then
    "$ROOT/.venv/bin/cantools" decode --single-line firmware_protocol/swpc.dbc \
        < "$OUT/vcan0.log" > "$OUT/vcan0.decoded.txt" || decode_status=1
    frames=$(wc -l < "$OUT/vcan0.log")
    unknown=$(grep -c 'Unknown frame id' "$OUT/vcan0.decoded.txt" || true)
    # the cansend test frame (Sync 42) and, from the calibration, every message of a run
    need=(Sync N1_FeedbackPosition N1_FeedbackVelocityTorque N1_Heartbeat N1_SetControl
          N1_SetAxisState N1_SetWatchdog N1_SetFeedback N1_SetLimits N1_StartHoming
          N1_HomingStatus N4_FeedbackPosition)
    missing=()
    for m in "${need[@]}"; do
        grep -q ":: $m(" "$OUT/vcan0.decoded.txt" || missing+=("$m")
    done
    grep -q ':: Sync(SyncCounter: 42)' "$OUT/vcan0.decoded.txt" || missing+=("Sync(42)")
    echo "[test-vcan] decode: $frames frames in vcan0.log, $unknown with ids not in the DBC; by message:"
    grep -v 'Unknown frame id' "$OUT/vcan0.decoded.txt" \
        | sed -n 's/.* :: \([A-Za-z0-9_]*\)(.*/\1/p' | sort | uniq -c | sort -rn | head -n 12 \
        | sed 's/^/[test-vcan]   /'
    if ((${#missing[@]} || unknown)); then
        echo "[test-vcan] decode: FAIL (missing: ${missing[*]:-none}; unknown ids: $unknown)"
        decode_status=1
    fi
else
    echo "[test-vcan] decode: FAIL (no $OUT/vcan0.log)"
    decode_status=1
fi
printf '%-16s %-4s %s\n' decode "$( ((decode_status)) && echo FAIL || echo PASS)" \
    "($(fmt "$t_dec" "$EPOCHREALTIME") s, on the host)" >> "$OUT/summary.txt"

# The in-process reference: the same calibration configuration here, `swpc serve` on its
# in-process simulator (python-can virtual bus, same truth, seed, mocap noise, feedback
# rate, physics step, protocol overrides; simulated time in lockstep, the robot's own
# windows), driven by the same HTTP client, after the VM (run concurrently, it took a host
# core from the emulation).
ref="$OUT/in-process"
run_reference() {
    local ref_port="${SWPC_VM_REF_PORT:-18080}" pid
    mkdir -p "$ref"
    echo "in-process reference: swpc serve (in-process simulator, lockstep)"
    SWPC_SIM_SEED="$SWPC_VM_SIM_SEED" SWPC_TOKEN=ref-token-0123456789 \
    SWPC_FEEDBACK_RATE="$SWPC_VM_FEEDBACK_RATE" SWPC_SIM_PHYSICS_DT="$SWPC_VM_PHYSICS_DT" \
    SWPC_DATA_DIR="$ref/data" SWPC_PORT="$ref_port" \
        "$ROOT/.venv/bin/swpc" serve > "$ref/service.log" 2>&1 &
    pid=$!
    "$ROOT/.venv/bin/python" deploy/vm/sim_calibration.py run \
        --url "http://127.0.0.1:$ref_port" --token ref-token-0123456789 \
        --overrides "$SWPC_VM_SIM_OVERRIDES" --out "$OUT/in-process.json" \
        --service-log "$ref/service.log" --health-timeout 120 || true
    kill "$pid" 2>/dev/null; wait "$pid" 2>/dev/null || true
}
# The VM's calibration through the simulator process on vcan0 against the in-process
# reference.  Exit status 10 if they do not agree within 3 combined std devs (11: the
# recording does not decode).
ref_status=0
t_ref=$EPOCHREALTIME
t_cmp=$t_ref
set +e
if grep -qs '"result"' "$OUT/sim-calibration.json"; then
    run_reference 2>&1 | tee "$OUT/in-process.log" | sed 's/^/[in-process] /'
    t_cmp=$EPOCHREALTIME
    "$ROOT/.venv/bin/python" deploy/vm/sim_calibration.py compare \
        "$OUT/sim-calibration.json" "$OUT/in-process.json" | tee "$OUT/comparison.txt" \
        | sed 's/^/[compare] /'
    ref_status=${PIPESTATUS[0]}
    if ((ref_status)); then
        echo "[test-vcan] FAIL: VM (socketcan, separate simulator) and in-process results differ"
    else
        echo "[test-vcan] PASS: VM (socketcan, separate simulator) and in-process results agree"
    fi
elif ((!$#)); then
    echo "[test-vcan] no VM calibration result (sim-calibration failed or skipped): no comparison"
fi
t_end2=$EPOCHREALTIME
((status == 0 && ref_status != 0)) && status=10
((status == 0 && decode_status != 0)) && status=11
set -e

t_ready=$t_end
[[ -s "$ready_file" ]] && t_ready="$(cat "$ready_file")"
{
    echo "set-up (deploy/vm/setup.sh): $(fmt "$t_setup0" "$t_setup1") s"
    echo "VM boot (vng start -> in-VM script running): $(fmt "$t_boot0" "$t_ready") s"
    echo "tests in VM + shutdown: $(fmt "$t_ready" "$t_end") s"
    echo "decode on the host: $(fmt "$t_dec" "$t_ref") s"
    echo "in-process reference calibration (host): $(fmt "$t_ref" "$t_cmp") s"
    echo "comparison (host): $(fmt "$t_cmp" "$t_end2") s"
    echo "total: $(fmt "$t_setup0" "$t_end2") s"
    echo "exit status: $status"
} | sed 's/^/[test-vcan] /' | tee "$OUT/timing.txt"
[[ $status -eq 124 ]] && echo "[test-vcan] error: timed out after $TIMEOUT s" >&2
exit "$status"
