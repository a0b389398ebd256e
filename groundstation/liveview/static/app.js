// swarm-gs live view: draws the state pushed on /ws (see groundstation/liveview/server.py for its fields).
"use strict";

const COLORS = { pursuer: "#d62728", scout: "#1f77b4", evader: "#2ca02c" };
const NO_ROLE = "#888888";
const TRAIL_S = 3.0;          // seconds of trail behind each drone
const WARN_EVENTS = new Set(["position_invalid", "roles_reassigned", "ground_station_stall", "preflight_failed"]);
const BAD_EVENTS = new Set(["link_lost", "low_battery", "agent_fault", "fence_breach", "emergency_stop", "dropped",
                            "abort"]);

const canvas = document.getElementById("arena");
const ctx = canvas.getContext("2d");
const trails = new Map();     // drone id -> [[t, x, y], ...]
const seenEvents = new Map(); // event index -> event
let state = null;
let frames = 0;
let lastT = null;

function fmt(v, digits = 2) {
  if (v === null || v === undefined) return "-";
  if (typeof v === "number") return Number.isFinite(v) ? v.toFixed(digits) : String(v);
  return String(v);
}

function message(text) { document.getElementById("message").textContent = text; }

// ---- drawing -----------------------------------------------------------------------------------

function worldToCanvas(scene) {
  const hw = (scene && scene.arena && scene.arena.half_width) || 3.0;
  let half = hw;
  if (scene && scene.fence) for (const [x, y] of scene.fence.polygon) half = Math.max(half, Math.abs(x), Math.abs(y));
  if (scene && scene.anchors) for (const a of scene.anchors) {
    half = Math.max(half, Math.abs(a.position[0]), Math.abs(a.position[1]));
  }
  half += 0.3;
  const s = Math.min(canvas.width, canvas.height) / (2 * half);
  return { s, x: (x) => canvas.width / 2 + x * s, y: (y) => canvas.height / 2 - y * s };
}

function polygon(m, pts) {
  ctx.beginPath();
  pts.forEach(([x, y], i) => (i ? ctx.lineTo(m.x(x), m.y(y)) : ctx.moveTo(m.x(x), m.y(y))));
  ctx.closePath();
}

