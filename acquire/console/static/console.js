// mls console: the status bus live over a WebSocket, drawn on <canvas>. Our own code, no library.
// State the page drew is exposed for tests and tools in window.mlsConsole and in data-* attributes.
"use strict";

const S = { topics: {}, track: [], lat: {}, messages: 0, frames: 0, acked: {}, token: null };
const view = { mPerPx: 0.15, follow: true, center: [0, 0], drawn: null };
const COLORS = { pending: "#5d6f82", accepted: "#3ecf6e", rejected: "#ff5c5c", active: "#4fc3f7",
  target: "#ff7b7b", vessel: "#ffd54f", track: "rgba(255,213,79,0.45)", grid: "#16222e",
  text: "#9fb0c2", roll: "#4fc3f7", pitch: "#ffb74d", yaw: "#ba68c8", limit: "#ff5c5c" };
const TRACK_MAX = 900;
const $ = (id) => document.getElementById(id);
let dirty = true;

function el(tag, cls, text) {
  const e = document.createElement(tag);
  if (cls) e.className = cls;
  if (text !== undefined && text !== null) e.textContent = String(text);
  return e;
}
function fmt(x, digits, unit) {
  if (x === null || x === undefined || Number.isNaN(x)) return "—";
  return Number(x).toFixed(digits) + (unit || "");
}
function guidance() { return (S.topics.checklist || {}).guidance || null; }

// -- the link ------------------------------------------------------------------------------------

function connect() {
  const scheme = location.protocol === "https:" ? "wss:" : "ws:";
  const ws = new WebSocket(scheme + "//" + location.host + "/ws");
  ws.onopen = () => setBadge($("link"), "live", "ok");
  ws.onmessage = (ev) => { receive(JSON.parse(ev.data)); };
  ws.onclose = () => { setBadge($("link"), "offline", "bad"); setTimeout(connect, 1000); };
}

function receive(msg) {
  S.messages += 1;
  const t = msg.topic, d = msg.data;
  if (t === "_console") { S.acked = {}; for (const a of d.acked || []) S.acked[a.alarm + "/" + a.device] = a; }
  else if (t !== "_snapshot_end" && t !== "alarms") S.topics[t] = d;
  if (t === "checklist") noteVessel();
  if (t === "metrics") noteLatency(d);
  dirty = true;
}

function noteVessel() {
  const g = guidance();
  const v = g && g.vessel;
  if (!v) return;
  const last = S.track[S.track.length - 1];
  if (!last || last[2] !== v.t_gps_s) S.track.push([v.n_m, v.e_m, v.t_gps_s]);
  if (S.track.length > TRACK_MAX) S.track.splice(0, S.track.length - TRACK_MAX);
}

function noteLatency(d) {
  for (const [name, st] of Object.entries(d.latency || {})) {
    const series = S.lat[name] || (S.lat[name] = []);
    series.push(st.latency_mean_ms);
    if (series.length > 120) series.shift();
  }
}

function setBadge(e, text, kind) { e.textContent = text; e.className = "badge " + (kind || ""); }

// -- the canvas ----------------------------------------------------------------------------------

function fitCanvas(c) {
  const r = window.devicePixelRatio || 1;
  const w = Math.max(1, Math.round(c.clientWidth * r)), h = Math.max(1, Math.round(c.clientHeight * r));
  if (c.width !== w || c.height !== h) { c.width = w; c.height = h; }
  const ctx = c.getContext("2d");
  ctx.setTransform(r, 0, 0, r, 0, 0);
  return [ctx, c.clientWidth, c.clientHeight];
}

