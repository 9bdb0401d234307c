// fxcell operator page: plain JavaScript, no build step, no external resources.
"use strict";

const $ = (sel) => document.querySelector(sel);
const $$ = (sel) => Array.from(document.querySelectorAll(sel));

const page = {
  info: null, chart: null, commands: null, state: "disconnected", robot: null, targetQ: null,
  control: null, lease: null, leaseComing: null, ops: new Map(), ws: null, wsRetry: 500,
  client: sessionStorage.getItem("fxcell-client") ||
    `web page ${Math.random().toString(16).slice(2, 8)} (${navigator.platform || "browser"})`,
  azimuth: -0.9, elevation: 0.45,
};
sessionStorage.setItem("fxcell-client", page.client);

// A token in the URL fragment (#token=...) is stored and removed from the address bar.
(function takeTokenFromUrl() {
  const m = location.hash.match(/token=([^&]+)/);
  if (m) {
    localStorage.setItem("fxcell-token", decodeURIComponent(m[1]));
    history.replaceState(null, "", location.pathname + location.search);
  }
  $("#token").value = localStorage.getItem("fxcell-token") || "";
  $("#token").addEventListener("change", (e) => localStorage.setItem("fxcell-token", e.target.value.trim()));
})();

// ------------------------------------------------------------------ event log

function log(text, kind = "") {
  const li = document.createElement("li");
  const t = new Date().toLocaleTimeString();
  li.textContent = `${t}  ${text}`;
  if (kind) li.className = kind;
  const ol = $("#log");
  ol.prepend(li);
  while (ol.children.length > 300) ol.lastChild.remove();
}

// ------------------------------------------------------------------ HTTP

// Header values are Latin-1 bytes: a name with other characters goes as an RFC 8187
// ext-value (UTF-8'' and its percent-encoded UTF-8), which the daemon decodes.
function clientHeader(name) {
  return /^[\x20-\x7e]*$/.test(name) && !/^utf-8''/i.test(name) ? name : `UTF-8''${encodeURIComponent(name)}`;
}

async function api(method, path, body) {
  // A request sent without a lease may take control, and its answer brings the lease. A
  // request made before that answer is in waits for it: sent without the lease, it would be
  // refused because of this page's own control (the stream can show the first command's
  // effect, and the operator click again, before its answer arrives).
  while (!page.lease && page.leaseComing) {
    try { await page.leaseComing; } catch (e) { /* its caller reports it */ }
  }
  const headers = { "X-Fxcell-Client": clientHeader(page.client) };
  const token = localStorage.getItem("fxcell-token");
  if (token) headers["Authorization"] = `Bearer ${token}`;
  if (page.lease) headers["X-Fxcell-Lease"] = page.lease;
  if (body !== undefined) headers["Content-Type"] = "application/json";
  const sent = fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  if (!page.lease && method !== "GET") {
    page.leaseComing = sent;
    const done = () => { if (page.leaseComing === sent) page.leaseComing = null; };
    sent.then(done, done);
  }
  const res = await sent;
  const lease = res.headers.get("X-Fxcell-Lease");
  if (lease && lease !== page.lease) setLease(lease);
  let data = null;
  try { data = await res.json(); } catch (e) { data = null; }
  if (!res.ok) {
    const err = (data && data.error) || { type: `HTTP ${res.status}`, message: res.statusText };
    const e = new Error(err.message); e.type = err.type; e.status = res.status;
    throw e;
  }
  return data;
}

async function command(name, body, opts = {}) {
  if (!localStorage.getItem("fxcell-token")) {
    log(`${name}: enter the daemon's token first (fxcell token)`, "error");
    $("#token").focus();
    return null;
  }
  const wait = opts.wait === undefined ? "" : `?wait=${opts.wait}`;
  try {
    const op = await api("POST", `/api/cell/${name}${wait}`, body);
    if (op && op.id) updateOperation(op);
    if (name !== "stop") { page.problem = null; showSituation(); }
    return op;
  } catch (e) {
    log(`${name} refused: ${e.type}: ${e.message}`, "error");
    if (opts.errorBox) opts.errorBox.textContent = e.message;
    reportProblem(`${label(name)} refused`, e.message);
    return null;
  }
}

// ------------------------------------------------------------------ the situation banner
// One line under the header, where the operator looks: what the cell is doing and what
// to do next (the statechart's `next` for each state), or why the last command failed.

function label(name) { return name.replaceAll("_", " "); }

function reportProblem(what, why) {
  page.problem = { what, why, at: Date.now() };
  showSituation();
}

function nextStep(state) {
  if (!page.chart) return "";
  const target = state === "disconnected" ? "disconnected" : `connected.${state}`;
  const find = (states, prefix) => {
    for (const s of states) {
      const name = prefix + s.name;
      if (name === target) return s.next || "";
      if (s.children && target.startsWith(name + ".")) return find(s.children, name + ".");
    }
    return "";
  };
  return find(page.chart.states, "");
}

function showSituation() {
  const el = $("#situation"), text = $("#situation-text");
  let kind = "info", message;
  const state = page.state || "disconnected";
  const wsUp = page.ws && page.ws.readyState === WebSocket.OPEN;
  if (!wsUp) {
    kind = "bad"; message = "No connection to the fxcell daemon: is it running? (the page retries by itself)";
  } else if (page.problem) {
    kind = "bad"; message = `${page.problem.what}: ${page.problem.why}`;
  } else if (state === "disconnected") {
    kind = "bad";
    message = `Robot not connected${page.cellError ? ": " + page.cellError : ""}. ${nextStep(state)}`;
  } else if (page.remote === false) {
    kind = "warn"; message = "The teach pendant is in Local control: switch it to Remote Control to command the cell.";
  } else if (/protective_stop|safeguard_stop|emergency_stop|fault/.test(state)) {
    kind = "bad"; message = `${label(state)}: ${nextStep(state)}`;
  } else if (state.includes("external_control_ready")) {
    kind = "ok"; message = "Ready for moves.";
  } else if (state.includes("moving")) {
    kind = "info"; message = "Moving. STOP brakes the arm to rest.";
  } else if (state.includes("program_stopped") && page.robot && page.robot.runtime_state === "PLAYING") {
    kind = "warn";
    message = "fxcell's external control is not connected, although a program plays on the controller: run init (or start external control)";
  } else {
    const next = nextStep(state);
    message = `${label(state.replace("running.", ""))}${next ? ": " + next : ""}`;
    kind = /power_off|idle|program_stopped/.test(state) ? "warn" : "info";
  }
  el.className = `situation ${kind}`;
  el.dataset.kind = kind;
  text.textContent = message.charAt(0).toUpperCase() + message.slice(1);
  $("#situation-dismiss").hidden = !page.problem;
}

