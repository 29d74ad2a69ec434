"""OpenCL runtime: device discovery, one context with several queues, specialised programs.

One `Runtime` owns the context, its queues and every program built for it. Programs are
specialised at build time by preprocessor defines (field kind, integrator, precision, lanes)
and cached by their full source and options, so each specialisation compiles once.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from .errors import ClrefractError

INSTALL_HINT = (
    "Install an OpenCL driver: `pip install 'clrefract[pocl]'` brings a CPU driver (PoCL) through "
    "pip alone; on Debian/Ubuntu `apt-get install pocl-opencl-icd` gives a faster one; GPU vendors "
    "ship their own (NVIDIA, AMD ROCm, Intel compute-runtime, Apple)."
)


def _cl():
    try:
        import pyopencl as cl
    except ImportError as exc:  # pragma: no cover - dependency is declared
        raise ClrefractError(f"pyopencl is not importable ({exc}). {INSTALL_HINT}") from None
    return cl


def kernel_source(name: str) -> str:
    """Text of one OpenCL source shipped in the package (`kernels_cl/` in the repository).

    Falls back to the repository's kernels_cl/ beside the package: an editable install maps
    clrefract.kernels_cl to the checkout it was installed from, which misses sources that
    exist only in another worktree run through PYTHONPATH."""
    try:
        return resources.files("clrefract.kernels_cl").joinpath(name).read_text()
    except (FileNotFoundError, ModuleNotFoundError) as exc:
        local = Path(__file__).resolve().parent.parent / "kernels_cl" / name
        if local.is_file():
            return local.read_text()
        raise ClrefractError(f"kernel source {name!r} is missing from the package: {exc}") from None


@dataclass(frozen=True)
class DeviceInfo:
    platform_index: int
    device_index: int
    platform: str
    name: str
    kind: str  # "cpu", "gpu" or "other"
    compute_units: int
    global_mem_bytes: int
    fp64: bool
    float_atomics: bool
    version: str

    @property
    def selector(self) -> str:
        return f"{self.platform_index}:{self.device_index}"


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
                    compute_units=int(dev.max_compute_units),
                    global_mem_bytes=int(dev.global_mem_size),
                    fp64=("cl_khr_fp64" in ext) or bool(dev.double_fp_config),
                    float_atomics="cl_ext_float_atomics" in ext,
                    version=dev.version.strip(),
                )
            )
    return out


def _pick_device(selector: str | None):
    """Device from 'P:D', 'P', a name substring, or PYOPENCL_CTX; else the first GPU, else CPU."""
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
        gpus = [i for i in infos if i.kind == "gpu"]
        chosen = gpus[0] if gpus else infos[0]
    dev = cl.get_platforms()[chosen.platform_index].get_devices()[chosen.device_index]
    return chosen, dev


class Runtime:
    """Context, command queues and compiled programs for one OpenCL device."""

    def __init__(self, device: str | None = None, queues: int = 1):
        cl = _cl()
        self.cl = cl
        self.info, self.device = _pick_device(device)
        self.context = cl.Context([self.device])
        if queues < 1:
            raise ClrefractError(f"number of queues must be at least 1, got {queues}")
        self.queues = [cl.CommandQueue(self.context) for _ in range(queues)]
        self._programs: dict[tuple, Kernels] = {}

    @property
    def queue(self):
        return self.queues[0]

    def default_lanes(self, precision: str) -> int:
        """Rays per work-item: SIMD lanes on CPUs (PoCL does not vectorise looping kernels)."""
        if self.info.kind == "cpu":
            return 16 if precision == "float32" else 8
        return 1

    def check_precision(self, precision: str) -> None:
        if precision not in ("float32", "float64"):
            raise ClrefractError(f"precision must be 'float32' or 'float64', got {precision!r}")
        if precision == "float64" and not self.info.fp64:
            raise ClrefractError(
                f"float64 was requested but device {self.info.name!r} has no cl_khr_fp64; "
                "use --precision float32 or pick another device (`clrefract devices`)."
            )

    def build(self, sources: list[str], defines: dict[str, object], precision: str) -> Kernels:
        """Compile (once) the concatenation of the named package sources with these defines."""
        self.check_precision(precision)
        key = (tuple(sources), tuple(sorted((k, str(v)) for k, v in defines.items())), precision)
        prg = self._programs.get(key)
        if prg is not None:
            return prg
        header = ["#define REAL_IS_DOUBLE 1" if precision == "float64" else ""]
        header += [f"#define {k} {v}" for k, v in sorted(defines.items())]
        text = "\n".join(header) + "\n" + "\n".join(kernel_source(s) for s in sources)
        options = ["-cl-std=CL1.2"]
        if self.info.float_atomics and self._opencl_c_3():
            # atomic float add from cl_ext_float_atomics instead of compare-and-swap loops
            options = ["-cl-std=CL3.0", "-DFLOAT_ATOMICS=1"]
        if precision == "float32":
            # unsuffixed literals stay single precision on devices without fp64
            options.append("-cl-single-precision-constant")
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                prg = self.cl.Program(self.context, text).build(options=options)
        except self.cl.RuntimeError as exc:
            raise ClrefractError(
                f"OpenCL build of {', '.join(sources)} failed on {self.info.name!r} "
                f"with defines {defines}:\n{exc}"
            ) from None
        self._programs[key] = Kernels(self.cl, prg)
        return self._programs[key]

    def _opencl_c_3(self) -> bool:
        try:
            return "3." in self.device.opencl_c_version
        except self.cl.Error:
            return False

    def real_dtype(self, precision: str):
        return np.float64 if precision == "float64" else np.float32


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
