"""Make the README's picture from a demo run: the processed pairs' contact sheet of the studio scene ``demo01``.

Usage::

    python -m dp5k_cli demo --out /tmp/demo-small --scale small
    python scripts/readme_image.py /tmp/demo-small [--out docs/images/demo01-contact.png]

Takes ``DEMO/report-figures/contact_demo01.png`` (per camera: sharp | left | right | depth | CoC, what
``dp5k process`` wrote for the scene) and stores it with a 192-colour palette, so that it stays well under
150 kB.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from PIL import Image

ROOT = Path(__file__).resolve().parents[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("demo", type=Path, help="a finished `dp5k demo --out DEMO`")
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "images" / "demo01-contact.png")
    a = ap.parse_args(argv)
    src = a.demo / "report-figures" / "contact_demo01.png"
    if not src.is_file():
        print(f"readme_image: {src} not found: run `python -m dp5k_cli demo --out {a.demo} --scale small` first",
              file=sys.stderr)
        return 3
    img = Image.open(src).convert("RGB").quantize(colors=192, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    img.save(a.out, optimize=True)
    print(f"wrote {a.out} ({a.out.stat().st_size / 1024:.0f} kB)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
