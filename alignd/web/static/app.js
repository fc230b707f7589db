// alignd dashboard: reads the daemon's JSON views and draws them. Read-only: this script
// never sends anything but GET requests.
"use strict";

const $ = (sel) => document.querySelector(sel);
const UM = "\u00b5m";

function esc(s) {
  return String(s ?? "").replace(/[&<>"']/g, (c) => ({"&": "&amp;", "<": "&lt;", ">": "&gt;",
    '"': "&quot;", "'": "&#39;"}[c]));
}
function fmt(v, digits = 1) { return v === null || v === undefined ? "\u2013" : Number(v).toFixed(digits); }
function offsetText(d) {
  if (!d || d.offset_norm_um === null || d.offset_norm_um === undefined) return "\u2013";
  return d.U_um === null || d.U_um === undefined ? `${fmt(d.offset_norm_um)} ${UM}`
    : `${fmt(d.offset_norm_um)} \u00b1 ${fmt(d.U_um)} ${UM}`;
}
function when(iso) { return iso ? String(iso).slice(0, 19).replace("T", " ") : ""; }
async function getJSON(url) {
  const r = await fetch(url, {cache: "no-store"});
  const body = await r.json();
  if (!r.ok) throw new Error(body.message || `HTTP ${r.status}`);
  return body;
}
function kv(el, pairs) {
  el.innerHTML = pairs.filter(([, v]) => v !== null && v !== undefined && v !== "")
    .map(([k, v]) => `<dt>${esc(k)}</dt><dd>${v}</dd>`).join("");
}
function verdictSpan(v) { return `<span class="v-${esc(v)}">${esc(v)}</span>`; }
function eventsList(el, events) {
  if (!events || !events.length) { el.innerHTML = '<li class="muted">none</li>'; return; }
  el.innerHTML = events.map((e) => `<li class="${esc(e.level || e.type)}">` +
    `${esc(when(e.t && typeof e.t === "number" ? new Date(e.t * 1000).toISOString() : e.t).slice(11))} ` +
    `${esc(e.msg || e.message || e.type)}</li>`).join("");
  el.scrollTop = el.scrollHeight;
}

// ---- dashboard ------------------------------------------------------------------------
const dash = {events: [], eventsRun: null, after: 0};

function showStatus(st) {
  document.title = `alignd: ${st.state}`;
  $("#title").textContent = `alignd \u2013 ${st.name || ""}`;
  const badge = $("#state");
  badge.textContent = st.state;
  badge.className = `badge ${st.state}`;
  const fault = $("#fault");
  fault.hidden = st.state !== "fault";
  if (st.state === "fault") {
    fault.textContent = `Faulted: ${st.fault || "unknown reason"}. An operator must fix the ` +
      "cause and run 'alignctl reset' on the instrument PC.";
  }
  kv($("#run-info"), [["version", esc(st.version)], ["uptime", `${fmt(st.uptime_s / 60, 0)} min`],
    ["config", `<code>${esc(String(st.config_hash || "").slice(0, 12))}</code>`]]);
  const p = st.progress || {};
  const busy = st.run_id !== null && st.run_id !== undefined;
  $("#no-run").hidden = busy;
  $("#run-live").hidden = !busy;
  if (busy) {
    $("#run-title").textContent = `${st.kind} \u2013 run ${st.run_id} (${st.started_by})`;
    $("#progress-phase").textContent = p.phase || "starting";
    $("#progress-iteration").textContent = p.iteration ?? "\u2013";
    $("#progress-step").textContent = p.step !== undefined && p.total ? `${p.step} / ${p.total}` : "\u2013";
    $("#progress-offset").textContent = offsetText(p);
    $("#progress-message").textContent = p.message || "";
    $("#progress-bar").style.width = p.step !== undefined && p.total
      ? `${Math.round(100 * p.step / p.total)}%` : "0%";
  }
  const last = st.last_run;
  $("#last-run").innerHTML = last ? `<a href="/run/${last.id}">run ${last.id}</a> ` +
    `(${esc(last.kind)}): ${verdictSpan(last.verdict)}${last.reason ? " \u2013 " + esc(last.reason) : ""}`
    : "none since the daemon started";
  const axes = st.axes || {};
  const roles = [...new Set([...Object.keys(st.devices || {}), ...Object.keys(axes)])].sort();
  const rows = roles.map((role) => {
    const id = (st.devices || {})[role] || {};
    const ax = axes[role] || {};
    const parts = [id.vendor, id.model].filter(Boolean).join(" ");
    const extra = [id.serial ? `s/n ${esc(id.serial)}` : "", id.firmware ? `fw ${esc(id.firmware)}` : ""]
      .filter(Boolean).join(" ");
    const pos = ax.position === null || ax.position === undefined ? '<span class="muted">not read yet</span>'
      : `${Number(ax.position).toFixed(ax.units === "deg" ? 3 : 4)} ${esc(ax.units)}`;
    const homed = ax.homed === true ? "homed" : ax.homed === false ? '<span class="v-fault">not homed</span>' : "";
    return `<tr><th>${esc(role)}</th><td class="num">${pos}</td><td>${homed}</td>` +
      `<td title="${extra}">${esc(parts)}</td></tr>`;
  });
  $("#devices tbody").innerHTML = rows.join("") ||
    '<tr><td class="muted">no devices connected</td></tr>';
  const web = st.dashboard || {};
  for (const role of ["top", "side"]) {
    const cam = (web.cameras || {})[role];
    const box = $(`#cam-${role}`);
    if (!box) continue;
    box.hidden = !cam;
    box.dataset.unavailable = web.cameras_unavailable || "";
    box.dataset.error = (cam && cam.error) || "";
  }
}

