"""The probe's child process: `python -m clrefract.probe PLATFORM DEVICE PRECISION` builds and
runs the probe at each width on that device and prints one JSON line per width."""

from __future__ import annotations

import json
import sys

from ..runtime import Runtime
from . import WIDTHS, probe_width


def main(argv: list[str]) -> int:
    pi, di, precision = int(argv[0]), int(argv[1]), argv[2]
    rt = Runtime(f"{pi}:{di}", probe_lanes=False)
    for w in WIDTHS:
        rec = probe_width(rt, w, precision)
        print(json.dumps(rec), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
