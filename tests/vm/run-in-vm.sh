#!/bin/sh
# Runs one command inside a throwaway QEMU VM booted from Debian's installed
# kernel, with kernel test drivers loaded, and returns its exit status and
# output to the host.
#
#   tests/vm/run-in-vm.sh [--modprobe "vivid n_devs=1 node_types=0x1"]... [--modules DIR] [--udev] [--timeout S]
#                         [--smp N] [--drive SPEC] [--pidfile FILE] [--out DIR] -- CMD [ARG]...
#
# --modules DIR: a private module tree from tests/vm/build-test-modules.sh
# (out-of-tree vimc, gpio-sim, irq_sim, raw_gadget beside the installed
# modules); the guest's modprobe then runs as `modprobe -d DIR`.
#
# --udev: start systemd-udevd before the modules load and let it process
# every device (udevadm trigger + settle) before CMD runs; libcamera's device
# enumerator and hotplug need it. Without it the guest has no udev at all.
#
# The guest's root is this machine's / shared read-only over 9p (so CMD, its
# libraries and the build tree are seen at the same paths); a second, writable
# 9p share carries CMD's stdout, stderr and exit status back. A tiny busybox
# initramfs built in a temp dir loads the virtio/9p modules and switches into
# the shared root. TCG only: the nested /dev/kvm here hangs the stock kernel
# (../shared/notes/kernel-test-drivers.md), and a boot takes ~7 s.
#
# --smp N: emulated CPUs (default 2). --drive SPEC: one more QEMU `-drive`
# (a virtual disk, /dev/vda for if=virtio). --pidfile FILE: QEMU writes its
# pid there (a caller can cut the VM off with SIGKILL, like a power cut).
# --out DIR: the writable share is DIR (created if needed, emptied first), not
# a temp dir, so the caller can read what the guest writes there while it runs
# and after the VM is gone; the guest sees it as /tmp/vm-out.
#
# Exit status: CMD's; 77 (skip) when qemu, a Debian kernel with its modules,
# busybox-static or a requested module is missing, or the VM does not boot.
set -eu

modprobes=""
timeout_s=120
moddir_extra=""
udev=0
smp=2
drive=""
pidfile=""
outdir=""
while [ $# -gt 0 ]; do
  case "$1" in
    --modprobe) modprobes="$modprobes$2
"; shift 2 ;;
    --timeout) timeout_s=$2; shift 2 ;;
    --modules) moddir_extra=$2; shift 2 ;;
    --udev) udev=1; shift ;;
    --smp) smp=$2; shift 2 ;;
    --drive) drive=$2; shift 2 ;;
    --pidfile) pidfile=$2; shift 2 ;;
    --out) outdir=$2; shift 2 ;;
    --) shift; break ;;
    *) break ;;
  esac
