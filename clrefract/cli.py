"""clrefract: recover index-of-refraction fields from photographs through curved rays.

Commands: devices, render, dataset make, dataset import, dataset export-colmap, dataset check,
fit, eval, report, table, bench."""

from __future__ import annotations

import argparse
import copy
import json
import logging
import math
import os
import re
import sys
import time
from dataclasses import fields
from pathlib import Path

from .errors import ClrefractError

log = logging.getLogger("clrefract")  # clrefract.log sets it up (without importing tqdm here)


class _HelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Help that shows every option's default (where its text does not say it already, and
    the default is a value: not None, not a switch's off), and a renamed option under its
    new spelling, its old ones named after its text."""

    def _get_help_string(self, action):
        text = action.help or ""
        old = getattr(action, "old_spellings", ())
        if old:
            text += f" (formerly {', '.join(old)})"
        default = action.default
        if (
            "(default" in text
            or default is None
            or default is argparse.SUPPRESS
            or isinstance(action, argparse._StoreConstAction | argparse._VersionAction)
            or (not action.option_strings and action.nargs not in ("?", "*"))
        ):
            return text
        if isinstance(default, list | tuple):
            default = " ".join(str(v) for v in default)
        return f"{text} (default: {str(default).replace('%', '%%')})"

    def _format_action_invocation(self, action):
        old = getattr(action, "old_spellings", ())
        if old:
            action = copy.copy(action)
            action.option_strings = [s for s in action.option_strings if s not in old]
        return super()._format_action_invocation(action)


class _Renamed(argparse._StoreAction):
    """An option stored under its new spelling (the first) and still taken under its old
    ones, which say on stderr that they are deprecated."""

    def __init__(self, option_strings, dest, old_spellings=(), **kw):
        super().__init__(option_strings, dest, **kw)
        self.old_spellings = tuple(old_spellings)

    def __call__(self, parser, namespace, values, option_string=None):
        if option_string in self.old_spellings:
            print(
                f"clrefract: warning: {option_string} is deprecated here; "
                f"use {self.option_strings[0]}",
                file=sys.stderr,
            )
        super().__call__(parser, namespace, values, option_string)


class _Commands(argparse._SubParsersAction):
    """Subcommands that take the global --quiet and --verbose after their name too."""

    def add_parser(self, name, **kw):
        p = super().add_parser(name, **kw)
        _add_log_options(p, argparse.SUPPRESS)
        return p


class _Parser(argparse.ArgumentParser):
    """The command line's parsers: defaults in every help, subcommands as _Commands."""

    def __init__(self, *a, **kw):
        kw.setdefault("formatter_class", _HelpFormatter)
        super().__init__(*a, **kw)

    def add_subparsers(self, **kw):
        kw.setdefault("action", _Commands)
        return super().add_subparsers(**kw)


def _add_log_options(p: argparse.ArgumentParser, default) -> None:
    """-q/--quiet, -v/--verbose; a subcommand's copies default to SUPPRESS, so that they do
    not undo the same flag given before the subcommand."""
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "-q",
        "--quiet",
        action="store_true",
        default=default,
        help="only warnings and errors: no progress bars, no progress messages",
    )
    g.add_argument(
        "-v",
        "--verbose",
        action="store_true",
        default=default,
        help="debug messages, and OpenCL compiler warnings and build logs",
    )


def _add_engine_options(p: argparse.ArgumentParser) -> None:
    g = p.add_argument_group("engine")
    g.add_argument(
        "--device",
        default=None,
        help="OpenCL device: 'P:D' index, a name substring (default: PYOPENCL_CTX, "
        "else the first GPU, else a CPU)",
    )
    g.add_argument(
        "--step",
        type=float,
        default=None,
        help="integrator step in mm of optical path (default: a fit run's own step, else what "
        "the field's finest feature needs, at most 0.5)",
    )
    g.add_argument(
        "--integrator",
        default="rkn4",
        choices=["rkn4", "rk4", "euler"],
        help="ray integrator",
    )
    g.add_argument(
        "--precision",
        default="float32",
        choices=["float32", "float64"],
        help="floating-point precision of the device kernels",
    )
    g.add_argument(
        "--lanes",
        type=int,
        default=None,
        help="rays per work-item (default: the widest the driver builds, up to 16, on CPUs; "
        "1 on GPUs)",
    )
    g.add_argument("--max-steps", type=int, default=None, help="step cap per ray")


def _cmd_devices(args) -> int:
    from .probe import lane_report, why_unusable
    from .runtime import INSTALL_HINT, list_devices

    infos = list_devices()
    if not infos:
        print(f"No OpenCL platform or device found. {INSTALL_HINT}")
        return 1
    print(
        f"{'id':5} {'type':5} {'CUs':>4} {'memory':>9} {'fp64':5} {'f-atomics':9} "
        f"{'lanes':11} device"
    )
    problems = []
    for i in infos:
        mem = f"{i.global_mem_bytes / 2**30:.1f} GiB"
        rep = lane_report(i, "float32")
        lanes = "/".join(str(w) for w in rep["widths"]) or "none"
        if not rep["widths"]:
            problems.append(f"{i.selector}: cannot build the kernels: {why_unusable(rep)}")
        print(
            f"{i.selector:5} {i.kind:5} {i.compute_units:4d} {mem:>9} "
            f"{'yes' if i.fp64 else 'no':5} {'yes' if i.float_atomics else 'no':9} "
            f"{lanes:11} {i.platform} / {i.name} ({i.version}, driver {i.driver_version})"
        )
    for line in problems:
        print(line)
    return 0


