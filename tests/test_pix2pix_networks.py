"""Pix2Pix networks, norms, metrics, shard reading and lighting-safe augmentation (fast)."""

from __future__ import annotations

import functools
import io
import json
import zipfile

import numpy as np
import pytest
import torch
from torch import nn

from pix2pix.augment import apply_flips, resolve_flips, safe_flips
from pix2pix.metrics import l1, psnr, smape
from pix2pix.networks import PatchDiscriminator, ResNetGenerator
from pix2pix.norms import PixelNorm, build_norm, norm_spec
from pix2pix.shards import DatasetFormatError, open_shard, read_manifest, select_shards
from pix2pix.testing import make_synthetic_pair_dataset

torch.set_num_threads(1)


# ---- generator -----------------------------------------------------------------------------------
@pytest.mark.parametrize("residual", [False, True])
@pytest.mark.parametrize("hw", [(8, 8), (32, 32), (36, 44), (64, 20)])
def test_generator_shape_equals_input(hw, residual):
    g = ResNetGenerator(ngf=4, n_blocks=2, residual=residual)
    x = torch.rand(2, 3, *hw)
    assert g(x).shape == x.shape


@pytest.mark.parametrize("hw", [(30, 32), (32, 33), (4, 4), (6, 8)])
def test_generator_rejects_bad_sizes(hw):
    g = ResNetGenerator(ngf=4, n_blocks=1)
    with pytest.raises(ValueError, match="multiples of 4"):
        g(torch.rand(1, 3, *hw))


def test_generator_rejects_wrong_channels_and_rank():
    g = ResNetGenerator(ngf=4, n_blocks=1)
    with pytest.raises(ValueError, match="expected 3 channels"):
        g(torch.rand(1, 32, 32, 3))  # channels-last by mistake
    with pytest.raises(ValueError, match=r"\(B, C, H, W\)"):
        g(torch.rand(3, 32, 32))


def test_generator_output_is_unbounded():
    """No tanh: the output follows the head past any fixed range, in both modes."""
    assert not any(isinstance(m, nn.Tanh | nn.Sigmoid | nn.Hardtanh) for m in ResNetGenerator().modules())
    g = ResNetGenerator(ngf=4, n_blocks=1, residual=False)
    with torch.no_grad():
        g.head[1].bias.fill_(5.0)  # normalised output 5 -> 5 * 0.5 + 0.5 = 3
    y = g(torch.rand(1, 3, 16, 16))
    assert y.min() > 2.9 and y.max() < 3.1
    with torch.no_grad():
        g.head[1].bias.fill_(-7.0)
    assert g(torch.rand(1, 3, 16, 16)).max() < -2.5  # -7 * 0.5 + 0.5 = -3
    # residual mode passes large inputs straight through (identity at init, no squashing)
    gr = ResNetGenerator(ngf=4, n_blocks=1, residual=True)
    x = torch.full((1, 3, 16, 16), 10.0)
    assert torch.allclose(gr(x), x, atol=0.5)


def test_generator_structure_and_blocks():
    g = ResNetGenerator(ngf=8, n_blocks=3)
    assert len(g.blocks) == 3
    # 7x7 stem with reflection padding, two stride-2 downs, two ups each with a 3x3 conv after
    assert isinstance(g.stem[0], nn.ReflectionPad2d) and g.stem[1].kernel_size == (7, 7)
    assert g.down1[0].stride == (2, 2) and g.down2[0].stride == (2, 2)
    for up in (g.up1, g.up2):
        assert isinstance(up[0], nn.ConvTranspose2d) and up[0].stride == (2, 2)
        assert any(isinstance(m, nn.Conv2d) and m.kernel_size == (3, 3) for m in up)
    assert sum(isinstance(m, PixelNorm) for m in g.modules()) == 1 + 2 + 2 * 3 + 2 * 2
    assert g.up2[-2].__class__ is PixelNorm