async function pollStatus() {
  try {
    const st = await getJSON("/api/status");
    showStatus(st);
    await pollEvents(st);
  } catch (e) {
    $("#state").textContent = "unreachable";
    $("#state").className = "badge unreachable";
    $("#fault").hidden = false;
    $("#fault").textContent = `The dashboard cannot reach alignd: ${e.message}`;
  }
  setTimeout(pollStatus, 500);
}

async function pollEvents(st) {
  const live = st.run_id !== null && st.run_id !== undefined;
  const runId = live ? st.run_id : (st.last_run ? st.last_run.id : null);
  if (runId === null || runId === undefined) return;
  if (runId !== dash.eventsRun) {
    dash.eventsRun = runId;
    dash.after = 0;
    dash.events = live ? [] : ((await getJSON(`/api/runs/${runId}`)).events || []);
  }
  if (live) {  // the daemon's live event stream: notes, warnings and phase changes
    const reply = await getJSON(`/api/runs/${runId}/events?after=${dash.after}`);
    dash.after = reply.next;
    for (const e of reply.events || []) {
      if (e.type === "progress" && (e.step !== undefined && e.step !== null)) continue;
      const msg = e.type === "progress" ? `[${e.phase}] ${e.message || ""}`
        : e.type === "end" ? `ended: ${e.verdict}${e.reason ? " – " + e.reason : ""}` : e.msg;
      dash.events.push({t: e.t, level: e.level || e.type, msg});
    }
  }
  eventsList($("#events"), dash.events);
}

async function refreshCamera(role) {
  const box = $(`#cam-${role}`);
  const img = box.querySelector("img");
  const none = box.querySelector(".none");
  const cap = box.querySelector("figcaption");
  let wait = 300;
  try {
    const r = await fetch(`/live/${role}.jpg?t=${Date.now()}`, {cache: "no-store"});
    if (!r.ok) {
      const body = await r.json().catch(() => ({message: `HTTP ${r.status}`}));
      img.hidden = true; none.hidden = false;
      none.textContent = body.message;
      cap.textContent = "";
      wait = 1000;
    } else {
      const info = JSON.parse(r.headers.get("X-Alignd-View") || "{}");
      const url = URL.createObjectURL(await r.blob());
      const old = img.src;
      img.src = url;
      img.hidden = false; none.hidden = true;
      if (old.startsWith("blob:")) URL.revokeObjectURL(old);
      const bits = [`frame ${info.seq}`];
      if (info.age_s !== null && info.age_s !== undefined) bits.push(`${fmt(info.age_s)} s old`);
      if (role === "top") {
        bits.push(`holder ${info.holder}`);
        bits.push(info.centre_run ? `centre from run ${info.centre_run}` : "no centre measured yet");
      }
      let text = bits.join(" \u00b7 ");
      if (info.error) text = `camera error: ${info.error} (showing the last good frame) \u00b7 ` + text;
      if (box.dataset.unavailable) text = `cameras unavailable: ${box.dataset.unavailable} \u00b7 ` + text;
      cap.textContent = text;
      cap.className = info.error || box.dataset.unavailable ? "v-fault" : "";
    }
  } catch (e) {
    cap.textContent = `cannot load the ${role} camera view: ${e.message}`;
    wait = 1000;
  }
  setTimeout(() => refreshCamera(role), wait);
}