def _check_render_request(args) -> None:
    """Sizes and counts of a render, refused before anything is read or allocated."""
    from .limits import check_count, check_image_size

    if args.max_steps is not None:
        check_count("--max-steps", args.max_steps)
    if args.step is not None and not (args.step > 0 and math.isfinite(args.step)):
        raise ClrefractError(f"--step must be a positive number of mm, got {args.step}")
    if args.orbit is not None:
        check_count("--orbit", args.orbit, 1, 100_000)
        if args.cameras:
            raise ClrefractError("--orbit places its own cameras: drop --cameras")
    if args.orbit is not None or (not args.cameras and not args.dataset):
        check_count("--views", args.views, 1, 100_000)
        check_count("--res", args.res, 1)
        check_image_size("--res", args.res, args.res)
        if not (args.radius > 0 and math.isfinite(args.radius)):
            raise ClrefractError(f"--radius must be a positive number of mm, got {args.radius}")


def _cmd_render(args) -> int:
    from .cameras import fibonacci_sphere_cameras, frame_stem, load_transforms
    from .envmap import EnvMap
    from .fields import Box
    from .imageio import ensure_out_dir, linear_to_srgb, write_exr_rgb, write_png
    from .limits import check_image_size, max_steps_for
    from .log import Progress
    from .render import render_camera
    from .runtime import Runtime
    from .tracer import TraceSettings
    from .tracing import tracer_for

    _check_render_request(args)
    box = Box()
    dataset = None
    if args.dataset:
        from .dataset import Dataset

        run = Path(args.field)
        if run.is_dir() and (run / "run.json").is_file():  # as the fit saw it: registered
            from .evaluate import run_dataset

            dataset = run_dataset(run, Path(args.dataset))
        else:
            dataset = Dataset(Path(args.dataset))
        box = dataset.box
    field = _field_for_render(args.field, box)
    box = field.tracing_box(box)
    if args.orbit is not None:
        cameras = _orbit(args.orbit, box, args.radius, args.res)
    elif args.cameras:
        cameras = load_transforms(Path(args.cameras))
    elif dataset is not None:
        cameras = {
            "train": dataset.train,
            "test": dataset.test,
            "all": dataset.train + dataset.test,
        }[args.split]
    else:
        cameras = fibonacci_sphere_cameras(
            args.views, radius=args.radius, width=args.res, height=args.res
        )
    if args.only is not None:
        bad = [i for i in args.only if not 0 <= i < len(cameras)]
        if bad:
            raise ClrefractError(f"--only: view(s) {bad} out of range 0..{len(cameras) - 1}")
        cameras = [cameras[i] for i in args.only]
    for k, cam in enumerate(cameras):
        check_image_size(f"view {k} ({cam.name})", cam.width, cam.height)
    if args.step is not None:
        max_steps_for(args.step, math.dist(box.lo, box.hi))
    out = ensure_out_dir(args.out)
    if args.envmap:
        envmap = EnvMap.from_exr(Path(args.envmap))
    elif dataset is not None:
        envmap = dataset.envmap()
    else:
        envmap = EnvMap.procedural(seed=args.seed)
    runtime = Runtime(args.device)
    if args.step is None:
        args.step = _run_step(Path(args.field)) or field.suggested_step
    settings = TraceSettings(
        step=args.step,
        integrator=args.integrator,
        precision=args.precision,
        lanes=args.lanes,
        max_steps=args.max_steps,
        skip_empty=args.skip_empty,
    )
    tracer = tracer_for(field, box, settings, runtime=runtime)
    log.info(
        f"rendering {len(cameras)} view(s) of {field.kind} on {runtime.info.name} "
        f"({args.precision}, {tracer.lanes} lanes, {args.integrator}, step {args.step} mm)"
    )
    bar = Progress(len(cameras), "render", unit="views")
    summary, frames = [], []
    for k, cam in enumerate(cameras):
        t0 = time.perf_counter()
        res = render_camera(tracer, cam, envmap)
        dt = time.perf_counter() - t0
        stem = frame_stem(cam, k)
        write_exr_rgb(out / f"{stem}.exr", res.image)
        write_png(out / f"{stem}.png", srgb := linear_to_srgb(res.image))
        if args.orbit is not None:
            frames.append(srgb)
        summary.append({"view": stem, "seconds": dt, "steps": res.steps, **res.status_counts})
        bar.update(1, msteps_per_s=res.steps / dt / 1e6)
    bar.close()
    if frames:
        _write_animation(out / "orbit.gif", frames)
    (out / "render.json").write_text(
        json.dumps(
            {
                "field": field.to_dict(),
                "device": runtime.info.name,
                "step": args.step,
                "integrator": args.integrator,
                "precision": args.precision,
                "lanes": tracer.lanes,
                "skip_empty": args.skip_empty,
                "views": summary,
            },
            indent=2,
        )
    )
    trapped = sum(v["trapped"] + v["nonfinite"] for v in summary)
    if trapped:
        log.warning(
            f"{trapped} pixel(s) hit the step cap or went non-finite and were "
            "rendered black; raise --max-steps or lower --step"
        )
    log.info(f"wrote {len(cameras)} view(s) to {out}" + (" and orbit.gif" if frames else ""))
    return 0


