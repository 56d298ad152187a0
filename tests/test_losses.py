"""SMAPE and L1 image losses on hand-computed cases."""

import pytest
import torch

from dss.losses import L1Loss, SmapeLoss, l1_loss, smape_loss


def test_identical_images_give_zero():
    img = torch.rand(3, 8, 9, 3)
    assert smape_loss(img, img.clone()).item() == 0.0
    assert l1_loss(img, img.clone()).item() == 0.0
    # also for all-zero images (eps keeps 0/0 away)
    z = torch.zeros(2, 4, 4, 3)
    assert smape_loss(z, z).item() == 0.0


def test_smape_hand_case():
    pred = torch.tensor([1.0, 0.0, 2.0]).view(1, 1, 1, 3).expand(1, 1, 2, 3).clone()
    target = torch.tensor([3.0, 1.0, 2.0]).view(1, 1, 1, 3).expand(1, 1, 2, 3).clone()
    pred[0, 0, 1] = 0.5
    target[0, 0, 1] = 0.5
    eps = 1e-5
    px0 = 2 / (4 + eps) + 1 / (1 + eps) + 0.0
    expected = (px0 + 0.0) / 2  # 1/(HW) sum over pixels of sum over channels
    assert smape_loss(pred, target).item() == pytest.approx(expected, rel=1e-6)
    # channel mean variant
    assert smape_loss(pred, target, channel_reduction="mean").item() == pytest.approx(
        expected / 3, rel=1e-6
    )


def test_smape_bounded_by_channels():
    g = torch.Generator().manual_seed(0)
    a = torch.randn(4, 16, 16, 3, generator=g) * 10
    b = -a  # worst case: opposite signs
    v = smape_loss(a, b).item()
    assert v <= 3.0 + 1e-6
    assert v > 2.99  # |a-(-a)| = |a|+|-a| -> each term ~1
    c = torch.randn(4, 16, 16, 3, generator=g)
    assert 0 < smape_loss(a, c).item() <= 3.0


def test_mean_over_views():
    a = torch.rand(2, 5, 5, 3)
    b = torch.rand(2, 5, 5, 3)
    per_view = torch.stack([smape_loss(a[i : i + 1], b[i : i + 1]) for i in range(2)])
    assert smape_loss(a, b).item() == pytest.approx(per_view.mean().item(), rel=1e-6)
    per_view = torch.stack([l1_loss(a[i : i + 1], b[i : i + 1]) for i in range(2)])
    assert l1_loss(a, b).item() == pytest.approx(per_view.mean().item(), rel=1e-6)


def test_l1_hand_case():
    a = torch.zeros(1, 2, 2, 2)
    b = torch.zeros(1, 2, 2, 2)
    b[0, 0, 0] = torch.tensor([1.0, -2.0])
    assert l1_loss(a, b).item() == pytest.approx(3.0 / 4)
    assert l1_loss(a, b, channel_reduction="mean").item() == pytest.approx(
        torch.nn.functional.l1_loss(a, b).item()
    )


def test_mask_restricts_and_normalises_over_masked_pixels():
    a = torch.rand(2, 4, 4, 3)
    b = a.clone()
    b[:, 0, 0] += 1.0  # error only at pixel (0,0)
    mask = torch.zeros(2, 4, 4, dtype=torch.bool)
    assert smape_loss(a, b, mask).item() == 0.0  # error pixels excluded, zero-mask -> 0
    mask[:, 0, 0] = True
    mask[:, 1, 1] = True
    per_px = smape_loss(a, b, reduction="none")
    expected = (per_px[:, 0, 0].sum() + per_px[:, 1, 1].sum()) / 4
    assert smape_loss(a, b, mask).item() == pytest.approx(expected.item(), rel=1e-6)
    # (V,H,W,1) and broadcast (H,W) masks are accepted
    assert smape_loss(a, b, mask[..., None]).item() == pytest.approx(expected.item(), rel=1e-6)
    assert smape_loss(a, b, mask[0]).item() == pytest.approx(expected.item(), rel=1e-6)
    l1 = l1_loss(a, b, mask).item()
    assert l1 == pytest.approx(3.0 * 2 / 4, rel=1e-5)


