// The viewport: frames from the websocket, the per-character overlay (and its regions': the
// face, the hands), the decisions table and the frame-time graph.
import { el, fmt } from "./util.js";

const STAGES = ["scene", "rig", "network", "shadows", "lighting", "composite"];
const COLORS = { scene: "#5fb3ff", rig: "#c99cff", network: "#ff9f5f", shadows: "#8a93a3", lighting: "#f2c14e", composite: "#5fd39a" };
const HISTORY = 90;

// A body's or region's view of its look-at joint outside the views its network learned
// (report novel_view: sdk/view_coverage.py): its image there is a guess.
function novelView(entry) {
  return entry.novel_view ? `view ${entry.novel_view_deg}° outside what it learned (${entry.novel_view})` : "";
}

export class Viewport {
  constructor(app) {
    this.app = app;
    this.canvas = document.getElementById("viewport");
    this.ctx = this.canvas.getContext("2d");
    this.overlay = document.getElementById("overlay");
    this.octx = this.overlay.getContext("2d");
    this.graph = document.getElementById("graph");
    this.gctx = this.graph.getContext("2d");
    this.history = [];
    this.last = null;
    this.paintedSeq = 0;
    document.getElementById("graph-legend").replaceChildren(
      ...STAGES.map((s) => [el("i", { style: `background:${COLORS[s]}` }), s]).flat());
  }

  async paint(header, jpeg, seq) {
    const error = document.getElementById("viewport-error");
    if (header.error) {  // the last good frame stays; the reason shows over it
      error.hidden = false;
      error.textContent = `${this.last ? "No new frame (the last good one stays)" : "No frames"}: ${header.error}`;
      return false;
    }
    error.hidden = true;
    const bitmap = await createImageBitmap(new Blob([jpeg], { type: "image/jpeg" }));
    // Decoding is asynchronous: a frame that arrived earlier never paints over a later one.
    if (seq < this.paintedSeq) { bitmap.close(); return false; }
    this.paintedSeq = seq;
    const w = header.view === "compare" ? this.app.size[0] * 2 : this.app.size[0];
    if (this.canvas.width !== w) {
      this.canvas.width = this.overlay.width = w;
      document.getElementById("viewport-wrap").style.aspectRatio = `${w} / ${this.app.size[1]}`;
    }
    this.ctx.imageSmoothingQuality = "high";
    this.ctx.drawImage(bitmap, 0, 0, this.canvas.width, this.canvas.height);
    bitmap.close();
    this.last = header;
    this.drawOverlay();
    this.decisions(header);
    if (!header.cached) this.record(header);
    document.getElementById("frame-info").textContent =
      `t ${fmt(header.time)} · ${header.quality}${header.cached ? " (cached)" : ""} · ` +
      `engine ${(header.report.seconds.total * 1e3).toFixed(0)} ms · server ${header.server_ms.toFixed(0)} ms · ` +
      `${(jpeg.byteLength / 1024).toFixed(0)} KB`;
    return true;
  }

  drawOverlay() {
    const ctx = this.octx, header = this.last;
    ctx.clearRect(0, 0, this.overlay.width, this.overlay.height);
    if (!header) return;
    const scale = this.app.size[0] / header.width;  // a preview is smaller than the canvas
    ctx.font = "12px system-ui, sans-serif";
    if (document.getElementById("regions-toggle").checked) this.drawRegions(header, scale);
    if (!document.getElementById("overlay-toggle").checked) return;
    for (const c of header.report.characters) {
      if (!c.region) continue;
      const [x, y, w, h] = c.region.map((v) => v * scale);
      const colour = c.decision === "evaluated" ? "#5fd39a" : c.decision === "reused" ? "#5fb3ff" : "#ff6b6b";
      ctx.strokeStyle = colour;
      ctx.lineWidth = 1.5;
      ctx.setLineDash([5, 3]);
      ctx.strokeRect(x + 0.5, y + 0.5, w, h);
      ctx.setLineDash([]);
      const lines = [
        `${c.path.split("/").pop()}  ${c.decision}`,
        `level ${c.level}/${c.top_level} · ${c.size_px} px · ${c.mode}`,
        c.reason || c.level_reason,
      ];
      const width = Math.max(...lines.map((l) => ctx.measureText(l).width)) + 10;
      const top = Math.max(0, y - 50);
      ctx.fillStyle = "rgba(12, 14, 18, 0.78)";
      ctx.fillRect(x, top, width, 46);
      ctx.fillStyle = colour;
      ctx.fillText(lines[0], x + 5, top + 14);
      ctx.fillStyle = "#d7dbe2";
      ctx.fillText(lines[1], x + 5, top + 28);
      ctx.fillStyle = "#8a93a3";
      ctx.fillText(lines[2], x + 5, top + 42);
    }
  }

