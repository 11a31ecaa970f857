#!/usr/bin/env bash
# Runs INSIDE the test VM (in-vm.sh, step robot-install): boots systemd as PID 1 of a new
# PID and mount namespace, a container in the sense of systemd's container interface
# (https://systemd.io/CONTAINER_INTERFACE/), and runs deploy/vm/robot-install-test.sh
# there as a unit: deploy/README.md's robot set-up, step by step, on a machine that runs
# systemd.
#
#   deploy/vm/robot-install.sh OUT            (as root, in the VM)
#
# The VM's root is this machine's filesystem, read-only.  In the new mount namespace
# /etc, /var and /opt get a tmpfs overlay (writable, discarded at exit), /opt/swpc is the
# checkout (the units' path), /run and /tmp fresh tmpfs, and cgroup2 is mounted if it is
# not.
# Exit status: robot-install-test.sh's number of failures (systemctl exit N), 124 if
# systemd did not finish in SWPC_VM_ROBOT_TIMEOUT s (default 900).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"

if [[ "${1:-}" != --pid1 ]]; then
    OUT="${1:?usage: robot-install.sh OUT}"
    : > "$OUT/robot-install.log"
    case "$ROOT/" in
    /tmp/*)  # the container's own /tmp covers it: its venv's scripts name paths there
        echo "robot-install: the checkout $ROOT is under /tmp, which the container covers" \
            "with its own /tmp (its venv's scripts would not be found): clone it elsewhere" \
            | tee -a "$OUT/robot-install.log" >&2
        exit 2
        ;;
    esac
    status=0
    timeout --kill-after=10 "${SWPC_VM_ROBOT_TIMEOUT:-900}" \
        unshare --pid --fork --mount --mount-proc --propagation private \
        "$0" --pid1 "$OUT" || status=$?
    cat "$OUT/robot-install.log"
    exit "$status"
fi

# --- PID 1 of the new namespaces -----------------------------------------------------------
OUT="$2"
# /run first: a fresh tmpfs that also holds the overlays' upper layers (a scratch mount
# anywhere that a later mount covers is one systemd cannot unmount: with the scratch
# under /tmp, covered by the /tmp below, the container did not exit in 4 min)
mount -t tmpfs -o mode=0755 tmpfs /run
ov=/run/swpc-robot-overlay
mkdir -p "$ov"
for d in etc var opt; do
    mkdir -p "$ov/$d/upper" "$ov/$d/work"
    mount -t overlay overlay \
        -o "lowerdir=/$d,upperdir=$ov/$d/upper,workdir=$ov/$d/work" "/$d"
done
# This machine's venv is built on a Python under /root or /home (pyenv), which the units'
# ProtectHome= hides and the swpc user may not read; a robot's venv uses the system
# Python (/usr).  Here the base Python is bound to /opt/python and the venv pointed at it
# through an overlay (the checkout itself stays untouched).
base="$("$ROOT/.venv/bin/python" -c 'import sys; print(sys.base_prefix)')"
setenv=()
case "$base" in
/root/* | /home/*)
    mkdir -p /opt/python "$ov/venv/upper" "$ov/venv/work" && mount --bind "$base" /opt/python
    mount -t overlay overlay \
        -o "lowerdir=$ROOT/.venv,upperdir=$ov/venv/upper,workdir=$ov/venv/work" "$ROOT/.venv"
    ln -sfn /opt/python/bin/python3 "$ROOT/.venv/bin/python3"
    sed -i -e "s|$base|/opt/python|g" "$ROOT/.venv/pyvenv.cfg"
    # its executable finds libpython by an absolute RUNPATH under /root: without this
    # default environment of every unit, the loader falls back to the system's
    # libpython3.11 of another patch release (`_ssl`: undefined symbol _PyModule_Add)
    setenv=("systemd.setenv=LD_LIBRARY_PATH=/opt/python/lib")
    echo "robot-install: base Python $base bound to /opt/python for the swpc user"
    ;;
esac
mkdir -p /opt/swpc && mount --rbind "$ROOT" /opt/swpc
# the results dir as the units see it, bound before the /tmp below covers a checkout
# under /tmp (a CI clone there: the test unit's log had no path, and systemd waited)
mkdir -p /opt/swpc-out && mount --bind "$OUT" /opt/swpc-out
OUT=/opt/swpc-out
# a /tmp of its own: systemd-tmpfiles empties /tmp at boot, which took the VM's
# candump recording with it (the overlays above keep their mounts)
mount -t tmpfs -o mode=1777 tmpfs /tmp
mountpoint -q /sys/fs/cgroup || mount -t cgroup2 cgroup2 /sys/fs/cgroup
# A fresh machine: no machine id (systemd writes one), no swpc user yet.
: > /etc/machine-id
if getent passwd swpc > /dev/null; then
    echo "robot-install: this machine already has a user swpc" >&2
    exit 2
fi

cat > /etc/systemd/system/swpc-robot-install-test.service <<UNIT
[Unit]
Description=deploy/README.md robot set-up, step by step (swpc test VM)
After=basic.target

[Service]
Type=oneshot
Environment=SWPC_VM_SIM_TIME_SCALE=${SWPC_VM_SIM_TIME_SCALE:-0.3}
ExecStart=/bin/bash /opt/swpc/deploy/vm/robot-install-test.sh $OUT
StandardOutput=append:$OUT/robot-install.log
StandardError=append:$OUT/robot-install.log
# The test script leaves its number of failures in the status file; whatever happened,
# the container's systemd exits with it (99: the script died before writing it).
ExecStopPost=/bin/sh -c 'systemctl --no-block exit "\$\$(cat /run/swpc-robot-install.status 2>/dev/null || echo 99)"'
UNIT

# Units of this machine that have no business in the test: the container has no udev,
# no logins, no consoles and no database.
masks=()
for u in systemd-udevd.service systemd-udev-trigger.service systemd-logind.service \
    console-getty.service getty@tty1.service postgresql.service postgresql@15-main.service \
    apt-daily.timer apt-daily-upgrade.timer man-db.timer e2scrub_all.timer \
    e2scrub_reap.service dpkg-db-backup.timer cron.service dbus.service dbus.socket; do
    masks+=("systemd.mask=$u")
done
export container=swpc-vm
exec /lib/systemd/systemd --unit=swpc-robot-install-test.service "${masks[@]}" "${setenv[@]}"
