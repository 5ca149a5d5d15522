/* The vfm workbench: field view, well view, live updates (server-sent events), diagnosis.
 * Plain JavaScript, no build step; charts with uPlot (vendored). The API token typed on the
 * page is kept in this script's memory only (never stored). Units: Sm3/h, bar a, degC, UTC. */
"use strict";

const state = {
  token: "",
  wells: {},            // well -> row of the field table (summary + view)
  latest: {},           // well -> latest prediction event (for the interval width)
  sort: { key: "well", dir: 1 },
  well: null,           // the well shown in the well view
  preds: [],            // [{t, q, lo, hi, version, choke, p_up, p_down, t_up}]
  meas: [],             // [{t, q, source, predicted, status, inputs}]
  markers: [],          // [{t, kind, label}]
  view: null,           // GET /wells/{well}
  charts: {},
  dirty: false,
  zoomed: false,
  diagJob: null,
  received: 0,
  params: null,         // GET /wells/{well}/parameters
  paramName: null,      // the parameter charted
};
window.vfm = state;     // for the browser tests and for curious users

const $ = (sel) => document.querySelector(sel);
const fmt = (v, d = 1) => (v === null || v === undefined || !isFinite(v) ? "\u2013" : Number(v).toFixed(d));
const secs = (iso) => (iso ? Date.parse(iso) / 1000 : null);
const utc = (iso) => (iso || "").replace("+00:00", "Z");
/* A p-value as read: three decimals down to 0.001, two significant digits below (1.5e-07). */
const pText = (p) => (p == null || !isFinite(p) ? "\u2013" : p >= 0.001 ? Number(p).toFixed(3) : Number(p).toExponential(1).replace(/e-(\d)$/, "e-0$1"));
const esc = (s) => String(s ?? "").replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" }[c]));

async function api(method, path, body) {
  const headers = {};
  if (body !== undefined) headers["content-type"] = "application/json";
  if (state.token) headers["authorization"] = "Bearer " + state.token;
  const r = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  let data = null;
  try { data = await r.json(); } catch (e) { data = null; }
  if (!r.ok) {
    const msg = (data && data.detail) ? (typeof data.detail === "string" ? data.detail : JSON.stringify(data.detail)) : r.statusText;
    const err = new Error(msg); err.status = r.status; throw err;
  }
  return data;
}

function needToken(out) {
  if (state.token) return false;
  out.textContent = "Type the service's API token at the top right first (it stays in this page's memory only).";
  out.className = "result error";
  return true;
}

/* ---------------------------------------------------------------- field view */
/* A residual alarm the service calls small (GET /wells/{well} residual_alarm.small,
   vfm_core.residual_alarm.alarm_size: its size at the raise, |shift|, under the meter's mean
   absolute error over the readings before the change, the error the operator read then): the CUSUM
   found a real move, but no single reading shows it. It is listed, prefixed "small", in the
   warning colour, not the red of an alarm that changes what a reading means; /metrics and the
   alert VfmResidualAlarmSmall (severity info) say the same. */
const SMALL_ALARM = "small ";
function smallShift(v) {
  const ra = v && v.residual_alarm;
  return !!(ra && ra.active && ra.small === true);
}
const isSmallAlarm = (text) => text.startsWith(SMALL_ALARM + "residual alarm");
/* "alarm" (red) when any alarm is not a small one, "warn" when all are, "ok" with none. */
function alarmClass(alarms) {
  return !alarms.length ? "ok" : alarms.every(isSmallAlarm) ? "warn" : "alarm";
}

/* The follow-up of an MPFM residual alarm in a few words, for the field table (the well's
   own page and the cell's tooltip keep the whole sentence): what the well tests since the
   alarm say (GET /wells/{well} residual_alarm.which_moved.moved), or when the next is due. */
function followUpBrief(ra) {
  const moved = ra.which_moved && ra.which_moved.moved;
  if (moved) return moved === "meter" ? "the well tests say the MPFM moved"
    : moved === "well" ? "the well tests say the well moved" : "the well tests cannot tell yet which moved";
  const wait = ra.awaiting_well_test;
  if (!wait) return "";
  if (wait.text.startsWith("which moved")) return "too few well tests before it to tell which moved";
  const due = (wait.due || "").slice(0, 10);
  return !due ? "no well test since the alarm" : wait.overdue ? `next well test overdue since ${due}` : `next well test due about ${due}`;
}

/* The well's alarms as sentences; ``brief``: the field table's (a follow-up in a few words). */
function alarmsOf(v, brief = false) {
  const out = [];
  if (!v) return out;
  // the residual alarm is the alarm; the T^2 input test (v.drift) is only a notice that the
  // operating point left the training data, shown in the drift column, not here
  const ra = v.residual_alarm;
  if (ra && ra.active) {
    const side = ra.direction === "high" ? "above" : "below";
    const meter = ra.source === "well_test" ? "well tests" : (ra.source || "measurements").toUpperCase();
    // its size at the raise, where known (vfm_core.residual_alarm.AlarmSize)
    const by = shiftText(ra.shift);
    const since = (ra.since || "").slice(0, 10);
    // the CUSUM's change-point estimate, where it lies days before the alarm was raised
    const onset = (ra.onset || "").slice(0, 10);
    const began = onset && onset < since ? ` (the change began about ${onset})` : "";
    const small = smallShift(v);
    const lines = [(small ? SMALL_ALARM : "") + `residual alarm: ${meter} ${side} the model${by} since ${since}${began}` +
      (small ? ` (under the model's usual error of ${fmt(ra.typical_error_percent, 1)} % before it)` : "")];
    // a well test since the alarm began: did the meter or the well move? (vfm_core.meter_check)
    if (brief) { const b = followUpBrief(ra); if (b) lines.push(b); }
    else if (ra.which_moved) lines.push(ra.which_moved.text);
    // none yet: when the next well test is due, or why it cannot tell
    else if (ra.awaiting_well_test) lines.push(ra.awaiting_well_test.text);
    // a small alarm's follow-up belongs to it (the same colour), a full one's stands apart
    if (small) out.push(lines.join("; ")); else out.push(...lines);
  }
  for (const [name, p] of Object.entries(v.parameters || {})) if (p.at_bound) out.push(name + " at bound");
  if (v.pending_measurements > 0) out.push(v.pending_measurements + " waiting for a sample");
  if (!v.ready) out.push("no model yet");
  if (v.mpfm_check && v.mpfm_check.alarm) out.push(v.mpfm_check.alarm);
  const held = (v.held_for_review || []).length;
  if (held) out.push(`${held} well test(s) held for review`);
  for (const f of activeFaults(v).filter(raisesAlarm))
    out.push(`instrument fault: ${f.sensor} ${f.kind} since ${day(f.start)}`);
  // a flagged input replaced by its stand-in at the latest sample (GET /wells/{well} fallback)
  const num = (x) => (x == null ? "\u2013" : Number(x).toPrecision(4));
  // the interval at the latest sample covers the rates across the stand-in's span; with a
  // method without intervals (ol, pbl) it is that span alone, empty when the rate does not
  // depend on the input there (critical flow, for p_down): then nothing was widened
  const last = state.latest[v.well];  // none yet on a page just opened: nothing said
  const band = last && last.q_total_p05 != null && last.q_total_p95 != null && last.q_total_p95 > last.q_total_p05;
  const widened = !last ? "" : band ? `, interval widened to ${num(last.q_total_p05)}\u2013${num(last.q_total_p95)} Sm3/h`
    : "; the predicted rate does not move across the stand-in's span here (nothing to widen)";
  for (const f of v.fallback || [])
    out.push(`rate predicted with a stand-in for ${f.sensor}: ${num(f.value)} instead of the reading ${num(f.measured)}${widened}`);
  return out;
}

/* Counts since the service started, not conditions of now: a note beside the alarms, in
   grey, never an alarm of its own (two measurements held at a transmitter's fault months
   ago would otherwise keep the well red for good). */
function notesOf(v) {
  const out = [];
  if (!v) return out;
  // a measurement held (for review, or at an instrument fault) is stored, not refused;
  // these are the well's own counts (GET /wells/{well} rejected), the banner's all wells'
  const counts = Object.entries(v.rejected || {});
  const listed = (rows) => rows.map(([r, k]) => `${r} (${k})`).join(", ");  // as the banner
  const total = (rows) => rows.reduce((a, [, k]) => a + k, 0);
  const heldRows = counts.filter(([r]) => HELD_REASONS.includes(r));
  const bad = counts.filter(([r]) => !HELD_REASONS.includes(r));
  if (heldRows.length)
    out.push(total(heldRows) + " measurement(s) of this well held since the service started (stored, not learned): " + listed(heldRows));
  if (bad.length) out.push(total(bad) + " input(s) of this well refused since the service started: " + listed(bad));
  return out;
}

/* The reasons under which a measurement is stored but not learned (service/errors.py): the
   page lists them apart from the inputs that were refused. */
const HELD_REASONS = ["held for review", "sensor fault at the sample"];

/* Instrument faults (GET /wells/{well} sensor_faults, vfm_core/sensor_faults.py): the
   active ones have no end. A spike begins and ends at its sample. */
/* Whether a fault raises an alarm is the service's (each fault's "alarm", from
   vfm_core.sensor_faults.raises_alarm: the kinds whose measured false rate is within the
   detectors' budget, and a choke offset, found by its witness); an input's own offset (0.2
   per well-year on clean fields, nearly all separator set-point steps) and a spike show on
   the charts and in the list only. */
const raisesAlarm = (f) => f.alarm === true;
function activeFaults(v) { return ((v && v.sensor_faults) || []).filter((f) => f.end == null); }
const day = (iso) => (iso || "").slice(0, 10);
const minute = (iso) => (iso || "").slice(0, 16).replace("T", " ");

function widthOf(well) {
  // the latest live prediction, else (a page opened after the predictions) the well view's
  const p = state.latest[well] || (state.wells[well] || {}).latest_prediction;
  if (!p || p.q_total_p05 == null || p.q_total_p95 == null || !p.q_total) return null;
  // an empty band is no interval: a method without intervals (ol, pbl) whose rate does not
  // move across a stand-in's span (p_down in critical flow) shows a dash, not a certain 0.0
  if (!(p.q_total_p95 > p.q_total_p05)) return null;
  return 100 * (p.q_total_p95 - p.q_total_p05) / p.q_total;
}

