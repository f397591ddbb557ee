#!/bin/sh
# Builds the kernel test drivers that Debian's kernel does not ship, for the
# throwaway VM of tests/vm/run-in-vm.sh, into a private module tree:
#
#   tests/vm/build-test-modules.sh OUTDIR
#
#   vimc       drivers/media/test-drivers/vimc  (libcamera's vimc pipeline)
#   irq_sim    kernel/irq/irq_sim.c             (needed by gpio-sim)
#   gpio-sim   drivers/gpio/gpio-sim.c          (simulated GPIO chip, configfs)
#   raw_gadget drivers/usb/gadget/legacy/raw_gadget.c (full ep0 control)
#
# Sources come from Debian's linux-source-X.Y tarball, built against
# linux-headers-KVER of the kernel the VM boots (the newest /boot/vmlinuz-*
# with modules, as run-in-vm.sh picks it). Result: OUTDIR/lib/modules/KVER
# with extra/*.ko, a `kernel` link to the installed modules and depmod's
# indexes, for `modprobe -d OUTDIR` in the guest (run-in-vm.sh --modules
# OUTDIR). The host's /lib/modules is never touched. A stamp skips the build
# when kernel, source and this script are unchanged.
#
# Exit status 0 built (or up to date); 77 when the kernel, its headers or the
# source package is missing (apt-get install linux-image-amd64
# linux-headers-amd64 linux-source-6.1); 1 when the build fails.
set -eu

[ $# -eq 1 ] || { echo "usage: $0 OUTDIR" >&2; exit 2; }
out=$1
skip() { echo "build-test-modules: SKIP: $*" >&2; exit 77; }

kver=""
for k in $(ls -1 /boot/vmlinuz-* 2>/dev/null | sed 's#^/boot/vmlinuz-##' | sort -V -r); do
  if [ -r "/boot/vmlinuz-$k" ] && [ -d "/lib/modules/$k/kernel" ]; then kver=$k; break; fi
done
[ -n "$kver" ] || skip "no Debian kernel with modules (apt-get install linux-image-amd64)"
kbuild=/lib/modules/$kver/build
[ -f "$kbuild/Makefile" ] || skip "no headers for kernel $kver (apt-get install linux-headers-$kver)"
series=$(echo "$kver" | sed -E 's/^([0-9]+\.[0-9]+).*/\1/')
tarball=""
for t in /usr/src/linux-source-"$series".tar.xz /usr/src/linux-source-"$series".tar.bz2; do
  [ -r "$t" ] && { tarball=$t; break; }
done
[ -n "$tarball" ] || skip "no kernel source for $series (apt-get install linux-source-$series)"
command -v depmod >/dev/null 2>&1 || [ -x /sbin/depmod ] || skip "no depmod (apt-get install kmod)"
PATH=$PATH:/sbin:/usr/sbin

mods=$out/lib/modules/$kver
stamp="$kver $(stat -c '%s %Y' "$tarball") $(cksum <"$0" | cut -d' ' -f1)"
if [ -f "$out/.stamp" ] && [ "$(cat "$out/.stamp")" = "$stamp" ] &&
   [ -f "$mods/extra/vimc.ko" ] && [ -f "$mods/extra/gpio-sim.ko" ]; then
  echo "build-test-modules: up to date in $mods"
  exit 0
fi

rm -rf "$out/src" "$out/lib" "$out/.stamp"
mkdir -p "$out/src" "$mods/extra"
top=linux-source-$series
echo "build-test-modules: extracting from $tarball" >&2
tar -xf "$tarball" -C "$out/src" --strip-components=1 \
  "$top/drivers/media/test-drivers/vimc" "$top/drivers/gpio/gpio-sim.c" "$top/drivers/gpio/gpiolib.h" \
  "$top/kernel/irq/irq_sim.c" "$top/drivers/usb/gadget/legacy/raw_gadget.c"

b=$out/src/build
mkdir -p "$b/vimc"
cp "$out"/src/drivers/media/test-drivers/vimc/*.[ch] "$b/vimc/"
cp "$out/src/drivers/gpio/gpio-sim.c" "$out/src/drivers/gpio/gpiolib.h" "$b/"
cp "$out/src/drivers/usb/gadget/legacy/raw_gadget.c" "$b/"
# irq_sim is built into kernels that select it; as a module it needs a
# licence, and irq_to_desc is not exported to modules: generic_handle_irq
# dispatches the same simple-irq flow through the exported path.
sed -e 's/handle_simple_irq(irq_to_desc(irqnum))/generic_handle_irq(irqnum)/' "$out/src/kernel/irq/irq_sim.c" >"$b/irq_sim.c"
grep -q 'generic_handle_irq(irqnum)' "$b/irq_sim.c" || { echo "build-test-modules: irq_sim.c changed upstream; adapt the patch" >&2; exit 1; }
printf '\n#include <linux/module.h>\nMODULE_LICENSE("GPL");\nMODULE_DESCRIPTION("interrupt simulator (out-of-tree build for the aggscan test VM)");\n' >>"$b/irq_sim.c"
cat >"$b/Kbuild" <<'EOF'
obj-m += irq_sim.o gpio-sim.o raw_gadget.o vimc.o
vimc-y := vimc/vimc-core.o vimc/vimc-common.o vimc/vimc-streamer.o vimc/vimc-capture.o \
          vimc/vimc-debayer.o vimc/vimc-scaler.o vimc/vimc-sensor.o vimc/vimc-lens.o
EOF

echo "build-test-modules: building vimc, irq_sim, gpio-sim, raw_gadget for $kver" >&2
if ! make -s -C "$kbuild" M="$b" -j2 modules >"$out/build.log" 2>&1; then
  tail -n 40 "$out/build.log" >&2
  echo "build-test-modules: the module build failed (full log: $out/build.log)" >&2
  exit 1
fi
cp "$b"/irq_sim.ko "$b"/gpio-sim.ko "$b"/raw_gadget.ko "$b"/vimc.ko "$mods/extra/"
ln -s "/lib/modules/$kver/kernel" "$mods/kernel"
for f in modules.order modules.builtin modules.builtin.modinfo; do
  [ -f "/lib/modules/$kver/$f" ] && cp "/lib/modules/$kver/$f" "$mods/"
done
depmod -b "$out" "$kver"
grep -q '^extra/gpio-sim.ko: extra/irq_sim.ko' "$mods/modules.dep" ||
  { echo "build-test-modules: depmod did not link gpio-sim to irq_sim" >&2; exit 1; }
grep -q '^kernel/.*/videodev.ko' "$mods/modules.dep" ||
  { echo "build-test-modules: depmod did not index the installed modules through $mods/kernel" >&2; exit 1; }
rm -rf "$out/src"
echo "$stamp" >"$out/.stamp"
echo "build-test-modules: built into $mods"