function showCalibration(cal) {
  // which arm model the planner uses, and the calibration's checksum
  const el = $("#kinematics");
  if (!cal) { el.textContent = "model: ?"; el.className = "pill"; return; }
  el.textContent = `model: ${cal.model}` + (cal.checksum ? ` · ${cal.checksum}` : "");
  el.title = `arm model: ${cal.model}; source: ${cal.source}` + (cal.checksum ? `; checksum ${cal.checksum}` : "");
  el.className = cal.model === "calibrated" ? "pill ok" : "pill warn";
}

function showRemote(remote) {
  page.remote = remote;
  const el = $("#remote");
  if (remote === null || remote === undefined) { el.textContent = "remote: ?"; el.className = "pill"; }
  else if (remote) { el.textContent = "remote control"; el.className = "pill ok"; }
  else { el.textContent = "LOCAL control"; el.className = "pill warn"; }
  showSituation();
}

$("#situation-dismiss").addEventListener("click", () => { page.problem = null; showSituation(); });

async function pollCell() {
  // what the stream does not carry: why the robot is not connected, the Local/Remote switch
  try {
    const snap = await api("GET", "/api/state");
    page.cellError = snap.cell_error;
    showRemote(snap.remote_control);
    showCalibration(snap.calibration);
  } catch (e) { /* the stream's own reconnect shows a lost daemon */ }
}
setInterval(pollCell, 2000);

// ------------------------------------------------------------------ status display

const JOINTS = ["base", "shoulder", "elbow", "wrist 1", "wrist 2", "wrist 3"];
const TCP = ["x (m)", "y (m)", "z (m)", "rx (rad)", "ry (rad)", "rz (rad)"];
(function buildTables() {
  $("#joints tbody").innerHTML = JOINTS.map((n, i) =>
    `<tr><td>${n}</td><td id="q${i}">–</td><td id="qd${i}">–</td><td id="v${i}">–</td></tr>`).join("");
  $("#tcp tbody").innerHTML = TCP.map((n, i) => `<tr><td>${n}</td><td id="p${i}">–</td></tr>`).join("");
})();

function stateClass(s) {
  if (s.includes("external_control_ready")) return "ready";
  if (s.includes("moving") || s.includes("stopping")) return "moving";
  if (/protective_stop|safeguard_stop|emergency_stop|fault/.test(s)) return "alarm";
  if (/disconnected|power_off|booting|shutting/.test(s)) return "off";
  return "";
}

function showState(state) {
  if (!state || state === page.state && page.chart && page.renderedState === state) return;
  page.state = state;
  const el = $("#cell-state");
  el.textContent = label(state.replace("running.", ""));  // whole words, never wrapped
  el.className = "big-state " + stateClass(state);
  el.dataset.state = state;
  el.title = state;
  if (state === "disconnected") {  // the last sample is stale: do not show it as current
    for (const id of ["#robot-mode", "#safety-mode", "#runtime-state"]) $(id).textContent = "no link";
  }
  updateButtons();
  renderStatechart();
  showSituation();
}

function showRobot(r) {
  page.robot = r;
  if (!r || page.state === "disconnected") return;
  const form = $("#form-joint");
  if (!page.prefilled) {   // once: later the operator's input is left alone
    page.prefilled = true;
    r.q.forEach((v, i) => { form.elements[`q${i}`].value = v.toFixed(4); });
  }
  $("#robot-mode").textContent = r.robot_mode;
  $("#safety-mode").textContent = r.safety_mode;
  $("#runtime-state").textContent = r.runtime_state;
  $("#speed-scaling").textContent = (r.speed_scaling ?? 1).toFixed(2);
  r.q.forEach((v, i) => {
    $(`#q${i}`).textContent = v.toFixed(4);
    $(`#qd${i}`).textContent = (v * 180 / Math.PI).toFixed(2);
    $(`#v${i}`).textContent = (r.qd ? r.qd[i] : 0).toFixed(3);
  });
  r.tcp.forEach((v, i) => { $(`#p${i}`).textContent = v.toFixed(i < 3 ? 5 : 4); });
  requestDraw();
}

function setLease(lease) {
  // The lease is this page's proof of control: it goes with every command, and the
  // stream shows it so that an open page keeps control while it answers the pings.
  page.lease = lease;
  if (page.ws) page.ws.close();  // reconnects with the lease
  showControl({ client: page.client, since: Date.now() / 1000 });
}

function showControl(holder) {
  page.control = holder;
  const el = $("#control");
  if (!holder) { page.lease = null; }
  const mine = !!(holder && page.lease && holder.client === page.client);
  if (holder && !mine && page.lease) page.lease = null;  // taken over by someone else
  el.textContent = !holder ? "control: free" : mine ? "control: this page" : `controlled by ${holder.client}`;
  $("#take-control").disabled = mine;
  $("#release-control").disabled = !mine;
}

// The command table (/api/commands) names the states in which each command is admitted.
function allowed(cmd) {
  if (!page.commands) return false;
  const entry = page.commands[cmd];
  return entry ? entry.allowed.includes(page.state) : false;
}

// ... and whether the cell's robot kind can do it at all (a Ned2 has no remote power):
// what it cannot do is not offered.
function supported(cmd) {
  const entry = page.commands && page.commands[cmd];
  return !entry || entry.supported !== false;
}

function updateButtons() {
  for (const b of $$("button[data-command]")) {
    b.hidden = !supported(b.dataset.command);
    b.disabled = !allowed(b.dataset.command);
  }
  for (const f of $$("form.move[data-command]")) {
    f.hidden = !supported(f.dataset.command);
    for (const b of f.querySelectorAll("button[type=submit]")) b.disabled = !allowed(f.dataset.command);
  }
}

function updateOperation(op) {
  page.ops.set(op.id, op);
  const ids = Array.from(page.ops.keys());
  for (const id of ids.slice(0, Math.max(0, ids.length - 8))) page.ops.delete(id);
  const ul = $("#operations");
  ul.innerHTML = "";
  for (const o of Array.from(page.ops.values()).reverse()) {
    const li = document.createElement("li");
    li.dataset.op = o.id;
    li.dataset.status = o.status;
    li.innerHTML = `<span class="st-${o.status}">${o.status}</span> <b>${o.name}</b> <span class="muted">${o.id}</span>`;
    if (o.status === "running") {
      const b = document.createElement("button");
      b.textContent = "cancel"; b.className = "link";
      b.onclick = () => api("POST", `/api/operations/${o.id}/cancel`).then(updateOperation)
        .catch((e) => log(`cancel ${o.id}: ${e.message}`, "error"));
      li.append(b);
    } else if (o.error) {
      li.title = o.error.message;
    }
    ul.append(li);
  }
}

// ------------------------------------------------------------------ WebSocket stream

