"""The speed/accuracy trade study (issue 12): `clrefract bench` under its old name.

    python tools/bench_tradeoff.py [--quick] [--rays 2048] [--out bench_results/tradeoff]

The study lives in clrefract/tradeoff.py; this writes tradeoff.md, tradeoff.json and
tradeoff.png into --out (a folder) as the command does.
"""

import sys

from clrefract.cli import main

if __name__ == "__main__":
    sys.exit(main(["bench", *sys.argv[1:]]))
