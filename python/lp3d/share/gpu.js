// lp3d share: the page's GPU side, the part of viewer.js (which follows it in the page's one
// script) that mirrors the renderer: the look-at camera of lp3d.render.camera, and the Gpu class,
// which builds what crates/renderer's Renderer builds (the render module from the embedded WGSL,
// the bindings of renderer/layouts.rs, the Params uniform of gpu_types.rs) and records the
// dispatches of renderer/frame.rs and render_to_texture; with a super-resolution network in the
// page's data, it runs the network's plan (crates/renderer/src/superres/layers.rs, NetworkPlan:
// the packed weights and the dispatches in order, made by the renderer) after a 32-channel render.
"use strict";

// ---- camera (lp3d.render.camera.look_at_camera, roll 0) -------------------------------------

const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
const normalize = (a) => {
  const n = Math.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2]);
  return [a[0] / n, a[1] / n, a[2] / n];
};

// The 25-float EG3D label of a camera at yaw/pitch (degrees) on the sphere of `radius` about the
// world origin, looking at `lookat`, with normalised focal length `focal` (float64, as Python).
function lookAtCamera(yawDeg, pitchDeg, cam, focal) {
  const h = Math.PI / 2 + (yawDeg * Math.PI) / 180;
  let v = (Math.PI / 2) * (1 - Math.sin((pitchDeg * Math.PI) / 180));
  v = Math.min(Math.max(v, 1e-5), Math.PI - 1e-5);
  const phi = Math.acos(1 - (2 * v) / Math.PI);
  const r = cam.radius;
  const origin = [
    r * Math.sin(phi) * Math.cos(Math.PI - h),
    r * Math.cos(phi),
    r * Math.sin(phi) * Math.sin(Math.PI - h),
  ];
  const forward = normalize(sub(cam.lookat, origin));
  const right = normalize(cross([0, 1, 0], forward)).map((x) => -x);
  const down = normalize(cross(forward, right));
  const label = [];
  for (let i = 0; i < 3; i++) label.push(right[i], down[i], forward[i], origin[i]);
  label.push(0, 0, 0, 1, focal, 0, 0.5, 0, focal, 0.5, 0, 0, 1);
  return label;
}

// ---- GPU: the renderer's pipelines, bindings and dispatches ----------------------------------

const WORKGROUP = 64;
// struct Decoder of params.wgsl: w0 512, b0 16, w1 528, b1 9 vec4<f32>.
const DECODER_BYTES = (512 + 16 + 528 + 9) * 16;
const FLAG_WHITE_BACK = 2;
const FLAG_HALF_PLANES = 4;
const PARAMS_BYTES = 96;
// The render's feature channels: rgb only, or all 32 for the super-resolution network.
const RGB_CHANNELS = 3;
const FEATURE_CHANNELS = 32;

class Gpu {
  static async create(data, onError) {
    const adapter = await navigator.gpu.requestAdapter();
    if (!adapter) {
      throw new Error(
        "WebGPU is present but offers no adapter: this browser found no GPU it may use (on Linux, " +
          "Chrome may need chrome://flags/#enable-unsafe-webgpu).",
      );
    }
    // WebGPU's default storage binding limit is 128 MiB; larger planes ask for more.
    const planeBytes = data.planes.bytes.length;
    const limits = {};
    if (planeBytes > 128 << 20) {
      for (const name of ["maxStorageBufferBindingSize", "maxBufferSize"]) {
        if (adapter.limits[name] < planeBytes) {
          throw new Error("this GPU's buffers are too small for these planes (" + planeBytes + " bytes)");
        }
        limits[name] = planeBytes;
      }
    }
    const device = await adapter.requestDevice({ requiredLimits: limits });
    device.addEventListener("uncapturederror", (e) => onError(e.error.message));
    device.lost.then((info) => {
      if (info.reason !== "destroyed") onError("the GPU device was lost: " + info.message);
    });
    const gpu = new Gpu(device, adapter.info || {}, data);
    await gpu.buildPipelines();
    return gpu;
  }

