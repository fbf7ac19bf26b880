// gridslam live viewer: one server-sent event stream of JSON state (services/viewer/state.py,
// ViewerState.view), drawn into one SVG. Trajectories arrive as tails: {epoch, from, points}
// appends to what is held when the epoch matches, replaces it otherwise.
"use strict";

const STAGES = ["ground_truth", "egomotion", "grid", "map"];
const MIN_EXTENT_M = 2;        // the plot never zooms in closer than this many metres
const MARGIN_PX = 24;
const ARROW_GAIN = 4;          // the lattice shift arrow is drawn this many times its length

const tracks = Object.fromEntries(STAGES.map((stage) => [stage, { epoch: null, points: [], pose: null }]));
const experiences = new Map(); // id → [x, y]
let links = [];                // [source, target, kind: 0 odometric, 1 closure kept, 2 closure refused]
let route = [];                // [[x, y], ...]: the last route asked of the map (map/route)
let currentExperience = null;
let updates = 0;
let drawPending = false;
let finished = false;          // the run has finished (the source said so)
// --fleet (services/viewer/fleet.py): robot → {joined, joined_at, part, track: {epoch, points, pose}}
const fleetRobots = new Map();
let fleetExperiences = {};     // robot → Map(id → [x, y]) in its part's frame
let fleetLinks = [];           // [robot, experience, matched robot, matched experience, fate]
// One colour per robot, in the order of their names (a, b, c, ...).
const FLEET_COLOURS = ["#1a9a4b", "#1f6fd1", "#d1541f", "#8e3fb5", "#b7791f", "#0e9aa7", "#c2185b", "#5d6d7e"];

const $ = (id) => document.getElementById(id);
const svg = $("map");

function applyState(state) {
  updates += 1;
  document.body.dataset.updates = String(updates);
  $("robot").textContent = state.robot;
  for (const stage of STAGES) {
    const incoming = state.tracks[stage];
    const track = tracks[stage];
    if (incoming.from === 0 || incoming.epoch !== track.epoch) {
      track.points = incoming.points;
    } else if (incoming.from === track.points.length) {
      for (const point of incoming.points) track.points.push(point);
    } else {
      // Out of step (cannot happen on one stream); the reconnection sends everything again.
      source.close();
      setTimeout(connect, 200);
      return;
    }
    track.epoch = incoming.epoch;
    track.pose = incoming.pose;
  }
  if (state.map) {
    experiences.clear();
    for (const [id, x, y] of state.map.experiences) experiences.set(id, [x, y]);
    links = state.map.links;
    route = state.map.route || [];
  }
  currentExperience = state.current_experience;
  showCounters(state.counters, state.connected);
  showLattice(state.grid, state.lattice);
  showCamera(state.camera, state.template);
  showLoopClosures(state.loop_closures);
  showServices(state.services);
  if (state.fleet && !applyFleet(state.fleet)) return;
  if (!drawPending) {
    drawPending = true;
    requestAnimationFrame(draw);
  }
}

// Tails as the main tracks: {epoch, from, points} appends to what is held when the epoch matches.
function applyFleet(fleet) {
  $("fleet-panel").hidden = false;
  for (const [name, incoming] of Object.entries(fleet.robots)) {
    let robot = fleetRobots.get(name);
    if (!robot) {
      robot = { track: { epoch: null, points: [], pose: null } };
      fleetRobots.set(name, robot);
    }
    const tail = incoming.track;
    if (tail.from === 0 || tail.epoch !== robot.track.epoch) {
      robot.track.points = tail.points;
    } else if (tail.from === robot.track.points.length) {
      for (const point of tail.points) robot.track.points.push(point);
    } else {
      source.close();
      setTimeout(connect, 200);
      return false;
    }
    robot.track.epoch = tail.epoch;
    robot.track.pose = tail.pose;
    robot.joined = incoming.joined;
    robot.joined_at = incoming.joined_at;
    robot.part = incoming.part;
    robot.experiences = incoming.experiences;
  }
  if (fleet.map) {
    fleetExperiences = {};
    for (const [name, rows] of Object.entries(fleet.map.experiences)) {
      fleetExperiences[name] = new Map(rows.map(([id, x, y]) => [id, [x, y]]));
    }
    fleetLinks = fleet.map.links;
  }
  showFleetLegend(fleet.closures);
  return true;
}

