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
  const LAT_WINDOW_S = 10;
  // the skeletons are drawn when a new frame came, at most `fps` times a second; text, extras and
  // the latency plot less often, so a page of many streams costs the capture box little
  const INFO_EVERY_MS = 500, LAT_EVERY_MS = 200, EXTRAS_EVERY_MS = 100, LAT_POINT_S = 0.1;
  // a draw is allowed once 1000/fps ms (less this slack: animation frames come on the display's
  // vsync, a little early or late) have passed since the last one
  const CAP_SLACK_MS = 2;
  // every stream is a cell of one canvas (one layer to raster and composite, however many streams);
  // CSS pixels: text head, three views side by side, the style and phase panels on the right
  const CELL = { w: 644, h: 270, gap: 10, pad: 8, head: 40, vw: 492, vh: 210, vgap: 6, sw: 130 };
  const BG = "#15191d", CARD = "#1b2126", PANEL = "#101316", DIM = "#7d8a95", TEXT = "#dde3e8", GREY = "#93a1ad";

  // fps / dpr: ?fps=60&dpr=2 in the page's address, else what the view process says (--fps, --max-dpr)
  const query = new URLSearchParams(location.search);
  // drawMs: the page's own JavaScript time drawing (performance.now around each animation frame's work);
  // held: animation frames that had a new frame to draw and left it to a later one (the fps cap);
  // drawT: the animation-frame times of the last draws; hiddenUpdates: updates taken while hidden
  const st = { connected: false, meta: null, updates: 0, raf: 0, draws: 0, drawMs: 0, held: 0, drawT: [], lastDraw: -1e9,
               hiddenUpdates: 0, streams: {}, order: [], layoutKey: "", fps: 30, dpr: 1 };

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

  function settings(m) {  // the fps cap and the device-pixel-ratio cap
    const num = (k, dflt) => { const v = parseFloat(query.get(k)); return v > 0 ? v : dflt; };
    st.fps = num("fps", (m && m.fps) || 30);
    st.dpr = Math.min(window.devicePixelRatio || 1, num("dpr", (m && m.max_dpr) || 1));
  }

  function drawLegend() {
    const cv = document.getElementById("scale"), ctx = cv.getContext("2d");
    const W = cv.width, max = stdMax();
    for (let x = 0; x < W; x++) { ctx.fillStyle = css(colourOf(max * x / (W - 1), max)); ctx.fillRect(x, 0, 1, 12); }
    ctx.fillStyle = TEXT; ctx.font = "10px system-ui, sans-serif";
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

  const board = document.getElementById("board");
  // opaque (every pixel is painted): the compositor need not blend what is under it
  const bctx = board.getContext("2d", { alpha: false });

  // ---- layout: the cells of the one canvas (redone only when the streams or the width change) ----
  function rects(s) {  // a stream's regions, device pixels
    const D = st.dpr, x = s.cx, y = s.cy, c = CELL, sx = x + (c.pad + c.vw + c.vgap) * D, vy = y + c.head * D;
    return { cell: [x, y, c.w * D, c.h * D], head: [x, y, c.w * D, c.head * D],
             views: [x + c.pad * D, vy, c.vw * D, c.vh * D],
             style: [sx, vy + 14 * D, c.sw * D, 70 * D], phase: [sx, vy + 102 * D, c.sw * D, 90 * D] };
  }
  function layout() {
    const host = document.getElementById("streams"), n = st.order.length, c = CELL, D = st.dpr;
    const cols = Math.max(1, Math.floor((host.clientWidth + c.gap) / (c.w + c.gap)));
    const key = `${st.order.join("\n")}/${cols}/${D}`;
    if (key === st.layoutKey) return;
    st.layoutKey = key;
    const rows = Math.ceil(n / cols), w = n ? Math.min(n, cols) * (c.w + c.gap) - c.gap : 0, h = n ? rows * (c.h + c.gap) - c.gap : 0;
    board.style.width = w + "px"; board.style.height = h + "px";
    board.width = Math.round(w * D); board.height = Math.round(h * D);  // (clears it)
    document.getElementById("empty").style.display = n ? "none" : "";
    bctx.fillStyle = BG; bctx.fillRect(0, 0, board.width, board.height);
    st.order.forEach((id, i) => {
      const s = st.streams[id];
      s.cx = Math.round((i % cols) * (c.w + c.gap) * D); s.cy = Math.round(Math.floor(i / cols) * (c.h + c.gap) * D);
      s.r = rects(s);
      box(s.r.cell, CARD);
      const [vx, vy, vw, vh] = s.r.views, [sx, sy] = s.r.style, [, py] = s.r.phase;
      bctx.font = `${11 * D}px system-ui, sans-serif`; bctx.fillStyle = DIM; bctx.textAlign = "center";
      VIEWS.forEach((v, k) => bctx.fillText(v, vx + (k + 0.5) * vw / 3, vy + vh + 13 * D));
      bctx.fillText("style posterior", sx + c.sw * D / 2, sy - 4 * D);
      bctx.fillText("gait phase", sx + c.sw * D / 2, py - 4 * D);
      bctx.textAlign = "left";
      s.dirty = true; s.infoAt = -1e9; s.extrasAt = -1e9; s.infoPending = s.extrasPending = true;
    });
  }
  function box(r, colour) { bctx.fillStyle = colour; bctx.fillRect(r[0], r[1], r[2], r[3]); }

  function makeStream(id) {
    const s = { id, last: null, pose: null, dirty: false, frame: null, px: {}, lat: [], stats: null, meta: null, text: "" };
    st.streams[id] = s;
    st.order.push(id);
    return s;
  }

  function onMeta(m) {
    st.meta = m; settings(m);
    document.getElementById("source").textContent = `${m.mode === "play" ? "playing" : "live from"} ${m.source}` +
      (m.skeleton ? ` | skeleton ${m.skeleton.source} (${m.skeleton.joints.length} joints)` : "") +
      ` | ${m.rate} updates/s, drawn at most ${st.fps} fps`;
    document.getElementById("error").textContent = m.error || "";
    const keep = new Set(m.streams.map(sm => sm.id));
    for (const id of st.order.filter(id => !keep.has(id))) delete st.streams[id];  // streams the view forgot (idle)
    st.order = st.order.filter(id => keep.has(id));
    for (const sm of m.streams) {
      const s = st.streams[sm.id] || makeStream(sm.id);
      s.meta = sm; s.dirty = true; s.infoPending = true;
    }
    layout();
    drawLegend();
  }

  function onFrame(u) {
    st.updates++;
    if (document.hidden) st.hiddenUpdates++;
    let added = false;
    for (const d of u.streams) {
      let s = st.streams[d.id];
      if (!s) { s = makeStream(d.id); added = true; }
      s.last = d; s.dirty = true;
      if (d.pos) s.pose = { pos: d.pos, fill: d.fill, seq: d.seq };
      const tail = s.lat[s.lat.length - 1];  // the plot keeps a point a LAT_POINT_S (the worst of it)
      if (tail && u.time - tail[0] < LAT_POINT_S) {
        if (d.proc_ms !== null && !(tail[1] >= d.proc_ms)) tail[1] = d.proc_ms;
        if (d.age_ms !== null && !(tail[2] >= d.age_ms)) tail[2] = d.age_ms;
      } else s.lat.push([u.time, d.proc_ms, d.age_ms]);
      while (s.lat.length && s.lat[0][0] < u.time - LAT_WINDOW_S) s.lat.shift();
    }
    if (added) layout();
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

  function drawProblem(s) {
    const [x, y, w, h] = s.r.views, D = st.dpr, why = (s.meta && s.meta.problem) || "";
    box(s.r.views, PANEL);
    if (!why) return;
    bctx.font = `${12 * D}px system-ui, sans-serif`; bctx.fillStyle = "#ffb74d";
    bctx.fillText(why, x + 8 * D, y + h / 2, w - 16 * D);
  }

  function drawSkeleton(s) {
    const sk = st.meta && st.meta.skeleton;
    if (!s.pose || !sk) { drawProblem(s); return; }
    if (!s.frame) s.frame = frameOf(s);
    const P = s.pose.pos, F = s.pose.fill, par = sk.parents, J = par.length, max = stdMax(), T = table(max);
    const withCh = (s.meta && s.meta.joints_with_channels) || null, dpr = st.dpr;
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
    const ctx = bctx, [X0, Y0, WV, H] = s.r.views, gap = Math.round(CELL.vgap * dpr);
    const W = Math.floor((WV - 2 * gap) / 3), root = s.root;
    ctx.fillStyle = CARD; ctx.fillRect(X0, Y0, WV, H);
    ctx.lineCap = "round";
    for (let vi = 0; vi < 3; vi++) {
      const v = VIEWS[vi], ox = X0 + vi * (W + gap), px = s.px[v];
      const k = H / s.frame.extent;
      const hx = vi === 1 ? 2 : 0, vy = vi === 2 ? 2 : 1, sgn = vi === 2 ? -1 : 1;
      const ch = P[3 * root + hx], cvv = vi === 2 ? P[3 * root + 2] : s.frame.midY;
      for (let j = 0; j < J; j++) {
        px[2 * j] = ox + W / 2 + (P[3 * j + hx] - ch) * k;
        px[2 * j + 1] = Y0 + H / 2 - sgn * (P[3 * j + vy] - cvv) * k;
      }
      ctx.save(); ctx.beginPath(); ctx.rect(ox, Y0, W, H); ctx.clip();
      ctx.fillStyle = PANEL; ctx.fillRect(ox, Y0, W, H);
      if (vi !== 2) {  // the floor under the first pose
        const y = Y0 + H / 2 - (s.frame.floor - cvv) * k;
        ctx.strokeStyle = "#2b343b"; ctx.lineWidth = dpr; ctx.beginPath(); ctx.moveTo(ox, y); ctx.lineTo(ox + W, y); ctx.stroke();
      }
      ctx.lineWidth = 2.5 * dpr;
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
    if (now - s.extrasAt < EXTRAS_EVERY_MS) { s.extrasPending = true; return; }
    s.extrasAt = now; s.extrasPending = false;
    const ctx = bctx, D = st.dpr;
    for (const [r, paint] of [[s.r.style, styleBars], [s.r.phase, phaseDial]]) {
      ctx.save(); ctx.translate(r[0], r[1]); ctx.scale(D, D);
      ctx.fillStyle = PANEL; ctx.fillRect(0, 0, CELL.sw, r[3] / D);
      ctx.font = "11px system-ui, sans-serif"; ctx.fillStyle = GREY;
      paint(ctx, d);
      ctx.restore();
    }
  }
  function styleBars(sc, d) {
    if (!(d && d.style)) { sc.fillText("no style posterior", 5, 38); return; }
    const K = d.style.length, w = 120 / K;
    let best = 0;
    d.style.forEach((p, i) => { if (p > d.style[best]) best = i; });
    d.style.forEach((p, i) => {
      sc.fillStyle = i === best ? "#4fc3f7" : "#4a5a66";
      const h = Math.max(1, p * 52);
      sc.fillRect(5 + i * w + 1, 56 - h, Math.max(1, w - 2), h);
    });
    sc.fillStyle = GREY; sc.fillText(`style ${best} (${(d.style[best] * 100).toFixed(0)}%)`, 5, 68);
  }
  function phaseDial(pc, d) {
    if (!(d && typeof d.phase === "number")) { pc.fillText("no gait phase", 5, 49); return; }
    const cx = 40, cy = 45, r = 32, a = 2 * Math.PI * d.phase - Math.PI / 2;
    pc.strokeStyle = "#4a5a66"; pc.lineWidth = 2; pc.beginPath(); pc.arc(cx, cy, r, 0, 2 * Math.PI); pc.stroke();
    pc.strokeStyle = "#ffd54f"; pc.lineWidth = 3; pc.beginPath(); pc.moveTo(cx, cy);
    pc.lineTo(cx + r * Math.cos(a), cy + r * Math.sin(a)); pc.stroke();
    pc.fillText(d.phase.toFixed(2), 80, 49);
  }

  function fmt(x, n) { return (x === null || x === undefined) ? "-" : x.toFixed(n); }
  const STATUS_RGB = { degraded: "#ffb74d", passthrough: "#ff8a80" };

  function drawInfo(s, now) {
    const d = s.last, t = s.stats, m = s.meta;
    if (now - s.infoAt < INFO_EVERY_MS) { s.infoPending = true; return; }
    s.infoAt = now; s.infoPending = false;
    s.text = !d ? "" : `seq ${d.seq} | ${d.status} | ${d.filled} filled` + (d.gap ? ` | gap ${d.gap}` : "") +
      (t ? ` | ${fmt(t.hz, 0)} Hz in | proc p50 ${fmt(t.proc_p50_ms, 2)} p99 ${fmt(t.proc_p99_ms, 2)} ms` +
           (t.age_p50_ms !== undefined ? ` | capture-to-view p50 ${fmt(t.age_p50_ms, 2)} p99 ${fmt(t.age_p99_ms, 2)} ms` : "") : "");
    const ctx = bctx, D = st.dpr, [x, y, w] = s.r.head, p = CELL.pad * D;
    box(s.r.head, CARD);
    ctx.font = `600 ${14 * D}px system-ui, sans-serif`; ctx.fillStyle = TEXT;
    ctx.fillText(s.id, x + p, y + 17 * D, w / 2);
    const idw = Math.min(ctx.measureText(s.id).width, w / 2);
    ctx.font = `${12 * D}px system-ui, sans-serif`; ctx.fillStyle = GREY;
    if (m && m.model) ctx.fillText(`model ${m.model}`, x + p + idw + 10 * D, y + 17 * D, w - idw - 3 * p);
    ctx.fillStyle = (d && STATUS_RGB[d.status]) || GREY;
    ctx.fillText(s.text, x + p, y + 34 * D, w - 2 * p);
  }

  // ---- latency plot (its own canvas, redrawn five times a second) -------------------------------
  function drawLatency() {
    const cv = document.getElementById("latency"), ctx = cv.getContext("2d", { alpha: false });
    const W = cv.width, H = cv.height, now = st.now || 0, L = 40, B = 16;
    let top = 1;
    for (const id of st.order) for (const [, p, a] of st.streams[id].lat) top = Math.max(top, p || 0, a || 0);
    const nice = [1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000, 5000];
    top = nice.find(n => n >= top) || top;
    ctx.fillStyle = PANEL; ctx.fillRect(0, 0, W, H);
    ctx.strokeStyle = "#2b343b"; ctx.fillStyle = DIM; ctx.font = "11px system-ui, sans-serif"; ctx.lineWidth = 1;
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
    if (key !== st.legendKey) {  // the streams' colours, as in the plot (DOM only when the streams change)
      st.legendKey = key;
      const box = document.getElementById("latency-text");
      box.textContent = "";
      st.order.forEach((id, i) => { const e = el("span", "", box, ` \u25a0 ${id}`); e.style.color = PALETTE[i % PALETTE.length]; });
    }
  }

  function loop(now) {
    requestAnimationFrame(loop);
    st.raf++;
    if (document.hidden) return;  // (Chromium sends a hidden tab no animation frames anyway)
    const fresh = st.order.some(id => st.streams[id].dirty);
    if (now - st.lastDraw < 1000 / st.fps - CAP_SLACK_MS) { if (fresh) st.held++; return; }
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
    if (drew) {
      st.draws++; st.drawMs += performance.now() - t0; st.lastDraw = now;
      st.drawT.push(now); if (st.drawT.length > 256) st.drawT.shift();
    }
  }

  function connect() {
    const es = new EventSource("events");
    const conn = document.getElementById("conn");
    es.onopen = () => { st.connected = true; conn.textContent = "connected"; conn.className = "conn on"; };
    es.onerror = () => { st.connected = false; conn.textContent = "reconnecting"; conn.className = "conn off"; };
    es.addEventListener("meta", e => onMeta(JSON.parse(e.data)));
    es.addEventListener("frame", e => onFrame(JSON.parse(e.data)));
  }

  // for scripts and tests: what was drawn where, in the canvas's own (device) pixels
  window.lacunaView = {
    state: st,
    colourOf: v => colourOf(v, stdMax()),
    joints(id) {
      const s = st.streams[id], sk = st.meta && st.meta.skeleton;
      if (!s || !s.pose || !sk || !s.px.front) return null;
      return sk.joints.map((name, j) => ({ name, fill: s.pose.fill[j], rgb: colourOf(s.pose.fill[j], stdMax()), seq: s.pose.seq,
        px: Object.fromEntries(VIEWS.map(v => [v, [Math.floor(s.px[v][2 * j]), Math.floor(s.px[v][2 * j + 1])]])) }));
    },
    pixel(id, x, y) { return Array.from(bctx.getImageData(x, y, 1, 1).data); },  // (every stream is on the one canvas)
    // [x, y, w, h] of a stream's region: head, views, front, side, top, style, phase
    region(id, name) {
      const s = st.streams[id];
      if (!s || !s.r) return null;
      if (!VIEWS.includes(name)) return s.r[name].map(Math.round);
      const [x, y, w, h] = s.r.views, gap = Math.round(CELL.vgap * st.dpr), W = Math.floor((w - 2 * gap) / 3);
      return [x + VIEWS.indexOf(name) * (W + gap), y, W, h].map(Math.round);
    },
    text(id) { const s = st.streams[id]; return s ? s.text : null; },
  };
  settings(null);
  window.addEventListener("resize", () => { layout(); st.latDirty = true; });
  document.addEventListener("visibilitychange", () => { if (!document.hidden) st.lastDraw = -1e9; });
  drawLegend();
  connect();
  requestAnimationFrame(loop);
})();