  constructor(device, info, data) {
    this.device = device;
    this.adapter = [info.vendor, info.architecture, info.description].filter((x) => x).join(" ");
    this.fallback = info.isFallbackAdapter === true;
    this.data = data;
    const buffer = (label, size, usage) => device.createBuffer({ label, size, usage });
    const U = GPUBufferUsage;
    const p = data.planes;
    this.half = p.dtype === "float16";
    this.planes = buffer("lp3d planes (3, H, W, 32)", p.bytes.length, U.STORAGE | U.COPY_DST);
    device.queue.writeBuffer(this.planes, 0, p.bytes);
    this.decoder = buffer("lp3d decoder weights", data.decoder.bytes.length, U.UNIFORM | U.COPY_DST);
    device.queue.writeBuffer(this.decoder, 0, data.decoder.bytes);
    const maxRes = Math.max(data.settings.resolution, data.probe.resolution);
    this.maxPixels = maxRes * maxRes;
    this.params = buffer("lp3d params", PARAMS_BYTES, U.UNIFORM | U.COPY_DST);
    this.cameras = buffer("lp3d cameras (1, 25)", 25 * 4, U.STORAGE | U.COPY_DST);
    // With a network, the features also hold its 32-channel input and, for the present pass, its image.
    const sr = data.superres;
    const featureFloats = Math.max(
      3 * this.maxPixels,
      sr ? FEATURE_CHANNELS * sr.input_resolution ** 2 : 0,
      sr ? 3 * sr.output_resolution ** 2 : 0,
    );
    this.features = buffer("lp3d features out", featureFloats * 4, U.STORAGE | U.COPY_SRC | U.COPY_DST);
    this.depth = buffer("lp3d depth out", this.maxPixels * 4, U.STORAGE);
    this.weightsSum = buffer("lp3d weights_sum out", this.maxPixels * 4, U.STORAGE);
    this.depthBounds = buffer("lp3d depth bounds", 8, U.STORAGE | U.COPY_DST);
    this.noOccupancy = buffer("lp3d no occupancy", 4, U.STORAGE);
    this.noBaked = buffer("lp3d no baked field", 16, U.STORAGE); // the page decodes every sample
    this.noFineBricks = device.createTexture({
      label: "lp3d no fine bricks",
      size: [1, 1, 1],
      dimension: "3d",
      format: "rgba16float",
      usage: GPUTextureUsage.TEXTURE_BINDING,
    });
    this.display = buffer("lp3d display", 16, U.UNIFORM | U.COPY_DST);
    device.queue.writeBuffer(this.display, 0, new Uint32Array([0, 0, 0, 0x3f800000])); // RGB, [0, 1]
    this.targets = new Map();
  }

  // The layouts of crates/renderer/src/renderer/layouts.rs, the module the renderer compiles.
  async buildPipelines() {
    const d = this.device;
    const S = GPUShaderStage.COMPUTE;
    const uniform = (binding) => ({ binding, visibility: S, buffer: { type: "uniform" } });
    const storage = (binding, readOnly) => ({
      binding,
      visibility: S,
      buffer: { type: readOnly ? "read-only-storage" : "storage" },
    });
    this.renderLayout = d.createBindGroupLayout({
      label: "lp3d render bindings",
      entries: [
        uniform(0), storage(1, true), storage(2, true), uniform(3),
        storage(4, false), storage(5, false), storage(6, false), storage(7, false), storage(8, true),
        storage(9, true),
        { binding: 10, visibility: S, texture: { sampleType: "unfilterable-float", viewDimension: "3d" } },
      ],
    });
    this.presentLayout = d.createBindGroupLayout({
      label: "lp3d present bindings",
      entries: [
        {
          binding: 0,
          visibility: S,
          storageTexture: { access: "write-only", format: "rgba8unorm", viewDimension: "2d" },
        },
        uniform(1),
      ],
    });
    const renderPipelineLayout = d.createPipelineLayout({ bindGroupLayouts: [this.renderLayout] });
    this.module = d.createShaderModule({
      label: "lp3d render module",
      code: this.data.shaders.map((s) => s[1]).join("\n"),
    });
    const info = await this.module.getCompilationInfo();
    const errors = info.messages.filter((m) => m.type === "error");
    if (errors.length) {
      throw new Error("the WGSL did not compile: " + errors.map((m) => m.lineNum + ": " + m.message).join("; "));
    }
    const make = (label, entryPoint, layout, constants) =>
      d.createComputePipelineAsync({
        label,
        layout,
        compute: { module: this.module, entryPoint, constants },
      });
    this.renderPipelineLayout = renderPipelineLayout;
    [this.boundsPipeline, this.presentPipeline, this.quick] = await Promise.all([
      make("lp3d depth_bounds_pass", "depth_bounds_pass", renderPipelineLayout, {}),
      make(
        "lp3d present",
        "present",
        d.createPipelineLayout({ bindGroupLayouts: [this.renderLayout, this.presentLayout] }),
        {},
      ),
      make("lp3d render_rays (quick kernel)", "render_rays", renderPipelineLayout, { ROLLED_DECODER: 1 }),
    ]);
    this.bindPlanes();
    this.kernel = "quick";
    this.pipeline = this.quick;
    if (this.data.superres) await this.buildSuperres(this.data.superres);
  }

