// The viewer in headless Chromium, against a running pranet-serve: open /, load two clouds through the
// file inputs, register (with the API key when one is given: first without it, expecting the prompt),
// wait for the animation to end, check what the page shows against the service's answer, screenshot.
//
// Environment: PRANET_VIEWER_URL (required), PRANET_VIEWER_SOURCE / _TARGET (cloud files, required),
// PRANET_VIEWER_API_KEY, PRANET_VIEWER_STEPS (e.g. "0,2"), PRANET_VIEWER_SCREENSHOT (default
// tests/web/out/viewer.png), CHROMIUM (default /usr/bin/chromium). Prints one JSON line; exit 1 on failure.
import { mkdirSync } from "node:fs";
import { dirname } from "node:path";
import { chromium } from "playwright-core";

const env = process.env;
const url = env.PRANET_VIEWER_URL;
const screenshot = env.PRANET_VIEWER_SCREENSHOT || "tests/web/out/viewer.png";
const key = env.PRANET_VIEWER_API_KEY || "";
const TIMEOUT_MS = 120000;
const ARGS = [
  "--headless",
  "--no-sandbox",
  "--disable-gpu",
  "--disable-quic",
  "--no-first-run",
  "--disable-background-networking",
  "--disable-component-update",
  "--disable-sync",
  // WebGL without a GPU: SwiftShader (recent Chromium wants it asked for explicitly)
  "--use-angle=swiftshader",
  "--enable-unsafe-swiftshader",
];

function fail(message, extra = {}) {
  console.log(JSON.stringify({ ok: false, error: message, ...extra }));
  process.exit(1);
}

if (!url || !env.PRANET_VIEWER_SOURCE || !env.PRANET_VIEWER_TARGET) {
  fail("set PRANET_VIEWER_URL, PRANET_VIEWER_SOURCE and PRANET_VIEWER_TARGET");
}

const browser = await chromium.launch({ executablePath: env.CHROMIUM || "/usr/bin/chromium", args: ARGS });
const consoleErrors = [];
const expectedErrors = [];
try {
  const page = await browser.newPage({ viewport: { width: 1280, height: 800 } });
  page.on("console", (m) => {
    if (m.type() === "error") consoleErrors.push(m.text());
  });
  page.on("pageerror", (e) => consoleErrors.push(`page error: ${e.message}`));
  const index = await page.goto(`${url}/`);
  if (!index || index.status() !== 200) fail(`GET / answered ${index && index.status()}`);

  await page.setInputFiles("#file-source", env.PRANET_VIEWER_SOURCE);
  await page.setInputFiles("#file-target", env.PRANET_VIEWER_TARGET);
  await page.waitForFunction(() => window.pranetViewer.source && window.pranetViewer.target, null, { timeout: 10000 });
  const loaded = await page.evaluate(() => [window.pranetViewer.source.n, window.pranetViewer.target.n]);
  if (env.PRANET_VIEWER_STEPS) await page.fill("#opt-steps", env.PRANET_VIEWER_STEPS);

  if (key) {
    // Without the key: the page must ask for it (the browser logs the 401 as a console error: expected).
    await page.click("#register");
    await page.waitForFunction(() => /API key/.test(document.getElementById("message").textContent), null, {
      timeout: TIMEOUT_MS,
    });
    expectedErrors.push(/status of 401/);
    await page.fill("#api-key", key);
  }
  const answer = page.waitForResponse((r) => r.url().endsWith("/register") && r.status() === 200, {
    timeout: TIMEOUT_MS,
  });
  await page.click("#register");
  const body = await (await answer).json();
  await page.waitForSelector("#result:not([hidden])", { timeout: TIMEOUT_MS });
  // The animation runs to its last frame (the final transform) and stops.
  await page.waitForFunction(
    () => {
      const s = window.pranetViewer;
      return s.frames.length > 0 && s.frame === s.frames.length - 1 && s.timer === null;
    },
    null,
    { timeout: TIMEOUT_MS },
  );
  const shown = await page.evaluate(() => ({
    result: document.getElementById("result").innerText,
    transform: document.getElementById("transform").textContent,
    confidence: document.getElementById("confidence").textContent,
    badge: document.getElementById("status-badge").textContent,
    frameLabel: document.getElementById("frame-label").textContent,
    frames: window.pranetViewer.frames.length,
    canvas: !!document.querySelector("#canvas-host canvas"),
    webglNotice: document.querySelector("#view .notice")?.textContent || null,
  }));
  mkdirSync(dirname(screenshot), { recursive: true });
  await page.screenshot({ path: screenshot });

  const problems = [];
  const matrix = shown.transform.trim().split("\n").map((row) => row.trim().split(/\s+/).map(Number));
  const maxDiff = Math.max(...body.transform.flatMap((row, i) => row.map((x, j) => Math.abs(x - matrix[i][j]))));
  if (!(maxDiff < 1e-5)) problems.push(`shown transform differs from the answer by ${maxDiff}`);
  if (!shown.confidence.startsWith(body.confidence.toFixed(3))) problems.push(`confidence shown: ${shown.confidence}`);
  if (shown.badge !== body.status) problems.push(`status shown: ${shown.badge}, answered ${body.status}`);
  if (!/T_target_source/.test(shown.result)) problems.push("no T_target_source heading");
  if (shown.frames !== body.trajectory.length + 2) problems.push(`${shown.frames} frames for ${body.trajectory.length} steps`);
  if (!shown.canvas) problems.push(`no WebGL canvas: ${shown.webglNotice}`);
  const unexpected = consoleErrors.filter((e) => !expectedErrors.some((re) => re.test(e)));
  if (unexpected.length) problems.push(`console errors: ${unexpected.join(" | ")}`);
  const report = {
    ok: problems.length === 0,
    problems,
    loaded,
    status: body.status,
    confidence: body.confidence,
    frames: shown.frames,
    frameLabel: shown.frameLabel,
    consoleErrors,
    screenshot,
  };
  console.log(JSON.stringify(report));
  process.exitCode = report.ok ? 0 : 1;
} catch (e) {
  console.log(JSON.stringify({ ok: false, error: String(e && e.stack ? e.stack : e), consoleErrors }));
  process.exitCode = 1;
} finally {
  await browser.close();
}