function fleetColour(name) {
  const names = [...fleetRobots.keys()].sort();
  return FLEET_COLOURS[names.indexOf(name) % FLEET_COLOURS.length];
}

function showFleetLegend(closures) {
  const items = [...fleetRobots.keys()].sort().map((name) => {
    const robot = fleetRobots.get(name);
    // The fleet frame is the map frame of the robot whose part holds itself (robot a).
    const state = !robot.joined ? "not joined: in its own frame, not drawn"
      : robot.part === name || robot.joined_at === null || robot.joined_at === undefined ? "fleet frame"
      : `joined at frame ${robot.joined_at}`;
    return `<li class="${robot.joined ? "joined" : "unjoined"}" data-robot="${name}"><span class="swatch" ` +
      `style="background:${fleetColour(name)}"></span>robot ${name} · ${state} · ${robot.experiences} experiences</li>`;
  });
  items.push(`<li>inter-robot closures: ${closures.accepted} accepted · ${closures.rejected} refused · ` +
    `${closures.pending} pending</li>`);
  const html = items.join("");
  if ($("fleet-legend").innerHTML !== html) $("fleet-legend").innerHTML = html;
}

// ------------------------------------------------------------------ counters and side panels
function text(id, value) {
  const element = $(id);
  const shown = value === null || value === undefined ? "–" : String(value);
  if (element.textContent !== shown) element.textContent = shown;
}

function showCounters(c, connected) {
  text("frame", c.frame);
  text("rate", c.rate_hz === null ? null : `${c.rate_hz.toFixed(1)} Hz`);
  text("latency", c.latency_ms === null ? null : `${Math.round(c.latency_ms)} ms`);
  text("latency-label", c.latency_stage ? `latency → ${c.latency_stage}` : "latency");
  text("loop-closures", c.loop_closures);
  text("experiences", c.experiences);
  text("templates", c.templates);
  text("decode-errors", c.decode_errors);
  text("gaps", c.gaps);
  text("services-alive", c.services_alive);
  const activity = $("activity");
  finished = c.finished != null;
  if (finished) {
    activity.textContent = `finished · ${c.finished.frames} frames`;
    activity.className = "badge done";
  } else if (!connected) {
    activity.textContent = "waiting for the Zenoh router";
    activity.className = "badge off";
  } else if (c.since_last_frame_s === null) {
    activity.textContent = "no frames yet";
    activity.className = "badge off";
  } else if (c.since_last_frame_s > 2) {
    activity.textContent = `idle ${Math.round(c.since_last_frame_s)} s`;
    activity.className = "badge warn";
  } else {
    activity.textContent = "running";
    activity.className = "badge on";
  }
}

// Image endpoints are fetched one at a time per <img>: a new revision while one is loading
// waits for it, so a slow link never piles up requests. Each image is fetched into a blob: URL,
// so what was shown stays on the page when the viewer is gone (the run ended) and a fetch that
// fails keeps the previous image instead of a broken one.
async function loadImage(img, url) {
  if (url === img.dataset.url) return;   // this revision is shown already
  if (img.dataset.loading === "1") {
    img.dataset.pending = url;
    return;
  }
  img.dataset.loading = "1";
  try {
    const response = await fetch(url, { cache: "no-store" });
    if (response.status === 200) {
      const shown = URL.createObjectURL(await response.blob());
      // Decoded off-screen first, so the <img> swaps from one whole image to the next and is
      // never blank (naturalWidth 0) while a new one loads.
      const next = new Image();
      next.src = shown;
      try {
        await next.decode();
        img.src = shown;
        if (img.dataset.blob) URL.revokeObjectURL(img.dataset.blob);
        img.dataset.blob = shown;
        img.dataset.url = url;
      } catch (error) {
        URL.revokeObjectURL(shown);   // not an image: keep the last one
      }
    }
  } catch (error) {
    // The viewer is unreachable: keep the last image.
  }
  img.dataset.loading = "0";
  const pending = img.dataset.pending;
  if (pending) {
    img.dataset.pending = "";
    loadImage(img, pending);
  }
}

