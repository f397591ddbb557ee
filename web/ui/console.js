// The operator's console: everything comes from the rig's API (see
// /api/v1/openapi.json); the page follows GET /api/v1/events and never polls.
// Libraries: three.js (3D viewer), Chart.js (plots), both from Debian.
'use strict';

(function () {
  const $ = (id) => document.getElementById(id);

  const ui = {
    token: sessionStorage.getItem('aggscan.token'),
    who: null,          // GET /api/v1/session
    status: null,       // GET /api/v1/status, then kept current by events
    devices: {},        // name -> {healthy, state, message}
    worker: null,       // the worker's report
    lastSample: null,   // the sample the rig captured last (for "Reconstructing", "Done")
    lastResult: null,   // that sample's GET /api/v1/samples/{id} once reconstructed
    events: null,       // the EventSource
    samples: [],
    sampleId: null,
    viewer: null,
    charts: [],
    stripSide: null,    // sample/side whose thumbnails the strip shows
  };

  // Figures a browser test and the console benchmark read (never used by the page itself).
  const probe = {
    events: 0,
    views: 0,
    thumbnailLatencyMs: [],  // view stored (daemon clock) -> its thumbnail decoded on the page
    sampleShown: null,
    chartsDrawn: 0,
  };

  class ApiError extends Error {
    constructor(status, message) {
      super(message);
      this.status = status;
    }
  }

  // --------------------------------------------------------------- API --

  async function api(path, opts = {}) {
    const headers = {};
    // The bearer token goes in a header, which a page of another site cannot
    // make the browser send: the daemon accepts state changes only with it.
    if (ui.token) headers.Authorization = 'Bearer ' + ui.token;
    let body;
    if (opts.body !== undefined) {
      headers['Content-Type'] = 'application/json';
      body = JSON.stringify(opts.body);
    }
    const r = await fetch(path, {method: opts.method || 'GET', headers, body, cache: 'no-store'});
    const type = r.headers.get('Content-Type') || '';
    const data = type.includes('json') ? await r.json() : await r.text();
    if (r.status === 401 && !opts.quiet401) showLogin();
    if (!r.ok && !(opts.accept || []).includes(r.status)) {
      const msg = data && data.error ? data.error.message : 'HTTP ' + r.status;
      throw new ApiError(r.status, msg);
    }
    return data;
  }

  function showError(where, e) {
    $(where).textContent = e ? (e.message || String(e)) : '';
  }

  // ------------------------------------------------------------ log in --

  function showLogin() {
    if (ui.events) {
      ui.events.close();
      ui.events = null;
    }
    stopLive();
    $('app').hidden = true;
    $('login').hidden = false;
  }

  $('login-form').addEventListener('submit', async (ev) => {
    ev.preventDefault();
    const f = ev.target;
    showError('login-error', null);
    try {
      const r = await fetch('/api/v1/session', {
        method: 'POST',
        headers: {'Content-Type': 'application/json'},
        body: JSON.stringify({user: f.user.value, password: f.password.value}),
      });
      const data = await r.json();
      if (!r.ok) throw new ApiError(r.status, data.error ? data.error.message : 'HTTP ' + r.status);
      ui.token = data.token;
      sessionStorage.setItem('aggscan.token', ui.token);
      f.password.value = '';
      await start();
    } catch (e) {
      showError('login-error', e);
    }
  });

  $('logout').addEventListener('click', async () => {
    try {
      await api('/api/v1/session', {method: 'DELETE'});
    } catch (e) { /* logged out either way */ }
    ui.token = null;
    ui.who = null;
    sessionStorage.removeItem('aggscan.token');
    // A shared tablet: the next person starts from an empty form.
    $('login-form').reset();
    $('who').textContent = '';
    showError('login-error', null);
    showLogin();
  });

  function canOperate() {
    return ui.who && ui.who.role === 'operator';
  }

  // -------------------------------------------------------------- tabs --

  function route() {
    const h = location.hash.replace(/^#/, '');
    const [tab, id] = h.split('/');
    const name = ['rig', 'samples', 'sample'].includes(tab) ? tab : 'rig';
    for (const v of document.querySelectorAll('.view')) v.hidden = v.id !== name;
    for (const b of document.querySelectorAll('button.tab'))
      b.setAttribute('aria-selected', b.dataset.tab === name ? 'true' : 'false');
    // The live view costs the rig a still every few hundred ms: only while shown.
    if (name === 'rig' && !document.hidden) startLive(); else stopLive();
    if (name === 'samples') loadSamples();
    if (name === 'sample' && id) {
      $('tab-sample').hidden = false;
      if (id !== ui.sampleId) openSample(decodeURIComponent(id));
    }
  }
  for (const b of document.querySelectorAll('button.tab')) {
    b.addEventListener('click', () => {
      location.hash = b.dataset.tab === 'sample' && ui.sampleId ? '#sample/' + ui.sampleId : '#' + b.dataset.tab;
    });
  }
  window.addEventListener('hashchange', route);
  document.addEventListener('visibilitychange', route);

  function startLive() {
    const img = $('live');
    if (!img.dataset.on) {
      img.dataset.on = '1';
      img.src = '/api/v1/preview';
    }
  }
  function stopLive() {
    const img = $('live');
    if (img.dataset.on) {
      delete img.dataset.on;
      img.removeAttribute('src');
    }
  }
  $('live').addEventListener('error', () => {
    $('live-caption').textContent = 'no live view (the rig has it switched off or the camera is not ready)';
  });

  // -------------------------------------------------------------- rig --

  const kRunning = ['homing', 'rotating', 'settling', 'waiting', 'capturing', 'storing', 'finishing'];

  function renderPrompt() {
    const s = ui.status || {};
    const prompt = $('prompt');
    let main = '…';
    let sub = '';
    prompt.classList.toggle('fault', s.state === 'faulted');
    const sides = s.sides || 2;
    const board = s.capture_kind === 'calibration';
    const cc = s.calibration_capture;
    switch (s.state) {
      case 'idle': {
        const w = ui.worker;
        if (board && cc) {
          // The last capture was of the board: its solve is what comes next.
          if (cc.state === 'done' && cc.result) {
            main = 'Calibrated';
            sub = 'RMS ' + Number(cc.result.reprojection_rms_px).toFixed(2) + ' px from ' +
                cc.result.views_used + ' of ' + cc.result.views_total +
                ' views. Take the board off the disc and arm a sample.';
          } else if (cc.state === 'failed') {
            main = 'Calibration failed';
            sub = (cc.error || '') + ' — check the board and the light, then press CALIBRATE again.';
          } else if (cc.state === 'queued' || cc.state === 'solving') {
            main = 'Solving the calibration';
            sub = w && w.job && w.job.sample_id === cc.id && w.stage ? w.stage : cc.id;
          } else {
            main = 'Calibration ' + cc.state;
            sub = 'Press CALIBRATE to capture the board again.';
          }
          break;
        }
        const job = w && w.job && ui.lastSample && w.job.sample_id === ui.lastSample ? w.job : null;
        if (job) {
          main = 'Reconstructing — ' + (w.stage || 'starting');
          if (w.progress) sub = w.progress.done + ' of ' + w.progress.total;
        } else if (ui.lastResult && ui.lastResult.id === ui.lastSample) {
          const rec = ui.lastResult.reconstruction;
          if (rec && rec.state === 'failed') {
            main = 'Reconstruction failed';
            sub = rec.error || '';
          } else if (ui.lastResult.result) {
            main = 'Done';
            const r = ui.lastResult.result;
            sub = ui.lastSample + ': ' + (r.volume_mm3 / 1000).toFixed(1) + ' cm³, ' +
                [r.a_mm, r.b_mm, r.c_mm].map((x) => x.toFixed(0)).join(' × ') + ' mm. Arm the next sample.';
          } else if (rec && rec.state === 'done') {
            main = 'Done — 2D figures only';
            sub = 'No 3D result without a rig calibration: calibrate the rig (aggscan calibrate).';
          } else {
            main = 'Reconstruction queued';
            sub = ui.lastSample;
          }
        } else {
          main = 'Arm a sample to start';
          sub = 'Fill in the sample id below and press ARM';
        }
        break;
      }
      case 'armed':
        if (board) {
          main = 'Lay the calibration board flat on the disc (no rock), then press START';
          sub = 'Calibration — one turn of ' + s.views_per_side + ' views';
          break;
        }
        main = s.side > 1 ? 'Flip the rock, then press START'
                          : 'Place the rock with its markers facing the camera, then press START';
        sub = 'Sample ' + s.sample_id + ' — side ' + Math.max(1, s.side) + ' of ' + sides;
        break;
      case 'awaiting_pose':
        main = 'Flip the rock, then press START';
        sub = 'Sample ' + s.sample_id + ' — side ' + (s.side - 1) + ' done, side ' + s.side + ' next';
        break;
      case 'faulted':
        main = 'Fault: ' + (s.fault ? s.fault.message : 'see the devices');
        sub = 'Fix the cause, then press RESET';
        break;
      case 'unavailable':
        main = 'The rig is not answering';
        sub = s.status_line || '';
        break;
      default:
        if (kRunning.includes(s.state) && ui.turn && Date.now() < ui.turn.handsOffAt) {
          // A hand-turned table: the operator turns it now, and lets go in time.
          main = ui.turn.camera ? 'Move the camera on round the rock now'
                                : 'Turn the table by ' + Math.abs(ui.turn.by).toFixed(0) + '° now';
          sub = 'Side ' + s.side + ' — view ' + ui.turn.number + ' of ' + s.views_per_side +
              '. Hands off in ' +
              Math.max(0, (ui.turn.handsOffAt - Date.now()) / 1000).toFixed(1) + ' s.';
        } else if (kRunning.includes(s.state)) {
          const what = board ? 'Calibration' : 'Side ' + s.side;
          main = s.state === 'homing' ? what + ' — homing'
                                      : what + ' — view ' + Math.max(1, s.view || 0) + ' of ' + s.views_per_side;
          sub = (board ? 'The board' : 'Sample ' + s.sample_id) + '. Keep clear of the turntable; ABORT stops it.';
        }
    }
    prompt.textContent = main;
    $('subprompt').textContent = sub;
    const running = kRunning.includes(s.state);
    $('start').disabled = !canOperate() || !(s.state === 'armed' || s.state === 'awaiting_pose');
    $('abort').disabled = !canOperate() || !(running || s.state === 'armed' || s.state === 'awaiting_pose');
    $('reset').disabled = !canOperate() || s.state !== 'faulted';
    $('arm').disabled = !canOperate() || s.state !== 'idle';
    $('calibrate').disabled = !canOperate() || s.state !== 'idle';
    $('live-caption').textContent = running ? 'the views as they are stored' : 'live view';
  }

  function renderDevices() {
    const ul = $('devices');
    ul.textContent = '';
    for (const [name, d] of Object.entries(ui.devices)) {
      const li = document.createElement('li');
      li.className = d.healthy ? '' : 'bad';
      li.textContent = name + ': ' + (d.healthy ? 'ok' : d.message || d.state);
      ul.appendChild(li);
    }
  }

  function renderWorker() {
    const w = ui.worker;
    let text = 'no reconstruction worker reported';
    if (w) {
      if (w.job) {
        text = 'Sample ' + w.job.sample_id + (w.job.side > 0 ? ' side ' + w.job.side : '') + ': ' +
            (w.stage || 'starting') + (w.progress ? ' (' + w.progress.done + ' of ' + w.progress.total + ')' : '');
      } else {
        text = w.message || w.state || 'idle';
      }
    }
    const st = ui.status || {};
    if (st.queue_depth) text += ' — ' + st.queue_depth + ' job(s) waiting';
    $('worker').textContent = text;
  }

  function renderCalibration() {
    const c = (ui.status || {}).calibration;
    if (!c) {
      $('calibration').textContent = 'not checked yet';
      return;
    }
    let text = c.message || c.state;
    if (c.state === 'ok' && c.created_utc) {
      const days = (Date.now() - Date.parse(c.created_utc)) / 86400e3;
      text = 'RMS ' + Number(c.reprojection_rms_px).toFixed(2) + ' px, ' +
          (days < 1 ? 'made today' : Math.floor(days) + ' day(s) old') + ' (' + c.method + ')';
    }
    $('calibration').textContent = text;
    const cc = (ui.status || {}).calibration_capture;
    let last = '';
    if (cc) {
      last = 'Last board capture ' + cc.id + ': ' + cc.state;
      if (cc.state === 'done' && cc.result)
        last += ', RMS ' + Number(cc.result.reprojection_rms_px).toFixed(2) + ' px, ' +
            cc.result.views_used + ' of ' + cc.result.views_total + ' views';
      if (cc.state === 'failed' && cc.error) last += ': ' + cc.error;
    }
    $('calibration-capture').textContent = last;
  }

  function renderRig() {
    renderPrompt();
    renderDevices();
    renderWorker();
    renderCalibration();
  }

  async function refreshStatus() {
    ui.status = await api('/api/v1/status');
    if (ui.status.worker) ui.worker = ui.status.worker;
    for (const [name, d] of Object.entries(ui.status.devices || {}))
      ui.devices[name] = {healthy: d.healthy, state: d.state, message: d.message};
    if (ui.status.sample_id) ui.lastSample = ui.status.sample_id;
    renderRig();
  }

  async function act(path, body) {
    showError('action-error', null);
    try {
      const r = await api(path, {method: 'POST', body: body || {}});
      if (r && r.state) {
        Object.assign(ui.status, r);
        renderRig();
      }
      return r;
    } catch (e) {
      showError('action-error', e);
      return null;
    }
  }

  $('start').addEventListener('click', () => act('/api/v1/button'));
  $('abort').addEventListener('click', () => act('/api/v1/abort'));
  $('reset').addEventListener('click', () => act('/api/v1/reset'));
  $('calibrate').addEventListener('click', async () => {
    const r = await act('/api/v1/calibration');
    if (r) clearStrip();
  });
  $('arm-form').addEventListener('submit', async (ev) => {
    ev.preventDefault();
    const f = ev.target;
    const body = {id: f.id.value.trim()};
    for (const k of ['operator', 'lot', 'notes']) if (f[k].value.trim()) body[k] = f[k].value.trim();
    const r = await act('/api/v1/samples', body);
    if (r) {
      ui.lastSample = body.id;
      ui.lastResult = null;
      clearStrip();
      f.id.value = '';
      f.notes.value = '';
    }
  });

  // A short two-tone chime (Web Audio): the rock must be flipped.
  let audio = null;
  function chime() {
    if (!$('sound').checked) return;
    audio = audio || new AudioContext();
    const t = audio.currentTime;
    for (const [i, f] of [[0, 660], [1, 880]]) {
      const o = audio.createOscillator();
      const g = audio.createGain();
      o.frequency.value = f;
      g.gain.setValueAtTime(0.3, t + i * 0.25);
      g.gain.exponentialRampToValueAtTime(0.001, t + i * 0.25 + 0.22);
      o.connect(g).connect(audio.destination);
      o.start(t + i * 0.25);
      o.stop(t + i * 0.25 + 0.24);
    }
  }
  // One short beep: turn the hand-turned table now (the study's phone beeped
  // at each shot; here the beep is the cue to turn).
  function beep() {
    if (!$('sound').checked) return;
    audio = audio || new AudioContext();
    const t = audio.currentTime;
    const o = audio.createOscillator();
    const g = audio.createGain();
    o.frequency.value = 1320;
    g.gain.setValueAtTime(0.3, t);
    g.gain.exponentialRampToValueAtTime(0.001, t + 0.12);
    o.connect(g).connect(audio.destination);
    o.start(t);
    o.stop(t + 0.14);
  }
  $('sound').checked = localStorage.getItem('aggscan.sound') === '1';
  $('sound').addEventListener('change', () => {
    localStorage.setItem('aggscan.sound', $('sound').checked ? '1' : '0');
    if ($('sound').checked) (audio = audio || new AudioContext()).resume();
  });

  function clearStrip(side) {
    ui.stripSide = side || null;
    $('strip').textContent = '';
  }

  // ------------------------------------------------------------ events --

  function on(type, fn) {
    ui.events.addEventListener(type, (e) => {
      probe.events++;
      let d = null;
      try {
        d = JSON.parse(e.data);
      } catch (err) {
        return;
      }
      fn(d);
    });
  }

  function openEvents() {
    if (ui.events) ui.events.close();
    // Sent with the session cookie; EventSource reconnects by itself and
    // tells the rig the last event it had (Last-Event-ID).
    ui.events = new EventSource('/api/v1/events');
    ui.events.onopen = () => {
      $('conn').textContent = 'live';
      $('conn').className = 'conn live';
    };
    ui.events.onerror = () => {
      $('conn').textContent = 'reconnecting…';
      $('conn').className = 'conn lost';
    };
    on('state', (d) => {
      const before = ui.status ? ui.status.state : null;
      ui.status = Object.assign(ui.status || {}, d);
      if (d.sample_id) ui.lastSample = d.sample_id;
      if (d.state === 'homing') ui.status.view = 0;
      if (d.state === 'awaiting_pose' && before !== 'awaiting_pose') chime();
      if (d.state !== 'faulted') ui.status.fault = null;
      renderRig();
      if (!$('samples').hidden) loadSamples();
    });
    on('calibration', (d) => {
      // The board capture's state; with it the rig calibration as re-checked.
      const rig = d.rig;
      delete d.rig;
      ui.status = Object.assign(ui.status || {}, {calibration_capture: d});
      if (rig) ui.status.calibration = rig;
      renderRig();
    });
    on('fault', (d) => {
      ui.status = Object.assign(ui.status || {}, {fault: d});
      renderRig();
    });
    on('turn', (d) => {
      ui.turn = {by: d.by_deg, number: d.number, camera: d.move === 'camera',
                 handsOffAt: Date.now() + d.hands_off_in_ms};
      beep();
      renderPrompt();
      // The prompt changes back to the view count at the hands-off moment.
      setTimeout(renderPrompt, d.hands_off_in_ms + 10);
    });
    on('view', (d) => {
      probe.views++;
      ui.status = Object.assign(ui.status || {}, {side: d.side, view: d.number, views_per_side: d.views_per_side});
      ui.lastSample = d.sample_id;
      renderPrompt();
      // The side's views as a strip of thumbnails under the camera; how long
      // from the store to the thumbnail shown is measured.
      const side = d.sample_id + '/' + d.side;
      if (ui.stripSide !== side) clearStrip(side);
      const img = document.createElement('img');
      img.alt = 'side ' + d.side + ' view ' + d.number;
      img.onload = () => {
        if (d.stored_utc_ms) probe.thumbnailLatencyMs.push(Date.now() - d.stored_utc_ms);
        $('live-caption').textContent = 'side ' + d.side + ', view ' + d.number + ' stored';
      };
      img.src = d.thumbnail;
      $('strip').appendChild(img);
    });
    on('worker', (d) => {
      const had = ui.worker && ui.worker.job ? ui.worker.job.sample_id : null;
      ui.worker = d;
      // A job just ended: fetch its sample's outcome for the "Done" prompt.
      if (had && (!d.job || d.job.sample_id !== had) && had === ui.lastSample) fetchLastResult();
      // A job ended: the queue's depth changed (read once, on this event).
      if (had && !d.job) refreshStatus().catch(() => {});
      renderRig();
      if (!$('samples').hidden) loadSamples();
      if (ui.sampleId && had === ui.sampleId && !d.job) openSample(ui.sampleId);
    });
    on('health', (d) => {
      if (d.device !== 'worker') ui.devices[d.device] = {healthy: d.healthy, state: d.state, message: d.message};
      renderDevices();
    });
    on('reset', () => {
      refreshStatus().catch(() => {});
    });
  }

  async function fetchLastResult() {
    try {
      ui.lastResult = await api('/api/v1/samples/' + encodeURIComponent(ui.lastSample));
    } catch (e) {
      ui.lastResult = null;
    }
    renderPrompt();
  }

  // ----------------------------------------------------------- samples --

  function sampleState(s) {
    const rec = s.reconstruction;
    if (rec && rec.state === 'failed') return {text: 'failed: ' + (rec.error || ''), cls: 'state-failed'};
    if (rec && rec.state === 'reconstructing') {
      const w = ui.worker;
      const stage = w && w.job && w.job.sample_id === s.id && w.stage ? ' — ' + w.stage : '';
      return {text: 'reconstructing' + stage, cls: ''};
    }
    if (rec && rec.state === 'queued') return {text: 'queued', cls: ''};
    if (rec && rec.state === 'done') return {text: 'done', cls: 'state-done'};
    return {text: s.state || '?', cls: ''};
  }

  let samplesLoading = false;
  async function loadSamples() {
    if (samplesLoading) return;
    samplesLoading = true;
    try {
      ui.samples = await api('/api/v1/samples');
      renderSamples();
    } catch (e) {
      $('sample-rows').textContent = e.message;
    } finally {
      samplesLoading = false;
    }
  }

  function renderSamples() {
    const q = $('search').value.trim().toLowerCase();
    const body = $('sample-rows');
    body.textContent = '';
    const rows = ui.samples.slice().reverse().filter((s) => {
      if (!q) return true;
      const m = s.meta || {};
      return [s.id, s.created_utc, m.lot, m.operator].some((x) => x && String(x).toLowerCase().includes(q));
    });
    for (const s of rows) {
      const tr = document.createElement('tr');
      const st = sampleState(s);
      const r = s.result;
      const cells = [
        s.id,
        (s.created_utc || '').replace('T', ' ').slice(0, 16),
        (s.meta || {}).lot || '',
        st.text,
        r ? (r.volume_mm3 / 1000).toFixed(1) + ' cm³' : '',
        r ? [r.a_mm, r.b_mm, r.c_mm].map((x) => x.toFixed(0)).join(' × ') + ' mm' : '',
        r ? fmt(r.sphericity, 3) : '',
      ];
      cells.forEach((c, i) => {
        const td = document.createElement('td');
        td.textContent = c;
        if (i === 3 && st.cls) td.className = st.cls;
        tr.appendChild(td);
      });
      tr.addEventListener('click', () => {
        location.hash = '#sample/' + encodeURIComponent(s.id);
      });
      body.appendChild(tr);
    }
  }
  $('search').addEventListener('input', renderSamples);

  // ------------------------------------------------------------ sample --

  const fmt = (x, d) => (typeof x === 'number' ? x.toFixed(d) : '—');

  async function openSample(id) {
    ui.sampleId = id;
    probe.sampleShown = null;
    $('sample-title').textContent = id;
    let d;
    try {
      d = await api('/api/v1/samples/' + encodeURIComponent(id));
    } catch (e) {
      $('sample-state').textContent = e.message;
      return;
    }
    const m = d.meta || {};
    $('sample-meta').textContent = [
      'created ' + (d.created_utc || '').replace('T', ' ').slice(0, 19),
      m.operator ? 'operator ' + m.operator : '',
      m.lot ? 'lot ' + m.lot : '',
      m.notes ? 'notes: ' + m.notes : '',
    ].filter(Boolean).join(' · ');
    const st = sampleState(d);
    $('sample-state').textContent = st.text;
    let morph = null;
    if (d.result) {
      try {
        morph = await api('/api/v1/samples/' + encodeURIComponent(id) + '/results');
      } catch (e) {
        $('sample-state').textContent = 'results unreadable: ' + e.message;
      }
    }
    renderFigures(morph);
    renderDownloads(id, morph);
    renderViews(id, d, morph);
    renderCharts(morph);
    if (morph) await showMesh(id); else clearMesh();
    probe.sampleShown = id;
  }

  function renderFigures(morph) {
    const t = $('figures');
    t.textContent = '';
    const warn = $('sample-warnings');
    warn.textContent = '';
    if (!morph) return;
    const m = morph.morphology_3d || {};
    const q = morph.quality || {};
    const c = morph.comparison_2d_3d || {};
    const rows = [
      ['Volume', fmt(m.volume_mm3 / 1000, 2) + ' cm³'],
      ['Surface area', fmt(m.surface_area_mm2 / 100, 2) + ' cm²'],
      ['a (shortest)', fmt(m.a_mm, 1) + ' mm'],
      ['b', fmt(m.b_mm, 1) + ' mm'],
      ['c (longest)', fmt(m.c_mm, 1) + ' mm'],
      ['Flat-and-elongated ratio c/a', fmt(m.fer_3d, 2)],
      ['c/b, b/a', fmt(m.ratio_c_b, 2) + ', ' + fmt(m.ratio_b_a, 2)],
      ['Sphericity', fmt(m.sphericity, 3)],
      ['Mean 2D FER (' + ((morph.views_2d || []).length) + ' views)', fmt(c.fer_2d_mean, 2)],
      ['Mean circularity', fmt(c.circularity_mean, 3)],
      ['Watertight', m.watertight ? 'yes' : 'no'],
      ['Stitch residual', q.stitch_rms_mm == null ? '—' : fmt(q.stitch_rms_mm, 2) + ' mm RMS'],
      ['Silhouette agreement (IoU, min)', fmt(q.silhouette_iou_min, 3)],
    ];
    for (const [k, v] of rows) {
      const tr = document.createElement('tr');
      const th = document.createElement('th');
      th.textContent = k;
      const td = document.createElement('td');
      td.textContent = v;
      tr.append(th, td);
      t.appendChild(tr);
    }
    const warnings = [];
    if (q.confident === false) warnings.push('The worker marks this result as doubtful.');
    for (const f of q.flags || []) warnings.push(typeof f === 'string' ? f : JSON.stringify(f));
    for (const w of morph.warnings || []) warnings.push(typeof w === 'string' ? w : (w.message || JSON.stringify(w)));
    if (m.box_ill_conditioned) warnings.push('The bounding box is ill-conditioned: a, b and c depend on its orientation.');
    for (const w of warnings) {
      const li = document.createElement('li');
      li.textContent = w;
      warn.appendChild(li);
    }
  }

  // The images are there from the first stored view on; the mesh and the
  // figures once the worker is done.
  function renderDownloads(id, morph) {
    const box = $('downloads');
    box.textContent = '';
    const base = '/api/v1/samples/' + encodeURIComponent(id);
    const files = morph ? [
      ['Mesh (PLY)', '/mesh.ply', id + '_mesh.ply'],
      ['Mesh (OBJ)', '/mesh.obj', id + '_mesh.obj'],
      ['Mesh (STL)', '/mesh.stl', id + '_mesh.stl'],
      ['morphology.json', '/results', id + '_morphology.json'],
      ['Report (PDF)', '/report.pdf', id + '-report.pdf'],
      ['Report (HTML)', '/report.html', id + '-report.html'],
    ] : [];
    files.push(['Images (ZIP)', '/images.zip', id + '_images.zip']);
    for (const [label, path, name] of files) {
      const a = document.createElement('a');
      a.href = base + path;
      a.download = name;
      a.textContent = label;
      box.appendChild(a);
    }
  }

  // Each view's thumbnail with its mask's outline and its 2D figures.
  function renderViews(id, d, morph) {
    const box = $('views');
    box.textContent = '';
    const per = {};
    for (const v of (morph && morph.views_2d) || []) per[v.side + '/' + v.view] = v;
    const base = '/api/v1/samples/' + encodeURIComponent(id);
    for (const side of d.sides || []) {
      for (const v of side.captured_views || []) {
        const fig = document.createElement('figure');
        const canvas = document.createElement('canvas');
        const cap = document.createElement('figcaption');
        const f = per[side.side + '/' + v.view];
        cap.textContent = 'side ' + side.side + ' view ' + (v.view + 1) +
            (f ? ' · 2D FER ' + fmt(f.fer_2d, 2) + ' · circularity ' + fmt(f.circularity, 3) : '');
        fig.append(canvas, cap);
        box.appendChild(fig);
        const url = base + '/sides/' + side.side + '/views/' + v.view;
        drawThumbnail(canvas, url + '/thumbnail', morph ? url + '/mask' : null);
      }
    }
  }

  function loadImage(src) {
    return new Promise((resolve, reject) => {
      const img = new Image();
      img.onload = () => resolve(img);
      img.onerror = () => reject(new Error('cannot load ' + src));
      img.src = src;
    });
  }

  async function drawThumbnail(canvas, thumbUrl, maskUrl) {
    let img;
    try {
      img = await loadImage(thumbUrl);
    } catch (e) {
      return;
    }
    canvas.width = img.naturalWidth;
    canvas.height = img.naturalHeight;
    const ctx = canvas.getContext('2d');
    ctx.drawImage(img, 0, 0);
    if (!maskUrl) return;
    let mask;
    try {
      mask = await loadImage(maskUrl);
    } catch (e) {
      return;  // no mask for this view (not reconstructed, or it was rejected)
    }
    // The mask scaled to the thumbnail; its outline is every inside pixel
    // with an outside neighbour.
    const w = canvas.width;
    const h = canvas.height;
    const off = document.createElement('canvas');
    off.width = w;
    off.height = h;
    const octx = off.getContext('2d');
    octx.drawImage(mask, 0, 0, w, h);
    const m = octx.getImageData(0, 0, w, h).data;
    const inside = (x, y) => x >= 0 && y >= 0 && x < w && y < h && m[(y * w + x) * 4] > 127;
    const out = ctx.getImageData(0, 0, w, h);
    for (let y = 0; y < h; y++) {
      for (let x = 0; x < w; x++) {
        if (!inside(x, y)) continue;
        if (inside(x - 1, y) && inside(x + 1, y) && inside(x, y - 1) && inside(x, y + 1)) continue;
        const i = (y * w + x) * 4;
        out.data[i] = 255;
        out.data[i + 1] = 0;
        out.data[i + 2] = 255;
      }
    }
    ctx.putImageData(out, 0, 0);
  }

  // The study's Figures 7 and 8 for this rock.
  function renderCharts(morph) {
    for (const c of ui.charts) c.destroy();
    ui.charts = [];
    if (!morph || !morph.views_2d || !morph.views_2d.length) return;
    const views = morph.views_2d;
    const m = morph.morphology_3d || {};
    const c = morph.comparison_2d_3d || {};
    const n = views.length;
    const line = (y, label, color) => ({
      type: 'line', label, data: [{x: 0, y}, {x: n + 1, y}], borderColor: color, borderDash: [8, 4],
      pointRadius: 0, borderWidth: 3,
    });
    const perView = (key, label, color) => ({
      type: 'scatter', label, borderColor: color, backgroundColor: color, pointRadius: 5,
      data: views.map((v, i) => ({x: i + 1, y: v[key]})),
    });
    const common = {
      animation: false, responsive: true,
      scales: {x: {type: 'linear', title: {display: true, text: 'view'}, min: 0, max: n + 1}},
      plugins: {legend: {labels: {font: {size: 14}}}},
    };
    ui.charts.push(new Chart($('chart-fer'), {
      data: {datasets: [perView('fer_2d', '2D FER per view', '#1f4e9c'), line(m.fer_3d, '3D FER', '#a30000')]},
      options: {...common, scales: {...common.scales, y: {title: {display: true, text: 'FER'}}}},
    }));
    ui.charts.push(new Chart($('chart-circ'), {
      data: {datasets: [perView('circularity', 'circularity per view', '#1f4e9c'),
        line(m.sphericity, '3D sphericity', '#a30000')]},
      options: {...common, scales: {...common.scales, y: {title: {display: true, text: 'circularity, sphericity'}}}},
    }));
    const hi = Math.max(c.fer_2d_mean || 1, m.ratio_c_b || 1, m.ratio_b_a || 1) * 1.15;
    ui.charts.push(new Chart($('chart-ratio'), {
      data: {datasets: [
        {type: 'scatter', label: 'mean 2D FER vs c/b', data: [{x: m.ratio_c_b, y: c.fer_2d_mean}],
          pointRadius: 9, backgroundColor: '#1f4e9c'},
        {type: 'scatter', label: 'mean 2D FER vs b/a', data: [{x: m.ratio_b_a, y: c.fer_2d_mean}],
          pointRadius: 9, pointStyle: 'triangle', backgroundColor: '#0a6b1f'},
        {type: 'line', label: 'equal', data: [{x: 1, y: 1}, {x: hi, y: hi}], borderColor: '#555',
          borderDash: [6, 4], pointRadius: 0},
      ]},
      options: {
        animation: false, responsive: true,
        scales: {x: {type: 'linear', min: 1, max: hi, title: {display: true, text: '3D ratio'}},
          y: {min: 1, max: hi, title: {display: true, text: 'mean 2D FER'}}},
      },
    }));
    probe.chartsDrawn = ui.charts.length;
  }

  // --------------------------------------------------------- 3D viewer --

  function ensureViewer() {
    if (ui.viewer) return ui.viewer;
    const canvas = $('viewer');
    const renderer = new THREE.WebGLRenderer({canvas, antialias: true});
    renderer.setClearColor(0xf4f4f4);
    const scene = new THREE.Scene();
    const camera = new THREE.PerspectiveCamera(35, canvas.width / canvas.height, 1, 10000);
    scene.add(new THREE.HemisphereLight(0xffffff, 0x666666, 0.9));
    const sun = new THREE.DirectionalLight(0xffffff, 0.6);
    sun.position.set(1, 2, 3);
    scene.add(sun);
    const controls = new THREE.OrbitControls(camera, canvas);
    const v = {renderer, scene, camera, controls, mesh: null};
    const draw = () => {
      renderer.render(scene, camera);
      updateScaleBar(v);
    };
    v.draw = draw;
    controls.addEventListener('change', draw);
    ui.viewer = v;
    return v;
  }

  function clearMesh() {
    if (!ui.viewer || !ui.viewer.mesh) return;
    ui.viewer.scene.remove(ui.viewer.mesh);
    ui.viewer.mesh.geometry.dispose();
    ui.viewer.mesh = null;
    ui.viewer.draw();
  }

  async function showMesh(id) {
    const v = ensureViewer();
    clearMesh();
    const r = await fetch('/api/v1/samples/' + encodeURIComponent(id) + '/mesh.ply', {
      headers: ui.token ? {Authorization: 'Bearer ' + ui.token} : {},
    });
    if (!r.ok) return;
    const geometry = new THREE.PLYLoader().parse(await r.arrayBuffer());
    geometry.computeVertexNormals();
    geometry.computeBoundingSphere();
    const s = geometry.boundingSphere;
    geometry.translate(-s.center.x, -s.center.y, -s.center.z);
    const material = geometry.attributes.color
      ? new THREE.MeshStandardMaterial({vertexColors: THREE.VertexColors, roughness: 0.9})
      : new THREE.MeshStandardMaterial({color: 0xb0a48a, roughness: 0.9});
    v.mesh = new THREE.Mesh(geometry, material);
    v.scene.add(v.mesh);
    // Millimetres throughout: the mesh is metric.
    v.radius = s.radius;
    v.camera.near = s.radius / 100;
    v.camera.far = s.radius * 100;
    v.camera.position.set(0, -s.radius * 3.2, s.radius * 1.2);
    v.camera.up.set(0, 0, 1);
    v.camera.updateProjectionMatrix();
    v.controls.target.set(0, 0, 0);
    v.controls.update();
    v.draw();
  }

  // A bar of a round length in mm, as long as that length looks at the
  // distance of the rock's centre.
  function updateScaleBar(v) {
    if (!v.mesh) {
      $('scalebar-label').textContent = '';
      $('scalebar-bar').style.width = '0';
      return;
    }
    const canvas = v.renderer.domElement;
    const dist = v.camera.position.distanceTo(v.controls.target);
    const mmVisible = 2 * dist * Math.tan((v.camera.fov * Math.PI) / 360);
    const pxPerMm = canvas.clientHeight / mmVisible;
    let len = 1;
    for (const l of [1, 2, 5, 10, 20, 50, 100, 200, 500]) if (l * pxPerMm <= 160) len = l;
    $('scalebar-bar').style.width = Math.round(len * pxPerMm) + 'px';
    $('scalebar-label').textContent = len + ' mm';
  }

  // For browser tests: the viewer's pixels after a render, without keeping
  // the drawing buffer (read in the same task as the render).
  probe.viewerPixels = function () {
    const v = ui.viewer;
    if (!v) return null;
    v.renderer.render(v.scene, v.camera);
    const gl = v.renderer.getContext();
    const w = gl.drawingBufferWidth;
    const h = gl.drawingBufferHeight;
    const px = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, px);
    let differing = 0;
    let hash = 0;
    for (let i = 0; i < px.length; i += 4) {
      if (Math.abs(px[i] - 0xf4) + Math.abs(px[i + 1] - 0xf4) + Math.abs(px[i + 2] - 0xf4) > 24) differing++;
      hash = (hash * 31 + px[i] + px[i + 1] * 7 + px[i + 2] * 13) >>> 0;
    }
    return {width: w, height: h, nonBackground: differing, hash};
  };
  // Turns the view as a drag would.
  probe.orbit = function (radians) {
    const v = ui.viewer;
    if (!v) return false;
    const p = v.camera.position.clone().sub(v.controls.target);
    p.applyAxisAngle(new THREE.Vector3(0, 0, 1), radians);
    v.camera.position.copy(v.controls.target.clone().add(p));
    v.controls.update();
    v.draw();
    return true;
  };
  window.aggscanConsole = probe;

  // ------------------------------------------------------------- start --

  async function start() {
    let who;
    try {
      who = await api('/api/v1/session', {quiet401: true});
    } catch (e) {
      if (e.status === 401) {
        ui.token = null;
        sessionStorage.removeItem('aggscan.token');
        showLogin();
        return;
      }
      $('prompt').textContent = 'The rig is not answering: ' + e.message;
      $('app').hidden = false;
      return;
    }
    ui.who = who;
    $('who').textContent = who.user ? who.user + ' (' + who.role + ')' : '';
    $('logout').hidden = who.auth === 'none';
    $('login').hidden = true;
    $('app').hidden = false;
    openEvents();
    try {
      await refreshStatus();
      if (ui.lastSample) fetchLastResult();
    } catch (e) {
      $('prompt').textContent = 'The rig is not answering: ' + e.message;
    }
    route();
  }

  start();
})();
