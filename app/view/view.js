// The live view of a room: plan, accuracy backdrop, tracks with 95 % ellipses and trails.
// Plain JavaScript and SVG, served by the service itself; every request goes to this origin
// with the key in X-API-Key (the stream is read with fetch: EventSource cannot send it).
"use strict";

(() => {
  const KEY_STORAGE = "vlp-view-key";
  const TRAIL_S = 30;
  const SEMI_AXIS_PER_SQRT_EIGENVALUE = 2.448; // sqrt(chi2_2(0.95))
  const MARGIN_M = 0.6;
  const SVG_NS = "http://www.w3.org/2000/svg";
  const $ = (id) => document.getElementById(id);

  const state = {
    key: sessionStorage.getItem(KEY_STORAGE),
    roomId: null,
    room: null, // {length, width}
    tracks: new Map(), // id -> {track, trail: [[t, x, y]], nodes}
    lastEventId: null,
    abort: null,
    dirty: true,
    view: null, // {x, y, w, h} in plan coordinates (metres, y down)
    frames: 0,
    fps: 0,
    events: 0,
  };

  // -- API ------------------------------------------------------------------------------
  async function api(path, options = {}) {
    const headers = Object.assign({ "X-API-Key": state.key }, options.headers || {});
    const response = await fetch(path, Object.assign({}, options, { headers }));
    if (response.status === 401) {
      forgetKey("the key was refused");
      throw new Error("unauthorised");
    }
    return response;
  }

  async function json(path) {
    const response = await api(path);
    if (!response.ok) throw new Error(`${path}: ${response.status}`);
    return response.json();
  }

  function setStatus(text) {
    $("status").textContent = text;
  }

  // -- key ------------------------------------------------------------------------------
  function askKey() {
    $("key-form").hidden = false;
    $("controls").hidden = true;
    $("key-input").focus();
  }

  function forgetKey(reason) {
    sessionStorage.removeItem(KEY_STORAGE);
    state.key = null;
    stopStream();
    setStatus(reason || "");
    askKey();
  }

  // -- plan -----------------------------------------------------------------------------
  function el(name, attributes, parent) {
    const node = document.createElementNS(SVG_NS, name);
    for (const [k, v] of Object.entries(attributes)) node.setAttribute(k, v);
    if (parent) parent.appendChild(node);
    return node;
  }

  const sy = (y) => state.room.width - y; // plan y (up) -> SVG y (down)

  function clear(id) {
    const group = $(id);
    while (group.firstChild) group.removeChild(group.firstChild);
    return group;
  }

  function drawPlan(layout) {
    const room = layout.room;
    state.room = { length: room.length, width: room.width };
    el("rect", { class: "wall", x: 0, y: 0, width: room.length, height: room.width }, clear("walls"));
    const leds = clear("leds");
    const r = Math.max(0.04, Math.min(room.length, room.width) / 80);
    for (const led of layout.leds) el("circle", { class: "led", cx: led.x, cy: sy(led.y), r }, leds);
    fit();
  }

  function heatColour(value, low, high) {
    // Pale green (accurate) to pale sand (poor); inf (position not determined) is grey.
    if (!Number.isFinite(value)) return "#d9d9d9";
    const t = Math.min(1, Math.max(0, (Math.log(value) - Math.log(low)) / (Math.log(high) - Math.log(low) || 1)));
    const from = [190, 224, 200], to = [250, 238, 220];
    const c = from.map((f, i) => Math.round(f + (to[i] - f) * t));
    return `rgb(${c[0]},${c[1]},${c[2]})`;
  }

  function drawBackdrop(map) {
    const group = clear("backdrop");
    const finite = map.accuracy_m.flat().filter(Number.isFinite);
    if (!finite.length) return;
    const low = Math.min(...finite), high = Math.max(...finite);
    map.accuracy_m.forEach((row, iy) => {
      row.forEach((value, ix) => {
        const x0 = map.x_edges[ix], x1 = map.x_edges[ix + 1];
        const y0 = map.y_edges[iy], y1 = map.y_edges[iy + 1];
        el("rect", { class: "cell", x: x0, y: sy(y1), width: x1 - x0, height: y1 - y0, fill: heatColour(value, low, high) }, group);
      });
    });
  }

  // -- zoom and pan ---------------------------------------------------------------------
  function fit() {
    const { length, width } = state.room;
    state.view = { x: -MARGIN_M, y: -MARGIN_M, w: length + 2 * MARGIN_M, h: width + 2 * MARGIN_M };
    applyView();
  }

  function applyView() {
    const v = state.view;
    $("plan").setAttribute("viewBox", `${v.x} ${v.y} ${v.w} ${v.h}`);
    state.dirty = true;
  }

  function toPlan(clientX, clientY) {
    const box = $("plan").getBoundingClientRect();
    const v = state.view;
    const scale = Math.max(v.w / box.width, v.h / box.height); // preserveAspectRatio meet
    const cx = v.x + v.w / 2 + (clientX - box.left - box.width / 2) * scale;
    const cy = v.y + v.h / 2 + (clientY - box.top - box.height / 2) * scale;
    return { x: cx, y: cy, scale };
  }

  function zoomAt(clientX, clientY, factor) {
    const p = toPlan(clientX, clientY);
    const v = state.view;
    state.view = { x: p.x - (p.x - v.x) * factor, y: p.y - (p.y - v.y) * factor, w: v.w * factor, h: v.h * factor };
    applyView();
  }

  function installZoom() {
    const svg = $("plan");
    const pointers = new Map();
    let pinch = null;
    svg.addEventListener("wheel", (event) => {
      event.preventDefault();
      zoomAt(event.clientX, event.clientY, Math.exp(event.deltaY * 0.0015));
    }, { passive: false });
    svg.addEventListener("pointerdown", (event) => {
      svg.setPointerCapture(event.pointerId);
      pointers.set(event.pointerId, { x: event.clientX, y: event.clientY });
    });
    svg.addEventListener("pointermove", (event) => {
      if (!pointers.has(event.pointerId) || !state.view) return;
      const before = pointers.get(event.pointerId);
      pointers.set(event.pointerId, { x: event.clientX, y: event.clientY });
      if (pointers.size === 2) {
        const [a, b] = [...pointers.values()];
        const distance = Math.hypot(a.x - b.x, a.y - b.y);
        if (pinch) zoomAt((a.x + b.x) / 2, (a.y + b.y) / 2, pinch / Math.max(distance, 1));
        pinch = distance;
      } else if (pointers.size === 1) {
        const { scale } = toPlan(event.clientX, event.clientY);
        state.view.x -= (event.clientX - before.x) * scale;
        state.view.y -= (event.clientY - before.y) * scale;
        applyView();
      }
    });
    const release = (event) => {
      pointers.delete(event.pointerId);
      pinch = null;
    };
    svg.addEventListener("pointerup", release);
    svg.addEventListener("pointercancel", release);
  }

  // -- tracks ---------------------------------------------------------------------------
  function ellipseOf(cov) {
    const [[a, b], [, c]] = cov;
    const mid = (a + c) / 2, half = Math.sqrt(((a - c) / 2) ** 2 + b * b);
    const major = Math.max(mid + half, 0), minor = Math.max(mid - half, 0);
    const angle = 0.5 * Math.atan2(2 * b, a - c); // of the major axis, plan coordinates
    return {
      rx: SEMI_AXIS_PER_SQRT_EIGENVALUE * Math.sqrt(major),
      ry: SEMI_AXIS_PER_SQRT_EIGENVALUE * Math.sqrt(minor),
      degrees: (-angle * 180) / Math.PI, // y flips on screen
    };
  }

  function inside(x, y) {
    return x >= 0 && y >= 0 && x <= state.room.length && y <= state.room.width;
  }

  function onTrack(track) {
    const now = Date.parse(track.time) / 1000;
    let entry = state.tracks.get(track.id);
    if (!entry) {
      entry = { track, trail: [], nodes: null };
      state.tracks.set(track.id, entry);
    }
    entry.track = track;
    const last = entry.trail[entry.trail.length - 1];
    if (!last || last[0] !== now || last[1] !== track.x || last[2] !== track.y) entry.trail.push([now, track.x, track.y]);
    while (entry.trail.length && entry.trail[0][0] < now - TRAIL_S) entry.trail.shift();
    state.dirty = true;
  }

  function onRemoved(data) {
    const entry = state.tracks.get(data.id);
    if (entry && entry.nodes) for (const node of Object.values(entry.nodes)) node.remove();
    state.tracks.delete(data.id);
    state.dirty = true;
  }

  function nodesOf(entry) {
    if (entry.nodes) return entry.nodes;
    const id = entry.track.id;
    entry.nodes = {
      trail: el("polyline", { class: "trail", "data-track-id": id }, $("trails")),
      raw: el("path", { class: "raw", "data-track-id": id }, $("raws")),
      ellipse: el("ellipse", { class: "ellipse", "data-track-id": id }, $("ellipses")),
      label: el("text", { class: "label", "data-track-id": id }, $("labels")),
    };
    return entry.nodes;
  }

  function render() {
    if (!state.room) return;
    const showRaw = $("show-raw").checked, showLost = $("show-lost").checked;
    const unit = state.view ? state.view.w / 100 : 0.05;
    for (const entry of state.tracks.values()) {
      const t = entry.track, n = nodesOf(entry);
      const e = ellipseOf(t.covariance);
      const out = !inside(t.x, t.y);
      const cls = `${t.status}${out ? " outside" : ""}`;
      const hide = t.status === "lost" && !showLost;
      n.ellipse.setAttribute("class", `ellipse ${cls}${hide ? " hidden" : ""}`);
      n.ellipse.setAttribute("cx", t.x);
      n.ellipse.setAttribute("cy", sy(t.y));
      n.ellipse.setAttribute("rx", e.rx);
      n.ellipse.setAttribute("ry", e.ry);
      n.ellipse.setAttribute("transform", `rotate(${e.degrees} ${t.x} ${sy(t.y)})`);
      n.trail.setAttribute("class", `trail ${t.status}${hide ? " hidden" : ""}`);
      n.trail.setAttribute("points", entry.trail.map(([, x, y]) => `${x},${sy(y)}`).join(" "));
      n.label.setAttribute("class", `label${out ? " outside" : ""}${hide ? " hidden" : ""}`);
      n.label.setAttribute("font-size", 1.6 * unit); // user units are metres
      n.label.setAttribute("x", t.x + unit);
      n.label.setAttribute("y", sy(t.y) - unit);
      n.label.textContent = (t.terminal_id || t.id.slice(0, 6)) + (out ? " (outside the plan)" : "");
      const raw = t.raw;
      const rawOut = raw && !inside(raw.x, raw.y);
      n.raw.setAttribute("class", `raw${rawOut ? " outside" : ""}${!showRaw || !raw || hide ? " hidden" : ""}`);
      if (raw) {
        const s = unit * 0.8, rx = raw.x, ry = sy(raw.y);
        n.raw.setAttribute("d", `M${rx - s},${ry - s}L${rx + s},${ry + s}M${rx - s},${ry + s}L${rx + s},${ry - s}`);
      }
    }
  }

  function frame() {
    state.frames += 1;
    if (state.dirty) {
      state.dirty = false;
      render();
    }
    requestAnimationFrame(frame);
  }

  setInterval(() => {
    state.fps = state.frames;
    state.frames = 0;
    $("fps").textContent = `${state.fps} frames/s, ${state.tracks.size} tracks`;
  }, 1000);

  // -- stream ---------------------------------------------------------------------------
  function stopStream() {
    if (state.abort) state.abort.abort();
    state.abort = null;
  }

  function dispatch(message) {
    if (message.id !== null) state.lastEventId = message.id;
    if (!message.data) return;
    const data = JSON.parse(message.data);
    state.events += 1;
    if (message.event === "track") onTrack(data);
    else if (message.event === "removed") onRemoved(data);
  }

  async function follow(roomId, abort) {
    let retryMs = 1000;
    while (!abort.signal.aborted) {
      try {
        const headers = { Accept: "text/event-stream" };
        if (state.lastEventId !== null) headers["Last-Event-ID"] = state.lastEventId;
        const response = await api(`/v1/rooms/${roomId}/tracks/stream`, { headers, signal: abort.signal });
        if (!response.ok) throw new Error(`stream: ${response.status}`);
        setStatus("live");
        const reader = response.body.getReader();
        const decoder = new TextDecoder();
        let buffer = "", message = { event: "message", id: null, data: "" };
        for (;;) {
          const { value, done } = await reader.read();
          if (done) break;
          buffer += decoder.decode(value, { stream: true });
          let newline;
          while ((newline = buffer.search(/\r\n|\r|\n/)) >= 0) {
            const line = buffer.slice(0, newline);
            buffer = buffer.slice(newline + (buffer.startsWith("\r\n", newline) ? 2 : 1));
            if (line === "") {
              dispatch(message);
              message = { event: "message", id: null, data: "" };
            } else if (!line.startsWith(":")) {
              const colon = line.indexOf(":");
              const field = colon < 0 ? line : line.slice(0, colon);
              const value = colon < 0 ? "" : line.slice(colon + 1).replace(/^ /, "");
              if (field === "event") message.event = value;
              else if (field === "data") message.data += (message.data ? "\n" : "") + value;
              else if (field === "id") message.id = value;
              else if (field === "retry" && /^\d+$/.test(value)) retryMs = Number(value);
            }
          }
        }
      } catch (error) {
        if (abort.signal.aborted || !state.key) return;
      }
      setStatus("reconnecting");
      await new Promise((resolve) => setTimeout(resolve, retryMs));
    }
  }

  // -- rooms ----------------------------------------------------------------------------
  async function openRoom(roomId) {
    stopStream();
    state.roomId = roomId;
    state.tracks.clear();
    state.lastEventId = null;
    for (const id of ["trails", "raws", "ellipses", "labels", "backdrop"]) clear(id);
    const room = await json(`/v1/rooms/${roomId}`);
    drawPlan(room.layout);
    json(`/v1/rooms/${roomId}/tracking/accuracy`).then(drawBackdrop).catch(() => setStatus("no accuracy map"));
    const abort = new AbortController();
    state.abort = abort;
    follow(roomId, abort);
  }

  async function start() {
    $("key-form").hidden = true;
    $("controls").hidden = false;
    setStatus("loading rooms");
    const page = await json("/v1/rooms?limit=100");
    const select = $("room-select");
    while (select.firstChild) select.removeChild(select.firstChild);
    for (const room of page.items) {
      const option = document.createElement("option");
      option.value = room.id;
      option.textContent = room.name;
      select.appendChild(option);
    }
    const wanted = new URLSearchParams(location.hash.slice(1)).get("room");
    const chosen = page.items.find((r) => r.id === wanted) || page.items[0];
    if (!chosen) {
      setStatus("no rooms yet");
      return;
    }
    select.value = chosen.id;
    await openRoom(chosen.id);
  }

  function init() {
    $("key-form").addEventListener("submit", (event) => {
      event.preventDefault();
      state.key = $("key-input").value.trim();
      $("key-input").value = "";
      sessionStorage.setItem(KEY_STORAGE, state.key);
      start().catch((error) => setStatus(String(error.message || error)));
    });
    $("room-select").addEventListener("change", (event) => {
      location.hash = `room=${event.target.value}`;
      openRoom(event.target.value).catch((error) => setStatus(String(error.message || error)));
    });
    $("show-raw").addEventListener("change", () => (state.dirty = true));
    $("show-lost").addEventListener("change", () => (state.dirty = true));
    $("reset-zoom").addEventListener("click", () => state.room && fit());
    $("forget-key").addEventListener("click", () => forgetKey("key forgotten"));
    installZoom();
    requestAnimationFrame(frame);
    if (state.key) start().catch((error) => setStatus(String(error.message || error)));
    else askKey();
  }

  // What the page shows, for tests and for the curious (read-only copies).
  window.vlpView = {
    fps: () => state.fps,
    events: () => state.events,
    roomId: () => state.roomId,
    tracks: () => [...state.tracks.values()].map((entry) => entry.track),
  };

  init();
})();
