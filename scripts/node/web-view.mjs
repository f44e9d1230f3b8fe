// Opens Texel's field display in headless Chromium and reports what it drew:
//   node web-view.mjs URL OUT_PNG [WIDTH HEIGHT] [--restart-wait-ms N]
// URL is the page (served by texeld) with its deep link, for example
// http://127.0.0.1:7878/?mode=blended&pose=...&ready=12. The page sets
// data-texel-ready on <body> once the model it was asked for is on screen; this waits
// for that, screenshots the canvas into OUT_PNG and prints one JSON report: the
// rendering path, the times (navigation to ready, from a cached wasm on a second
// load, and where the cached load's time went), the frames drawn while idle and
// during a drag, the frame time while dragging, the bytes received and any page
// errors. WebGPU runs on
// SwiftShader where there is no GPU. With --restart-wait-ms the page stays open after
// the screenshot: the caller restarts the daemon (then writes a line to stdin) and the
// page must reconnect by itself and be ready again within that time.
import { chromium } from "playwright-core";
import { createInterface } from "node:readline";

const args = process.argv.slice(2);
const flag = (name) => {
  const i = args.indexOf(name);
  if (i < 0) return null;
  const v = args[i + 1];
  args.splice(i, 2);
  return v;
};
const restartWaitMs = Number(flag("--restart-wait-ms") ?? 0);
const backend = flag("--backend") ?? "webgpu";
const [url, outPng, w, h] = args;
if (!url || !outPng) {
  console.error("usage: node web-view.mjs URL OUT_PNG [WIDTH HEIGHT] [--backend webgpu|webgl2] [--restart-wait-ms N]");
  process.exit(2);
}
const width = Number(w ?? 640);
const height = Number(h ?? 480);