function fieldRow(well) {
  const v = state.wells[well] || {};
  // the operating point inside/outside the training data: a notice, not an alarm, in plain
  // text (renderField colours only "active"/"seen")
  const drift = v.drift ? (v.drift.active ? "outside" : (v.drift.enabled ? "inside" : "off")) : "";
  return {
    well, model: v.model, method: v.method, version: v.version, last_update: v.last_update || "",
    mape: v.rolling_mape ? v.rolling_mape.value : null, mape_n: v.rolling_mape ? v.rolling_mape.n : 0,
    width: widthOf(well), drift, alarms: alarmsOf(v, true), notes: notesOf(v),
    // the cell's tooltip: the instrument faults' evidence and the alarms in whole sentences
    faults: activeFaults(v).map((f) => `${f.sensor} ${f.kind}: ${f.evidence}`),
    full: alarmsOf(v),
    // a full alarm's follow-up stands in the list apart from it: shown in plain text, not in
    // the alarm's red (walk56: "the well tests cannot tell yet which moved" read as urgent,
    // when it means "wait for the next well test"); an overdue well test in the warning colour
    follow: v.residual_alarm && v.residual_alarm.active && !smallShift(v) ? followUpBrief(v.residual_alarm) : "",
  };
}

/* The alarm cell's items: the follow-up of a full alarm (fieldRow's ``follow``) in its own span. */
function alarmItems(r) {
  if (!r.alarms.length) return "none";
  const cls = (a) => (a.includes("overdue") ? "follow-up warn" : "follow-up");
  return r.alarms.map((a) => (r.follow && a === r.follow ? `<span class="${cls(a)}">${esc(a)}</span>` : esc(a))).join("; ");
}

function renderField() {
  const rows = Object.keys(state.wells).map(fieldRow);
  const { key, dir } = state.sort;
  rows.sort((a, b) => {
    let x = a[key], y = b[key];
    if (Array.isArray(x)) { x = x.length; y = y.length; }
    if (x == null) return 1; if (y == null) return -1;
    return (x < y ? -1 : x > y ? 1 : 0) * dir;
  });
  const body = $("#field-table tbody");
  body.innerHTML = rows.map((r) => `<tr data-well="${esc(r.well)}">
    <td><a href="#well=${encodeURIComponent(r.well)}">${esc(r.well)}</a></td><td>${esc(r.model)}</td>
    <td>${esc(r.method)}</td><td class="num">${esc(r.version)}</td><td>${esc(r.last_update.replace("+00:00", "Z"))}</td>
    <td class="num" title="over ${r.mape_n} measurement(s)">${fmt(r.mape, 2)}</td><td class="num">${fmt(r.width, 1)}</td>
    <td class="${r.drift === "outside" ? "warn" : ""}">${esc(r.drift)}</td>
    <td class="${alarmClass(r.alarms)}"${r.faults.length || r.full.join() !== r.alarms.join() ? ` title="${esc([...r.full, ...r.faults].join("\n"))}"` : ""}>${alarmItems(r)}${r.notes.length ? `<div class="hint note">${esc(r.notes.join("; "))}</div>` : ""}</td></tr>`).join("");
  document.querySelectorAll("#field-table th").forEach((th) => {
    th.classList.toggle("sorted", th.dataset.key === key);
    th.classList.toggle("asc", th.dataset.key === key && dir > 0);
    th.classList.toggle("desc", th.dataset.key === key && dir < 0);
  });
  $("#field-summary").textContent = `${rows.length} well(s)`;
}

async function refreshField() {
  try {
    const list = await api("GET", "/wells");
    const views = await Promise.all(list.map((w) => api("GET", "/wells/" + encodeURIComponent(w.well)).catch(() => w)));
    const next = {};
    for (const v of views) next[v.well] = v;
    state.wells = next;
    const health = await api("GET", "/health");
    // held measurements (HELD_REASONS) are stored, not refused: listed apart
    const counted = Object.entries(health.rejected || {}).filter(([, n]) => n > 0);
    const rej = counted.filter(([k]) => !HELD_REASONS.includes(k));
    const held = counted.filter(([k]) => HELD_REASONS.includes(k));
    const heldText = held.length ? ` Held (stored, not learned), all wells: ${held.map(([k, n]) => `${k} (${n})`).join(", ")}.` : "";
    // counts since the service started (a restart begins them anew): say so, and since when
    const up = health.uptime_s == null ? "" : ` at ${new Date(Date.now() - 1000 * health.uptime_s).toISOString().slice(0, 16).replace("T", " ")} UTC`;
    $("#inputs-summary").textContent = `Inputs since the service started${up}: accepted ${Object.entries(health.accepted || {}).map(([k, n]) => k + " " + n).join(", ") || "none"}; ` +
      `refused ${rej.length ? rej.map(([k, n]) => k + " " + n).join(", ") : "none"}.` + heldText;
    const banner = $("#banner");
    if (rej.length) {
      banner.hidden = false;
      banner.textContent = "Refused inputs since the start, all wells: " + rej.map(([k, n]) => `${k} (${n})`).join(", ") + ". GET /health gives the reasons.";
    } else banner.hidden = true;
    renderField();
    if (state.well && state.wells[state.well]) {
      state.view = state.wells[state.well]; renderWellHeader(); renderParams(); loadParams(state.well, false);
    }
  } catch (e) {
    $("#field-summary").textContent = "(cannot reach the service: " + e.message + ")";
  }
}

/* ---------------------------------------------------------------- charts */
function wheelZoomPlugin() {
  return {
    hooks: {
      ready: (u) => {
        u.over.addEventListener("wheel", (e) => {
          e.preventDefault();
          const { left } = u.cursor; const x = u.posToVal(left, "x");
          const min = u.scales.x.min, max = u.scales.x.max, f = e.deltaY < 0 ? 0.8 : 1.25;
          u.setScale("x", { min: x - (x - min) * f, max: x + (max - x) * f });
          state.zoomed = true;
        }, { passive: false });
        let drag = null;
        u.over.addEventListener("mousedown", (e) => {
          if (!e.shiftKey) return;
          e.stopPropagation(); e.preventDefault();
          drag = { x: e.clientX, min: u.scales.x.min, max: u.scales.x.max };
        }, true);
        window.addEventListener("mousemove", (e) => {
          if (!drag) return;
          const dx = (e.clientX - drag.x) / u.over.clientWidth * (drag.max - drag.min);
          u.setScale("x", { min: drag.min - dx, max: drag.max - dx });
          state.zoomed = true;
        });
        window.addEventListener("mouseup", () => { drag = null; });
        u.over.addEventListener("dblclick", () => { state.zoomed = false; });
      },
      setSelect: (u) => { if (u.select.width > 0) state.zoomed = true; },
    },
  };
}

const MARK_COLORS = { model: "#c62828", drift: "#ef8f00", retrain: "#7a7a7a", alarm: "rgba(179,38,30,0.75)",
  smallAlarm: "rgba(178,106,0,0.75)", fault: "rgba(106,27,154,0.8)" };
/* A residual alarm's band: red, or the warning colour for a small one (the event's "small":
   its size under the meter's usual error before it), as the lists say. */
const alarmFill = (b) => (b.small === true ? MARK_COLORS.smallAlarm : MARK_COLORS.alarm);
const BAND_PX = 5;  // height of the alarm band and of the fault band under it (CSS px)

/* A residual alarm's event (GET /wells/{well} residual_alarm.events) whose detector started
   over (service/engine/residual_alarms.py WellResidualAlarm.reset, meant for a model change:
   the new model's residuals are a new stream): its end is "reset", not a time. */
const alarmReset = (e) => e.end === "reset" || e.closed === "reset";

/* The residual alarms of the well on view as spans {t0, t1, ...event}, t1 null while active
   (drawn to the chart's right edge); one ended by a model change ends at the first model-change
   marker after its start (at its start when none is on the chart). From GET /wells/{well},
   refreshed every 5 s. */
function alarmBands() {
  const ra = state.view && state.view.residual_alarm;
  return ((ra && ra.events) || []).map((e) => {
    const t0 = secs(e.start);
    let t1 = e.end == null ? null : secs(e.end);
    if (alarmReset(e)) {
      const change = state.markers.filter((m) => m.kind === "model" && m.t >= t0).map((m) => m.t);
      t1 = change.length ? Math.min(...change) : t0;
    }
    return { ...e, t0, t1 };
  });
}

/* A residual alarm in plain words: the meter, its side of the model, its span and how it
   ended (vfm_core/residual_alarm.py: "cleared" when the residuals came back, "accepted" when
   it lasted accept_periods periods; end "reset" when its detector started over; events saved
   before s46 have no "closed": "ended"). */
/* An alarm's size at its raise (vfm_core.residual_alarm.AlarmSize): how far the meter's
   readings moved against the model, " (a shift of +6.3 %)", or "" when not known. */
function shiftText(shift) {
  if (typeof shift !== "number") return "";
  return ` (a shift of ${shift >= 0 ? "+" : "-"}${Math.abs(100 * shift).toFixed(1)} %)`;
}

function alarmText(e, acceptPeriods) {
  const meter = e.source === "well_test" ? "well tests" : (e.source || "measurements").toUpperCase();
  const side = e.direction === "high" ? "above" : e.direction === "low" ? "below" : "off";
  const n = acceptPeriods ?? (state.view && state.view.residual_alarm && state.view.residual_alarm.accept_periods);
  // a small one says so (the service's event.small, its size under the meter's usual error
  // before it, event.typical_error as a ratio)
  const by = e.small === true && typeof e.shift === "number" && typeof e.typical_error === "number"
    ? ` (a small shift of ${e.shift >= 0 ? "+" : "-"}${Math.abs(100 * e.shift).toFixed(1)} %, under the usual error of ${(100 * e.typical_error).toFixed(1)} % before it)`
    : shiftText(e.shift);
  // the change's onset (the CUSUM's change point), where it lies days before the raise
  const onset = (e.onset || "").slice(0, 10);
  const began = onset && onset < (e.start || "").slice(0, 10) ? ` (the change began about ${onset})` : "";
  const what = `${meter} ${side} the model${by}`;
  if (e.end == null) {
    const accept = n > 0 ? `; accepted as the new level if it lasts ${n} periods` : "";
    return `${what} since ${minute(e.start)} UTC${began} (active${accept})`;
  }
  if (alarmReset(e)) return `${what} from ${minute(e.start)} UTC${began}: ended by a model change`;
  const how = e.closed === "cleared" ? "cleared: the residuals came back"
    : e.closed === "accepted" ? `accepted as the new level after ${n ?? "accept_periods"} periods: the alarm restarts from it`
    : "ended";
  return `${what} ${minute(e.start)} to ${minute(e.end)} UTC${began}: ${how}`;
}

