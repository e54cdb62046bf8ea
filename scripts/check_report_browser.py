"""Render a report.html in headless Chromium and save a screenshot.

Usage::

    python scripts/check_report_browser.py [REPORT_HTML] [--out outputs/report_screenshot.png]
                                           [--height 6000]

Without REPORT_HTML the demo's report (``outputs/demo/run-paper/report.html``)
is used. Needs Debian's Chromium (``apt-get install chromium``); the browser
runs with networking off (``--disable-background-networking`` ...), so an
image that shows in the screenshot is really embedded in the file. Exit
code 0 when a non-empty screenshot was written, 2 when Chromium is missing.
Look at the screenshot afterwards: this checks that the page renders, not
that it reads well.
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--hide-scrollbars", "--blink-settings=imagesEnabled=true"]


def find_chromium() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome", "chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


def screenshot(report: Path, out: Path, *, width: int = 1280, height: int = 6000,
               timeout_s: float = 120.0) -> Path:
    """Render ``report`` with headless Chromium into the PNG ``out``."""
    exe = find_chromium()
    if exe is None:
        raise FileNotFoundError("chromium not found; install it with `apt-get install chromium`")
    out.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="chromium-") as profile:
        cmd = [exe, *FLAGS, f"--user-data-dir={profile}", f"--window-size={width},{height}",
               f"--screenshot={out.resolve()}", report.resolve().as_uri()]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    if not out.is_file() or out.stat().st_size == 0:
        raise RuntimeError(f"chromium wrote no screenshot (exit {proc.returncode}): "
                           f"{proc.stderr.strip()[-500:]}")
    return out


#: appended to a copy of the report: writes the page's layout into the DOM
_MEASURE = r"""<script>
addEventListener('load', () => {
  document.querySelectorAll('details').forEach(d => { d.open = true; });  // folded tables too
  const main = document.querySelector('main');
  const right = el => el.getBoundingClientRect().right;
  const scrollBox = t => {  // the nearest ancestor (inside main) that scrolls sideways
    for (let el = t.parentElement; el && el !== main; el = el.parentElement) {
      const o = getComputedStyle(el).overflowX;
      if (o === 'auto' || o === 'scroll') return el;
    }
    return null;
  };
  let cut = 0, scrolling = 0; const what = [];
  for (const t of document.querySelectorAll('table')) {
    const box = scrollBox(t);
    if (box === null) {  // no scroll box: the table must fit its container
      if (right(t) > right(t.parentElement) + 1 || right(t) > right(main) + 1) cut++;
    } else if (right(box) > right(main) + 1) {
      cut++;  // the box itself sticks out
    } else if (box.scrollWidth > box.clientWidth + 1) {
      scrolling++;
      what.push(t.textContent.slice(0, 30).replace(/\s+/g, ' ') + ' (+' + (box.scrollWidth - box.clientWidth) + ' px)');
    }
  }
  const imgs = [...document.querySelectorAll('img')];
  const out = document.createElement('pre');
  out.id = 'layout';
  out.textContent = JSON.stringify({inner: innerWidth,
    page: document.documentElement.scrollWidth, tables: document.querySelectorAll('table').length,
    cut_tables: cut, scrolling_tables: scrolling, scrolling_what: what, images: imgs.length,
    broken_images: imgs.filter(i => !(i.complete && i.naturalWidth > 0)).length});
  document.body.appendChild(out);
});
</script>"""


def layout(report: Path, *, width: int, timeout_s: float = 120.0) -> dict:
    """How the report lays out in a ``width`` px window, every ``<details>``
    unfolded (one Chromium launch).

    Returns a dict: ``inner`` (the window's width [px]), ``page`` (the
    page's scroll width: > inner when something sticks out sideways),
    ``tables``, ``cut_tables`` (tables wider than their container without a
    box that scrolls them sideways, or whose box sticks out of the page's
    column), ``scrolling_tables`` (tables that fit only by scrolling their
    box; ``scrolling_what``: their first words), ``images`` and ``broken_images`` (not decoded: not embedded)."""
    import json
    import re

    exe = find_chromium()
    if exe is None:
        raise FileNotFoundError("chromium not found; install it with `apt-get install chromium`")
    with tempfile.TemporaryDirectory(prefix="chromium-") as profile:
        copy = Path(profile) / "report.html"
        copy.write_text(report.read_text().replace("</body>", _MEASURE + "</body>"))
        cmd = [exe, *FLAGS, f"--user-data-dir={profile}", f"--window-size={width},2000",
               "--virtual-time-budget=5000", "--dump-dom", copy.as_uri()]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
    m = re.search(r"<pre id=\"layout\">(.*?)</pre>", proc.stdout)
    if m is None:
        raise RuntimeError(f"chromium gave no layout (exit {proc.returncode}): "
                           f"{proc.stderr.strip()[-500:]}")
    return json.loads(m.group(1).replace("&quot;", '"'))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("report", nargs="?", type=Path,
                   default=Path("outputs/demo/run-paper/report.html"))
    p.add_argument("--out", type=Path, default=Path("outputs/report_screenshot.png"))
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=6000)
    args = p.parse_args(argv)
    if not args.report.is_file():
        print(f"error: {args.report}: no such report; run `make demo` first", file=sys.stderr)
        return 2
    try:
        path = screenshot(args.report, args.out, width=args.width, height=args.height)
    except FileNotFoundError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"screenshot: {path} ({path.stat().st_size // 1024} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