function connect() {
  const proto = location.protocol === "https:" ? "wss" : "ws";
  const lease = page.lease ? `&lease=${encodeURIComponent(page.lease)}` : "";
  const ws = new WebSocket(`${proto}://${location.host}/api/stream?rate=50&client=${encodeURIComponent(page.client)}${lease}`);
  page.ws = ws;
  ws.onopen = () => { page.wsRetry = 500; $("#link").textContent = "daemon live"; $("#link").className = "pill ok"; };
  ws.onclose = () => {
    $("#link").textContent = "daemon offline"; $("#link").className = "pill bad";
    page.problem = null;
    showSituation();
    setTimeout(connect, page.wsRetry);
    page.wsRetry = Math.min(page.wsRetry * 2, 5000);
  };
  ws.onmessage = (msg) => onMessage(JSON.parse(msg.data));
}

function onMessage(m) {
  switch (m.type) {
    case "ping":  // the daemon checks that this page is alive
      if (page.ws && page.ws.readyState === WebSocket.OPEN) page.ws.send(JSON.stringify({ type: "pong" }));
      break;
    case "hello":
      page.cellError = m.snapshot.cell_error;
      showRemote(m.snapshot.remote_control);
      showCalibration(m.snapshot.calibration);
      showControl(m.snapshot.control);
      showState(m.snapshot.state);
      showRobot(m.snapshot.robot);
      showGripper(m.snapshot.gripper);
      m.snapshot.operations.forEach(updateOperation);
      loadJob();  // job events sent while the stream was down are not replayed
      log(`connected to the daemon (state ${m.snapshot.state})`);
      break;
    case "state":
      showState(m.state);
      page.targetQ = m.target_q;
      showRobot(m);
      showIO(m);
      break;
    case "device":
      if (m.device === "gripper") showGripper(m.data);
      if (m.device === "job") onJobEvent(m.data);
      break;
    case "transition":
      showState(m.dest);
      log(`${m.source} → ${m.dest}  (${m.trigger}, ${m.cause}${m.detail ? ": " + m.detail : ""})`, "transition");
      break;
    case "command":
      if (m.outcome === "error") log(`${m.name}: ${m.error_type}: ${m.error_message}`, "error");
      else if (m.outcome === "ok") log(`${m.name} done (${m.origin})`);
      if (m.outcome === "ok" && (m.name === "teach")) loadPositions();
      if (m.outcome === "ok" && m.name === "teach_frame_point") loadLayout();
      if (m.outcome === "ok" && m.name === "check_placement" && m.result) {
        showPlacement({ ...m.result, time: m.ended }, `/api/camera/placement.jpg?t=${m.ended}`);
        log(`placement check: ${m.result.ok ? "OK" : "STOP: " + m.result.reason}`, m.result.ok ? "" : "warn");
      }
      else log(`${m.name} started (${m.origin})`);
      break;
    case "operation":
      updateOperation(m);
      if (m.status === "failed") {
        log(`${m.id} ${m.name} failed: ${m.error.message}`, "error");
        reportProblem(`${label(m.name)} failed`, m.error.message);
      }
      else if (m.status === "cancelled") log(`${m.id} ${m.name} cancelled`, "warn");
      break;
    case "control":
      showControl(m.holder);
      log(m.holder ? `control taken by ${m.holder.client}` : "control released");
      break;
    case "log":
      log(`${m.name}: ${m.message}`, m.level >= 40 ? "error" : "warn");
      break;
  }
}

// ------------------------------------------------------------------ commands and forms

for (const b of $$("button[data-command]")) {
  if (b.closest("form")) continue;
  b.addEventListener("click", async () => {
    if (b.dataset.confirm && !confirm(b.dataset.confirm)) return;
    const body = b.dataset.body ? JSON.parse(b.dataset.body) : undefined;
    log(`${b.dataset.command} requested`);
    await command(b.dataset.command, body);
  });
}
$("#form-joint button[data-command=go_home]").addEventListener("click", () => command("go_home", factors()));
$("#stop").addEventListener("click", async () => {
  log("STOP requested");
  await command("stop", undefined);
});
$("#take-control").addEventListener("click", async () => {
  const holder = page.control && page.control.client;
  if (holder && holder !== page.client && !confirm(`Take control over from ${holder}?`)) return;
  try {
    const holder = await api("POST", "/api/control", { force: true });
    setLease(holder.lease);
    showControl({ client: holder.client, since: holder.since });
  } catch (e) { log(`take control: ${e.message}`, "error"); }
});
$("#release-control").addEventListener("click", async () => {
  try { await api("DELETE", "/api/control"); page.lease = null; showControl(null); }
  catch (e) { log(`release control: ${e.message}`, "error"); }
});

function factors() {
  const f = {};
  for (const [id, key] of [["#vf", "velocity_factor"], ["#af", "acceleration_factor"]]) {
    const v = Number($(id).value);
    if (!(v > 0 && v <= 1)) throw new Error(`${key.replace("_", " ")} must be in (0, 1]`);
    f[key] = v;
  }
  return f;
}

function numbers(form, names) {
  return names.map((n) => {
    const input = form.elements[n];
    const v = Number(input.value);
    if (input.value === "" || !Number.isFinite(v)) throw new Error(`${n}: enter a number`);
    if (!input.checkValidity()) throw new Error(`${n}: ${input.validationMessage}`);
    return v;
  });
}

function validateJoints(q) {
  const lim = page.info && page.info.limits;
  if (!lim) return;
  q.forEach((v, i) => {
    if (v < lim.position_min[i] || v > lim.position_max[i])
      throw new Error(`${JOINTS[i]}: ${v} rad is outside [${lim.position_min[i].toFixed(3)}, ${lim.position_max[i].toFixed(3)}]`);
  });
}

const FORMS = {
  "form-joint": (f) => { const q = numbers(f, ["q0", "q1", "q2", "q3", "q4", "q5"]); validateJoints(q); return { target: q }; },
  "form-pose": (f) => ({ target: numbers(f, ["x", "y", "z", "roll", "pitch", "yaw"]), linear: f.elements.linear.checked }),
  "form-distance": (f) => {
    const d = numbers(f, ["dx", "dy", "dz"]);
    if (d.every((v) => v === 0)) throw new Error("the distance is zero");
    return { distance: d };
  },
};
for (const form of $$("form.move")) {
  form.addEventListener("submit", async (e) => {
    e.preventDefault();
    const box = form.querySelector(".error");
    box.textContent = "";
    let body;
    try { body = { ...FORMS[form.id](form), ...factors() }; }
    catch (err) { box.textContent = err.message; return; }
    log(`${form.dataset.command} requested`);
    await command(form.dataset.command, body, { errorBox: box });
  });
}
$("#copy-joints").addEventListener("click", () => {
  if (!page.robot) return;
  page.robot.q.forEach((v, i) => { $("#form-joint").elements[`q${i}`].value = v.toFixed(4); });
});
$("#copy-pose").addEventListener("click", async () => {
  try {
    const r = (await api("GET", "/api/cell/get_current_pose_rpy")).result;
    ["x", "y", "z", "roll", "pitch", "yaw"].forEach((n, i) => { $("#form-pose").elements[n].value = Number(r[i]).toFixed(i < 3 ? 4 : 4); });
  } catch (e) { log(`current pose: ${e.message}`, "error"); }
});