def test_gradient_and_modules():
    a = torch.rand(1, 3, 3, 3, requires_grad=True)
    b = torch.rand(1, 3, 3, 3)
    SmapeLoss()(a, b).backward()
    assert torch.isfinite(a.grad).all() and a.grad.abs().sum() > 0
    a.grad = None
    L1Loss()(a, b, torch.ones(1, 3, 3)).backward()
    assert torch.isfinite(a.grad).all()


def test_bad_shapes():
    with pytest.raises(ValueError, match="differ"):
        smape_loss(torch.rand(1, 2, 2, 3), torch.rand(1, 2, 3, 3))
    with pytest.raises(ValueError, match=r"\(V, H, W, C\)"):
        l1_loss(torch.rand(2, 2, 3), torch.rand(2, 2, 3))
    with pytest.raises(ValueError, match="broadcast"):
        smape_loss(torch.rand(1, 2, 2, 3), torch.rand(1, 2, 2, 3), torch.ones(3, 3))


@pytest.mark.parametrize("channel_reduction", ["sum", "mean"])
def test_fused_smape_equals_the_torch_expression(channel_reduction, cpp_backend):
    """With the C++ module loaded, smape_loss takes the one-pass fused kernel (CPU, no mask,
    mean); value and gradient equal the torch expression's, zeros (sign 0) included."""
    from dss import _ext
    from dss.losses import _fused_smape_ok

    g = torch.Generator().manual_seed(0)
    pred = torch.rand(2, 9, 11, 3, generator=g) - 0.3
    target = torch.rand(2, 9, 11, 3, generator=g)
    pred[0, :2] = 0.0
    target[0, :1] = 0.0  # both zero: the eps-only denominator
    target[1, 3] = pred[1, 3]  # equal: sign(d) = 0
    assert _ext.loaded_cpu() is not None and _fused_smape_ok(pred, target, None, "mean")
    p1, p2 = pred.clone().requires_grad_(), pred.clone().requires_grad_()
    fused = smape_loss(p1, target, channel_reduction=channel_reduction)
    fused.backward()
    per = (p2 - target).abs() / (p2.abs() + target.abs() + 1e-5)
    ref = per.sum(-1).mean() if channel_reduction == "sum" else per.mean()
    ref.backward()
    torch.testing.assert_close(fused, ref, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(p1.grad, p2.grad, rtol=1e-5, atol=1e-6)
    assert p1.grad.abs().max() > 0 and fused.grad_fn is not None
    # the kernel's derivative comes pre-scaled to the mean; an outer factor still reaches it
    p3 = pred.clone().requires_grad_()
    (2.5 * smape_loss(p3, target, channel_reduction=channel_reduction)).backward()
    torch.testing.assert_close(p3.grad, 2.5 * p2.grad, rtol=1e-5, atol=1e-6)
    assert not _fused_smape_ok(pred, target, torch.ones(2, 9, 11), "mean")  # masks take the torch path


def test_fused_smape_vector_path_gives_the_baseline_bits(cpp_backend):
    """The kernel's AVX2 build and its baseline build run the same float operations: the same
    sum and the same derivative bit for bit (a size that leaves a tail after the runs of 8 and
    spans several blocks of 2^16 elements)."""
    from dss import _ext

    mod = _ext.loaded_cpu()
    if not mod.vector_path_available():
        pytest.skip("this CPU has no AVX2 path to compare")
    g = torch.Generator().manual_seed(3)
    pred = torch.rand(3, 131, 173, 3, generator=g) - 0.2
    target = torch.rand(3, 131, 173, 3, generator=g)
    target[0, :5] = pred[0, :5]
    before = mod.set_vector_path(True)
    try:
        value_vec, grad_vec = mod.smape_sum(pred, target, 1e-5, 1.0 / pred.numel(), True)
        mod.set_vector_path(False)
        value_base, grad_base = mod.smape_sum(pred, target, 1e-5, 1.0 / pred.numel(), True)
    finally:
        mod.set_vector_path(before)
    assert value_vec.item() == value_base.item()
    assert torch.equal(grad_vec, grad_base) and grad_vec.abs().max() > 0