/* The instrument faults of the well on view as spans {t0, t1, sensor, kind, evidence}, t1 null
   while active (drawn to the chart's right edge). From GET /wells/{well}, refreshed every 5 s. */
function faultBands() {
  return ((state.view && state.view.sensor_faults) || []).map((f) => ({
    t0: secs(f.start), t1: f.end == null ? null : secs(f.end), sensor: f.sensor, kind: f.kind,
    evidence: f.evidence, start: f.start, end: f.end,
  }));
}

function faultText(f) {
  const when = f.end == null ? `since ${minute(f.start)}` : f.kind === "spike" ? `at ${minute(f.start)}`
    : `${minute(f.start)} to ${minute(f.end)}`;
  return `${f.sensor} ${f.kind} ${when} UTC${f.end == null ? " (active)" : ""}: ${f.evidence}`;
}

/* Markers on a time chart: a model change is a line with its label; a scheduled retrain a
   dashed grey line; an operating-point notice (the T^2 input test, kind "drift") a short tick
   at the bottom, no label; residual alarms a thin red band along the top over their span,
   instrument faults a thin purple band right under it (no text on the chart: the fault's
   sensor, kind and evidence show on hover and in the list line under the rate chart).
   u.faultSpans keeps the fault bands drawn, in canvas pixels, for hover and for tests. */
function markersPlugin(source = () => state.markers, bands = alarmBands, faults = faultBands) {
  const spans = (u, list, y, color) => {
    const ctx = u.ctx; const { left, width } = u.bbox; const dpr = devicePixelRatio;
    const xmin = u.scales.x.min, xmax = u.scales.x.max, out = [];
    for (const b of list) {
      const t1 = b.t1 == null ? xmax : b.t1;
      if (b.t0 == null || t1 < xmin || b.t0 > xmax) continue;
      const x0 = Math.max(left, u.valToPos(b.t0, "x", true));
      const x1 = Math.min(left + width, u.valToPos(t1, "x", true));
      const w = Math.max(2 * dpr, x1 - x0);
      const fill = typeof color === "function" ? color(b) : color;
      ctx.fillStyle = fill;
      ctx.fillRect(x0, y, w, BAND_PX * dpr);
      out.push({ ...b, fill, x0, x1: x0 + w, y0: y, y1: y + BAND_PX * dpr });
    }
    return out;
  };
  return {
    hooks: {
      draw: (u) => {
        const ctx = u.ctx; const { top, height } = u.bbox;
        const dpr = devicePixelRatio;
        const xmin = u.scales.x.min, xmax = u.scales.x.max;
        ctx.save();
        u.alarmSpans = spans(u, bands(), top, alarmFill);
        u.faultSpans = spans(u, faults(), top + (BAND_PX + 1) * dpr, MARK_COLORS.fault);
        ctx.restore();
        for (const m of source()) {
          if (m.t < xmin || m.t > xmax) continue;
          const x = Math.round(u.valToPos(m.t, "x", true));
          ctx.save();
          ctx.strokeStyle = MARK_COLORS[m.kind] || "#000";
          if (m.kind === "drift") {  // a notice: a tick at the bottom edge
            ctx.lineWidth = 1.5 * dpr;
            ctx.beginPath(); ctx.moveTo(x, top + height); ctx.lineTo(x, top + height - 6 * dpr); ctx.stroke();
            ctx.restore();
            continue;
          }
          ctx.lineWidth = m.kind === "retrain" ? 1 : 2 * dpr;
          if (m.kind === "retrain") ctx.setLineDash([4, 4]);
          ctx.beginPath(); ctx.moveTo(x, top); ctx.lineTo(x, top + height); ctx.stroke();
          if (m.kind !== "retrain") {
            ctx.fillStyle = MARK_COLORS[m.kind];
            ctx.font = `${11 * dpr}px system-ui`;
            ctx.fillText(m.label, x + 4, top + 22 * dpr);  // below the alarm and fault bands
          }
          ctx.restore();
        }
      },
      // hovering a band names its alarm or fault (the chart's title attribute: no text drawn);
      // the two bands touch, so the hover margin reaches only away from the other band
      setCursor: (u) => {
        const dpr = devicePixelRatio, { left, top } = u.cursor;
        const x = left * dpr + u.bbox.left, y = top * dpr + u.bbox.top;
        const on = (s, above, below) => left >= 0 && x >= s.x0 - dpr && x <= s.x1 + dpr && y >= s.y0 - above && y <= s.y1 + below;
        const alarms = (u.alarmSpans || []).filter((s) => on(s, 3 * dpr, 0));
        const faults = (u.faultSpans || []).filter((s) => on(s, 0, 3 * dpr));
        const title = [...alarms.map((s) => "Residual alarm: " + alarmText(s)),
          ...faults.map((s) => "Instrument fault: " + faultText(s))].join("\n");
        if (u.over.title !== title) u.over.title = title;
      },
    },
  };
}

function chartWidth(el) { return Math.max(320, el.clientWidth || el.parentElement.clientWidth - 24); }

function makeCharts() {
  for (const [name, c] of Object.entries(state.charts)) if (name !== "param") c.destroy();
  state.charts = state.charts.param ? { param: state.charts.param } : {};
  const rateEl = $("#rate-chart");
  rateEl.innerHTML = "";
  const pts = (size, fill, shape) => ({ show: true, size, fill, stroke: fill, ...(shape ? { shape } : {}) });
  state.charts.rate = new uPlot({
    width: chartWidth(rateEl), height: 330,
    scales: { x: { time: true } },
    series: [
      { label: "time (UTC)", value: "{YYYY}-{MM}-{DD} {HH}:{mm}" },
      { label: "p05", stroke: "rgba(31,78,121,0.35)", width: 1, spanGaps: true, value: (u, v) => fmt(v, 0) },
      { label: "p95", stroke: "rgba(31,78,121,0.35)", width: 1, spanGaps: true, value: (u, v) => fmt(v, 0) },
      { label: "predicted", stroke: "#1f4e79", width: 1.5, spanGaps: true, value: (u, v) => fmt(v, 0) },
      { label: "MPFM", stroke: "#2e9e44", paths: () => null, points: pts(5, "#2e9e44"), value: (u, v) => fmt(v, 0) },
      { label: "well test", stroke: "#d1495b", paths: () => null, points: pts(9, "#d1495b"), value: (u, v) => fmt(v, 0) },
    ],
    bands: [{ series: [2, 1], fill: "rgba(31,78,121,0.13)" }],
    axes: [{}, { label: "Sm3/h", size: 70 }],
    cursor: { sync: { key: "vfm-x", setSeries: false } },
    plugins: [wheelZoomPlugin(), markersPlugin()],
  }, [[], [], [], [], [], []], rateEl);

  const errEl = $("#error-chart");
  errEl.innerHTML = "";
  state.charts.error = new uPlot({
    width: chartWidth(errEl), height: 220,
    scales: { x: { time: true } },
    series: [
      { label: "time (UTC)", value: "{YYYY}-{MM}-{DD} {HH}:{mm}" },
      { label: "error MPFM %", stroke: "#2e9e44", paths: () => null, points: pts(4, "#2e9e44"), value: (u, v) => fmt(v, 1) },
      { label: "error well test %", stroke: "#d1495b", paths: () => null, points: pts(7, "#d1495b"), value: (u, v) => fmt(v, 1) },
      { label: "rolling |error| %", stroke: "#444", width: 1.5, spanGaps: true, value: (u, v) => fmt(v, 1) },
    ],
    axes: [{}, { label: "%", size: 60 }],
    cursor: { sync: { key: "vfm-x", setSeries: false } },
    plugins: [wheelZoomPlugin(), markersPlugin()],
  }, [[], [], [], []], errEl);

  const resEl = $("#residual-chart");
  resEl.innerHTML = "";
  state.charts.residual = new uPlot({
    width: chartWidth(resEl), height: 230,
    scales: { x: { time: false } },
    series: [
      { label: $("#residual-input").value, value: (u, v) => (v == null ? "\u2013" : String(Number(v.toPrecision(6)))) },
      { label: "error %", stroke: "#1f4e79", paths: () => null, points: pts(4, "#1f4e79"), value: (u, v) => fmt(v, 1) },
    ],
    axes: [{ label: $("#residual-input").selectedOptions[0].textContent, values: tickLabels }, { label: "%", size: 50 }],
  }, [[], []], resEl);
}

/* Tick labels of a numeric axis with as many decimals as the tick spacing needs, so that an
   input that barely moves (a choke from 0.540 to 0.542, ticks 0.0002 apart) gets distinct
   labels (uPlot's default rounds to 3 decimals: 0.54, 0.54, 0.541, 0.541, 0.541, ...). */
function tickLabels(u, splits, axisIdx, space, incr) {
  let d = 0;
  while (d < 12 && Math.abs(incr * 10 ** d - Math.round(incr * 10 ** d)) > 1e-6 * Math.max(1, incr * 10 ** d)) d++;
  return splits.map((v) => (v == null ? "" : v.toFixed(d)));
}

/* The parameter chart: value, value -/+ 2 sd (the band), the bounds dashed. */
function paramSeries() {
  const h = state.params;
  return (h && state.paramName && h.parameters[state.paramName]) || null;
}

function paramMarkers() {
  const h = state.params;
  return ((h && h.model_changes) || []).map((c) => ({ t: secs(c.time), kind: "model", label: "\u2192 " + c.model_after }));
}

function paramRange(u, dmin, dmax) {
  const p = paramSeries();
  if (!p || !p.value.length) return [dmin, dmax];
  const lo = [], hi = [];
  p.value.forEach((v, i) => {
    if (v == null) return;
    const sd = p.std[i] || 0; lo.push(v - 2 * sd); hi.push(v + 2 * sd);
  });
  let min = Math.min(...lo), max = Math.max(...hi);
  let span = max - min || Math.abs(max) * 0.01 || 1;
  const all = $("#param-bounds").checked;
  // a bound near the values is drawn in view; far ones only when asked for
  if (p.low != null && (all || p.low >= min - span)) min = Math.min(min, p.low);
  if (p.high != null && (all || p.high <= max + span)) max = Math.max(max, p.high);
  span = max - min || 1;
  return [min - 0.08 * span, max + 0.08 * span];
}