function showLattice(grid, lattice) {
  if (lattice) loadImage($("lattice"), `lattice.png?r=${lattice.revision}`);
  const shift = grid ? grid.shift : lattice ? lattice.shift : null;
  if (!shift) return;
  const line = $("shift-line");
  // Columns grow rightwards and rows downwards in the image, as in the lattice shift (dx, dy).
  const neurons = lattice ? lattice.neurons : 128;
  line.setAttribute("x2", String((ARROW_GAIN * 2 * shift[0]) / neurons));
  line.setAttribute("y2", String((ARROW_GAIN * 2 * shift[1]) / neurons));
  let caption = `shift (${shift[0].toFixed(2)}, ${shift[1].toFixed(2)}) neurons, arrow ×${ARROW_GAIN}`;
  if (grid) {
    caption += ` · step ${(grid.step_length * 100).toFixed(1)} cm · ${grid.integrator}`;
    if (grid.saturated) caption += ' <span class="tag saturated">saturated</span>';
  }
  $("lattice-caption").innerHTML = caption;
}

function showCamera(camera, template) {
  if (camera) loadImage($("camera"), `camera.jpg?r=${camera.revision}`);
  if (!template && !camera) return;
  const parts = [];
  if (camera) parts.push(`frame ${camera.seq}`);
  if (template) {
    const tag = template.new ? '<span class="tag new">new</span>' : '<span class="tag matched">matched</span>';
    parts.push(`template ${template.id} ${tag} d=${template.distance.toFixed(3)}`);
    if (!template.new) parts.push(`first seen at frame ${template.matched_frame}`);
  }
  if (parts.length) $("camera-caption").innerHTML = parts.join(" · ");
}

function showLoopClosures(closures) {
  const list = $("loop-closure-list");
  const html = closures.length
    ? closures.map((c) => `<li>frame ${c.frame} ↔ frame ${c.matched_frame} · template ${c.template} · ${c.votes} votes</li>`).join("")
    : `<li class="none">${finished ? "none" : "none yet"}</li>`;
  if (list.innerHTML !== html) list.innerHTML = html;
}

function showServices(rows) {
  const body = document.querySelector("#health tbody");
  const cell = (value) => `<td>${value === undefined || value === null ? "–" : value}</td>`;
  const html = rows.map((row) => {
    const kind = row.stopped ? "stopped" : !row.alive ? "dead" : row.silent ? "silent" : "";
    const notes = [];
    if (row.stopped) notes.push("stopped");
    else if (!row.alive) notes.push("no liveliness token");
    if (row.silent) notes.push("no recent status");
    for (const [name, value] of Object.entries(row.extra || {})) notes.push(`${name}=${value}`);
    return `<tr class="${kind}" title="${notes.join(" · ")}">` +
      `<td><span class="dot"></span></td>${cell(row.service)}${cell(row.instance)}${cell(row.state)}` +
      `${cell(row.received)}${cell(row.published)}${cell(row.decode_errors)}${cell(row.gaps)}${cell(row.stale)}${cell(row.uptime)}</tr>`;
  }).join("");
  if (body.innerHTML !== html) body.innerHTML = html;
}

// ------------------------------------------------------------------ the plot
function niceStep(metres) {
  const power = 10 ** Math.floor(Math.log10(metres));
  for (const factor of [1, 2, 5, 10]) if (factor * power >= metres) return factor * power;
  return 10 * power;
}

