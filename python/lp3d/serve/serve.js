// lp3d serve: the page's entry point, after lp3d share's gpu.js and viewer.js in its one script.
// A photo (dropped or picked) is posted to /api/photo; the webcam's frames go over the WebSocket
// /ws/live as [frame number u32 LE][JPEG]. Both answer triplane messages ("LP3T", header length
// u32 LE, JSON header, float16 planes channel-last), drawn by the renderer's WGSL on WebGPU from the
// view the user holds. Text from the server is shown with textContent only.
//
// Test mode (#probe=YAW,PITCH): the first photo's and the first live frame's triplanes are each
// rendered at the probe settings and logged as one line "LP3D_SERVE_PROBE {json}" (the RGB image
// (3, R, R) float32 and the planes drawn, base64). Messages shown to the user are also logged as
// "LP3D_MESSAGE <text>", live statistics once a second as "LP3D_LIVE {json}"; "LP3D_READY" once the
// page's controls work.
"use strict";

const $ = (id) => document.getElementById(id);

function checkServeData(d) {
  if (d.format !== "lp3d-serve" || d.version !== 1) throw new Error("not an lp3d serve page of version 1");
  d.decoder.bytes = base64Bytes(d.decoder.base64);
  if (d.decoder.bytes.length !== DECODER_BYTES) throw new Error("the decoder holds " + d.decoder.bytes.length + " bytes");
  delete d.decoder.base64;
  decodeSuperres(d);
}

// A triplane message -> {header, planes: {height, width, dtype, bytes}}.
function parseTriplane(buffer) {
  const bytes = new Uint8Array(buffer);
  const magic = String.fromCharCode(bytes[0], bytes[1], bytes[2], bytes[3]);
  if (bytes.length < 8 || magic !== "LP3T") throw new Error("the server sent something that is not a triplane");
  const n = new DataView(buffer).getUint32(4, true);
  const header = JSON.parse(new TextDecoder().decode(bytes.subarray(8, 8 + n)));
  const planes = bytes.slice(8 + n);
  if (planes.length !== 3 * header.height * header.width * 32 * 2 || header.dtype !== "float16") {
    throw new Error("the server's planes hold " + planes.length + " bytes, not 3 x H x W x 32 float16");
  }
  return { header, planes: { height: header.height, width: header.width, dtype: "float16", bytes: planes } };
}

async function main() {
  const messageBox = $("message");
  const note = (text) => {
    messageBox.textContent = text;
    messageBox.hidden = false;
    console.log("LP3D_MESSAGE " + text);
  };
  const clearNote = () => {
    messageBox.hidden = true;
  };
  const fail = (text) => {
    note(text);
    console.error("LP3D_ERROR " + text);
  };
  let data;
  try {
    data = JSON.parse($("lp3d-data").textContent);
    checkServeData(data);
  } catch (e) {
    fail("This page's data is damaged: " + e.message);
    return;
  }
  $("model").textContent = "model: " + data.model;
  const probe = parseProbe(location.hash);
  if (probe !== null && probe.error) return fail(probe.error);
  if (!navigator.gpu) {
    return fail(
      "This page needs WebGPU, and this browser does not offer it (navigator.gpu is missing). " +
        "Open it in a current Chrome, Edge or Safari, or in Firefox where WebGPU is enabled.",
    );
  }
  const token = new URLSearchParams(location.search).get("token");
  const withToken = (path) =>
    token === null ? path : path + (path.includes("?") ? "&" : "?") + "token=" + encodeURIComponent(token);
  const display = new Display(data, probe, fail);
  setUpPhoto(data, display, withToken, note, clearNote);
  setUpLive(data, display, withToken, note, clearNote);
  console.log("LP3D_READY");
}

// The WebGPU side: one Gpu made with the first planes, then new planes written into it.
class Display {
  constructor(data, probe, fail) {
    this.data = data;
    this.probe = probe;
    this.fail = fail;
    this.gpu = null;
    this.viewer = null;
    this.making = null;
    this.probed = {};
    this.probing = Promise.resolve();
  }

  async show(message) {
    const { header, planes } = message;
    try {
      if (this.making === null) {
        this.data.planes = planes;
        this.making = Gpu.create(this.data, (e) => this.fail("The GPU reported an error: " + e));
        this.gpu = await this.making;
        if (this.probe === null) this.viewer = runViewer(this.gpu, this.data, $("status"), this.fail);
      } else {
        await this.making;
        this.gpu.setPlanes(planes);
        if (this.viewer !== null) this.viewer.refresh();
      }
      if (this.probe !== null && !this.probed[header.kind]) {
        this.probed[header.kind] = true;
        this.probing = this.probing.then(() => this.runProbe(header, planes));
        await this.probing;
      }
    } catch (e) {
      this.fail(e && e.message ? e.message : String(e));
    }
  }

