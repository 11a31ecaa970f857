#!/usr/bin/env bash
# Idempotent set-up for `make test-vcan` (see deploy/README.md, "Real SocketCAN in a VM").
#
#   1. Debian packages: qemu-system-x86 kmod can-utils iproute2 busybox-static udev
#      (apt-get update only when one of them is missing).
#   2. The Debian kernel that linux-image-amd64 depends on: `apt-get download`, then
#      `dpkg-deb -x` into the cache (never installed into the host's /boot), module tree
#      trimmed to what the VM needs, decompressed, `depmod -b`.
#   3. virtme-ng (pinned) in the project venv.
#   4. A matplotlib font cache for the VM.
#   5. The C controller emulator (make ctrl-emu), for the VM's deadman step.
#
# Everything is cached under $SWPC_VM_CACHE (default .cache/vm/); a second run only checks.
# Prints, on the last line, the path of a file with the kernel variables for run-in-vm.sh.
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/../.." && pwd)"
CACHE="${SWPC_VM_CACHE:-$ROOT/.cache/vm}"
VENV="${SWPC_VENV:-$ROOT/.venv}"
VIRTME_NG_VERSION="1.42"
PACKAGES=(qemu-system-x86 kmod can-utils iproute2 busybox-static udev)

log() { printf '[vm-setup] %s\n' "$*" >&2; }
die() { printf '[vm-setup] error: %s\n' "$*" >&2; exit 1; }

mkdir -p "$CACHE"

# --- 1. Debian packages -------------------------------------------------------------------
missing=()
for p in "${PACKAGES[@]}"; do
    if ! dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q 'install ok installed'; then
        missing+=("$p")
    fi
done
if ((${#missing[@]})); then
    [[ $(id -u) -eq 0 ]] || die "missing packages (${missing[*]}): run as root or install them"
    log "installing ${missing[*]}"
    export DEBIAN_FRONTEND=noninteractive
    apt-get update -q >&2
    apt-get install -y -q --no-install-recommends "${missing[@]}" >&2
else
    log "packages present: ${PACKAGES[*]}"
fi

# --- 2. Kernel: fetch, unpack, trim, decompress, depmod --------------------------------------
# Modules the VM needs (their dependencies are added from the full tree): SocketCAN and vcan;
# what virtme-ng loads to reach the host filesystem (9p over virtio, overlay, fuse/virtiofs),
# the virtio console and the PCI/MMIO transports; kvaser_pci (SJA1000) for the two CAN
# controllers QEMU emulates on one CAN bus, on which deploy/can-up.sh is tested.
MODULES=(vcan can_raw can_bcm can_gw can_dev kvaser_pci 9p 9pnet_virtio virtio_pci
         virtio_mmio virtio_console overlay fuse virtiofs)
KDIR="$CACHE/kernel"              # trimmed tree: boot/vmlinux-<ver>, lib/modules/<ver>/
STAMP="$KDIR/.ready"
ENVFILE="$CACHE/kernel.env"

kpkg="$(apt-cache depends linux-image-amd64 2>/dev/null \
        | awk '/Depends: linux-image-[0-9]/{print $2; exit}')"
if [[ -z "$kpkg" ]]; then
    apt-get update -q >&2
    kpkg="$(apt-cache depends linux-image-amd64 | awk '/Depends: linux-image-[0-9]/{print $2; exit}')"
fi
[[ -n "$kpkg" ]] || die "apt-cache depends linux-image-amd64 names no kernel package"
kver="${kpkg#linux-image-}"
kver="${kver%-unsigned}"
stamp_text="$kver ${MODULES[*]}"

if [[ -f "$STAMP" && "$(cat "$STAMP")" == "$stamp_text" ]]; then
    log "kernel $kver cached in $KDIR"
else
    log "preparing kernel $kver"
    debdir="$CACHE/debs"
    full="$CACHE/full-$kver"
    mkdir -p "$debdir"
    if ! ls "$debdir/${kpkg}_"*.deb >/dev/null 2>&1; then
        # (apt warns that root downloads unsandboxed into a folder _apt cannot read: harmless)
        (cd "$debdir" && apt-get download -q "$kpkg" 2>&1 | grep -v '^W: Download is performed unsandboxed' >&2)
    fi
    deb="$(ls "$debdir/${kpkg}_"*.deb | head -n1)"
    rm -rf "$full" && mkdir -p "$full"
    dpkg-deb -x "$deb" "$full"
    fullmods="$full/lib/modules/$kver"
    [[ -d "$fullmods" ]] || die "no lib/modules/$kver in $deb"
    depmod -b "$full" "$kver"

    rm -rf "$KDIR" && mkdir -p "$KDIR/boot" "$KDIR/lib/modules/$kver"
    # Trimmed module tree: the closure of MODULES, as plain (uncompressed) .ko files.
    for m in "${MODULES[@]}"; do
        modprobe -d "$full" -S "$kver" --show-depends "$m" \
            | awk '$1 == "insmod" {print $2}'
    done | sort -u | while read -r ko; do
        rel="${ko#"$fullmods"/}"
        mkdir -p "$KDIR/lib/modules/$kver/$(dirname "$rel")"
        case "$ko" in
            *.ko.xz) xz -dc "$ko" > "$KDIR/lib/modules/$kver/${rel%.xz}" ;;
            *.ko.zst) zstd -qdc "$ko" > "$KDIR/lib/modules/$kver/${rel%.zst}" ;;
            *.ko.gz) gzip -dc "$ko" > "$KDIR/lib/modules/$kver/${rel%.gz}" ;;
            *) cp "$ko" "$KDIR/lib/modules/$kver/$rel" ;;
        esac
    done
    cp "$fullmods"/modules.builtin "$fullmods"/modules.builtin.modinfo "$KDIR/lib/modules/$kver/"
    (cd "$KDIR/lib/modules/$kver" && grep -xFf <(find kernel -name '*.ko' | sort) \
        "$fullmods/modules.order" > modules.order || true)
    depmod -b "$KDIR" "$kver"
    cp "$full/boot/config-$kver" "$KDIR/boot/"

    # Uncompressed kernel: the ELF vmlinux inside the bzImage (QEMU boots it through its
    # PVH entry point, CONFIG_PVH=y), which saves the in-guest decompression under TCG.
    "$VENV/bin/python" - "$full/boot/vmlinuz-$kver" "$KDIR/boot/vmlinux-$kver" <<'PY'