def _orbit(n: int, box, radius: float, res: int) -> list:
    """A turntable: n cameras on a ring about the box centre's vertical, 20 degrees above
    it, `radius` mm away, looking at the centre."""
    import numpy as np

    from .cameras import orbit_cameras

    centre = (np.asarray(box.lo, dtype=float) + np.asarray(box.hi, dtype=float)) / 2
    cams = orbit_cameras(n, radius=radius, width=res, height=res)
    for cam in cams:
        cam.c2w[:3, 3] += centre
    return cams


def _write_animation(path: Path, frames: list) -> None:
    """An endlessly looping GIF of sRGB frames, 10 a second (imageio)."""
    import imageio.v3 as iio
    import numpy as np

    from .imageio import atomic_path

    data = np.stack([np.round(np.clip(f, 0, 1) * 255).astype(np.uint8) for f in frames])
    with atomic_path(path, suffix=".gif") as tmp:
        iio.imwrite(tmp, data, extension=".gif", duration=100, loop=0)


def _run_step(run: Path) -> float | None:
    """The step a fit run folder was fitted (and is scored) with: a fitted field renders as
    it was trained (a hash grid fitted at w/4 renders 5 dB worse at twice that)."""
    if not (run.is_dir() and (run / "config.toml").is_file()):
        return None
    from .fit import load_config, step_mm

    return step_mm(load_config(run / "config.toml", {}))


def _field_for_render(spec: str, box):
    """A field spec, or a fit run folder (its field.npz, else its latest checkpoint)."""
    from .fields import field_from_spec

    p = Path(spec)
    if p.is_dir():
        if (p / "field.npz").is_file():
            return field_from_spec(str(p / "field.npz"), box)
        if (p / "checkpoint.npz").is_file():
            from .fit import field_from_run

            return field_from_run(p)
        from .errors import ClrefractError

        raise ClrefractError(f"{p}: a folder, but not a fit run (no field.npz or checkpoint.npz)")
    return field_from_spec(spec, box)


def _cmd_dataset_make(args) -> int:
    from .family import parse_tilt
    from .synth import MakeOptions, make_dataset

    opt = MakeOptions(
        eta=args.eta,
        tilt=None if args.tilt is None else parse_tilt(args.tilt),
        views=args.views,
        res=args.res,
        test_every=args.test_every,
        seed=args.seed,
        envmap=args.envmap,
        env_width=args.env_width,
        radius=args.radius,
        fov_y=args.fov,
        device=args.device,
    )
    if args.full:
        opt.views, opt.res = 100, 800
    if args.realistic or args.flaws is not None:
        from .realistic import Flaws, parse_flaws

        opt.realistic = parse_flaws(args.flaws or "", Flaws() if args.realistic else None)
    info = make_dataset(args.scene, Path(args.out), opt)
    print(json.dumps(info, indent=2))
    return 0


def _cmd_dataset_import(args) -> int:
    from .importer import import_capture

    info = import_capture(
        Path(args.src),
        Path(args.out),
        scale=args.scale,
        box=args.box,
        eta_range=tuple(args.eta_range),
        envmap=Path(args.envmap) if args.envmap else None,
        env_rotation=args.env_rotation,
        known_distance=args.known_distance,
        images=Path(args.images) if args.images else None,
        up=args.up,
    )
    print(json.dumps(info, indent=2))
    return 0


def _cmd_dataset_export_colmap(args) -> int:
    from .colmap import export_colmap

    info = export_colmap(Path(args.dataset), Path(args.out), text=args.text)
    print(json.dumps(info, indent=2))
    return 0


def _cmd_dataset_check(args) -> int:
    from .dataset import box_of, check_dataset

    notes: list[str] = []
    box = box_of(args.box) if args.box else None
    problems = check_dataset(Path(args.dir), notes, box=box)
    if not problems:
        from .calibrate import describe_background

        describe_background(Path(args.dir), box, notes)
    for n in notes:
        print(f"{args.dir}: {n}")
    for p in problems:
        print(p)
    print(f"{args.dir}: {'OK' if not problems else f'{len(problems)} problem(s)'}")
    return 2 if problems else 0  # bad input, as everywhere


def _cmd_dataset_register_env(args) -> int:
    from .calibrate import calibrate
    from .dataset import box_of

    info = calibrate(
        Path(args.dataset),
        exposure=args.exposure,
        write=args.write,
        box=box_of(args.box) if args.box else None,
        keep_rotation=args.keep_rotation,
        poses=args.poses,
    )
    print(json.dumps(info, indent=2))
    return 0


def _cmd_dataset_refine_positions(args) -> int:
    from .camera_positions import refine_positions

    info = refine_positions(Path(args.dataset), Path(args.run), write=args.write)
    print(json.dumps(info, indent=2))
    return 0


def _config_names_field(path) -> bool:
    from .fit.config import read_toml

    return path is not None and "field" in read_toml(Path(path))


