"""Screenshot a specgpu HTML report in a real browser (headless Chromium) and check its layout.

    PYTHONPATH=. python tools/maintenance/screenshot_report.py specgpu-report/index.html --widths 1000 1400 --out shots/

For each width: a screenshot of the page's top (``report-<width>.png``, the window ``--height`` px high), and a
layout check in the same browser: the page must not scroll sideways, and no table, image, figure or text block
may reach past the page's right edge (a table wider than its column scrolls inside its own box, which the check
reports too, as a table wider than the page). Prints one line per width and exits 1 when any check fails.

Chromium comes from the distribution's packages (Debian: ``apt-get install chromium``); ``--browser`` names
another binary. The report is copied to a temporary file with a small script appended that measures the laid out
page and writes the result into the DOM, which ``--dump-dom`` prints; the report itself is not changed.
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")

#: Measures the laid-out page once everything (the embedded images included) has loaded.
CHECK_SCRIPT = """
<script>
window.addEventListener('load', function () {
  var page = document.documentElement.clientWidth, bad = [];
  document.querySelectorAll('table, img, figure, pre, p, h1, h2, h3, ul, .grid, .table-wrap, .summary')
    .forEach(function (el) {
      var r = el.getBoundingClientRect();
      if (r.right > page + 0.5 || r.width > page + 0.5) {
        bad.push({tag: el.tagName.toLowerCase(), cls: el.className || '', width: Math.round(r.width),
                  right: Math.round(r.right), text: (el.textContent || el.alt || '').slice(0, 60)});
      }
    });
  var out = document.createElement('pre');
  out.id = 'specgpu-layout';
  out.textContent = JSON.stringify({page: page, scroll: document.documentElement.scrollWidth,
                                    tables: document.querySelectorAll('table').length,
                                    images: document.querySelectorAll('img').length, overflow: bad});
  document.body.appendChild(out);
});
</script>
"""


def find_browser(name=None) -> str:
    """The Chromium binary: ``name`` or the first of :data:`BROWSERS` on the PATH."""
    for candidate in ([name] if name else BROWSERS):
        path = shutil.which(candidate)
        if path:
            return path
    raise SystemExit(f"no Chromium found ({', '.join([name] if name else BROWSERS)}); install the distribution's "
                     "package (Debian: apt-get install chromium) or give --browser")


def _chromium(browser, width, height, *args, timeout=120) -> subprocess.CompletedProcess:
    cmd = [browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--no-first-run",
           "--disable-extensions", "--disable-background-networking", f"--window-size={width},{height}",
           "--virtual-time-budget=10000", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def layout(browser, report: Path, width: int, height: int) -> dict:
    """The measured layout of ``report`` at ``width`` px (see :data:`CHECK_SCRIPT`)."""
    text = report.read_text()
    with tempfile.TemporaryDirectory() as tmp:
        probe = Path(tmp) / report.name
        probe.write_text(text.replace("</body>", CHECK_SCRIPT + "</body>") if "</body>" in text
                         else text + CHECK_SCRIPT)
        done = _chromium(browser, width, height, "--dump-dom", probe.as_uri())
    found = re.search(r"<pre id=\"specgpu-layout\">(.*?)</pre>", done.stdout, re.S)
    if not found:
        raise SystemExit(f"{report}: Chromium did not lay out the page at {width} px "
                         f"({(done.stderr.strip().splitlines() or ['no output'])[-1]})")
    return json.loads(found.group(1).replace("&quot;", '"').replace("&amp;", "&").replace("&lt;", "<")
                      .replace("&gt;", ">"))


def screenshot(browser, report: Path, width: int, height: int, out: Path) -> Path:
    """A screenshot of the top ``height`` px of ``report`` at ``width`` px."""
    done = _chromium(browser, width, height, f"--screenshot={out}", report.resolve().as_uri())
    if not out.is_file():
        raise SystemExit(f"{report}: no screenshot at {width} px ({done.stderr.strip()[-300:]})")
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("report", type=Path, help="The report (index.html of specgpu demo, or specgpu report's).")
    parser.add_argument("--widths", type=int, nargs="+", default=[1000, 1400])
    parser.add_argument("--height", type=int, default=1400, help="Window height (px) of the screenshots.")
    parser.add_argument("--out", type=Path, default=Path("."), help="Folder of the screenshots.")
    parser.add_argument("--browser", default=None, help="Chromium binary [default: found on the PATH].")
    args = parser.parse_args(argv)
    if not args.report.is_file():
        parser.error(f"{args.report}: no such file")
    browser = find_browser(args.browser)
    args.out.mkdir(parents=True, exist_ok=True)
    failed = False
    for width in args.widths:
        shot = screenshot(browser, args.report, width, args.height, args.out / f"report-{width}.png")
        m = layout(browser, args.report, width, args.height)
        ok = m["scroll"] <= m["page"] and not m["overflow"]
        failed |= not ok
        print(f"{width} px: page {m['page']} px, content {m['scroll']} px wide, {m['tables']} tables, "
              f"{m['images']} images, {len(m['overflow'])} elements past the edge: {'ok' if ok else 'FAIL'}; "
              f"screenshot {shot}")
        for el in m["overflow"][:10]:
            print(f"    {el['tag']}.{el['cls']} {el['width']} px wide, right edge {el['right']} px: {el['text']!r}")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