function paramData() {
  const p = paramSeries();
  if (!p) return [[], [], [], [], [], []];
  const t = p.time.map(secs);
  const band = (k) => p.value.map((v, i) => (v == null || p.std[i] == null ? null : v + k * 2 * p.std[i]));
  return [t, p.value, band(-1), band(1), t.map(() => p.low), t.map(() => p.high)];
}

function makeParamChart() {
  if (state.charts.param) state.charts.param.destroy();
  const el = $("#param-chart");
  el.innerHTML = "";
  const p = paramSeries();
  const unit = p ? p.unit : "";
  const f = (u, v) => (v == null ? "\u2013" : Math.abs(v) >= 1000 || (Math.abs(v) < 0.01 && v !== 0) ? Number(v).toPrecision(4) : fmt(v, 4));
  state.charts.param = new uPlot({
    width: chartWidth(el), height: 240,
    scales: { x: { time: true }, y: { range: paramRange } },
    series: [
      { label: "time (UTC)", value: "{YYYY}-{MM}-{DD} {HH}:{mm}" },
      { label: (state.paramName || "value") + (unit && unit !== "-" ? " (" + unit + ")" : ""), stroke: "#1f4e79", width: 1.5,
        points: { show: true, size: 4, fill: "#1f4e79" }, value: f },
      { label: "\u2212 2 sd", stroke: "rgba(31,78,121,0.35)", width: 1, value: f },
      { label: "+ 2 sd", stroke: "rgba(31,78,121,0.35)", width: 1, value: f },
      { label: "low bound", stroke: "#7a7a7a", width: 1, dash: [6, 4], value: f },
      { label: "high bound", stroke: "#7a7a7a", width: 1, dash: [6, 4], value: f },
    ],
    bands: [{ series: [3, 2], fill: "rgba(31,78,121,0.15)" }],
    axes: [{}, { label: unit && unit !== "-" ? unit : "(dimensionless)", size: 80 }],
    cursor: { sync: { key: "vfm-x", setSeries: false } },
    plugins: [wheelZoomPlugin(), markersPlugin(paramMarkers)],
  }, paramData(), el);
}

function renderParamChoice() {
  const h = state.params;
  const names = h ? Object.keys(h.parameters) : [];
  const sel = $("#param-name");
  if (!names.includes(state.paramName)) state.paramName = names.includes("c_d") ? "c_d" : (names[0] || null);
  const want = names.join("|");
  if (sel.dataset.names !== want) {
    sel.innerHTML = names.map((n) => `<option value="${esc(n)}">${esc(n)}${h.parameters[n].unit && h.parameters[n].unit !== "-" ? " (" + esc(h.parameters[n].unit) + ")" : ""}</option>`).join("");
    sel.dataset.names = want;
  }
  if (state.paramName) sel.value = state.paramName;
  const p = paramSeries();
  const sd = p ? p.std.filter((v) => v != null).length : 0;
  $("#param-stats").textContent = !h ? "" : !names.length ? "No parameters recorded yet (a model without physical parameters, or no learning step since the start)."
    : `${h.rows} recorded row(s)${h.truncated ? " (the latest " + h.rows + ")" : ""}` +
      (p ? ` \u00b7 ${state.paramName}: ${p.value.length} point(s), ${sd ? "with sd" : "no sd (the method keeps none)"}` +
        (p.low != null ? `, bounds ${fmt(p.low, 3)} .. ${fmt(p.high, 3)}` : "") : "");
}

async function loadParams(well, rebuild) {
  try {
    const h = await api("GET", `/wells/${encodeURIComponent(well)}/parameters?limit=2000`);
    if (state.well !== well) return;
    const before = state.paramName;
    state.params = h;
    renderParamChoice();
    if (rebuild || !state.charts.param || before !== state.paramName) makeParamChart();
    else state.charts.param.setData(paramData(), !state.zoomed);
    if (state.zoomed && state.charts.rate) {
      const { min, max } = state.charts.rate.scales.x;
      state.charts.param.setScale("x", { min, max });
    }
  } catch (e) {
    $("#param-stats").textContent = "Cannot load the parameter history: " + e.message;
  }
}

function hasInterval(p) { return p.lo != null && p.hi != null && p.hi > p.lo; }

/* The legend lists p05 and p95 only when some prediction shown has an interval. */
function showIntervalLegend(u, show) {
  const rows = u.root.querySelectorAll(".u-legend .u-series");
  for (const i of [1, 2]) if (rows[i]) rows[i].style.display = show ? "" : "none";
}

/* Align predictions and measurements on one time axis (uPlot wants one x array). */
function rateData() {
  const rows = new Map();
  const row = (t) => { let r = rows.get(t); if (!r) { r = [t, null, null, null, null, null]; rows.set(t, r); } return r; };
  // an interval only where the method gives one (bayes, or a stand-in's widened one): a
  // point whose p05 and p95 equal the prediction (ol, pbl) has none to draw or list
  for (const p of state.preds) {
    const r = row(p.t), band = hasInterval(p);
    r[1] = band ? p.lo : null; r[2] = band ? p.hi : null; r[3] = p.q;
  }
  for (const m of state.meas) { const r = row(m.t); r[m.source === "well_test" ? 5 : 4] = m.q; }
  const all = Array.from(rows.values()).sort((a, b) => a[0] - b[0]);
  return [0, 1, 2, 3, 4, 5].map((i) => all.map((r) => r[i]));
}

function errorRows() {
  return state.meas.filter((m) => m.predicted != null && m.q).map((m) => ({ ...m, err: 100 * (m.predicted - m.q) / m.q }))
    .sort((a, b) => a.t - b.t);
}

function errorData() {
  const rows = errorRows();
  const window = Math.max(5, (state.view && state.view.rolling_mape && state.view.rolling_mape.window) || 50);
  const out = [[], [], [], []]; let sum = 0; const q = [];
  for (const r of rows) {
    q.push(Math.abs(r.err)); sum += Math.abs(r.err);
    if (q.length > window) sum -= q.shift();
    out[0].push(r.t); out[1].push(r.source === "well_test" ? null : r.err);
    out[2].push(r.source === "well_test" ? r.err : null); out[3].push(sum / q.length);
  }
  return out;
}

function residualData() {
  const key = $("#residual-input").value;
  const pts = errorRows().filter((r) => r.inputs).map((r) => [key === "dp" ? r.inputs.p_up - r.inputs.p_down : r.inputs[key], r.err])
    .filter((p) => p[0] != null && isFinite(p[0])).sort((a, b) => a[0] - b[0]);
  return [pts.map((p) => p[0]), pts.map((p) => p[1])];
}

function draw() {
  if (!state.dirty || !state.charts.rate) return;
  state.dirty = false;
  const keep = state.zoomed;
  state.charts.rate.setData(rateData(), !keep);
  showIntervalLegend(state.charts.rate, state.preds.some(hasInterval));
  state.charts.error.setData(errorData(), !keep);
  if (keep) {  // the zoom stays, the other charts follow it
    const { min, max } = state.charts.rate.scales.x;
    state.charts.error.setScale("x", { min, max });
    if (state.charts.param) state.charts.param.setScale("x", { min, max });
  }
  state.charts.residual.setData(residualData());
  const learned = state.meas.filter((m) => m.predicted != null).length;
  $("#well-stats").textContent = `${state.preds.length} predictions, ${state.meas.length} measurements (${learned} learned), ` +
    `${state.markers.length} marker(s)`;
}
setInterval(draw, 500);

/* ---------------------------------------------------------------- well view */
function renderWellHeader() {
  const v = state.view || {};
  $("#well-title").textContent = state.well;
  $("#well-model").textContent = `${v.model || ""} \u00b7 ${v.method || ""} \u00b7 version ${v.version ?? ""} \u00b7 rolling MAPE ` +
    `${fmt(v.rolling_mape && v.rolling_mape.value, 2)} % over ${(v.rolling_mape && v.rolling_mape.n) || 0}`;
  $("#well-model").dataset.model = v.model || "";
  const alarms = alarmsOf(v);
  $("#well-alarms").hidden = !alarms.length;
  $("#well-alarms").className = alarmClass(alarms);
  $("#well-alarms").innerHTML = alarms.length ? "Alarms: " + alarms.map((a) => isSmallAlarm(a)
    ? `<span class="small-shift">${esc(a)}</span>` : esc(a)).join("; ") : "";
  const notes = notesOf(v);  // counts since the service started: a note, not an alarm
  $("#well-notes").hidden = !notes.length;
  $("#well-notes").textContent = notes.join("; ");
  renderTrial(v); renderVersions(v); renderFaults(v); renderAlarms(v); renderReview(v);
}

/* Well tests held for review (GET /wells/{well} held_for_review): far off the model and the
   MPFM, not learned until accepted; accept or reject each (POST .../measurements/review). */
function renderReview(v) {
  const list = (v && v.held_for_review) || [];
  const el = $("#well-review");
  const key = JSON.stringify([state.well, list]);
  if (state.reviewKey === key) return;  // unchanged: no redraw
  state.reviewKey = key;
  el.hidden = !list.length;
  el.innerHTML = !list.length ? "" : `<b>Held for review</b> <span class="hint">(not learned until accepted; GET /wells/${esc(state.well)}: held_for_review)</span>` +
    `<ul>${list.map((h) => `<li class="active" data-time="${esc(h.time)}" title="${esc(h.reason)}">${esc(minute(h.time))} ${esc(h.source)}: ` +
      `${fmt(h.q_total, 0)} Sm3/h, model ${fmt(h.predicted, 0)} Sm3/h (z ${fmt(h.z, 1)}), MPFM ${h.mpfm == null ? "none near" : fmt(h.mpfm, 0) + " Sm3/h"} ` +
      `<button class="review" data-time="${esc(h.time)}" data-source="${esc(h.source)}" data-decision="accept">accept</button> ` +
      `<button class="review" data-time="${esc(h.time)}" data-source="${esc(h.source)}" data-decision="reject">reject</button></li>`).join("")}</ul>`;
  el.querySelectorAll("button.review").forEach((b) => b.addEventListener("click", () => decideReview(b)));
}

async function decideReview(button) {
  const out = $("#review-result");
  if (needToken(out)) return;
  const { time, source, decision } = button.dataset;
  out.className = "result"; out.textContent = `${decision === "accept" ? "accepting" : "rejecting"} the ${source} of ${minute(time)}...`;
  try {
    const r = await api("POST", `/wells/${encodeURIComponent(state.well)}/measurements/review`, { time, source, decision });
    out.textContent = r.status === "learned"
      ? `Accepted and learned: version ${r.version_before} \u2192 ${r.version_after}.` : r.message;
    const v = await api("GET", "/wells/" + encodeURIComponent(state.well));
    state.view = v; state.wells[state.well] = v; renderWellHeader(); renderParams();
    state.dirty = true;
  } catch (err) { out.className = "result error"; out.textContent = err.message; }
}