const gpuArgs = [
  "--no-sandbox", "--disable-gpu-sandbox", "--ignore-gpu-blocklist", "--enable-unsafe-swiftshader",
  "--use-angle=swiftshader", "--disable-quic", "--no-first-run", "--disable-background-networking",
  "--disable-component-update", "--disable-sync",
  // WebGPU on SwiftShader's Vulkan where there is no GPU.
  // (--use-vulkan=swiftshader: without it the compositor never shows the WebGPU canvas.)
  ...(backend === "webgpu" ? ["--enable-unsafe-webgpu", "--enable-features=Vulkan", "--use-vulkan=swiftshader", "--use-webgpu-adapter=swiftshader"] : []),
];
const browser = await chromium.launch({
  executablePath: process.env.CHROMIUM || "/usr/bin/chromium",
  args: gpuArgs,
});
const errors = [];
const report = { backend };
const readyOf = (tab) => tab.evaluate(() => ({
  ready: Number(document.body.dataset.texelReady ?? 0),
  readyMs: Number(document.body.dataset.texelReadyMs ?? 0),
  // Where the load's time went: ms after navigation of each step, and the frame
  // loop's time decoding, uploading and drawing until ready.
  load: JSON.parse(document.body.dataset.texelLoad ?? "{}"),
  // Frames the page drew since it started.
  frames: Number(document.body.dataset.texelFrames ?? 0),
  // The page's own files: when each came (ms after navigation).
  files: Object.fromEntries([
    ["html", performance.getEntriesByType("navigation")[0]],
    ...performance.getEntriesByType("resource")
      .filter((e) => /\.(js|wasm)$/.test(e.name))
      .map((e) => [e.name.endsWith(".wasm") ? "wasm" : "js", e]),
  ].filter(([, e]) => e).map(([k, e]) => [k, {
    start: e.startTime, responseStart: e.responseStart, end: e.responseEnd, bytes: e.transferSize,
  }])),
  path: document.body.dataset.texelPath ?? "",
  scans: Number(document.body.dataset.texelScans ?? 0),
  drawn: Number(document.body.dataset.texelDrawn ?? 0),
  frameMs: Number(document.body.dataset.texelFrameMs ?? 0),
  bytes: Number(document.body.dataset.texelBytes ?? 0),
  status: document.getElementById("texel-status")?.textContent ?? "",
}));
const waitReady = (tab, timeout) => tab.waitForFunction(
  () => document.body.dataset.texelReady || document.body.dataset.texelError,
  null,
  { timeout, polling: 100 },
);
try {
  const context = await browser.newContext({ viewport: { width, height }, deviceScaleFactor: 1 });
  const tab = await context.newPage();
  tab.on("pageerror", (e) => errors.push(String(e)));
  tab.on("console", (m) => { if (m.type() === "error") errors.push(m.text()); });
  const sep = url.includes("?") ? "&" : "?";
  const pageUrl = backend === "webgl2" ? `${url}${sep}backend=webgl2` : url;

  // First load: fetches and compiles the wasm.
  await tab.goto(pageUrl);
  await waitReady(tab, 240000);
  report.first = await readyOf(tab);
  const error = await tab.evaluate(() => document.body.dataset.texelError ?? null);
  if (error) throw new Error(`the page reported: ${error}`);

  // Second load, the wasm in the browser's cache (the daemon answers its entity tag
  // with 304): the figure a returning user sees. The first page is left and the GPU
  // given time to finish its last frames first, so that this load does not wait for
  // the previous page's work in the GPU process.
  await tab.goto("about:blank");
  await tab.waitForTimeout(3000);
  await tab.goto(pageUrl);
  await waitReady(tab, 240000);
  report.cached = await readyOf(tab);
  // Idle: with the model on screen and nothing touched, the page draws nothing.
  const framesOf = () => tab.evaluate(() => Number(document.body.dataset.texelFrames ?? 0));
  const idleFrom = await framesOf();
  await tab.waitForTimeout(2000);
  report.idleFrames = (await framesOf()) - idleFrom;
  await tab.locator("#texel-panel").evaluate((p) => { p.style.display = "none"; });
  await tab.waitForTimeout(300);
  await tab.locator("#texel-canvas").screenshot({ path: outPng });
  // The hand: a drag orbits, and the address bar follows the view.
  report.beforeDrag = await tab.evaluate(() => location.search);
  const dragFrom = await framesOf();
  await tab.mouse.move(width / 2, height / 2);
  await tab.mouse.down();
  await tab.mouse.move(width / 2 + 80, height / 2 + 20, { steps: 8 });
  await tab.mouse.up();
  await tab.waitForTimeout(800);
  report.afterDrag = await tab.evaluate(() => location.search);
  report.dragFrames = (await framesOf()) - dragFrom;
  // The frame time while the hand keeps moving the view (a paced page draws only
  // then): three seconds of orbiting to and fro.
  await tab.mouse.down();
  for (let until = Date.now() + 3000, dx = 40; Date.now() < until; dx = -dx) {
    await tab.mouse.move(width / 2 + 80 + dx, height / 2 + 20, { steps: 4 });
  }
  await tab.mouse.up();
  await tab.waitForTimeout(600);
  report.steady = await readyOf(tab);

  if (restartWaitMs > 0) {
    // Tell the caller the screenshot is taken and wait for it to restart the daemon
    // (it writes a line to our stdin); then the page must have reconnected by itself
    // and drawn the new daemon's model.
    const connections = await tab.evaluate(() => Number(document.body.dataset.texelReadyConnection ?? 0));
    console.log(JSON.stringify({ screenshot: outPng, connections }));
    const rl = createInterface({ input: process.stdin });
    await new Promise((resolve) => rl.once("line", resolve));
    rl.close();
    await tab.waitForFunction(
      (n) => Number(document.body.dataset.texelReadyConnection ?? 0) > n,
      connections,
      { timeout: restartWaitMs, polling: 100 },
    ).catch((e) => errors.push(`no reconnection: ${e}`));
    report.afterRestart = await readyOf(tab);
    report.afterRestart.connections = await tab.evaluate(() => Number(document.body.dataset.texelConnections ?? 0));
  }
} catch (e) {
  errors.push(String(e));
} finally {
  report.errors = errors;
  console.log(JSON.stringify(report));
  await browser.close();
}
