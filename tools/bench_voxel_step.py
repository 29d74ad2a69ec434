"""The voxel fit's default step: the truth sampled on the fit's grid, rendered at a fixed
1 mm step and at fractions of a cell, scored against the dataset's test views (PSNR), with
the time and the steps it takes. What the fit's step costs in accuracy at its best field.

    python tools/bench_voxel_step.py [--scenes luneburg,plume,sphere] [--res 16,32,64,96,128]
        [--views 10 --pixels 64] [--json bench_results/voxel_step.json]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from clrefract.dataset import Dataset
from clrefract.fields import field_from_dict
from clrefract.fields.voxel import VoxelGrid
from clrefract.metrics import psnr_ssim
from clrefract.render import render_camera
from clrefract.synth import MakeOptions, make_dataset
from clrefract.tracer import Tracer, TraceSettings


def score(tracer, ds, env, fine=None):
    """Mean PSNR over the test views against the dataset and against `fine` (renders of the
    same grid at a fine step: the integration error alone), seconds, steps per ray, and the
    renders."""
    psnrs, own, images, steps, rays = [], [], [], 0, 0
    t0 = time.perf_counter()
    for cam in ds.test:
        r = render_camera(tracer, cam, env)
        images.append(r.image)
        steps += r.steps
        rays += cam.width * cam.height
    secs = time.perf_counter() - t0
    for k, cam in enumerate(ds.test):
        psnrs.append(psnr_ssim(images[k], ds.image(cam))[0])
        if fine is not None:
            own.append(min(psnr_ssim(images[k], fine[k])[0], 99.0))
    own_psnr = float(np.mean(own)) if own else float("nan")
    return float(np.mean(psnrs)), own_psnr, secs, steps / rays, images


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="luneburg,plume,sphere")
    ap.add_argument("--res", default="16,32,64,96,128")
    ap.add_argument("--views", type=int, default=10)
    ap.add_argument("--pixels", type=int, default=64)
    ap.add_argument("--precision", default="float32")
    ap.add_argument("--json", default="bench_results/voxel_step.json")
    args = ap.parse_args()
    rows = []
    tmp = Path(tempfile.mkdtemp(prefix="voxel_step_"))
    for scene in args.scenes.split(","):
        opt = MakeOptions(views=args.views, res=args.pixels, env_width=512, volume_res=16)
        make_dataset(scene, tmp / scene, opt, stream=open("/dev/null", "w"))  # noqa: SIM115
        ds = Dataset(tmp / scene)
        env = ds.envmap()
        truth = field_from_dict(ds.scene.object)
        for res in (int(r) for r in args.res.split(",")):
            vox = VoxelGrid.from_field(truth, box=ds.box, res=res, interp="bspline")
            cell = float(vox.spacing.min())
            ref = Tracer(vox, ds.box, TraceSettings(step=min(cell / 16, 0.1), precision="float64"))
            fine = score(ref, ds, env)[4]
            steps = {"1 mm": 1.0, "cell": cell, "cell/2": cell / 2, "cell/4": cell / 4}
            for name, step in steps.items():
                tr = Tracer(vox, ds.box, TraceSettings(step=step, precision=args.precision))
                render_camera(tr, ds.test[0], env)  # warm-up: the build
                psnr, own, secs, per_ray, _ = score(tr, ds, env, fine)
                row = dict(
                    scene=scene,
                    res=res,
                    cell_mm=cell,
                    rule=name,
                    step_mm=step,
                    psnr=psnr,
                    psnr_vs_fine_step=own,
                    seconds=secs,
                    steps_per_ray=per_ray,
                )
                rows.append(row)
                print(
                    f"{scene:9s} res {res:3d} (cell {cell:5.2f} mm)  {name:7s} step "
                    f"{step:5.3f} mm  PSNR {psnr:6.2f} dB (fine step {own:5.1f})  {secs:6.2f} s  "
                    f"{per_ray:6.1f} "
                    "steps/ray",
                    flush=True,
                )
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(rows, indent=1))
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
