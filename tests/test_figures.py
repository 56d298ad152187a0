"""The backward-pass figures (paper Figs. 1Dplot and twopoints): each command runs with tiny
settings, writes its PNG and JSON, and the numbers in the JSON support the paper's claims."""

import json

import numpy as np
import pytest

from experiments.figures import cutoff_for_radius, ellipse_radius_px, gradient_1d, two_points

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _read_outputs(folder, stem):
    png = folder / f"{stem}.png"
    js = folder / f"{stem}.json"
    assert png.exists() and js.exists()
    assert png.read_bytes()[:8] == PNG_MAGIC and png.stat().st_size > 10_000
    return json.loads(js.read_text())


def test_cutoff_for_radius_round_trip():
    for sigma in (0.05, 0.5, 5.0):
        c = cutoff_for_radius(sigma, 50.0, 9.0)
        assert ellipse_radius_px(sigma, 50.0, c) == pytest.approx(9.0)
    # C = 1: radius = sqrt(2) * sqrt((sigma f/Z)^2 + 1)
    assert ellipse_radius_px(0.1, 50.0, 1.0) == pytest.approx(np.sqrt(2 * 26))


@pytest.fixture(scope="module")
def gradient_1d_result(tmp_path_factory):
    out = tmp_path_factory.mktemp("fig1d")
    assert gradient_1d.main(["--out", str(out), "--distance-step", "5", "--steps", "40",
                             "--optimizers", "adam:0.01", "sgd:2e-5"]) == 0
    return _read_outputs(out, "gradient_1d")


def test_gradient_1d_outputs(gradient_1d_result):
    r = gradient_1d_result
    assert r["command"].startswith("dss-fig-gradient1d")
    assert set(r["rows"]) == {"fixed_ellipse", "default_cutoff"}
    d = np.asarray(r["distances_px"])
    assert d[0] == 5 and d[-1] == 50
    for row in r["rows"].values():
        for mode in ("dss", "rbf"):
            for s in ("0.05", "0.1", "0.5"):
                assert len(row["gradient"][mode][s]) == len(d)
                for key in r["settings"]["optimizers"]:
                    assert len(row["residual"][key][mode][s]) == 41


def test_gradient_1d_dss_is_invariant_to_sigma(gradient_1d_result):
    r = gradient_1d_result
    d = np.asarray(r["distances_px"])
    fixed = r["rows"]["fixed_ellipse"]
    assert all(v == pytest.approx(9.0) for v in fixed["ellipse_radius_px"].values())
    g = np.array([fixed["gradient"]["dss"][s] for s in ("0.05", "0.1", "0.5")])
    # Same disc for every sigma: the DSS gradient does not see sigma at all, inside or outside.
    assert np.allclose(g, g[0], rtol=1e-3, atol=1e-7)
    outside = d > 10
    # Outside the ellipse, Eq. gradcase (a) gives |Delta I| / d pixel^-1, pointing at the pixel.
    assert np.allclose(-g[:, outside] * d[outside], 1.0, atol=1e-2)
    # With C = 1 the discs differ (3.8, 7.2, 35.4 px), but beyond all of them the value is still 1/d.
    c1 = r["rows"]["default_cutoff"]
    far = d > max(c1["ellipse_radius_px"].values()) + 1
    assert far.sum() >= 2
    g1 = np.array([c1["gradient"]["dss"][s] for s in ("0.05", "0.1", "0.5")])
    assert np.allclose(-g1[:, far] * d[far], 1.0, atol=1e-2)
    assert fixed["summary"]["dss_outside_max_relative_spread_over_sigma"] < 1e-3