def test_norm_is_a_callable_argument():
    calls = []

    def my_norm(c):
        calls.append(c)
        return nn.GroupNorm(1, c)

    g = ResNetGenerator(ngf=4, n_blocks=1, norm_layer=my_norm)
    assert calls and all(isinstance(c, int) for c in calls)
    assert any(isinstance(m, nn.GroupNorm) for m in g.modules())
    g2 = ResNetGenerator(ngf=4, n_blocks=1, norm_layer=functools.partial(nn.InstanceNorm2d, affine=True))
    assert any(isinstance(m, nn.InstanceNorm2d) and m.affine for m in g2.modules())


def test_config_round_trip_rebuilds_identical_network():
    g = ResNetGenerator(ngf=4, n_blocks=2, residual=True,
                        norm_layer=functools.partial(nn.InstanceNorm2d, affine=True))
    cfg = json.loads(json.dumps(g.config()))
    g2 = ResNetGenerator.from_config(cfg)
    g2.load_state_dict(g.state_dict())
    x = torch.rand(1, 3, 16, 16)
    assert torch.equal(g(x), g2(x))
    assert norm_spec(build_norm(cfg["norm_layer"])) == cfg["norm_layer"]


def test_xavier_init_statistics():
    g = ResNetGenerator(ngf=32, n_blocks=2, init_gain=0.02)
    conv = g.blocks[0].body[1]
    fan_in = conv.in_channels * 9
    fan_out = conv.out_channels * 9
    expected = 0.02 * (2.0 / (fan_in + fan_out)) ** 0.5
    assert conv.weight.std().item() == pytest.approx(expected, rel=0.1)
    assert torch.all(conv.bias == 0)


def test_pixel_norm_unit_rms_per_pixel():
    x = torch.randn(2, 16, 5, 7) * 30
    y = PixelNorm()(x)
    rms = y.pow(2).mean(dim=1).sqrt()
    assert torch.allclose(rms, torch.ones_like(rms), atol=1e-4)


