"""dss-prep: deterministic, resumable, split-by-shape shards of noisy/clean render pairs."""

from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from data_prep.render_spec import RenderSpec, RenderSpecError, View, load_render_spec
from data_prep.shards import (
    DatasetConflictError,
    PrepConfig,
    PrepConfigError,
    build_plan,
    generate_dataset,
    marker_path,
    npz_bytes,
)

# ----------------------------------------------------------------------------- helpers


def fake_renderer(points, normals, views, spec):
    """Cheap deterministic stand-in for DSS: nearest-pixel point splats with a z-buffer.

    Uses the spec's cameras, so it depends on the views exactly as the real renderer does.
    """
    import torch

    cams = spec.cameras(views)
    uv, z = cams.project(torch.from_numpy(points))
    uv, z = uv.numpy(), z.numpy()
    H, W = spec.image_size
    images = np.zeros((len(views), H, W, 3), np.float32)
    mask = np.zeros((len(views), H, W), bool)
    for v in range(len(views)):
        j, i = np.floor(uv[v, :, 0]).astype(int), np.floor(uv[v, :, 1]).astype(int)
        ok = (z[v] > 0) & (i >= 0) & (i < H) & (j >= 0) & (j < W)
        order = np.argsort(-z[v][ok], kind="stable")  # far to near: nearest written last
        ii, jj = i[ok][order], j[ok][order]
        n_cam = normals[ok][order] @ cams.R[v].numpy().T
        images[v, ii, jj] = np.abs(n_cam[:, 2:3]) * np.array([1.0, 0.8, 0.6], np.float32)
        mask[v, ii, jj] = True
    return images, mask


SMALL = dict(seed=7, families=("superquadric", "torus", "teapot"), shapes_per_family=2, resolution=28,
             val_fraction=0.2, test_fraction=0.2, num_points=1500, normals_k=10, noise_levels=(0.003, 0.01),
             views_per_shape=2, shapes_per_shard=2)


def small_spec(**kw) -> RenderSpec:
    return load_render_spec(image_size=[32, 32], backend="reference", **kw)


