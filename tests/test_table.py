"""`clrefract table` (and tools/table.py): a protocol split into shards, merged into Table 1."""

import json

import pytest

from clrefract.cli import main
from clrefract.errors import ClrefractError
from clrefract.shards import parse
from clrefract.table import jobs, merge, run_protocol


def test_shards_cover_every_job_once():
    scenes, methods = ("sphere", "prism", "drop"), ("grid", "meridian", "synapse", "vertexnet")
    parts = [jobs(scenes, methods, f"{i}/5") for i in range(5)]
    flat = [j for p in parts for j in p]
    assert sorted(flat) == sorted(jobs(scenes, methods)) and len(flat) == 12
    with pytest.raises(ClrefractError):
        parse("2/2")


def test_tiny_protocol_in_two_shards_merges_into_the_table(tmp_path):
    data = tmp_path / "data"
    run_protocol(
        "tiny",
        tmp_path / "shard0",
        "0/2",
        scenes=["sphere"],
        methods=["meridian", "synapse"],
        data_root=data,
    )
    run = ["table", "run", "--protocol", "tiny", "--out", str(tmp_path / "shard1")]
    run += ["--shard", "1/2", "--scenes", "sphere", "--methods", "meridian,synapse"]
    assert main([*run, "--data", str(data)]) == 0
    records = merge([tmp_path / "shard0", tmp_path / "shard1"])
    assert [r["method"] for r in records] == ["meridian", "synapse"]
    shard_folders = [str(tmp_path / "shard0"), str(tmp_path / "shard1")]
    assert main(["table", "merge", *shard_folders, "--out", str(tmp_path / "table")]) == 0
    assert main(["table", "run", "--protocol", "huge", "--out", str(tmp_path / "x")]) == 2
    md = (tmp_path / "table" / "table.md").read_text()
    assert "Synapse-Volumetric" in md and "(26.89)" in md  # ours beside the paper's
    csv_lines = (tmp_path / "table" / "table.csv").read_text().splitlines()
    assert len(csv_lines) == 3 and "wall_seconds" in csv_lines[0]
    saved = json.loads((tmp_path / "table" / "table.json").read_text())
    assert all(r["eta_rmse"] == "n/a" and r["psnr"] > 10 for r in saved)