// ---- history --------------------------------------------------------------------------
function trendSVG(runs, tol) {
  const pts = runs.filter((r) => r.offset_norm_um !== null && r.offset_norm_um !== undefined
    && r.started_at && (r.kind === "check" || r.kind === "align"));
  if (!pts.length) return '<span class="muted">no measured runs yet</span>';
  const W = 1000, H = 340, L = 64, R = 150, T = 14, B = 46;
  const ts = pts.map((r) => Date.parse(r.started_at));
  let t0 = Math.min(...ts), t1 = Math.max(...ts);
  if (t1 - t0 < 60000) { t0 -= 30000; t1 += 30000; }
  const span = t1 - t0; t0 -= span * 0.03; t1 += span * 0.03;
  const top = Math.max(tol || 0, ...pts.map((r) => r.offset_norm_um + (r.U_um || 0)));
  const positive = pts.map((r) => r.offset_norm_um).filter((v) => v > 0);
  // offsets from sub-um to mm: a log axis keeps the tolerance line and both ends readable
  const logScale = positive.length > 0 && top / Math.min(tol || top, ...positive) > 30;
  const x = (t) => L + (t - t0) / (t1 - t0) * (W - L - R);
  let y, ticksY;
  if (logScale) {
    const lo = Math.pow(10, Math.ceil(Math.log10(Math.min(tol || top, ...positive))) - 1);
    const hi = Math.pow(10, Math.ceil(Math.log10(top * 1.05)));
    y = (v) => T + (1 - (Math.log10(Math.max(v, lo)) - Math.log10(lo)) /
      (Math.log10(hi) - Math.log10(lo))) * (H - T - B);
    ticksY = [];
    for (let v = lo; v <= hi * 1.0001; v *= 10) ticksY.push(v);
  } else {
    const ymax = top * 1.12;
    y = (v) => T + (1 - v / ymax) * (H - T - B);
    const step = niceStep(ymax / 5);
    ticksY = [];
    for (let v = 0; v <= ymax + 1e-9; v += step) ticksY.push(v);
  }
  const out = [`<svg class="chart" viewBox="0 0 ${W} ${H}" role="img" aria-label="offset trend">`];
  for (const v of ticksY) {
    out.push(`<line x1="${L}" x2="${W - R}" y1="${y(v)}" y2="${y(v)}" stroke="#e3e6ec"/>`);
    out.push(`<text x="${L - 8}" y="${y(v) + 4}" text-anchor="end">${+v.toFixed(3)}</text>`);
  }
  out.push(`<text x="16" y="${(T + H - B) / 2}" transform="rotate(-90 16 ${(T + H - B) / 2})" ` +
    `text-anchor="middle">|offset| (${UM}${logScale ? ", log scale" : ""})</text>`);
  const ticks = 6;
  let lastDay = "";
  for (let i = 0; i <= ticks; i++) {
    const t = t0 + (t1 - t0) * i / ticks;
    const d = new Date(t).toISOString();
    const clock = t1 - t0 < 2 * 3600e3 ? d.slice(11, 19) : d.slice(11, 16);
    out.push(`<text x="${x(t)}" y="${H - B + 18}" text-anchor="middle">${clock}</text>`);
    if (d.slice(0, 10) !== lastDay) {
      out.push(`<text x="${x(t)}" y="${H - B + 33}" text-anchor="middle">${d.slice(0, 10)}</text>`);
      lastDay = d.slice(0, 10);
    }
  }
  out.push(`<text x="${W - R}" y="${H - 2}" text-anchor="end" fill="#667085">UTC</text>`);
  out.push(`<rect x="${L}" y="${T}" width="${W - L - R}" height="${H - T - B}" fill="none" stroke="#98a2b3"/>`);
  if (tol) {
    out.push(`<line id="tolerance-line" x1="${L}" x2="${W - R}" y1="${y(tol)}" y2="${y(tol)}" ` +
      `stroke="#1a7f37" stroke-dasharray="6 4" stroke-width="1.5"/>`);
    out.push(`<text x="${W - R - 6}" y="${y(tol) - 6}" text-anchor="end" fill="#1a7f37">tolerance ${tol} ${UM}</text>`);
  }
  for (const r of pts) {
    const cx = x(Date.parse(r.started_at)), cy = y(r.offset_norm_um);
    const ok = r.verdict === "aligned" || r.verdict === "within_tolerance";
    const col = ok ? "#1a7f37" : "#c62828";
    if (r.U_um) {
      const y1 = y(r.offset_norm_um + r.U_um), y2 = y(Math.max(r.offset_norm_um - r.U_um, 0));
      out.push(`<line x1="${cx}" x2="${cx}" y1="${y1}" y2="${y2}" stroke="#667085"/>`);
      out.push(`<line x1="${cx - 4}" x2="${cx + 4}" y1="${y1}" y2="${y1}" stroke="#667085"/>`);
      out.push(`<line x1="${cx - 4}" x2="${cx + 4}" y1="${y2}" y2="${y2}" stroke="#667085"/>`);
    }
    const title = `<title>run ${r.id} ${r.kind}: ${offsetText(r)} (${r.verdict})</title>`;
    out.push(r.kind === "check"
      ? `<a href="/run/${r.id}"><circle class="pt" cx="${cx}" cy="${cy}" r="5" fill="${col}">${title}</circle></a>`
      : `<a href="/run/${r.id}"><rect class="pt" x="${cx - 5}" y="${cy - 5}" width="10" height="10" fill="none" stroke="${col}" stroke-width="2">${title}</rect></a>`);
  }
  const lx = W - R + 6;
  out.push(`<circle cx="${lx + 5}" cy="${T + 12}" r="5" fill="#667085"/><text x="${lx + 16}" y="${T + 16}">check</text>`);
  out.push(`<rect x="${lx}" y="${T + 28}" width="10" height="10" fill="none" stroke="#667085" stroke-width="2"/>` +
    `<text x="${lx + 16}" y="${T + 37}">align (final)</text>`);
  out.push(`<text x="${lx}" y="${T + 60}" fill="#1a7f37">green: within</text>`);
  out.push(`<text x="${lx}" y="${T + 76}" fill="#c62828">red: not</text>`);
  out.push("</svg>");
  return out.join("");
}
function niceStep(raw) {
  const p = Math.pow(10, Math.floor(Math.log10(raw)));
  for (const m of [1, 2, 5, 10]) if (m * p >= raw) return m * p;
  return 10 * p;
}

