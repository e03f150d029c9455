// lp3d share: the page's viewer. It renders the embedded triplane with lp3d's own WGSL (the
// renderer's stage files, embedded by `lp3d share` from lp3d_render.shader_sources()) on WebGPU,
// with the renderer's bindings (crates/renderer/src/renderer/layouts.rs), its Params uniform
// (gpu_types.rs) and its dispatches (renderer/frame.rs, render_to_texture): depth_bounds_pass,
// render_rays, then present into a texture that is copied to the canvas.
//
// Everything the page shows comes from the JSON block #lp3d-data, read with JSON.parse and shown
// with textContent: nothing from the file is ever evaluated as code or inserted as HTML.
//
// A page's script is gpu.js (the camera and the Gpu class), this file, then the page's own entry
// point: share.js for lp3d share's page, lp3d/serve/serve.js for lp3d serve's.
//
// With a super-resolution network in the data (a head of the model whose network it is), the still
// view is drawn once more: the network's image of the 32-channel feature image at its input side
// (gpu.js, drawSuperres); moving frames stay raw.
//
// Test mode: the URL fragment #probe=YAW,PITCH renders that view at the probe settings (64²,
// 48+48, exact EG3D semantics) and logs one console line "LP3D_PROBE " + base64 of the float32
// RGB image (3, 64, 64), the layout of lp3d_render.render(...)["rgb"]; with &superres=1, of the
// network's image (3, R_out, R_out) at the page's settings' samples, lp3d_render.render(...,
// superres=)["image"]. Errors are logged as "LP3D_ERROR <message>".
"use strict";

