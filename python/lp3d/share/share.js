// lp3d share: the share page's entry point, after gpu.js and viewer.js in the page's one script.
// It reads the page's data block (the triplane embedded by lp3d share), then runs the test mode
// (#probe=YAW,PITCH) or the viewer.
"use strict";

async function main() {
  const statusLine = document.getElementById("status");
  const messageBox = document.getElementById("message");
  const fail = (text) => {
    messageBox.textContent = text;
    messageBox.hidden = false;
    document.getElementById("view").hidden = true;
    document.getElementById("bar").hidden = true;
    console.error("LP3D_ERROR " + text);
  };

  let data;
  try {
    data = JSON.parse(document.getElementById("lp3d-data").textContent);
    checkData(data);
  } catch (e) {
    fail("This page's data is damaged: " + e.message);
    return;
  }
  document.getElementById("title").textContent = data.title;
  document.getElementById("source").textContent = data.source === null ? "" : data.source;
  const probe = parseProbe(location.hash);
  if (probe !== null && probe.error) {
    fail(probe.error);
    return;
  }

  if (!navigator.gpu) {
    fail(
      "This page needs WebGPU, and this browser does not offer it (navigator.gpu is missing). " +
        "Open it in a current Chrome, Edge or Safari, or in Firefox where WebGPU is enabled; " +
        "pages opened from a file need no server.",
    );
    return;
  }
  try {
    const gpu = await Gpu.create(data, (e) => fail("The GPU reported an error: " + e));
    if (probe !== null) {
      await runProbe(gpu, data, probe);
    } else {
      runViewer(gpu, data, statusLine, fail);
    }
  } catch (e) {
    fail(e && e.message ? e.message : String(e));
  }
}

function checkData(d) {
  if (d.format !== "lp3d-share" || d.version !== 1) {
    throw new Error("not an lp3d share page of version 1");
  }
  const p = d.planes;
  const bytesPer = p.dtype === "float16" ? 2 : p.dtype === "float32" ? 4 : 0;
  if (!bytesPer || !(p.height >= 2 && p.width >= 2)) {
    throw new Error("bad planes description");
  }
  p.bytes = base64Bytes(p.base64);
  if (p.bytes.length !== 3 * p.height * p.width * 32 * bytesPer) {
    throw new Error("the planes hold " + p.bytes.length + " bytes, not 3 x H x W x 32 values");
  }
  d.decoder.bytes = base64Bytes(d.decoder.base64);
  if (d.decoder.bytes.length !== DECODER_BYTES) {
    throw new Error("the decoder holds " + d.decoder.bytes.length + " bytes");
  }
  delete p.base64;
  delete d.decoder.base64;
  decodeSuperres(d);
}

main();
