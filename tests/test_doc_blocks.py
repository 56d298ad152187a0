"""Tables in README.md and docs/*.md generated from tracked result files: every block equals what
its source gives (dss-results --publish rewrites them), and broken markers are named."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from experiments.evaluation import doc_blocks
from experiments.evaluation.results_index import main

ROOT = Path(__file__).resolve().parents[1]
BUDGETS = "results/denoise/budgets_0.01_20000/table.json"


def test_the_docs_generated_blocks_match_their_sources():
    blocks = [b for p in doc_files() for b in doc_blocks.find_blocks(p)]
    sources = {b.source for b in blocks}
    assert BUDGETS in sources and len(blocks) >= 4  # README's results table, the budgets table, ...
    assert any(b.path.name == "README.md" for b in blocks)
    stale = doc_blocks.update(ROOT)
    assert not stale, "out of date (run dss-results --publish): " + ", ".join(
        f"{b.path.relative_to(ROOT)}:{b.line} from {b.source}" for b in stale)


def doc_files():
    return doc_blocks.doc_files(ROOT)


def _repo(tmp_path: Path, body: str) -> Path:
    """A repository with the budgets table as its one result and a README holding ``body``."""
    src = tmp_path / BUDGETS
    src.parent.mkdir(parents=True)
    shutil.copy(ROOT / BUDGETS, src)
    (tmp_path / "README.md").write_text(body)
    return tmp_path


MARKER = ('<!-- generated: denoise_methods ' + BUDGETS + '\n  methods="cgal_jet=jet|dss_identity=identity" '
          'columns="mean_cd=mean CD|case_cd:kangaroo=kangaroo CD" -->\n')


def test_publish_rewrites_a_stale_block_and_check_fails_until_then(tmp_path, capsys):
    repo = _repo(tmp_path, "# Title\n\nBefore.\n\n" + MARKER + "| old | table |\n<!-- end generated -->\n\nAfter.\n")
    assert main(["--results", str(repo / "results"), "--check"]) == 1
    assert "README.md:5" in capsys.readouterr().err
    data = json.loads((repo / BUDGETS).read_text())
    jet = next(r for r in data["rows"] if r["method"] == "cgal_jet")
    ident = next(r for r in data["rows"] if r["method"] == "dss_identity")
    assert ident["mean"]["chamfer"] < jet["mean"]["chamfer"]  # the tracked table: identity is the column's best
    assert main(["--results", str(repo / "results"), "--publish"]) == 0
    text = (repo / "README.md").read_text()
    assert text.startswith("# Title\n\nBefore.\n\n" + MARKER) and text.endswith("<!-- end generated -->\n\nAfter.\n")
    assert "| old | table |" not in text
    assert f"| jet | {jet['mean']['chamfer']:.3f} | {jet['cases']['kangaroo']['chamfer']:.3f} |" in text
    assert f"| identity | **{ident['mean']['chamfer']:.3f}** |" in text  # the best of the column in bold
    assert main(["--results", str(repo / "results"), "--check"]) == 0
    # a changed result makes the block stale again
    jet["mean"]["chamfer"] = 0.123
    (repo / BUDGETS).write_text(json.dumps(data))
    assert [b.line for b in doc_blocks.update(repo)] == [5]
    doc_blocks.update(repo, write=True)
    assert "| jet | **0.123** |" in (repo / "README.md").read_text()


def test_markers_in_a_code_block_are_an_example_not_a_block(tmp_path):
    body = "# Title\n\n```\n" + MARKER + "<!-- end generated -->\n```\n\n" + MARKER + "<!-- end generated -->\n"
    repo = _repo(tmp_path, body)
    assert [b.line for b in doc_blocks.find_blocks(repo / "README.md")] == [9]
    doc_blocks.update(repo, write=True)
    text = (repo / "README.md").read_text()
    assert text.startswith("# Title\n\n```\n" + MARKER + "<!-- end generated -->\n```\n") and text.count("| jet |") == 1


@pytest.mark.parametrize("body, message", [
    ("<!-- generated: nosuch " + BUDGETS + " -->\n<!-- end generated -->\n", "unknown generator 'nosuch'"),
    ("<!-- generated: denoise_methods results/none.json methods=a columns=mean_cd -->\n<!-- end generated -->\n",
     "source results/none.json does not exist"),
    (MARKER + "| no end |\n", "no <!-- end generated -->"),
    ("<!-- generated: denoise_methods " + BUDGETS + ' methods="nope" columns=mean_cd -->\n<!-- end generated -->\n',
     r"no rows \['nope'\]"),
    ("<!-- generated: denoise_methods " + BUDGETS + ' methods=cgal_jet columns=median -->\n<!-- end generated -->\n',
     "unknown column 'median'"),
])
def test_a_broken_block_is_named_with_its_line(tmp_path, body, message):
    repo = _repo(tmp_path, "# Title\n\n" + body)
    with pytest.raises(ValueError, match=message) as e:
        doc_blocks.update(repo)
    assert "README.md:3" in str(e.value)