def test_gradient_1d_rbf_depends_strongly_on_sigma(gradient_1d_result):
    fixed = gradient_1d_result["rows"]["fixed_ellipse"]
    at = fixed["summary"]["at_report_distance"]  # 25 px from the splat
    assert at["0.05"]["rbf_over_dss"] < 1e-6  # vanishes: a small sigma cannot see the target
    assert at["0.5"]["rbf_over_dss"] > 0.1
    assert at["0.5"]["rbf"] > 1e3 * at["0.1"]["rbf"] > 1e6 * at["0.05"]["rbf"]
    inc = fixed["summary"]["rbf_increases_outside_ellipse"]
    assert inc["0.5"] and not inc["0.05"]  # large sigma: grows with distance outside the ellipse


def test_gradient_1d_convergence(gradient_1d_result):
    fixed = gradient_1d_result["rows"]["fixed_ellipse"]
    adam = fixed["residual"]["adam:0.01"]
    sgd = fixed["residual"]["sgd:2e-05"]
    # Adam: DSS moves the same way for every sigma; RBF with the small sigma does not move toward the target.
    for s in ("0.05", "0.1", "0.5"):
        assert adam["dss"][s][0] - adam["dss"][s][-1] > 15
        assert np.allclose(adam["dss"][s], adam["dss"]["0.05"], atol=0.05)
    assert adam["rbf"]["0.05"][-1] > 24
    # SGD follows the gradient's value: DSS converges, small-sigma RBF crawls or stalls.
    for s in ("0.05", "0.1", "0.5"):
        assert abs(sgd["dss"][s][-1]) < 1.0
    assert sgd["rbf"]["0.05"][-1] > 20 and sgd["rbf"]["0.1"][-1] > 20


def test_gradient_1d_rejects_a_window_that_misses_pixels(tmp_path):
    with pytest.raises(ValueError, match="window"):
        gradient_1d.main(["--out", str(tmp_path), "--window", "20", "--max-distance", "50"])
    with pytest.raises(SystemExit):
        gradient_1d.main(["--out", str(tmp_path), "--optimizers", "rmsprop:0.1"])


def test_two_points_outputs_and_claims(tmp_path):
    assert two_points.main(["--out", str(tmp_path), "--trials", "1", "--trial-steps", "10"]) == 0
    js = _read_outputs(tmp_path, "two_points")
    assert js["command"].startswith("dss-fig-twopoints")
    assert js["settings"]["snapshots"] == [0, 12, 24, 36, 48]
    dss, rbf = js["methods"]["dss"], js["methods"]["rbf"]
    assert len(dss["trajectory_px"]) == 49 and len(dss["loss"]) == 49
    # Ours reaches both targets; the wide RBF pulls both points toward the middle (a local minimum).
    assert dss["reached_both"] and dss["max_distance_px"] < 1.5
    assert not rbf["reached_both"] and rbf["max_distance_px"] > 5
    assert dss["loss"][-1] < 0.1 * dss["loss"][0]
    assert rbf["loss"][-1] > 0.5 * rbf["loss"][0]
    end = np.asarray(rbf["final_px"])
    mid = np.asarray(js["settings"]["target_px"]).mean(0)
    assert np.linalg.norm(end - mid, axis=1).max() < 6  # both sit near the targets' midpoint
    for row in js["trials"]["settings"]:
        assert row["trials"] == 1 and set(row["reached_both"]) == {"dss", "rbf"}
        assert all(0 <= v <= 1 for v in row["reached_both"].values())


def test_two_points_is_deterministic(tmp_path):
    a = two_points.run(tmp_path / "a", trials=0, steps=12, snapshots=(0, 12))
    b = two_points.run(tmp_path / "b", trials=0, steps=12, snapshots=(0, 12))
    assert a["methods"]["dss"]["trajectory_px"] == b["methods"]["dss"]["trajectory_px"]
    assert a["methods"]["rbf"]["trajectory_px"] == b["methods"]["rbf"]["trajectory_px"]
    with pytest.raises(ValueError, match="snapshot"):
        two_points.main(["--out", str(tmp_path / "c"), "--trials", "0", "--steps", "12", "--snapshots", "0", "24"])
