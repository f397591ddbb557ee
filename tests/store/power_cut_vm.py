#!/usr/bin/env python3
"""Power cuts in the VM lane: aggscand and aggscan-worker inside a QEMU VM
(tests/vm/run-in-vm.sh) write their state dir to a virtual ext4 disk, and the
VM is cut off at random moments of the capture; the next boot checks the disk.

  power_cut_vm.py --build-dir BUILD --work-dir DIR [--trials N] [--seed S]

The disk: a raw image on this machine served by nbdkit with its cache filter
in writeback mode, which QEMU reaches over NBD (virtio-blk in the guest, which
sees a volatile write cache and issues flushes). Writes stay in nbdkit's cache
until the guest flushes; a cut kills nbdkit (the disk) and then QEMU, so
everything the guest wrote but did not flush is lost, as on a disk with a
volatile write cache losing power. (QEMU alone cannot model that: whatever
QEMU writes to an image file sits in this machine's page cache, which
outlives the QEMU process whatever its cache= mode, so a SIGKILL of QEMU
loses only the guest's own page cache; cache=unsafe only skips the flushes
on this machine.) A first boot checks the model itself: a block written with
O_DIRECT and not flushed must be gone after a cut.

What the guest had stored before a cut is known from what aggscand logged:
its stderr goes to a file on the VM's 9p share, written through to this
machine at each write(), and aggscand logs a view's move out of "storing" only
after the image and sidecar are fsynced, and "side N done and queued" only
after the manifest and the record are (a failed enqueue logs its own error). Each boot then, before
aggscand starts: e2fsck (journal replay), mount, power_cut_check files (every
file presented as complete is complete, every view/manifest/captured state
logged before the cut is there, the queue passes integrity_check); then
aggscand and the worker start on the disk, power_cut_check queue (every
captured side and sample has a job), and a driver re-arms an interrupted
sample (it resumes at its first side without a manifest) or arms a new one.
The last boot is not cut: the driver completes every sample, and the disk is
checked once more after a clean stop.

Cut moments rotate through three phases (--phases): during the views (a
random delay after a random stored view), around a manifest (0-150 ms after a
side's last view is stored: manifest, record update, enqueue; the first and
the last side in turn) and during the worker's output (a random delay into a
job).

Exit status: 0 no finding, 1 findings (listed), 77 skip (no qemu, kernel
with virtio_blk/ext4, nbdkit, e2fsprogs or busybox-static; the VM does not
boot).
"""
import argparse
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))
SRC = os.path.dirname(os.path.dirname(HERE))
RUN_IN_VM = os.path.join(SRC, "tests", "vm", "run-in-vm.sh")
PHASES = ("views", "manifest", "worker")


def skip(msg):
    print(f"power_cut_vm: SKIP: {msg}", file=sys.stderr)
    sys.exit(77)


def log(msg):
    print(f"power_cut_vm: {msg}", flush=True)


# ------------------------------------------------------------------ guest --