# ---- discriminator -------------------------------------------------------------------------------
def test_patchgan_layout_and_70px_receptive_field():
    d = PatchDiscriminator(ndf=64, n_layers=3)
    convs = [m for m in d.modules() if isinstance(m, nn.Conv2d)]
    assert [c.out_channels for c in convs] == [64, 128, 256, 512, 1]
    assert d.receptive_field == 70
    assert d(torch.rand(1, 6, 256, 256)).shape == (1, 1, 30, 30)
    # empirical receptive field: the gradient of one output value covers a 70x70 patch
    # (a per-pixel norm: instance norm would spread the gradient over the whole image)
    dt = PatchDiscriminator(ndf=2, n_layers=3, norm_layer=PixelNorm)
    x = torch.rand(1, 6, 128, 128, requires_grad=True)
    out = dt(x)
    out[0, 0, out.shape[2] // 2, out.shape[3] // 2].backward()
    rows = torch.nonzero(x.grad.abs().sum(dim=(0, 1, 3)))
    cols = torch.nonzero(x.grad.abs().sum(dim=(0, 1, 2)))
    assert rows.max() - rows.min() + 1 == 70
    assert cols.max() - cols.min() + 1 == 70


def test_patchgan_rejects_too_small_inputs():
    d = PatchDiscriminator(ndf=4)
    with pytest.raises(ValueError, match="at least 24"):
        d(torch.rand(1, 6, 16, 16))


# ---- metrics -------------------------------------------------------------------------------------
def test_metrics_hand_cases():
    a = torch.zeros(1, 3, 2, 2)
    b = torch.full((1, 3, 2, 2), 0.1)
    assert l1(a, b).item() == pytest.approx(0.1)
    assert psnr(a, b).item() == pytest.approx(20.0, abs=1e-4)  # 10 log10(1 / 0.01)
    assert smape(b, 3 * b).item() == pytest.approx(3 * 0.5, rel=1e-4)  # channel sum of 0.2/0.4
    assert psnr(a, a).item() == 100.0
    mask = torch.tensor([[[True, False], [False, False]]])
    c = b.clone()
    c[..., 0, 0] = 0.0  # only the masked pixel agrees
    assert smape(c, a, mask).item() == 0.0 and smape(c, a).item() > 2.0


def test_metrics_reject_mismatched_shapes():
    with pytest.raises(ValueError, match="equal shape"):
        l1(torch.zeros(1, 3, 4, 4), torch.zeros(1, 3, 4, 5))


# ---- shards --------------------------------------------------------------------------------------
def test_shards_memory_mapped_and_equal_to_np_load(tmp_path):
    root = make_synthetic_pair_dataset(tmp_path / "ds", n_train=5, n_val=2, size=16,
                                       noise_level=[0.003, 0.01], shard_size=3)
    manifest = read_manifest(root)
    shards = select_shards(root, manifest, "train", 0.01)
    assert [s.num_pairs for s in shards] == [3, 2] and all(s.noise_level == 0.01 for s in shards)
    arrays = open_shard(shards[0].path, (16, 16), 3, 3)
    assert isinstance(arrays["noisy"], np.memmap)
    ref = np.load(shards[0].path)
    for k in ("noisy", "clean", "mask", "pair_id"):
        np.testing.assert_array_equal(np.asarray(arrays[k]), ref[k])
    assert arrays["noisy"].dtype == np.float16 and arrays["mask"].dtype == bool
    ids = np.concatenate([open_shard(s.path)["pair_id"] for s in shards])
    assert all(manifest["pairs"][i]["noise_level"] == 0.01 for i in ids)


def test_shard_errors_are_clear(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        read_manifest(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="manifest.json"):
        read_manifest(tmp_path / "empty")
    root = make_synthetic_pair_dataset(tmp_path / "ds", n_train=2, n_val=1, size=16, shard_size=2)
    manifest = read_manifest(root)
    with pytest.raises(DatasetFormatError, match="noise levels"):
        select_shards(root, manifest, "train", 0.05)
    bad = tmp_path / "bad.npz"
    buf = io.BytesIO()
    np.savez_compressed(buf, noisy=np.zeros((1, 4, 4, 3), np.float16))
    bad.write_bytes(buf.getvalue())
    with pytest.raises(DatasetFormatError, match="compressed"):
        open_shard(bad)
    with zipfile.ZipFile(bad, "w") as zf:
        zf.writestr("noisy.npy", b"")
    with pytest.raises(DatasetFormatError, match=str(bad.name)):
        open_shard(bad)
    bad.write_bytes(b"not a zip")
    with pytest.raises(DatasetFormatError, match="not a readable"):
        open_shard(bad)
    (root / "manifest.json").write_text(json.dumps({"format": "other"}))
    with pytest.raises(DatasetFormatError, match="dss-pairs/1"):
        read_manifest(root)


# ---- augmentation --------------------------------------------------------------------------------
def test_safe_flips_follow_the_light():
    on_axis = {"light": {"position": [0, 0, 0], "space": "camera"}}
    assert safe_flips(on_axis) == ["hflip", "vflip", "transpose"]
    above = {"light": {"position": [0.0, -1.0, 0.0], "space": "camera"}}  # y down: light above
    assert safe_flips(above) == ["hflip"]
    assert safe_flips({"light_position": [0.5, 0.0, 0.0]}) == ["vflip"]
    assert safe_flips({"light_position": [0.5, 0.5, 0.0]}) == ["transpose"]
    assert safe_flips({"shading": "sun"}) == []
    assert safe_flips({"light": {"position": [0, 0, 0], "space": "world"}}) == []
    assert safe_flips({}) == [] and safe_flips(None) == []
    assert resolve_flips("auto", above) == ["hflip"]
    assert resolve_flips("none", on_axis) == []
    with pytest.raises(ValueError, match="unknown flips"):
        resolve_flips(["rotate45"], on_axis)


def test_apply_flips_transforms_all_arrays_alike():
    a = np.arange(12).reshape(3, 4)
    b = a * 10
    rng = np.random.default_rng(0)
    seen = set()
    for _ in range(20):
        fa, fb = apply_flips([a, b], ["hflip", "vflip"], rng)
        np.testing.assert_array_equal(fb, fa * 10)
        seen.add(fa.tobytes())
    assert len(seen) == 4  # identity, h, v, both


# ---- coverage head ---------------------------------------------------------------------------------
def _disks(n: int, size: int = 32, seed: int = 0) -> list[dict]:
    """Render-like pairs: a shaded disk on black (clean) and the same disk with a 2 px bright halo
    around it (noisy), as noise spreads a render's silhouette."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(size), torch.arange(size), indexing="ij")
    out = []
    for _ in range(n):
        c, r = 8 + torch.rand(2, generator=g) * (size - 16), 4 + torch.rand(1, generator=g) * 4
        d = ((yy - c[0]) ** 2 + (xx - c[1]) ** 2).sqrt()
        clean = (d <= r).float() * (0.3 + 0.5 * (1 - d / (r + 1)))
        noisy = clean + ((d > r) & (d <= r + 2)).float() * 0.4
        out.append({"noisy": noisy.expand(3, -1, -1).clone(), "clean": clean.expand(3, -1, -1).clone()})
    return out


def test_coverage_head_starts_at_the_input_coverage_and_exports_exactly(tmp_path):
    """Warm-started from a generator without the head, the coverage generator returns that
    generator's output on the pixels the input covers and exact zeros elsewhere; the gated output
    exports to ONNX with exact zeros; the config round-trips; the ONNX weights warm-start it."""
    from pix2pix.export import export_onnx, onnx_parity
    from pix2pix.module import load_generator_weights
    from pix2pix.networks import covered

    torch.manual_seed(0)
    plain = ResNetGenerator(ngf=8, n_blocks=1, residual=True, init_gain=1.0)
    nn.init.normal_(plain.head[1].weight, std=0.05)  # a non-identity network
    for name, prm in plain.named_parameters():  # distinct biases: ONNX stores equal tensors once
        if name.endswith("bias"):
            nn.init.normal_(prm, std=0.01)
    cov = ResNetGenerator(ngf=8, n_blocks=1, residual=True, init_gain=1.0, coverage_head=True)
    path = export_onnx(plain, tmp_path / "plain.onnx", {})
    report = load_generator_weights(cov, path)
    assert report["kept_init"] == ["coverage.1.bias", "coverage.1.weight"]
    x = torch.rand(2, 3, 32, 32)
    x[:, :, :10] = 0  # background rows
    with torch.no_grad():
        ref, out = plain.eval()(x), cov.eval()(x)
    assert torch.allclose(out, ref * covered(x), atol=1e-5)
    assert (out[:, :, :10] == 0).all() and (ref[:, :, :10] != 0).any()  # plain leaks into the background
    nn.init.normal_(cov.coverage[1].weight, std=0.5)
    import onnxruntime as ort

    sess = ort.InferenceSession(str(export_onnx(cov, tmp_path / "cov.onnx", {})))
    y = sess.run(None, {sess.get_inputs()[0].name: x.numpy()})[0]
    with torch.no_grad():
        gate = cov(x) != 0
    assert onnx_parity(cov, tmp_path / "cov.onnx", x) < 1e-4 and 0.05 < gate.float().mean() < 0.95
    assert ((y != 0) == gate.numpy()).mean() > 0.999  # the same exact zeros
    assert ResNetGenerator.from_config(json.loads(json.dumps(cov.config()))).coverage is not None
    with pytest.raises(ValueError, match="does not fit this generator"):
        load_generator_weights(ResNetGenerator(ngf=16, n_blocks=1, residual=True), path)
    fresh = ResNetGenerator(ngf=8, n_blocks=1, residual=True, init_gain=1.0)  # zero biases, merged
    with pytest.raises(ValueError, match="not in the file.*training checkpoint"):
        load_generator_weights(cov, export_onnx(fresh, tmp_path / "fresh.onnx", {}))
    with pytest.raises(FileNotFoundError, match="init_from=.*absent.onnx"):
        load_generator_weights(cov, tmp_path / "absent.onnx")


def test_coverage_head_learns_to_cut_the_halo():
    """Trained with its cross-entropy, the head zeroes most of a halo the clean render does not
    cover (at the start: none of it) and keeps the surface."""
    import lightning as L

    from pix2pix.module import Pix2PixModule

    torch.manual_seed(0)
    gen = ResNetGenerator(ngf=8, n_blocks=1, residual=True, init_gain=1.0, coverage_head=True)
    test = _disks(16, seed=1)
    x, c = torch.stack([d["noisy"] for d in test]), torch.stack([d["clean"] for d in test])
    halo, disk = (x[:, 0] > 0) & (c[:, 0] == 0), c[:, 0] > 0

    def rates():
        with torch.no_grad():
            y = gen.eval()(x)[:, 0]
        return float((y[halo] == 0).float().mean()), float((y[disk] != 0).float().mean())

    assert rates() == (0.0, 1.0)
    module = Pix2PixModule(gen, None, lr=2e-3, lr_schedule="constant")
    L.seed_everything(0)
    L.Trainer(max_epochs=15, logger=False, enable_checkpointing=False, enable_progress_bar=False,
              enable_model_summary=False, limit_val_batches=0).fit(
        module, torch.utils.data.DataLoader(_disks(64), batch_size=8, shuffle=True))
    cut, kept = rates()
    assert cut > 0.8 and kept > 0.95, (cut, kept)


def test_validation_grids_kept_on_disk_are_capped(tmp_path):
    """A short run validates hundreds of times: val_grids/ keeps the first grid and the newest
    max_grid_files - 1, the rest are deleted as new ones come (the loggers still get each)."""
    from types import SimpleNamespace

    from pix2pix.module import Pix2PixModule

    m = Pix2PixModule(ResNetGenerator(ngf=4, n_blocks=1), None, num_grid_images=1, max_grid_files=3)
    state = SimpleNamespace(fn="fit")
    m._val_grid = tuple(torch.zeros(1, 3, 8, 8) for _ in range(3))
    for epoch in range(6):
        m._trainer = SimpleNamespace(global_rank=0, default_root_dir=str(tmp_path), state=state, loggers=[],
                                     global_step=10 * epoch, current_epoch=epoch)
        m._save_grid()
    kept = sorted(p.name for p in (tmp_path / "val_grids").glob("*.png"))
    assert kept == ["epoch000-step0000000.png", "epoch004-step0000040.png", "epoch005-step0000050.png"]
    assert (tmp_path / "val_grids" / kept[0]).stat().st_mode & 0o044 == 0o044


def test_validation_grid_is_labelled_and_small_renders_are_enlarged():
    """make_grid: a header naming the three columns, then per image noisy | output | clean, each
    32 px render enlarged by a whole factor (nearest neighbour: every source pixel a block)."""
    from pix2pix.module import GRID_LABELS, GRID_MIN_TILE, make_grid

    g = torch.Generator().manual_seed(0)
    noisy, output, clean = (torch.rand(2, 3, 32, 24, generator=g) for _ in range(3))
    grid = make_grid(noisy, output, clean)
    s = -(-GRID_MIN_TILE // 32)
    head = grid.shape[0] - 2 * 32 * s
    assert grid.dtype == np.uint8 and grid.shape == (head + 2 * 32 * s, 3 * 24 * s, 3) and 0 < head <= 32
    for col in range(len(GRID_LABELS)):  # each column's label: dark text on the white header
        band = grid[:head, col * 24 * s:(col + 1) * 24 * s]
        assert band.min() < 128 and (band == 255).mean() > 0.5
    body = grid[head:]
    for b in range(2):
        for col, t in enumerate((noisy, output, clean)):
            tile = body[b * 32 * s:(b + 1) * 32 * s, col * 24 * s:(col + 1) * 24 * s]
            want = (t[b].permute(1, 2, 0).numpy() * 255.0 + 0.5).astype(np.uint8)
            assert np.array_equal(tile[::s, ::s], want) and np.array_equal(tile, want.repeat(s, 0).repeat(s, 1))
    big = make_grid(*(torch.rand(1, 3, 256, 256, generator=g) for _ in range(3)))
    assert big.shape[1] == 3 * 256  # renders of GRID_MIN_TILE px or more keep their size
