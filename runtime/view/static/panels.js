// The data panels: prim tree, properties, composition and layers, findings, live bindings.
import { el, fmt, getJSON, shortLayer } from "./util.js";

export class TreePanel {
  constructor(app) {
    this.app = app;
    this.box = document.getElementById("tree");
    this.search = document.getElementById("tree-search");
    this.rows = [];
    this.collapsed = new Set();
    this.search.addEventListener("input", () => this.render());
  }
  async load() {
    this.rows = await getJSON("/api/tree");
    document.getElementById("tree-count").textContent = `${this.rows.length}`;
    this.render();
  }
  visible() {
    const query = this.search.value.trim().toLowerCase();
    if (query) {
      const keep = new Set();
      for (const row of this.rows) {
        if (row.name.toLowerCase().includes(query) || row.type.toLowerCase().includes(query)) {
          let path = row.path;
          while (path) { keep.add(path); path = path.slice(0, path.lastIndexOf("/")); }
        }
      }
      return this.rows.filter((row) => keep.has(row.path));
    }
    return this.rows.filter((row) => ![...this.collapsed].some((c) => row.path.startsWith(c + "/")));
  }
  render() {
    const marks = this.app.findingMarks;
    const nodes = this.visible().map((row) => {
      const sev = marks.get(row.path);
      const node = el("div", {
        class: `node${row.path === this.app.state.selected ? " sel" : ""}${row.active ? "" : " inactive"}${row.rigspace ? " rig" : ""}`,
        "data-path": row.path, role: "treeitem",
        style: `padding-left:${8 + row.depth * 14}px`,
        onclick: () => this.app.select(row.path),
      },
        el("span", { class: "tw", onclick: (e) => { e.stopPropagation(); this.toggle(row); } },
          row.children ? (this.collapsed.has(row.path) ? "▸" : "▾") : ""),
        row.rigspace ? el("span", { title: "rigspace prim", style: "color:var(--rig)" }, "◆") : null,
        el("span", { class: "name" }, row.name),
        el("span", { class: "type" }, row.type || "(typeless)"),
        ...row.applied.map((a) => el("span", { class: `chip${a.startsWith("Rigspace") ? "" : " api"}`, title: "applied API schema" }, a.replace(/API(:|$)/, "$1"))),
        row.active ? null : el("span", { class: "chip api" }, "inactive"),
        sev ? el("span", { class: `dot-${sev}`, title: `${sev} in validation` }) : null,
      );
      return node;
    });
    this.box.replaceChildren(...nodes);
    const sel = this.box.querySelector(".node.sel");
    if (sel) sel.scrollIntoView({ block: "nearest" });
  }
  toggle(row) {
    if (!row.children) return;
    if (this.collapsed.has(row.path)) this.collapsed.delete(row.path); else this.collapsed.add(row.path);
    this.render();
  }
}

function sourceBadge(row) {
  if (row.kind === "attribute" && row.samples > 0) return el("span", { class: "src samples", title: "time-sampled" }, `⏱ ${row.samples} samples`);
  if (row.source === "authored") return el("span", { class: "src authored" }, "authored");
  if (row.source === "fallback") return el("span", { class: "src fallback" }, "fallback");
  return el("span", { class: "src fallback" }, row.source);
}