// ------------------------------------------------------------------ arm view

// The arm's chain comes from the daemon (the configured robot kind's own model): each joint
// an origin (4x4 row-major, in the previous joint's frame) and an axis, then the tool frame.
let ARM = null;
(async () => {
  try { ARM = await api("GET", "/api/robot/model"); requestDraw(); }
  catch (e) { log(`cannot load the robot model: ${e.message}`, "error"); }
})();

function matMul(A, B) {
  const C = new Array(16).fill(0);
  for (let r = 0; r < 4; r++) for (let c = 0; c < 4; c++)
    for (let k = 0; k < 4; k++) C[r * 4 + c] += A[r * 4 + k] * B[k * 4 + c];
  return C;
}
function turn([x, y, z], th) {  // rotation by th about the unit axis (x, y, z), 4x4
  const c = Math.cos(th), s = Math.sin(th), C = 1 - c;
  return [c + x * x * C, x * y * C - z * s, x * z * C + y * s, 0, y * x * C + z * s, c + y * y * C, y * z * C - x * s, 0,
    z * x * C - y * s, z * y * C + x * s, c + z * z * C, 0, 0, 0, 0, 1];
}
function rotvec(rx, ry, rz) {
  const th = Math.hypot(rx, ry, rz);
  if (th < 1e-12) return [1, 0, 0, 0, 1, 0, 0, 0, 1];
  const [x, y, z] = [rx / th, ry / th, rz / th], c = Math.cos(th), s = Math.sin(th), C = 1 - c;
  return [c + x * x * C, x * y * C - z * s, x * z * C + y * s, y * x * C + z * s, c + y * y * C, y * z * C - x * s,
    z * x * C - y * s, z * y * C + x * s, c + z * z * C];
}
const P = (T) => [T[3], T[7], T[11]];
const at = (T, [x, y, z]) => [T[0] * x + T[1] * y + T[2] * z + T[3], T[4] * x + T[5] * y + T[6] * z + T[7],
  T[8] * x + T[9] * y + T[10] * z + T[11]];

// Points along the arm: from each joint, the offset to the next joint (or the tool frame)
// first along the joint's axis (a joint marker there), then the rest; then the TCP.
function armPoints(q) {
  let T = [1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1];
  const pts = [P(T)], joints = [];
  if (!ARM || !ARM.joints.length) return { pts, joints };  // the model has not arrived yet
  const J = ARM.joints;
  T = J[0].origin;
  if (Math.hypot(...P(T)) > 1e-9) pts.push(P(T));  // a base below the first joint
  for (let i = 0; i < J.length; i++) {
    const axis = J[i].axis;
    T = matMul(T, turn(axis, q[i] || 0));
    const next = i + 1 < J.length ? J[i + 1].origin : ARM.tool;
    const along = next[3] * axis[0] + next[7] * axis[1] + next[11] * axis[2];
    joints.push(pts.length);
    pts.push(at(T, axis.map((v) => v * along)));
    T = matMul(T, next);
    pts.push(P(T));
  }
  const tcp = (page.info && page.info.tcp) || [0, 0, 0, 0, 0, 0];
  const R = rotvec(tcp[3], tcp[4], tcp[5]);
  const Tt = [R[0], R[1], R[2], tcp[0], R[3], R[4], R[5], tcp[1], R[6], R[7], R[8], tcp[2], 0, 0, 0, 1];
  pts.push(P(matMul(T, Tt)));
  return { pts, joints };
}

let drawPending = false;
function requestDraw() {
  if (drawPending) return;
  drawPending = true;
  requestAnimationFrame(() => { drawPending = false; drawArm(); drawLayout(); });
}

function drawArm() {
  const cv = $("#arm"), g = cv.getContext("2d");
  const W = cv.width, H = cv.height, s = H * 0.8;
  const ca = Math.cos(page.azimuth), sa = Math.sin(page.azimuth), ce = Math.cos(page.elevation), se = Math.sin(page.elevation);
  const project = ([x, y, z]) => {
    const u = ca * x - sa * y, v = sa * x + ca * y;   // rotate about z
    return [W / 2 + s * u, H * 0.86 - s * (ce * z - se * v)];
  };
  g.clearRect(0, 0, W, H);
  g.fillStyle = "#fbfcfe"; g.fillRect(0, 0, W, H);
  // floor grid (0.1 m)
  g.strokeStyle = "#e1e6ec"; g.lineWidth = 1;
  for (let i = -5; i <= 5; i++) {
    for (const [a, b] of [[[i / 10, -0.5, 0], [i / 10, 0.5, 0]], [[-0.5, i / 10, 0], [0.5, i / 10, 0]]]) {
      const [x1, y1] = project(a), [x2, y2] = project(b);
      g.beginPath(); g.moveTo(x1, y1); g.lineTo(x2, y2); g.stroke();
    }
  }
  // scene boxes (wireframe), the stations' bodies and the objects where the cell believes they are
  for (const o of (page.info && page.info.scene) || []) drawBox(g, project, o);
  drawStations(g, project);
  // base axes
  const axes = [[[0.15, 0, 0], "#d1242f"], [[0, 0.15, 0], "#1a7f37"], [[0, 0, 0.15], "#1f6feb"]];
  for (const [p, col] of axes) {
    const [x0, y0] = project([0, 0, 0]), [x1, y1] = project(p);
    g.strokeStyle = col; g.lineWidth = 2; g.beginPath(); g.moveTo(x0, y0); g.lineTo(x1, y1); g.stroke();
  }
  if (!page.robot) {
    g.fillStyle = "#6b7785"; g.font = "16px system-ui"; g.fillText("no robot state", 20, 30);
    return;
  }
  const moving = page.state.includes("moving") || page.state.includes("stopping");
  if (moving && page.targetQ) drawChain(g, project, armPoints(page.targetQ), "rgba(31,111,235,0.25)", 8);
  drawChain(g, project, armPoints(page.robot.q), "#3d5a80", 12);
}