function draw() {
  drawPending = false;
  drawFleet();
  const width = svg.clientWidth;
  const height = svg.clientHeight;
  let xmin = Infinity, xmax = -Infinity, ymin = Infinity, ymax = -Infinity;
  const extend = (x, y) => {
    if (x < xmin) xmin = x; if (x > xmax) xmax = x;
    if (y < ymin) ymin = y; if (y > ymax) ymax = y;
  };
  for (const stage of STAGES) {
    for (const [x, y] of tracks[stage].points) extend(x, y);
    if (tracks[stage].pose) extend(tracks[stage].pose[0], tracks[stage].pose[1]);
  }
  for (const [x, y] of experiences.values()) extend(x, y);
  const empty = xmin === Infinity;
  $("waiting").style.display = empty ? "" : "none";
  if (empty) return;
  const spanX = Math.max(xmax - xmin, MIN_EXTENT_M);
  const spanY = Math.max(ymax - ymin, MIN_EXTENT_M);
  const scale = Math.min((width - 2 * MARGIN_PX) / spanX, (height - 2 * MARGIN_PX) / spanY);
  const midX = (xmin + xmax) / 2, midY = (ymin + ymax) / 2;
  // Planar frame: x to the right, y (left of the robot) up the screen.
  const sx = (x) => (width / 2 + (x - midX) * scale).toFixed(1);
  const sy = (y) => (height / 2 - (y - midY) * scale).toFixed(1);

  drawGrid(width, height, scale, midX, midY);
  for (const stage of STAGES) {
    const track = tracks[stage];
    const points = track.points.slice();
    if (track.pose) points.push([track.pose[0], track.pose[1]]);
    const path = $(`track-${stage}`);
    path.setAttribute("d", points.length ? "M" + points.map(([x, y]) => `${sx(x)},${sy(y)}`).join("L") : "");
    path.dataset.count = String(points.length);
  }
  const dots = [];
  for (const [x, y] of experiences.values()) dots.push(`M${sx(x)},${sy(y)}h0`);
  $("experience-dots").setAttribute("d", dots.join(""));
  $("experience-dots").dataset.count = String(experiences.size);
  const paths = [[], [], []];   // odometric, closures kept, closures refused
  for (const [source, target, kind] of links) {
    const a = experiences.get(source), b = experiences.get(target);
    if (!a || !b) continue;
    paths[kind].push(`M${sx(a[0])},${sy(a[1])}L${sx(b[0])},${sy(b[1])}`);
  }
  $("links").setAttribute("d", paths[0].join(""));
  $("loop-links").setAttribute("d", paths[1].join(""));
  $("loop-links").dataset.count = String(paths[1].length);
  $("refused-links").setAttribute("d", paths[2].join(""));
  $("refused-links").dataset.count = String(paths[2].length);
  $("route").setAttribute("d", route.length ? "M" + route.map(([x, y]) => `${sx(x)},${sy(y)}`).join("L") : "");
  $("route").dataset.count = String(route.length);
  const current = currentExperience === null ? undefined : experiences.get(currentExperience);
  $("current-experience").setAttribute("cx", current ? sx(current[0]) : "-100");
  $("current-experience").setAttribute("cy", current ? sy(current[1]) : "-100");

  const poses = [];
  for (const stage of STAGES) {
    const pose = tracks[stage].pose;
    if (!pose) continue;
    const [x, y, heading] = pose;
    const cx = Number(sx(x)), cy = Number(sy(y));
    const corner = (angle, radius) =>
      `${(cx + radius * Math.cos(angle)).toFixed(1)},${(cy - radius * Math.sin(angle)).toFixed(1)}`;
    poses.push(`<polygon class="pose ${stage}" points="${corner(heading, 11)} ${corner(heading + 2.5, 7)} ${corner(heading - 2.5, 7)}"></polygon>`);
  }
  $("poses").innerHTML = poses.join("");
}

