"""dss.filters: L0 smoothing and SLIC superpixels (fast)."""

import numpy as np
import pytest
import torch

from dss.filters import get_filter, gradient_sparsity, identity, l0_smooth, slic_filter


def _piecewise_images(v=2, h=48, w=48, noise=0.05, seed=0):
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    base = torch.zeros(v, h, w, 3)
    base[:, :, : w // 2] = torch.tensor([0.2, 0.25, 0.3])
    base[:, :, w // 2 :] = torch.tensor([0.7, 0.6, 0.5])
    disk = (yy - h // 2) ** 2 + (xx - w // 2) ** 2 < (h // 5) ** 2
    base[:, disk] = torch.tensor([0.9, 0.3, 0.1])
    noisy = (base + noise * torch.randn(v, h, w, 3, generator=g)).clamp(0, 1)
    return base, noisy


def test_l0_shape_dtype_and_piecewise_constant():
    base, noisy = _piecewise_images()
    out = l0_smooth(noisy)
    assert out.shape == noisy.shape and out.dtype == torch.float32
    assert torch.isfinite(out).all()
    # removes the noise: closer to the piecewise-constant truth than the input
    assert (out - base).abs().mean() < 0.25 * (noisy - base).abs().mean()
    assert gradient_sparsity(out) > 0.85 > gradient_sparsity(noisy)


def test_l0_sparsity_rises_with_lambda():
    _, noisy = _piecewise_images()
    s = [gradient_sparsity(l0_smooth(noisy, lam=lam)) for lam in (1e-4, 2e-3, 2e-2, 1e-1)]
    assert all(b >= a for a, b in zip(s, s[1:])), s
    assert s[-1] > s[0] + 0.3


def test_l0_constant_image_unchanged_and_mask_keeps_background():
    const = torch.full((1, 16, 20, 3), 0.4)
    torch.testing.assert_close(l0_smooth(const), const, atol=1e-5, rtol=0)
    _, noisy = _piecewise_images(v=1)
    mask = torch.zeros(1, 48, 48, dtype=torch.bool)
    mask[:, 8:40, 8:40] = True
    out = l0_smooth(noisy, mask=mask)
    assert torch.equal(out[~mask], noisy[~mask])
    assert not torch.equal(out[mask], noisy[mask])


def test_l0_float64_and_bad_input():
    _, noisy = _piecewise_images(v=1)
    out = l0_smooth(noisy.double())
    assert out.dtype == torch.float64
    with pytest.raises(ValueError, match=r"\(V,H,W,C\)"):
        l0_smooth(noisy[0])
    with pytest.raises(ValueError, match="lam"):
        l0_smooth(noisy, lam=0)


def test_slic_labels_cover_image_and_fill_means():
    _, noisy = _piecewise_images(v=2)
    out, labels = slic_filter(noisy, n_segments=30, return_labels=True)
    assert out.shape == noisy.shape and out.dtype == noisy.dtype
    assert labels.shape == (2, 48, 48)
    assert (labels >= 1).all()  # every pixel belongs to a superpixel
    for i in range(2):
        ids = np.unique(labels[i])
        assert 2 <= len(ids) <= 60
        for lab in ids[:5]:
            m = labels[i] == lab
            region = out[i].numpy()[m]
            np.testing.assert_allclose(region, region[:1].repeat(len(region), 0), atol=1e-6)
            np.testing.assert_allclose(region[0], noisy[i].numpy()[m].mean(0), atol=1e-5)


def test_slic_mask_background_stays_background():
    _, noisy = _piecewise_images(v=2)
    mask = torch.zeros(2, 48, 48, dtype=torch.bool)
    mask[0, 10:38, 6:42] = True  # view 1 has an empty mask: returned unchanged
    out, labels = slic_filter(noisy, n_segments=20, mask=mask, return_labels=True)
    m = mask.numpy()
    assert (labels[m] >= 1).all() and (labels[~m] == 0).all()
    assert torch.equal(out[~mask], noisy[~mask])
    assert torch.equal(out[1], noisy[1])


def test_slic_single_channel_and_registry():
    _, noisy = _piecewise_images(v=1)
    gray = noisy[..., :1]
    assert slic_filter(gray, n_segments=10).shape == gray.shape
    f = get_filter("l0", lam=0.05)
    assert f(noisy).shape == noisy.shape
    assert torch.equal(get_filter("identity")(noisy), identity(noisy))
    with pytest.raises(ValueError, match="unknown image filter"):
        get_filter("sharpen")
