#!/usr/bin/python3
"""The operator's console in a real browser: Debian's chromium, headless,
driven over the DevTools protocol (a WebSocket, python3-websocket), against
the real aggscand on the sim rig and the real aggscan-worker.

  console_browser_test.py --build-dir BUILD --artifacts DIR [--part open|accounts|all]

open: open the console, arm from the form (with operator, lot and notes),
press START on the screen, watch the view counter advance by events, see the
flip prompt, press START, wait for "Done"; then the samples list, the sample's
3D viewer (not blank, and different after an orbit), its three plots drawn,
its thumbnails, and a download that is the mesh.
accounts: the same console with credentials required: the API refuses a page
without them, a viewer's START is disabled and the API refuses its press, an
operator arms and starts a side.

Screenshots of every view are written to --artifacts. Prints the figures it
measured (console load time, view-to-thumbnail latency). Exit status: 0 pass,
1 a check failed, 77 chromium cannot start here.
"""
import argparse
import base64
import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import zipfile
import urllib.request

try:
    import websocket  # python3-websocket
except ImportError:
    websocket = None


class Failure(Exception):
    pass


def check(cond, what):
    if not cond:
        raise Failure(what)
    print("ok:", what, flush=True)


def wait_for(pred, timeout_s, what, interval_s=0.1):
    until = time.monotonic() + timeout_s
    last = None
    while time.monotonic() < until:
        last = pred()
        if last:
            return last
        time.sleep(interval_s)
    raise Failure("timed out after %.0f s waiting for %s (last: %r)" % (timeout_s, what, last))


# ------------------------------------------------------------ the rig --

class Rig:
    """aggscand on the sim rig and a worker, in a temporary state dir."""

    def __init__(self, build, work, extra_daemon=""):
        self.build = build
        self.work = work
        os.makedirs(work, exist_ok=True)
        self.config = os.path.join(work, "test.toml")
        with open(self.config, "w") as f:
            # The sim rig 20x faster than real time; the paper's plan (2 x 30
            # views) at 640x480.
            f.write('[daemon]\nstate_dir = "%s/state"\nlisten_port = 0\ntime_scale = 20\n'
                    'log_level = "info"\n%s\n[camera]\nwidth = 640\nheight = 480\n\n'
                    '[worker]\nheartbeat_interval = "200ms"\nsilent_after = "60s"\n'
                    % (work, extra_daemon))
        self.procs = []

    def with_board(self):
        """The printed board the operator lays on the disc to calibrate: the
        sim camera draws it (sim.board_image) while the daemon captures it."""
        board = os.path.join(self.work, "board.pgm")
        r = subprocess.run([os.path.join(self.build, "cli", "aggscan"), "calibrate", "board",
                            "--out", board, "--margin-mm", "0"], capture_output=True)
        if r.returncode != 0:
            raise Failure("aggscan calibrate board failed: %s" % r.stderr.decode()[-2000:])
        with open(self.config, "a") as f:
            f.write('\n[sim]\nboard_image = "%s"\n' % board)
        return self

    def start(self):
        port_file = os.path.join(self.work, "port")
        if os.path.exists(port_file):
            os.remove(port_file)
        self.daemon = self._spawn([os.path.join(self.build, "daemon", "aggscand"), "--config",
                                   self.config, "--port", "0", "--port-file", port_file],
                                  "aggscand.log")
        self.port = int(wait_for(lambda: _read(port_file).strip(), 10, "aggscand's port"))
        self.worker = self._spawn([os.path.join(self.build, "pipeline", "aggscan-worker"),
                                   "--state-dir", os.path.join(self.work, "state"), "--config",
                                   self.config, "--poll-ms", "100"], "worker.log")
        return self

    def url(self, path="/"):
        return "http://127.0.0.1:%d%s" % (self.port, path)

    def _spawn(self, argv, log):
        p = subprocess.Popen(argv, stdout=open(os.path.join(self.work, log), "ab"),
                             stderr=subprocess.STDOUT, start_new_session=True)
        self.procs.append(p)
        return p

    def stop(self):
        for p in self.procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in self.procs:
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
        self.procs = []


def _read(path):
    try:
        with open(path) as f:
            return f.read()
    except OSError:
        return ""


# ----------------------------------------------------------- chromium --

def find_chromium():
    for name in (os.environ.get("CHROMIUM", ""), "chromium", "chromium-browser"):
        if name and shutil.which(name):
            return shutil.which(name)
    return None