function drawStations(g, project) {
  const L = page.layout;
  if (!L) return;
  for (const [name, st] of Object.entries(L.stations)) {
    if (st.body) {
      const [x, y, z] = st.body.pose;
      drawBox(g, project, { size: st.body.size, position: [x, y, z], rpy: [0, 0, rotZ(st.body.pose.slice(3))] },
        st.zone ? "#c99a5b" : "#7d8da0");
    }
    const kind = L.objects[st.holds];
    for (const [slot, p] of Object.entries(st.slots)) {
      const who = page.occupants && page.occupants[`${name}:${slot}`];
      const [sx, sy] = project(p.seat);
      if (!who) {  // an empty slot: a small ring on the seat
        g.strokeStyle = "#b4bfcc"; g.lineWidth = 1; g.beginPath(); g.arc(sx, sy, 2.5, 0, 2 * Math.PI); g.stroke();
        continue;
      }
      drawObject(g, project, p.seat, kind, who);
    }
  }
  // what the gripper holds, at the TCP
  const held = page.occupants && page.occupants.gripper;
  if (held && page.robot && page.robot.tcp) {
    const kind = L.objects[held.kind] || { width: 0.03, height: 0.03, grip_height: 0.02 };
    const [x, y, z] = page.robot.tcp;
    drawObject(g, project, [x, y, z - kind.grip_height], kind, held);
  }
}

function drawObject(g, project, seat, kind, who) {
  const [x, y, z] = seat, r = kind.width / 2, h = kind.height;
  const colour = who.kind === "bead" ? "#4f8fe0" : "#d08a2e";
  const [bx, by] = project([x, y, z]), [tx, ty] = project([x, y, z + h]);
  const [rx] = project([x + r, y, z]);
  const w = Math.max(4, Math.abs(rx - bx) * 1.6);
  g.strokeStyle = colour; g.lineCap = "butt"; g.lineWidth = w;
  g.beginPath(); g.moveTo(bx, by); g.lineTo(tx, ty); g.stroke();
  g.fillStyle = "#1d2733"; g.font = "10px sans-serif"; g.textAlign = "center";
  if (who.label) g.fillText(who.label, tx, ty - 4);
  g.textAlign = "left";
}

function drawChain(g, project, { pts, joints }, colour, width) {
  const xy = pts.map(project);
  if (xy.length < 2) return;
  g.lineCap = "round"; g.lineJoin = "round";
  g.strokeStyle = colour; g.lineWidth = width;
  g.beginPath(); xy.slice(0, -1).forEach(([x, y], i) => (i ? g.lineTo(x, y) : g.moveTo(x, y))); g.stroke();
  g.strokeStyle = "#f08c00"; g.lineWidth = width * 0.5;   // gripper to the TCP
  const [fx, fy] = xy[xy.length - 2], [tx, ty] = xy[xy.length - 1];
  g.beginPath(); g.moveTo(fx, fy); g.lineTo(tx, ty); g.stroke();
  g.fillStyle = "#17202b";
  for (const i of joints) { g.beginPath(); g.arc(xy[i][0], xy[i][1], width * 0.45, 0, 2 * Math.PI); g.fill(); }
  g.fillStyle = "#f08c00"; g.beginPath(); g.arc(tx, ty, 5, 0, 2 * Math.PI); g.fill();
}

function drawBox(g, project, o, colour = "#9aa7b6") {
  const [sx, sy, sz] = o.size.map((v) => v / 2), [cx, cy, cz] = o.position;
  const yaw = (o.rpy || [0, 0, 0])[2], c = Math.cos(yaw), s = Math.sin(yaw);
  const corner = (i) => {
    const x = (i & 1 ? sx : -sx), y = (i & 2 ? sy : -sy), z = (i & 4 ? sz : -sz);
    return project([cx + c * x - s * y, cy + s * x + c * y, cz + z]);
  };
  const edges = [[0, 1], [1, 3], [3, 2], [2, 0], [4, 5], [5, 7], [7, 6], [6, 4], [0, 4], [1, 5], [2, 6], [3, 7]];
  g.strokeStyle = colour; g.lineWidth = 1;
  for (const [a, b] of edges) {
    const [x1, y1] = corner(a), [x2, y2] = corner(b);
    g.beginPath(); g.moveTo(x1, y1); g.lineTo(x2, y2); g.stroke();
  }
}

(function dragToRotate() {
  const cv = $("#arm");
  let last = null;
  cv.addEventListener("pointerdown", (e) => { last = [e.clientX, e.clientY]; cv.setPointerCapture(e.pointerId); });
  cv.addEventListener("pointerup", () => { last = null; });
  cv.addEventListener("pointermove", (e) => {
    if (!last) return;
    page.azimuth += (e.clientX - last[0]) * 0.01;
    page.elevation = Math.max(-0.2, Math.min(1.5, page.elevation + (e.clientY - last[1]) * 0.01));
    last = [e.clientX, e.clientY];
    requestDraw();
  });
})();

// ------------------------------------------------------------------ state-machine diagram

const SVGNS = "http://www.w3.org/2000/svg";
function svg(tag, attrs, parent) {
  const el = document.createElementNS(SVGNS, tag);
  for (const [k, v] of Object.entries(attrs || {})) el.setAttribute(k, v);
  if (parent) parent.append(el);
  return el;
}

// Flow layout of the state tree: leaves are boxes, compound states frame their children.
function layoutStates(states, prefix, maxWidth) {
  const BOX_H = 26, GAP = 8, PAD = 8, HEAD = 16;
  const items = states.map((st) => {
    const name = prefix + st.name;
    if (st.children && st.children.length) {
      const inner = layoutStates(st.children, name + ".", maxWidth - 2 * PAD);
      return { name, label: st.name, group: true, w: inner.w + 2 * PAD, h: inner.h + PAD + HEAD, inner };
    }
    return { name, label: st.name.replace(/_/g, " "), group: false, w: Math.max(70, st.name.length * 6.4 + 16), h: BOX_H };
  });
  let x = 0, y = 0, rowH = 0, w = 0;
  for (const it of items) {
    if (x > 0 && x + it.w > maxWidth) { x = 0; y += rowH + GAP; rowH = 0; }
    it.x = x; it.y = y;
    x += it.w + GAP; rowH = Math.max(rowH, it.h); w = Math.max(w, x - GAP);
  }
  return { items, w, h: y + rowH, PAD, HEAD };
}

function publicName(name) { return name.startsWith("connected.") ? name.slice("connected.".length) : name; }