// The fleet frame: only the robots joined to it (a robot not joined is posed in a frame of its own).
function drawFleet() {
  if ($("fleet-panel").hidden) return;
  const plot = $("fleet-map");
  const width = plot.clientWidth, height = plot.clientHeight;
  let xmin = Infinity, xmax = -Infinity, ymin = Infinity, ymax = -Infinity;
  const extend = (x, y) => {
    if (x < xmin) xmin = x; if (x > xmax) xmax = x;
    if (y < ymin) ymin = y; if (y > ymax) ymax = y;
  };
  const joined = [...fleetRobots.keys()].sort().filter((name) => fleetRobots.get(name).joined);
  for (const name of joined) {
    const track = fleetRobots.get(name).track;
    for (const [x, y] of track.points) extend(x, y);
    if (track.pose) extend(track.pose[0], track.pose[1]);
    for (const [x, y] of (fleetExperiences[name] || new Map()).values()) extend(x, y);
  }
  const empty = xmin === Infinity;
  $("fleet-waiting").style.display = empty ? "" : "none";
  if (empty) return;
  const spanX = Math.max(xmax - xmin, MIN_EXTENT_M), spanY = Math.max(ymax - ymin, MIN_EXTENT_M);
  const scale = Math.min((width - 2 * MARGIN_PX) / spanX, (height - 2 * MARGIN_PX) / spanY);
  const midX = (xmin + xmax) / 2, midY = (ymin + ymax) / 2;
  const sx = (x) => (width / 2 + (x - midX) * scale).toFixed(1);
  const sy = (y) => (height / 2 - (y - midY) * scale).toFixed(1);
  drawGrid(width, height, scale, midX, midY, "fleet-grid-lines", "fleet-scale-bar");
  const tracks = [], dots = [], poses = [];
  for (const name of joined) {
    const colour = fleetColour(name);
    const track = fleetRobots.get(name).track;
    const points = track.points.slice();
    if (track.pose) points.push([track.pose[0], track.pose[1]]);
    if (points.length) {
      tracks.push(`<path class="track" data-robot="${name}" data-count="${points.length}" style="stroke:${colour}" ` +
        `d="M${points.map(([x, y]) => `${sx(x)},${sy(y)}`).join("L")}"></path>`);
    }
    const experiences = [...(fleetExperiences[name] || new Map()).values()];
    dots.push(`<path class="experience-dots" data-robot="${name}" data-count="${experiences.length}" ` +
      `style="stroke:${colour};stroke-width:4;stroke-opacity:.45" d="${experiences.map(([x, y]) => `M${sx(x)},${sy(y)}h0`).join("")}"></path>`);
    if (track.pose) {
      const [x, y, heading] = track.pose;
      const cx = Number(sx(x)), cy = Number(sy(y));
      const corner = (angle, radius) =>
        `${(cx + radius * Math.cos(angle)).toFixed(1)},${(cy - radius * Math.sin(angle)).toFixed(1)}`;
      poses.push(`<polygon class="pose" data-robot="${name}" style="fill:${colour}" points="${corner(heading, 12)} ` +
        `${corner(heading + 2.5, 8)} ${corner(heading - 2.5, 8)}"></polygon>` +
        `<text x="${cx + 10}" y="${cy - 10}" style="fill:${colour};font-size:12px;font-weight:600">${name}</text>`);
    }
  }
  const closures = [];
  for (const [robot, experience, matchedRobot, matchedExperience, fate] of fleetLinks) {
    if (fate !== "accepted" || !joined.includes(robot) || !joined.includes(matchedRobot)) continue;
    const a = (fleetExperiences[robot] || new Map()).get(experience);
    const b = (fleetExperiences[matchedRobot] || new Map()).get(matchedExperience);
    if (a && b) closures.push(`M${sx(a[0])},${sy(a[1])}L${sx(b[0])},${sy(b[1])}`);
  }
  $("fleet-tracks").innerHTML = tracks.join("");
  $("fleet-experiences").innerHTML = dots.join("");
  $("fleet-closures").setAttribute("d", closures.join(""));
  $("fleet-closures").dataset.count = String(closures.length);
  $("fleet-poses").innerHTML = poses.join("");
}

function drawGrid(width, height, scale, midX, midY, gridId = "grid-lines", barId = "scale-bar") {
  const step = niceStep(90 / scale);   // metres between grid lines, about 90 px apart
  const lines = [];
  const x0 = midX - width / 2 / scale, y0 = midY - height / 2 / scale;
  for (let x = Math.ceil(x0 / step) * step; x < x0 + width / scale; x += step) {
    const px = (width / 2 + (x - midX) * scale).toFixed(1);
    lines.push(`<line x1="${px}" y1="0" x2="${px}" y2="${height}"></line>`);
  }
  for (let y = Math.ceil(y0 / step) * step; y < y0 + height / scale; y += step) {
    const py = (height / 2 - (y - midY) * scale).toFixed(1);
    lines.push(`<line x1="0" y1="${py}" x2="${width}" y2="${py}"></line>`);
  }
  $(gridId).innerHTML = lines.join("");
  const bar = step * scale;
  const label = step >= 1 ? `${step} m` : `${Math.round(step * 100)} cm`;
  $(barId).innerHTML =
    `<line x1="14" y1="${height - 14}" x2="${(14 + bar).toFixed(1)}" y2="${height - 14}"></line>` +
    `<text x="14" y="${height - 20}">${label}</text>`;
}

window.addEventListener("resize", () => requestAnimationFrame(draw));

// ------------------------------------------------------------------ the stream
let source = null;
function connect() {
  source = new EventSource("events");
  source.onopen = () => {
    $("connection").textContent = "live";
    $("connection").className = "badge on";
  };
  source.onerror = () => {
    // After a finished run the viewer is stopped with Ctrl-C: what the page shows is the run's end.
    $("connection").textContent = finished ? "viewer stopped" : "reconnecting…";
    $("connection").className = finished ? "badge" : "badge off";
  };
  source.onmessage = (event) => applyState(JSON.parse(event.data));
}
connect();
