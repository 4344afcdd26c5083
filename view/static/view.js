// Lacuna view: draws what the view process sends (positions are computed there; this page only draws).
// Plain JS, no build step, nothing fetched but this server's own /events.
"use strict";
(function () {
  const OBSERVED_RGB = [0xcf, 0xd8, 0xdc];
  const HELD_RGB = [0xe0, 0x40, 0xfb];
  // std 0 .. std_max: green (confident) -> yellow -> orange -> red (could be anywhere)
  const STOPS = [[0.0, [0x1a, 0x98, 0x50]], [0.33, [0xd9, 0xef, 0x3b]], [0.66, [0xfd, 0x8d, 0x3c]], [1.0, [0xd7, 0x19, 0x1c]]];
  const PALETTE = ["#4fc3f7", "#ffd54f", "#81c784", "#f06292", "#ba68c8", "#ff8a65", "#4db6ac", "#a1887f"];
  const VIEWS = ["front", "side", "top"];
  const PANEL_GAP = 6;  // CSS pixels between the three views on a stream's canvas
  const LAT_WINDOW_S = 10;
  // the skeletons are drawn at every update; text, extras and the latency plot less often, so a
  // page of many streams costs the capture box little (software raster in a headless browser)
  const INFO_EVERY_MS = 500, LAT_EVERY_MS = 200, EXTRAS_EVERY_MS = 100, LAT_POINT_S = 0.1;

  // drawMs: the page's own JavaScript time drawing (performance.now around each animation frame's work)
  const st = { connected: false, meta: null, metaVersion: -1, updates: 0, raf: 0, draws: 0, drawMs: 0, streams: {}, order: [] };

  // Colours come from a table of LEVELS std levels (built once per std_max): a frame's drawing
  // makes no colour strings, and joints of one colour are stroked and filled as one path.
  const LEVELS = 256, C_OBS = LEVELS, C_HELD = LEVELS + 1, C_BONE_OBS = LEVELS + 2;
  const lut = { max: -1, rgb: [], css: [] };
  function ramp(u) {
    for (let i = 1; i < STOPS.length; i++) {
      const [u1, c1] = STOPS[i];
      if (u <= u1 || i === STOPS.length - 1) {
        const [u0, c0] = STOPS[i - 1];
        const a = (u - u0) / (u1 - u0);
        return [0, 1, 2].map(k => Math.round(c0[k] + a * (c1[k] - c0[k])));
      }
    }
  }
  function table(max) {
    if (lut.max === max) return lut;
    lut.max = max; lut.rgb = []; lut.css = [];
    for (let i = 0; i < LEVELS; i++) lut.rgb.push(ramp(i / (LEVELS - 1)));
    lut.rgb.push(OBSERVED_RGB, HELD_RGB, [0x78, 0x86, 0x90]);
    lut.css = lut.rgb.map(c => `rgb(${c[0]},${c[1]},${c[2]})`);
    return lut;
  }
  function colourIndex(v, max) {
    if (v === -1) return C_OBS;
    if (v === -2) return C_HELD;
    return Math.round(Math.max(0, Math.min(1, v / (max || 20))) * (LEVELS - 1));
  }
  function colourOf(v, max) { return table(max || 20).rgb[colourIndex(v, max || 20)].slice(); }
  const css = rgb => `rgb(${rgb[0]},${rgb[1]},${rgb[2]})`;
  const stdMax = () => (st.meta && st.meta.std_max) || 20;

  function drawLegend() {
    const cv = document.getElementById("scale"), ctx = cv.getContext("2d");
    const W = cv.width, max = stdMax();
    for (let x = 0; x < W; x++) { ctx.fillStyle = css(colourOf(max * x / (W - 1), max)); ctx.fillRect(x, 0, 1, 12); }
    ctx.fillStyle = "#dde3e8"; ctx.font = "10px system-ui, sans-serif";
    ctx.textAlign = "left"; ctx.fillText("0", 0, 21);
    ctx.textAlign = "center"; ctx.fillText((max / 2).toFixed(0), W / 2, 21);
    ctx.textAlign = "right"; ctx.fillText(max.toFixed(0) + " deg", W, 21);
  }

  function el(tag, cls, parent, text) {
    const e = document.createElement(tag);
    if (cls) e.className = cls;
    if (text !== undefined) e.textContent = text;
    if (parent) parent.appendChild(e);
    return e;
  }

  function sizeCanvas(cv) {  // device pixels, so a drawn joint's pixel can be read back exactly
    const dpr = window.devicePixelRatio || 1;
    cv.width = Math.round(cv.clientWidth * dpr);
    cv.height = Math.round(cv.clientHeight * dpr);
  }

  function makeStream(id) {
    const main = document.getElementById("streams");
    const empty = document.getElementById("empty");
    if (empty) empty.remove();
    const card = el("section", "stream", main);
    card.dataset.stream = id;
    const head = el("div", "head", card);
    el("span", "id", head, id);
    const model = el("span", "info", head);
    const info = el("span", "info", head);
    const problem = el("div", "problem", card);
    const views = el("div", "views", card);
    // the three views share one canvas (one layer for the browser to raster and composite)
    const f = el("figure", "", views);
    const cv = el("canvas", "views", f);
    const caps = el("div", "caps", f);
    for (const v of VIEWS) el("span", "", caps, v);
    const side = el("div", "side", views);
    el("figcaption", "", side, "style posterior");
    const styleCv = el("canvas", "style", side); styleCv.width = 130; styleCv.height = 70;
    el("figcaption", "", side, "gait phase");
    const phaseCv = el("canvas", "phase", side); phaseCv.width = 130; phaseCv.height = 90;
    sizeCanvas(cv);
    // opaque (every pixel is painted each draw): the compositor need not blend what is under it
    const ctx = cv.getContext("2d", { alpha: false });
    const s = { id, card, model, info, problem, cv, ctx, styleCv, phaseCv, last: null, pose: null, dirty: false,
                frame: null, px: {}, rgb: [], lat: [], stats: null, meta: null };
    st.streams[id] = s;
    st.order.push(id);
    return s;
  }

  function onMeta(m) {
    st.meta = m; st.metaVersion = m.version;
    document.getElementById("source").textContent = `${m.mode === "play" ? "playing" : "live from"} ${m.source}` +
      (m.skeleton ? ` | skeleton ${m.skeleton.source} (${m.skeleton.joints.length} joints)` : "") + ` | ${m.rate} updates/s`;
    document.getElementById("error").textContent = m.error || "";
    const keep = new Set(m.streams.map(sm => sm.id));
    for (const id of st.order.filter(id => !keep.has(id))) {  // streams the view forgot (idle)
      st.streams[id].card.remove(); delete st.streams[id];
    }
    st.order = st.order.filter(id => keep.has(id));
    for (const sm of m.streams) {
      const s = st.streams[sm.id] || makeStream(sm.id);
      s.meta = sm;
      s.model.textContent = sm.model ? `model ${sm.model}` : "";
      s.problem.textContent = sm.problem || "";
      s.dirty = true;
    }
    drawLegend();
  }

  function onFrame(u) {
    st.updates++;
    for (const d of u.streams) {
      const s = st.streams[d.id] || makeStream(d.id);
      s.last = d; s.dirty = true;
      if (d.pos) s.pose = { pos: d.pos, fill: d.fill, seq: d.seq };
      const tail = s.lat[s.lat.length - 1];  // the plot keeps a point a LAT_POINT_S (the worst of it)
      if (tail && u.time - tail[0] < LAT_POINT_S) {
        if (d.proc_ms !== null && !(tail[1] >= d.proc_ms)) tail[1] = d.proc_ms;
        if (d.age_ms !== null && !(tail[2] >= d.age_ms)) tail[2] = d.age_ms;
      } else s.lat.push([u.time, d.proc_ms, d.age_ms]);
      while (s.lat.length && s.lat[0][0] < u.time - LAT_WINDOW_S) s.lat.shift();
    }
    if (u.stats) for (const id in u.stats) if (st.streams[id]) st.streams[id].stats = u.stats[id];
    st.now = u.time; st.latDirty = true;
  }

  // ---- skeleton views --------------------------------------------------------------------------
  // y is up (the view process turns other files); front: x right, y up; side: z right, y up;
  // top: x right, z down the canvas.  Each stream's scale is fixed from its first pose; the
  // views follow the root horizontally so a walk stays in frame.
  function frameOf(s) {
    const P = s.pose.pos, J = P.length / 3;
    let lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (let j = 0; j < J; j++) for (let k = 0; k < 3; k++) { lo[k] = Math.min(lo[k], P[3 * j + k]); hi[k] = Math.max(hi[k], P[3 * j + k]); }
    const span = Math.max(hi[0] - lo[0], hi[1] - lo[1], hi[2] - lo[2]);
    return { extent: Math.max(0.5, 1.3 * span), midY: (lo[1] + hi[1]) / 2, floor: lo[1] };
  }

  function drawSkeleton(s) {
    const sk = st.meta && st.meta.skeleton;
    if (!s.pose || !sk) return;
    if (!s.frame) s.frame = frameOf(s);
    const P = s.pose.pos, F = s.pose.fill, par = sk.parents, J = par.length, max = stdMax(), T = table(max);
    const withCh = (s.meta && s.meta.joints_with_channels) || null, dpr = window.devicePixelRatio || 1;
    if (!s.ci || s.ci.length !== J) {  // per-stream buffers, made once: no allocation per frame
      s.ci = new Int16Array(J); s.bi = new Int16Array(J); s.rad = new Float32Array(J);
      s.stamp = new Int32Array(C_BONE_OBS + 1); s.used = new Int16Array(2 * J);
      for (const v of VIEWS) s.px[v] = new Float32Array(2 * J);
      s.root = par.indexOf(-1);
    }
    const ci = s.ci, bi = s.bi, rad = s.rad, used = s.used, stamp = s.stamp;
    let nUsed = 0;
    s.draws = (s.draws || 0) + 1;
    for (let j = 0; j < J; j++) {  // colour of each joint, of the bone to it, the colours in use
      const c = colourIndex(F[j], max);
      ci[j] = c; bi[j] = c === C_OBS ? C_BONE_OBS : c;
      rad[j] = ((withCh && !withCh[j]) ? 2.5 : (c === C_OBS ? 4 : 5)) * dpr;
      if (stamp[c] !== s.draws) { stamp[c] = s.draws; used[nUsed++] = c; }
      if (stamp[bi[j]] !== s.draws) { stamp[bi[j]] = s.draws; used[nUsed++] = bi[j]; }
    }
    s.rgb = null;  // joints() looks colours up when asked
    const cv = s.cv, ctx = s.ctx, gap = Math.round(PANEL_GAP * dpr);
    const W = Math.floor((cv.width - 2 * gap) / 3), H = cv.height, root = s.root;
    ctx.fillStyle = "#1b2126"; ctx.fillRect(0, 0, cv.width, H);
    ctx.lineCap = "round";
    for (let vi = 0; vi < 3; vi++) {
      const v = VIEWS[vi], ox = vi * (W + gap), px = s.px[v];
      const k = H / s.frame.extent;
      const hx = vi === 1 ? 2 : 0, vy = vi === 2 ? 2 : 1, sgn = vi === 2 ? -1 : 1;
      const ch = P[3 * root + hx], cvv = vi === 2 ? P[3 * root + 2] : s.frame.midY;
      for (let j = 0; j < J; j++) {
        px[2 * j] = ox + W / 2 + (P[3 * j + hx] - ch) * k;
        px[2 * j + 1] = H / 2 - sgn * (P[3 * j + vy] - cvv) * k;
      }
      ctx.save(); ctx.beginPath(); ctx.rect(ox, 0, W, H); ctx.clip();
      ctx.fillStyle = "#101316"; ctx.fillRect(ox, 0, W, H);
      if (vi !== 2) {  // the floor under the first pose
        const y = H / 2 - (s.frame.floor - cvv) * k;
        ctx.strokeStyle = "#2b343b"; ctx.lineWidth = 1; ctx.beginPath(); ctx.moveTo(ox, y); ctx.lineTo(ox + W, y); ctx.stroke();
      }
      ctx.lineWidth = 2.5;
      for (let u = 0; u < nUsed; u++) {  // bones, one path a colour
        const c = used[u];
        let any = false;
        ctx.beginPath();
        for (let j = 0; j < J; j++) {
          const p = par[j];
          if (p < 0 || bi[j] !== c) continue;
          ctx.moveTo(px[2 * p], px[2 * p + 1]); ctx.lineTo(px[2 * j], px[2 * j + 1]); any = true;
        }
        if (any) { ctx.strokeStyle = T.css[c]; ctx.stroke(); }
      }
      for (let pass = 0; pass < 2; pass++) {  // joints: observed first, filled on top, one path a colour
        for (let u = 0; u < nUsed; u++) {
          const c = used[u];
          if ((c === C_OBS) === (pass === 1) || c === C_BONE_OBS) continue;
          ctx.beginPath();
          for (let j = 0; j < J; j++) {
            if (ci[j] !== c) continue;
            ctx.moveTo(px[2 * j] + rad[j], px[2 * j + 1]); ctx.arc(px[2 * j], px[2 * j + 1], rad[j], 0, 2 * Math.PI);
          }
          ctx.fillStyle = T.css[c]; ctx.fill();
        }
      }
      ctx.restore();
    }
  }

  function drawExtras(s, now) {
    const d = s.last;
    if (now - (s.extrasAt || -1e9) < EXTRAS_EVERY_MS) { s.extrasPending = true; return; }
    s.extrasAt = now; s.extrasPending = false;
    const sc = s.styleCv.getContext("2d"), pc = s.phaseCv.getContext("2d");
    sc.fillStyle = "#101316"; sc.fillRect(0, 0, 130, 70);
    sc.font = "11px system-ui, sans-serif"; sc.fillStyle = "#93a1ad";
    if (d && d.style) {
      const K = d.style.length, w = 120 / K;
      let best = 0;
      d.style.forEach((p, i) => { if (p > d.style[best]) best = i; });
      d.style.forEach((p, i) => {
        sc.fillStyle = i === best ? "#4fc3f7" : "#4a5a66";
        const h = Math.max(1, p * 52);
        sc.fillRect(5 + i * w + 1, 56 - h, Math.max(1, w - 2), h);
      });
      sc.fillStyle = "#93a1ad"; sc.fillText(`style ${best} (${(d.style[best] * 100).toFixed(0)}%)`, 5, 68);
    } else sc.fillText("no style posterior", 5, 38);
    pc.fillStyle = "#101316"; pc.fillRect(0, 0, 130, 90);
    pc.font = "11px system-ui, sans-serif"; pc.fillStyle = "#93a1ad";
    if (d && typeof d.phase === "number") {
      const cx = 40, cy = 45, r = 32, a = 2 * Math.PI * d.phase - Math.PI / 2;
      pc.strokeStyle = "#4a5a66"; pc.lineWidth = 2; pc.beginPath(); pc.arc(cx, cy, r, 0, 2 * Math.PI); pc.stroke();
      pc.strokeStyle = "#ffd54f"; pc.lineWidth = 3; pc.beginPath(); pc.moveTo(cx, cy);
      pc.lineTo(cx + r * Math.cos(a), cy + r * Math.sin(a)); pc.stroke();
      pc.fillText(d.phase.toFixed(2), 80, 49);
    } else pc.fillText("no gait phase", 5, 49);
  }

  function fmt(x, n) { return (x === null || x === undefined) ? "-" : x.toFixed(n); }

  function drawInfo(s, now) {
    const d = s.last, t = s.stats;
    if (!d) return;
    if (now - (s.infoAt || 0) < INFO_EVERY_MS) { s.infoPending = true; return; }
    s.infoAt = now; s.infoPending = false;
    s.info.textContent = `seq ${d.seq} | ${d.status} | ${d.filled} filled` + (d.gap ? ` | gap ${d.gap}` : "") +
      (t ? ` | ${fmt(t.hz, 0)} Hz in | proc p50 ${fmt(t.proc_p50_ms, 2)} p99 ${fmt(t.proc_p99_ms, 2)} ms` +
           (t.age_p50_ms !== undefined ? ` | capture-to-view p50 ${fmt(t.age_p50_ms, 2)} p99 ${fmt(t.age_p99_ms, 2)} ms` : "") : "");
    s.info.className = "info status-" + d.status;
  }

  // ---- latency plot ----------------------------------------------------------------------------
  function drawLatency() {
    const cv = document.getElementById("latency"), ctx = cv.getContext("2d");
    const W = cv.width, H = cv.height, now = st.now || 0, L = 40, B = 16;
    let top = 1;
    for (const id of st.order) for (const [, p, a] of st.streams[id].lat) top = Math.max(top, p || 0, a || 0);
    const nice = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000];
    top = nice.find(n => n >= top) || top;
    ctx.fillStyle = "#101316"; ctx.fillRect(0, 0, W, H);
    ctx.strokeStyle = "#2b343b"; ctx.fillStyle = "#7d8a95"; ctx.font = "11px system-ui, sans-serif"; ctx.lineWidth = 1;
    for (const f of [0, 0.5, 1]) {
      const y = H - B - f * (H - B - 6);
      ctx.beginPath(); ctx.moveTo(L, y); ctx.lineTo(W, y); ctx.stroke();
      ctx.fillText(`${(f * top).toFixed(top < 5 ? 1 : 0)} ms`, 2, y + 4);
    }
    ctx.fillText(`-${LAT_WINDOW_S} s`, L, H - 3); ctx.fillText("now", W - 26, H - 3);
    const X = t => L + (W - L) * (1 - (now - t) / LAT_WINDOW_S), Y = v => H - B - (v / top) * (H - B - 6);
    st.order.forEach((id, i) => {
      const s = st.streams[id];
      ctx.strokeStyle = PALETTE[i % PALETTE.length]; ctx.lineWidth = 1.5;
      for (const [col, dash] of [[1, []], [2, [4, 3]]]) {
        ctx.setLineDash(dash); ctx.beginPath();
        let pen = false;
        for (const r of s.lat) {
          if (r[col] === null || r[col] === undefined) { pen = false; continue; }
          if (pen) ctx.lineTo(X(r[0]), Y(r[col])); else ctx.moveTo(X(r[0]), Y(r[col]));
          pen = true;
        }
        ctx.stroke();
      }
      ctx.setLineDash([]);
    });
    const key = st.order.join("\n");
    if (key !== st.legendKey) {  // the streams' colours, as in the plot
      st.legendKey = key;
      const box = document.getElementById("latency-text");
      box.textContent = "";
      st.order.forEach((id, i) => { const e = el("span", "", box, ` \u25a0 ${id}`); e.style.color = PALETTE[i % PALETTE.length]; });
    }
  }

  function loop(now) {
    st.raf++;
    const t0 = performance.now();
    let drew = false;
    for (const id of st.order) {
      const s = st.streams[id];
      if (!s.dirty) {
        if (s.infoPending) drawInfo(s, now);
        if (s.extrasPending) drawExtras(s, now);
        continue;
      }
      s.dirty = false; drew = true;
      drawSkeleton(s); drawExtras(s, now); drawInfo(s, now);
    }
    if (st.latDirty && now - (st.latAt || 0) >= LAT_EVERY_MS) {
      st.latDirty = false; st.latAt = now; drawLatency(); drew = true;
    }
    if (drew) { st.draws++; st.drawMs += performance.now() - t0; }
    requestAnimationFrame(loop);
  }

  function connect() {
    const es = new EventSource("events");
    const conn = document.getElementById("conn");
    es.onopen = () => { st.connected = true; conn.textContent = "connected"; conn.className = "conn on"; };
    es.onerror = () => { st.connected = false; conn.textContent = "reconnecting"; conn.className = "conn off"; };
    es.addEventListener("meta", e => onMeta(JSON.parse(e.data)));
    es.addEventListener("frame", e => onFrame(JSON.parse(e.data)));
  }

  // for scripts and tests: what was drawn where, in the canvases' own pixels
  window.lacunaView = {
    state: st,
    colourOf: v => colourOf(v, stdMax()),
    joints(id) {
      const s = st.streams[id], sk = st.meta && st.meta.skeleton;
      if (!s || !s.pose || !sk || !s.px.front) return null;
      return sk.joints.map((name, j) => ({ name, fill: s.pose.fill[j], rgb: colourOf(s.pose.fill[j], stdMax()), seq: s.pose.seq,
        px: Object.fromEntries(VIEWS.map(v => [v, [Math.floor(s.px[v][2 * j]), Math.floor(s.px[v][2 * j + 1])]])) }));
    },
    pixel(id, x, y) {  // x, y: canvas pixels, as joints() gives them
      const cv = st.streams[id].cv;
      return Array.from(cv.getContext("2d").getImageData(x, y, 1, 1).data);
    },
  };
  drawLegend();
  connect();
  requestAnimationFrame(loop);
})();