def _tree_digest(root: Path) -> dict[str, str]:
    """sha256 of every regular file (relative path -> digest), temp files included."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def reference_dataset(tmp_path_factory):
    """An uninterrupted run with the fake renderer (the baseline for several tests)."""
    root = tmp_path_factory.mktemp("ref")
    stats = generate_dataset(PrepConfig(**SMALL), small_spec(), root, renderer=fake_renderer, progress=False)
    return root, stats


# ----------------------------------------------------------------------------- determinism


def test_npz_bytes_deterministic_and_loadable(tmp_path):
    arrays = [("noisy", np.arange(24, dtype=np.float16).reshape(1, 2, 4, 3)), ("pair_id", np.array([5], np.int64))]
    a, b = npz_bytes(arrays), npz_bytes(arrays)
    assert a == b
    (tmp_path / "x.npz").write_bytes(a)
    with np.load(tmp_path / "x.npz") as z:
        assert list(z.files) == ["noisy", "pair_id"]
        np.testing.assert_array_equal(z["noisy"], arrays[0][1])
    with zipfile.ZipFile(tmp_path / "x.npz") as zf:
        for info in zf.infolist():
            assert info.date_time == (1980, 1, 1, 0, 0, 0) and info.compress_type == zipfile.ZIP_STORED


def test_same_seed_same_manifest_and_shard_hashes(reference_dataset, tmp_path):
    ref, stats = reference_dataset
    assert stats["complete"] and stats["pairs_written"] == stats["pairs_total"] > 0
    again = generate_dataset(PrepConfig(**SMALL), small_spec(), tmp_path, renderer=fake_renderer, progress=False)
    assert again["complete"]
    assert (tmp_path / "manifest.json").read_bytes() == (ref / "manifest.json").read_bytes()
    assert _tree_digest(tmp_path) == _tree_digest(ref)
    manifest = json.loads((ref / "manifest.json").read_text())
    for s in manifest["shards"]:  # the manifest's hashes are the files' hashes
        assert hashlib.sha256((ref / s["path"]).read_bytes()).hexdigest() == s["sha256"]


def test_other_seed_other_data(reference_dataset, tmp_path):
    ref, _ = reference_dataset
    cfg = PrepConfig(**{**SMALL, "seed": 8})
    generate_dataset(cfg, small_spec(), tmp_path, renderer=fake_renderer, progress=False)
    a = json.loads((ref / "manifest.json").read_text())
    b = json.loads((tmp_path / "manifest.json").read_text())
    assert a["fingerprint"] != b["fingerprint"]
    assert [s["sha256"] for s in a["shards"]] != [s["sha256"] for s in b["shards"]]


# ----------------------------------------------------------------------------- resumability


class _Interrupt(RuntimeError):
    pass


def test_interrupted_then_resumed_equals_uninterrupted(reference_dataset, tmp_path):
    ref, stats = reference_dataset
    written = []

    def stop_after_3(path):
        written.append(path)
        if len(written) == 3:  # mid-task: the task's second noise level is not written yet
            raise _Interrupt

    with pytest.raises(_Interrupt):
        generate_dataset(PrepConfig(**SMALL), small_spec(), tmp_path, renderer=fake_renderer,
                         on_shard_written=stop_after_3, progress=False)
    assert not (tmp_path / "manifest.json").exists()  # the manifest is written last
    plan = build_plan(PrepConfig(**SMALL), small_spec())
    shards = [s.path for s in plan.shards]
    nxt = tmp_path / shards[3]
    # leftovers of a killed writer: a stale temp file, and a torn shard without a marker
    (nxt.parent / f".{nxt.stem}.abc123.tmp.npz").write_bytes(b"half a shard")
    nxt.write_bytes(npz_bytes([("noisy", np.zeros(3))])[:50])
    # and a finished shard whose bytes were damaged afterwards (its marker no longer matches)
    bad = tmp_path / shards[1]
    data = bytearray(bad.read_bytes())
    data[-10] ^= 0xFF
    bad.write_bytes(bytes(data))

    resumed = generate_dataset(PrepConfig(**SMALL), small_spec(), tmp_path, renderer=fake_renderer, progress=False)
    assert resumed["complete"]
    assert resumed["shards_skipped"] == 2  # shards 0 and 2 were kept; 1 (damaged) and 3.. redone
    assert resumed["shards_written"] == len(shards) - 2
    assert _tree_digest(tmp_path) == _tree_digest(ref)  # same bytes, no temp file left behind

    # a further re-run skips everything
    again = generate_dataset(PrepConfig(**SMALL), small_spec(), tmp_path, renderer=fake_renderer, progress=False)
    assert again["pairs_written"] == 0 and again["shards_skipped"] == len(shards)


def test_other_config_in_same_folder_is_refused(reference_dataset, tmp_path):
    generate_dataset(PrepConfig(**SMALL), small_spec(), tmp_path, renderer=fake_renderer, progress=False)
    other = PrepConfig(**{**SMALL, "num_points": 1400})
    with pytest.raises(DatasetConflictError, match="another configuration"):
        generate_dataset(other, small_spec(), tmp_path, renderer=fake_renderer, progress=False)
    (tmp_path / "manifest.json").unlink()  # the shard markers alone also identify the config
    with pytest.raises(DatasetConflictError, match="another configuration"):
        generate_dataset(other, small_spec(), tmp_path, renderer=fake_renderer, progress=False)
    out = generate_dataset(other, small_spec(), tmp_path, renderer=fake_renderer, progress=False, overwrite=True)
    assert out["complete"]


def test_parts_cover_the_dataset_and_manifest_comes_last(reference_dataset, tmp_path):
    ref, _ = reference_dataset
    a = generate_dataset(PrepConfig(**SMALL), small_spec(), tmp_path, renderer=fake_renderer, part_index=0,
                         part_count=2, progress=False)
    assert not a["complete"] and a["manifest"] is None and not (tmp_path / "manifest.json").exists()
    b = generate_dataset(PrepConfig(**SMALL), small_spec(), tmp_path, renderer=fake_renderer, part_index=1,
                         part_count=2, progress=False)
    assert b["complete"] and a["pairs_written"] + b["pairs_written"] == a["pairs_total"]
    assert _tree_digest(tmp_path) == _tree_digest(ref)


@pytest.mark.slow
def test_process_pool_gives_the_same_bytes(reference_dataset, tmp_path):
    ref, _ = reference_dataset
    st = generate_dataset(PrepConfig(**SMALL), small_spec(), tmp_path, workers=2, renderer=fake_renderer,
                          progress=False)
    assert st["complete"]
    assert _tree_digest(tmp_path) == _tree_digest(ref)


# ----------------------------------------------------------------------------- content


def test_format_and_split_by_shape(reference_dataset):
    from pix2pix.shards import open_shard, read_manifest, select_shards

    ref, _ = reference_dataset
    m = read_manifest(ref)
    assert m["format"] == "dss-pairs/1" and m["image_size"] == [32, 32] and m["channels"] == 3
    assert m["noise_levels"] == [0.003, 0.01]
    split_of = {}
    for p in m["pairs"]:
        assert split_of.setdefault(p["shape_id"], p["split"]) == p["split"]  # never split by view
    assert {p["split"] for p in m["pairs"]} == {"train", "val", "test"}
    assert [p["pair_id"] for p in m["pairs"]] == list(range(len(m["pairs"])))
    for split in ("train", "val", "test"):
        for level in m["noise_levels"]:
            for ref_shard in select_shards(ref, m, split, level):
                arr = open_shard(ref_shard.path, m["image_size"], 3, ref_shard.num_pairs)
                assert arr["noisy"].dtype == np.float16 and arr["mask"].dtype == bool
                for pid, i in zip(arr["pair_id"], range(len(arr["pair_id"]))):
                    rec = m["pairs"][int(pid)]
                    assert rec["split"] == split and rec["noise_level"] == level and rec["index"] == i


def test_split_fractions_and_families_in_every_split():
    pc = PrepConfig(seed=0, families=("all",), shapes_per_family=10, val_fraction=0.1, test_fraction=0.1,
                    views_per_shape=1)
    plan = build_plan(pc, small_spec())
    by = {s: [x for x in plan.shapes if x.split == s] for s in ("train", "val", "test")}
    assert len(by["val"]) == len(by["test"]) == 10 and len(by["train"]) == 80
    for s in ("val", "test"):  # stratified: one shape of every family
        assert sorted(x.family for x in by[s]) == sorted(pc.families)
    ids = [x.shape_id for x in plan.shapes]
    assert len(set(ids)) == len(ids)


def test_measured_noise_std_matches_requested():
    from data_prep.sampling import measured_noise_std, noisy_copy, poisson_disk
    from data_prep.shapes import make_shape

    mesh = make_shape("displaced_sphere", 1, 40)
    clean = poisson_disk(mesh, 5000, seed=1).points
    for level in (0.003, 0.01, 0.02):
        noisy = noisy_copy(clean, level, seed=11)
        assert measured_noise_std(clean, noisy) == pytest.approx(level, rel=0.05)
    assert np.array_equal(noisy_copy(clean, 0.01, 3), noisy_copy(clean, 0.01, 3))
    assert np.array_equal(poisson_disk(mesh, 500, seed=2).points, poisson_disk(mesh, 500, seed=2).points)


def test_mesh_oriented_pca_normals():
    """orient='mesh': PCA lines with the sign of the generating mesh, also for noisy clouds."""
    from data_prep.sampling import SamplingError, noisy_copy, poisson_disk, with_normals
    from data_prep.shapes import make_shape

    sample = poisson_disk(make_shape("revolution", 2, 40), 3000, seed=0)  # thin-walled vessel
    ref = sample.normals
    assert np.allclose(np.linalg.norm(ref, axis=1), 1, atol=1e-5)
    for pts in (sample.points, noisy_copy(sample.points, 0.01, seed=4)):
        mesh_o = with_normals(pts, k=12, reference=ref).normals
        pca = with_normals(pts, k=12, orient="none").normals
        assert np.allclose(np.abs(np.einsum("ij,ij->i", mesh_o, pca)), 1, atol=1e-5)  # same lines
        assert (np.einsum("ij,ij->i", mesh_o, ref) >= 0).all()  # signs from the mesh
    with pytest.raises(SamplingError, match="reference normals"):
        with_normals(sample.points, k=12)


def test_noisy_and_clean_share_cameras():
    from data_prep.pairs import render_pairs

    spec = small_spec()
    views = spec.sample_views(3, np.random.default_rng(0))
    calls = []

    def recording(points, normals, vs, sp):
        calls.append((list(vs), sp))
        return fake_renderer(points, normals, vs, sp)

    rng = np.random.default_rng(1)
    clean = rng.normal(size=(400, 3)).astype(np.float32) * 0.2
    nrm = clean / np.linalg.norm(clean, axis=1, keepdims=True)
    noisy = clean + rng.normal(size=clean.shape).astype(np.float32) * 0.01
    out = render_pairs(clean, nrm, noisy, nrm, views, spec, recording)
    assert len(calls) == 2 and calls[0] == calls[1]  # identical views and spec for both renders
    assert out["noisy"].shape == out["clean"].shape == (3, 32, 32, 3)
    assert (out["mask"] >= out["noisy"].any(-1)).all()


def test_real_renderer_pair_is_identical_without_noise():
    """With the DSS renderer: same cloud as 'noisy' and 'clean' -> identical images (same cameras
    and light), and a noisy cloud changes the image."""
    pytest.importorskip("dss.render")
    from data_prep.pairs import render_pairs
    from data_prep.sampling import noisy_copy, poisson_disk, with_normals
    from data_prep.shapes import make_shape

    spec = small_spec()
    sample = poisson_disk(make_shape("torus", 0, 32), 1500, seed=0)
    clean = with_normals(sample.points, k=10, reference=sample.normals)
    views = spec.sample_views(2, np.random.default_rng(3))
    same = render_pairs(clean.points, clean.normals, clean.points, clean.normals, views, spec)
    assert same["clean"].max() > 0.2 and same["mask"].mean() > 0.05
    np.testing.assert_array_equal(same["noisy"], same["clean"])
    noisy = with_normals(noisy_copy(clean.points, 0.01, seed=1), k=10, reference=sample.normals)
    diff = render_pairs(clean.points, clean.normals, noisy.points, noisy.normals, views, spec)
    np.testing.assert_array_equal(diff["clean"], same["clean"])
    assert np.abs(diff["noisy"] - diff["clean"]).mean() > 1e-3


def test_manifest_cameras_are_the_rendered_cameras(reference_dataset):
    ref, _ = reference_dataset
    m = json.loads((ref / "manifest.json").read_text())
    spec = RenderSpec.from_manifest(m["render"])
    plan = build_plan(PrepConfig(**SMALL), spec)
    assert [s.path for s in plan.shards] == [s["path"] for s in m["shards"]]
    views = {(x.shape_id, i): v for x in plan.shapes for i, v in enumerate(x.views)}
    for p in m["pairs"]:
        v = views[(p["shape_id"], p["view"])]
        cam = p["camera"]
        assert cam["eye"] == list(v.eye) and cam["up"] == list(v.up) and cam["target"] == list(v.target)
        assert cam["focal"] == pytest.approx(spec.focal)
    # the clean render stored for a pair is what the renderer gives for the manifest's camera
    with np.load(ref / m["shards"][0]["path"]) as z:
        clean0 = z["clean"][0].astype(np.float32)
    rec = m["pairs"][0]
    from data_prep.sampling import poisson_disk, with_normals
    from data_prep.shapes import make_shape

    sample = poisson_disk(make_shape(rec["family"], rec["seed"], SMALL["resolution"]), SMALL["num_points"],
                          rec["seed"])
    cloud = with_normals(sample.points, k=SMALL["normals_k"], reference=sample.normals)
    c = rec["camera"]
    img, _ = fake_renderer(cloud.points, cloud.normals,
                           [View(tuple(c["eye"]), tuple(c["target"]), tuple(c["up"]), (0.0, 0.0, 0.0))], spec)
    np.testing.assert_array_equal(img[0].astype(np.float16).astype(np.float32), clean0)


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("change,message", [
    ({"families": ("blob",)}, "unknown shape family 'blob'"),
    ({"num_points": 0}, "num_points must be > 0"),
    ({"noise_levels": (0.01, -0.003)}, "noise levels must be finite and >= 0"),
    ({"noise_levels": ()}, "noise_levels is empty"),
    ({"views_per_shape": 0}, "views_per_shape must be > 0"),
    ({"val_fraction": 0.6, "test_fraction": 0.5}, "must leave shapes for training"),
    ({"normals_k": 2}, "normals_k must be >= 3"),
])
def test_bad_config_fails_clearly(change, message):
    with pytest.raises(PrepConfigError, match=message):
        PrepConfig(**{**SMALL, **change})


def test_bad_render_spec_fails_clearly():
    with pytest.raises(RenderSpecError, match="image_size.*multiples of 4"):
        load_render_spec(image_size=[30, 32])
    with pytest.raises(RenderSpecError, match="unknown keys.*colour"):
        load_render_spec(colour=1)
    with pytest.raises(RenderSpecError, match="distance"):
        load_render_spec(distance=[2.0, 1.0])
    with pytest.raises(RenderSpecError, match="renderer.*unknown RenderSettings keys"):
        load_render_spec(renderer={"KK": 3})


def test_too_few_shapes_for_the_splits():
    with pytest.raises(PrepConfigError, match="too few"):
        build_plan(PrepConfig(**{**SMALL, "families": ("torus",), "shapes_per_family": 2}), small_spec())


# ----------------------------------------------------------------------------- the app and its configs


def _compose(overrides):
    from hydra import compose, initialize_config_dir

    import conf

    with initialize_config_dir(version_base="1.3", config_dir=str(Path(conf.__file__).parent)):
        return compose(config_name="prep", overrides=overrides, return_hydra_config=False)


@pytest.mark.parametrize("preset,size", [("tiny", 32), ("cpu", 128), ("paper", 256)])
def test_presets_compose(preset, size):
    cfg = _compose([f"prep_preset={preset}"])
    pc = PrepConfig.from_config(cfg)
    spec = RenderSpec.from_config(cfg.render)
    assert spec.image_size == (size, size)
    plan_pairs = len(pc.families) * pc.shapes_per_family * pc.views_per_shape * len(pc.noise_levels)
    if preset == "paper":
        assert 140_000 <= plan_pairs <= 160_000  # the paper rendered 149,240 pairs
    if preset == "cpu":
        assert 6_000 <= plan_pairs <= 12_000


def test_paper_preset_multirun_axis():
    from hydra import compose, initialize_config_dir

    import conf

    with initialize_config_dir(version_base="1.3", config_dir=str(Path(conf.__file__).parent)):
        cfg = compose(config_name="prep", overrides=["prep_preset=paper"], return_hydra_config=True)
    assert "joblib" in cfg.hydra.launcher._target_.lower()
    assert "parts.index" in cfg.hydra.sweeper.params


def test_app_tiny_preset_end_to_end(tmp_path):
    """dss-prep's run() on the tiny preset with the real DSS renderer (reference backend)."""
    pytest.importorskip("dss.render")
    from experiments.apps.prep import run
    from pix2pix.shards import read_manifest

    cfg = _compose(["prep_preset=tiny", f"out_dir={tmp_path / 'ds'}", "render.backend=reference", "progress=false",
                    "preview=true"])
    stats = run(cfg)
    assert stats["complete"] and stats["pairs_written"] == stats["pairs_total"] > 0
    m = read_manifest(tmp_path / "ds")
    assert m["render"]["light"]["position"] == [0.0, 0.0, 0.0] and m["render"]["shading"] == "point"
    assert all((tmp_path / "ds" / s["path"]).is_file() for s in m["shards"])
    assert all(Path(p).is_file() for p in stats["previews"])
    for s in m["shards"]:
        assert json.loads(marker_path(tmp_path / "ds" / s["path"]).read_text())["sha256"] == s["sha256"]
    # the pix2pix side derives its flip augmentation from this block: a headlight allows all flips
    from pix2pix.augment import safe_flips

    assert safe_flips(m["render"]) == ["hflip", "vflip", "transpose"]
    # real renderer, same config and seed -> the same bytes
    run(_compose(["prep_preset=tiny", f"out_dir={tmp_path / 'ds2'}", "render.backend=reference", "progress=false",
                  "preview=false"]))
    digest = {k: v for k, v in _tree_digest(tmp_path / "ds").items() if not k.startswith(("logs", "preview"))}
    assert digest == {k: v for k, v in _tree_digest(tmp_path / "ds2").items() if not k.startswith("logs")}


def test_app_rejects_bad_config(tmp_path):
    from experiments.apps.prep import run

    with pytest.raises(PrepConfigError, match="unknown shape family 'nope'"):
        run(_compose(["prep_preset=tiny", f"out_dir={tmp_path}", "shapes.families=[nope]"]))
    with pytest.raises(PrepConfigError, match="num_points must be > 0"):
        run(_compose(["prep_preset=tiny", f"out_dir={tmp_path}", "sampling.num_points=0"]))
    with pytest.raises(PrepConfigError, match="noise levels must be finite and >= 0"):
        run(_compose(["prep_preset=tiny", f"out_dir={tmp_path}", "noise_levels=[-0.01]"]))
