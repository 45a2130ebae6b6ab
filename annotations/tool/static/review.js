// Review mode: the server's automatic checks, and a filmstrip per query (thumbnails with the mask).

const MAX_STRIP = 400; // more frames than this: the strip shows annotated frames only

export class Review {
  constructor(root, hooks) {
    this.root = root;
    this.hooks = hooks; // {api, queries(), frames(), ownerOf(qid), statusOf(owner, frame), open(qid, frame)}
    root.querySelector("#review-refresh").addEventListener("click", () => this.refresh());
  }

  async refresh() {
    const { findings } = await this.hooks.api.get("/api/review");
    const queries = this.hooks.queries();
    const textOf = Object.fromEntries(queries.map((q) => [q.id, q.text]));
    const list = this.root.querySelector("#findings");
    list.textContent = "";
    const counts = {};
    for (const f of findings) {
      counts[f.kind] = (counts[f.kind] || 0) + 1;
      const li = document.createElement("li");
      li.dataset.kind = f.kind;
      const kind = document.createElement("span");
      kind.className = "kind";
      kind.textContent = f.kind;
      li.append(kind, `${textOf[f.query] ?? f.query} · ${f.frame_name} (t=${f.time_index}): ${f.message}`);
      if (f.frame !== null && f.frame !== undefined) li.addEventListener("click", () => this.hooks.open(f.query, f.frame));
      list.append(li);
    }
    const summary = Object.entries(counts).map(([k, n]) => `${n} ${k}`).join(", ");
    this.root.querySelector("#review-summary").textContent = findings.length ? summary : "no findings";
    this.renderStrips(queries);
    return findings;
  }

  renderStrips(queries) {
    const host = this.root.querySelector("#filmstrips");
    host.textContent = "";
    const frames = this.hooks.frames();
    for (const q of queries) {
      const owner = this.hooks.ownerOf(q.id);
      if (owner !== q.id) continue; // a time-sensitive query shows its base's strip
      const box = document.createElement("div");
      box.className = "filmstrip";
      const h = document.createElement("h3");
      h.textContent = q.text;
      const strip = document.createElement("div");
      strip.className = "strip";
      const shown = frames.length > MAX_STRIP ? frames.filter((f) => this.hooks.statusOf(owner, f.index) !== undefined) : frames;
      for (const f of shown) {
        const st = this.hooks.statusOf(owner, f.index);
        const fig = document.createElement("figure");
        fig.className = st === 1 ? "mask" : st === 0 ? "absent" : "none";
        fig.title = `${f.name} t=${f.time_index}: ${st === 1 ? "mask" : st === 0 ? "absent" : "not annotated"}`;
        const img = document.createElement("img");
        img.loading = "lazy";
        img.width = 96;
        img.src = `/api/thumb/${f.index}.jpg?query=${owner}&r=${this.hooks.revision()}`;
        const cap = document.createElement("figcaption");
        cap.textContent = `${f.time_index}`;
        fig.append(img, cap);
        fig.addEventListener("click", () => this.hooks.open(q.id, f.index));
        strip.append(fig);
      }
      box.append(h, strip);
      host.append(box);
    }
  }
}