def api(method, base, path, body=None, timeout=30):
    data = json.dumps(body).encode() if body is not None else None
    req = urllib.request.Request(base + path, data=data, method=method,
                                 headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(req, timeout=timeout) as r:
            return r.status, json.loads(r.read() or b"null")
    except urllib.error.HTTPError as e:
        try:
            return e.code, json.loads(e.read() or b"null")
        except ValueError:
            return e.code, None
    except (urllib.error.URLError, OSError, ValueError):
        return 0, None


def guest_drive(args):
    """Inside the VM: captures samples through the API until cut (mode cut), or
    until every sample is captured and the worker is done (mode final)."""
    base = f"http://127.0.0.1:{args.port}"
    out = open(args.log, "a", buffering=1)

    def say(msg):
        out.write(f"{time.monotonic():.3f} {msg}\n")

    deadline = time.monotonic() + 300
    while api("GET", base, "/api/v1/status")[0] != 200:
        if time.monotonic() > deadline:
            say("FINDING aggscand API never answered")
            return 1
        time.sleep(0.3)
    say("api up")
    refused = set()
    rc = 0
    while True:
        code, samples = api("GET", base, "/api/v1/samples")
        if code != 200 or not isinstance(samples, list):
            say(f"FINDING sample list failed ({code})")
            return 1
        open_ = [s["id"] for s in samples if s.get("state") != "captured" and s["id"] not in refused]
        if open_:
            sid = open_[0]
        elif args.mode == "final":
            break
        else:
            sid = f"rock-{len(samples) + 1:03d}"
        code, body = api("POST", base, "/api/v1/samples", {"id": sid})
        if code != 200:
            state = next((s.get("state") for s in samples if s["id"] == sid), "new")
            say(f"FINDING arm refused {sid} (state {state}, {code}): {json.dumps(body)}")
            refused.add(sid)
            rc = 1
            continue
        say(f"armed {sid} (state before: {next((s.get('state') for s in samples if s['id'] == sid), 'new')})")
        api("POST", base, "/api/v1/button", {})
        t_end = time.monotonic() + 600
        while time.monotonic() < t_end:
            code, st = api("GET", base, "/api/v1/status")
            state = st.get("state") if isinstance(st, dict) else None
            if state == "awaiting_pose":
                api("POST", base, "/api/v1/button", {})
            elif state == "idle":
                say(f"sample {sid} ended idle")
                break
            elif state == "faulted":
                say(f"FINDING {sid} faulted: {json.dumps(st.get('fault', st))[:400]}")
                api("POST", base, "/api/v1/reset", {})
                rc = 1
                break
            time.sleep(0.2)
    # Final boot: every side and sample job reaches an end.
    t_end = time.monotonic() + args.worker_wait
    while time.monotonic() < t_end:
        code, samples = api("GET", base, "/api/v1/samples")
        states = []
        for s in samples if isinstance(samples, list) else []:
            c, d = api("GET", base, "/api/v1/samples/" + s["id"])
            states += [j.get("state") for j in (d or {}).get("jobs", [])]
        if states and all(x in ("done", "failed") for x in states):
            say(f"worker finished: {states.count('done')} jobs done, {states.count('failed')} failed")
            return rc
        time.sleep(2)
    say(f"worker still busy after {args.worker_wait} s: job states {states}")
    return rc


# ------------------------------------------------------------------- host --

STORED = re.compile(r"capture: \[([^\]]+)\] storing -> \S+ on view_stored")
STARTED = re.compile(r"capture: \[([^\]]+)\] side (\d+) started")
SIDE_DONE = re.compile(r"capture: \[([^\]]+)\] side (\d+) done and queued")
CAPTURED = re.compile(r"capture: \[([^\]]+)\] sample captured")
JOB_START = re.compile(r"worker: \[([^\]]+)\] job (\d+): (.*), attempt")


class LogState:
    """What aggscand and the worker reported durable, from their logs."""

    def __init__(self):
        self.side = {}  # sample -> side in progress
        self.count = {}  # (sample, side) -> views stored in this attempt
        self.expect = []
        self.last_event = None  # (kind, time seen)
        self.views = 0
        self.jobs_started = 0

    def feed(self, line, now):
        if m := STARTED.search(line):
            # A side shot again in the same boot: its earlier views were moved
            # to a sideN.interrupted-K directory first.
            key = (m[1], int(m[2]))
            tag = f"view {m[1]} {m[2]} "
            self.expect = [e.replace("view ", "moved ", 1) if e.startswith(tag) else e for e in self.expect]
            self.side[m[1]] = key[1]
            self.count[key] = 0
        elif m := STORED.search(line):
            side = self.side.get(m[1], 0)
            v = self.count.get((m[1], side), 0)
            self.count[(m[1], side)] = v + 1
            self.expect.append(f"view {m[1]} {side} {v}")
            self.views += 1
            self.last_event = ("view", now, m[1], side, v)
        elif m := SIDE_DONE.search(line):
            self.expect.append(f"manifest {m[1]} {m[2]}")
        elif m := CAPTURED.search(line):
            self.expect.append(f"captured {m[1]}")
        elif m := JOB_START.search(line):
            self.jobs_started += 1
            self.last_event = ("job", now, m[1], m[3], 0)


class Tail:
    def __init__(self, path):
        self.path, self.pos, self.buf = path, 0, ""

    def lines(self):
        try:
            with open(self.path, "r", errors="replace") as f:
                f.seek(self.pos)
                data = f.read()
                self.pos = f.tell()
        except FileNotFoundError:
            return []
        self.buf += data
        *done, self.buf = self.buf.split("\n")
        return done


def check_tools():
    for tool in ("qemu-system-x86_64", "nbdkit"):
        if not shutil.which(tool):
            skip(f"{tool} not installed (scripts/install-deps.sh: qemu-system-x86, nbdkit)")
    for tool in ("mkfs.ext4", "e2fsck"):
        if not shutil.which(tool) and not os.path.exists("/sbin/" + tool):
            skip(f"{tool} not installed (apt-get install e2fsprogs)")
    if subprocess.run(["nbdkit", "--filter=cache", "memory", "1M", "--dump-plugin"],
                      capture_output=True).returncode != 0:
        skip("nbdkit has no cache filter or memory plugin")
    kvers = sorted((k[len("vmlinuz-"):] for k in os.listdir("/boot") if k.startswith("vmlinuz-")), reverse=True)
    for k in kvers:
        mods = f"/lib/modules/{k}/kernel"
        if os.path.isdir(mods):
            found = subprocess.run(["find", mods, "-name", "virtio_blk.ko*", "-o", "-name", "ext4.ko*"],
                                   capture_output=True, text=True).stdout.split()
            if len(found) < 2:
                skip(f"kernel {k} has no virtio_blk or ext4 module")
            return
    skip("no Debian kernel with modules (apt-get install linux-image-amd64)")


def write_config(work, args):
    cfg = os.path.join(work, "aggscand.toml")
    with open(cfg, "w") as f:
        f.write(f"""[daemon]
state_dir = "/tmp/disk/state"
listen_port = {args.port}
time_scale = {args.time_scale}
log_level = "debug"

[capture]
profile = "custom"
sides = 2
views_per_side = {args.views}
step_deg = {360.0 / args.views}
interval = "2s"
# Sim-clock deadlines sized for an emulated CPU (TCG renders a still in
# hundreds of ms of real time, = seconds of sim time): a cut, not a timeout,
# is what each trial is about.
home_timeout = "300s"
move_timeout = "120s"
frame_timeout = "120s"
stall_timeout = "60s"

[camera]
width = {args.width}
height = {args.height}
""")
    return cfg


GUEST_SH = """#!/bin/sh
# One boot of a power-cut trial (see power_cut_vm.py).
work=$1 build=$2 mode=$3 port=$4 worker_wait=$5
out=/tmp/vm-out
say() { echo "$(cut -d' ' -f1 /proc/uptime) $*" >>$out/guest.log; }
ip link set lo up
e2fsck -f -p /dev/vda >$out/fsck.log 2>&1; echo $? >$out/fsck.rc
mkdir -p /tmp/disk
# lazytime in the probe boot: the probe's new mtime stays in memory, so no
# journal commit (and its flush) follows the unflushed write.
opts=defaults; [ "$mode" = probe ] && opts=lazytime
mount -t ext4 -o $opts /dev/vda /tmp/disk 2>>$out/fsck.log || { say "mount failed"; exit 3; }
if [ "$mode" = probe ]; then
  # The cache model's own check: a block written to the disk but not flushed
  # must not outlive the cut (the host cuts as soon as it sees out/probe).
  head -c 65536 /dev/zero | tr '\\0' o >/tmp/disk/probe && sync
  head -c 65536 /dev/zero | tr '\\0' n |
    dd of=/tmp/disk/probe bs=65536 count=1 iflag=fullblock oflag=direct conv=notrunc 2>>$out/fsck.log
  cp /sys/block/vda/stat $out/stat.written
  echo written >$out/probe
  # The disk's counters until the cut (field 16: flushes completed): a flush
  # the guest issued after the write would make the probe inconclusive.
  while :; do cp /sys/block/vda/stat $out/stat.last; sleep 0.05; done
fi
mkdir -p /tmp/disk/state
"$build/tests/store/power_cut_check" files /tmp/disk/state "$work/expect.txt" >$out/check_files.log 2>&1
echo $? >$out/check_files.rc
say "checked files"
"$build/daemon/aggscand" --config "$work/aggscand.toml" 2>>$out/daemon.log &
d=$!
nice "$build/pipeline/aggscan-worker" --config "$work/aggscand.toml" --state-dir /tmp/disk/state --poll-ms 200 \\
  2>>$out/worker.log &
w=$!
python3 "$work/power_cut_vm.py" drive --port "$port" --mode "$mode" --log "$out/drive.log" --queue-check \\
  "$build/tests/store/power_cut_check" --queue-out "$out" --worker-wait "$worker_wait"
echo $? >$out/drive.rc
say "drive ended"
kill -TERM $d $w
wait $d; echo $? >$out/daemon.rc
wait $w
"$build/tests/store/power_cut_check" files /tmp/disk/state /dev/null >$out/check_end.log 2>&1
echo $? >$out/check_end.rc
"$build/tests/store/power_cut_check" queue /tmp/disk/state >>$out/check_end.log 2>&1 || echo 1 >$out/check_end.rc
umount /tmp/disk
say "clean end"
"""


def read(path, default=""):
    try:
        with open(path, errors="replace") as f:
            return f.read().strip()
    except FileNotFoundError:
        return default


def start_boot(work, build, disk, out, mode, args):
    """nbdkit serving the disk image with a volatile write-back cache, and the
    VM on it running guest.sh in MODE."""
    sock = os.path.join(work, "nbd.sock")
    if os.path.exists(sock):
        os.unlink(sock)
    nbd = subprocess.Popen(["nbdkit", "-f", "-U", sock, "--filter=cache", "file", disk, "cache=writeback",
                            "cache-min-block-size=4096"], stderr=subprocess.DEVNULL)
    t0 = time.monotonic()
    while not os.path.exists(sock) and time.monotonic() - t0 < 20:
        time.sleep(0.1)
    pidfile = os.path.join(work, "qemu.pid")
    if os.path.exists(pidfile):
        os.unlink(pidfile)
    vm = subprocess.Popen(
        ["nice", "-n", "5", RUN_IN_VM, "--smp", "1", "--modprobe", "virtio_blk", "--modprobe", "crc32c_generic",
         "--modprobe", "ext4", "--drive", f"file=nbd:unix:{sock},format=raw,if=virtio,cache=writeback",
         "--pidfile", pidfile, "--out", out, "--timeout", str(args.boot_timeout),
         "--", os.path.join(work, "guest.sh"), work, build, mode, str(args.port), str(args.worker_wait)],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    return nbd, vm, pidfile


def cut(nbd, pidfile):
    """The power cut: the disk first, with what the guest did not flush
    (nbdkit writes its cache back when its client goes, so QEMU must not go
    first), then QEMU, whose guest has no disk left to write to."""
    nbd.send_signal(signal.SIGKILL)
    try:
        qpid = int(read(pidfile, "0"))
        if qpid > 0:
            os.kill(qpid, signal.SIGKILL)
    except (ProcessLookupError, ValueError):
        pass


def probe_cache_model(work, build, disk, args):
    """One boot that writes a block with O_DIRECT and no flush, cut at once:
    the block must be lost (else the cut does not model a volatile cache)."""
    out = os.path.join(work, "boot-probe")
    nbd, vm, pidfile = start_boot(work, build, disk, out, "probe", args)
    while vm.poll() is None and not os.path.exists(os.path.join(out, "probe")):
        time.sleep(0.02)
    cut(nbd, pidfile)
    vm_out = vm.communicate()[0]
    nbd.wait()
    if not os.path.exists(os.path.join(out, "booted")):
        print(vm_out, file=sys.stderr)
        skip("the VM did not boot")
    if not os.path.exists(os.path.join(out, "probe")):
        return f"probe boot ended without writing its probe: {vm_out.strip()[-600:]}"
    # debugfs reads the image as it lies, so the journal (which holds the
    # probe's inode) is replayed first, as the next boot would.
    e2fsck = shutil.which("e2fsck") or "/sbin/e2fsck"
    subprocess.run([e2fsck, "-f", "-y", disk], capture_output=True)
    debugfs = shutil.which("debugfs") or "/sbin/debugfs"
    data = subprocess.run([debugfs, "-R", "cat /probe", disk], capture_output=True).stdout
    flushes = [read(os.path.join(out, f"stat.{k}"), "").split() for k in ("written", "last")]
    log(f"probe: {data.count(b'n')} unflushed bytes kept of 65536; disk flushes completed when written / "
        f"last seen before the cut: {' / '.join(f[15] if len(f) > 15 else '?' for f in flushes)}")
    flushed_after = len(flushes[0]) > 15 and len(flushes[1]) > 15 and int(flushes[1][15]) > int(flushes[0][15])
    if len(data) == 65536 and data.count(b"o") != 65536 and flushed_after:
        log("cache model probe inconclusive: the guest flushed the disk after the write, before the cut")
        return None
    if len(data) != 65536 or data.count(b"o") != 65536:
        return (f"cache model: after a cut, the probe file holds {data.count(b'n')} unflushed bytes and "
                f"{data.count(b'o')} flushed ones of 65536 (expected only flushed ones)")
    log("cache model: a block written without a flush was lost in the cut, the flushed one kept")
    return None


def host_run(args):
    check_tools()
    build = os.path.abspath(args.build_dir)
    for b in ("daemon/aggscand", "pipeline/aggscan-worker", "tests/store/power_cut_check"):
        if not os.access(os.path.join(build, b), os.X_OK):
            log(f"{b} is not built in {build}")
            return 1
    work = os.path.abspath(args.work_dir)
    for bad in ("/tmp/", "/run/", "/var/tmp/", "/root/"):
        if (work + "/").startswith(bad):
            log(f"--work-dir {work}: the guest mounts fresh tmpfs there and cannot see it")
            return 2
    shutil.rmtree(work, ignore_errors=True)
    os.makedirs(work)
    # The guest runs this file and its shell part from the work dir (its /tmp is its own).
    shutil.copy(os.path.abspath(__file__), os.path.join(work, "power_cut_vm.py"))
    guest = os.path.join(work, "guest.sh")
    with open(guest, "w") as f:
        f.write(GUEST_SH)
    os.chmod(guest, 0o755)
    write_config(work, args)
    disk = os.path.join(work, "disk.img")
    with open(disk, "wb") as f:
        f.truncate(args.disk_mb << 20)
    mkfs = shutil.which("mkfs.ext4") or "/sbin/mkfs.ext4"
    # Inode tables and journal initialised now: no lazy init writes in the guest.
    subprocess.run([mkfs, "-q", "-F", "-E", "lazy_itable_init=0,lazy_journal_init=0", disk], check=True)
    rng = random.Random(args.seed)
    phases = args.phases.split(",")
    if any(p not in PHASES for p in phases):
        log(f"--phases {args.phases}: use a comma list of {', '.join(PHASES)}")
        return 2
    findings, trials, expect, seen_drive = [], [], [], set()
    totals = {"views_checked": 0, "json_checked": 0, "manifests_checked": 0, "png_checked": 0,
              "expected_checked": 0, "temp_seen": 0, "fsck_fixed": 0}
    if problem := probe_cache_model(work, build, disk, args):
        findings.append(problem)
    for boot in range(args.trials + 1):
        final = boot == args.trials
        phase = phases[boot % len(phases)]
        # Manifest cuts alternate between the first side's and the last side's.
        manifest_side = 1 if sum(1 for t in trials if t["phase"] == "manifest") % 2 == 0 else 2
        with open(os.path.join(work, "expect.txt"), "w") as f:
            f.write("\n".join(expect) + ("\n" if expect else ""))
        out = os.path.join(work, f"boot-{boot:02d}")
        nbd, vm, pidfile = start_boot(work, build, disk, out, "final" if final else "cut", args)
        t0 = time.monotonic()
        state = LogState()
        dtail, wtail = Tail(os.path.join(out, "daemon.log")), Tail(os.path.join(out, "worker.log"))
        cut_at, moment = None, None
        # Cut plan for this boot: which event, and how long after it.
        target_view = rng.randrange(0, 2 * args.views)
        delay = {"views": rng.uniform(0.0, 0.6), "manifest": rng.uniform(0.0, 0.15),
                 "worker": rng.uniform(0.0, args.worker_window)}[phase]
        views_this_boot = 0
        while vm.poll() is None:
            now = time.monotonic()
            for line in dtail.lines():
                before = state.views
                state.feed(line, now)
                if state.views > before:
                    views_this_boot += 1
                    _, _, sid, side, v = state.last_event
                    if cut_at is None and not final:
                        if phase == "views" and views_this_boot > target_view:
                            cut_at, moment = now + delay, f"{delay * 1000:.0f} ms after view {v} of {sid} side {side}"
                        elif phase == "manifest" and v == args.views - 1 and side == manifest_side:
                            cut_at = now + delay
                            moment = f"{delay * 1000:.0f} ms after the last view ({v}) of {sid} side {side}"
            for line in wtail.lines():
                state.feed(line, now)
                if (cut_at is None and not final and phase == "worker" and state.last_event
                        and state.last_event[0] == "job"):
                    cut_at = now + delay
                    moment = f"{delay * 1000:.0f} ms into worker job ({state.last_event[3]}) of {state.last_event[2]}"
            if cut_at is not None and now >= cut_at:
                cut(nbd, pidfile)
                break
            time.sleep(0.02)
        vm_out = vm.communicate()[0]
        if nbd.poll() is None:
            if final:
                nbd.terminate()  # a clean end: nbdkit writes its cache back on exit
            else:
                nbd.send_signal(signal.SIGKILL)
        nbd.wait()
        # What the boot found about the previous cut.
        booted = os.path.exists(os.path.join(out, "booted"))
        if boot == 0 and not booted:
            print(vm_out, file=sys.stderr)
            skip("the VM did not boot")
        fsck_rc = read(os.path.join(out, "fsck.rc"), "none")
        chk = read(os.path.join(out, "check_files.log"))
        chk_rc = read(os.path.join(out, "check_files.rc"), "none")
        drive = read(os.path.join(out, "drive.log"))
        qchk = read(os.path.join(out, "check_queue.log"))
        rec = {"boot": boot, "phase": None if final else phase, "cut": moment, "fsck_rc": fsck_rc,
               "check_files_rc": chk_rc, "views_stored_this_boot": views_this_boot,
               "worker_jobs_started": state.jobs_started, "wall_s": round(time.monotonic() - t0, 1)}
        if m := re.search(r"check files: (.*)", chk):
            rec["check"] = m[1]
            kv = dict(x.split("=") for x in m[1].split())
            totals["views_checked"] += int(kv["views"]) + int(kv["orphan_images"])
            totals["json_checked"] += int(kv["json"])
            totals["manifests_checked"] += int(kv["manifests"])
            totals["png_checked"] += int(kv["png"])
            totals["expected_checked"] += int(kv["expected"])
            totals["temp_seen"] += int(kv["temp"])
        rec["resumed"] = len(re.findall(r"armed \S+ \(state before: interrupted\)", drive))
        rec["samples_ended"] = len(re.findall(r"sample \S+ ended idle", drive))
        totals["resumed"] = totals.get("resumed", 0) + rec["resumed"]
        if m := re.search(r"check queue: (.*)", qchk):
            rec["check_queue"] = m[1]
        where = f"boot {boot} (after the cut of boot {boot - 1}: {trials[-1]['cut'] if trials else 'none'})"
        if fsck_rc not in ("0", "1"):
            findings.append(f"{where}: e2fsck exit {fsck_rc}: {read(os.path.join(out, 'fsck.log'))[-600:]}")
        elif fsck_rc == "1":
            totals["fsck_fixed"] += 1
        if chk_rc != "0":
            findings.append(f"{where}: file check exit {chk_rc}:\n    " +
                            "\n    ".join(l for l in chk.splitlines() if l.startswith("problem") or not chk_rc.isdigit())
                            or read(os.path.join(out, 'fsck.log')))
        for l in qchk.splitlines():
            if l.startswith("problem"):
                findings.append(f"{where}: after aggscand's start-up recovery: {l}")
        for l in drive.splitlines():
            text = l.split("FINDING", 1)[1].strip() if "FINDING" in l else None
            if text and text not in seen_drive:  # a stuck sample is refused again in every later boot
                seen_drive.add(text)
                findings.append(f"{where}: {text}")
        if not final and cut_at is None:
            findings.append(f"boot {boot}: no cut happened (the VM ended first: {vm_out.strip()[-400:]})")
        if final:
            end_rc = read(os.path.join(out, "check_end.rc"), "none")
            rec["check_end"] = read(os.path.join(out, "check_end.log"))
            rec["drive_end"] = drive.splitlines()[-1] if drive else ""
            rec["daemon_rc"] = read(os.path.join(out, "daemon.rc"), "none")
            if end_rc != "0":
                findings.append(f"final boot: check after a clean stop exit {end_rc}: {rec['check_end'][-1200:]}")
            if rec["daemon_rc"] != "0":
                findings.append(f"final boot: aggscand exit {rec['daemon_rc']} after SIGTERM")
            if read(os.path.join(out, "drive.rc"), "none") == "none":
                findings.append(f"final boot did not finish: {vm_out.strip()[-600:]}")
        trials.append(rec)
        log(json.dumps(rec))
        expect = state.expect
    by_phase = {p: sum(1 for t in trials if t["phase"] == p) for p in PHASES}
    by_phase["manifest_side2"] = sum(1 for t in trials if t["phase"] == "manifest" and " side 2" in (t["cut"] or ""))
    summary = {"trials": args.trials, "cuts_by_phase": by_phase, "totals": totals, "findings": findings,
               "boots": trials}
    with open(os.path.join(work, "summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    log(f"{args.trials} cuts ({', '.join(f'{k} {v}' for k, v in by_phase.items())}); checked over all boots: "
        + ", ".join(f"{k} {v}" for k, v in totals.items()))
    for f_ in findings:
        log("FINDING " + f_)
    log(f"{len(findings)} finding(s); details in {work}/summary.json and {work}/boot-*/")
    return 1 if findings else 0


def main():
    p = argparse.ArgumentParser()
    sub = p.add_subparsers(dest="cmd")
    d = sub.add_parser("drive")
    d.add_argument("--port", type=int, required=True)
    d.add_argument("--mode", choices=("cut", "final"), required=True)
    d.add_argument("--log", required=True)
    d.add_argument("--queue-check", required=True)
    d.add_argument("--queue-out", required=True)
    d.add_argument("--worker-wait", type=float, default=240)
    p.add_argument("--build-dir")
    p.add_argument("--work-dir")
    p.add_argument("--trials", type=int, default=3)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--phases", default=",".join(PHASES), help="cut phases to rotate through")
    p.add_argument("--views", type=int, default=8, help="views per side (two sides)")
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--time-scale", type=float, default=20.0)
    p.add_argument("--disk-mb", type=int, default=256)
    p.add_argument("--port", type=int, default=8470)
    p.add_argument("--boot-timeout", type=int, default=400)
    p.add_argument("--worker-wait", type=float, default=240, help="the last boot waits this long for the jobs")
    p.add_argument("--worker-window", type=float, default=20.0, help="cut within this many s of a job's start")
    a = p.parse_args()
    if a.cmd == "drive":
        # After aggscand's start-up recovery (its API answers): every captured
        # side and sample must have a job.
        base = f"http://127.0.0.1:{a.port}"
        t_end = time.monotonic() + 300
        while api("GET", base, "/api/v1/status")[0] != 200 and time.monotonic() < t_end:
            time.sleep(0.3)
        with open(os.path.join(a.queue_out, "check_queue.log"), "w") as f:
            subprocess.run([a.queue_check, "queue", "/tmp/disk/state"], stdout=f, stderr=subprocess.STDOUT)
        sys.exit(guest_drive(a))
    if not a.build_dir or not a.work_dir:
        p.error("--build-dir and --work-dir are needed")
    sys.exit(host_run(a))


if __name__ == "__main__":
    main()
