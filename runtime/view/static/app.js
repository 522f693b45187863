// rigspace view: the page's state, its websocket, the timeline, and the panels' wiring.
import { el, getJSON } from "./util.js";
import { CompositionPanel, FindingsPanel, LivePanel, PropertiesPanel, TreePanel } from "./panels.js";
import { Viewport } from "./viewport.js";

class App {
  constructor() {
    this.state = { time: 0, map: "beauty", view: "neural", camera: null, selected: null, playing: false, weights: {}, controls: {} };
    this.findingMarks = new Map();
    this.paints = [];      // scrub-to-paint measurements, read by the bench and the tests
    this.pending = new Map();  // time -> performance.now() of the input that asked for it
    this.frames = 0;
    this.received = 0;
    this.nextId = 1;
    this.tree = new TreePanel(this);
    this.props = new PropertiesPanel(this);
    this.comp = new CompositionPanel(this);
    this.findings = new FindingsPanel(this);
    this.live = new LivePanel(this);
    this.viewport = new Viewport(this);
  }

  async start() {
    await this.loadSummary();
    this.bindTimeline();
    await this.findings.load();
    await this.tree.load();
    await this.comp.load(null);
    await this.live.load();
    this.connect();
    // The default prim, unless the user picked one while the panels were loading (a
    // finding's link, a tree row): their choice stands.
    const first = this.summary.defaultPrim || (this.tree.rows[0] || {}).path;
    if (first && !this.state.selected) this.select(first);
  }

  async loadSummary() {
    const s = this.summary = await getJSON("/api/summary");
    this.size = s.size;
    this.state.camera = this.state.camera || s.camera;
    document.getElementById("scene-name").textContent = s.scene;
    document.getElementById("stage-info").textContent =
      `${s.upAxis}-up · ${s.metersPerUnit} m/unit · ${s.start}–${s.end} @ ${s.fps} fps`;
    document.getElementById("fps").textContent = `${s.fps} fps`;
    const scrub = document.getElementById("scrub");
    scrub.min = s.start; scrub.max = s.end;
    if (!this.started) { this.started = true; this.state.time = s.start; }
    scrub.value = this.state.time;
    document.getElementById("time").value = this.state.time;
    const maps = document.getElementById("maps");
    maps.replaceChildren(...s.maps.map((m) => el("button", {
      "data-map": m, class: m === this.state.map ? "on" : "", onclick: () => this.setMap(m),
    }, m === "mask" ? "mask/alpha" : m)));
    const views = document.getElementById("view-mode");
    const names = { neural: "neural", reference: "reference", compare: "side by side", error: "error ×4" };
    views.replaceChildren(...s.views.map((v) => el("option", { value: v, disabled: !s.reference && v !== "neural" }, names[v])));
    views.title = s.reference ? "neural / reference views" : "start with --reference for the reference views";
    document.getElementById("camera").replaceChildren(...s.cameras.map((c) => el("option", { value: c, selected: c === this.state.camera }, c)));
    this.viewportError(s.render_error);
  }

  viewportError(text) {
    const box = document.getElementById("viewport-error");
    box.hidden = !text;
    box.textContent = text ? `No frames: ${text}` : "";
  }

  status(text, kind = "") {
    const s = document.getElementById("status");
    s.textContent = text; s.className = `status ${kind}`;
  }

  connect() {
    const ws = this.ws = new WebSocket(`ws://${location.host}/ws`);
    ws.binaryType = "arraybuffer";
    ws.onopen = () => { this.status("connected", "ok"); this.request("auto"); };
    ws.onclose = (e) => this.status(`disconnected (${e.code})`, "err");
    ws.onmessage = (e) => (typeof e.data === "string" ? this.message(JSON.parse(e.data)) : this.frame(e.data));
  }

  async message(m) {
    if (m.type === "live") this.live.show({ bindings: m.bindings });
    if (m.type === "reload") {
      this.status(`reloaded (v${m.version})`, m.error ? "err" : "ok");
      await this.loadSummary();
      this.viewportError(m.error);
      await this.findings.load();
      await this.tree.load();
      this.refreshPrim();
      this.request("auto");
    }
  }

