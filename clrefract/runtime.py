"""OpenCL runtime: device discovery, one context with several queues, specialised programs.

One `Runtime` owns the context, its queues and every program built for it. Programs are
specialised at build time by preprocessor defines (field kind, integrator, precision, lanes)
and cached by their full source and options, so each specialisation compiles once per process;
across processes the driver's own cache (PoCL, NVIDIA) or pyopencl's binary cache keeps them.
The lane widths a device may use come from a probe (clrefract.probe), cached per driver.
"""

from __future__ import annotations

import hashlib
import os
import re
import time
import warnings
from dataclasses import dataclass

import numpy as np

from .drivers import register_pip_drivers
from .errors import BuildError, ClrefractError
from .locations import cache_dir, kernel_source
from .probe import WIDTHS, lane_report, why_unusable

INSTALL_HINT = (
    "Install an OpenCL driver: `pip install 'clrefract[pocl]'` or `pip install 'clrefract[cpu]'` "
    "(Intel's CPU runtime, for any x86-64 CPU) bring one through pip alone; on Debian/Ubuntu "
    "`apt-get install pocl-opencl-icd` gives a fast one; GPU vendors ship their own (NVIDIA, AMD "
    "ROCm, Intel compute-runtime, Apple)."
)
CPU_HINT = (
    "Other CPU drivers: Debian/Ubuntu's `apt-get install pocl-opencl-icd`, or `pip install "
    "'clrefract[cpu]'` (Intel's CPU OpenCL runtime through pip); `clrefract devices` lists what "
    "is installed and `--device` picks one."
)

# CLREFRACT_VERBOSE=1 (or --verbose) shows compiler warnings and build logs
VERBOSE = bool(os.environ.get("CLREFRACT_VERBOSE"))


def set_verbose(on: bool) -> None:
    global VERBOSE
    VERBOSE = bool(on)


def _cl():
    register_pip_drivers()
    try:
        import pyopencl as cl
    except ImportError as exc:  # pragma: no cover - dependency is declared
        raise ClrefractError(f"pyopencl is not importable ({exc}). {INSTALL_HINT}") from None
    return cl


@dataclass(frozen=True)
class DeviceInfo:
    platform_index: int
    device_index: int
    platform: str
    name: str
    kind: str  # "cpu", "gpu" or "other"
    platform_version: str
    driver_version: str
    compute_units: int
    global_mem_bytes: int
    fp64: bool
    float_atomics: bool
    version: str

    @property
    def selector(self) -> str:
        return f"{self.platform_index}:{self.device_index}"

    @property
    def driver(self) -> str:
        """The driver as a user would name it: platform, driver version, device."""
        return f"{self.platform} {self.driver_version} ({self.name})"


def _device_kind(cl, dev) -> str:
    if dev.type & cl.device_type.GPU:
        return "gpu"
    if dev.type & cl.device_type.CPU:
        return "cpu"
    return "other"


def list_devices() -> list[DeviceInfo]:
    """Every OpenCL device on every platform; empty when no platform is installed."""
    cl = _cl()
    try:
        platforms = cl.get_platforms()
    except cl.Error:  # the ICD loader reports no platform as an error
        return []
    out = []
    for pi, plat in enumerate(platforms):
        try:
            devices = plat.get_devices()
        except cl.Error:
            continue
        for di, dev in enumerate(devices):
            ext = dev.extensions
            out.append(
                DeviceInfo(
                    platform_index=pi,
                    device_index=di,
                    platform=plat.name.strip(),
                    name=dev.name.strip(),
                    kind=_device_kind(cl, dev),
                    platform_version=plat.version.strip(),
                    driver_version=dev.driver_version.strip(),
                    compute_units=int(dev.max_compute_units),
                    global_mem_bytes=int(dev.global_mem_size),
                    fp64=("cl_khr_fp64" in ext) or bool(dev.double_fp_config),
                    float_atomics="cl_ext_float_atomics" in ext,
                    version=dev.version.strip(),
                )
            )
    return out


