"""Open a local HTML page in Debian's headless Chromium: did every image load, did the page log errors.

The page is copied beside itself with a small probe script injected at the top of ``<head>``: it records
script errors and failed resource loads (the capture-phase ``error`` event fires for an ``<img>`` that
cannot load) and, once the page has loaded, writes what it found into the DOM, which Chromium prints
with ``--dump-dom``. The console is read too (``--enable-logging=stderr``): any ``CONSOLE`` line at
level ERROR counts. A screenshot of the original page is taken in a second run.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars", "--allow-file-access-from-files"]

PROBE = """<script>
window.__errors = [];
window.addEventListener('error', function (e) {
  var t = e.target && e.target !== window ? (e.target.tagName + ' ' + (e.target.src || e.target.href || '')) : '';
  window.__errors.push(t ? 'failed to load ' + t.slice(0, 200) : String(e.message));
}, true);
(function () { var ce = console.error; console.error = function () {
  window.__errors.push('console.error: ' + Array.prototype.join.call(arguments, ' ')); ce.apply(console, arguments); }; })();
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var bad = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); })
                .map(function (i) { return (i.alt || '') + ' ' + i.src.slice(0, 80); });
  var pre = document.createElement('pre'); pre.id = '__probe';
  pre.textContent = JSON.stringify({images: imgs.length, broken: bad, errors: window.__errors,
                                    links: Array.prototype.map.call(document.querySelectorAll('a[href]'),
                                                                    function (a) { return a.getAttribute('href'); })});
  document.body.appendChild(pre);
});
</script>"""


def available() -> bool:
    return Path(CHROMIUM).is_file()


def check_page(page: Path, profile: Path, screenshot: Path | None = None, width: int = 1280,
               height: int = 3000) -> dict:
    """``{"images": n, "broken": [...], "errors": [...], "links": [...], "console_errors": [...]}``."""
    page = Path(page).resolve()
    probed = page.with_name(page.stem + ".probe.html")
    text = page.read_text(encoding="utf-8")
    probed.write_text(text.replace("<head>", "<head>" + PROBE, 1), encoding="utf-8")
    try:
        r = subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={profile}", "--enable-logging=stderr",
                            "--v=0", "--virtual-time-budget=10000", "--dump-dom", probed.as_uri()],
                           capture_output=True, text=True, timeout=180)
    finally:
        probed.unlink(missing_ok=True)
    m = re.search(r'<pre id="__probe">(.*?)</pre>', r.stdout, re.S)
    if m is None:
        raise AssertionError(f"the page did not finish loading in Chromium (rc {r.returncode}): "
                             f"{r.stderr[-2000:]}")
    import html

    out = json.loads(html.unescape(m.group(1)))
    out["console_errors"] = [line for line in r.stderr.splitlines()
                             if "CONSOLE" in line and ("ERROR" in line or "Uncaught" in line)]
    if screenshot is not None:
        subprocess.run([CHROMIUM, *FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}",
                        f"--screenshot={screenshot}", page.as_uri()], capture_output=True, text=True,
                       timeout=180, check=True)
    return out
