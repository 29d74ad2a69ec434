"""The run folder: every file a fit reads and writes, each written whole or not at all.

config.toml        the resolved configuration (`fit --config` reads it back as it is)
run.json           the field's box and eta_max, the dataset; a narrowed run's mark; where the
                   run came from: version, commit, command, device, driver, start and end
checkpoint.npz     parameters, Adam state, the best so far and the iteration
metrics.jsonl      one JSON line per iteration
init.json, start.json, field.npz, results.json, loss.png, slices.png, test/, surface.ply
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..calibrate import CENTRES_FILE, REGISTRATION_FILE
from ..errors import ClrefractError
from ..fields.base import Box
from ..imageio import atomic_path
from ..provenance import command, git_state, now, started, version
from .centres import KEY as CENTRES_KEY
from .config import FitConfig, to_toml
from .configure import load_config

# what a run folder holds that a new run would overwrite
RUN_FILES = (
    "checkpoint.npz",
    "field.npz",
    "results.json",
    "start.json",
    "run.json",
    CENTRES_FILE,
)
# what the start of a new run writes, removed again when the start fails
START_FILES = ("config.toml", "metrics.jsonl", "init.json", REGISTRATION_FILE, *RUN_FILES)
# run.json's record of where the run came from, kept when its other keys are rewritten
PROVENANCE = (
    "version",
    "commit",
    "commit_dirty",
    "command",
    "device",
    "driver",
    "started",
    "ended",
    "resumed",
)


@dataclass
class Best:
    """The parameters that scored the lowest held-out loss, and where."""

    loss: float = np.inf
    iteration: int = 0
    params: np.ndarray | None = None
    eta_max: float | None = None  # a hash grid's top there (its guide's index moves)

    @property
    def found(self) -> bool:
        return bool(np.isfinite(self.loss))


@dataclass
class Checkpoint:
    """What checkpoint.npz holds."""

    params: np.ndarray
    iteration: int
    resolution: int  # grid nodes per axis (0: no grid)
    best: Best
    adam: dict
    eta_max: float | None = None  # None in runs that predate it
    guide: dict = field(default_factory=dict)  # a hash grid's level set (guide_*)
    centres: dict = field(default_factory=dict)  # fitted camera centres (centres_*)


class RunFolder:
    """One run's files (rank 0's: it alone writes them under MPI)."""

    writes = True

    def __init__(self, path: Path):
        self.path = Path(path)
        self.opened = now()  # the start of this process's work on it, outside the CLI
        self.begun_here = False  # whether this process started the run (else resumed it)

    def __truediv__(self, name: str) -> Path:
        return self.path / name

    def __str__(self) -> str:
        return str(self.path)

    def __fspath__(self) -> str:  # a run folder is where a path is asked for
        return str(self.path)

    # --- config.toml -------------------------------------------------------------------------
    def write_config(self, cfg: FitConfig) -> None:
        # whole or not at all: under MPI the other ranks read it
        self.write_text("config.toml", to_toml(cfg))

    def config(self) -> FitConfig:
        return load_config(self.path / "config.toml", {})

    def has_config(self) -> bool:
        return (self.path / "config.toml").is_file()

    # --- run.json ---------------------------------------------------------------------------
    def meta(self) -> dict | None:
        """run.json, or None where there is none to read (a run that predates it)."""
        try:
            return json.loads((self.path / "run.json").read_text())
        except (OSError, ValueError):
            return None

    def write_meta(self, meta: dict) -> None:
        old = self.meta() or {}
        kept = {k: old[k] for k in PROVENANCE if k in old and k not in meta}
        self.write_text("run.json", json.dumps({**meta, **kept}, indent=2))

    def _session(self, device) -> dict:
        """This process: version, commit, command line, device (a runtime's DeviceInfo) and
        when it began."""
        commit, dirty = git_state()
        return {
            "version": version(),
            "commit": commit,
            "commit_dirty": dirty,
            "command": command(),
            "device": device.name if device is not None else None,
            "driver": f"{device.platform} {device.driver_version}" if device else None,
            "started": started(self.opened),
        }

    def record_start(self, device) -> None:
        """run.json of a new run gets where it came from (the run's own keys follow)."""
        self.begun_here = True
        self.write_meta({**(self.meta() or {}), **self._session(device)})

    def record_end(self, device) -> None:
        """run.json gets the end time; a run this process resumed (rather than started) also
        gets the resuming session, under "resumed". Nothing where there is no run.json."""
        meta = self.meta()
        if meta is None:
            return
        end = now()
        if not self.begun_here:
            meta.setdefault("resumed", []).append({**self._session(device), "ended": end})
        meta["ended"] = end
        self.write_meta(meta)

    def box_and_top(self) -> tuple[Box, float | None]:
        """The field's box and eta_max (None in runs that predate it) that run.json holds."""
        try:
            meta = json.loads((self.path / "run.json").read_text())
            return Box.from_dict(meta["box"]), meta.get("eta_max")
        except Exception as exc:  # noqa: BLE001 - any damage is the user's to know about
            raise ClrefractError(
                f"{self.path}: cannot read the run's box from run.json ({exc})"
            ) from None

    # --- checkpoint.npz ---------------------------------------------------------------------
    @property
    def checkpoint_path(self) -> Path:
        return self.path / "checkpoint.npz"

    def save_checkpoint(self, ckpt: Checkpoint) -> None:
        best = ckpt.best
        with atomic_path(self.checkpoint_path, suffix=".npz") as tmp:
            np.savez(
                tmp,
                params=ckpt.params,
                iteration=ckpt.iteration,
                shape=np.array([ckpt.resolution] * 3 if ckpt.resolution else [0]),
                best_loss=best.loss,
                best_iteration=best.iteration,
                best_params=ckpt.params if best.params is None else best.params,
                eta_max=ckpt.eta_max,
                best_eta_max=best.eta_max or ckpt.eta_max,
                **ckpt.adam,
                **ckpt.guide,
                **ckpt.centres,
            )

    def checkpoint(self) -> Checkpoint:
        path = self.checkpoint_path
        try:
            with np.load(path) as z:
                best = Best(float(z["best_loss"]), int(z["best_iteration"]), z["best_params"])
                tops = [float(z[k]) if k in z.files else None for k in ("eta_max", "best_eta_max")]
                best.eta_max = tops[1]
                if not best.found:
                    best = Best()
                return Checkpoint(
                    params=z["params"],
                    iteration=int(z["iteration"]),
                    resolution=int(z["shape"][0]),
                    best=best,
                    adam={k: z[k] for k in ("adam_m", "adam_v", "adam_t")},
                    eta_max=tops[0],
                    guide={k: z[k] for k in z.files if k.startswith("guide_")},
                    centres={k: z[k] for k in z.files if k.startswith(CENTRES_KEY)},
                )
        except FileNotFoundError:
            raise ClrefractError(f"{path}: no checkpoint to resume from") from None
        except Exception as exc:  # noqa: BLE001 - any damage is the user's to know about
            raise ClrefractError(f"{path}: cannot read checkpoint ({exc})") from None

    # --- metrics.jsonl ------------------------------------------------------------------------
    def open_metrics(self):
        return (self.path / "metrics.jsonl").open("a")

    def truncate_metrics(self, iteration: int) -> None:
        """Drop metric lines past the checkpoint being resumed from."""
        path = self.path / "metrics.jsonl"
        if not path.is_file():
            return
        keep = [
            ln
            for ln in path.read_text().splitlines()
            if ln.strip() and json.loads(ln)["iteration"] <= iteration
        ]
        self.write_text("metrics.jsonl", "".join(ln + "\n" for ln in keep))

    # --- the rest ---------------------------------------------------------------------------
    def save_field(self, field) -> None:
        field.save(self.path / "field.npz")  # each field writes itself atomically

    def write_json(self, name: str, value) -> None:
        self.write_text(name, json.dumps(value, indent=2))

    def record_start_loss(self, loss: float) -> None:
        """The start's held-out loss, beside its scores in start.json: a resumed run, and
        the run a model choice goes on with, find it there."""
        self.write_json("start.json", {**self._start_scores(), "val_loss": float(loss)})

    def start_loss(self) -> float | None:
        return self._start_scores().get("val_loss")

    def _start_scores(self) -> dict:
        try:
            return json.loads((self.path / "start.json").read_text())
        except (OSError, ValueError):  # runs from before start.json, or a damaged one
            return {}

    def write_text(self, name: str, text: str) -> None:
        target = self.path / name
        with atomic_path(target, suffix=target.suffix) as tmp:
            tmp.write_text(text)

    def holds_run(self) -> bool:
        return any((self.path / name).exists() for name in RUN_FILES)


class FollowerFolder(RunFolder):
    """An MPI rank other than 0: it reads rank 0's run folder and writes nothing of it (its
    metrics and field go to a scratch folder that is thrown away)."""

    writes = False

    def __init__(self, run: Path, scratch: Path):
        super().__init__(run)
        self.scratch = Path(scratch)

    def save_checkpoint(self, ckpt: Checkpoint) -> None:
        pass

    def open_metrics(self):
        return (self.scratch / "metrics.jsonl").open("a")

    def truncate_metrics(self, iteration: int) -> None:
        pass

    def write_text(self, name: str, text: str) -> None:
        (self.scratch / name).write_text(text)

    def save_field(self, field) -> None:
        field.save(self.scratch / "field.npz")

    def meta(self) -> dict | None:
        return None  # a narrowed run is judged by rank 0
