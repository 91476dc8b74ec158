// overgrid view: the live map on a canvas, fed by the viewer's WebSocket.
// Messages: text JSON ("hello", "status") and binary frames ("map": the whole map, "rect": a
// changed rectangle): u32 LE header length, JSON header, int8 occupancy, u16 LE height in mm.
"use strict";

(() => {
  const canvas = document.getElementById("map");
  const ctx = canvas.getContext("2d");
  const banner = document.getElementById("banner");
  const summary = document.getElementById("summary");
  const readout = document.getElementById("readout");
  const pairsList = document.getElementById("pairs");
  const objectsBox = document.getElementById("objects");
  const legend = document.getElementById("legend");
  const heightMode = document.getElementById("height-mode");

  const COLORS = { alive: "#1f9d45", dead: "#d32f2f", unknown: "#e0a100", object: "#1565c0", lastKnown: "#8a8f98", axisX: "#d32f2f", axisY: "#1f9d45" };
  const MIN_SPEED_MPS = 0.05; // slower is drawn as standing still: no arrow
  const SERVER_SILENT_S = 3.5; // the server sends status every second: silence means a lost link
  const CONNECT_TIMEOUT_S = 5; // a viewer that accepts the connection but never answers is as gone
  const RETRY_MIN_MS = 500;
  const RETRY_MAX_MS = 5000;
  const CELL_QUERY_MS = 250; // "last observed" is asked at most this often, and only for a new cell
  const CELL_REFRESH_MS = 1000; // … or again for the same cell (the viewer's layer is about this old)
  const HEIGHT_RAMP = [[48, 18, 59], [70, 134, 251], [27, 229, 181], [164, 252, 60], [251, 185, 56], [228, 70, 10], [122, 4, 3]];

  const state = {
    hello: null,
    map: null, // {i0, j0, cols, rows, resolution_m, version, stamp_ns, occupancy, height, image}
    status: null,
    // The view in CSS pixels (w × h, the canvas's size on the page); the canvas holds
    // devicePixelRatio device pixels to each, or the map and its labels blur on a phone.
    view: { cx: 0, cy: 0, pxPerM: 40, w: 1, h: 1, pixelRatio: 1 },
    userMoved: false,
    socket: null,
    socketStartedMs: 0,
    connected: false,
    rejected: false, // the viewer answered 401: this page's token is not (or no longer) the one
    probing: false,
    retryTimer: null,
    lastMessageMs: 0,
    retryMs: RETRY_MIN_MS,
    frames: { map: 0, rect: 0 }, // frames received, by type: after the first map, rectangles
    pointer: null,
    drawQueued: false,
    // The viewer's answer for the cell under the pointer: {key, lastSeenS, nowS, receivedMs}.
    seen: { key: null, wanted: null, asking: false, lastAskMs: 0 },
  };

  // ---- frames -------------------------------------------------------------------------------
  function readFrame(buffer) {
    const length = new DataView(buffer).getUint32(0, true);
    const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, length)));
    const cells = header.rows * header.cols;
    const start = 4 + length;
    const occupancy = new Int8Array(buffer, start, cells);
    const height = new Uint16Array(buffer.slice(start + cells, start + 3 * cells)); // copied: aligned
    return { header, occupancy, height };
  }

  function onMapFrame({ header, occupancy, height }) {
    const image = document.createElement("canvas");
    image.width = Math.max(header.cols, 1);
    image.height = Math.max(header.rows, 1);
    state.map = { ...header, occupancy: new Int8Array(occupancy), height, image };
    paint(0, 0, header.cols, header.rows);
    if (!state.userMoved && header.cols > 0) fit(); // the map grew: show all of it, unless moved
    queueDraw();
  }

  function onRectFrame({ header, occupancy, height }) {
    const map = state.map;
    if (!map) return;
    const col0 = header.i0 - map.i0;
    const row0 = header.j0 - map.j0;
    if (col0 < 0 || row0 < 0 || col0 + header.cols > map.cols || row0 + header.rows > map.rows) return;
    for (let r = 0; r < header.rows; r++) {
      const at = (row0 + r) * map.cols + col0;
      map.occupancy.set(occupancy.subarray(r * header.cols, (r + 1) * header.cols), at);
      map.height.set(height.subarray(r * header.cols, (r + 1) * header.cols), at);
    }
    map.version = header.version;
    map.stamp_ns = header.stamp_ns;
    paint(col0, row0, header.cols, header.rows);
    queueDraw();
  }

  // ---- colours ------------------------------------------------------------------------------
  function mix(a, b, t) {
    return [0, 1, 2].map((k) => Math.round(a[k] + (b[k] - a[k]) * t));
  }

  function ramp(t) {
    const x = Math.min(Math.max(t, 0), 1) * (HEIGHT_RAMP.length - 1);
    const k = Math.min(Math.floor(x), HEIGHT_RAMP.length - 2);
    return mix(HEIGHT_RAMP[k], HEIGHT_RAMP[k + 1], x - k);
  }

  function cellColor(p, heightMm) {
    const h = state.hello;
    if (p < 0) return h.colors.unknown;
    if (heightMode.checked && p >= h.occupied_min && heightMm !== h.no_height_mm) {
      return ramp(heightMm / 1000 / h.height_band_m[1]);
    }
    if (p <= h.free_max) return h.colors.free;
    if (p >= h.occupied_min) return h.colors.occupied;
    // Undecided cells: shades between free and occupied, by their probability.
    return mix(h.colors.free, h.colors.occupied, 0.25 + (0.5 * (p - h.free_max)) / (h.occupied_min - h.free_max));
  }

  // Paint map rows [row0, row0+rows) × cols [col0, col0+cols) into the map's image (y up).
  function paint(col0, row0, cols, rows) {
    const map = state.map;
    if (!map || !state.hello || cols <= 0 || rows <= 0) return;
    const pixels = new ImageData(cols, rows);
    const data = pixels.data;
    for (let y = 0; y < rows; y++) {
      const row = row0 + (rows - 1 - y);
      for (let x = 0; x < cols; x++) {
        const cell = row * map.cols + col0 + x;
        const rgb = cellColor(map.occupancy[cell], map.height[cell]);
        const o = 4 * (y * cols + x);
        data[o] = rgb[0];
        data[o + 1] = rgb[1];
        data[o + 2] = rgb[2];
        data[o + 3] = 255;
      }
    }
    map.image.getContext("2d").putImageData(pixels, col0, map.rows - row0 - rows);
  }

  // ---- view ---------------------------------------------------------------------------------
  function worldToScreen(x, y) {
    const v = state.view;
    return [v.w / 2 + (x - v.cx) * v.pxPerM, v.h / 2 - (y - v.cy) * v.pxPerM];
  }

  function screenToWorld(sx, sy) {
    const v = state.view;
    return [v.cx + (sx - v.w / 2) / v.pxPerM, v.cy - (sy - v.h / 2) / v.pxPerM];
  }

  function fit() {
    const map = state.map;
    if (!map || map.cols === 0) return;
    measure();
    const r = map.resolution_m;
    const width = map.cols * r;
    const height = map.rows * r;
    state.view.cx = map.i0 * r + width / 2;
    state.view.cy = map.j0 * r + height / 2;
    state.view.pxPerM = 0.95 * Math.min(state.view.w / width, state.view.h / height);
    queueDraw();
  }

  // The canvas's size on the page and its backing store at the device's pixel ratio (which a
  // browser zoom changes too); true if either changed.
  function measure() {
    const v = state.view;
    const ratio = window.devicePixelRatio || 1;
    const w = Math.max(canvas.clientWidth, 1);
    const h = Math.max(canvas.clientHeight, 1);
    if (v.w === w && v.h === h && v.pixelRatio === ratio) return false;
    Object.assign(v, { w, h, pixelRatio: ratio });
    canvas.width = Math.round(w * ratio);
    canvas.height = Math.round(h * ratio);
    return true;
  }

  function resize() {
    if (measure() && state.map && !state.userMoved) fit();
  }

  function queueDraw() {
    if (state.drawQueued) return;
    state.drawQueued = true;
    requestAnimationFrame(() => {
      state.drawQueued = false;
      draw();
    });
  }

  function draw() {
    resize();
    const v = state.view;
    ctx.setTransform(v.pixelRatio, 0, 0, v.pixelRatio, 0, 0); // draw in CSS pixels
    ctx.fillStyle = "#d9dce2";
    ctx.fillRect(0, 0, v.w, v.h);
    const map = state.map;
    if (map && map.cols > 0) {
      const r = map.resolution_m;
      const [sx, sy] = worldToScreen(map.i0 * r, (map.j0 + map.rows) * r);
      const k = state.view.pxPerM * r;
      ctx.imageSmoothingEnabled = false;
      ctx.drawImage(map.image, sx, sy, map.cols * k, map.rows * k);
      ctx.strokeStyle = "#7a808a";
      ctx.lineWidth = 1;
      ctx.strokeRect(sx - 0.5, sy - 0.5, map.cols * k + 1, map.rows * k + 1);
    }
    drawFootprints();
    drawObjects();
    drawOriginAxes();
    drawScaleBar();
    drawAxesGlyph();
  }

  function polygonPath(points) {
    ctx.beginPath();
    points.forEach(([x, y], k) => {
      const [sx, sy] = worldToScreen(x, y);
      if (k === 0) ctx.moveTo(sx, sy);
      else ctx.lineTo(sx, sy);
    });
    ctx.closePath();
  }

  function pairState(pair) {
    if (!state.status || !live()) return "unknown";
    if (pair.alive) return "alive";
    return pair.known_to_fusion ? "dead" : "no-depth";
  }

  function stale() {
    return Boolean(state.status && state.status.stale);
  }

  // Whether what the page shows is current: the viewer connected and speaking, fusion answering.
  // Otherwise pairs, ages and objects are the last known, and said to be (they read as live
  // through a viewer's outage).
  function live() {
    const silentS = (performance.now() - state.lastMessageMs) / 1000;
    return state.connected && silentS <= SERVER_SILENT_S && !stale();
  }

  function pairLine(pair) {
    const s = pairState(pair);
    if (s === "alive") {
      const parts = [pair.pair];
      if (pair.frame_rate_hz !== null) parts.push(`${pair.frame_rate_hz.toFixed(1)} Hz`);
      if (pair.capture_to_map_ms !== null && pair.capture_to_map_ms !== undefined) parts.push(`${Math.round(pair.capture_to_map_ms)} ms`);
      return parts.join(" · ");
    }
    return `${pair.pair} · ${s === "unknown" ? "state unknown" : s === "dead" ? "DEAD" : "no depth process"}`;
  }

  function drawFootprints() {
    const pairs = state.status ? state.status.pairs : [];
    for (const pair of pairs) {
      if (!pair.footprint_m) continue;
      const s = pairState(pair);
      const color = s === "alive" ? COLORS.alive : s === "dead" ? COLORS.dead : COLORS.unknown;
      polygonPath(pair.footprint_m);
      ctx.setLineDash(s === "alive" ? [] : [8, 5]);
      ctx.lineWidth = 2;
      ctx.strokeStyle = color;
      ctx.stroke();
      ctx.setLineDash([]);
      const xs = pair.footprint_m.map((p) => p[0]);
      const ys = pair.footprint_m.map((p) => p[1]);
      const [lx, ly] = worldToScreen(Math.min(...xs), Math.max(...ys));
      label(pairLine(pair), lx + 6, ly + 6, color);
    }
  }

  function label(text, x, y, color) {
    ctx.font = "12px system-ui, sans-serif";
    const w = ctx.measureText(text).width;
    ctx.fillStyle = "rgba(255, 255, 255, 0.85)";
    ctx.fillRect(x, y, w + 8, 17);
    ctx.fillStyle = color;
    ctx.fillText(text, x + 4, y + 13);
  }

  function objectOutline(o) {
    if (!o.center_m || !o.size_m) return null;
    const [cx, cy] = o.center_m;
    const [l, w] = o.size_m;
    const c = Math.cos(o.yaw_rad || 0);
    const s = Math.sin(o.yaw_rad || 0);
    // A round top (a drum, a person) is the ellipse inscribed in its rectangle.
    const unit = o.round
      ? Array.from({ length: 32 }, (_, k) => [Math.cos((k * Math.PI) / 16), Math.sin((k * Math.PI) / 16)])
      : [[-1, -1], [1, -1], [1, 1], [-1, 1]];
    return unit.map(([a, b]) => [cx + (a * l * c - b * w * s) / 2, cy + (a * l * s + b * w * c) / 2]);
  }

  function drawObjects() {
    const objects = (state.status && state.status.objects) || [];
    const color = live() ? COLORS.object : COLORS.lastKnown; // as last known: greyed
    for (const o of objects) {
      const outline = objectOutline(o);
      if (!outline) continue;
      polygonPath(outline);
      ctx.lineWidth = 2;
      ctx.strokeStyle = color;
      ctx.stroke();
      const cx = outline.reduce((a, p) => a + p[0], 0) / outline.length;
      const cy = outline.reduce((a, p) => a + p[1], 0) / outline.length;
      if (o.velocity_mps && Math.hypot(o.velocity_mps[0], o.velocity_mps[1]) > MIN_SPEED_MPS) {
        const [ax, ay] = worldToScreen(cx, cy);
        const [bx, by] = worldToScreen(cx + o.velocity_mps[0], cy + o.velocity_mps[1]); // 1 s ahead
        arrow(ax, ay, bx, by, color);
      }
      const bound = o.partial ? "≥" : o.size_unsure ? "~" : "";
      const size = o.size_m ? ` ${bound}${o.size_m[0].toFixed(2)}×${o.size_m[1].toFixed(2)} m` : "";
      const [sx, sy] = worldToScreen(cx, cy);
      label(`${o.id}${o.class ? " " + o.class : ""}${size}`, sx + 6, sy - 20, color);
    }
  }

  function arrow(ax, ay, bx, by, color) {
    const angle = Math.atan2(by - ay, bx - ax);
    ctx.strokeStyle = color;
    ctx.fillStyle = color;
    ctx.lineWidth = 2;
    ctx.beginPath();
    ctx.moveTo(ax, ay);
    ctx.lineTo(bx, by);
    ctx.stroke();
    ctx.beginPath();
    ctx.moveTo(bx, by);
    ctx.lineTo(bx - 9 * Math.cos(angle - 0.4), by - 9 * Math.sin(angle - 0.4));
    ctx.lineTo(bx - 9 * Math.cos(angle + 0.4), by - 9 * Math.sin(angle + 0.4));
    ctx.closePath();
    ctx.fill();
  }

  function drawOriginAxes() {
    // The world frame's origin with 1 m axes: where (0, 0) is, which way x and y point.
    const [ox, oy] = worldToScreen(0, 0);
    const [xx, xy] = worldToScreen(1, 0);
    const [yx, yy] = worldToScreen(0, 1);
    arrow(ox, oy, xx, xy, COLORS.axisX);
    arrow(ox, oy, yx, yy, COLORS.axisY);
    ctx.font = "bold 12px system-ui, sans-serif";
    ctx.fillStyle = COLORS.axisX;
    ctx.fillText("x", xx + 4, xy + 4);
    ctx.fillStyle = COLORS.axisY;
    ctx.fillText("y", yx - 4, yy - 6);
  }

  function drawAxesGlyph() {
    const x0 = state.view.w - 60;
    const y0 = state.view.h - 20;
    arrow(x0, y0, x0 + 36, y0, COLORS.axisX);
    arrow(x0, y0, x0, y0 - 36, COLORS.axisY);
    ctx.font = "bold 12px system-ui, sans-serif";
    ctx.fillStyle = COLORS.axisX;
    ctx.fillText("x", x0 + 40, y0 + 4);
    ctx.fillStyle = COLORS.axisY;
    ctx.fillText("y", x0 - 4, y0 - 42);
  }

  function drawScaleBar() {
    const k = state.view.pxPerM;
    const steps = [0.05, 0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50, 100];
    const lengthM = steps.find((m) => m * k >= 80) || steps[steps.length - 1];
    const px = lengthM * k;
    const x0 = 16;
    const y0 = state.view.h - 18;
    ctx.fillStyle = "rgba(255, 255, 255, 0.85)";
    ctx.fillRect(x0 - 6, y0 - 22, px + 12, 30);
    ctx.fillStyle = "#1d1f24";
    ctx.fillRect(x0, y0 - 3, px, 4);
    ctx.fillRect(x0, y0 - 9, 2, 10);
    ctx.fillRect(x0 + px - 2, y0 - 9, 2, 10);
    ctx.font = "12px system-ui, sans-serif";
    ctx.fillText(lengthM >= 1 ? `${lengthM} m` : `${Math.round(lengthM * 100)} cm`, x0 + 4, y0 - 10);
  }

  // ---- side panel, summary, banner ----------------------------------------------------------
  function fmt(value, digits, unit) {
    return value === null || value === undefined ? "—" : `${Number(value).toFixed(digits)}\u00a0${unit}`;
  }

  function ago(seconds) {
    return seconds === null || seconds === undefined ? "—" : `${fmt(seconds, 1, "s")} ago`;
  }

  function renderPanel() {
    const status = state.status;
    pairsList.replaceChildren();
    if (!status || status.pairs.length === 0) {
      const li = document.createElement("li");
      li.className = "muted";
      li.textContent = "none yet";
      pairsList.append(li);
    }
    for (const pair of status ? status.pairs : []) {
      const s = pairState(pair);
      const li = document.createElement("li");
      li.dataset.pair = pair.pair;
      li.dataset.state = s;
      li.classList.toggle("stale", !live()); // the details are as last told
      const name = document.createElement("span");
      name.className = "name";
      name.textContent = pair.pair;
      const word = document.createElement("span");
      word.className = "state";
      word.textContent = { alive: "alive", dead: "DEAD", "no-depth": "no depth", unknown: "unknown" }[s];
      const detail = document.createElement("div");
      detail.className = "detail";
      const working = s === "alive" || s === "unknown"; // a dead pair has no rate nor latency now
      detail.textContent =
        (live() ? "" : "as last known: ") +
        `frame rate ${working ? fmt(pair.frame_rate_hz, 1, "Hz") : "—"} · ` +
        `latency ${working ? fmt(pair.capture_to_map_ms, 0, "ms") : "—"}\n` +
        `last tile ${ago(pair.last_tile_age_s)}` +
        (pair.floor_model ? ` · floor model ${pair.floor_model}` : "") +
        (pair.footprint_m ? "" : " · no calibration");
      detail.style.whiteSpace = "pre-line";
      li.append(name, word, detail);
      pairsList.append(li);
    }
    if (!status || status.objects === null || status.objects === undefined) {
      objectsBox.className = "muted";
      objectsBox.textContent = "map/objects not served";
    } else {
      objectsBox.className = live() ? "" : "muted";
      const moving = status.objects.filter((o) => o.velocity_mps && Math.hypot(...o.velocity_mps) > MIN_SPEED_MPS);
      objectsBox.textContent = (live() ? "" : "as last known: ") + (status.objects.length
        ? `${status.objects.length} tracked, ${moving.length} moving` +
          (moving.length ? `: ${moving.map((o) => `${o.id} (${Math.hypot(...o.velocity_mps).toFixed(1)} m/s)`).join(", ")}` : "")
        : "none tracked");
    }
  }

  function renderLegend() {
    const h = state.hello;
    if (!h) return;
    legend.replaceChildren();
    const swatch = (rgb, text) => {
      const row = document.createElement("div");
      const box = document.createElement("i");
      box.style.background = `rgb(${rgb.join(",")})`;
      row.append(box, document.createTextNode(text));
      legend.append(row);
    };
    swatch(h.colors.free, `free (p ≤ ${h.free_max}%)`);
    swatch(h.colors.occupied, `occupied (p ≥ ${h.occupied_min}%)`);
    swatch(mix(h.colors.free, h.colors.occupied, 0.5), "undecided");
    swatch(h.colors.unknown, "unknown");
    if (heightMode.checked) {
      const row = document.createElement("div");
      const bar = document.createElement("i");
      bar.className = "ramp";
      bar.style.background = `linear-gradient(to right, ${HEIGHT_RAMP.map((c) => `rgb(${c.join(",")})`).join(", ")})`;
      row.append(document.createTextNode("0"), bar, document.createTextNode(`${h.height_band_m[1]} m`));
      legend.append(row);
    }
  }

  function renderSummary() {
    const status = state.status;
    const map = state.map;
    const parts = [];
    if (map) parts.push(`map v${map.version} · ${map.cols}×${map.rows} cells @ ${Math.round(map.resolution_m * 100)} cm`);
    if (status && status.map && status.map.capture_age_s !== null) parts.push(`newest capture ${status.map.capture_age_s.toFixed(1)} s ago`);
    if (status && status.pairs.length === 0) {
      parts.push("no pairs yet");
    } else if (status && !live()) {
      const n = status.pairs.length;
      parts.push(`${n} pair${n === 1 ? "" : "s"}, state unknown`); // as the panel says
    } else if (status) {
      const alive = status.pairs.filter((p) => pairState(p) === "alive").length;
      parts.push(`${alive}/${status.pairs.length} pairs alive`);
    }
    summary.textContent = parts.join(" · ") || (state.connected ? "waiting for the map…" : "connecting…");
  }

  function renderBanner() {
    let kind = null;
    let text = "";
    const silentS = (performance.now() - state.lastMessageMs) / 1000;
    if (!state.connected && state.rejected) {
      kind = "rejected";
      text = "Access token rejected by the viewer — open the URL `overgrid view` printed";
    } else if (!state.connected) {
      kind = "disconnected";
      text = "Connection to the viewer lost — reconnecting…";
    } else if (silentS > SERVER_SILENT_S) {
      kind = "disconnected";
      text = `No word from the viewer for ${silentS.toFixed(0)} s — reconnecting…`;
    } else if (stale()) {
      kind = "stale";
      const since = state.status.fusion_silent_s;
      const limit = state.hello ? ` (the limit is ${state.hello.stale_after_s} s)` : "";
      text =
        since === null
          ? "Map unavailable: the fusion service has not answered yet"
          : `Map is stale: no answer from the fusion service for ${since.toFixed(0)} s${limit} — showing the last map`;
    }
    banner.hidden = kind === null;
    banner.dataset.kind = kind || "";
    banner.textContent = text;
  }

  function renderReadout() {
    const p = state.pointer;
    const map = state.map;
    if (!p || !map) return;
    const [x, y] = screenToWorld(p[0], p[1]);
    const r = map.resolution_m;
    const i = Math.floor(x / r);
    const j = Math.floor(y / r);
    const col = i - map.i0;
    const row = j - map.j0;
    let cell = "outside the map";
    if (col >= 0 && row >= 0 && col < map.cols && row < map.rows) {
      const value = map.occupancy[row * map.cols + col];
      const mm = map.height[row * map.cols + col];
      const prob = value < 0 ? "unknown" : `p(occ) ${value}%`;
      const height = mm === state.hello.no_height_mm ? "height —" : `height ${(mm / 1000).toFixed(2)} m`;
      cell = `${prob}  ${height}  ${lastObserved(i, j)}`;
    }
    readout.textContent = `x ${x.toFixed(2)} m  y ${y.toFixed(2)} m  cell (${i}, ${j})  ${cell}`;
  }

  // "last observed" comes from the viewer (cell?i=&j=), which answers from the last-seen layer it
  // fetches with the height layer: hovering asks the viewer, never fusion.
  function lastObserved(i, j) {
    const key = `${i},${j}`;
    const seen = state.seen;
    if (seen.key !== key) {
      seen.wanted = key;
      askLastSeen();
      return "last observed …";
    }
    if (performance.now() - seen.receivedMs > CELL_REFRESH_MS) {
      seen.wanted = key;
      askLastSeen();
    }
    if (seen.lastSeenS === null) return "last observed — (no layer yet)";
    if (seen.lastSeenS === 0) return "never observed";
    const ageS = seen.nowS - seen.lastSeenS + (performance.now() - seen.receivedMs) / 1000;
    return `last observed ${Math.max(ageS, 0).toFixed(1)} s ago`;
  }

  function askLastSeen() {
    const seen = state.seen;
    if (seen.asking || seen.wanted === null) return;
    const waitMs = seen.lastAskMs + CELL_QUERY_MS - performance.now();
    if (waitMs > 0) {
      seen.asking = true;
      setTimeout(() => { seen.asking = false; askLastSeen(); }, waitMs);
      return;
    }
    const key = seen.wanted;
    const [i, j] = key.split(",");
    seen.asking = true;
    seen.lastAskMs = performance.now();
    fetch(`cell?i=${i}&j=${j}`, { cache: "no-store" })
      .then((response) => (response.ok ? response.json() : Promise.reject(response.status)))
      .then((answer) => {
        Object.assign(seen, { key, lastSeenS: answer.last_seen_s, nowS: answer.now_s, receivedMs: performance.now() });
        if (seen.wanted === key) seen.wanted = null;
      })
      .catch(() => {}) // the viewer is gone: the banner says so, the readout keeps "…"
      .finally(() => {
        seen.asking = false;
        renderReadout();
        askLastSeen();
      });
  }

  // ---- socket -------------------------------------------------------------------------------
  function connect() {
    state.retryTimer = null;
    const url = new URL("ws", location.href);
    url.protocol = location.protocol === "https:" ? "wss:" : "ws:";
    url.search = "";
    const socket = new WebSocket(url);
    socket.binaryType = "arraybuffer";
    state.socket = socket;
    state.socketStartedMs = performance.now();
    let opened = false;
    socket.onopen = () => {
      opened = true;
      state.connected = true;
      state.rejected = false;
      state.retryMs = RETRY_MIN_MS;
      state.lastMessageMs = performance.now();
      renderBanner();
    };
    socket.onmessage = (event) => {
      state.lastMessageMs = performance.now();
      if (typeof event.data === "string") {
        const message = JSON.parse(event.data);
        if (message.type === "hello") {
          state.hello = message;
          renderLegend();
        } else if (message.type === "status") {
          state.status = message;
          renderPanel();
          queueDraw();
        }
      } else {
        const frame = readFrame(event.data);
        state.frames[frame.header.type] = (state.frames[frame.header.type] || 0) + 1;
        if (frame.header.type === "map") onMapFrame(frame);
        else if (frame.header.type === "rect") onRectFrame(frame);
      }
      renderSummary();
      renderBanner();
    };
    socket.onclose = () => {
      if (!opened) probeToken(); // a refused handshake says nothing of why: ask over HTTP
      abandon(socket);
    };
    socket.onerror = () => socket.close();
  }

  // Give up on a socket and try a new one (after the back-off). Its handlers go first: a socket
  // whose peer stopped answering stays CLOSING for tens of seconds after close(), and must
  // neither hold up the next attempt nor speak after it.
  function abandon(socket) {
    socket.onopen = socket.onmessage = socket.onclose = socket.onerror = null;
    if (socket.readyState === WebSocket.CONNECTING || socket.readyState === WebSocket.OPEN) socket.close();
    if (state.socket !== socket) return;
    state.socket = null;
    state.connected = false;
    renderBanner();
    renderSummary();
    if (state.retryTimer === null) state.retryTimer = setTimeout(connect, state.retryMs);
    state.retryMs = Math.min(state.retryMs * 2, RETRY_MAX_MS);
  }

  // Whether the viewer turns this page away (401: it was restarted with another --token) rather
  // than being unreachable: the same cookie and origin as the socket, on a cheap read.
  function probeToken() {
    if (state.probing) return;
    state.probing = true;
    fetch("cell?i=0&j=0", { cache: "no-store", signal: AbortSignal.timeout(2000) })
      .then((response) => {
        state.rejected = response.status === 401;
      })
      .catch(() => {
        state.rejected = false; // unreachable: the plain "reconnecting" is right
      })
      .finally(() => {
        state.probing = false;
        renderBanner();
      });
  }

  let wasLive = null;
  setInterval(() => {
    renderBanner();
    renderReadout(); // the age of "last observed" goes on
    if (live() !== wasLive) { // the link or fusion went or came back: say which values are current
      wasLive = live();
      renderPanel();
      renderSummary();
      queueDraw();
    }
    const socket = state.socket;
    if (!socket) return;
    const nowMs = performance.now();
    if (state.connected && (nowMs - state.lastMessageMs) / 1000 > SERVER_SILENT_S) abandon(socket);
    else if (!state.connected && (nowMs - state.socketStartedMs) / 1000 > CONNECT_TIMEOUT_S) abandon(socket);
  }, 1000);

  // ---- pointer: pan, zoom, readout ----------------------------------------------------------
  // A mouse drags and wheels; fingers drag, and two pinch (zoom about their midpoint, pan with it).
  const pressed = new Map(); // pointer id → its [x, y] on the canvas, in CSS pixels
  let pinch = null; // the two first pointers' distance and midpoint when last seen

  function onCanvas(event) {
    const rect = canvas.getBoundingClientRect();
    return [event.clientX - rect.left, event.clientY - rect.top];
  }

  function pinchOf() {
    const [a, b] = pressed.values();
    return { distance: Math.max(Math.hypot(a[0] - b[0], a[1] - b[1]), 1), mid: [(a[0] + b[0]) / 2, (a[1] + b[1]) / 2] };
  }

  // Scale the view by `factor`, and put the world point that was under `from` under `to`.
  function zoomAt(from, to, factor) {
    const [wx, wy] = screenToWorld(from[0], from[1]);
    state.view.pxPerM = Math.min(Math.max(state.view.pxPerM * factor, 1), 5000);
    const [nx, ny] = screenToWorld(to[0], to[1]);
    state.view.cx += wx - nx;
    state.view.cy += wy - ny;
    state.userMoved = true;
    queueDraw();
  }

  canvas.addEventListener("pointerdown", (event) => {
    const at = onCanvas(event);
    pressed.set(event.pointerId, at);
    pinch = pressed.size >= 2 ? pinchOf() : null;
    canvas.setPointerCapture(event.pointerId);
    canvas.classList.add("dragging");
    state.pointer = at; // a tap reads the cell out too
    renderReadout();
  });
  canvas.addEventListener("pointermove", (event) => {
    const at = onCanvas(event);
    state.pointer = at;
    const before = pressed.get(event.pointerId);
    if (before) {
      pressed.set(event.pointerId, at);
      if (pinch) {
        const now = pinchOf();
        zoomAt(pinch.mid, now.mid, now.distance / pinch.distance);
        pinch = now;
      } else {
        zoomAt(before, at, 1);
      }
    }
    renderReadout();
  });
  const release = (event) => {
    pressed.delete(event.pointerId);
    pinch = pressed.size >= 2 ? pinchOf() : null;
    if (pressed.size === 0) canvas.classList.remove("dragging");
  };
  canvas.addEventListener("pointerup", release);
  canvas.addEventListener("pointercancel", release);
  canvas.addEventListener("pointerleave", (event) => {
    if (event.pointerType === "touch") return; // a lifted finger: the cell it tapped stays read out
    state.pointer = null; // the readout is of the cell under the pointer: none now
    readout.textContent = "\u00a0"; // its line kept: the canvas must not change size under it
  });
  canvas.addEventListener(
    "wheel",
    (event) => {
      event.preventDefault();
      const at = onCanvas(event);
      zoomAt(at, at, Math.exp(-event.deltaY * 0.0015)); // the point under the pointer stays put
      renderReadout();
    },
    { passive: false },
  );
  document.getElementById("fit").addEventListener("click", () => {
    state.userMoved = false;
    fit();
  });
  heightMode.addEventListener("change", () => {
    if (state.map) paint(0, 0, state.map.cols, state.map.rows);
    renderLegend();
    queueDraw();
  });
  window.addEventListener("resize", queueDraw);

  // For tests and for the curious: read what is drawn where.
  window.overgridView = {
    state,
    worldToScreen,
    pixelAt(x, y) {
      draw();
      const [sx, sy] = worldToScreen(x, y);
      const k = state.view.pixelRatio;
      return Array.from(ctx.getImageData(Math.round(sx * k), Math.round(sy * k), 1, 1).data);
    },
    // The [r, g, b] of every device pixel within `radius` CSS px of world point (x, y): for thin
    // lines.
    pixelsNear(x, y, radius) {
      draw();
      const [sx, sy] = worldToScreen(x, y);
      const k = state.view.pixelRatio;
      const reach = Math.round(radius * k);
      const size = 2 * reach + 1;
      const data = ctx.getImageData(Math.round(sx * k) - reach, Math.round(sy * k) - reach, size, size).data;
      const pixels = [];
      for (let k = 0; k < data.length; k += 4) pixels.push([data[k], data[k + 1], data[k + 2]]);
      return pixels;
    },
  };

  connect();
  queueDraw();
})();