/* The well's instrument faults as lines under the rate chart, newest first (the latest 8;
   the API keeps the latest 50). */
function renderFaults(v) {
  const list = ((v && v.sensor_faults) || []).slice().reverse();
  const el = $("#well-faults");
  const key = JSON.stringify([state.well, list]);
  if (state.faultsKey === key) return;  // unchanged: no redraw
  state.faultsKey = key;
  el.hidden = !list.length;
  const shown = list.slice(0, 8);
  el.innerHTML = !list.length ? "" : `<span class="mk fault"><b>Instrument faults</b></span> <span class="hint">(newest first; GET /wells/${esc(state.well)}: sensor_faults)</span>` +
    `<ul>${shown.map((f) => `<li class="${f.end == null ? "active" : "past"}" data-sensor="${esc(f.sensor)}" data-kind="${esc(f.kind)}"` +
      ` data-start="${esc(f.start)}" data-active="${f.end == null}">${esc(faultText(f))}</li>`).join("")}</ul>` +
    (list.length > shown.length ? `<span class="hint">and ${list.length - shown.length} earlier</span>` : "");
  state.dirty = true;  // the bands come with the view: redraw
}

/* What a period of the residual alarm's meters is, from its streams (the settings'
   residual_alarm.mpfm_period_s and well_test_period_s): "a period: a day of MPFM readings; ". */
function periodWords(ra) {
  const words = Object.entries(ra.streams || {}).map(([source, st]) => {
    const meter = source === "well_test" ? "well test" : source.toUpperCase() + " reading";
    const p = st.period_s || 0;
    if (!(p > 0)) return `one ${meter}`;
    const span = p % 86400 === 0 ? (p === 86400 ? "a day" : `${p / 86400} days`) : `${fmt(p / 3600, 1)} h`;
    return `${span} of ${meter}s`;
  });
  return words.length ? `a period: ${words.join(", ")}; ` : "";
}

/* The well's residual alarms as lines under the rate chart beside the instrument faults,
   newest first (the latest 8; the API keeps the latest 20): the meter, the side of the model,
   the span and how each ended. */
function renderAlarms(v) {
  const ra = (v && v.residual_alarm) || {};
  const list = (ra.events || []).slice().reverse();
  const el = $("#well-residual-alarms");
  const key = JSON.stringify([state.well, list, ra.accept_periods]);
  if (state.alarmsKey === key) return;  // unchanged: no redraw
  state.alarmsKey = key;
  el.hidden = !list.length;
  const shown = list.slice(0, 8);
  const closed = (e) => (alarmReset(e) ? "reset" : e.closed || (e.end == null ? "" : "ended"));
  el.innerHTML = !list.length ? "" : `<span class="mk alarm"><b>Residual alarms</b></span> <span class="hint">(newest first; ` +
    `${periodWords(ra)}GET /wells/${esc(state.well)}: residual_alarm.events)</span>` +
    `<ul>${shown.map((e) => `<li class="${e.end == null ? "active" : "past"}" data-source="${esc(e.source)}" data-direction="${esc(e.direction)}"` +
      ` data-start="${esc(e.start)}" data-closed="${esc(closed(e))}" data-active="${e.end == null}">${esc(alarmText(e, ra.accept_periods))}</li>`).join("")}</ul>` +
    (list.length > shown.length ? `<span class="hint">and ${list.length - shown.length} earlier</span>` : "");
  state.dirty = true;  // the bands come with the view: redraw
}

/* The trial of the last model change against its shadow (the model it replaced), both
   errors side by side on the same paired measurements. */
function renderTrial(v) {
  const t = v.trial, el = $("#well-trial");
  el.hidden = !t;
  if (!t) { el.textContent = ""; return; }
  const what = { running: "running", kept: "kept", rolled_back: "rolled back", superseded: "superseded", interrupted: "interrupted" }[t.outcome] || t.outcome;
  // a p-value is not the chance that the shadow is better: name the test, and print a small
  // p as it is (1.5e-07), not as a bare 0.000
  const test = t.p_value == null ? "" : ` (one-sided test of "the shadow is better": p ${pText(t.p_value)})`;
  el.className = "trial " + t.outcome;
  el.dataset.outcome = t.outcome;
  // a change of the learning method alone keeps the model's name: name the methods then
  const named = t.method && t.shadow_method && t.method !== t.shadow_method;
  const label = (m, k) => named ? `${m} (${k})` : m;
  // an ended trial says when it ended: its errors are of its own days, not of the rolling
  // window in the line above
  const span = t.outcome !== "running" && t.ended ? `from ${utc(t.since)} to ${utc(t.ended)}` : `since ${utc(t.since)}`;
  el.textContent = `Trial of ${label(t.model, t.method)} against its shadow ${label(t.shadow_model, t.shadow_method)} ${span}: ` +
    `MAPE ${fmt(t.mape, 2)} % against the shadow's ${fmt(t.shadow_mape, 2)} % over ${t.n} paired measurement(s)${test}. ` +
    `Outcome: ${what}` + (t.outcome === "running" ? ` until ${utc(t.until)} of data (at least ${t.min_pairs ?? ""} pairs).` : ".") +
    (t.why ? " " + t.why : "") + (t.rule ? ` Rule: ${t.rule}` : "") + replacedSince(v, t);
}

/* A kept trial whose model a later change or rollback replaced: the line above it names the
   model that runs now, so say that the trial's model no longer does. */
function replacedSince(v, t) {
  if (t.outcome !== "kept" || t.version == null) return "";
  const later = (v.model_changes || []).filter((c) => c.version_after > t.version);
  if (!later.length) return "";
  const c = later[later.length - 1];
  return ` Since then ${c.kind === "rollback" ? "rolled back" : "changed"} to ${c.model_after}` +
    `${c.method ? " (" + c.method + ")" : ""}, version ${c.version_after}: ${t.model} no longer runs.`;
}

function renderVersions(v) {
  const rows = v.versions || [];
  const key = JSON.stringify([state.well, rows.map((r) => r.version)]);
  if (state.versionsKey === key) return;   // unchanged: keep the buttons under the cursor
  state.versionsKey = key;
  $("#versions-table tbody").innerHTML = rows.map((r) => `<tr><td class="num">${esc(r.version)}</td><td>${esc(r.model)}</td>
    <td>${esc(r.method)}</td><td>${esc((r.replaced || "").replace("+00:00", "Z"))}</td><td>${esc(r.note)}</td>
    <td><button class="rollback" data-version="${esc(r.version)}" title="POST /wells/${esc(state.well)}/model/rollback">roll back</button></td></tr>`).join("") ||
    `<tr><td colspan="6" class="hint">No earlier model yet: the well runs the model it started with.</td></tr>`;
  document.querySelectorAll("#versions-table button.rollback").forEach((b) => b.addEventListener("click", () => rollbackTo(b)));
}

async function rollbackTo(button) {
  const out = $("#rollback-result");
  if (needToken(out)) return;
  const version = Number(button.dataset.version);
  // a rollback swaps the live model at once (recorded, undone only by another change): ask
  const row = ((state.view && state.view.versions) || []).find((r) => Number(r.version) === version) || {};
  if (!window.confirm(`Roll ${state.well} back to version ${version}${row.model ? " (" + row.model + ")" : ""}? ` +
      `It replaces the model that runs now at once, after re-learning what came since it was replaced; no trial runs.`)) {
    out.className = "result"; out.textContent = "Not rolled back."; return;
  }
  out.className = "result"; out.textContent = `rolling back to version ${version} (re-learning what came since)...`;
  document.querySelectorAll("button.rollback").forEach((b) => { b.disabled = true; });
  try {
    const c = await api("POST", `/wells/${encodeURIComponent(state.well)}/model/rollback`, { version });
    out.textContent = `Rolled back: ${c.model_before} \u2192 ${c.model_after} (version ${c.version_before} \u2192 ${c.version_after}); ` +
      `it re-learned ${c.relearned ?? 0} measurement(s) since it was replaced.`;
    const v = await api("GET", "/wells/" + encodeURIComponent(state.well));
    state.view = v; state.wells[state.well] = v; renderWellHeader(); renderParams(); syncDiagModel(v);
    loadParams(state.well, false);
    state.dirty = true;
  } catch (err) { out.className = "result error"; out.textContent = err.message; }
  finally { document.querySelectorAll("button.rollback").forEach((b) => { b.disabled = false; }); }
}

function renderParams() {
  const params = (state.view && state.view.parameters) || {};
  $("#params tbody").innerHTML = Object.entries(params).map(([name, p]) => `<tr><td>${esc(name)}</td>
    <td class="num">${fmt(p.value, 4)}</td><td class="num">${p.fixed ? `<span class="hint" title="set by the model's specification (the diagnosis identified it); nothing learns it">fixed</span>` : p.std == null ? "\u2013" : fmt(p.std, 4)}</td><td>${esc(p.unit)}</td>
    <td>${p.low == null ? "" : fmt(p.low, 3) + " .. " + fmt(p.high, 3)}</td>
    <td class="${p.at_bound ? "alarm" : ""}">${p.at_bound ? "at bound" : ""}</td></tr>`).join("") ||
    `<tr><td colspan="6" class="hint">No physical parameters (the model is not physical, or not ready).</td></tr>`;
}

function markersFromView(v) {
  const out = [];
  // operating-point notices (the T^2 input test): drawn as ticks without a label
  for (const d of (v.drift && v.drift.events) || []) out.push({ t: secs(d.time), kind: "drift", label: "operating point" });
  const changes = v.model_changes || [];
  for (const c of changes) {
    const t = changeTime(v, c);
    // a change of the method alone keeps the model's name: the label names the method then
    const label = "\u2192 " + c.model_after + (c.model_before === c.model_after && c.method ? ` (${c.method})` : "");
    if (t) out.push({ t, kind: "model", label, version: c.version_after });
  }
  // a pbl method's retrains raise the version; so does every step of an online method (ol,
  // bayes) and a model change: only the rises since the well has run the pbl method it runs
  // now are retrains, not the steps of the method it ran before a change
  if ((v.method || "").startsWith("pbl")) {
    const since = pblSince(v);
    let prev = null;
    for (const p of state.preds) {
      if (prev !== null && prev >= since && p.version != null && p.version > prev) out.push({ t: p.t, kind: "retrain", label: "retrain" });
      if (p.version != null) prev = p.version;
    }
  }
  return out;
}

