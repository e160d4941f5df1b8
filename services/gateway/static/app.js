// Live view: one panel per robot with its map (PNG, refetched on `map` events) and its
// trajectory (loaded, then extended by `pose` events from the server-sent stream, and loaded
// again when a pose says loop closure redrew the map).
"use strict";

const API = "/api/v1";
const BACKGROUND = "#20242a";
const views = new Map(); // robot id -> {canvas, label, meta, image, path}

function viewOf(robot) {
  let view = views.get(robot);
  if (view) return view;
  const node = document.getElementById("robot-template").content.cloneNode(true);
  const section = node.querySelector("section");
  section.id = `robot-${robot}`;
  section.querySelector("h2").textContent = robot;
  document.getElementById("empty")?.remove();
  document.getElementById("robots").appendChild(node);
  view = { canvas: section.querySelector("canvas"), label: section.querySelector(".pose"),
           meta: null, image: null, path: [] };
  views.set(robot, view);
  loadTrajectory(robot, view);
  loadMap(robot, view);
  return view;
}

// `untilStamp`: after a redraw, ask again (a few times) until the map server's path reaches
// the redraw's scan, so that an old-frame path is not drawn under the new-frame poses.
async function loadTrajectory(robot, view, untilStamp = -Infinity, tries = 20) {
  const r = await fetch(`${API}/robots/${encodeURIComponent(robot)}/trajectory`);
  if (!r.ok) return;
  const body = await r.json();
  const last = body.poses.length ? body.poses[body.poses.length - 1].stamp_s : -Infinity;
  if (last < untilStamp && tries > 1) {
    setTimeout(() => loadTrajectory(robot, view, untilStamp, tries - 1), 250);
    return;
  }
  view.path = body.poses.map((p) => [p.x_m, p.y_m]).concat(view.path);
  draw(view);
}

async function loadMap(robot, view) {
  const base = `${API}/robots/${encodeURIComponent(robot)}`;
  const meta = await fetch(`${base}/map`);
  if (!meta.ok) return;
  const m = await meta.json();
  const image = new Image();
  image.onload = () => { view.meta = m; view.image = image; draw(view); };
  image.src = `${base}/map.png?revision=${m.revision}`;
}

// World -> canvas transform: fit the map (or, without one, the trajectory) into the canvas.
function frame(view) {
  const c = view.canvas;
  let x0, y0, w, h;
  if (view.meta) {
    ({ origin_x_m: x0, origin_y_m: y0, width_m: w, height_m: h } = view.meta);
  } else if (view.path.length) {
    const xs = view.path.map((p) => p[0]), ys = view.path.map((p) => p[1]);
    x0 = Math.min(...xs) - 1; y0 = Math.min(...ys) - 1;
    w = Math.max(...xs) + 1 - x0; h = Math.max(...ys) + 1 - y0;
  } else {
    return null;
  }
  const scale = Math.min(c.width / w, c.height / h);
  return { scale, x0, y0, h,
           px: (x) => (x - x0) * scale, py: (y) => (h - (y - y0)) * scale };
}

function draw(view) {
  const ctx = view.canvas.getContext("2d");
  ctx.fillStyle = BACKGROUND;
  ctx.fillRect(0, 0, view.canvas.width, view.canvas.height);
  const f = frame(view);
  if (!f) return;
  if (view.image) {
    ctx.imageSmoothingEnabled = false;
    ctx.drawImage(view.image, 0, 0, view.meta.width_m * f.scale, view.meta.height_m * f.scale);
  }
  if (view.path.length) {
    ctx.strokeStyle = "#e0452b";
    ctx.lineWidth = 2;
    ctx.beginPath();
    view.path.forEach(([x, y], i) => (i ? ctx.lineTo(f.px(x), f.py(y)) : ctx.moveTo(f.px(x), f.py(y))));
    ctx.stroke();
    const [x, y] = view.path[view.path.length - 1];
    ctx.fillStyle = "#2b8ae0";
    ctx.beginPath();
    ctx.arc(f.px(x), f.py(y), 4, 0, 2 * Math.PI);
    ctx.fill();
  }
}

function onPose(event) {
  const p = JSON.parse(event.data);
  const view = viewOf(p.robot_id);
  if (p.map_correction) {  // loop closure redrew the map: the whole path moved, load it again
    view.path = [];
    loadTrajectory(p.robot_id, view, p.stamp_s);
  } else {
    view.path.push([p.x_m, p.y_m]);
  }
  view.label.textContent =
    `#${p.seq} t=${p.stamp_s.toFixed(2)} x=${p.x_m.toFixed(2)} y=${p.y_m.toFixed(2)} ` +
    `θ=${p.theta_rad.toFixed(2)} ${p.status}`;
  draw(view);
}

function onMap(event) {
  const m = JSON.parse(event.data);
  const view = viewOf(m.robot_id);
  if (!view.meta || view.meta.revision !== m.revision) loadMap(m.robot_id, view);
}

async function refreshRobots() {
  const status = document.getElementById("status");
  try {
    const r = await fetch(`${API}/robots`);
    if (r.status === 401 || r.status === 403) {
      status.textContent = "this gateway needs its API key for reads " +
        "(SCANFLOW_GATEWAY_GUARD_READS): the live page cannot show them";
      return;
    }
    const body = await r.json();
    body.robots.forEach((robot) => viewOf(robot.robot_id));
    status.textContent = `${body.robots.length} robot(s), services: ` +
      (body.services.map((s) => s.service).join(", ") || "none");
    views.forEach((view, robot) => { if (!view.image) loadMap(robot, view); });
  } catch (err) {
    status.textContent = `gateway unreachable: ${err}`;
  }
}

const stream = new EventSource(`${API}/poses/stream`);
stream.addEventListener("pose", onPose);
stream.addEventListener("map", onMap);
refreshRobots();
setInterval(refreshRobots, 3000);
