#!/usr/bin/env bash
# Configure and raise a real CAN interface (the robot's bus to the caster controllers).
#
#   sudo deploy/can-up.sh [IFACE] [--bitrate BPS] [--restart-ms MS] [--sample-point SP]
#                         [--txqueuelen N]
#
#   IFACE           default can0 (or $SWPC_CAN)
#   --bitrate       nominal bit rate in bit/s, default 1000000 (or $SWPC_CAN_BITRATE);
#                   must match the controllers' firmware
#   --restart-ms    automatic restart delay after bus-off, default 100 (0 = stay bus-off
#                   until someone runs `ip link set IFACE type can restart`)
#   --sample-point  e.g. 0.875; default: the driver's choice
#   --txqueuelen    transmit queue length in frames, default 128 (more than the
#                   kernel's 10, so a burst of set-points is not dropped with ENOBUFS)
#
# Idempotent: the interface is taken down, (re)configured and raised again.
# Exit status: 0 ok; 2 usage; 3 no such CAN interface or the driver refused the
#              settings; 4 not permitted (run as root).
set -euo pipefail

iface="${SWPC_CAN:-can0}"
bitrate="${SWPC_CAN_BITRATE:-1000000}"
restart_ms=100
sample_point=""
txqueuelen=128

fail() { # fail STATUS MESSAGE...
    local status=$1; shift
    printf 'can-up: error: %s\n' "$*" >&2
    exit "$status"
}
need_value() { [[ $# -ge 2 && -n "$2" ]] || fail 2 "$1 needs a value"; }
is_uint() { [[ "$1" =~ ^[0-9]+$ ]]; }

while [[ $# -gt 0 ]]; do
    case "$1" in
        --bitrate) need_value "$@"; bitrate="$2"; shift 2 ;;
        --restart-ms) need_value "$@"; restart_ms="$2"; shift 2 ;;
        --sample-point) need_value "$@"; sample_point="$2"; shift 2 ;;
        --txqueuelen) need_value "$@"; txqueuelen="$2"; shift 2 ;;
        -h|--help) awk 'NR > 1 && !/^#/ {exit} NR > 1 {sub(/^# ?/, ""); print}' "$0"; exit 0 ;;
        -*) fail 2 "unknown option $1" ;;
        *) iface="$1"; shift ;;
    esac
done
is_uint "$bitrate" && ((bitrate > 0 && bitrate <= 1000000)) \
    || fail 2 "--bitrate must be an integer in 1..1000000 bit/s, not '$bitrate'"
is_uint "$restart_ms" || fail 2 "--restart-ms must be a non-negative integer, not '$restart_ms'"
is_uint "$txqueuelen" || fail 2 "--txqueuelen must be a non-negative integer, not '$txqueuelen'"
[[ -z "$sample_point" || "$sample_point" =~ ^0?\.[0-9]+$ ]] \
    || fail 2 "--sample-point must be a fraction like 0.875, not '$sample_point'"

PATH="$PATH:/usr/sbin:/sbin"
command -v ip >/dev/null || fail 3 "'ip' (iproute2) is not installed"

if [[ ! -e "/sys/class/net/$iface" ]]; then
    have="$(ip -o link show 2>/dev/null | awk -F': ' '$2 ~ /can/ {printf "%s ", $2}')"
    fail 3 "no interface named $iface. CAN interfaces present: ${have:-none}." \
        "Check the adapter is plugged in and its driver is loaded (dmesg; e.g. gs_usb," \
        "peak_usb, mcp251x, kvaser_pci)."
fi
# ARPHRD_CAN = 280; a vcan also has it but takes no bit timing.
[[ "$(cat "/sys/class/net/$iface/type")" == 280 ]] || fail 3 "$iface is not a CAN interface"
if ip -details link show dev "$iface" | grep -qE '^ +vcan'; then
    fail 3 "$iface is a virtual CAN interface: use deploy/vcan-up.sh for it"
fi

run_ip() {
    local err
    if ! err="$(ip "$@" 2>&1)"; then
        [[ "$err" == *"Operation not permitted"* ]] \
            && fail 4 "configuring $iface needs CAP_NET_ADMIN: run as root (sudo $0 ...)"
        fail 3 "ip $*: $err"
    fi
}

settings=(bitrate "$bitrate" restart-ms "$restart_ms")
[[ -n "$sample_point" ]] && settings+=(sample-point "$sample_point")

run_ip link set dev "$iface" down
run_ip link set dev "$iface" type can "${settings[@]}"
run_ip link set dev "$iface" txqueuelen "$txqueuelen"
run_ip link set dev "$iface" up

state="$(ip -details link show dev "$iface" | awk '/can state/ {print $3; exit}')"
echo "can-up: $iface is up: bitrate $bitrate, restart-ms $restart_ms," \
    "txqueuelen $txqueuelen, state ${state:-unknown}"
