#!/usr/bin/env bash
# Installs every build and test dependency of aggscan from Debian 12 packages.
# Idempotent: apt-get skips what is already installed. Run as root (or via sudo).
set -euo pipefail

SUDO=""
if [ "$(id -u)" -ne 0 ]; then SUDO="sudo"; fi
export DEBIAN_FRONTEND=noninteractive

PACKAGES=(
  # toolchain and test tools
  build-essential cmake pkg-config git
  googletest libgtest-dev libgmock-dev libbenchmark-dev
  # common / config / daemon
  nlohmann-json3-dev libtomlplusplus-dev libcpp-httplib-dev
  libsystemd-dev libsqlite3-dev libturbojpeg0-dev
  # convex hulls (minimum-volume box of a mesh)
  libqhull-dev
  # Modbus RTU/TCP turntable controllers (drivers/modbus/)
  libmodbus-dev
  # pipeline (worker only): OpenCV (calib3d, features2d, aruco in contrib,
  # dnn), Eigen, Ceres; COLMAP as a subprocess for the SfM path
  libopencv-core-dev libopencv-imgproc-dev libopencv-imgcodecs-dev
  libopencv-calib3d-dev libopencv-features2d-dev libopencv-contrib-dev
  libopencv-dnn-dev libeigen3-dev libceres-dev colmap
  # systemd-analyze for the unit verification test, curl and python3 for the README demo
  systemd curl python3
  # tests only: writes the small ONNX networks of the mask-network test
  python3-onnx
  # tests only: an independent Modbus implementation acting as the turntable
  # controller in the interoperability test (skipped, 77, without it)
  python3-pymodbus
  # tests only: the kernel-test-driver VM lane (tests/vm/run-in-vm.sh): QEMU
  # (TCG), Debian's kernel and modules (vivid for the V4L2 camera test; it is
  # booted in the VM, never loaded on this machine), a static busybox and cpio
  # for the initramfs, kmod for modprobe inside the guest. Skipped (77) without.
  qemu-system-x86 linux-image-amd64 busybox-static cpio kmod
)

missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done

if [ "${#missing[@]}" -eq 0 ]; then
  echo "install-deps: all ${#PACKAGES[@]} packages already installed"
  exit 0
fi
echo "install-deps: installing ${missing[*]}"
$SUDO apt-get update -q
$SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"