/* Where a model change stands on the charts (data time, s): the well's latest sample when it
   was swapped in, as the replaced version records it (`versions[].replaced`); for a version
   no longer kept, the first prediction of the new version, when the window also holds one of
   an older version; the latest sample for a change with no prediction yet. A change before
   the window's first prediction has no marker (it stood at the window's left edge, dated
   wrongly). */
function changeTime(v, c) {
  const kept = (v.versions || []).find((x) => x.version === c.version_before && x.replaced);
  if (kept) {
    const t = secs(kept.replaced);
    return state.preds.length && t < state.preds[0].t ? null : t;
  }
  const i = state.preds.findIndex((p) => p.version != null && p.version >= c.version_after);
  if (i > 0) return state.preds[i].t;
  return i < 0 ? secs(v.last_sample_time) : null;
}

/* The first version under the pbl method the well runs now: the version after the latest
   change that brought it, walking back over earlier changes while the version each replaced
   ran a pbl method too (`versions[].method`); 0 (from the start) when no change brought it. */
function pblSince(v) {
  const changes = v.model_changes || [];
  let since = 0;
  for (let i = changes.length - 1; i >= 0; i--) {
    const c = changes[i];
    since = c.version_after;
    const before = (v.versions || []).find((x) => x.version === c.version_before);
    if (!before || !(before.method || "").startsWith("pbl")) break;
    if (i === 0) since = 0;
  }
  return since;
}

async function loadWell(well) {
  state.well = well; state.preds = []; state.meas = []; state.markers = []; state.zoomed = false; state.params = null;
  state.diagnosed = null;
  $("#field-view").hidden = true; $("#well-view").hidden = false;
  $("#csv-link").href = `/wells/${encodeURIComponent(well)}/history.csv`;
  $("#csv-link").setAttribute("download", `${well}-history.csv`);
  renderVerdictText(""); $("#diag-headline").textContent = ""; $("#diag-status").textContent = "";
  $("#diag-candidates-table").hidden = true; $("#change-result").textContent = ""; $("#wt-result").textContent = "";
  makeCharts();
  try {
    const v = await api("GET", "/wells/" + encodeURIComponent(well));
    state.view = v; renderWellHeader(); renderParams(); syncDiagModel(v);
    loadParams(well, true);
    const days = Number($("#span").value);
    let query = "?limit=100000";
    if (days > 0 && v.last_sample_time) {
      const start = new Date(Date.parse(v.last_sample_time) - days * 86400e3).toISOString();
      query += "&start=" + encodeURIComponent(start);
    }
    const h = await api("GET", `/wells/${encodeURIComponent(well)}/history${query}`);
    if (state.well !== well) return;
    const byTime = new Map(h.samples.map((s) => [s.time, s]));
    state.preds = h.predictions.map((p) => {
      const s = byTime.get(p.time) || {};
      return { t: secs(p.time), q: p.q_total, lo: p.q_total_p05, hi: p.q_total_p95, version: p.version,
        inputs: { choke: s.choke, p_up: s.p_up, p_down: s.p_down, t_up: s.t_up } };
    });
    state.meas = h.measurements.map((m) => {
      const s = m.paired_sample_time ? byTime.get(m.paired_sample_time) : null;
      return { t: secs(m.time), q: m.q_total, source: m.source, status: m.status, predicted: m.predicted,
        inputs: s ? { choke: s.choke, p_up: s.p_up, p_down: s.p_down, t_up: s.t_up } : null };
    });
    if (!$("#wt-time").value && v.last_sample_time) $("#wt-time").value = v.last_sample_time.replace("+00:00", "Z");
    state.markers = markersFromView(v);
    if (h.truncated) $("#well-stats").textContent = "(only the first 100000 rows of the window are shown)";
    state.dirty = true; draw();
  } catch (e) {
    $("#well-stats").textContent = "Cannot load " + well + ": " + e.message;
  }
}

/* ---------------------------------------------------------------- live */
function onEvent(type, ev) {
  state.received += 1;
  if (type === "prediction") state.latest[ev.well] = ev;
  if (ev.well !== state.well) return;
  const t = secs(ev.time);
  if (type === "prediction") {
    state.preds.push({ t, q: ev.q_total, lo: ev.q_total_p05, hi: ev.q_total_p95, version: ev.version,
      inputs: { choke: ev.choke, p_up: ev.p_up, p_down: ev.p_down, t_up: ev.t_up } });
    const n = state.preds.length;
    if ((state.view && (state.view.method || "").startsWith("pbl")) && n > 1 && ev.version > (state.preds[n - 2].version ?? ev.version))
      state.markers.push({ t, kind: "retrain", label: "retrain" });
  } else if (type === "measurement") {
    state.meas.push({ t, q: ev.q_total, source: ev.source, status: "pending", predicted: null, inputs: null });
  } else if (type === "learned") {
    const m = state.meas.find((x) => x.t === t && x.source === ev.source);
    const s = state.preds.find((p) => p.t === secs(ev.sample_time));
    const inputs = s ? s.inputs : null;
    if (m) { m.predicted = ev.predicted; m.status = "learned"; m.inputs = inputs; }
    else state.meas.push({ t, q: ev.q_total, source: ev.source, status: "learned", predicted: ev.predicted, inputs });
  } else if (type === "drift") {
    state.markers.push({ t, kind: "drift", label: "drift" });
  } else if (type === "alarm" || type === "trial") {
    refreshField();  // the alarm's band and the trial's line come with the well's view
  } else if (type === "model") {
    state.markers.push({ t, kind: "model", label: "\u2192 " + ev.model_after, version: ev.version_after });
    refreshField();
    loadParams(state.well, false);
  }
  state.dirty = true;
}

function connect() {
  const live = $("#live");
  const es = new EventSource("/events");
  es.onopen = () => { live.textContent = "live"; live.className = "live on"; };
  es.onerror = () => { live.textContent = "live: reconnecting"; live.className = "live off"; };
  for (const type of ["prediction", "measurement", "learned", "drift", "model", "alarm", "trial"]) {
    es.addEventListener(type, (e) => onEvent(type, JSON.parse(e.data)));
  }
  es.addEventListener("dropped", (e) => {
    live.textContent = `live (${JSON.parse(e.data).dropped} event(s) dropped: reload for all)`;
  });
}

/* ---------------------------------------------------------------- well test */
async function postWellTest(e) {
  e.preventDefault();
  const out = $("#wt-result");
  if (needToken(out)) return;
  out.className = "result"; out.textContent = "posting...";
  try {
    const r = await api("POST", `/wells/${encodeURIComponent(state.well)}/well-tests`,
      { time: $("#wt-time").value.trim(), q_total: Number($("#wt-rate").value) });
    const b = r.before && r.before.q_total, a = r.after && r.after.q_total;
    out.textContent = `${r.message}\nPrediction at ${r.paired_sample_time || r.time}: before ${fmt(b, 0)} Sm3/h` +
      (r.status === "learned" ? `, after ${fmt(a, 0)} Sm3/h (measured ${fmt(r.q_total, 0)}); version ${r.version_before} \u2192 ${r.version_after}.` : ".");
    refreshField();
  } catch (err) { out.className = "result error"; out.textContent = err.message; }
}

/* ---------------------------------------------------------------- diagnosis */
/* The form's base model follows the well's (mm, hem or ham; else mm), so that what it shows
   is what the diagnosis starts from with the effects the well has. */
function syncDiagModel(v) {
  const select = $("#diag-model");
  const base = v && v.base_model;
  select.value = [...select.options].some((o) => o.value === base) ? base : "mm";
}

async function runDiagnosis(e) {
  e.preventDefault();
  const status = $("#diag-status");
  if (needToken(status)) return;
  status.className = "hint";
  const cands = $("#diag-candidates").value.split(",").map((s) => s.trim()).filter(Boolean);
  const body = { model: $("#diag-model").value, suggest: $("#diag-suggest").checked };
  if (cands.length) body.candidates = cands;
  $("#diag-run").disabled = true; renderVerdictText(""); $("#diag-headline").textContent = ""; $("#diag-candidates-table").hidden = true;
  $("#change-result").textContent = ""; $("#change-result").className = "result";
  try {
    const job = await api("POST", `/wells/${encodeURIComponent(state.well)}/diagnosis`, body);
    state.diagJob = job.job;
    await followDiagnosis(job.job);
  } catch (err) { status.className = "hint error"; status.textContent = err.message; }
  finally { $("#diag-run").disabled = false; }
}

async function followDiagnosis(id) {
  const bar = $("#diag-progress"), status = $("#diag-status");
  bar.hidden = false;
  for (;;) {
    const j = await api("GET", "/diagnosis/" + id);
    bar.value = j.progress;
    status.textContent = `${j.state}: ${Math.round(100 * j.progress)} % \u00b7 ${j.progress_text} \u00b7 ${fmt(j.elapsed_s, 0)} s`;
    if (j.state === "done") { bar.hidden = true; showDiagnosis(j); return; }
    if (j.state === "failed") { bar.hidden = true; status.className = "hint error"; status.textContent = j.error; return; }
    await new Promise((r) => setTimeout(r, 700));
  }
}

/* A hybrid (ham, hem: vfm_core.jobs.diagnose_results.HYBRIDS), whose network takes up what
   an added effect's parameter would read. */
const isHybrid = (model) => ["ham", "hem"].includes(String(model || "").split("+")[0]);

/* The verdict in one line above its sentence (diagnosis.json's verdict: kind, effect,
   driver, live change in MAPE points, instrument): what it is and what the operator can do. */
function verdictHeadline(v, anyway = false) {
  if (!v) return "";
  const live = v.live && v.live.change != null ? ` (live MAPE ${v.live.change >= 0 ? "+" : ""}${fmt(v.live.change, 2)} points)` : "";
  const ins = v.instrument || {};
  switch (v.kind) {
    case "effect": return `Verdict: add ${v.effect}${live}.`;
    case "carried": return `Verdict: ${v.effect}, carried: the learner already follows it${live}; ` +
      (anyway === "hybrid" ? `not offered for accuracy ("add anyway" below adds its parameter, which the hybrid's network may leave near its prior).`
        : anyway ? `not offered for accuracy ("add anyway" below adds it as a parameter to read).` : "nothing offered.");
    case "driver": return `Verdict: the residual depends on ${v.driver}, which no library effect explains; a correction is offered${live}.`;
    case "noise": return "Verdict: noise. Nothing the data support would lower the error.";
    case "instrument": return `Verdict: an instrument, not physics: ${ins.sensor || "an input"} ${ins.kind || "fault"}${ins.start ? " since " + day(ins.start) : ""}.`;
    default: return `Verdict: ${v.kind}.`;
  }
}

