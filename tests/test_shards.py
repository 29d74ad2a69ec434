"""`--shard i/n` and `--merge` of the benchmark runner: every scene runs exactly once, and
the merged table is the unsharded one."""

import json

import pytest

from clrefract import shards
from clrefract.errors import ClrefractError

SCENES = ["sphere", "prism", "drop", "vase", "bowl"]


@pytest.mark.parametrize("n", [1, 2, 3, 5, 7])
def test_shards_cover_the_suite_once(n):
    runs = [s for i in range(n) for s in shards.select(SCENES, f"{i}/{n}")]
    assert sorted(runs) == sorted(SCENES)
    assert shards.select(SCENES, "") == SCENES


@pytest.mark.parametrize("bad", ["2/2", "1", "a/b", "-1/2", "1/0"])
def test_bad_shard_specs_are_refused(bad):
    with pytest.raises(ClrefractError, match="i/n"):
        shards.parse(bad)


def test_merge_restores_the_suite_order(tmp_path):
    target = tmp_path / "reconstruction.json"
    for i in range(3):
        path = shards.path_for(target, f"{i}/3")
        assert path.name == f"reconstruction.shard-{i}-of-3.json"
        rows = [{"scene": s, "psnr": k} for k, s in enumerate(shards.select(SCENES, f"{i}/3"))]
        path.write_text(json.dumps({"args": {"shard": f"{i}/3"}, "scenes": rows}))
    merged = shards.merge(target, SCENES)
    assert [r["scene"] for r in merged["scenes"]] == SCENES
    assert len(merged["shards"]) == 3
    shards.path_for(target, "1/3").unlink()  # a shard that has not finished
    with pytest.raises(ClrefractError, match="incomplete"):
        shards.merge(target, SCENES)