  async runProbe(header, planes) {
    const cam = this.data.camera;
    const label = lookAtCamera(this.probe.yaw, this.probe.pitch, cam, cam.focal);
    this.gpu.setPlanes(planes); // then at once the render: no other planes in between
    const t0 = performance.now();
    const rgb = await this.gpu.readRgb(this.data.probe, label);
    const line = {
      kind: header.kind,
      id: header.id === undefined ? null : header.id,
      frame: header.frame === undefined ? null : header.frame,
      yaw: this.probe.yaw,
      pitch: this.probe.pitch,
      ms: performance.now() - t0,
      adapter: this.gpu.adapter,
      height: planes.height,
      width: planes.width,
      rgb: bytesBase64(rgb),
      planes: bytesBase64(planes.bytes),
    };
    console.log("LP3D_SERVE_PROBE " + JSON.stringify(line));
    $("status").textContent = header.kind + " probe done (" + line.ms.toFixed(0) + " ms)";
  }
}

// ---- photo ---------------------------------------------------------------------------------------

function setUpPhoto(data, display, withToken, note, clearNote) {
  const lim = data.limits;
  let current = null; // the photo's id
  const info = $("photo-info");
  async function upload(file) {
    clearNote();
    if (file.size > lim.max_bytes) {
      return note(file.name + ": larger than the " + (lim.max_bytes >> 20) + " MiB upload limit");
    }
    info.textContent = "lifting " + file.name + "…";
    $("photo-bar").hidden = false;
    const detect = $("detect").checked ? "1" : "0";
    const url = withToken("/api/photo?detect=" + detect + "&name=" + encodeURIComponent(file.name));
    let answer;
    try {
      const r = await fetch(url, { method: "POST", body: file });
      if (!r.ok) {
        const j = await r.json().catch(() => ({ error: "the server answered " + r.status }));
        info.textContent = "";
        return note(j.error);
      }
      answer = parseTriplane(await r.arrayBuffer());
    } catch (e) {
      info.textContent = "";
      return note("upload failed: " + e.message);
    }
    const h = answer.header;
    current = h.id;
    const t = h.timings_ms;
    info.textContent = h.name + ": " + h.description + " · align " + t.align.toFixed(0) + " ms, encode " + t.encode.toFixed(0) + " ms";
    if (h.notes.length) note(h.notes.join("; "));
    $("get-npz").href = withToken("/api/photo/" + h.id + ".npz");
    $("get-html").href = withToken("/api/photo/" + h.id + ".html");
    $("get-glb").href = withToken("/api/photo/" + h.id + ".glb");
    $("get-gif").href = withToken("/api/photo/" + h.id + ".gif");
    await display.show(answer);
  }
  $("file").addEventListener("change", (e) => {
    if (e.target.files.length) upload(e.target.files[0]);
  });
  const drop = $("drop");
  drop.addEventListener("dragover", (e) => {
    e.preventDefault();
    drop.classList.add("over");
  });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (e) => {
    e.preventDefault();
    drop.classList.remove("over");
    if (e.dataTransfer.files.length) upload(e.dataTransfer.files[0]);
  });
  $("refine").addEventListener("click", async () => {
    if (current === null) return;
    const id = current;
    const bar = $("refine-progress");
    const r = await fetch(withToken("/api/photo/" + id + "/refine?steps=" + Number($("steps").value)), { method: "POST" });
    if (!r.ok) return note((await r.json()).error);
    bar.hidden = false;
    for (;;) {
      await new Promise((done) => setTimeout(done, 500));
      const p = await (await fetch(withToken("/api/photo/" + id + "/refine"))).json();
      bar.max = Math.max(1, p.total);
      bar.value = p.step;
      if (p.state === "failed") return note("refinement failed: " + p.error);
      if (p.state === "done") {
        info.textContent = "refined in " + p.seconds + " s: input view " + p.psnr_before + " → " + p.psnr_after + " dB";
        const t = await fetch(withToken("/api/photo/" + id + "/triplane"));
        if (id === current) await display.show(parseTriplane(await t.arrayBuffer()));
        return;
      }
    }
  });
}

// ---- live ----------------------------------------------------------------------------------------