function drawPlan() {
  const c = $("plan");
  const [ctx, w, h] = fitCanvas(c);
  ctx.clearRect(0, 0, w, h);
  const g = guidance();
  const v = g && g.vessel;
  if (view.follow && v) view.center = [v.n_m, v.e_m];
  const toPx = (n, e) => [w / 2 + (e - view.center[1]) / view.mPerPx, h / 2 - (n - view.center[0]) / view.mPerPx];
  drawGrid(ctx, w, h, toPx);
  if (g && g.plan) { drawLines(ctx, g, toPx); drawTargets(ctx, g.plan.targets || [], toPx); }
  drawTrack(ctx, toPx);
  view.drawn = v ? drawVessel(ctx, v, toPx) : null;
  $("scale").textContent = fmt(view.mPerPx * 100, 0, " m / 100 px");
  S.frames += 1;
  c.dataset.frames = String(S.frames);
  if (view.drawn) {
    c.dataset.vesselN = String(v.n_m); c.dataset.vesselE = String(v.e_m);
    c.dataset.vesselX = view.drawn.x.toFixed(1); c.dataset.vesselY = view.drawn.y.toFixed(1);
    c.dataset.vesselHeading = String(v.heading_deg);
  }
}

function drawGrid(ctx, w, h, toPx) {
  const step = niceStep(view.mPerPx * 120);
  ctx.strokeStyle = COLORS.grid; ctx.lineWidth = 1; ctx.fillStyle = COLORS.text; ctx.font = "11px sans-serif";
  const n0 = view.center[0] - (h / 2) * view.mPerPx, e0 = view.center[1] - (w / 2) * view.mPerPx;
  for (let e = Math.floor(e0 / step) * step; e < e0 + w * view.mPerPx; e += step) {
    const [x] = toPx(0, e); ctx.beginPath(); ctx.moveTo(x, 0); ctx.lineTo(x, h); ctx.stroke();
    ctx.fillText(fmt(e, 0, " E"), x + 2, h - 4);
  }
  for (let n = Math.floor(n0 / step) * step; n < n0 + h * view.mPerPx; n += step) {
    const [, y] = toPx(n, 0); ctx.beginPath(); ctx.moveTo(0, y); ctx.lineTo(w, y); ctx.stroke();
    ctx.fillText(fmt(n, 0, " N"), 2, y - 2);
  }
  ctx.fillText("N ↑", w - 30, 14);
}

function niceStep(m) {
  const p = Math.pow(10, Math.floor(Math.log10(m)));
  for (const k of [1, 2, 5, 10]) if (k * p >= m) return k * p;
  return 10 * p;
}

function passStatus(g, id) {
  const p = (g.passes || []).find((q) => q.id === id);
  return p ? p.status : "pending";
}

function drawLines(ctx, g, toPx) {
  const activeId = g.active ? g.active.pass_id : null;
  for (const p of g.plan.passes || []) {
    const st = p.id === activeId ? "active" : passStatus(g, p.id);
    const a = toPx(...p.start_ne_m), b = toPx(...p.end_ne_m);
    ctx.strokeStyle = COLORS[st] || COLORS.pending;
    ctx.lineWidth = st === "active" ? 3 : 1.5;
    ctx.setLineDash(st === "pending" ? [6, 4] : []);
    ctx.beginPath(); ctx.moveTo(...a); ctx.lineTo(...b); ctx.stroke();
    ctx.setLineDash([]);
    drawCapture(ctx, p, toPx);
    arrowHead(ctx, a, b);
    ctx.fillStyle = ctx.strokeStyle; ctx.font = "bold 12px sans-serif";
    ctx.fillText(String(p.order), a[0] - 14, a[1] - 4);
  }
}

function drawCapture(ctx, p, toPx) {
  if (!p.capture_m || !p.length_m) return;
  const at = (s) => {
    const f = s / p.length_m;
    return toPx(p.start_ne_m[0] + f * (p.end_ne_m[0] - p.start_ne_m[0]), p.start_ne_m[1] + f * (p.end_ne_m[1] - p.start_ne_m[1]));
  };
  ctx.lineWidth = 6; ctx.globalAlpha = 0.35;
  ctx.beginPath(); ctx.moveTo(...at(p.capture_m[0])); ctx.lineTo(...at(p.capture_m[1])); ctx.stroke();
  ctx.globalAlpha = 1;
}