class Browser:
    """One headless chromium and a DevTools session on its page."""

    def __init__(self, binary, work):
        self.profile = tempfile.mkdtemp(prefix="chromium-", dir=work)
        self.downloads = os.path.join(work, "downloads")
        os.makedirs(self.downloads, exist_ok=True)
        # --no-sandbox: CI runs as root, where chromium refuses its sandbox.
        # WebGL without a GPU: ANGLE on SwiftShader (software).
        self.proc = subprocess.Popen(
            [binary, "--headless", "--no-sandbox", "--no-first-run", "--disable-extensions",
             "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
             "--window-size=1280,800", "--remote-debugging-port=0",
             "--user-data-dir=" + self.profile, "about:blank"],
            stdout=subprocess.DEVNULL, stderr=open(os.path.join(work, "chromium.log"), "ab"),
            start_new_session=True)
        port_file = os.path.join(self.profile, "DevToolsActivePort")
        until = time.monotonic() + 60
        while time.monotonic() < until and not _read(port_file).strip():
            if self.proc.poll() is not None:
                break
            time.sleep(0.1)
        text = _read(port_file).split()
        if not text:
            self.close()
            raise OSError("chromium did not open its DevTools port (see %s/chromium.log)" % work)
        self.port = int(text[0])
        targets = json.load(urllib.request.urlopen("http://127.0.0.1:%d/json/list" % self.port))
        page = next(t for t in targets if t["type"] == "page")
        self.ws = websocket.create_connection(page["webSocketDebuggerUrl"], timeout=120,
                                              suppress_origin=True)
        self.next_id = 0
        self.call("Page.enable")
        self.call("Runtime.enable")
        self.call("Page.setDownloadBehavior", behavior="allow", downloadPath=self.downloads)
        self.errors = []

    def call(self, method, **params):
        self.next_id += 1
        mid = self.next_id
        self.ws.send(json.dumps({"id": mid, "method": method, "params": params}))
        while True:
            msg = json.loads(self.ws.recv())
            if msg.get("method") == "Runtime.exceptionThrown":
                self.errors.append(msg["params"]["exceptionDetails"].get("exception", {})
                                   .get("description", str(msg["params"])))
            if msg.get("id") == mid:
                if "error" in msg:
                    raise Failure("%s: %s" % (method, msg["error"]))
                return msg.get("result", {})

    def js(self, expr, await_promise=False):
        r = self.call("Runtime.evaluate", expression=expr, returnByValue=True,
                      awaitPromise=await_promise)
        if "exceptionDetails" in r:
            raise Failure("page script failed: %s: %s" % (expr[:80], r["exceptionDetails"]))
        return r["result"].get("value")

    def goto(self, url):
        self.call("Page.navigate", url=url)

    def text(self, element_id):
        return self.js("(document.getElementById(%s) || {}).textContent" % json.dumps(element_id))

    def visible(self, element_id):
        return self.js("(() => { const e = document.getElementById(%s); return !!e && "
                       "e.offsetParent !== null; })()" % json.dumps(element_id))

    def enabled(self, element_id):
        return self.js("!document.getElementById(%s).disabled" % json.dumps(element_id))

    def click(self, selector):
        """A real mouse click at the element's centre, as a finger or a mouse would."""
        box = self.js("(() => { const e = document.querySelector(%s); if (!e) return null; "
                      "e.scrollIntoView({block: 'center'}); const r = e.getBoundingClientRect(); "
                      "return [r.left + r.width / 2, r.top + r.height / 2]; })()"
                      % json.dumps(selector))
        if box is None:
            raise Failure("nothing to click at " + selector)
        for kind in ("mousePressed", "mouseReleased"):
            self.call("Input.dispatchMouseEvent", type=kind, x=box[0], y=box[1], button="left",
                      clickCount=1)

    def type_into(self, selector, text):
        self.js("document.querySelector(%s).focus()" % json.dumps(selector))
        self.call("Input.insertText", text=text)

    def screenshot(self, path):
        data = self.call("Page.captureScreenshot", format="png", captureBeyondViewport=True)
        with open(path, "wb") as f:
            f.write(base64.b64decode(data["data"]))
        print("screenshot:", path, flush=True)

    def describe(self):
        """What the page showed, printed when a check fails."""
        print("page at the failure: " + json.dumps({k: self.text(k) for k in (
            "prompt", "subprompt", "action-error", "login-error", "who", "conn")}))
        print("arm form (disabled, id, focus): " + json.dumps(self.js(
            "[document.getElementById('arm').disabled, "
            "document.querySelector('#arm-form input[name=id]').value, "
            "document.activeElement && document.activeElement.outerHTML.slice(0, 60)]")))

    def close(self):
        try:
            self.ws.close()
        except Exception:
            pass
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
        shutil.rmtree(self.profile, ignore_errors=True)


