// The web page with a faired mesh drawn, as a PNG (run by scripts/screenshot-web.sh, which
// starts the server and sets WILLOW_URL). Arguments: the mesh to submit, the PNG to write.
// Reuses the browser tests' launch (Debian's chromium, software WebGL, a fresh profile).
import { launch, waitStats, watchedPage } from '../../tests/browser/support.mjs';

const [mesh, out] = process.argv.slice(2);
const base = process.env.WILLOW_URL;
if (!mesh || !out || !base) {
  console.error('usage: WILLOW_URL=http://127.0.0.1:PORT node web-page.mjs MESH OUT.png');
  process.exit(2);
}

const browser = await launch();
try {
  const { page, problems } = await watchedPage(browser.context, base);
  await page.setViewportSize({ width: 1200, height: 750 });
  await page.goto(base + '/');
  await page.setInputFiles('#files', [mesh]);
  // The defaults come from the server before the form is used; the input is drawn at once.
  await page.waitForFunction(() => document.querySelector('select[name=method]').options.length > 0);
  await page.waitForFunction(() => !document.getElementById('submit').disabled);
  await page.click('#submit');
  await page.waitForFunction(() => /^#job=/.test(location.hash));
  const s = await waitStats(page, () => window.willowStats.state === 'succeeded'
    && window.willowStats.framesApplied >= 1, undefined, 300_000);
  // The page from its top (the click scrolled to the form's end), the mean-curvature colours
  // (the creases the filter kept stand out), the model turned a little by a drag on the view
  // (the orbit control) so it is not seen straight on; then let the last frame and the plots
  // be drawn before the picture is taken.
  await page.evaluate(() => window.scrollTo(0, 0));
  await page.selectOption('#colour', 'curvature');
  const box = await page.locator('#canvas').boundingBox();
  const [cx, cy] = [box.x + box.width / 2, box.y + box.height / 2];
  await page.mouse.move(cx, cy);
  await page.mouse.down();
  await page.mouse.move(cx - 90, cy + 70, { steps: 12 });
  await page.mouse.up();
  await page.waitForTimeout(1500);
  await page.screenshot({ path: out });
  console.log(`web-page.mjs: ${s.framesApplied} frames applied, last step ${s.lastStep}, ${s.triangleCount} triangles`);
  if (problems.length) {
    console.error(problems.join('\n'));
    process.exitCode = 1;
  }
} finally {
  await browser.close();
}