def _cmd_fit(args) -> int:
    from .fit import FitConfig, FitDiverged, load_config, run_fit
    from .log import LogStream
    from .parallel import world

    # every FitConfig key is a flag (None: not given); argparse's lists as the config's tuples
    overrides = {
        f.name: tuple(v) if isinstance(v := getattr(args, f.name), list) else v
        for f in fields(FitConfig)
        if f.name != "box"
    }
    if args.box:
        from .dataset import box_values

        overrides["box"] = tuple(box_values(args.box))
    if args.resume:
        _check_resume_flags(Path(args.out), overrides, args.config)
    elif overrides["field"] is None and not _config_names_field(args.config):
        overrides["field"] = "auto"  # the model is picked from the data at the start
    cfg = load_config(Path(args.config) if args.config else None, overrides)
    run = Path(args.out)
    try:
        result = run_fit(Path(args.dataset), run, cfg, resume=args.resume, stream=LogStream())
    except FitDiverged:
        if world().root:
            _write_report(run, Path(args.dataset), cfg.device)  # what it kept, to look at
        raise
    if not result:
        return 0  # an MPI rank other than 0: rank 0 reports
    _write_report(run, Path(args.dataset), cfg.device)
    print(json.dumps({k: v for k, v in result.items() if k != "views"}, indent=2))
    return 0


def _write_report(run: Path, dataset: Path | None, device: str | None) -> None:
    """RUN/report.html at the end of a fit: a report that cannot be made is a warning, as
    the run itself is whole."""
    from .report_html import write_html_report

    try:
        log.info(f"wrote {write_html_report(run, dataset, device=device)}")
    except Exception as exc:  # noqa: BLE001 - the run is kept whatever the report does
        log.warning(f"{run / 'report.html'} not written: {str(exc).splitlines()[0]}")


def _cmd_report(args) -> int:
    from .report_html import write_html_report

    run = Path(args.run)
    path = write_html_report(
        run,
        Path(args.dataset) if args.dataset else None,
        Path(args.out) if args.out else None,
        device=args.device,
    )
    log.info(f"wrote {path}")
    return 0


def _check_resume_flags(run: Path, overrides: dict, config: str | None) -> None:
    """--resume continues a run with its own settings: a flag that asks for different ones
    (another field kind, say) is refused rather than silently ignored. --iterations may
    lengthen a line-search run (extend_run), --width change its interface (narrow_run)."""
    from .fit import extend_run, load_config, narrow_run
    from .parallel import world

    if config:
        raise ClrefractError("--resume takes the run's own config.toml; drop --config")
    if not (run / "config.toml").is_file():
        return  # prepare_fit names the missing run
    saved = load_config(run / "config.toml", {})
    clash = [
        f"{_fit_flag(k)} {v} (the run has {getattr(saved, k)})"
        for k, v in overrides.items()
        if v is not None
        and k not in ("device", "iterations", "width")
        and k in vars(saved)
        and v != getattr(saved, k)
    ]
    if clash:
        raise ClrefractError(
            f"{run}: --resume cannot change the run's settings: {'; '.join(clash)}"
        )
    if world().root:  # rank 0 writes the run
        if overrides.get("width") is not None:
            narrow_run(run, overrides["width"])
        if overrides.get("iterations") is not None:
            extend_run(run, overrides["iterations"])


def _cmd_eval(args) -> int:
    from .evaluate import evaluate_run, format_table

    result = evaluate_run(
        Path(args.run),
        Path(args.dataset) if args.dataset else None,
        Path(args.out) if args.out else None,
        views=args.views,
        figures=not args.no_figures,
    )
    print(format_table(result), end="")
    return 0


def _names(text: str) -> list[str]:
    return [n for n in text.split(",") if n]


def _check_readme(args) -> None:
    if args.readme and not args.page:
        raise ClrefractError("--readme needs --page: the results at a glance summarise the page")


def _cmd_table_run(args) -> int:
    from . import shards
    from .table import run_protocol, write_page, write_table

    out = Path(args.out)
    whole = shards.parse(args.shard)[1] == 1
    if args.page and not whole:
        raise ClrefractError("--page needs the whole protocol: give it to `table merge`")
    _check_readme(args)
    records = run_protocol(
        args.protocol,
        out,
        args.shard,
        scenes=_names(args.scenes),
        methods=_names(args.methods),
        data_root=Path(args.data) if args.data else None,
        family_methods=_names(args.family_methods),
    )
    if whole and records:
        write_table(records, out)
        if args.page:
            write_page(records, args.page, args.readme)
        print((out / "table.md").read_text(), end="")
    return 0


def _cmd_table_merge(args) -> int:
    from .table import merge, write_page, write_table

    _check_readme(args)
    out = Path(args.out)
    records = merge([Path(f) for f in args.folders])
    write_table(records, out)
    if args.page:
        write_page(records, args.page, args.readme)
    print((out / "table.md").read_text(), end="")
    return 0


def _cmd_table_page(args) -> int:
    from .table import read_records, write_page

    write_page(read_records(args.records), args.out, args.readme)
    also = f" and the results at a glance in {args.readme}" if args.readme else ""
    print(f"wrote {args.out} and {Path(args.out).with_suffix('.json')}{also}")
    return 0