@contextlib.contextmanager
def browsing(rig, binary, work):
    """A browser on `rig`; on a failed check the page's state is printed;
    the browser and the rig are stopped whatever happens."""
    b = None
    try:
        b = Browser(binary, work)
        yield b
    except Failure:
        if b:
            b.describe()
        raise
    finally:
        if b:
            b.close()
        rig.stop()


def percentile(values, p):
    v = sorted(values)
    if not v:
        return float("nan")
    return v[min(len(v) - 1, int(round(p / 100 * (len(v) - 1))))]


# ------------------------------------------------------------ scenarios --

def capture_a_rock(b, rig, sample, art, shots=True):
    """From the rig view: arm from the form, START, flip, START, wait for Done."""
    wait_for(lambda: b.text("prompt") in ("Arm a sample to start", "Calibrated"), 20,
             "the idle prompt")
    b.type_into("#arm-form input[name=id]", sample)
    b.type_into("#arm-form input[name=operator]", "M. Rossi")
    b.type_into("#arm-form input[name=lot]", "lot-7 north face")
    b.type_into("#arm-form textarea[name=notes]", "wet from rain")
    b.click("#arm")
    wait_for(lambda: b.text("prompt").startswith("Place the rock"), 20, "the place-the-rock prompt")
    if shots:
        b.screenshot(os.path.join(art, "rig-armed.png"))
    views_before = b.js("window.aggscanConsole.views")
    b.click("#start")
    # The counter as the page shows it, read often: it must step through the views.
    seen = []
    until = time.monotonic() + 120
    while time.monotonic() < until:
        p = b.text("prompt")
        if p.startswith("Side 1 — view") and (not seen or seen[-1] != p):
            seen.append(p)
        if p.startswith("Flip the rock"):
            break
        time.sleep(0.05)
    check(b.text("prompt") == "Flip the rock, then press START", "the flip prompt after side 1")
    # Read every 50 ms: the last views may go by faster than that.
    numbers = [int(p.split("view ")[1].split(" ")[0]) for p in seen]
    check(len(numbers) >= 5 and numbers == sorted(set(numbers)) and numbers[-1] >= 25,
          "the view counter advanced through %d values, in order, up to %r" % (len(seen), seen[-1:]))
    check(b.js("window.aggscanConsole.views") - views_before == 30,
          "30 view events reached the page during side 1")
    shown = wait_for(lambda: b.js("(() => { const i = [...document.querySelectorAll('#strip img')]; "
                                  "return i.length === 30 && i.every(x => x.complete && x.naturalWidth > 0)"
                                  " ? i[0].naturalWidth : 0; })()"), 10, "side 1's 30 thumbnails")
    check(shown > 0, "side 1's 30 thumbnails shown under the camera (%d px wide)" % shown)
    if shots:
        b.screenshot(os.path.join(art, "rig-flip.png"))
    b.click("#start")
    wait_for(lambda: b.text("prompt").startswith("Side 2"), 30, "side 2 to start")
    wait_for(lambda: b.text("prompt") == "Done", 600, "the reconstruction to be done",
             interval_s=0.5)
    check(sample in b.text("subprompt") and "cm³" in b.text("subprompt"),
          "the done prompt names the sample and its volume: %r" % b.text("subprompt"))
    if shots:
        b.screenshot(os.path.join(art, "rig-done.png"))


def calibrate_the_rig(b, art):
    """The operator's calibrate flow: the board captured by the rig, solved by
    the worker, the new calibration shown."""
    wait_for(lambda: b.text("prompt") == "Arm a sample to start", 20, "the idle prompt")
    check("no rig calibration" in b.text("calibration"),
          "a rig without a calibration says so: %r" % b.text("calibration"))
    b.click("#calibrate")
    wait_for(lambda: b.text("prompt").startswith("Lay the calibration board"), 20,
             "the lay-the-board prompt")
    b.screenshot(os.path.join(art, "rig-calibrate.png"))
    b.click("#start")
    seen = wait_for(lambda: b.text("prompt") if b.text("prompt").startswith("Calibration — view")
                    else None, 60, "the calibration's view counter", interval_s=0.05)
    check(seen.endswith("of 30"), "the board is shot like a side: %r" % seen)
    wait_for(lambda: b.text("prompt") in ("Calibrated", "Calibration failed"), 300,
             "the calibration to be solved", interval_s=0.5)
    check(b.text("prompt") == "Calibrated", "calibrated: %r" % b.text("subprompt"))
    rig_cal = b.text("calibration")
    check(rig_cal.startswith("RMS ") and "made today" in rig_cal,
          "the rig's calibration is the new one: %r" % rig_cal)
    check("done, RMS" in b.text("calibration-capture"),
          "the board capture is listed as solved: %r" % b.text("calibration-capture"))
    b.screenshot(os.path.join(art, "rig-calibrated.png"))
    print("figure: calibration on the console: %s; %s" % (b.text("subprompt"), rig_cal))