def pick_device(selector: str | None, probe: bool = True):
    """Device from 'P:D', 'P', a name substring, or PYOPENCL_CTX; else the first GPU, else the
    first other device whose driver can build the kernels (probed once, then cached)."""
    cl = _cl()
    infos = list_devices()
    if not infos:
        raise ClrefractError(f"No OpenCL platform or device found. {INSTALL_HINT}")
    selector = selector if selector is not None else os.environ.get("PYOPENCL_CTX")
    if selector not in (None, ""):
        chosen = None
        parts = selector.split(":")
        if all(p.strip().isdigit() for p in parts if p.strip()) and parts[0].strip():
            pi = int(parts[0])
            di = int(parts[1]) if len(parts) > 1 and parts[1].strip() else 0
            chosen = next(
                (i for i in infos if i.platform_index == pi and i.device_index == di), None
            )
        else:
            low = selector.lower()
            chosen = next((i for i in infos if low in f"{i.platform} {i.name}".lower()), None)
        if chosen is None:
            listing = "\n".join(f"  {i.selector}  {i.platform} / {i.name}" for i in infos)
            raise ClrefractError(
                f"Unknown OpenCL device {selector!r}. Available devices "
                f"(select with --device P:D or PYOPENCL_CTX):\n{listing}"
            )
    else:
        order = [i for i in infos if i.kind == "gpu"] + [i for i in infos if i.kind != "gpu"]
        chosen, failures = (order[0] if not probe else None), []
        for info in order if probe else ():
            why = why_unusable(lane_report(info, "float32"))
            if not why:
                chosen = info
                break
            failures.append(f"{info.selector} {info.driver}: {why}")
        if chosen is None:
            raise ClrefractError(
                f"No OpenCL device here can build clrefract's kernels ({'; '.join(failures)}). "
                f"{CPU_HINT}"
            )
    dev = cl.get_platforms()[chosen.platform_index].get_devices()[chosen.device_index]
    return chosen, dev


