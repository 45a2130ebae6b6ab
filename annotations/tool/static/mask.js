// Binary masks as Uint8Array(W*H), row-major, values 0/1. Every edit is rasterised here, by
// pixel-centre rules, so no anti-aliasing ever reaches storage (the canvas is display only and is
// never read back).

// Pixel (row y, column x) covers [x, x+1) x [y, y+1); its centre is (x + 0.5, y + 0.5).

export function emptyMask(w, h) {
  return new Uint8Array(w * h);
}

export function isEmpty(mask) {
  for (let i = 0; i < mask.length; i++) if (mask[i]) return false;
  return true;
}

export function area(mask) {
  let n = 0;
  for (let i = 0; i < mask.length; i++) n += mask[i];
  return n;
}

export function equal(a, b) {
  if (a === b) return true;
  if (!a || !b || a.length !== b.length) return false;
  for (let i = 0; i < a.length; i++) if (a[i] !== b[i]) return false;
  return true;
}

// Set every pixel whose centre lies within radius r of (cx, cy) to value (0 or 1).
export function stampDisk(mask, w, h, cx, cy, r, value) {
  const x0 = Math.max(0, Math.floor(cx - r)), x1 = Math.min(w - 1, Math.ceil(cx + r));
  const y0 = Math.max(0, Math.floor(cy - r)), y1 = Math.min(h - 1, Math.ceil(cy + r));
  const r2 = r * r;
  for (let y = y0; y <= y1; y++) {
    const dy = y + 0.5 - cy;
    const row = y * w;
    for (let x = x0; x <= x1; x++) {
      const dx = x + 0.5 - cx;
      if (dx * dx + dy * dy <= r2) mask[row + x] = value;
    }
  }
}

// A brush segment: disks every half radius (at most) from (ax, ay) to (bx, by).
export function strokeSegment(mask, w, h, ax, ay, bx, by, r, value) {
  const d = Math.hypot(bx - ax, by - ay);
  const n = Math.max(1, Math.ceil(d / Math.max(0.5, r / 2)));
  for (let i = 0; i <= n; i++) {
    const t = i / n;
    stampDisk(mask, w, h, ax + (bx - ax) * t, ay + (by - ay) * t, r, value);
  }
}

// Even-odd polygon fill: a pixel is inside when its centre is (scanline at y + 0.5).
export function fillPolygon(mask, w, h, pts, value) {
  if (pts.length < 3) return;
  let ymin = Infinity, ymax = -Infinity;
  for (const [, y] of pts) { ymin = Math.min(ymin, y); ymax = Math.max(ymax, y); }
  const r0 = Math.max(0, Math.floor(ymin - 0.5)), r1 = Math.min(h - 1, Math.ceil(ymax));
  const xs = [];
  for (let row = r0; row <= r1; row++) {
    const yc = row + 0.5;
    xs.length = 0;
    for (let i = 0, j = pts.length - 1; i < pts.length; j = i++) {
      const [xi, yi] = pts[i], [xj, yj] = pts[j];
      // half-open rule on y so a vertex on the scanline is counted once
      if ((yi <= yc && yj > yc) || (yj <= yc && yi > yc)) {
        xs.push(xi + ((yc - yi) / (yj - yi)) * (xj - xi));
      }
    }
    xs.sort((a, b) => a - b);
    for (let k = 0; k + 1 < xs.length; k += 2) {
      // centres x + 0.5 in [xa, xb)
      const c0 = Math.max(0, Math.ceil(xs[k] - 0.5));
      const c1 = Math.min(w - 1, Math.ceil(xs[k + 1] - 0.5) - 1);
      for (let x = c0; x <= c1; x++) mask[row * w + x] = value;
    }
  }
}

// COCO uncompressed RLE: run lengths in column-major order, the first run counts zeros.
export function encodeRuns(mask, w, h) {
  const runs = [];
  let cur = 0, len = 0;
  for (let x = 0; x < w; x++) {
    for (let y = 0; y < h; y++) {
      const v = mask[y * w + x];
      if (v !== cur) { runs.push(len); len = 0; cur = v; }
      len++;
    }
  }
  runs.push(len);
  return runs;
}

export function decodeRuns(runs, w, h) {
  const mask = new Uint8Array(w * h);
  let pos = 0, v = 0;
  for (const n of runs) {
    if (v) {
      for (let k = pos; k < pos + n; k++) {
        const x = (k / h) | 0, y = k - x * h;
        mask[y * w + x] = 1;
      }
    }
    pos += n;
    v ^= 1;
  }
  if (pos !== w * h) throw new Error(`RLE covers ${pos} pixels, expected ${w * h}`);
  return mask;
}

// Paint a mask into RGBA pixels (display only). style: "fill" or "hatch" (proposals).
export function paint(imageData, mask, rgb, alpha, style = "fill") {
  const d = imageData.data, w = imageData.width;
  for (let i = 0, p = 0; i < mask.length; i++, p += 4) {
    if (!mask[i]) { d[p + 3] = 0; continue; }
    if (style === "hatch") {
      const x = i % w, y = (i / w) | 0;
      if (((x + y) & 7) >= 4) { d[p + 3] = 40; d[p] = rgb[0]; d[p + 1] = rgb[1]; d[p + 2] = rgb[2]; continue; }
    }
    d[p] = rgb[0]; d[p + 1] = rgb[1]; d[p + 2] = rgb[2]; d[p + 3] = alpha;
  }
}

// Outline pixels (4-neighbour boundary) of a mask, for drawing edges crisply over the fill.
export function paintOutline(imageData, mask, rgb) {
  const d = imageData.data, w = imageData.width, h = imageData.height;
  for (let y = 0; y < h; y++) {
    for (let x = 0; x < w; x++) {
      const i = y * w + x;
      if (!mask[i]) continue;
      if (x === 0 || y === 0 || x === w - 1 || y === h - 1 || !mask[i - 1] || !mask[i + 1] || !mask[i - w] || !mask[i + w]) {
        const p = 4 * i;
        d[p] = rgb[0]; d[p + 1] = rgb[1]; d[p + 2] = rgb[2]; d[p + 3] = 255;
      }
    }
  }
}
