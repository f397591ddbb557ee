#!/bin/sh
# Inside the VM lane (tests/vm/run-in-vm.sh, the camera's kernel test driver
# loaded): runs a camera backend's own test program against that driver, then
# the camera contract suite for the backend against the same driver, in one
# VM boot.
#
#   camera_vm.sh v4l2 DRIVER SPECIFIC_TEST CONTRACT_TEST        (DRIVER: vivid)
#   camera_vm.sh libcamera CAMERA SPECIFIC_TEST CONTRACT_TEST   (CAMERA: vimc, part of libcamera's id)
#
# The specific test goes first: it exits 77 when the driver is absent, and
# then so does this script, without running the contract (which would fail:
# the environment below promises the device). Its last test unplugs and
# replugs the device, so the contract also shows the device is usable after.
#
# Exit status: the first failing program's, 0 when both pass, 77 when the
# specific test found no device.
set -u
[ $# -eq 4 ] || { echo "usage: $0 v4l2|libcamera DRIVER_OR_CAMERA SPECIFIC_TEST CONTRACT_TEST" >&2; exit 2; }
backend=$1 peer=$2 specific_bin=$3 contract_bin=$4
case "$backend" in
  v4l2) export AGGSCAN_V4L2_CONTRACT_DRIVER="$peer" ;;
  libcamera) export AGGSCAN_LIBCAMERA_CONTRACT_CAMERA="$peer" ;;
  *) echo "camera_vm: unknown backend '$backend' (v4l2 or libcamera)" >&2; exit 2 ;;
esac

echo "camera_vm: $backend against $peer: the backend's own tests" >&2
rc=0
"$specific_bin" || rc=$?
[ $rc -ne 77 ] || { echo "camera_vm: SKIP: no $peer device" >&2; exit 77; }
echo "camera_vm: contract suite, backend $backend" >&2
"$contract_bin" --gtest_filter="Backends/CameraContract.*/$backend" || { r=$?; [ $rc -ne 0 ] || rc=$r; }
if [ $rc -ne 0 ]; then
  echo "camera_vm: kernel log (last 20 lines):" >&2
  dmesg 2>/dev/null | tail -n 20 >&2
fi
exit $rc