function arrowHead(ctx, a, b) {
  const ang = Math.atan2(b[1] - a[1], b[0] - a[0]);
  ctx.lineWidth = 1.5; ctx.beginPath();
  ctx.moveTo(b[0] - 9 * Math.cos(ang - 0.4), b[1] - 9 * Math.sin(ang - 0.4));
  ctx.lineTo(b[0], b[1]);
  ctx.lineTo(b[0] - 9 * Math.cos(ang + 0.4), b[1] - 9 * Math.sin(ang + 0.4));
  ctx.stroke();
}

function drawTargets(ctx, targets, toPx) {
  ctx.fillStyle = COLORS.target; ctx.strokeStyle = COLORS.target; ctx.font = "11px sans-serif";
  for (const t of targets) {
    const pts = (t.corners_ne_m || []).map((q) => toPx(q[0], q[1]));
    if (pts.length) {
      ctx.beginPath(); ctx.moveTo(...pts[0]); for (const q of pts.slice(1)) ctx.lineTo(...q); ctx.closePath();
      ctx.globalAlpha = 0.5; ctx.fill(); ctx.globalAlpha = 1; ctx.stroke();
    }
    const cpx = toPx(...t.center_ne_m);
    ctx.beginPath(); ctx.arc(cpx[0], cpx[1], 3, 0, 2 * Math.PI); ctx.fill();
    ctx.fillText(t.name, cpx[0] + 5, cpx[1] + 12);
  }
}

function drawTrack(ctx, toPx) {
  if (S.track.length < 2) return;
  ctx.strokeStyle = COLORS.track; ctx.lineWidth = 2; ctx.beginPath();
  S.track.forEach((q, i) => { const p = toPx(q[0], q[1]); if (i) ctx.lineTo(...p); else ctx.moveTo(...p); });
  ctx.stroke();
}

function drawVessel(ctx, v, toPx) {
  const [x, y] = toPx(v.n_m, v.e_m);
  const hd = (v.heading_deg * Math.PI) / 180;
  ctx.save(); ctx.translate(x, y); ctx.rotate(hd);
  ctx.fillStyle = COLORS.vessel; ctx.strokeStyle = "#000"; ctx.lineWidth = 1;
  ctx.beginPath(); ctx.moveTo(0, -12); ctx.lineTo(7, 9); ctx.lineTo(0, 5); ctx.lineTo(-7, 9); ctx.closePath();
  ctx.fill(); ctx.stroke();
  ctx.strokeStyle = COLORS.vessel; ctx.beginPath(); ctx.moveTo(0, -12); ctx.lineTo(0, -40); ctx.stroke();
  ctx.restore();
  return { x, y, n_m: v.n_m, e_m: v.e_m, heading_deg: v.heading_deg };
}

// -- the line, the passes, sigma ------------------------------------------------------------------

function renderLine() {
  const g = guidance();
  const a = g && g.active, v = g && g.vessel;
  $("line-now").textContent = a ? `line ${a.pass_id} · ${a.state}` : "no active line";
  $("xte-val").textContent = a && a.xte_m !== undefined ? `${fmt(Math.abs(a.xte_m), 2, " m")} ${a.xte_m > 0 ? "starboard → steer port" : "port → steer starboard"}` : "—";
  $("hdg-err").textContent = a && a.heading_error_deg !== undefined ? fmt(a.heading_error_deg, 1, "°") : "—";
  $("speed").textContent = v ? `${fmt(v.speed_mps, 2, " m/s")}${a && a.planned_speed_mps ? " (plan " + fmt(a.planned_speed_mps, 1, ")") : ""}` : "—";
  $("to-go").textContent = a && a.length_m !== undefined ? toGo(a) : "—";
  const nb = g && g.sigma && g.sigma.next_best;
  const wk = g && g.sigma && g.sigma.weakest;
  const weak = wk && wk.best_pass !== null ? ` · weakest ${wk.angle} ${fmt(wk.realistic_deg, 3, "°")}: line ${wk.best_pass} → ${fmt(wk.best_deg, 3, "°")}` : "";
  $("next-line").textContent = (nb ? `line ${nb.pass_id}` : nextPending(g)) + weak;
  if (a && !$("pass-id").matches(":focus")) $("pass-id").value = a.pass_id;
  drawXte(a, g ? g.tolerances : null);
}

