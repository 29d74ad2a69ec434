"""docs/results.md, the paper's Table 1 as measured: `clrefract table run --page` writes it from
the table's records (and saves them beside it), `clrefract table page` writes it again from
them; it names every method and scene with the records' figures, and the commands it states
parse with the real parser."""

import json
from pathlib import Path

import pytest
from test_docs import _parse, clrefract_commands

import clrefract.evaluate
import clrefract.table
from clrefract.baselines.methods import METHODS
from clrefract.cli import main
from clrefract.family import FAMILY
from clrefract.table import FIGURES, GLANCE_BEGIN, GLANCE_END, SCENES, glance, page, read_records

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "results.md"
README = ROOT / "README.md"


@pytest.fixture
def stubbed(tmp_path, monkeypatch):
    """The tiny protocol's jobs run through the real table, their training and scoring stubbed:
    distinct figures per (scene, method), eta RMSE 'n/a' for the straight-ray methods."""
    figures = {}

    def train(method, data, run, settings, stream=None):
        run.mkdir(parents=True)
        return {"method": method, "wall_seconds": 10.0 + len(figures)}

    def score(run, samples=None):
        scene, method = run.name.rsplit("-", 1)
        k = len(figures)
        figures[scene, method] = {
            "psnr": 20.125 + k,
            "ssim": 0.5 + k / 100,
            "chamfer_mm": 3.0 + k / 8,
            "eta_rmse": "n/a" if METHODS[method].rays == "straight" else 0.0123 + k / 1000,
        }
        return figures[scene, method]

    monkeypatch.setattr(clrefract.table, "dataset_for", lambda *a: tmp_path / "data")
    monkeypatch.setattr(clrefract.table, "run_method", train)
    monkeypatch.setattr(clrefract.evaluate, "evaluate_run", score)
    return figures


def _cells(md: str, heading: str) -> dict[str, list[str]]:
    """The rows of the table under `## heading`, by their first cell."""
    part = md.split(f"## {heading}\n", 1)[1].split("\n## ", 1)[0]
    rows = [line.strip("|").split("|") for line in part.splitlines() if line.startswith("| ")]
    return {r[0].strip(): [c.strip() for c in r[1:]] for r in rows}


def test_table_run_writes_the_page_with_every_figure(tmp_path, stubbed):
    out, path = tmp_path / "t", tmp_path / "docs" / "results.md"
    assert main(["table", "run", "--protocol", "tiny", "--out", str(out), "--page", str(path)]) == 0
    records = json.loads((out / "table.json").read_text())
    assert len(records) == len(SCENES) * len(METHODS) == len(stubbed)
    assert read_records(path.with_suffix(".json")) == records  # saved beside the page
    md = path.read_text()
    assert md == page(records, path)
    assert "**Not Table 1's figures: the `tiny` protocol" in md
    for r in records:  # where it was measured: this checkout's commit, the OpenCL device
        assert r["device"] and r["driver"] and r["ended"] and r["eval_seconds"] is not None
        assert r["device"] in md and r["driver"] in md
    if records[0]["commit"]:
        assert records[0]["commit"][:12] in md
    for key, heading, digits, paper_key in FIGURES:
        table = _cells(md, heading)
        assert list(_cells(md, heading)["Method"]) == [*SCENES, "mean"] + ["paper"] * bool(
            paper_key
        )
        for method, m in METHODS.items():
            row = table[f"{m.paper_name} (`{method}`)"]
            for i, scene in enumerate(SCENES):
                (r,) = [r for r in records if (r["scene"], r["method"]) == (scene, method)]
                value = r[key]
                want = value if isinstance(value, str) else f"{value:.{digits}f}"
                assert row[i] == want, (heading, method, scene)
                if key != "wall_seconds":
                    assert value == stubbed[scene, method][key]
            if paper_key:  # the paper's figure beside ours; none for the interface row
                assert row[-1] == ("" if m.paper is None else f"{r[paper_key]:.{digits}f}")
    assert _cells(md, "PSNR (dB, test views)")["Vertex-Net (`vertexnet`)"][-1] == "31.54"

    # the stated commands parse; the render-only one writes the same page from the records
    commands = [a for _, a in clrefract_commands(md)]
    assert ["table", "run", "--protocol", "tiny", "--out", "table/tiny", "--page", str(path)] in (
        commands
    )
    assert ["table", "run", "--protocol", "quick", "--out", "table/quick"] == commands[0][:6]
    assert all(_parse(a) == "" for a in commands)
    (again,) = [a for a in commands if a[:2] == ["table", "page"]]
    path.unlink()
    assert main(again) == 0 and path.read_text() == md


def test_a_shard_leaves_the_page_to_merge(tmp_path, stubbed, capsys):
    shard = ["table", "run", "--protocol", "tiny", "--out", str(tmp_path / "s0")]
    shard += ["--scenes", "drop", "--methods", "synapse,interface", "--shard", "0/2"]
    assert main([*shard, "--page", str(tmp_path / "p.md")]) == 2
    assert "give it to `table merge`" in capsys.readouterr().err and not stubbed
    assert main(shard) == 0 and main([*shard[:-1], "1/2"]) == 0
    folders = [str(tmp_path / "s0")]
    merged = ["table", "merge", *folders, "--out", str(tmp_path / "m"), "--page"]
    assert main([*merged, str(tmp_path / "p.md")]) == 0
    md = (tmp_path / "p.md").read_text()
    assert "--scenes drop --methods synapse,interface --page" in md
    assert "| Synapse-Volumetric (`synapse`) |" in md and "| sphere |" not in md
    assert main(["table", "page", str(tmp_path / "m" / "table.csv"), "--out", "x.md"]) == 2


