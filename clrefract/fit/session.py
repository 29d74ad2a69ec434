"""A run folder from the command line's point of view: start a run in a new folder, resume
one, give a line search more steps, read a run's field at its latest checkpoint."""

from __future__ import annotations

import math
import shutil
import sys
import time
from dataclasses import replace
from pathlib import Path

from .. import start_losses
from ..calibrate import REGISTRATION_FILE
from ..dataset import read_scene
from ..errors import ClrefractError
from ..imageio import ensure_out_dir
from .centres import centres_setting
from .config import FitConfig
from .kinds import candidate_config, graded_candidate, guide_config, kind_of
from .registration import register_run, share_registration
from .runfolder import START_FILES, RunFolder
from .starts import NoObject
from .trainer import Fit


def prepare_fit(dataset: Path, out: Path, cfg: FitConfig, resume: bool = False, stream=None) -> Fit:
    """A run ready to go: a new run folder with its field at the start, or a resumed one."""
    folder = RunFolder(out)
    if resume:
        if not folder.has_config():
            if start_losses.count(folder.path):
                raise ClrefractError(
                    f"{out}: its start was interrupted before the run began; the same "
                    "command without --resume takes up the losses its search kept"
                )
            raise ClrefractError(f"{out}: no run to resume (config.toml missing)")
        cfg = folder.config()
        ensure_out_dir(folder.path, "run folder")
        fit = Fit(dataset, out, cfg, stream=stream, folder=folder)
        fit.load_checkpoint()
        folder.truncate_metrics(fit.it)
        return fit
    if folder.holds_run():
        raise ClrefractError(
            f"{out} already holds a run: use --resume to continue it, or another --out"
        )
    fresh_folder = not folder.path.exists()
    ensure_out_dir(folder.path, "run folder")
    had = {name for name in START_FILES if (folder / name).exists()}
    try:
        register_run(dataset, folder, cfg, stream or sys.stderr)
        say_centres(dataset, folder, cfg, stream or sys.stderr)
        return start_run(dataset, folder, cfg, stream)
    except BaseException:
        # a start that failed (or was interrupted) leaves no run behind, only its search's
        # losses, which the same command run again takes up
        for name in START_FILES:
            if name not in had:
                (folder / name).unlink(missing_ok=True)
        kept = start_losses.count(folder.path)
        if kept:
            (stream or sys.stderr).write(
                f"start: {kept} losses of its search kept in {folder / start_losses.NAME}; "
                "the same command takes them up\n"
            )
        if fresh_folder and not any(folder.path.iterdir()):
            folder.path.rmdir()
        raise


def say_centres(dataset: Path, folder: RunFolder, cfg: FitConfig, stream) -> None:
    """Settle camera_centres = "auto" for the run and its candidates, saying where it fits
    them."""
    chosen = centres_setting(cfg, read_scene(Path(dataset)), (folder / REGISTRATION_FILE).is_file())
    said, cfg.camera_centres = cfg.camera_centres, chosen
    if chosen != said and chosen == "fitted":
        stream.write(
            "camera centres: fitted with the field, as a real capture's need "
            "(--camera-centres recorded: as the dataset states them)\n"
        )


def start_run(
    dataset: Path, folder: RunFolder, cfg: FitConfig, stream, say_walls: bool = True
) -> Fit:
    from ..report import write_start_report

    if kind_of(cfg).candidates:
        return choose_model(dataset, folder, cfg, stream)
    fit = Fit(dataset, folder.path, cfg, stream=stream, folder=folder)
    folder.write_config(cfg)
    folder.write_text("metrics.jsonl", "")
    t0 = time.perf_counter()
    fit.start(say_walls)
    folder.write_config(fit.cfg)  # with what the start resolved
    write_start_report(fit, time.perf_counter() - t0)
    folder.write_meta(  # the field's box: a level set's is the object's
        {
            "dataset": str(Path(dataset).resolve()),
            "box": fit.box.to_dict(),
            "eta_max": fit.eta_max,
            **({"box_walls": fit.walls.to_dict()} if fit.walls else {}),
        }
    )
    fit.save_checkpoint()  # a run killed before its first step resumes from its start
    return fit


# share of its iterations each candidate model runs before the held-out views choose: a
# start alone misjudges a graded medium, whose voxel grid starts from empty space (the hull
# filled with glass scores better than air on every graded development scene) and
# descends from there
PROBE_SHARE = 0.1


def probe_length(cfg: FitConfig) -> int:
    """The iterations a candidate runs before the choice: PROBE_SHARE of its run, in whole
    validations, short of its end (whose finish only the chosen one runs)."""
    every = max(cfg.validate_every, 1)
    probe = every * max(1, math.ceil(PROBE_SHARE * cfg.iterations / every))
    return max(0, min(cfg.iterations - 1, probe))


# a graded interior is chosen where its probe's best held-out loss is below this share of
# its surface's with one index. Quick protocol, 100 steps of each: nine glass scenes 1.01 (two
# bodies) to 2.08 (a cut stone), graded glass 0.52 to 0.61 (grin-ball); graded cut stones
# spread from 0.75 to 1.02 (docs/design/graded-interior.md)
GRADED_SHARE = 0.9