function renderStatechart() {
  const chart = page.chart;
  if (!chart) return;
  page.renderedState = page.state;
  const host = $("#statechart");
  const WIDTH = 640;
  const layout = layoutStates(chart.states, "", WIDTH - 4);
  const root = svg("svg", { viewBox: `-2 -2 ${WIDTH} ${layout.h + 6}`, role: "img", "aria-label": "state machine" });
  const boxes = new Map();
  const place = (lay, ox, oy, parent) => {
    for (const it of lay.items) {
      const x = ox + it.x, y = oy + it.y;
      if (it.group) {
        const g = svg("g", { class: "group" }, parent);
        svg("rect", { x, y, width: it.w, height: it.h, rx: 8 }, g);
        svg("text", { x: x + 8, y: y + 12 }, g).textContent = it.label;
        boxes.set(it.name, { x, y, w: it.w, h: it.h, group: true });
        place(it.inner, x + lay.PAD, y + lay.HEAD + 2, parent);
      } else {
        const pub = publicName(it.name);
        const g = svg("g", { class: "state" + (pub === page.state ? " current" : ""), "data-state": pub }, parent);
        svg("rect", { x, y, width: it.w, height: it.h, rx: 5 }, g);
        const t = svg("text", { x: x + it.w / 2, y: y + it.h / 2 + 4, "text-anchor": "middle" }, g);
        t.textContent = it.label;
        boxes.set(it.name, { x, y, w: it.w, h: it.h });
      }
    }
  };
  const edgeLayer = svg("g", {}, root);
  place(layout, 0, 0, root);
  svg("marker", { id: "arrow", viewBox: "0 0 10 10", refX: 9, refY: 5, markerWidth: 6, markerHeight: 6, orient: "auto-start-reverse" },
    svg("defs", {}, root)).append(svg("path", { d: "M0,0 L10,5 L0,10 z", fill: "#8a97a6" }));
  const current = page.state === "disconnected" ? "disconnected" : "connected." + page.state;
  for (const t of chart.transitions) {
    for (const src of [].concat(t.source)) {
      const a = boxes.get(src), b = boxes.get(t.dest);
      if (!a || !b || src === t.dest) continue;
      if (a.group) continue;   // "from any connected state" edges would cover the chart
      const live = current === src || current.startsWith(src + ".");
      const [x1, y1] = [a.x + a.w / 2, a.y + a.h / 2], [x2, y2] = [b.x + b.w / 2, b.y + b.h / 2];
      const mx = (x1 + x2) / 2 - (y2 - y1) * 0.15, my = (y1 + y2) / 2 + (x2 - x1) * 0.15;
      svg("path", { d: `M${x1},${y1} Q${mx},${my} ${x2},${y2}`, class: "edge" + (live ? " live" : ""), "marker-end": "url(#arrow)" }, edgeLayer)
        .append(Object.assign(svg("title"), { textContent: t.trigger }));
    }
  }
  host.replaceChildren(root);
}


// ------------------------------------------------------------------ gripper, IO, teach, layout

function showGripper(g) {
  if (!g) return;
  page.gripper = { ...(page.gripper || {}), ...g };
  const s = page.gripper;
  if (s.width !== undefined) $("#gripper-width").textContent = `${(s.width * 1000).toFixed(1)} mm`;
  $("#gripper-held").textContent = s.held ? s.held : (s.holding ? "an object" : "nothing");
  if (s.event) $("#gripper-event").textContent = s.event;
}

function ioValue(name, r) {
  const address = page.info.io[name];
  const n = Number(address.slice(2));
  const offset = { D: 0, C: 8, T: 16 }[address[0]];
  if (address[0] === "A") return (address[1] === "I" ? r.analog_in : r.analog_out)[n];
  const bits = address[1] === "I" ? r.digital_in : r.digital_out;
  return Boolean((bits / 2 ** (offset + n)) % 2 >= 1);
}

function showIO(r) {
  if (!page.info || !page.info.io || !r || r.digital_in === undefined) return;
  const body = $("#io tbody");
  const names = Object.keys(page.info.io).sort();
  if (body.children.length !== names.length) {
    body.innerHTML = "";
    for (const name of names) {
      const tr = document.createElement("tr");
      tr.dataset.signal = name;
      const output = page.info.io[name][1] === "O";
      tr.innerHTML = `<td title="${page.info.io[name]}">${name}</td><td class="v"></td><td></td>`;
      if (output && page.info.io[name][0] !== "A") {
        const b = document.createElement("button");
        b.textContent = "toggle"; b.dataset.command = "io_set";
        b.onclick = () => command("io_set", { signal: name, value: !ioValue(name, page.robot) });
        tr.lastChild.append(b);
      }
      body.append(tr);
    }
    updateButtons();
  }
  for (const tr of body.children) {
    const v = ioValue(tr.dataset.signal, r);
    const cell = tr.querySelector(".v");
    cell.textContent = typeof v === "boolean" ? (v ? "on" : "off") : v.toFixed(3);
    cell.className = "v " + (v === true ? "on" : "off");
  }
}

async function loadPositions() {
  try {
    const { result } = await api("GET", "/api/cell/get_positions");
    const body = $("#positions tbody");
    body.innerHTML = "";
    for (const [name, p] of Object.entries(result)) {
      const tr = document.createElement("tr");
      tr.innerHTML = `<td title="taught ${p.taught}">${name}</td><td></td>`;
      const go = document.createElement("button");
      go.textContent = "move to"; go.dataset.command = "move_to"; go.dataset.move = "1";
      go.onclick = () => command("move_to", { name, ...factors() });
      const again = document.createElement("button");
      again.textContent = "re-teach"; again.dataset.command = "teach";
      again.onclick = async () => {
        if (!confirm(`Re-teach ${name} at the arm's current position? (the old one is kept as 'previous')`)) return;
        await command("teach", { name });
      };
      tr.lastChild.append(go, " ", again);
      body.append(tr);
    }
    updateButtons();
  } catch (e) { log(`positions: ${e.message}`, "error"); }
}

$("#form-teach").addEventListener("submit", async (e) => {
  e.preventDefault();
  const f = e.target, box = f.querySelector(".error");
  box.textContent = "";
  if (!f.elements.name.checkValidity()) { box.textContent = "a letter, then letters, digits, _ or -"; return; }
  await command("teach", { name: f.elements.name.value }, { errorBox: box });
});

$("#form-grip").addEventListener("submit", async (e) => {
  e.preventDefault();
  const f = e.target, box = f.querySelector(".error");
  box.textContent = "";
  const width = Number(f.elements.width.value);
  if (!(width >= 0 && width <= 0.05)) { box.textContent = "width: 0 to 0.050 m"; return; }
  await command("gripper_move", { width }, { errorBox: box });
});

// The layout, seen from above (x right, y up, base at the origin).
async function loadLayout() {
  try { page.layout = (await api("GET", "/api/cell/get_layout")).result; drawLayout(); }
  catch (e) { log(`layout: ${e.message}`, "error"); }
}

function layoutView(canvas) {
  const [x0, x1, y0, y1] = [-0.45, 0.45, -0.2, 0.55];
  const s = Math.min(canvas.width / (x1 - x0), canvas.height / (y1 - y0));
  return { px: (x) => (x - x0) * s, py: (y) => canvas.height - (y - y0) * s, s };
}