  // Each region drawn this frame: its square, dotted, with its name, level and decision.
  drawRegions(header, scale) {
    const ctx = this.octx;
    for (const c of header.report.characters) {
      for (const r of (c.regions || []).filter((r) => r.region)) {
        const [x, y, w, h] = r.region.map((v) => v * scale);
        ctx.strokeStyle = r.decision === "evaluated" ? "#f2c14e" : "#c99cff";
        ctx.lineWidth = 1.5;
        ctx.setLineDash([2, 3]);
        ctx.strokeRect(x + 0.5, y + 0.5, w, h);
        ctx.setLineDash([]);
        const novel = r.novel_view ? ` · view ${r.novel_view_deg}° outside` : "";
        const label = `${r.name} ${r.decision} · level ${r.level}/${r.top_level} · ${r.size_px} px${novel}`;
        ctx.fillStyle = "rgba(12, 14, 18, 0.78)";
        ctx.fillRect(x, y + h - 18, ctx.measureText(label).width + 10, 18);
        ctx.fillStyle = ctx.strokeStyle;
        ctx.fillText(label, x + 5, y + h - 5);
      }
    }
  }

  decisions(header) {
    const report = header.report;
    const rows = report.characters.flatMap((c) => [el("tr", { "data-character": c.path },
      el("td", { class: "value" }, c.path),
      el("td", {}, el("span", { class: `st ${c.decision}` }, c.decision)),
      el("td", { class: "num" }, c.level ? `${c.level}/${c.top_level}` : "—"),
      el("td", {}, c.mode || ""),
      el("td", { class: "muted" }, [c.reason, c.mode_reason, c.level_reason, novelView(c)].filter(Boolean).join("; "))),
    ...(c.regions || []).map((r) => el("tr", { "data-region": `${c.path}#${r.name}` },
      el("td", { class: "value" }, `  ↳ region ${r.name}`),
      el("td", {}, el("span", { class: `st ${r.decision}` }, r.decision)),
      el("td", { class: "num" }, r.level ? `${r.level}/${r.top_level}` : "—"),
      el("td", {}, r.mode || ""),
      el("td", { class: "muted" }, [r.reason, r.level_reason, novelView(r)].filter(Boolean).join("; "))))]);
    const secs = report.seconds;
    document.getElementById("decisions").replaceChildren(
      el("table", {}, el("tr", {}, ...["character", "decision", "level", "mode", "why"].map((h) => el("th", {}, h))), ...rows),
      el("div", { class: "section" }, `${header.quality} frame ${header.width}x${header.height}: ms per stage`),
      el("table", { id: "stage-ms" }, el("tr", {}, ...STAGES.map((s) => el("th", { class: "num" }, s)), el("th", { class: "num" }, "total")),
        el("tr", {}, ...STAGES.map((s) => el("td", { class: "num" }, (secs[s] * 1e3).toFixed(1))), el("td", { class: "num" }, (secs.total * 1e3).toFixed(1)))));
  }

  record(header) {
    this.history.push({ seconds: header.report.seconds, quality: header.quality });
    if (this.history.length > HISTORY) this.history.shift();
    const ctx = this.gctx, W = this.graph.width, H = this.graph.height;
    ctx.clearRect(0, 0, W, H);
    const top = 1.1 * Math.max(180, ...this.history.map((h) => h.seconds.total * 1e3));
    const y = (ms) => H - 14 - (ms / top) * (H - 22);
    ctx.strokeStyle = "#2e333d"; ctx.fillStyle = "#8a93a3"; ctx.font = "10px system-ui, sans-serif";
    let labelled = H;
    for (const ms of [33, 100, 150, 250, 500, 1000, 2000].filter((v) => v < top)) {
      ctx.beginPath(); ctx.moveTo(0, y(ms)); ctx.lineTo(W, y(ms)); ctx.stroke();
      if (labelled - y(ms) >= 12) { ctx.fillText(`${ms} ms`, W - 44, y(ms) - 2); labelled = y(ms); }
    }
    const bar = W / HISTORY;
    this.history.forEach((h, i) => {
      let acc = 0;
      for (const s of STAGES) {
        const ms = h.seconds[s] * 1e3;
        ctx.fillStyle = COLORS[s];
        ctx.globalAlpha = h.quality === "preview" ? 0.55 : 1;
        ctx.fillRect(i * bar, y(acc + ms), Math.max(bar - 1, 1), y(acc) - y(acc + ms));
        acc += ms;
      }
    });
    ctx.globalAlpha = 1;
    ctx.fillStyle = "#8a93a3";
    ctx.fillText(`last ${this.history.length} rendered frames (faded: preview)`, 4, H - 2);
  }
}