def part_open(build, art, work, binary):
    rig = Rig(build, os.path.join(work, "open")).with_board().start()
    with browsing(rig, binary, work) as b:
        t0 = time.monotonic()
        b.goto(rig.url())
        wait_for(lambda: b.text("prompt") not in (None, "", "…"), 20, "the console's first prompt",
                 interval_s=0.01)
        first_prompt_ms = (time.monotonic() - t0) * 1000
        wait_for(lambda: b.js("document.readyState") == "complete", 20, "the page's load")
        load_ms = b.js("(() => { const n = performance.getEntriesByType('navigation')[0]; "
                       "return n.loadEventEnd - n.startTime; })()")
        wait_for(lambda: b.text("conn") == "live", 20, "the event stream to open")
        b.screenshot(os.path.join(art, "rig-idle.png"))
        # The page asks only the rig for anything.
        outside = b.js("performance.getEntriesByType('resource').map(e => e.name)"
                       ".filter(n => !n.startsWith(location.origin))")
        check(outside == [], "every resource comes from the rig itself")

        calibrate_the_rig(b, art)
        # The board is no sample: the list stays empty.
        samples = b.js("fetch('/api/v1/samples').then(r => r.json())", await_promise=True)
        check(samples == [], "the board capture is not listed as a sample: %s" % samples)
        capture_a_rock(b, rig, "rock-b1", art)
        lat = b.js("window.aggscanConsole.thumbnailLatencyMs")
        check(len(lat) >= 60, "%d view thumbnails shown as they were stored" % len(lat))

        # The samples list, searched by lot.
        b.click("button.tab[data-tab=samples]")
        wait_for(lambda: "rock-b1" in (b.text("sample-rows") or ""), 20, "the sample in the list")
        b.type_into("#search", "lot-7")
        wait_for(lambda: "done" in (b.text("sample-rows") or ""), 30, "the sample listed as done")
        b.screenshot(os.path.join(art, "samples.png"))

        # The sample: viewer, figures, plots, thumbnails, downloads.
        b.click("table.samples tbody tr")
        wait_for(lambda: b.js("window.aggscanConsole.sampleShown") == "rock-b1", 60,
                 "the sample page with its mesh")
        meta = b.text("sample-meta")
        check("M. Rossi" in meta and "lot-7 north face" in meta and "wet from rain" in meta,
              "the arm form's operator, lot and notes are kept: %r" % meta)
        px = b.js("window.aggscanConsole.viewerPixels()")
        check(px and px["nonBackground"] > 0.01 * px["width"] * px["height"],
              "the 3D viewer shows the mesh (%s of %d pixels not background)"
              % (px and px["nonBackground"], px and px["width"] * px["height"]))
        b.js("window.aggscanConsole.orbit(0.9)")
        px2 = b.js("window.aggscanConsole.viewerPixels()")
        check(px2["hash"] != px["hash"] and px2["nonBackground"] > 0.01 * px2["width"] * px2["height"],
              "the view changes after an orbit and still shows the mesh")
        check("mm" in b.text("scalebar-label"), "a scale bar in mm: %r" % b.text("scalebar-label"))
        check(b.js("window.aggscanConsole.chartsDrawn") == 3, "three plots made")
        drawn = b.js("""[...document.querySelectorAll('.charts canvas')].map(c => {
              const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
              let n = 0; for (let i = 3; i < d.length; i += 4) if (d[i] > 0) n++; return n; })""")
        check(len(drawn) == 3 and all(n > 500 for n in drawn), "every plot drew (%s pixels)" % drawn)
        figures = b.text("figures")
        check("cm³" in figures and "Sphericity" in figures, "the figures table has units")
        outlined = wait_for(lambda: b.js("""(() => { const cs = [...document.querySelectorAll('#views canvas')];
              let n = 0; for (const c of cs) { if (!c.width) continue;
                const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;
                for (let i = 0; i < d.length; i += 4) if (d[i] === 255 && d[i+1] === 0 && d[i+2] === 255) { n++; break; } }
              return n >= 60 ? n : 0; })()"""), 60, "every view's thumbnail with its mask outline")
        check(outlined >= 60, "%d thumbnails drawn with their mask outline" % outlined)
        b.screenshot(os.path.join(art, "sample.png"))
        for f in os.listdir(b.downloads):
            os.remove(os.path.join(b.downloads, f))
        b.click("#downloads a[href$='mesh.ply']")
        path = os.path.join(b.downloads, "rock-b1_mesh.ply")
        wait_for(lambda: os.path.exists(path) and _read_bytes(path)[:4] == b"ply\n", 30,
                 "the PLY download")
        head = _read_bytes(path)[:400].decode("latin-1")
        check("element vertex" in head and "element face" in head,
              "the download is the mesh (%d bytes)" % os.path.getsize(path))
        b.click("#downloads a[href$='report.pdf']")
        path = os.path.join(b.downloads, "rock-b1-report.pdf")
        wait_for(lambda: os.path.exists(path) and _read_bytes(path)[:5] == b"%PDF-", 120,
                 "the rock's report (PDF) download")
        check(os.path.getsize(path) > 20000,
              "the report is a whole document (%d bytes)" % os.path.getsize(path))
        b.click("#downloads a[href$='images.zip']")
        path = os.path.join(b.downloads, "rock-b1_images.zip")
        wait_for(lambda: os.path.exists(path) and zipfile.is_zipfile(path), 60,
                 "the images archive download")
        with zipfile.ZipFile(path) as z:
            names = z.namelist()
            bad = z.testzip()
            first = z.read("side1/view_000.jpg")
        jpgs = [n for n in names if n.endswith(".jpg")]
        masks = [n for n in names if n.startswith("results/masks/") and n.endswith(".png")]
        check(bad is None and len(jpgs) == 60 and len(masks) == 60 and "sample.json" in names
              and first[:3] == b"\xff\xd8\xff",
              "the images archive holds 60 views and their masks (%d members, %d bytes)"
              % (len(names), os.path.getsize(path)))
        # A phone: one column, nothing wider than the screen, START still large.
        b.call("Emulation.setDeviceMetricsOverride", width=390, height=844, deviceScaleFactor=2,
               mobile=True)
        for tab in ("rig", "sample"):
            b.click("button.tab[data-tab=%s]" % tab)
            time.sleep(0.5)
            width = b.js("document.documentElement.scrollWidth")
            if width > 390:
                print("wider than the screen: " + json.dumps(b.js(
                    "[...document.querySelectorAll('body *')].filter(e => e.offsetParent !== null && "
                    "e.getBoundingClientRect().right > 391).slice(0, 8).map(e => "
                    "e.tagName + '#' + e.id + '.' + e.className + ' ' + "
                    "Math.round(e.getBoundingClientRect().right))")))
            check(width <= 390, "the %s view fits a 390 px phone (%s px wide)" % (tab, width))
            b.screenshot(os.path.join(art, "phone-%s.png" % tab))
            if tab == "rig":
                start = b.js("(() => { const r = document.getElementById('start')"
                             ".getBoundingClientRect(); return [r.width, r.height]; })()")
                check(start[0] >= 48 and start[1] >= 48,
                      "START is a large touch target on a phone (%s)" % start)
        b.call("Emulation.clearDeviceMetricsOverride")
        check(b.errors == [], "no script error on the page: %s" % b.errors)
        print("figure: console first prompt %.0f ms, load event %.0f ms" % (first_prompt_ms, load_ms))
        print("figure: view stored -> thumbnail on the page: p50 %.0f ms, p99 %.0f ms (n=%d)"
              % (percentile(lat, 50), percentile(lat, 99), len(lat)))