function drawLayout() {
  const canvas = $("#layout"), g = canvas.getContext("2d"), L = page.layout;
  if (!L) return;
  const v = layoutView(canvas);
  g.clearRect(0, 0, canvas.width, canvas.height);
  g.fillStyle = "#9aa7b6"; g.beginPath(); g.arc(v.px(0), v.py(0), 0.06 * v.s, 0, 2 * Math.PI); g.fill();
  page.slotHits = [];
  for (const [name, st] of Object.entries(L.stations)) {
    if (st.body) {
      const [cx, cy] = st.body.pose, [w, h] = st.body.size, yaw = rotZ(st.body.pose.slice(3));
      g.save(); g.translate(v.px(cx), v.py(cy)); g.rotate(-yaw);
      g.fillStyle = st.zone ? "#f6e7d2" : "#e8eef6"; g.strokeStyle = "#9aa7b6";
      g.fillRect(-w * v.s / 2, -h * v.s / 2, w * v.s, h * v.s); g.strokeRect(-w * v.s / 2, -h * v.s / 2, w * v.s, h * v.s);
      g.restore();
    }
    const r = L.objects[st.holds].width / 2 * v.s;
    let lx = Infinity, ly = -Infinity;
    for (const [slot, p] of Object.entries(st.slots)) {
      const [x, y] = [v.px(p.seat[0]), v.py(p.seat[1])];
      const occupant = page.occupants && page.occupants[`${name}:${slot}`];
      g.beginPath(); g.arc(x, y, r, 0, 2 * Math.PI);
      g.fillStyle = occupant ? (occupant.kind === "bead" ? "#7fb3f5" : "#e0a458") : "#ffffff";
      g.fill(); g.strokeStyle = "#6b7785"; g.stroke();
      if (occupant && occupant.label) { g.fillStyle = "#1d2733"; g.font = "9px sans-serif"; g.textAlign = "center"; g.fillText(occupant.label, x, y + 3); }
      page.slotHits.push({ station: name, slot, x, y, r });
      lx = Math.min(lx, x); ly = Math.max(ly, y);
    }
    g.fillStyle = "#1d2733"; g.font = "11px sans-serif"; g.textAlign = "left";
    g.fillText(name, lx - r, ly + r + 12);
  }
  if (page.robot && page.robot.tcp) {
    const [x, y] = page.robot.tcp;
    g.strokeStyle = "#1f6feb"; g.lineWidth = 2;
    g.beginPath(); g.moveTo(v.px(x) - 6, v.py(y)); g.lineTo(v.px(x) + 6, v.py(y));
    g.moveTo(v.px(x), v.py(y) - 6); g.lineTo(v.px(x), v.py(y) + 6); g.stroke(); g.lineWidth = 1;
  }
}

function rotZ(rotvec) {  // yaw of a rotation vector whose axis is (nearly) vertical
  const [rx, ry, rz] = rotvec, a = Math.hypot(rx, ry, rz);
  return a < 1e-9 ? 0 : Math.sign(rz) * a;
}

$("#layout").addEventListener("click", async (e) => {
  const c = e.target, rect = c.getBoundingClientRect();
  const x = (e.clientX - rect.left) * c.width / rect.width, y = (e.clientY - rect.top) * c.height / rect.height;
  const hit = (page.slotHits || []).find((h) => Math.hypot(h.x - x, h.y - y) <= Math.max(h.r, 6));
  if (!hit) return;
  const holding = page.gripper && page.gripper.held;
  const what = holding ? "place" : "pick";
  $("#slot-info").textContent = `${hit.station} ${hit.slot}`;
  if (!confirm(`${what} ${hit.station} ${hit.slot}?`)) return;
  await command(what, { station: hit.station, slot: hit.slot, ...factors() });
});


// ------------------------------------------------------------------ the job

const JOB_ALLOWED = {
  start: ["idle", "done"], pause: ["running", "waiting_for_machine"], resume: ["paused", "fault"],
  abort: ["running", "pausing", "waiting_for_machine"], confirm: ["waiting_for_machine"], discard: ["paused", "fault"],
};
const STATION_OF = { rack: "rack", machine: "machine", mould: "moulds", tray: "tray" };

async function loadJob() {
  try { showJob(await api("GET", "/api/job")); } catch (e) { log(`job: ${e.message}`, "error"); }
}

let jobReload = null;
function onJobEvent() {  // events come in bursts: reload the status at most every 200 ms
  if (jobReload) return;
  jobReload = setTimeout(() => { jobReload = null; loadJob(); }, 200);
}

function showJob(st) {
  page.job = st;
  const box = $("#job-state");
  box.textContent = st.state.replaceAll("_", " ");
  box.className = "big-state " + ({ running: "moving", waiting_for_machine: "moving", done: "ready",
    fault: "alarm", paused: "alarm" }[st.state] || "off");
  $("#job-message").textContent = st.message || "";
  $("#job-step").textContent = st.step ? `step: ${st.step}` : "";
  const heals = st.heals || { count: 0, recent: [] };
  const last = heals.recent.length ? heals.recent[heals.recent.length - 1] : null;
  $("#job-heals").textContent = heals.count
    ? `went on by itself after ${heals.count} lost robot link${heals.count > 1 ? "s" : ""}` +
      (last ? ` (last: ${last.what}, ${last.phase})` : "")
    : "";
  const p = st.progress;
  $("#job-progress").max = p ? Math.max(1, p.total) : 1;
  $("#job-progress").value = p ? p.done : 0;
  $("#job-eta").textContent = p ? `${p.done}/${p.total} steps, about ${Math.ceil(p.eta / 60)} min left` : "";
  const qs = $("#job-questions");
  qs.innerHTML = "";
  for (const q of st.questions || []) {
    const div = document.createElement("div");
    div.className = "small";
    div.innerHTML = `<b>${q.text}</b> `;
    const sel = document.createElement("select");
    sel.dataset.question = q.id;
    for (const c of q.choices) sel.append(new Option(c, c));
    div.append(sel);
    qs.append(div);
  }
  const prompt = st.prompt;
  $("#job-prompt").textContent = prompt ? `waiting for you: ${prompt.text || prompt} — press Confirm` : "";
  for (const b of $$("button[data-job]")) b.disabled = !(JOB_ALLOWED[b.dataset.job] || []).includes(st.state);
  page.occupants = {};
  for (const s of st.samples || []) {
    for (const [kind, where] of [["crucible", s.crucible], ["bead", s.bead]]) {
      if (!where) continue;
      if (where === "gripper") { page.occupants.gripper = { kind, label: s.id }; continue; }
      const [prefix, slot] = where.split(":");
      page.occupants[`${STATION_OF[prefix] || prefix}:${slot}`] = { kind, label: s.id };
    }
  }
  showRun(st);
  requestDraw();
}

// ------------------------------------------------------------------ the run view

