"""Data-parallel fitting over MPI: the fixed-order sum, device picking, and `mpiexec -n 2`
runs that must agree with one process (gradient to 1e-12, a short fit, resume across rank
counts)."""

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from clrefract import parallel
from clrefract.errors import ClrefractError
from clrefract.fit import load_config, run_fit
from clrefract.synth import MakeOptions, make_dataset

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from mpi_worker import gradient_case  # noqa: E402


# --- the fixed-order sum, without MPI ---------------------------------------------------
@pytest.mark.parametrize("chunks", [1, 8, 16])
def test_subtrees_tile_each_ranks_block(chunks):
    for size in range(1, chunks + 1):
        seen = []
        for rank in range(size):
            block = parallel.owned(rank, size, chunks)
            for a, w in parallel.subtrees(block, chunks):
                assert w & (w - 1) == 0 and a % w == 0  # an aligned subtree of the tree
                seen.extend(range(a, a + w))
        assert seen == list(range(chunks))


def test_tree_sum_is_the_same_for_every_rank_count():
    """Leaves of wildly different sizes: any change of order changes the rounding."""
    rng = np.random.default_rng(1)
    chunks = 16
    leaves = [rng.normal(size=50) * 10.0 ** rng.integers(-8, 9, 50) for _ in range(chunks)]
    sums = []
    for size in (1, 2, 3, 5, 8, 16):
        known = {}
        for rank in range(size):
            mine = {(j, 1): leaves[j] for j in parallel.owned(rank, size, chunks)}
            block = parallel.owned(rank, size, chunks)
            for a, w in parallel.subtrees(block, chunks):
                known[(a, w)] = parallel.tree_sum(a, w, mine)
        sums.append(parallel.tree_sum(0, chunks, known))
    for s in sums[1:]:
        assert np.array_equal(s, sums[0])  # bit for bit
    # the check above can fail: adding in plain order rounds differently
    assert not np.array_equal(np.sum(leaves, axis=0), sums[0])


def test_chunks_must_be_a_power_of_two():
    with pytest.raises(ClrefractError, match="power of two"):
        parallel.check_chunks(12)


def test_device_by_local_rank():
    ranks = parallel.Ranks(rank=3, size=4, local_rank=1, local_size=2)
    assert parallel.device_for("0:0, 0:1", ranks) == "0:1"
    assert parallel.device_for("0:0,0:1,0:2", parallel.Ranks(0, 4, 2, 4)) == "0:2"
    assert parallel.device_for("0:1", ranks) == "0:1"  # one device for every rank


def test_one_process_is_untouched(monkeypatch):
    """Without a launcher nothing changes: the engine is not wrapped."""
    for var in parallel._LAUNCHER_VARS + ("CLREFRACT_MPI",):
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(parallel, "_WORLD", None)
    assert not parallel.launched() and parallel.world().size == 1
    engine = object()
    assert parallel.shard(engine) is engine


# --- mpiexec ----------------------------------------------------------------------------
def _mpiexec() -> list[str]:
    exe = shutil.which("mpiexec")
    try:
        import mpi4py  # noqa: F401
    except ImportError:
        exe = None
    if exe is None:
        pytest.skip("mpiexec or mpi4py is not installed (tools/setup.sh installs both)")
    version = subprocess.run([exe, "--version"], capture_output=True, text=True).stdout
    if "Open MPI" in version or "OpenRTE" in version:
        # two ranks on however few cores; root in containers
        return [exe, "--oversubscribe", "--allow-run-as-root"]
    return [exe]


def _run(n: int, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    env.pop("CLREFRACT_MPI", None)
    env["PYTHONPATH"] = os.pathsep.join([str(HERE.parent), env.get("PYTHONPATH", "")])
    env.update(
        OMPI_MCA_mpi_yield_when_idle="1",  # waiting ranks give up the CPU
        OMPI_MCA_btl="self,vader",  # one machine: shared memory, no network
        OMPI_MCA_btl_vader_single_copy_mechanism="none",  # containers forbid ptrace
        OMPI_ALLOW_RUN_AS_ROOT="1",
        OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1",
    )
    cmd = [*_mpiexec(), "-n", str(n), sys.executable, *args]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=300)
    if check:
        assert out.returncode == 0, out.stdout + out.stderr
    return out


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    out = tmp_path_factory.mktemp("mpi")
    make_dataset("luneburg", out, MakeOptions(views=12, res=32, env_width=512, volume_res=16))
    return out


def test_two_ranks_give_the_one_rank_gradient(dataset, tmp_path):
    _run(2, str(HERE / "mpi_worker.py"), "grad", str(dataset), str(tmp_path / "g2.npz"))
    two = np.load(tmp_path / "g2.npz")
    assert int(two["size"]) == 2
    assert two["traced"].tolist() == [1500, 1500]  # each rank traced its half, no more
    assert float(two["spread"]) == 0.0  # both ranks hold the very same numbers
    engine, o, d, t, env = gradient_case(dataset)
    one = engine.loss_and_grad(o, d, t, env)  # one process, no chunks at all
    scale = np.abs(one.grad).max()
    assert scale > 1e-4 and np.count_nonzero(one.grad) > 1000  # a gradient worth comparing
    assert np.abs(two["grad"] - one.grad).max() < 1e-12
    assert abs(float(two["loss"]) - one.loss) < 1e-12
    assert np.array_equal(two["status"], one.status)  # per-ray results back in ray order
    assert np.abs(two["radiance"] - one.radiance).max() < 1e-12