def part_accounts(build, art, work, binary):
    root = os.path.join(work, "accounts")
    os.makedirs(root, exist_ok=True)
    accounts = os.path.join(root, "accounts")
    aggscan = os.path.join(build, "cli", "aggscan")
    for user, role, pw in (("ana", "operator", "operator-pass-1"), ("vic", "viewer", "viewer-pass-1")):
        subprocess.run([aggscan, "user", "add", user, "--role", role, "--file", accounts],
                       input=(pw + "\n").encode(), check=True, capture_output=True)
    rig = Rig(build, root, 'credentials_file = "%s"' % accounts).start()
    with browsing(rig, binary, work) as b:
        b.goto(rig.url())
        wait_for(lambda: b.visible("login"), 20, "the log-in form")
        status = b.js("fetch('/api/v1/status').then(r => r.status)", await_promise=True)
        check(status == 401, "the API refuses the page without credentials (%s)" % status)
        b.screenshot(os.path.join(art, "login.png"))

        def login(user, pw):
            b.type_into("#login-form input[name=user]", user)
            b.type_into("#login-form input[name=password]", pw)
            b.click("#login-form button[type=submit]")

        login("vic", "wrong-password")
        wait_for(lambda: b.text("login-error"), 20, "a refused log-in")
        b.js("document.querySelector('#login-form').reset()")
        login("vic", "viewer-pass-1")
        wait_for(lambda: b.visible("prompt") and b.text("conn") == "live", 20, "the viewer's console")
        check("vic (viewer)" in b.text("who"), "logged in as the viewer")
        check(not b.enabled("arm") and not b.enabled("start") and not b.enabled("calibrate"),
              "a viewer's ARM, START and CALIBRATE are disabled")
        code = b.js("""fetch('/api/v1/samples', {method: 'POST', headers: {'Content-Type': 'application/json',
              Authorization: 'Bearer ' + sessionStorage.getItem('aggscan.token')},
              body: JSON.stringify({id: 'by-viewer'})}).then(r => r.status)""", await_promise=True)
        check(code == 403, "the API refuses a viewer's arm (%s)" % code)
        code = b.js("""fetch('/api/v1/calibration', {method: 'POST', headers: {'Content-Type': 'application/json',
              Authorization: 'Bearer ' + sessionStorage.getItem('aggscan.token')},
              body: '{}'}).then(r => r.status)""", await_promise=True)
        check(code == 403, "the API refuses a viewer's calibration (%s)" % code)
        b.screenshot(os.path.join(art, "rig-viewer.png"))
        b.click("#logout")
        wait_for(lambda: b.visible("login"), 20, "the log-in form after logging out")

        login("ana", "operator-pass-1")
        wait_for(lambda: "ana (operator)" in b.text("who") and b.visible("prompt") and
                 b.enabled("arm"), 20, "the operator's console")
        b.type_into("#arm-form input[name=id]", "rock-op")
        b.click("#arm")
        wait_for(lambda: b.text("prompt").startswith("Place the rock"), 20, "armed by the operator")
        b.click("#start")
        wait_for(lambda: b.text("prompt").startswith("Side 1 — view"), 30, "the operator's side running")
        b.screenshot(os.path.join(art, "rig-operator.png"))
        b.click("#abort")
        wait_for(lambda: b.text("prompt") == "Arm a sample to start", 30, "the abort")
        check(b.errors == [], "no script error on the page: %s" % b.errors)