function showDiagnosis(j) {
  const d = j.diagnosis;
  state.diagnosed = d;
  $("#diag-headline").textContent = verdictHeadline(d.verdict);
  renderVerdictText(d.verdict.text);
  const diagnosed = [d.model, ...(d.base_effects || [])].join("+");
  // one error, the one the operator sees: the well's own method replayed (live), the outage
  // error beside it; the fit-once figure only as evidence
  const lv = d.live || {}, ou = d.outage || {};
  const mine = (x) => (x.well_mape != null ? x.well_mape : x.mape);
  const errors = d.live ? `live MAPE ${fmt(mine(lv), 2)} % (${esc(lv.method || d.method)} replayed` +
      (lv.service_well_mape != null ? `; the service recorded ${fmt(lv.service_well_mape, 2)} %` : "") + ")" +
      (d.outage && ou.mape != null ? ` \u00b7 in ${esc(ou.label)} outages ${fmt(mine(ou), 2)} %` : "") +
      ` \u00b7 fit-once evidence ${fmt(d.baseline && d.baseline.candidate_mape, 2)} %`
    : `MAPE without a candidate ${fmt(d.baseline && d.baseline.candidate_mape, 2)} % (${esc(d.headline ? d.headline.protocol : "")})`;
  const pool = d.pool && d.pool.focus && (d.pool.wells || []).length > 1 ? ` \u00b7 evidence pooled over ${d.pool.wells.length} wells` : "";
  $("#diag-status").innerHTML = `done in ${fmt(j.elapsed_s, 0)} s \u00b7 ${esc(diagnosed)}: ${errors}${pool} ` +
    (j.report ? `\u00b7 <a href="${j.report}" target="_blank">full report (residual panels)</a>` : "");
  const focus = d.pool && d.pool.focus;
  const mineTest = (c, p) => {
    const t = (c.tests || {})[p];
    if (!t) return null;
    return focus && t.per_well && t.per_well[focus] ? t.per_well[focus] : t;
  };
  const change = (t) => !t || t.change == null ? "\u2013" :
    `${t.change > 0 ? "+" : ""}${fmt(t.change, 2)}` + (t.low != null ? ` [${fmt(t.low, 2)}, ${fmt(t.high, 2)}]` : "");
  const evidence = (c) => {
    const f = (c.tests || {}).live, w = mineTest(c, "live");
    if (!c.replayed || !f) return "not replayed";
    return `p ${fmt(f.p_value, 3)}, q ${fmt(f.q_value, 3)} (field, ${f.n_blocks} blocks)` +
      (focus && w !== f && w ? `; this well p ${fmt(w.p_value, 3)} (${w.n_blocks} blocks)` : "");
  };
  // a "carried" verdict names the physics, but the learner already follows it: adding it
  // is the operator's choice (a parameter to read, outages), offered as such when it raises
  // neither error (the field's, and this well's own where its whole 95 % interval lies above
  // zero: the verdict's sentence reports that rise, and a button beside it must not say the
  // effect "may help when the meter fails"); its trial against the shadow then shows what it does
  const risesHere = (c) => ["live", "outage"].find((p) => ((mineTest(c, p) || {}).low ?? -1) > 0);
  const carried = (c) => !c.offer && d.verdict && d.verdict.kind === "carried" &&
    d.verdict.effect === c.effect && c.replayed && !c.raises_error &&
    !(((c.tests || {}).outage || {}).change > 0) && !risesHere(c);
  // a gain the replay shows (95 % interval below zero, 0.1 points or more) that the
  // diagnosis's whole family of tests does not confirm: the learner does not carry it
  const unproven = (c) => [mineTest(c, "live"), (c.tests || {}).outage].some((t) =>
    t && t.change != null && t.change <= -0.1 && t.high != null && t.high < 0);
  const addTitle = (c) => unproven(c)
    ? `The replay lowers the error with ${esc(c.effect)}, but not beyond chance once every test of the diagnosis is counted: adding it is your call; its trial against the shadow will show`
    : `The learner already carries what ${esc(c.effect)} explains: adding it gives a physical parameter${isHybrid(d.model) ? " (on a hybrid the network takes up the same misfit: the parameter need not read the effect)" : " to read"} and may help when the meter fails, not live accuracy; its trial against the shadow will show`;
  const action = (c, spec) => c.offer
    ? `<button class="apply" data-spec="${esc(spec)}" title="PUT /wells/${esc(state.well)}/model with effects=[${esc(spec)}]">apply</button>`
    : d.verdict && d.verdict.kind === "carried" && d.verdict.effect === c.effect && risesHere(c)
    ? `<span class="hint">raises this well's ${risesHere(c)} error (${change(mineTest(c, risesHere(c)))} points, beyond chance)</span>`
    : carried(c)
    ? `<button class="apply optional" data-spec="${esc(spec)}" title="${addTitle(c)}">add anyway</button>`
    : `<span class="hint">${esc(c.offer_note || (c.raises_error ? "raises the error" : c.replayed ? "no gain beyond noise" : "not replayed"))}</span>`;
  $("#diag-candidates-table thead").innerHTML = `<tr><th>candidate</th><th class="num">live MAPE %</th>
    <th class="num">&Delta; live [95 %]</th><th class="num" title="the outage change pooled over the wells diagnosed together: one well has too few outage windows to sign its own (the verdict text gives this well's)">&Delta; outage, all wells [95 %]</th>
    <th class="num" title="what a trial of the change would measure against its shadow: the candidate fitted before the last 30 days of data, as apply installs it, then learning with the well's method, against the live replay over those days (95 % prediction interval of the next window; a forecast, not a test)">&Delta; trial forecast [95 %]</th><th>meaning and evidence</th><th></th></tr>`;
  const rows = (d.candidates || []).map((c) => `<tr${c.raises_error ? ' class="worse"' : ""}><td>${esc(c.effect)}</td>
    <td class="num">${c.replayed ? fmt((mineTest(c, "live") || {}).mape, 2) : "\u2013"}</td>
    <td class="num">${change(mineTest(c, "live"))}</td><td class="num">${change((c.tests || {}).outage)}</td>
    <td class="num trial">${change(mineTest(c, "trial"))}</td>
    <td>${esc(c.meaning)} <span class="hint">(${esc(evidence(c))}; fit-once ${fmt(c.delta_mape, 2)})</span>${(c.warnings || []).length ? ' <span class="warn">' + esc(c.warnings.map((w) => w.replace(/\.$/, "")).join("; ") + ".") + "</span>" : ""}</td>
    <td>${action(c, c.spec || c.effect)}</td></tr>`);
  if (d.suggestion) {
    const s = d.suggestion;
    rows.push(`<tr><td>suggested: ${esc(s.form)}</td><td class="num">${s.replayed ? fmt((mineTest(s, "live") || {}).mape, 2) : fmt(s.mape, 2)}</td>
      <td class="num">${change(mineTest(s, "live"))}</td><td class="num">${change((s.tests || {}).outage)}</td>
      <td class="num trial">${change(mineTest(s, "trial"))}</td>
      <td>a correction outside the library (${esc(s.driver)}) <span class="hint">(${esc(evidence(s))})</span></td>
      <td>${action(s, s.effects)}</td></tr>`);
  }
  $("#diag-candidates-table tbody").innerHTML = rows.join("") || `<tr><td colspan="7" class="hint">No candidate could be tried.</td></tr>`;
  $("#diag-candidates-table").hidden = false;
  if (d.verdict && d.verdict.kind === "carried") {
    // "nothing offered" beside an "add anyway" button reads as a contradiction: say which
    const anyway = (d.candidates || []).some(carried) && (isHybrid(d.model) ? "hybrid" : true);
    $("#diag-headline").textContent = verdictHeadline(d.verdict, anyway);
  }
  const drivers = (d.drivers || []).filter((x) => x.role === "driver").sort((a, b) => b.score - a.score).slice(0, 4)
    .map((x) => `${x.name} (score ${fmt(x.score, 3)}` + (x.p_value == null ? ")" : `, p ${fmt(x.p_value, 2)})`));
  const real = (d.drivers || []).filter((x) => x.role === "driver" && x.score > 0 && x.p_value != null && x.p_value < 0.05);
  $("#diag-drivers").textContent = (!drivers.length ? "" : real.length
    ? "Inputs the residual depends on beyond chance: " + real.map((x) => `${x.name} (p ${fmt(x.p_value, 3)})`).join(", ") + "."
    : "No input explains the residual beyond chance (p < 0.05); the strongest: " + drivers.join(", ") + ".") +
    (d.fdr && d.fdr.procedure ? ` False discoveries: ${d.fdr.procedure}; ${d.fdr.rejected} of ${d.fdr.tests} tests rejected` +
      (d.fdr.family != null && d.fdr.family < d.fdr.tests ? ` (${d.fdr.family} could reach significance)` : "") +
      (rejectedTests(d).length ? ": " + rejectedTests(d).join(", ") : "") + "." : "");
  document.querySelectorAll("#diag-candidates-table button.apply").forEach((b) => b.addEventListener("click", () => applyEffect(b)));
}

/* The verdict's text, folded: its first sentence (what was found, and what it does to the
   live error) stands in #diag-verdict; the sentences after it (evidence, rivals, what was not
   tested) go under a "the evidence" fold, each a paragraph, unless the whole is short. The
   full text ran to 2,600 characters of bold. Sentences end at ". " before a capital, so
   decimals ("3.55 %") and parameters ("exponent=1.04") stay whole. */
const VERDICT_FOLD = 320;  // characters: about three lines of the verdict's column
function renderVerdictText(text) {
  const all = (text || "").trim();
  const sentences = all.split(/(?<=[.!?])\s+(?=[A-Z])/);
  const more = $("#diag-verdict-more");
  const fold = all.length > VERDICT_FOLD && sentences.length > 1;
  $("#diag-verdict").textContent = fold ? sentences[0] : all;
  more.hidden = !fold;
  more.open = false;
  more.innerHTML = !fold ? "" : `<summary>the evidence (${sentences.length - 1} more sentence${sentences.length > 2 ? "s" : ""})</summary>` +
    sentences.slice(1).map((x) => `<p>${esc(x)}</p>`).join("");
}