function base64Bytes(text) {
  const s = atob(text);
  const out = new Uint8Array(s.length);
  for (let i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
  return out;
}

function bytesBase64(bytes) {
  let s = "";
  for (let i = 0; i < bytes.length; i += 0x8000) {
    s += String.fromCharCode.apply(null, bytes.subarray(i, i + 0x8000));
  }
  return btoa(s);
}

// The data block's super-resolution network (lp3d.share.superres_data), if any, its weights
// decoded from base64 in place (gpu.js, buildSuperres, reads them).
function decodeSuperres(d) {
  const sr = d.superres;
  if (!sr) return;
  sr.weights = base64Bytes(sr.weights_base64);
  delete sr.weights_base64;
  if (sr.weights.length !== sr.weights_floats * 4 || !Array.isArray(sr.steps) || !sr.steps.length) {
    throw new Error("bad super-resolution network");
  }
}

// "#probe=YAW,PITCH[&kernel=quick|fast][&superres=1]" -> {yaw, pitch, kernel, superres}; null
// without a probe.
function parseProbe(hash) {
  const params = new URLSearchParams(hash.replace(/^#/, ""));
  if (!params.has("probe")) return null;
  const parts = params.get("probe").split(",");
  const yaw = Number(parts[0]);
  const pitch = Number(parts[1]);
  const kernel = params.get("kernel") || "quick";
  if (parts.length !== 2 || !Number.isFinite(yaw) || !(pitch > -90 && pitch < 90)) {
    return { error: "probe: expected #probe=YAW,PITCH with pitch in (-90, 90)" };
  }
  if (kernel !== "quick" && kernel !== "fast") return { error: "probe: kernel must be quick or fast" };
  return { yaw, pitch, kernel, superres: params.get("superres") === "1" };
}

// ---- test mode -------------------------------------------------------------------------------

async function runProbe(gpu, data, probe) {
  if (probe.kernel === "fast") await gpu.compileFastKernel(() => {});
  const cam = data.camera;
  const label = lookAtCamera(probe.yaw, probe.pitch, cam, cam.focal);
  if (probe.superres && !gpu.superres) throw new Error("probe: this page has no super-resolution network");
  const t0 = performance.now();
  const rgb = probe.superres ? await gpu.readSuperres(label) : await gpu.readRgb(data.probe, label);
  const info = {
    yaw: probe.yaw,
    pitch: probe.pitch,
    superres: probe.superres,
    kernel: gpu.kernel,
    adapter: gpu.adapter,
    ms: performance.now() - t0,
    camera: Array.from(new Float32Array(label)),
  };
  console.log("LP3D_PROBE_INFO " + JSON.stringify(info));
  console.log(data.probe.prefix + bytesBase64(rgb));
  document.getElementById("status").textContent = "probe done (" + info.ms.toFixed(0) + " ms)";
}

// ---- the viewer: orbit, zoom, reset and the quality ladder of crates/viewer ------------------

// crates/viewer/src/quality.rs: (resolution divisor, sample divisor), each rung ~4x the one below.
const LADDER_STEPS = [[4, 4], [2, 4], [2, 1], [1, 1]];
// The viewer's default frame budget (--frame-budget-ms): the rung drawn while moving is the
// costliest predicted to fit it.
const FRAME_BUDGET_MS = 100;
// The view counts as moving for this long after its last change.
const SETTLE_MS = 150;

function ladder(top) {
  const fine = top.depth_resolution_importance;
  const minCoarse = Math.min(fine > 0 ? 4 : 2, top.depth_resolution);
  const rungs = [];
  for (const [resDiv, sampleDiv] of LADDER_STEPS) {
    const rung = {
      resolution: Math.max(Math.ceil(top.resolution / resDiv), Math.min(8, top.resolution)),
      depth_resolution: Math.max(Math.floor(top.depth_resolution / sampleDiv), minCoarse),
      depth_resolution_importance: fine === 0 ? 0 : Math.max(Math.floor(fine / sampleDiv), Math.min(2, fine)),
    };
    const last = rungs[rungs.length - 1];
    if (!last || rungLabel(last) !== rungLabel(rung)) rungs.push(rung);
  }
  return rungs;
}

const rungCost = (r) => r.resolution * r.resolution * (r.depth_resolution + r.depth_resolution_importance);
const rungLabel = (r) =>
  r.resolution + "² · " + r.depth_resolution + (r.depth_resolution_importance ? "+" + r.depth_resolution_importance : "");

// Measured times per rung: the last three of each, read by their lower median (as lp3d-view's
// quality::FrameTimes: one slow frame does not demote a rung, two of three do; a rung with fewer
// frames takes the lesser of its own time and the rung measured last's, scaled by cost); unmeasured
// rungs scaled from the nearest in cost.
const RECENT = 3;
const lowerMedian = (times) => [...times].sort((a, b) => a - b)[(times.length - 1) >> 1];
// A measured rung's time scaled to `rung` by the ratio of costs.
const scaledTo = (m, rung) => (lowerMedian(m.recent) * rungCost(rung)) / rungCost(m.rung);
class FrameTimes {
  constructor() {
    this.ms = new Map(); // in the order measured: the rung measured last is last
  }
  record(rung, ms) {
    if (!Number.isFinite(ms) || ms < 0) return;
    const key = rungLabel(rung);
    const recent = [...(this.ms.get(key)?.recent ?? []), ms].slice(-RECENT);
    this.ms.delete(key);
    this.ms.set(key, { rung, recent });
  }
  predict(rung) {
    const own = this.ms.get(rungLabel(rung));
    if (own) {
      const last = [...this.ms.values()].pop();
      const ms = lowerMedian(own.recent);
      return own.recent.length < RECENT ? Math.min(ms, scaledTo(last, rung)) : ms;
    }
    let best = null;
    for (const m of this.ms.values()) {
      const d = Math.abs(Math.log(rungCost(m.rung) / rungCost(rung)));
      if (best === null || d < best.d) best = { d, ms: scaledTo(m, rung) };
    }
    return best === null ? null : best.ms;
  }
  interactive(rungs) {
    for (let i = rungs.length - 1; i >= 0; i--) {
      const ms = this.predict(rungs[i]);
      if (ms !== null && ms <= FRAME_BUDGET_MS) return i;
    }
    return 0;
  }
}

// Returns {refresh}: call refresh() after gpu.setPlanes to draw the new planes from the view held.
function runViewer(gpu, data, statusLine, fail) {
  const canvas = document.getElementById("view");
  const context = canvas.getContext("webgpu");
  context.configure({ device: gpu.device, format: "rgba8unorm", usage: GPUTextureUsage.COPY_DST, alphaMode: "opaque" });
  const cam = data.camera;
  const start = { yaw: cam.yaw, pitch: cam.pitch, zoom: 1 };
  const view = { ...start };
  const rungs = ladder(data.settings);
  const top = rungs.length - 1;
  let times = new FrameTimes();
  let shown = null; // {key, rung, ms, superres: the network's image replaced it}
  let lastChange = -Infinity;
  let running = false;
  let drag = null;
  let generation = 0; // counts the planes drawn: new planes redraw the view

  const key = () => generation + "," + view.yaw + "," + view.pitch + "," + view.zoom;
  const changed = () => {
    lastChange = performance.now();
    wake();
  };
  const wake = () => {
    if (!running) {
      running = true;
      requestAnimationFrame(step);
    }
  };
  // The still view is final once exact at the top rung and, with a network, super-resolved.
  const isFinal = (s) => s.rung === top && (s.superres || !gpu.superres);
  const show = (moving) => {
    const phase = moving ? "moving" : isFinal(shown) ? "final" : "refining";
    const ms = shown.ms;
    const time = ms < 1000 ? ms.toFixed(1) + " ms (" + (1000 / ms).toFixed(0) + " fps)" : (ms / 1000).toFixed(1) + " s";
    const quality = shown.superres
      ? gpu.superres.outputResolution + "² super-resolved from " + gpu.superres.inputResolution + "² · " +
        data.settings.depth_resolution + "+" + data.settings.depth_resolution_importance
      : rungLabel(rungs[shown.rung]);
    statusLine.textContent =
      quality + " (" + phase + ") · " + time + " · " + gpu.kernel + " kernel · " +
      gpu.adapter + (gpu.fallback ? " (software)" : "");
  };

  async function step() {
    const moving = performance.now() - lastChange < SETTLE_MS;
    const k = key();
    let rung = null;
    if (shown === null || shown.key !== k) rung = times.interactive(rungs);
    else if (!moving && shown.rung < top) rung = shown.rung + 1;
    const label = lookAtCamera(view.yaw, view.pitch, cam, cam.focal * view.zoom);
    if (rung === null && !moving && !isFinal(shown)) {
      try {
        const ms = await gpu.drawSuperres(label, context, canvas);
        // The exact frame's time stays the ladder's; this one is the network's frame.
        shown = { ...shown, ms, exactMs: shown.ms, superres: true };
        console.debug("LP3D_FRAME superres " + ms.toFixed(1) + " ms");
      } catch (e) {
        running = false;
        fail("Super-resolving the view failed: " + e.message);
        return;
      }
      requestAnimationFrame(step);
      return;
    }
    if (rung === null) {
      if (moving) requestAnimationFrame(step);
      else {
        running = false;
        show(false);
        const final = { yaw: view.yaw, pitch: view.pitch, zoom: view.zoom, ms: shown.ms, kernel: gpu.kernel };
        if (shown.superres) Object.assign(final, { superres: true, exact_ms: shown.exactMs });
        if (isFinal(shown)) console.log("LP3D_FINAL " + rungLabel(rungs[top]) + " " + JSON.stringify(final));
      }
      return;
    }
    try {
      const ms = await gpu.draw(rungs[rung], label, context, canvas);
      times.record(rungs[rung], ms);
      shown = { key: k, rung, ms, superres: false };
      console.debug("LP3D_FRAME " + rungLabel(rungs[rung]) + " " + ms.toFixed(1) + " ms");
      show(moving);
    } catch (e) {
      running = false;
      fail("Rendering failed: " + e.message);
      return;
    }
    requestAnimationFrame(step);
  }

  // crates/viewer/src/orbit.rs: a drag across the view turns 120° of yaw, 90° of pitch.
  canvas.addEventListener("pointerdown", (e) => {
    drag = { x: e.clientX, y: e.clientY };
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener("pointermove", (e) => {
    if (drag === null) return;
    const w = canvas.clientWidth || 1;
    const dx = (e.clientX - drag.x) / w;
    const dy = (e.clientY - drag.y) / w;
    drag = { x: e.clientX, y: e.clientY };
    let yaw = (((view.yaw - 120 * dx) % 360) + 360) % 360;
    view.yaw = yaw > 180 ? yaw - 360 : yaw;
    view.pitch = Math.min(85, Math.max(-85, view.pitch + 90 * dy));
    changed();
  });
  const endDrag = () => {
    drag = null;
  };
  canvas.addEventListener("pointerup", endDrag);
  canvas.addEventListener("pointercancel", endDrag);
  canvas.addEventListener(
    "wheel",
    (e) => {
      e.preventDefault();
      view.zoom = Math.min(8, Math.max(0.2, view.zoom * Math.exp(-e.deltaY / 400)));
      changed();
    },
    { passive: false },
  );
  const reset = () => {
    Object.assign(view, start);
    changed();
  };
  canvas.addEventListener("dblclick", reset);
  document.getElementById("reset").addEventListener("click", reset);
  document.getElementById("reset").disabled = false;

  // On a CPU adapter the fast kernel's compile would hold up the frames for a minute or more (it
  // is not compiled on a thread of its own there): the quick kernel draws, as LP3D_KERNEL=quick.
  if (!gpu.fallback) {
    gpu
      .compileFastKernel(() => {
        times = new FrameTimes(); // the fast kernel's times replace the quick one's
      })
      .catch((e) => console.warn("lp3d: the fast kernel did not compile (" + e.message + "); keeping the quick one"));
  }
  wake();
  return {
    refresh() {
      generation++;
      changed();
    },
  };
}