export class PropertiesPanel {
  constructor(app) {
    this.app = app;
    this.box = document.getElementById("props");
    this.token = 0;
  }
  async load(path, time) {
    const token = ++this.token;
    document.getElementById("props-path").textContent = path || "";
    if (!path) { this.box.replaceChildren(el("div", { class: "empty" }, "Select a prim.")); return; }
    let data;
    try { data = await getJSON(`/api/prim?path=${encodeURIComponent(path)}&time=${time}`); }
    catch (err) { this.box.replaceChildren(el("div", { class: "empty" }, String(err.message))); return; }
    if (token !== this.token) return;  // a newer selection or time won
    const rows = data.properties.map((p) => el("tr", { "data-prop": p.name },
      el("td", { class: "name", title: p.type || "relationship" }, p.name),
      el("td", { class: "value" }, p.kind === "relationship"
        ? (p.targets.length ? p.targets.map((t) => el("a", { class: "prim", onclick: () => this.app.select(t) }, t, " ")) : "—")
        : fmt(p.value)),
      el("td", {}, sourceBadge(p)),
    ));
    const meta = Object.entries(data.metadata).filter(([k]) => k !== "typeName")
      .map(([k, v]) => el("tr", {}, el("td", { class: "name" }, k), el("td", { class: "value", colspan: 2 }, fmt(v))));
    const parts = [
      el("div", { class: "section" }, `${data.type || "(typeless)"} at time ${fmt(data.time)}`),
      el("table", { class: "props" }, el("colgroup", {}, el("col", { class: "c1" }), el("col", {}), el("col", { class: "c3" })),
        el("tr", {}, el("th", {}, "property"), el("th", {}, "value"), el("th", {}, "from")), ...rows),
      el("div", { class: "section" }, "metadata"),
      el("table", { class: "props" }, el("colgroup", {}, el("col", { class: "c1" }), el("col", {}), el("col", { class: "c3" })), ...meta),
    ];
    if (data.bundle) parts.push(...this.bundle(data.bundle));
    if (data.bundle && (data.bundle.blend_shapes || []).length) parts.push(...this.sliders(path, data.bundle.blend_shapes));
    if (data.bundle && (data.bundle.controls || []).length) parts.push(...this.controlSliders(path, data.bundle.controls));
    this.box.replaceChildren(...parts);
  }
  sliders(path, shapes) {
    // Blend shape weights to try on the character: a slider moved overrides the animation's
    // (and a live source's) weight of that shape in every frame until reset.
    const app = this.app;
    const mine = () => app.state.weights[path] || {};
    const set = (name, value) => {
      const next = { ...mine() };
      if (value === null) delete next[name]; else next[name] = value;
      if (Object.keys(next).length) app.state.weights[path] = next; else delete app.state.weights[path];
      app.request("auto");
    };
    const rows = shapes.map((name) => {
      const value = mine()[name];
      const label = el("td", { class: "value num" }, value === undefined ? "animation" : value.toFixed(2));
      const input = el("input", { type: "range", min: "0", max: "1", step: "0.01", value: String(value ?? 0), "data-shape": name });
      input.addEventListener("input", () => { label.textContent = Number(input.value).toFixed(2); set(name, Number(input.value)); });
      return el("tr", {}, el("td", { class: "name" }, name), el("td", {}, input), label);
    });
    const reset = el("button", { id: "weights-reset" }, "reset to the animation");
    reset.addEventListener("click", () => { delete app.state.weights[path]; app.request("auto"); this.load(path, app.state.time); });
    return [el("div", { class: "section" }, "blend shapes (drag to override the animation)"),
      el("table", { id: "blend-sliders", class: "props" }, ...rows), reset];
  }
  controlSliders(path, controls) {
    // The rig's named controls (RigspaceControlAPI), each over its own range: a slider moved
    // overrides the stage's (and a live source's) value of that control until reset.
    const app = this.app;
    const mine = () => app.state.controls[path] || {};
    const set = (name, value) => {
      const next = { ...mine() };
      if (value === null) delete next[name]; else next[name] = value;
      if (Object.keys(next).length) app.state.controls[path] = next; else delete app.state.controls[path];
      app.request("auto");
    };
    const rows = controls.map(({ name, range }) => {
      const [low, high] = range;
      const value = mine()[name];
      const label = el("td", { class: "value num" }, value === undefined ? "stage" : value.toFixed(2));
      const step = String((high - low) / 100);
      const input = el("input", { type: "range", min: String(low), max: String(high), step, value: String(value ?? low), "data-control": name });
      input.addEventListener("input", () => { label.textContent = Number(input.value).toFixed(2); set(name, Number(input.value)); });
      return el("tr", {}, el("td", { class: "name" }, name), el("td", {}, input), label);
    });
    const reset = el("button", { id: "controls-reset" }, "reset to the stage");
    reset.addEventListener("click", () => { delete app.state.controls[path]; app.request("auto"); this.load(path, app.state.time); });
    return [el("div", { class: "section" }, "controls (drag to override the stage)"),
      el("table", { id: "control-sliders", class: "props" }, ...rows), reset];
  }
  bundle(b) {
    const out = [el("div", { class: "section" }, "model bundle")];
    if (b.error) out.push(el("div", { class: "empty", style: "color:var(--err)" }, b.error));
    if (!b.levels) return out;
    out.push(el("table", {},
      el("tr", {}, el("td", { class: "name" }, "manifest"), el("td", { class: "value" }, b.manifest)),
      el("tr", {}, el("td", { class: "name" }, "format"), el("td", { class: "value" }, b.format)),
      el("tr", {}, el("td", { class: "name" }, "joints"), el("td", { class: "value" }, b.joints)),
      el("tr", {}, el("td", { class: "name" }, "blend shapes"), el("td", { class: "value" }, (b.blend_shapes || []).join(", ") || "none")),
      el("tr", {}, el("td", { class: "name" }, "controls"), el("td", { class: "value" }, (b.controls || []).map((c) => `${c.name} ${c.range[0]}..${c.range[1]}`).join(", ") || "none")),
      el("tr", {}, el("td", { class: "name" }, "levels"), el("td", { class: "value" }, b.levels.join(", "))),
      el("tr", {}, el("td", { class: "name" }, "maps"), el("td", { class: "value" }, (b.maps || []).join(", "))),
      el("tr", {}, el("td", { class: "name" }, "training"), el("td", { class: "value" }, `${b.training.preset || "?"}, ${b.training.steps ?? "?"} steps`)),
    ));
    const cols = ["split", "precision", "predictor", "albedo_psnr", "mask_iou", "normal_mean_deg"];
    out.push(el("div", { class: "section" }, "metrics (held-out evaluation)"));
    out.push(el("table", { id: "bundle-metrics" },
      el("tr", {}, ...cols.map((c) => el("th", {}, c.replace("_", " ")))),
      ...b.metrics.map((r) => el("tr", {}, ...cols.map((c) => el("td", { class: typeof r[c] === "number" ? "num" : "" }, typeof r[c] === "number" ? r[c].toFixed(2) : fmt(r[c])))))));
    return out;
  }
}