function minutes(seconds) {
  if (seconds === undefined || seconds === null) return "–";
  const m = Math.ceil(seconds / 60);
  return m < 60 ? `${m} min` : `${Math.floor(m / 60)} h ${m % 60} min`;
}

function describePlace(where) {
  if (!where) return "–";
  if (where === "gripper") return "in the gripper";
  const [prefix, slot] = where.split(":");
  return `${{ rack: "rack", machine: "machine", mould: "mould", tray: "tray" }[prefix] || prefix} ${slot}`;
}

// What the operator must do now, in one sentence, from the job's status.
function runNext(st) {
  const p = st.placement;
  const msg = (st.message || "").replace(/\.$/, "");
  if (st.questions && st.questions.length) return ["bad", "Tell the job where the sample is (below), then press Resume."];
  if (st.prompt) return ["warn", `${st.prompt.text || st.prompt} Then press Confirm.`];
  if (st.state === "paused" && p && !p.ok && msg.startsWith("placement check"))
    return ["bad", `Fix the crucibles before the fusion: ${p.reason}. Then press Resume: the camera checks again.`];
  if (st.state === "fault") return ["bad", `${msg}. Clear the cause, then press Resume.`];
  if (st.state === "paused") return ["warn", `Paused (${msg}). Press Resume to go on.`];
  if (st.state === "pausing") return ["info", "Pausing: the current step finishes first."];
  if (st.state === "waiting_for_machine")
    return ["info", `Nothing to do: the fusion machine runs. About ${minutes(st.progress && st.progress.eta)} left in the run.`];
  if (st.state === "running") return ["info", `Nothing to do: the robot works (${st.step || "next step"}). Keep clear of the cell.`];
  if (st.state === "done") return ["ok", "Run done: every bead is on the tray, every crucible back in the rack."];
  return ["info", msg || st.state];
}

function showRun(st) {
  const box = $("#run");
  const has = st.run !== null && st.run !== undefined;
  box.hidden = !has;
  document.body.classList.toggle("has-run", has);
  if (!has) return;
  const [kind, text] = runNext(st);
  const next = $("#run-next");
  next.className = `run-next ${kind}`;
  next.textContent = text;
  $("#run-name").textContent = `run ${st.run}${st.name ? " · " + st.name : ""}`;
  const state = $("#run-state");
  state.textContent = st.state.replaceAll("_", " ");
  state.className = "big-state " + ({ running: "moving", waiting_for_machine: "moving", done: "ready",
    fault: "alarm", paused: "alarm" }[st.state] || "off");
  const p = st.progress;
  $("#run-progress").max = p ? Math.max(1, p.total) : 1;
  $("#run-progress").value = p ? p.done : 0;
  $("#run-eta").textContent = p ? `${p.done} of ${p.total} steps · about ${minutes(p.eta)} left` : "–";
  $("#run-step").textContent = st.step ? `now: ${st.step}` : "";
  const qs = $("#run-questions");
  qs.innerHTML = "";
  for (const q of st.questions || []) {
    const div = document.createElement("div");
    div.className = "small";
    const b = document.createElement("b"); b.textContent = q.text + " ";
    const sel = document.createElement("select");
    sel.dataset.question = q.id;
    for (const c of q.choices) sel.append(new Option(describePlace(c), c));
    div.append(b, sel);
    qs.append(div);
  }
  const active = new Set([...(st.step || "").matchAll(/sample (\S+)/g)].map((m) => m[1]));
  const body = $("#run-samples tbody");
  body.innerHTML = "";
  for (const s of st.samples || []) {
    const tr = document.createElement("tr");
    if (active.has(s.id)) tr.className = "active";
    for (const [value, where] of [[s.id], [s.cycle], [s.rack], [s.machine], [s.tray],
      [describePlace(s.crucible), s.crucible], [describePlace(s.bead), s.bead]]) {
      const td = document.createElement("td");
      td.textContent = value;
      if (where) td.className = `where-${where.split(":")[0]}`;
      tr.append(td);
    }
    body.append(tr);
  }
  if (st.placement) showPlacement(st.placement, `/api/job/placement/${st.placement.check}.jpg`);
}

function showPlacement(p, src) {
  const img = $("#placement-image"), cap = $("#placement-verdict");
  if (img.dataset.src !== src) { img.src = src; img.dataset.src = src; }
  img.className = p.ok ? "ok" : "bad";
  img.alt = `placement check: ${p.ok ? "OK" : p.reason}`;
  const when = p.time ? new Date(p.time * 1000).toLocaleTimeString() : "";
  cap.className = `small ${p.ok ? "ok" : "bad"}`;
  cap.textContent = `${p.ok ? "Placement OK" : "STOP: " + p.reason} ${when ? "(" + when + ")" : ""}`;
}

$("#run-stop").addEventListener("click", () => command("stop"));
$("#run-manual").addEventListener("click", () => $("#commands").scrollIntoView({ behavior: "smooth", block: "start" }));

for (const b of $$("button[data-job]")) {
  b.addEventListener("click", async () => {
    const name = b.dataset.job, err = b.closest("#run") ? $("#run-error") : $("#job-error");
    err.textContent = "";
    let body = {};
    try {
      if (name === "start") body = { run: JSON.parse($("#job-run").value) };
      if (name === "resume") {
        body = { answers: {} };
        const box = b.closest("#run") ? "#run-questions" : "#job-questions";
        for (const sel of $$(`${box} select`)) body.answers[sel.dataset.question] = sel.value;
      }
      if (name === "abort" && !confirm("Abort the current step? The arm brakes; the run can be resumed.")) return;
      if (name === "discard" && !confirm("Forget this run? The samples stay where the job says they are.")) return;
    } catch (e) { err.textContent = `the run is not valid JSON: ${e.message}`; return; }
    try { showJob(await api("POST", `/api/job/${name}`, body)); log(`job ${name} requested`); }
    catch (e) { err.textContent = e.message; log(`job ${name} refused: ${e.message}`, "error"); }
  });
}

// ------------------------------------------------------------------ start

async function start() {
  try {
    const [info, chart, commands, snap] = await Promise.all([
      api("GET", "/api/info"), api("GET", "/api/statechart"), api("GET", "/api/commands"), api("GET", "/api/state")]);
    page.info = info; page.chart = chart; page.commands = commands;
    $("#robot-name").textContent = `· ${info.robot}${info.simulated ? "" : " (real robot)"} · v${info.version}`;
    showControl(snap.control);
    page.state = "";
    showState(snap.state);
    showRobot(snap.robot);
    showGripper(snap.gripper);
    snap.operations.forEach(updateOperation);
    loadPositions();
    loadLayout();
    loadJob();
  } catch (e) {
    log(`cannot load the daemon's state: ${e.message}`, "error");
  }
  updateButtons();
  requestDraw();
  connect();
}
start();
