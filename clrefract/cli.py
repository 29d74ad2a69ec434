"""Command line: `clrefract devices`, `clrefract render`."""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from .errors import ClrefractError


def _add_engine_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("engine")
    g.add_argument("--device", default=None,
                   help="OpenCL device: 'P:D' index, a name substring (default: PYOPENCL_CTX, "
                        "else the first GPU, else a CPU)")
    g.add_argument("--step", type=float, default=0.5,
                   help="integrator step in mm of optical path (default 0.5)")
    g.add_argument("--integrator", default="rkn4", choices=["rkn4", "rk4", "euler"])
    g.add_argument("--precision", default="float32", choices=["float32", "float64"])
    g.add_argument("--lanes", type=int, default=None,
                   help="rays per work-item (default: 16 on CPUs, 1 on GPUs)")
    g.add_argument("--max-steps", type=int, default=None, help="step cap per ray")


def _cmd_devices(args) -> int:
    from .runtime import INSTALL_HINT, list_devices

    infos = list_devices()
    if not infos:
        print(f"No OpenCL platform or device found. {INSTALL_HINT}")
        return 1
    print(f"{'id':5} {'type':5} {'CUs':>4} {'memory':>9} {'fp64':5} {'f-atomics':9} device")
    for i in infos:
        mem = f"{i.global_mem_bytes / 2**30:.1f} GiB"
        print(f"{i.selector:5} {i.kind:5} {i.compute_units:4d} {mem:>9} "
              f"{'yes' if i.fp64 else 'no':5} {'yes' if i.float_atomics else 'no':9} "
              f"{i.platform} / {i.name} ({i.version})")
    return 0


def _cmd_render(args) -> int:
    from .cameras import fibonacci_sphere_cameras, load_transforms
    from .envmap import EnvMap
    from .fields import Box, field_from_spec
    from .imageio import write_exr_rgb, write_png_srgb
    from .progress import Progress
    from .render import render_camera
    from .runtime import Runtime
    from .tracer import Tracer

    box = Box()
    field = field_from_spec(args.field, box)
    if args.cameras:
        cameras = load_transforms(Path(args.cameras))
    else:
        cameras = fibonacci_sphere_cameras(args.views, radius=args.radius, width=args.res,
                                           height=args.res)
    if args.only is not None:
        bad = [i for i in args.only if not 0 <= i < len(cameras)]
        if bad:
            raise ClrefractError(f"--only: view(s) {bad} out of range 0..{len(cameras) - 1}")
        cameras = [cameras[i] for i in args.only]
    envmap = EnvMap.from_exr(Path(args.envmap)) if args.envmap else EnvMap.procedural(
        seed=args.seed)
    runtime = Runtime(args.device)
    tracer = Tracer(field, box, step=args.step, integrator=args.integrator,
                    precision=args.precision, lanes=args.lanes, max_steps=args.max_steps,
                    runtime=runtime)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    print(f"rendering {len(cameras)} view(s) of {field.kind} on {runtime.info.name} "
          f"({args.precision}, {tracer.lanes} lanes, {args.integrator}, step {args.step} mm)",
          file=sys.stderr)
    bar = Progress(len(cameras), "render", unit="views")
    summary = []
    for k, cam in enumerate(cameras):
        t0 = time.perf_counter()
        res = render_camera(tracer, cam, envmap)
        dt = time.perf_counter() - t0
        stem = Path(cam.file_path).stem if getattr(cam, "file_path", None) else f"view_{k:03d}"
        write_exr_rgb(out / f"{stem}.exr", res.image)
        write_png_srgb(out / f"{stem}.png", res.image)
        summary.append({"view": stem, "seconds": dt, "steps": res.steps, **res.status_counts})
        bar.update(1, msteps_per_s=res.steps / dt / 1e6)
    (out / "render.json").write_text(json.dumps(
        {"field": field.to_dict(), "device": runtime.info.name, "step": args.step,
         "integrator": args.integrator, "precision": args.precision, "lanes": tracer.lanes,
         "views": summary}, indent=2))
    trapped = sum(v["trapped"] + v["nonfinite"] for v in summary)
    if trapped:
        print(f"warning: {trapped} pixel(s) hit the step cap or went non-finite and were "
              "rendered black; raise --max-steps or lower --step", file=sys.stderr)
    print(f"wrote {len(cameras)} view(s) to {out}", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="clrefract", description=__doc__)
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("devices", help="list OpenCL platforms and devices")
    p.set_defaults(func=_cmd_devices)

    p = sub.add_parser("render", help="render a field through curved rays")
    p.add_argument("--field", default="sphere",
                   help="analytic spec 'kind:key=value,...' (kinds: luneburg, maxwell, fibre, "
                        "blobs, sphere, prism, drop), or a voxel/hash-grid .npz, or a .json")
    p.add_argument("--cameras", help="NeRF-convention transforms JSON")
    p.add_argument("--views", type=int, default=8,
                   help="without --cameras: this many views on a Fibonacci sphere")
    p.add_argument("--res", type=int, default=128, help="without --cameras: image size")
    p.add_argument("--radius", type=float, default=200.0, help="camera distance in mm")
    p.add_argument("--only", type=int, nargs="+", help="render only these view indices")
    p.add_argument("--envmap", help="HDR equirectangular EXR (default: procedural)")
    p.add_argument("--seed", type=int, default=0, help="seed of the procedural environment")
    p.add_argument("--out", default="renders", help="output folder")
    _add_engine_options(p)
    p.set_defaults(func=_cmd_render)
    return ap


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except ClrefractError as exc:
        print(f"clrefract: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("clrefract: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
