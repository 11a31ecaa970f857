#!/usr/bin/env bash
# Create and raise a virtual CAN interface (default vcan0) for the lab simulator.
#
#   sudo deploy/vcan-up.sh [IFACE] [--fd]
#
#   IFACE   interface name, default vcan0 (or $SWPC_VCAN)
#   --fd    CAN FD MTU (72); the default is classic CAN (MTU 16), which is what the
#           SWPC controllers speak.
#
# Idempotent: an existing vcan interface of that name is only (re)raised.
# Exit status: 0 ok; 2 usage; 3 the kernel has no vcan (or no SocketCAN) support;
#              4 not permitted (run as root); 5 the name exists but is not a vcan interface.
set -euo pipefail

iface="${SWPC_VCAN:-vcan0}"
mtu=16
for arg in "$@"; do
    case "$arg" in
        --fd) mtu=72 ;;
        -h|--help) awk 'NR > 1 && !/^#/ {exit} NR > 1 {sub(/^# ?/, ""); print}' "$0"; exit 0 ;;
        -*) echo "vcan-up: unknown option $arg" >&2; exit 2 ;;
        *) iface="$arg" ;;
    esac
done

fail() { # fail STATUS MESSAGE...
    local status=$1; shift
    printf 'vcan-up: error: %s\n' "$*" >&2
    exit "$status"
}

PATH="$PATH:/usr/sbin:/sbin"
command -v ip >/dev/null || fail 3 "'ip' (iproute2) is not installed"

no_vcan() {
    fail 3 "the running kernel ($(uname -r)) has no vcan support: $1." \
        "Install this kernel's modules (Debian: linux-image-amd64 ships can, can-raw, vcan)" \
        "or boot a kernel with CONFIG_CAN, CONFIG_CAN_RAW and CONFIG_CAN_VCAN." \
        "Without SocketCAN, use python-can's 'virtual' interface instead" \
        "(swpc ... --interface virtual)."
}

if [[ -e "/sys/class/net/$iface" ]]; then
    kind="$(ip -details link show dev "$iface" 2>/dev/null | awk '/^ +vcan/{print "vcan"; exit}')"
    [[ "$kind" == vcan ]] || fail 5 "$iface exists but is not a vcan interface"
else
    if [[ ! -d /sys/module/vcan ]]; then
        if ! err="$(modprobe vcan 2>&1)"; then
            [[ -d /sys/module/vcan ]] || no_vcan "modprobe vcan failed (${err:-no message})"
        fi
    fi
    if ! err="$(ip link add dev "$iface" type vcan 2>&1)"; then
        if [[ -e "/sys/class/net/$iface" ]]; then
            :   # created concurrently: fine
        elif [[ "$err" == *"Operation not permitted"* ]]; then
            fail 4 "creating $iface needs CAP_NET_ADMIN: run as root (sudo $0 $iface)"
        elif [[ "$err" == *"Unknown device type"* || "$err" == *"not supported"* ]]; then
            no_vcan "'ip link add type vcan' says: $err"
        else
            fail 3 "ip link add dev $iface type vcan: $err"
        fi
    fi
fi

cur_mtu="$(cat "/sys/class/net/$iface/mtu")"
if [[ "$cur_mtu" != "$mtu" ]]; then
    ip link set dev "$iface" down
    ip link set dev "$iface" mtu "$mtu" \
        || fail 3 "cannot set MTU $mtu on $iface (CAN FD needs a kernel with CAN FD support)"
fi
if ! err="$(ip link set dev "$iface" up 2>&1)"; then
    [[ "$err" == *"Operation not permitted"* ]] \
        && fail 4 "raising $iface needs CAP_NET_ADMIN: run as root (sudo $0 $iface)"
    fail 3 "ip link set dev $iface up: $err"
fi
echo "vcan-up: $iface is up (vcan, mtu $mtu)"