function toGo(a) {
  if (a.along_m < 0) return `${fmt(-a.along_m, 1, " m")} to the line's start`;
  if (a.along_m > a.length_m) return `past the line's end by ${fmt(a.along_m - a.length_m, 1, " m")}`;
  if (a.state === "approach" && a.to_capture_m > 0) return `${fmt(a.to_capture_m, 1, " m")} to the capture window`;
  return `${fmt(a.length_m - a.along_m, 1, " m")} to the line's end`;
}

function nextPending(g) {
  if (!g || !g.passes) return "—";
  const p = g.passes.filter((q) => q.status !== "accepted").sort((x, y) => x.order - y.order)[0];
  return p ? `line ${p.id}` : "all accepted";
}

function drawXte(a, tol) {
  const [ctx, w, h] = fitCanvas($("xte"));
  ctx.clearRect(0, 0, w, h);
  const lim = (tol && tol.max_xte_m) || 2, span = 2.5 * lim;
  const x = (m) => w / 2 + (Math.max(-span, Math.min(span, m)) / span) * (w / 2 - 6);
  ctx.fillStyle = "rgba(62,207,110,0.15)"; ctx.fillRect(x(-lim), 4, x(lim) - x(-lim), h - 8);
  ctx.strokeStyle = COLORS.text; ctx.beginPath(); ctx.moveTo(w / 2, 2); ctx.lineTo(w / 2, h - 2); ctx.stroke();
  if (!a || a.xte_m === undefined) return;
  ctx.fillStyle = Math.abs(a.xte_m) <= lim ? COLORS.accepted : COLORS.rejected;
  ctx.beginPath(); ctx.arc(x(a.xte_m), h / 2, 7, 0, 2 * Math.PI); ctx.fill();
}

function renderPasses() {
  const g = guidance();
  const body = $("passes").tBodies[0];
  body.replaceChildren();
  if (!g || !g.passes) return;
  $("accepted").textContent = `${g.accepted} of ${g.passes.length} accepted`;
  const activeId = g.active ? g.active.pass_id : null;
  for (const p of [...g.passes].sort((x, y) => x.order - y.order)) {
    const tr = el("tr", p.status + (p.id === activeId ? " active" : ""));
    tr.dataset.pass = String(p.id); tr.dataset.status = p.status;
    const hits = Object.entries(p.hits || {}).map(([k, n]) => `${k} ${n}`).join(", ");
    for (const cell of [p.id, fmt(p.heading_deg, 0, "°"), p.status, hits || "—"]) tr.append(el("td", "", cell));
    tr.append(el("td", "why", (p.reasons || []).join("; ")));
    body.append(tr);
  }
}

function sigmaPoints(g) {
  const hist = (g && g.sigma && g.sigma.history) || [];
  return hist.filter((h) => h.realistic_deg && ["roll", "pitch", "yaw"].some((k) => h.realistic_deg[k] !== null));
}