def test_chunks_keep_the_420_loss_blocks_whole(dataset):
    """Chunks end on 2 x 2 blocks under the srgb420 loss (3000 rays in 16 chunks: 187.5 a
    chunk), so the sharded loss and gradient are the whole batch's, as one rank computes it."""
    engine, o, d, t, env = gradient_case(dataset)
    engine.loss_space = "srgb420"
    one = engine.loss_and_grad(o, d, t, env)
    split = parallel.ShardedEngine(engine, parallel.Ranks(), chunks=16).loss_and_grad(o, d, t, env)
    assert one.loss > 1e-4 and abs(split.loss - one.loss) < 1e-12 * one.loss
    assert np.abs(split.grad - one.grad).max() < 1e-12 * np.abs(one.grad).max()


def _cfg(path: Path) -> Path:
    cfg = load_config(
        None,
        dict(
            field="voxel",
            init="empty",
            res=16,
            res_schedule=(),
            iterations=6,
            batch=2048,
            step=2.0,
            lr=0.003,
            checkpoint_every=3,
            validate_every=3,
            test_views=1,
            precision="float64",
        ),
    )
    from clrefract.fit import to_toml

    path.write_text(to_toml(cfg))
    return path


def _params(run: Path) -> np.ndarray:
    with np.load(run / "checkpoint.npz") as z:
        assert int(z["iteration"]) == 6
        return z["params"]


def _losses(run: Path) -> list[float]:
    return [json.loads(ln)["loss"] for ln in (run / "metrics.jsonl").read_text().splitlines()]


def test_two_rank_fit_and_resume_across_rank_counts(dataset, tmp_path, monkeypatch):
    import clrefract.fit as fitmod

    toml = _cfg(tmp_path / "cfg.toml")
    cfg = load_config(toml, {})
    one = tmp_path / "one"
    run_fit(dataset, one, cfg, stream=open(os.devnull, "w"))  # noqa: SIM115
    ref = _params(one)
    assert np.abs(ref - 1.0).max() > 1e-3  # the fit moved

    # the CLI under mpiexec: the same fit on two ranks; rank 0 alone writes and reports
    clrefract = Path(sys.executable).with_name("clrefract")
    # (the console script is a Python file: run by this interpreter, whatever its #! line)
    cli = [str(clrefract)] if clrefract.is_file() else ["-m", "clrefract.cli"]
    two = tmp_path / "two"
    out = _run(2, *cli, "fit", str(dataset), "--out", str(two), "--config", str(toml))
    assert out.stdout.count('"psnr_gain_over_start"') == 1, out.stdout  # one report, from rank 0
    assert np.abs(_params(two) - ref).max() < 1e-10
    assert np.allclose(_losses(two), _losses(one), rtol=1e-10, atol=0)

    # two ranks stop after iteration 4 (checkpoint at 3); one rank finishes the run
    a = tmp_path / "two_then_one"
    _run(2, str(HERE / "mpi_worker.py"), "stop", str(dataset), str(a), str(toml), "4")
    with np.load(a / "checkpoint.npz") as z:
        assert int(z["iteration"]) == 3
    run_fit(dataset, a, cfg, resume=True, stream=open(os.devnull, "w"))  # noqa: SIM115
    assert np.abs(_params(a) - ref).max() < 1e-10

    # one rank stops after iteration 4; two ranks finish it
    b = tmp_path / "one_then_two"
    real_step = fitmod.Fit.step

    def step_then_stop(self):
        m = real_step(self)
        if self.it == 4:
            raise KeyboardInterrupt
        return m

    monkeypatch.setattr(fitmod.Fit, "step", step_then_stop)
    with pytest.raises(ClrefractError, match="iteration 3"):
        run_fit(dataset, b, cfg, stream=open(os.devnull, "w"))  # noqa: SIM115
    monkeypatch.setattr(fitmod.Fit, "step", real_step)
    _run(2, *cli, "fit", str(dataset), "--out", str(b), "--resume")
    assert np.abs(_params(b) - ref).max() < 1e-10
    assert np.allclose(_losses(b), _losses(one), rtol=1e-10, atol=0)


def test_a_failure_on_rank_0_ends_every_rank(tmp_path):
    """Rank 0 refuses a run (here: nothing to resume); the other ranks must not wait for it
    forever, and the message is rank 0's."""
    out = _run(2, "-m", "clrefract.cli", "fit", str(tmp_path), "--out", str(tmp_path / "r"),
               "--resume", check=False)  # fmt: skip
    assert out.returncode != 0
    assert "no run to resume" in out.stderr
    assert "rank 1: rank 0 failed" in out.stderr