def _cmd_bench(args) -> int:
    from dataclasses import replace

    from .imageio import ensure_out_dir
    from .limits import check_count
    from .runtime import Runtime
    from .tradeoff import SIZES, markdown, run_study, write_study

    size = SIZES["quick" if args.quick else "full"]
    if args.rays is not None:
        size = replace(size, rays=check_count("--rays", args.rays, 1, 1 << 22))
    if args.image is not None:
        size = replace(size, image=check_count("--image", args.image, 1, 4096))
    if args.scenes:
        size = replace(size, scenes=tuple(args.scenes))
    if args.precision:
        size = replace(size, precisions=tuple(args.precision))
    if args.integrators:
        fixed = {k: v for k, v in size.fixed.items() if k in args.integrators}
        size = replace(size, fixed=fixed, tols=size.tols if "dopri5" in args.integrators else [])
    out = ensure_out_dir(Path(args.out), "bench folder")
    runtime = Runtime(args.device)
    log.info(f"bench on {runtime.info.name}: {len(size.scenes)} scene(s)")
    rows = run_study(size, runtime, log=log.info)
    paths = write_study(rows, out)
    print(markdown(rows), end="")
    log.info(f"wrote {', '.join(str(p) for p in paths.values())}")
    return 0


_BOX_FLAGS = ("--box", "--pose-box")


def _add_box_option(p, what: str, names: tuple[str, ...] = ("--box",)) -> None:
    # parsed by dataset.box_values, which names a bad value in one line (exit status 2);
    # names: the spelling, then old ones that still work
    p.add_argument(
        *names,
        dest="box",
        nargs="+",
        metavar="XMIN,YMIN,ZMIN,XMAX,YMAX,ZMAX",
        help=what,
        action=_Renamed,
        old_spellings=names[1:],
    )


# FitConfig keys whose flag is spelled otherwise (the first name; the key's own also works).
# The grid's resolution is --grid-res and the field's kind --field-kind, as --res is an
# image's size (render, dataset make) and --field a field spec (render); their keys in
# config.toml stay `res` and `field`, and --res and --field still work here, deprecated.
_FIT_FLAG_NAMES = {
    "adjoint_growth_max": ("--growth-max", "--adjoint-growth-max"),
    "res": ("--grid-res", "--res"),
    "field": ("--field-kind", "--field"),
}
_FIT_OLD_SPELLINGS = {"res": ("--res",), "field": ("--field",)}
_FIT_METAVARS = {
    "res_schedule": "RES",
    "grad_sigma": "CELLS",
    "line_steps": "MM",
    "index_steps": "DETA",
}


def _fit_default(value) -> str:
    """A FitConfig default as --help shows it."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return " ".join(str(v) for v in value) or "none"
    return repr(value) if value == "" else str(value)


def _fit_flag(key: str) -> str:
    """The flag of a FitConfig key, as help and messages spell it."""
    if key in _FIT_OLD_SPELLINGS:
        return _FIT_FLAG_NAMES[key][0]
    return "--" + key.replace("_", "-")


def _new_fit_spellings(text: str) -> str:
    """fit/config.py's help texts with the renamed flags' new spellings."""
    for key, (old,) in _FIT_OLD_SPELLINGS.items():
        text = re.sub(rf"{old}(?![\w-])", _fit_flag(key), text)
    return text


def _add_fit_options(p: argparse.ArgumentParser) -> None:
    """One flag per FitConfig key, its help text and values from fit/config.py (HELP,
    CHOICES), default None: a flag not given leaves the --config file's value (or the
    key's default, shown in --help; some depend on the field kind and optimiser)."""
    from .fit.config import CHOICES, HELP, FitConfig

    g = p.add_argument_group(
        "fit settings", "the keys of a --config file (config.toml), which these flags override"
    )
    for f in fields(FitConfig):
        text = _new_fit_spellings(HELP[f.name])
        if "(default:" not in text:
            text += f" (default: {_fit_default(f.default)})"
        text = text.replace("%", "%%")
        if f.name == "box":
            _add_box_option(g, text)
            continue
        kw: dict = {"dest": f.name, "default": None, "help": text}
        if isinstance(f.default, bool):
            kw["action"] = argparse.BooleanOptionalAction
        elif isinstance(f.default, tuple):
            # an empty default may be set empty again: a flag with no values
            kw["nargs"] = "*" if not f.default else "+"
            kw["type"] = int if f.name == "res_schedule" else float
            kw["metavar"] = _FIT_METAVARS.get(f.name)
        else:
            kw["type"] = type(f.default)
        if f.name in CHOICES:
            kw["choices"] = CHOICES[f.name]
        if f.name in _FIT_OLD_SPELLINGS:
            kw.update(action=_Renamed, old_spellings=_FIT_OLD_SPELLINGS[f.name])
        g.add_argument(*_FIT_FLAG_NAMES.get(f.name, ("--" + f.name.replace("_", "-"),)), **kw)


def _joined_box(argv: list[str]) -> list[str]:
    """'--box -5,-5,-5,5,5,5' as '--box=-5,...': argparse takes a value that starts with '-'
    and is not one number for an option."""
    out: list[str] = []
    for a in argv:
        if out and out[-1] in _BOX_FLAGS and "," in a:
            out[-1] = f"{out[-1]}={a}"
        else:
            out.append(a)
    return out


PAGE_HELP = (
    "also write the results page (markdown: how, where and when it was measured, then one "
    "table per figure; e.g. docs/results.md) and its records beside it (PAGE with .json)"
)


README_HELP = (
    "with --page: also write the results at a glance into this README, between its "
    "results-at-a-glance comment lines (e.g. README.md)"
)


