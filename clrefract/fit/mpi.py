"""`clrefract fit`: one process, or several under mpiexec. There rank 0 prepares the run
folder (start or resume), which leaves its checkpoint (a start writes that of iteration
0); the other ranks load that checkpoint, exactly as a resumed run would, so all start from
the same parameters, and write nothing of the run (parallel.py splits each batch over the
ranks)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from ..errors import ClrefractError
from ..parallel import check_chunks, world
from .loop import train
from .runfolder import FollowerFolder, RunFolder
from .session import prepare_fit
from .trainer import Fit


def run_fit(dataset, out, cfg, resume: bool = False, stream=None) -> dict:
    """Fit (a new run, or `resume` the one in `out`); its results ({} on ranks but 0)."""
    if world().size == 1:
        return train(prepare_fit(dataset, out, cfg, resume, stream))
    return run_fit_ranks(dataset, out, cfg, resume, stream)


def run_fit_ranks(dataset, out, cfg, resume: bool = False, stream=None) -> dict:
    ranks = world()
    out = Path(out)
    check_chunks(cfg.chunks)  # on every rank, before any of them waits for another
    try:
        if ranks.root:
            error = None
            try:
                fit = prepare_fit(dataset, out, cfg, resume, stream)
            except ClrefractError as exc:
                error = str(exc)
            ranks.share_from_root(error)
            if error is not None:
                raise ClrefractError(error)
            return train(fit)
        error = ranks.share_from_root(None)
        if error is not None:  # rank 0 names the problem; the others just stop
            raise ClrefractError(f"rank {ranks.rank}: rank 0 failed")
        cfg = RunFolder(out).config() if resume else cfg
        scratch = tempfile.TemporaryDirectory(prefix=f"clrefract-rank{ranks.rank}-")
        with open(os.devnull, "w") as quiet, scratch:
            folder = FollowerFolder(out, Path(scratch.name))
            fit = Fit(dataset, out, cfg, stream=quiet, folder=folder)
            fit.load_checkpoint()
            train(fit)
        return {}
    except ClrefractError:
        raise  # every rank meets these at the same point (an interrupt, a bad number)
    except BaseException:
        import traceback

        traceback.print_exc()
        ranks.abort(1)
        raise
