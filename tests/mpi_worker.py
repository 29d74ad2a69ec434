"""Run by tests/test_mpi.py under `mpiexec -n N`: one rank's side of a gradient or a fit.

python mpi_worker.py grad DATASET OUT.npz       the sharded gradient of a fixed batch
python mpi_worker.py stop DATASET RUN CONFIG.toml STOP
                                                a fit that stops after iteration STOP
                                                (as Ctrl-C would, on every rank)
"""

import sys
from pathlib import Path

import numpy as np


def gradient_case(dataset: Path):
    """Engine, rays and parameters of the gradient comparison (shared with the test)."""
    from clrefract.dataset import Dataset
    from clrefract.fields.voxel import VoxelGrid
    from clrefract.gradient import GradientEngine
    from clrefract.tracer import TraceSettings

    ds = Dataset(dataset)
    origins, dirs, rgb = ds.rays_and_pixels("train")
    rng = np.random.default_rng(5)
    idx = rng.integers(0, len(origins), 3000)  # not a multiple of the chunk count
    field = VoxelGrid(np.ones((16, 16, 16)), ds.box, eta_max=1.6)
    # a lumpy field, so that rays bend and every chunk has a different gradient
    params = 1.0 + 0.04 * rng.uniform(size=16**3)
    engine = GradientEngine(field, ds.box, TraceSettings(step=2.0, precision="float64"))
    engine.set_params(params)
    return engine, origins[idx], dirs[idx], rgb[idx], ds.envmap()


def main() -> None:
    from clrefract import parallel

    mode, dataset = sys.argv[1], Path(sys.argv[2])
    ranks = parallel.world()
    if mode == "grad":
        engine, o, d, t, env = gradient_case(dataset)
        chunks = int(sys.argv[4]) if len(sys.argv) > 4 else 16
        sharded = parallel.ShardedEngine(engine, ranks, chunks)
        r = sharded.loss_and_grad(o, d, t, env)
        comm = ranks.comm
        grads = comm.allgather(r.grad) if comm is not None else [r.grad]
        traced = comm.allgather(sharded.rays_traced) if comm is not None else [len(o)]
        if ranks.root:
            np.savez(
                sys.argv[3],
                grad=r.grad,
                loss=r.loss,
                status=r.status,
                radiance=r.radiance,
                size=ranks.size,
                traced=traced,  # rays each rank traced
                # every rank must hold the very same gradient (their Adam steps must agree)
                spread=max(float(np.abs(g - r.grad).max()) for g in grads),
            )
    elif mode == "stop":
        import clrefract.fit as fitmod
        from clrefract.errors import ClrefractError

        real_step, stop = fitmod.Fit.step, int(sys.argv[5])

        def step_then_stop(self):
            m = real_step(self)
            if self.it == stop:
                raise KeyboardInterrupt  # what a second Ctrl-C raises, on every rank at once
            return m

        fitmod.Fit.step = step_then_stop
        cfg = fitmod.load_config(Path(sys.argv[4]), {})
        try:
            fitmod.run_fit(dataset, Path(sys.argv[3]), cfg)
        except ClrefractError as exc:
            print(f"rank {ranks.rank}: {exc}")


if __name__ == "__main__":
    main()
