"""Fits on shapes nobody tuned them on: the level-set start finds the index of a family solid
whose visual hull is too big (a hull from few views), not a lower index."""

import json

import pytest

from clrefract.fit import FitConfig, prepare_fit
from clrefract.synth import MakeOptions, make_dataset


@pytest.mark.parametrize("shape,eta", [("rounded-cube", 1.6), ("vase", 1.45)])
def test_start_finds_the_index_of_a_family_solid(tmp_path, shape, eta):
    data = tmp_path / "data"
    opts = MakeOptions(views=30, res=32, env_width=512, volume_res=32, eta=eta)
    make_dataset(shape, data, opts, stream=open("/dev/null", "w"))
    cfg = FitConfig(field="levelset", iterations=1, res=32, batch=4096, test_views=2)
    fit = prepare_fit(data, tmp_path / "run", cfg, stream=open("/dev/null", "w"))
    init = json.loads((tmp_path / "run" / "init.json").read_text())
    assert abs(init["eta"] - eta) < 0.05, init
    start = json.loads((tmp_path / "run" / "start.json").read_text())
    assert start["test_psnr"] > 0 and fit.params[-1] == pytest.approx(init["eta"])
