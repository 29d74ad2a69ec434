"""Does a hollow object's start want its lid off? The hull's shells, closed and opened.

    python tools/diag_open_shell.py [--scene bowl] [--data bench_results/data]
        [--etas 1.3,1.35,1.4,1.45,1.5] [--json bench_results/diag_open_shell.json]

No silhouette shows a bowl's hollow, so the start's shell of the visual hull keeps a lid
over the opening. On a family solid's quick-protocol dataset (128 x 128, 100 views; made in
DATA if missing) and the level-set start's 64^3 grid of the object's box, this prints the
start search's loss (its fixed batch of mask rays) at each index for: the whole hull; its
shells 2, 4 and 6 cells deep (`Hull.hollowed`, what the start tries); and each shell opened
along each of 26 directions (to a cube's faces, edges and corners: the hollow carried out
of the box that way, removing the shell beyond it), and on the bowl along its true opening.
Beside them: the empty box, the truth on the same grid, and the truth with the closed
shell's lid added.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from clrefract.fit_start import START_BATCH

SHELL_CELLS = (2, 4, 6)


def opened(hull, depth: float, direction, spacing) -> object:
    """The hull's shell `depth` mm deep with its hollow carried out of the box along
    `direction` (world axes; `spacing`: the grid's mm per node on each axis): a node is
    hollow where any node behind it along the direction is inside the hollow (a running
    maximum of the hollow's signed distance, sampled every half node)."""
    from scipy import ndimage

    from clrefract.hull import Hull

    hollow = hull.distance - depth
    u = np.asarray(direction, float) / np.asarray(spacing, float)
    u /= np.linalg.norm(u)
    n = max(hollow.shape)
    out = hollow.copy()
    for s in np.arange(0.5, 2 * n, 0.5):
        moved = ndimage.shift(hollow, s * u, order=1, mode="constant", cval=-np.inf)
        if not np.isfinite(moved).any():
            break
        np.maximum(out, moved, out=out)
    return Hull(np.minimum(hull.distance, -out), hull.width, hull.mask_fraction, hull.rejected)


def directions() -> dict:
    """The 26 directions to a cube's faces, edges and corners."""
    out = {}
    for d in np.ndindex(3, 3, 3):
        v = np.array(d) - 1
        if v.any():
            out["".join("-0+"[c + 1] for c in v)] = v / np.linalg.norm(v)
    return out


def main() -> None:
    from diag_shape_gradient import levelset_fit, set_params, true_levelset

    from clrefract.report import scene_truth

    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scene", default="bowl")
    ap.add_argument("--data", default="bench_results/data")
    ap.add_argument("--etas", default="1.3,1.35,1.4,1.45,1.5")
    ap.add_argument("--json", default="bench_results/diag_open_shell.json")
    args = ap.parse_args()
    etas = [float(e) for e in args.etas.split(",")]
    t0 = time.perf_counter()
    fit = levelset_fit(args.scene, args.data, "diag_open_shell_run")
    fit._bind(fit._make_field(fit.start_grid()))  # the start's own grid, without its search
    hull = fit._hull(64)
    idx = fit._mask_batch(START_BATCH)

    def loss(shape, eta: float) -> float:
        fit._set_start(shape, eta, 0.0)
        return fit._forward_loss(idx)

    dirs = directions()
    spacing = fit.box.size / (np.asarray(hull.distance.shape) - 1)
    truth = scene_truth(fit.ds)
    if getattr(truth, "kind", "") == "bowl":  # its opening: local +z turned by the tilt
        from clrefract.fields.analytic import rotation_xyz

        dirs["truth's opening"] = rotation_xyz(truth.tilt)[:, 2]
    shapes = {"hull": hull}
    for cells in SHELL_CELLS:
        shapes[f"shell {cells}"] = hull.hollowed(cells * hull.width)
        for tag, u in dirs.items():
            shapes[f"shell {cells} open {tag}"] = opened(hull, cells * hull.width, u, spacing)
    out = {"scene": args.scene, "etas": etas, "empty": loss(hull, 1.0), "losses": {}}
    print(f"{'shape':18s}" + "".join(f"{e:>9.3f}" for e in etas) + "      min")
    for name, shape in shapes.items():
        row = [loss(shape, e) for e in etas]
        out["losses"][name] = row
        print(f"{name:18s}" + "".join(f"{v:9.5f}" for v in row) + f"{min(row):9.5f}")
    phi = true_levelset(fit, truth).reshape(hull.distance.shape)
    set_params(fit, phi.ravel(), truth.eta)
    out["truth"] = fit._forward_loss(idx)
    out["truth with lid"] = {}
    for cells in SHELL_CELLS:  # the lid: the closed shell less the best-opened one
        name = min(
            (k for k in out["losses"] if k.startswith(f"shell {cells} open")),
            key=lambda k: min(out["losses"][k]),
        )
        lid = np.minimum(shapes[f"shell {cells}"].distance, -shapes[name].distance)
        band = 8 * hull.width
        set_params(fit, np.clip(np.minimum(phi, -lid), -band, band).ravel(), truth.eta)
        out["truth with lid"][f"shell {cells}, {name}"] = fit._forward_loss(idx)
    out["seconds"] = time.perf_counter() - t0
    print(
        f"empty box {out['empty']:.5f}; truth on the grid (eta {truth.eta:g}) "
        f"{out['truth']:.5f}; {out['seconds']:.0f} s"
    )
    for name, v in out["truth with lid"].items():
        print(f"the truth with the lid of {name} added: {v:.5f}")
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