function renderSigma() {
  const g = guidance();
  const pts = sigmaPoints(g);
  const c = $("sigma");
  c.dataset.points = String(pts.length);
  const [ctx, w, h] = fitCanvas(c);
  ctx.clearRect(0, 0, w, h);
  const limit = (g && g.sigma && g.sigma.current && g.sigma.current.limit_deg) || 0.05;
  const top = Math.max(limit * 1.5, ...pts.flatMap((p) => ["roll", "pitch", "yaw"].map((k) => p.realistic_deg[k] || 0)));
  const L = 34, B = h - 16, nMax = Math.max(6, pts.length);
  const X = (i) => L + (i / Math.max(1, nMax - 1)) * (w - L - 8), Y = (s) => B - (s / top) * (B - 6);
  ctx.strokeStyle = COLORS.grid; ctx.strokeRect(L, 4, w - L - 8, B - 4);
  ctx.fillStyle = COLORS.text; ctx.font = "10px sans-serif";
  ctx.fillText(fmt(top, 3, "°"), 0, 12); ctx.fillText("0", 20, B);
  ctx.fillText("accepted passes →", L + 4, h - 3);
  ctx.strokeStyle = COLORS.limit; ctx.setLineDash([4, 3]);
  ctx.beginPath(); ctx.moveTo(L, Y(limit)); ctx.lineTo(w - 8, Y(limit)); ctx.stroke(); ctx.setLineDash([]);
  for (const k of ["roll", "pitch", "yaw"]) {
    const q = pts.map((p, i) => [X(i), p.realistic_deg[k]]).filter((x) => x[1] !== null && x[1] !== undefined);
    ctx.strokeStyle = COLORS[k]; ctx.fillStyle = COLORS[k]; ctx.lineWidth = 2; ctx.beginPath();
    q.forEach(([x, s], i) => { if (i) ctx.lineTo(x, Y(s)); else ctx.moveTo(x, Y(s)); });
    ctx.stroke();
    for (const [x, s] of q) { ctx.beginPath(); ctx.arc(x, Y(s), 3, 0, 2 * Math.PI); ctx.fill(); }
    ctx.fillText(k, w - 40, 14 + 11 * ["roll", "pitch", "yaw"].indexOf(k));
  }
  const cur = g && g.sigma && g.sigma.current;
  $("sigma-now").textContent = cur && cur.realistic_deg && cur.realistic_deg.roll !== null
    ? `roll ${fmt(cur.realistic_deg.roll, 4, "°")} · pitch ${fmt(cur.realistic_deg.pitch, 4, "°")} · yaw ${fmt(cur.realistic_deg.yaw, 4, "°")} (limit ${fmt(limit, 2, "°")})${g.calibration_ready ? " — every angle observable" : ""}`
    : "no prediction yet: after the first accepted passes";
}

// -- devices, clock, disk, alarms, checks ---------------------------------------------------------

function renderStatus() {
  const st = S.topics.status || {};
  $("vessel").textContent = st.vessel || "—";
  setBadge($("state"), st.state || "?", st.state === "running" ? "ok" : "warn");
  const clk = (S.topics.clock || {}).state || st.clock || "?";
  setBadge($("clock-state"), "clock " + clk, clk === "LOCKED" ? "ok" : clk === "HOLDOVER" ? "warn" : "bad");
  $("session").textContent = st.session || "";
  renderDevices(st);
  const c = S.topics.clock;
  $("clock-detail").textContent = c ? `clock ${c.state}: ±${fmt(c.error_bound_us, 0, " µs")}, jitter ${fmt(c.jitter_rms_us, 0, " µs")} rms, last PPS ${fmt(c.last_edge_age_s, 1, " s")} ago` : "";
  const lg = st.log || {};
  $("disk").textContent = lg.state ? `log ${lg.state}: ${lg.segment || ""}, ${lg.messages || 0} messages, ${fmt((lg.free_mb || 0) / 1024, 1, " GiB")} free, dropped ${lg.dropped || 0}` : "";
  renderMount();
  renderCalibration();
  drawLatency();
}

function renderDevices(st) {
  const body = $("devices").tBodies[0];
  body.replaceChildren();
  for (const name of Object.keys(st.devices || {}).sort()) {
    const s = S.topics["sensors/" + name] || {};
    const tr = el("tr", s.state === "connected" ? "" : "bad");
    tr.dataset.device = name; tr.dataset.state = s.state || st.devices[name];
    tr.append(el("td", "", name), el("td", "", s.state || st.devices[name]), el("td", "", fmt(s.rate_hz, 1, " Hz")),
      el("td", "", s.latency_ms !== undefined ? `${fmt(s.latency_ms, 1)} / ${fmt(s.latency_p99_ms, 1, " ms")}` : "—"));
    body.append(tr);
  }
}