def _read_bytes(path):
    try:
        with open(path, "rb") as f:
            return f.read()
    except OSError:
        return b""


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--build-dir", required=True)
    ap.add_argument("--artifacts", required=True)
    ap.add_argument("--part", choices=("open", "accounts", "all"), default="all")
    args = ap.parse_args()
    binary = find_chromium()
    if binary is None:
        print("SKIP: no chromium here (apt-get install chromium; scripts/install-deps.sh does)")
        return 77
    if websocket is None:
        print("FAIL: python3-websocket is missing (scripts/install-deps.sh installs it)")
        return 1
    os.makedirs(args.artifacts, exist_ok=True)
    work = tempfile.mkdtemp(prefix="console-browser-")
    # Chromium starts, or the test skips: nothing else may skip it.
    try:
        Browser(binary, work).close()
    except (OSError, StopIteration, websocket.WebSocketException) as e:
        print("SKIP: chromium cannot start here: %s" % e)
        return 77
    try:
        if args.part in ("open", "all"):
            part_open(args.build_dir, args.artifacts, work, binary)
        if args.part in ("accounts", "all"):
            part_accounts(args.build_dir, args.artifacts, work, binary)
    except Failure as e:
        print("FAIL:", e)
        for log in ("open/aggscand.log", "open/worker.log", "accounts/aggscand.log", "chromium.log"):
            text = _read(os.path.join(work, log))
            if text:
                print("---- %s (last 40 lines)\n%s" % (log, "\n".join(text.splitlines()[-40:])))
        return 1
    shutil.rmtree(work, ignore_errors=True)
    print("console browser test: every check passed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
