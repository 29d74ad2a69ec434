"""Data-parallel fitting over MPI ranks (mpi4py, the optional `[mpi]` extra).

`mpiexec -n N clrefract fit ...` splits every batch over N processes, each tracing on its
own OpenCL device. Without a launcher (or without mpi4py) nothing here is used: one process
fits exactly as before.

Why fixed chunks: the backward kernel adds each ray's gradient with atomics, so the sum over
a batch is only defined up to rounding, and an Allreduce may add ranks in any order. To keep
the result independent of the number of ranks, a batch is cut into `chunks` pieces (a power
of two) that depend on the batch alone; rank r owns a contiguous run of them. Chunk gradients
are added along one fixed binary tree over the chunks: each rank adds the whole subtrees it
owns, the subtree sums travel by Allgatherv, and every rank finishes the same tree in the same
order. One rank and two ranks thus add the same numbers in the same order, and every rank
holds bit-identical gradients, so every rank's Adam step leaves identical parameters.

Rank 0 alone writes the run folder; the others read its checkpoint and keep their own
copies of per-run files in a scratch folder that is removed at the end.
"""

from __future__ import annotations

import os
import sys
import time
from dataclasses import dataclass

import numpy as np

from .errors import ClrefractError
from .limits import host_cores

# variables that MPI launchers set in each process they start (OpenMPI, MPICH/Hydra and
# Intel MPI, PMI-2 and PMIx under srun); a plain `python` leaves them unset, and importing
# mpi4py there would start MPI for nothing (OpenMPI's singleton start is slow, or fails)
_LAUNCHER_VARS = ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMI_RANK", "PMIX_RANK", "MPI_LOCALNRANKS")
_SIZE_VARS = ("OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "MPI_LOCALNRANKS")


@dataclass
class Ranks:
    """This process's place among the fit's processes."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0  # among the ranks on this machine: picks the device
    local_size: int = 1
    comm: object = None  # mpi4py communicator; None for one process

    @property
    def root(self) -> bool:
        return self.rank == 0

    def share_from_root(self, value):
        """Rank 0's value on every rank, once rank 0 gets there. The others wait in a
        non-blocking barrier, sleeping between tests: OpenMPI's blocking calls spin a core,
        which would steal it from rank 0 while it works (a start's line searches take
        minutes)."""
        request = self.comm.Ibarrier()
        while not request.Test():
            time.sleep(0.02)
        return self.comm.bcast(value, root=0)

    def abort(self, code: int = 1) -> None:
        """End every rank: one that fails alone would leave the others waiting forever."""
        if self.comm is not None and self.size > 1:
            sys.stderr.flush()
            self.comm.Abort(code)


_WORLD: Ranks | None = None


def launched() -> bool:
    """Whether an MPI launcher started this process (CLREFRACT_MPI=0/1 overrides)."""
    force = os.environ.get("CLREFRACT_MPI", "")
    if force in ("0", "1"):
        return force == "1"
    return any(os.environ.get(v) for v in _LAUNCHER_VARS)


def world() -> Ranks:
    """The fit's processes: all of MPI_COMM_WORLD under a launcher, else this one alone."""
    global _WORLD
    if _WORLD is not None:
        return _WORLD
    if not launched():
        _WORLD = Ranks()
        return _WORLD
    try:
        from mpi4py import MPI
    except ImportError:
        size = max((int(os.environ.get(v) or 1) for v in _SIZE_VARS), default=1)
        if size > 1:  # N independent fits would overwrite one run folder
            raise ClrefractError(
                f"started by an MPI launcher with {size} ranks, but mpi4py is not "
                "installed: `pip install 'clrefract[mpi]'` (and an MPI library: OpenMPI or "
                "MPICH from the OS packages)"
            ) from None
        _WORLD = Ranks()
        return _WORLD
    comm = MPI.COMM_WORLD
    local = comm.Split_type(MPI.COMM_TYPE_SHARED)  # the ranks that share this machine
    _WORLD = Ranks(comm.rank, comm.size, local.rank, local.size, comm)
    if _WORLD.local_size > 1:
        share_cores(_WORLD.local_size)
    return _WORLD


def share_cores(processes: int) -> None:
    """Processes on one machine that run on its CPU (PoCL: MPI ranks, test workers) split its
    cores between them rather than each starting a thread per core, as do their hash-grid
    distillations' threads. Must run before OpenCL starts; the user's own settings win."""
    cores = max(1, host_cores() // max(1, processes))
    for var in ("POCL_CPU_MAX_CU_NUM", "POCL_MAX_PTHREAD_COUNT", "CLREFRACT_HOST_THREADS"):
        os.environ.setdefault(var, str(cores))


def device_for(selector: str | None, ranks: Ranks | None = None) -> str | None:
    """The OpenCL device of this rank.

    selector: "" (or None) picks, by local rank, among the machine's GPUs (round-robin),
    else the default device; a comma-separated list ("0:0,0:1" or name substrings) is
    indexed by local rank; a single selector is used by every rank."""
    ranks = ranks or world()
    parts = [p.strip() for p in (selector or "").split(",") if p.strip()]
    if len(parts) > 1:
        return parts[ranks.local_rank % len(parts)]
    if parts:
        return parts[0]
    if ranks.size == 1 or os.environ.get("PYOPENCL_CTX"):
        return None
    from .runtime import list_devices

    gpus = [i for i in list_devices() if i.kind == "gpu"]
    return gpus[ranks.local_rank % len(gpus)].selector if gpus else None


# --- the fixed-order sum ---------------------------------------------------------------------
def owned(rank: int, size: int, chunks: int) -> range:
    """The chunks of a rank: a contiguous run, as even as the counts allow."""
    return range(rank * chunks // size, (rank + 1) * chunks // size)


def subtrees(block: range, chunks: int) -> list[tuple[int, int]]:
    """The largest aligned subtrees (start, width) of the binary tree over `chunks` leaves
    that tile `block`: the sums a rank can finish on its own."""
    out, a = [], block.start
    while a < block.stop:
        w = a & -a if a else chunks  # the widest subtree that starts at a
        while a + w > block.stop:
            w //= 2
        out.append((a, w))
        a += w
    return out


def tree_sum(start: int, width: int, known: dict) -> np.ndarray:
    """Sum of leaves [start, start + width) along the fixed tree: a known subtree sum, or
    its left half plus its right half."""
    hit = known.get((start, width))
    if hit is not None:
        return hit
    if width == 1:
        raise KeyError(f"chunk {start} is missing")
    half = width // 2
    return tree_sum(start, half, known) + tree_sum(start + half, half, known)


def check_chunks(chunks: int) -> None:
    if chunks < 1 or chunks & (chunks - 1):
        raise ClrefractError(f"chunks must be a power of two, got {chunks}")


class ShardedEngine:
    """A GradientEngine whose batches are split over MPI ranks; it answers everything else
    (tracer, field, set_params) as the engine it wraps."""

    def __init__(self, engine, ranks: Ranks, chunks: int = 16):
        check_chunks(chunks)
        self.engine, self.ranks, self.chunks = engine, ranks, chunks
        self.comm_seconds = 0.0  # time spent in collectives, for the benchmark
        self.rays_traced = 0  # by this rank: its share of the batches

    def __getattr__(self, name):
        return getattr(self.engine, name)

    def loss_and_grad(self, origins, dirs, targets, env, weights=None, group=1):
        from .gradient import GradientResult

        n, c = len(origins), self.chunks
        if group > 1 and (n // group) % c:
            raise ValueError(f"{n // group} ray groups do not split into {c} chunks")
        # fixed by the batch alone, not by the ranks; whole blocks of the srgb420 loss
        unit = 4 if group == 1 and self.engine.loss_space == "srgb420" else 1
        edges = np.arange(c + 1) * (n // unit) // c * unit
        edges[-1] = n
        n_par = len(self.engine.field.data())
        weights = np.ones(n) if weights is None else np.asarray(weights)
        leaves, rays = {}, []
        for j in owned(self.ranks.rank, self.ranks.size, c):
            s = slice(edges[j], edges[j + 1])
            m = s.stop - s.start
            leaf = np.zeros(n_par + 1)  # gradient, then the chunk's share of the loss
            self.rays_traced += m
            if m:
                try:
                    r = self.engine.loss_and_grad(
                        origins[s], dirs[s], targets[s], env, weights[s], group
                    )
                    # each chunk's loss is a mean over its own rays: weight it by its share
                    leaf[:n_par], leaf[n_par] = r.grad * (m / n), r.loss * (m / n)
                    grad_o = r.origin_grad * (m / n)
                    rays.append((j, r.radiance, r.status, r.drift, r.growth, r.steps, grad_o))
                except FloatingPointError:
                    # not raised here alone: the NaN reaches every rank through the sum
                    leaf[:] = np.nan
                    rays.append((j, None, None, None, None, 0, None))
            leaves[(j, 1)] = leaf
        mine = subtrees(owned(self.ranks.rank, self.ranks.size, c), c)
        sums = [tree_sum(a, w, leaves) for a, w in mine]
        t0 = time.perf_counter()
        known, rays = self.gather(mine, sums, n_par + 1, rays)
        self.comm_seconds += time.perf_counter() - t0
        total = tree_sum(0, c, known)
        if not np.all(np.isfinite(total)):
            raise FloatingPointError("non-finite loss or gradient")
        rays.sort(key=lambda item: item[0])
        cat = [np.concatenate([item[k] for item in rays]) for k in (1, 2, 3, 4, 6)]
        steps = sum(item[5] for item in rays)
        return GradientResult(float(total[n_par]), total[:n_par], *cat[:3], steps, *cat[3:])

    def gather(self, mine, sums, length, rays):
        """Every rank's subtree sums (Allgatherv of the float64 vectors) and per-ray results
        (pickled; a few numbers per ray)."""
        comm = self.ranks.comm
        if comm is None:  # one process: nothing to exchange
            return dict(zip(mine, sums)), rays
        from mpi4py import MPI

        layout = comm.allgather(mine)
        counts = [len(x) * length for x in layout]
        displs = np.concatenate([[0], np.cumsum(counts)[:-1]]).tolist()
        send = np.concatenate(sums) if sums else np.empty(0)
        recv = np.empty(sum(counts))
        comm.Allgatherv(send, [recv, counts, displs, MPI.DOUBLE])
        keys = [key for part in layout for key in part]
        known = {key: recv[i * length : (i + 1) * length] for i, key in enumerate(keys)}
        return known, [item for part in comm.allgather(rays) for item in part]


def shard(engine, chunks: int = 16, ranks: Ranks | None = None):
    """The engine itself for one process; split over the ranks under MPI."""
    ranks = ranks or world()
    return engine if ranks.size == 1 else ShardedEngine(engine, ranks, chunks)