async function loadHistory() {
  try {
    const h = await getJSON("/api/history?limit=500");
    const runs = h.runs || [];
    $("#trend").innerHTML = trendSVG([...runs].reverse(), h.tolerance_um);
    $("#runs-table tbody").innerHTML = runs.map((r) => `<tr>` +
      `<td><a href="/run/${r.id}">${r.id}</a></td><td>${esc(r.kind)}</td>` +
      `<td>${esc(when(r.started_at))}</td><td>${esc(r.user || "?")}/${esc(r.started_by)}</td>` +
      `<td>${verdictSpan(r.verdict || r.status)}</td><td class="num">${offsetText(r)}</td>` +
      `<td>${esc(r.reason || "")}</td></tr>`).join("") ||
      '<tr><td colspan="7" class="muted">no runs recorded yet</td></tr>';
  } catch (e) {
    $("#trend").textContent = `cannot load the history: ${e.message}`;
  }
  setTimeout(loadHistory, 5000);
}

// ---- one run --------------------------------------------------------------------------
function budgetTable(b) {
  if (Array.isArray(b)) {
    const keys = [...new Set(b.flatMap((row) => Object.keys(row)))];
    return `<table><thead><tr>${keys.map((k) => `<th>${esc(k)}</th>`).join("")}</tr></thead><tbody>` +
      b.map((row) => `<tr>${keys.map((k) => `<td>${esc(typeof row[k] === "number" ? +row[k].toPrecision(4) : row[k])}</td>`).join("")}</tr>`).join("") +
      "</tbody></table>";
  }
  return `<pre class="block">${esc(JSON.stringify(b, null, 1))}</pre>`;
}