function setUpLive(data, display, withToken, note, clearNote) {
  const cfg = data.live;
  const button = $("live");
  const video = $("camera");
  const stats = $("live-stats");
  let session = null;

  function stop(why) {
    if (session === null) return;
    const s = session;
    session = null;
    s.stream.getTracks().forEach((t) => t.stop());
    if (s.ws.readyState <= 1) s.ws.close(1000, "stopped");
    clearInterval(s.timer);
    video.hidden = true;
    button.textContent = "Start webcam";
    if (why) note(why);
  }

  async function start() {
    clearNote();
    let stream;
    try {
      stream = await navigator.mediaDevices.getUserMedia({
        video: { width: { ideal: cfg.width }, height: { ideal: cfg.height } },
        audio: false,
      });
    } catch (e) {
      return note("the webcam is not available: " + e.message);
    }
    video.srcObject = stream;
    video.hidden = false;
    await video.play();
    const proto = location.protocol === "https:" ? "wss:" : "ws:";
    const ws = new WebSocket(withToken(proto + "//" + location.host + "/ws/live"));
    ws.binaryType = "arraybuffer";
    const s = { stream, ws, sent: new Map(), next: 0, answered: 0, dropped: 0, lastShown: -1, lastSent: 0,
                times: [], latencies: [], server: [], bytes: 0, timer: null };
    session = s;
    button.textContent = "Stop webcam";
    const canvas = document.createElement("canvas");
    const ctx = canvas.getContext("2d");
    const inFlight = () => s.next - s.answered - s.dropped;
    async function pump() {
      if (session !== s) return;
      const now = performance.now();
      if (ws.readyState === 1 && inFlight() < cfg.in_flight && now - s.lastSent >= 1000 / cfg.max_fps &&
          video.readyState >= 2 && video.videoWidth > 0) {
        s.lastSent = now;
        const scale = Math.min(1, cfg.width / video.videoWidth);
        canvas.width = Math.round(video.videoWidth * scale);
        canvas.height = Math.round(video.videoHeight * scale);
        ctx.drawImage(video, 0, 0, canvas.width, canvas.height);
        const id = s.next++;
        const blob = await new Promise((done) => canvas.toBlob(done, "image/jpeg", cfg.jpeg_quality));
        const head = new Uint8Array(4);
        new DataView(head.buffer).setUint32(0, id, true);
        s.sent.set(id, performance.now());
        if (ws.readyState === 1) ws.send(new Blob([head, blob]));
      }
      setTimeout(pump, 4);
    }
    ws.onopen = () => pump();
    ws.onmessage = async (e) => {
      if (typeof e.data === "string") {
        const m = JSON.parse(e.data);
        s.answered++;
        return note(m.error);
      }
      let answer;
      try {
        answer = parseTriplane(e.data);
      } catch (err) {
        return stop(err.message);
      }
      const h = answer.header;
      const now = performance.now();
      s.answered++;
      s.dropped = h.dropped;
      s.bytes = e.data.byteLength;
      if (s.sent.has(h.frame)) {
        s.latencies.push(now - s.sent.get(h.frame));
        s.sent.delete(h.frame);
      }
      s.server.push(h.timings_ms.server);
      s.times.push(now);
      if (h.frame <= s.lastShown) return; // overtaken by a later frame already drawn
      s.lastShown = h.frame;
      await display.show(answer);
    };
    ws.onclose = (e) => {
      if (session === s) stop("the live stream closed: " + (e.reason || "connection lost") + " (" + e.code + ")");
    };
    s.timer = setInterval(() => {
      const now = performance.now();
      s.times = s.times.filter((t) => now - t < 2000);
      const recent = (xs) => xs.slice(-10);
      const median = (xs) => (xs.length ? [...xs].sort((a, b) => a - b)[xs.length >> 1] : NaN);
      const line = {
        fps: s.times.length / 2,
        latency_ms: median(recent(s.latencies)),
        server_ms: median(recent(s.server)),
        frames: s.answered,
        dropped: s.dropped,
        bytes_per_frame: s.bytes,
      };
      stats.textContent = line.fps.toFixed(1) + " fps · latency " + line.latency_ms.toFixed(0) + " ms (server " +
        line.server_ms.toFixed(0) + ") · " + (line.bytes_per_frame / 1024).toFixed(0) + " KiB/frame · dropped " + line.dropped;
      console.log("LP3D_LIVE " + JSON.stringify(line));
    }, 1000);
  }

  button.addEventListener("click", () => (session === null ? start() : stop(null)));
}

main();