done
[ $# -gt 0 ] || { echo "usage: $0 [--modprobe 'MOD ARGS']... [--modules DIR] [--udev] [--timeout S] [--smp N] [--drive SPEC] [--pidfile FILE] [--out DIR] -- CMD [ARG]..." >&2; exit 2; }

skip() { echo "run-in-vm: SKIP: $*" >&2; exit 77; }

command -v qemu-system-x86_64 >/dev/null 2>&1 || skip "qemu-system-x86_64 not installed (apt-get install qemu-system-x86)"
busybox=""
for b in /bin/busybox /usr/bin/busybox; do
  if [ -x "$b" ] && ! ldd "$b" >/dev/null 2>&1; then busybox=$b; break; fi  # must be static
done
[ -n "$busybox" ] || skip "no static busybox (apt-get install busybox-static)"
udevd=/lib/systemd/systemd-udevd
[ "$udev" = 0 ] || { [ -x "$udevd" ] && command -v udevadm >/dev/null 2>&1; } || skip "--udev: no $udevd or udevadm (apt-get install udev)"

# The newest installed Debian kernel that has its modules (not the host's
# running kernel, which may be anything in a container).
kver=""
for k in $(ls -1 /boot/vmlinuz-* 2>/dev/null | sed 's#^/boot/vmlinuz-##' | sort -V -r); do
  if [ -r "/boot/vmlinuz-$k" ] && [ -d "/lib/modules/$k/kernel" ]; then kver=$k; break; fi
done
[ -n "$kver" ] || skip "no readable /boot/vmlinuz-* with /lib/modules (apt-get install linux-image-amd64)"
moddir=/lib/modules/$kver

if [ -n "$moddir_extra" ]; then
  moddir_extra=$(cd "$moddir_extra" 2>/dev/null && pwd) || skip "no module tree $moddir_extra (tests/vm/build-test-modules.sh builds it)"
  [ -f "$moddir_extra/lib/modules/$kver/modules.dep" ] ||
    skip "module tree $moddir_extra has no modules for kernel $kver (tests/vm/build-test-modules.sh builds it)"
  case "$moddir_extra/" in
    /tmp/*|/run/*|/var/tmp/*|/root/*)
      echo "run-in-vm: --modules $moddir_extra: the guest mounts fresh tmpfs on /tmp, /run, /var/tmp and /root, so it cannot see it; build the tree elsewhere (the build directory)" >&2; exit 2 ;;
  esac
fi

find_mod() {  # prints the module file for a name, empty if none (maybe built in)
  { find "$moddir/kernel" -name "$1.ko" -o -name "$1.ko.xz" -o -name "$1.ko.zst" -o -name "$1.ko.gz" 2>/dev/null
    [ -z "$moddir_extra" ] || find "$moddir_extra/lib/modules/$kver/extra" -name "$1.ko" 2>/dev/null; } | head -n 1
}
printf '%s' "$modprobes" | while read -r m _; do
  [ -z "$m" ] || [ -n "$(find_mod "$m")" ] || grep -q "/$m.ko" "$moddir/modules.builtin" 2>/dev/null ||
    { echo "run-in-vm: SKIP: module $m not in kernel $kver" >&2; exit 77; }
done || exit 77

work=$(mktemp -d /tmp/aggscan-vm.XXXXXX)
trap 'rm -rf "$work"' EXIT INT TERM
mkdir -p "$work/initrd/bin" "$work/initrd/mods" "$work/initrd/newroot"
if [ -n "$outdir" ]; then
  mkdir -p "$outdir"
  find "$outdir" -mindepth 1 -delete
  ln -s "$(cd "$outdir" && pwd)" "$work/out"
else
  mkdir -p "$work/out"
fi
cp "$busybox" "$work/initrd/bin/busybox"
i=0
for m in virtio_ring virtio virtio_pci_modern_dev virtio_pci_legacy_dev virtio_pci 9pnet 9pnet_virtio netfs fscache 9p; do
  f=$(find_mod "$m")
  [ -n "$f" ] || continue  # built in
  i=$((i + 1))
  dst="$work/initrd/mods/$(printf '%02d' $i)-$m.ko"
  case "$f" in
    *.xz) xz -dc "$f" >"$dst" ;;
    *.zst) zstd -qdc "$f" >"$dst" ;;
    *.gz) gzip -dc "$f" >"$dst" ;;
    *) cp "$f" "$dst" ;;
  esac
done

cat >"$work/initrd/init" <<'INIT'
#!/bin/busybox sh
/bin/busybox mkdir -p /proc /sys /dev
/bin/busybox mount -t proc proc /proc
/bin/busybox mount -t devtmpfs dev /dev
for m in /mods/*.ko; do /bin/busybox insmod "$m" || echo "init: insmod $m failed"; done
o=trans=virtio,version=9p2000.L,msize=262144
/bin/busybox mount -t 9p -o $o,cache=loose,ro hostroot /newroot || { echo "init: no host root"; echo o >/proc/sysrq-trigger; }
/bin/busybox mount -t proc proc /newroot/proc
/bin/busybox mount -t sysfs sys /newroot/sys
/bin/busybox mount -t devtmpfs dev /newroot/dev
for d in run tmp var/tmp root; do /bin/busybox mount -t tmpfs tmpfs /newroot/$d; done
/bin/busybox mkdir -p /newroot/tmp/vm-out
/bin/busybox mount -t 9p -o $o vmout /newroot/tmp/vm-out || { echo "init: no out share"; echo o >/proc/sysrq-trigger; }
exec /bin/busybox switch_root /newroot /bin/sh /tmp/vm-out/guest.sh
INIT
chmod +x "$work/initrd/init"

# Stage 2, in the shared root: load the drivers, run the command, report.
mpopt=""
[ -z "$moddir_extra" ] || mpopt="-d $moddir_extra "
{
  echo '#!/bin/sh'
  echo 'export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin HOME=/root'
  echo 'out=/tmp/vm-out'
  echo 'echo booted >$out/booted'
  [ "$udev" = 0 ] || echo "$udevd --daemon >>\$out/udev.log 2>&1"
  printf '%s' "$modprobes" | while read -r line; do
    [ -n "$line" ] || continue
    echo "modprobe $mpopt$line >>\$out/modprobe.log 2>&1 || { echo 'modprobe $line failed' >\$out/nodriver; echo o >/proc/sysrq-trigger; sleep 10; }"
  done
  [ "$udev" = 0 ] || echo 'udevadm trigger --action=add >>$out/udev.log 2>&1; udevadm settle --timeout=60 >>$out/udev.log 2>&1'
  echo 'grep -qw configfs /proc/filesystems && mount -t configfs none /sys/kernel/config 2>/dev/null'
  echo "cd '$(pwd)'"
  printf 'AGGSCAN_IN_VM=1 '
  for a in "$@"; do printf "'%s' " "$(printf '%s' "$a" | sed "s/'/'\\\\''/g")"; done
  echo '>$out/stdout 2>$out/stderr'
  echo 'echo $? >$out/rc'
  echo 'sync'
  echo 'echo o >/proc/sysrq-trigger'
  echo 'sleep 10'
} >"$work/out/guest.sh"

(cd "$work/initrd" && find . | cpio -o -H newc --quiet | gzip -1) >"$work/initrd.gz"

start=$(date +%s.%N)
set +e
set --  # CMD is in guest.sh already: "$@" now collects extra QEMU arguments
[ -z "$drive" ] || set -- "$@" -drive "$drive"
[ -z "$pidfile" ] || set -- "$@" -pidfile "$pidfile"
timeout "$timeout_s" qemu-system-x86_64 "$@" \
  -machine pc -accel tcg -cpu max -m 2048 -smp "$smp" -bios /usr/share/qemu/qboot.rom \
  -nographic -no-reboot -monitor none -serial "file:$work/console.log" \
  -kernel "/boot/vmlinuz-$kver" -initrd "$work/initrd.gz" \
  -append "console=ttyS0 quiet panic=-1 loglevel=4 no_timer_check" \
  -virtfs local,path=/,mount_tag=hostroot,security_model=none,readonly=on,multidevs=remap \
  -virtfs "local,path=$(cd "$work/out" && pwd -P),mount_tag=vmout,security_model=none,multidevs=remap" \
  </dev/null >"$work/qemu.log" 2>&1
qrc=$?
set -e
end=$(date +%s.%N)
echo "run-in-vm: kernel $kver, VM ran $(echo "$end $start" | awk '{printf "%.1f", $1 - $2}') s (qemu exit $qrc)" >&2

[ -f "$work/out/stdout" ] && cat "$work/out/stdout"
[ -f "$work/out/stderr" ] && cat "$work/out/stderr" >&2
if [ -f "$work/out/rc" ]; then
  exit "$(cat "$work/out/rc")"
fi
if [ ! -f "$work/out/booted" ]; then
  echo "run-in-vm: the VM did not boot (qemu exit $qrc); console and qemu output:" >&2
  tail -n 30 "$work/console.log" "$work/qemu.log" >&2 2>/dev/null || true
  exit 77
fi
if [ -f "$work/out/nodriver" ]; then
  cat "$work/out/nodriver" "$work/out/modprobe.log" >&2 2>/dev/null || true
  exit 77
fi
echo "run-in-vm: the command did not finish within ${timeout_s} s (or the guest crashed); console tail:" >&2
tail -n 30 "$work/console.log" >&2 2>/dev/null || true
exit 1