export class CompositionPanel {
  constructor(app) { this.app = app; this.box = document.getElementById("comp"); this.token = 0; }
  async load(path) {
    const token = ++this.token;
    const summary = this.app.summary;
    const parts = [el("div", { class: "section" }, "layer stack (strongest first)"),
      el("table", {}, ...summary.layers.map((l, i) => el("tr", {},
        el("td", { class: "num muted" }, i), el("td", { class: "value", title: l.layer }, l.name))))];
    const others = summary.used.filter((u) => !summary.layers.some((l) => l.layer === u));
    if (others.length) parts.push(el("div", { class: "section" }, "also used (references, payloads)"),
      el("table", {}, ...others.map((u) => el("tr", {}, el("td", { class: "value", title: u }, shortLayer(u))))));
    if (path) {
      try {
        const c = await getJSON(`/api/composition?path=${encodeURIComponent(path)}`);
        if (token !== this.token) return;
        parts.push(el("div", { class: "section" }, `composition of ${path}`),
          el("table", { id: "arcs" }, el("tr", {}, el("th", {}, "arc"), el("th", {}, "layer"), el("th", {}, "path"), el("th", {}, "specs")),
            ...c.arcs.map((a) => el("tr", {}, el("td", {}, a.arc), el("td", { class: "value", title: a.layer }, shortLayer(a.layer)),
              el("td", { class: "value" }, a.path), el("td", {}, a.hasSpecs ? "yes" : "no")))),
          el("div", { class: "section" }, "prim stack"),
          el("table", {}, ...c.primStack.map((s) => el("tr", {}, el("td", {}, s.specifier.replace("Specifier", "")),
            el("td", { class: "value", title: s.layer }, shortLayer(s.layer)), el("td", { class: "value" }, s.path)))),
          el("div", { class: "section" }, "property opinions (strongest layer, count)"),
          el("table", { id: "opinions" }, ...c.properties.filter((p) => p.stack.length).map((p) => el("tr", {},
            el("td", { class: "name" }, p.name),
            el("td", { class: "value", title: p.stack.map((s) => s.layer).join("\n") }, shortLayer(p.stack[0].layer)),
            el("td", { class: "num muted" }, p.stack.length),
            el("td", {}, p.resolvedFrom ? el("span", { class: `src ${p.resolvedFrom === "time samples" ? "samples" : "authored"}` }, p.resolvedFrom) : "")))));
      } catch (err) { parts.push(el("div", { class: "empty" }, err.message)); }
    }
    this.box.replaceChildren(...parts);
  }
}