  async frame(buffer) {
    const length = new DataView(buffer).getUint32(0);
    const header = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 4, length)));
    const seq = ++this.received;
    const painted = await this.viewport.paint(header, new Uint8Array(buffer, 4 + length), seq);
    if (!painted) return;
    await new Promise(requestAnimationFrame);  // measured when the frame is on screen
    const asked = this.pending.get(header.time);
    if (asked !== undefined) {
      this.paints.push({ time: header.time, quality: header.quality, cached: header.cached,
        ms: performance.now() - asked, server_ms: header.server_ms });
      if (header.quality === "full") this.pending.delete(header.time);
    }
    this.frames += 1;
    if (this.state.playing) this.advance();
    else if (this.summary.live && header.quality === "full") setTimeout(() => this.request("full"), 100);
  }

  request(quality, id = this.nextId++) {
    if (!this.ws || this.ws.readyState !== WebSocket.OPEN) return;
    const { time, map, view, camera, weights, controls } = this.state;
    this.ws.send(JSON.stringify({ op: "frame", id, time, map, view, camera, quality, weights, controls }));
  }

  setTime(time, quality = "auto") {
    const s = this.summary;
    time = Math.min(Math.max(Math.round(time), s.start), s.end);
    this.state.time = time;
    document.getElementById("scrub").value = time;
    document.getElementById("time").value = time;
    if (!this.pending.has(time)) this.pending.set(time, performance.now());
    this.request(quality);
    clearTimeout(this.propTimer);
    this.propTimer = setTimeout(() => this.refreshPrim(), this.state.playing ? 500 : 120);
  }

  advance() {
    // Real time: skip the frames that rendering took longer than the frame rate allows.
    const now = performance.now();
    const step = Math.max(1, Math.round(((now - this.playClock) / 1000) * this.summary.fps));
    this.playClock = now;
    let t = this.state.time + step;
    if (t > this.summary.end) t = this.summary.start;
    this.setTime(t, "preview");
  }

  bindTimeline() {
    if (this.bound) return;
    this.bound = true;
    const scrub = document.getElementById("scrub");
    scrub.addEventListener("input", () => this.setTime(Number(scrub.value)));
    document.getElementById("time").addEventListener("change", (e) => this.setTime(Number(e.target.value)));
    document.getElementById("play").addEventListener("click", () => this.togglePlay());
    document.getElementById("step-back").addEventListener("click", () => this.setTime(this.state.time - 1));
    document.getElementById("step-fwd").addEventListener("click", () => this.setTime(this.state.time + 1));
    document.getElementById("view-mode").addEventListener("change", (e) => { this.state.view = e.target.value; this.request("auto"); });
    document.getElementById("camera").addEventListener("change", (e) => { this.state.camera = e.target.value; this.request("auto"); });
    document.getElementById("overlay-toggle").addEventListener("change", () => this.viewport.drawOverlay());
    document.getElementById("regions-toggle").addEventListener("change", () => this.viewport.drawOverlay());
    document.addEventListener("keydown", (e) => {
      if (e.target.tagName === "INPUT" && e.target.type !== "range") return;
      if (e.key === " ") { e.preventDefault(); this.togglePlay(); }
      if (e.key === "ArrowRight") this.setTime(this.state.time + 1);
      if (e.key === "ArrowLeft") this.setTime(this.state.time - 1);
    });
  }

  togglePlay() {
    this.state.playing = !this.state.playing;
    document.getElementById("play").textContent = this.state.playing ? "⏸" : "▶";
    if (this.state.playing) { this.playClock = performance.now(); this.advance(); }
    else this.request("full");  // paused: refine what is on screen
  }

  setMap(map) {
    this.state.map = map;
    for (const b of document.querySelectorAll("#maps button")) b.classList.toggle("on", b.dataset.map === map);
    this.request("auto");
  }

  select(path) {
    this.state.selected = path;
    this.tree.render();
    this.refreshPrim();
  }

  refreshPrim() {
    this.props.load(this.state.selected, this.state.time);
    this.comp.load(this.state.selected);
  }
}

const app = new App();
window.rigspaceView = app;
app.start().catch((err) => app.status(`error: ${err.message}`, "err"));
