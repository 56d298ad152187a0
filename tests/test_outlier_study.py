"""experiments.evaluation.outlier_study: the counts behind the README's outlier numbers are consistent."""

from __future__ import annotations

from experiments.evaluation.outlier_study import _pct, render_markdown, study_case, summarize

PARAMS = {"k": 16, "z_threshold": 8.0, "ratio_threshold": 3.0, "iterations": 3}


def test_study_case_counts_and_chamfer_order():
    case = {"name": "sq", "family": "superquadric", "index": 0, "resolution": 32}
    r = study_case(case, 3000, 0.01, 0.05, PARAMS)
    assert r["outliers"] == 150 and 0 <= r["far_kept"] <= r["far"] <= r["outliers"]
    assert r["found"] >= r["far"] - r["far_kept"]  # every far one not kept was found
    assert r["far_kept"] < 0.3 * r["far"] and r["inliers_removed"] < 30
    # removal brings the noisy cloud's Chamfer most of the way to the true-removed one
    assert r["chamfer_true_removed"] <= r["chamfer_removed"] < 0.6 * r["chamfer_input"]
    clean = study_case(case, 3000, 0.01, 0.0, PARAMS)
    assert clean["outliers"] == 0 and clean["chamfer_input"] == clean["chamfer_true_removed"]
    s = summarize([r, clean])
    assert [x["outlier_fraction"] for x in s] == [0.05, 0.0] and s[1]["found_fraction"] is None
    md = render_markdown(s, "cmd", PARAMS)
    assert "| 3000 | 0.01 | 0.05 | 1 |" in md and _pct(None) == "-"