def build_parser(fit_flags: bool = True) -> argparse.ArgumentParser:
    """The command line; fit_flags=False leaves out `fit`'s FitConfig flags, whose import
    (the fit package: about 1.5 s) only `fit` needs."""
    from .provenance import version

    ap = _Parser(prog="clrefract", description=__doc__)
    ap.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    _add_log_options(ap, False)
    sub = ap.add_subparsers(dest="command", required=True)

    p = sub.add_parser("devices", help="list OpenCL platforms and devices")
    p.set_defaults(func=_cmd_devices)

    p = sub.add_parser("render", help="render a field through curved rays")
    p.add_argument(
        "--field",
        default="sphere",
        help="analytic spec 'kind:key=value,...' (kinds: luneburg, maxwell, fibre, "
        "blobs, sphere, prism, drop), a voxel/hash-grid .npz, a .json, or a "
        "fit run folder",
    )
    p.add_argument("--dataset", help="take cameras and environment map from a dataset folder")
    p.add_argument(
        "--split",
        default="test",
        choices=["train", "test", "all"],
        help="with --dataset: which views (default test)",
    )
    p.add_argument("--cameras", help="NeRF-convention transforms JSON")
    p.add_argument(
        "--views",
        type=int,
        default=8,
        help="without --cameras: this many views on a Fibonacci sphere",
    )
    p.add_argument(
        "--res", type=int, default=128, help="without --cameras: image width and height, pixels"
    )
    p.add_argument("--radius", type=float, default=200.0, help="camera distance in mm")
    p.add_argument(
        "--orbit",
        type=int,
        metavar="N",
        help="a turntable instead: N views on a ring around the object (20 degrees above "
        "it, --radius away), written as frames and as orbit.gif",
    )
    p.add_argument("--only", type=int, nargs="+", help="render only these view indices")
    p.add_argument("--envmap", help="HDR equirectangular EXR or .hdr (default: procedural)")
    p.add_argument("--seed", type=int, default=0, help="seed of the procedural environment")
    p.add_argument("--out", default="renders", help="output folder")
    p.add_argument(
        "--skip-empty",
        action="store_true",
        help="fly straight through the cells where eta is constant (sampled on the device): "
        "the same image in float64, in fewer steps (as fits score their test views)",
    )
    _add_engine_options(p)
    p.set_defaults(func=_cmd_render)

    ds = sub.add_parser("dataset", help="make or check datasets").add_subparsers(
        dest="dataset_command", required=True
    )
    p = ds.add_parser("make", help="generate a synthetic benchmark scene")
    p.add_argument(
        "scene",
        help="the paper's solids sphere, prism, drop (exact Snell ground truth); the family "
        "shapes rounded-cube, cylinder, bowl, two-bodies, vase, random, faceted (exact Snell "
        "at a signed-distance surface); luneburg, blobs (drawn by --seed), grin-rod, grin-lens or "
        "plume (graded index)",
    )
    p.add_argument("--out", required=True, help="dataset folder to write")
    p.add_argument("--views", type=int, default=100, help="how many views")
    p.add_argument("--res", type=int, default=128, help="image width and height, pixels")
    p.add_argument("--full", action="store_true", help="the full protocol: 100 views, 800x800")
    p.add_argument("--test-every", type=int, default=5, help="every k-th view is a test view")
    p.add_argument(
        "--seed",
        type=int,
        default=0,
        help="seed of the procedural environment (and of the shape, for `random`, "
        "`faceted` and `blobs`, and of --realistic's flaws)",
    )
    p.add_argument(
        "--eta", type=float, default=None, help="family shapes: glass index, 1.2 to 1.9 (1.5)"
    )
    p.add_argument(
        "--tilt",
        default=None,
        help="family shapes: rotation a/b/c in degrees about x, y, z (default per shape)",
    )
    p.add_argument("--envmap", help="your own equirectangular EXR or .hdr instead")
    p.add_argument("--env-width", type=int, default=2048, help="procedural map width")
    p.add_argument(
        "--radius",
        type=float,
        default=200.0,
        help="distance of the cameras from the box centre, mm (outside the 100 mm box)",
    )
    p.add_argument("--fov", type=float, default=30.0, help="vertical field of view, degrees")
    p.add_argument("--device", default=None, help="OpenCL device, as for render")
    p.add_argument(
        "--realistic",
        action="store_true",
        help="render a real capture's flaws, each a --flaws key (default): an OPENCV lens "
        "(k1=-0.05, k2=0.01, p1=0.001, p2=0.001), recorded; poses recorded off by pose_deg=0.1 "
        "degree and pose_mm=0.2 mm (frames from the true ones); Poisson-Gaussian sensor noise "
        "(value = Poisson(v x full_well) / full_well + Normal(0, read_noise), v in units of full "
        "scale; full_well=4000, read_noise=0.001); 8-bit sRGB JPEG frames (jpeg=90; 0: linear "
        "EXR; chroma=420, 422 or 444 subsampling) at an exposure that clips clip=0.02 of the "
        "panorama in the brightest view, recorded as exposure_scale; per-view exposure within "
        "+-exposure_ev=0.3 EV and red and blue gains within 1 +- tint=0.03, and the panorama "
        "turned by env_rotation=3/-2/4 degrees, none of these three recorded. The truth goes "
        "to OUT/realistic.json",
    )
    p.add_argument(
        "--flaws",
        metavar="KEY=VALUE,...",
        help="set these flaws of --realistic (with it: change them; without it: only these, "
        "e.g. k1=-0.05,k2=0.01 for the lens alone)",
    )
    p.set_defaults(func=_cmd_dataset_make)
    p = ds.add_parser(
        "import",
        help="make a dataset folder from a NeRF-synthetic, instant-ngp or COLMAP capture",
    )
    p.add_argument(
        "src",
        help="capture folder (or its transforms.json); a COLMAP project holds its sparse model "
        "in sparse/0, sparse or the folder itself",
    )
    p.add_argument("--out", required=True, help="dataset folder to write")
    p.add_argument(
        "--scale",
        type=float,
        default=None,
        help="millimetres per unit of the camera poses (without it or --known-distance: 1)",
    )
    p.add_argument(
        "--known-distance",
        nargs=3,
        metavar=("I", "J", "MM"),
        help="the scale instead: the images named I and J have their centres MM mm apart",
    )
    p.add_argument("--images", help="a COLMAP project's image folder (default: SRC/images)")
    p.add_argument(
        "--up",
        metavar="auto|keep|X,Y,Z",
        help="a COLMAP model's up direction, turned to +z with its heading kept: auto (the "
        "default) estimates it from the cameras (the plane of their centres, else the normal "
        "to their image-right axes, else their mean image-up vector), keep leaves the model's "
        "frame, X,Y,Z gives it in the model's world (write --up=-X,Y,Z where X is negative)",
    )
    # --pose-box: in the poses' units, where every other --box is in mm (old name: --box)
    _add_box_option(
        p,
        "the object's box in the poses' units (default: instant-ngp's box where "
        "transforms.json sets aabb_scale, scale or offset; a COLMAP model's sparse points in "
        "the region the cameras look at; else that region)",
        ("--pose-box", "--box"),
    )
    p.add_argument(
        "--eta-range",
        type=float,
        nargs=2,
        default=[1.0, 1.6],
        metavar=("LO", "HI"),
        help="the range of eta the object may hold",
    )
    p.add_argument(
        "--envmap",
        help="equirectangular HDR panorama, EXR or Radiance .hdr (default: SRC/envmap.exr "
        "or SRC/envmap.hdr)",
    )
    p.add_argument(
        "--env-rotation",
        type=float,
        nargs=3,
        metavar=("RX", "RY", "RZ"),
        help="the panorama's orientation in the world: degrees about x, then y, then z "
        "(scene.json's envmap_rotation)",
    )
    p.set_defaults(func=_cmd_dataset_import)
    p = ds.add_parser(
        "export-colmap",
        help="write a dataset folder as a COLMAP project (sparse/0, images/, envmap)",
    )
    p.add_argument("dataset", help="dataset folder")
    p.add_argument("--out", required=True, help="COLMAP project folder to write")
    p.add_argument("--text", action="store_true", help="write the model as .txt, not .bin")
    p.set_defaults(func=_cmd_dataset_export_colmap)
    p = ds.add_parser("check", help="validate a dataset folder and name every problem")
    p.add_argument("dir")
    _add_box_option(p, "the object's box in mm, instead of scene.json's or the cameras'")
    p.set_defaults(func=_cmd_dataset_check)
    p = ds.add_parser(
        "register-env",
        help="find the panorama's rotation (and each view's exposure, white balance and "
        "camera rotation) from the pixels that see it straight",
    )
    p.add_argument("dataset", help="dataset folder")
    p.add_argument(
        "--exposure",
        action="store_true",
        help="also estimate each frame's exposure_scale and white_balance (RGB gains)",
    )
    p.add_argument(
        "--keep-rotation",
        action="store_true",
        help="take scene.json's envmap_rotation as it is (with --exposure: only the gains)",
    )
    p.add_argument(
        "--poses",
        action="store_true",
        help="also correct each camera's rotation (not its position) to the panorama: a pose "
        "off by a tenth of a degree misplaces the object by half a pixel at 128 x 128",
    )
    p.add_argument(
        "--write",
        action="store_true",
        help="write the rotation into scene.json (and with --exposure the gains, with --poses "
        "the corrected poses, into the transforms files), keeping every other key",
    )
    _add_box_option(
        p,
        "the object's box in mm, instead of scene.json's or the cameras': only rays that miss "
        "it are used, so a tight one gives more",
    )
    p.set_defaults(func=_cmd_dataset_register_env)
    p = ds.add_parser(
        "refine-positions",
        help="move each training camera's centre (in its image plane) to where a fitted run's "
        "field renders its photograph best; test views keep their recorded positions, so "
        "their scores stay honest",
    )
    p.add_argument("dataset", help="dataset folder")
    p.add_argument(
        "--run", required=True, help="run folder of a fit of this dataset (its field.npz)"
    )
    p.add_argument(
        "--write",
        action="store_true",
        help="move the cameras in the training transforms file, keeping every other key "
        "(then fit again)",
    )
    p.set_defaults(func=_cmd_dataset_refine_positions)

    p = sub.add_parser(
        "fit",
        help="recover eta from a dataset",
        usage="%(prog)s DATASET --out OUT [--config CONFIG] [--resume] [fit settings]",
    )
    p.add_argument("dataset", help="dataset folder (see `clrefract dataset make`)")
    p.add_argument("--out", required=True, help="run folder")
    p.add_argument("--config", help="TOML file of fit settings (flags override it)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out")
    if fit_flags:
        _add_fit_options(p)
    p.set_defaults(func=_cmd_fit)

    p = sub.add_parser("eval", help="score a run: PSNR, SSIM, chamfer distance, eta RMSE")
    p.add_argument("run", help="run folder (of `clrefract fit` or a baseline)")
    p.add_argument("--dataset", help="dataset folder (default: the one the run names)")
    p.add_argument("--out", help="folder for eval.json, eval.md and figures (default RUN/eval)")
    p.add_argument("--views", type=int, default=-1, help="score the first N test views (-1 all)")
    p.add_argument("--no-figures", action="store_true", help="scores only")
    p.set_defaults(func=_cmd_eval)

    p = sub.add_parser(
        "report",
        help="RUN/report.html, one page to open: scores, loss curves, test views beside the "
        "truth, eta slices, the surface, the settings (`fit` writes it at its end)",
    )
    p.add_argument("run", help="run folder (of `clrefract fit`)")
    p.add_argument(
        "--dataset",
        help="dataset folder, for views the run folder lacks (default: the one the run names)",
    )
    p.add_argument("--out", help="the page to write (default RUN/report.html)")
    p.add_argument("--device", default=None, help="OpenCL device, as for render")
    p.set_defaults(func=_cmd_report)

    tab = sub.add_parser(
        "table", help="the paper's Table 1: every method on every scene under a protocol"
    ).add_subparsers(dest="table_command", required=True)
    p = tab.add_parser("run", help="run a protocol (or one shard of it) and write the table")
    p.add_argument(
        "--protocol", required=True, help="tiny (smoke test), quick (128 x 128), standard, full"
    )
    p.add_argument("--out", required=True, help="folder for runs, shard records and the table")
    p.add_argument("--shard", default="", help="i/n, 0 <= i < n: every n-th run from the i-th")
    p.add_argument("--scenes", default="sphere,prism,drop", help="comma-separated scenes")
    p.add_argument(
        "--methods",
        default="grid,meridian,synapse,vertexnet,interface,auto",
        help="comma-separated methods",
    )
    p.add_argument(
        "--family-methods",
        default="",
        help="comma-separated methods also run on each solid of the family (the development "
        "set: rounded-cube, cylinder, bowl, two-bodies, vase, random, faceted), e.g. interface",
    )
    p.add_argument("--data", help="dataset folder root (default OUT/data)")
    p.add_argument("--page", help=PAGE_HELP + " (the whole protocol only: no --shard)")
    p.add_argument("--readme", help=README_HELP)
    p.set_defaults(func=_cmd_table_run)
    p = tab.add_parser("merge", help="join shard records into the table")
    p.add_argument("folders", nargs="+", help="folders holding shard-*-of-*.json")
    p.add_argument("--out", required=True, help="folder for the table")
    p.add_argument("--page", help=PAGE_HELP)
    p.add_argument("--readme", help=README_HELP)
    p.set_defaults(func=_cmd_table_merge)
    p = tab.add_parser("page", help="write the results page from saved records, running nothing")
    p.add_argument("records", help="a table's records: OUT/table.json, or a page's .json")
    p.add_argument("--out", required=True, help="the page, e.g. docs/results.md")
    p.add_argument("--readme", help=README_HELP)
    p.set_defaults(func=_cmd_table_page)

    from .tradeoff import SCENES

    p = sub.add_parser(
        "bench",
        help="the speed/accuracy trade: exit-direction error, image PSNR, gradient error, "
        "device memory and throughput per integrator, precision and step",
    )
    p.add_argument("--out", default="bench_results/tradeoff", help="folder for the results")
    p.add_argument("--quick", action="store_true", help="the small study (about a minute)")
    p.add_argument("--scenes", nargs="+", choices=list(SCENES), help="default: the size's")
    p.add_argument("--precision", nargs="+", choices=["float32", "float64"])
    p.add_argument(
        "--integrators", nargs="+", choices=["rkn4", "rk4", "euler", "dopri5"], help="a subset"
    )
    p.add_argument("--rays", type=int, help="rays in the bundle (quick 256, full 2048)")
    p.add_argument("--image", type=int, help="pixels across the PSNR view (quick 32, full 64)")
    p.add_argument("--device", default=None, help="OpenCL device, as for render")
    p.set_defaults(func=_cmd_bench)
    return ap


def main(argv: list[str] | None = None) -> int:
    # one BLAS thread unless the user sets it (read when NumPy loads, after this): the
    # host's products are long and thin (points by 3), and where another process shares
    # the cores OpenBLAS's spinning threads made a surface start 1.46 times slower on 2
    # cores (its visual hull 4 times); alone, the model choice gains 3%
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    argv = _joined_box(list(sys.argv[1:] if argv is None else argv))
    args = build_parser(fit_flags="fit" in argv).parse_args(argv)
    from .log import configured
    from .provenance import begin, end

    with configured(quiet=args.quiet, verbose=args.verbose):
        begin(argv)  # run.json records the command and its start
        if args.verbose:
            from .runtime import set_verbose

            set_verbose(True)
        try:
            return args.func(args)
        except ClrefractError as exc:
            print(f"clrefract: error: {exc}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print("clrefract: interrupted", file=sys.stderr)
            return 130
        except BrokenPipeError:  # `clrefract ... | head`: the reader left, as with any tool
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # no flush error
            return 141
        finally:
            end()


if __name__ == "__main__":
    sys.exit(main())
