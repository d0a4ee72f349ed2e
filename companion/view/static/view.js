// The operator's view: draws the companion's scene and step messages on a metres grid (Leaflet,
// CRS.Simple: y north, x east). Live, messages come over the WebSocket /api/stream; a replay
// fetches /api/step/K for the slider's step. Read-only: the page never sends anything.
"use strict";
(function () {
  const params = new URLSearchParams(location.search);
  const token = params.get("token");
  const query = token ? "?token=" + encodeURIComponent(token) : "";
  const $ = (id) => document.getElementById(id);
  const ll = (x, y) => L.latLng(y, x);
  const pts = (xy) => xy.map((p) => ll(p[0], p[1]));
  const state = { scene: null, message: null, unseen: null, lastAt: 0, ws: null,
                  everConnected: false, bounds: null };
  window.companionView = state;

  const map = L.map("map", {
    crs: L.CRS.Simple, preferCanvas: true, minZoom: -4, maxZoom: 7, zoomSnap: 0.25,
    attributionControl: false,
  });
  state.map = map;  // for scripts and tests: where the page draws what
  L.control.scale({ imperial: false, metric: true }).addTo(map);
  // the operator's orthophoto lies in a pane of its own, under every other layer
  map.createPane("ortho");
  map.getPane("ortho").style.zIndex = 350;
  map.getPane("ortho").style.pointerEvents = "none";
  let orthoOverlay = null;
  const layers = {};
  for (const name of ["grid", "heat", "fence", "area", "footprint", "path", "components",
                      "scans", "tracks", "labels", "home", "vehicle"]) {
    layers[name] = L.layerGroup().addTo(map);
  }
  let heatOverlay = null;
  let fitted = false;

  function ellipse(x, y, cov, sigma) {
    // the sigma ellipse of a 2x2 covariance [xx, xy, yy] about (x, y), as points
    const [a, b, c] = cov;
    const tr = a + c, det = a * c - b * b;
    const disc = Math.sqrt(Math.max(tr * tr / 4 - det, 0));
    const l1 = Math.max(tr / 2 + disc, 0), l2 = Math.max(tr / 2 - disc, 0);
    const angle = Math.abs(b) > 1e-12 ? Math.atan2(l1 - a, b) : (a >= c ? 0 : Math.PI / 2);
    const r1 = sigma * Math.sqrt(l1), r2 = sigma * Math.sqrt(l2);
    const out = [];
    for (let k = 0; k < 36; k++) {
      const t = (2 * Math.PI * k) / 36;
      const u = r1 * Math.cos(t), v = r2 * Math.sin(t);
      out.push(ll(x + u * Math.cos(angle) - v * Math.sin(angle),
                  y + u * Math.sin(angle) + v * Math.cos(angle)));
    }
    return out;
  }

  function drawOrtho(ortho) {
    // the orthophoto of the scene (its PNG and its bounds in grid metres), with its toggle
    if (orthoOverlay) { map.removeLayer(orthoOverlay); orthoOverlay = null; }
    $("ortho-toggle").hidden = !ortho;
    state.ortho = ortho || null;
    if (!ortho) return;
    const [[w, s], [e, n]] = ortho.bounds;
    orthoOverlay = L.imageOverlay(ortho.url + query, L.latLngBounds([ll(w, s), ll(e, n)]), {
      pane: "ortho", interactive: false, alt: `orthophoto ${ortho.name}`, className: "orthophoto",
    });
    orthoOverlay.on("add", () => {  // the image exists once the map has a view
      const img = orthoOverlay.getElement();
      img.dataset.west = String(w); img.dataset.south = String(s);
      img.dataset.east = String(e); img.dataset.north = String(n);
    });
    if ($("ortho-on").checked) orthoOverlay.addTo(map);
  }

  $("ortho-on").addEventListener("change", () => {
    if (!orthoOverlay) return;
    if ($("ortho-on").checked) orthoOverlay.addTo(map); else map.removeLayer(orthoOverlay);
  });

  function drawScene(scene) {
    state.scene = scene;
    drawOrtho(scene.orthophoto);
    layers.grid.clearLayers(); layers.area.clearLayers(); layers.fence.clearLayers();
    const [w, h] = scene.size_m;
    const step = Math.max(w, h) > 200 ? 50 : 10;
    for (let x = 0; x <= w + 1e-6; x += step) {
      L.polyline([ll(x, 0), ll(x, h)], { color: "#9ca3af", weight: 0.5, interactive: false }).addTo(layers.grid);
    }
    for (let y = 0; y <= h + 1e-6; y += step) {
      L.polyline([ll(0, y), ll(w, y)], { color: "#9ca3af", weight: 0.5, interactive: false }).addTo(layers.grid);
    }
    if (scene.area) {
      L.polygon(pts(scene.area), { color: "#1d4ed8", weight: 2, fill: false }).addTo(layers.area);
    }
    if (scene.geofence) {
      L.polygon(pts(scene.geofence), { color: "#dc2626", weight: 2, dashArray: "6 4", fill: false }).addTo(layers.fence);
    }
    $("grid").textContent = `grid: metres east / north of the search area's south-west corner ` +
      `(UTM zone ${scene.utm_zone}, EPSG:${scene.utm_epsg}, origin E ${scene.origin_utm[0]} ` +
      `N ${scene.origin_utm[1]}); lines every ${step} m`;
    if (scene.notes && scene.notes.length) {
      $("notes").textContent = scene.notes.join(" ");
      $("notes").hidden = false;
    }
    if (!fitted) {
      const bounds = L.latLngBounds([ll(0, 0), ll(w, h)]);
      if (scene.geofence) scene.geofence.forEach((p) => bounds.extend(ll(p[0], p[1])));
      state.bounds = bounds.pad(0.05);
      map.fitBounds(state.bounds);
      fitted = true;
    }
  }

  function heatImage(heat) {
    const canvas = document.createElement("canvas");
    canvas.width = heat.nx; canvas.height = heat.ny;
    const ctx = canvas.getContext("2d");
    const img = ctx.createImageData(heat.nx, heat.ny);
    const cells = atob(heat.cells);
    for (let row = 0; row < heat.ny; row++) {
      for (let col = 0; col < heat.nx; col++) {
        const v = cells.charCodeAt(row * heat.nx + col) / 255;
        const o = ((heat.ny - 1 - row) * heat.nx + col) * 4;  // rows come from the south
        img.data[o] = 255; img.data[o + 1] = Math.round(220 * (1 - v)); img.data[o + 2] = 0;
        img.data[o + 3] = v < 0.02 ? 0 : Math.round(20 + 180 * v);
      }
    }
    ctx.putImageData(img, 0, 0);
    return canvas.toDataURL();
  }

  function drawHeat(heat) {
    if (!heat) {
      if (heatOverlay) { layers.heat.removeLayer(heatOverlay); heatOverlay = null; }
      return;
    }
    const bounds = L.latLngBounds([ll(0, 0), ll(heat.nx * heat.cell_m, heat.ny * heat.cell_m)]);
    const url = heatImage(heat);
    if (heatOverlay) { heatOverlay.setUrl(url); heatOverlay.setBounds(bounds); } else {
      heatOverlay = L.imageOverlay(url, bounds, { opacity: 0.85, interactive: false }).addTo(layers.heat);
      heatOverlay.getElement() && heatOverlay.getElement().classList.add("heat");
    }
  }

  function fmtAgo(seconds) {
    if (seconds < 1) return "now";
    if (seconds < 120) return `${Math.round(seconds)} s ago`;
    return `${Math.round(seconds / 60)} min ago`;
  }

  function drawTable(m) {
    const body = $("tracks").tBodies[0];
    const rows = [];
    for (const t of m.tracks.filter((t) => t.confirmed)) {
      const tr = document.createElement("tr");
      const state = t.coasting ? "coasting" : "seen";
      tr.dataset.trackId = String(t.id);
      tr.dataset.lat = String(t.lat); tr.dataset.lon = String(t.lon);
      tr.dataset.x = String(t.x); tr.dataset.y = String(t.y);
      tr.dataset.state = state;
      tr.className = state;
      for (const [text, cls] of [[String(t.id), ""], [t.lat.toFixed(7), "num"],
                                 [t.lon.toFixed(7), "num"], [fmtAgo(m.t_s - t.seen_s), ""],
                                 [state, ""]]) {
        const td = document.createElement("td");
        td.textContent = text; if (cls) td.className = cls;
        tr.appendChild(td);
      }
      rows.push(tr);
    }
    body.replaceChildren(...rows);
    $("no-tracks").hidden = rows.length > 0;
  }

  function chip(id, text, ok) {
    const el = $(id);
    el.textContent = text;
    el.classList.toggle("ok", ok === true);
    el.classList.toggle("bad", ok === false);
  }

  function drawStep(m) {
    state.message = m;
    document.body.dataset.seq = String(m.seq);
    // a replay of a run folder of an earlier version: its steps recorded no status
    const unknown = state.scene && state.scene.mode === "replay" ? " not recorded" : " –";
    chip("mission", m.mission || "mission" + unknown, null);
    chip("link", m.link_ok === false ? "link lost" : m.link_ok ? "link ok" : "link" + unknown, m.link_ok);
    chip("camera", m.camera_ok === false ? "camera: no picture" : m.camera_ok ? "camera ok" : "camera" + unknown, m.camera_ok);
    chip("clock", `t ${m.t_s.toFixed(1)} s${m.blind ? " · blind: " + m.blind : ""}`, m.blind ? false : null);
    const expected = state.scene && state.scene.expected_targets;
    chip("expected", `targets ≈ ${m.expected_targets.toFixed(1)}${expected ? " of " + expected : ""}`, null);

    drawHeat(m.heat);
    layers.footprint.clearLayers();
    if (m.footprint) {
      L.polygon(pts(m.footprint), { color: "#0891b2", weight: 1.5, fillOpacity: 0.08 }).addTo(layers.footprint);
    }
    layers.path.clearLayers();
    if (m.path.length > 1) {
      L.polyline(pts(m.path), { color: "#4b5563", weight: 1.5, opacity: 0.8 }).addTo(layers.path);
    }
    layers.components.clearLayers();
    for (const c of m.components) {
      L.polygon(ellipse(c[0], c[1], [c[2], c[3], c[4]], 2), {
        color: "#7c3aed", weight: 1, opacity: Math.min(1, 0.25 + c[5]), fill: false, interactive: false,
      }).addTo(layers.components);
    }
    layers.scans.clearLayers();
    m.scans.forEach((scan, k) => {
      const age = m.scans.length - 1 - k;
      for (const p of scan.xy) {
        L.circleMarker(ll(p[0], p[1]), { radius: 3, color: "#111827", weight: 1,
          fillColor: "#facc15", fillOpacity: 1 - 0.18 * age, opacity: 1 - 0.18 * age }).addTo(layers.scans);
      }
    });
    layers.tracks.clearLayers(); layers.labels.clearLayers();
    for (const t of m.tracks) {
      const colour = !t.confirmed ? "#6b7280" : t.coasting ? "#d97706" : "#15803d";
      L.polygon(ellipse(t.x, t.y, t.cov, 2), { color: colour, weight: t.confirmed ? 2.5 : 1,
        dashArray: t.confirmed ? null : "3 3", fillOpacity: t.confirmed ? 0.12 : 0 }).addTo(layers.tracks);
      if (t.history.length > 1) {
        L.polyline(pts(t.history), { color: colour, weight: 1, opacity: 0.7 }).addTo(layers.tracks);
      }
      L.circleMarker(ll(t.x, t.y), { radius: t.confirmed ? 4 : 2, color: colour, fillOpacity: 1 }).addTo(layers.tracks);
      if (t.confirmed) {
        L.tooltip({ permanent: true, direction: "right", className: "track-label", offset: [6, 0] })
          .setLatLng(ll(t.x, t.y)).setContent(String(t.id)).addTo(layers.labels);
      }
    }
    layers.home.clearLayers();
    if (m.home) {
      L.circleMarker(ll(m.home[0], m.home[1]), { radius: 6, color: "#1d4ed8", weight: 2, fillColor: "#fff", fillOpacity: 1 })
        .bindTooltip("home").addTo(layers.home);
    }
    layers.vehicle.clearLayers();
    const v = m.vehicle;
    const pos = $("vehicle-pos");
    if (v) {
      const h = ((v.heading_deg || 0) * Math.PI) / 180;
      const size = Math.max(1.2, state.scene ? Math.max(...state.scene.size_m) / 40 : 1.5);
      const dx = Math.sin(h), dy = Math.cos(h);
      const tip = ll(v.x + dx * size * 1.4, v.y + dy * size * 1.4);
      const left = ll(v.x - dx * size * 0.7 - dy * size * 0.7, v.y - dy * size * 0.7 + dx * size * 0.7);
      const right = ll(v.x - dx * size * 0.7 + dy * size * 0.7, v.y - dy * size * 0.7 - dx * size * 0.7);
      L.polygon([tip, left, right], { color: "#111827", weight: 1.5, fillColor: "#f97316", fillOpacity: 1 }).addTo(layers.vehicle);
      pos.dataset.x = String(v.x); pos.dataset.y = String(v.y);
      pos.textContent = `x ${v.x.toFixed(1)} m, y ${v.y.toFixed(1)} m` +
        (v.heading_deg == null ? "" : `, heading ${v.heading_deg.toFixed(0)}°`) +
        (v.alt_m == null ? "" : `, ${v.alt_m.toFixed(1)} m above home`);
    }
    drawTable(m);
    $("scans").replaceChildren(...m.scans.slice().reverse().map((s) => {
      const li = document.createElement("li");
      li.textContent = `t ${s.t_s.toFixed(1)} s: ${s.xy.length} detection${s.xy.length === 1 ? "" : "s"}`;
      return li;
    }));
    $("blind").replaceChildren(...m.blind_steps.slice().reverse().map((b) => {
      const li = document.createElement("li");
      li.textContent = `t ${b.t_s.toFixed(1)} s: ${b.reason}`;
      return li;
    }));
    const dl = $("counters");
    const entries = Object.entries(m.counters || {});
    dl.replaceChildren(...entries.flatMap(([k, n]) => {
      const dt = document.createElement("dt"); dt.textContent = k.replaceAll("_", " ");
      const dd = document.createElement("dd"); dd.textContent = String(n);
      return [dt, dd];
    }));
  }

  // -- live -----------------------------------------------------------------------------------
  function staleAfterMs() {
    const rate = state.scene && state.scene.rate_hz ? state.scene.rate_hz : 2;
    return Math.max(3000, 4000 / rate);
  }

  function connect() {
    const scheme = location.protocol === "https:" ? "wss:" : "ws:";
    const ws = new WebSocket(`${scheme}//${location.host}${location.pathname.replace(/[^/]*$/, "")}api/stream${query}`);
    state.ws = ws;
    ws.onopen = () => { state.everConnected = true; };
    ws.onmessage = (event) => {
      const m = JSON.parse(event.data);
      state.lastAt = performance.now();
      if (m.type === "scene") drawScene(m);
      else if (m.type === "step") {
        if (document.hidden) state.unseen = m;  // a background tab draws when shown again
        else drawStep(m);
      }
    };
    ws.onclose = () => { state.ws = null; setTimeout(connect, 2000); };
  }

  function watchStale() {
    const open = state.ws && state.ws.readyState === WebSocket.OPEN;
    const quiet = performance.now() - state.lastAt > staleAfterMs();
    $("stale").hidden = !(state.everConnected && (!open || quiet));
  }

  // -- replay ---------------------------------------------------------------------------------
  let playing = false, loading = false, wanted = null, timer = null;

  async function load(index) {
    wanted = index;
    if (loading) return;
    loading = true;
    try {
      while (wanted !== null) {
        const k = wanted; wanted = null;
        const response = await fetch(`api/step/${k}${query}`);
        if (!response.ok) throw new Error(`step ${k}: HTTP ${response.status}`);
        drawStep(await response.json());
        const times = state.scene.times_s;
        $("slider-time").textContent = `t ${times[k].toFixed(1)} s · step ${k + 1} of ${times.length}`;
        $("slider-time").dataset.index = String(k);
      }
    } finally { loading = false; }
  }

  function tick() {
    const slider = $("slider");
    const k = Number(slider.value);
    const times = state.scene.times_s;
    if (!playing || k >= times.length - 1) { setPlaying(false); return; }
    slider.value = String(k + 1);
    load(k + 1);
    const dt = Math.max(times[k + 2 < times.length ? k + 2 : k + 1] - times[k + 1], 0.05);
    timer = setTimeout(tick, (1000 * dt) / Number($("speed").value));
  }

  function setPlaying(on) {
    playing = on;
    $("play").textContent = on ? "❚❚" : "▶";
    $("play").setAttribute("aria-label", on ? "pause" : "play");
    clearTimeout(timer);
    if (on) {
      const slider = $("slider");
      if (Number(slider.value) >= state.scene.times_s.length - 1) slider.value = "0";
      timer = setTimeout(tick, 0);
    }
  }

  async function startReplay(scene) {
    drawScene(scene);
    $("replay").hidden = false;
    const slider = $("slider");
    slider.max = String(scene.steps - 1);
    slider.value = String(scene.steps - 1);  // the run's last step
    slider.addEventListener("input", () => { setPlaying(false); load(Number(slider.value)); });
    $("play").addEventListener("click", () => setPlaying(!playing));
    await load(scene.steps - 1);
  }

  async function start() {
    const response = await fetch(`api/scene${query}`);
    if (!response.ok) {
      $("stale").textContent = `The companion refused this page (HTTP ${response.status}): ${await response.text()}`;
      $("stale").hidden = false;
      return;
    }
    const scene = await response.json();
    if (scene.mode === "replay") {
      await startReplay(scene);
    } else {
      drawScene(scene);
      connect();
      setInterval(watchStale, 250);
    }
  }
  let userMoved = false;  // once the operator pans the map, a resize keeps their view
  map.on("dragstart", () => { userMoved = true; });
  window.addEventListener("resize", () => {
    map.invalidateSize();
    if (!userMoved && state.bounds) map.fitBounds(state.bounds);
  });
  document.addEventListener("visibilitychange", () => {
    if (!document.hidden && state.unseen) { drawStep(state.unseen); state.unseen = null; }
  });
  start();
})();
