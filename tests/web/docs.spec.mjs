// The OpenAPI page (/docs, Swagger UI) in headless Chromium, against a running pranet-serve, with every request
// to another host than the service's aborted (as on a machine without internet): the page must still render
// the POST /register operation from the service's own assets, and must not even try to reach another host.
//
// Environment: PRANET_DOCS_URL (required: the service's base URL), PRANET_DOCS_API_KEY (sent with every
// request when the service needs one), PRANET_DOCS_SCREENSHOT (optional), CHROMIUM (default /usr/bin/chromium).
// Prints one JSON line; exit 1 on failure.
import { mkdirSync } from "node:fs";
import { dirname } from "node:path";
import { chromium } from "playwright-core";

const env = process.env;
const base = env.PRANET_DOCS_URL;
const TIMEOUT_MS = 60000;
const ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
  "--disable-background-networking", "--disable-component-update", "--disable-sync"];

function fail(message, extra = {}) {
  console.log(JSON.stringify({ ok: false, error: message, ...extra }));
  process.exit(1);
}

if (!base) fail("set PRANET_DOCS_URL");
const serviceOrigin = new URL(base).origin;

const browser = await chromium.launch({ executablePath: env.CHROMIUM || "/usr/bin/chromium", args: ARGS });
const blocked = [];
const consoleErrors = [];
try {
  const context = await browser.newContext({ viewport: { width: 1280, height: 900 } });
  if (env.PRANET_DOCS_API_KEY) await context.setExtraHTTPHeaders({ Authorization: `Bearer ${env.PRANET_DOCS_API_KEY}` });
  // Offline: only the service itself answers; anything else fails as it would without a network.
  await context.route("**/*", (route) => {
    const url = route.request().url();
    if (url.startsWith("data:") || new URL(url).origin === serviceOrigin) return route.continue();
    blocked.push(url);
    return route.abort("internetdisconnected");
  });
  const page = await context.newPage();
  page.on("console", (m) => {
    if (m.type() === "error") consoleErrors.push(m.text());
  });
  page.on("pageerror", (e) => consoleErrors.push(`page error: ${e.message}`));
  const answer = await page.goto(`${base}/docs`);
  if (!answer || answer.status() !== 200) fail(`GET /docs answered ${answer && answer.status()}`);

  const register = page.locator(".opblock.opblock-post .opblock-summary-path", { hasText: /^\/register$/ });
  let rendered = true;
  try {
    await register.first().waitFor({ state: "visible", timeout: TIMEOUT_MS });
  } catch {
    rendered = false;
  }
  const shown = await page.evaluate(() => ({
    title: document.querySelector(".swagger-ui .info .title")?.textContent || null,
    operations: [...document.querySelectorAll(".opblock-summary-path")].map((e) => e.textContent.trim()),
  }));
  if (env.PRANET_DOCS_SCREENSHOT) {
    mkdirSync(dirname(env.PRANET_DOCS_SCREENSHOT), { recursive: true });
    await page.screenshot({ path: env.PRANET_DOCS_SCREENSHOT });
  }
  const problems = [];
  if (!rendered) problems.push("Swagger UI did not render POST /register");
  if (blocked.length) problems.push(`requests to other hosts: ${blocked.join(" ")}`);
  if (consoleErrors.length) problems.push(`console errors: ${consoleErrors.join(" | ")}`);
  const report = { ok: problems.length === 0, problems, ...shown, blocked, consoleErrors };
  console.log(JSON.stringify(report));
  process.exitCode = report.ok ? 0 : 1;
} catch (e) {
  console.log(JSON.stringify({ ok: false, error: String(e && e.stack ? e.stack : e), blocked, consoleErrors }));
  process.exitCode = 1;
} finally {
  await browser.close();
}