  // The network of the page's data (superres: the renderer's NetworkPlan, its weights as bytes):
  // its weights and layer uniforms uploaded once, its buffers for one image, its four pipelines
  // (shaders/superres.wgsl binds group 2; groups 0 and 1 are bound empty).
  async buildSuperres(sr) {
    const d = this.device;
    const U = GPUBufferUsage;
    const S = GPUShaderStage.COMPUTE;
    const storage = (binding, readOnly) => ({
      binding,
      visibility: S,
      buffer: { type: readOnly ? "read-only-storage" : "storage" },
    });
    const layout = d.createBindGroupLayout({
      label: "lp3d superres bindings",
      entries: [{ binding: 0, visibility: S, buffer: { type: "uniform" } }, storage(1, true), storage(2, true),
        storage(3, false), storage(4, true)],
    });
    const empty = d.createBindGroupLayout({ label: "lp3d empty", entries: [] });
    const pipelineLayout = d.createPipelineLayout({ bindGroupLayouts: [empty, empty, layout] });
    const kernels = [...new Set(sr.steps.map((s) => s.kernel))];
    const pipelines = await Promise.all(
      kernels.map((entryPoint) =>
        d.createComputePipelineAsync({ label: "lp3d " + entryPoint, layout: pipelineLayout, compute: { module: this.module, entryPoint } }),
      ),
    );
    const buffer = (label, size, usage) => d.createBuffer({ label, size: Math.max(size, 16), usage });
    const weights = buffer("lp3d superres weights", sr.weights.length, U.STORAGE | U.COPY_DST);
    d.queue.writeBuffer(weights, 0, sr.weights);
    const slots = {
      features: this.features,
      x: buffer("lp3d superres x", sr.scratch_floats * 4, U.STORAGE),
      up: buffer("lp3d superres up", sr.scratch_floats * 4, U.STORAGE),
      act: buffer("lp3d superres act", sr.scratch_floats * 4, U.STORAGE),
      image_a: buffer("lp3d superres image a", sr.image_floats * 4, U.STORAGE | U.COPY_SRC),
      image_b: buffer("lp3d superres image b", sr.image_floats * 4, U.STORAGE | U.COPY_SRC),
      empty: buffer("lp3d superres no skip", 16, U.STORAGE),
    };
    const steps = sr.steps.map((step) => {
      const uniform = buffer("lp3d superres layer", 32, U.UNIFORM | U.COPY_DST);
      d.queue.writeBuffer(uniform, 0, new Uint32Array(step.layer));
      const group = d.createBindGroup({
        label: "lp3d superres layer bindings",
        layout,
        entries: [uniform, weights, slots[step.src], slots[step.dst], slots[step.skip]].map((b, binding) => ({
          binding,
          resource: { buffer: b },
        })),
      });
      return { pipeline: pipelines[kernels.indexOf(step.kernel)], group, workgroups: step.workgroups };
    });
    this.superres = {
      steps,
      emptyGroup: d.createBindGroup({ label: "lp3d empty", layout: empty, entries: [] }),
      output: slots[sr.output],
      inputResolution: sr.input_resolution,
      outputResolution: sr.output_resolution,
    };
  }

  // The render bind group, over the current planes buffer.
  bindPlanes() {
    this.renderGroup = this.device.createBindGroup({
      label: "lp3d render bind group",
      layout: this.renderLayout,
      entries: [
        ...[
          this.params, this.cameras, this.planes, this.decoder, this.features,
          this.depth, this.weightsSum, this.depthBounds, this.noOccupancy, this.noBaked,
        ].map((buffer, binding) => ({ binding, resource: { buffer } })),
        { binding: 10, resource: this.noFineBricks.createView() },
      ],
    });
  }