import lzma, sys, zlib
src, dst = sys.argv[1], sys.argv[2]
data = open(src, "rb").read()
for magic, make in ((b"\xfd7zXZ\x00", lambda: lzma.LZMADecompressor(lzma.FORMAT_XZ)),
                    (b"\x1f\x8b\x08", lambda: zlib.decompressobj(31))):
    pos = data.find(magic)
    while pos >= 0:
        try:
            out = make().decompress(data[pos:])
        except (lzma.LZMAError, zlib.error):
            out = b""
        if out[:4] == b"\x7fELF":
            open(dst, "wb").write(out)
            sys.exit(0)
        pos = data.find(magic, pos + 1)
sys.exit(f"no ELF vmlinux found inside {src}")
PY
    nmods=$(find "$KDIR/lib/modules/$kver" -name '*.ko' | wc -l)
    log "kernel $kver: $nmods modules, $(du -sh "$KDIR" | cut -f1) (full tree: $(du -sh "$full" | cut -f1))"
    rm -rf "$full"          # the .deb stays in $debdir; the trimmed tree is all we boot
    echo "$stamp_text" > "$STAMP"
fi

# --- 3. virtme-ng, pinned, in the project venv ----------------------------------------------
if [[ "$("$VENV/bin/python" -c 'import importlib.metadata as m; print(m.version("virtme-ng"))' \
        2>/dev/null)" != "$VIRTME_NG_VERSION" ]]; then
    log "installing virtme-ng==$VIRTME_NG_VERSION into $VENV"
    "$VENV/bin/python" -m pip install -q "virtme-ng==$VIRTME_NG_VERSION" >&2
else
    log "virtme-ng $VIRTME_NG_VERSION present"
fi

# --- 4. matplotlib font cache (cantools' CLI imports matplotlib; building the cache inside
#        the VM scans every font over 9p and takes ~30 s under TCG) -------------------------
if ! ls "$CACHE/mpl"/fontlist-*.json >/dev/null 2>&1; then
    MPLCONFIGDIR="$CACHE/mpl" "$VENV/bin/python" -c 'import matplotlib.font_manager' >&2
fi

# --- 5. the module controllers emulated in C (build/swpc-ctrl-emu; the deadman step runs
#        them in the VM as the controllers' firmware: Python there is ~50x slower) --------
if make -s -C "$ROOT" ctrl-emu >&2; then
    log "controller emulator: build/swpc-ctrl-emu"
else
    log "warning: make ctrl-emu failed (a C compiler is needed): the deadman step will fail"
fi

cat > "$ENVFILE" <<ENV
SWPC_VM_KVER=$kver
SWPC_VM_KIMG=$KDIR/boot/vmlinux-$kver
SWPC_VM_MPLCONFIGDIR=$CACHE/mpl
ENV
echo "$ENVFILE"