function renderMount() {
  const m = ((S.topics.checklist || {}).mount) || null;
  const e = $("mount");
  if (!m) { e.textContent = "mount watch: not running"; e.dataset.verdict = ""; return; }
  const stat = ((S.topics.mount || {}).state || {}).statistic;
  const per = Array.isArray(stat) ? ` (statistic roll ${fmt(stat[0], 2)}, pitch ${fmt(stat[1], 2)}, yaw ${fmt(stat[2], 2)} of the threshold)` : "";
  e.textContent = `mount watch: ${m.verdict}${per}`;
  e.dataset.verdict = m.verdict;
}

function renderCalibration() {
  const c = S.topics.calibration || null;
  const e = $("calibration");
  if (!c) { e.textContent = ""; return; }
  if (c.error) { e.textContent = `last calibration: history unreadable (${c.error})`; e.dataset.verdict = ""; return; }
  if (!c.recorded) { e.textContent = `last calibration: none recorded for ${c.vessel}`; e.dataset.verdict = ""; return; }
  const b = c.boresight_deg, s = c.sigma_deg;
  const angle = (k) => `${k} ${fmt(b[k], 4)}° ± ${fmt(s[k], 4)}°`;
  e.textContent = `last calibration #${c.id} (${c.date_utc.slice(0, 10)}, mount ${c.mount_id}): ${c.verdict || "no verdict"} — ` +
    `${angle("roll")}, ${angle("pitch")}, ${angle("yaw")} (${c.sigma_kind} σ)`;
  e.dataset.verdict = c.verdict || "";
}

function drawLatency() {
  const [ctx, w, h] = fitCanvas($("latency"));
  ctx.clearRect(0, 0, w, h);
  const series = Object.entries(S.lat);
  const top = Math.max(1, ...series.flatMap(([, s]) => s));
  const palette = [COLORS.roll, COLORS.pitch, COLORS.yaw, COLORS.accepted];
  ctx.font = "10px sans-serif";
  series.forEach(([name, s], k) => {
    ctx.strokeStyle = palette[k % palette.length]; ctx.fillStyle = ctx.strokeStyle; ctx.lineWidth = 1.5; ctx.beginPath();
    s.forEach((y, i) => { const p = [(i / 119) * w, h - 4 - (y / top) * (h - 14)]; if (i) ctx.lineTo(...p); else ctx.moveTo(...p); });
    ctx.stroke(); ctx.fillText(`${name} ${fmt(s[s.length - 1], 1, " ms")}`, 4 + k * 110, 10);
  });
}

function renderAlarms() {
  const st = S.topics.status || {};
  const now = (S.topics.clock || {}).host_ns;
  const active = (st.alarms || []).filter((a) => a.active !== false);
  const ul = $("alarms");
  ul.replaceChildren();
  ul.dataset.active = active.map((a) => a.name + "/" + a.device).join(" ");
  $("alarm-count").textContent = active.length ? `${active.length} active` : "none";
  for (const a of active) {
    const key = a.name + "/" + a.device;
    const ack = S.acked[key], acked = !!ack && ack.first_host_ns === a.first_host_ns;
    const li = el("li", a.severity + (acked ? " acked" : ""));
    li.dataset.alarm = key;
    const age = now ? Math.max(0, (now - a.first_host_ns) / 1e9) : null;  // (the clock message may be older)
    li.append(el("b", "", `${a.severity} ${key}`), el("span", "age", age !== null ? ageText(age) : ""));
    if (acked) { li.dataset.acked = "yes"; li.append(el("span", "age", "· acknowledged")); }
    else {
      const b = el("button", "act ack", "ack");
      b.disabled = !S.token;
      b.addEventListener("click", () => act("alarm_ack", { alarm: a.name, device: a.device }));
      li.append(b);
    }
    li.append(el("div", "dim", a.message));
    ul.append(li);
  }
}

function ageText(s) { return s < 120 ? `${s.toFixed(0)} s` : s < 7200 ? `${(s / 60).toFixed(0)} min` : `${(s / 3600).toFixed(1)} h`; }

