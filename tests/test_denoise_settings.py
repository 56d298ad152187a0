"""The denoise job's settings (experiments.denoising.settings): resolved from the config without
changing it, by noise level, point count, budget, render channel and fusion, and pinned to what
the job chose before its settings became one object (tests/data/denoise_settings_pins.json)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir
from omegaconf import OmegaConf

from experiments.denoising import settings as st

REPO = Path(__file__).resolve().parents[1]
PINS = Path(__file__).with_name("data") / "denoise_settings_pins.json"
AUTO = ("cycles", "lr_points", "projection_weight", "reg_cutoff", "final_projection_k")
RIM = ("rim_k", "rim_ratio", "rim_target", "rim_iterations")


def compose_denoise(overrides: list[str]):
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        return compose("denoise", overrides=overrides)


def _generator(name: str):
    from experiments.denoising.reference_generators import (
        IdentityReference,
        L0Reference,
        OracleReference,
    )

    return {"identity": IdentityReference, "l0": L0Reference, "oracle": OracleReference}[name]()


def _plain(x):
    """JSON round trip: float table keys become strings, as in the pins file."""
    return json.loads(json.dumps(x))


def _pinned_config(pins: dict, overrides: list[str], reference: str):
    """conf/denoise.yaml with the pins' tables and budget presets (the shipped values are tuned
    apart from this test)."""
    cfg = compose_denoise([*overrides, f"reference={reference}"])
    OmegaConf.set_struct(cfg, False)
    # what the pins predate, switched off: the displacement bound, the sparse-cloud rate, the
    # fusion weight by noise, the rim pull; and channel=auto meant planes for identity then
    if not any(o.startswith("optimizer.max_displacement=") for o in overrides):
        cfg.optimizer.max_displacement = 0.0
    cfg.sparse_rate_power = 0.0
    cfg.max_move_by_noise = None
    for key in RIM:  # absent: OptimizerConfig's default, rim_k 0 (off)
        del cfg.optimizer[key]
    if cfg.get("fusion") is not None:
        cfg.fusion.weight_by_noise = None
    if reference == "identity" and cfg.channel.name == "auto":
        cfg.channel = {"name": "planes"}
    for key, value in pins["tables"].items():
        cfg[key] = {float(k): v for k, v in value.items()} if isinstance(value, dict) else value
    if cfg.budget.name == "auto":
        cfg.budget.presets = pins["budget_presets"]
        cfg.budget.fast_above = pins["budget_fast_above"]
    else:
        cfg.budget = {"name": cfg.budget.name, **pins["budget_presets"][cfg.budget.name]}
    return cfg


def test_settings_match_the_pinned_choices_and_leave_the_config_alone():
    """Every pinned case (noise levels between and beyond the tables, 5K-250K points, budgets,
    channels, fusion, explicit optimiser settings; identity, L0 and oracle references) resolves
    to the same optimiser values, notes, budget, render size, channel and fusion passes, and the
    config is the same before and after. The only change in the notes: the budget's threshold is
    named by its key, ``budget.fast_above`` (conf/denoise_parts/budget/auto.yaml)."""
    from dataclasses import asdict

    pins = json.loads(PINS.read_text())
    keys = ("cycles", "lr_points", "projection_weight", "reg_cutoff", "final_projection_k", "max_displacement",
            "reg_dilation", "views", "seed")
    generators = {}
    assert len(pins["cases"]) >= 20
    for case in pins["cases"]:
        cfg = _pinned_config(pins, case["overrides"], case["reference"])
        before = OmegaConf.to_yaml(cfg)
        gen = generators.setdefault(case["reference"], _generator(case["reference"]))
        s = st.resolve(cfg, case["noise"], case["points"], gen)
        assert OmegaConf.to_yaml(cfg) == before, case
        notes = _plain(s.notes)
        for key, note in notes.items():  # each auto note carries the table it read
            if note.get("setting") == "auto" and key in AUTO:
                assert note.pop(f"{key}_by_noise") == pins["tables"][f"{key}_by_noise"]
        expected_budget = dict(case["budget"])
        expected_budget["reason"] = expected_budget["reason"].replace("budget_fast_above", "budget.fast_above")
        o = asdict(s.optimizer)
        got = {"notes": notes, "budget": _plain(s.budget), "optimizer": {k: o[k] for k in keys},
               "fusion_passes": None if s.fusion is None else s.fusion.passes, "image_size": list(s.spec.image_size),
               "spec_source": s.spec_source, "shading": s.shading_name}
        want = {k: case[k] for k in ("notes", "optimizer", "fusion_passes", "image_size", "spec_source", "shading")}
        want["budget"] = expected_budget
        assert got == want, (case["overrides"], case["reference"], case["noise"], case["points"])
        # config.yaml records the values in use
        for k in ("cycles", "lr_points", "reg_cutoff", "reg_dilation"):
            assert s.config.optimizer[k] == o[k]
        assert s.config.views == o["views"]


def test_auto_cycles_follow_the_noise_level():
    """cycles=auto: the table interpolated in log noise (rounded), its end values beyond it; the
    point rate takes the rounding, so cycles x rate is continuous."""
    cfg = OmegaConf.create({"optimizer": {"cycles": "auto"}, "cycles_by_noise": {0.003: 2, 0.01: 16}})
    assert st.by_noise(cfg, 0.002, "cycles", int)[0] == 2
    assert st.by_noise(cfg, 0.02, "cycles", int)[0] == 16
    mid = math.sqrt(0.003 * 0.01)  # half way in log noise: the geometric mean of 2 and 16
    value, note = st.by_noise(cfg, mid, "cycles", int)
    assert note["exact"] == pytest.approx(math.sqrt(2 * 16)) and value == note["used"] == 6
    assert cfg.optimizer.cycles == "auto"  # never changed in place
    assert st.by_noise(OmegaConf.create({"optimizer": {"cycles": 5}}), 0.003, "cycles", int) == (
        5, {"setting": 5, "used": 5})
    with pytest.raises(ValueError, match="cycles_by_noise"):
        st.by_noise(OmegaConf.create({"optimizer": {"cycles": "auto"}}), 0.01, "cycles", int)
    # no jump between two tuned levels: cycles x rate moves continuously
    c = OmegaConf.create({"optimizer": {k: "auto" for k in AUTO},
                          "cycles_by_noise": {0.003: 2, 0.01: 16}, "lr_points_by_noise": {0.003: 5, 0.01: 15},
                          "projection_weight_by_noise": {0.003: 0.1}, "reg_cutoff_by_noise": {0.003: 1},
                          "final_projection_k_by_noise": {0.003: 32}})
    products = []
    for noise in np.geomspace(0.003, 0.01, 41):
        values, _ = st.noise_settings(c, float(noise))
        products.append(values["cycles"] * values["lr_points"])
    steps = np.diff(np.log(products))
    assert (steps > 0).all() and steps.max() < 2.5 * steps.min()


def test_auto_projection_weight_follows_the_noise_level():
    cfg = OmegaConf.create({"optimizer": {"projection_weight": "auto"},
                            "projection_weight_by_noise": {0.01: 0.1, 0.02: 0.5}})
    assert st.by_noise(cfg, 0.025, "projection_weight")[0] == 0.5
    assert st.by_noise(cfg, 0.014, "projection_weight")[0] == pytest.approx(0.1 * 5 ** (math.log(1.4) / math.log(2)))
    fixed = OmegaConf.create({"optimizer": {"projection_weight": 0.3}})
    assert st.by_noise(fixed, 0.02, "projection_weight") == (0.3, {"setting": 0.3, "used": 0.3})
    with pytest.raises(ValueError, match="projection_weight_by_noise"):
        st.by_noise(OmegaConf.create({"optimizer": {"projection_weight": "auto"}}), 0.01, "projection_weight")
    # a table with a zero interpolates linearly
    assert st.interpolate_by_noise({0.01: 0.0, 0.04: 1.0}, 0.02) == pytest.approx(0.5)


def test_shipped_config_resolves_every_auto_setting():
    """conf/denoise.yaml: every ``auto`` optimiser entry has its table, and the shipped config
    resolves at the tuned levels and beyond them."""
    cfg = compose_denoise(["reference=identity"])
    for noise in (0.001, 0.003, 0.01, 0.02, 0.05):
        values, notes = st.noise_settings(cfg, noise)
        auto = (*AUTO, *RIM, "max_displacement")  # the shipped config bounds the displacement (auto) too
        assert set(notes) == set(auto) and all(notes[k]["setting"] == "auto" for k in auto)
        assert values["cycles"] >= 1 and values["lr_points"] > 0 and values["final_projection_k"] >= 1
        assert values["rim_k"] >= 1 and values["rim_iterations"] >= 1 and values["rim_ratio"] > values["rim_target"] > 0
    # the rim pull: gentle to 0.5% (a thin part's last samples are surface), firmer from 1%
    low, high = st.noise_settings(cfg, 0.004)[0], st.noise_settings(cfg, 0.012)[0]
    assert low["rim_ratio"] > high["rim_ratio"] and low["rim_target"] > high["rim_target"]
    assert low["rim_k"] <= high["rim_k"] and low["rim_iterations"] <= high["rim_iterations"]


def test_neighbourhood_dilation_follows_density():
    """reg_dilation=auto: 1 up to ~30K points (the tuned setting), 5 at 100K, capped; the cutoff
    from the noise table grows to sqrt(d) only when it was auto itself."""
    base = {"optimizer": {"reg_dilation": "auto", **{k: "auto" for k in AUTO}},
            "cycles_by_noise": {0.01: 4}, "lr_points_by_noise": {0.01: 15.0}, "projection_weight_by_noise": {0.01: 0.1},
            "reg_cutoff_by_noise": {0.01: 1.0, 0.02: 3.0}, "final_projection_k_by_noise": {0.01: 32},
            "reg_dilation_points": 20000, "reg_dilation_max": 8}
    cfg = OmegaConf.create(base)
    for n, d, cutoff in ((10000, 1, 1.0), (20000, 1, 1.0), (50000, 3, math.sqrt(3)), (100000, 5, math.sqrt(5)),
                         (10**7, 8, math.sqrt(8))):
        values, notes = st.noise_settings(cfg, 0.01, n)
        assert values["reg_dilation"] == d and notes["reg_dilation"]["used"] == d
        assert values["reg_cutoff"] == pytest.approx(cutoff) and notes["reg_cutoff"]["used"] == pytest.approx(cutoff)
    values, _ = st.noise_settings(cfg, 0.02, 100000)  # the 2% table's 3 x D already exceeds sqrt(5)
    assert values["reg_dilation"] == 5 and values["reg_cutoff"] == 3.0
    assert cfg.optimizer.reg_dilation == "auto" and cfg.optimizer.reg_cutoff == "auto"
    fixed = OmegaConf.create({"optimizer": {"reg_dilation": "auto"}})
    d, cutoff, note = st.neighbourhood(fixed, 100000, 1.5, {"setting": 1.5, "used": 1.5})
    assert d == 5 and cutoff == 1.5 and "reg_cutoff" not in note
    assert st.neighbourhood(OmegaConf.create({"optimizer": {"reg_dilation": 2}}), 100000, 1.0) == (
        None, 1.0, {"setting": 2, "used": 2})
    with pytest.raises(ValueError, match="point count"):
        st.neighbourhood(OmegaConf.create({"optimizer": {"reg_dilation": "auto"}}), 0, 1.0)


def test_budget_presets_set_views_and_scale_auto_cycles():
    presets = {"default": {"name": "default", "views": 12, "cycles_scale": 1.0, "filter_image_size": 64},
               "fast": {"name": "fast", "views": 4, "cycles_scale": 0.5, "lr_points_scale": 2.0,
                        "fusion_passes": 2, "planes_image_size": 192}}

    def cfg(**kw):
        return OmegaConf.create({"views": None, "budget": {"name": "auto", "fast_above": 1000, "presets": presets},
                                 "image_size": None, "fusion": {"passes": None}, **kw})

    values = {"cycles": 16, "lr_points": 15.0}
    auto = {"cycles": {"setting": "auto", "used": 16}, "lr_points": {"setting": "auto", "used": 15.0}}
    out, views, passes, note = st.budget(cfg(), 1000, values, auto)
    assert note["used"] == "default" and views == 12 and out == values and passes == 4 == note["fusion_passes"]
    assert note["filter_image_size"] == 64  # the filters' render size; a given image_size wins
    assert "filter_image_size" not in st.budget(cfg(image_size=128), 1000, values, auto)[3]
    out, views, passes, note = st.budget(cfg(), 1001, values, auto)  # half the cycles, twice the point rate
    assert note["used"] == "fast" and views == 4 and out == {"cycles": 8, "lr_points": 30.0}
    assert passes == 2 and note["planes_image_size"] == 192 and values == {"cycles": 16, "lr_points": 15.0}
    given = {**auto, "lr_points": {"setting": 15.0, "used": 15.0}}  # a given point rate is kept
    assert st.budget(cfg(), 1001, values, given)[0]["lr_points"] == 15.0
    out, views, passes, note = st.budget(cfg(fusion={"passes": 3}, image_size=128), 1001, values, auto)
    assert passes is None and "planes_image_size" not in note  # a given fusion.passes and image_size win
    fixed = {**auto, "cycles": {"setting": 16, "used": 16}}  # explicit views and cycles win over the preset
    out, views, passes, note = st.budget(cfg(views=6), 5000, values, fixed)
    assert views is None and out["cycles"] == 16 and note["views"] == "6 (given)"
    named = OmegaConf.create({"views": None, "image_size": None, "budget": presets["fast"]})
    assert st.budget(named, 10, values, auto)[3]["reason"] == "given"
    with pytest.raises(ValueError, match="preset of conf/denoise_parts/budget"):
        st.budget(cfg(budget="huge"), 10, values, auto)


def test_budget_channel_and_fusion_groups_compose():
    """The swappable parts are Hydra groups (conf/denoise_parts): budget=fast|default|auto,
    channel=..., fusion=on|off; the keys inside them still take overrides."""
    assert compose_denoise([]).budget.name == "auto"
    fast = compose_denoise(["budget=fast"]).budget
    assert fast.name == "fast" and fast.cycles_scale == 0.5
    assert compose_denoise(["budget.fast_above=5"]).budget.fast_above == 5
    assert compose_denoise(["channel=sun"]).channel.name == "sun"
    off = compose_denoise(["fusion=off"]).fusion
    assert off.enabled is False and off.tau == compose_denoise([]).fusion.tau
    assert compose_denoise(["fusion=on", "fusion.passes=3"]).fusion.passes == 3
    with pytest.raises(Exception, match="channel"):
        compose_denoise(["channel=plane"])
    # the groups are dss-denoise's own (its search path): dss-deform's budget stays a plain key
    with initialize_config_dir(config_dir=str(REPO / "conf"), version_base="1.3"):
        assert compose("deform", overrides=["budget=fast"]).budget == "fast"


def test_fusion_and_channel_refusals():
    cfg = compose_denoise(["reference=identity", "fusion=on", "channel=sun"])
    with pytest.raises(ValueError, match="needs the planes channel"):
        st.resolve(cfg, 0.01, 20000, _generator("identity"))
    cfg = compose_denoise(["reference=identity", "fusion.enabled=sometimes"])
    with pytest.raises(ValueError, match="fusion.enabled must be"):
        st.resolve(cfg, 0.01, 20000, _generator("identity"))
    planes = st.resolve(compose_denoise(["reference=identity", "channel=planes"]), 0.01, 20000, _generator("identity"))
    assert planes.shading == "planes" and planes.fusion is not None and planes.fusion.passes == 4
    sun = st.resolve(compose_denoise(["reference=l0"]), 0.01, 20000, _generator("l0"))
    assert sun.shading == "sun" and sun.fusion is None and list(sun.spec.image_size) == [64, 64]