async function loadRun() {
  const id = location.pathname.split("/").pop();
  try {
    const run = await getJSON(`/api/runs/${id}`);
    const res = run.result || {};
    document.title = `alignd: run ${id}`;
    $("#run-title").textContent = `run ${id} \u2013 ${run.kind}`;
    $("#run-verdict").innerHTML = `<span class="badge ${run.verdict ? "" : "checking"}">` +
      `${esc(run.verdict || run.status)}</span> ${esc(run.reason || "")}`;
    $("#run-verdict .badge").style.background =
      ["aligned", "within_tolerance"].includes(run.verdict) ? "var(--ok)" : run.verdict ? "var(--bad)" : "";
    const off = res.offset_um ? `${offsetText(res)} (k = 2) &nbsp; <span class="muted">x ${fmt(res.offset_um[0])}, ` +
      `y ${fmt(res.offset_um[1])} ${UM}</span>` : offsetText(res);
    kv($("#run-summary"), [["offset", off], ["iterations", res.iterations],
      ["tilt", res.tilt_deg !== null && res.tilt_deg !== undefined ? `${fmt(res.tilt_deg, 4)}\u00b0` +
        (res.tilt_u_deg !== null && res.tilt_u_deg !== undefined
          ? ` \u00b1 ${fmt(res.tilt_u_deg, 4)}\u00b0 <span class="muted">(u, k = 1)</span>` : "") : ""],
      ["yaw", res.yaw_deg !== null && res.yaw_deg !== undefined ? `${fmt(res.yaw_deg, 3)}\u00b0` : ""],
      ["rim eccentricity", res.eccentricity !== null && res.eccentricity !== undefined ? fmt(res.eccentricity, 4) +
        (res.eccentricity_u !== null && res.eccentricity_u !== undefined
          ? ` \u00b1 ${fmt(res.eccentricity_u, 4)} <span class="muted">(u, k = 1)</span>` : "") : ""],
      ["started", `${esc(when(run.started_at))} UTC by ${esc(run.user || "?")}/${esc(run.started_by)}`],
      ["ended", run.ended_at ? `${esc(when(run.ended_at))} UTC` : "still running"],
      ["software", `alignd ${esc(run.software_version)}, config <code>${esc(String(run.config_hash).slice(0, 12))}</code>`],
      ["truth (simulator)", res.truth && res.truth.offset_norm_um !== undefined
        ? `${fmt(res.truth.offset_norm_um)} ${UM} (not used by the loop)` : ""]]);
    $("#download-json").href = `/runs/${id}.json`;
    $("#download-csv").href = `/runs/${id}.csv`;
    const budget = res.budget || res.uncertainty_budget || (run.details || {}).budget;
    $("#budget-card").hidden = !budget;
    if (budget) $("#budget").innerHTML = budgetTable(budget);
    $("#report-img").src = `/runs/${id}/report.png?s=${run.status}`;
    eventsList($("#events"), run.events);
    if (run.status === "running") setTimeout(loadRun, 2000);
  } catch (e) {
    $("#run-title").textContent = `run ${id}: ${e.message}`;
  }
}

const page = document.body.dataset.page;
if (page === "dashboard") { pollStatus(); refreshCamera("top"); refreshCamera("side"); }
else if (page === "history") loadHistory();
else if (page === "run") loadRun();
