#!/usr/bin/env bash
# Installs the build into a staging root and checks the systemd integration
# there, as a package would ship it:
#   1. `cmake --install --prefix` puts units, udev rules, tmpfiles.d and
#      sysusers.d under the prefix (prefix-relative paths);
#   2. `DESTDIR=root cmake --install` stages a full root; systemd-sysusers and
#      systemd-tmpfiles apply our files to it (the aggscan user now exists);
#   3. `systemd-analyze verify --root` checks the units, including that the
#      ExecStart binaries exist; any message at all is a failure (unknown keys
#      and bad values are only warnings with exit status 0);
#   4. `systemd-analyze security --offline` keeps the hardening from eroding
#      (each unit at or below the exposure it has now), and the keys that keep
#      a bad config from a restart loop and the units off the network are set;
#   5. the udev rules pass a syntax check;
#   6. a deliberately broken copy of the daemon unit must fail step 3, so this
#      test cannot pass by checking nothing.
#
# Usage: verify_units.sh BUILD_DIR. Needs the binaries built (cmake --build).
# Exit 77 (skip) when systemd-analyze is not installed.
set -uo pipefail

build=${1:?usage: verify_units.sh BUILD_DIR}
fail() { echo "FAIL: $*" >&2; exit 1; }

if ! command -v systemd-analyze >/dev/null 2>&1; then
  echo "SKIP: systemd-analyze not installed (apt-get install systemd)"
  exit 77
fi

work=$(mktemp -d "${TMPDIR:-/tmp}/aggscan-units.XXXXXX")
trap 'rm -rf "$work"' EXIT

# The prefix the build was configured with; the units name binaries under it.
prefix=$(sed -n 's/^CMAKE_INSTALL_PREFIX:PATH=//p' "$build/CMakeCache.txt")
[ -n "$prefix" ] || fail "no CMAKE_INSTALL_PREFIX in $build/CMakeCache.txt"
sbindir=$(sed -n 's/^CMAKE_INSTALL_SBINDIR:PATH=//p' "$build/CMakeCache.txt")
bindir=$(sed -n 's/^CMAKE_INSTALL_BINDIR:PATH=//p' "$build/CMakeCache.txt")

# --- 1. prefix install: everything lands under the prefix ---------------------
if ! cmake --install "$build" --prefix "$work/prefix" >"$work/install1.log" 2>&1; then
  cat "$work/install1.log" >&2
  fail "cmake --install failed; build every target first (cmake --build $build)"
fi
for f in lib/systemd/system/aggscand.service lib/systemd/system/aggscan-worker.service \
         lib/udev/rules.d/70-aggscan.rules lib/tmpfiles.d/aggscan.conf lib/sysusers.d/aggscan.conf; do
  [ -f "$work/prefix/$f" ] || fail "cmake --install --prefix did not install $f"
done
if grep -n '@[A-Za-z_]*@' "$work/prefix/lib/systemd/system/"aggscan*.service; then
  fail "unsubstituted @VARIABLE@ in an installed unit"
fi

# --- 2. staged root, with our user and state directory ------------------------
root="$work/root"
mkdir -p "$root/etc"
if ! DESTDIR="$root" cmake --install "$build" >"$work/install2.log" 2>&1; then
  cat "$work/install2.log" >&2
  fail "DESTDIR install failed"
fi
unitdir="$root$prefix/lib/systemd/system"
daemon_bin="$root$prefix/$sbindir/aggscand"
worker_bin="$root$prefix/$bindir/aggscan-worker"
[ -x "$daemon_bin" ] || fail "aggscand is not installed by this build ($prefix/$sbindir/aggscand): build the aggscand target (daemon/main_aggscand.cpp) before this test"
[ -x "$worker_bin" ] || fail "aggscan-worker is not installed by this build ($prefix/$bindir/aggscan-worker): build the aggscan-worker target (pipeline/worker/main_worker.cpp) before this test"

# The units pull in targets (multi-user, sysinit, ...): give the root the
# host's vendor units, never overwriting ours.
for d in /usr/lib/systemd/system /lib/systemd/system; do
  if [ -d "$d" ]; then
    mkdir -p "$root/lib/systemd/system"
    cp -rn "$d/." "$root/lib/systemd/system/" 2>/dev/null
    break
  fi
done

if command -v systemd-sysusers >/dev/null 2>&1; then
  systemd-sysusers --root="$root" "$root$prefix/lib/sysusers.d/aggscan.conf" >"$work/sysusers.log" 2>&1 ||
    { cat "$work/sysusers.log" >&2; fail "systemd-sysusers rejected sysusers.d/aggscan.conf"; }
  grep -q '^aggscan:' "$root/etc/passwd" || fail "sysusers.d/aggscan.conf did not create user aggscan"
  for g in video dialout plugdev; do
    grep -Eq "^$g:[^:]*:[^:]*:(.*,)?aggscan(,|$)" "$root/etc/group" || fail "aggscan is not in group $g"
  done
fi
# Creating the directory chowns it to aggscan: only root may do that.
if [ "$(id -u)" -eq 0 ] && command -v systemd-tmpfiles >/dev/null 2>&1; then
  systemd-tmpfiles --root="$root" --create "$root$prefix/lib/tmpfiles.d/aggscan.conf" >"$work/tmpfiles.log" 2>&1 ||
    { cat "$work/tmpfiles.log" >&2; fail "systemd-tmpfiles rejected tmpfiles.d/aggscan.conf"; }
  [ "$(stat -c %a "$root/var/lib/aggscan")" = 750 ] || fail "state directory mode is not 0750"
