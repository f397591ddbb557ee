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
  # fuzzing (scripts/run-fuzzers.sh): clang with libFuzzer's runtime (only
  # recommended by clang, so named here) and llvm-symbolizer for the stacks
  clang-14 libclang-rt-14-dev llvm-14
  # the C++ format, checked by a test (scripts/check-format.sh: this version
  # exactly, since another one formats differently), and clang-tidy (.clang-tidy)
  clang-format-14 clang-tidy-14
  # LLVM's linker: the build links its ~80 programs with it (GNU ld is ~6x slower)
  lld
  # common / config / daemon
  nlohmann-json3-dev libtomlplusplus-dev libcpp-httplib-dev
  # the daemon's HTTP server (cpp-httplib stays for the CLI and the test clients)
  libmicrohttpd-dev
  libsystemd-dev libsqlite3-dev libturbojpeg0-dev libexif-dev
  # a sample's images as one ZIP, streamed to the client (the API)
  libarchive-dev
  # the API's accounts (crypt(3) yescrypt hashes) and the CLI's https:// client
  libcrypt-dev libssl-dev
  # tests only: the TLS test makes a certificate (openssl) and talks to the
  # daemon with an independent TLS client (curl, listed below)
  openssl
  # the operator's console (web/): three.js and Chart.js, copied into the
  # install tree at build time (the rig is offline)
  libjs-three libjs-chart.js
  # tests only: the console's browser tests drive Debian's chromium, headless,
  # over the DevTools protocol (python3-websocket); skipped (77) without it
  # (fonts-dejavu-core: the console's font, named in its stylesheet)
  chromium python3-websocket fonts-dejavu-core
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
  # `aggscan masks train` (scripts/masks/train_masks.py: CPU training, ONNX
  # export, the export checked in OpenCV DNN) and tests/masks/masks_train_test
  # (its training case skips without them)
  python3-torch python3-opencv
  # the Blender frames' denoiser (scripts/blender/denoise.py, inside Blender's
  # Python) and its test tests/validate/denoise_test.py
  python3-numpy
  # tests only: an independent Modbus implementation acting as the turntable
  # controller in the interoperability test (skipped, 77, without it).
  # pymodbus.server imports serial and serial_asyncio, which Debian's
  # python3-pymodbus only recommends (python3-serial comes with
  # python3-serial-asyncio); its other recommend, python3-typer, is for the
  # REPL and is not imported by the server
  python3-pymodbus python3-serial-asyncio python3-serial
  # tests only: the kernel-test-driver VM lane (tests/vm/run-in-vm.sh): QEMU
  # (TCG), Debian's kernel and modules (vivid for the V4L2 camera test; it is
  # booted in the VM, never loaded on this machine), a static busybox and cpio
  # for the initramfs, kmod for modprobe inside the guest. Skipped (77) without.
  qemu-system-x86 linux-image-amd64 busybox-static cpio kmod
  # tests only: loopback (ip) and a udev daemon (libusb hotplug events) inside
  # the VM for the USB turntable test (tests/drivers/usb/tic_vm.sh)
  iproute2 udev
  # tests only: the test drivers Debian's kernel lacks (vimc, gpio-sim,
  # raw_gadget) are built for the VM's kernel from Debian's kernel source
  # (tests/vm/build-test-modules.sh); the headers of that exact kernel are
  # installed below
  linux-source-6.1 bc
  # tests only: the power-cut VM test (tests/store/power_cut_vm.py): an ext4
  # disk image (e2fsprogs: mkfs, e2fsck, debugfs) served by nbdkit, whose
  # cache filter is the disk's volatile write cache
  e2fsprogs nbdkit
  # `aggscan validate --renderer blender` and its test: Blender's Cycles path
  # tracer (CPU, headless) redraws simulated captures as an independent renderer
  blender
  # `aggscan report` (scripts/report/): plots by matplotlib (Pillow reads the
  # photos), the PDF laid out from the same HTML by WeasyPrint; tests only:
  # poppler-utils (pdftotext, pdftoppm) reads the PDFs back
  python3-matplotlib python3-pil weasyprint poppler-utils
  # USB turntable controllers (libusb), start buttons (libgpiod v1, evdev),
  # the libcamera camera backend (and its IPA modules, which vimc needs)
  libusb-1.0-0-dev libgpiod-dev libevdev-dev libcamera-dev libcamera-ipa
  # (udev, listed above, also serves run-in-vm.sh --udev for the libcamera
  # backend's vimc test: libcamera enumerates devices through udev)
)

missing=()
for p in "${PACKAGES[@]}"; do
  dpkg-query -W -f='${Status}' "$p" 2>/dev/null | grep -q "install ok installed" || missing+=("$p")
done

updated=0
if [ "${#missing[@]}" -eq 0 ]; then
  echo "install-deps: all ${#PACKAGES[@]} packages already installed"
else
  echo "install-deps: installing ${missing[*]}"
  $SUDO apt-get update -q
  updated=1
  $SUDO apt-get install -y -q --no-install-recommends "${missing[@]}"
fi

# The headers of the kernel the test VM boots (the newest installed Debian
# kernel with modules), which may differ from linux-headers-amd64's. Where
# Debian no longer has them, the VM tests that need out-of-tree drivers skip.
kver=""
for k in $(ls -1 /boot/vmlinuz-* 2>/dev/null | sed 's#^/boot/vmlinuz-##' | sort -V -r); do
  if [ -d "/lib/modules/$k/kernel" ]; then kver=$k; break; fi
done
if [ -n "$kver" ] && ! dpkg-query -W -f='${Status}' "linux-headers-$kver" 2>/dev/null | grep -q "install ok installed"; then
  [ "$updated" -eq 1 ] || $SUDO apt-get update -q
  $SUDO apt-get install -y -q --no-install-recommends "linux-headers-$kver" ||
    echo "install-deps: linux-headers-$kver is not available; the VM tests with out-of-tree drivers will be skipped" >&2
fi