function draw() {
  ctx.clearRect(0, 0, canvas.width, canvas.height);
  if (!state || !state.scene) { canvas.dataset.drones = "0"; return; }
  const sc = state.scene;
  const m = worldToCanvas(sc);
  // arena
  const hw = sc.arena.half_width;
  ctx.fillStyle = "#f4f4f4";
  ctx.fillRect(m.x(-hw), m.y(hw), 2 * hw * m.s, 2 * hw * m.s);
  // fence and the margin setpoints are kept inside
  ctx.lineWidth = 2; ctx.strokeStyle = "#d62728"; ctx.setLineDash([]);
  polygon(m, sc.fence.polygon); ctx.stroke();
  ctx.lineWidth = 1; ctx.setLineDash([6, 4]);
  polygon(m, sc.fence.safe_polygon); ctx.stroke();
  // keep-out circles, grown by the margin
  for (const k of sc.keep_out) {
    ctx.setLineDash([]); ctx.fillStyle = "rgba(120,120,120,0.55)";
    ctx.beginPath(); ctx.arc(m.x(k.x), m.y(k.y), k.radius * m.s, 0, 2 * Math.PI); ctx.fill();
    ctx.setLineDash([4, 3]); ctx.strokeStyle = "#777";
    ctx.beginPath(); ctx.arc(m.x(k.x), m.y(k.y), (k.radius + sc.fence.margin) * m.s, 0, 2 * Math.PI); ctx.stroke();
  }
  ctx.setLineDash([]);
  // anchors
  ctx.fillStyle = "#7a3fbf";
  for (const a of sc.anchors) {
    const x = m.x(a.position[0]), y = m.y(a.position[1]);
    ctx.beginPath(); ctx.moveTo(x, y - 7); ctx.lineTo(x - 6, y + 5); ctx.lineTo(x + 6, y + 5); ctx.closePath(); ctx.fill();
  }
  // drones: sensing disc, trail, marker
  let drawn = 0;
  for (const d of state.drones) {
    if (!d.position) continue;
    const color = COLORS[d.role] || NO_ROLE;
    const [x, y, z] = d.position;
    const cx = m.x(x), cy = m.y(y);
    const airborne = ["taking_off", "flying", "holding", "landing", "lost"].includes(d.status);
    if (sc.sensing_range && airborne) {
      ctx.fillStyle = color + "14"; ctx.strokeStyle = color + "55";
      ctx.beginPath(); ctx.arc(cx, cy, sc.sensing_range * m.s, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
    }
    const trail = trails.get(d.id) || [];
    if (trail.length > 1) {
      ctx.strokeStyle = color; ctx.globalAlpha = 0.6; ctx.lineWidth = 1.5;
      ctx.beginPath();
      trail.forEach(([, tx, ty], i) => (i ? ctx.lineTo(m.x(tx), m.y(ty)) : ctx.moveTo(m.x(tx), m.y(ty))));
      ctx.stroke(); ctx.globalAlpha = 1.0; ctx.lineWidth = 1;
    }
    ctx.fillStyle = color;
    ctx.strokeStyle = d.status === "lost" || d.status === "stopped" ? "#000" : "#fff";
    ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(cx, cy, airborne ? 7 : 5, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
    ctx.lineWidth = 1;
    ctx.fillStyle = "#222"; ctx.font = "11px sans-serif";
    ctx.fillText(`${d.id} ${z.toFixed(2)}`, cx + 9, cy - 6);
    drawn += 1;
  }
  canvas.dataset.drones = String(drawn);
}

// ---- tables --------------------------------------------------------------------------------------

function updateTable() {
  const body = document.querySelector("#drones tbody");
  const rows = new Map([...body.querySelectorAll("tr")].map((tr) => [tr.dataset.drone, tr]));
  const canLand = state.controls.includes("land");
  for (const d of state.drones) {
    let tr = rows.get(d.id);
    if (!tr) {
      tr = document.createElement("tr");
      tr.dataset.drone = d.id;
      for (let i = 0; i < 10; i++) tr.appendChild(document.createElement("td"));
      const cell = document.createElement("td");
      const b = document.createElement("button");
      b.textContent = "Land"; b.className = "land-one warn";
      b.addEventListener("click", () => post(`/api/land/${encodeURIComponent(d.id)}`, {}));
      cell.appendChild(b); tr.appendChild(cell);
      body.appendChild(tr);
    }
    rows.delete(d.id);
    const pos = d.position ? `(${d.position.map((c) => c.toFixed(2)).join(", ")})` : "-";
    const vals = [d.id, d.role || "-", d.actor || "-", d.status + (d.reason ? ` (${d.reason})` : ""),
                  fmt(d.battery), fmt(d.link_quality), fmt(d.position_variance, 5), fmt(d.command_age),
                  fmt(d.telemetry_age, 3), pos];
    vals.forEach((v, i) => { if (tr.children[i].textContent !== v) tr.children[i].textContent = v; });
    tr.dataset.status = d.status;
    tr.className = `status-${d.status}`;
    const btn = tr.querySelector("button");
    btn.disabled = !canLand || !["taking_off", "flying", "holding"].includes(d.status);
  }
  for (const tr of rows.values()) tr.remove();
}

function updateMetrics() {
  const body = document.querySelector("#metrics tbody");
  const m = state.metrics || {};
  const names = [["mean_min_dist", "distance to targets, min [m]"], ["mean_avg_dist", "mean [m]"],
                 ["mean_max_dist", "max [m]"], ["tracking_rate", "tracking rate"], ["coverage", "coverage"],
                 ["coverage_instant", "coverage now"], ["captures", "captures"], ["episodes", "episodes"],
                 ["steps", "control periods"]];
  body.innerHTML = "";
  for (const [k, label] of names) {
    if (!(k in m)) continue;
    const tr = document.createElement("tr");
    tr.dataset.metric = k;
    const digits = ["captures", "episodes", "steps"].includes(k) ? 0 : 3;
    tr.innerHTML = `<td>${label}</td><td class="num">${fmt(m[k], digits)}</td>`;
    body.appendChild(tr);
  }
}

function updateEvents() {
  for (const e of state.events || []) if (!seenEvents.has(e.i)) seenEvents.set(e.i, e);
  const show = document.getElementById("show-status").checked;
  const list = document.getElementById("events");
  const items = [...seenEvents.values()].filter((e) => show || e.kind !== "status").sort((a, b) => b.i - a.i);
  const key = items.length ? `${items.length}:${items[0].i}:${show}` : "0";
  if (list.dataset.key === key) return;
  list.dataset.key = key;
  list.innerHTML = "";
  for (const e of items.slice(0, 300)) {
    const li = document.createElement("li");
    li.className = BAD_EVENTS.has(e.kind) ? "bad" : WARN_EVENTS.has(e.kind) ? "warn" : "";
    li.textContent = `t=${e.t.toFixed(2)} s ${e.drone || ""} ${e.kind}${e.detail ? ": " + e.detail : ""}`;
    list.appendChild(li);
  }
}

function updateHeader() {
  document.getElementById("mode").textContent = state.mode + (state.mission ? " (mission)" : "");
  document.getElementById("clock").textContent = `t = ${fmt(state.t, 1)} s`;
  const c = state.controls || [];
  document.getElementById("land-all").disabled = !c.includes("land_all");
  document.getElementById("estop").disabled = !c.includes("emergency_stop");
  document.getElementById("controls").hidden = state.mode === "replay";  // a replay commands no drone
  const replay = document.getElementById("replay");
  replay.hidden = state.mode !== "replay";
  if (state.mode === "replay" && state.replay) {
    const r = state.replay;
    const seek = document.getElementById("replay-seek");
    seek.max = String(r.duration);
    if (document.activeElement !== seek) seek.value = String(r.t);
    document.getElementById("replay-time").textContent = `${fmt(r.t, 1)} / ${fmt(r.duration, 1)} s`;
    document.getElementById("replay-pause").textContent = r.paused ? "Play" : "Pause";
  }
}

function updateTrails() {
  if (lastT !== null && state.t < lastT) trails.clear();  // a replay seeked back
  lastT = state.t;
  for (const d of state.drones) {
    if (!d.position) continue;
    const tr = trails.get(d.id) || [];
    tr.push([state.t, d.position[0], d.position[1]]);
    while (tr.length && tr[0][0] < state.t - TRAIL_S) tr.shift();
    trails.set(d.id, tr);
  }
}

function onState(s) {
  state = s;
  frames += 1;
  canvas.dataset.frames = String(frames);
  updateTrails();
  updateHeader();
  updateTable();
  updateMetrics();
  updateEvents();
  draw();
}

// ---- controls ----------------------------------------------------------------------------------

async function post(path, body) {
  try {
    const r = await fetch(path, { method: "POST", headers: { "Content-Type": "application/json" },
                                  body: JSON.stringify(body) });
    const out = await r.json();
    message(out.ok ? `${path}: done` : `${path}: ${out.error}`);
    return out;
  } catch (err) {
    message(`${path}: ${err}`);
    return null;
  }
}

document.getElementById("land-all").addEventListener("click", () => post("/api/land_all", {}));
document.getElementById("estop").addEventListener("click", () => {
  document.getElementById("estop-confirm").hidden = false;
});
document.getElementById("estop-no").addEventListener("click", () => {
  document.getElementById("estop-confirm").hidden = true;
});
document.getElementById("estop-yes").addEventListener("click", () => {
  document.getElementById("estop-confirm").hidden = true;
  post("/api/emergency_stop", { confirm: true });
});
document.getElementById("show-status").addEventListener("change", () => state && updateEvents());
document.getElementById("replay-pause").addEventListener("click", () => {
  post("/api/replay", { pause: !(state && state.replay && state.replay.paused) });
});
document.getElementById("replay-seek").addEventListener("change", (e) => {
  post("/api/replay", { seek: Number(e.target.value) });
});
document.getElementById("replay-speed").addEventListener("change", (e) => {
  post("/api/replay", { speed: Number(e.target.value) });
});

// ---- the WebSocket -------------------------------------------------------------------------------

function connect() {
  const ws = new WebSocket(`ws://${location.host}/ws`);
  const link = document.getElementById("link");
  ws.onopen = () => { link.textContent = "connected"; link.className = "ok"; };
  ws.onmessage = (ev) => onState(JSON.parse(ev.data));
  ws.onclose = () => {
    link.textContent = "no connection (retrying)"; link.className = "bad";
    setTimeout(connect, 1000);
  };
}
connect();
