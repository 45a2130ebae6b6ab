// Time intervals of time-sensitive queries: inclusive, 0-based time indices, kept sorted and merged.

// Sort and merge; touching intervals merge ([0,3] + [4,6] -> [0,6]), as the server does.
export function normalise(intervals) {
  const ivs = intervals.map(([a, b]) => [Math.min(a, b), Math.max(a, b)]).sort((p, q) => p[0] - q[0] || p[1] - q[1]);
  const out = [];
  for (const [a, b] of ivs) {
    if (out.length && a <= out[out.length - 1][1] + 1) out[out.length - 1][1] = Math.max(out[out.length - 1][1], b);
    else out.push([a, b]);
  }
  return out;
}

// "]" at time t: close a pending start, else end the interval that holds t there, else extend
// the nearest interval on the left to t, else a one-frame interval.
export function endAt(intervals, t, pendingStart) {
  const ivs = intervals.map((iv) => iv.slice());
  if (pendingStart !== null && pendingStart !== undefined) return normalise([...ivs, [pendingStart, t]]);
  const holding = ivs.find(([a, b]) => a <= t && t <= b);
  if (holding) { holding[1] = t; return normalise(ivs); }
  const left = ivs.filter(([, b]) => b < t).sort((p, q) => q[1] - p[1])[0];
  if (left) { left[1] = t; return normalise(ivs); }
  return normalise([...ivs, [t, t]]);
}

export function removeAt(intervals, t) {
  return intervals.filter(([a, b]) => !(a <= t && t <= b)).map((iv) => iv.slice());
}

const ROW_H = 26;

// One row per time-sensitive query. Drag an interval edge to move it; click elsewhere to jump.
export class Timeline {
  constructor(canvas, hooks) {
    this.canvas = canvas;
    this.hooks = hooks; // {rows(), numSteps(), currentTime(), selected(), select(qid), jump(t), changed(qid, ivs), pending()}
    this.drag = null;
    canvas.addEventListener("pointerdown", (e) => this.down(e));
    canvas.addEventListener("pointermove", (e) => this.move(e));
    canvas.addEventListener("pointerup", (e) => this.up(e));
    canvas.addEventListener("pointercancel", () => { this.drag = null; });
  }

  xOf(t) {
    const n = this.hooks.numSteps();
    return ((t + 0.5) / n) * this.canvas.width;
  }

  tOf(x) {
    const n = this.hooks.numSteps();
    return Math.max(0, Math.min(n - 1, Math.floor((x / this.canvas.width) * n)));
  }

  local(e) {
    const r = this.canvas.getBoundingClientRect();
    return [((e.clientX - r.left) * this.canvas.width) / r.width, ((e.clientY - r.top) * this.canvas.height) / r.height];
  }

  down(e) {
    const [x, y] = this.local(e);
    const rows = this.hooks.rows();
    const row = Math.floor(y / ROW_H);
    if (row < 0 || row >= rows.length) return;
    const q = rows[row];
    this.hooks.select(q.id);
    const n = this.hooks.numSteps();
    const half = this.canvas.width / n / 2;
    const grab = Math.max(5, half);
    for (let k = 0; k < q.intervals.length; k++) {
      const [a, b] = q.intervals[k];
      if (Math.abs(x - (this.xOf(a) - half)) <= grab) { this.drag = { q, k, edge: 0 }; break; }
      if (Math.abs(x - (this.xOf(b) + half)) <= grab) { this.drag = { q, k, edge: 1 }; break; }
    }
    if (this.drag) {
      this.canvas.setPointerCapture(e.pointerId);
      this.drag.work = q.intervals.map((iv) => iv.slice());
    } else {
      this.hooks.jump(this.tOf(x));
    }
  }

  move(e) {
    if (!this.drag) return;
    const [x] = this.local(e);
    const t = this.tOf(x);
    const iv = this.drag.work[this.drag.k];
    iv[this.drag.edge] = t;
    this.draw(this.drag.q.id, this.drag.work);
  }

  up(e) {
    if (!this.drag) return;
    const { q, work } = this.drag;
    this.drag = null;
    this.hooks.changed(q.id, normalise(work));
  }

  draw(overrideId = null, overrideIvs = null) {
    const rows = this.hooks.rows();
    const c = this.canvas;
    const width = c.clientWidth || 800;
    if (c.width !== width) c.width = width;
    const height = Math.max(ROW_H, rows.length * ROW_H);
    if (c.height !== height) c.height = height;
    const g = c.getContext("2d");
    g.clearRect(0, 0, c.width, c.height);
    const n = this.hooks.numSteps();
    const cell = c.width / n;
    const sel = this.hooks.selected();
    rows.forEach((q, r) => {
      const y = r * ROW_H;
      g.fillStyle = q.id === sel ? "#2b3445" : "#1c222d";
      g.fillRect(0, y, c.width, ROW_H - 2);
      // where the base is annotated: ticks (object / absent)
      const marks = this.hooks.baseMarks(q);
      for (const [t, v] of marks) {
        g.fillStyle = v ? "#6c7a93" : "#4a3030";
        g.fillRect(t * cell, y + ROW_H - 7, Math.max(1, cell), 4);
      }
      const ivs = q.id === overrideId ? overrideIvs : q.intervals;
      g.fillStyle = "#e0a030";
      for (const [a, b] of ivs) g.fillRect(a * cell, y + 3, (b - a + 1) * cell, ROW_H - 12);
      g.fillStyle = "#fff";
      g.font = "12px sans-serif";
      g.fillText(`${q.text}  ${ivs.map(([a, b]) => `[${a},${b}]`).join(" ")}`, 4, y + 15);
      const p = this.hooks.pending(q.id);
      if (p !== null && p !== undefined) {
        g.fillStyle = "#50e0a0";
        g.fillRect(p * cell, y, Math.max(2, cell), ROW_H - 2);
      }
    });
    const t = this.hooks.currentTime();
    g.fillStyle = "#ff4060";
    g.fillRect(t * cell + cell / 2 - 1, 0, 2, c.height);
  }
}