fi

# --- 3. systemd-analyze verify: clean means no output at all ------------------
verify() {  # verify UNIT_FILE...: prints the messages, returns non-zero on any
  local out rc
  out=$(SYSTEMD_LOG_COLOR=0 systemd-analyze verify --man=no --root="$root" "$@" 2>&1)
  rc=$?
  if [ $rc -ne 0 ] || [ -n "$out" ]; then
    printf '%s\n' "$out"
    return 1
  fi
  return 0
}
# With --root, verify looks units up by name in the root's search path, and
# the prefix's unit directory need not be on it (/opt/...): check copies of
# the installed units from the root's /etc/systemd/system, first on the path.
etcdir="$root/etc/systemd/system"
mkdir -p "$etcdir"
cp "$unitdir/aggscand.service" "$unitdir/aggscan-worker.service" "$etcdir/"
echo "systemd-analyze verify --root of ${unitdir#"$root"}/aggscand.service aggscan-worker.service"
if ! verify "$etcdir/aggscand.service" "$etcdir/aggscan-worker.service"; then
  fail "systemd-analyze verify reported problems in the installed units"
fi

# --- 4. hardening does not erode ---------------------------------------------
# Exposure x10 as systemd-analyze scores it (systemd 252): aggscand 1.5,
# the worker 0.3. A change that raises either fails here.
declare -A max_exposure=([aggscand.service]=15 [aggscan-worker.service]=3)
if systemd-analyze security --help 2>/dev/null | grep -q -- '--offline'; then
  for u in aggscand.service aggscan-worker.service; do
    if ! systemd-analyze security --offline=yes --root="$root" --threshold="${max_exposure[$u]}" "$etcdir/$u" >"$work/security.log" 2>&1; then
      cat "$work/security.log" >&2
      fail "$u exposure above ${max_exposure[$u]} (of 100) (systemd-analyze security --offline)"
    fi
    grep 'Overall' "$work/security.log"
  done
fi
# has_key UNIT KEY=VALUE: the unit sets exactly that line.
has_key() { grep -qxF "$2" "$1" || fail "$(basename "$1") lacks $2"; }
# A bad config exits 78 (EX_CONFIG): never restarted in a loop.
has_key "$etcdir/aggscand.service" "RestartPreventExitStatus=78"
has_key "$etcdir/aggscan-worker.service" "RestartPreventExitStatus=2 78"
# The API is loopback-only: no IP traffic beyond it; the worker none at all.
has_key "$etcdir/aggscand.service" "IPAddressDeny=any"
has_key "$etcdir/aggscand.service" "IPAddressAllow=localhost"
has_key "$etcdir/aggscan-worker.service" "IPAddressDeny=any"
has_key "$etcdir/aggscan-worker.service" "PrivateNetwork=yes"
if grep -q '^IPAddressAllow=' "$etcdir/aggscan-worker.service"; then
  fail "aggscan-worker.service allows IP addresses; it needs no network"
fi

# --- 5. udev rules syntax ---------------------------------------------------
rules="$root$prefix/lib/udev/rules.d/70-aggscan.rules"
if udevadm verify --help >/dev/null 2>&1; then
  udevadm verify --no-style "$rules" || fail "udevadm verify rejected 70-aggscan.rules"
else
  # Each rule: comma-separated KEY[{attr}] OP "value" items.
  item='[A-Z_]+(\{[^}]+\})?(==|!=|=|\+=|-=|:=)"[^"]*"'
  n=0
  while IFS= read -r line; do
    n=$((n + 1))
    case "$line" in ''|'#'*) continue ;; esac
    printf '%s\n' "$line" | grep -Eq "^$item(, *$item)*$" || fail "70-aggscan.rules:$n: malformed rule: $line"
  done <"$rules"
  grep -q '^LABEL="aggscan_end"' "$rules" || fail "70-aggscan.rules: GOTO target aggscan_end missing"
fi

# --- 6. the checks above do catch a broken unit -------------------------------
broken="$etcdir/aggscand.service"
sed -e 's/^ProtectSystem=strict/ProtectSystem=strcit/' "$unitdir/aggscand.service" >"$broken"
if verify "$broken" >"$work/broken.log" 2>&1; then
  fail "a unit with ProtectSystem=strcit passed verification: the check is blind"
fi
sed -e "s#^ExecStart=[^ ]*#ExecStart=$prefix/$sbindir/aggscand-missing#" "$unitdir/aggscand.service" >"$broken"
if verify "$broken" >"$work/broken.log" 2>&1; then
  fail "a unit with a missing ExecStart binary passed verification: the check is blind"
fi

# ... and the key check sees a missing one.
sed -e '/^RestartPreventExitStatus=/d' "$unitdir/aggscand.service" >"$broken"
if (has_key "$broken" "RestartPreventExitStatus=78") 2>/dev/null; then
  fail "a unit without RestartPreventExitStatus= passed the key check: the check is blind"
fi

echo "OK: units, udev rules, tmpfiles.d and sysusers.d verified"