  // New planes for the next frames (lp3d serve: each lifted photo or webcam frame), described as
  // data.planes is: {height, width, dtype, bytes}. Planes of the same size overwrite the buffer in
  // queue order (frames already submitted keep the old ones); others get a new buffer.
  setPlanes(planes) {
    const p = this.data.planes;
    const same = planes.bytes.length === p.bytes.length;
    this.data.planes = planes;
    this.half = planes.dtype === "float16";
    if (!same) {
      this.planes.destroy();
      this.planes = this.device.createBuffer({
        label: "lp3d planes (3, H, W, 32)",
        size: planes.bytes.length,
        usage: GPUBufferUsage.STORAGE | GPUBufferUsage.COPY_DST,
      });
      this.bindPlanes();
    }
    this.device.queue.writeBuffer(this.planes, 0, planes.bytes);
  }

  // The fast (unrolled) kernel, compiled in the background as the renderer's KernelChoice::Auto
  // does; same arithmetic, bit-identical images. `ready` is called once it draws.
  compileFastKernel(ready) {
    const make = this.device.createComputePipelineAsync({
      label: "lp3d render_rays (fast kernel)",
      layout: this.renderPipelineLayout,
      compute: { module: this.module, entryPoint: "render_rays", constants: { ROLLED_DECODER: 0 } },
    });
    return make.then((pipeline) => {
      this.pipeline = pipeline;
      this.kernel = "fast";
      ready();
    });
  }

  // gpu_types.rs's Params::new for one camera, `channels` feature channels (rgb only by default), no skips.
  writeParams(rung, channels = RGB_CHANNELS) {
    const b = this.data.bounds;
    const s = rung.depth_resolution;
    const n = rung.depth_resolution_importance;
    const f = Math.fround;
    const start = f(b.ray_start);
    const end = f(b.ray_end);
    let flags = this.half ? FLAG_HALF_PLANES : 0;
    if (this.data.settings.white_back) flags |= FLAG_WHITE_BACK;
    const buf = new ArrayBuffer(PARAMS_BYTES);
    const u = new Uint32Array(buf);
    const x = new Float32Array(buf);
    u.set([rung.resolution, s, n, 0, this.data.planes.height, this.data.planes.width, channels, flags]);
    x.set([start, end, b.box_warp], 8);
    u[11] = 0; // seed (deterministic)
    x[12] = f(f(end - start) / (s - 1)); // lin_step: float32 arithmetic, as torch.linspace
    x[13] = f((end - start) / (s - 1)); // jitter_step: float64, rounded once
    x[14] = n > 1 ? f(1 / (n - 1)) : 0; // u_step
    u[15] = 1; // n_cameras
    // 16, 17: transmittance_threshold, empty_threshold = 0; 18: occupancy_resolution = 0 (off);
    // 19-22: the baked field's = 0 (off); 23: padding.
    this.device.queue.writeBuffer(this.params, 0, buf);
  }

  // Records depth_bounds_pass and render_rays for one camera at `rung` (frame.rs, encode_chunk).
  encodeRender(rung, label, channels = RGB_CHANNELS) {
    const q = this.device.queue;
    this.writeParams(rung, channels);
    q.writeBuffer(this.cameras, 0, new Float32Array(label));
    q.writeBuffer(this.depthBounds, 0, new Uint32Array([0x7f800000, 0])); // [+inf, 0] as bits
    const encoder = this.device.createCommandEncoder({ label: "lp3d render" });
    const pass = encoder.beginComputePass({ label: "lp3d render pass" });
    const groups = Math.ceil((rung.resolution * rung.resolution) / WORKGROUP);
    pass.setBindGroup(0, this.renderGroup);
    pass.setPipeline(this.boundsPipeline);
    // The page renders without jitter, so every ray has the same coarse depths: the bounds pass
    // reads the first ray's, one invocation (frame.rs does the same).
    pass.dispatchWorkgroups(1, 1, 1);
    pass.setPipeline(this.pipeline);
    pass.dispatchWorkgroups(groups, 1, 1);
    return { encoder, pass };
  }

  // The present pass's RGBA8 target for a resolution, and its bind group.
  target(resolution) {
    if (!this.targets.has(resolution)) {
      const texture = this.device.createTexture({
        label: "lp3d display " + resolution,
        size: [resolution, resolution],
        format: "rgba8unorm",
        usage: GPUTextureUsage.STORAGE_BINDING | GPUTextureUsage.COPY_SRC,
      });
      const group = this.device.createBindGroup({
        label: "lp3d present bind group",
        layout: this.presentLayout,
        entries: [
          { binding: 0, resource: texture.createView() },
          { binding: 1, resource: { buffer: this.display } },
        ],
      });
      this.targets.set(resolution, { texture, group });
    }
    return this.targets.get(resolution);
  }