class Runtime:
    """Context, command queues and compiled programs for one OpenCL device."""

    def __init__(self, device: str | None = None, queues: int = 1, probe_lanes: bool = True):
        cl = _cl()
        self.cl = cl
        self.probe_lanes = probe_lanes
        self.info, self.device = pick_device(device, probe=probe_lanes)
        self.context = cl.Context([self.device])
        if queues < 1:
            raise ClrefractError(f"number of queues must be at least 1, got {queues}")
        self.queues = [cl.CommandQueue(self.context) for _ in range(queues)]
        self._programs: dict[tuple, Kernels] = {}
        self.build_seconds: dict[tuple, float] = {}  # per program built by this runtime

    @property
    def queue(self):
        return self.queues[0]

    def lane_widths(self, precision: str) -> list[int]:
        """Lane widths this device's driver builds and runs correctly."""
        if not self.probe_lanes:
            return list(WIDTHS)
        return lane_report(self.info, precision)["widths"]

    def default_lanes(self, precision: str) -> int:
        """Rays per work-item: SIMD lanes on CPUs (PoCL does not vectorise looping kernels),
        the widest the driver handles up to 16 (float32) or 8 (float64); 1 on GPUs."""
        want = (16 if precision == "float32" else 8) if self.info.kind == "cpu" else 1
        ok = [w for w in self.lane_widths(precision) if w <= want]
        if not ok:
            raise ClrefractError(self._no_lanes_message(precision))
        return max(ok)

    def check_lanes(self, lanes: int, precision: str) -> None:
        """A one-line error when the driver cannot build `lanes`-wide kernels."""
        if lanes not in WIDTHS:
            raise ClrefractError(f"lanes must be one of {WIDTHS}, got {lanes}")
        ok = self.lane_widths(precision)
        if lanes not in ok:
            if not ok:
                raise ClrefractError(self._no_lanes_message(precision))
            raise ClrefractError(
                f"{self.info.driver} cannot build {precision} kernels at {lanes} lanes "
                f"(probe: {self._probe_why(lanes, precision)}); use --lanes {max(ok)} or "
                "leave --lanes unset"
            )

    def _probe_why(self, lanes: int, precision: str) -> str:
        rep = lane_report(self.info, precision)
        rec = next((r for r in rep["results"] if r["lanes"] == lanes), {})
        return rec.get("why") or rep.get("note") or "failed"

    def _no_lanes_message(self, precision: str) -> str:
        return (
            f"{self.info.driver} cannot build clrefract's {precision} kernels at any lane width "
            f"({self._probe_why(1, precision)}). {CPU_HINT}"
        )

    def check_precision(self, precision: str) -> None:
        if precision not in ("float32", "float64"):
            raise ClrefractError(f"precision must be 'float32' or 'float64', got {precision!r}")
        if precision == "float64" and not self.info.fp64:
            raise ClrefractError(
                f"float64 was requested but device {self.info.name!r} has no cl_khr_fp64; "
                "use --precision float32 or pick another device (`clrefract devices`)."
            )

    def build(
        self,
        sources: list[str],
        defines: dict[str, object],
        precision: str,
        extra_source: str = "",
    ) -> Kernels:
        """Compile (once) the concatenation of the named package sources with these defines,
        followed by `extra_source` (kernels of a test or a tool)."""
        self.check_precision(precision)
        key = (
            tuple(sources),
            tuple(sorted((k, str(v)) for k, v in defines.items())),
            precision,
            extra_source,
        )
        prg = self._programs.get(key)
        if prg is not None:
            return prg
        header = ["#define REAL_IS_DOUBLE 1" if precision == "float64" else ""]
        header += [f"#define {k} {v}" for k, v in sorted(defines.items())]
        text = "\n".join(header) + "\n" + "\n".join(kernel_source(s) for s in sources)
        text += "\n" + extra_source
        options = ["-cl-std=CL1.2"]
        if self.info.float_atomics and self._opencl_c_3():
            # atomic float add from cl_ext_float_atomics instead of compare-and-swap loops
            options = ["-cl-std=CL3.0", "-DFLOAT_ATOMICS=1"]
        if precision == "float32":
            # unsuffixed literals stay single precision on devices without fp64
            options.append("-cl-single-precision-constant")
        if not VERBOSE:
            options.append("-w")
        t0 = time.perf_counter()
        try:
            with warnings.catch_warnings():
                if not VERBOSE:
                    warnings.simplefilter("ignore")
                prg = self.cl.Program(self.context, text).build(options=options)
        except self.cl.RuntimeError as exc:
            msg, first = self._build_failure(sources, defines, text, str(exc))
            raise BuildError(msg, first) from None
        self.build_seconds[key] = time.perf_counter() - t0
        self._programs[key] = Kernels(self.cl, prg)
        return self._programs[key]

    def _build_failure(self, sources, defines, text: str, log: str) -> tuple[str, str]:
        """One line naming the driver, the program and the way round, and the compiler's first
        error; the whole log goes to a file."""
        first = next(
            (s.strip() for s in log.splitlines() if "error" in s.lower() and "failed" not in s),
            log.strip().splitlines()[0] if log.strip() else "no build log",
        )
        # drop the driver's temporary file name and position
        first = re.sub(r"\S+\.cl:\d+:\d+(\s*<Spelling=[^>]*>)?:\s*", "", first)[:200]
        where = ""
        try:
            tag = hashlib.sha1(text.encode()).hexdigest()[:12]
            path = cache_dir() / "build-logs" / f"{sources[-1].split('.')[0]}-{tag}.log"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(f"driver: {self.info.driver}\ndefines: {defines}\n\n{log}\n")
            where = f"; full log: {path}"
        except OSError:
            pass
        lanes = defines.get("LANES", 1)
        hint = (
            f"try --lanes {int(lanes) // 2} or another device"
            if int(lanes) > 1
            else "try another device"
        )
        return (
            f"OpenCL build of {sources[-1]} ({lanes} lanes) failed on {self.info.driver}: "
            f"{first} ({hint}; `clrefract devices` lists them){where}"
        ), first

    def _opencl_c_3(self) -> bool:
        try:
            return "3." in self.device.opencl_c_version
        except self.cl.Error:
            return False

    def real_dtype(self, precision: str):
        return np.float64 if precision == "float64" else np.float32


class Launch:
    """A launch in flight on one queue, with the events of its copies back to host memory:
    pyopencl waits for such a copy when its event is dropped, which ran several queues one
    after another; they are held until the queue is finished."""

    def __init__(self, queue, events=()):
        self.queue, self.events = queue, list(events)

    def hold(self, event) -> None:
        self.events.append(event)

    def finish(self) -> None:
        self.queue.finish()
        self.events.clear()


class Kernels:
    """The kernels of one built program, each created once and then reused."""

    def __init__(self, cl, program):
        self._cl, self.program, self._kernels = cl, program, {}

    def __getattr__(self, name: str):
        if name.startswith("_"):
            raise AttributeError(name)
        k = self._kernels.get(name)
        if k is None:
            k = self._kernels[name] = self._cl.Kernel(self.program, name)
        return k


_default_runtime: Runtime | None = None


def default_runtime() -> Runtime:
    """A process-wide runtime on the default device (PYOPENCL_CTX or first GPU, else CPU)."""
    global _default_runtime
    if _default_runtime is None:
        _default_runtime = Runtime()
    return _default_runtime
