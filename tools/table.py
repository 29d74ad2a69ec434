"""Table 1 of the paper, measured: every method on every scene under a named protocol.

    python tools/table.py run --protocol tiny --out table/tiny [--shard 0/2]
        [--scenes sphere,prism,drop] [--methods grid,meridian,synapse,vertexnet] [--data DIR]
    python tools/table.py merge table/tiny-a table/tiny-b --out table/tiny

`run` writes shard-i-of-n.json (one record per run) and, for the whole protocol (no --shard),
table.md, table.csv and table.json; `merge` joins the shards' records into the table.
Protocols (clrefract.table.PROTOCOLS): tiny (smoke test), quick (128 x 128), standard
(256 x 256), full (the paper's 800 x 800, for GPUs).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from clrefract import shards
from clrefract.errors import ClrefractError
from clrefract.table import PROTOCOLS, SCENES, merge, run_protocol, write_table


def main(argv=None) -> int:
    from clrefract.baselines.methods import METHODS

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("run", help="run a protocol (or one shard of it)")
    p.add_argument("--protocol", required=True, choices=list(PROTOCOLS))
    p.add_argument("--out", required=True, help="folder for runs, shard records and the table")
    p.add_argument("--shard", default="", help="i/n, 0 <= i < n: every n-th run from the i-th")
    p.add_argument("--scenes", default=",".join(SCENES))
    p.add_argument("--methods", default=",".join(METHODS))
    p.add_argument("--data", help="dataset folder root (default OUT/data)")
    p = sub.add_parser("merge", help="join shard records into the table")
    p.add_argument("folders", nargs="+", help="folders holding shard-*-of-*.json")
    p.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    try:
        if args.cmd == "run":
            shard = args.shard
            out = Path(args.out)
            records = run_protocol(
                args.protocol,
                out,
                shard,
                scenes=[s for s in args.scenes.split(",") if s],
                methods=[m for m in args.methods.split(",") if m],
                data_root=Path(args.data) if args.data else None,
            )
            if shards.parse(shard)[1] == 1 and records:
                write_table(records, out)
                print((out / "table.md").read_text())
        else:
            records = merge([Path(f) for f in args.folders])
            write_table(records, Path(args.out))
            print((Path(args.out) / "table.md").read_text())
    except ClrefractError as exc:
        print(f"table: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