def test_docs_results_is_the_page_of_its_saved_records():
    """docs/results.md is what `clrefract table page docs/results.json` writes, and states the
    command that measures it again (it parses)."""
    records = read_records(PAGE.with_suffix(".json"))
    assert PAGE.read_text() == page(records, "docs/results.md", "README.md"), (
        "docs/results.md is stale: clrefract table page docs/results.json --out docs/results.md "
        "--readme README.md"
    )
    commands = [a for _, a in clrefract_commands(PAGE.read_text())]
    protocol = records[0]["protocol"]
    measure = ["table", "run", "--protocol", protocol, "--out", f"table/{protocol}"]
    measure += ["--family-methods", "interface,auto", "--page", "docs/results.md"]
    assert [*measure, "--readme", "README.md"] in commands
    again = ["table", "page", "docs/results.json", "--out", "docs/results.md"]
    assert [*again, "--readme", "README.md"] in commands
    assert all(_parse(a) == "" for a in commands)
    names = {(r["scene"], r["method"]) for r in records}
    family = {(s, m) for s in FAMILY for m in ("interface", "auto")}
    assert names == {(s, m) for s in SCENES for m in METHODS} | family
    # the README's results at a glance are this page's
    block = README.read_text().split(GLANCE_BEGIN + "\n")[1].split(GLANCE_END)[0]
    assert block == glance(records, "docs/results.md"), (
        "README.md's results at a glance are stale: clrefract table page docs/results.json "
        "--out docs/results.md --readme README.md"
    )


def _glance_cells(block: str) -> dict[str, list[str]]:
    rows = [line.strip("|").split("|") for line in block.splitlines() if line.startswith("| ")]
    return {r[0].strip(): [c.strip() for c in r[1:]] for r in rows}


def test_the_family_and_the_readme_come_with_the_page(tmp_path, stubbed, capsys):
    """`--family-methods` runs the family's solids beside Table 1 and the page gives them a
    table of their own; `--readme` writes the results at a glance between the README's comment
    lines, leaving the rest of it as it was; a README without them is refused, naming it."""
    readme, path = tmp_path / "README.md", tmp_path / "docs" / "results.md"
    before, after = "# a tool\n\n## Results\n\n", "\nMore words.\n"
    readme.write_text(before + GLANCE_BEGIN + "\nold\n" + GLANCE_END + after)
    run = ["table", "run", "--protocol", "tiny", "--out", str(tmp_path / "t")]
    run += ["--methods", "synapse,interface", "--family-methods", "interface"]
    assert main([*run, "--page", str(path), "--readme", str(readme)]) == 0
    records = read_records(path.with_suffix(".json"))
    assert len(records) == 2 * len(SCENES) + len(FAMILY) == len(stubbed)
    md = path.read_text()
    assert md == page(records, path, readme)
    family = _cells(md, "The family of glass solids")
    psnr = [stubbed[s, "interface"]["psnr"] for s in FAMILY]
    for s in FAMILY:
        want = stubbed[s, "interface"]
        assert family[s][:5] == [
            "`interface`",
            f"{want['psnr']:.2f}",
            f"{want['ssim']:.3f}",
            f"{want['chamfer_mm']:.2f}",
            f"{want['eta_rmse']:.4f}",
        ]
    assert family["mean"][1] == f"{sum(psnr) / len(psnr):.2f}"
    # Table 1's figures leave the family out
    assert list(_cells(md, "PSNR (dB, test views)")["Method"]) == [*SCENES, "mean", "paper"]

    text = readme.read_text()
    assert text.startswith(before + GLANCE_BEGIN + "\n") and text.endswith(GLANCE_END + after)
    block = text.split(GLANCE_BEGIN + "\n")[1].split(GLANCE_END)[0]
    assert block == glance(records, "docs/results.md") and "[results.md](docs/results.md)" in block
    cells = _glance_cells(block)
    for i, scene in enumerate(SCENES):
        assert cells["Interface (SDF + Snell) (`interface`)"][i] == (
            f"{stubbed[scene, 'interface']['psnr']:.2f}"
        )
    assert f"{min(psnr):.2f} to {max(psnr):.2f}" in block

    commands = [a for _, a in clrefract_commands(md)]
    measure = [a for a in commands if a[:2] == ["table", "run"] and "quick" not in a]
    assert measure == [
        [*run[:5], "table/tiny", *run[6:], "--page", str(path), "--readme", str(readme)]
    ]
    (again,) = [a for a in commands if a[:2] == ["table", "page"]]
    readme.write_text(before + GLANCE_BEGIN + "\n" + GLANCE_END + after)
    assert main(again) == 0 and readme.read_text() == text and path.read_text() == md

    bare = tmp_path / "BARE.md"
    bare.write_text("# no markers\n")
    capsys.readouterr()
    assert main([*again[:-1], str(bare)]) == 2
    err = capsys.readouterr().err
    assert str(bare) in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert main([*run, "--readme", str(readme)]) == 2  # a glance of no page
