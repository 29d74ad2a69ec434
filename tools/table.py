"""Table 1 of the paper, measured: every method on every scene under a named protocol.
The same as `clrefract table`:

    python tools/table.py run --protocol tiny --out table/tiny [--shard 0/2]
        [--scenes sphere,prism,drop] [--methods grid,meridian,synapse,vertexnet,interface]
        [--data DIR] [--page docs/results.md]
    python tools/table.py merge table/tiny-a table/tiny-b --out table/tiny [--page PAGE]
    python tools/table.py page docs/results.json --out docs/results.md

`run` writes shard-i-of-n.json (one record per run) and, for the whole protocol (no --shard),
table.md, table.csv and table.json; `merge` joins the shards' records into the table; `--page`
also writes the results page (docs/results.md) and its records beside it, which `page` renders
again without running anything.
Protocols (clrefract.table.PROTOCOLS): tiny (smoke test), quick (128 x 128), standard
(256 x 256), full (the paper's 800 x 800, for GPUs).
"""

from __future__ import annotations

import sys

from clrefract.cli import main

if __name__ == "__main__":
    sys.exit(main(["table", *sys.argv[1:]]))
