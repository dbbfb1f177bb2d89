"""The dashboard's formatting of sizes, run in Node: the very function in ``api/static/app.js`` that the browser
runs, without a browser (``test_dashboard.py`` checks the page itself where Chromium is installed)."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import pytest

APP = Path(__file__).resolve().parents[1] / "api" / "static" / "app.js"
NODE = shutil.which("node") or shutil.which("nodejs")


def js_function(name: str) -> str:
    """The source of top-level ``function name(…) {…}`` in app.js (its body ends at the first ``}`` in column 0)."""
    found = re.search(rf"^function {name}\(.*?^\}}$", APP.read_text(), re.S | re.M)
    assert found, f"app.js has no function {name}"
    return found.group(0)


@pytest.mark.skipif(NODE is None, reason="needs node (apt-get install nodejs)")
def test_checkpoint_sizes_read_as_people_write_them() -> None:
    """A checkpoint's download link read "best.pt (1.32M B)": a count's "M" glued to a byte unit. Sizes now read
    "1.3 MB", "842 kB", "512 B"."""
    sizes = [0, 512, 999, 1000, 842_300, 999_999, 1_320_000, 15_400_000, 2_500_000_000]
    script = f"{js_function('fmtBytes')}\nconsole.log(JSON.stringify({json.dumps(sizes)}.map(fmtBytes)));"
    assert NODE is not None
    shown = json.loads(
        subprocess.run([NODE, "-e", script], capture_output=True, text=True, check=True, timeout=60).stdout
    )
    assert shown == ["0 B", "512 B", "999 B", "1.0 kB", "842 kB", "1.0 MB", "1.3 MB", "15 MB", "2.5 GB"]
    link = re.search(r"a\.textContent = `\$\{c\.name\} \((.*?)\)`", APP.read_text())
    assert link and link.group(1) == "${fmtBytes(c.bytes)}", "the download links show sizes with fmtBytes"
