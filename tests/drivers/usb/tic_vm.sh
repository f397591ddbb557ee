#!/bin/sh
# Inside the VM lane (tests/vm/run-in-vm.sh, with dummy_hcd, libcomposite and
# usb_f_fs loaded): builds a configfs USB gadget that looks like a Pololu Tic
# T834 (VID:PID 1ffb:00b5, serial 00123456) with one FunctionFS function served
# by tic_gadget, binds it to dummy_hcd's UDC, waits for the host side to
# enumerate it, then runs the given test programs against it (the environment
# tells them where it is).
#
#   tic_vm.sh TIC_GADGET TURNTABLE_CONTRACT_TEST USB_TIC_VM_TEST
#
# Exit status: the first failing test's, 0 when both pass, 77 when the gadget
# cannot be set up (no configfs, no UDC).
set -u
[ $# -eq 3 ] || { echo "usage: $0 TIC_GADGET TURNTABLE_CONTRACT_TEST USB_TIC_VM_TEST" >&2; exit 2; }
gadget_bin=$1 contract_bin=$2 vm_test_bin=$3
skip() { echo "tic_vm: SKIP: $*" >&2; exit 77; }

cfg=/sys/kernel/config/usb_gadget
[ -d "$cfg" ] || skip "no $cfg (configfs or libcomposite missing)"
udc=""
for u in /sys/class/udc/*; do [ -e "$u" ] && udc=${u##*/}; done
[ -n "$udc" ] || skip "no UDC (dummy_hcd not loaded)"

serial=00123456
g=$cfg/tic
mkdir $g $g/strings/0x409 $g/configs/c.1 $g/configs/c.1/strings/0x409 $g/functions/ffs.tic /tmp/ffs ||
  skip "cannot create the gadget in configfs"
echo 0x1ffb >$g/idVendor
echo 0x00b5 >$g/idProduct
echo 0x0100 >$g/bcdDevice
echo Pololu >$g/strings/0x409/manufacturer
echo "Tic T834 (aggscan test gadget)" >$g/strings/0x409/product
echo $serial >$g/strings/0x409/serialnumber
echo "Tic native" >$g/configs/c.1/strings/0x409/configuration
echo 100 >$g/configs/c.1/MaxPower
ln -s $g/functions/ffs.tic $g/configs/c.1/ || skip "cannot link the function"
mount -t functionfs tic /tmp/ffs || skip "cannot mount functionfs"

glog=/tmp/tic-gadget.log
"$gadget_bin" --ffs /tmp/ffs --ready /tmp/tic-ready --steps-per-rev 1600 --start-at 400 2>"$glog" &
gpid=$!
n=0
while [ ! -e /tmp/tic-ready ]; do
  n=$((n + 1))
  [ $n -lt 200 ] || { echo "tic_vm: the gadget did not start" >&2; kill $gpid; exit 1; }
  kill -0 $gpid 2>/dev/null || { echo "tic_vm: the gadget exited" >&2; cat "$glog" >&2; exit 1; }
  sleep 0.05
done
echo "$udc" >$g/UDC || { echo "tic_vm: cannot bind the gadget to $udc" >&2; kill $gpid; exit 1; }

# The host side: wait for 1ffb:00b5 in sysfs.
n=0
found=""
while [ -z "$found" ]; do
  for f in /sys/bus/usb/devices/*/idVendor; do
    [ -e "$f" ] || continue
    read -r v <"$f"
    [ "$v" = 1ffb ] && found=${f%/idVendor}
  done
  [ -n "$found" ] && break
  n=$((n + 1))
  [ $n -lt 200 ] || { echo "tic_vm: the host did not enumerate the gadget" >&2; kill $gpid; exit 1; }
  sleep 0.05
done
echo "tic_vm: gadget bound to $udc, host sees $found" >&2

export AGGSCAN_TIC_SERIAL=$serial AGGSCAN_TIC_UDC_FILE=$g/UDC AGGSCAN_TIC_UDC=$udc AGGSCAN_TIC_GADGET_PID=$gpid
rc=0
echo "tic_vm: contract suite, backend usb_tic" >&2
"$contract_bin" --gtest_filter='Backends/TurntableContract.*/usb_tic' || rc=$?
kill -0 $gpid 2>/dev/null || echo "tic_vm: the gadget program is gone after the contract suite" >&2
# A udev daemon, as on a real system, so libusb's hotplug events flow (the
# backend copes without one: it then learns of an unplug from a failing
# transfer). Started only now: its start-up work would compete with the
# contract suite's timing on the emulated CPU.
if [ -x /lib/systemd/systemd-udevd ] && /lib/systemd/systemd-udevd --daemon 2>/dev/null; then
  export AGGSCAN_TIC_UDEVD=1
fi
# Loopback for aggscand's HTTP API (the guest configures no network).
ip link set lo up 2>/dev/null || ifconfig lo 127.0.0.1 up 2>/dev/null || true
echo "tic_vm: hotplug, error classification, daemon health" >&2
"$vm_test_bin" || { r=$?; [ $rc -ne 0 ] || rc=$r; }
if [ $rc -ne 0 ]; then
  # What the emulated Tic and the kernel saw, last, so a CI log's tail has it.
  kill -0 $gpid 2>/dev/null || echo "tic_vm: the gadget program had ended" >&2
  echo "tic_vm: the gadget's log (last 40 lines):" >&2
  tail -n 40 "$glog" >&2
  echo "tic_vm: kernel log (last 40 lines):" >&2
  dmesg 2>/dev/null | tail -n 40 >&2
fi
kill $gpid 2>/dev/null
exit $rc
