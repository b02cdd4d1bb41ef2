// The openral console page: one WebSocket in (state as JSON, camera frames as binary), controls out.
// Plots are drawn on canvases here (no library, no network: the page works offline).
"use strict";
(() => {
  const token = new URLSearchParams(location.search).get("token");
  const query = token ? "?token=" + encodeURIComponent(token) : "";
  const WINDOW_S = 20;            // seconds of joints a plot shows
  const MAX_POINTS = 1200;        // samples kept per joint
  const $ = (id) => document.getElementById(id);
  const css = getComputedStyle(document.documentElement);
  const COLOURS = {};               // read once: a style lookup per draw would force style recalculation
  for (const name of ["--measured", "--commanded", "--muted"]) COLOURS[name] = css.getPropertyValue(name).trim() || "#888";

  let ws = null;
  let ended = false;
  let nextId = 1;
  let controlsKey = "";
  const plots = new Map();        // joint name -> {canvas, points: [[t, measured, commanded]]}
  const cameras = new Map();      // sensor id -> {img, url}
  let dirty = false;

  function text(id, value) { const el = $(id); if (el.textContent !== value) el.textContent = value; }
  function fmt(value, digits = 1) {
    return value === null || value === undefined ? "–" : Number(value).toFixed(digits);
  }
  function say(message, error = false) { const el = $("message"); el.textContent = message; el.className = error ? "error" : ""; }

  // -- connection -------------------------------------------------------------------------------
  function connect() {
    const scheme = location.protocol === "https:" ? "wss://" : "ws://";
    ws = new WebSocket(scheme + location.host + "/ws" + query);
    ws.binaryType = "arraybuffer";
    ws.onopen = () => { setConnection(true); };
    ws.onmessage = (event) => {
      if (typeof event.data === "string") onMessage(JSON.parse(event.data));
      else onFrame(event.data);
    };
    ws.onclose = () => {
      setConnection(false);
      if (!ended) setTimeout(connect, 1000);  // the server may be restarting: try again
    };
  }
  function setConnection(on) {
    const el = $("connection");
    el.textContent = ended ? "run ended" : on ? "live" : "disconnected";
    el.className = "badge " + (on && !ended ? "on" : "off");
    document.querySelectorAll("#controls button").forEach((b) => { b.disabled = !on || ended; });
  }

  function onMessage(message) {
    if (message.type === "hello") {
      renderControls(message.controls);
      for (const sample of message.history) addSample(sample);
    } else if (message.type === "state") {
      renderState(message);
    } else if (message.type === "control_result") {
      const button = document.querySelector(`#controls button[data-control="${CSS.escape(message.name || "")}"]`);
      if (button) button.disabled = false;
      say(message.ok ? `${message.name}: done` : `${message.name || "control"}: ${message.error}`, !message.ok);
    } else if (message.type === "closed") {
      ended = true;
      say(message.reason || "the run ended");
      setConnection(false);
    } else if (message.type === "error") {
      say(message.error, true);
    }
  }

  // -- cameras ----------------------------------------------------------------------------------
  function onFrame(buffer) {
    const size = new DataView(buffer).getUint32(0);
    const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, size)));
    const blob = new Blob([new Uint8Array(buffer, 4 + size)], { type: "image/jpeg" });
    let camera = cameras.get(header.sensor_id);
    if (!camera) {
      const figure = document.createElement("figure");
      const img = document.createElement("img");
      img.id = "camera-" + header.sensor_id;
      img.alt = header.sensor_id;
      const caption = document.createElement("figcaption");
      caption.textContent = header.sensor_id;
      figure.append(img, caption);
      $("cameras").append(figure);
      camera = { img, url: null };
      cameras.set(header.sensor_id, camera);
    }
    const previous = camera.url;
    camera.url = URL.createObjectURL(blob);
    camera.img.onload = () => { if (previous) URL.revokeObjectURL(previous); };
    camera.img.dataset.stamp = String(header.stamp_ns);
    camera.img.src = camera.url;
  }

  // -- controls ---------------------------------------------------------------------------------
  function renderControls(controls) {
    const key = JSON.stringify(controls);
    if (key === controlsKey) return;
    controlsKey = key;
    const nav = $("controls");
    nav.replaceChildren();
    for (const control of controls) {
      const button = document.createElement("button");
      button.type = "button";
      button.textContent = control.label;
      button.dataset.control = control.name;
      button.id = "control-" + control.name;
      button.disabled = !ws || ws.readyState !== WebSocket.OPEN || ended;
      button.addEventListener("click", () => press(control.name, button));
      nav.append(button);
    }
  }
  function press(name, button) {
    if (!ws || ws.readyState !== WebSocket.OPEN) { say("not connected", true); return; }
    button.disabled = true;
    ws.send(JSON.stringify({ type: "control", name, id: nextId++ }));
    say(`${name}: sent`);
  }

  // -- state ------------------------------------------------------------------------------------
  function renderState(state) {
    text("ticks", String(state.ticks));
    renderControls(state.controls);
    if (state.sample) addSample(state.sample);
    const status = state.status || {};
    text("skill", status.skill_id || "–");
    text("task", (state.episode && state.episode.task) || status.task || "–");
    text("episode", state.episode ? String(state.episode.index) : "–");
    const takeover = $("takeover");
    if (takeover.hidden !== !status.takeover) takeover.hidden = !status.takeover;
    if (status.takeover) {
      text("takeover", status.takeover.human_in_control ? `human in control (${status.takeover.skill_id})` : "policy in control");
      const cls = "badge" + (status.takeover.human_in_control ? " human" : "");
      if (takeover.className !== cls) takeover.className = cls;
    }
    renderHealth(status);
    renderExecutor(status.executor);
  }
  function rows(tableId, entries) {
    const body = $(tableId).tBodies[0];
    while (body.rows.length > entries.length) body.deleteRow(-1);
    entries.forEach(([label, value, warn], i) => {
      const row = body.rows[i] || body.insertRow();
      if (row.cells.length === 0) { row.insertCell(); row.insertCell(); }
      if (row.cells[0].textContent !== label) row.cells[0].textContent = label;
      if (row.cells[1].textContent !== value) row.cells[1].textContent = value;
      const cls = warn ? "warn" : "";
      if (row.cells[1].className !== cls) row.cells[1].className = cls;
    });
  }
  function renderHealth(status) {
    const live = status.live || {};
    const withheld = Object.entries(status.withheld || {});
    const stale = status.stale_sensors || [];
    const entries = [
      ["rate", `${fmt(live.recent_rate_hz, 2)} / ${fmt(live.target_hz, 0)} Hz`, false],
      ["start jitter p99", live.start_jitter_us_p99 == null ? "–" : `${fmt(live.start_jitter_us_p99, 0)} µs`, false],
      ["tick p50 / p99", `${fmt(live.tick_ms_p50, 2)} / ${fmt(live.tick_ms_p99, 2)} ms`, false],
      ["missed slots", fmt(live.missed_slots, 0), live.missed_slots > 0],
      ["deadline misses", fmt(live.deadline_misses, 0), live.deadline_misses > 0],
      ["withheld actions", fmt(live.withheld_actions, 0), live.withheld_actions > 0],
    ];
    for (const [reason, count] of withheld) entries.push([`  withheld: ${reason}`, String(count), true]);
    entries.push(["stale sensors", stale.length ? stale.join(", ") : "none", stale.length > 0]);
    entries.push(["safety violations", fmt(live.safety_violations, 0), live.safety_violations > 0]);
    if (status.error) entries.push(["status", status.error, true]);
    rows("health", entries);
  }
  function renderExecutor(executor) {
    if ($("executor").hidden !== !executor) $("executor").hidden = $("executor-title").hidden = !executor;
    if (!executor) return;
    rows("executor", [
      ["chunk delay", executor.chunk_delay_ticks == null ? "–" : `${executor.chunk_delay_ticks} ticks (max ${executor.chunk_delay_ticks_max})`, false],
      ["starved ticks", String(executor.starved_ticks), executor.starved_ticks > 0],
      ["fallback active", executor.fallback_active == null ? "–" : executor.fallback_active ? "yes" : "no", !!executor.fallback_active],
      ["chunks used / requests", `${executor.chunks_used} / ${executor.requests}`, false],
      ["errors", String(executor.errors), executor.errors > 0],
    ]);
  }

  // -- joints -----------------------------------------------------------------------------------
  function addSample(sample) {
    const measured = sample.measured || [];
    const commanded = sample.commanded || [];
    const count = Math.max(measured.length, commanded.length);
    for (let i = 0; i < count; i++) {
      const name = sample.names[i] || `axis ${i}`;
      let plot = plots.get(name);
      if (!plot) plot = newPlot(name);
      const last = plot.points[plot.points.length - 1];
      if (last && last[0] === sample.t) continue;
      plot.points.push([sample.t, measured[i] ?? null, commanded[i] ?? null]);
      if (plot.points.length > MAX_POINTS) plot.points.splice(0, plot.points.length - MAX_POINTS);
    }
    if (!dirty) { dirty = true; requestAnimationFrame(draw); }
  }
  function newPlot(name) {
    const box = document.createElement("div");
    box.className = "plot";
    const label = document.createElement("span");
    label.textContent = name;
    const canvas = document.createElement("canvas");
    canvas.dataset.joint = name;
    box.append(label, canvas);
    $("joints").append(box);
    const plot = { canvas, points: [] };
    plots.set(name, plot);
    return plot;
  }
  function draw() {
    dirty = false;
    if (document.hidden) return;  // a background tab draws nothing; the next sample redraws
    for (const plot of plots.values()) drawPlot(plot);
  }
  function drawPlot({ canvas, points }) {
    const ratio = window.devicePixelRatio || 1;
    const width = Math.round(canvas.clientWidth * ratio), height = Math.round(canvas.clientHeight * ratio);
    if (canvas.width !== width || canvas.height !== height) { canvas.width = width; canvas.height = height; }
    const g = canvas.getContext("2d");
    g.clearRect(0, 0, width, height);
    if (points.length === 0) return;
    const t1 = points[points.length - 1][0], t0 = t1 - WINDOW_S;
    let lo = Infinity, hi = -Infinity;
    for (const p of points) {
      if (p[0] < t0) continue;
      for (const v of [p[1], p[2]]) if (v !== null) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
    }
    if (!isFinite(lo)) return;
    const pad = Math.max((hi - lo) * 0.1, 1e-3);
    lo -= pad; hi += pad;
    const x = (t) => ((t - t0) / WINDOW_S) * width;
    const y = (v) => height - ((v - lo) / (hi - lo)) * height;
    g.lineWidth = 1.5 * ratio;
    for (const [index, name, dash] of [[1, "--measured", []], [2, "--commanded", [4 * ratio, 3 * ratio]]]) {
      g.strokeStyle = COLOURS[name];
      g.setLineDash(dash);
      g.beginPath();
      let pen = false;
      for (const p of points) {
        if (p[0] < t0 || p[index] === null) { pen = false; continue; }
        if (pen) g.lineTo(x(p[0]), y(p[index])); else g.moveTo(x(p[0]), y(p[index]));
        pen = true;
      }
      g.stroke();
    }
    g.setLineDash([]);
    g.fillStyle = COLOURS["--muted"];
    g.font = `${10 * ratio}px system-ui, sans-serif`;
    g.fillText(hi.toFixed(2), 2 * ratio, 10 * ratio);
    g.fillText(lo.toFixed(2), 2 * ratio, height - 2 * ratio);
  }
  window.addEventListener("resize", () => { if (!dirty) { dirty = true; requestAnimationFrame(draw); } });

  connect();
})();
