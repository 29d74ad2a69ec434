"""A fit's first step where the dataset asks for it (`--register`): the panorama's rotation,
each view's exposure and white balance, and each camera's rotation, fitted to the background
pixels (calibrate.register) and kept in the run folder, which every later reader of the run
applies to its dataset (Fit, eval, report, render, refine-positions). The dataset's own files
are not touched: `dataset register-env --write` is the way to change them."""

from __future__ import annotations

import shutil

import numpy as np

from ..calibrate import REGISTRATION_FILE, NoBackground, mismatch, register
from ..dataset import Dataset, box_of
from .config import FitConfig
from .runfolder import RunFolder


def register_run(dataset, folder: RunFolder, cfg: FitConfig, stream) -> None:
    """Register the dataset into folder's registration.json where `cfg.register` asks for it
    ("auto": where its background differs from its panorama as stated); a run folder that
    holds one already (a start taken up again) keeps it."""
    if cfg.register == "off" or (folder / REGISTRATION_FILE).is_file():
        return
    given = bool(cfg.box)
    ds = Dataset(dataset, box=box_of(cfg.box) if given else None)
    if cfg.register != "on":  # auto
        try:
            found = mismatch(ds, given, cfg.seed)
        except NoBackground as exc:  # nothing to register on (bad frames stop the fit here)
            stream.write(f"register: not checked ({exc})\n")
            return
        if not found.needs_registration():
            return
        stream.write(
            f"register: the background differs from the panorama as {ds.root} states it "
            f"({found.words()}): fitting the panorama's rotation, the exposures and the "
            "cameras' rotations to it (--register off: as stated)\n"
        )
    info, corrections = register(ds, exposure=True, given=given, seed=cfg.seed, poses=True)
    folder.write_json(REGISTRATION_FILE, {**corrections.to_dict(), "found": info})
    turns = [t for t in info.get("view_turns_deg", []) if t is not None]
    gains = [np.log(f["exposure_scale"]) for f in info.get("frames", [])]
    stream.write(
        f"register: panorama turned by {info['turned_deg']:.2f} degrees, RMS log residual "
        f"{info['residual_log_rms_before']:.3f} -> {info['residual_log_rms']:.3f}; cameras "
        f"turned by up to {max(turns, default=0.0):.2f} degrees; exposures "
        f"{np.exp(min(gains, default=0.0)):.3g} to {np.exp(max(gains, default=0.0)):.3g} "
        f"(kept in {folder / REGISTRATION_FILE})\n"
    )


def share_registration(folder: RunFolder, sub: RunFolder) -> None:
    """A candidate model's run folder takes its parent run's registration."""
    src = folder / REGISTRATION_FILE
    if src.is_file() and not (sub / REGISTRATION_FILE).is_file():
        shutil.copy2(src, sub / REGISTRATION_FILE)