  // Renders `label` at `rung` into the canvas (render_to_texture, then a copy); resolves with
  // the frame's time in milliseconds, submit to completion.
  async draw(rung, label, context, canvas) {
    const t0 = performance.now();
    const { encoder, pass } = this.encodeRender(rung, label);
    await this.present(encoder, pass, rung.resolution, context, canvas);
    return performance.now() - t0;
  }

  // Ends `pass` with the present dispatch of the features' r² RGB image (params at side r), copies
  // it to the canvas, submits and waits for the GPU.
  async present(encoder, pass, r, context, canvas) {
    const target = this.target(r);
    pass.setBindGroup(0, this.renderGroup);
    pass.setPipeline(this.presentPipeline);
    pass.setBindGroup(1, target.group);
    pass.dispatchWorkgroups(Math.ceil(r / 8), Math.ceil(r / 8), 1);
    pass.end();
    if (canvas.width !== r) {
      canvas.width = r;
      canvas.height = r;
    }
    encoder.copyTextureToTexture({ texture: target.texture }, { texture: context.getCurrentTexture() }, [r, r]);
    this.device.queue.submit([encoder.finish()]);
    await this.device.queue.onSubmittedWorkDone();
  }

  // Submits `encoder` with a copy of `buffer`'s first `bytes` and resolves with them (a Uint8Array).
  async readBack(encoder, buffer, bytes) {
    const read = this.device.createBuffer({
      label: "lp3d readback",
      size: bytes,
      usage: GPUBufferUsage.MAP_READ | GPUBufferUsage.COPY_DST,
    });
    encoder.copyBufferToBuffer(buffer, 0, read, 0, bytes);
    this.device.queue.submit([encoder.finish()]);
    await read.mapAsync(GPUMapMode.READ);
    const out = new Uint8Array(read.getMappedRange().slice(0));
    read.unmap();
    read.destroy();
    return out;
  }

  // Renders `label` at `rung` and reads the RGB image (3, R, R) float32 back.
  async readRgb(rung, label) {
    const { encoder, pass } = this.encodeRender(rung, label);
    pass.end();
    return this.readBack(encoder, this.features, 3 * rung.resolution * rung.resolution * 4);
  }

  // The network's image of `label`: the 32-channel feature image at its input side and the
  // settings' samples, then the plan's dispatches (SuperRes::record), in one command buffer; the
  // image (3, R_out, R_out) lands in the plan's output buffer, which is returned.
  encodeSuperres(label) {
    const sr = this.superres;
    const s = this.data.settings;
    const rung = {
      resolution: sr.inputResolution,
      depth_resolution: s.depth_resolution,
      depth_resolution_importance: s.depth_resolution_importance,
    };
    const { encoder, pass } = this.encodeRender(rung, label, FEATURE_CHANNELS);
    pass.end();
    const srPass = encoder.beginComputePass({ label: "lp3d superres pass" });
    srPass.setBindGroup(0, sr.emptyGroup);
    srPass.setBindGroup(1, sr.emptyGroup);
    for (const step of sr.steps) {
      srPass.setPipeline(step.pipeline);
      srPass.setBindGroup(2, step.group);
      srPass.dispatchWorkgroups(step.workgroups[0], step.workgroups[1], 1);
    }
    srPass.end();
    return encoder;
  }

  // Draws the network's image of `label` into the canvas: the image is copied into the features
  // buffer, which the present pass then shows at the output side (a second submit, after the
  // params of that side are written); resolves with the time, submit to completion.
  async drawSuperres(label, context, canvas) {
    const t0 = performance.now();
    const sr = this.superres;
    const r = sr.outputResolution;
    const encoder = this.encodeSuperres(label);
    encoder.copyBufferToBuffer(sr.output, 0, this.features, 0, 3 * r * r * 4);
    this.device.queue.submit([encoder.finish()]);
    this.writeParams({ resolution: r, depth_resolution: 2, depth_resolution_importance: 0 });
    const present = this.device.createCommandEncoder({ label: "lp3d present superres" });
    await this.present(present, present.beginComputePass({ label: "lp3d present pass" }), r, context, canvas);
    return performance.now() - t0;
  }

  // The network's image of `label` read back: (3, R_out, R_out) float32 bytes.
  async readSuperres(label) {
    const r = this.superres.outputResolution;
    return this.readBack(this.encodeSuperres(label), this.superres.output, 3 * r * r * 4);
  }
}
