// A small point-cloud viewer on a 2D canvas: coloured points (z-buffered, written as pixels),
// camera frusta (the model's orange, located photos' cyan), orbit controls (drag, wheel, keys),
// click a camera to pick it. No WebGL: it
// draws the same on any browser, a headless one included, and needs no dependency.
//
// After each frame it publishes what it drew (canvas data-points / data-cameras and
// window.geomatchViewer) so that a test can compare it with the model endpoint's numbers.

const FOV = (50 * Math.PI) / 180;
const PICK_PX = 14;

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const add = (a, b) => [a[0] + b[0], a[1] + b[1], a[2] + b[2]];
const scale = (a, s) => [a[0] * s, a[1] * s, a[2] * s];
const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const norm = (a) => {
  const n = Math.hypot(a[0], a[1], a[2]) || 1;
  return [a[0] / n, a[1] / n, a[2] / n];
};

// A camera drawn as a pyramid: lines from its centre to the image's four corners, and the
// image's outline.
function strokeFrustum(ctx, c, corners) {
  ctx.beginPath();
  for (const p of corners) {
    ctx.moveTo(c[0], c[1]);
    ctx.lineTo(p[0], p[1]);
  }
  ctx.moveTo(corners[3][0], corners[3][1]);
  for (const p of corners) ctx.lineTo(p[0], p[1]);
  ctx.stroke();
}

// A camera's frustum in world coordinates: its centre and the four image corners at `depth`.
function frustum(cam, depth) {
  const r = cam.rotation; // world to camera, rows: world = R^T * x_cam + C
  const corners = [
    [0, 0],
    [cam.width, 0],
    [cam.width, cam.height],
    [0, cam.height],
  ].map(([u, v]) => {
    const x = [((u - cam.cx) / cam.focal) * depth, ((v - cam.cy) / cam.focal) * depth, depth];
    const w = [0, 1, 2].map((i) => r[0][i] * x[0] + r[1][i] * x[1] + r[2][i] * x[2]);
    return add(w, cam.center);
  });
  return { centre: cam.center, corners };
}

const median = (values) => {
  const v = Float64Array.from(values).sort();
  return v.length ? v[Math.floor(v.length / 2)] : 0;
};

// The points within 3x the 95th percentile of their distances from the median point.
function inliers(points) {
  if (points.length < 20) return points;
  const m = [0, 1, 2].map((k) => median(points.map((p) => p[k])));
  const d = points.map((p) => Math.hypot(...sub(p, m)));
  const sorted = Float64Array.from(d).sort();
  const limit = 3 * sorted[Math.floor(0.95 * (sorted.length - 1))];
  return limit > 0 ? points.filter((_, i) => d[i] <= limit) : points;
}