export class FindingsPanel {
  constructor(app) { this.app = app; this.box = document.getElementById("findings"); this.items = []; }
  async load() {
    this.items = await getJSON("/api/findings");
    const errors = this.items.filter((f) => f.severity === "error").length;
    document.getElementById("findings-count").textContent = `${errors} errors, ${this.items.length - errors} warnings`;
    this.app.findingMarks = new Map();
    for (const f of this.items) {
      if (!f.prim || !f.prim.startsWith("/")) continue;
      if (this.app.findingMarks.get(f.prim) !== "error") this.app.findingMarks.set(f.prim, f.severity);
    }
    if (!this.items.length) { this.box.replaceChildren(el("div", { class: "empty" }, "No findings: the scene is valid.")); return; }
    this.box.replaceChildren(...this.items.map((f) => el("div", { class: `finding ${f.severity}`, "data-prim": f.prim, "data-code": f.code },
      el("span", { class: "sev" }, f.severity),
      f.prim && f.prim.startsWith("/") ? el("a", { class: "prim", onclick: () => this.app.select(f.prim) }, f.prim) : el("span", { class: "muted" }, shortLayer(f.prim) || "stage"),
      el("span", { class: "code" }, `  ${f.validator}.${f.code}`),
      f.blocks.length ? el("span", { class: "code" }, `  stops ${f.blocks.join(", ")}`) : null,
      el("div", { class: "msg" }, f.message))));
  }
}

const COUNTERS = ["packets", "samples", "malformed", "dropped", "reconnects"];

export class LivePanel {
  constructor(app) { this.app = app; this.box = document.getElementById("live"); }
  async load() { this.show(await getJSON("/api/live")); }
  show(data) {
    const rows = data.bindings || [];
    if (!rows.length) { this.box.replaceChildren(el("div", { class: "empty" }, data.error || "No live bindings on this stage.")); return; }
    const ms = (v) => (v == null ? "—" : `${v.toFixed(1)} ms`);
    this.box.replaceChildren(
      data.error ? el("div", { class: "empty", style: "color:var(--err)" }, data.error) : "",
      el("table", { id: "live-table" }, ...rows.map((r) => el("tr", { "data-binding": r.binding },
        el("td", {},
          el("div", {}, el("b", {}, r.binding), " ", el("span", { class: `st ${r.status}` }, r.enabled ? r.status : "disabled"),
            el("span", { class: "muted" }, `  ${r.character}`)),
          el("div", { class: "muted mono" }, r.url),
          el("div", { class: "counters" },
            ...COUNTERS.map((c) => el("span", {}, `${c} `, el("b", { "data-counter": c }, r[c] ?? "—"))),
            el("span", {}, "last ", el("b", {}, r.last_seen == null ? "—" : `${r.last_seen.toFixed(2)} s ago`)),
            el("span", {}, "latency p50 ", el("b", {}, ms(r.latency_p50_ms))),
            el("span", {}, "jitter p50 ", el("b", {}, ms(r.jitter_p50_ms)))))))));
  }
}
