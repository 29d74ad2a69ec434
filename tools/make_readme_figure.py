"""The README's picture, docs/img/overview.png: glass objects rendered through curved rays by
clrefract's own OpenCL tracer, beside a slice of the index field eta(x) each was traced
through.

    python tools/make_readme_figure.py [--out docs/img/overview.png] [--res 160]
                                       [--field SPEC ...] [--device P:D]

Each --field is a `clrefract render --field` spec: an analytic field, or a fitted run's
field.npz. The default, a smoothed glass sphere and a water drop in the procedural HDR
environment, takes well under a minute on 2 CPU cores with PoCL.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from clrefract.cameras import orbit_cameras  # noqa: E402
from clrefract.envmap import EnvMap  # noqa: E402
from clrefract.fields import Box, field_from_spec  # noqa: E402
from clrefract.imageio import linear_to_srgb  # noqa: E402
from clrefract.render import render_camera  # noqa: E402
from clrefract.runtime import Runtime  # noqa: E402
from clrefract.tracer import Tracer, TraceSettings  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
FIELDS = ("sphere:radius=20,eta=1.5,width=1", "drop")
TITLES = {"sphere": "glass sphere, n = 1.5", "drop": "water drop, n = 1.33"}


def view_and_slice(spec: str, res: int, envmap: EnvMap, runtime: Runtime):
    """(sRGB image, eta on the y = 0 plane, the plane's extent in mm) of one field."""
    box = Box()
    field = field_from_spec(spec, box)
    box = field.tracing_box(box)
    settings = TraceSettings(step=field.suggested_step, precision="float32")
    tracer = Tracer(field, box, settings, runtime=runtime)
    cam = orbit_cameras(1, radius=120.0, elevation_deg=15.0, width=res, height=res)[0]
    image = render_camera(tracer, cam, envmap).image
    half = 30.0
    u = np.linspace(-half, half, 241)
    x, z = np.meshgrid(u, u[::-1])
    pts = np.stack([x.ravel(), np.zeros(x.size), z.ravel()], axis=1)
    eta, _ = field.eval(pts)
    return linear_to_srgb(image), eta.reshape(x.shape), (-half, half, -half, half)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default=str(ROOT / "docs" / "img" / "overview.png"))
    ap.add_argument("--res", type=int, default=160, help="rendered image size, pixels")
    ap.add_argument("--field", nargs="+", default=list(FIELDS), help="field specs")
    ap.add_argument("--device", default=None, help="OpenCL device, as for clrefract render")
    args = ap.parse_args(argv)

    runtime = Runtime(args.device)
    envmap = EnvMap.procedural(seed=0)
    n = len(args.field)
    fig, axes = plt.subplots(
        1, 2 * n, figsize=(3.1 * 2 * n, 3.4), gridspec_kw={"wspace": 0.35}, squeeze=False
    )
    for k, spec in enumerate(args.field):
        image, eta, extent = view_and_slice(spec, args.res, envmap, runtime)
        name = spec.split(":")[0]
        ax = axes[0, 2 * k]
        ax.imshow(np.clip(image, 0, 1))
        ax.set_title(f"{TITLES.get(name, Path(name).stem)}: render", fontsize=9)
        ax.axis("off")
        ax = axes[0, 2 * k + 1]
        im = ax.imshow(eta, extent=extent, cmap="viridis", vmin=1.0)
        ax.set_title("eta(x), slice y = 0", fontsize=9)
        ax.set_xlabel("x (mm)", fontsize=8)
        ax.set_ylabel("z (mm)", fontsize=8)
        ax.tick_params(labelsize=7)
        cb = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.03)
        cb.ax.tick_params(labelsize=7)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80, bbox_inches="tight")
    print(f"wrote {out}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