/* Beside a held-out check that calls a change worse, what the diagnosis that offered it
   expected (its live replay, this well's figure): two numbers that disagree, each named, and
   which one decides. Empty when the change is not one of the diagnosis's candidates. */
function diagnosisBeside(d, spec) {
  const c = [...(d.candidates || []), ...(d.suggestion ? [d.suggestion] : [])]
    .find((x) => (x.spec || x.effect || x.effects) === spec || x.effect === spec);
  const all = c && (c.tests || {}).live, focus = d.pool && d.pool.focus;
  const t = all && focus && all.per_well && all.per_well[focus] ? all.per_well[focus] : all;
  if (!t || t.base_mape == null || t.mape == null) return "";
  return `\n\nThe diagnosis replayed it learning with ${d.method || "the well's method"}, as the service runs: ` +
    `live MAPE ${fmt(t.base_mape, 2)} % -> ${fmt(t.mape, 2)} %. The held-out check fits both models on the ` +
    `older four fifths of the stored history and lets each learn with its method over the latest fifth; over ` +
    `different spans the two can disagree, and the trial against the shadow decides.`;
}

/* Which tests the false-discovery procedure rejected, by candidate and protocol, as
   "erosion (fit-once: field)" or "slip (fit-once: field, W01, W03; live: W01)": a count alone
   beside a "noise" verdict reads as a contradiction; named, the reader sees which they are
   (fit-once tests name an effect, they do not by themselves give a verdict). */
function rejectedTests(d) {
  const out = [];
  for (const c of [...(d.candidates || []), ...(d.suggestion ? [d.suggestion] : [])]) {
    const parts = [];
    for (const [protocol, t] of Object.entries(c.tests || {})) {
      if (!t || typeof t !== "object") continue;
      const where = [...(t.rejected ? ["field"] : []),
        ...Object.entries(t.per_well || {}).filter(([, w]) => w && w.rejected).map(([well]) => well)];
      if (where.length) parts.push(`${protocol.replace("_", "-")}: ${where.join(", ")}`);
    }
    if (parts.length) out.push(`${c.effect || "the suggested correction"} (${parts.join("; ")})`);
  }
  return out;
}

/* What PUT /wells/{well}/model answered, in a line: the change, its held-out check (named as
   the service ran it: "replayed", each model learning with its own method over the latest
   fifth, as the trial scores it; or fitted once), the trial it starts. */
function changedLine(c) {
  const h = c.holdout || {};
  const how = h.protocol === "replayed" ? ", each model learning with its own method over it as the trial will score it"
    : h.protocol ? ` (${h.protocol})` : "";
  return `Model changed: ${c.model_before} \u2192 ${c.model_after} (version ${c.version_before} \u2192 ${c.version_after}). ` +
    `Held-out MAPE on the latest fifth of the history${how}: ${fmt(h.before, 2)} % before, ${fmt(h.after, 2)} % after` +
    (h.confirmed_worse ? " (worse: applied as confirmed)" : "") + ". " +
    (c.trial ? `On trial against ${c.trial.shadow_model} as a shadow until ${(c.trial.until || "").replace("+00:00", "Z")} of data. ` : "") +
    `Watch the error-over-time chart right of the red marker.`;
}

async function applyEffect(button) {
  const out = $("#change-result");
  if (needToken(out)) return;
  const spec = button.dataset.spec;
  // the model diagnosed (the well's, with the effects found by earlier turns of the loop,
  // or the base model chosen in the form) with the effect added, not in their place
  const d = state.diagnosed || {};
  const model = d.model || state.view.base_model;
  const base = d.model ? (d.base_effects || []) : (state.view.effects || []);
  const effects = [...base.filter((x) => x !== spec), spec];
  out.className = "result"; out.textContent = `fitting ${[model, ...effects].join("+")} on the stored history...`;
  document.querySelectorAll("button.apply").forEach((b) => { b.disabled = true; });
  try {
    const body = model ? { model, effects } : { effects };
    const path = `/wells/${encodeURIComponent(state.well)}/model`;
    let c;
    try {
      c = await api("PUT", path, body);
    } catch (err) {
      // 409 with both held-out MAPEs: the change's own check says worse; ask before forcing it
      if (err.status !== 409 || !/confirm_worse/.test(err.message)) throw err;
      if (!window.confirm(err.message.replace(/ ?Nothing was changed;.*$/, "") + diagnosisBeside(d, spec) +
          "\n\nApply it anyway? Its trial then compares it with the current model.")) {
        out.className = "result"; out.textContent = "Not applied: " + err.message; return;
      }
      out.textContent = `fitting ${[model, ...effects].join("+")} again, confirmed...`;
      c = await api("PUT", path, { ...body, confirm_worse: true });
    }
    out.textContent = changedLine(c);
    const v = await api("GET", "/wells/" + encodeURIComponent(state.well));
    state.view = v; state.wells[state.well] = v; renderWellHeader(); renderParams(); syncDiagModel(v);
    loadParams(state.well, false);
    if (!state.markers.some((m) => m.kind === "model" && m.version === c.version_after)) {
      state.markers.push(...markersFromView(v).filter((m) => m.kind === "model" && m.version === c.version_after));
    }
    state.dirty = true;
  } catch (err) { out.className = "result error"; out.textContent = err.message; }
  finally { document.querySelectorAll("button.apply").forEach((b) => { b.disabled = false; }); }
}

/* ---------------------------------------------------------------- routing */
function route() {
  const m = location.hash.match(/^#well=(.+)$/);
  if (m) loadWell(decodeURIComponent(m[1]));
  else { state.well = null; $("#well-view").hidden = true; $("#field-view").hidden = false; renderField(); }
}

function init() {
  $("#token").addEventListener("input", (e) => { state.token = e.target.value.trim(); });
  document.querySelectorAll("#field-table th").forEach((th) => th.addEventListener("click", () => {
    const key = th.dataset.key;
    state.sort = { key, dir: state.sort.key === key ? -state.sort.dir : 1 };
    renderField();
  }));
  $("#field-table tbody").addEventListener("click", (e) => {
    const tr = e.target.closest("tr[data-well]");
    if (tr) location.hash = "well=" + encodeURIComponent(tr.dataset.well);
  });
  $("#span").addEventListener("change", () => state.well && loadWell(state.well));
  $("#residual-input").addEventListener("change", () => { if (state.well) { makeCharts(); state.dirty = true; draw(); } });
  $("#param-name").addEventListener("change", (e) => { state.paramName = e.target.value; renderParamChoice(); makeParamChart(); });
  $("#param-bounds").addEventListener("change", () => state.charts.param && makeParamChart());
  $("#well-test-form").addEventListener("submit", postWellTest);
  $("#diag-form").addEventListener("submit", runDiagnosis);
  window.addEventListener("hashchange", route);
  window.addEventListener("resize", () => {
    for (const [name, c] of Object.entries(state.charts)) {
      const el = $("#" + name + "-chart"); if (el) c.setSize({ width: chartWidth(el), height: c.height });
    }
  });
  connect();
  refreshField().then(route);
  setInterval(refreshField, 5000);
}

init();

/* ---------------------------------------------------------------- separators (docs/guide/separator.md) */
const sepCharts = {};

/* No line across a stretch without readings (walk57: two months of a historian gap drawn as
   a straight line): a gap over 3 times the readings' median spacing gets a point of nulls.
   ``data``: [times (s), ...series], rising in time. A pending reading's sum (null) is a
   break of that line too: nothing is known there yet. */
function breakGaps(data) {
  const t = data[0];
  if (t.length < 3) return data;
  const steps = t.slice(1).map((x, i) => x - t[i]).sort((a, b) => a - b);
  const limit = 3 * steps[Math.floor(steps.length / 2)];
  const out = data.map(() => []);
  for (let i = 0; i < t.length; i++) {
    if (i > 0 && t[i] - t[i - 1] > limit) {
      out[0].push((t[i] + t[i - 1]) / 2);
      for (let k = 1; k < data.length; k++) out[k].push(null);
    }
    for (let k = 0; k < data.length; k++) out[k].push(data[k][i]);
  }
  return out;
}

function separatorChart(name, recent) {
  const id = "sep-chart-" + name.replace(/[^A-Za-z0-9_-]/g, "_");
  let el = document.getElementById(id);
  if (!el) {
    el = document.createElement("div");
    el.id = id; el.className = "chart small"; el.dataset.separator = name;
    $("#separator-charts").appendChild(el);
  }
  const data = breakGaps([recent.map((r) => secs(r.time)), recent.map((r) => r.q_total), recent.map((r) => r.predicted)]);
  if (sepCharts[name]) { sepCharts[name].setData(data); return; }
  sepCharts[name] = new uPlot({
    title: name, width: chartWidth(el), height: 200,
    scales: { x: { time: true } },
    series: [
      { label: "time (UTC)", value: "{YYYY}-{MM}-{DD} {HH}:{mm}" },
      { label: "measured total", stroke: "#d1495b", width: 1.5, value: (u, v) => fmt(v, 0) },
      { label: "sum of predictions", stroke: "#1f4e79", width: 1.5, value: (u, v) => fmt(v, 0) },
    ],
    axes: [{}, { label: "Sm3/h", size: 70 }],
  }, data, el);
}

async function refreshSeparators() {
  let list;
  try { list = await api("GET", "/separators"); } catch (e) { return; }
  $("#separators").hidden = !list.length;
  $("#separators-table tbody").innerHTML = list.map((s) => `<tr data-separator="${esc(s.separator)}">
    <td>${esc(s.separator)}</td><td>${esc(s.wells.join(", "))}</td><td>${esc(minute(s.time))}</td>
    <td class="num">${fmt(s.q_total, 0)}</td><td class="num">${fmt(s.predicted, 0)}</td>
    <td class="num">${fmt(s.residual, 0)}</td>
    <td class="num">${s.q_total ? fmt(100 * s.residual / s.q_total, 2) : "\u2013"}</td>
    <td>${esc(s.status || "no reading yet")}</td></tr>`).join("");
  for (const s of list) {
    try {
      const v = await api("GET", "/separators/" + encodeURIComponent(s.separator));
      separatorChart(s.separator, v.recent);
    } catch (e) { /* the table says what is known */ }
  }
}

refreshSeparators();
setInterval(refreshSeparators, 5000);
