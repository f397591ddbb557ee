#!/usr/bin/python3
"""Benchmark: the daemon with five operator consoles open (Debian's chromium,
headless), in real time on the sim rig at full size (2016x1512).

  bench/console_bench.py [--build-dir build-release] [--consoles 5] [--views 30]

Reports, each measured on the real aggscand:
  - console load: navigation start to the load event, and to the first prompt;
  - idle, nobody watching: daemon CPU (% of one core) and RSS;
  - N consoles on the rig view (live view): stills shot per second for the
    live view, daemon CPU and RSS;
  - one side captured (custom plan, one view every 2 s) with the N consoles
    open: the schedule error of the views (p50 / p99 / max, ms; target p99
    <= 20 ms), view stored -> thumbnail decoded on a page (p50 / p99), and the
    daemon's peak RSS (VmHWM; target <= 60 MB + one frame).
The sim camera renders its frames inside aggscand, so the daemon's CPU here
includes the renderer, which a real camera does not cost.
"""
import argparse
import json
import os
import sys
import tempfile
import time
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(os.path.dirname(HERE), "tests", "web"))
import console_browser_test as cb  # noqa: E402  (the test's rig and browser)


def proc_cpu_s(pid):
    with open("/proc/%d/stat" % pid) as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def proc_mem_mb(pid, key):
    with open("/proc/%d/status" % pid) as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def metric(rig, name):
    text = urllib.request.urlopen(rig.url("/metrics")).read().decode()
    for line in text.splitlines():
        if line.startswith(name + " "):
            return float(line.split()[1])
    return float("nan")


def window(rig, seconds):
    """Daemon CPU % of one core and stills shot per second over `seconds`."""
    pid = rig.daemon.pid
    c0, s0, t0 = proc_cpu_s(pid), metric(rig, "aggscan_preview_stills_total"), time.monotonic()
    time.sleep(seconds)
    c1, s1, t1 = proc_cpu_s(pid), metric(rig, "aggscan_preview_stills_total"), time.monotonic()
    return 100 * (c1 - c0) / (t1 - t0), (s1 - s0) / (t1 - t0)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--build-dir", default="build-release")
    ap.add_argument("--consoles", type=int, default=5)
    ap.add_argument("--views", type=int, default=30)
    args = ap.parse_args()
    binary = cb.find_chromium()
    if binary is None:
        sys.exit("no chromium: apt-get install chromium")
    work = tempfile.mkdtemp(prefix="console-bench-")
    plan = ('\n[capture]\nprofile = "custom"\nsides = 1\nviews_per_side = %d\nstep_deg = 12.0\n'
            'interval = "2s"\n' % args.views)
    rig = cb.Rig(args.build_dir, os.path.join(work, "rig"), "time_scale = 1.0\n" + plan)
    # Full-size frames, as on the rig (the test's rig runs at 640x480, 20x).
    with open(rig.config) as f:
        text = f.read()
    text = text.replace("time_scale = 20\n", "").replace("width = 640\nheight = 480",
                                                          "width = 2016\nheight = 1512")
    with open(rig.config, "w") as f:
        f.write(text)
    rig.start()
    pages = []
    try:
        time.sleep(3)
        cpu, _ = window(rig, 10)
        print("idle, no console: daemon CPU %.1f %%, RSS %.1f MB" %
              (cpu, proc_mem_mb(rig.daemon.pid, "VmRSS")))

        main_page = cb.Browser(binary, work)
        pages.append(main_page)
        t0 = time.monotonic()
        main_page.goto(rig.url())
        cb.wait_for(lambda: main_page.text("prompt") not in (None, "", "…"), 30, "the first prompt",
                    interval_s=0.01)
        first_prompt = (time.monotonic() - t0) * 1000
        cb.wait_for(lambda: main_page.js("document.readyState") == "complete", 30, "load")
        load = main_page.js("performance.getEntriesByType('navigation')[0].loadEventEnd")
        print("console load: load event %.0f ms, first prompt %.0f ms" % (load, first_prompt))
        # The others on browsers of their own, as on separate tablets (a tab
        # in the background would stop its live view, as the console does).
        for _ in range(args.consoles - 1):
            other = cb.Browser(binary, work)
            pages.append(other)
            other.goto(rig.url())
        cb.wait_for(lambda: metric(rig, "aggscan_preview_viewers") >= args.consoles, 60,
                    "%d live views" % args.consoles)
        time.sleep(3)
        cpu, stills = window(rig, 15)
        print("%d consoles watching the live view: %.2f stills/s, daemon CPU %.1f %%, RSS %.1f MB"
              % (args.consoles, stills, cpu, proc_mem_mb(rig.daemon.pid, "VmRSS")))

        sample = "bench-%d" % int(time.time())
        main_page.type_into("#arm-form input[name=id]", sample)
        main_page.click("#arm")
        cb.wait_for(lambda: main_page.text("prompt").startswith("Place the rock"), 30, "armed")
        main_page.click("#start")
        cb.wait_for(lambda: main_page.text("prompt").startswith("Flip the rock") or
                    main_page.text("prompt").startswith("Reconstruct") or
                    main_page.text("prompt") == "Arm a sample to start", args.views * 2 + 120,
                    "the side to end", interval_s=0.5)
        d = json.load(urllib.request.urlopen(rig.url("/api/v1/samples/" + sample)))
        errs = [abs(v["schedule_error_ms"]) for s in d["sides"] for v in s["captured_views"]]
        lat = main_page.js("window.aggscanConsole.thumbnailLatencyMs")
        print("one side with %d consoles open: %d views, schedule error p50 %.1f ms, p99 %.1f ms, "
              "max %.1f ms" % (args.consoles, len(errs), cb.percentile(errs, 50),
                               cb.percentile(errs, 99), max(errs)))
        print("view stored -> thumbnail on the page: p50 %.0f ms, p99 %.0f ms (n=%d)"
              % (cb.percentile(lat, 50), cb.percentile(lat, 99), len(lat)))
        frame_mb = 2016 * 1512 * 3 / 2 ** 20
        print("daemon peak RSS (VmHWM) %.1f MB (budget 60 MB + one %.1f MB frame = %.1f MB)"
              % (proc_mem_mb(rig.daemon.pid, "VmHWM"), frame_mb, 60 + frame_mb))
    finally:
        for p in pages:
            p.close()
        rig.stop()


if __name__ == "__main__":
    main()
