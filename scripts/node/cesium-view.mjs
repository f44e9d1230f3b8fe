// Opens a 3D Tiles tileset in CesiumJS in headless Chromium and reports what it drew:
//   node cesium-view.mjs TILESET_DIR OUT_PNG
// Serves the tileset and Cesium's prebuilt bundle on 127.0.0.1, shows the tileset
// alone (no globe, imagery, sky or network), looks at its bounding sphere from the
// south-east, waits until every tile is loaded, and prints one JSON report: the share
// of pixels the model covers, their mean colour, the tiles Cesium loaded and any page
// errors. The screenshot goes to OUT_PNG.
import { createServer } from "node:http";
import { readFile } from "node:fs/promises";
import { join, normalize, extname } from "node:path";
import { fileURLToPath } from "node:url";
import { chromium } from "playwright-core";

const [tilesetDir, outPng] = process.argv.slice(2);
if (!tilesetDir || !outPng) {
  console.error("usage: node cesium-view.mjs TILESET_DIR OUT_PNG");
  process.exit(2);
}
const here = fileURLToPath(new URL(".", import.meta.url));
const cesiumDir = join(here, "node_modules", "cesium", "Build", "Cesium");

const page = `<!doctype html>
<html><head><meta charset="utf-8">
<script src="/cesium/Cesium.js"></script>
<link rel="stylesheet" href="/cesium/Widgets/widgets.css">
<style>html, body, #c { margin: 0; width: 100%; height: 100%; overflow: hidden; background: #000; }</style>
</head><body><div id="c"></div><script>
window.report = null;
(async () => {
  try {
    const widget = new Cesium.CesiumWidget("c", {
      baseLayer: false,
      skyBox: false,
      skyAtmosphere: false,
      contextOptions: { webgl: { preserveDrawingBuffer: true, antialias: false } },
    });
    widget.resize();
    const scene = widget.scene;
    scene.globe.show = false;
    scene.backgroundColor = Cesium.Color.BLACK;
    scene.fog.enabled = false;
    if (scene.sun) scene.sun.show = false;
    if (scene.moon) scene.moon.show = false;
    const tileset = await Cesium.Cesium3DTileset.fromUrl("/tiles/tileset.json", {
      maximumScreenSpaceError: 1,
    });
    scene.primitives.add(tileset);
    const sphere = tileset.boundingSphere;
    widget.camera.viewBoundingSphere(
      sphere,
      new Cesium.HeadingPitchRange(Cesium.Math.toRadians(-30), Cesium.Math.toRadians(-35), sphere.radius * 2.2),
    );
    widget.camera.lookAtTransform(Cesium.Matrix4.IDENTITY);
    let loaded = 0;
    tileset.tileLoad.addEventListener(() => { loaded += 1; });
    await new Promise((resolve) => {
      const started = performance.now();
      const poll = () => {
        widget.render();
        if ((tileset.tilesLoaded && loaded > 0) || performance.now() - started > 60000) resolve();
        else setTimeout(poll, 100);
      };
      poll();
    });
    for (let i = 0; i < 3; i++) widget.render();
    const canvas = scene.canvas;
    const gl = scene.context._gl;
    const w = gl.drawingBufferWidth, h = gl.drawingBufferHeight;
    const pixels = new Uint8Array(w * h * 4);
    gl.readPixels(0, 0, w, h, gl.RGBA, gl.UNSIGNED_BYTE, pixels);
    let covered = 0, r = 0, g = 0, b = 0;
    for (let i = 0; i < w * h; i++) {
      const pr = pixels[4 * i], pg = pixels[4 * i + 1], pb = pixels[4 * i + 2];
      if (pr + pg + pb > 0) { covered += 1; r += pr; g += pg; b += pb; }
    }
    window.report = {
      width: w, height: h,
      coverage: covered / (w * h),
      meanRgb: covered ? [r / covered, g / covered, b / covered] : null,
      tilesLoaded: loaded,
      allLoaded: tileset.tilesLoaded,
      radius: sphere.radius,
    };
  } catch (e) {
    window.report = { error: String(e && e.stack || e) };
  }
})();
</script></body></html>`;

const types = { ".js": "text/javascript", ".json": "application/json", ".glb": "model/gltf-binary",
  ".css": "text/css", ".png": "image/png", ".jpg": "image/jpeg", ".wasm": "application/wasm" };
const server = createServer(async (req, res) => {
  const url = decodeURIComponent(new URL(req.url, "http://x").pathname);
  let file = null;
  if (url === "/favicon.ico") {
    res.writeHead(204);
    res.end();
    return;
  }
  if (url === "/" || url === "/index.html") {
    res.writeHead(200, { "content-type": "text/html" });
    res.end(page);
    return;
  }
  if (url.startsWith("/cesium/")) file = join(cesiumDir, normalize(url.slice(8)));
  if (url.startsWith("/tiles/")) file = join(tilesetDir, normalize(url.slice(7)));
  try {
    if (!file || file.includes("..")) throw new Error("outside");
    const body = await readFile(file);
    res.writeHead(200, { "content-type": types[extname(file)] || "application/octet-stream" });
    res.end(body);
  } catch {
    res.writeHead(404);
    res.end();
  }
});
await new Promise((resolve) => server.listen(0, "127.0.0.1", resolve));
const port = server.address().port;

const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  args: [
    "--no-sandbox", "--disable-gpu-sandbox", "--use-gl=angle", "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
  ],
});
const errors = [];
let report = null;
try {
  const tab = await browser.newPage({ viewport: { width: 800, height: 600 } });
  tab.on("pageerror", (e) => errors.push(String(e)));
  tab.on("console", (m) => { if (m.type() === "error") errors.push(m.text()); });
  await tab.goto(`http://127.0.0.1:${port}/`);
  await tab.waitForFunction(() => window.report !== null, null, { timeout: 120000 });
  report = await tab.evaluate(() => window.report);
  await tab.screenshot({ path: outPng });
} finally {
  await browser.close();
  server.close();
}
console.log(JSON.stringify({ ...report, pageErrors: errors }));