export class Viewer {
  constructor(canvas, onPick) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.onPick = onPick;
    this.scene = null;
    this.selected = -1;
    this.located = []; // cameras of located photos (setLocated), drawn apart from the model's
    this.yaw = 0.6;
    this.pitch = 0.5;
    this.stats = { points: 0, cameras: 0, drawnPoints: 0, located: 0, frames: 0 };
    this.publish();
    this.bind();
    new ResizeObserver(() => this.draw()).observe(canvas);
  }

  clear() {
    this.scene = null;
    this.selected = -1;
    this.located = [];
    this.stats = { points: 0, cameras: 0, drawnPoints: 0, located: 0, frames: this.stats.frames };
    this.draw();
    this.publish();
  }

  load(scene) {
    this.scene = scene;
    this.selected = -1;
    const n = scene.points;
    const xyz = scene.xyz;
    // frame the model: the bounding box's centre and the farthest camera or point from it, of the
    // points within 3x the 95th percentile of their distances from the median point (a real
    // survey has a few points triangulated far away from near-parallel rays, which would leave
    // the model a speck in a corner; turning and zooming reach them)
    const pts = [];
    for (let i = 0; i < n; i++) pts.push([xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]]);
    const all = [...inliers(pts), ...scene.cameras.map((c) => c.center)];
    const lo = [Infinity, Infinity, Infinity];
    const hi = [-Infinity, -Infinity, -Infinity];
    for (const p of all) {
      for (let k = 0; k < 3; k++) {
        lo[k] = Math.min(lo[k], p[k]);
        hi[k] = Math.max(hi[k], p[k]);
      }
    }
    const centre = all.length ? scale(add(lo, hi), 0.5) : [0, 0, 0];
    let radius = 1e-6;
    for (const p of all) radius = Math.max(radius, Math.hypot(...sub(p, centre)));
    this.target = centre;
    this.radius = radius;
    this.distance = (radius / Math.sin(FOV / 2)) * 1.05;
    // "up" is where the cameras' up points on average (COLMAP's image y axis points down)
    let up = [0, 0, 0];
    for (const c of scene.cameras) up = add(up, scale(c.rotation[1], -1));
    this.up = Math.hypot(...up) > 1e-9 ? norm(up) : [0, 0, 1];
    const helper = Math.abs(this.up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0];
    this.side = norm(cross(helper, this.up));
    this.front = cross(this.up, this.side);
    // frusta sized to the scene: a tenth of the mean distance between cameras, or of the radius
    const cams = scene.cameras;
    let spacing = 0;
    for (let i = 1; i < cams.length; i++) spacing += Math.hypot(...sub(cams[i].center, cams[i - 1].center));
    spacing = cams.length > 1 ? spacing / (cams.length - 1) : radius;
    this.depth = Math.min(spacing * 0.3, radius * 0.2);
    this.frusta = cams.map((c) => frustum(c, this.depth));
    this.fit([...all, ...this.frusta.flatMap((fr) => fr.corners)]);
    this.draw();
  }

  // Cameras of photos located against the model (same shape as the scene's cameras), drawn in
  // their own colour on top of the model's and not pickable: they have no image in the project.
  setLocated(cameras) {
    this.located = cameras;
    this.draw();
  }

  // The closest distance at which the first view shows every point and camera (with a margin):
  // tighter than the bounding sphere, which leaves most of the canvas empty.
  fit(points) {
    const { right, up, forward } = this.view();
    const rect = this.canvas.getBoundingClientRect();
    const aspect = rect.width > 0 && rect.height > 0 ? rect.width / rect.height : 1.6;
    const tanV = Math.tan(FOV / 2) * 0.9;
    const tanH = tanV * aspect;
    let distance = this.radius * 0.05;
    for (const p of points) {
      const d = sub(p, this.target);
      const z = dot(d, forward);
      distance = Math.max(
        distance,
        Math.abs(dot(d, right)) / tanH - z,
        Math.abs(dot(d, up)) / tanV - z,
        this.radius * 0.01 - z,
      );
    }
    this.distance = distance;
  }

  // the eye and its axes (right, up, forward) for the current orbit
  view() {
    const dir = add(
      add(scale(this.side, Math.cos(this.pitch) * Math.cos(this.yaw)), scale(this.front, Math.cos(this.pitch) * Math.sin(this.yaw))),
      scale(this.up, Math.sin(this.pitch)),
    );
    const eye = add(this.target, scale(dir, this.distance));
    const forward = scale(dir, -1);
    const right = norm(cross(forward, this.up));
    const up = cross(right, forward);
    return { eye, right, up, forward };
  }

  project(v, p, w, h, f) {
    const d = sub(p, v.eye);
    const z = dot(d, v.forward);
    if (z <= 1e-9) return null;
    return [w / 2 + (f * dot(d, v.right)) / z, h / 2 - (f * dot(d, v.up)) / z, z];
  }

  draw() {
    const canvas = this.canvas;
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(1, Math.round(canvas.clientWidth * dpr));
    const h = Math.max(1, Math.round(canvas.clientHeight * dpr));
    if (canvas.width !== w || canvas.height !== h) {
      canvas.width = w;
      canvas.height = h;
    }
    const ctx = this.ctx;
    if (!this.scene) {
      ctx.fillStyle = "#10151c";
      ctx.fillRect(0, 0, w, h);
      return;
    }
    const v = this.view();
    const f = h / 2 / Math.tan(FOV / 2);
    const image = ctx.createImageData(w, h);
    const px = new Uint32Array(image.data.buffer);
    px.fill(0xff1c1510); // #10151c, little-endian ABGR
    const depth = new Float32Array(w * h).fill(Infinity);
    const { xyz, rgb, points } = this.scene;
    const size = Math.max(1, Math.round((points < 20000 ? 3 : 2) * dpr)); // sparse models: bigger dots
    let drawn = 0;
    for (let i = 0; i < points; i++) {
      const s = this.project(v, [xyz[3 * i], xyz[3 * i + 1], xyz[3 * i + 2]], w, h, f);
      if (!s) continue;
      const x0 = Math.floor(s[0]);
      const y0 = Math.floor(s[1]);
      if (x0 < 0 || y0 < 0 || x0 >= w || y0 >= h) continue;
      drawn++;
      const colour = 0xff000000 | (rgb[3 * i + 2] << 16) | (rgb[3 * i + 1] << 8) | rgb[3 * i];
      for (let dy = 0; dy < size; dy++) {
        for (let dx = 0; dx < size; dx++) {
          const x = x0 + dx;
          const y = y0 + dy;
          if (x >= w || y >= h) continue;
          const k = y * w + x;
          if (s[2] < depth[k]) {
            depth[k] = s[2];
            px[k] = colour;
          }
        }
      }
    }
    ctx.putImageData(image, 0, 0);
    let cameras = 0;
    ctx.lineWidth = Math.max(1, dpr);
    this.screen = [];
    this.frusta.forEach((fr, i) => {
      const c = this.project(v, fr.centre, w, h, f);
      const corners = fr.corners.map((p) => this.project(v, p, w, h, f));
      this.screen.push(c);
      if (!c || corners.some((p) => !p)) return;
      cameras++;
      ctx.strokeStyle = i === this.selected ? "#ffffff" : "#ff9d2e";
      strokeFrustum(ctx, c, corners);
    });
    let located = 0;
    ctx.lineWidth = Math.max(2, 2 * dpr);
    ctx.strokeStyle = "#3ee0ff";
    for (const cam of this.located) {
      const fr = frustum(cam, this.depth);
      const c = this.project(v, fr.centre, w, h, f);
      const corners = fr.corners.map((p) => this.project(v, p, w, h, f));
      if (!c || corners.some((p) => !p)) continue;
      located++;
      strokeFrustum(ctx, c, corners);
      ctx.fillStyle = "#3ee0ff";
      ctx.beginPath();
      ctx.arc(c[0], c[1], 4 * dpr, 0, 2 * Math.PI);
      ctx.fill();
    }
    this.stats = { points, cameras, drawnPoints: drawn, located, frames: this.stats.frames + 1 };
    this.publish();
  }

  publish() {
    this.canvas.dataset.points = String(this.stats.points);
    this.canvas.dataset.cameras = String(this.stats.cameras);
    this.canvas.dataset.drawnPoints = String(this.stats.drawnPoints);
    this.canvas.dataset.located = String(this.stats.located);
    window.geomatchViewer = { ...this.stats, cameraPoint: (i) => this.cameraPoint(i) };
  }

  turn(dyaw, dpitch) {
    this.yaw += dyaw;
    this.pitch = Math.max(-1.55, Math.min(1.55, this.pitch + dpitch));
    this.draw();
  }

  zoom(factor) {
    if (!this.scene) return;
    this.distance = Math.max(this.radius * 0.05, Math.min(this.radius * 50, this.distance * factor));
    this.draw();
  }

  select(i) {
    if (!this.scene || !this.scene.cameras.length) return;
    const n = this.scene.cameras.length;
    this.selected = ((i % n) + n) % n;
    this.draw();
    this.onPick(this.scene.cameras[this.selected]);
  }

  pick(clientX, clientY) {
    if (!this.screen) return;
    const rect = this.canvas.getBoundingClientRect();
    const dpr = this.canvas.width / rect.width;
    const x = (clientX - rect.left) * dpr;
    const y = (clientY - rect.top) * dpr;
    let best = -1;
    let bestD = PICK_PX * dpr;
    this.screen.forEach((s, i) => {
      if (!s) return;
      const d = Math.hypot(s[0] - x, s[1] - y);
      if (d < bestD) {
        bestD = d;
        best = i;
      }
    });
    if (best >= 0) this.select(best);
  }

  // the screen position of camera i (CSS pixels relative to the canvas): lets a test click it
  cameraPoint(i) {
    const s = this.screen && this.screen[i];
    if (!s) return null;
    const dpr = this.canvas.width / this.canvas.getBoundingClientRect().width;
    return { x: s[0] / dpr, y: s[1] / dpr };
  }

  bind() {
    const c = this.canvas;
    let drag = null;
    c.addEventListener("pointerdown", (e) => {
      drag = { x: e.clientX, y: e.clientY, moved: 0 };
      c.setPointerCapture(e.pointerId);
    });
    c.addEventListener("pointermove", (e) => {
      if (!drag) return;
      const dx = e.clientX - drag.x;
      const dy = e.clientY - drag.y;
      drag.moved += Math.abs(dx) + Math.abs(dy);
      drag.x = e.clientX;
      drag.y = e.clientY;
      this.turn(-dx * 0.01, dy * 0.01);
    });
    c.addEventListener("pointerup", (e) => {
      if (drag && drag.moved < 4) this.pick(e.clientX, e.clientY);
      drag = null;
    });
    c.addEventListener(
      "wheel",
      (e) => {
        e.preventDefault();
        this.zoom(Math.exp(e.deltaY * 0.001));
      },
      { passive: false },
    );
    c.addEventListener("keydown", (e) => {
      const keys = {
        ArrowLeft: () => this.turn(0.1, 0),
        ArrowRight: () => this.turn(-0.1, 0),
        ArrowUp: () => this.turn(0, 0.1),
        ArrowDown: () => this.turn(0, -0.1),
        "+": () => this.zoom(0.9),
        "=": () => this.zoom(0.9),
        "-": () => this.zoom(1.1),
        n: () => this.select(this.selected + 1),
        p: () => this.select(this.selected - 1),
      };
      if (keys[e.key]) {
        e.preventDefault();
        keys[e.key]();
      }
    });
  }
}