function renderChecks() {
  const cl = S.topics.checklist || {};
  const ul = $("checks");
  ul.replaceChildren();
  for (const [name, c] of Object.entries(cl.presurvey || {})) {
    const li = el("li", c.ok ? "check-ok" : "check-bad", `${name.replace(/_/g, " ")}: ${c.detail}`);
    ul.append(li);
  }
}

// -- operator actions -------------------------------------------------------------------------------

async function act(name, body) {
  const out = $("action-result");
  const headers = { "Content-Type": "application/json" };
  if (S.token) headers.Authorization = "Bearer " + S.token;
  let answer;
  try {
    const r = await fetch("/api/action/" + name, { method: "POST", headers, body: JSON.stringify(body) });
    answer = await r.json();
    answer.status = r.status;
    if (r.status === 401 || r.status === 403) setToken(null);
  } catch (e) {
    answer = { ok: false, message: String(e), status: 0 };
  }
  out.textContent = `${name}: ${answer.message}`;
  out.dataset.status = answer.ok ? "ok" : "refused";
  out.dataset.code = String(answer.status);
  window.mlsConsole.lastAction = answer;
}

function setToken(tok) {
  S.token = tok || null;
  if (S.token) sessionStorage.setItem("mls-token", S.token); else sessionStorage.removeItem("mls-token");
  const on = !!S.token;
  setBadge($("mode"), on ? "operator" : "read-only", on ? "ok" : "");
  for (const b of document.querySelectorAll("button.act")) b.disabled = !on;
  $("token").value = "";
}

function wireControls() {
  $("token-form").addEventListener("submit", (ev) => { ev.preventDefault(); setToken($("token").value.trim()); });
  $("token-forget").addEventListener("click", () => setToken(null));
  const passId = () => parseInt($("pass-id").value, 10);
  $("pass-start").addEventListener("click", () => act("pass_start", { pass_id: passId() }));
  $("pass-end").addEventListener("click", () => act("pass_end", { pass_id: passId() }));
  $("mark").addEventListener("click", () => act("mark", { text: $("mark-text").value || "mark" }));
  $("zoom-in").addEventListener("click", () => zoom(1 / 1.5));
  $("zoom-out").addEventListener("click", () => zoom(1.5));
  $("follow").addEventListener("change", (ev) => { view.follow = ev.target.checked; dirty = true; });
  $("plan").addEventListener("wheel", (ev) => { ev.preventDefault(); zoom(ev.deltaY > 0 ? 1.25 : 0.8); }, { passive: false });
  window.addEventListener("resize", () => { dirty = true; });
}

function zoom(f) { view.mPerPx = Math.min(20, Math.max(0.01, view.mPerPx * f)); dirty = true; }

// What each render drew, for tests and tools (window.mlsConsole.history, the last HISTORY_MAX).
const HISTORY_MAX = 20000;
function remember() {
  const g = guidance(), d = view.drawn, h = window.mlsConsole.history;
  h.push({ t_ms: performance.now(), x: d ? d.x : null, y: d ? d.y : null, n_m: d ? d.n_m : null, e_m: d ? d.e_m : null,
    sigma_points: window.mlsConsole.sigmaPoints, accepted: g ? g.accepted : 0,
    alarms: $("alarms").dataset.active });
  if (h.length > HISTORY_MAX) h.splice(0, h.length - HISTORY_MAX);
}

// -- the loop --------------------------------------------------------------------------------------

function render() {
  if (dirty) {
    dirty = false;
    renderStatus(); renderLine(); renderPasses(); renderSigma(); renderAlarms(); renderChecks(); drawPlan();
    window.mlsConsole.drawn = view.drawn;
    window.mlsConsole.sigmaPoints = sigmaPoints(guidance()).length;
    remember();
  }
  requestAnimationFrame(render);
}

window.mlsConsole = { state: S, view, drawn: null, sigmaPoints: 0, lastAction: null, history: [] };
window.addEventListener("DOMContentLoaded", () => {
  wireControls();
  setToken(sessionStorage.getItem("mls-token"));
  connect();
  requestAnimationFrame(render);
});