class Candidates:
    """The model choice's candidate runs in RUN/candidates/NAME, each started and probed
    (one process; under MPI its start alone), and their best held-out losses on the same
    held-out rays."""

    def __init__(self, dataset: Path, folder: RunFolder, stream):
        from ..parallel import world

        self.dataset, self.folder, self.stream = dataset, folder, stream
        self.out = stream or sys.stderr
        self.probing = world().size == 1
        self.scores, self.probes, self.refused = {}, {}, {}

    def run(self, name: str, cfg: FitConfig, say_walls: bool) -> None:
        from .loop import FitDiverged, train

        sub = RunFolder(self.folder.path / "candidates" / name)
        ensure_out_dir(sub.path, "run folder")
        share_registration(self.folder, sub)
        self.out.write(f"model: starting {name}\n")
        if not sub.holds_run():  # a candidate started before is taken up
            try:
                start_run(self.dataset, sub, cfg, self.stream, say_walls)
            except NoObject as exc:  # a gas has no surface for an interface to start on
                self.refused[name] = str(exc)
                self.out.write(f"model: {name} cannot start: {exc}\n")
                return
        cand = prepare_fit(self.dataset, sub.path, None, resume=True, stream=self.stream)
        if self.probing:
            try:
                train(cand, until=probe_length(cand.cfg))
            except FitDiverged as exc:  # it keeps its best; the other may do better
                self.out.write(f"model: {name}: {exc}\n")
            self.probes[name] = cand.it
        self.scores[name] = float(cand.best.loss if cand.best.found else cand.held_out_loss())


def choose_model(dataset: Path, folder: RunFolder, cfg: FitConfig, stream) -> Fit:
    """Start each candidate kind in RUN/candidates/KIND, run it for its probe_length, and go
    on, in RUN, with the one whose best held-out loss is lowest; with interior = "auto", a
    surface chosen so is then tried with a quadratic interior (KIND-graded), kept below
    GRADED_SHARE of its loss. model.json says what each scored."""
    names = kind_of(cfg).usable(cfg)
    if len(names) == 1 and graded_candidate(cfg, names[0]) is None:
        return start_run(dataset, folder, candidate_config(cfg, names[0]), stream)
    cands = Candidates(dataset, folder, stream)
    for name in names:
        cands.run(name, candidate_config(cfg, name), name == names[0])
    scores = cands.scores
    if not scores:
        raise ClrefractError(next(iter(cands.refused.values())))
    best = min(scores, key=scores.get)
    graded = graded_candidate(cfg, best)
    if graded is not None:
        cands.run(f"{best}-graded", graded, False)
        if scores.get(f"{best}-graded", math.inf) < GRADED_SHARE * scores[best]:
            best = f"{best}-graded"
    for name in START_FILES:
        src = folder.path / "candidates" / best / name
        if src.is_file():
            shutil.copy2(src, folder.path / name)
    folder.write_json(
        "model.json",
        {
            "chosen": best,
            "held_out_loss": scores,
            "probe_iterations": cands.probes,
            "refused": cands.refused,
        },
    )
    cands.out.write(
        "model: "
        + ", ".join(f"{k} held-out loss {v:.5g}" for k, v in scores.items())
        + f": going on with {best}\n"
    )
    return prepare_fit(dataset, folder.path, None, resume=True, stream=stream)


def extend_run(out: Path, iterations: int) -> None:
    """Give a line-search run more steps before it is resumed: its config.toml is the
    record of what it runs. Adam's rates decay over the run's whole length, so its length
    stays."""
    folder = RunFolder(out)
    cfg = folder.config()
    if iterations == cfg.iterations:
        return
    if cfg.optimizer != "line-search":
        raise ClrefractError(
            f"{out}: --resume --iterations {iterations}: an Adam run's rates decay over its "
            f"{cfg.iterations} iterations; start a new run to train longer"
        )
    if iterations < cfg.iterations:
        raise ClrefractError(
            f"{out}: --resume --iterations {iterations}: the run has {cfg.iterations} steps, "
            "and --resume can only add steps"
        )
    folder.write_config(replace(cfg, iterations=iterations))


def field_from_run(run: Path):
    """The field of a run folder at its latest checkpoint (for rendering a run in progress):
    a hash grid's guide where the grid is fitted to it only at the end (a level set's with
    refit = "best", a graded medium's voxel grid)."""
    folder = RunFolder(run)
    cfg = folder.config()
    try:
        ckpt = folder.checkpoint()
        box, top = folder.box_and_top()
    except ClrefractError as exc:
        raise ClrefractError(f"{run}: cannot read the run's checkpoint ({exc})") from None
    params, res, top = ckpt.params, ckpt.resolution, ckpt.eta_max or top
    if ckpt.guide and kind_of(cfg).shows_guide(cfg):
        cfg, params = guide_config(cfg, top), ckpt.guide["guide_params"]
        top, res = float(ckpt.guide["guide_eta_max"]), int(ckpt.guide["guide_res"])
    field = kind_of(cfg).run_field(cfg, box, top, res)
    field.set_data(params)
    return field
